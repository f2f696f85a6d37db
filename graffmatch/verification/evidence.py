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

_KEY_BITS = 20
_KEY_OFF = 1 << (_KEY_BITS - 1)


def _voxel_keys(points: NDArray[np.float64], voxel: float) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """int64 key of each point's voxel, and whether it is inside the keyed range (+-2^19 voxels)."""
    ijk = np.floor(points / voxel)
    inside = np.all(np.abs(ijk) < _KEY_OFF - 2, axis=-1)
    ijk = np.where(inside[..., None], ijk, 0).astype(np.int64) + _KEY_OFF
    return (ijk[..., 0] << (2 * _KEY_BITS)) | (ijk[..., 1] << _KEY_BITS) | ijk[..., 2], inside


@dataclass
class SupportCloud:
    """Voxel-downsampled non-ground evidence points of one scan, with their KD-tree and a
    dilated voxel occupancy (sorted keys) that scores many hypotheses in one lookup."""

    points: NDArray[np.float64]
    tree: cKDTree
    occupancy: NDArray[np.int64] | None = None
    occupancy_voxel: float = 0.0

    def __len__(self) -> int:
        return len(self.points)

    def occupied(self, voxel: float) -> NDArray[np.int64]:
        """Sorted keys of the voxels that hold a point or touch one by a face (built once)."""
        if self.occupancy is None or self.occupancy_voxel != voxel:
            off = np.array([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
            base = np.floor(self.points / voxel)
            pts = ((base[:, None, :] + off[None]) + 0.5) * voxel
            keys, inside = _voxel_keys(pts.reshape(-1, 3), voxel)
            self.occupancy = np.unique(keys[inside])
            self.occupancy_voxel = voxel
        return self.occupancy


def occupancy_overlap(
    source: SupportCloud, target: SupportCloud, Ts: NDArray[np.float64], voxel: float, n_points: int = 256,
) -> NDArray[np.float64]:
    """(H, 2) approximate shares explained in both directions for H transforms at once: a point
    counts when it falls in a voxel next to an occupied one (distance up to ~2 voxels)."""
    out = np.zeros((len(Ts), 2))
    for k, (a, b, T) in enumerate(((source, target, Ts), (target, source, None))):
        P = a.points[np.linspace(0, len(a) - 1, min(n_points, len(a))).astype(np.int64)]
        if T is None:  # target -> source: inverse transforms
            R = np.swapaxes(Ts[:, :3, :3], 1, 2)
            t = -np.einsum("hij,hj->hi", R, Ts[:, :3, 3])
        else:
            R, t = T[:, :3, :3], T[:, :3, 3]
        q = P @ np.swapaxes(R, 1, 2) + t[:, None, :]  # (H, n, 3); matmul is ~3x faster than einsum here
        keys, inside = _voxel_keys(q, voxel)
        occ = b.occupied(voxel)
        pos = np.searchsorted(occ, keys)
        hit = (occ[np.minimum(pos, len(occ) - 1)] == keys) & inside
        out[:, k] = hit.mean(axis=1)
    return out


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


def align_on_evidence(
    source: SupportCloud, target: SupportCloud, T_target_source: NDArray[np.float64],
    distances: tuple[float, ...] = (1.0, 0.6, 0.4, 0.3, 0.3),
) -> NDArray[np.float64]:
    """A few point-to-point alignment steps of the source evidence onto the target's, from a
    hypothesis (nearest neighbours within a shrinking distance, then the closed-form rigid fit).

    Landmark registration is only as good as the landmarks' fits; aligning the evidence points
    turns near misses (rotation right, translation off by a metre) into accurate transforms
    before they are scored. Uses the clouds' KD-trees; deterministic (no threads)."""
    T = np.array(T_target_source, dtype=np.float64)
    P = source.points
    for d_max in distances:
        q = P @ T[:3, :3].T + T[:3, 3]
        d, idx = target.tree.query(q, k=1, distance_upper_bound=d_max)
        m = np.isfinite(d)
        if m.sum() < 10:
            break
        a, b = P[m], target.points[idx[m]]
        ca, cb = a.mean(0), b.mean(0)
        U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
        R = Vt.T @ D @ U.T
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, cb - R @ ca
    return T


def landmark_overlap(
    source: LandmarkSet, target: LandmarkSet, T_target_source: NDArray[np.float64],
    max_deg: float = 5.0, max_m: float = 0.4, counts: list | None = None,
) -> NDArray[np.float64]:
    """Graded share of landmarks (ground plane excluded) with a same-type counterpart, both ways
    (each landmark counts 1 for an exact counterpart, falling linearly to 0 at the tolerances).
    ``counts`` (a list) receives the number of landmarks explained (the smaller direction).

    ``T_target_source`` is one (4, 4) transform -> (2,), or H stacked (H, 4, 4) -> (H, 2).
    Lines count when directions agree within ``max_deg`` and the axes pass within ``max_m``;
    planes when normals agree, the planes are within ``max_m`` and the anchors are closer than
    the supports' half sizes plus 2 m (a wall does not explain a wall 50 m along it).
    """
    Ts = np.asarray(T_target_source, dtype=float)
    single = Ts.ndim == 2
    Ts = Ts[None] if single else Ts
    src = _without_ground(source)
    tgt = _without_ground(target)
    if len(src) == 0 or len(tgt) == 0:
        out = np.zeros((len(Ts), 2))
        if counts is not None:
            counts.append(np.zeros(len(Ts), np.int64))
        return out[0] if single else out
    R, t = Ts[:, :3, :3], Ts[:, :3, 3]
    Rt = np.swapaxes(R, 1, 2)
    ds = src.directions @ Rt  # (H, ns, 3)
    bs = src.anchors @ Rt + t[:, None, :]
    dt, bt = tgt.directions, tgt.anchors
    same = (src.types[:, None] == tgt.types[None, :])[None]
    cosang = np.abs(np.einsum("hsi,ti->hst", ds, dt))
    diff = bt[None, None, :, :] - bs[:, :, None, :]  # (H, ns, nt, 3)
    along_t = np.einsum("hsti,ti->hst", diff, dt)
    is_plane = (tgt.types == LandmarkType.PLANE)[None, None, :]
    is_line = (tgt.types == LandmarkType.LINE)[None, None, :]
    dist = np.linalg.norm(diff, axis=3)
    dist_line = np.sqrt(np.maximum(dist**2 - along_t**2, 0.0))
    off = np.where(is_plane, np.abs(along_t), np.where(is_line, dist_line, dist))
    reach = (_reach(src)[:, None] + _reach(tgt)[None, :] + 2.0)[None]
    near = np.where(is_plane | is_line, dist <= reach, True)
    directional = (src.types[:, None] > 0)[None]
    ang = np.degrees(np.arccos(np.clip(cosang, 0.0, 1.0)))
    ok = same & np.where(directional, ang <= max_deg, True) & (off <= max_m) & near
    # graded: an exact counterpart counts 1, one at the tolerance 0 (tent kernels)
    w = np.where(ok, np.where(directional, 1.0 - ang / max_deg, 1.0) * (1.0 - off / max_m), 0.0)
    out = np.stack([w.max(axis=2).mean(axis=1), w.max(axis=1).mean(axis=1)], axis=1)
    if counts is not None:
        counts.append(np.minimum(ok.any(axis=2).sum(axis=1), ok.any(axis=1).sum(axis=1)))
    return out[0] if single else out


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
        # planes without a box: the half diagonal of a square of that area
        r = np.where((ls.types == LandmarkType.PLANE) & ~np.isfinite(r) & np.isfinite(e) & (e > 0),
                     np.sqrt(np.maximum(e, 0) / 2), r)
    return r
