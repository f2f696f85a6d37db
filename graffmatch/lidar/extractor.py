"""``LandmarkExtractor``: one LiDAR scan -> a :class:`~graffmatch.geometry.landmarks.LandmarkSet`.

Pipeline (each stage timed in :attr:`LandmarkExtractor.last_timings`):

1. ``validate``  drop NaN/Inf rows (warning), crop to ``max_range``, centre far-away clouds;
2. ``ground``    local-ground height per point, ground points, and the ground plane landmark;
3. ``poles``     semantic (labels) or geometric pole detection -> LINE landmarks;
4. ``planes``    Open3D planar patches on the non-ground points, merged -> PLANE landmarks;
5. ``assemble``  anchors, directions, attributes and capped support points into one set.
"""

from __future__ import annotations

import hashlib
import time
import warnings
from typing import Literal

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.errors import InvalidInputError, PrecisionLossWarning
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.lidar._stats import subsample_groups
from graffmatch.lidar.ground import GroundConfig, segment_ground
from graffmatch.lidar.io import PRECISION_TOLERANCE, semantic_class
from graffmatch.lidar.planes import (
    PlaneConfig,
    drop_ground_duplicates,
    extract_planes,
    voxel_planes,
)
from graffmatch.lidar.poles import PoleConfig, PoleResult, poles_geometric, poles_semantic
from graffmatch.lidar.voxels import VoxelCloud, build_voxel_grid
from graffmatch.verification.free_space import cell_minimum_ranges

Array = NDArray[np.float64]

#: A cloud spanning more than this [m] (1st-99th percentile, per axis) is no single LiDAR scan
#: in metres: ranges end at ~100-300 m. It is taken as a scan in other units (see units_hint).
UNITS_EXTENT_LIMIT = 2000.0

#: Points further than this from the (possibly recentred) cloud's origin are dropped with a
#: warning: no LiDAR map spans 10,000 km, and grid indices of such values overflow int64.
MAX_COORDINATE = 1e7

#: Version of the extraction code's output; part of :meth:`LandmarkExtractorConfig.config_hash`,
#: so cached landmark files of an older front end are recomputed. 2: the voxel plane detector
#: and compiled ground / pole / crop kernels (issue 14). 3: the whole scan's range image, and
#: landmark files that load back bit for bit (format 2), so a cached set equals an extracted one.
EXTRACTION_VERSION = 3

#: Plausible span of one scan in metres, used to say which unit an oversized cloud is in.
PLAUSIBLE_SPAN = (10.0, 400.0)

#: Singular-value ratio s_k / s_0 of the centred cloud below which it is degenerate: rank < 2
#: (collinear) admits no plane, so ground and planar patches are skipped (Open3D's patch
#: detector and hulls, Qhull inside, are never fed such sets); a plane needs s_1/s_0 above it.
DEGENERATE_RATIO = 1e-3


#: Relative margin of :func:`_crop`'s borderline rows: far above the few ulps by which two
#: evaluations of |p|^2 (and sqrt, and squaring the bounds) can differ.
_CROP_MARGIN = 1e-9


@nb.njit(cache=True)
def _crop(A, rmin2, rmax2):
    """In one pass: whether every row is finite, the largest |coordinate| (of the rows seen),
    and for the fast path float64 xyz of the rows with rmin2 <= |p|^2 <= rmax2, their indices
    and how many kept rows lie within a relative :data:`_CROP_MARGIN` of either bound (only
    those can fail the caller's sqrt-then-compare test: none means every kept row passes it).
    Stops at the first row with a NaN/Inf coordinate (finite False: the general path)."""
    n = A.shape[0]
    keep = np.empty(n, np.int64)
    lo = rmin2 * (1.0 + _CROP_MARGIN)
    hi = rmax2 * (1.0 - _CROP_MARGIN)
    m = 0
    border = 0
    amax = 0.0
    for i in range(n):
        if not (np.isfinite(A[i, 0]) and np.isfinite(A[i, 1]) and np.isfinite(A[i, 2])):
            return False, amax, np.empty((0, 3)), keep[:0].copy(), 0
        amax = max(amax, abs(A[i, 0]), abs(A[i, 1]), abs(A[i, 2]))
        x, y, z = np.float64(A[i, 0]), np.float64(A[i, 1]), np.float64(A[i, 2])
        r2 = x * x + y * y + z * z
        if rmin2 <= r2 <= rmax2:
            keep[m] = i
            m += 1
            if not (lo < r2 < hi):
                border += 1
    P = np.empty((m, 3))
    for k in range(m):
        i = keep[k]
        P[k, 0], P[k, 1], P[k, 2] = A[i, 0], A[i, 1], A[i, 2]
    return True, amax, P, keep[:m].copy(), border


