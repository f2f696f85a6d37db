"""Fixed-radius nearest neighbours and voxel occupancy on cell hashes (numba).

Why not a KD-tree: verification queries a few thousand points per hypothesis against clouds of
a few thousand, many times per pair; a cell table of twice the radius answers exactly what
``cKDTree.query(..., k=1, distance_upper_bound=r)`` answers (the same nearest point, the same
strict ``d < r``; tested against scipy) at a fraction of its cost. Clouds whose coordinates do
not fit the cell keys are reported (``CellHash.ok``) so the caller falls back to the KD-tree.

The module runs past 600 lines on purpose: the table, its queries, the alignment step and the
occupancy bitmaps share one key layout and one set of bounds checks; the kernels that read the
layout stay beside the code that writes it.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

_KEY_BITS = 20
_KEY_OFF = 1 << (_KEY_BITS - 1)


def voxel_keys(points: NDArray[np.float64], voxel: float,
                origin: NDArray[np.float64] | None = None) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """int64 key of each point's voxel counted from ``origin`` (a voxel index; 0 if None), and
    whether it is inside the keyed range (+-2^19 voxels around the origin)."""
    ijk = np.floor(points / voxel)
    if origin is not None:
        ijk = ijk - origin
    inside = np.all(np.abs(ijk) < _KEY_OFF - 2, axis=-1)
    ijk = np.where(inside[..., None], ijk, 0).astype(np.int64) + _KEY_OFF
    return (ijk[..., 0] << (2 * _KEY_BITS)) | (ijk[..., 1] << _KEY_BITS) | ijk[..., 2], inside


_GRID_BITS = 20
_GRID_LIM = 1 << _GRID_BITS  # cells per axis a cell hash can key
_GRID_MARGIN = 1e-5  # cells are this much wider than twice the radius: rounding never hides a neighbour
_DENSE_MAX = 1 << 19  # largest dense cell table (int32, 2 MB); bigger boxes use the hash
NEAR_BITS = 1 << 23  # largest 'near' bitmap of a cell hash (1 MB); bigger boxes search every query


@nb.njit(cache=True, inline="always")
def _slot(key: int, mask: int) -> int:
    """Multiplicative (Fibonacci) hash of a packed cell key."""
    h = np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)
    return np.int64(h >> np.uint64(32)) & mask


@nb.njit(cache=True)
def hash_table(keys: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Open-addressing table (linear probing, load <= 1/4) of distinct non-negative keys -> index."""
    cap = 8
    while cap < 4 * len(keys):
        cap *= 2
    tk = np.full(cap, -1, np.int64)
    tv = np.empty(cap, np.int64)
    mask = cap - 1
    for i in range(len(keys)):
        s = _slot(keys[i], mask)
        while tk[s] != -1:
            s = (s + 1) & mask
        tk[s] = keys[i]
        tv[s] = i
    return tk, tv


@nb.njit(cache=True, inline="always")
def _lookup(tk: NDArray[np.int64], tv: NDArray[np.int64], key: int) -> int:
    mask = len(tk) - 1
    s = _slot(key, mask)
    while True:
        k = tk[s]
        if k == key:
            return tv[s]
        if k == -1:
            return -1
        s = (s + 1) & mask


@nb.njit(cache=True, inline="always")
def _nearest_in_grid(qx: float, qy: float, qz: float, spts: NDArray[np.float64], h: float, inv_h: float,
                     origin: NDArray[np.int64], dims: NDArray[np.int64], dense: NDArray[np.int32],
                     tk: NDArray[np.int64], tv: NDArray[np.int64], starts: NDArray[np.int64], r2: float,
                     nearest: bool) -> int:
    """Row of ``spts`` (cell order) nearest to (qx, qy, qz) with squared distance < r2, -1 if
    none; ``nearest=False``: the first such row (existence only).

    Cells are twice the radius: the ball around a point lies in the 2 x 2 x 2 cells nearest to
    it (per axis, its own cell and the neighbour on the side of the half it is in). A cell is
    found in ``dense`` (a full table over the cloud's box) when it is given, else in the hash.
    The own cell is searched first; a neighbour cell whose box is no closer than the best point
    so far is skipped (it cannot hold a strictly closer one, so the answer is unchanged)."""
    ux = qx * inv_h
    uy = qy * inv_h
    uz = qz * inv_h
    fx = np.floor(ux)
    fy = np.floor(uy)
    fz = np.floor(uz)
    gx = fx - origin[0]
    gy = fy - origin[1]
    gz = fz - origin[2]
    if not (gx >= -1.0 and gx <= dims[0] and gy >= -1.0 and gy <= dims[1] and gz >= -1.0 and gz <= dims[2]):
        return -1  # also NaN: farther than a cell from the cloud
    cx, cy, cz = int(gx), int(gy), int(gz)
    rx = ux - fx
    ry = uy - fy
    rz = uz - fz
    sx = 1 if rx >= 0.5 else -1
    sy = 1 if ry >= 0.5 else -1
    sz = 1 if rz >= 0.5 else -1
    # distance to the neighbour cell's face per axis, less a margin far above the rounding of
    # the cell coordinates (|u| < 2^28: error < 1e-7 cells), so a skipped cell is truly farther
    tol = 1e-6 * h
    bx = max(((1.0 - rx) if sx > 0 else rx) * h - tol, 0.0)
    by = max(((1.0 - ry) if sy > 0 else ry) * h - tol, 0.0)
    bz = max(((1.0 - rz) if sz > 0 else rz) * h - tol, 0.0)
    bx2 = bx * bx
    by2 = by * by
    bz2 = bz * bz
    use_dense = len(dense) > 0
    best = r2
    bi = -1
    for c8 in range(8):
        box = 0.0
        if c8 & 1:
            box += bx2
        if c8 & 2:
            box += by2
        if c8 & 4:
            box += bz2
        if box >= best:
            continue
        x = cx + (sx if c8 & 1 else 0)
        y = cy + (sy if c8 & 2 else 0)
        z = cz + (sz if c8 & 4 else 0)
        if x < 0 or y < 0 or z < 0 or x >= dims[0] or y >= dims[1] or z >= dims[2]:
            continue
        if use_dense:
            c = dense[(x * dims[1] + y) * dims[2] + z]
        else:
            c = _lookup(tk, tv, (x << (2 * _GRID_BITS)) | (y << _GRID_BITS) | z)
        if c < 0:
            continue
        for s in range(starts[c], starts[c + 1]):
            d0 = qx - spts[s, 0]
            d1 = qy - spts[s, 1]
            d2 = qz - spts[s, 2]
            d = d0 * d0 + d1 * d1 + d2 * d2
            if d < best:
                best = d
                bi = s
                if not nearest:
                    return bi
    return bi


