"""One voxel grid per scan, shared by plane detection and ICP, and a voxel region-growing plane
detector.

Why our own detector: Open3D's patch detector (normals by 8-NN, then robust-statistics patch
growth) cost ~35-40 ms of CPU on the ~7.5k voxels of a KITTI scan, most of the 40 ms budget
of the whole front end. Here every voxel keeps the raw moments (count, sum, sum of outer
products) of its points, so a voxel's local plane is the PCA of the moments summed over its
3x3x3 neighbourhood -- no k-NN search -- and planes grow voxel to voxel over the same
neighbour table. Everything is one pass of compiled code over the points plus a few passes
over the voxels (~2-4 ms). ``bench/bench_extraction.py --compare-detectors`` measures both
detectors (time and repeatability on real scans) side by side.

Region growing: seeds are planar voxels in order of increasing surface variation; a neighbour
(up to two voxels away, so that growth crosses the gaps between far scan lines) joins a region
when it is planar, its normal is within ``grow_angle_deg`` of the region's and its centroid
within ``max_residual`` of the region's plane, which is refitted from the summed moments as the
region grows (so a curved surface cannot creep away from the plane). A voxel whose 3x3x3
neighbourhood is no plane is tested again on its 5x5x5 one: beyond ~50 m (HDL-64E) or on sparse
hand-held scans, one 3x3x3 block holds a single scan line.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from graffmatch.errors import InvalidInputError

Array = NDArray[np.float64]

#: Refuse xy grids with more columns than this (a cloud much wider than one scan at this voxel).
MAX_COLUMNS = 64_000_000


@dataclass(frozen=True)
class VoxelGrid:
    """Occupied voxels of a cloud: centroids, raw moments and the 26-neighbour table.

    Moments are about ``origin`` (the grid's corner) so that far clouds keep their precision.
    """

    origin: Array  # (3,)
    size: float
    centroids: Array  # (V, 3) mean of each voxel's points (absolute coordinates)
    counts: NDArray[np.int64]  # (V,)
    sums: Array  # (V, 3) sum of (p - origin)
    outer: Array  # (V, 6) sums of xx, xy, xz, yy, yz, zz of (p - origin)
    neighbours: NDArray[np.int32]  # (V, 26) occupied neighbours (-1 none)
    point_voxel: NDArray[np.int64]  # (N,) voxel of each input point
    columns: tuple  # voxel indices and the per-column z ranges / slots (for ring2)

    def __len__(self) -> int:
        return int(self.counts.shape[0])

    def ring2(self, need: NDArray[np.bool_]) -> NDArray[np.int32]:
        """(V, 98) occupied neighbours two voxels away of the voxels in ``need`` (else -1):
        computed only where needed (planar and retried voxels, ~1/3 of a KITTI scan)."""
        if len(self) == 0:
            return np.zeros((0, 98), np.int32)
        return _ring(np.asarray(need, np.bool_), 2, *self.columns)


@dataclass(frozen=True)
class VoxelCloud:
    """A scan's voxel centroids and their local normals (PCA of the 3x3x3 neighbourhood; zero
    where a voxel's neighbourhood has fewer than 3 points): the down-sampled cloud with normals
    that point-to-plane ICP needs, computed once by the extractor."""

    points: Array  # (V, 3)
    normals: Array  # (V, 3) unit or zero
    voxel_size: float

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def shifted(self, offset: Array) -> VoxelCloud:
        """The same cloud moved by ``offset`` (back from a recentred frame)."""
        return VoxelCloud(self.points + offset, self.normals, self.voxel_size)


@nb.njit(cache=True)
def _voxelise(P, origin, inv):
    """Voxel of every point without sorting: each occupied xy column gets a dense run of slots
    over its own z range, so (column, z) -> voxel is O(1) and voxels come out ordered by
    (column, z), deterministically."""
    N = P.shape[0]
    ix = np.empty(N, np.int64)
    iy = np.empty(N, np.int64)
    iz = np.empty(N, np.int64)
    nx = ny = 0
    for i in range(N):
        a = int((P[i, 0] - origin[0]) * inv)
        b = int((P[i, 1] - origin[1]) * inv)
        ix[i] = a
        iy[i] = b
        iz[i] = int((P[i, 2] - origin[2]) * inv)
        nx = max(nx, a + 1)
        ny = max(ny, b + 1)
    return ix, iy, iz, nx, ny


@nb.njit(cache=True)
def _ring(need, r, vx, vy, vz, zlo, zhi, first, slot, nx, ny):
    """Occupied neighbours at Chebyshev distance exactly ``r`` (1: 26, 2: 98 columns) of the
    voxels flagged in ``need`` (-1: none, or not needed)."""
    V = vx.shape[0]
    w = (2 * r + 1) ** 3 - (2 * r - 1) ** 3
    nbr = np.full((V, w), -1, np.int32)
    for v in range(V):
        if not need[v]:
            continue
        j = 0
        for dx in range(-r, r + 1):
            x = vx[v] + dx
            for dy in range(-r, r + 1):
                y = vy[v] + dy
                ok = 0 <= x < nx and 0 <= y < ny
                c = x * ny + y if ok else 0
                lo = zlo[c] if ok else 1
                hi = zhi[c] if ok else 0
                for dz in range(-r, r + 1):
                    if max(abs(dx), abs(dy), abs(dz)) != r:
                        continue
                    z = vz[v] + dz
                    if lo <= z <= hi:
                        nbr[v, j] = slot[first[c] + z - lo]
                    j += 1
    return nbr


@nb.njit(cache=True)
def _index(P, origin, ix, iy, iz, nx, ny):
    N = P.shape[0]
    ncol = nx * ny
    zlo = np.full(ncol, 2**62, np.int64)
    zhi = np.full(ncol, -1, np.int64)
    for i in range(N):
        c = ix[i] * ny + iy[i]
        zlo[c] = min(zlo[c], iz[i])
        zhi[c] = max(zhi[c], iz[i])
    first = np.zeros(ncol + 1, np.int64)  # first slot of each column
    for c in range(ncol):
        h = zhi[c] - zlo[c] + 1 if zhi[c] >= 0 else 0
        first[c + 1] = first[c] + h
    slot = np.full(first[ncol], -1, np.int64)
    for i in range(N):
        c = ix[i] * ny + iy[i]
        slot[first[c] + iz[i] - zlo[c]] = 0
    V = 0
    for s in range(slot.shape[0]):
        if slot[s] == 0:
            slot[s] = V
            V += 1
    cnt = np.zeros(V, np.int64)
    s1 = np.zeros((V, 3))
    s2 = np.zeros((V, 6))
    vx = np.empty(V, np.int64)
    vy = np.empty(V, np.int64)
    vz = np.empty(V, np.int64)
    pv = np.empty(N, np.int64)
    for i in range(N):
        c = ix[i] * ny + iy[i]
        v = slot[first[c] + iz[i] - zlo[c]]
        pv[i] = v
        vx[v], vy[v], vz[v] = ix[i], iy[i], iz[i]
        x = P[i, 0] - origin[0]
        y = P[i, 1] - origin[1]
        z = P[i, 2] - origin[2]
        cnt[v] += 1
        s1[v, 0] += x
        s1[v, 1] += y
        s1[v, 2] += z
        s2[v, 0] += x * x
        s2[v, 1] += x * y
        s2[v, 2] += x * z
        s2[v, 3] += y * y
        s2[v, 4] += y * z
        s2[v, 5] += z * z
    nbr = _ring(np.ones(V, np.bool_), 1, vx, vy, vz, zlo, zhi, first, slot, nx, ny)
    return cnt, s1, s2, nbr, pv, (vx, vy, vz, zlo, zhi, first, slot, nx, ny)


def build_voxel_grid(points: Array, size: float) -> VoxelGrid:
    """Voxelise ``points`` (N, 3) at ``size`` metres; deterministic (voxels ordered by index)."""
    P = np.ascontiguousarray(points, dtype=np.float64)
    if P.shape[0] == 0:
        z = np.zeros((0, 3))
        return VoxelGrid(np.zeros(3), size, z, np.zeros(0, np.int64), z, np.zeros((0, 6)),
                         np.zeros((0, 26), np.int32), np.zeros(0, np.int64), ())  # fmt: skip
    origin = P.min(axis=0)
    ix, iy, iz, nx, ny = _voxelise(P, origin, 1.0 / size)
    if nx * ny > MAX_COLUMNS:
        raise InvalidInputError(
            f"voxel grid of {nx} x {ny} columns of {size} m is too large; crop the cloud (max_range)"
        )
    cnt, s1, s2, nbr, pv, cols = _index(P, origin, ix, iy, iz, nx, ny)
    cen = s1 / cnt[:, None] + origin
    return VoxelGrid(origin, float(size), cen, cnt, s1, s2, nbr, pv, cols)


@nb.njit(cache=True, inline="always")
def _eig3(c00, c01, c02, c11, c12, c22):
    """Ascending eigenvalues of a symmetric 3x3 matrix and the eigenvector of the smallest."""
    p1 = c01 * c01 + c02 * c02 + c12 * c12
    q = (c00 + c11 + c22) / 3.0
    d0, d1, d2 = c00 - q, c11 - q, c22 - q
    p2 = d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * p1
    if p2 <= 1e-300:
        return q, q, q, 0.0, 0.0, 1.0
    p = np.sqrt(p2 / 6.0)
    b00, b11, b22 = d0 / p, d1 / p, d2 / p
    b01, b02, b12 = c01 / p, c02 / p, c12 / p
    r = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02)
               + b02 * (b01 * b12 - b11 * b02))  # fmt: skip
    r = min(1.0, max(-1.0, r))
    phi = np.arccos(r) / 3.0
    e2 = q + 2.0 * p * np.cos(phi)
    e0 = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    e1 = 3.0 * q - e0 - e2
    # Eigenvector of e0: the largest cross product of two rows of (C - e0 I).
    r0 = (c00 - e0, c01, c02)
    r1 = (c01, c11 - e0, c12)
    r2 = (c02, c12, c22 - e0)
    best = -1.0
    nx_, ny_, nz_ = 0.0, 0.0, 1.0
    for a, b in ((r0, r1), (r0, r2), (r1, r2)):
        x = a[1] * b[2] - a[2] * b[1]
        y = a[2] * b[0] - a[0] * b[2]
        z = a[0] * b[1] - a[1] * b[0]
        m = x * x + y * y + z * z
        if m > best:
            best, nx_, ny_, nz_ = m, x, y, z
    if best <= 0.0:
        return e0, e1, e2, 0.0, 0.0, 1.0
    s = 1.0 / np.sqrt(best)
    return max(e0, 0.0), max(e1, 0.0), max(e2, 0.0), nx_ * s, ny_ * s, nz_ * s


@nb.njit(cache=True, inline="always")
def _plane_of(n, s0, s1, s2, o0, o1, o2, o3, o4, o5):
    """(eigenvalues, normal, mean) of the moments of n points."""
    mx, my, mz = s0 / n, s1 / n, s2 / n
    e0, e1, e2, a, b, c = _eig3(o0 / n - mx * mx, o1 / n - mx * my, o2 / n - mx * mz,
                                o3 / n - my * my, o4 / n - my * mz, o5 / n - mz * mz)  # fmt: skip
    return e0, e1, e2, a, b, c, mx, my, mz


@nb.njit(cache=True)
def _local_planes(cnt, s1, s2, nbr, extra, todo, normals, variation, planar, max_variation,
                  min_flatness, min_points):  # fmt: skip
    """For the voxels in ``todo``: the plane of the moments summed over the voxel, its ``nbr``
    and (when ``extra`` has rows) its ``extra`` neighbours; fills normals, surface variation
    l0 / (l0 + l1 + l2) and the planar flag in place. Returns, per voxel, whether a wider
    neighbourhood may help: not planar, yet not volumetric (too few points, or a line)."""
    V = cnt.shape[0]
    retry = np.zeros(V, np.bool_)
    o = np.zeros(6)
    for v in range(V):
        if not todo[v]:
            continue
        n = cnt[v]
        t0, t1, t2 = s1[v, 0], s1[v, 1], s1[v, 2]
        for k in range(6):
            o[k] = s2[v, k]
        for tab in (nbr, extra):
            for j in range(tab.shape[1]):
                u = tab[v, j]
                if u >= 0:
                    n += cnt[u]
                    t0 += s1[u, 0]
                    t1 += s1[u, 1]
                    t2 += s1[u, 2]
                    for k in range(6):
                        o[k] += s2[u, k]
        if n < 3:
            retry[v] = True
            continue
        e0, e1, e2, a, b, c, _, _, _ = _plane_of(n, t0, t1, t2, o[0], o[1], o[2], o[3], o[4], o[5])
        tot = e0 + e1 + e2
        var = e0 / tot if tot > 0 else np.inf
        flat = e1 / e2 if e2 > 0 else 0.0
        ok = var <= max_variation and flat >= min_flatness and n >= min_points
        if ok or (not planar[v] and (np.isinf(variation[v]) or var <= max_variation)):
            normals[v, 0], normals[v, 1], normals[v, 2] = a, b, c
            variation[v] = var
        planar[v] = ok
        retry[v] = not ok and (var <= max_variation or n < min_points)
    return retry


@nb.njit(cache=True)
def _grow(cnt, s1, s2, cen, nbr, nbr2, normals, planar, order, cos_max, max_offset, min_voxels,
          refit):  # fmt: skip
    V = cnt.shape[0]
    label = np.full(V, -1, np.int64)
    queue = np.empty(V, np.int64)
    n_regions = 0
    for seed in order:
        if label[seed] != -1 or not planar[seed]:
            continue
        rid = n_regions
        nxr, nyr, nzr = normals[seed, 0], normals[seed, 1], normals[seed, 2]
        cx, cy, cz = cen[seed, 0], cen[seed, 1], cen[seed, 2]
        n = cnt[seed]
        t = s1[seed].copy()
        o = s2[seed].copy()
        label[seed] = rid
        queue[0] = seed
        head, tail = 0, 1
        size, next_fit = 1, refit
        while head < tail:
            v = queue[head]
            head += 1
            for j in range(nbr.shape[1] + nbr2.shape[1]):  # across one-voxel gaps too (far lines)
                u = nbr[v, j] if j < nbr.shape[1] else nbr2[v, j - nbr.shape[1]]
                if u < 0 or label[u] >= 0 or not planar[u]:
                    continue
                if abs(nxr * normals[u, 0] + nyr * normals[u, 1] + nzr * normals[u, 2]) < cos_max:
                    continue
                off = nxr * (cen[u, 0] - cx) + nyr * (cen[u, 1] - cy) + nzr * (cen[u, 2] - cz)
                if abs(off) > max_offset:
                    continue
                label[u] = rid
                queue[tail] = u
                tail += 1
                size += 1
                n += cnt[u]
                for k in range(3):
                    t[k] += s1[u, k]
                for k in range(6):
                    o[k] += s2[u, k]
                if size >= next_fit:  # refit the region's plane from its summed moments
                    _, _, _, a, b, c, mx, my, mz = _plane_of(
                        n, t[0], t[1], t[2], o[0], o[1], o[2], o[3], o[4], o[5]
                    )
                    nxr, nyr, nzr = a, b, c
                    cx, cy, cz = mx, my, mz
                    next_fit = size + max(refit, size // 2)
        if size >= min_voxels:
            n_regions += 1
        else:
            for k in range(tail):
                label[queue[k]] = -2  # too small: never a seed again, still free to join others
    for v in range(V):
        if label[v] == -2:
            label[v] = -1
    return label, n_regions


def grow_planes(
    grid: VoxelGrid,
    max_variation: float,
    min_flatness: float,
    grow_angle_deg: float,
    max_offset: float,
    min_voxels: int,
    min_points: int = 5,
) -> tuple[NDArray[np.int64], Array, Array]:
    """Region growing over the voxels: (region id per voxel (-1 none), local normals, variation).

    A voxel is planar when its neighbourhood holds >= ``min_points`` points, its surface
    variation l0 / (l0 + l1 + l2) is <= ``max_variation`` and l1 / l2 >= ``min_flatness``
    (a thin strip -- one scan line, a pole -- fixes no plane).
    """
    if len(grid) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
    V = len(grid)
    normals = np.zeros((V, 3))
    variation = np.full(V, np.inf)
    planar = np.zeros(V, np.bool_)
    args = (max_variation, min_flatness, min_points)
    none = np.zeros((V, 0), np.int32)
    retry = _local_planes(grid.counts, grid.sums, grid.outer, grid.neighbours, none,
                          np.ones(V, np.bool_), normals, variation, planar, *args)  # fmt: skip
    nbr2 = grid.ring2(planar | retry)
    _local_planes(grid.counts, grid.sums, grid.outer, grid.neighbours, nbr2, retry, normals,
                  variation, planar, *args)  # fmt: skip
    order = np.argsort(variation, kind="stable")
    labels, _ = _grow(
        grid.counts, grid.sums, grid.outer, grid.centroids - grid.origin, grid.neighbours, nbr2,
        normals, planar, order, float(np.cos(np.radians(grow_angle_deg))), float(max_offset),
        int(min_voxels), 8,
    )  # fmt: skip
    return labels, normals, variation
