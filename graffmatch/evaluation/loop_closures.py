"""The paper's loop-closure dataset ("Dataset Preparation", Sec. V-A), built from any Dataset.

1. **Places**: a scan every ``place_spacing`` (2 m) of path length along the ground truth.
2. **Revisits**: place p and an earlier place p' with more than ``min_path_length`` (50 m) of
   path between them and less than ``max_distance`` (16 m) between the sensors.
3. **Landmarks** per place from :class:`graffmatch.lidar.extractor.LandmarkExtractor`, in
   parallel, cached on disk next to the pair list (``landmarks/NNNNNN.npz``, with support points).
4. **Ground-truth matches**: source landmarks moved into the target frame with the true relative
   pose, invariant d_Graff between them (:func:`graffmatch.geometry.distance.cross_distances`,
   +inf across types), linear-sum assignment, gate ``tau_d`` = 6 deg.
5. **Valid loop closures**: more than 4 true matches, kappa < 1e3 and registration with the true
   matches within 5 deg and 1 m of the ground truth.
6. **IIR** = true matches / possible matches (sum over types of n_i(type) n_j(type), i.e. the
   putative all-to-all associations); case 1: IIR >= 0.05, case 2: 0.03-0.05, case 3: < 0.03.

The rules (steps 1, 2, 4-6) live in :mod:`~graffmatch.evaluation.places`, the reader in
:mod:`~graffmatch.evaluation.loop_closure_dataset`; their names stay importable from here. The
output folder (``pairs.json`` + ``landmarks/``) is read back by :class:`LoopClosureDataset`;
the evaluation runner iterates over it.

Over 500 lines because the build is one pipeline (places -> landmarks -> revisits -> ground
truth -> negatives -> pairs.json) whose stages share the cached per-place sets; the rules
themselves are already in ``places.py``.
"""

from __future__ import annotations

import json
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from graffmatch.atomic_files import write_text_atomic
from graffmatch.datasets.base import Dataset, ScanSequence
from graffmatch.errors import InvalidInputError
from graffmatch.evaluation.executors import LocalProcessExecutor, SerialExecutor
from graffmatch.evaluation.loop_closure_dataset import (
    CACHE_INDEX,
    FORMAT_NAME,
    FORMAT_VERSION,
    LANDMARK_DIR,
    PAIRS_FILE,
    LoopClosureDataset,
    LoopClosurePair,
    load_landmarks_cached,
)
from graffmatch.evaluation.places import (
    LoopClosureConfig,
    Validity,
    check_validity,
    find_negatives,
    find_revisits,
    ground_truth_matches,
    iir_case,
    keep_most_salient,
    path_lengths,
    possible_matches,
    select_places,
)
from graffmatch.evaluation.progress import progress_bar
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.geometry.transforms import invert, rotation_error_deg
from graffmatch.lidar.cache import LandmarkCache
from graffmatch.lidar.extractor import LandmarkExtractor

__all__ = [
    "CACHE_INDEX",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "LANDMARK_DIR",
    "PAIRS_FILE",
    "LoopClosureConfig",
    "LoopClosureDataset",
    "LoopClosurePair",
    "PairRecord",
    "Validity",
    "build_loop_closure_dataset",
    "check_validity",
    "evaluate_revisit",
    "extract_place_landmarks",
    "find_negatives",
    "find_revisits",
    "ground_truth_matches",
    "iir_case",
    "keep_most_salient",
    "load_landmarks_cached",
    "path_lengths",
    "possible_matches",
    "select_places",
    "summary_text",
]

Array = NDArray[np.float64]


def _landmark_file(out_dir: Path, scan_index: int) -> Path:
    return out_dir / LANDMARK_DIR / f"{scan_index:06d}.npz"


