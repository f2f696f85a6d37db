"""The sparse consistency graph over putative associations (paper, Sec. "Consistency Graph").

Vertices are associations u = (a, b). Two associations u = (a, b), v = (a', b') are consistent
if ``c = |D_i[a, a'] - D_j[b, b']| < epsilon``; the edge weight is ``exp(-c^2 / (2 sigma^2))``.
The graph is one-to-one: no edge when a == a' or b == b'.

Every consistency comes from the two intra-scan matrices (computed once per scan, O(n^2)); no
distance is ever computed per association pair. Row u = (a, b) of the graph is found by a binary
search, per other source landmark a', in b's distances to the target landmarks of a''s type,
sorted once per scan, so the work is proportional to the edges (plus m x n_i searches), and each
row is written once, in order, straight into the symmetric CSR arrays. An explicit association
list (a subset, e.g. gated associations) takes the same path through a lookup table. No dense
m x m matrix is allocated.

The module runs past 600 lines on purpose: the window search (which target pairs lie within
epsilon of a row), the weights and the two-pass CSR fill read the same group-sorted tables and
the same window layout, and their choice between per-row and stored windows is one decision in
``_build``. ``bench/association_ab.py`` also loads an older version of this one file next to the
current one for its in-process A/B, so the whole graph build stays in one file.
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
    """Weighted consistency graph as symmetric CSR arrays (m x m, zero diagonal).

    ``indices`` are uint16 when m <= 65,536 (else int32) and ``data`` float32 by default:
    6 bytes per stored non-zero instead of scipy's 8 (int32 + float32), i.e. 259 instead of
    345 MB at W3 (43 M non-zeros), and a quarter less memory traffic per solver mat-vec.
    :func:`~graffmatch.association.clipper.solve_clipper` takes the graph itself; ``weights``
    is the scipy view for everything else."""

    associations: NDArray[np.int64]
    indptr: NDArray[np.int64]
    indices: NDArray[np.integer]
    data: NDArray[np.floating]
    # Row sums of ``data``, set only by :func:`build_consistency_graph`, whose weights are in
    # (0, 1] with no diagonal by construction: the solver then skips its validation pass.
    weighted_degrees: NDArray[np.float64] | None = None
    # The largest stored weight (0 without edges), also from the build: the greedy cliques'
    # bound needs it, and numpy's max over W2's 2.5 M weights costs ~0.4 ms.
    max_weight: float | None = None

    @property
    def m(self) -> int:
        return int(self.associations.shape[0])

    @property
    def n_edges(self) -> int:
        return int(self.data.shape[0] // 2)

    @property
    def density(self) -> float:
        m = self.m
        return 0.0 if m < 2 else 2.0 * self.n_edges / (m * (m - 1))

    @property
    def weights(self) -> sp.csr_matrix:
        """The graph as a scipy CSR matrix sharing ``data``. scipy keeps int32 indices only,
        so compact (uint16) indices are widened here once, in place: the graph then holds the
        int32 copy and drops the compact one (no second copy stays alive)."""
        if self.indices.dtype != np.int32 and self.indices.dtype != np.int64:
            self.indices = self.indices.astype(np.int32)
        m = self.m
        return sp.csr_matrix((self.data, self.indices, self.indptr), shape=(m, m))

    def __repr__(self) -> str:
        return f"ConsistencyGraph(m={self.m}, edges={self.n_edges}, density={self.density:.4f})"


@nb.njit(cache=True)
def _row_pair_tables(D_j, groups_j, n_groups):
    """For every target landmark b and group t: the b2 != b of group t sorted by D_j[b, b2]
    (stable, so ties stay in b2 order). Returns (values, b2, start) with the run of (b, t) at
    start[b, t]:start[b, t + 1]."""
    n = D_j.shape[0]
    gcount = np.zeros(n_groups, dtype=np.int64)
    for b2 in range(n):
        gcount[groups_j[b2]] += 1
    start = np.empty((n, n_groups + 1), dtype=np.int64)
    total = 0
    for b in range(n):
        for t in range(n_groups):
            start[b, t] = total
            total += gcount[t] - (groups_j[b] == t)
        start[b, n_groups] = total
    vals = np.empty(total)
    b2s = np.empty(total, dtype=np.int64)
    fill = np.empty(n_groups, dtype=np.int64)
    for b in range(n):
        for t in range(n_groups):
            fill[t] = start[b, t]
        for b2 in range(n):
            if b2 != b:
                k = fill[groups_j[b2]]
                vals[k] = D_j[b, b2]
                b2s[k] = b2
                fill[groups_j[b2]] = k + 1
        for t in range(n_groups):
            lo, hi = start[b, t], start[b, t + 1]
            order = np.argsort(vals[lo:hi], kind="mergesort")
            vals[lo:hi] = vals[lo:hi][order]
            b2s[lo:hi] = b2s[lo:hi][order]
    return vals, b2s, start


# Target runs up to this long are searched by counting (see :func:`_row_windows`), longer ones
# by merging: counting reads the whole run per source landmark, the merge ~2 entries.
_COUNT_MAX_RUN = 64


@nb.njit(cache=True)
def _row_windows(src_vals, src_a2s, src_start, vals, start, a, b, n_groups, epsilon, win0, win1):
    """For row u = (a, b): the run [win0[a2], win1[a2]) of target pairs (b, b2) whose distance
    is within epsilon of D_i[a, a2], for every a2 != a (np.searchsorted's 'right' of
    d - epsilon and 'left' of d + epsilon, i.e. the run's entries <= d - epsilon and
    < d + epsilon).

    A short run (<= _COUNT_MAX_RUN entries) is counted for every a2: a branch-free loop that
    vectorises, ~1 ms less than the merge at W2 (runs of 25-46). A long one is merged with the
    a2 of its group in ascending distance (``src_*``: :func:`_row_pair_tables` of the source),
    so both ends only move forward. Both give the same ends."""
    for t in range(n_groups):
        # slices, so that every index runs from 0 (no wrap-around select per access)
        lo = start[b, t]
        run = vals[lo:start[b, t + 1]]
        hi = run.shape[0]
        s_lo = src_start[a, t]
        s_vals = src_vals[s_lo:src_start[a, t + 1]]
        s_a2s = src_a2s[s_lo:src_start[a, t + 1]]
        if hi <= _COUNT_MAX_RUN:
            for s in range(s_vals.shape[0]):
                d = s_vals[s]
                x0 = d - epsilon
                x1 = d + epsilon
                c0 = 0
                c1 = 0
                for k in range(hi):
                    v = run[k]
                    c0 += v <= x0
                    c1 += v < x1
                win0[s_a2s[s]] = lo + c0
                win1[s_a2s[s]] = lo + c1
            continue
        k0 = 0
        k1 = 0
        for s in range(s_vals.shape[0]):
            d = s_vals[s]
            x0 = d - epsilon
            x1 = d + epsilon
            while k0 < hi and run[k0] <= x0:
                k0 += 1
            if k1 < k0:
                k1 = k0
            while k1 < hi and run[k1] < x1:
                k1 += 1
            win0[s_a2s[s]] = lo + k0
            win1[s_a2s[s]] = lo + k1


@nb.njit(cache=True)
def _query_windows(D_i, groups_i, groups_j, vals, start, n_groups, epsilon):
    """The windows of every same-group pair (a, b) at once, in query order: :func:`_row_windows`'
    ends for row (a, b) and source landmark a2 != a are ``win0[boff[b] + pos[a, a2]]`` and
    ``win1[...]`` (the same values).

    The distances D_i[a, a2] of each group pair (g, t) (a in g, a2 in t, a2 != a) are sorted
    once; each target b of group g merges that one list with its run of group t and writes the
    ends in list order (sequential writes). A pointer moves ~36 times over ~1,300 queries at W2
    (a predictable branch), where counting a run per row reads the whole run (~36 comparisons a
    query) and merging per row mispredicts about every other step. Returns
    (win0, win1, boff, pos) as int32 / int64."""
    n_i = D_i.shape[0]
    n_j = groups_j.shape[0]
    gsize = np.zeros(n_groups, dtype=np.int64)
    for a in range(n_i):
        gsize[groups_i[a]] += 1
    # the queries of group pair (g, t) at qstart[g, t]:qstart[g, t + 1], ascending distance;
    # group g's list starts at qstart[g, 0]
    qstart = np.zeros((n_groups, n_groups + 1), dtype=np.int64)
    total = 0
    for g in range(n_groups):
        for t in range(n_groups):
            qstart[g, t] = total
            total += gsize[g] * (gsize[t] - (g == t))
        qstart[g, n_groups] = total
    qd = np.empty(total)
    qpos = np.empty(total, dtype=np.int64)  # a * n_i + a2 of each query
    fill = qstart[:, :n_groups].copy()
    for a in range(n_i):
        g = groups_i[a]
        for a2 in range(n_i):
            if a2 != a:
                t = groups_i[a2]
                k = fill[g, t]
                qd[k] = D_i[a, a2]
                qpos[k] = a * n_i + a2
                fill[g, t] = k + 1
    pos = np.zeros((n_i, n_i), dtype=np.int64)
    for g in range(n_groups):
        for t in range(n_groups):
            lo, hi = qstart[g, t], qstart[g, t + 1]
            order = np.argsort(qd[lo:hi], kind="quicksort")
            qd[lo:hi] = qd[lo:hi][order]
            qpos[lo:hi] = qpos[lo:hi][order]
            for q in range(lo, hi):
                pa = qpos[q]
                pos[pa // n_i, pa % n_i] = q - qstart[g, 0]
    boff = np.empty(n_j + 1, dtype=np.int64)
    boff[0] = 0
    for b in range(n_j):
        g = groups_j[b]
        boff[b + 1] = boff[b] + qstart[g, n_groups] - qstart[g, 0]
    win0 = np.empty(boff[n_j], dtype=np.int32)
    win1 = np.empty(boff[n_j], dtype=np.int32)
    for b in range(n_j):
        g = groups_j[b]
        out = boff[b] - qstart[g, 0]
        for t in range(n_groups):
            lo = start[b, t]
            run = vals[lo:start[b, t + 1]]
            hi = run.shape[0]
            k0 = 0
            k1 = 0
            for q in range(qstart[g, t], qstart[g, t + 1]):
                d = qd[q]
                x0 = d - epsilon
                x1 = d + epsilon
                while k0 < hi and run[k0] <= x0:
                    k0 += 1
                if k1 < k0:
                    k1 = k0
                while k1 < hi and run[k1] < x1:
                    k1 += 1
                win0[out + q] = lo + k0
                win1[out + q] = lo + k1
    return win0, win1, boff, pos


@nb.njit(cache=True, fastmath=True)
def _exp_nonpositive(x, out, n, squarings):
    """out[:n] = exp(x[:n]) for -0.5 * 2**squarings <= x <= 0, branch-free so that it
    vectorises (numba's np.exp is a scalar libm call per edge: ~8 ns, 60 % of the fill).

    exp(x) = exp(x / 2**s)**(2**s): a degree-16 Taylor polynomial on [-0.5, 0] (truncation
    < 1e-18) and s squarings (relative error ~ 2**s * 1e-16: 2e-15 at the default s = 4, far
    below float32 rounding, so the stored float32 weights equal np.exp's but for values within
    1e-15 of a float32 rounding boundary)."""
    scale = 1.0 / 2.0 ** squarings
    for i in range(n):
        y = x[i] * scale
        p = 1.0 + y * (1.0 + y * (1.0 / 2 + y * (1.0 / 6 + y * (1.0 / 24 + y * (1.0 / 120 + y * (
            1.0 / 720 + y * (1.0 / 5040 + y * (1.0 / 40320 + y * (1.0 / 362880 + y * (
                1.0 / 3628800 + y * (1.0 / 39916800 + y * (1.0 / 479001600 + y * (
                    1.0 / 6227020800 + y * (1.0 / 87178291200 + y * (1.0 / 1307674368000 + y * (
                        1.0 / 20922789888000))))))))))))))))
        out[i] = p
    for _ in range(squarings):  # a loop of its own: the polynomial loop stays vectorisable
        for i in range(n):
            out[i] = out[i] * out[i]


def _squarings(epsilon: float, inv_two_sigma2: float) -> int:
    """Squarings for :func:`_exp_nonpositive` over the weights' arguments -c^2 / (2 sigma^2),
    |c| < epsilon."""
    x_min = epsilon * epsilon * inv_two_sigma2
    return max(0, int(np.ceil(np.log2(max(x_min, 1e-300) / 0.5))))


# Largest table of one row's windows per source landmark kept from the counting pass for the
# filling pass (m x n_i x 2 int32; 13 MB at W3) instead of merging the sorted runs twice; also the
# bound on it plus :func:`_query_windows`' table (the filling pass gathering from that one
# directly, without the row table, was ~1 ms slower at W2).
_MAX_WINDOW_TABLE_BYTES = 64 * 2**20
# Entries the affine fill writes per chunk of a window (2.5 M at W2: 10.3 -> 8.0 ms for the fill
# against a loop over each window's own length, the same values).
_CHUNK = 8


@nb.njit(cache=True)
def _fill_affine_row(a, d_row, win0, win1, row_base, col_k, vals_p, indices, pos, buf_x, inv_two_sigma2):
    """Row u = (a, b) of an affine layout (see :func:`_build`): for every a2 != a, its window's
    vertex ids ``row_base[a2] + col_k[k]`` into ``indices[pos:]`` and the weights' arguments
    -(D_i[a, a2] - D_j[b, b2])^2 / (2 sigma^2) into ``buf_x``. Returns the row's length.

    Whole chunks of _CHUNK into the padded buffers (the entries past a window are overwritten by
    the next one): the windows are short (~12 at W2), and a loop of fixed length compiles
    without a scalar remainder. The offsets are unsigned, so numba indexes without a wrap-around
    select per access (what the slices of the CSR kernels do, without four slices per chunk)."""
    n = 0
    for a2 in range(d_row.shape[0]):
        if a2 == a:
            continue
        d = d_row[a2]
        base = row_base[a2]
        k0 = win0[a2]
        cnt = win1[a2] - k0
        for t0 in range(0, cnt, _CHUNK):
            o = np.uint64(n + t0)
            q = np.uint64(k0 + t0)
            p = np.uint64(pos + n + t0)
            for t in range(_CHUNK):
                tt = np.uint64(t)
                indices[p + tt] = base + col_k[q + tt]
                c = d - vals_p[q + tt]
                buf_x[o + tt] = -c * c * inv_two_sigma2
        n += cnt
    return n


# A row of n float32 weights in [min, max] with 0 < min and max <= min / (n x this scale) sums
# exactly in float64 in any order (see :func:`_row_sum_any_order`).
_EXACT_SUM_SCALE = 2.0**-29


@nb.njit(cache=True, fastmath=True)
def _row_sum_any_order(w, bounds):
    """The sum of a row's float32 weights, reassociated (vectorised); their smallest and largest
    into ``bounds`` (a float32 pair).

    Why it still equals the sum in order (s = 0; s += w[t]), bit for bit, whenever
    0 < min <= max <= min 2**29 / n (n = len(w); the caller checks): every weight is a float32
    >= min >= 2**e with e = floor(log2(min)), so a multiple of q = 2**(e - 23); every partial
    sum, in any order, is a multiple of q of at most n max < 2**53 q (as 2**e > min / 2), so
    float64 holds it exactly and no addition rounds. At W2 (rows of ~900 weights in
    [3.4e-4, 1]) min may go down to 1.7e-6. The in-order sum waits on each addition's latency:
    ~1.6 of W2's 13 ms build. min and max are taken on the bits (for floats >= +0 their order
    is the integers'; a negative or NaN weight fails the caller's check), which vectorises where
    float min / max do not."""
    s = 0.0
    for t in range(w.shape[0]):
        s += w[t]
    bits = w.view(np.uint32)
    lo = np.uint32(0xFFFFFFFF)
    hi = np.uint32(0)
    for t in range(bits.shape[0]):
        b = bits[t]
        lo = min(lo, b)
        hi = max(hi, b)
    out = bounds.view(np.uint32)
    out[0] = lo
    out[1] = hi
    return s


@nb.njit(cache=True)
def _stored_windows(qwin0, qwin1, base, pos_a, a, win0, win1):
    """Row (a, b)'s windows from :func:`_query_windows`' table (``base`` = boff[b], ``pos_a`` =
    pos[a]); win0[a] = win1[a] = 0 (unused)."""
    for a2 in range(pos_a.shape[0]):
        k = base + pos_a[a2]
        ok = a2 != a
        win0[a2] = qwin0[k] if ok else 0
        win1[a2] = qwin1[k] if ok else 0


def _build(D_i, D_j, groups_i, groups_j, assoc, lookup, all_valid, epsilon, inv_two_sigma2, n_groups, weights,
           index, squarings, keep_windows, by_query, row_base, col_rank, exact_scale):
    """Symmetric CSR (indptr, indices, data) of the graph over the associations ``assoc``
    (``lookup[a, b]`` = vertex id or -1), with ``index``'s and ``weights``' dtypes (empty
    arrays), written row by row: row u = (a, b) takes, for every other source landmark a2 of
    group t, the window of b's sorted distances to group t within epsilon of D_i[a, a2]. Each
    row is written once, in order (no scattered writes); a first pass counts the row lengths
    (with ``all_valid``, every same-group pair is an association: the window sizes). With
    ``keep_windows`` the first pass stores every row's windows for the second (one merge of the
    sorted runs per row instead of two); with ``by_query`` too, the first pass takes them from
    one merge per target landmark and group (:func:`_query_windows`; for short runs). Also returns the weighted degrees (row sums of the
    stored weights, equal to the sum in order that
    :func:`~graffmatch.association.clipper.solve_clipper`'s validation pass does, see
    :func:`_row_sum_any_order`) and the largest weight (0 for no edges), so the solver need not
    read the graph once more for them. ``exact_scale``: :data:`_EXACT_SUM_SCALE` for float32
    weights, 0 for others (their rows are summed in order).

    Non-empty ``row_base`` / ``col_rank``: ``lookup[a2, b2] = row_base[a2] + col_rank[b2]`` for
    every same-group pair (all-to-all in :func:`all_to_all`'s order), so a vertex id is a
    sequential read along the sorted run plus a base instead of a dependent lookup.

    Two compiled passes (:func:`_count_rows`, :func:`_fill_rows`) with the CSR arrays allocated
    between them by numpy, which asks the kernel for huge pages on large arrays (madvise): at W3
    (43 M non-zeros, 258 MB) their page faults cost ~120 ms when allocated in compiled code
    (4 kB pages), ~35 ms this way."""
    state = _count_rows(D_i, D_j, groups_i, groups_j, assoc, lookup, all_valid, epsilon, n_groups,
                        keep_windows, by_query, row_base, col_rank)
    indptr = state[0]
    nnz = int(indptr[-1])
    indices = np.empty(nnz + _CHUNK, dtype=index.dtype)  # (+ a chunk: see the affine fill)
    data = np.empty(nnz, dtype=weights.dtype)
    wdeg, w_max = _fill_rows(D_i, assoc, lookup, epsilon, inv_two_sigma2, n_groups, squarings, keep_windows,
                             row_base, exact_scale, indices, data, *state)
    return indptr, indices[:nnz], data, wdeg, w_max


@nb.njit(cache=True)
def _count_rows(D_i, D_j, groups_i, groups_j, assoc, lookup, all_valid, epsilon, n_groups, keep_windows,
                by_query, row_base, col_rank):
    """:func:`_build`'s first pass: the sorted runs, each row's windows (into ``table`` with
    ``keep_windows``) and length. Returns (indptr, longest row, table, vals, b2s, start, col_k,
    vals_p, src_vals, src_a2s, src_start) for :func:`_fill_rows`."""
    m = assoc.shape[0]
    n_i = D_i.shape[0]
    vals, b2s, start = _row_pair_tables(D_j, groups_j, n_groups)
    affine = row_base.shape[0] > 0
    # padded by a chunk: the affine fill reads and writes whole chunks of _CHUNK (see below)
    col_k = np.zeros(b2s.shape[0] + _CHUNK if affine else 0, dtype=np.int64)
    for k in range(b2s.shape[0] if affine else 0):
        col_k[k] = col_rank[b2s[k]]
    vals_p = np.zeros(vals.shape[0] + _CHUNK)
    vals_p[: vals.shape[0]] = vals
    # the source's sorted runs serve the per-row merges only (none with a window table)
    src_vals, src_a2s, src_start = _row_pair_tables(D_i[:0, :0] if by_query else D_i, groups_i, n_groups)
    win0 = np.zeros(n_i, dtype=np.int64)
    win1 = np.zeros(n_i, dtype=np.int64)
    if by_query:
        qwin0, qwin1, boff, qpos = _query_windows(D_i, groups_i, groups_j, vals, start, n_groups, epsilon)
    else:
        qwin0 = qwin1 = np.zeros(0, dtype=np.int32)
        boff = np.zeros(0, dtype=np.int64)
        qpos = np.zeros((0, 0), dtype=np.int64)
    table = np.empty((m if keep_windows else 0, 2, n_i), dtype=np.int32)
    indptr = np.zeros(m + 1, dtype=np.int64)
    longest = 0
    for u in range(m):
        a, b = assoc[u, 0], assoc[u, 1]
        if by_query:
            _stored_windows(qwin0, qwin1, boff[b], qpos[a], a, win0, win1)
        else:
            _row_windows(src_vals, src_a2s, src_start, vals, start, a, b, n_groups, epsilon, win0, win1)
        if keep_windows:
            for a2 in range(n_i):
                table[u, 0, a2] = win0[a2]
                table[u, 1, a2] = win1[a2]
        c = 0
        for a2 in range(n_i):
            if a2 == a:
                continue
            if all_valid:
                c += win1[a2] - win0[a2]
            else:
                for k in range(win0[a2], win1[a2]):
                    c += lookup[a2, b2s[k]] >= 0
        indptr[u + 1] = indptr[u] + c
        longest = max(longest, c)
    return indptr, longest, table, vals, b2s, start, col_k, vals_p, src_vals, src_a2s, src_start


@nb.njit(cache=True)
def _fill_rows(D_i, assoc, lookup, epsilon, inv_two_sigma2, n_groups, squarings, keep_windows, row_base,
               exact_scale, indices, data, indptr, longest, table, vals, b2s, start, col_k, vals_p,
               src_vals, src_a2s, src_start):
    """:func:`_build`'s second pass: every row's ids and weights into ``indices`` / ``data`` (sized
    by :func:`_count_rows`); returns the weighted degrees and the largest weight."""
    m = assoc.shape[0]
    n_i = D_i.shape[0]
    affine = row_base.shape[0] > 0
    win0 = np.zeros(n_i, dtype=np.int64)
    win1 = np.zeros(n_i, dtype=np.int64)
    wdeg = np.zeros(m)
    w_max = 0.0
    bounds = np.zeros(2, dtype=np.float32)  # a row's smallest and largest weight
    buf_x = np.empty(longest + _CHUNK)
    buf_w = np.empty(longest)
    for u in range(m):
        a, b = assoc[u, 0], assoc[u, 1]
        if keep_windows:
            for a2 in range(n_i):
                win0[a2] = table[u, 0, a2]
                win1[a2] = table[u, 1, a2]
        else:
            _row_windows(src_vals, src_a2s, src_start, vals, start, a, b, n_groups, epsilon, win0, win1)
        pos = indptr[u]
        n = 0
        if affine:
            n = _fill_affine_row(a, D_i[a], win0, win1, row_base, col_k, vals_p, indices, pos, buf_x,
                                 inv_two_sigma2)
        for a2 in range(0 if affine else n_i):
            if a2 == a:
                continue
            d = D_i[a, a2]
            for k in range(win0[a2], win1[a2]):
                v = lookup[a2, b2s[k]]
                if v < 0:
                    continue
                indices[pos + n] = v
                c = d - vals[k]
                buf_x[n] = -c * c * inv_two_sigma2
                n += 1
        # the row's weights in one branch-free (vectorised) loop
        _exp_nonpositive(buf_x, buf_w, n, squarings)
        row_w = data[pos:pos + n]
        for t in range(n):
            row_w[t] = buf_w[t]
        s = 0.0
        hi = 0.0
        exact = False
        if exact_scale > 0.0 and n:  # float32 weights
            s = _row_sum_any_order(row_w, bounds)
            lo, hi = np.float64(bounds[0]), np.float64(bounds[1])
            exact = lo > 0.0 and hi >= lo and lo >= n * hi * exact_scale
        if not exact:
            s = 0.0  # the sum may round: add in order, as the solver's validation pass does
            hi = 0.0
            for t in range(n):
                s += row_w[t]
                hi = max(hi, np.float64(row_w[t]))
        wdeg[u] = s
        w_max = max(w_max, hi)
    return wdeg, w_max


@nb.njit(cache=True)
def _affine_layout(lookup, gi, gj, n_groups):
    """:func:`_affine_ids` compiled (one pass over the n_i x n_j table instead of ~20 numpy
    temporaries: ~60 us of a 6 ms W1 match). Returns (ok, row_base, col_rank)."""
    n_i, n_j = gi.shape[0], gj.shape[0]
    col_rank = np.zeros(n_j, dtype=np.int64)
    first_b = np.full(n_groups, -1, dtype=np.int64)
    count = np.zeros(n_groups, dtype=np.int64)
    for b in range(n_j):
        t = gj[b]
        col_rank[b] = count[t]
        count[t] += 1
        if first_b[t] < 0:
            first_b[t] = b
    row_base = np.zeros(n_i, dtype=np.int64)
    for a in range(n_i):
        fb = first_b[gi[a]]
        if fb >= 0:
            row_base[a] = lookup[a, fb]
    for a in range(n_i):
        for b in range(n_j):
            if gi[a] == gj[b] and row_base[a] + col_rank[b] != lookup[a, b]:
                return False, row_base, col_rank
    return True, row_base, col_rank


def _affine_ids(lookup: NDArray, gi: NDArray[np.int64], gj: NDArray[np.int64]
                ) -> tuple[NDArray[np.int64], NDArray[np.int64]] | tuple[None, None]:
    """(row_base, col_rank) with ``lookup[a, b] = row_base[a] + col_rank[b]`` for every
    same-group pair (col_rank: b's rank within its group), or (None, None) when the vertex
    ids are not laid out that way (e.g. an explicit list in another order)."""
    n_groups = int(max(gi.max(initial=0), gj.max(initial=0))) + 1
    ok, row_base, col_rank = _affine_layout(lookup, np.ascontiguousarray(gi, dtype=np.int64),
                                            np.ascontiguousarray(gj, dtype=np.int64), n_groups)
    return (row_base, col_rank) if ok else (None, None)


def _window_table_entries(gi: NDArray[np.int64], gj: NDArray[np.int64], n_i: int) -> int:
    """Entries of :func:`_query_windows`' table: per target b of group g, one per source pair
    (a, a2 != a) with a in g."""
    n_groups = int(max(gi.max(initial=0), gj.max(initial=0))) + 1
    ci, cj = np.bincount(gi, minlength=n_groups), np.bincount(gj, minlength=n_groups)
    return int(np.sum(cj * ci * (n_i - 1)))


def build_consistency_graph(
    D_i: ArrayLike,
    D_j: ArrayLike,
    associations: ArrayLike | None = None,
    epsilon: float = 0.2,
    sigma: float = 0.05,
    types_i: ArrayLike | None = None,
    types_j: ArrayLike | None = None,
    dtype: type = np.float32,
    compact: bool = True,
) -> ConsistencyGraph:
    """Build the weighted consistency graph from the two intra-scan distance matrices.

    Either pass ``associations`` (m, 2) explicitly (e.g. gated ones), or pass ``types_i``/
    ``types_j`` to use all same-type associations (the paper's default). Both take the same
    sorted construction; with the types given and every association within one type, target
    pairs are windowed per type pair. ``dtype`` of the weights: float32 (default) halves the
    graph's memory and the solver's traffic; the weights' relative error is 6e-8. ``compact``:
    uint16 column indices when m <= 65,536 (see :class:`ConsistencyGraph`); False: int32.
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
    ti = tj = None
    if types_i is not None and types_j is not None:
        ti = np.asarray(types_i, dtype=np.int64).reshape(-1)
        tj = np.asarray(types_j, dtype=np.int64).reshape(-1)
        if ti.shape[0] != n_i or tj.shape[0] != n_j:
            raise InvalidInputError("types must have one entry per row of D")
    if associations is None:
        if ti is None or tj is None:
            raise InvalidInputError("pass associations or the landmark types of both sets")
        assoc = all_to_all(ti, tj)
    else:
        assoc = check_associations(associations, n_i, n_j)
    m = assoc.shape[0]
    if ti is not None and tj is not None and np.all(ti[assoc[:, 0]] == tj[assoc[:, 1]]):
        gi, gj = ti, tj  # same-type associations: one sorted window per type pair
    else:
        gi, gj = np.zeros(n_i, dtype=np.int64), np.zeros(n_j, dtype=np.int64)
    lo = int(min(gi.min(initial=0), gj.min(initial=0)))
    gi, gj = gi - lo, gj - lo
    n_groups = int(max(gi.max(initial=0), gj.max(initial=0))) + 1
    lookup = np.full((n_i, n_j), -1, dtype=np.int32 if m < 2**31 else np.int64)
    lookup[assoc[:, 0], assoc[:, 1]] = np.arange(m)
    index = np.empty(0, dtype=np.uint16 if compact and m <= 2**16 else np.int32)
    same_group_pairs = int(np.bincount(gi, minlength=n_groups) @ np.bincount(gj, minlength=n_groups))
    all_valid = m == same_group_pairs
    row_base, col_rank = _affine_ids(lookup, gi, gj) if all_valid else (None, None)
    if row_base is None:
        row_base = col_rank = np.zeros(0, dtype=np.int64)
    # int32 window ends; the query windows only where runs are short (W2: 1 ms less; at W3, runs
    # of ~72, the per-row merge is as fast and the second table cost ~10 ms more)
    keep = m * n_i * 8 <= _MAX_WINDOW_TABLE_BYTES and n_j * n_j < 2**31
    by_query = (keep and int(np.bincount(gj, minlength=n_groups).max(initial=0)) <= _COUNT_MAX_RUN
                and (_window_table_entries(gi, gj, n_i) + m * n_i) * 8 <= _MAX_WINDOW_TABLE_BYTES)
    indptr, indices, data, wdeg, w_max = _build(
        D_i, D_j, gi, gj, assoc, lookup, all_valid, float(epsilon), inv2s2, n_groups,
        np.empty(0, dtype=dtype), index, _squarings(float(epsilon), inv2s2),
        keep, by_query,
        row_base, col_rank,
        _EXACT_SUM_SCALE if np.dtype(dtype) == np.float32 else 0.0,  # float32's 24-bit significand
    )
    return ConsistencyGraph(assoc, indptr, indices, data, wdeg, float(w_max))
