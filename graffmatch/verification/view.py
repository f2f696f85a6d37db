"""View coverage: how much of the place around its sensor a scan saw, and the overlap counted
only where both scans looked.

The decision's thresholds were chosen on whole 360 deg scans. When one scan sees only a sector
(occlusion, a sensor's field of view, a cropped map), two things change: a wrong answer needs
to explain only the few structures of that sector, so slides along a wall and 180 deg flips
reach whole-scan overlaps and margins (real courtyard pairs cut to 90-180 deg: 5 of 66 valid
answers wrong, docs/verification.md, Session 14); and a right answer's overlap is diluted,
because the whole scan's points outside the other's sector cannot be explained at all.

* :func:`azimuth_mask`: which 1 deg azimuth cells of a scan's whole-scan range image
  (``LandmarkSet.scan_ranges``, sensor frame) hold a return; its mean is the scan's
  **coverage** (about 1 for a whole scan, the sector's share for a cropped one). Computed once
  per evidence cloud (:meth:`SupportCloud.view_mask`).
* :func:`covisible_overlap`: each direction's share of explained points counted only over the
  points that the hypothesis puts inside the other scan's observed azimuth cells: on a partial
  view a right answer is not diluted by what the other sensor never looked at, and a wrong one
  must explain what the other scan saw where it looked.

:func:`check_view` (called by ``verify.verify_graph`` after the free-space check) applies stricter thresholds to pairs whose smaller coverage is below
``VerificationConfig.view_whole``; whole-scan pairs are decided exactly as before.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from graffmatch.geometry.transforms import invert

if TYPE_CHECKING:
    from graffmatch.geometry.landmarks import LandmarkSet
    from graffmatch.verification.config import VerificationConfig
    from graffmatch.verification.decision import Verdict
    from graffmatch.verification.evidence import SupportCloud
    from graffmatch.verification.verify import Evidence


def azimuth_mask(scan_ranges: NDArray | None) -> NDArray[np.bool_] | None:
    """(n_azimuth,) True where the whole-scan range image holds a return in any elevation cell
    (None without an image). Cell ``a`` covers azimuths [-180 + a w, -180 + (a + 1) w) deg in
    the sensor frame (``free_space._cells``)."""
    if scan_ranges is None:
        return None
    R = np.asarray(scan_ranges)
    if R.ndim != 2 or R.shape[0] == 0:
        return None
    return np.isfinite(R).any(axis=1)


def coverage(mask: NDArray[np.bool_] | None) -> float:
    """Share of azimuth cells with a return (1.0 when unknown: no image, no view check)."""
    return 1.0 if mask is None or len(mask) == 0 else float(np.mean(mask))


def view_mask_of(sensor_pose: NDArray | None, scan_ranges: NDArray | None) -> NDArray[np.bool_] | None:
    """:func:`azimuth_mask` of a scan's image, None when the view is unknown (no image, or no
    sensor pose: a map-frame set, whose image says nothing about where a sensor looked)."""
    return None if sensor_pose is None else azimuth_mask(scan_ranges)


def set_coverage(landmarks: LandmarkSet) -> float | None:
    """Coverage of a landmark set's scan, None when unknown (as :meth:`SupportCloud.view_mask`)."""
    mask = view_mask_of(landmarks.sensor_pose, landmarks.scan_ranges)
    return None if mask is None else coverage(mask)


def pair_view(ev: Evidence) -> tuple[float, float] | None:
    """Both clouds' coverage, None when either is unknown or the images are not whole-scan
    views (``Evidence.view`` False)."""
    if ev.source is None or ev.target is None or not ev.view:
        return None
    m_s, m_t = ev.source.view_mask(), ev.target.view_mask()
    return None if m_s is None or m_t is None else (float(m_s.mean()), float(m_t.mean()))


