"""The fast evidence paths give exactly what the KD-tree / sorted-key specifications give, and
the per-scan evidence cache never hands one set's cloud to another."""

from __future__ import annotations

import gc

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from graffmatch.datasets.landmark_scene import make_scene_pair
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.transforms import random_transform
from graffmatch.verification import cell_hash
from graffmatch.verification import evidence as E

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _cloud(rng: np.random.Generator, n: int, scale: float, offset: float) -> np.ndarray:
    """Points on a few planes and lines plus scatter, like landmark support."""
    parts = [rng.uniform(-scale, scale, (n // 3, 3))]
    for _ in range(3):
        c = rng.uniform(-scale, scale, 3)
        u, v = np.linalg.qr(rng.normal(size=(3, 3)))[0][:, :2].T
        ab = rng.uniform(-scale / 2, scale / 2, (n // 6, 2))
        parts.append(c + ab[:, :1] * u + ab[:, 1:] * v)
    return np.concatenate(parts) + offset


def _kd_idx(points: np.ndarray, q: np.ndarray, r: float) -> np.ndarray:
    _, i = cKDTree(points).query(q, k=1, distance_upper_bound=r)
    return np.where(i < len(points), i, -1)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 400), scale=st.sampled_from([0.5, 5.0, 50.0]),
       offset=st.sampled_from([0.0, -37.3, 5e4]), r=st.floats(0.05, 2.0))
def test_cell_hash_equals_kdtree(seed, n, scale, offset, r):
    rng = np.random.default_rng(seed)
    P = _cloud(rng, max(n, 6), scale, offset)
    Q = np.concatenate([P[: len(P) // 2] + rng.normal(scale=r, size=(len(P) // 2, 3)),
                        rng.uniform(-2 * scale, 2 * scale, (50, 3)) + offset,
                        P[:5] + [r, 0, 0], [[1e300, 0, 0], [0, -1e300, 0]]])
    h = E.CellHash(P, r)
    assert h.ok
    ref = _kd_idx(P, Q, r)
    np.testing.assert_array_equal(h.query(Q), ref)
    np.testing.assert_array_equal(h.query(Q, nearest=False) >= 0, ref >= 0)
    assert h.query(np.array([[np.nan, 0.0, 0.0]]))[0] == -1  # (the KD-tree refuses NaN)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), scale=st.sampled_from([0.5, 5.0, 50.0]),
       offset=st.sampled_from([0.0, -37.3, 5e4]), r=st.floats(0.05, 2.0))
def test_moved_hit_counts_equal_kdtree(seed, scale, offset, r):
    """CellHash.hits (moved points, the 'near' bitmap filter, then the search) counts exactly
    the points the KD-tree finds within r, for transforms and their inverses."""
    rng = np.random.default_rng(seed)
    P = _cloud(rng, 240, scale, offset)
    Q = P[rng.permutation(len(P))[:150]] + rng.normal(scale=r, size=(150, 3))
    Ts = np.stack([np.eye(4)] + [random_transform(rng, max_translation=r * 3) for _ in range(4)])
    Ts[1:, :3, 3] += offset - Ts[1:, :3, :3] @ np.full(3, offset)  # turn about the cloud, not the origin
    h = E.CellHash(P, r)
    for inverse in (False, True):
        got = h.hits(Q, Ts, inverse)
        for k, T in enumerate(Ts):
            R, t = (T[:3, :3].T, -T[:3, :3].T @ T[:3, 3]) if inverse else (T[:3, :3], T[:3, 3])
            assert got[k] == np.count_nonzero(_kd_idx(P, Q @ R.T + t, r) >= 0)
    if scale / r < 50:  # a box of < ~5e6 voxels (planes reach ~1.7 scale out): the filter is built and exercised
        assert len(h.near_bitmap()[0]) > 0


def test_clouds_too_far_out_fall_back_to_the_kdtree():
    rng = np.random.default_rng(1)
    P = _cloud(rng, 200, 5.0, 1e12)
    cloud = E.SupportCloud(P)
    Q = P + rng.normal(scale=0.2, size=P.shape)
    np.testing.assert_array_equal(cloud.neighbours(Q, 0.3), _kd_idx(P, Q, 0.3))
    assert not cloud._hashes[0.3].ok


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), H=st.integers(1, 12), offset=st.sampled_from([0.0, 1e5, 3e5]))
def test_occupancy_overlap_equals_sorted_key_reference(seed, H, offset):
    rng = np.random.default_rng(seed)
    a = E.SupportCloud(_cloud(rng, 300, 20.0, offset))
    b = E.SupportCloud(_cloud(rng, 300, 20.0, offset))
    Ts = np.stack([random_transform(rng, max_translation=3.0) for _ in range(H)])
    np.testing.assert_array_equal(E.occupancy_overlap(a, b, Ts, 0.3), E._occupancy_overlap_reference(a, b, Ts, 0.3))


def test_occupancy_bitmap_and_hash_table_agree_with_the_reference():
    """A box too large for the bitmap (two clusters 3 km apart) takes the hash table; both
    answer what the sorted-key reference answers."""
    rng = np.random.default_rng(5)
    near = _cloud(rng, 300, 20.0, 0.0)
    far = np.concatenate([near, _cloud(rng, 300, 20.0, 3000.0)])
    Ts = np.stack([random_transform(rng, max_translation=3.0) for _ in range(6)] + [np.eye(4)])
    for pts, bitmap in ((near, True), (far, False)):
        a, b = E.SupportCloud(pts + rng.normal(scale=0.05, size=pts.shape)), E.SupportCloud(pts)
        assert (len(b.occupied_table(0.3)[2]) > 0) == bitmap
        got = E.occupancy_overlap(a, b, Ts, 0.3)
        np.testing.assert_array_equal(got, E._occupancy_overlap_reference(a, b, Ts, 0.3))
        assert got[-1].min() > 0.9  # the identity explains nearly everything: the test is not empty


def _align_reference(source, target, T, distances=(1.0, 0.6, 0.4, 0.3, 0.3)):
    """align_on_evidence as it was specified: scipy KD-tree nearest neighbours."""
    T = np.array(T, dtype=np.float64)
    P = source.points
    tree = cKDTree(target.points)
    for d_max in distances:
        q = P @ T[:3, :3].T + T[:3, 3]
        d, idx = tree.query(q, k=1, distance_upper_bound=d_max)
        m = np.isfinite(d)
        if m.sum() < 10:
            break
        a, b = P[m], target.points[idx[m]]
        ca, cb = a.mean(0), b.mean(0)
        U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
        R = Vt.T @ D @ U.T
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, cb - R @ ca
    return T


def _small(rng: np.random.Generator) -> np.ndarray:
    """A perturbation of a few degrees and decimetres."""
    from graffmatch.geometry.transforms import make_transform, rot_z

    return make_transform(rot_z(np.radians(rng.uniform(-4, 4))), rng.uniform(-0.5, 0.5, 3))


def test_align_and_point_overlap_equal_the_kdtree_versions():
    for seed in range(4):
        rng = np.random.default_rng(seed)
        P = _cloud(rng, 900, 15.0, 0.0)
        T_true = random_transform(rng, max_translation=5.0)
        Pt = (P - T_true[:3, 3]) @ T_true[:3, :3]  # source frame
        src = E.SupportCloud(Pt + rng.normal(scale=0.03, size=P.shape))
        tgt = E.SupportCloud(P[rng.permutation(len(P))[:700]])
        T0 = T_true @ _small(rng)
        T = E.align_on_evidence(src, tgt, T0)
        # the compiled steps sum in another order than numpy: equal up to rounding
        np.testing.assert_allclose(T, _align_reference(src, tgt, T0), rtol=0, atol=1e-12)
        np.testing.assert_allclose(T, E._align_on_evidence_reference(src, tgt, T0), rtol=0, atol=1e-12)
        assert np.abs(T - T0).max() > 1e-3  # the alignment moved: the comparison is not trivial
        q = src.points @ T[:3, :3].T + T[:3, 3]
        p = (tgt.points - T[:3, 3]) @ T[:3, :3]
        ref = (np.mean(_kd_idx(tgt.points, q, 0.3) >= 0), np.mean(_kd_idx(src.points, p, 0.3) >= 0))
        assert E.point_overlap(src, tgt, T, 0.3) == ref
        assert ref[0] > 0.8  # the test exercises real overlap, not empty clouds


def _with_support(ls: LandmarkSet, seed: int) -> LandmarkSet:
    """The set with 40 support points per landmark, spread over its line or plane."""
    rng = np.random.default_rng(seed)
    pts = [ls.anchors[i] + rng.uniform(-3, 3, (40, 2)) @ ls.bases[i].T for i in range(len(ls))]
    return LandmarkSet(ls.types, ls.bases, ls.anchors, ls.attributes, np.concatenate(pts),
                       np.arange(len(ls) + 1) * 40)


def test_evidence_cache_reuses_a_set_and_never_confuses_sets():
    cache = E.EvidenceCache(max_entries=4)
    source = _with_support(make_scene_pair(15, 30, seed=0).source, 0)
    a = cache.support_cloud(source)
    assert a is not None and cache.misses == 1
    assert cache.support_cloud(source) is a and cache.hits == 1
    np.testing.assert_array_equal(a.points, E.support_cloud(source).points)
    sub = source[np.arange(len(source) // 2)]  # new arrays: its own cloud
    b = cache.support_cloud(sub)
    assert b is not a and len(b) < len(a)
    assert cache.support_cloud(source, voxel=0.5) is not a  # other settings, other entry
    n = len(cache)
    del sub, b
    gc.collect()
    assert len(cache) == n - 1  # the entry died with the set's arrays
    for seed in range(1, 6):  # bounded
        cache.support_cloud(_with_support(make_scene_pair(5, 10, seed=seed).target, seed))
    assert len(cache) <= 4


def test_evidence_cache_notices_points_changed_in_place():
    cache = E.EvidenceCache()
    source = _with_support(make_scene_pair(15, 30, seed=1).source, 1)
    a = cache.support_cloud(source)
    source.points[:] += 100.0  # same array objects, new content
    b = cache.support_cloud(source)
    assert b is not a
    np.testing.assert_array_equal(b.points, E.support_cloud(source).points)


def test_dense_table_and_hash_give_the_same_neighbours(monkeypatch):
    rng = np.random.default_rng(3)
    P = _cloud(rng, 600, 10.0, 12.5)
    Q = P + rng.normal(scale=0.4, size=P.shape)
    dense = E.CellHash(P, 0.3)
    monkeypatch.setattr(cell_hash, "_DENSE_MAX", 0)
    hashed = E.CellHash(P, 0.3)
    assert len(dense.dense) > 0 and len(hashed.dense) == 0
    ref = _kd_idx(P, Q, 0.3)
    np.testing.assert_array_equal(dense.query(Q), ref)
    np.testing.assert_array_equal(hashed.query(Q), ref)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n_poles=st.integers(0, 10), n_planes=st.integers(1, 20),
       H=st.integers(1, 8), noise=st.sampled_from([0.0, 0.05, 1.0]))
def test_landmark_overlap_equals_the_numpy_reference(seed, n_poles, n_planes, H, noise):
    sc = make_scene_pair(n_poles, n_planes, seed=seed % 1000)
    rng = np.random.default_rng(seed)
    Ts = np.stack([sc.T_target_source] + [random_transform(rng, 2.0) for _ in range(H - 1)])
    Ts[0, :3, 3] += rng.normal(scale=noise, size=3)
    c_new: list = []
    c_ref: list = []
    new = E.landmark_overlap(sc.source, sc.target, Ts, counts=c_new)
    ref = E._landmark_overlap_reference(sc.source, sc.target, Ts, counts=c_ref)
    # Fractions in [0, 1] summed in another order: 1.1e-12 apart was seen (random seed 140), so
    # 1e-10 (a hundred times that) while the counts below must agree exactly.
    np.testing.assert_allclose(new, ref, rtol=0, atol=1e-10)
    np.testing.assert_array_equal(c_new[0], c_ref[0])
    one = E.landmark_overlap(sc.source, sc.target, Ts[0])
    assert one.shape == (2,) and np.allclose(one, ref[0], rtol=0, atol=1e-10)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 300), scale=st.sampled_from([0.5, 5.0, 50.0]),
       offset=st.sampled_from([0.0, -37.3, 1e5]), voxel=st.sampled_from([0.1, 0.3, 0.77]))
