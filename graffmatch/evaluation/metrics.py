"""Evaluation metrics of the GraffMatch paper (section "Evaluation Metrics").

All metrics share one small interface, after evo: a :class:`Metric` has a ``name`` and
``compute(records) -> MetricResult``; a :class:`MetricResult` holds ``info`` (what was computed,
with which parameters), ``statistics`` (scalars) and ``arrays`` (curves), and round-trips through
JSON so that runs can be saved and compared.

The per-pair input of every metric is a :class:`PairRecord`: the estimate of one method on one
place pair, the ground truth, the d_Graff distance of each selected association after
ground-truth alignment, and the timings. Keeping the per-association distances (not only the
inlier count) lets the LMR-vs-tau_d curve be computed later without the landmarks.

Definitions (the paper's, made precise where it is silent):

* An association (i, j) is an *inlier* if ``d_ij < tau_d`` where ``d_ij`` is the invariant
  d_Graff distance (``rho = 40``) between source landmark i, moved into the target frame with the
  ground-truth transform, and target landmark j; ``tau_d`` defaults to 6 degrees. Distances are
  radians internally and reported in degrees.
* The *output inlier ratio* (OIR) of a pair is the fraction of its selected associations that
  are inliers; a pair with no associations has OIR 0 (it recovered nothing).
* ``LMR(tau_OIR) = mean_s 1[OIR_s > tau_OIR]`` (strict, as in the paper's formula).
* The LMR AUC is the integral of ``LMR(tau_OIR)`` over ``tau_OIR in [0, 1]``. For this step
  function the integral is exactly the mean of ``clip(OIR, 0, 1)``; we return that exact value
  (a trapezoid on a 101-point grid differs by at most 0.005).
* A registration succeeds if rotation error <= 5 deg and translation error <= 1 m; a pair with no
  estimate fails. Rotation error is ``arccos((tr(R_est^T R_gt) - 1) / 2)``, translation error
  ``||t_est - t_gt||``; their means are over successful pairs only (NaN if none).
* Runtime statistics: median, mean and the 5/25/75/95th percentiles per timing stage.

The module runs past 500 lines on purpose: the metric definitions, the record they read and the
evo-style interface over them are one concept, and splitting them would part a definition from
the only type it is computed on.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.transforms import check_transform, transform_errors

#: Paper defaults.
DEFAULT_TAU_D_DEG = 6.0
DEFAULT_TAU_OIR = 0.8
DEFAULT_RHO = 40.0
DEFAULT_MAX_ROTATION_DEG = 5.0
DEFAULT_MAX_TRANSLATION_M = 1.0
DEFAULT_TAU_OIR_GRID = np.linspace(0.0, 1.0, 101)
DEFAULT_TAU_D_GRID_DEG = np.linspace(0.0, 20.0, 81)
PERCENTILES = (5, 25, 75, 95)


# ----------------------------------------------------------------------------------------------
# association-level metrics
# ----------------------------------------------------------------------------------------------
def _check_associations(associations: ArrayLike, n_source: int, n_target: int) -> NDArray[np.intp]:
    a = np.asarray(associations)
    if a.size == 0:
        return np.zeros((0, 2), dtype=np.intp)
    if a.ndim != 2 or a.shape[1] != 2:
        raise InvalidInputError(f"associations must have shape (k, 2), got {a.shape}")
    if not np.issubdtype(a.dtype, np.integer):
        if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
            raise InvalidInputError("associations must be integer indices")
    a = a.astype(np.intp)
    if a.min() < 0 or a[:, 0].max() >= n_source or a[:, 1].max() >= n_target:
        raise InvalidInputError(
            f"association indices out of range for {n_source} source / {n_target} target landmarks"
        )
    return a


def association_distances_deg(
    source: LandmarkSet,
    target: LandmarkSet,
    associations: ArrayLike,
    T_target_source_gt: ArrayLike,
    rho: float = DEFAULT_RHO,
) -> NDArray[np.float64]:
    """Invariant d_Graff [deg] of each association after ground-truth alignment.

    Associations between different landmark types get +inf (never inliers).
    """
    from graffmatch.geometry.distance import directed_distances  # lazy: keep metrics light

    a = _check_associations(associations, len(source), len(target))
    if len(a) == 0:
        return np.zeros(0)
    T = check_transform(T_target_source_gt, "T_target_source_gt")
    src = source.without_points().transform(T)
    s = (src.types[a[:, 0]], src.bases[a[:, 0]], src.anchors[a[:, 0]])
    t = (target.types[a[:, 1]], target.bases[a[:, 1]], target.anchors[a[:, 1]])
    # Symmetrised over the shift order, exactly as geometry.distance.cross_distances, but only
    # for the k associated pairs (O(k), not O(n_s n_t)).
    d = 0.5 * (directed_distances(*s, *t, rho=rho) + directed_distances(*t, *s, rho=rho))
    d[s[0] != t[0]] = np.inf
    return np.degrees(d)


def association_inlier_mask(
    source: LandmarkSet,
    target: LandmarkSet,
    associations: ArrayLike,
    T_target_source_gt: ArrayLike,
    tau_d_deg: float = DEFAULT_TAU_D_DEG,
    rho: float = DEFAULT_RHO,
) -> NDArray[np.bool_]:
    """(k,) bool: association is an inlier if its GT-aligned invariant d_Graff < tau_d."""
    d = association_distances_deg(source, target, associations, T_target_source_gt, rho=rho)
    return d < float(tau_d_deg)


def output_inlier_ratio(inlier_mask: ArrayLike) -> float:
    """Fraction of inliers among the selected associations; 0 when nothing was selected."""
    m = np.asarray(inlier_mask, dtype=bool).reshape(-1)
    return float(m.mean()) if m.size else 0.0


def oir_from_distances(distances_deg: ArrayLike, tau_d_deg: float = DEFAULT_TAU_D_DEG) -> float:
    d = np.asarray(distances_deg, dtype=float).reshape(-1)
    return float(np.mean(d < tau_d_deg)) if d.size else 0.0


def _oirs(oirs: ArrayLike) -> NDArray[np.float64]:
    o = np.asarray(oirs, dtype=float).reshape(-1)
    if np.any(~np.isfinite(o)) or np.any(o < 0) or np.any(o > 1):
        raise InvalidInputError("OIR values must be finite and in [0, 1]")
    return o


def lmr(oir_per_pair: ArrayLike, tau_oir: float = DEFAULT_TAU_OIR) -> float:
    """Landmark-match recall: fraction of pairs with OIR strictly above tau_OIR."""
    o = _oirs(oir_per_pair)
    if o.size == 0:
        raise InvalidInputError("LMR needs at least one pair")
    return float(np.mean(o > tau_oir))


def lmr_curve(
    oirs: ArrayLike, taus: ArrayLike | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(taus, LMR(tau)) for each tau_OIR of the grid (default 0, 0.01, ..., 1)."""
    o = _oirs(oirs)
    if o.size == 0:
        raise InvalidInputError("LMR needs at least one pair")
    t = DEFAULT_TAU_OIR_GRID if taus is None else np.asarray(taus, dtype=float).reshape(-1)
    # Sorting once gives every LMR value by binary search (no pairs x taus matrix).
    s = np.sort(o)
    above = o.size - np.searchsorted(s, t, side="right")
    return t.copy(), above / o.size


