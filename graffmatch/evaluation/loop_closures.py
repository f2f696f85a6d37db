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

The output folder (``pairs.json`` + ``landmarks/``) is read back by :class:`LoopClosureDataset`;
the evaluation runner iterates over it.
"""

from __future__ import annotations

import functools
import json
import os
import time
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from graffmatch.association.putative import count_all_to_all
from graffmatch.datasets.base import Dataset, ScanSequence
from graffmatch.errors import DegenerateGeometryError, InvalidInputError, MalformedFileError
from graffmatch.evaluation.executors import LocalProcessExecutor, SerialExecutor
from graffmatch.geometry.distance import cross_distances
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.geometry.transforms import invert, rotation_error_deg, transform_errors
from graffmatch.lidar.cache import LandmarkCache
from graffmatch.lidar.extractor import LandmarkExtractor, LandmarkExtractorConfig

FORMAT_NAME = "graffmatch-loop-closures"
FORMAT_VERSION = 1
PAIRS_FILE = "pairs.json"
LANDMARK_DIR = "landmarks"
CACHE_INDEX = "cache.json"

Array = NDArray[np.float64]


class LoopClosureConfig(BaseModel):
    """Every rule of the dataset preparation; defaults are the paper's."""

    model_config = ConfigDict(extra="forbid")

    place_spacing: float = Field(
        2.0, gt=0, description="Path length between consecutive places [m] (paper: 2 m)."
    )
    min_path_length: float = Field(
        50.0, ge=0, description="A revisit needs more path than this between the places [m] (50 m)."
    )
    max_distance: float = Field(
        16.0, gt=0, description="A revisit needs the sensors closer than this [m] (paper: 16 m)."
    )
    wide_baseline_min_distance: float | None = Field(
        None,
        gt=0,
        description="Also accept pairs at least this far apart (and < max_distance) whatever the "
        "path between them: wide-baseline pairs of short walks. None: the paper's rule only [m].",
    )
    tau_d_deg: float = Field(
        6.0, gt=0, description="Gate on the GT-aligned invariant d_Graff of a true match [deg]."
    )
    rho: float = Field(40.0, gt=0, description="Scale rho of the invariant d_Graff [m] (paper: 40).")
    min_true_matches: int = Field(
        4, ge=0, description="A loop closure needs MORE than this many true matches (paper: 4)."
    )
    kappa_max: float = Field(
        1e3, gt=1, description="A loop closure needs a registration condition number below this."
    )
    max_rotation_error_deg: float = Field(
        5.0, gt=0, description="Registration with the true matches must be within this [deg]."
    )
    max_translation_error: float = Field(
        1.0, gt=0, description="Registration with the true matches must be within this [m]."
    )
    case_thresholds: tuple[float, float] = Field(
        (0.05, 0.03),
        description="IIR bounds: case 1 if IIR >= [0], case 2 if >= [1], else case 3.",
    )
    max_places: int | None = Field(
        None, ge=2, description="Keep only the first places (quick builds and tests)."
    )
    max_pairs: int | None = Field(
        None, ge=1, description="Keep at most this many revisits, evenly spaced (None: all)."
    )
    max_landmarks_per_type: int | None = Field(
        None,
        ge=1,
        description="Keep at most this many lines and this many planes per place, the largest "
        "by 'extent' (length / area); None keeps all (the paper). Fewer, more salient landmarks "
        "raise the IIR: with n planes per scan the IIR cannot exceed about 1/n.",
    )
    use_labels: bool = Field(
        True, description="Pass the dataset's semantic labels to the extractor when it has them."
    )
    store_support_points: bool = Field(
        True, description="Store the support points in the landmark files (ICP, BruteForceRMSE)."
    )
    workers: int = Field(
        2, ge=1, description="Processes extracting landmarks (1: in this process)."
    )
    extractor: LandmarkExtractorConfig = Field(
        default_factory=LandmarkExtractorConfig, description="Front-end configuration."
    )

    @model_validator(mode="after")
    def _check(self) -> LoopClosureConfig:
        hi, lo = self.case_thresholds
        if not 0 <= lo <= hi <= 1:
            raise ValueError("case_thresholds must be (case-1 bound, case-2 bound), 1 >= hi >= lo >= 0")
        wb = self.wide_baseline_min_distance
        if wb is not None and wb >= self.max_distance:
            raise ValueError("wide_baseline_min_distance must be below max_distance")
        return self


