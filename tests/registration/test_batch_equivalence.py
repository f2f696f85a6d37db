"""register_batch (numba) against the numpy reference: same transforms, conditioning and residuals.

Tolerances: 1e-9, relative to the size of the numbers compared (a transform's translation,
anchors of tens of metres); kappa relative 1e-9 with inf kept inf. Angle residuals agree to
1e-9 degrees or their cosines to 1e-13: arccos turns a one-ulp difference of a cosine near 1
into up to 1e-6 degrees (small angles), which no two implementations (or LAPACK builds) share.
A group may exceed these only where the reference itself moves as much when its weights are
jittered by 1e-13 (``ref_sensitivity``: a nearly degenerate correlation turned one-ulp
differences into 3e-8 of a rotation on a random street scene), and in at most a tenth of the
groups of an example.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from graffmatch.datasets.landmark_scene import make_scene_pair
from graffmatch.errors import DegenerateGeometryError, InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.transforms import random_transform
from graffmatch.registration import closed_form as cf

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def ref_sensitivity(source, target, A, g, w, kappa_max, n_groups, ref) -> dict[str, np.ndarray]:
    """How far the reference itself moves when the weights move by 1e-13 (relative), per group:
    rotation, relative kappas and translation. A group whose correlation is nearly degenerate
    turns one-ulp differences of two implementations into far more than 1e-9 (seen: 3e-8 in a
    rotation, seed 29), so each group may differ by 10x this (a 1e-13 jitter is ~1,000 ulp)
    where that exceeds the fixed tolerance. A group whose discrete choices (signs, ranks,
    degeneracy) flip under the jitter is ill posed at this level: infinite tolerance."""
    A = np.asarray(A).reshape(-1, 2)
    g = np.asarray(g)
    base = np.ones(len(A)) if w is None else np.asarray(w, float)
    jitter = 1 + 1e-13 * np.random.default_rng(0).standard_normal(len(A))
    other = cf._register_batch_reference(source, target, A, g, base * jitter, kappa_max, n_groups)
    G = len(ref)
    flip = np.zeros(G, bool)
    np.logical_or.at(flip, g[g >= 0], (other.signs != ref.signs)[g >= 0])
    for name in ("degenerate", "rotation_rank", "translation_rank", "used_line_positions"):
        flip |= getattr(other, name) != getattr(ref, name)
    out = {"R": np.abs(other.T_target_source[:, :3, :3] - ref.T_target_source[:, :3, :3]).max((1, 2)),
           "t": np.abs(other.T_target_source[:, :3, 3] - ref.T_target_source[:, :3, 3]).max(1)}
    for name in ("kappa", "kappa_rotation", "kappa_translation"):
        a, b = getattr(other, name), getattr(ref, name)
        rel = np.zeros(G)
        fin = np.isfinite(a) & np.isfinite(b) & (b != 0)
        rel[fin] = np.abs(a[fin] - b[fin]) / np.abs(b[fin])
        flip |= np.isinf(a) != np.isinf(b)
        out[name] = rel
    for v in out.values():
        v[flip] = np.inf
    return {k: 10 * v for k, v in out.items()}


def assert_same(new: cf.BatchRegistration, ref: cf.BatchRegistration, source: LandmarkSet,
                target: LandmarkSet, A: np.ndarray, g: np.ndarray,
                slack: dict[str, np.ndarray] | None = None) -> None:
    G = len(ref)
    assert len(new) == G
    for name in ("degenerate", "rotation_rank", "translation_rank", "used_line_positions"):
        np.testing.assert_array_equal(getattr(new, name), getattr(ref, name), err_msg=name)
    np.testing.assert_array_equal(new.signs, ref.signs)
    strict = np.ones(G, bool)  # groups within the fixed tolerances
    kappas = {}
    for name in ("kappa", "kappa_rotation", "kappa_translation"):
        a, b = getattr(new, name), getattr(ref, name)
        np.testing.assert_array_equal(np.isinf(a), np.isinf(b), err_msg=name)
        fin = np.isfinite(b)
        rel = np.zeros(G)
        rel[fin] = np.abs(a[fin] - b[fin]) / np.maximum(np.abs(b[fin]), 1e-300)
        kappas[name] = rel
        strict &= rel <= 1e-9
    # scale of the numbers each group's results are made of: anchors and translation
    anchors = np.maximum(np.abs(source.anchors[A[:, 0]]).max(1), np.abs(target.anchors[A[:, 1]]).max(1))
    scale = np.ones(G)
    np.maximum.at(scale, g, anchors)
    scale = scale + np.abs(ref.T_target_source[:, :3, 3]).max(1)
    dR = np.abs(new.T_target_source[:, :3, :3] - ref.T_target_source[:, :3, :3]).max((1, 2))
    dt = np.abs(new.T_target_source[:, :3, 3] - ref.T_target_source[:, :3, 3]).max(1)
    dc = np.abs(new.cost - ref.cost)
    strict &= (dR <= 1e-9) & (dt <= 1e-9 * scale) & (dc <= 1e-9 + 1e-12 * scale**2)
    do = np.abs(new.offset_residuals - ref.offset_residuals) <= 1e-9 * scale[g]
    a, b = new.angle_residuals_deg, ref.angle_residuals_deg
    da = (np.abs(a - b) <= 1e-9) | (np.abs(np.cos(np.radians(a)) - np.cos(np.radians(b))) <= 1e-13)
    ok_rows = np.ones(G, bool)
    np.logical_and.at(ok_rows, g[g >= 0], (do & da)[g >= 0])
    strict &= ok_rows
    # a group beyond them must be one the reference itself cannot hold to that (its own move
    # under a 1e-13 jitter, x10, covers the difference), and such groups stay rare
    bad = np.flatnonzero(~strict)
    for k in bad.tolist():
        assert slack is not None, f"group {k}: dR {dR[k]:.3g}, dt {dt[k]:.3g}, kappa {kappas['kappa'][k]:.3g}"
        assert dR[k] <= max(1e-9, slack["R"][k]) and dt[k] <= max(1e-9 * scale[k], slack["t"][k]), (
            k, dR[k], slack["R"][k], dt[k], slack["t"][k])
        for name in kappas:
            assert kappas[name][k] <= max(1e-9, slack[name][k]), (k, name, kappas[name][k], slack[name][k])
    assert len(bad) <= max(1, G // 10), f"{len(bad)} of {G} groups beyond the fixed tolerances"


def both(source, target, A, g, w=None, n_groups=None, **kw):
    new, reasons = cf._register_batch_numba(
        source, target, A, g, w, kw.get("kappa_max", 1e3), n_groups, 0.03, 0.01, 1e-2)
    ref = cf._register_batch_reference(source, target, A, g, w, kw.get("kappa_max", 1e3), n_groups)
    slack = ref_sensitivity(source, target, A, g, w, kw.get("kappa_max", 1e3), n_groups, ref)
    assert_same(new, ref, source, target, np.asarray(A).reshape(-1, 2), np.asarray(g), slack)
    assert_same(cf.register_batch(source, target, A, g, w, kw.get("kappa_max", 1e3), n_groups),
                ref, source, target, np.asarray(A).reshape(-1, 2), np.asarray(g), slack)
    return reasons


def random_groups(rng, k_total_max, sizes_max, G):
    sizes = rng.integers(1, sizes_max + 1, G)
    return sizes[np.cumsum(sizes) <= k_total_max] if sizes[0] <= k_total_max else sizes[:1]


def same_type_pairs(rng, source, target, k, true_matches=None, p_true=0.7):
    """k associations: true matches (if any) mixed with random same-type pairs."""
    out = []
    for _ in range(k):
        if true_matches is not None and len(true_matches) and rng.random() < p_true:
            out.append(true_matches[rng.integers(len(true_matches))])
            continue
        i = rng.integers(len(source))
        cand = np.flatnonzero(target.types == source.types[i])
        if len(cand) == 0:
            continue
        out.append([i, cand[rng.integers(len(cand))]])
    return np.array(out, np.int64).reshape(-1, 2)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), noise=st.sampled_from([0.0, 0.5, 1.0]),
       n_outliers=st.sampled_from([0, 5]), G=st.integers(1, 40), max_size=st.sampled_from([2, 8, 40]),
       p_true=st.sampled_from([1.0, 0.7, 0.3]), weighted=st.booleans(), extra_groups=st.integers(0, 2))
def test_street_scenes(seed, noise, n_outliers, G, max_size, p_true, weighted, extra_groups):
    sc = make_scene_pair(10, 20, seed=seed % 1000, anchor_noise=0.05 * noise, angle_noise_deg=noise,
                         n_outliers=n_outliers)
    rng = np.random.default_rng(seed)
    sizes = rng.integers(1, max_size + 1, G)
    A = np.concatenate([same_type_pairs(rng, sc.source, sc.target, s, sc.true_matches, p_true)
                        for s in sizes])
    g = np.repeat(np.arange(G), sizes)[: len(A)]
    if rng.random() < 0.5:  # groups need not be contiguous
        perm = rng.permutation(len(A))
        A, g = A[perm], g[perm]
    w = None
    if weighted:
        w = rng.uniform(0, 3, len(A)) * (rng.random(len(A)) > 0.2)
        w[np.unique(g, return_index=True)[1]] += 0.1  # every group keeps a positive weight
    both(sc.source, sc.target, A, g, w, n_groups=int(g.max()) + 1 + extra_groups)


def _random_set(rng, n, types):
    dirs = rng.normal(size=(n, 3))
    return LandmarkSet.from_arrays(types, dirs, rng.uniform(-30, 30, (n, 3)))


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), kinds=st.sampled_from(["mixed", "points", "lines", "planes"]),
       G=st.integers(1, 30), max_size=st.sampled_from([1, 2, 3, 10, 40]),
       noise=st.sampled_from([0.0, 1e-3, 0.05]))
def test_random_landmark_sets(seed, kinds, G, max_size, noise):
    rng = np.random.default_rng(seed)
    n = 40
    types = {"mixed": rng.integers(0, 3, n), "points": np.zeros(n, int), "lines": np.ones(n, int),
             "planes": np.full(n, 2)}[kinds]
    tgt = _random_set(rng, n, types)
    T = random_transform(rng, 20.0)
    src = tgt.transform(np.linalg.inv(T))
    if noise:
        src = LandmarkSet.from_arrays(src.types, src.directions + rng.normal(0, noise, (n, 3)),
                                      src.anchors + rng.normal(0, noise, (n, 3)))
    flips = rng.choice([-1.0, 1.0], n)
    src = LandmarkSet.from_arrays(src.types, src.directions * flips[:, None], src.anchors)
    true = np.stack([np.arange(n)] * 2, 1)
    sizes = rng.integers(1, max_size + 1, G)
    A = np.concatenate([same_type_pairs(rng, src, tgt, s, true, 0.8) for s in sizes])
    g = np.repeat(np.arange(G), sizes)
    both(src, tgt, A, g)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n_poles=st.integers(1, 12), tilt=st.sampled_from([0.0, 1e-9, 0.01]),
       with_points=st.booleans(), with_plane=st.booleans())
def test_parallel_poles_and_point_groups(seed, n_poles, tilt, with_points, with_plane):
    """Vertical poles only (positions fix the yaw), exactly or nearly parallel; points-only groups."""
    rng = np.random.default_rng(seed)
    dirs = np.tile([0.0, 0.0, 1.0], (n_poles, 1)) + rng.normal(0, tilt, (n_poles, 3))
    anchors = np.c_[rng.uniform(-20, 20, (n_poles, 2)), rng.uniform(0, 3, n_poles)]
    types = [1] * n_poles
    if with_points:
        dirs = np.r_[dirs, np.zeros((5, 3))]
        anchors = np.r_[anchors, rng.uniform(-10, 10, (5, 3))]
        types += [0] * 5
    if with_plane:
        dirs = np.r_[dirs, [[0.0, 0.0, 1.0]]]
        anchors = np.r_[anchors, [[0.0, 0.0, 0.0]]]
        types += [2]
    tgt = LandmarkSet.from_arrays(np.array(types), dirs, anchors)
    T = random_transform(rng, 15.0)
    src = tgt.transform(np.linalg.inv(T))
    n = len(tgt)
    idx = np.arange(n)
    poles = idx[:n_poles]
    groups = [poles, poles[: 2], poles[:1], poles[::-1]]
    if with_points:
        pts = idx[n_poles:n_poles + 5]
        groups += [pts, pts[:3], pts[:2], np.r_[poles[:1], pts[:3]]]
    if with_plane:
        groups += [np.r_[poles, n - 1], np.array([n - 1])]
    A = np.concatenate([np.stack([gr, gr], 1) for gr in groups])
    g = np.concatenate([np.full(len(gr), i) for i, gr in enumerate(groups)])
    both(src, tgt, A, g)


def test_fast_path_covers_noisy_street_hypotheses():
    """Realistic groups (noisy street scene, 6-10 associations, a fifth of them wrong, some
    landmarks twice) rarely need the reference."""
    sc = make_scene_pair(15, 30, seed=3)
    rng = np.random.default_rng(3)
    sizes = rng.integers(6, 11, 300)
    A = np.concatenate([same_type_pairs(rng, sc.source, sc.target, s, sc.true_matches, 0.8)
                        for s in sizes])
    g = np.repeat(np.arange(300), sizes)
    reasons = both(sc.source, sc.target, A, g)
    assert np.count_nonzero(reasons) <= 6


def test_fragile_groups_are_solved_by_the_reference():
    """Exactly parallel poles without positions, a single plane and an empty group are fragile."""
    rng = np.random.default_rng(0)
    tgt = LandmarkSet.from_arrays(np.array([1, 1, 2, 2]), np.tile([0.0, 0.0, 1.0], (4, 1)),
                                  rng.uniform(-5, 5, (4, 3)))
    A = np.array([[0, 0], [1, 1], [2, 2], [2, 2], [3, 3]])
    g = np.array([0, 0, 1, 2, 2])
    reasons = both(tgt, tgt, A, g, n_groups=4)
    assert reasons[3] == 1 and np.all(reasons[1:] != 0)


@pytest.mark.parametrize("case", ["empty", "bad_group", "neg_group", "index", "type", "weight", "zero_weight"])
def test_errors_match_the_reference(case):
    ls = LandmarkSet.from_arrays(np.array([2, 1]), np.array([[0, 0, 1.0], [1, 0, 0]]), np.zeros((2, 3)))
    args = {
        "empty": (np.zeros((0, 2), int), None, None, None),
        "bad_group": ([[0, 0], [1, 1]], [0], None, None),
        "neg_group": ([[0, 0], [1, 1]], [0, -1], None, None),
        "index": ([[0, 0], [1, 5]], None, None, None),
        "type": ([[0, 1]], None, None, None),
        "weight": ([[0, 0], [1, 1]], None, [1.0, np.nan], None),
        "zero_weight": ([[0, 0], [1, 1]], [0, 1], [1.0, 0.0], None),
    }[case]
    errs = []
    for f in (cf.register_batch, cf._register_batch_reference):
        with pytest.raises((InvalidInputError, DegenerateGeometryError)) as info:
            f(ls, ls, args[0], args[1], args[2])
        errs.append((type(info.value), str(info.value)))
    assert errs[0] == errs[1]
    with pytest.raises(InvalidInputError):
        cf.register_batch(ls, ls, [[0, 0], [1, 1]], [0, 3], None, 1e3, 2)


def test_deterministic():
    sc = make_scene_pair(10, 20, seed=1)
    A = np.concatenate([sc.true_matches] * 3)
    g = np.repeat(np.arange(3), len(sc.true_matches))
    a, b = cf.register_batch(sc.source, sc.target, A, g), cf.register_batch(sc.source, sc.target, A, g)
    for name in ("T_target_source", "kappa", "cost", "offset_residuals", "signs"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_directions_cache_follows_bases_changed_in_place():
    """register_batch caches each set's directions; bases edited in place are noticed."""
    sc = make_scene_pair(10, 20, seed=2)
    A = sc.true_matches
    before = cf.register_batch(sc.source, sc.target, A).T_target_source[0]
    R = random_transform(np.random.default_rng(0))[:3, :3]
    sc.source.bases[:] = R @ sc.source.bases  # rotate every basis, same array object
    after = cf.register_batch(sc.source, sc.target, A).T_target_source[0]
    fresh = cf._register_batch_reference(sc.source, sc.target, A).T_target_source[0]
    np.testing.assert_allclose(after[:3, :3], fresh[:3, :3], atol=1e-9)
    assert np.abs(after[:3, :3] - before[:3, :3]).max() > 1e-3


