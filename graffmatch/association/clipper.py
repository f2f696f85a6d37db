"""CLIPPER: the densest-clique relaxation solved by projected gradient ascent (Lusk et al. 2021).

Problem (paper eq. densestclique): maximise u^T M u / u^T u over binary u subject to
u_i u_j = 0 for non-edges. CLIPPER relaxes u to the unit sphere in the positive orthant and
penalises non-edges with a weight d that a homotopy increases:

    F(u) = u^T (M + I) u - d u^T Cbar u,   Cbar = 1 1^T - C - I   (C: adjacency pattern)

Each homotopy step runs projected gradient ascent (step, clamp to the orthant, normalise) with
a backtracking line search; d then grows by the smallest ratio that makes some active non-edge
unprofitable, until the support of u is a clique. The whole loop runs in one numba function on
the CSR arrays: no dense m x m matrix, and the cost is non-zeros times iterations.

The module runs past 500 lines on purpose: the homotopy, the pruning and the greedy cliques
share the same numba CSR kernels and the same bounds, and splitting them would split one solver.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Literal

import numba as nb
import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.association.consistency_graph import ConsistencyGraph
from graffmatch.errors import InvalidInputError

Rounding = Literal["nonzero", "dsd_heu", "clique"]
# Largest active-set subgraph the homotopy copies out (bound: the active rows' non-zeros x 8 B);
# above it, the ascent runs on the active rows of the whole graph (same arithmetic, no copy).
_MAX_SUBGRAPH_BYTES = 64 * 2**20
# Active sets whose n x n float32 block fits in ClipperConfig.max_dense_block_mb run on a dense
# block when its n^2 entries cost less than the CSR rows' non-zeros: a dense entry costs ~0.14
# of a CSR non-zero (W1 graph, one core: 0.086 ms for 708^2 entries against 0.19 ms for 148k
# non-zeros).
_DENSE_ENTRY_COST = 0.2
# A sparse mat-vec scatters the rows of x's support instead of gathering every row when that
# support holds less than this fraction of the rows' non-zeros. A scattered non-zero costs only
# ~1.05-1.1x a gathered one (random supports, one core: W2 1.74 ms at 55 % against 2.87 ms for
# the gather, W3 30.3 against 52 ms), so the break-even is ~0.9 of the non-zeros, not 0.6.
_SCATTER_FRACTION = 0.9
# On graphs of at least this many vertices the CSR mat-vecs gather x from a float32 copy (sums
# stay float64): x then fits the 48 kB L1 cache up to 12k vertices instead of 6k, and a
# whole-graph pass at W3 (m = 11.5k, 43 M non-zeros) takes 34 instead of 41 ms (one core,
# isolated). Below it (x already in L1: W2 0.94 against 0.86 ms) the float64 gather is kept.
# Products differ by ~4e-9 relative (x's float32 rounding).
_F32_GATHER_MIN = 6144
# The greedy cliques scan a new member's row with a branch per entry (candidate or not) when
# the candidates number less than 1 / this of the row, else branch-free.
_SPARSE_SCAN = 8
_NO_DENSE = np.zeros((0, 0), dtype=np.float32)
_NO_QU = np.zeros(0)
_NO_POSITIONS = np.zeros(0, dtype=np.int64)


class ClipperConfig(BaseModel):
    """Solver parameters: tolerances and line search as in the reference CLIPPER; the d schedule
    defaults to the paper's (the most exact), the reference C++'s faster one is an option."""

    model_config = ConfigDict(extra="forbid")

    tol_u: float = Field(1e-8, gt=0, description="stop inner ascent when |u_new - u| < tol_u")
    tol_F: float = Field(1e-9, gt=0, description="stop inner ascent when |F_new - F| < tol_F")
    max_outer_iterations: int = Field(1000, ge=1, description="homotopy steps (increases of d)")
    max_inner_iterations: int = Field(200, ge=1, description="gradient steps per homotopy step")
    max_line_search_iterations: int = Field(99, ge=1, description="backtracking steps")
    beta: float = Field(0.25, gt=0, lt=1, description="backtracking step-size factor")
    alpha: float = Field(1.0, gt=0, description="initial step size of each homotopy step")
    eps: float = Field(1e-9, gt=0, description="numerical zero for u entries and line search")
    line_search: Literal["backtracking", "backtracking_linear", "exact"] = Field(
        "backtracking",
        description=(
            "backtracking: the reference's (a mat-vec per trial step); backtracking_linear: the "
            "same steps from one mat-vec per step (Q is linear in the trial step); exact: the "
            "maximiser of the "
            "Rayleigh quotient along the projected gradient in closed form (one mat-vec per step, "
            "about half the mat-vecs on landmark graphs; it can reach a different, denser clique: "
            "bench/solver_selections.py)"
        ),
    )
    step_cap: float = Field(
        0.0,
        ge=0,
        description=(
            "largest backtracking step size times F (0: none, the reference's). The step grows "
            "4x after every step accepted at once; once it dwarfs 1 / F the ascent is a projected "
            "power iteration of M - d Cbar that zig-zags (the support flips between two sizes) "
            "and crawls: at W3, 86 steps in one homotopy step. A cap of c / F is a shift of F / c "
            "that damps the zig-zag; 8 cut the solver's work by 17 % on W1/W2 and 20-40 % on W3 "
            "with the same selections (bench/solver_selections.py)"
        ),
    )
    rounding: Rounding = Field(
        "clique",
        description=(
            "nonzero: keep every positive entry of u; dsd_heu: keep the round(score) largest "
            "entries (reference default); clique: nonzero, then remove the vertices with most "
            "non-edges until the selection is a clique (exact feasibility clean-up)"
        ),
    )
    prune: bool = Field(
        True,
        description=(
            "drop vertices whose weighted degree cannot reach the best clique found by a greedy "
            "seed (lossless bound: a vertex in a clique of size k has >= k-1 neighbours)"
        ),
    )
    seed: int = Field(0, description="seed of the random start vector (deterministic)")
    d_schedule: Literal["min", "mean"] = Field(
        "min",
        description=(
            "how the penalty d grows between homotopy steps, from the ratios Mu/(sum u - Cu) "
            "over active non-edges: 'min' (the paper's CLIPPER: the smallest ratio, many short "
            "steps) or 'mean' (the current reference C++: the mean ratio, also for the initial "
            "d; fewer, longer steps)"
        ),
    )
    rescale_u0: bool = Field(
        False,
        description="one power-method step on the start vector (the current reference C++ does)",
    )
    greedy_starts: int = Field(
        0,
        ge=0,
        description=(
            "also grow greedy max-weight cliques from this many highest weighted-degree "
            "vertices and return the clique with the best densest-clique objective (CLIPPER's "
            "or a greedy one); the relaxation can settle on a sparser clique (e.g. a street "
            "seen 180 degrees flipped) while a denser one exists. 0 = CLIPPER only"
        ),
    )
    greedy_max_work: float = Field(
        1.0,
        ge=0,
        description=(
            "bound on the greedy cliques' work, in edge visits per stored non-zero of W "
            "(1.0 ~ one mat-vec); deterministic, unlike a timer"
        ),
    )
    greedy_min_work: int = Field(
        50_000,
        ge=0,
        description="floor of that bound in edge visits, so small graphs try every start",
    )
    max_dense_block_mb: float = Field(
        16.0,
        ge=0,
        description=(
            "largest dense float32 block of an active set [MB] (a temporary on top of the "
            "graph); a dense active set within it is multiplied without gathers. Larger blocks "
            "can pay off on huge graphs: at W3 (m = 11.5k) 80 puts a 4,090-vertex step in a "
            "67 MB block instead of streaming its 18 M CSR non-zeros; match() CPU 3.6 -> 3.0 s "
            "for a 64 MB higher peak (bench/results/matcher_W3_noverif_dense80_session5.json)"
        ),
    )


@dataclass
class ClipperSolution:
    """Result of :func:`solve_clipper`."""

    selected: NDArray[np.int64]
    u: NDArray[np.float64]
    score: float
    outer_iterations: int
    inner_iterations: int
    matvecs: int
    d: float
    info: dict = field(default_factory=dict)

    def __repr__(self) -> str:
        return (
            f"ClipperSolution(selected={len(self.selected)}, score={self.score:.3f}, "
            f"outer={self.outer_iterations}, inner={self.inner_iterations}, matvecs={self.matvecs})"
        )


@nb.njit(cache=True, inline="always")
def _row(indptr, indices, data, r):
    """Row r's column indices and weights as slices. A loop ``for k in range(indptr[r],
    indptr[r + 1])`` indexes with a k numba cannot prove non-negative, so every access carries
    a wrap-around select, which LLVM turns into a gather of ``data`` (W2: 2.7 ms a mat-vec);
    over slices the index runs from 0 and the loads are contiguous (1.3 ms, the same sums)."""
    lo = indptr[r]
    hi = indptr[r + 1]
    return indices[lo:hi], data[lo:hi]


@nb.njit(cache=True, fastmath=True)
def _matvecs(indptr, indices, data, u, Mu, Cu):
    """Mu = (W + I) u and Cu = (A + I) u (A: the edge pattern) in one row-wise pass; the
    gathered u in float32 on large graphs (:data:`_F32_GATHER_MIN`)."""
    m = u.shape[0]
    if m >= _F32_GATHER_MIN:
        _matvecs_gather(indptr, indices, data, u, u.astype(np.float32), Mu, Cu)
        return
    for r in range(m):
        cols, w = _row(indptr, indices, data, r)
        sw = u[r]
        sc = u[r]
        for k in range(cols.shape[0]):
            x = u[cols[k]]
            sw += w[k] * x
            sc += x
        Mu[r] = sw
        Cu[r] = sc


@nb.njit(cache=True, fastmath=True)
def _matvecs_gather(indptr, indices, data, u, ug, Mu, Cu):
    """:func:`_matvecs` with the neighbours' entries gathered from ``ug`` (u's float32 copy)."""
    m = u.shape[0]
    for r in range(m):
        cols, w = _row(indptr, indices, data, r)
        sw = u[r]
        sc = u[r]
        for k in range(cols.shape[0]):
            x = ug[cols[k]]
            sw += w[k] * x
            sc += x
        Mu[r] = sw
        Cu[r] = sc


@nb.njit(cache=True, fastmath=True)
def _wmatvec(indptr, indices, data, u, Mu):
    """Mu = (W + I) u alone, bit for bit :func:`_matvecs`'s Mu (the same loop without the
    second accumulator; ~10 % cheaper)."""
    m = u.shape[0]
    if m >= _F32_GATHER_MIN:
        _wmatvec_gather(indptr, indices, data, u, u.astype(np.float32), Mu)
        return
    for r in range(m):
        cols, w = _row(indptr, indices, data, r)
        sw = u[r]
        for k in range(cols.shape[0]):
            sw += w[k] * u[cols[k]]
        Mu[r] = sw


@nb.njit(cache=True, fastmath=True)
def _wmatvec_gather(indptr, indices, data, u, ug, Mu):
    m = u.shape[0]
    for r in range(m):
        cols, w = _row(indptr, indices, data, r)
        sw = u[r]
        for k in range(cols.shape[0]):
            sw += w[k] * ug[cols[k]]
        Mu[r] = sw


@nb.njit(cache=True)
def _matvecs_from_support(indptr, indices, data, u, support, Mu, Cu):
    """Same as :func:`_matvecs` for a u that is zero outside ``support``: W is symmetric, so
    scattering the support's rows costs their degrees instead of every edge."""
    Mu[:] = 0.0
    Cu[:] = 0.0
    for v in support:
        x = u[v]
        Mu[v] += x
        Cu[v] += x
        cols, w = _row(indptr, indices, data, v)
        for k in range(cols.shape[0]):
            c = cols[k]
            Mu[c] += w[k] * x
            Cu[c] += x


