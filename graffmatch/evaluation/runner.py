"""The experiment runner: every method on every loop-closure pair, one JSON record per result.

A study is the cross product (suite, pair, method). Each task is independent, so it is handed to
a pluggable :mod:`~graffmatch.evaluation.executors` engine (local process pool, Dask, Ray). The
driver writes every finished record *at once* with an atomic write (temporary file +
``os.replace``), so killing a worker or the driver loses no finished result, and a rerun skips
what is on disk and computes only the rest.

Layout of a results folder::

    config.json                 the exact configuration of the last invocation
    runs.jsonl                  one line per invocation (config, start, end, counts)
    pairs/<suite>.json          per pair: id, case, IIR, baseline distance, #true matches, counts
    stats/<suite>.json          histogram of pairwise landmark-centroid distances (rho choice)
    records/<suite>/<method>/<pair_id>.json   one record per (method, pair)

A record is :class:`graffmatch.evaluation.metrics.PairRecord` (estimate, ground truth, the
GT-aligned d_Graff distance of every selected association, timings) plus the derived numbers a
human wants to grep: rotation/translation error, success, OIR and the inlier mask at tau_d.

The pseudo-method ``GT-matches`` registers each pair with its true landmark matches; it is the
best a landmark-only registration can do and the first column of the error heatmaps.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import platform
import re
import subprocess
import tempfile
import time
import traceback
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.errors import InvalidInputError, MalformedFileError
from graffmatch.evaluation import metrics as M
from graffmatch.evaluation.executors import Executor, make_executor
from graffmatch.geometry.landmarks import LandmarkSet

GT_METHOD = "GT-matches"
RECORD_VERSION = 1
DEFAULT_RHO_VALUES = (5.0, 10.0, 20.0, 40.0, 80.0, 160.0)
RHO_METHOD = "GraffMatch"

#: Point methods skipped by ``quick=True`` (each takes seconds per pair on full scans).
QUICK_SKIP_METHODS = ("FPFH+RANSAC", "KISS-Matcher", "ScanContext+ICP")
#: Pairs per case and rho-study pairs per suite of ``quick=True``.
QUICK_PAIRS_PER_CASE = 3
QUICK_RHO_PAIRS = 4


# ----------------------------------------------------------------------------------------------
# inputs
# ----------------------------------------------------------------------------------------------
@runtime_checkable
class LoopClosurePair(Protocol):
    """What the runner needs of a pair (``LoopClosureDataset`` pairs satisfy it)."""

    source: LandmarkSet
    target: LandmarkSet
    T_target_source: NDArray[np.float64]
    true_matches: NDArray[np.intp]
    case: int


@runtime_checkable
class EvaluationMethod(Protocol):
    """A method given as an object instead of a registry name (custom methods, tests).

    It must be picklable (a module-level class) so that it can travel to workers, and return an
    object with ``T_target_source`` (4x4 or None), ``associations`` (k, 2), ``timings`` (dict),
    ``valid`` and ``info``.
    """

    name: str
    kind: str  # "landmark" or "point"

    def __call__(self, pair: Any) -> Any: ...


class StudyConfig(BaseModel):
    """Everything that determines the records of a study (written to ``config.json``)."""

    model_config = ConfigDict(extra="forbid")

    methods: list[str] = Field(
        default_factory=list,
        description="Method names in column order; GT-matches is always added first.",
    )
    tau_d_deg: float = Field(
        M.DEFAULT_TAU_D_DEG, gt=0, description="Inlier threshold on GT-aligned d_Graff [deg]."
    )
    rho_eval: float = Field(
        M.DEFAULT_RHO, gt=0, description="rho of the invariant d_Graff used for the inlier test."
    )
    max_rotation_deg: float = Field(
        M.DEFAULT_MAX_ROTATION_DEG, gt=0, description="Success threshold on rotation error [deg]."
    )
    max_translation_m: float = Field(
        M.DEFAULT_MAX_TRANSLATION_M, gt=0, description="Success threshold on translation [m]."
    )
    max_pairs_per_case: int | None = Field(
        None, ge=1, description="Evenly spaced subset of at most this many pairs per case."
    )
    rho_values: list[float] = Field(
        default_factory=lambda: list(DEFAULT_RHO_VALUES),
        description="rho values of the GraffMatch sensitivity study (empty: no study).",
    )
    rho_pairs_per_suite: int = Field(
        24, ge=0, description="Pairs per suite (evenly spaced) used for the rho study."
    )
    retry_errors: bool = Field(
        False, description="Rerun tasks whose saved record says the method raised."
    )


@dataclass(frozen=True)
class PairRef:
    """A pair stored in a loop-closure dataset folder, loaded by the worker (no pickling)."""

    dataset_dir: str
    index: int

    def load(self) -> Any:
        return _dataset_pairs(self.dataset_dir)[self.index]


def _dataset_pairs(dataset_dir: str) -> list[Any]:
    """The pairs of a dataset folder, loaded once per process (and again if rebuilt)."""
    from graffmatch.evaluation.loop_closures import PAIRS_FILE

    f = Path(dataset_dir) / PAIRS_FILE
    return _dataset_pairs_cached(dataset_dir, f.stat().st_mtime_ns if f.is_file() else 0)


@functools.lru_cache(maxsize=8)
def _dataset_pairs_cached(dataset_dir: str, mtime_ns: int) -> list[Any]:
    from graffmatch.evaluation.loop_closures import LoopClosureDataset

    return list(LoopClosureDataset.load(Path(dataset_dir)))


@dataclass(frozen=True)
class Task:
    """One (suite, pair, method) unit of work; small and picklable."""

    suite: str
    pair_id: str
    method: str | EvaluationMethod
    pair: Any  # a LoopClosurePair or a PairRef
    task_key: str  # fingerprint of the pair content and evaluation settings (see _task_key)
    tau_d_deg: float
    rho_eval: float
    max_rotation_deg: float
    max_translation_m: float

    @property
    def method_name(self) -> str:
        return self.method if isinstance(self.method, str) else str(self.method.name)


# ----------------------------------------------------------------------------------------------
# method specs: "GraffMatch[rho=20]" -> ("GraffMatch", {"rho": 20.0})
# ----------------------------------------------------------------------------------------------
_SPEC = re.compile(r"^(?P<name>[^\[\]]+?)(?:\[(?P<params>[^\[\]]*)\])?$")


def parse_method_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """Split ``Name[key=value,...]`` into the registry name and config overrides."""
    m = _SPEC.match(spec.strip())
    if not m:
        raise InvalidInputError(f"malformed method spec {spec!r}; expected Name or Name[k=v,...]")
    params: dict[str, Any] = {}
    for part in filter(None, (p.strip() for p in (m.group("params") or "").split(","))):
        if "=" not in part:
            raise InvalidInputError(f"malformed parameter {part!r} in method spec {spec!r}")
        k, v = (s.strip() for s in part.split("=", 1))
        try:
            params[k] = json.loads(v)
        except json.JSONDecodeError:
            params[k] = v
    return m.group("name").strip(), params


def rho_spec(rho: float, method: str = RHO_METHOD) -> str:
    return f"{method}[rho={float(rho):g}]"


def method_kind(spec: str) -> str:
    """'landmark' or 'point' from the registry ('landmark' for the GT pseudo-method)."""
    name = parse_method_spec(spec)[0]
    if name == GT_METHOD:
        return "landmark"
    from graffmatch.evaluation import methods as registry

    entry = registry.METHODS.get(name)
    if entry is None:
        raise InvalidInputError(
            f"unknown method {name!r}; available: {', '.join(registry.list_methods())}"
        )
    return str(entry.kind)


# ----------------------------------------------------------------------------------------------
# the worker side
# ----------------------------------------------------------------------------------------------
@dataclass
class _Output:
    T_target_source: NDArray[np.float64] | None
    associations: NDArray[np.intp]
    timings: dict[str, float]
    valid: bool
    info: dict[str, Any]


def _gt_output(pair: Any) -> _Output:
    """Register the landmarks with the true matches: the landmark-only best case."""
    from graffmatch.registration.closed_form import register_landmarks

    t0 = time.perf_counter()
    matches = np.asarray(pair.true_matches, dtype=np.intp).reshape(-1, 2)
    est = register_landmarks(pair.source, pair.target, matches)
    dt = time.perf_counter() - t0
    return _Output(
        T_target_source=np.asarray(est.T_target_source, float),
        associations=matches,
        timings={"registration": dt, "total": dt},
        valid=not bool(getattr(est, "degenerate", False)),
        info={"kappa": float(getattr(est, "kappa", np.nan))},
    )


@functools.lru_cache(maxsize=64)
def _registry_method(spec: str) -> Any:
    from graffmatch.evaluation import methods as registry

    name, params = parse_method_spec(spec)
    return registry.get_method(name, **params) if params else registry.get_method(name)


def _run_registry_method(spec: str, pair: Any) -> Any:
    from graffmatch.evaluation import methods as registry

    method = _registry_method(spec)
    # LoopClosurePair.source_scan is the scan *index*; only arrays are raw points.
    src_pts, tgt_pts = getattr(pair, "source_scan", None), getattr(pair, "target_scan", None)
    inp = registry.PairInput(
        source=pair.source,
        target=pair.target,
        source_scan=src_pts if isinstance(src_pts, np.ndarray) else None,
        target_scan=tgt_pts if isinstance(tgt_pts, np.ndarray) else None,
        source_scan_path=getattr(pair, "source_scan_path", None),
        target_scan_path=getattr(pair, "target_scan_path", None),
    )
    return method.run(inp)


def _as_output(out: Any) -> _Output:
    T = getattr(out, "T_target_source", None)
    a = getattr(out, "associations", None)
    a = np.zeros((0, 2), np.intp) if a is None else np.asarray(a)
    return _Output(
        T_target_source=None if T is None else np.asarray(T, dtype=float),
        associations=a.reshape(-1, 2) if a.size else np.zeros((0, 2), np.intp),
        timings={str(k): float(v) for k, v in (getattr(out, "timings", None) or {}).items()},
        valid=bool(getattr(out, "valid", T is not None)),
        info=dict(getattr(out, "info", None) or {}),
    )


def _jsonable_info(info: Mapping[str, Any]) -> dict[str, Any]:
    """Keep what JSON can hold; everything else is written as its repr (never crash on info)."""

    def conv(v: Any) -> Any:
        if isinstance(v, (str, bool, int, float)) or v is None:
            return v
        if isinstance(v, (np.generic, np.ndarray)):
            return v.tolist() if np.size(v) <= 64 else f"<array shape={np.shape(v)}>"
        if isinstance(v, Mapping):
            return {str(k): conv(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v][:64]
        return repr(v)

    return {str(k): conv(v) for k, v in info.items()}


def execute_task(task: Task) -> dict[str, Any]:
    """Run one method on one pair and evaluate it (runs in a worker; returns a JSON dict).

    A method that raises yields a record with ``status="error"`` and the message: one baseline
    crashing on one pair must not end a study of hours. The report counts these.
    """
    pair = task.pair.load() if isinstance(task.pair, PairRef) else task.pair
    name = task.method_name
    kind = (
        str(getattr(task.method, "kind", "landmark"))
        if not isinstance(task.method, str)
        else method_kind(name)
    )
    T_gt = np.asarray(pair.T_target_source, dtype=float)
    error: str | None = None
    t0 = time.perf_counter()
    try:
        if name == GT_METHOD:
            out = _gt_output(pair)
        elif isinstance(task.method, str):
            out = _as_output(_run_registry_method(task.method, pair))
        else:
            out = _as_output(task.method(pair))
    except Exception as exc:  # recorded, see docstring
        tb = traceback.format_exc(limit=6)
        error = f"{type(exc).__name__}: {exc}\n{tb}"
        out = _Output(None, np.zeros((0, 2), np.intp), {}, False, {})
    wall = time.perf_counter() - t0
    timings = dict(out.timings)
    timings.setdefault("total", wall)

    def evaluate(o: _Output) -> M.PairRecord:
        # Point methods return point correspondences, not landmark indices: no LMR for them.
        return M.PairRecord.from_output(
            pair_id=task.pair_id,
            method=name,
            source=pair.source,
            target=pair.target,
            T_target_source_gt=T_gt,
            T_target_source_est=o.T_target_source if o.valid else None,
            associations=o.associations if kind == "landmark" else None,
            timings=timings,
            valid=o.valid,
            kind=kind,
            rho=task.rho_eval,
            info=_jsonable_info(o.info),
        )

    try:
        rec = evaluate(out)
    except Exception as exc:  # malformed output (e.g. indices out of range): an error record
        error = f"invalid output: {type(exc).__name__}: {exc}"
        out = _Output(None, np.zeros((0, 2), np.intp), {}, False, {})
        rec = evaluate(out)
    if kind != "landmark":
        rec.n_associations = len(out.associations)
    rot, trans = rec.errors()
    d = rec.association_distances_deg
    doc = rec.to_dict()
    doc.update(
        M._jsonable(
            {
                "record_version": RECORD_VERSION,
                "task_key": task.task_key,
                "suite": task.suite,
                "case": int(getattr(pair, "case", 0)),
                "iir": float(getattr(pair, "iir", np.nan)),
                "distance": float(getattr(pair, "distance", np.nan)),
                "n_true_matches": len(np.asarray(pair.true_matches).reshape(-1, 2)),
                "rotation_error_deg": rot,
                "translation_error_m": trans,
                "success": M.registration_success(
                    rot, trans, task.max_rotation_deg, task.max_translation_m
                ),
                "tau_d_deg": task.tau_d_deg,
                "oir": M.oir_from_distances(d, task.tau_d_deg) if kind == "landmark" else None,
                "inlier_mask": (d < task.tau_d_deg) if kind == "landmark" else None,
                "status": "ok" if error is None else "error",
                "error": error,
            }
        )
    )
    return doc


# ----------------------------------------------------------------------------------------------
# files
# ----------------------------------------------------------------------------------------------
def slug(text: str) -> str:
    """A file-name-safe, readable and injective-enough form of a method or pair name."""
    s = re.sub(r"[^A-Za-z0-9._+=-]+", "_", text).strip("_")
    return s or "_"


def record_path(out_dir: str | Path, suite: str, method: str, pair_id: str) -> Path:
    return Path(out_dir) / "records" / slug(suite) / slug(method) / f"{slug(pair_id)}.json"


def atomic_write_json(path: Path, doc: Any) -> None:
    """Write JSON so that a reader sees the old file or the complete new one, never half."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(doc, f, indent=1)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _read_record(path: Path) -> dict[str, Any] | None:
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return doc if isinstance(doc, dict) and doc.get("record_version") == RECORD_VERSION else None