@nb.njit(cache=True)
def _grid_query(q: NDArray[np.float64], spts: NDArray[np.float64], order: NDArray[np.int64], h: float,
                inv_h: float, origin: NDArray[np.int64], dims: NDArray[np.int64], dense: NDArray[np.int32],
                tk: NDArray[np.int64], tv: NDArray[np.int64], starts: NDArray[np.int64], r2: float,
                nearest: bool, out: NDArray[np.int64]) -> None:
    """For each query point, the index of its nearest cloud point with squared distance < r2
    (-1 if none); ``nearest=False``: of any such point (existence only)."""
    # Results go to a local array first: a store into an argument array inside the search loop
    # (which might alias the grid's arrays) makes LLVM reload the grid on every point (~4x slower).
    found = np.empty(q.shape[0], np.int64)
    for a in range(q.shape[0]):
        found[a] = _nearest_in_grid(q[a, 0], q[a, 1], q[a, 2], spts, h, inv_h, origin, dims, dense, tk, tv,
                                    starts, r2, nearest)
    for a in range(q.shape[0]):
        bi = found[a]
        out[a] = order[bi] if bi >= 0 else -1


@nb.njit(cache=True)
def _moved_near(P: NDArray[np.float64], r00: float, r01: float, r02: float, t0: float, r10: float, r11: float,
                r12: float, t1: float, r20: float, r21: float, r22: float, t2: float, near: NDArray[np.uint8],
                near_lo: NDArray[np.int64], near_dims: NDArray[np.int64], near_inv: float,
                q: NDArray[np.float64], cand: NDArray[np.int64]) -> int:
    """Move the rows of ``P`` by (R, t) and keep those inside the ``near`` bitmap (every row when
    it is empty): their moved coordinates go to ``q[:m]`` and their rows to ``cand[:m]``; returns
    m. (Kept out of the search loops: inside them this test made LLVM compile the search ~3x
    slower.)"""
    use_near = len(near) > 0
    lo0, lo1, lo2 = near_lo[0], near_lo[1], near_lo[2]
    n0, n1, n2 = near_dims[0], near_dims[1], near_dims[2]
    m = 0
    for a in range(P.shape[0]):
        px, py, pz = P[a, 0], P[a, 1], P[a, 2]
        qx = (r00 * px + r01 * py + r02 * pz) + t0
        qy = (r10 * px + r11 * py + r12 * pz) + t1
        qz = (r20 * px + r21 * py + r22 * pz) + t2
        if use_near:
            vx = np.floor(qx * near_inv) - lo0
            vy = np.floor(qy * near_inv) - lo1
            vz = np.floor(qz * near_inv) - lo2
            if not (vx >= 0.0 and vx < n0 and vy >= 0.0 and vy < n1 and vz >= 0.0 and vz < n2):
                continue  # (NaN too)
            f = (int(vx) * n1 + int(vy)) * n2 + int(vz)
            if not near[f >> 3] & (1 << (f & 7)):
                continue
        q[m, 0] = qx
        q[m, 1] = qy
        q[m, 2] = qz
        cand[m] = a
        m += 1
    return m