_FIELDS = ("T_target_source", "kappa", "kappa_rotation", "kappa_translation", "degenerate", "rotation_rank",
           "translation_rank", "cost", "used_line_positions", "angle_residuals_deg", "offset_residuals", "signs")


def _bit_equal(a: cf.BatchRegistration, b: cf.BatchRegistration) -> list[str]:
    """Fields of two results that differ in any bit."""
    return [f for f in _FIELDS if np.asarray(getattr(a, f)).tobytes() != np.asarray(getattr(b, f)).tobytes()]


def _near_parallel_pair(rng, n: int, spread: float, types: np.ndarray) -> tuple[LandmarkSet, LandmarkSet]:
    base = rng.normal(size=3)
    dirs = (base / np.linalg.norm(base) + spread * rng.normal(size=(n, 3))) * rng.choice([-1.0, 1.0], (n, 1))
    tgt = LandmarkSet.from_arrays(types, dirs, rng.uniform(-30, 30, (n, 3)))
    src = tgt.transform(np.linalg.inv(random_transform(rng, 20.0)))
    src = LandmarkSet.from_arrays(src.types, src.directions + rng.normal(0, 1e-3, (n, 3)),
                                  src.anchors + rng.normal(0, 0.05, (n, 3)))
    return src, tgt


@pytest.mark.parametrize("seed", range(4))
def test_exact_path_equals_the_reference_bit_for_bit(seed: int) -> None:
    """_solve_exactly (the reference's arithmetic without its numpy overheads, for one group
    without centred rows) gives the reference's result in every bit, on groups of planes and
    lines from parallel (rank-deficient correlations) to spread directions; and register_batch
    on one rank-deficient group (FRAGILE_REASONS 32), which takes that path, too."""
    rng = np.random.default_rng(seed)
    n_exact = n_fragile = 0
    for it in range(60):
        n = 10
        types = [np.full(n, 2), np.ones(n, np.int64), rng.integers(1, 3, n)][it % 3]
        spread = [0.0, 1e-9, 1e-6, 1e-3, 0.05, 1.0][it % 6]
        src, tgt = _near_parallel_pair(rng, n, spread, types)
        m = int(rng.integers(1, 7))
        i = rng.choice(n, m)
        j = np.array([rng.choice(np.flatnonzero(tgt.types == src.types[x])) if rng.random() < 0.3 else x for x in i])
        A = np.stack([i, j], 1)
        w = None if it % 2 else rng.uniform(0.1, 3.0, m)
        ref = cf._register_batch_reference(src, tgt, A, None, w, 1e3, 1)
        ww = np.ones(m) if w is None else w
        ds, dt = cf._directions_of(src)[i], cf._directions_of(tgt)[j]
        ts = src.types[i].astype(np.int64)
        bs, bt = src.anchors[i].astype(float), tgt.anchors[j].astype(float)
        reasons, seeds, centred = np.zeros(1, np.int64), np.full((1, 2), -1, np.int64), np.zeros(1, np.bool_)
        cf._register_kernel(np.array([0, m]), ww, ts, ds, dt, bs, bt, 0.03, 0.01, 1e-2, cf.UPRIGHT_MIN,
                            np.empty((1, 3, 3)), np.empty((1, 3)), np.zeros((1, 3)), np.zeros((1, 3)), np.zeros(1),
                            np.zeros(1, np.bool_), np.empty(m), np.empty(m), np.empty(m), reasons, seeds, centred)
        if not reasons[0] & 7 and not centred[0]:
            sub = cf._solve_exactly(ww, ts, ds, dt, bs, bt, int(seeds[0, 0]), int(seeds[0, 1]), 1e3, 0.01, 1e-2,
                                    cf.UPRIGHT_MIN)
            if sub is not None:
                n_exact += 1
                assert _bit_equal(sub, ref) == [], (it, reasons)
        out, r = cf._register_batch_numba(src, tgt, A, None, w, 1e3, None, 0.03, 0.01, 1e-2)
        if r[0]:
            n_fragile += 1
            assert _bit_equal(out, ref) == [], (it, r)
    assert n_exact >= 20 and n_fragile >= 5, (n_exact, n_fragile)