def _extract_one(
    dataset: Dataset, scan_index: int, config: LoopClosureConfig, out_file: str
) -> tuple[int, dict[str, int], float]:
    """Worker: read one scan, extract its landmarks, write the landmark file."""
    t0 = time.perf_counter()
    scan = dataset[scan_index]
    labels = scan.labels if config.use_labels else None
    extractor = LandmarkExtractor(config.extractor)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ls = extractor.extract(scan.points, labels)
    ls = keep_most_salient(ls, config.max_landmarks_per_type)
    ls.save(out_file, include_points=config.store_support_points)
    return scan_index, ls.counts(), time.perf_counter() - t0


def _extract_star(args: tuple[Dataset, int, LoopClosureConfig, str]) -> tuple[int, dict, float]:
    return _extract_one(*args)


def extract_place_landmarks(
    dataset: Dataset,
    scan_indices: Sequence[int],
    out_dir: Path,
    config: LoopClosureConfig,
    progress: bool = True,
) -> dict[str, Any]:
    """Landmark files for the places, reusing cached ones whose scan and config are unchanged.

    Returns {"extracted": n, "cached": n, "extract_seconds": cpu-seconds in workers}.
    """
    out_dir = Path(out_dir)
    (out_dir / LANDMARK_DIR).mkdir(parents=True, exist_ok=True)
    index_file = out_dir / LANDMARK_DIR / CACHE_INDEX
    try:
        cache: dict[str, str] = json.loads(index_file.read_text()) if index_file.is_file() else {}
    except json.JSONDecodeError:
        cache = {}
    # The key logic is the front end's (scan and label stamps, extractor config, points).
    keyer = LandmarkCache(
        out_dir / LANDMARK_DIR,
        LandmarkExtractor(config.extractor),
        include_points=config.store_support_points,
    )
    keys = {
        int(i): keyer.key(
            dataset.scan_path(int(i)),
            dataset.label_path(int(i)) if config.use_labels else None,
        )
        + f"-top{config.max_landmarks_per_type}"
        for i in scan_indices
    }
    todo = [
        i for i in keys if cache.get(str(i)) != keys[i] or not _landmark_file(out_dir, i).is_file()
    ]
    stats: dict[str, Any] = {"extracted": len(todo), "cached": len(keys) - len(todo)}
    seconds = 0.0
    if todo:
        with progress_bar(progress) as bar:
            task = bar.add_task(
                f"landmarks ({getattr(dataset, 'name', 'dataset')})", total=len(todo)
            )
            args = [(dataset, i, config, str(_landmark_file(out_dir, i))) for i in todo]
            executor: Any
            if config.workers == 1:
                executor = SerialExecutor()
            else:
                # forkserver (the executors' default): the rich progress thread makes fork()
                # unsafe, and the server imports the front end (Open3D) once for all workers.
                executor = LocalProcessExecutor(
                    workers=config.workers, preload=("graffmatch.evaluation.loop_closures",)
                )
            try:
                for _, (i, _, dt) in executor.imap_unordered(_extract_star, args):
                    seconds += dt
                    cache[str(i)] = keys[i]
                    bar.advance(task)
            finally:
                executor.close()
                index_file.write_text(json.dumps(cache, indent=0, sort_keys=True))
    stats["extract_seconds"] = seconds
    return stats


# ---- pairs ----------------------------------------------------------------------------------
@dataclass
class PairRecord:
    """One revisit as written to ``pairs.json`` (valid ones only)."""

    source_scan: int
    target_scan: int
    T_target_source: Array
    true_matches: NDArray[np.int64]
    n_possible: int
    iir: float
    case: int
    distance: float
    rotation_deg: float
    path_length: float
    n_true_lines: int
    n_true_planes: int
    n_true_points: int
    kappa: float
    gt_rotation_error_deg: float
    gt_translation_error: float

    def to_json(self) -> dict[str, Any]:
        return {
            "source_scan": self.source_scan,
            "target_scan": self.target_scan,
            "T_target_source": np.round(self.T_target_source, 10).tolist(),
            "true_matches": self.true_matches.tolist(),
            "n_possible": self.n_possible,
            "iir": self.iir,
            "case": self.case,
            "distance": self.distance,
            "rotation_deg": self.rotation_deg,
            "path_length": self.path_length,
            "n_true_lines": self.n_true_lines,
            "n_true_planes": self.n_true_planes,
            "n_true_points": self.n_true_points,
            "kappa": self.kappa,
            "gt_rotation_error_deg": self.gt_rotation_error_deg,
            "gt_translation_error": self.gt_translation_error,
        }


