"""The place check: a loop estimated just beyond the place radius re-measured on the two scans.

With a place radius (``VerificationConfig.max_translation_m``, e.g. the benchmark's 5 m) a verified loop is
reported only when its estimated sensor distance is at most the radius less ``place_margin_m`` (0.25 m), because
the landmark estimate of that distance is off by up to decimetres (p99 0.17-0.25 m, max 0.38-0.75 m on the
calibration drives). A true loop 4.75-5 m apart is therefore never reported. Point-to-plane ICP on the two scans,
started from the verified pose, measures the distance to centimetres (calibration drives, docs/loops.md session
23), so a query whose only verified candidates were refused by the radius alone gets them re-measured here, the
nearest estimate first, and one is a loop when the re-measured distance lies within the radius less the smaller
``place_check_margin_m``. Only estimates at most ``place_check_band_m`` beyond the gate are re-measured: on the
calibration drives none estimated farther was accepted (docs/loops.md session 23, rule v2).

The check never makes a candidate a loop that the landmark rule did not verify: it only replaces the distance
(and the pose, by the ICP's). ICP that moves the verified pose by more than ``place_check_max_move_m`` /
``place_check_max_move_deg`` says the pose and the scans disagree, and the candidate stays refused.

It needs the scans themselves (the database keeps landmarks): ``graffmatch loops`` and the benchmark read them
from the dataset; an online :class:`~graffmatch.loops.detector.LoopDetector` needs its ``scans``.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.transforms import rotation_error_deg
from graffmatch.loops.verify import VerificationConfig
from graffmatch.registration.icp import refine_icp
from graffmatch.verification.evidence import voxel_downsample, voxel_sample_rows

#: The scan cloud of the check: the whole scan (ground included: on the calibration drives ICP measured the
#: distance as well with the ground as without, and the database keeps no ground flag), voxelised, capped.
PLACE_VOXEL_M = 0.4
PLACE_MAX_POINTS = 8000
#: Source points ICP iterates on (evenly spaced through the voxel cloud), and the target normals' radius.
PLACE_SOURCE_POINTS = 3000
PLACE_NORMAL_RADIUS_M = 1.0
PLACE_NORMAL_NEIGHBOURS = 15  # 12.6 against 19.5 ms a target cloud at 30 (one core)
#: ICP stages (correspondence distance [m], iterations): the second, tighter stage removes the ~4 cm the
#: 1 m correspondences leave along the street (calibration drives, docs/loops.md session 23).
PLACE_ICP_STAGES: tuple[tuple[float, int], ...] = ((1.0, 15), (0.3, 15))
PLACE_RELATIVE_CHANGE = 1e-4


@dataclass
class PlaceCloud:
    """A scan's voxel sample for the place check, with its normals computed once (a scan recurs as the target of
    several checks: the frames of an earlier pass near a query)."""

    points: NDArray[np.float64]
    _normals: NDArray[np.float64] | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def normals(self) -> NDArray[np.float64]:
        if self._normals is None:
            self._normals = _normals(self.points)
        return self._normals


def place_cloud(points: NDArray) -> PlaceCloud:
    """The cloud a scan is re-measured on (:data:`PLACE_VOXEL_M`, :data:`PLACE_MAX_POINTS`)."""
    P = np.asarray(points)
    if P.ndim != 2 or P.shape[1] < 3 or not np.issubdtype(P.dtype, np.number):
        raise InvalidInputError(f"place check: scan points must be a numeric (N, >=3) array, got shape {P.shape}")
    P = P[:, :3].astype(np.float64)
    P = P[np.all(np.isfinite(P), axis=1)]
    return PlaceCloud(voxel_downsample(P, PLACE_VOXEL_M, PLACE_MAX_POINTS))


def _voxel_rows(points: NDArray) -> NDArray[np.int64]:
    """Rows of :func:`place_cloud`'s voxel sample of ``points``."""
    return voxel_sample_rows(points, PLACE_VOXEL_M, PLACE_MAX_POINTS)


def scan_place_cloud(scans: Any, i: int) -> PlaceCloud:
    """Scan i's :func:`place_cloud` read from ``scans`` (a dataset, or any sequence of scans or point arrays); a
    de-skewed drive de-skews only the sampled points (:meth:`graffmatch.datasets.deskewed.Deskewed.points_subset`:
    ~2 instead of ~30 ms a scan)."""
    subset = getattr(scans, "points_subset", None)
    read = getattr(scans, "read_points", None)  # a dataset: the points alone, without the labels
    try:
        if subset is not None:
            points = subset(i, _voxel_rows)
        elif read is not None:
            points = read(i)
        else:
            scan = scans[i]
            points = getattr(scan, "points", scan)
    except (IndexError, KeyError, TypeError) as exc:
        raise InvalidInputError(f"place check: scan {i} is not in the scans given ({type(scans).__name__}): "
                                f"they must hold every added scan, in order ({exc})") from None
    return place_cloud(points)


