"""Sparse consistency graph: equals a brute-force construction; one-to-one; no dense m x m."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from graffmatch.association.consistency_graph import build_consistency_graph
from graffmatch.association.putative import all_to_all, count_all_to_all
from graffmatch.datasets.landmark_scene import make_scene_pair
from graffmatch.errors import InvalidInputError
from graffmatch.geometry.distance import pairwise_distances


def _brute(D_i, D_j, assoc, eps, sigma):
    m = len(assoc)
    W = np.zeros((m, m))
    for u in range(m):
        for v in range(m):
            a, b = assoc[u]
            a2, b2 = assoc[v]
            if u == v or a == a2 or b == b2:
                continue
            c = abs(D_i[a, a2] - D_j[b, b2])
            if c < eps:
                W[u, v] = np.exp(-c * c / (2 * sigma * sigma))
    return W


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_all_to_all_graph_equals_bruteforce(seed):
    sc = make_scene_pair(5, 8, seed=seed)
    Di, Dj = pairwise_distances(sc.source), pairwise_distances(sc.target)
    g = build_consistency_graph(Di, Dj, types_i=sc.source.types, types_j=sc.target.types)
    assert np.array_equal(g.associations, all_to_all(sc.source.types, sc.target.types))
    assert g.m == count_all_to_all(sc.source.types, sc.target.types)
    W = _brute(Di, Dj, g.associations, 0.2, 0.05)
    assert np.allclose(g.weights.toarray(), W, atol=1e-7)  # float32 weights
    # explicit list path gives the same graph
    g2 = build_consistency_graph(Di, Dj, associations=g.associations)
    assert np.allclose(g2.weights.toarray(), W, atol=1e-7)


def test_one_to_one_and_true_matches_are_connected():
    sc = make_scene_pair(8, 16, seed=4, anchor_noise=0.0, angle_noise_deg=0.0)
    g = build_consistency_graph(pairwise_distances(sc.source), pairwise_distances(sc.target),
                                types_i=sc.source.types, types_j=sc.target.types)
    W = g.weights.tocoo()
    A = g.associations
    assert not np.any(A[W.row, 0] == A[W.col, 0]) and not np.any(A[W.row, 1] == A[W.col, 1])
    idx = {tuple(a): i for i, a in enumerate(A.tolist())}
    true = [idx[tuple(t)] for t in sc.true_matches.tolist()]
    sub = g.weights[true][:, true].toarray()
    k = len(true)
    assert np.count_nonzero(sub) == k * (k - 1)  # the true associations form a clique
    assert np.allclose(sub[~np.eye(k, dtype=bool)], 1.0)  # noiseless: c = 0, w = 1


def test_bad_inputs():
    with pytest.raises(InvalidInputError):
        build_consistency_graph(np.zeros((2, 3)), np.zeros((2, 2)), types_i=[1, 1], types_j=[1, 1])
    with pytest.raises(InvalidInputError):
        build_consistency_graph(np.full((2, 2), np.nan), np.zeros((2, 2)), types_i=[1, 1], types_j=[1, 1])
    with pytest.raises(InvalidInputError):
        build_consistency_graph(np.zeros((2, 2)), np.zeros((2, 2)), associations=[[0, 5]])


@pytest.mark.parametrize(("epsilon", "sigma"), [(0.2, 0.05), (0.1, 0.5), (3.0, 0.05)])
def test_vectorised_exp_matches_numpy(epsilon, sigma):
    """The fill's branch-free exp: relative error <= 1e-12 over the whole argument range, and
    the float32 weights equal np.exp's (at most 1 in 10^5 differs by one float32 ulp)."""
    from graffmatch.association.consistency_graph import _exp_nonpositive, _squarings

    inv = 1.0 / (2.0 * sigma * sigma)
    c = np.random.default_rng(3).uniform(-epsilon, epsilon, 200_000)
    x = -c * c * inv
    out = np.empty_like(x)
    _exp_nonpositive(x, out, x.size, _squarings(epsilon, inv))
    ref = np.exp(x)
    ok = ref > 1e-290
    assert np.max(np.abs(out[ok] - ref[ok]) / ref[ok]) < 1e-12
    assert np.count_nonzero(out.astype(np.float32) != ref.astype(np.float32)) <= 2


