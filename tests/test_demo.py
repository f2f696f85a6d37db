"""The demo recovers the 180 deg / 14 m transform within its bounds (both flavours)."""

from __future__ import annotations

from graffmatch.demo import MAX_ROTATION_ERROR_DEG, MAX_TRANSLATION_ERROR_M, run_demo


def test_demo_landmarks():
    rep = run_demo(seed=0, mode="landmarks")
    assert rep.passed, rep
    assert rep.rotation_error_deg < MAX_ROTATION_ERROR_DEG
    assert rep.translation_error_m < MAX_TRANSLATION_ERROR_M


def test_demo_lidar_default():
    rep = run_demo(seed=0)
    assert rep.mode == "lidar" and rep.passed, rep
    assert rep.n_correct >= 0.9 * rep.n_associations