def test_occupancy_bitmap_equals_the_table_of_the_sorted_keys(seed, n, scale, offset, voxel):
    """The bitmap built straight from the points is bit for bit the one built from the sorted
    voxel keys (same origin, low corner and dims)."""
    P = _cloud(np.random.default_rng(seed), max(n, 6), scale, offset)
    built = cell_hash.occupancy_bitmap(P, voxel)
    ref_cloud = E.SupportCloud(P)
    ref = cell_hash.occupancy_lookup(ref_cloud.occupied(voxel))
    if len(ref[2]) == 0:  # too large for a bitmap: both take the hash table
        assert built is None
        return
    origin, table = built
    np.testing.assert_array_equal(origin, ref_cloud.occupancy_origin)
    for got, want in zip(table, ref, strict=True):
        np.testing.assert_array_equal(got, want)
    assert np.count_nonzero(table[2]) > 0
    want = cell_hash._occupancy_bitmap_reference(P, voxel)  # the compiled build = its numpy one
    assert want is not None and want[0].tobytes() == origin.tobytes()
    for got, w in zip(table, want[1], strict=True):
        assert got.dtype == w.dtype and got.tobytes() == w.tobytes()


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(0, 50), voxel=st.sampled_from([0.1, 0.3, 1e-6]),
       bad=st.sampled_from([None, np.nan, np.inf, 1e300]))
