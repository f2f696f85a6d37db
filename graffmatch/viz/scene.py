"""What the 3D view and the plots draw: colours, downsampled points, pole segments, plane
quads, and a checked match. Shared so that the HTML view and the PNG agree."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.geometry.transforms import check_transform

SOURCE_COLOR = "#1f77b4"
TARGET_COLOR = "#ff7f0e"
SOURCE_LANDMARK_COLOR = "#0b3d91"
TARGET_LANDMARK_COLOR = "#b34700"
INLIER_COLOR = "#2ca02c"
OUTLIER_COLOR = "#d62728"
UNKNOWN_COLOR = "#9467bd"
AXIS_COLORS = ("#e41a1c", "#4daf4a", "#377eb8")

#: Fallback sizes [m] when a landmark carries neither an extent attribute nor support points.
DEFAULT_POLE_LENGTH = 3.0
DEFAULT_PLANE_SIDE = 4.0


def downsample(points: ArrayLike | None, max_points: int, seed: int = 0) -> NDArray[np.float32]:
    """Deterministic uniform subset of at most ``max_points`` rows (x, y, z only).

    A uniform subset keeps the look of the scan (dense near the sensor) which is what people
    expect from a LiDAR viewer, and is reproducible for the same seed.
    """
    if points is None:
        return np.zeros((0, 3), np.float32)
    P = np.asarray(points)
    if P.ndim != 2 or P.shape[1] < 3:
        raise InvalidInputError(f"points must be (N, 3+) arrays, got shape {P.shape}")
    P = P[:, :3]
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) > max_points > 0:
        idx = np.sort(np.random.default_rng(seed).choice(len(P), max_points, replace=False))
        P = P[idx]
    return np.ascontiguousarray(P, dtype=np.float32)


def _support_uv(
    ls: LandmarkSet, idx: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Support points of landmarks ``idx`` in basis coordinates relative to the anchor.

    Returns (has_points (len(idx),) bool, owner (M,) position in ``idx[has]``, uv (M, k),
    first (len(idx[has]),) start of each group), gathered without Python loops.
    """
    has = np.zeros(len(idx), bool)
    empty = (has, np.zeros(0, np.int64), np.zeros((0, k)), np.zeros(0, np.int64))
    if ls.points is None or ls.point_offsets is None or len(idx) == 0:
        return empty
    counts = ls.point_offsets[idx + 1] - ls.point_offsets[idx]
    has = counts > 0
    if not np.any(has):
        return (has, *empty[1:])
    sel = idx[has]
    c = counts[has]
    first = np.concatenate([[0], np.cumsum(c)[:-1]])
    owner = np.repeat(np.arange(len(sel)), c)
    gather = np.repeat(ls.point_offsets[sel], c) + (np.arange(c.sum()) - np.repeat(first, c))
    P = ls.points[gather].astype(np.float64) - ls.anchors[sel][owner]
    uv = np.einsum("ni,nik->nk", P, ls.bases[sel][owner][:, :, :k])
    return has, owner, uv, first