def test_compact_storage_is_six_bytes_per_nonzero_and_equals_int32():
    """uint16 indices + float32 weights (m <= 65,536); the scipy view widens them once, in place;
    compact=False stores int32 from the start; both hold the same graph."""
    sc = make_scene_pair(6, 10, seed=1)
    Di, Dj = pairwise_distances(sc.source), pairwise_distances(sc.target)
    g = build_consistency_graph(Di, Dj, types_i=sc.source.types, types_j=sc.target.types)
    ref = build_consistency_graph(Di, Dj, types_i=sc.source.types, types_j=sc.target.types, compact=False)
    assert g.indices.dtype == np.uint16 and g.data.dtype == np.float32
    assert ref.indices.dtype == np.int32
    assert g.indices.nbytes + g.data.nbytes == 6 * g.data.size
    assert g.n_edges == ref.n_edges > 0 and g.m == ref.m
    assert np.array_equal(g.indptr, ref.indptr) and np.array_equal(g.indices, ref.indices)
    assert np.array_equal(g.data, ref.data)
    W = g.weights
    assert g.indices.dtype == np.int32 and np.shares_memory(W.data, g.data)
    assert (W != ref.weights).nnz == 0 and (W != W.T).nnz == 0


def test_row_order_is_source_landmark_then_target_distance():
    """Row u = (a, b) lists, for a2 = 0, 1, ... (a2 != a), the associations (a2, b2) of b2 in
    ascending D_j[b, b2] (ties: b2): the order the solver's sums were checked with."""
    sc = make_scene_pair(5, 9, seed=7)
    Di, Dj = pairwise_distances(sc.source), pairwise_distances(sc.target)
    ti, tj = sc.source.types, sc.target.types
    full = all_to_all(ti, tj)
    assoc = full[np.random.default_rng(0).random(len(full)) < 0.7]  # gated-like subset
    g = build_consistency_graph(Di, Dj, assoc, types_i=ti, types_j=tj)
    vid = {(int(a), int(b)): u for u, (a, b) in enumerate(assoc)}
    for u, (a, b) in enumerate(assoc.tolist()):
        expected = []
        for a2 in range(len(ti)):
            if a2 == a:
                continue
            b2s = [b2 for b2 in range(len(tj)) if b2 != b and tj[b2] == ti[a2] and (a2, b2) in vid
                   and abs(Di[a, a2] - Dj[b, b2]) < 0.2]
            expected += [vid[(a2, b2)] for b2 in sorted(b2s, key=lambda b2: (Dj[b, b2], b2))]
        row = g.indices[g.indptr[u]:g.indptr[u + 1]].tolist()
        assert row == expected
    assert g.n_edges > 100


def test_matcher_builds_compact_graph_only_without_verification(monkeypatch):
    """match() without verification solves on the compact (uint16) graph; with verification,
    whose hypotheses read graph.weights, the graph is int32 from the start (no widening copy)."""
    import graffmatch.matcher as gm
    from graffmatch.verification.config import VerificationConfig

    seen = []
    build = gm.build_consistency_graph
    monkeypatch.setattr(gm, "build_consistency_graph", lambda *a, **k: seen.append(build(*a, **k)) or seen[-1])
    sc = make_scene_pair(6, 12, seed=2)
    a = gm.GraffMatcher(gm.GraffMatchConfig(verification=VerificationConfig(enabled=False))).match(sc.source, sc.target)
    assert seen[-1].indices.dtype == np.uint16
    b = gm.GraffMatcher().match(sc.source, sc.target)
    assert seen[-1].indices.dtype == np.int32
    assert a.n_edges == b.n_edges > 0