@nb.njit(cache=True)
def _align_step(P: NDArray[np.float64], T: NDArray[np.float64], spts: NDArray[np.float64], h: float,
                inv_h: float, origin: NDArray[np.int64], dims: NDArray[np.int64], dense: NDArray[np.int32],
                tk: NDArray[np.int64], tv: NDArray[np.int64], starts: NDArray[np.int64], r2: float,
                near: NDArray[np.uint8], near_lo: NDArray[np.int64], near_dims: NDArray[np.int64],
                near_inv: float, min_pairs: int) -> int:
    """One point-to-point step: pair each row of ``P`` moved by ``T`` with its nearest cloud
    point (squared distance < r2), then replace ``T`` by the closed-form rigid fit of the pairs
    (centroids, cross-covariance, SVD with the reflection fixed). Returns the number of pairs;
    fewer than ``min_pairs``: ``T`` is left as it was. Points outside the ``near`` bitmap are
    not searched (see :func:`_moved_hits`)."""
    r00, r01, r02, t0 = T[0, 0], T[0, 1], T[0, 2], T[0, 3]
    r10, r11, r12, t1 = T[1, 0], T[1, 1], T[1, 2], T[1, 3]
    r20, r21, r22, t2 = T[2, 0], T[2, 1], T[2, 2], T[2, 3]
    n_p = P.shape[0]
    q = np.empty((n_p, 3))
    cand = np.empty(n_p, np.int64)
    m = _moved_near(P, r00, r01, r02, t0, r10, r11, r12, t1, r20, r21, r22, t2, near, near_lo, near_dims,
                    near_inv, q, cand)
    found = np.empty(m, np.int64)
    for k in range(m):  # the search alone in this loop: LLVM keeps the grid in registers
        found[k] = _nearest_in_grid(q[k, 0], q[k, 1], q[k, 2], spts, h, inv_h, origin, dims, dense, tk, tv, starts,
                                    r2, True)
    # the pairs in row order (cand is ascending): the sums below add the same terms in the same
    # order as a pass over every row of P would
    n = 0
    sa0 = sa1 = sa2 = sb0 = sb1 = sb2 = 0.0
    for k in range(m):
        bi = found[k]
        if bi >= 0:
            a = cand[k]
            n += 1
            sa0 += P[a, 0]
            sa1 += P[a, 1]
            sa2 += P[a, 2]
            sb0 += spts[bi, 0]
            sb1 += spts[bi, 1]
            sb2 += spts[bi, 2]
    if n < min_pairs:
        return n
    ca0, ca1, ca2 = sa0 / n, sa1 / n, sa2 / n
    cb0, cb1, cb2 = sb0 / n, sb1 / n, sb2 / n
    H = np.zeros((3, 3))
    for k in range(m):
        bi = found[k]
        if bi < 0:
            continue
        a = cand[k]
        a0, a1, a2 = P[a, 0] - ca0, P[a, 1] - ca1, P[a, 2] - ca2
        b0, b1, b2 = spts[bi, 0] - cb0, spts[bi, 1] - cb1, spts[bi, 2] - cb2
        H[0, 0] += a0 * b0
        H[0, 1] += a0 * b1
        H[0, 2] += a0 * b2
        H[1, 0] += a1 * b0
        H[1, 1] += a1 * b1
        H[1, 2] += a1 * b2
        H[2, 0] += a2 * b0
        H[2, 1] += a2 * b1
        H[2, 2] += a2 * b2
    U, _, Vt = np.linalg.svd(H)
    V = np.ascontiguousarray(Vt.T)
    M = V @ U.T
    det = (M[0, 0] * (M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]) - M[0, 1] * (M[1, 0] * M[2, 2] - M[1, 2] * M[2, 0])
           + M[0, 2] * (M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]))
    if det < 0:
        V[:, 2] = -V[:, 2]
        M = V @ U.T
    cb = (cb0, cb1, cb2)
    for i in range(3):
        for j in range(3):
            T[i, j] = M[i, j]
        T[i, 3] = cb[i] - (M[i, 0] * ca0 + M[i, 1] * ca1 + M[i, 2] * ca2)
        T[3, i] = 0.0
    T[3, 3] = 1.0
    return n