def pole_segments(ls: LandmarkSet) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(indices, start, end) of every line landmark, in the set's frame.

    The segment spans the support points along the axis when they are present, else
    ``extent`` centred on the anchor, else ``DEFAULT_POLE_LENGTH``.
    """
    idx = ls.indices_of_type(LandmarkType.LINE)
    d = ls.bases[idx, :, 0]
    a = ls.anchors[idx]
    half = np.full(len(idx), DEFAULT_POLE_LENGTH / 2)
    if "extent" in ls.attributes:
        ext = np.asarray(ls.attributes["extent"], float).reshape(len(ls), -1)[idx, 0]
        ok = np.isfinite(ext) & (ext > 0)
        half[ok] = ext[ok] / 2
    lo = -half
    hi = half.copy()
    has, _, uv, first = _support_uv(ls, idx, 1)
    if np.any(has):
        slo = np.minimum.reduceat(uv[:, 0], first)
        shi = np.maximum.reduceat(uv[:, 0], first)
        ok = shi > slo
        pos = np.flatnonzero(has)[ok]
        lo[pos], hi[pos] = slo[ok], shi[ok]
    return idx, a + lo[:, None] * d, a + hi[:, None] * d


def plane_quads(ls: LandmarkSet) -> tuple[np.ndarray, np.ndarray]:
    """(indices, corners (n, 4, 3)) of a rectangle per plane landmark, in the set's frame.

    The rectangle is the minimum-area rectangle of the support points when they are present,
    else the ``box`` sides (or a square of the ``extent`` area) centred on the anchor, the
    larger side horizontal for non-horizontal planes.
    """
    idx = ls.indices_of_type(LandmarkType.PLANE)
    n = len(idx)
    half = np.full((n, 2), DEFAULT_PLANE_SIDE / 2)
    if "extent" in ls.attributes:
        area = np.asarray(ls.attributes["extent"], float).reshape(len(ls), -1)[idx, 0]
        ok = np.isfinite(area) & (area > 0)
        half[ok] = np.sqrt(area[ok])[:, None] / 2
    if "box" in ls.attributes:
        box = np.asarray(ls.attributes["box"], float).reshape(len(ls), -1)
        if box.shape[1] >= 2:
            box = box[idx, :2]
            ok = np.all(np.isfinite(box) & (box > 0), axis=1)
            half[ok] = -np.sort(-box[ok], axis=1) / 2  # larger side first
    lo, hi = -half, half.copy()
    # Without support points the box orientation is unknown: lay the larger side horizontally
    # (facades, walls, boards are drawn upright); horizontal planes keep their basis.
    normal = ls.directions[idx]
    horiz = np.cross([0.0, 0.0, 1.0], normal)
    hn = np.linalg.norm(horiz, axis=1)
    upright = hn > 0.1
    u = ls.bases[idx, :, 0].copy()
    v = ls.bases[idx, :, 1].copy()
    u[upright] = horiz[upright] / hn[upright, None]
    v[upright] = np.cross(normal[upright], u[upright])
    a = ls.anchors[idx]
    has, owner, uv, first = _support_uv(ls, idx, 2)
    if np.any(has):
        # Minimum-area rectangle over a 1-degree grid of in-plane angles (vectorised over
        # points x angles): it orients the patch like its support rather than like the
        # arbitrary basis, and unlike PCA it is stable for near-square patches.
        angles = np.deg2rad(np.arange(0.0, 90.0, 1.0))
        ca, sa = np.cos(angles), np.sin(angles)
        pu = uv[:, :1] * ca + uv[:, 1:] * sa  # (M, n_angles)
        pv = -uv[:, :1] * sa + uv[:, 1:] * ca
        span_u = np.maximum.reduceat(pu, first, axis=0) - np.minimum.reduceat(pu, first, axis=0)
        span_v = np.maximum.reduceat(pv, first, axis=0) - np.minimum.reduceat(pv, first, axis=0)
        best = np.argmin(span_u * span_v, axis=1)
        c, s_ = ca[best], sa[best]
        rot_uv = np.c_[
            uv[:, 0] * c[owner] + uv[:, 1] * s_[owner], -uv[:, 0] * s_[owner] + uv[:, 1] * c[owner]
        ]
        slo = np.minimum.reduceat(rot_uv, first, axis=0)
        shi = np.maximum.reduceat(rot_uv, first, axis=0)
        ok = np.all(shi > slo, axis=1)
        pos = np.flatnonzero(has)[ok]
        cu, su = c[ok, None], s_[ok, None]
        u0, v0 = ls.bases[idx[pos], :, 0], ls.bases[idx[pos], :, 1]  # the basis of uv
        u[pos] = cu * u0 + su * v0
        v[pos] = -su * u0 + cu * v0
        lo[pos], hi[pos] = slo[ok], shi[ok]
    corners = np.stack(
        [
            a + lo[:, :1] * u + lo[:, 1:] * v,
            a + hi[:, :1] * u + lo[:, 1:] * v,
            a + hi[:, :1] * u + hi[:, 1:] * v,
            a + lo[:, :1] * u + hi[:, 1:] * v,
        ],
        axis=1,
    )
    return idx, corners


def check_match(
    source_landmarks: LandmarkSet,
    target_landmarks: LandmarkSet,
    T_target_source: ArrayLike,
    associations: ArrayLike,
    inlier_mask: ArrayLike | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.bool_] | None]:
    """(T, associations (k, 2), inlier mask or None) of a match to draw, checked."""
    T = check_transform(T_target_source, "T_target_source")
    assoc = np.asarray(associations, dtype=np.int64).reshape(-1, 2)
    if len(assoc) and (
        assoc.min() < 0
        or assoc[:, 0].max() >= len(source_landmarks)
        or assoc[:, 1].max() >= len(target_landmarks)
    ):
        raise InvalidInputError("associations index beyond the landmark sets")
    mask = None
    if inlier_mask is not None:
        mask = np.asarray(inlier_mask, dtype=bool).reshape(-1)
        if mask.shape != (len(assoc),):
            raise InvalidInputError(
                f"inlier_mask must have one entry per association ({len(assoc)}), got {mask.shape}"
            )
    return T, assoc, mask