@nb.njit(cache=True)
def _increment_d(u, Mu, Cu, eps, use_mean=False):
    """Increase of d from |Mu / (sum u - Cu)| over the active vertices with non-edges in the
    support: the smallest ratio (the first non-edge to become unprofitable) or their mean.
    inf when there is no such vertex, i.e. the support is a clique."""
    s = np.sum(u)
    best = np.inf
    total = 0.0
    count = 0
    for r in range(u.shape[0]):
        cb = s - Cu[r]
        if cb > eps and u[r] > eps:
            ratio = abs(Mu[r] / cb)
            total += ratio
            count += 1
            if ratio < best:
                best = ratio
    if use_mean and count > 0:
        return total / count
    return best


@nb.njit(cache=True, fastmath=True)
def _qmatvec_rows(indptr, indices, data, dense, x, rows, d, Qx):
    """Qx = (W + d A + (1 + d) I) x on the listed rows, for an x that is zero outside them (the
    zero columns add exact zeros, so the values equal those on the induced subgraph).

    The ascent only ever needs M x - d (sum x - C x) = Qx - d sum x (M = W + I, C = A + I), so
    one accumulator per row with the weight w + d replaces the two sums of W x and A x: half
    the additions, and fastmath lets the row's sum be reassociated (vectorised).

    With a non-empty ``dense`` (the active subgraph as an n x n matrix, see :func:`_dense_block`;
    rows = 0..n-1) the product is ``dense @ x`` = M x - d (sum x - C x) itself: contiguous rows
    instead of gathers, float32 entries summed in float64."""
    if dense.shape[0]:
        n = dense.shape[0]
        for r in range(n):
            row = dense[r]
            s = 0.0
            for c in range(n):
                s += row[c] * x[c]
            Qx[r] = s
        return
    dd = 1.0 + d
    n = rows.shape[0]
    supp_nnz = 0
    all_nnz = 0
    for i in range(n):
        r = rows[i]
        deg = indptr[r + 1] - indptr[r]
        all_nnz += deg
        supp_nnz += deg * (x[r] != 0.0)
    if supp_nnz < _SCATTER_FRACTION * all_nnz:
        # x is zero on most rows (the clamped coordinates of an ascent): W is symmetric, so
        # scattering the rows of x's support reads only their non-zeros.
        Qx[:] = 0.0
        for i in range(n):
            r = rows[i]
            xr = x[r]
            if xr != 0.0:
                Qx[r] += dd * xr
                cols, w = _row(indptr, indices, data, r)
                for k in range(cols.shape[0]):
                    Qx[cols[k]] += (w[k] + d) * xr
        return
    if x.shape[0] >= _F32_GATHER_MIN:
        _qgather_rows(indptr, indices, data, x, x.astype(np.float32), rows, d, Qx)
        return
    for i in range(n):
        r = rows[i]
        cols, w = _row(indptr, indices, data, r)
        s = 0.0
        for k in range(cols.shape[0]):
            s += (w[k] + d) * x[cols[k]]
        Qx[r] = s + dd * x[r]


@nb.njit(cache=True, fastmath=True)
def _qgather_rows(indptr, indices, data, x, xg, rows, d, Qx):
    """The row-wise gather of :func:`_qmatvec_rows`, the neighbours' entries read from ``xg``
    (x's float32 copy)."""
    dd = 1.0 + d
    for i in range(rows.shape[0]):
        r = rows[i]
        cols, w = _row(indptr, indices, data, r)
        s = 0.0
        for k in range(cols.shape[0]):
            s += (w[k] + d) * xg[cols[k]]
        Qx[r] = s + dd * x[r]


