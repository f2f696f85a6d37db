"""One call from suite names to a report: build the suites, run the study, write the report.

``run_benchmark(["balm_courtyard"], "bench_out", quick=True)`` makes::

    <out_dir>/data/<suite>[-quick]/   the loop-closure datasets (cached: rebuilt only if stale)
    <out_dir>/results/                one JSON record per (suite, pair, method); resumable
    <out_dir>/report/                 tables, figures, summary.md
    <out_dir>/benchmark.json          what ran, and how long each phase took

Rerunning the same command resumes: built suites and finished records are reused.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from graffmatch.errors import InvalidInputError
from graffmatch.evaluation.executors import make_executor
from graffmatch.evaluation.report import make_report
from graffmatch.evaluation.runner import StudyConfig, atomic_write_json, run_study

#: Real data suite of the default benchmark (the simulated ones are added by name prefix).
REAL_DEFAULT_SUITES = ("balm_courtyard",)
#: Pairs per case of the full benchmark: an evenly spaced subset keeps the default study within
#: an hour on a 2-core machine (about 15 methods x ~5 s of CPU per pair); pass a StudyConfig with
#: ``max_pairs_per_case=None`` for every pair.
FULL_MAX_PAIRS_PER_CASE = 40


def default_suites() -> list[str]:
    """The simulated suites (``sim-*``) and ``balm_courtyard``."""
    from graffmatch.evaluation.suites import available_suites

    names = available_suites()
    return [n for n in names if n.startswith("sim")] + [
        n for n in REAL_DEFAULT_SUITES if n in names
    ]


def run_benchmark(
    suites: Sequence[str] | None = None,
    out_dir: str | Path = "graffmatch-benchmark",
    quick: bool = False,
    executor: str = "local",
    address: str | None = None,
    workers: int | None = None,
    methods: Sequence[str] | None = None,
    data_dir: str | Path | None = None,
    data_root: str | Path | None = None,
    config: StudyConfig | None = None,
    progress: bool = True,
) -> Path:
    """Build ``suites``, run every method on every pair, write the report; returns ``out_dir``.

    Args:
        suites: suite names (see ``graffmatch.evaluation.suites.available_suites()``);
            None or empty: :func:`default_suites`.
        out_dir: where data, results and the report go.
        quick: small suites, a few pairs per case, the fast point methods (minutes).
        executor: "local" (process pool, default), "serial", "dask" or "ray".
        address: scheduler address of a Dask/Ray cluster (``tcp://host:8786``); without it,
            dask starts a local cluster.
        workers: worker processes for local execution / a local cluster (default: all cores).
        methods: method names; None: every registered method (``quick``: without the slow
            point methods).
        data_dir: where built suites are cached (default ``<out_dir>/data``); share it
            between benchmarks to build each suite once.
        data_root: folder of the real datasets (default ``../shared/data``).
        config: thresholds and subset sizes of the study (default: at most
            ``FULL_MAX_PAIRS_PER_CASE`` pairs per case, or the quick subset).
        progress: rich progress bars.
    """
    from graffmatch.evaluation.suites import build_suite

    names = list(suites or default_suites())
    if not names:
        raise InvalidInputError("no suites to run (none given and none registered)")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = Path(data_dir) if data_dir is not None else out / "data"
    log: dict[str, Any] = {
        "suites": names,
        "quick": quick,
        "executor": executor,
        "address": address,
        "workers": workers,
        "methods": list(methods) if methods is not None else None,
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "build": {},
    }
    if config is None and not quick:
        config = StudyConfig(max_pairs_per_case=FULL_MAX_PAIRS_PER_CASE)
    # Fail on a bad executor before spending minutes on building data.
    ex = make_executor(executor, workers=workers, address=address)
    try:
        t0 = time.perf_counter()
        built: dict[str, Path] = {}
        for name in names:
            t = time.perf_counter()
            summary = build_suite(name, data, quick=quick, data_root=data_root, progress=progress)
            folder = data / (f"{name}-quick" if quick else name)
            log["build"][name] = {
                "folder": str(folder),
                "pairs": summary.get("n_valid"),
                "cases": {k: v.get("pairs") for k, v in summary.get("cases", {}).items()},
                "seconds": time.perf_counter() - t,
            }
            if summary.get("n_valid", 0):
                built[name] = folder
        log["build_s"] = time.perf_counter() - t0
        if not built:
            raise InvalidInputError(f"no suite produced a loop closure: {log['build']}")
        t0 = time.perf_counter()
        results = run_study(
            built,
            methods,
            out / "results",
            executor=ex,
            quick=quick,
            workers=workers,
            address=address,
            config=config,
            progress=progress,
        )
        log["study_s"] = time.perf_counter() - t0
    finally:
        ex.close()
        atomic_write_json(out / "benchmark.json", log)
    t0 = time.perf_counter()
    make_report(results, out / "report")
    log["report_s"] = time.perf_counter() - t0
    log["ended_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    atomic_write_json(out / "benchmark.json", log)
    return out