def load_records(results_dir: str | Path, current_only: bool = True) -> list[dict[str, Any]]:
    """The records of a results folder, sorted by (suite, method, pair_id).

    ``current_only``: keep only records of the pairs selected by the last run (``pairs/``),
    computed on the same pair content and settings; stale records of a rebuilt dataset or of a
    larger earlier selection stay on disk but are not reported.
    """
    root = Path(results_dir) / "records"
    if not root.is_dir():
        raise MalformedFileError(f"{results_dir} is not a results folder (no records/)")
    out = [r for p in sorted(root.glob("*/*/*.json")) if (r := _read_record(p)) is not None]
    if current_only:
        keys = _current_task_keys(Path(results_dir))
        if keys is not None:
            out = [
                r for r in out if keys.get((slug(r["suite"]), r["pair_id"])) == r.get("task_key")
            ]
    out.sort(key=lambda r: (r["suite"], r["method"], r["pair_id"]))
    return out


def _current_task_keys(results_dir: Path) -> dict[tuple[str, str], str] | None:
    """(suite slug, pair_id) -> task key of the latest selection per suite; None if unknown."""
    cfg = load_config(results_dir)
    pairs_dir = results_dir / "pairs"
    if not cfg.get("study") or not pairs_dir.is_dir():
        return None
    study = StudyConfig.model_validate(cfg["study"])
    out: dict[tuple[str, str], str] = {}
    for f in sorted(pairs_dir.glob("*.json")):
        for meta in json.loads(f.read_text()):
            out[(f.stem, str(meta["pair_id"]))] = _task_key(str(meta.get("fingerprint")), study)
    return out