def lmr_auc(oirs: ArrayLike) -> float:
    """Exact area under LMR(tau_OIR) for tau_OIR in [0, 1] (= mean OIR)."""
    o = _oirs(oirs)
    if o.size == 0:
        raise InvalidInputError("LMR AUC needs at least one pair")
    return float(np.mean(o))


def lmr_auc_trapezoid(oirs: ArrayLike, taus: ArrayLike | None = None) -> float:
    """Trapezoid AUC of the sampled LMR curve (what a plotted curve would integrate to)."""
    t, v = lmr_curve(oirs, taus)
    return float(np.trapezoid(v, t))


def lmr_vs_tau_d(
    distances_deg_per_pair: Sequence[ArrayLike],
    tau_ds_deg: ArrayLike | None = None,
    tau_oir: float = DEFAULT_TAU_OIR,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(tau_d grid [deg], LMR at fixed tau_OIR) -- the right plot of the paper's Fig. 6."""
    if len(distances_deg_per_pair) == 0:
        raise InvalidInputError("LMR needs at least one pair")
    t = DEFAULT_TAU_D_GRID_DEG if tau_ds_deg is None else np.asarray(tau_ds_deg, float).reshape(-1)
    out = np.zeros(len(t))
    for d in distances_deg_per_pair:  # loop over pairs, vectorised over the tau grid
        d = np.sort(np.asarray(d, dtype=float).reshape(-1))
        if d.size == 0:
            continue
        oir = np.searchsorted(d, t, side="left") / d.size  # #(d < tau) / k
        out += oir > tau_oir
    return t.copy(), out / len(distances_deg_per_pair)


# ----------------------------------------------------------------------------------------------
# registration metrics
# ----------------------------------------------------------------------------------------------
def registration_errors(T_est: ArrayLike | None, T_gt: ArrayLike) -> tuple[float, float]:
    """(rotation error [deg], translation error [m]); (inf, inf) when there is no estimate."""
    if T_est is None:
        return float("inf"), float("inf")
    T_est = np.asarray(T_est, dtype=float)
    if T_est.shape != (4, 4) or not np.all(np.isfinite(T_est)):
        return float("inf"), float("inf")
    return transform_errors(T_est, check_transform(T_gt, "T_gt"))


def registration_success(
    rotation_error_deg: float,
    translation_error_m: float,
    max_rotation_deg: float = DEFAULT_MAX_ROTATION_DEG,
    max_translation_m: float = DEFAULT_MAX_TRANSLATION_M,
) -> bool:
    return bool(rotation_error_deg <= max_rotation_deg and translation_error_m <= max_translation_m)


def ground_truth_report(
    source: LandmarkSet,
    target: LandmarkSet,
    associations: ArrayLike,
    T_est: ArrayLike | None,
    T_gt: ArrayLike,
    tau_d_deg: float = DEFAULT_TAU_D_DEG,
    max_rotation_deg: float = DEFAULT_MAX_ROTATION_DEG,
    max_translation_m: float = DEFAULT_MAX_TRANSLATION_M,
    rho: float = DEFAULT_RHO,
) -> dict[str, Any]:
    """One estimate judged against ground truth, exactly as the evaluation judges a pair.

    Errors (inf without an estimate), success within the bounds, and each association's
    GT-aligned d_Graff with its inlier flag. ``graffmatch register --gt`` prints this; a Python
    user gets the same numbers from here.
    """
    a = _check_associations(associations, len(source), len(target))
    rot, trans = registration_errors(T_est, T_gt)
    d = association_distances_deg(source, target, a, T_gt, rho=rho) if len(a) else np.zeros(0)
    mask = d < float(tau_d_deg)
    return {
        "T_target_source": np.asarray(T_gt, dtype=float),
        "rotation_error_deg": float(rot),
        "translation_error_m": float(trans),
        "success": registration_success(rot, trans, max_rotation_deg, max_translation_m),
        "tau_d_deg": float(tau_d_deg),
        "association_distance_deg": d,
        "inlier_mask": mask,
        "n_inliers": int(mask.sum()),
    }


def runtime_stats(values_s: ArrayLike) -> dict[str, float]:
    """Median, mean, min, max and 5/25/75/95th percentiles [s] of a set of runtimes."""
    v = np.asarray(values_s, dtype=float).reshape(-1)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"n": 0}
    out: dict[str, float] = {
        "n": int(v.size),
        "median": float(np.median(v)),
        "mean": float(v.mean()),
        "min": float(v.min()),
        "max": float(v.max()),
    }
    for p, q in zip(PERCENTILES, np.percentile(v, PERCENTILES), strict=True):
        out[f"p{p}"] = float(q)
    return out


