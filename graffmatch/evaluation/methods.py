"""One interface for every registration method of the evaluation (the registry: registry.py).

Every method -- GraffMatch and its variants, the landmark baselines of the paper's Table I and
the point-based methods of its Table II -- takes the same :class:`PairInput` and returns the same
:class:`MethodOutput`, so that the experiment runner treats them alike and the metrics see
identical inputs.

Usage::

    from graffmatch.evaluation.methods import get_method, list_methods, PairInput
    method = get_method("GraffMatch")            # or get_method("CLIPPER-Rn", epsilon=4.0)
    out = method.run(PairInput(source=src_landmarks, target=tgt_landmarks))
    out.T_target_source, out.associations, out.timings["total"]

Every method also has a JSON-serialisable ``params`` dict (written next to the results) and
pickles (it can be sent to worker processes).

``kind == "landmark"`` methods use ``PairInput.source/target`` (and, for BruteForceRMSE and
GraffMatch+ICP, their support points); ``kind == "point"`` methods use the raw scans.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from graffmatch.errors import DegenerateGeometryError, InvalidInputError, MalformedFileError
from graffmatch.geometry.landmarks import LandmarkSet

MethodKind = Literal["landmark", "point"]


def _load_scan_file(path: Path) -> NDArray[np.float32]:
    """Read a raw scan: KITTI ``.bin`` (float32 x,y,z,i), ``.npy``, or PCD/PLY via Open3D."""
    if not path.is_file():
        raise MalformedFileError(f"{path}: scan file not found")
    suffix = path.suffix.lower()
    if suffix == ".bin":
        raw = np.fromfile(path, dtype=np.float32)
        if raw.size % 4:
            raise MalformedFileError(f"{path}: size is not a multiple of 4 float32 values")
        return raw.reshape(-1, 4)
    if suffix == ".npy":
        return np.asarray(np.load(path), dtype=np.float32)
    if suffix in (".pcd", ".ply"):
        import open3d as o3d

        pcd = o3d.io.read_point_cloud(str(path))
        return np.asarray(pcd.points, dtype=np.float32)
    raise MalformedFileError(f"{path}: unsupported scan format {suffix!r}")


def as_xyz(scan: Any, name: str) -> NDArray[np.float64]:
    """Validate a raw scan (N, >=3) and return its (N, 3) float64 coordinates."""
    P = np.asarray(scan)
    if P.ndim != 2 or P.shape[1] < 3:
        raise InvalidInputError(f"{name} must have shape (N, 3) or (N, 4), got {P.shape}")
    P = P[:, :3].astype(np.float64)
    finite = np.all(np.isfinite(P), axis=1)
    P = P[finite]
    if len(P) < 10:
        raise InvalidInputError(f"{name} has only {len(P)} finite points")
    return P


def dataclass_params(method: Any) -> dict[str, Any]:
    """A dataclass method's parameters for ``config.json``: every field but ``name`` and
    ``kind``, JSON-ready (an identity ``T_init`` is written as "identity")."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(method):
        if f.name in ("name", "kind"):
            continue
        v = getattr(method, f.name)
        if isinstance(v, np.ndarray):
            v = "identity" if v.shape == (4, 4) and np.allclose(v, np.eye(4)) else v.tolist()
        elif isinstance(v, tuple):
            v = list(v)
        out[f.name] = v
    return out


class MethodBase:
    """What every method shares: its parameters (for ``config.json``) are its dataclass fields."""

    @property
    def params(self) -> dict[str, Any]:
        return dataclass_params(self)