@nb.njit(cache=True)
def _dense_block(indptr, indices, data, rows, d, store):
    """The quadratic form of F on the active ``rows`` as a dense float32 matrix: w on edges,
    -d on non-edges, 1 on the diagonal (M - d Cbar). No cancellation: the penalty is stored
    per entry instead of as d (A + I) x - d sum x. Written to the start of the flat float32
    ``store`` (>= n^2 + 1 entries; see :class:`_DenseStore`) and returned as an n x n view of it.

    Each row is scattered branch-free with one spare column, where the columns outside ``rows``
    land (a test per non-zero mispredicts on ~n / m of them: 3-6x slower at W2 / W3). Row i's
    spare column is row i + 1's first entry, which that row's fill then overwrites (the last
    row's is store[n^2], outside the block), so each row is written in place, without a buffer
    and its copy (W2: ~12 % less time, the same block). With every row active there is no
    column to divert."""
    n = rows.shape[0]
    m = indptr.shape[0] - 1
    out = store[: n * n].reshape((n, n))
    nd = np.float32(-d)
    if n == m:  # every row (rows = 0..m-1, e.g. W1's first step): no column to divert
        for i in range(n):
            row = out[i]
            for j in range(n):
                row[j] = nd
            cols, w = _row(indptr, indices, data, i)
            for k in range(cols.shape[0]):
                row[cols[k]] = w[k]
            row[i] = 1.0
        return out
    pos = np.full(m, n, dtype=np.int32)
    for i in range(n):
        pos[rows[i]] = i
    for i in range(n):
        base = i * n  # row i in the flat store; its spare column is base + n
        for j in range(n):
            store[base + j] = nd
        cols, w = _row(indptr, indices, data, rows[i])
        for k in range(cols.shape[0]):
            store[base + pos[cols[k]]] = w[k]
        store[base + i] = 1.0
    return out


@nb.njit(cache=True)
def _dense_block_shrink(store, n_prev, sel, d):
    """:func:`_dense_block` of a subset of the previous dense block's rows (``sel``: their
    positions in it, ascending) at a new penalty d, gathered from that block (n^2 reads instead
    of the rows' non-zeros): its non-edges are its negative entries (weights are >= 0, the old
    penalty was > 0), the same float32 values otherwise.

    In place: the previous block is the n_prev x n_prev start of the flat ``store``, and the new
    one overwrites it. Entry (i, j) goes to i n + j and comes from sel[i] n_prev + sel[j] >=
    i n + j, which no earlier write has reached (every later read lies beyond every earlier
    write), so no value is overwritten before it is read."""
    n = sel.shape[0]
    nd = np.float32(-d)
    for i in range(n):
        src = sel[i] * n_prev
        dst = i * n
        for j in range(n):
            x = store[src + sel[j]]
            store[dst + j] = nd if x < 0.0 else x
    return store[: n * n].reshape((n, n))


class _DenseStore:
    """One float32 buffer for the dense blocks, kept from one solve to the next (at most
    ``ClipperConfig.max_dense_block_mb``): a fresh 2-4 MB block costs its page faults every
    solve (~0.5 ms at W1, ~1.4 ms at W2, more than filling it). A solve takes the buffer and
    gives it back (``list.pop`` / ``append`` are atomic, so concurrent solves never share one:
    the second allocates its own)."""

    _free: ClassVar[list[np.ndarray]] = []

    @classmethod
    def take(cls, n_entries: int) -> np.ndarray:
        try:
            buf = cls._free.pop()
        except IndexError:
            buf = None
        if buf is None or buf.shape[0] < n_entries:
            buf = np.empty(n_entries, dtype=np.float32)
        return buf

    @classmethod
    def give_back(cls, buf: np.ndarray, max_bytes: float) -> None:
        if buf.nbytes <= max_bytes and not cls._free:
            cls._free.append(buf)


@nb.njit(cache=True)
def _clamped_trial(u, dirv, step, rows, indptr, indices, data, dense, rows_nnz, d, Qu, Qd, v, Qv, clamped):
    """Trial point ``v = max(u + step * dirv, 0)`` on the active rows with ``Q v`` (see
    :func:`_qmatvec_rows`): by linearity from ``Q u`` and ``Q dirv`` plus a sparse correction
    for each clamped entry, or one direct mat-vec when the clamped rows hold more than half the
    non-zeros. Returns (sum of squares of v, sum of v, mat-vecs spent: 0 or 1). Both line
    searches use it."""
    n = rows.shape[0]
    nclamp = 0
    clamp_nnz = 0
    for i in range(n):
        r = rows[i]
        x = u[r] + step * dirv[r]
        v[r] = x
        if x < 0.0:
            clamped[nclamp] = r
            nclamp += 1
            clamp_nnz += n if dense.shape[0] else indptr[r + 1] - indptr[r]
    direct = 0
    if 2 * clamp_nnz > rows_nnz:
        for j in range(nclamp):
            v[clamped[j]] = 0.0
        _qmatvec_rows(indptr, indices, data, dense, v, rows, d, Qv)
        direct = 1
    else:
        for i in range(n):
            r = rows[i]
            Qv[r] = Qu[r] + step * Qd[r]
        for j in range(nclamp):  # add Q of the clamp correction -v_r e_r (W symmetric)
            r = clamped[j]
            x = -v[r]
            v[r] = 0.0
            if dense.shape[0]:
                row = dense[r]  # symmetric: column r = row r
                for c in range(n):
                    Qv[c] += row[c] * x
                continue
            Qv[r] += (1.0 + d) * x
            cols, w = _row(indptr, indices, data, r)
            for k in range(cols.shape[0]):
                Qv[cols[k]] += (w[k] + d) * x
    nrm = 0.0
    sv = 0.0
    for i in range(n):
        x = v[rows[i]]
        nrm += x * x
        sv += x
    return nrm, sv, direct


@nb.njit(cache=True)
def _ascent(indptr, indices, data, dense, u, rows, d, tol_u, tol_F, max_inner, max_ls, beta, alpha, eps,
            step_cap=0.0):
    """Projected gradient ascent of F at fixed penalty d (one homotopy step), in place on u.

    Only the coordinates in ``rows`` (ascending) move; u must be zero elsewhere and stays so.
    ``rows`` = all rows of an extracted subgraph, or the active rows of the whole graph (then
    no copy of a large subgraph is needed; the arithmetic is the same, in the same order).
    The gradient M u - d (sum u - C u) is Q u - d sum u (:func:`_qmatvec_rows`).
    Returns (inner iterations, mat-vecs)."""
    m = u.shape[0]
    n = rows.shape[0]
    ds = 0.0 if dense.shape[0] else d  # the dense block holds the -d sum x term itself
    Qu = np.zeros(m)
    unew = np.zeros(m)
    grad = np.zeros(m)
    gradnew = np.zeros(m)
    Qunew = np.zeros(m)
    _qmatvec_rows(indptr, indices, data, dense, u, rows, d, Qu)
    matvecs = 1
    s = 0.0
    for i in range(n):
        s += u[rows[i]]
    F = 0.0
    for i in range(n):
        r = rows[i]
        grad[r] = Qu[r] - ds * s
        F += u[r] * grad[r]
    inner = 0
    for _ in range(max_inner):
        inner += 1
        Fnew = F
        deltaF = 0.0
        accepted = False
        for _ls in range(max_ls):
            nrm = 0.0
            for i in range(n):
                r = rows[i]
                x = u[r] + alpha * grad[r]
                if x < 0.0:
                    x = 0.0
                unew[r] = x
                nrm += x * x
            if nrm <= 0.0:
                alpha *= beta
                continue
            inv = 1.0 / np.sqrt(nrm)
            for i in range(n):
                unew[rows[i]] *= inv
            _qmatvec_rows(indptr, indices, data, dense, unew, rows, d, Qunew)
            matvecs += 1
            sn = 0.0
            for i in range(n):
                sn += unew[rows[i]]
            Fnew = 0.0
            for i in range(n):
                r = rows[i]
                gradnew[r] = Qunew[r] - ds * sn
                Fnew += unew[r] * gradnew[r]
            deltaF = Fnew - F
            if deltaF < -eps:
                alpha *= beta
            else:
                accepted = True
                if _ls == 0:
                    alpha /= beta  # accepted at once: try a longer step next time
                    if step_cap > 0.0 and Fnew > 0.0 and alpha * Fnew > step_cap:
                        alpha = step_cap / Fnew
                break
        if not accepted:
            break
        du = 0.0
        for i in range(n):
            r = rows[i]
            diff = unew[r] - u[r]
            du += diff * diff
            u[r] = unew[r]
            grad[r] = gradnew[r]
        F = Fnew
        if np.sqrt(du) < tol_u or abs(deltaF) < tol_F:
            break
    return inner, matvecs