def test_parallel_planes_take_the_exact_path() -> None:
    """Three near-parallel planes (a KITTI street's walls): the correlation is rank-deficient
    (reason 32 alone), register_batch solves the group without the numpy reference and returns
    the reference's result bit for bit."""
    n = np.array([[-0.0365, 0.9987, -0.0349], [0.0491, -0.9978, 0.0437], [0.043, -0.9989, 0.0192]])
    tgt = LandmarkSet.from_arrays(np.full(3, 2), n, np.array([[3.0, 8.0, 0.5], [-4.0, -7.5, 1.0], [10.0, -8.2, 0.2]]))
    src = tgt.transform(np.linalg.inv(random_transform(np.random.default_rng(1), 5.0)))
    src = LandmarkSet.from_arrays(src.types, src.directions + 1e-3 * np.eye(3)[[0, 2, 1]], src.anchors)
    A = np.stack([np.arange(3)] * 2, 1)
    _, reasons = cf._register_batch_numba(src, tgt, A, None, None, 1e3, None, 0.03, 0.01, 1e-2)
    assert reasons.tolist() == [32]
    called = []
    orig = cf._register_batch_reference
    cf._register_batch_reference = lambda *a, **k: called.append(1) or orig(*a, **k)
    try:
        out = cf.register_batch(src, tgt, A)
    finally:
        cf._register_batch_reference = orig
    assert called == []
    assert _bit_equal(out, orig(src, tgt, A, None, None, 1e3, 1)) == []