@nb.njit(cache=True)
def _moved_hits(P: NDArray[np.float64], Ts: NDArray[np.float64], inverse: bool, spts: NDArray[np.float64],
                h: float, inv_h: float, origin: NDArray[np.int64], dims: NDArray[np.int64],
                dense: NDArray[np.int32], tk: NDArray[np.int64], tv: NDArray[np.int64],
                starts: NDArray[np.int64], r2: float, near: NDArray[np.uint8], near_lo: NDArray[np.int64],
                near_dims: NDArray[np.int64], near_inv: float) -> NDArray[np.int64]:
    """(H,) how many of the points ``P`` moved by each transform (its inverse when ``inverse``)
    have a cloud point with squared distance < r2. Points outside the ``near`` bitmap
    (:meth:`CellHash.near_bitmap`) have none and are not searched: most points of a wrong
    hypothesis. (The bitmap test runs in a pass of its own: inside the search loop it made LLVM
    compile the search ~3x slower.)"""
    H, n = Ts.shape[0], P.shape[0]
    out = np.zeros(H, np.int64)
    R = np.empty((3, 3))
    t = np.empty(3)
    q = np.empty((n, 3))
    cand = np.empty(n, np.int64)
    found = np.empty(n, np.int64)
    for hh in range(H):
        _moved_frame(Ts, hh, inverse, R, t)
        r00, r01, r02, t0 = R[0, 0], R[0, 1], R[0, 2], t[0]
        r10, r11, r12, t1 = R[1, 0], R[1, 1], R[1, 2], t[1]
        r20, r21, r22, t2 = R[2, 0], R[2, 1], R[2, 2], t[2]
        # moved points next to the cloud first, the search in a loop of its own
        m = _moved_near(P, r00, r01, r02, t0, r10, r11, r12, t1, r20, r21, r22, t2, near, near_lo, near_dims,
                        near_inv, q, cand)
        # the search alone in its loop, results to a local array (counting inside the search
        # loop made LLVM keep less of the grid in registers: ~3x slower)
        for a in range(m):
            found[a] = _nearest_in_grid(q[a, 0], q[a, 1], q[a, 2], spts, h, inv_h, origin, dims, dense, tk, tv,
                                        starts, r2, False)
        cnt = 0
        for a in range(m):
            if found[a] >= 0:
                cnt += 1
        out[hh] = cnt
    return out


@nb.njit(cache=True, inline="always")
def _moved_frame(Ts: NDArray[np.float64], hh: int, inverse: bool, R: NDArray[np.float64],
                 t: NDArray[np.float64]) -> None:
    """Rotation and translation of transform ``hh`` of ``Ts``, or of its inverse (R^T, -R^T t)."""
    for i in range(3):
        for j in range(3):
            R[i, j] = Ts[hh, j, i] if inverse else Ts[hh, i, j]
    for i in range(3):
        if inverse:
            t[i] = -(R[i, 0] * Ts[hh, 0, 3] + R[i, 1] * Ts[hh, 1, 3] + R[i, 2] * Ts[hh, 2, 3])
        else:
            t[i] = Ts[hh, i, 3]


OCCUPANCY_BITS = 1 << 24  # largest occupancy bitmap (2 MB); larger boxes use the hash table


def occupancy_lookup(keys: NDArray[np.int64]) -> tuple:
    """What :func:`occupied_hits` looks the keys of :func:`voxel_keys` up in: (hash keys, hash
    values, bitmap, bitmap low corner, bitmap dims). The bitmap covers the keys' box (one bit a
    voxel: ~0.1 MB for a courtyard scan at 0.3 m, in cache) and is empty when the box is larger
    than ``OCCUPANCY_BITS``; then the hash table answers."""
    empty = np.zeros(0, np.int64)
    if len(keys) == 0:
        return empty, empty, np.zeros(0, np.uint8), np.zeros(3, np.int64), np.zeros(3, np.int64)
    mask = (1 << _KEY_BITS) - 1
    ijk = np.stack([(keys >> (2 * _KEY_BITS)) & mask, (keys >> _KEY_BITS) & mask, keys & mask], axis=1) - _KEY_OFF
    lo = ijk.min(axis=0)
    dims = ijk.max(axis=0) - lo + 1
    if float(np.prod(dims.astype(float))) > OCCUPANCY_BITS:
        tk, tv = hash_table(keys)
        return tk, tv, np.zeros(0, np.uint8), lo, dims
    flat = ((ijk[:, 0] - lo[0]) * dims[1] + (ijk[:, 1] - lo[1])) * dims[2] + (ijk[:, 2] - lo[2])
    bits = np.zeros((int(np.prod(dims)) + 7) // 8, np.uint8)
    np.bitwise_or.at(bits, flat >> 3, (1 << (flat & 7)).astype(np.uint8))
    return empty, empty, bits, lo, dims


def occupancy_bitmap(points: NDArray[np.float64], voxel: float) -> tuple | None:
    """(origin, table) of the voxels holding a point or touching one by a face, counted from
    ``origin`` (the cloud's lowest voxel), for :func:`occupied_hits`: what
    ``occupancy_lookup`` gives for those voxels' :func:`voxel_keys`, built in one compiled
    pass without the sorted keys. None when the box is too large for the bitmap (then the
    keys and the hash table answer)."""
    ok, origin, bits, dims = _occupancy_build(np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3),
                                              float(voxel), OCCUPANCY_BITS)
    if not ok:
        return None
    empty = np.zeros(0, np.int64)
    return origin, (empty, empty, bits, np.full(3, -1, np.int64), dims)