# ---- places and revisits -------------------------------------------------------------------
def path_lengths(poses: Array) -> Array:
    """Cumulative path length (n,) along the trajectory of (n, 4, 4) poses [m]."""
    P = np.asarray(poses, dtype=float)[:, :3, 3]
    steps = np.linalg.norm(np.diff(P, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def select_places(poses: Array, spacing: float = 2.0) -> NDArray[np.int64]:
    """Scan indices of the places: the first scan, then the first scan at least ``spacing`` of
    path after the previous place (greedy, as Scan Context's place sampling)."""
    s = path_lengths(poses)
    if len(s) == 0:
        return np.zeros(0, np.int64)
    places = [0]
    nxt = s[0] + spacing
    # Each place is found by a binary search, so this is O(places log n), not a loop over scans.
    while True:
        j = int(np.searchsorted(s, nxt - 1e-9, side="left"))
        if j >= len(s):
            break
        places.append(j)
        nxt = s[j] + spacing
    return np.asarray(places, dtype=np.int64)


def find_revisits(
    poses: Array,
    places: NDArray[np.int64],
    min_path_length: float = 50.0,
    max_distance: float = 16.0,
    wide_baseline_min_distance: float | None = None,
) -> NDArray[np.int64]:
    """(m, 2) scan indices (later place p, earlier place p') of the revisits, sorted."""
    places = np.asarray(places, dtype=np.int64)
    if len(places) < 2:
        return np.zeros((0, 2), np.int64)
    s = path_lengths(poses)[places]
    X = np.asarray(poses, dtype=float)[places, :3, 3]
    pairs = cKDTree(X).query_pairs(r=max_distance, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 2), np.int64)
    a, b = np.minimum(pairs[:, 0], pairs[:, 1]), np.maximum(pairs[:, 0], pairs[:, 1])
    d = np.linalg.norm(X[b] - X[a], axis=1)
    keep = (d < max_distance) & (s[b] - s[a] > min_path_length)
    if wide_baseline_min_distance is not None:
        keep |= (d >= wide_baseline_min_distance) & (d < max_distance)
    out = np.stack([places[b[keep]], places[a[keep]]], axis=1)
    order = np.lexsort((out[:, 1], out[:, 0]))
    return out[order]


# ---- ground-truth matches, IIR, validity ---------------------------------------------------
def ground_truth_matches(
    source: LandmarkSet,
    target: LandmarkSet,
    T_target_source: Array,
    tau_d_deg: float = 6.0,
    rho: float = 40.0,
) -> tuple[NDArray[np.int64], Array]:
    """True matches (k, 2) (source, target) and their GT-aligned distances [rad].

    Linear-sum assignment on the invariant d_Graff of the aligned sets; only same-type pairs
    below the gate are kept, so every landmark is matched at most once.
    """
    if len(source) == 0 or len(target) == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0)
    aligned = source.without_points().transform(T_target_source)
    D = cross_distances(aligned, target.without_points(), rho=rho)
    gate = np.deg2rad(tau_d_deg)
    feasible = D < gate
    if not feasible.any():
        return np.zeros((0, 2), np.int64), np.zeros(0)
    # Infeasible entries get a cost above any feasible sum so the assignment never trades a
    # gated match for them; they are dropped afterwards.
    cost = np.where(feasible, D, gate * (min(D.shape) + 1))
    r, c = linear_sum_assignment(cost)
    ok = feasible[r, c]
    matches = np.stack([r[ok], c[ok]], axis=1).astype(np.int64)
    return matches, D[r[ok], c[ok]]


def possible_matches(source: LandmarkSet, target: LandmarkSet) -> int:
    """Number of putative all-to-all (same-type) associations: sum n_i(type) n_j(type)."""
    return count_all_to_all(source.types, target.types)