@dataclass
class PairInput:
    """The two places of one pair, exactly as every method sees them.

    ``source``/``target`` are the landmarks of each scan in its own sensor frame (with support
    points when available). ``source_scan``/``target_scan`` are the raw (N, 4) or (N, 3) points,
    or give ``*_scan_path`` to load them lazily.
    """

    source: LandmarkSet
    target: LandmarkSet
    source_scan: np.ndarray | None = None
    target_scan: np.ndarray | None = None
    source_scan_path: str | Path | None = None
    target_scan_path: str | Path | None = None
    pair_id: str = ""

    def scans(self, method_name: str = "this method") -> tuple[np.ndarray, np.ndarray]:
        """(source, target) raw scans, loading them from their paths if needed."""
        if self.source_scan is None and self.source_scan_path is not None:
            self.source_scan = _load_scan_file(Path(self.source_scan_path))
        if self.target_scan is None and self.target_scan_path is not None:
            self.target_scan = _load_scan_file(Path(self.target_scan_path))
        if self.source_scan is None or self.target_scan is None:
            raise InvalidInputError(
                f"{method_name} is point-based and needs PairInput.source_scan and "
                "target_scan (or *_scan_path); they are None"
            )
        return self.source_scan, self.target_scan


@dataclass
class MethodOutput:
    """What a method returns for one pair.

    ``T_target_source`` maps source-frame points into the target frame; ``None`` means the method
    gave no estimate (counted as a failed registration). ``associations`` are (k, 2) indices
    (source, target) into the landmark sets; empty for point-based methods. ``timings`` are
    seconds per stage and always include ``"total"``.
    """

    T_target_source: np.ndarray | None
    associations: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.intp))
    timings: dict[str, float] = field(default_factory=dict)
    valid: bool = False
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        a = np.asarray(self.associations)
        self.associations = (
            np.zeros((0, 2), np.intp) if a.size == 0 else a.astype(np.intp).reshape(-1, 2)
        )
        if self.T_target_source is not None:
            self.T_target_source = np.asarray(self.T_target_source, dtype=float)

    def __repr__(self) -> str:
        t = self.timings.get("total", float("nan"))
        return (
            f"MethodOutput(valid={self.valid}, estimate={self.T_target_source is not None}, "
            f"associations={len(self.associations)}, total={1e3 * t:.1f} ms)"
        )


@runtime_checkable
class Method(Protocol):
    """A registration method: ``run`` one pair, uniform output."""

    name: str
    kind: MethodKind

    def run(self, pair: PairInput) -> MethodOutput: ...


class Timer:
    """Collects named stage timings; ``total`` is added by :meth:`finish`."""

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}
        self._t0 = time.perf_counter()

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        t = time.perf_counter()
        try:
            yield
        finally:
            self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - t

    def finish(self) -> dict[str, float]:
        self.timings["total"] = time.perf_counter() - self._t0
        return dict(self.timings)


def register_associations(
    source: LandmarkSet,
    target: LandmarkSet,
    associations: np.ndarray,
    kappa_max: float = 1e3,
    min_associations: int = 3,
) -> tuple[np.ndarray | None, bool, dict[str, Any]]:
    """Closed-form landmark registration shared by the landmark baselines.

    Returns (T or None, valid, info). ``valid`` is False if there are too few associations or the
    problem is ill-conditioned (kappa > kappa_max); T is still returned when it exists, as in the
    paper (which registers whatever a method selected).
    """
    from graffmatch.registration.closed_form import register_landmarks

    a = np.asarray(associations, dtype=np.intp).reshape(-1, 2)
    if len(a) == 0:
        return None, False, {"message": "no associations"}
    try:
        est = register_landmarks(source, target, a, kappa_max=kappa_max)
    except DegenerateGeometryError as exc:
        return None, False, {"message": f"degenerate: {exc}"}
    kappa = float(getattr(est, "kappa", np.nan))
    degenerate = bool(getattr(est, "degenerate", False))
    valid = len(a) >= min_associations and not degenerate
    return np.asarray(est.T_target_source, float), valid, {"kappa": kappa, "degenerate": degenerate}


def no_estimate(message: str, timer: Timer | None = None) -> MethodOutput:
    """The uniform "could not match" output (counted as a failed pair, never an error)."""
    timings = (timer or Timer()).finish()
    return MethodOutput(None, timings=timings, valid=False, info={"message": message})