@nb.njit(cache=True)
def _ascent_exact(indptr, indices, data, dense, u, rows, d, tol_u, tol_F, max_inner, max_ls, beta, eps):
    """:func:`_ascent` with an exact line search: one mat-vec per step instead of one per trial.

    F is a Rayleigh quotient u^T Q u / u^T u (Q = M - d Cbar), so along the ray u + t p
    (p: the gradient's part tangent to the sphere, zero where u sits on the orthant's boundary
    and the gradient points out) F(t) = (a + 2bt + ct^2) / (1 + 2et + ft^2) is a ratio of
    quadratics whose maximiser over t >= 0 has a closed form. Q p costs one mat-vec; Q of the
    clamped step follows linearly from Qu and Qp, plus a scatter of the rows of the (few)
    coordinates the orthant projection clamps to zero. If the clamping lowers F, t shrinks by
    ``beta`` (no new mat-vec). Same stopping rules, same fixed points (KKT points at this d)."""
    m = u.shape[0]
    n = rows.shape[0]
    ds = 0.0 if dense.shape[0] else d  # the dense block holds the -d sum x term itself
    Qu = np.zeros(m)
    p = np.zeros(m)
    Qp = np.zeros(m)
    v = np.zeros(m)
    Qv = np.zeros(m)
    clamped = np.empty(n, dtype=np.int64)
    rows_nnz = n * n if dense.shape[0] else 0
    for i in range(0 if dense.shape[0] else n):
        rows_nnz += indptr[rows[i] + 1] - indptr[rows[i]]
    _qmatvec_rows(indptr, indices, data, dense, u, rows, d, Qu)
    matvecs = 1
    s = 0.0
    F = 0.0
    for i in range(n):
        s += u[rows[i]]
    for i in range(n):
        r = rows[i]
        F += u[r] * (Qu[r] - ds * s)
    inner = 0
    for _ in range(max_inner):
        inner += 1
        for i in range(n):
            r = rows[i]
            x = Qu[r] - ds * s - F * u[r]
            if u[r] <= 0.0 and x < 0.0:
                x = 0.0
            p[r] = x
        _qmatvec_rows(indptr, indices, data, dense, p, rows, d, Qp)
        matvecs += 1
        sp_ = 0.0
        for i in range(n):
            sp_ += p[rows[i]]
        b = 0.0
        c = 0.0
        e = 0.0
        f = 0.0
        for i in range(n):
            r = rows[i]
            b += p[r] * (Qu[r] - ds * s)
            c += p[r] * (Qp[r] - ds * sp_)
            e += u[r] * p[r]
            f += p[r] * p[r]
        if f <= 0.0 or b <= 0.0:
            break  # no ascent direction: a KKT point at this d
        # F'(t) = 0 <=> qa t^2 + qb t + qc = 0 (F'(0) ~ qc = b - F e > 0)
        qa = c * e - b * f
        qb = c - F * f
        qc = b - F * e
        t = -1.0
        best = F
        if qa == 0.0:
            if qb != 0.0:
                t = -qc / qb
        else:
            disc = qb * qb - 4.0 * qa * qc
            if disc >= 0.0:
                sq = np.sqrt(disc)
                q = -0.5 * (qb + (sq if qb >= 0.0 else -sq))  # stable roots q / qa, qc / q
                for root in (q / qa, qc / q if q != 0.0 else -1.0):
                    if root > 0.0:
                        val = (F + 2.0 * b * root + c * root * root) / (1.0 + 2.0 * e * root + f * root * root)
                        if val > best:
                            best = val
                            t = root
        if t <= 0.0:
            t = 1e8 / np.sqrt(f)  # F rises along the whole ray: step (almost) onto p
        accepted = False
        Fnew = F
        nrm = 1.0
        sv = 0.0
        for _ls in range(max_ls):
            nrm, sv, direct = _clamped_trial(u, p, t, rows, indptr, indices, data, dense, rows_nnz, d,
                                             Qu, Qp, v, Qv, clamped)
            matvecs += direct
            if nrm <= 0.0:
                t *= beta
                continue
            Fnew = 0.0
            for i in range(n):
                r = rows[i]
                Fnew += v[r] * (Qv[r] - ds * sv)
            Fnew /= nrm
            if Fnew - F < -eps:
                t *= beta
            else:
                accepted = True
                break
        if not accepted:
            break
        inv = 1.0 / np.sqrt(nrm)
        du = 0.0
        for i in range(n):
            r = rows[i]
            x = v[r] * inv
            diff = x - u[r]
            du += diff * diff
            u[r] = x
            Qu[r] = Qv[r] * inv
        s = sv * inv
        deltaF = Fnew - F
        F = Fnew
        if np.sqrt(du) < tol_u or abs(deltaF) < tol_F:
            break
    return inner, matvecs


@nb.njit(cache=True)
def _ascent_linear(indptr, indices, data, dense, u, rows, d, tol_u, tol_F, max_inner, max_ls, beta, alpha, eps,
                   step_cap=0.0, Qu0=_NO_QU):
    """:func:`_ascent`'s iterates (the same backtracking, the same steps) with one mat-vec per step
    instead of one per trial: Q is linear, so Q (u + alpha g) = Q u + alpha Q g for every trial
    alpha, from one mat-vec Q g. Coordinates that the orthant projection clamps for any alpha
    (u_i = 0, g_i < 0) are dropped from g first; the few others a trial clamps are corrected by
    scattering their rows (W symmetric), or by a direct mat-vec when they are many. Values equal
    :func:`_ascent`'s up to rounding. A non-empty ``Qu0`` is Q u on ``rows``, given instead of
    computed."""
    m = u.shape[0]
    n = rows.shape[0]
    ds = 0.0 if dense.shape[0] else d  # the dense block holds the -d sum x term itself
    Qu = np.zeros(m)
    g = np.zeros(m)
    Qg = np.zeros(m)
    v = np.zeros(m)
    Qv = np.zeros(m)
    clamped = np.empty(n, dtype=np.int64)
    rows_nnz = n * n if dense.shape[0] else 0
    for i in range(0 if dense.shape[0] else n):
        rows_nnz += indptr[rows[i] + 1] - indptr[rows[i]]
    if Qu0.shape[0]:
        for i in range(n):  # Q u given (the homotopy's (W + I) u + d (A + I) u): no mat-vec
            Qu[rows[i]] = Qu0[rows[i]]
        matvecs = 0
    else:
        _qmatvec_rows(indptr, indices, data, dense, u, rows, d, Qu)
        matvecs = 1
    s = 0.0
    for i in range(n):
        s += u[rows[i]]
    F = 0.0
    for i in range(n):
        r = rows[i]
        F += u[r] * (Qu[r] - ds * s)
    inner = 0
    for _ in range(max_inner):
        inner += 1
        for i in range(n):
            r = rows[i]
            x = Qu[r] - ds * s
            if u[r] <= 0.0 and x < 0.0:
                x = 0.0  # clamped at every alpha > 0: max(0, 0 + alpha x) = 0
            g[r] = x
        _qmatvec_rows(indptr, indices, data, dense, g, rows, d, Qg)
        matvecs += 1
        Fnew = F
        deltaF = 0.0
        nrm = 0.0
        sv = 0.0
        accepted = False
        for _ls in range(max_ls):
            nrm, sv, direct = _clamped_trial(u, g, alpha, rows, indptr, indices, data, dense, rows_nnz, d,
                                             Qu, Qg, v, Qv, clamped)
            matvecs += direct
            if nrm <= 0.0:
                alpha *= beta
                continue
            nrm = np.sqrt(nrm)
            Fnew = 0.0
            for i in range(n):
                r = rows[i]
                Fnew += v[r] * (Qv[r] - ds * sv)
            Fnew /= nrm * nrm
            deltaF = Fnew - F
            if deltaF < -eps:
                alpha *= beta
            else:
                accepted = True
                if _ls == 0:
                    alpha /= beta  # accepted at once: try a longer step next time
                    if step_cap > 0.0 and Fnew > 0.0 and alpha * Fnew > step_cap:
                        alpha = step_cap / Fnew
                break
        if not accepted:
            break
        inv = 1.0 / nrm
        du = 0.0
        for i in range(n):
            r = rows[i]
            x = v[r] * inv
            diff = x - u[r]
            du += diff * diff
            u[r] = x
            Qu[r] = Qv[r] * inv
        s = sv * inv
        F = Fnew
        if np.sqrt(du) < tol_u or abs(deltaF) < tol_F:
            break
    return inner, matvecs