def iir_case(iir: float, thresholds: Sequence[float] = (0.05, 0.03)) -> int:
    """Case 1 (IIR >= 0.05), 2 (0.03 <= IIR < 0.05) or 3 (IIR < 0.03)."""
    hi, lo = thresholds
    if iir >= hi:
        return 1
    if iir >= lo:
        return 2
    return 3


@dataclass
class Validity:
    """Outcome of the loop-closure rules for one revisit."""

    valid: bool
    reason: str
    kappa: float = float("nan")
    rotation_error_deg: float = float("nan")
    translation_error: float = float("nan")


def check_validity(
    source: LandmarkSet,
    target: LandmarkSet,
    matches: NDArray[np.int64],
    T_target_source: Array,
    config: LoopClosureConfig,
) -> Validity:
    """Apply the paper's rules: > 4 matches, kappa < kappa_max, errors < 5 deg and 1 m."""
    from graffmatch.registration.closed_form import register_landmarks

    if len(matches) <= config.min_true_matches:
        return Validity(False, "few_matches")
    try:
        est = register_landmarks(
            source.without_points(), target.without_points(), matches, kappa_max=config.kappa_max
        )
    except DegenerateGeometryError:
        return Validity(False, "degenerate")
    kappa = float(est.kappa)
    if bool(getattr(est, "degenerate", False)) or not np.isfinite(kappa) or kappa >= config.kappa_max:
        return Validity(False, "ill_conditioned", kappa=kappa)
    rot, trans = transform_errors(est.T_target_source, T_target_source)
    v = Validity(False, "registration_error", kappa, float(rot), float(trans))
    if rot < config.max_rotation_error_deg and trans < config.max_translation_error:
        v.valid, v.reason = True, "valid"
    return v


# ---- per-place landmark extraction (parallel, cached) ---------------------------------------
def keep_most_salient(ls: LandmarkSet, max_per_type: int | None) -> LandmarkSet:
    """At most ``max_per_type`` landmarks of each type, the largest by ``extent`` (ties and
    missing extents: support, then original order); the original order is kept."""
    if max_per_type is None or len(ls) == 0:
        return ls
    n = len(ls)
    extent = np.nan_to_num(np.asarray(ls.attributes.get("extent", np.zeros(n)), float).reshape(n))
    support = np.nan_to_num(np.asarray(ls.attributes.get("support", np.zeros(n)), float).reshape(n))
    keep = np.zeros(n, bool)
    for t in np.unique(ls.types):
        idx = np.flatnonzero(ls.types == t)
        order = np.lexsort((idx, -support[idx], -extent[idx]))
        keep[idx[order[:max_per_type]]] = True
    return ls[np.flatnonzero(keep)]


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
        with _progress(progress) as bar:
            task = bar.add_task(f"landmarks ({getattr(dataset, 'name', 'dataset')})", total=len(todo))
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


class _NullProgress:
    def __enter__(self) -> _NullProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def add_task(self, *a: Any, **k: Any) -> int:
        return 0

    def advance(self, *a: Any, **k: Any) -> None:
        return None


def _progress(enabled: bool) -> Any:
    if not enabled:
        return _NullProgress()
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

    return Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        transient=True,
    )


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
        poses, places, config.min_path_length, config.max_distance, config.wide_baseline_min_distance
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
    for src, tgt in revisits:
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

    place_counts = {i: sets[i].counts() for i in sets}
    summary = _summary(
        dataset, places, n_revisits, len(revisits), records, reasons, place_counts,
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
        "summary": summary,
    }
    _atomic_write(out_dir / PAIRS_FILE, json.dumps(doc, indent=1))
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    if figure:
        plot_dataset_details(LoopClosureDataset.load(out_dir), out_dir / "dataset_details.png")
    summary["total_s"] = time.perf_counter() - t_start
    return summary


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


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


# ---- reading the dataset back ---------------------------------------------------------------
@functools.lru_cache(maxsize=1024)
def _load_landmarks(path: str, mtime_ns: int, size: int) -> LandmarkSet:
    return LandmarkSet.load(path)


