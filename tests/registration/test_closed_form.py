"""Closed-form registration: exact recovery, sign flips, noise, weights, degeneracy via kappa."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from graffmatch.datasets.landmark_scene import make_scene_pair
from graffmatch.errors import DegenerateGeometryError, InvalidInputError
from graffmatch.geometry.landmarks import Landmark, LandmarkSet
from graffmatch.geometry.transforms import invert, random_transform, transform_errors
from graffmatch.registration.closed_form import register_landmarks


def _scene(rng, n_lines=6, n_planes=8, n_points=0):
    n = n_lines + n_planes + n_points
    types = np.r_[np.full(n_lines, 1), np.full(n_planes, 2), np.zeros(n_points, int)]
    return LandmarkSet.from_arrays(types, rng.normal(size=(n, 3)), rng.uniform(-20, 20, (n, 3)))


def _view(ls, T_target_source, rng, drift=0.0):
    """Source-frame copy of target landmarks; anchors drift within the landmark."""
    src = ls.transform(invert(T_target_source))
    if drift:
        coef = rng.normal(0, drift, (len(src), 2))
        anchors = src.anchors + np.einsum("nik,nk->ni", src.bases, coef)
        src = LandmarkSet(src.types, src.bases, anchors)
    return src


@given(seed=st.integers(0, 2**32 - 1), n_points=st.sampled_from([0, 4]))
def test_exact_recovery_with_random_sign_flips_and_anchor_drift(seed, n_points):
    rng = np.random.default_rng(seed)
    tgt = _scene(rng, n_points=n_points)
    T = random_transform(rng, 30.0)
    src = _view(tgt, T, rng, drift=3.0 if n_points == 0 else 0.0)
    # flip direction signs at random: lines and plane normals carry no orientation
    flips = rng.choice([-1.0, 1.0], len(src))
    src = LandmarkSet.from_arrays(src.types, src.directions * flips[:, None], src.anchors)
    A = np.stack([np.arange(len(tgt))] * 2, 1)
    est = register_landmarks(src, tgt, A)
    r, t = transform_errors(est.T_target_source, T)
    assert r < 1e-5 and t < 1e-6
    assert not est.degenerate and est.kappa < 100


def test_graceful_accuracy_with_noise():
    errs = []
    for seed in range(10):
        sc = make_scene_pair(15, 30, seed=seed, anchor_noise=0.05, angle_noise_deg=0.5)
        est = register_landmarks(sc.source, sc.target, sc.true_matches)
        errs.append(transform_errors(est.T_target_source, sc.T_target_source))
    errs = np.array(errs)
    assert np.median(errs[:, 0]) < 0.5 and np.median(errs[:, 1]) < 0.2
    assert errs[:, 0].max() < 1.5 and errs[:, 1].max() < 0.6


def test_weights_downweight_an_outlier():
    rng = np.random.default_rng(0)
    tgt = _scene(rng, 6, 10)
    T = random_transform(rng, 10)
    src = _view(tgt, T, rng)
    A = np.stack([np.arange(len(tgt))] * 2, 1)
    A_bad = A.copy()
    planes = np.flatnonzero(tgt.types == 2)
    A_bad[planes[0], 1], A_bad[planes[1], 1] = A[planes[1], 1], A[planes[0], 1]  # swap two planes
    w = np.ones(len(A))
    w[planes[:2]] = 1e-6
    bad = transform_errors(register_landmarks(src, tgt, A_bad).T_target_source, T)
    good = transform_errors(register_landmarks(src, tgt, A_bad, weights=w).T_target_source, T)
    # a symmetric swap adds a symmetric term to the correlation: rotation survives, translation not
    assert good[1] < 1e-3 < 0.5 < bad[1]


def test_degenerate_parallel_planes_and_parallel_lines():
    planes = LandmarkSet.from_landmarks([Landmark.plane([0, 0, z], [0, 0, 1]) for z in (0, 1, 2, 3)])
    A = np.stack([np.arange(4)] * 2, 1)
    est = register_landmarks(planes, planes, A)
    assert est.degenerate and est.rotation_rank == 1
    lines = LandmarkSet.from_landmarks([Landmark.line([x, 0, 0], [0, 0, 1]) for x in (0, 1, 2)])
    est = register_landmarks(lines, lines, np.stack([np.arange(3)] * 2, 1))
    assert est.degenerate  # rotation about the common direction and z-translation unknown
    mixed = LandmarkSet.from_landmarks(
        [Landmark.plane([0, 0, 0], [0, 0, 1]), Landmark.plane([3, 0, 0], [1, 0, 0]),
         Landmark.plane([0, 5, 0], [0, 1, 0])]
    )
    est = register_landmarks(mixed, mixed, np.stack([np.arange(3)] * 2, 1))
    assert not est.degenerate and est.kappa < 2


def test_bad_input():
    ls = LandmarkSet.from_landmarks([Landmark.plane([0, 0, 0], [0, 0, 1]), Landmark.line([0, 0, 0], [1, 0, 0])])
    with pytest.raises(DegenerateGeometryError):
        register_landmarks(ls, ls, np.zeros((0, 2), int))
    with pytest.raises(InvalidInputError):
        register_landmarks(ls, ls, [[0, 1]])  # plane with line
    with pytest.raises(InvalidInputError):
        register_landmarks(ls, ls, [[0, 0], [1, 1]], weights=[1.0, np.nan])