@nb.njit(cache=True)
def _active_rows(active, indptr):
    """The active vertex ids (ascending, np.flatnonzero's) and their rows' stored non-zeros."""
    m = active.shape[0]
    idx = np.empty(m, dtype=np.int64)
    n = 0
    nnz = 0
    for v in range(m):
        if active[v]:
            idx[n] = v
            n += 1
            nnz += indptr[v + 1] - indptr[v]
    return idx[:n], nnz


@nb.njit(cache=True)
def _positions_in(prev, idx):
    """Where each of ``idx`` sits in ``prev`` (both ascending, distinct), or an empty array when
    ``prev`` is empty or lacks one of them (a merge: np.searchsorted and a check in one pass)."""
    n = idx.shape[0]
    p = prev.shape[0]
    at = np.empty(n, dtype=np.int64)
    if p == 0 or n == 0:
        return at[:0]
    j = 0
    for i in range(n):
        v = idx[i]
        while j < p and prev[j] < v:
            j += 1
        if j == p or prev[j] != v:
            return at[:0]
        at[i] = j
    return at


@nb.njit(cache=True)
def _scatter_back(u, uk, rows, idx):
    """u = uk[rows] on ``idx`` and 0 elsewhere, in place; returns the ids of u's support
    (ascending, as ``idx``). One pass instead of five numpy temporaries per homotopy step."""
    u[:] = 0.0
    n = idx.shape[0]
    support = np.empty(n, dtype=np.int64)
    c = 0
    for i in range(n):
        x = uk[rows[i]]
        u[idx[i]] = x
        support[c] = idx[i]
        c += x > 0.0
    return support[:c]


@nb.njit(cache=True)
def _update_active(u, Mu, Cu, d, s, eps, active):
    """The homotopy's active-set update from the full-graph gradient Mu - d (s - Cu) (s = sum
    u): vertices in u's support or with a non-negative gradient. If one lies outside ``active``,
    ``active`` grows by them (True: redo the step); else it becomes exactly them (False). In
    place, the same IEEE operations as the numpy expressions it replaces (no fastmath)."""
    m = u.shape[0]
    grew = False
    for i in range(m):
        if not active[i] and (u[i] > eps or Mu[i] - d * (s - Cu[i]) >= 0.0):
            grew = True
            break
    for i in range(m):
        new = u[i] > eps or Mu[i] - d * (s - Cu[i]) >= 0.0
        active[i] = (active[i] or new) if grew else new
    return grew


def _homotopy(indptr, indices, data, u0,
              cfg: ClipperConfig) -> tuple[np.ndarray, int, int, int, float, np.ndarray]:
    """CLIPPER's outer loop with an active set.

    Each homotopy step runs the ascent only on vertices that are in the support of u or whose
    gradient is non-negative (others would be clamped to zero by the projection anyway); the
    set is re-derived from a full-graph gradient after every step, and the loop ends only when
    no excluded vertex has a positive gradient, so the result is a KKT point of the full problem.
    Returns (u, outer, inner, mat-vecs, d, (W + I) u).
    """
    m = u0.shape[0]
    u = u0 / np.linalg.norm(u0)
    Mu = np.empty(m)
    Cu = np.empty(m)
    matvecs = 1
    use_mean = cfg.d_schedule == "mean"
    if cfg.rescale_u0:
        _wmatvec(indptr, indices, data, u, Mu)  # (W + I) u0 alone: its (A + I) u0 is not used
        u = Mu / np.linalg.norm(Mu)  # (W + I) u0: random starts look alike after one step
        matvecs += 1
    _matvecs(indptr, indices, data, u, Mu, Cu)
    d = _increment_d(u, Mu, Cu, cfg.eps, use_mean)
    d = 0.0 if not np.isfinite(d) else d
    inner_total = 0
    outer = 0
    active = np.ones(m, dtype=np.bool_)
    sub = (indptr, indices, data)
    sub_ids = np.arange(m)  # global vertex ids of the rows of ``sub``
    max_dense = cfg.max_dense_block_mb * 2**20
    prev_idx, prev_d = np.zeros(0, dtype=np.int64), 0.0  # the last dense block's rows and d
    # the dense blocks' buffer, the last block at its start (not given back after an exception:
    # the next solve then allocates its own)
    store = _DenseStore.take(0)
    for outer in range(1, cfg.max_outer_iterations + 1):  # noqa: B007 (returned count)
        idx, idx_nnz = _active_rows(active, indptr)
        n = idx.size
        dense = _NO_DENSE
        if n * n * 4 <= max_dense and n * n * _DENSE_ENTRY_COST < idx_nnz:
            # A small, dense active set: its block as a dense matrix (contiguous rows, no
            # gathers) is cheaper to multiply than its rows in CSR.
            at = _positions_in(prev_idx, idx) if prev_d > 0.0 else _NO_POSITIONS
            if at.shape[0]:  # idx within the last block's rows: gather from that block
                dense = _dense_block_shrink(store, prev_idx.size, at, d)
            else:
                if store.shape[0] < n * n + 1:  # (+ 1: the last row's spare column)
                    store = np.empty(n * n + 1, dtype=np.float32)
                dense = _dense_block(indptr, indices, data, idx, d, store)
            prev_idx, prev_d = idx, d
            uk = np.ascontiguousarray(u[idx])
            rows = np.arange(n)
        elif n * 2 > m or idx_nnz * 8 > _MAX_SUBGRAPH_BYTES:
            # A large active set: run on its rows of the whole graph instead of copying an
            # induced subgraph of a similar size (the copy was +90 MB at m = 11.5k).
            sub, sub_ids = (indptr, indices, data), np.arange(m)
            prev_idx, prev_d = np.zeros(0, dtype=np.int64), 0.0
            uk = np.zeros(m)
            uk[idx] = u[idx]
            rows = idx
        else:
            if idx.size != sub_ids.size or not np.array_equal(idx, sub_ids):
                # The active set mostly shrinks: cut it from the current (smaller) subgraph
                # when it can, and from the whole graph only when a vertex came back.
                if np.all(np.isin(idx, sub_ids, assume_unique=True)):
                    sub = _subgraph(sub[0], sub[1], sub[2], active[sub_ids])
                else:
                    sub = _subgraph(indptr, indices, data, active)
                sub_ids = idx
            uk = np.ascontiguousarray(u[idx])
            rows = np.arange(idx.size)
        Qu0 = _NO_QU
        on_rows = uk if rows.shape[0] == uk.shape[0] else uk[rows]  # rows = 0..n-1: uk itself
        if not np.any(on_rows > 0):
            uk[rows] = 1.0
            on_rows = uk if rows.shape[0] == uk.shape[0] else uk[rows]
        elif (dense.shape[0] == 0 and cfg.line_search == "backtracking_linear"
              and not np.any((u > 0.0) & ~active)):
            # u lies on these rows, and Q u = (W + I) u + d (A + I) u = Mu + d Cu, known from
            # the last full-graph product: the ascent's first mat-vec is not needed (a CSR
            # pass over the active rows; up to rounding, bench/solver_selections.py)
            Qu0 = np.zeros(uk.shape[0])
            Qu0[rows] = Mu[idx] + d * Cu[idx]
        nrm = np.linalg.norm(on_rows)
        if rows.shape[0] == uk.shape[0]:
            uk /= nrm
        else:
            uk[rows] /= nrm
        if Qu0.shape[0]:
            Qu0[rows] /= nrm
        if cfg.line_search == "exact":
            inner, nmv = _ascent_exact(
                sub[0], sub[1], sub[2], dense, uk, rows, d, cfg.tol_u, cfg.tol_F, cfg.max_inner_iterations,
                cfg.max_line_search_iterations, cfg.beta, cfg.eps,
            )
        elif cfg.line_search == "backtracking_linear":
            inner, nmv = _ascent_linear(
                sub[0], sub[1], sub[2], dense, uk, rows, d, cfg.tol_u, cfg.tol_F, cfg.max_inner_iterations,
                cfg.max_line_search_iterations, cfg.beta, cfg.alpha, cfg.eps, cfg.step_cap, Qu0,
            )
        else:
            inner, nmv = _ascent(
                sub[0], sub[1], sub[2], dense, uk, rows, d, cfg.tol_u, cfg.tol_F, cfg.max_inner_iterations,
                cfg.max_line_search_iterations, cfg.beta, cfg.alpha, cfg.eps, cfg.step_cap,
            )
        inner_total += inner
        matvecs += nmv + 1
        _matvecs_from_support(indptr, indices, data, u, _scatter_back(u, uk, rows, idx), Mu, Cu)
        # u.sum() stays numpy's (pairwise) sum: the gradient below is the one it always was
        if _update_active(u, Mu, Cu, d, u.sum(), cfg.eps, active):
            continue  # an excluded vertex became profitable: redo this step with it (same d)
        step = _increment_d(u, Mu, Cu, cfg.eps, use_mean)
        if not np.isfinite(step):
            break
        d += step
    _DenseStore.give_back(store, max_dense)
    return u, outer, inner_total, matvecs, float(d), Mu


