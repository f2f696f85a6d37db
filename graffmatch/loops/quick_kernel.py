"""The quick check of one query against all its candidates in one compiled pass (numba).

The same computation as :func:`graffmatch.loops.quickcheck.quick_check_numpy` (hypotheses from
invariant-matched pairs, voting in (yaw, tx, ty) bins, inliers of the best bins), in the same
order, so that ties resolve the same way; a test compares the two on real landmark maps. It
exists because the NumPy version spends its ~1-4 ms a candidate in array overhead (dozens of
small temporaries, a sort of the vote keys), where the arithmetic is a few thousand flops.

Each scan's :class:`QuickIndex` is packed once into one float64 array (:func:`pack`): a header
of counts, then its BEV elements, its pair tables and their invariants sorted (the per-scan
part of every search). A query concatenates its candidates' packed arrays and calls
:func:`quick_scores`.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

HEADER = 8
HALF_SPAN = 256  # translation bins per side (the NumPy version's ``half``)


def pack(
    poles: NDArray, angle: NDArray, normal: NDArray, offset: NDArray, anchor: NDArray,
    pp: NDArray, pf: NDArray, ff: NDArray,
) -> NDArray[np.float64]:
    """One flat array of a scan's BEV index: header, elements, pair tables, sorted invariants."""
    pp_order = np.argsort(pp[:, 2], kind="stable")
    pf_order = np.argsort(pf[:, 2], kind="stable")
    ff_order = np.argsort(ff[:, 2], kind="stable")
    ffs_val = np.pi - ff[:, 2]
    ffs_order = np.argsort(ffs_val, kind="stable")
    head = np.zeros(HEADER)
    head[:5] = len(poles), len(angle), len(pp), len(pf), len(ff)
    parts = [
        head, poles.ravel(), angle, normal.ravel(), offset, anchor.ravel(),
        pp.ravel(), pp_order, pp[pp_order, 2],
        pf.ravel(), pf_order, pf[pf_order, 2],
        ff.ravel(), ff_order, ff[ff_order, 2], ffs_order, ffs_val[ffs_order],
    ]
    return np.ascontiguousarray(np.concatenate([np.asarray(p, np.float64).ravel() for p in parts]))


@nb.njit(cache=True, inline="always")
def _offsets(buf: NDArray, o: int) -> tuple:
    """Start of every section of the packed index at ``o`` (see :func:`pack`)."""
    n_p, n_f, n_pp, n_pf, n_ff = int(buf[o]), int(buf[o + 1]), int(buf[o + 2]), int(buf[o + 3]), int(buf[o + 4])
    poles = o + HEADER
    angle = poles + 2 * n_p
    normal = angle + n_f
    offset = normal + 2 * n_f
    anchor = offset + n_f
    pp = anchor + 2 * n_f
    pp_order = pp + 4 * n_pp
    pp_sorted = pp_order + n_pp
    pf = pp_sorted + n_pp
    pf_order = pf + 3 * n_pf
    pf_sorted = pf_order + n_pf
    ff = pf_sorted + n_pf
    ff_order = ff + 5 * n_ff
    ff_sorted = ff_order + n_ff
    ffs_order = ff_sorted + n_ff
    ffs_sorted = ffs_order + n_ff
    return (n_p, n_f, n_pp, n_pf, n_ff, poles, angle, normal, offset, anchor, pp, pp_order, pp_sorted,
            pf, pf_order, pf_sorted, ff, ff_order, ff_sorted, ffs_order, ffs_sorted)


_FIB = np.int64(-7046029254386353131)  # 2**64 / golden ratio, as a signed 64-bit integer


@nb.njit(cache=True, inline="always")
def _mod_2pi(t: float) -> float:
    """np.mod(t, 2 pi) exactly as NumPy computes it (npy_divmod: fmod, then into [0, 2 pi))."""
    two_pi = 2.0 * np.pi
    m = np.fmod(t, two_pi)
    if m < 0.0:
        m += two_pi
    return m


@nb.njit(cache=True, inline="always")
def _window(buf: NDArray, start: int, n: int, lo_v: float, hi_v: float) -> tuple[int, int]:
    """[lo, hi) of the sorted values buf[start:start+n] within [lo_v, hi_v] (searchsorted left/right)."""
    a, b = 0, n
    while a < b:
        m = (a + b) // 2
        if buf[start + m] < lo_v:
            a = m + 1
        else:
            b = m
    lo = a
    a, b = lo, n
    while a < b:
        m = (a + b) // 2
        if buf[start + m] <= hi_v:
            a = m + 1
        else:
            b = m
    return lo, a