def load_landmarks_cached(path: str | Path) -> LandmarkSet:
    """Load a landmark file once per process (keyed on path, mtime and size).

    Pairs share places, so the sets are shared too; treat them as read-only.
    """
    p = Path(path)
    try:
        st = p.stat()
    except OSError as exc:
        raise MalformedFileError(f"{p}: landmark file missing ({exc})") from exc
    return _load_landmarks(str(p.resolve()), st.st_mtime_ns, st.st_size)


@dataclass
class LoopClosurePair:
    """One loop closure: two landmark sets and the ground truth relating them."""

    index: int
    source_scan: int
    target_scan: int
    T_target_source: Array
    true_matches: NDArray[np.int64]
    n_possible: int
    iir: float
    case: int
    distance: float
    rotation_deg: float
    n_true_lines: int
    n_true_planes: int
    source_scan_path: Path
    target_scan_path: Path
    source_landmarks_path: Path
    target_landmarks_path: Path
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def source(self) -> LandmarkSet:
        """Landmarks of the source scan (its frame), with support points when stored."""
        return load_landmarks_cached(self.source_landmarks_path)

    @property
    def target(self) -> LandmarkSet:
        """Landmarks of the target scan (its frame)."""
        return load_landmarks_cached(self.target_landmarks_path)

    @property
    def pair_id(self) -> str:
        return f"{self.source_scan:06d}-{self.target_scan:06d}"

    def __repr__(self) -> str:
        return (
            f"LoopClosurePair({self.pair_id}, case={self.case}, iir={self.iir:.3f}, "
            f"true_matches={len(self.true_matches)}/{self.n_possible}, "
            f"distance={self.distance:.1f} m, rotation={self.rotation_deg:.0f} deg)"
        )


class LoopClosureDataset(Sequence):
    """A built loop-closure dataset: ``for pair in LoopClosureDataset.load(dir): ...``.

    Landmark sets are loaded lazily and shared between the pairs of a place.
    """

    def __init__(self, root: Path, doc: dict[str, Any]) -> None:
        self.root = Path(root)
        self.doc = doc
        self.config = LoopClosureConfig.model_validate(doc["config"])
        self.summary: dict[str, Any] = doc.get("summary", {})
        self.name: str = doc.get("dataset", {}).get("name", self.root.name)
        #: Encoding of the scan files ("kitti-bin", "nclt-bin", "unknown") for point methods.
        self.scan_format: str = doc.get("dataset", {}).get("scan_format", "kitti-bin")
        self.places: dict[int, dict[str, Any]] = {int(p["scan"]): p for p in doc["places"]}
        self.pairs = [self._make_pair(k, p) for k, p in enumerate(doc["pairs"])]

    @classmethod
    def load(cls, root: str | Path) -> LoopClosureDataset:
        root = Path(root)
        f = root / PAIRS_FILE
        if not f.is_file():
            raise InvalidInputError(f"not a loop-closure dataset (no {PAIRS_FILE}): {root}")
        try:
            doc = json.loads(f.read_text())
        except json.JSONDecodeError as exc:
            raise MalformedFileError(f"{f}: not valid JSON ({exc})") from exc
        if doc.get("format") != FORMAT_NAME:
            raise MalformedFileError(f"{f}: not a {FORMAT_NAME} file")
        if int(doc.get("version", 0)) > FORMAT_VERSION:
            raise MalformedFileError(
                f"{f}: format version {doc.get('version')} is newer than {FORMAT_VERSION}"
            )
        for key in ("config", "places", "pairs"):
            if key not in doc:
                raise MalformedFileError(f"{f}: missing {key!r}")
        return cls(root, doc)

    def landmark_path(self, scan: int) -> Path:
        place = self.places.get(int(scan))
        if place is None:
            raise MalformedFileError(f"{self.root / PAIRS_FILE}: scan {scan} is not a place")
        return self.root / place["landmarks"]

    def landmarks(self, scan: int) -> LandmarkSet:
        """Landmarks of a place by scan index."""
        return load_landmarks_cached(self.landmark_path(scan))

    def _make_pair(self, k: int, p: dict[str, Any]) -> LoopClosurePair:
        try:
            src, tgt = int(p["source_scan"]), int(p["target_scan"])
            T = np.asarray(p["T_target_source"], dtype=float).reshape(4, 4)
            m = np.asarray(p["true_matches"], dtype=np.int64).reshape(-1, 2)
            pair = LoopClosurePair(
                index=k,
                source_scan=src,
                target_scan=tgt,
                T_target_source=T,
                true_matches=m,
                n_possible=int(p["n_possible"]),
                iir=float(p["iir"]),
                case=int(p["case"]),
                distance=float(p["distance"]),
                rotation_deg=float(p["rotation_deg"]),
                n_true_lines=int(p["n_true_lines"]),
                n_true_planes=int(p["n_true_planes"]),
                source_scan_path=Path(self.places[src]["scan_path"]),
                target_scan_path=Path(self.places[tgt]["scan_path"]),
                source_landmarks_path=self.landmark_path(src),
                target_landmarks_path=self.landmark_path(tgt),
                info={
                    key: p[key]
                    for key in ("path_length", "kappa", "gt_rotation_error_deg", "gt_translation_error")
                    if key in p
                },
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise MalformedFileError(f"{self.root / PAIRS_FILE}: pair {k} is malformed ({exc})") from exc
        return pair

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, i: int) -> LoopClosurePair:  # type: ignore[override]
        return self.pairs[i]

    def __iter__(self) -> Iterator[LoopClosurePair]:
        return iter(self.pairs)

    def of_case(self, case: int) -> list[LoopClosurePair]:
        return [p for p in self.pairs if p.case == case]

    def case_counts(self) -> dict[int, int]:
        return {c: sum(p.case == c for p in self.pairs) for c in (1, 2, 3)}

    def __repr__(self) -> str:
        c = self.case_counts()
        return (
            f"LoopClosureDataset({self.name!r}, pairs={len(self)}, cases={c}, "
            f"places={len(self.places)})"
        )