@nb.njit(cache=True)
def _greedy_clique_size(indptr, indices, order):
    """Size of a greedy clique grown in ``order`` (a lower bound on the maximum clique)."""
    m = indptr.shape[0] - 1
    in_clique = np.zeros(m, dtype=np.bool_)
    count = np.zeros(m, dtype=np.int64)  # neighbours already in the clique
    size = 0
    for v in order:
        if count[v] == size:
            in_clique[v] = True
            size += 1
            for k in range(indptr[v], indptr[v + 1]):
                count[indices[k]] += 1
    return size


@nb.njit(cache=True)
def _kcore_keep(indptr, indices, k):
    """Vertices of the k-core (every kept vertex keeps >= k kept neighbours), by peeling."""
    m = indptr.shape[0] - 1
    deg = np.empty(m, dtype=np.int64)
    alive = np.ones(m, dtype=np.bool_)
    stack = np.empty(m, dtype=np.int64)
    top = 0
    for v in range(m):
        deg[v] = indptr[v + 1] - indptr[v]
        if deg[v] < k:
            alive[v] = False
            stack[top] = v
            top += 1
    while top > 0:
        top -= 1
        v = stack[top]
        for t in range(indptr[v], indptr[v + 1]):
            w = indices[t]
            if alive[w]:
                deg[w] -= 1
                if deg[w] < k:
                    alive[w] = False
                    stack[top] = w
                    top += 1
    return alive


@nb.njit(cache=True)
def _subgraph(indptr, indices, data, keep_mask):
    """CSR of the subgraph induced by ``keep_mask`` (re-indexed)."""
    m = indptr.shape[0] - 1
    newid = np.full(m, -1, dtype=np.int64)
    n = 0
    for v in range(m):
        if keep_mask[v]:
            newid[v] = n
            n += 1
    counts = np.zeros(n + 1, dtype=np.int64)
    for v in range(m):
        if keep_mask[v]:
            c = 0
            cols = indices[indptr[v]:indptr[v + 1]]
            for t in range(cols.shape[0]):
                c += keep_mask[cols[t]]  # branch-free: a kept/dropped neighbour is a coin flip
            counts[newid[v] + 1] = c
    ip = np.cumsum(counts)
    ind = np.empty(ip[-1] + 1, dtype=indices.dtype)  # + 1: the branch-free copy writes one past a row
    dat = np.empty(ip[-1] + 1, dtype=data.dtype)
    for v in range(m):
        if keep_mask[v]:
            pos = ip[newid[v]]
            cols, wv = _row(indptr, indices, data, v)
            for t in range(cols.shape[0]):
                # write every entry, advance only past kept ones (overwritten otherwise)
                w = cols[t]
                ind[pos] = newid[w]  # fits: the subgraph has fewer vertices
                dat[pos] = wv[t]
                pos += keep_mask[w]
    return ip, ind[: ip[-1]], dat[: ip[-1]]


@nb.njit(cache=True)
def _is_clique(indptr, indices, sel, m):
    mask = np.zeros(m, dtype=np.bool_)
    for v in sel:
        mask[v] = True
    k = sel.shape[0]
    for v in sel:
        c = 0
        for t in range(indptr[v], indptr[v + 1]):
            if mask[indices[t]]:
                c += 1
        if c != k - 1:
            return False
    return True


@nb.njit(cache=True)
def _induced_adjacency(indptr, indices, sel, m):
    """Adjacency (k x k, bool) of the subgraph induced by ``sel``, diagonal True."""
    k = sel.shape[0]
    pos = np.full(m, -1, dtype=np.int64)
    for i in range(k):
        pos[sel[i]] = i
    A = np.zeros((k, k), dtype=np.bool_)
    for i in range(k):
        A[i, i] = True
        for t in range(indptr[sel[i]], indptr[sel[i] + 1]):
            j = pos[indices[t]]
            if j >= 0:
                A[i, j] = True
    return A


def _clique_cleanup(csr: tuple, sel: NDArray[np.int64], u: NDArray[np.float64]) -> NDArray[np.int64]:
    """Remove vertices with the most non-edges (ties: smallest u) until ``sel`` is a clique."""
    indptr, indices, _ = csr
    m = indptr.shape[0] - 1
    sel = np.asarray(sel, dtype=np.int64)
    if sel.size < 2 or _is_clique(indptr, indices, sel, m):
        return sel
    A = _induced_adjacency(indptr, indices, sel, m)
    alive = np.ones(sel.size, dtype=bool)
    while True:
        missing = (~A[np.ix_(alive, alive)]).sum(axis=1)
        if missing.max() == 0:
            break
        idx = np.flatnonzero(alive)
        worst = np.lexsort((u[sel[idx]], -missing))[0]
        alive[idx[worst]] = False
    return sel[alive]


def clique_density(W: sp.csr_matrix, sel: NDArray[np.int64]) -> float:
    """Objective of the densest-clique problem for a binary selection: u^T (W + I) u / u^T u."""
    W = W if isinstance(W, sp.csr_matrix) else sp.csr_matrix(W)
    sel = np.asarray(sel, dtype=np.int64).reshape(-1)
    return float(_clique_objective(W.indptr, W.indices, W.data, sel, W.shape[0]))


@nb.njit(cache=True)
def _check_graph(indptr, indices, data):
    """(all weights finite and in [0, 1], some stored entry on the diagonal, the weighted
    degrees): one pass, no copy."""
    valid = True
    diagonal = False
    m = indptr.shape[0] - 1
    wdeg = np.zeros(m)
    for r in range(m):
        s = 0.0
        cols, w = _row(indptr, indices, data, r)
        for k in range(cols.shape[0]):
            x = w[k]
            valid &= x >= 0.0 and x <= 1.0 + 1e-12
            diagonal |= cols[k] == r
            s += x
        wdeg[r] = s
    return valid, diagonal, wdeg


@nb.njit(cache=True)
def _row_sums(indptr, data):
    """Weighted degree of every vertex (CSR row sums), without a scipy temporary."""
    m = indptr.shape[0] - 1
    out = np.zeros(m)
    for r in range(m):
        s = 0.0
        w = data[indptr[r]:indptr[r + 1]]
        for k in range(w.shape[0]):
            s += w[k]
        out[r] = s
    return out


@nb.njit(cache=True)
def _clique_objective(indptr, indices, data, sel, m):
    """u^T (W + I) u / u^T u of the indicator of ``sel``: (k + sum of in-selection weights) / k."""
    k = sel.shape[0]
    if k == 0:
        return 0.0
    mask = np.zeros(m, dtype=np.bool_)
    for v in sel:
        mask[v] = True
    total = 0.0
    for v in sel:
        for t in range(indptr[v], indptr[v + 1]):
            if mask[indices[t]]:
                total += data[t]
    return (k + total) / k


@nb.njit(cache=True, inline="always")
def best_candidate(cand: NDArray[np.int64], n_cand: int, score: NDArray) -> tuple[int, float]:
    """The greedy step shared by every greedy clique kernel: the first of ``cand[:n_cand]`` with
    the highest score (-1, -1.0 when no score is positive)."""
    bi = -1
    bs = -1.0
    for c in range(n_cand):
        v = cand[c]
        if score[v] > bs:
            bs = score[v]
            bi = v
    return bi, bs