@nb.njit(cache=True)
def _count_matches(x: NDArray, x_start: int, x_stride: int, n_x: int, y: NDArray, y_start: int, n_y: int,
                   tol: float) -> int:
    total = 0
    for a in range(n_x):
        v = x[x_start + a * x_stride]
        lo, hi = _window(y, y_start, n_y, v - tol, v + tol)
        total += hi - lo
    return total


@nb.njit(cache=True)
def _one(qb: NDArray, cb: NDArray, o: int, tol_m: float, tol_ang: float, yaw_bin: float, t_bin: float,
         top_bins: int, inlier_m: float, cos_inlier: float, anchor_m: float) -> tuple[int, float, float, float]:
    """Score and (yaw, tx, ty) of the query index ``qb`` (at 0) against the candidate at ``cb[o:]``."""
    (qn_p, qn_f, qn_pp, qn_pf, qn_ff, q_poles, q_angle, q_normal, q_offset, q_anchor, q_pp, _a, _b,
     q_pf, _c, _d, q_ff, _e, _f, _g, _h) = _offsets(qb, 0)
    (cn_p, cn_f, cn_pp, cn_pf, cn_ff, c_poles, c_angle, c_normal, c_offset, c_anchor, c_pp, c_pp_order,
     c_pp_sorted, c_pf, c_pf_order, c_pf_sorted, c_ff, c_ff_order, c_ff_sorted, c_ffs_order,
     c_ffs_sorted) = _offsets(cb, o)
    # hypotheses, in the NumPy version's order: pole pairs (flip 0, pi), pole-facade (flip 0, pi),
    # facade pairs (straight: flip 0, pi; swapped: flip 0, pi)
    m_pp = _count_matches(qb, q_pp + 2, 4, qn_pp, cb, c_pp_sorted, cn_pp, tol_m)
    m_pf = _count_matches(qb, q_pf + 2, 3, qn_pf, cb, c_pf_sorted, cn_pf, tol_m)
    m_ff = 0
    m_ffs = 0
    if qn_ff > 0 and cn_ff > 0:
        m_ff = _count_matches(qb, q_ff + 2, 5, qn_ff, cb, c_ff_sorted, cn_ff, tol_ang)
        m_ffs = _count_matches(qb, q_ff + 2, 5, qn_ff, cb, c_ffs_sorted, cn_ff, tol_ang)
    H = 2 * (m_pp + m_pf + m_ff + m_ffs)
    if H == 0:
        return 0, 0.0, 0.0, 0.0
    th = np.empty(H)  # yaw in [0, 2 pi)
    yb = np.empty(H, np.int64)  # its vote bin
    tx = np.empty(H)
    ty = np.empty(H)
    # yaw of a pole-facade or facade-pair hypothesis = candidate facade angle - query facade angle
    # (+ pi): its cos/sin and bin once per facade pair and flip, not per hypothesis (same values)
    nf1, cf1 = max(qn_f, 1), max(cn_f, 1)
    fcos = np.empty((2, nf1, cf1))
    fsin = np.empty((2, nf1, cf1))
    fth = np.empty((2, nf1, cf1))
    fyb = np.empty((2, nf1, cf1), np.int64)
    for flip_k in range(2):
        flip = 0.0 if flip_k == 0 else np.pi
        for k in range(qn_f):
            for kk in range(cn_f):
                t = (cb[c_angle + kk] - qb[q_angle + k]) + flip
                fcos[flip_k, k, kk] = np.cos(t)
                fsin[flip_k, k, kk] = np.sin(t)
                tm = _mod_2pi(t)
                fth[flip_k, k, kk] = tm
                fyb[flip_k, k, kk] = np.int64(np.floor(tm / yaw_bin))
    h = 0
    for flip_k in range(2):
        flip = 0.0 if flip_k == 0 else np.pi
        for a in range(qn_pp):
            r = q_pp + 4 * a
            v = qb[r + 2]
            lo, hi = _window(cb, c_pp_sorted, cn_pp, v - tol_m, v + tol_m)
            qi = int(qb[r])
            sx, sy = qb[q_poles + 2 * qi], qb[q_poles + 2 * qi + 1]
            for s in range(lo, hi):
                b = int(cb[c_pp_order + s])
                rb = c_pp + 4 * b
                t = cb[rb + 3] + flip - qb[r + 3]
                ci = int(cb[rb]) if flip_k == 0 else int(cb[rb + 1])
                c, sn = np.cos(t), np.sin(t)
                tm = _mod_2pi(t)
                th[h] = tm
                yb[h] = np.int64(np.floor(tm / yaw_bin))
                tx[h] = cb[c_poles + 2 * ci] - (c * sx - sn * sy)
                ty[h] = cb[c_poles + 2 * ci + 1] - (sn * sx + c * sy)
                h += 1
    # pole + facade: the base angle does not depend on the flip, the order is flip-major
    for flip_k in range(2):
        flip = 0.0 if flip_k == 0 else np.pi
        for a in range(qn_pf):
            r = q_pf + 3 * a
            v = qb[r + 2]
            lo, hi = _window(cb, c_pf_sorted, cn_pf, v - tol_m, v + tol_m)
            qi = int(qb[r])
            qk = int(qb[r + 1])
            sx, sy = qb[q_poles + 2 * qi], qb[q_poles + 2 * qi + 1]
            for s in range(lo, hi):
                b = int(cb[c_pf_order + s])
                rb = c_pf + 3 * b
                ck = int(cb[rb + 1])
                ci = int(cb[rb])
                c, sn = fcos[flip_k, qk, ck], fsin[flip_k, qk, ck]
                th[h] = fth[flip_k, qk, ck]
                yb[h] = fyb[flip_k, qk, ck]
                tx[h] = cb[c_poles + 2 * ci] - (c * sx - sn * sy)
                ty[h] = cb[c_poles + 2 * ci + 1] - (sn * sx + c * sy)
                h += 1
    if qn_ff > 0 and cn_ff > 0:
        for swap in range(2):
            srt = c_ffs_sorted if swap == 1 else c_ff_sorted
            odr = c_ffs_order if swap == 1 else c_ff_order
            for flip_k in range(2):
                flip = 0.0 if flip_k == 0 else np.pi
                for a in range(qn_ff):
                    r = q_ff + 5 * a
                    v = qb[r + 2]
                    lo, hi = _window(cb, srt, cn_ff, v - tol_ang, v + tol_ang)
                    qk = int(qb[r])
                    sx, sy = qb[r + 3], qb[r + 4]
                    for s in range(lo, hi):
                        b = int(cb[odr + s])
                        rb = c_ff + 5 * b
                        first = int(cb[rb + 1]) if swap == 1 else int(cb[rb])
                        c, sn = fcos[flip_k, qk, first], fsin[flip_k, qk, first]
                        th[h] = fth[flip_k, qk, first]
                        yb[h] = fyb[flip_k, qk, first]
                        tx[h] = cb[rb + 3] - (c * sx - sn * sy)
                        ty[h] = cb[rb + 4] - (sn * sx + c * sy)
                        h += 1
    # count the votes of each (yaw, tx, ty) key in a hash table (open addressing); a bin's first
    # hypothesis is the one that created its entry
    span = 2 * HALF_SPAN
    size = 16
    while size < 2 * H:
        size *= 2
    mask = size - 1
    slot_key = np.full(size, -1, np.int64)
    slot_cnt = np.zeros(size, np.int32)
    slot_first = np.zeros(size, np.int32)
    for k in range(H):
        bx = min(max(np.int64(np.floor(tx[k] / t_bin)) + HALF_SPAN, 0), span - 1)
        by = min(max(np.int64(np.floor(ty[k] / t_bin)) + HALF_SPAN, 0), span - 1)
        key = (yb[k] * span + bx) * span + by
        i = ((key * _FIB) >> 20) & mask  # Fibonacci hashing (the product wraps in int64)
        while slot_key[i] != -1 and slot_key[i] != key:
            i = (i + 1) & mask
        if slot_key[i] == -1:
            slot_key[i] = key
            slot_first[i] = k
        slot_cnt[i] += 1
    n_runs = 0
    for i in range(size):
        if slot_key[i] != -1:
            n_runs += 1
    ukey = np.empty(n_runs, np.int64)
    cnt = np.empty(n_runs, np.int64)
    first = np.empty(n_runs, np.int64)
    u = 0
    for i in range(size):
        if slot_key[i] != -1:
            ukey[u], cnt[u], first[u] = slot_key[i], slot_cnt[i], slot_first[i]
            u += 1
    # the best bins: largest count, ties to the smaller key (a stable sort of -count)
    n_best = min(top_bins, n_runs)
    taken = np.zeros(n_runs, np.bool_)
    best_score, best_h = -1, 0
    for _ in range(n_best):
        bi, bc, bk = -1, -1, 0
        for k in range(n_runs):
            if not taken[k] and (cnt[k] > bc or (cnt[k] == bc and ukey[k] < bk)):
                bi, bc, bk = k, cnt[k], ukey[k]
        taken[bi] = True
        hh = first[bi]
        c, sn = np.cos(th[hh]), np.sin(th[hh])
        score = 0
        if qn_p > 0 and cn_p > 0:
            for i in range(qn_p):
                px, py = qb[q_poles + 2 * i], qb[q_poles + 2 * i + 1]
                x = c * px - sn * py + tx[hh]
                y = sn * px + c * py + ty[hh]
                for j in range(cn_p):
                    dx = x - cb[c_poles + 2 * j]
                    dy = y - cb[c_poles + 2 * j + 1]
                    if dx * dx + dy * dy < inlier_m * inlier_m:
                        score += 1
                        break
        if qn_f > 0 and cn_f > 0:
            for i in range(qn_f):
                nx0, ny0 = qb[q_normal + 2 * i], qb[q_normal + 2 * i + 1]
                nx = c * nx0 - sn * ny0
                ny = sn * nx0 + c * ny0
                cq = qb[q_offset + i] + (nx * tx[hh] + ny * ty[hh])
                ax0, ay0 = qb[q_anchor + 2 * i], qb[q_anchor + 2 * i + 1]
                ax = c * ax0 - sn * ay0 + tx[hh]
                ay = sn * ax0 + c * ay0 + ty[hh]
                for j in range(cn_f):
                    dot = nx * cb[c_normal + 2 * j] + ny * cb[c_normal + 2 * j + 1]
                    if abs(dot) <= cos_inlier:
                        continue
                    sg = 1.0 if dot > 0 else (-1.0 if dot < 0 else 0.0)
                    if abs(cq - sg * cb[c_offset + j]) >= inlier_m:
                        continue
                    dx = ax - cb[c_anchor + 2 * j]
                    dy = ay - cb[c_anchor + 2 * j + 1]
                    if dx * dx + dy * dy < anchor_m * anchor_m:
                        score += 1
                        break
        if score > best_score:
            best_score, best_h = score, hh
    return best_score, th[best_h], tx[best_h], ty[best_h]