_TYPE_IDS = {"point": 0, "line": 1, "plane": 2}


def too_few_landmarks(pair: PairInput, types: Any = None, minimum: int = 2) -> str | None:
    """A message if either scan has fewer than ``minimum`` landmarks of the given types."""
    ids = [0, 1, 2] if types is None else [_TYPE_IDS[str(t)] for t in types]
    ns = int(np.isin(pair.source.types, ids).sum())
    nt = int(np.isin(pair.target.types, ids).sum())
    if ns < minimum or nt < minimum:
        return f"too few landmarks to match: source {ns}, target {nt} (types {types or 'all'})"
    return None


# ----------------------------------------------------------------------------------------------
# GraffMatch and its variants
# ----------------------------------------------------------------------------------------------
class LocalMethod(MethodBase):
    """A local method: associate with the source moved by an initial guess ``T_init``, then
    register the *original* source, so that T maps source-frame points into the target.

    Subclasses are dataclasses with ``T_init`` and ``kappa_max`` and implement :meth:`associate`
    (timing their own stages); ``moves_points`` says whether it needs the support points moved.
    """

    T_init: NDArray[np.float64]
    kappa_max: float
    moves_points = False

    def associate(
        self, moved_source: LandmarkSet, target: LandmarkSet, timer: Timer
    ) -> tuple[NDArray[np.intp], dict[str, Any]]:
        raise NotImplementedError

    def run(self, pair: PairInput) -> MethodOutput:
        from graffmatch.geometry.transforms import check_transform

        T_init = check_transform(self.T_init, "T_init")
        timer = Timer()
        problem = too_few_landmarks(pair)
        if problem:
            return no_estimate(problem, timer)
        src = pair.source if self.moves_points else pair.source.without_points()
        a, extra = self.associate(src.transform(T_init), pair.target, timer)
        with timer.stage("registration"):
            T, valid, info = register_associations(pair.source, pair.target, a, self.kappa_max)
        info.update(extra)
        return MethodOutput(T, a, timer.finish(), valid, info)


def _icp_info(info: dict) -> dict:
    """The refinement's numbers from a MatchResult's info, under the evaluation's names."""
    out = {k: info[k] for k in ("icp_fitness", "icp_rmse", "icp") if k in info}
    if "icp_n_source" in info:
        out["icp_points"] = int(info["icp_n_source"])
    return out