@nb.njit(cache=True)
def _greedy_core(indptr, indices, data, starts, lower_bound, max_cliques, max_work,
                 prune_to_best, skip_covered, covered, allowed, w_max):
    """Grow a greedy max-weight clique from each start, in order; returns the cliques found.

    Each step adds the candidate (adjacent to the whole clique and ``allowed``) with the largest
    summed weight to the clique. Work is bounded three ways, none of which can drop a clique that beats
    ``lower_bound`` on the objective (k + 2 W) / k <= 1 + (k - 1) w_max:
      * with ``skip_covered``, a start inside ``covered`` (given: e.g. CLIPPER's clique; updated
        with every clique grown here) is skipped: it would regrow (around) that clique;
      * a growth stops as soon as 1 + (size + candidates - 1) w_max <= the best objective so far
        (``prune_to_best``) or <= ``lower_bound``;
      * the total of edges visited stops at ``max_work``, also within a growth (deterministic,
        not a timer; a growth cut short is dropped).
    ``w_max``: the largest weight, max(0, data.max()), from the caller (numpy's max: 0.4 ms over
    W2's 2.5 M weights, where a scalar pass here took 3.4 ms).
    Returns (members, offsets, objectives, work): clique c is members[offsets[c]:offsets[c+1]]."""
    m = indptr.shape[0] - 1
    score = np.zeros(m)
    # 1: a candidate, 3: a candidate adjacent to the vertex just added, 0: neither. One uint8
    # array instead of two bool ones: the row scan below ran 1.8x slower with them (W2: 6.5 ->
    # 3.6 ms a greedy stage, the same cliques and work).
    mark = np.zeros(m, dtype=np.uint8)
    clique = np.empty(m, dtype=np.int64)
    cand = np.empty(m, dtype=np.int64)
    members = np.empty(0, dtype=np.int64)
    n_members = 0
    offsets = np.zeros(max_cliques + 1, dtype=np.int64)
    objectives = np.empty(max_cliques)
    n_found = 0
    best = lower_bound
    work = 0
    for s in starts:
        if n_found >= max_cliques or work >= max_work:
            break
        if (skip_covered and covered[s]) or 1.0 + (indptr[s + 1] - indptr[s]) * w_max <= best:
            continue
        n_cand = 0
        repeated = 0  # a column repeated in the start's row (the candidates hold it twice)
        cols, w = _row(indptr, indices, data, s)
        for t in range(cols.shape[0]):
            j = cols[t]
            score[j] = w[t] * allowed[j]  # branch-free: the other vertices keep score 0
            repeated |= mark[j]
            mark[j] = allowed[j]
            cand[n_cand] = j
            n_cand += allowed[j]
        work += indptr[s + 1] - indptr[s]
        clique[0] = s
        k = 1
        total_w = 0.0
        aborted = False
        bi, bs = best_candidate(cand, n_cand, score)
        while n_cand > 0:
            # Bound on any clique grown from here: the candidates S (j = |S|) add at most
            # their current scores (<= bs each) plus j (j - 1) / 2 w_max among themselves;
            # the objective, quasi-convex in j, is largest at j = 0 or j = n_cand.
            bound = 1.0 + (2.0 * total_w + 2.0 * n_cand * bs + n_cand * (n_cand - 1.0) * w_max) / (k + n_cand)
            if (bound <= best and (2.0 * total_w + k) / k <= best) or work >= max_work:
                aborted = True
                break
            clique[k] = bi
            k += 1
            total_w += bs
            # Keep the candidates adjacent to bi: scan bi's row once (the candidates are
            # flagged 1 already), compact, and pick the next best while compacting.
            mark[bi] = 0
            score[bi] = 0.0
            cols, w = _row(indptr, indices, data, bi)
            if n_cand * _SPARSE_SCAN < cols.shape[0]:
                # few candidates: a branch that is nearly always "not a candidate" is cheaper
                # than the stores below (for a non-candidate they store the values it has)
                for t in range(cols.shape[0]):
                    j = cols[t]
                    c = mark[j] & 1
                    if c:
                        score[j] += w[t] * c
                        mark[j] = c * 3
            else:
                for t in range(cols.shape[0]):
                    # branch-free: non-candidates (score 0) add exact zeros
                    j = cols[t]
                    c = mark[j] & 1  # (& 1: a repeated column counts as a candidate again, as before)
                    score[j] += w[t] * c
                    mark[j] = c * 3
            new_n = 0
            nbi = -1
            nbs = -1.0
            for c in range(n_cand):
                v = cand[c]
                keep = mark[v] == 3 and v != bi
                mark[v] = keep  # a candidate again (1) or not (0)
                cand[new_n] = v
                new_n += keep
                x = score[v] if keep else 0.0
                score[v] = x
                better = keep and x > nbs  # the first of the highest, as best_candidate
                nbi = v if better else nbi
                nbs = x if better else nbs
            work += (indptr[bi + 1] - indptr[bi]) + 2 * n_cand
            n_cand = new_n
            if repeated:  # a repeated candidate's second copy unflags and zeroes the first
                for c in range(n_cand):
                    mark[cand[c]] = 1
                nbi, nbs = best_candidate(cand, n_cand, score)
            bi, bs = nbi, nbs
        for c in range(n_cand):
            score[cand[c]] = 0.0
            mark[cand[c]] = 0
        if aborted:
            continue
        for c in range(k):
            covered[clique[c]] = True
        objective = (k + 2.0 * total_w) / k
        if objective <= lower_bound:
            continue
        if prune_to_best:
            if objective <= best:
                continue
            best = objective
        if n_members + k > members.shape[0]:
            bigger = np.empty(max(2 * members.shape[0], n_members + k), dtype=np.int64)
            bigger[:n_members] = members[:n_members]
            members = bigger
        members[n_members:n_members + k] = np.sort(clique[:k])
        n_members += k
        objectives[n_found] = objective
        n_found += 1
        offsets[n_found] = n_members
    return members[:n_members], offsets[: n_found + 1], objectives[:n_found], work


