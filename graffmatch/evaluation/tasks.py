"""The worker side of a study: one (suite, pair, method) task, run and evaluated into a record.

A task is small and picklable; a pair stored in a dataset folder travels as a :class:`PairRef`
and is loaded by the worker. The pseudo-method ``GT-matches`` registers each pair with its true
landmark matches; it is the best a landmark-only registration can do.
"""

from __future__ import annotations

import functools
import json
import re
import time
import traceback
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from graffmatch.errors import InvalidInputError
from graffmatch.evaluation import metrics as M
from graffmatch.evaluation.records import GT_METHOD, RECORD_VERSION, RHO_METHOD
from graffmatch.geometry.landmarks import LandmarkSet


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


@dataclass(frozen=True)
class PairRef:
    """A pair stored in a loop-closure dataset folder, loaded by the worker (no pickling)."""

    dataset_dir: str
    index: int

    def load(self) -> Any:
        return _dataset_pairs(self.dataset_dir)[self.index]


def _dataset_pairs(dataset_dir: str) -> list[Any]:
    """The pairs of a dataset folder, loaded once per process (and again if rebuilt)."""
    from graffmatch.evaluation.loop_closure_dataset import PAIRS_FILE

    f = Path(dataset_dir) / PAIRS_FILE
    return _dataset_pairs_cached(dataset_dir, f.stat().st_mtime_ns if f.is_file() else 0)


@functools.lru_cache(maxsize=8)
def _dataset_pairs_cached(dataset_dir: str, mtime_ns: int) -> list[Any]:
    from graffmatch.evaluation.loop_closure_dataset import LoopClosureDataset

    return LoopClosureDataset.load(Path(dataset_dir)).with_negatives()


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
    from graffmatch.evaluation import registry

    entry = registry.METHODS.get(name)
    if entry is None:
        raise InvalidInputError(
            f"unknown method {name!r}; available: {', '.join(registry.list_methods())}"
        )
    return str(entry.kind)


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
    from graffmatch.evaluation import registry

    name, params = parse_method_spec(spec)
    return registry.get_method(name, **params) if params else registry.get_method(name)


def _run_registry_method(spec: str, pair: Any) -> Any:
    from graffmatch.evaluation.methods import PairInput

    method = _registry_method(spec)
    # LoopClosurePair.source_scan is the scan *index*; only arrays are raw points.
    src_pts, tgt_pts = getattr(pair, "source_scan", None), getattr(pair, "target_scan", None)
    inp = PairInput(
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


def _validity_score(out: _Output) -> float:
    try:
        v = float(out.info.get("validity_score", float(out.valid)))
    except (TypeError, ValueError):
        return float(out.valid)
    return v if np.isfinite(v) else float(out.valid)


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
                # validity (graffmatch.evaluation.validity): negatives have no right answer;
                # each method's own signal, float(valid) where it has none
                "negative": bool(getattr(pair, "negative", False)),
                "validity_score": _validity_score(out),
                "validity_signal": str(out.info.get("validity_signal", "valid")),
                "status": "ok" if error is None else "error",
                "error": error,
            }
        )
    )
    return doc