# ----------------------------------------------------------------------------------------------
# per-pair record and serialisable results
# ----------------------------------------------------------------------------------------------
def _jsonable(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return [_jsonable(v) for v in x.tolist()] if x.ndim else _jsonable(x.item())
    if isinstance(x, (np.floating, float)):
        x = float(x)
        if np.isnan(x):
            return "nan"
        if np.isinf(x):
            return "inf" if x > 0 else "-inf"
        return x
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    if isinstance(x, Mapping):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


def _unjson_float(x: Any) -> float:
    return float(x)  # float("nan") / float("inf") parse the strings written by _jsonable


def _unjson_array(x: Any) -> np.ndarray:
    def conv(v: Any) -> Any:
        if isinstance(v, list):
            return [conv(w) for w in v]
        return float(v) if isinstance(v, str) else v

    return np.asarray(conv(x))


@dataclass
class PairRecord:
    """What one method produced on one place pair, reduced to what the metrics need."""

    pair_id: str
    method: str
    T_target_source_gt: NDArray[np.float64]
    T_target_source_est: NDArray[np.float64] | None
    association_distances_deg: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    n_associations: int = 0
    timings: dict[str, float] = field(default_factory=dict)
    valid: bool = True
    kind: str = "landmark"
    info: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_output(
        cls,
        pair_id: str,
        method: str,
        source: LandmarkSet | None,
        target: LandmarkSet | None,
        T_target_source_gt: ArrayLike,
        T_target_source_est: ArrayLike | None,
        associations: ArrayLike | None,
        timings: Mapping[str, float] | None = None,
        valid: bool = True,
        kind: str = "landmark",
        rho: float = DEFAULT_RHO,
        info: Mapping[str, Any] | None = None,
    ) -> PairRecord:
        """Evaluate the associations against the ground truth and keep their distances."""
        T_gt = check_transform(T_target_source_gt, "T_target_source_gt")
        a = np.zeros((0, 2), np.intp) if associations is None else np.asarray(associations)
        if a.size and (source is None or target is None):
            raise InvalidInputError("associations need the source and target landmark sets")
        d = (
            association_distances_deg(source, target, a, T_gt, rho=rho)  # type: ignore[arg-type]
            if a.size
            else np.zeros(0)
        )
        T_est = None if T_target_source_est is None else np.asarray(T_target_source_est, float)
        return cls(
            pair_id=str(pair_id),
            method=str(method),
            T_target_source_gt=T_gt,
            T_target_source_est=T_est,
            association_distances_deg=d,
            n_associations=len(d),
            timings={k: float(v) for k, v in (timings or {}).items()},
            valid=bool(valid),
            kind=kind,
            info=dict(info or {}),
        )

    def oir(self, tau_d_deg: float = DEFAULT_TAU_D_DEG) -> float:
        return oir_from_distances(self.association_distances_deg, tau_d_deg)

    def errors(self) -> tuple[float, float]:
        return registration_errors(self.T_target_source_est, self.T_target_source_gt)

    def to_dict(self) -> dict[str, Any]:
        return _jsonable(
            {
                "pair_id": self.pair_id,
                "method": self.method,
                "T_target_source_gt": self.T_target_source_gt,
                "T_target_source_est": self.T_target_source_est,
                "association_distances_deg": self.association_distances_deg,
                "n_associations": self.n_associations,
                "timings": self.timings,
                "valid": self.valid,
                "kind": self.kind,
                "info": self.info,
            }
        )

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> PairRecord:
        est = d.get("T_target_source_est")
        return cls(
            pair_id=str(d["pair_id"]),
            method=str(d["method"]),
            T_target_source_gt=_unjson_array(d["T_target_source_gt"]).astype(float),
            T_target_source_est=None if est is None else _unjson_array(est).astype(float),
            association_distances_deg=_unjson_array(d.get("association_distances_deg", []))
            .astype(float)
            .reshape(-1),
            n_associations=int(d.get("n_associations", 0)),
            timings={k: _unjson_float(v) for k, v in d.get("timings", {}).items()},
            valid=bool(d.get("valid", True)),
            kind=str(d.get("kind", "landmark")),
            info=dict(d.get("info", {})),
        )


@dataclass
class MetricResult:
    """Result of one metric over a set of pairs: info, scalar statistics, arrays (curves)."""

    name: str
    info: dict[str, Any] = field(default_factory=dict)
    statistics: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, NDArray[Any]] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return _jsonable(
            {
                "name": self.name,
                "info": self.info,
                "statistics": self.statistics,
                "arrays": self.arrays,
            }
        )

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> MetricResult:
        return cls(
            name=str(d["name"]),
            info=dict(d.get("info", {})),
            statistics={
                k: (v if isinstance(v, Mapping) else _unjson_float(v))
                for k, v in d.get("statistics", {}).items()
            },
            arrays={k: _unjson_array(v) for k, v in d.get("arrays", {}).items()},
        )

    def to_json(self, indent: int | None = 2) -> str:
        return json.dumps(self.to_dict(), indent=indent)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(self.to_json())
        return path

    @classmethod
    def load(cls, path: str | Path) -> MetricResult:
        return cls.from_dict(json.loads(Path(path).read_text()))

    def __repr__(self) -> str:
        stats = ", ".join(
            f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
            for k, v in self.statistics.items()
        )
        return f"MetricResult({self.name}: {stats})"