class GraffMatchMethod:
    """GraffMatch behind the uniform interface, through ``graffmatch.pipeline.ScanMatcher`` (the
    same configured path as ``register_scans``, the CLI and the demo).

    Parameters are fields of ``GraffMatchConfig`` (paper defaults: rho=40, epsilon=0.2,
    sigma=0.05); the registry's variants set ``variant="naive"`` or ``landmark_types``. Its
    native validity signal is ``valid`` with ``confidence`` (``info['confidence']``).
    """

    kind: MethodKind = "landmark"

    def __init__(self, name: str = "GraffMatch", config: Any = None, **params: Any) -> None:
        from graffmatch.matcher import GraffMatchConfig, GraffMatcher

        if config is None:
            if "landmark_types" in params:
                params["landmark_types"] = list(params["landmark_types"])
            config = GraffMatchConfig(**params)
        elif params:
            config = config.model_copy(update=params)
        from graffmatch.pipeline import RefinementConfig, ScanMatcher, ScanMatcherConfig

        self.name = name
        self.config = config
        self.params = config.model_dump(mode="json")
        self._scan_matcher = ScanMatcher(ScanMatcherConfig(matcher=config, refinement=self._refinement(RefinementConfig)))
        self._matcher: GraffMatcher = self._scan_matcher.matcher

    def _refinement(self, cls: Any) -> Any:
        return cls(method="none")

    def _match(self, pair: PairInput) -> Any:
        return self._scan_matcher.match(pair.source, pair.target)

    def run(self, pair: PairInput) -> MethodOutput:
        timer = Timer()
        problem = too_few_landmarks(pair, self.config.landmark_types)
        if problem:
            return no_estimate(problem, timer)
        with timer.stage("match"):
            res = self._match(pair)
        timings = timer.finish()
        for k, v in dict(getattr(res, "timings", {}) or {}).items():
            if k != "total":
                timings[f"match.{k}"] = float(v)
        T = getattr(res, "T_target_source", None)
        return MethodOutput(
            T_target_source=None if T is None else np.asarray(T, float),
            associations=np.asarray(res.associations),
            timings=timings,
            valid=bool(res.valid),
            info={
                "score": float(getattr(res, "score", np.nan)),
                "kappa": float(getattr(res, "kappa", np.nan)),
                "n_putative": int(getattr(res, "n_putative", -1)),
                "n_edges": int(getattr(res, "n_edges", -1)),
                "message": str(getattr(res, "message", "")),
                # the native validity signal: the matcher's calibrated confidence (issue 11)
                "validity_score": float(getattr(res, "confidence", float(res.valid))),
                "validity_signal": "confidence" if hasattr(res, "confidence") else "valid",
                "confidence": float(getattr(res, "confidence", float(res.valid))),
                "overlap": float(getattr(res, "overlap", np.nan)),
                "margin": float(getattr(res, "margin", np.nan)),
                **_icp_info(getattr(res, "info", {}) or {}),
            },
        )


class GraffMatchICP(GraffMatchMethod):
    """GraffMatch, then ICP on only the support points of the matched landmarks (Table II).

    ICP is ``graffmatch.registration.icp.refine_icp`` (Open3D) with
    ``max_correspondence_distance`` [m] and ``max_iterations``; it is skipped (GraffMatch's
    estimate is kept) when GraffMatch selected no association.
    """

    def __init__(
        self,
        name: str = "GraffMatch+ICP",
        max_correspondence_distance: float = 1.0,
        max_iterations: int = 30,
        config: Any = None,
        **params: Any,
    ) -> None:
        self.max_correspondence_distance = float(max_correspondence_distance)
        self.max_iterations = int(max_iterations)
        super().__init__(name=name, config=config, **params)
        self.params = {
            **self.params,
            "icp_max_correspondence_distance": self.max_correspondence_distance,
            "icp_max_iterations": self.max_iterations,
        }

    def _refinement(self, cls: Any) -> Any:
        return cls(method="icp", points="landmarks", max_correspondence_distance=self.max_correspondence_distance,
                   max_iterations=self.max_iterations, point_to_plane=True)

    def _match(self, pair: PairInput) -> Any:
        res = self._scan_matcher.match(pair.source, pair.target)
        if res.T_target_source is None or len(res.associations) == 0:
            res.info["icp"] = "skipped: no GraffMatch estimate"
            return res
        if pair.source.points is None or pair.target.points is None:
            res.info["icp"] = "skipped: no support points"
            return res
        try:
            self._scan_matcher.refine(res, pair.source, pair.target)
        except InvalidInputError as exc:
            res.info["icp"] = f"skipped: {exc}"
        return res

    def run(self, pair: PairInput) -> MethodOutput:
        out = super().run(pair)
        if "match.icp" in out.timings:
            out.timings["icp"] = out.timings["match.icp"]
        return out


# The registry moved to graffmatch.evaluation.registry; its names stay importable from here.
_REGISTRY_NAMES = (
    "GLOBAL_BASELINES",
    "LOCAL_METHODS",
    "METHODS",
    "MethodFactory",
    "TABLE_II_METHODS",
    "TABLE_I_METHODS",
    "get_method",
    "list_methods",
    "register_method",
)


def __getattr__(name: str) -> Any:
    if name in _REGISTRY_NAMES:
        from graffmatch.evaluation import registry

        return getattr(registry, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