@nb.njit(cache=True)
def _plane_points(P, is_ground, max_range2):
    """The rows of ``P`` (float64) that are not ground and within ``max_range2`` horizontally
    (x^2 + y^2, the same products and sum as numpy's), in order: ``P[keep]`` in one pass."""
    n = P.shape[0]
    m = 0
    for i in range(n):
        if not is_ground[i] and P[i, 0] * P[i, 0] + P[i, 1] * P[i, 1] <= max_range2:
            m += 1
    Q = np.empty((m, 3))
    k = 0
    for i in range(n):
        if not is_ground[i] and P[i, 0] * P[i, 0] + P[i, 1] * P[i, 1] <= max_range2:
            Q[k, 0], Q[k, 1], Q[k, 2] = P[i, 0], P[i, 1], P[i, 2]
            k += 1
    return Q


def units_hint(extent: float) -> str | None:
    """Which unit a cloud of this span [file units] is probably in, as a sentence; None if it
    could be metres. Both candidates are named when both give a plausible scan size."""
    if not np.isfinite(extent) or extent <= UNITS_EXTENT_LIMIT:
        return None
    lo, hi = PLAUSIBLE_SPAN
    cands = [
        (name, factor)
        for name, factor in (("centimetres", 0.01), ("millimetres", 0.001))
        if lo <= extent * factor <= hi
    ]
    if not cands:
        return (
            f"extent {extent:.3g} m is far too large for one scan in metres (wrong units?); "
            "pass --scale / scale= with the factor to metres"
        )
    what = " or ".join(f"{name} ({extent * f:.0f} m)" for name, f in cands)
    flags = " or ".join(f"{f:g}" for _, f in cands)
    return f"extent {extent:.0f} m suggests {what}; pass --scale {flags} / scale={cands[0][1]:g}"


