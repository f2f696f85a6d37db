"""d_Graff and the invariant distance: SE(3) invariance, closed forms, symmetry, kernels."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from graffmatch.geometry.distance import (
    cross_distances,
    directed_distances,
    directed_distances_reference,
    graff_distance,
    invariant_distance,
    naive_distance,
    pairwise_distances,
)
from graffmatch.geometry.landmarks import Landmark, LandmarkSet
from graffmatch.geometry.transforms import random_transform, rot_z

RHO = 40.0


def _lm(kind: int, rng: np.random.Generator) -> Landmark:
    p = rng.uniform(-50, 50, 3)
    if kind == 0:
        return Landmark.point(p)
    if kind == 1:
        return Landmark.line(p, rng.normal(size=3))
    return Landmark.plane(p, rng.normal(size=3))


def _move(lm: Landmark, T) -> Landmark:
    return LandmarkSet.from_landmarks([lm]).transform(T).landmark(0)


@given(k1=st.integers(0, 2), k2=st.integers(0, 2), seed=st.integers(0, 2**32 - 1))
def test_invariant_distance_is_se3_invariant(k1, k2, seed):
    rng = np.random.default_rng(seed)
    a, b = _lm(k1, rng), _lm(k2, rng)
    T = random_transform(rng, 200.0)
    d0 = invariant_distance(a, b, RHO)
    d1 = invariant_distance(_move(a, T), _move(b, T), RHO)
    assert abs(d0 - d1) < 1e-9


@given(seed=st.integers(0, 2**32 - 1))
def test_batched_matrix_is_invariant_and_matches_reference(seed):
    rng = np.random.default_rng(seed)
    n = 12
    ls = LandmarkSet.from_arrays(rng.integers(0, 3, n), rng.normal(size=(n, 3)), rng.uniform(-60, 60, (n, 3)))
    D = pairwise_distances(ls, RHO)
    D2 = pairwise_distances(ls.transform(random_transform(rng, 300.0)), RHO)
    assert np.abs(D - D2).max() < 1e-9
    assert np.allclose(D, D.T) and np.all(np.diag(D) == 0)
    i, j = np.nonzero(~np.eye(n, dtype=bool))
    fast = directed_distances(ls.types[i], ls.bases[i], ls.anchors[i], ls.types[j], ls.bases[j], ls.anchors[j], RHO)
    ref = directed_distances_reference(ls.types[i], ls.bases[i], ls.anchors[i], ls.types[j], ls.bases[j], ls.anchors[j], RHO)
    assert np.abs(fast - ref).max() < 1e-10


def test_naive_distance_breaks_invariance():
    rng = np.random.default_rng(3)
    n = 30
    ls = LandmarkSet.from_arrays(rng.integers(1, 3, n), rng.normal(size=(n, 3)), rng.uniform(-30, 30, (n, 3)))
    T = random_transform(rng, 50.0)
    D = pairwise_distances(ls, RHO, "naive")
    D2 = pairwise_distances(ls.transform(T), RHO, "naive")
    assert np.abs(D - D2).max() > 0.05  # measurably not invariant (radians)
    assert np.abs(pairwise_distances(ls, RHO) - pairwise_distances(ls.transform(T), RHO)).max() < 1e-9


@given(s=st.floats(0.0, 200.0), th=st.floats(0.0, np.pi / 2), seed=st.integers(0, 1000))
def test_closed_form_cases(s, th, seed):
    rng = np.random.default_rng(seed)
    T = random_transform(rng, 100.0)
    n = np.array([0.0, 0.0, 1.0])
    # parallel planes at separation s (anchors anywhere on them): atan(s / rho)
    p1 = Landmark.plane([3.0, -2.0, 0.0], n)
    p2 = Landmark.plane([-7.0, 11.0, s], n)
    assert abs(invariant_distance(_move(p1, T), _move(p2, T)) - np.arctan(s / RHO)) < 1e-9
    # two lines through a common anchor at angle th: th
    c = rng.uniform(-20, 20, 3)
    l1 = Landmark.line(c, [1.0, 0.0, 0.0])
    l2 = Landmark.line(c, [np.cos(th), np.sin(th), 0.0])
    assert abs(invariant_distance(_move(l1, T), _move(l2, T)) - th) < 1e-9
    # two points at distance s: atan(s / rho)
    q1, q2 = Landmark.point(c), Landmark.point(c + s * np.array([0.6, 0.0, 0.8]))
    assert abs(invariant_distance(q1, q2) - np.arctan(s / RHO)) < 1e-9
    # a point on a plane (anchor of the point on the plane): 0; off the plane by s: atan(s/rho)
    assert abs(invariant_distance(Landmark.point([4.0, 5.0, 0.0]), p1)) < 1e-9
    assert abs(invariant_distance(Landmark.point([4.0, 5.0, s]), p1) - np.arctan(s / RHO)) < 1e-9
    # parallel lines at separation s: atan(s / rho); line inside a plane: 0
    l3 = Landmark.line(c + [0.0, 0.0, s], [1.0, 0.0, 0.0])
    assert abs(invariant_distance(l1, l3) - np.arctan(s / RHO)) < 1e-9
    assert abs(invariant_distance(Landmark.line([1.0, 2.0, 0.0], [np.cos(th), np.sin(th), 0.0]), p1)) < 1e-9
    # planes through a common anchor with normals at angle th: th
    p3 = Landmark.plane(c, [0.0, 0.0, 1.0])
    p4 = Landmark.plane(c, [np.sin(th), 0.0, np.cos(th)])
    assert abs(invariant_distance(p3, p4) - th) < 1e-9


def test_symmetry_and_documented_asymmetry():
    # same-type points and parallel planes: symmetric
    a, b = Landmark.point([0, 0, 0]), Landmark.point([3, 4, 0])
    assert abs(invariant_distance(a, b) - invariant_distance(b, a)) < 1e-12
    # non-parallel planes: the shift makes the distance order dependent
    p = Landmark.plane([0, 0, 0], [0, 0, 1])
    q = Landmark.plane([30, 0, 5], [1, 0, 1])
    assert abs(invariant_distance(p, q) - invariant_distance(q, p)) > 1e-3
    # the batched matrix averages both orders
    D = pairwise_distances(LandmarkSet.from_landmarks([p, q]))
    assert abs(D[0, 1] - 0.5 * (invariant_distance(p, q) + invariant_distance(q, p))) < 1e-12


def test_graff_distance_without_shift_decays_with_translation():
    # paper Fig. 2(b): applied directly, d_Graff shrinks as both landmarks move away
    d = [graff_distance(np.zeros((3, 0)), [s, 0, 0], np.zeros((3, 0)), [s + 1, 0, 0]) for s in (0, 10, 100)]
    assert d[0] > d[1] > d[2]
    assert naive_distance(Landmark.point([0, 0, 0]), Landmark.point([1, 0, 0])) > 0


def test_cross_distances_types_and_identity(rng):
    ls = LandmarkSet.from_arrays([1, 2, 2], rng.normal(size=(3, 3)), rng.uniform(-5, 5, (3, 3)))
    T = rot_z(0.2)
    D = cross_distances(ls, ls)
    assert np.all(np.diag(D) < 1e-7)
    assert np.isinf(D[0, 1]) and np.isinf(D[1, 0])
    assert T.shape == (3, 3)