def evaluate_revisit(
    source: LandmarkSet,
    target: LandmarkSet,
    T_target_source: Array,
    config: LoopClosureConfig,
) -> tuple[NDArray[np.int64], int, float, int, Validity]:
    """True matches, possible matches, IIR, case and validity of one revisit."""
    matches, _ = ground_truth_matches(source, target, T_target_source, config.tau_d_deg, config.rho)
    n_possible = possible_matches(source, target)
    iir = len(matches) / n_possible if n_possible else 0.0
    case = iir_case(iir, config.case_thresholds)
    validity = check_validity(source, target, matches, T_target_source, config)
    return matches, n_possible, iir, case, validity


def _negative_pairs(
    poses: Array,
    places: NDArray[np.int64],
    sets: dict[int, LandmarkSet],
    config: LoopClosureConfig,
    n_positive: int,
) -> list[dict[str, Any]]:
    """Pairs of places without overlap, in the pairs.json format (case 0, no true matches).

    Far apart is not enough: an 80 m lidar on an open road shares poles with a place 60-80 m
    away, and a matcher that registers such a pair right is not wrong. A negative is at least
    ``negative_min_distance`` apart *and* shares no landmark (no ground-truth match); the
    candidates are taken evenly over all far pairs (four times as many as needed)."""
    if config.negative_min_distance is None:
        return []
    n = n_positive if config.max_negatives is None else config.max_negatives
    out = []
    cand = find_negatives(poses, places, config.negative_min_distance, 4 * n)
    kept = []
    for src, tgt in cand:
        T = invert(poses[int(tgt)]) @ poses[int(src)]
        shared, _ = ground_truth_matches(sets[int(src)], sets[int(tgt)], T, config.tau_d_deg, config.rho)
        if len(shared) == 0:
            kept.append((int(src), int(tgt)))
    if len(kept) > n:
        kept = [kept[i] for i in np.unique(np.linspace(0, len(kept) - 1, n).round().astype(np.int64))]
    for src, tgt in kept:
        T = invert(poses[tgt]) @ poses[src]
        out.append(
            {
                "source_scan": src,
                "target_scan": tgt,
                "T_target_source": np.round(T, 10).tolist(),
                "true_matches": [],
                "n_possible": possible_matches(sets[src], sets[tgt]),
                "iir": 0.0,
                "case": 0,
                "distance": float(np.linalg.norm(T[:3, 3])),
                "rotation_deg": float(rotation_error_deg(T[:3, :3], np.eye(3))),
                "n_true_lines": 0,
                "n_true_planes": 0,
                "negative": True,
            }
        )
    return out