def robust_extent(P: Array) -> float:
    """Largest 1st-99th percentile span over the axes (a few outliers do not count) [m]."""
    if P.shape[0] == 0:
        return 0.0
    sample = P[:: max(1, P.shape[0] // 20000)]
    lo, hi = np.percentile(sample, [1.0, 99.0], axis=0)
    return float(np.max(hi - lo))


def degeneracy(P: Array) -> Literal["point", "line", "plane", "volume"]:
    """Rank of the (sub-sampled, centred) cloud judged with :data:`DEGENERATE_RATIO`."""
    sample = P[:: max(1, P.shape[0] // 4096)]
    Q = sample - sample.mean(axis=0)
    s = np.linalg.svd(Q, compute_uv=False)
    if s.size == 0 or s[0] <= 0:
        return "point"
    r = s / s[0]
    if r.size < 2 or r[1] <= DEGENERATE_RATIO:
        return "line"
    if r.size < 3 or r[2] <= DEGENERATE_RATIO:
        return "plane"
    return "volume"


class LandmarkExtractorConfig(BaseModel):
    """Every threshold of the front end, nested by stage (defaults tuned on KITTI HDL-64E)."""

    model_config = ConfigDict(extra="forbid")

    min_range: float = Field(
        2.5,
        ge=0,
        description="Drop points closer than this to the sensor (ego vehicle, operator) [m].",
    )
    max_range: float | None = Field(
        80.0, gt=0, description="Drop points further than this from the sensor; None keeps all [m]."
    )
    recenter_distance: float = Field(
        1.0e4,
        gt=0,
        description="If the median point is further than this from the origin (e.g. UTM "
        "coordinates), compute in a frame centred on it and the range crop is skipped [m].",
    )
    min_points: int = Field(
        50, ge=1, description="Fewer valid points than this gives an empty set with a warning."
    )
    min_extent: float = Field(
        1e-3,
        gt=0,
        description="A cloud spanning less than this gives no landmarks (wrong units?) [m].",
    )
    max_points_per_landmark: int = Field(
        256, ge=0, description="Support points stored per landmark (even stride); 0 stores none."
    )
    scan_ranges: bool = Field(
        True,
        description="Keep the whole scan's nearest return per 1 deg cell with the support points "
        "(LandmarkSet.scan_ranges): verification's free-space check then sees every beam, not only "
        "the landmarks' support.",
    )
    ground: GroundConfig = Field(
        default_factory=GroundConfig, description="Ground segmentation and plane."
    )
    poles: PoleConfig = Field(default_factory=PoleConfig, description="Pole (LINE) detection.")
    planes: PlaneConfig = Field(
        default_factory=PlaneConfig, description="Planar patches and merging."
    )

    @classmethod
    def short_range(cls) -> LandmarkExtractorConfig:
        """Preset for short-range scenes (hand-held / indoor, median range ~5-10 m, e.g.
        balm_courtyard): finer voxels and smaller planes, so that doors, recesses and pillars
        add landmarks that break the symmetry of a few large walls; operator closer than 1 m."""
        return cls(min_range=1.0, planes=PlaneConfig(voxel_size=0.25, min_area=3.0))

    def config_hash(self) -> str:
        """Stable hash of every field and of :data:`EXTRACTION_VERSION` (landmark-cache key)."""
        text = f"v{EXTRACTION_VERSION}|{self.model_dump_json()}"
        return hashlib.sha256(text.encode()).hexdigest()[:16]


class LandmarkExtractor:
    """Extract pole (LINE) and plane (PLANE) landmarks from one scan.

    After each call, ``last_timings`` / ``last_cpu_timings`` hold the wall-clock / process CPU
    seconds per stage and ``last_info`` the counts (points, poles, planes, patches, pole mode).

    >>> ex = LandmarkExtractor()
    >>> ls = ex.extract(points)            # (N,3|4) float array, sensor frame
    >>> ls = ex.extract(points, labels)    # SemanticKITTI labels -> semantic pole mode (auto)
    """

    def __init__(self, config: LandmarkExtractorConfig | None = None) -> None:
        self.config = config or LandmarkExtractorConfig()
        self.last_timings: dict[str, float] = {}
        self.last_cpu_timings: dict[str, float] = {}
        self.last_info: dict[str, object] = {}
        #: The voxelised non-ground points of the last scan (within planes.max_range) with their
        #: normals, in the scan's frame (voxel plane detector only; else None): ICP reuses it.
        self.last_cloud: VoxelCloud | None = None

    # ------------------------------------------------------------------------------------------
    def _validate(
        self, points: ArrayLike, labels: ArrayLike | None
    ) -> tuple[Array, NDArray | None, Array]:
        try:
            arr = np.asarray(points)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"points must be an (N, 3) or (N, 4+) array ({exc})") from exc
        if arr.ndim != 2 or arr.shape[1] < 3:
            raise InvalidInputError(f"points must have shape (N, 3) or (N, 4+), got {arr.shape}")
        if arr.dtype.kind not in "fiu":
            raise InvalidInputError(f"points must be numeric, got dtype {arr.dtype}")
        lab = None
        if labels is not None:
            try:
                lab = np.asarray(labels).reshape(-1)
            except (TypeError, ValueError) as exc:
                raise InvalidInputError(f"labels must be an integer array ({exc})") from exc
            if lab.shape[0] != arr.shape[0]:
                raise InvalidInputError(f"{lab.shape[0]} labels for {arr.shape[0]} points")
            if lab.dtype.kind not in "iu":
                raise InvalidInputError(f"labels must be integers, got dtype {lab.dtype}")
            lab = semantic_class(lab)
        cfg = self.config
        self._extent = 0.0
        if arr.dtype.kind == "f" and arr.shape[0]:
            # Fast path (finite, near the origin, in metres): one pass checks and crops.
            rmax = np.inf if cfg.max_range is None else cfg.max_range
            finite, amax, P, keep, border = _crop(arr, cfg.min_range**2, rmax**2)
            small = min(UNITS_EXTENT_LIMIT, cfg.recenter_distance, MAX_COORDINATE)
            if finite and amax <= small:
                self._n_finite = int(arr.shape[0])
                # The same float64 comparison as the general path below (sqrt then compare),
                # needed only for rows within rounding of a bound (every other kept row passes)
                if border:
                    r = np.sqrt(np.einsum("ij,ij->i", P, P))
                    ok = (r >= cfg.min_range) & (r <= rmax)
                    if not ok.all():
                        P, keep = P[ok], keep[ok]
                return P, (None if lab is None else lab[keep]), np.zeros(3)
        P = arr[:, :3].astype(np.float64)
        # NaN/Inf propagate through the sum; cheaper than a reduce over the length-3 axis.
        finite = np.isfinite(P[:, 0] + P[:, 1] + P[:, 2])
        if not finite.all():
            warnings.warn(
                f"dropped {int((~finite).sum())} of {P.shape[0]} points with NaN/Inf coordinates",
                RuntimeWarning,
                stacklevel=3,
            )
            P = P[finite]
            lab = None if lab is None else lab[finite]
        offset = np.zeros(3)
        self._n_finite = int(P.shape[0])
        if P.shape[0] and float(np.abs(P).max()) > UNITS_EXTENT_LIMIT:
            self._extent = robust_extent(P)
        if P.shape[0] and float(np.abs(P).max()) > cfg.recenter_distance:
            med = np.median(P, axis=0)
            # Far away *and* compact (UTM, map frames): a cloud wider than its distance to the
            # origin is a sensor frame in other units (mm), which the range crop must see.
            if np.linalg.norm(med) > cfg.recenter_distance and self._extent < np.linalg.norm(med):
                offset = np.round(med, 0)
                P = P - offset
        if P.shape[0] and float(np.abs(P).max()) > MAX_COORDINATE:
            wild = np.abs(P).max(axis=1) > MAX_COORDINATE
            warnings.warn(
                f"dropped {int(wild.sum())} of {P.shape[0]} points further than "
                f"{MAX_COORDINATE:g} m from the cloud's centre",
                RuntimeWarning,
                stacklevel=3,
            )
            P = P[~wild]
            lab = None if lab is None else lab[~wild]
        r = np.sqrt(P[:, 0] ** 2 + P[:, 1] ** 2 + P[:, 2] ** 2)
        keep = r >= cfg.min_range
        if cfg.max_range is not None and not np.any(offset):
            keep &= r <= cfg.max_range
        if not keep.all():
            P = P[keep]
            lab = None if lab is None else lab[keep]
        return P, lab, offset

    def pole_mode(self, labels_given: bool) -> Literal["semantic", "geometric"]:
        mode = self.config.poles.mode
        if mode == "auto":
            return "semantic" if labels_given else "geometric"
        if mode == "semantic" and not labels_given:
            raise InvalidInputError(
                "pole mode 'semantic' needs labels; pass labels or use 'geometric'"
            )
        return mode

    # ------------------------------------------------------------------------------------------
    def extract(self, points: ArrayLike, labels: ArrayLike | None = None) -> LandmarkSet:
        """Landmarks of one scan in the scan's frame (poles as LINE, planes as PLANE)."""
        cfg = self.config
        timings: dict[str, float] = {}
        cpu: dict[str, float] = {}
        t0, c0 = time.perf_counter(), time.process_time()
        mode = self.pole_mode(labels is not None) if cfg.poles.enabled else None
        P, sem, offset = self._validate(points, labels)
        timings["validate"] = time.perf_counter() - t0
        cpu["validate"] = time.process_time() - c0
        self.last_timings = timings
        self.last_cloud = None
        self.last_cpu_timings = cpu
        self.last_info = {"n_points": int(P.shape[0]), "pole_mode": mode}
        hint = None if np.any(offset) else units_hint(self._extent)
        self.last_info["units_hint"] = hint
        if P.shape[0] < cfg.min_points:
            if hint is not None:
                msg = f"{self._n_finite} finite points, {P.shape[0]} in range: {hint}; no landmarks"
            elif self._n_finite >= cfg.min_points:
                msg = (
                    f"only {P.shape[0]} of {self._n_finite} finite points lie within "
                    f"[min_range, max_range] = [{cfg.min_range:g}, {cfg.max_range}] m of the "
                    f"sensor (< min_points={cfg.min_points}); no landmarks"
                )
            else:
                msg = (
                    f"only {P.shape[0]} valid points (< min_points={cfg.min_points}); no landmarks"
                )
            warnings.warn(msg, RuntimeWarning, stacklevel=2)
            return LandmarkSet.empty()
        sample = P[:: max(1, P.shape[0] // 4096)]  # the extent test needs no precision
        extent = max(float(np.ptp(sample[:, j])) for j in range(3))
        if extent < cfg.min_extent:
            warnings.warn(
                f"the cloud spans less than min_extent={cfg.min_extent} m; no landmarks (wrong units?)",
                RuntimeWarning,
                stacklevel=2,
            )
            return LandmarkSet.empty()

        # Collinear clouds (rank < 2) hold no plane: Open3D (Qhull inside) is never fed them.
        shape = degeneracy(P)
        self.last_info["degenerate"] = None if shape == "volume" else shape
        planar_ok = shape not in ("point", "line")

        t, c = time.perf_counter(), time.process_time()
        gcfg = cfg.ground
        if gcfg.enabled and planar_ok:
            ground = segment_ground(P, gcfg)
            is_ground, height = ground.is_ground, ground.height
        else:
            ground = None
            is_ground = np.zeros(P.shape[0], bool)
            zmin = P[:, 2].min()
            height = P[:, 2] - zmin
        timings["ground"] = time.perf_counter() - t
        cpu["ground"] = time.process_time() - c

        t, c = time.perf_counter(), time.process_time()
        poles: PoleResult | None = None
        if mode == "semantic":
            assert sem is not None
            poles = poles_semantic(P, sem, cfg.poles)
        elif mode == "geometric":
            poles = poles_geometric(P, height, is_ground, cfg.poles)
        timings["poles"] = time.perf_counter() - t
        cpu["poles"] = time.process_time() - c

        t, c = time.perf_counter(), time.process_time()
        planes = None
        if cfg.planes.enabled and planar_ok:
            mr = cfg.planes.max_range
            Q = _plane_points(P, is_ground, np.inf if mr is None else mr**2)
            if cfg.planes.detector == "voxel":
                grid = build_voxel_grid(Q, cfg.planes.voxel_size)
                planes, cloud = voxel_planes(grid, cfg.planes)
                self.last_cloud = cloud.shifted(offset) if np.any(offset) else cloud
            else:
                planes = extract_planes(Q, cfg.planes)
            if ground is not None and ground.normal is not None and ground.centroid is not None:
                planes = drop_ground_duplicates(planes, ground.normal, ground.centroid, cfg.planes)
        timings["planes"] = time.perf_counter() - t
        cpu["planes"] = time.process_time() - c

        t, c = time.perf_counter(), time.process_time()
        parts: list[dict] = []
        cap = cfg.max_points_per_landmark
        ground_ok = (
            ground is not None and ground.normal is not None and ground.plane_inliers.size >= 3
        )
        if ground_ok:
            assert ground is not None
            sup = ground.plane_inliers
            # PCA box of the ground support, in the plane (its centred points, from the fit).
            q = ground.centred_inliers if ground.centred_inliers is not None else P[sup] - ground.centroid
            # The in-plane axes need no more than a few thousand points (an even stride).
            _, _, Vt = np.linalg.svd(q[:: max(1, q.shape[0] // 4096)], full_matrices=False)
            uv = q @ Vt[:2].T
            box = np.array([np.ptp(uv[:, 0]), np.ptp(uv[:, 1])])
            take = np.linspace(0, sup.size - 1, min(cap, sup.size)).astype(np.int64)
            # A "ground" whose support is a strip (a kerb, a collinear cloud) fixes no normal.
            ground_ok = bool(box.min() > max(cfg.min_extent, DEGENERATE_RATIO * box.max()))
        if ground_ok:
            assert ground is not None and ground.normal is not None
            parts.append(
                {
                    "type": LandmarkType.PLANE,
                    "dirs": ground.normal[None],
                    "anchors": ground.centroid[None],
                    "support": np.array([sup.size], float),
                    "rms": np.array([ground.rms]),
                    "box": box[None],
                    "extent": np.array([box[0] * box[1]]),
                    "radius": np.array([np.nan]),
                    "is_ground": np.array([1.0]),
                    "points": P[sup[take]],
                    "counts": np.array([take.size]),
                }
            )
        if poles is not None and len(poles):
            idx, offs = subsample_groups(poles.labels, np.arange(len(poles)), cap)
            parts.append(
                {
                    "type": LandmarkType.LINE,
                    "dirs": poles.directions,
                    "anchors": poles.anchors,
                    "support": poles.support.astype(float),
                    "rms": poles.rms,
                    "box": np.full((len(poles), 2), np.nan),
                    "extent": poles.extent,
                    "radius": poles.radius,
                    "is_ground": np.zeros(len(poles)),
                    "points": P[idx],
                    "counts": np.diff(offs),
                }
            )
        if planes is not None and len(planes):
            idx, offs = subsample_groups(planes.labels, np.arange(len(planes)), cap)
            parts.append(
                {
                    "type": LandmarkType.PLANE,
                    "dirs": planes.normals,
                    "anchors": planes.anchors,
                    "support": planes.support.astype(float),
                    "rms": planes.rms,
                    "box": planes.box,
                    "extent": planes.area,
                    "radius": np.full(len(planes), np.nan),
                    "is_ground": np.zeros(len(planes)),
                    "points": planes.points[idx],
                    "counts": np.diff(offs),
                }
            )
        if parts:
            cat = {k: np.concatenate([pt[k] for pt in parts]) for k in parts[0] if k != "type"}
            types = np.concatenate(
                [np.full(len(pt["anchors"]), pt["type"], np.int8) for pt in parts]
            )
            attrs = {k: cat[k] for k in ("support", "rms", "box", "extent", "radius", "is_ground")}
            out = LandmarkSet.from_arrays(
                types,
                cat["dirs"],
                cat["anchors"],
                attrs,
                cat["points"],
                np.concatenate([[0], np.cumsum(cat["counts"])]),
            )
        else:
            out = LandmarkSet.empty()
        if cfg.scan_ranges and out.points is not None and not np.any(offset):
            out.scan_ranges = cell_minimum_ranges(P[:, :3])
        if np.any(offset):
            T = np.eye(4)
            T[:3, 3] = offset
            out = out.transform(T)
            out.sensor_pose = None  # a map frame (UTM): where the sensor was is unknown
            # Anchors are float64 and exact; support points are float32 in the far frame.
            step = float(np.abs(offset).max()) * 2.0**-24
            if out.points is not None and len(out.points) and step > PRECISION_TOLERANCE:
                warnings.warn(
                    f"far cloud (offset {offset.tolist()} m): landmark support points are float32 "
                    f"and moved by up to {step:.2g} m; extract from read_scan(...).points and map "
                    "the transform back with restore_offsets",
                    PrecisionLossWarning,
                    stacklevel=2,
                )
        timings["assemble"] = time.perf_counter() - t
        cpu["assemble"] = time.process_time() - c
        timings["total"] = time.perf_counter() - t0
        cpu["total"] = time.process_time() - c0
        self.last_info.update(
            {
                "n_poles": 0 if poles is None else len(poles),
                "n_planes": 0 if planes is None else len(planes),
                "n_patches": 0 if planes is None else planes.n_patches,
                "ground": bool(ground_ok),
            }
        )
        if len(out) == 0:
            why = f" ({hint})" if hint else ""
            if shape in ("point", "line"):
                why = f" (the cloud is degenerate: all points lie near one {shape})"
            warnings.warn(
                f"no pole or plane landmark found in this scan{why}", RuntimeWarning, stacklevel=2
            )
        return out