def place_check_scans(scans: Any, config: VerificationConfig) -> Any:
    """``scans`` when the place check runs on them, else None. It needs the check on, a place radius, and scans
    that do not say they are motion-smeared (``motion_compensated`` False: a simulated ``realistic`` drive that was
    not de-skewed). Why: the check's 0.1 m margin rests on de-skewed scans (ICP within 0.056 m); on smeared scans ICP
    measured a loop 23.5 cm short (docs/loops.md, session 24). With the check on, a refusal is said, not silent:
    the warning names the way out."""
    if not config.place_check or config.max_translation_m is None:
        return None
    why = None
    if scans is None:
        why = ("no scans were given (LoopDetector(config, scans=...)), so loops estimated just beyond the radius less "
               f"{config.place_margin_m} m stay refused; pass the scans, or set verification.place_check=False")
    elif getattr(scans, "motion_compensated", None) is False:
        why = (f"the scans of {getattr(scans, 'name', type(scans).__name__)} are motion-distorted and not de-skewed, "
               "and the check's margin holds only on motion-compensated scans; de-skew them (graffmatch loops "
               "--deskew, or graffmatch.datasets.Deskewed)")
    if why is not None:
        warnings.warn(f"place check off ({config.max_translation_m} m place radius): {why}", stacklevel=2)
        return None
    return scans


def _normals(points: NDArray) -> NDArray[np.float64]:
    import open3d as o3d

    o3d.utility.set_max_threads(1)  # one core, as every timed query
    try:
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=PLACE_NORMAL_RADIUS_M,
                                                                   max_nn=PLACE_NORMAL_NEIGHBOURS))
    finally:
        o3d.utility.set_max_threads(0)
    return np.asarray(pc.normals, dtype=np.float64)


def remeasure(query_cloud: PlaceCloud, match_cloud: PlaceCloud, T_match_query: NDArray) -> tuple[NDArray[np.float64], float]:
    """(T_match_query refined by point-to-plane ICP of the query cloud onto the match cloud, fitness of the last
    stage), from the verified pose (:data:`PLACE_ICP_STAGES`)."""
    S = query_cloud.points
    if len(S) > PLACE_SOURCE_POINTS:
        S = S[np.linspace(0, len(S) - 1, PLACE_SOURCE_POINTS).astype(np.int64)]
    Tt, N = match_cloud.points, match_cloud.normals
    T = np.asarray(T_match_query, dtype=np.float64)
    fit = 0.0
    for dist, iters in PLACE_ICP_STAGES:
        T, fit, _ = refine_icp(S, Tt, T, dist, iters, True, PLACE_NORMAL_RADIUS_M, N,
                               PLACE_RELATIVE_CHANGE, PLACE_RELATIVE_CHANGE)
    return T, float(fit)


def place_check_candidates(recs: list[dict], config: VerificationConfig) -> list[dict]:
    """The records the check re-measures: none when a record is already a loop; else the verified ones refused by
    the place radius alone (``radius_confidence`` reaches ``min_confidence``) whose estimate lies at most
    ``place_check_band_m`` beyond the radius less ``place_margin_m`` (the gate), the nearest first, at most
    ``place_check_max``."""
    if not config.place_check or config.max_translation_m is None:
        return []
    if any(r.get("confidence", 0.0) >= config.min_confidence for r in recs):
        return []
    lo = config.max_translation_m - config.place_margin_m
    hi = lo + config.place_check_band_m
    out = []
    for r in recs:
        T = r.get("radius_T")
        if T is None or r.get("radius_confidence", 0.0) < config.min_confidence:
            continue
        d = float(np.linalg.norm(np.asarray(T, float).reshape(4, 4)[:3, 3]))
        if lo < d <= hi:
            out.append((d, r["rank"], r))
    return [r for _, _, r in sorted(out, key=lambda x: (x[0], x[1]))[: config.place_check_max]]


def run_place_check(query: int, recs: list[dict], config: VerificationConfig,
                    cloud_of: Callable[[int], PlaceCloud | None]) -> None:
    """Re-measure :func:`place_check_candidates` on the scans (``cloud_of(i)``: scan i's :func:`place_cloud`, or None
    when it cannot be read), in place: the first whose re-measured distance is within the radius less
    ``place_check_margin_m`` becomes the query's loop (its ``radius_confidence``, the ICP pose; the verified pose
    stays in ``place_T0``). Every re-measured record gets ``place_distance_m``, ``place_moved_m``,
    ``place_moved_deg``, ``place_fitness``, ``place_seconds`` and ``place_accepted``."""
    todo = place_check_candidates(recs, config)
    if not todo:
        return
    t_query = time.perf_counter()
    qc = cloud_of(query)
    if qc is None or len(qc) < 10:
        return
    radius = float(config.max_translation_m) - config.place_check_margin_m  # type: ignore[arg-type]
    for k, r in enumerate(todo):
        t0 = t_query if k == 0 else time.perf_counter()  # the first check's time includes reading the query's scan
        mc = cloud_of(r["match"])
        if mc is None or len(mc) < 10:
            continue
        T0 = np.asarray(r["radius_T"], float).reshape(4, 4)
        T, fit = remeasure(qc, mc, T0)
        moved_m = float(np.linalg.norm(T[:3, 3] - T0[:3, 3]))
        moved_deg = rotation_error_deg(T[:3, :3], T0[:3, :3])
        d = float(np.linalg.norm(T[:3, 3]))
        ok = (d <= radius and moved_m <= config.place_check_max_move_m
              and moved_deg <= config.place_check_max_move_deg)
        dt = time.perf_counter() - t0
        r.update(place_distance_m=d, place_moved_m=moved_m, place_moved_deg=float(moved_deg), place_fitness=fit,
                 place_seconds=dt, place_accepted=bool(ok), seconds=r.get("seconds", 0.0) + dt)
        if ok:
            r.update(place_T0=r["radius_T"], T=T.ravel().tolist(), confidence=float(r["radius_confidence"]))
            return