def load_config(results_dir: str | Path) -> dict[str, Any]:
    p = Path(results_dir) / "config.json"
    return json.loads(p.read_text()) if p.is_file() else {}


def record_without_timings(rec: Mapping[str, Any]) -> dict[str, Any]:
    """A record minus what legitimately differs between runs (timings)."""
    drop = {"timings"}
    return {k: v for k, v in rec.items() if k not in drop}


# ----------------------------------------------------------------------------------------------
# the driver
# ----------------------------------------------------------------------------------------------
@dataclass
class _PairEntry:
    pair_id: str
    case: int
    ref: Any  # pair object or PairRef
    meta: dict[str, Any]


def _pair_id(pair: Any, index: int) -> str:
    for attr in ("pair_id", "name", "id"):
        v = getattr(pair, attr, None)
        if v is not None and not callable(v):
            return str(v)
    return f"{index:06d}"


def pair_fingerprint(pair: Any) -> str:
    """Hash of what defines a pair (ground truth, true matches, case, both landmark sets).

    A record is reused on resume only if the pair it was computed on is unchanged: a rebuilt
    dataset may keep pair ids while their landmarks or cases change.
    """
    h = hashlib.sha1()
    for a in (
        np.round(np.asarray(pair.T_target_source, dtype=float), 9),
        np.asarray(pair.true_matches, dtype=np.int64),
        np.asarray([int(getattr(pair, "case", 0))]),
    ):
        h.update(np.ascontiguousarray(a).tobytes())
    for ls in (pair.source, pair.target):
        h.update(np.ascontiguousarray(ls.types).tobytes())
        h.update(np.ascontiguousarray(np.round(ls.anchors, 9)).tobytes())
        h.update(np.ascontiguousarray(np.round(ls.bases, 9)).tobytes())
        h.update(str(None if ls.points is None else ls.points.shape).encode())
    return h.hexdigest()[:16]


