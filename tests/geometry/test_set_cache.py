"""Per-set derived values (graffmatch.geometry.set_cache): computed once per set of arrays,
recomputed for other or edited arrays; the matcher's cached distances and landmark-level
evidence equal the uncached ones."""

from __future__ import annotations

import numpy as np

from graffmatch.datasets.landmark_scene import make_scene_pair
from graffmatch.geometry.distance import pairwise_distances
from graffmatch.geometry.set_cache import DerivedCache, derived_cache
from graffmatch.matcher import GraffMatcher
from graffmatch.verification import evidence as E


def test_value_is_kept_for_the_same_arrays_and_recomputed_otherwise():
    cache = DerivedCache(max_entries=2)
    a, b = np.arange(5.0), np.ones(3)
    calls = []

    def make():
        calls.append(1)
        return float(a.sum() + b.sum())

    assert cache.get("x", (a, b), make) == 13.0
    assert cache.get("x", (a, b), make) == 13.0
    assert len(calls) == 1 and cache.hits == 1
    a[0] = 100.0  # edited in place: same ids, other contents
    assert cache.get("x", (a, b), make) == 113.0
    assert len(calls) == 2
    assert cache.get("x", (a.copy(), b), lambda: -1.0) == -1.0  # another array: its own entry
    assert cache.get("y", (a, None), lambda: 7) == 7
    assert len(cache) == 2  # least recently used dropped
    cache.clear()
    assert len(cache) == 0


def test_byte_budget_drops_the_least_recently_used():
    cache = DerivedCache(max_entries=100, max_bytes=3 * 8000 + 100)
    arrays = [np.full(500, float(i)) for i in range(4)]  # 4 kB each, value 4 kB: 8 kB an entry
    for a in arrays:
        cache.get("z", (a,), lambda a=a: a * 2)
    assert len(cache) == 3 and cache.nbytes <= cache.max_bytes
    calls = []
    cache.get("z", (arrays[0],), lambda: calls.append(1) or arrays[0] * 2)  # the oldest was dropped
    assert calls == [1]


def test_matcher_distances_are_cached_read_only_and_exact():
    pair = make_scene_pair(n_poles=8, n_planes=12, seed=3)
    m = GraffMatcher()
    derived_cache.clear()
    D1 = m.distance_matrix(pair.source)
    D2 = m.distance_matrix(pair.source)
    assert D1 is D2 and not D1.flags.writeable
    np.testing.assert_array_equal(D1, pairwise_distances(pair.source, m.config.rho, m.config.variant))


def test_landmark_overlap_with_cache_equals_without():
    rng = np.random.default_rng(0)
    for seed in range(6):
        pair = make_scene_pair(n_poles=6 + seed, n_planes=10 + seed, seed=seed)
        Ts = np.tile(np.eye(4), (20, 1, 1))
        Ts[:, :3, 3] = rng.normal(0, 1.0, (20, 3))
        Ts[0] = pair.T_target_source
        derived_cache.clear()
        c1: list = []
        first = E.landmark_overlap(pair.source, pair.target, Ts, counts=c1)
        c2: list = []
        again = E.landmark_overlap(pair.source, pair.target, Ts, counts=c2)  # from the cache
        c3: list = []
        ref = E._landmark_overlap_reference(pair.source, pair.target, Ts, counts=c3)
        np.testing.assert_array_equal(first, again)
        np.testing.assert_array_equal(c1[0], c2[0])
        np.testing.assert_allclose(first, ref, atol=1e-12)
        np.testing.assert_array_equal(c1[0], c3[0])


def test_match_with_warm_caches_equals_cold():
    """A scan matched against several candidates (the loop detector's warm path) gets what a
    fresh process gets: transforms bit for bit, the same decision, overlap and confidence."""
    m = GraffMatcher()
    pairs = [make_scene_pair(n_poles=6 + s % 4, n_planes=10 + s % 5, seed=s) for s in range(8)]
    cold = []
    for p in pairs:
        derived_cache.clear()
        E.evidence_cache.clear()
        cold.append(m.match(p.source, p.target))
    for p, c in zip(pairs, cold, strict=True):
        for _ in range(2):  # second and third call: every per-set value from the caches
            w = m.match(p.source, p.target)
            assert (w.T_target_source is None) == (c.T_target_source is None)
            if c.T_target_source is not None:
                np.testing.assert_array_equal(w.T_target_source, c.T_target_source)
            assert (w.valid, w.overlap, w.confidence, w.message) == (c.valid, c.overlap, c.confidence, c.message)
    assert derived_cache.hits > 0
