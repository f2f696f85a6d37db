"""The demo recovers the 180 deg / 14 m transform within its bounds, or says honestly that it
cannot: never valid-and-wrong. Several seeds per mode here; bench/bench_demo.py runs 20."""

from __future__ import annotations

import pytest

from graffmatch.demo import BOUNDS, MAX_ROTATION_ERROR_DEG, MAX_TRANSLATION_ERROR_M, run_demo


def test_demo_lidar_default():
    rep = run_demo(seed=0)
    assert rep.mode == "lidar" and rep.passed, rep
    assert rep.rotation_error_deg < MAX_ROTATION_ERROR_DEG
    assert rep.translation_error_m < MAX_TRANSLATION_ERROR_M
    assert rep.n_correct >= 0.9 * rep.n_associations
    assert rep.result.confidence > 0.9 and "icp_fitness" in rep.result.info


def test_demo_landmarks_seeds_0_to_7():
    """The documented seeds: seeds 1, 3 and 6 used to miss the bounds while reported valid."""
    reps = [run_demo(seed=s, mode="landmarks") for s in range(8)]
    assert all(r.honest for r in reps), [str(r) for r in reps if not r.honest]
    assert sum(r.passed for r in reps) >= 7, [str(r) for r in reps]
    assert BOUNDS["landmarks"] == (1.0, 0.5)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_demo_lidar_more_seeds_are_right_or_honestly_invalid(seed):
    rep = run_demo(seed=seed, mode="lidar")
    assert rep.honest, rep
    if rep.result.valid:
        assert rep.rotation_error_deg < 1.0 and rep.translation_error_m < 0.2
