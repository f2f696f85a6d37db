"""The realism statistics (issue 13) measure what they claim, with numbers."""

from __future__ import annotations

import numpy as np

from graffmatch.evaluation.realism import (
    graph_density,
    pairs_at_distance,
    scattered_mask,
    strict_repeatability,
    true_shared_landmarks,
)
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.transforms import make_transform, rot_z


def _street(rng) -> LandmarkSet:
    n_l, n_p = 6, 6
    types = np.r_[np.ones(n_l, int), np.full(n_p, 2)]
    dirs = np.r_[np.tile([0.0, 0.0, 1.0], (n_l, 1)), np.tile([1.0, 0.0, 0.0], (n_p, 1))]
    dirs[n_l:] = np.c_[np.cos(rng.uniform(0, np.pi, n_p)), np.sin(rng.uniform(0, np.pi, n_p)), np.zeros(n_p)]
    anchors = rng.uniform(-20, 20, (n_l + n_p, 3))
    return LandmarkSet.from_arrays(types, dirs, anchors)


def test_strict_repeatability_and_shared_landmarks():
    ls = _street(np.random.default_rng(0))
    assert strict_repeatability(ls, ls) == 1.0
    assert len(true_shared_landmarks(ls, ls)) == len(ls)
    # 0.5 m sideways: beyond the strict 0.3 m gate for every pole and most planes
    moved = ls.transform(make_transform(np.eye(3), np.array([0.0, 0.5, 0.0])))
    assert strict_repeatability(ls, moved) < 0.6
    # 5 deg of yaw: every plane fails the 2 deg gate, poles (vertical) keep their direction
    turned = ls.transform(make_transform(rot_z(np.radians(5.0)), np.zeros(3)))
    assert strict_repeatability(ls, turned) <= 0.5


def test_scattered_mask_tells_foliage_from_surfaces():
    rng = np.random.default_rng(1)
    u, v = rng.uniform(0, 4, (2, 4000))
    wall = np.c_[np.full(4000, 8.0) + rng.normal(0, 0.02, 4000), u, v]  # 2 cm noise
    # a shrub as a LiDAR sees it: a few hundred returns spread through a 1 m volume
    bush = rng.normal([5.0, -5.0, 1.0], 0.5, (400, 3))
    m = scattered_mask(np.r_[wall, bush])
    assert m[:4000].mean() < 0.01
    assert m[4000:].mean() > 0.5


def test_pairs_at_distance_and_graph_density():
    T = np.tile(np.eye(4), (20, 1, 1))
    T[:, 0, 3] = np.arange(20) * 1.0
    pairs = pairs_at_distance(T, 4.0, 5.0, max_pairs=3)
    assert len(pairs) == 3 and all(b - a == 4 for a, b in pairs)
    assert graph_density(10, 45) == 1.0 and np.isnan(graph_density(1, 0))


def test_every_b_pairs_and_pooled_summary():
    """A short real sequence lends every pair in range (KITTI's six scans: 0-4, 0-5, 1-5), and
    pooled drives give means over all scans/pairs and medians over all planes/pairs."""
    from graffmatch.evaluation.realism import summarize_realism

    T = np.tile(np.eye(4), (6, 1, 1))
    T[:, 0, 3] = np.arange(6) * 0.86
    assert pairs_at_distance(T, 3.4, 5.0, 8) == [(0, 4), (1, 5)]
    assert pairs_at_distance(T, 3.4, 5.0, 8, every_b=True) == [(0, 4), (0, 5), (1, 5)]

    def scan(poles, rms):
        return {"poles": poles, "planes": 2, "plane_rms_m": rms, "scattered_share": 0.01,
                "ground_share": 0.5, "points": 100, "range_median_m": 9.0, "intensity_mean": 0.3}  # fmt: skip

    def pair(err):
        return {"shared": 4, "strict_repeatability": 0.5, "trans_err_m": err, "graph_density": 0.3}

    one = summarize_realism([scan(2, [0.02])], [pair(0.1)])
    pooled = summarize_realism(
        [scan(2, [0.02]), scan(6, [0.05, 0.07])], [pair(0.1), pair(5.0), pair(0.3)]
    )
    assert one["poles_per_scan"] == 2 and pooled["poles_per_scan"] == 4
    assert np.isclose(pooled["plane_rms_cm"], 5.0)  # median of 2, 5, 7 cm
    assert np.isclose(pooled["trans_err_median_m"], 0.3)  # a failure does not move the median
    assert pooled["n_scans"] == 2 and pooled["n_pairs"] == 3