@pytest.mark.parametrize("gated", [False, True])
def test_stored_windows_give_the_same_graph_as_merging_twice(monkeypatch, gated):
    """The filling pass reads the windows the counting pass stored (small tables; taken from
    _query_windows' table where runs are short, else merged per row) or merges the sorted runs
    again (tables over _MAX_WINDOW_TABLE_BYTES): the same CSR and degrees, bit for bit,
    all-to-all and for an explicit (gated) association list."""
    import graffmatch.association.consistency_graph as cg

    sc = make_scene_pair(9, 14, seed=2)
    Di, Dj = pairwise_distances(sc.source), pairwise_distances(sc.target)
    assoc = all_to_all(sc.source.types, sc.target.types)
    kw = dict(types_i=sc.source.types, types_j=sc.target.types)
    if gated:
        kw["associations"] = assoc[np.random.default_rng(0).random(len(assoc)) < 0.6]
    by_query = build_consistency_graph(Di, Dj, **kw)
    monkeypatch.setattr(cg, "_COUNT_MAX_RUN", 0)  # the Python-side choice only: rows merged per row
    stored = build_consistency_graph(Di, Dj, **kw)
    monkeypatch.setattr(cg, "_MAX_WINDOW_TABLE_BYTES", 0)
    merged = build_consistency_graph(Di, Dj, **kw)
    assert stored.n_edges == merged.n_edges > 100
    for name in ("indptr", "indices", "data", "weighted_degrees"):
        assert np.array_equal(getattr(stored, name), getattr(merged, name))
        assert np.array_equal(getattr(by_query, name), getattr(merged, name))
    assert np.allclose(stored.weighted_degrees, np.asarray(stored.weights.astype(np.float64).sum(axis=1)).ravel(), rtol=1e-12)


def test_vertex_ids_from_row_bases_equal_the_lookup_table(monkeypatch):
    """All-to-all graphs read vertex ids as row base + column rank along the sorted runs; the
    lookup table gives the same CSR bit for bit, and a reordered explicit list (ids not laid
    out that way) falls back to it and still equals the brute force."""
    import graffmatch.association.consistency_graph as cg

    sc = make_scene_pair(7, 12, seed=5)
    Di, Dj = pairwise_distances(sc.source), pairwise_distances(sc.target)
    kw = dict(types_i=sc.source.types, types_j=sc.target.types)
    fast = build_consistency_graph(Di, Dj, **kw)
    ids = cg._affine_ids(*_lookup_and_groups(fast, sc))
    assert ids[0] is not None
    monkeypatch.setattr(cg, "_affine_ids", lambda *a: (None, None))
    slow = build_consistency_graph(Di, Dj, **kw)
    for name in ("indptr", "indices", "data", "weighted_degrees"):
        assert np.array_equal(getattr(fast, name), getattr(slow, name))
    monkeypatch.undo()
    perm = np.random.default_rng(1).permutation(fast.m)
    shuffled = build_consistency_graph(Di, Dj, associations=fast.associations[perm], **kw)
    lut = np.full((len(sc.source), len(sc.target)), -1)
    lut[shuffled.associations[:, 0], shuffled.associations[:, 1]] = np.arange(fast.m)
    assert cg._affine_ids(lut, sc.source.types.astype(np.int64), sc.target.types.astype(np.int64))[0] is None
    assert np.allclose(shuffled.weights.toarray(), fast.weights.toarray()[np.ix_(perm, perm)], atol=0)


def _lookup_and_groups(g, sc):
    lut = np.full((len(sc.source), len(sc.target)), -1)
    lut[g.associations[:, 0], g.associations[:, 1]] = np.arange(g.m)
    return lut, sc.source.types.astype(np.int64), sc.target.types.astype(np.int64)


def test_compiled_affine_layout_equals_the_numpy_definition():
    """_affine_ids (compiled) gives the numpy definition's row bases and column ranks, and None
    exactly when some same-group pair's id is not row_base + col_rank."""
    import graffmatch.association.consistency_graph as cg

    def reference(lookup, gi, gj):
        n_groups = int(max(gi.max(initial=0), gj.max(initial=0))) + 1
        col_rank = np.zeros(gj.shape[0], dtype=np.int64)
        first_b = np.full(n_groups, -1, dtype=np.int64)
        for t in range(n_groups):
            b = np.flatnonzero(gj == t)
            col_rank[b] = np.arange(b.size)
            if b.size:
                first_b[t] = b[0]
        fb = first_b[gi]
        row_base = np.where(fb >= 0, lookup[np.arange(gi.shape[0]), np.maximum(fb, 0)], 0).astype(np.int64)
        same = gi[:, None] == gj[None, :]
        if not np.array_equal((row_base[:, None] + col_rank[None, :])[same], lookup[same]):
            return None, None
        return row_base, col_rank

    rng = np.random.default_rng(6)
    outcomes = set()
    for trial in range(40):
        gi, gj = rng.integers(0, 3, rng.integers(2, 30)), rng.integers(0, 3, rng.integers(2, 30))
        assoc = all_to_all(gi, gj)
        if trial % 2:
            assoc = assoc[rng.permutation(len(assoc))]
        lookup = np.full((gi.size, gj.size), -1, dtype=np.int32)
        lookup[assoc[:, 0], assoc[:, 1]] = np.arange(len(assoc))
        got, ref = cg._affine_ids(lookup, gi, gj), reference(lookup, gi, gj)
        outcomes.add(ref[0] is None)
        assert (got[0] is None) == (ref[0] is None)
        if ref[0] is not None:
            assert np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])
    assert outcomes == {True, False}


