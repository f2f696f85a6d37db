"""The sparse consistency graph over putative associations (paper, Sec. "Consistency Graph").

Vertices are associations u = (a, b). Two associations u = (a, b), v = (a', b') are consistent
if ``c = |D_i[a, a'] - D_j[b, b']| < epsilon``; the edge weight is ``exp(-c^2 / (2 sigma^2))``.
The graph is one-to-one: no edge when a == a' or b == b'.

Every consistency comes from the two intra-scan matrices (computed once per scan, O(n^2)); no
distance is ever computed per association pair. For all-to-all associations the edges are found
per source landmark pair (a, a') by a binary search in the sorted target pair distances of the
same type combination, so the work is proportional to the number of edges, and the graph is
written straight into a symmetric CSR matrix. No dense m x m matrix is allocated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from graffmatch.association.putative import all_to_all, check_associations
from graffmatch.errors import InvalidInputError


@dataclass
class ConsistencyGraph:
    """Weighted consistency graph. ``weights`` is symmetric CSR (m x m) with a zero diagonal."""

    associations: NDArray[np.int64]
    weights: sp.csr_matrix

    @property
    def m(self) -> int:
        return int(self.associations.shape[0])

    @property
    def n_edges(self) -> int:
        return int(self.weights.nnz // 2)

    @property
    def density(self) -> float:
        m = self.m
        return 0.0 if m < 2 else 2.0 * self.n_edges / (m * (m - 1))

    def __repr__(self) -> str:
        return f"ConsistencyGraph(m={self.m}, edges={self.n_edges}, density={self.density:.4f})"


@nb.njit(cache=True)
def _sorted_pair_tables(D_j, types_j, n_types):
    """Target ordered pairs (b, b'), b != b', grouped by (type b, type b') and sorted by distance.

    Returns (values, b, b2, group_start) with group g = t1 * n_types + t2."""
    n = D_j.shape[0]
    n_groups = n_types * n_types
    counts = np.zeros(n_groups + 1, dtype=np.int64)
    for b in range(n):
        for b2 in range(n):
            if b != b2:
                counts[types_j[b] * n_types + types_j[b2] + 1] += 1
    start = np.cumsum(counts)
    total = start[-1]
    vals = np.empty(total)
    bs = np.empty(total, dtype=np.int64)
    b2s = np.empty(total, dtype=np.int64)
    fill = start[:-1].copy()
    for b in range(n):
        for b2 in range(n):
            if b != b2:
                g = types_j[b] * n_types + types_j[b2]
                k = fill[g]
                vals[k] = D_j[b, b2]
                bs[k] = b
                b2s[k] = b2
                fill[g] += 1
    for g in range(n_groups):
        lo, hi = start[g], start[g + 1]
        order = np.argsort(vals[lo:hi], kind="mergesort")
        vals[lo:hi] = vals[lo:hi][order]
        bs[lo:hi] = bs[lo:hi][order]
        b2s[lo:hi] = b2s[lo:hi][order]
    return vals, bs, b2s, start


@nb.njit(cache=True)
def _edges_pass(D_i, types_i, vals, bs, b2s, start, lookup, epsilon, inv_two_sigma2, n_types,
                fill, deg, indices, data, cursor):
    """One sweep over the source landmark pairs and their target windows.

    First sweep (``fill`` False) counts each vertex's degree into ``deg``; second sweep writes
    both directions of every edge at ``cursor`` (the row starts)."""
    n_i = D_i.shape[0]
    for a in range(n_i):
        for a2 in range(a + 1, n_i):
            g = types_i[a] * n_types + types_i[a2]
            lo, hi = start[g], start[g + 1]
            if lo == hi:
                continue
            d = D_i[a, a2]
            k0 = lo + np.searchsorted(vals[lo:hi], d - epsilon, side="right")
            k1 = lo + np.searchsorted(vals[lo:hi], d + epsilon, side="left")
            for k in range(k0, k1):
                u = lookup[a, bs[k]]
                v = lookup[a2, b2s[k]]
                if u < 0 or v < 0:
                    continue
                if not fill:
                    deg[u + 1] += 1
                    deg[v + 1] += 1
                    continue
                c = d - vals[k]
                w = np.exp(-c * c * inv_two_sigma2)
                indices[cursor[u]] = v
                data[cursor[u]] = w
                cursor[u] += 1
                indices[cursor[v]] = u
                data[cursor[v]] = w
                cursor[v] += 1


@nb.njit(cache=True)
def _build_all_to_all(D_i, D_j, types_i, types_j, lookup, m, epsilon, inv_two_sigma2, n_types):
    vals, bs, b2s, start = _sorted_pair_tables(D_j, types_j, n_types)
    deg = np.zeros(m + 1, dtype=np.int64)
    no_idx = np.empty(0, dtype=np.int32)
    no_dat = np.empty(0)
    _edges_pass(D_i, types_i, vals, bs, b2s, start, lookup, epsilon, inv_two_sigma2, n_types,
                False, deg, no_idx, no_dat, deg)
    indptr = np.cumsum(deg)
    indices = np.empty(indptr[-1], dtype=np.int32)
    data = np.empty(indptr[-1])
    cursor = indptr[:-1].copy()
    _edges_pass(D_i, types_i, vals, bs, b2s, start, lookup, epsilon, inv_two_sigma2, n_types,
                True, deg, indices, data, cursor)
    return indptr, indices, data


@nb.njit(cache=True)
def _build_explicit(D_i, D_j, assoc, epsilon, inv_two_sigma2):
    """O(m^2) construction for explicit (typically short) association lists."""
    m = assoc.shape[0]
    deg = np.zeros(m + 1, dtype=np.int64)
    for u in range(m):
        a, b = assoc[u, 0], assoc[u, 1]
        for v in range(u + 1, m):
            a2, b2 = assoc[v, 0], assoc[v, 1]
            if a == a2 or b == b2:
                continue
            if abs(D_i[a, a2] - D_j[b, b2]) < epsilon:
                deg[u + 1] += 1
                deg[v + 1] += 1
    indptr = np.cumsum(deg)
    indices = np.empty(indptr[-1], dtype=np.int32)
    data = np.empty(indptr[-1])
    fill = indptr[:-1].copy()
    for u in range(m):
        a, b = assoc[u, 0], assoc[u, 1]
        for v in range(u + 1, m):
            a2, b2 = assoc[v, 0], assoc[v, 1]
            if a == a2 or b == b2:
                continue
            c = D_i[a, a2] - D_j[b, b2]
            if abs(c) < epsilon:
                w = np.exp(-c * c * inv_two_sigma2)
                indices[fill[u]] = v
                data[fill[u]] = w
                fill[u] += 1
                indices[fill[v]] = u
                data[fill[v]] = w
                fill[v] += 1
    return indptr, indices, data


def build_consistency_graph(
    D_i: ArrayLike,
    D_j: ArrayLike,
    associations: ArrayLike | None = None,
    epsilon: float = 0.2,
    sigma: float = 0.05,
    types_i: ArrayLike | None = None,
    types_j: ArrayLike | None = None,
) -> ConsistencyGraph:
    """Build the weighted consistency graph from the two intra-scan distance matrices.

    Either pass ``associations`` (m, 2) explicitly, or pass ``types_i``/``types_j`` to use all
    same-type associations (the paper's default, with the fast sorted construction).
    """
    D_i = np.ascontiguousarray(D_i, dtype=np.float64)
    D_j = np.ascontiguousarray(D_j, dtype=np.float64)
    for name, D in (("D_i", D_i), ("D_j", D_j)):
        if D.ndim != 2 or D.shape[0] != D.shape[1]:
            raise InvalidInputError(f"{name} must be a square matrix, got {D.shape}")
        if not np.all(np.isfinite(D)):
            raise InvalidInputError(f"{name} contains NaN or Inf")
    if not (epsilon > 0 and sigma > 0):
        raise InvalidInputError("epsilon and sigma must be positive")
    n_i, n_j = D_i.shape[0], D_j.shape[0]
    inv2s2 = 1.0 / (2.0 * sigma * sigma)
    if associations is None:
        if types_i is None or types_j is None:
            raise InvalidInputError("pass associations or the landmark types of both sets")
        ti = np.asarray(types_i, dtype=np.int64).reshape(-1)
        tj = np.asarray(types_j, dtype=np.int64).reshape(-1)
        if ti.shape[0] != n_i or tj.shape[0] != n_j:
            raise InvalidInputError("types must have one entry per row of D")
        assoc = all_to_all(ti, tj)
        m = assoc.shape[0]
        lookup = np.full((n_i, n_j), -1, dtype=np.int64)
        lookup[assoc[:, 0], assoc[:, 1]] = np.arange(m)
        n_types = int(max(ti.max(initial=0), tj.max(initial=0))) + 1
        indptr, indices, data = _build_all_to_all(
            D_i, D_j, ti, tj, lookup, m, float(epsilon), inv2s2, n_types
        )
    else:
        assoc = check_associations(associations, n_i, n_j)
        m = assoc.shape[0]
        indptr, indices, data = _build_explicit(D_i, D_j, assoc, float(epsilon), inv2s2)
    W = sp.csr_matrix((data, indices, indptr), shape=(m, m))
    return ConsistencyGraph(assoc, W)
