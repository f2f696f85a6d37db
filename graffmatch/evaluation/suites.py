"""Named, reproducible loop-closure benchmark suites: ``build_suite("sim-downtown", out_root)``.

A suite is a data source plus the loop-closure rules used on it:

* ``sim-*``: a world of :mod:`graffmatch.datasets.simulator` (named and seeded there), ray-cast
  into a KITTI-layout folder ``<out_root>/<name>/raw`` on first use, then built with the
  paper's rules (2 m places, > 50 m of path, < 16 m apart).
* ``balm_courtyard``: the real hand-held recording in ``../shared/data``. The walk is only
  74 m long, so the paper's 50 m path rule leaves few revisits; the suite uses 1 m places,
  10 m of path for a revisit, and also keeps every pair 5-16 m apart (its wide baselines)
  whatever the path between them (``wide_baseline_min_distance=5``).

Suites are registered explicitly in :data:`SUITES`; add your own with :func:`register_suite`.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from graffmatch.datasets.base import Dataset
from graffmatch.datasets.folder import KittiFolder
from graffmatch.datasets.simulator import SUITES as SIM_SUITES
from graffmatch.datasets.simulator import simulate_dataset
from graffmatch.errors import InvalidInputError
from graffmatch.evaluation.loop_closures import LoopClosureConfig, build_loop_closure_dataset
from graffmatch.evaluation.progress import progress_bar
from graffmatch.lidar.extractor import LandmarkExtractorConfig

#: ``progress(done, total)`` of a long step.
ProgressFn = Callable[[int, int], None]


def shared_data_root() -> Path:
    """``$GRAFFMATCH_SHARED_DATA`` or ``../shared/data`` next to the repository."""
    env = os.environ.get("GRAFFMATCH_SHARED_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3] / "shared" / "data"


@dataclass(frozen=True)
class Suite:
    """A named data source and the loop-closure rules applied to it.

    ``make_dataset(suite_dir, quick, data_root)`` returns the Dataset (simulating it first when
    needed). ``make_raw(suite_dir, quick, progress)``, when given, makes the raw data first and
    reports ``progress(done, total)``, so that a long simulation shows a progress bar. ``quick``
    overrides are applied to the config for fast smoke builds.
    """

    name: str
    description: str
    make_dataset: Callable[[Path, bool, Path | None], Dataset]
    config: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    quick_overrides: dict[str, Any] = field(default_factory=lambda: {"max_places": 40})
    make_raw: Callable[[Path, bool, ProgressFn | None], None] | None = None
    #: A builder of its own (``build(suite_dir, quick, data_root, progress) -> summary``) for
    #: suites that are not revisits of one drive, such as the cross-dataset negatives.
    build: Callable[[Path, bool, Path | None, bool], dict[str, Any]] | None = None


SUITES: dict[str, Suite] = {}


def register_suite(suite: Suite, overwrite: bool = False) -> None:
    if suite.name in SUITES and not overwrite:
        raise InvalidInputError(f"suite {suite.name!r} is already registered")
    SUITES[suite.name] = suite


def available_suites() -> list[str]:
    return sorted(SUITES)


def suite_config(name: str, quick: bool = False) -> LoopClosureConfig:
    suite = _get(name)
    if not quick:
        return suite.config
    return suite.config.model_copy(update=suite.quick_overrides)


def _get(name: str) -> Suite:
    if name not in SUITES:
        raise InvalidInputError(
            f"unknown suite {name!r}; available: {', '.join(available_suites())}"
        )
    return SUITES[name]


def build_suite(
    name: str,
    out_root: str | Path,
    quick: bool = False,
    data_root: str | Path | None = None,
    progress: bool = True,
    config: LoopClosureConfig | None = None,
) -> dict[str, Any]:
    """Build suite ``name`` into ``<out_root>/<name>`` (``<name>-quick`` when quick).

    Returns the builder's summary plus ``simulate_s`` (time to make the raw data, 0 when it
    was already there or is real). ``config`` replaces the suite's own rules when given.
    """
    suite = _get(name)
    out_dir = Path(out_root) / (f"{name}-quick" if quick else name)
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if suite.build is not None:
        root = None if data_root is None else Path(data_root)
        summary = suite.build(out_dir, quick, root, progress)
        summary.update(suite=name, quick=quick)
        (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
        return summary
    if suite.make_raw is not None:
        with progress_bar(progress, "{task.description}") as bar:
            task = bar.add_task(f"{name}: making the scans", total=None)

            def tick(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total)

            suite.make_raw(out_dir, quick, tick)
    dataset = suite.make_dataset(out_dir, quick, None if data_root is None else Path(data_root))
    t_sim = time.perf_counter() - t0
    cfg = config or suite_config(name, quick)
    summary = build_loop_closure_dataset(dataset, out_dir, cfg, progress=progress)
    summary["suite"] = name
    summary["quick"] = quick
    summary["times"]["simulate_s"] = t_sim
    summary["total_s"] = summary["total_s"] + t_sim
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


# ---- built-in suites ------------------------------------------------------------------------
def _balm(suite_dir: Path, quick: bool, data_root: Path | None) -> Dataset:
    root = (data_root or shared_data_root()) / "balm_courtyard"
    if not root.is_dir():
        raise InvalidInputError(
            f"balm_courtyard not found at {root} (set GRAFFMATCH_SHARED_DATA or pass data_root)"
        )
    return KittiFolder(root)


register_suite(
    Suite(
        name="balm_courtyard",
        description="Real hand-held 360-degree LiDAR walk (74 m, 89 scans) around a courtyard; "
        "1 m places, revisits after 10 m of path, plus all pairs 5-16 m apart.",
        make_dataset=_balm,
        config=LoopClosureConfig(
            place_spacing=1.0,
            min_path_length=10.0,
            max_distance=16.0,
            wide_baseline_min_distance=5.0,
        ),
        quick_overrides={"place_spacing": 3.0, "max_places": 16},
    )
)


class _Simulated:
    """A simulated suite: simulate into ``<suite_dir>/raw`` once, then read it as a KITTI folder.

    The raw data is reused when its ``sim_meta.json`` records the same request (world config,
    seed, sensor, scan count, realism preset): the simulator is deterministic, so it would be
    byte-identical. The suites run the ``realistic`` simulator (``SuiteSpec.realism``).
    """

    def __init__(self, spec_name: str, quick_scans: int) -> None:
        self.spec_name = spec_name
        self.quick_scans = quick_scans

    def raw(self, suite_dir: Path, quick: bool, progress: ProgressFn | None = None) -> Path:
        spec = SIM_SUITES[self.spec_name]
        return simulate_dataset(
            suite_dir / "raw",
            style=spec.style,
            seed=spec.seed,
            n_scans=min(self.quick_scans, spec.n_scans) if quick else spec.n_scans,
            sensor=spec.sensor,
            world_config=spec.world_config(),
            realism=spec.realism,
            reuse=True,
            progress=progress,
        )

    def dataset(self, suite_dir: Path, quick: bool, data_root: Path | None) -> Dataset:
        return KittiFolder(self.raw(suite_dir, quick), name=self.spec_name)


#: Scans of a quick simulated suite (default 160). The realistic drive slows down in turns, so
#: 160 scans of downtown close no loop (0 revisits; 240 scans: 59, measured with plan_route).
#: All three use 240: the GraffMatch recall floors of tests/evaluation/test_quick_benchmark.py
#: were measured on these (open road at 160 scans: 4 of 7 positive pairs, too few to judge).
QUICK_SIM_SCANS: dict[str, int] = {"sim-downtown": 240, "sim-suburban": 240, "sim-openroad": 240}

#: Front end of each simulated suite. The default extractor (planes of >= 10 m^2 within 50 m)
#: keeps ~15 planes per place, so every pair's IIR stays above 0.03 and case 3 would be empty.
#: Looking further and keeping smaller planes gives 20-35 landmarks per place, closer to a
#: KITTI scan, and spreads the pairs over all three IIR cases (see docs/simulator.md).
SIM_EXTRACTORS: dict[str, dict[str, Any]] = {
    "sim-downtown": {"planes": {"max_range": 75.0, "min_area": 6.0}},
    "sim-suburban": {"planes": {"max_range": 65.0, "min_area": 8.0}},
    "sim-openroad": {"planes": {"max_range": 80.0, "min_area": 4.0}, "poles": {"min_support": 14}},
}

for _spec in SIM_SUITES.values():
    register_suite(
        Suite(
            name=_spec.name,
            description=f"simulated ({_spec.style}, seed {_spec.seed}, {_spec.n_scans} scans, "
            f"{_spec.sensor}): {_spec.description}; the paper's rules",
            make_dataset=(
                _sim := _Simulated(_spec.name, QUICK_SIM_SCANS.get(_spec.name, 160))
            ).dataset,
            make_raw=_sim.raw,
            config=LoopClosureConfig(
                extractor=LandmarkExtractorConfig.model_validate(SIM_EXTRACTORS.get(_spec.name, {}))
            ),
            quick_overrides={},
        )
    )


# ---- negatives across datasets -----------------------------------------------------------------
#: Places per source of the cross-dataset negatives (full, quick) and pairs at most.
CROSS_PLACES = {"kitti00_first6": (6, 3), "balm_courtyard": (12, 4), "sim-suburban": (8, 3)}
CROSS_MAX_PAIRS = (120, 12)
#: Scans simulated for the simulated source (full, quick): a few are enough for negatives.
CROSS_SIM_SCANS = (16, 6)


def cross_sources_available(data_root: Path | None = None) -> list[str]:
    """The real sources of the cross-dataset negatives found under the shared data."""
    root = data_root or shared_data_root()
    return [n for n in ("kitti00_first6", "balm_courtyard") if (root / n / "velodyne").is_dir()]


def _build_cross(suite_dir: Path, quick: bool, data_root: Path | None, progress: bool) -> dict:
    from graffmatch.evaluation.cross_negatives import NegativeSource, build_cross_negatives

    root = data_root or shared_data_root()
    q = int(quick)
    sources = []
    for name in cross_sources_available(root):
        cfg = suite_config(name, quick) if name in SUITES else LoopClosureConfig()
        sources.append(
            NegativeSource(name, KittiFolder(root / name, name=name), cfg, CROSS_PLACES[name][q])
        )
    spec = SIM_SUITES["sim-suburban"]
    raw = simulate_dataset(
        suite_dir / "sim-suburban",
        style=spec.style,
        seed=spec.seed + 1000,  # not the drive of the sim-suburban suite itself
        n_scans=CROSS_SIM_SCANS[q],
        sensor=spec.sensor,
        world_config=spec.world_config(),
        reuse=True,
    )
    sources.append(
        NegativeSource(
            "sim-suburban",
            KittiFolder(raw, name="sim-suburban"),
            suite_config("sim-suburban", quick),
            CROSS_PLACES["sim-suburban"][q],
        )
    )
    return build_cross_negatives(sources, suite_dir, CROSS_MAX_PAIRS[q], progress)


def _no_dataset(suite_dir: Path, quick: bool, data_root: Path | None) -> Dataset:
    raise InvalidInputError("cross-dataset is built by its own builder, not from one drive")


register_suite(
    Suite(
        name="cross-dataset",
        description="negative pairs only: KITTI 00 vs the courtyard vs a simulated street "
        "(places that share nothing; scores the validity flags)",
        make_dataset=_no_dataset,
        build=_build_cross,
        quick_overrides={},
    )
)