@pytest.mark.parametrize("n_j", [20, 90])
def test_row_windows_equal_searchsorted(n_j):
    """_row_windows' ends (counted on runs <= _COUNT_MAX_RUN, merged on longer ones) equal
    np.searchsorted's on every target run, ties included (distances on a 0.05 grid)."""
    import graffmatch.association.consistency_graph as cg

    rng = np.random.default_rng(n_j)
    n_i, eps = 20, 0.2

    def dist(n):
        D = np.round(rng.uniform(0, 5, (n, n)) / 0.05) * 0.05
        D = np.triu(D, 1)
        return D + D.T

    Di, Dj = dist(n_i), dist(n_j)
    gi, gj = rng.integers(0, 2, n_i), (rng.random(n_j) < 0.15).astype(np.int64)  # runs of ~0.85 n_j
    assert (max(np.bincount(gj)) > cg._COUNT_MAX_RUN) == (n_j > 64)
    vals, _, start = cg._row_pair_tables(Dj, gj, 2)
    src_vals, src_a2s, src_start = cg._row_pair_tables(Di, gi, 2)
    win0, win1 = np.zeros(n_i, dtype=np.int64), np.zeros(n_i, dtype=np.int64)
    for a in range(n_i):
        for b in range(n_j):
            cg._row_windows(src_vals, src_a2s, src_start, vals, start, a, b, 2, eps, win0, win1)
            for a2 in range(n_i):
                if a2 == a:
                    continue
                lo, hi = start[b, gi[a2]], start[b, gi[a2] + 1]
                run = vals[lo:hi]
                assert win0[a2] == lo + np.searchsorted(run, Di[a, a2] - eps, "right")
                assert win1[a2] == lo + np.searchsorted(run, Di[a, a2] + eps, "left")


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_i=st.integers(1, 30), n_j=st.integers(1, 90), n_groups=st.integers(1, 3),
       grid=st.booleans())
def test_query_windows_equal_the_row_windows(seed, n_i, n_j, n_groups, grid):
    """_query_windows (one merge per target landmark and group over sorted source distances)
    gives every same-group pair (a, b) the ends of _row_windows (counted or merged per row), and
    so np.searchsorted's: ties (distances on a 0.05 grid), empty groups, runs over
    _COUNT_MAX_RUN and single landmarks."""
    import graffmatch.association.consistency_graph as cg

    rng = np.random.default_rng(seed)
    eps = 0.2

    def dist(n):
        D = rng.uniform(0, 5, (n, n))
        D = np.round(D / 0.05) * 0.05 if grid else D
        D = np.triu(D, 1)
        return D + D.T

    Di, Dj = dist(n_i), dist(n_j)
    gi, gj = rng.integers(0, n_groups, n_i), rng.integers(0, n_groups, n_j)
    vals, _, start = cg._row_pair_tables(Dj, gj, n_groups)
    src_vals, src_a2s, src_start = cg._row_pair_tables(Di, gi, n_groups)
    qwin0, qwin1, boff, pos = cg._query_windows(Di, gi, gj, vals, start, n_groups, eps)
    assert qwin0.size == cg._window_table_entries(gi, gj, n_i)
    win0, win1 = np.zeros(n_i, dtype=np.int64), np.zeros(n_i, dtype=np.int64)
    got0, got1 = np.zeros(n_i, dtype=np.int64), np.zeros(n_i, dtype=np.int64)
    for b in range(n_j):
        for a in np.flatnonzero(gi == gj[b]):
            cg._row_windows(src_vals, src_a2s, src_start, vals, start, a, b, n_groups, eps, win0, win1)
            cg._stored_windows(qwin0, qwin1, boff[b], pos[a], a, got0, got1)
            others = np.arange(n_i) != a
            assert np.array_equal(got0[others], win0[others]) and np.array_equal(got1[others], win1[others])
            for a2 in np.flatnonzero(others):
                lo, hi = start[b, gi[a2]], start[b, gi[a2] + 1]
                assert got0[a2] == lo + np.searchsorted(vals[lo:hi], Di[a, a2] - eps, "right")
                assert got1[a2] == lo + np.searchsorted(vals[lo:hi], Di[a, a2] + eps, "left")