def _inside(points: NDArray[np.float64], M: NDArray[np.float64], mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Which ``points`` moved by ``M`` (into a sensor frame) fall in an observed azimuth cell."""
    q = points @ M[:3, :3].T + M[:3, 3]
    na = len(mask)
    a = (np.floor((np.degrees(np.arctan2(q[:, 1], q[:, 0])) + 180.0) * (na / 360.0)).astype(np.int64)) % na
    return mask[a]


def covisible_overlap(source: SupportCloud, target: SupportCloud, T_target_source: NDArray[np.float64], inlier_m: float,
                      source_mask: NDArray[np.bool_], target_mask: NDArray[np.bool_]
                      ) -> tuple[float, float, int, int]:
    """(source share explained, target share explained, source points judged, target points
    judged), counting in each direction only the points that ``T_target_source`` puts inside
    the other scan's observed azimuth cells (``*_mask`` from :func:`azimuth_mask`, in each
    cloud's sensor frame, ``SupportCloud.sensor_pose``). A direction with no point judged
    explains 0. With both masks all True this is :func:`evidence.point_overlap`."""
    T = np.asarray(T_target_source, dtype=np.float64)
    Ps = np.eye(4) if source.sensor_pose is None else source.sensor_pose
    Pt = np.eye(4) if target.sensor_pose is None else target.sensor_pose
    in_s = _inside(source.points, invert(Pt) @ T, target_mask)  # source points the target looked at
    in_t = _inside(target.points, invert(Ps) @ invert(T), source_mask)
    ns, nt = int(in_s.sum()), int(in_t.sum())
    out = []
    for n, pts, other, inverse in ((ns, source.points[in_s], target, False), (nt, target.points[in_t], source, True)):
        if n == 0:
            out.append(0.0)
            continue
        h = other.cell_hash(inlier_m)
        if h.ok:
            out.append(float(h.hits(np.ascontiguousarray(pts), T[None], inverse=inverse)[0]) / n)
        else:
            R, t = T[:3, :3], T[:3, 3]
            q = (pts - t) @ R if inverse else pts @ R.T + t
            out.append(float(np.mean(other.neighbours(q, inlier_m, nearest=False) >= 0)))
    return out[0], out[1], ns, nt


def whole_views(ev: Evidence, cfg: VerificationConfig) -> bool:
    """Both scans' coverage is known and at least ``view_whole`` (a whole-scan pair)."""
    v = pair_view(ev)
    return v is not None and min(v) >= cfg.view_whole


def check_view(verdict: Verdict, ev: Evidence, cfg: VerificationConfig) -> None:
    """Partial views: when the smaller azimuth coverage of the two scans is below
    ``view_whole``, the winner must also explain ``partial_min_overlap`` (``narrow_min_overlap``
    below ``view_narrow``) of the points that lie where the other scan looked (co-visible overlap)
    and its rival may score at most ``partial_max_rival_ratio`` (``narrow_max_rival_ratio``) of it.
    Thresholds calibrated on whole scans let slides along a wall and 180 deg flips through when one
    scan sees only a sector (docs/verification.md, Sessions 14 and 15). Whole-scan pairs, and sets
    without a whole-scan range image, are left as they are (the view is then not known). Cost: the
    coverage is built once per evidence cloud; a partial pair adds one co-visible count (~0.25 ms)."""
    v = pair_view(ev)
    if v is None or verdict.best is None:
        return
    best = verdict.best
    best.info["view_coverage"] = v
    view = min(v)
    if view >= cfg.view_whole:
        return
    if view >= cfg.view_narrow:
        tier, min_ov, max_ratio = "partial", cfg.partial_min_overlap, cfg.partial_max_rival_ratio
    else:
        tier, min_ov, max_ratio = "narrow", cfg.narrow_min_overlap, cfg.narrow_max_rival_ratio
    p0, p1, _, _ = covisible_overlap(ev.source, ev.target, best.T_target_source, cfg.inlier_m,  # type: ignore[arg-type]
                                     ev.source.view_mask(), ev.target.view_mask())  # type: ignore[union-attr]
    cov = 0.5 * (p0 + p1)
    best.info["covisible_overlap"] = (p0, p1)
    if cov < min_ov:
        verdict.valid = False
        verdict.problems.append(f"{tier} view: coverage {view:.2f}, co-visible overlap {cov:.3f} < {min_ov:.3g}")
    if verdict.runner_up is not None and verdict.rival_ratio > max_ratio:
        verdict.valid = False
        verdict.problems.append(
            f"{tier} view: coverage {view:.2f}, rival ratio {verdict.rival_ratio:.3f} > {max_ratio:.3g}")