@runtime_checkable
class Metric(Protocol):
    """A metric over a set of per-pair records."""

    name: str

    def compute(self, records: Sequence[PairRecord]) -> MetricResult: ...


def _require_records(records: Iterable[PairRecord]) -> list[PairRecord]:
    recs = list(records)
    if not recs:
        raise InvalidInputError("a metric needs at least one pair record")
    return recs


@dataclass
class LandmarkMatchRecall:
    """LMR at tau_OIR, the LMR curve over tau_OIR with its AUC, and LMR vs tau_d."""

    tau_d_deg: float = DEFAULT_TAU_D_DEG
    tau_oir: float = DEFAULT_TAU_OIR
    name: str = "lmr"

    def compute(self, records: Sequence[PairRecord]) -> MetricResult:
        recs = _require_records(records)
        oirs = np.array([r.oir(self.tau_d_deg) for r in recs])
        taus, curve = lmr_curve(oirs)
        tds, curve_d = lmr_vs_tau_d(
            [r.association_distances_deg for r in recs], tau_oir=self.tau_oir
        )
        return MetricResult(
            name=self.name,
            info={
                "tau_d_deg": self.tau_d_deg,
                "tau_oir": self.tau_oir,
                "definition": "LMR = mean(OIR > tau_OIR); AUC = integral over [0,1] = mean OIR",
                "n_pairs": len(recs),
            },
            statistics={
                "lmr": lmr(oirs, self.tau_oir),
                "auc": lmr_auc(oirs),
                "mean_oir": float(oirs.mean()),
                "mean_associations": float(np.mean([r.n_associations for r in recs])),
            },
            arrays={
                "oir": oirs,
                "tau_oir": taus,
                "lmr_curve": curve,
                "tau_d_deg": tds,
                "lmr_vs_tau_d": curve_d,
            },
        )