def _task_key(fingerprint: str, cfg: StudyConfig) -> str:
    params = (cfg.tau_d_deg, cfg.rho_eval, cfg.max_rotation_deg, cfg.max_translation_m)
    return hashlib.sha1(f"{fingerprint}|{params!r}".encode()).hexdigest()[:16]


def _pair_meta(pair: Any, pair_id: str) -> dict[str, Any]:
    src, tgt = pair.source, pair.target
    return M._jsonable(
        {
            "pair_id": pair_id,
            "fingerprint": pair_fingerprint(pair),
            "case": int(getattr(pair, "case", 0)),
            "iir": float(getattr(pair, "iir", np.nan)),
            "distance": float(getattr(pair, "distance", np.nan)),
            "n_true_matches": len(np.asarray(pair.true_matches).reshape(-1, 2)),
            "source_counts": src.counts(),
            "target_counts": tgt.counts(),
            "source_scan_path": str(getattr(pair, "source_scan_path", "") or ""),
            "target_scan_path": str(getattr(pair, "target_scan_path", "") or ""),
        }
    )


def _entries_from(pairs: Iterable[Any], dataset_dir: str | None) -> list[_PairEntry]:
    out = []
    seen: set[str] = set()
    for i, pair in enumerate(pairs):
        pid = _pair_id(pair, i)
        if pid in seen:
            raise InvalidInputError(f"duplicate pair id {pid!r}")
        seen.add(pid)
        ref = PairRef(dataset_dir, i) if dataset_dir else pair
        out.append(_PairEntry(pid, int(getattr(pair, "case", 0)), ref, _pair_meta(pair, pid)))
    return out