@nb.njit(cache=True)
def _scores(qb: NDArray, cb: NDArray, starts: NDArray, tol_m: float, tol_ang: float, yaw_bin: float,
            t_bin: float, top_bins: int, inlier_m: float, cos_inlier: float, anchor_m: float,
            ) -> tuple[NDArray, NDArray]:
    n = len(starts)
    score = np.zeros(n, np.int64)
    est = np.zeros((n, 3))
    for k in range(n):
        s, a, x, y = _one(qb, cb, starts[k], tol_m, tol_ang, yaw_bin, t_bin, top_bins, inlier_m, cos_inlier,
                          anchor_m)
        score[k] = s
        est[k, 0], est[k, 1], est[k, 2] = a, x, y
    return score, est


def quick_scores(
    query: NDArray, candidates: list[NDArray], tol_m: float, tol_deg: float, yaw_bin_deg: float, t_bin_m: float,
    top_bins: int, inlier_m: float, inlier_deg: float, anchor_m: float,
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """(inliers (C,), (yaw, tx, ty) (C, 3)) of a packed query index against packed candidates."""
    if not candidates:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    sizes = np.array([len(c) for c in candidates], np.int64)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    return _scores(
        query, np.concatenate(candidates), starts, float(tol_m), float(np.radians(tol_deg)),
        float(np.radians(yaw_bin_deg)), float(t_bin_m), int(top_bins), float(inlier_m),
        float(np.cos(np.radians(inlier_deg))), float(anchor_m),
    )
