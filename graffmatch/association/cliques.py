"""Several distinct greedy cliques of one consistency graph (hypothesis generation).

CLIPPER returns one densest clique; verification needs its rivals too (a street seen flipped by
180 degrees, a courtyard's symmetric twin). Greedy max-weight cliques grown from chosen starts
are cheap (about clique size x degree per start) and return every clique, not only the best.

Why not ``clipper.greedy_cliques``: that one serves the solver (it skips starts inside earlier
cliques, prunes by a bound and runs in float32), while verification grows from *every* start,
inside an ``allowed`` subset (the associations that disagree with the winner), and its decision
thresholds were calibrated on exactly these cliques (``bench/verification.py``).
"""

from __future__ import annotations

import numba as nb
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from graffmatch.association.clipper import _clique_objective, best_candidate


@nb.njit(cache=True, inline="always")
def _seed_candidates(indptr, indices, data, s, allowed, score, cand) -> int:
    """The allowed neighbours of start ``s`` as candidates (CSR order), each scored by its edge
    to ``s``; returns how many."""
    n_cand = 0
    for t in range(indptr[s], indptr[s + 1]):
        j = indices[t]
        if allowed[j]:
            score[j] = data[t]
            cand[n_cand] = j
            n_cand += 1
    return n_cand


@nb.njit(cache=True)
def _grow_cliques(indptr, indices, data, starts, allowed):
    """Grow one greedy clique per start inside ``allowed`` vertices; flat output + offsets."""
    m = indptr.shape[0] - 1
    score = np.zeros(m)
    is_nbr = np.zeros(m, dtype=np.bool_)
    nbr_w = np.zeros(m)
    cand = np.empty(m, dtype=np.int64)
    out = np.empty(0, dtype=np.int64)
    chunks = []
    for s in starts:
        if not allowed[s]:
            continue
        n_cand = _seed_candidates(indptr, indices, data, s, allowed, score, cand)
        clique = [s]
        while n_cand > 0:
            bi, _ = best_candidate(cand, n_cand, score)
            clique.append(bi)
            for t in range(indptr[bi], indptr[bi + 1]):
                is_nbr[indices[t]] = True
                nbr_w[indices[t]] = data[t]
            new_n = 0
            for c in range(n_cand):
                v = cand[c]
                if v != bi and is_nbr[v]:
                    score[v] += nbr_w[v]
                    cand[new_n] = v
                    new_n += 1
                else:
                    score[v] = 0.0
            for t in range(indptr[bi], indptr[bi + 1]):
                is_nbr[indices[t]] = False
            n_cand = new_n
        for c in range(n_cand):
            score[cand[c]] = 0.0
        chunks.append(np.array(clique, dtype=np.int64))
    n_total = 0
    for c in chunks:
        n_total += c.shape[0]
    out = np.empty(n_total, dtype=np.int64)
    offsets = np.zeros(len(chunks) + 1, dtype=np.int64)
    p = 0
    for i in range(len(chunks)):
        c = chunks[i]
        out[p : p + c.shape[0]] = c
        p += c.shape[0]
        offsets[i + 1] = p
    return out, offsets


@nb.njit(cache=True)
def _grow_cliques_dense(indptr, indices, data, starts, allowed):
    """:func:`_grow_cliques` with the graph also held as dense rows (built once): each step
    looks its candidates up in the chosen vertex's row instead of marking and unmarking that
    row's neighbours. Candidates start in CSR order and keep their order, scores add the same
    weights in the same order (a repeated entry: the last one, as there), so the cliques are the
    same. For graphs small enough for dense rows, grown from many starts (every vertex)."""
    m = indptr.shape[0] - 1
    adj = np.zeros((m, m), dtype=np.bool_)
    wd = np.zeros((m, m))
    for i in range(m):
        for t in range(indptr[i], indptr[i + 1]):
            adj[i, indices[t]] = True
            wd[i, indices[t]] = data[t]
    score = np.zeros(m)
    cand = np.empty(m + indptr[m], dtype=np.int64)  # (a repeated entry is a candidate twice)
    clique = np.empty(m + 1, dtype=np.int64)
    out = np.empty(len(starts) * 8, dtype=np.int64)
    offsets = np.zeros(len(starts) + 1, dtype=np.int64)
    n_out = 0
    n_cl = 0
    for s in starts:
        if not allowed[s]:
            continue
        n_cand = _seed_candidates(indptr, indices, data, s, allowed, score, cand)
        clique[0] = s
        size = 1
        while n_cand > 0:
            bi, _ = best_candidate(cand, n_cand, score)
            clique[size] = bi
            size += 1
            new_n = 0
            for c in range(n_cand):
                v = cand[c]
                if v != bi and adj[bi, v]:
                    score[v] += wd[bi, v]
                    cand[new_n] = v
                    new_n += 1
                else:
                    score[v] = 0.0
            n_cand = new_n
        for c in range(n_cand):
            score[cand[c]] = 0.0
        if n_out + size > len(out):
            grown = np.empty(2 * (n_out + size), dtype=np.int64)
            grown[:n_out] = out[:n_out]
            out = grown
        out[n_out:n_out + size] = clique[:size]
        n_out += size
        n_cl += 1
        offsets[n_cl] = n_out
    return out[:n_out], offsets[:n_cl + 1]