def test_weights_and_degrees_equal_their_definition_bit_for_bit():
    """Every stored weight is float32(_exp_nonpositive(-(D_i[a, a2] - D_j[b, b2])^2 / (2 sigma^2)))
    and every weighted degree the sequential float64 sum of its row's stored weights, bit for bit
    (whatever the build's loop structure)."""
    from graffmatch.association.consistency_graph import _exp_nonpositive, _squarings

    sc = make_scene_pair(12, 24, seed=3)
    Di, Dj = pairwise_distances(sc.source), pairwise_distances(sc.target)
    g = build_consistency_graph(Di, Dj, types_i=sc.source.types, types_j=sc.target.types)
    rows = np.repeat(np.arange(g.m), np.diff(g.indptr))
    A = g.associations
    c = Di[A[rows, 0], A[g.indices, 0]] - Dj[A[rows, 1], A[g.indices, 1]]
    inv = 1.0 / (2.0 * 0.05 * 0.05)
    x = -c * c * inv
    w = np.empty_like(x)
    _exp_nonpositive(x, w, x.size, _squarings(0.2, inv))
    assert g.n_edges > 1000 and np.array_equal(g.data, w.astype(np.float32))
    seq = np.array([np.cumsum(g.data[g.indptr[u]:g.indptr[u + 1]].astype(np.float64))[-1]
                    if g.indptr[u + 1] > g.indptr[u] else 0.0 for u in range(g.m)])
    assert np.array_equal(g.weighted_degrees, seq)


def _sums_in_order(g) -> np.ndarray:
    out = np.zeros(g.m)
    for u in range(g.m):
        s = 0.0
        for w in g.data[g.indptr[u]:g.indptr[u + 1]].astype(np.float64).tolist():
            s += w
        out[u] = s
    return out


def test_row_sums_in_any_order_equal_the_sums_in_order():
    """The build sums a row's float32 weights reassociated only where no partial sum can round
    (smallest >= n x largest x 2**-29), so the degrees equal the in-order sums bit for bit; rows
    outside that bound (a wide epsilon: weights down to exp(-72)), float64 weights and
    adversarial rows are summed in order. ``max_weight`` is the largest stored weight."""
    import math

    from graffmatch.association.consistency_graph import _EXACT_SUM_SCALE, _row_sum_any_order

    rng = np.random.default_rng(4)
    bounds = np.zeros(2, dtype=np.float32)
    for n, lo in ((1, 0.5), (7, 1e-3), (900, 3.4e-4), (4000, 3.4e-4), (4000, 4000 * _EXACT_SUM_SCALE)):
        w = rng.uniform(lo, 1.0, n).astype(np.float32)
        w[0] = np.float32(lo)
        w[-1] = 1.0
        s = _row_sum_any_order(w, bounds)
        assert bounds[0] == w.min() and bounds[1] == w.max()
        seq = 0.0
        for x in w.astype(np.float64).tolist():
            seq += x
        assert s == seq == math.fsum(w.astype(np.float64))
    sc = make_scene_pair(10, 16, seed=1)
    Di, Dj = pairwise_distances(sc.source), pairwise_distances(sc.target)
    kw = dict(types_i=sc.source.types, types_j=sc.target.types)
    for extra in ({}, {"epsilon": 0.6}, {"dtype": np.float64}):
        g = build_consistency_graph(Di, Dj, **kw, **extra)
        assert g.n_edges > 100
        assert np.array_equal(g.weighted_degrees, _sums_in_order(g))
        assert g.max_weight == float(g.data.max())
    assert float(build_consistency_graph(Di, Dj, epsilon=0.6, **kw).data.min()) < 1e-20  # outside the bound
    empty = build_consistency_graph(Di[:1, :1], Dj[:1, :1], **dict(types_i=kw["types_i"][:1], types_j=kw["types_j"][:1]))
    assert empty.n_edges == 0 and empty.max_weight == 0.0