def test_occupancy_bitmap_edge_cases_equal_the_numpy_build(seed, n, voxel, bad):
    """Empty clouds, non-finite or far coordinates, boxes too large: None exactly where the
    numpy build gives None, the same arrays elsewhere."""
    P = np.random.default_rng(seed).normal(0, 5, (n, 3))
    if bad is not None and n:
        P[n // 2, n % 3] = bad
    got, want = cell_hash.occupancy_bitmap(P, voxel), cell_hash._occupancy_bitmap_reference(P, voxel)
    assert (got is None) == (want is None)
    if got is not None:
        assert got[0].tobytes() == want[0].tobytes()
        for g, w in zip(got[1], want[1], strict=True):
            assert g.tobytes() == w.tobytes()


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(0, 400), neighbours=st.integers(0, 3),
       cell=st.sampled_from([(1.0, 1.0), (2.0, 0.5), (30.0, 30.0), (7.0, 3.0)]))
def test_range_image_equals_the_minimum_filter_reference(seed, n, neighbours, cell):
    from graffmatch.verification.free_space import RangeImage

    rng = np.random.default_rng(seed)
    P = rng.normal(scale=20.0, size=(n, 3))
    P[: n // 4, 2] = rng.choice([-1e3, 1e3], n // 4)  # elevations at the image's top and bottom rows
    if n > 2:
        P[0] = [np.nan, 0.0, 0.0]
    got = RangeImage.from_points(P, *cell, neighbours)
    want = RangeImage._from_points_reference(P, *cell, neighbours)
    np.testing.assert_array_equal(got.ranges, want.ranges)
    assert n < 3 or np.isfinite(got.ranges).sum() >= min(n // 2, 1)


@SETTINGS
@given(keys=st.lists(st.integers(0, 2**62 - 1) | st.integers(0, 20), max_size=300))
def test_first_of_each_equals_numpy_unique(keys):
    k = np.array(keys, dtype=np.int64)
    want = np.zeros(len(k), bool)
    want[np.unique(k, return_index=True)[1]] = True
    np.testing.assert_array_equal(E.first_of_each(k), want)


def test_voxel_downsample_keeps_the_first_point_of_each_voxel():
    rng = np.random.default_rng(2)
    P = np.r_[rng.uniform(-20, 20, (3000, 3)), [[np.nan, 0, 0]]]
    got = E.voxel_downsample(P, 0.7, 10**6)
    keys = np.floor(P[:-1] / 0.7).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    np.testing.assert_array_equal(got, P[np.sort(first)])
    assert 1000 < len(got) < 3000


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(0, 400), scale=st.sampled_from([0.5, 5.0, 50.0, 3e3]),
       offset=st.sampled_from([0.0, -37.3, 5e4, 1e9]), r=st.floats(0.05, 2.0), bad=st.booleans())
def test_compiled_cell_hash_build_equals_the_numpy_build(seed, n, scale, offset, r, bad):
    """Same cells, order, runs, dense table or hash, and 'near' bitmap as the argsort build."""
    P = _cloud(np.random.default_rng(seed), n, scale, offset) if n else np.zeros((0, 3))
    if bad and len(P):
        P[len(P) // 2, 1] = np.nan
    got, want = E.CellHash(P, r), E.CellHash._reference(P, r)
    assert got.ok == want.ok
    if not want.ok:
        return
    for name in ("origin", "dims", "order", "points", "starts", "dense", "tk"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
    np.testing.assert_array_equal(got.tv[got.tk >= 0], want.tv[want.tk >= 0])  # (other slots unset)
    for g, w in zip(got.near_bitmap(), want._near_bitmap_reference(), strict=True):
        np.testing.assert_array_equal(g, w)
    assert len(got.dense) > 0 or len(got.tk) > 0


@SETTINGS
@given(rows=st.lists(st.tuples(st.sampled_from([0.0, -0.0, 0.25, 0.5, 1.0, np.inf]),
                               st.sampled_from([1.0, 2.5, 2.5, 7.0, -0.0]), st.booleans(), st.integers(2, 5)),
                     min_size=1, max_size=40),
       by=st.sampled_from(["score", "objective"]))
def test_rank_order_equals_the_sorted_key_reference(rows, by):
    from graffmatch.verification.decision import Hypothesis, _rank_order, _rank_order_reference

    hyps = [Hypothesis(np.eye(4), np.zeros((k, 2), np.int64), "greedy", obj, 1.0, deg, score=sc)
            for sc, obj, deg, k in rows]
    assert _rank_order(hyps, by) == _rank_order_reference(hyps, by)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(0, 500), scale=st.sampled_from([0.5, 20.0, 1e4]),
       offset=st.sampled_from([0.0, -37.3, 1e7]), voxel=st.sampled_from([0.05, 0.3, 1.1]),
       cap=st.sampled_from([5, 100, 10**6]), bad=st.booleans())
def test_voxel_downsample_equals_its_numpy_path(seed, n, scale, offset, voxel, cap, bad):
    rng = np.random.default_rng(seed)
    P = _cloud(rng, n, scale, offset) if n >= 6 else rng.normal(size=(n, 3))
    if bad and len(P) > 2:
        P[1, 2] = np.inf
        P[2, 0] = np.nan
    want = P[np.all(np.isfinite(P), axis=1)]
    if len(want):
        keys = np.floor(want / voxel).astype(np.int64)
        want = want[np.sort(np.unique(keys, axis=0, return_index=True)[1])]
        if len(want) > cap:
            want = want[np.linspace(0, len(want) - 1, cap).astype(np.int64)]
    np.testing.assert_array_equal(E.voxel_downsample(P, voxel, cap), want)


@SETTINGS
@given(st.integers(0, 10_000), st.sampled_from([0.05, 0.3, 0.5, 1.0, 2.0]), st.sampled_from([0.0, 1e3]))
def test_cell_hash_and_near_bitmap_equal_their_numpy_specifications(seed, r, offset):
    """The compiled constructor (counting sort by cell, points gathered in the same pass) and
    the 'near' bitmap (3-bit masks per voxel column) build exactly the numpy specifications:
    the same cells, order, points and bits, on clouds with points on cell boundaries too."""
    rng = np.random.default_rng(seed)
    P = _cloud(rng, 600, 20.0, offset)
    P[:50] = np.round(P[:50] / (2 * r)) * (2 * r)  # on cell edges
    h, ref = cell_hash.CellHash(P, r), cell_hash.CellHash._reference(P, r)
    assert h.ok and ref.ok
    for name in ("origin", "dims", "order", "starts", "dense", "points", "tk"):
        np.testing.assert_array_equal(getattr(h, name), getattr(ref, name), err_msg=name)
    assert h.points.flags.c_contiguous
    bits, lo, dims, inv = h.near_bitmap()
    rbits, rlo, rdims, rinv = h._near_bitmap_reference()
    assert inv == rinv and (len(bits) > 0 or r < 0.3)  # (too many voxels at 5 cm: no bitmap)
    np.testing.assert_array_equal(lo, rlo)
    np.testing.assert_array_equal(dims, rdims)
    np.testing.assert_array_equal(bits, rbits)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), angle=st.sampled_from([0.0, 1e-9, 1e-4, 0.05, 1.0, 3.1415]),
       same=st.booleans(), nan=st.booleans())
def test_transform_gap_equals_its_reference_bit_for_bit(seed, angle, same, nan):
    from graffmatch.verification.decision import _transform_gap_reference, transform_gap

    rng = np.random.default_rng(seed)
    A = random_transform(rng, max_translation=20.0)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    dR = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    B = A.copy()
    if not same:
        B[:3, :3] = dR @ A[:3, :3]
        B[:3, 3] += rng.normal(size=3)
    if nan:
        B[0, 0] = np.nan
    got, want = transform_gap(A, B), _transform_gap_reference(A, B)
    assert np.array(got).tobytes() == np.array(want).tobytes()
    assert all(isinstance(x, float) for x in got)