#: ``{suite: pairs or dataset folder}`` or a list of dataset folders (suite = folder name).
Sources = Mapping[str, Iterable[Any] | str | Path] | Sequence[str | Path] | str | Path


def _normalize_sources(sources: Sources) -> dict[str, tuple[list[_PairEntry], list[Any]]]:
    """suite -> (entries, pairs). Dataset folders become PairRefs (workers load them)."""
    out: dict[str, tuple[list[_PairEntry], list[Any]]] = {}
    if isinstance(sources, (str, Path)):
        sources = [sources]
    named: list[tuple[str, Any]] = (
        [(str(k), v) for k, v in sources.items()]
        if isinstance(sources, Mapping)
        else [(Path(d).name, d) for d in sources]
    )
    for name, src in named:
        if name in out:
            raise InvalidInputError(f"two suites named {name!r}; rename one")
        if isinstance(src, (str, Path)):
            d = Path(src)
            if not d.is_dir():
                raise InvalidInputError(f"loop-closure dataset folder not found: {d}")
            pairs = _dataset_pairs(str(d.resolve()))
            out[name] = (_entries_from(pairs, str(d.resolve())), pairs)
        else:
            pairs = list(src)
            out[name] = (_entries_from(pairs, None), pairs)
    return out


def _subset_per_case(entries: list[_PairEntry], k: int | None) -> list[_PairEntry]:
    """Evenly spaced subset of at most k pairs per case (deterministic, representative)."""
    if k is None:
        return entries
    out: list[_PairEntry] = []
    for case in sorted({e.case for e in entries}):
        group = [e for e in entries if e.case == case]
        if len(group) > k:
            idx = np.unique(np.round(np.linspace(0, len(group) - 1, k)).astype(int))
            group = [group[i] for i in idx]
        out.extend(group)
    return out