def _street_walls(rng, n_parallel: int, tilt: float):
    """A street's landmarks: ``n_parallel`` near-parallel walls (normal y, either sign), two
    walls across them (normals x and diagonal), the ground and a pole, moved by a random
    transform."""
    normals = np.tile([0.0, 1.0, 0.0], (n_parallel, 1)) + rng.normal(0, tilt, (n_parallel, 3))
    normals *= rng.choice([-1.0, 1.0], (n_parallel, 1))
    dirs = np.r_[normals, [[1.0, 0.0, 0.0], [0.7071, 0.7071, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]]
    n = n_parallel + 4
    anchors = np.c_[rng.uniform(-20, 20, n), rng.uniform(-8, 8, n), rng.uniform(0, 3, n)]
    tgt = LandmarkSet.from_arrays(np.r_[np.full(n - 1, 2), 1], dirs, anchors)
    src = tgt.transform(np.linalg.inv(random_transform(rng, 15.0)))
    src = LandmarkSet.from_arrays(src.types, src.directions + rng.normal(0, 1e-3, (n, 3)) * (tilt > 0),
                                  src.anchors + rng.normal(0, 0.02, (n, 3)))
    return src, tgt


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n_parallel=st.integers(2, 5), tilt=st.sampled_from([0.0, 1e-9, 1e-4]))
def test_degenerate_groups_keep_the_kernels_result(seed: int, n_parallel: int, tilt: float) -> None:
    """``reference_degenerate=False``: a degenerate group fragile only for its conditioning keeps
    the kernel's result. It is still a proper rotation (exactly parallel walls included), maps
    every direction onto its counterpart as the reference's does (within 1e-6: second order in
    the tilt), and is degenerate like it; every other group is bit for bit the default's. What
    the two give along the free axes is not compared: it hangs on the arbitrary choice (seen:
    costs 30x apart either way on noisy walls; translations metres apart where three parallel
    walls put both millions of metres out). Groups: the parallel walls (a free rotation), the walls (a free
    height), everything and the walls across with the ground (well posed)."""
    rng = np.random.default_rng(seed)
    src, tgt = _street_walls(rng, n_parallel, tilt)
    n = len(tgt)
    par = np.arange(n_parallel)
    groups = [par, par[:2], np.arange(n - 2), np.arange(n), np.r_[n - 4, n - 3, n - 2], par[::-1]]
    A = np.concatenate([np.stack([gr, gr], 1) for gr in groups])
    g = np.concatenate([np.full(len(gr), i) for i, gr in enumerate(groups)])
    default, reasons = cf._register_batch_numba(src, tgt, A, g, None, 1e3, None, 0.03, 0.01, 1e-2)
    fast = cf.register_batch(src, tgt, A, g, reference_degenerate=False)
    kept = (reasons != 0) & ((reasons & ~cf.CONDITIONING_REASONS) == 0) & (default.kappa > 1e3)
    assert not kept[3] and not kept[4], reasons  # well posed
    for name in _FIELDS:
        sel = ~kept[g] if name in ("angle_residuals_deg", "offset_residuals", "signs") else ~kept
        np.testing.assert_array_equal(getattr(fast, name)[sel], getattr(default, name)[sel], err_msg=name)
    np.testing.assert_array_equal(fast.degenerate, default.degenerate)
    ds, dt = cf._directions_of(src)[A[:, 0]], cf._directions_of(tgt)[A[:, 1]]
    for gi in np.flatnonzero(kept):
        R = fast.T_target_source[gi, :3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert abs(np.linalg.det(R) - 1.0) < 1e-12
        rows = g == gi
        dots = np.abs(np.einsum("ij,ij->i", dt[rows], ds[rows] @ R.T))
        ref_dots = np.abs(np.einsum("ij,ij->i", dt[rows], ds[rows] @ default.T_target_source[gi, :3, :3].T))
        np.testing.assert_allclose(dots, ref_dots, atol=1e-6)


def test_degenerate_groups_skip_the_reference() -> None:
    """The street's three near-parallel walls (reason 32 alone): with
    ``reference_degenerate=False`` neither the reference nor its exact path runs, and the
    same inputs give the same bits twice."""
    n = np.array([[-0.0365, 0.9987, -0.0349], [0.0491, -0.9978, 0.0437], [0.043, -0.9989, 0.0192]])
    tgt = LandmarkSet.from_arrays(np.full(3, 2), n, np.array([[3.0, 8.0, 0.5], [-4.0, -7.5, 1.0], [10.0, -8.2, 0.2]]))
    src = tgt.transform(np.linalg.inv(random_transform(np.random.default_rng(1), 5.0)))
    src = LandmarkSet.from_arrays(src.types, src.directions + 1e-3 * np.eye(3)[[0, 2, 1]], src.anchors)
    A = np.stack([np.arange(3)] * 2, 1)
    called = []
    orig_ref, orig_exact = cf._register_batch_reference, cf._solve_exactly
    cf._register_batch_reference = lambda *a, **k: called.append("ref") or orig_ref(*a, **k)
    cf._solve_exactly = lambda *a, **k: called.append("exact") or orig_exact(*a, **k)
    try:
        a = cf.register_batch(src, tgt, A, reference_degenerate=False)
        b = cf.register_batch(src, tgt, A, reference_degenerate=False)
    finally:
        cf._register_batch_reference, cf._solve_exactly = orig_ref, orig_exact
    assert called == []
    assert _bit_equal(a, b) == []
    assert bool(a.degenerate[0]) and a.kappa_rotation[0] > 1e3
