"""The dense-row greedy clique kernel grows exactly the cliques of the CSR kernel."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from graffmatch.association import cliques as C


def _graph(rng: np.random.Generator, m: int, density: float, ties: bool) -> sp.csr_matrix:
    A = np.triu(rng.random((m, m)) < density, 1)
    w = np.round(rng.random((m, m)), 1) if ties else rng.random((m, m))  # ties: equal scores
    W = np.where(A, w + 0.05, 0.0)
    W = W + W.T
    M = sp.csr_matrix(W.astype(np.float32))
    return M


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), m=st.integers(1, 120), density=st.floats(0.02, 0.9), ties=st.booleans(),
       restrict=st.booleans())
def test_dense_greedy_kernel_equals_the_csr_kernel(seed, m, density, ties, restrict):
    rng = np.random.default_rng(seed)
    W = _graph(rng, m, density, ties)
    indptr, indices, data = C._csr64(W)
    starts = rng.permutation(m).astype(np.int64)
    allowed = rng.random(m) < 0.7 if restrict else np.ones(m, bool)
    a_flat, a_off = C._grow_cliques(indptr, indices, data, starts, allowed)
    b_flat, b_off = C._grow_cliques_dense(indptr, indices, data, starts, allowed)
    np.testing.assert_array_equal(a_off, b_off)
    np.testing.assert_array_equal(a_flat, b_flat)
    assert len(a_off) - 1 == int(allowed[starts].sum())


def test_dense_greedy_kernel_keeps_repeated_and_zero_entries_as_stored():
    """CSR with a repeated entry (the last weight counts) and an explicit zero (still a
    neighbour): both kernels read them alike."""
    rng = np.random.default_rng(4)
    W = _graph(rng, 40, 0.5, False).tocoo()
    rows = np.r_[W.row, 3, 5, 7, 9]
    cols = np.r_[W.col, 5, 3, 9, 7]
    vals = np.r_[W.data, 0.0, 0.0, 5.0, 5.0]
    order = np.argsort(rows, kind="stable")
    indptr = np.searchsorted(rows[order], np.arange(41)).astype(np.int64)
    indices, data = cols[order].astype(np.int64), vals[order].astype(np.float64)
    starts = np.arange(40, dtype=np.int64)
    allowed = np.ones(40, bool)
    a = C._grow_cliques(indptr, indices, data, starts, allowed)
    b = C._grow_cliques_dense(indptr, indices, data, starts, allowed)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert any(7 in a[0][a[1][i]:a[1][i + 1]] and 9 in a[0][a[1][i]:a[1][i + 1]] for i in range(40))


def test_greedy_cliques_are_sorted_distinct_and_in_order_of_first_appearance():
    rng = np.random.default_rng(9)
    W = _graph(rng, 80, 0.4, True)
    starts = rng.permutation(80).astype(np.int64)
    got = C.greedy_cliques(W, starts)  # dense kernel (>= 32 starts)
    indptr, indices, data = C._csr64(W)
    flat, off = C._grow_cliques(indptr, indices, data, starts, np.ones(80, bool))
    want: list = []
    for i in range(len(off) - 1):
        c = np.sort(flat[off[i]:off[i + 1]])
        if not any(np.array_equal(c, w) for w in want):
            want.append(c)
    assert len(got) == len(want) < 80
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