@dataclass
class RegistrationRecall:
    """Recall (success within 5 deg / 1 m) and mean errors over the successful pairs."""

    max_rotation_deg: float = DEFAULT_MAX_ROTATION_DEG
    max_translation_m: float = DEFAULT_MAX_TRANSLATION_M
    name: str = "registration"

    def compute(self, records: Sequence[PairRecord]) -> MetricResult:
        recs = _require_records(records)
        errs = np.array([r.errors() for r in recs], dtype=float).reshape(-1, 2)
        ok = (errs[:, 0] <= self.max_rotation_deg) & (errs[:, 1] <= self.max_translation_m)
        has = np.array([r.T_target_source_est is not None for r in recs])
        return MetricResult(
            name=self.name,
            info={
                "max_rotation_deg": self.max_rotation_deg,
                "max_translation_m": self.max_translation_m,
                "n_pairs": len(recs),
            },
            statistics={
                "recall": float(ok.mean()),
                "n_success": int(ok.sum()),
                "estimate_rate": float(has.mean()),
                "rotation_error_deg_mean": float(errs[ok, 0].mean()) if ok.any() else float("nan"),
                "translation_error_m_mean": float(errs[ok, 1].mean()) if ok.any() else float("nan"),
            },
            arrays={
                "rotation_error_deg": errs[:, 0],
                "translation_error_m": errs[:, 1],
                "success": ok,
            },
        )


@dataclass
class Runtime:
    """Runtime statistics per timing stage (seconds); 'total' is always present if timed."""

    name: str = "runtime"

    def compute(self, records: Sequence[PairRecord]) -> MetricResult:
        recs = _require_records(records)
        stages = sorted({k for r in recs for k in r.timings})
        stats: dict[str, Any] = {}
        arrays: dict[str, np.ndarray] = {}
        for s in stages:
            v = np.array([r.timings.get(s, np.nan) for r in recs], dtype=float)
            arrays[s] = v
            stats[s] = runtime_stats(v)
        return MetricResult(
            name=self.name,
            info={"unit": "s", "n_pairs": len(recs)},
            statistics=stats,
            arrays=arrays,
        )


def default_metrics() -> list[Metric]:
    """The paper's metrics with its default thresholds."""
    return [LandmarkMatchRecall(), RegistrationRecall(), Runtime()]


def evaluate(
    records: Sequence[PairRecord], metrics: Sequence[Metric] | None = None
) -> dict[str, MetricResult]:
    """Compute every metric on the records of one method: name -> result."""
    return {m.name: m.compute(records) for m in (metrics or default_metrics())}