@nb.njit(cache=True)
def _sort_segments(flat, off):
    """Sort each segment ``flat[off[i]:off[i + 1]]`` in place."""
    for i in range(len(off) - 1):
        flat[off[i]:off[i + 1]] = np.sort(flat[off[i]:off[i + 1]])


_DENSE_GREEDY_MAX = 512  # graphs up to this many associations: dense rows (2 MB of weights at most)


def greedy_cliques(
    W: sp.csr_matrix, starts: NDArray[np.int64], allowed: NDArray[np.bool_] | None = None
) -> list[NDArray[np.int64]]:
    """One greedy max-weight clique per start (sorted vertex indices), restricted to
    ``allowed`` vertices; duplicates removed, order of first appearance kept."""
    m = W.shape[0]
    if m == 0 or len(starts) == 0:
        return []
    allowed = np.ones(m, dtype=np.bool_) if allowed is None else np.asarray(allowed, dtype=np.bool_)
    indptr, indices, data = _csr64(W)
    starts = np.asarray(starts, dtype=np.int64)
    grow = _grow_cliques_dense if m <= _DENSE_GREEDY_MAX and len(starts) >= 32 else _grow_cliques
    flat, off = grow(indptr, indices, data, starts, allowed)
    n = len(off) - 1
    _sort_segments(flat, off)  # each clique sorted, in one call
    buf = flat.tobytes()
    b = (off * flat.itemsize).tolist()
    lo = off.tolist()
    seen: set[bytes] = set()
    out = []
    for i in range(n):
        key = buf[b[i] : b[i + 1]]
        if key not in seen:
            seen.add(key)
            out.append(flat[lo[i] : lo[i + 1]])
    return out


def clique_objective(W: sp.csr_matrix, sel: NDArray[np.int64]) -> float:
    """Densest-clique objective of a binary selection: u^T (W + I) u / u^T u (no slicing)."""
    if len(sel) == 0:
        return 0.0
    indptr, indices, data = _csr64(W)
    return float(_clique_objective(indptr, indices, data, np.asarray(sel, np.int64), W.shape[0]))


def clique_objectives(W: sp.csr_matrix, cliques: list[NDArray[np.int64]]) -> NDArray[np.float64]:
    """:func:`clique_objective` of many selections in one compiled call (same arithmetic)."""
    if not cliques:
        return np.zeros(0)
    indptr, indices, data = _csr64(W)
    flat = np.concatenate([np.asarray(c, np.int64).reshape(-1) for c in cliques])
    off = np.zeros(len(cliques) + 1, np.int64)
    off[1:] = np.cumsum([len(c) for c in cliques])
    return _objectives(indptr, indices, data, flat, off, W.shape[0])


@nb.njit(cache=True)
def _objectives(indptr, indices, data, flat, off, m):
    out = np.zeros(len(off) - 1)
    for i in range(len(off) - 1):
        out[i] = _clique_objective(indptr, indices, data, flat[off[i]:off[i + 1]], m)
    return out


def _csr64(W: sp.csr_matrix) -> tuple[NDArray, NDArray, NDArray]:
    """(indptr, indices, data) for the kernels, without copies when they are int32/int64 and
    float32/float64: the kernels accumulate in float64 (a float32 weight converts exactly), so
    the results equal those on converted arrays. Verification calls the kernels dozens of times
    on one (float32, int32) graph; converting it on every call cost more than the kernels
    (W1: ~6 ms per match), and a converted copy of a W3 graph is ~700 MB."""
    ints, floats = (np.int32, np.int64), (np.float32, np.float64)
    indptr = W.indptr if W.indptr.dtype in ints else W.indptr.astype(np.int64)
    indices = W.indices if W.indices.dtype in ints else W.indices.astype(np.int64)
    data = W.data if W.data.dtype in floats else W.data.astype(np.float64)
    return indptr, indices, data