def _evenly(entries: list[_PairEntry], k: int) -> list[_PairEntry]:
    if k <= 0 or not entries:
        return []
    if len(entries) <= k:
        return entries
    idx = np.unique(np.round(np.linspace(0, len(entries) - 1, k)).astype(int))
    return [entries[i] for i in idx]


def centroid_distance_stats(pairs: Iterable[Any], bin_width: float = 2.0) -> dict[str, Any]:
    """Histogram of intra-scan pairwise landmark-anchor distances (the paper's rho argument)."""
    from scipy.spatial.distance import pdist

    seen: set[str] = set()
    hist = np.zeros(0, dtype=np.int64)
    n = 0
    s1 = s2 = 0.0
    for pair in pairs:
        for side in ("source", "target"):
            key = str(getattr(pair, f"{side}_scan_path", "") or "")
            if key and key in seen:
                continue
            seen.add(key)
            anchors = getattr(pair, side).anchors
            if len(anchors) < 2:
                continue
            d = pdist(anchors)
            counts = np.bincount((d // bin_width).astype(np.int64))
            if len(counts) > len(hist):
                hist = np.pad(hist, (0, len(counts) - len(hist)))
            hist[: len(counts)] += counts
            n += d.size
            s1 += float(d.sum())
            s2 += float((d * d).sum())
    mean = s1 / n if n else float("nan")
    std = float(np.sqrt(max(s2 / n - mean * mean, 0.0))) if n else float("nan")
    return {
        "bin_width_m": bin_width,
        "counts": hist.tolist(),
        "n_distances": n,
        "mean_m": mean,
        "std_m": std,
    }


def _git_commit() -> str | None:
    try:
        r = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
    except OSError:
        return None
    return r.stdout.strip() or None


def _method_params(method: str | EvaluationMethod) -> Any:
    """The parameters a method runs with, for config.json (what the paper calls its setup)."""
    try:
        obj = _registry_method(method) if isinstance(method, str) else method
        params = getattr(obj, "params", None)
        if params is None and hasattr(obj, "__dataclass_fields__"):
            params = {k: getattr(obj, k) for k in obj.__dataclass_fields__}
        return _jsonable_info(dict(params or {}))
    except Exception as exc:  # never fail a study on bookkeeping; say why it is missing
        return {"unavailable": f"{type(exc).__name__}: {exc}"}


def default_methods(quick: bool = False) -> list[str]:
    """Every registered method; quick mode keeps the fast point methods only."""
    from graffmatch.evaluation import methods as registry

    names = list(registry.list_methods())
    if quick:
        names = [n for n in names if n not in QUICK_SKIP_METHODS]
    return names


def run_study(
    sources: Sources,
    methods: Sequence[str | EvaluationMethod] | None = None,
    out_dir: str | Path = "results",
    executor: str | Executor = "local",
    quick: bool = False,
    workers: int | None = None,
    address: str | None = None,
    config: StudyConfig | None = None,
    progress: bool = True,
    on_record: Callable[[dict[str, Any]], None] | None = None,
) -> Path:
    """Run every method on every pair and persist one record per (method, pair).

    Args:
        sources: ``{suite: iterable of pairs | dataset folder}`` (in-memory pairs, e.g. for
            tests or custom data; folders are loaded lazily by the workers) or a list of
            loop-closure dataset folders (the suite is the folder name).
        methods: registry names (``"GraffMatch"``, ``"GraffMatch[rho=20]"``) or picklable
            method objects; default: every registered method. ``GT-matches`` always runs.
        out_dir: results folder; existing records are kept and skipped (resume).
        executor: ``"local"`` (process pool), ``"serial"``, ``"dask"``, ``"ray"`` or an
            executor object.
        quick: at most 3 pairs per case, the fast point methods, a 4-pair rho study.
        workers, address: for the executor (``address`` of a Dask/Ray cluster).
        config: thresholds and subset sizes (``StudyConfig``); ``methods`` overrides its list.
        progress: show a rich progress bar with ETA.
        on_record: called in the driver after each record is saved (for monitoring, tests).

    Returns the results folder.
    """
    out = Path(out_dir)
    cfg = (config or StudyConfig()).model_copy(deep=True)
    if quick:
        if cfg.max_pairs_per_case is None:
            cfg.max_pairs_per_case = QUICK_PAIRS_PER_CASE
        cfg.rho_pairs_per_suite = min(cfg.rho_pairs_per_suite, QUICK_RHO_PAIRS)
    method_objs: dict[str, str | EvaluationMethod] = {}
    if methods is None:
        methods = cfg.methods or default_methods(quick)
    for m in methods:
        if isinstance(m, str):
            method_kind(m)  # fail early on a malformed spec or an unknown name
            method_objs[m] = m
        elif isinstance(m, EvaluationMethod):
            method_objs[str(m.name)] = m
        else:
            raise InvalidInputError(f"method must be a name or an EvaluationMethod, got {m!r}")
    method_objs.pop(GT_METHOD, None)
    cfg.methods = [GT_METHOD, *method_objs]
    rho_specs = [rho_spec(r) for r in cfg.rho_values] if RHO_METHOD in method_objs else []

    suites = _normalize_sources(sources)
    if not suites:
        raise InvalidInputError("run_study needs at least one suite")

    out.mkdir(parents=True, exist_ok=True)
    started = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    config_doc = {
        "study": cfg.model_dump(),
        "suites": {
            name: (str(e[0].ref.dataset_dir) if e and isinstance(e[0].ref, PairRef) else "memory")
            for name, (e, _) in suites.items()
        },
        "rho_study": {"method": RHO_METHOD, "specs": rho_specs},
        "quick": quick,
        "executor": executor if isinstance(executor, str) else executor.name,
        "address": address,
        "workers": workers,
        "graffmatch_commit": _git_commit(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "started_utc": started,
        "record_version": RECORD_VERSION,
    }
    config_doc["method_params"] = {
        name: _method_params(m) for name, m in [*method_objs.items(), *((r, r) for r in rho_specs)]
    }
    atomic_write_json(out / "config.json", config_doc)

    # Task list: pair-major so consecutive tasks reuse a worker's cached dataset.
    tasks: list[Task] = []
    n_done_before = 0
    for name, (entries, pairs) in suites.items():
        chosen = _subset_per_case(entries, cfg.max_pairs_per_case)
        atomic_write_json(out / "pairs" / f"{slug(name)}.json", [e.meta for e in chosen])
        stats_path = out / "stats" / f"{slug(name)}.json"
        if not stats_path.is_file():
            atomic_write_json(stats_path, centroid_distance_stats(pairs))
        rho_ids = {e.pair_id for e in _evenly(chosen, cfg.rho_pairs_per_suite)}
        for e in chosen:
            specs: list[str | EvaluationMethod] = [GT_METHOD, *method_objs.values()]
            if e.pair_id in rho_ids:
                specs += rho_specs
            for spec in specs:
                mname = spec if isinstance(spec, str) else str(spec.name)
                key = _task_key(e.meta["fingerprint"], cfg)
                rec = _read_record(record_path(out, name, mname, e.pair_id))
                if (
                    rec is not None
                    and rec.get("task_key") == key
                    and (rec.get("status") == "ok" or not cfg.retry_errors)
                ):
                    n_done_before += 1
                    continue
                tasks.append(
                    Task(
                        suite=name,
                        pair_id=e.pair_id,
                        method=spec,
                        pair=e.ref,
                        task_key=key,
                        tau_d_deg=cfg.tau_d_deg,
                        rho_eval=cfg.rho_eval,
                        max_rotation_deg=cfg.max_rotation_deg,
                        max_translation_m=cfg.max_translation_m,
                    )
                )

    own_executor = isinstance(executor, str)
    ex: Executor = (
        make_executor(executor, workers=workers, address=address) if own_executor else executor  # type: ignore[arg-type]
    )
    n_new = n_err = 0
    try:
        with _progress(progress, len(tasks), n_done_before) as advance:
            for i, doc in ex.imap_unordered(execute_task, tasks):
                t = tasks[i]
                atomic_write_json(record_path(out, t.suite, t.method_name, t.pair_id), doc)
                n_new += 1
                n_err += doc.get("status") != "ok"
                if on_record is not None:
                    on_record(doc)
                advance(t.method_name)
    finally:
        if own_executor:
            ex.close()
        with open(out / "runs.jsonl", "a") as f:
            f.write(
                json.dumps(
                    {
                        "started_utc": started,
                        "ended_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                        "tasks": len(tasks),
                        "skipped_existing": n_done_before,
                        "written": n_new,
                        "errors": n_err,
                        "complete": n_new == len(tasks),
                        "executor": config_doc["executor"],
                    }
                )
                + "\n"
            )
    return out


class _progress:
    """A rich progress bar with ETA (or nothing), used as ``with _progress(...) as advance``."""

    def __init__(self, enabled: bool, total: int, done_before: int) -> None:
        self.enabled = enabled and total > 0
        self.total = total
        self.done_before = done_before
        self._p: Any = None

    def __enter__(self) -> Callable[[str], None]:
        if not self.enabled:
            return lambda _m: None
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self._p = Progress(
            TextColumn("[bold]study[/] {task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TextColumn("ETA"),
            TimeRemainingColumn(),
        )
        self._p.start()
        desc = f"({self.done_before} already done)" if self.done_before else ""
        tid = self._p.add_task(desc, total=self.total)

        def advance(method: str) -> None:
            self._p.update(tid, advance=1, description=f"{method:<22}")

        return advance

    def __exit__(self, *exc: object) -> None:
        if self._p is not None:
            self._p.stop()


# ----------------------------------------------------------------------------------------------
# comparing runs
# ----------------------------------------------------------------------------------------------
COMPARE_METRICS = ("recall", "auc", "rotation_error_deg", "translation_error_m", "median_ms")


def compare_runs(dir_a: str | Path, dir_b: str | Path) -> list[dict[str, Any]]:
    """Metric differences (b - a) per (suite, case, method), on the pairs both runs finished.

    Returns rows ``{suite, case, method, n, <metric>_a, <metric>_b, <metric>_delta}``; render
    them with :func:`format_comparison`.
    """
    from graffmatch.evaluation.report import summarize

    ra, rb = load_records(dir_a), load_records(dir_b)
    key = lambda r: (r["suite"], r["method"], r["pair_id"])  # noqa: E731
    common = {key(r) for r in ra} & {key(r) for r in rb}
    sa = {
        (s["suite"], s["case"], s["method"]): s
        for s in summarize([r for r in ra if key(r) in common])
    }
    sb = {
        (s["suite"], s["case"], s["method"]): s
        for s in summarize([r for r in rb if key(r) in common])
    }
    rows = []
    for k in sorted(set(sa) & set(sb), key=lambda k: (k[0], str(k[1]), k[2])):
        row: dict[str, Any] = {"suite": k[0], "case": k[1], "method": k[2], "n": sa[k]["n"]}
        for m in COMPARE_METRICS:
            a, b = sa[k].get(m), sb[k].get(m)
            row[f"{m}_a"], row[f"{m}_b"] = a, b
            ok = a is not None and b is not None and np.isfinite(a) and np.isfinite(b)
            row[f"{m}_delta"] = (b - a) if ok else None
        rows.append(row)
    return rows


def format_comparison(rows: Sequence[Mapping[str, Any]]) -> str:
    """Markdown table of :func:`compare_runs` rows."""
    head = ["suite", "case", "method", "n"] + [f"Δ{m}" for m in COMPARE_METRICS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        vals = [str(r["suite"]), str(r["case"]), str(r["method"]), str(r["n"])]
        for m in COMPARE_METRICS:
            d = r[f"{m}_delta"]
            vals.append("–" if d is None else f"{d:+.3g}")
        lines.append("| " + " | ".join(vals) + " |")
    return "\n".join(lines)