def build_loop_closure_dataset(
    dataset: Dataset,
    out_dir: str | Path,
    config: LoopClosureConfig | None = None,
    progress: bool = True,
    figure: bool = True,
) -> dict[str, Any]:
    """Build the loop-closure dataset of ``dataset`` into ``out_dir``; returns the summary.

    ``out_dir`` receives ``pairs.json``, ``landmarks/NNNNNN.npz`` (one per place, cached
    across runs), ``summary.json`` and ``dataset_details.png``.
    """
    config = config or LoopClosureConfig()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    poses = np.asarray(dataset.poses, dtype=float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(dataset):
        raise InvalidInputError("dataset.poses must be (n, 4, 4) with one pose per scan")
    places = select_places(poses, config.place_spacing)
    if config.max_places is not None:
        places = places[: config.max_places]
    revisits = find_revisits(
        poses,
        places,
        config.min_path_length,
        config.max_distance,
        config.wide_baseline_min_distance,
    )
    n_revisits = len(revisits)
    if config.max_pairs is not None and len(revisits) > config.max_pairs:
        pick = np.linspace(0, len(revisits) - 1, config.max_pairs).round().astype(np.int64)
        revisits = revisits[np.unique(pick)]
    # Only places that take part in a revisit need landmarks; we extract all places anyway so
    # the landmark statistics describe the whole trajectory and other pair rules can reuse them.
    t0 = time.perf_counter()
    ext = extract_place_landmarks(dataset, places.tolist(), out_dir, config, progress)
    t_extract = time.perf_counter() - t0

    t0 = time.perf_counter()
    sets = {int(i): LandmarkSet.load(_landmark_file(out_dir, int(i))) for i in places}
    s_all = path_lengths(poses)
    records: list[PairRecord] = []
    reasons: dict[str, int] = {}
    with progress_bar(progress and len(revisits) > 0) as bar:
        task = bar.add_task(
            f"revisits ({getattr(dataset, 'name', 'dataset')})", total=len(revisits)
        )
        for src, tgt in revisits:
            bar.advance(task)
            src, tgt = int(src), int(tgt)
            T = invert(poses[tgt]) @ poses[src]
            matches, n_possible, iir, case, v = evaluate_revisit(sets[src], sets[tgt], T, config)
            reasons[v.reason] = reasons.get(v.reason, 0) + 1
            if not v.valid:
                continue
            mtypes = sets[src].types[matches[:, 0]]
            records.append(
                PairRecord(
                    source_scan=src,
                    target_scan=tgt,
                    T_target_source=T,
                    true_matches=matches,
                    n_possible=n_possible,
                    iir=float(iir),
                    case=case,
                    distance=float(np.linalg.norm(T[:3, 3])),
                    rotation_deg=float(rotation_error_deg(T[:3, :3], np.eye(3))),
                    path_length=float(abs(s_all[src] - s_all[tgt])),
                    n_true_lines=int(np.sum(mtypes == LandmarkType.LINE)),
                    n_true_planes=int(np.sum(mtypes == LandmarkType.PLANE)),
                    n_true_points=int(np.sum(mtypes == LandmarkType.POINT)),
                    kappa=v.kappa,
                    gt_rotation_error_deg=v.rotation_error_deg,
                    gt_translation_error=v.translation_error,
                )
            )
    t_match = time.perf_counter() - t0
    negatives = _negative_pairs(poses, places, sets, config, len(records))

    place_counts = {i: sets[i].counts() for i in sets}
    summary_negatives = len(negatives)
    summary = _summary(
        dataset,
        places,
        n_revisits,
        len(revisits),
        records,
        reasons,
        place_counts,
        times={
            "total_s": time.perf_counter() - t_start,
            "extract_s": t_extract,
            "extract_worker_s": ext["extract_seconds"],
            "match_s": t_match,
        },
        cache=ext,
    )
    doc = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "dataset": {
            "name": getattr(dataset, "name", type(dataset).__name__),
            "loader": type(dataset).__name__,
            "scan_format": dataset.scan_format if isinstance(dataset, ScanSequence) else "unknown",
            "n_scans": len(dataset),
        },
        "config": config.model_dump(mode="json"),
        "places": [
            {
                "scan": int(i),
                "scan_path": str(Path(dataset.scan_path(int(i))).resolve()),
                "landmarks": f"{LANDMARK_DIR}/{int(i):06d}.npz",
                "T_world_lidar": np.round(poses[int(i)], 10).tolist(),
                "counts": place_counts[int(i)],
            }
            for i in places
        ],
        "pairs": [r.to_json() for r in records],
        "negatives": negatives,
        "summary": summary,
    }
    summary["n_negatives"] = summary_negatives
    write_text_atomic(out_dir / PAIRS_FILE, json.dumps(doc, indent=1))
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    if figure:
        from graffmatch.evaluation.figures import plot_dataset_details

        plot_dataset_details(LoopClosureDataset.load(out_dir), out_dir / "dataset_details.png")
    summary["total_s"] = time.perf_counter() - t_start
    return summary