def _occupancy_bitmap_reference(points: NDArray[np.float64], voxel: float) -> tuple | None:
    """numpy specification of :func:`occupancy_bitmap`."""
    base = np.floor(np.asarray(points, dtype=np.float64) / voxel)
    if len(base) == 0 or not np.all(np.isfinite(base)):
        return None
    origin = base.min(axis=0)
    ijk = base - origin  # >= 0; the face neighbours reach -1 .. max + 1
    top = ijk.max(axis=0)
    if top.max() >= (1 << (_KEY_BITS - 1)) - 3:  # before the cast: far coordinates overflow int64
        return None
    dims = top.astype(np.int64) + 3
    if float(np.prod(dims.astype(float))) > OCCUPANCY_BITS:
        return None
    bits = np.zeros((int(np.prod(dims)) + 7) // 8, np.uint8)
    _set_face_bits(ijk.astype(np.int64), dims, bits)
    empty = np.zeros(0, np.int64)
    return origin, (empty, empty, bits, np.full(3, -1, np.int64), dims)


@nb.njit(cache=True)
def _occupancy_build(P: NDArray[np.float64], voxel: float, max_bits: int) -> tuple:
    """(ok, origin, bits, dims) of :func:`occupancy_bitmap` in one compiled call (its dozen numpy
    steps cost more than the work; a cold match builds two): the same floors, origin (the
    lowest voxel), dims and bits; ok False where the reference returns None."""
    n = P.shape[0]
    base = np.empty((n, 3))
    origin = np.zeros(3)
    top = np.zeros(3)
    empty_bits = np.zeros(0, np.uint8)
    dims = np.zeros(3, np.int64)
    if n == 0:
        return False, origin, empty_bits, dims
    for a in range(n):
        for j in range(3):
            b = np.floor(P[a, j] / voxel)
            if not np.isfinite(b):
                return False, origin, empty_bits, dims
            base[a, j] = b
            if a == 0 or b < origin[j]:
                origin[j] = b
    for a in range(n):
        for j in range(3):
            d = base[a, j] - origin[j]
            base[a, j] = d
            if a == 0 or d > top[j]:
                top[j] = d
    for j in range(3):
        dims[j] = int(top[j]) + 3
    if (float(dims[0]) * float(dims[1]) * float(dims[2]) > max_bits
            or max(top[0], top[1], top[2]) >= (1 << (_KEY_BITS - 1)) - 3):
        return False, origin, empty_bits, dims
    bits = np.zeros((dims[0] * dims[1] * dims[2] + 7) // 8, np.uint8)
    ijk = np.empty((n, 3), np.int64)
    for a in range(n):
        for j in range(3):
            ijk[a, j] = int(base[a, j])
    _set_face_bits(ijk, dims, bits)
    return True, origin, bits, dims


@nb.njit(cache=True)
def _set_face_bits(ijk: NDArray[np.int64], dims: NDArray[np.int64], bits: NDArray[np.uint8]) -> None:
    """Set the bit of each row's voxel and of its six face neighbours (bitmap low corner -1)."""
    for a in range(ijk.shape[0]):
        for o in range(7):
            x, y, z = ijk[a, 0] + 1, ijk[a, 1] + 1, ijk[a, 2] + 1
            if o == 1:
                x += 1
            elif o == 2:
                x -= 1
            elif o == 3:
                y += 1
            elif o == 4:
                y -= 1
            elif o == 5:
                z += 1
            elif o == 6:
                z -= 1
            f = (x * dims[1] + y) * dims[2] + z
            bits[f >> 3] |= np.uint8(1 << (f & 7))


@nb.njit(cache=True)
def occupied_hits(P: NDArray[np.float64], Ts: NDArray[np.float64], inverse: bool, voxel: float,
                  origin: NDArray[np.float64], tk: NDArray[np.int64], tv: NDArray[np.int64],
                  bits: NDArray[np.uint8], lo: NDArray[np.int64], dims: NDArray[np.int64]) -> NDArray[np.int64]:
    """(H,) how many of the points ``P`` (n, 3) moved by each of H transforms ``Ts`` (by their
    inverses when ``inverse``) fall in an occupied voxel (the keys of :func:`voxel_keys`, looked
    up in :func:`occupancy_lookup`'s bitmap, or its hash table). One pass, no (H, n, 3) array of
    moved points."""
    H, n = Ts.shape[0], P.shape[0]
    out = np.zeros(H, np.int64)
    bound = float((1 << (_KEY_BITS - 1)) - 2)
    use_bits = len(bits) > 0
    lo0, lo1, lo2 = lo[0], lo[1], lo[2]
    n0, n1, n2 = dims[0], dims[1], dims[2]
    o0, o1, o2 = origin[0], origin[1], origin[2]
    R = np.empty((3, 3))
    t = np.empty(3)
    for hh in range(H):
        _moved_frame(Ts, hh, inverse, R, t)
        r00, r01, r02, t0 = R[0, 0], R[0, 1], R[0, 2], t[0]
        r10, r11, r12, t1 = R[1, 0], R[1, 1], R[1, 2], t[1]
        r20, r21, r22, t2 = R[2, 0], R[2, 1], R[2, 2], t[2]
        cnt = 0
        for a in range(n):
            px, py, pz = P[a, 0], P[a, 1], P[a, 2]
            qx = (r00 * px + r01 * py + r02 * pz) + t0
            qy = (r10 * px + r11 * py + r12 * pz) + t1
            qz = (r20 * px + r21 * py + r22 * pz) + t2
            i = np.floor(qx / voxel) - o0
            j = np.floor(qy / voxel) - o1
            k = np.floor(qz / voxel) - o2
            if not (abs(i) < bound and abs(j) < bound and abs(k) < bound):
                continue
            if use_bits:
                x = int(i) - lo0
                y = int(j) - lo1
                z = int(k) - lo2
                if x < 0 or y < 0 or z < 0 or x >= n0 or y >= n1 or z >= n2:
                    continue
                f = (x * n1 + y) * n2 + z
                if bits[f >> 3] & (1 << (f & 7)):
                    cnt += 1
                continue
            key = (((int(i) + _KEY_OFF) << (2 * _KEY_BITS)) | ((int(j) + _KEY_OFF) << _KEY_BITS)
                   | (int(k) + _KEY_OFF))
            if _lookup(tk, tv, key) >= 0:
                cnt += 1
        out[hh] = cnt
    return out


@nb.njit(cache=True)
def _set_near_bits(cells: NDArray[np.int64], dims: NDArray[np.int64], bits: NDArray[np.uint8]) -> None:
    """Set the bit of every voxel in the 27-neighbourhood of each row of ``cells`` (voxel
    indices inside a box of ``dims``, one voxel from its border)."""
    for a in range(cells.shape[0]):
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-1, 2):
                    f = ((cells[a, 0] + dx) * dims[1] + (cells[a, 1] + dy)) * dims[2] + (cells[a, 2] + dz)
                    bits[f >> 3] |= np.uint8(1 << (f & 7))


@nb.njit(cache=True)
def _cells_of(P: NDArray[np.float64], inv_h: float) -> tuple:
    """(ok, integer cell of each point, lowest cell, highest cell): ok False when a cell is not
    finite or not below 2^28 in magnitude (the keys and the rounding margin cannot hold it)."""
    n = P.shape[0]
    ci = np.empty((n, 3), np.int64)
    lo = np.zeros(3, np.int64)
    hi = np.zeros(3, np.int64)
    if n == 0:
        return False, ci, lo, hi
    for a in range(n):
        for j in range(3):
            c = np.floor(P[a, j] * inv_h)
            if not abs(c) < 2.0**28:  # (NaN and inf too)
                return False, ci, lo, hi
            k = int(c)
            ci[a, j] = k
            if a == 0 or k < lo[j]:
                lo[j] = k
            if a == 0 or k > hi[j]:
                hi[j] = k
    return True, ci, lo, hi


@nb.njit(cache=True)
def _dense_grid(ci: NDArray[np.int64], origin: NDArray[np.int64], dims: NDArray[np.int64],
                P: NDArray[np.float64]) -> tuple:
    """(order, starts, dense, points) of a grid over a dense table: points sorted by cell in key
    order, each cell's points in their original order (what a stable argsort of the packed keys
    gives), the first row of each occupied cell, each cell's run (-1: empty), and the rows of
    ``P`` in that order (``P[order]``, gathered here: numpy's fancy indexing of 900 rows cost
    ~11 us, a quarter of the whole constructor)."""
    n = ci.shape[0]
    dense = np.full(dims[0] * dims[1] * dims[2], -1, np.int32)
    flat = np.empty(n, np.int64)
    cell_flat = np.empty(n, np.int64)
    count = np.zeros(n, np.int64)
    m = 0
    for a in range(n):  # cells in order of first appearance
        f = ((ci[a, 0] - origin[0]) * dims[1] + (ci[a, 1] - origin[1])) * dims[2] + (ci[a, 2] - origin[2])
        flat[a] = f
        c = dense[f]
        if c < 0:
            c = m
            dense[f] = m
            cell_flat[m] = f
            m += 1
        count[c] += 1
    rank = np.argsort(cell_flat[:m])  # distinct values: cells in key order
    run_of = np.empty(m, np.int64)
    starts = np.empty(m + 1, np.int64)
    pos = 0
    for j in range(m):
        c = rank[j]
        run_of[c] = j
        starts[j] = pos
        pos += count[c]
        dense[cell_flat[c]] = j
    starts[m] = pos
    fill = starts[:m].copy()
    order = np.empty(n, np.int64)
    for a in range(n):  # stable within a cell
        j = dense[flat[a]]
        order[fill[j]] = a
        fill[j] += 1
    points = np.empty((n, 3))
    for i in range(n):
        a = order[i]
        points[i, 0] = P[a, 0]
        points[i, 1] = P[a, 1]
        points[i, 2] = P[a, 2]
    return order, starts, dense, points


@nb.njit(cache=True)
def _near_box(P: NDArray[np.float64], inv_v: float) -> tuple:
    """Low corner and dims of the 'near' bitmap: the voxels of the points, one voxel around."""
    lo = np.zeros(3, np.int64)
    hi = np.zeros(3, np.int64)
    for a in range(P.shape[0]):
        for j in range(3):
            k = int(np.floor(P[a, j] * inv_v))
            if a == 0 or k < lo[j]:
                lo[j] = k
            if a == 0 or k > hi[j]:
                hi[j] = k
    lo -= 1
    return lo, hi - lo + 2


@nb.njit(cache=True)
def _set_near_bits_of(P: NDArray[np.float64], inv_v: float, lo: NDArray[np.int64], dims: NDArray[np.int64],
                      bits: NDArray[np.uint8]) -> None:
    """:func:`_set_near_bits` of the points' voxels (relative to ``lo``), without the arrays.

    The three voxels z - 1, z, z + 1 of a column are consecutive bits: they are set as one
    3-bit mask over (at most) two bytes, 9 writes a point instead of 27 (the same bitmap). The
    second byte is written only when the mask reaches into it, i.e. holds a voxel of the box,
    so it never lies past the bitmap's end."""
    n1, n2 = dims[1], dims[2]
    px = py = pz = -2  # the previous point's voxel (none: no voxel is at -2)
    for a in range(P.shape[0]):
        x = int(np.floor(P[a, 0] * inv_v)) - lo[0]
        y = int(np.floor(P[a, 1] * inv_v)) - lo[1]
        z = int(np.floor(P[a, 2] * inv_v)) - lo[2]
        if x == px and y == py and z == pz:
            continue  # the same bits again (points in cell order share voxels)
        px, py, pz = x, y, z
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                f = ((x + dx) * n1 + (y + dy)) * n2 + (z - 1)
                word = 7 << (f & 7)
                i = f >> 3
                bits[i] |= np.uint8(word & 255)
                if word > 255:
                    bits[i + 1] |= np.uint8(word >> 8)


@nb.njit(cache=True)
def _grid_build(P: NDArray[np.float64], inv_h: float, dense_max: int) -> tuple:
    """What :class:`CellHash`'s constructor computes, in one compiled call (its numpy steps and
    the calls of :func:`_cells_of` and :func:`_dense_grid` cost more than the work on ~1,000
    points; a cold match builds nine grids): (status, origin, dims, cells, order, starts,
    dense, points). status 0: a cell is not representable or the box too large for the keys
    (no hash); 1: grid over a dense table; 2: more than ``dense_max`` cells (the caller hashes
    ``cells``, counted from ``origin``)."""
    ok, ci, lo, hi = _cells_of(P, inv_h)
    no_rows = np.zeros(0, np.int64)
    origin = lo - 1
    dims = hi - origin + 2
    if not ok or max(dims[0], dims[1], dims[2]) >= _GRID_LIM:
        return 0, origin, dims, ci, no_rows, no_rows, np.zeros(0, np.int32), np.zeros((0, 3))
    if float(dims[0]) * float(dims[1]) * float(dims[2]) <= dense_max:  # counting sort by cell
        order, starts, dense, points = _dense_grid(ci, origin, dims, P)
        return 1, origin, dims, ci, order, starts, dense, points
    return 2, origin, dims, ci, no_rows, no_rows, np.zeros(0, np.int32), np.zeros((0, 3))


@nb.njit(cache=True)
def _near_build(P: NDArray[np.float64], inv_v: float, max_bits: int) -> tuple:
    """(bits, low corner, dims) of :meth:`CellHash.near_bitmap` in one compiled call: the box of
    :func:`_near_box`, no bits when it has more than ``max_bits`` voxels, else the bitmap of
    :func:`_set_near_bits_of`."""
    lo, dims = _near_box(P, inv_v)
    if float(dims[0]) * float(dims[1]) * float(dims[2]) > max_bits:
        return np.zeros(0, np.uint8), lo, dims
    bits = np.zeros((dims[0] * dims[1] * dims[2] + 7) // 8, np.uint8)
    _set_near_bits_of(P, inv_v, lo, dims, bits)
    return bits, lo, dims


class CellHash:
    """Points of one cloud bucketed by cells of twice the radius (slightly more), found through
    a dense table over the cloud's box when that is small (<= ``_DENSE_MAX`` cells), else a hash.

    ``query(q)`` returns what ``cKDTree(points).query(q, k=1, distance_upper_bound=radius)[1]``
    returns, with -1 for "none within the radius" instead of ``len(points)``."""

    def __init__(self, points: NDArray[np.float64], radius: float) -> None:
        self.radius = float(radius)
        self._near: tuple | None = None
        self.h = 2.0 * self.radius * (1.0 + _GRID_MARGIN)
        self.inv_h = 1.0 / self.h
        P = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        # one compiled call: cells, box and (small boxes) the dense grid; coordinates that the
        # cell keys or the rounding margin cannot represent: no hash
        status, self.origin, self.dims, ci, self.order, self.starts, self.dense, self.points = _grid_build(
            P, self.inv_h, _DENSE_MAX)
        self.ok = status > 0
        if status == 1:
            self.tk, self.tv = np.zeros(0, np.int64), np.zeros(0, np.int64)
        elif status == 2:
            self._hashed(P, ci - self.origin)

    def _hashed(self, P: NDArray[np.float64], ci: NDArray[np.int64]) -> None:
        """The grid through a hash of the occupied cells (boxes too large for a dense table)."""
        key = (ci[:, 0] << (2 * _GRID_BITS)) | (ci[:, 1] << _GRID_BITS) | ci[:, 2]
        self.order = np.argsort(key, kind="stable")
        self.points = np.ascontiguousarray(P[self.order])  # cell by cell
        ks = key[self.order]
        first = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
        self.starts = np.r_[first, len(ks)].astype(np.int64)
        self.dense = np.zeros(0, np.int32)
        self.tk, self.tv = hash_table(ks[first])

    @classmethod
    def _reference(cls, points: NDArray[np.float64], radius: float, dense_max: int | None = None) -> CellHash:
        """numpy specification of the constructor (cells by a stable argsort of packed keys)."""
        self = cls.__new__(cls)
        self.radius = float(radius)
        self._near = None
        self.h = 2.0 * self.radius * (1.0 + _GRID_MARGIN)
        self.inv_h = 1.0 / self.h
        c = np.floor(points * self.inv_h)
        self.ok = bool(len(points) and np.all(np.isfinite(c)) and np.abs(c).max() < 2.0**28)
        if not self.ok:
            return self
        ci = c.astype(np.int64)
        self.origin = ci.min(axis=0) - 1
        ci -= self.origin
        self.dims = ci.max(axis=0) + 2
        if self.dims.max() >= _GRID_LIM:
            self.ok = False
            return self
        self._hashed(np.asarray(points, dtype=np.float64), ci)
        if np.prod(self.dims.astype(float)) <= (_DENSE_MAX if dense_max is None else dense_max):
            first = self.starts[:-1]
            cc = ci[self.order[first]]
            self.dense = np.full(int(np.prod(self.dims)), -1, np.int32)
            self.dense[(cc[:, 0] * self.dims[1] + cc[:, 1]) * self.dims[2] + cc[:, 2]] = np.arange(len(first))
            self.tk, self.tv = np.zeros(0, np.int64), np.zeros(0, np.int64)
        return self

    def _grid(self) -> tuple:
        """The arguments the kernels take for this grid (after the query points)."""
        return (self.points, self.h, self.inv_h, self.origin, self.dims, self.dense, self.tk, self.tv,
                self.starts, self.radius * self.radius)

    def query(self, q: NDArray[np.float64], nearest: bool = True) -> NDArray[np.int64]:
        """Index of the nearest point strictly within the radius (-1: none); ``nearest=False``:
        any point within the radius (enough to count explained points)."""
        q = np.ascontiguousarray(q, dtype=np.float64).reshape(-1, 3)
        out = np.empty(len(q), np.int64)
        g = self._grid()
        _grid_query(q, g[0], self.order, *g[1:], nearest, out)
        return out

    def hits(self, P: NDArray[np.float64], Ts: NDArray[np.float64], inverse: bool = False) -> NDArray[np.int64]:
        """(H,) how many rows of ``P`` moved by each of the (H, 4, 4) ``Ts`` (their inverses when
        ``inverse``) have a point of this cloud strictly within the radius: exact overlap counts
        of many hypotheses in one compiled call."""
        return _moved_hits(np.ascontiguousarray(P, dtype=np.float64), np.ascontiguousarray(Ts, dtype=np.float64),
                           inverse, *self._grid(), *self.near_bitmap())

    def near_bitmap(self) -> tuple:
        """(bits, low corner, dims, 1 / side) of a bitmap of voxels of side ``radius (1 + 1e-6)``:
        those within one voxel (27-neighbourhood) of a voxel holding a point. A point closer than
        the radius to q lies in a voxel next to q's (the 1e-6 margin is far above the rounding
        of voxel coordinates below 2^28), so a query outside the bitmap has no neighbour. Built
        on first use; empty (every query searched) when the box has more than ``NEAR_BITS`` voxels."""
        if self._near is None:
            inv_v = 1.0 / (self.radius * (1.0 + 1e-6))
            self._near = (*_near_build(self.points, inv_v, NEAR_BITS), inv_v)  # (empty bits: too large)
        return self._near

    def _near_bitmap_reference(self) -> tuple:
        """numpy specification of :meth:`near_bitmap` (a fresh bitmap, not cached)."""
        v = self.radius * (1.0 + 1e-6)
        base = np.floor(self.points * (1.0 / v)).astype(np.int64)
        lo = base.min(axis=0) - 1
        dims = base.max(axis=0) - lo + 2
        if float(np.prod(dims.astype(float))) > NEAR_BITS:
            return np.zeros(0, np.uint8), lo, dims, 1.0 / v
        bits = np.zeros((int(np.prod(dims)) + 7) // 8, np.uint8)
        _set_near_bits(np.ascontiguousarray(base - lo), dims, bits)
        return bits, lo, dims, 1.0 / v

    def align_step(self, P: NDArray[np.float64], T: NDArray[np.float64], min_pairs: int = 10) -> int:
        """One nearest-neighbour rigid alignment step of ``P`` (C-contiguous float64) onto this
        cloud within the radius, updating the 4 x 4 ``T`` (C-contiguous float64) in place; see
        :func:`_align_step`. Returns the number of pairs (``T`` unchanged below ``min_pairs``)."""
        return int(_align_step(P, T, *self._grid(), *self.near_bitmap(), min_pairs))
