"""Point-level and landmark-level evidence for a hypothesis ``T_target_source``.

Default evidence is the landmarks' own support points, which the extractor stores (a few
thousand per scan): how much of the non-ground support of each scan lands within
``inlier_m`` of the other's under the hypothesis, in both directions. KD-trees (scipy) and no
Python loop over points. Bare landmark sets without points fall back to landmark-level
evidence: the share of landmarks that land on a counterpart of the same type.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType


@dataclass
class SupportCloud:
    """Voxel-downsampled non-ground evidence points of one scan, with their KD-tree."""

    points: NDArray[np.float64]
    tree: cKDTree

    def __len__(self) -> int:
        return len(self.points)


def voxel_downsample(points: NDArray, voxel: float, max_points: int) -> NDArray[np.float64]:
    """One point per occupied voxel (the first, deterministic), then an even stride to the cap."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) == 0:
        return P
    keys = np.floor(P / voxel).astype(np.int64)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 1
    if np.prod(dims.astype(float)) < 2**62:
        flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
        _, first = np.unique(flat, return_index=True)
    else:  # absurd extents: fall back to row-unique
        _, first = np.unique(keys, axis=0, return_index=True)
    P = P[np.sort(first)]
    if len(P) > max_points:
        P = P[np.linspace(0, len(P) - 1, max_points).astype(np.int64)]
    return P


def non_ground_support(landmarks: LandmarkSet) -> NDArray[np.float32] | None:
    """Support points of every landmark except the ground plane, or None without points."""
    if landmarks.points is None or landmarks.point_offsets is None:
        return None
    g = landmarks.attributes.get("is_ground")
    if g is None:
        return landmarks.points
    keep = np.asarray(g, dtype=float).reshape(-1) < 0.5
    off = landmarks.point_offsets
    counts = np.diff(off)
    mask = np.repeat(keep, counts)
    return landmarks.points[mask]


def support_cloud(landmarks: LandmarkSet, voxel: float = 0.3, max_points: int = 1500) -> SupportCloud | None:
    """Evidence points of one landmark set (None when it carries too few support points)."""
    pts = non_ground_support(landmarks)
    if pts is None:
        return None
    P = voxel_downsample(pts, voxel, max_points)
    if len(P) < 10:
        return None
    return SupportCloud(P, cKDTree(P))


def cloud_from_points(points: NDArray, voxel: float, max_points: int) -> SupportCloud | None:
    """Evidence points from a raw scan (already without its ground)."""
    P = voxel_downsample(points, voxel, max_points)
    if len(P) < 10:
        return None
    return SupportCloud(P, cKDTree(P))


def point_overlap(
    source: SupportCloud, target: SupportCloud, T_target_source: NDArray[np.float64], inlier_m: float
) -> tuple[float, float]:
    """(source share explained by target, target share explained by source) under T (4x4)."""
    R, t = T_target_source[:3, :3], T_target_source[:3, 3]
    q = source.points @ R.T + t
    d_st, _ = target.tree.query(q, k=1, distance_upper_bound=inlier_m)
    p = (target.points - t) @ R  # R^T (p - t)
    d_ts, _ = source.tree.query(p, k=1, distance_upper_bound=inlier_m)
    return float(np.mean(np.isfinite(d_st))), float(np.mean(np.isfinite(d_ts)))


def landmark_overlap(
    source: LandmarkSet, target: LandmarkSet, T_target_source: NDArray[np.float64],
    max_deg: float = 5.0, max_m: float = 0.4,
) -> tuple[float, float]:
    """Share of landmarks (ground plane excluded) with a same-type counterpart under T, both ways.

    Lines count when directions agree within ``max_deg`` and the axes pass within ``max_m``;
    planes when normals agree, the planes are within ``max_m`` and the anchors are closer than
    the larger support's half diagonal plus 2 m (a wall does not explain a wall 50 m along it).
    """
    src = _without_ground(source).transform(T_target_source)
    tgt = _without_ground(target)
    if len(src) == 0 or len(tgt) == 0:
        return 0.0, 0.0
    cos_max = np.cos(np.radians(max_deg))
    same = src.types[:, None] == tgt.types[None, :]
    ds, dt = src.directions, tgt.directions
    cosang = np.abs(ds @ dt.T)
    diff = tgt.anchors[None, :, :] - src.anchors[:, None, :]  # (ns, nt, 3)
    along_t = np.einsum("stk,tk->st", diff, dt)
    is_plane = (tgt.types == LandmarkType.PLANE)[None, :]
    is_line = (tgt.types == LandmarkType.LINE)[None, :]
    dist_plane = np.abs(along_t)
    dist_line = np.linalg.norm(diff - along_t[..., None] * dt[None], axis=2)
    dist_point = np.linalg.norm(diff, axis=2)
    off = np.where(is_plane, dist_plane, np.where(is_line, dist_line, dist_point))
    reach = _reach(src)[:, None] + _reach(tgt)[None, :] + 2.0
    near = np.where(is_plane | is_line, np.linalg.norm(diff, axis=2) <= reach, True)
    ok = same & (np.where(src.types[:, None] > 0, cosang >= cos_max, True)) & (off <= max_m) & near
    return float(ok.any(axis=1).mean()), float(ok.any(axis=0).mean())


def _without_ground(ls: LandmarkSet) -> LandmarkSet:
    g = ls.attributes.get("is_ground")
    if g is None:
        return ls.without_points()
    keep = np.flatnonzero(np.asarray(g, dtype=float).reshape(-1) < 0.5)
    return ls.without_points()[keep]


def _reach(ls: LandmarkSet) -> NDArray[np.float64]:
    """Half the size of each landmark's support: plane box diagonal / 2, line length / 2 (inf if unknown)."""
    r = np.full(len(ls), np.inf)  # unknown size: no bound
    box = ls.attributes.get("box")
    ext = ls.attributes.get("extent")
    if box is not None:
        b = np.asarray(box, dtype=float).reshape(len(ls), -1)
        diag = np.sqrt(np.nansum(b**2, axis=1)) / 2
        r = np.where(np.isfinite(diag), diag, r)
    if ext is not None:
        e = np.asarray(ext, dtype=float).reshape(-1)
        r = np.where((ls.types == LandmarkType.LINE) & np.isfinite(e), e / 2, r)
    return r