def _summary(
    dataset: Dataset,
    places: NDArray[np.int64],
    n_revisits: int,
    n_checked: int,
    records: list[PairRecord],
    reasons: dict[str, int],
    place_counts: dict[int, dict[str, int]],
    times: dict[str, float],
    cache: dict[str, Any],
) -> dict[str, Any]:
    lines = np.array([c["lines"] for c in place_counts.values()], dtype=float)
    planes = np.array([c["planes"] for c in place_counts.values()], dtype=float)
    cases: dict[str, Any] = {}
    for c in (1, 2, 3):
        rs = [r for r in records if r.case == c]
        cases[str(c)] = {
            "pairs": len(rs),
            "mean_distance": float(np.mean([r.distance for r in rs])) if rs else None,
            "mean_iir": float(np.mean([r.iir for r in rs])) if rs else None,
            "mean_true_lines": float(np.mean([r.n_true_lines for r in rs])) if rs else None,
            "mean_true_planes": float(np.mean([r.n_true_planes for r in rs])) if rs else None,
        }

    def _stat(a: Array) -> dict[str, float]:
        if a.size == 0:
            return {"mean": 0.0, "median": 0.0, "min": 0.0, "max": 0.0}
        return {
            "mean": float(a.mean()),
            "median": float(np.median(a)),
            "min": float(a.min()),
            "max": float(a.max()),
        }

    return {
        "dataset": getattr(dataset, "name", type(dataset).__name__),
        "n_scans": len(dataset),
        "n_places": len(places),
        "n_revisits": int(n_revisits),
        "n_revisits_checked": int(n_checked),
        "n_valid": len(records),
        "cases": cases,
        "rejected": {k: v for k, v in sorted(reasons.items()) if k != "valid"},
        "landmarks_per_place": {"lines": _stat(lines), "planes": _stat(planes)},
        "landmarks_total": {"lines": int(lines.sum()), "planes": int(planes.sum())},
        "times": times,
        "cache": {k: cache[k] for k in ("extracted", "cached")},
    }


def summary_text(summary: dict[str, Any]) -> str:
    """A build summary as a few readable lines (what ``graffmatch build-dataset`` prints)."""
    cases = summary.get("cases", {})
    per_case = ", ".join(f"case {c}: {cases[c]['pairs']}" for c in sorted(cases))
    lines = [
        f"{summary.get('n_scans', '?')} scans, {summary.get('n_places', '?')} places, "
        f"{summary.get('n_revisits', '?')} revisits -> {summary.get('n_valid', 0)} loop "
        f"closures ({per_case or 'none'}), {summary.get('n_negatives', 0)} negative pairs "
        "(places without overlap)",
    ]
    rejected = summary.get("rejected") or {}
    if rejected:
        lines.append("rejected: " + ", ".join(f"{k} {v}" for k, v in rejected.items()))
    lm = summary.get("landmarks_per_place", {})
    if lm:
        lines.append(
            f"landmarks per place: {lm['lines']['mean']:.1f} poles, "
            f"{lm['planes']['mean']:.1f} planes (mean)"
        )
    if "total_s" in summary:
        lines.append(f"built in {summary['total_s']:.1f} s")
    return "\n".join(lines)


def __getattr__(name: str) -> Any:
    """The dataset figure moved to :mod:`graffmatch.evaluation.figures` (matplotlib, lazily)."""
    if name in ("plot_dataset_details", "CASE_COLORS"):
        from graffmatch.evaluation import figures

        return getattr(figures, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