# ---- figure ---------------------------------------------------------------------------------
CASE_COLORS = {1: "#2ca02c", 2: "#ff7f0e", 3: "#d62728"}


def plot_dataset_details(ds: LoopClosureDataset, path: str | Path) -> Path:
    """The paper's dataset-details figure: IIR vs sensor distance (coloured by case), and the
    true line and plane matches per case."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 4))
    for c in (1, 2, 3):
        ps = ds.of_case(c)
        ax0.scatter(
            [p.distance for p in ps], [p.iir for p in ps], s=10, alpha=0.7,
            color=CASE_COLORS[c], label=f"case {c} ({len(ps)})",
        )
    ax0.set_xlabel("sensor distance [m]")
    ax0.set_ylabel("input inlier ratio")
    ax0.set_yscale("log")
    for y in ds.config.case_thresholds:
        ax0.axhline(y, color="grey", lw=0.8, ls="--")
    ax0.legend(loc="upper right", fontsize=8)
    ax0.set_title(f"{ds.name}: {len(ds)} loop closures")
    data, pos, colors = [], [], []
    for k, c in enumerate((1, 2, 3)):
        ps = ds.of_case(c)
        if not ps:  # an empty case gets no box (not a misleading box at zero)
            continue
        data += [[p.n_true_lines for p in ps], [p.n_true_planes for p in ps]]
        pos += [3 * k + 0.6, 3 * k + 1.4]
        colors += ["#1f77b4", "#9467bd"]
    if data:
        bp = ax1.boxplot(data, positions=pos, widths=0.7, patch_artist=True, showfliers=False)
        for patch, col in zip(bp["boxes"], colors, strict=True):
            patch.set_facecolor(col)
            patch.set_alpha(0.6)
    counts = ds.case_counts()
    ax1.set_xticks([1, 4, 7], [f"case {c}\n(n={counts[c]})" for c in (1, 2, 3)])
    ax1.set_xlim(-0.5, 8.5)
    ax1.set_ylabel("true matches per pair")
    from matplotlib.patches import Patch

    ax1.legend(
        [Patch(color="#1f77b4", alpha=0.6), Patch(color="#9467bd", alpha=0.6)],
        ["lines", "planes"], fontsize=8,
    )
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