def _csr_parts(W: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The CSR arrays as they are (numba compiles for their dtypes): no copies or casts."""
    return W.indptr, W.indices, W.data


def greedy_start_order(W: sp.csr_matrix, n_starts: int) -> NDArray[np.int64]:
    """The ``n_starts`` vertices of largest weighted degree (ties: smaller index first)."""
    indptr, _, data = _csr_parts(W)
    wdeg = _row_sums(indptr, data)
    n = min(n_starts, wdeg.shape[0])
    if n <= 0:
        return np.zeros(0, dtype=np.int64)
    return np.argsort(-wdeg, kind="stable")[:n].astype(np.int64)


def greedy_cliques(
    W: sp.spmatrix, starts: ArrayLike, max_cliques: int | None = None, lower_bound: float = 0.0,
    max_work: int | None = None,
) -> tuple[list[NDArray[np.int64]], NDArray[np.float64]]:
    """Distinct greedy max-weight cliques grown from ``starts`` (in that order).

    A start inside an earlier clique is skipped, so every clique is distinct. Only cliques whose
    objective (k + sum of in-clique weights) / k exceeds ``lower_bound`` are kept, and a growth
    that provably cannot exceed it stops early. ``max_work`` bounds the edges
    visited (default unbounded). Returns the cliques (sorted vertex ids) and their objectives,
    in the order found. For multi-hypothesis verification: several clique hypotheses of one
    graph at the cost of a few mat-vecs."""
    W = sp.csr_matrix(W)
    starts = np.asarray(starts, dtype=np.int64).reshape(-1)
    if starts.size and (starts.min() < 0 or starts.max() >= W.shape[0]):
        raise InvalidInputError("greedy start index out of range")
    indptr, indices, data = _csr_parts(W)
    n_max = starts.size if max_cliques is None else int(max_cliques)
    budget = np.iinfo(np.int64).max if max_work is None else int(max_work)
    members, offsets, objectives, _ = _greedy_core(
        indptr, indices, data, starts, float(lower_bound), max(n_max, 0), budget, False, True,
        np.zeros(W.shape[0], dtype=np.bool_), np.ones(W.shape[0], dtype=np.bool_),
        max(0.0, float(data.max())) if data.shape[0] else 0.0,
    )
    return [members[offsets[c]:offsets[c + 1]] for c in range(len(objectives))], objectives


def solve_clipper(weights: sp.spmatrix | ConsistencyGraph, config: ClipperConfig | None = None,
                  u0: NDArray[np.float64] | None = None) -> ClipperSolution:
    """Find the densest consistent clique of a weighted consistency graph.

    ``weights``: symmetric (m x m) sparse matrix of edge weights in (0, 1], zero diagonal
    (non-zero pattern = edges), or a :class:`ConsistencyGraph`, whose compact arrays are used
    as stored (no copy). Returns the selected vertex indices, sorted. With
    ``config.greedy_starts`` > 0, greedy cliques compete with CLIPPER's on the same objective;
    they only run where they can beat it (see :func:`greedy_cliques`), within
    max(``greedy_max_work`` x nnz, ``greedy_min_work``) edge visits.
    """
    cfg = config or ClipperConfig()
    wdeg = None  # weighted degrees, from the validation pass or the graph builder
    w_max = None  # the largest weight, from the graph builder
    checked = False
    if isinstance(weights, ConsistencyGraph):
        csr = (weights.indptr, weights.indices, weights.data)
        m = weights.m
        if weights.weighted_degrees is not None and weights.weighted_degrees.shape == (m,):
            # built by build_consistency_graph: weights in (0, 1], no diagonal, degrees known
            wdeg, checked = weights.weighted_degrees, True
            w_max = weights.max_weight
    else:
        W = weights if isinstance(weights, sp.csr_matrix) else sp.csr_matrix(weights)
        if W.shape[0] != W.shape[1]:
            raise InvalidInputError(f"weights must be square, got {W.shape}")
        csr, m = _csr_parts(W), W.shape[0]
    if csr[1].shape[0] and not checked:
        valid, diagonal, wdeg = _check_graph(*csr)
        if not valid:
            raise InvalidInputError("edge weights must be finite and in [0, 1]")
        if diagonal:
            W = sp.csr_matrix((csr[2], csr[1], csr[0]), shape=(m, m), copy=True)
            W.setdiag(0)
            W.eliminate_zeros()
            csr, wdeg = _csr_parts(W), None
    sol = _solve_once(csr, m, cfg, u0)
    if cfg.greedy_starts and csr[1].shape[0]:
        _greedy_stage(csr, sol, cfg, wdeg, w_max)
    return sol


def _greedy_stage(csr: tuple, sol: ClipperSolution, cfg: ClipperConfig,
                  wdeg: NDArray[np.float64] | None = None, w_max: float | None = None) -> None:
    """Let greedy cliques compete with CLIPPER's clique (in place on ``sol``), only where they can win.

    A clique of k vertices has objective <= 1 + (k - 1) w_max, so one that beats CLIPPER's
    density needs k >= k_min and lies in the (k_min - 1)-core of the graph. The greedy cliques
    start and grow inside that core only (a mask, no copy), from the ``greedy_starts``
    best-connected core vertices: a growth that would leave the core ends in a clique too small
    to win, and a growth that can win picks only core vertices, so the restriction loses no
    winner. ``wdeg`` / ``w_max``: the weighted degrees and the largest weight when known (from
    the graph builder), else computed here."""
    indptr, indices, data = csr
    m = indptr.shape[0] - 1
    density = _clique_objective(indptr, indices, data, sol.selected, m)
    w_max = float(data.max()) if w_max is None else w_max
    k_min = int(np.floor((density - 1.0) / w_max)) + 2 if w_max > 0 else m + 1
    core = _kcore_keep(indptr, indices, k_min - 1) if k_min > 1 else np.ones(m, dtype=np.bool_)
    keep = np.flatnonzero(core)
    work = 0
    objectives = np.zeros(0)
    if keep.size >= k_min:
        wdeg = (_row_sums(indptr, data) if wdeg is None else wdeg)[keep]
        starts = keep[np.argsort(-wdeg, kind="stable")[: cfg.greedy_starts]].astype(np.int64)
        budget = max(int(cfg.greedy_max_work * indices.shape[0]), cfg.greedy_min_work)
        members, offsets, objectives, work = _greedy_core(
            indptr, indices, data, starts, density + 1e-9, starts.size, budget, True, False,
            np.zeros(m, dtype=np.bool_), core, max(w_max, 0.0),
        )
    sol.info.update(clipper_density=float(density), greedy_work=int(work),
                    greedy_cliques=int(objectives.size), greedy_core=int(keep.size))
    if objectives.size:
        c = int(np.argmax(objectives))  # first of equals, as before
        sol.selected = members[offsets[c]:offsets[c + 1]].copy()
        sol.u = np.zeros(m)
        sol.u[sol.selected] = 1.0 / np.sqrt(len(sol.selected))  # the clique's indicator
        sol.score = float(objectives[c])
        sol.info["greedy_density"] = float(objectives[c])
        sol.info["chosen"] = "greedy"
    else:
        sol.info["chosen"] = "clipper"


_STARTS: dict[int, np.ndarray] = {}


def _uniform_start(seed: int, m: int) -> NDArray[np.float64]:
    """``np.random.default_rng(seed).uniform(0, 1, m)``, read-only, from a kept stream: each
    value takes one 64-bit draw, so the first m of a longer draw are these m values bit for bit,
    and a solve skips the generator's seeding (~30-50 us, a W1 solve is ~3 ms)."""
    cached = _STARTS.get(seed)
    if cached is None or cached.shape[0] < m:
        cached = np.random.default_rng(seed).uniform(0.0, 1.0, max(m, 1024))
        cached.setflags(write=False)
        if seed not in _STARTS and len(_STARTS) >= 8:
            _STARTS.pop(next(iter(_STARTS)))  # a handful of seeds at most
        _STARTS[seed] = cached
    return cached[:m]


def _solve_once(csr: tuple, m: int, cfg: ClipperConfig,
                u0: NDArray[np.float64] | None) -> ClipperSolution:
    """CLIPPER alone on a checked graph (CSR arrays; square, weights in [0, 1], no diagonal)."""
    if m == 0:
        return ClipperSolution(np.zeros(0, np.int64), np.zeros(0), 0.0, 0, 0, 0, 0.0)
    # float32 weights (the graph builder's) are used as stored: the mat-vec streams 8 bytes per
    # non-zero instead of 12, and accumulates in float64.
    indptr, indices, data = csr
    nnz = int(indices.shape[0])
    if cfg.prune and nnz:
        order = np.argsort(-np.diff(indptr), kind="stable")
        lower_bound = _greedy_clique_size(indptr, indices, order)
        mask = _kcore_keep(indptr, indices, lower_bound - 1)
        keep = np.flatnonzero(mask)
        if keep.size < m:
            indptr, indices, data = _subgraph(indptr, indices, data, mask)
    else:
        keep = np.arange(m)
    start = _uniform_start(cfg.seed, m) if u0 is None else np.asarray(u0, dtype=float).reshape(m)
    start = np.ascontiguousarray(start[keep])
    if not np.any(start > 0):
        raise InvalidInputError("start vector must have a positive entry")
    uk, outer, inner, nmv, d, Muk = _homotopy(indptr, indices, data, start, cfg)
    u = np.zeros(m)
    u[keep] = uk
    # u^T (W + I) u from the homotopy's last (W + I) u: u's support lies in ``keep``, so those
    # entries are the whole graph's (same terms, same order) and the others meet u = 0.
    Mu = np.zeros(m)
    Mu[keep] = Muk
    score = float(u @ Mu)
    if cfg.rounding == "dsd_heu":
        k = max(1, round(score))
        sel = np.sort(np.argsort(-u, kind="stable")[:k])
        sel = sel[u[sel] > cfg.eps] if np.any(u[sel] > cfg.eps) else sel
    else:
        sel = np.flatnonzero(u > cfg.eps)
        if cfg.rounding == "clique":
            sel = np.sort(_clique_cleanup(csr, sel, u))
    return ClipperSolution(
        np.asarray(sel, dtype=np.int64), u, score, outer, inner, nmv, float(d),
        {"m": m, "m_after_pruning": int(keep.size), "nnz": nnz},
    )
