"""De-skewing: exact inverse of a constant-velocity sweep, input errors, and the dataset wrapper.
(The azimuth-timed path against the simulator's rendered motion: tests/datasets/test_simulator.py.)"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from graffmatch.datasets.base import Scan
from graffmatch.datasets.deskewed import Deskewed
from graffmatch.errors import InvalidInputError
from graffmatch.lidar.deskew import (
    azimuth_times,
    deskew_in_sequence,
    deskew_scan,
    sweep_motion,
    sweep_twist,
)


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    yaw_deg=st.floats(-15, 15),
    speed=st.floats(0, 3),
)
def test_deskew_inverts_a_constant_velocity_sweep(seed, yaw_deg, speed):
    """Points seen from the pose at their time (distorted) come back to the mid-sweep frame
    within 1e-9 m, for any pose of the sequence in the world."""
    rng = np.random.default_rng(seed)
    true = rng.uniform(-40, 40, (300, 3))  # in the mid-sweep frame
    times = rng.uniform(0, 1, 300)
    W = _pose(rng.normal(size=3), rng.uniform(-1e3, 1e3, 3))  # any world frame
    step = _pose([0, 0, np.radians(yaw_deg)], [speed, 0.1 * speed, 0])  # motion per sweep
    T_prev, T_next = W @ np.linalg.inv(step), W @ step  # two sweeps apart, centred on W
    M = sweep_motion(sweep_twist(T_prev, T_next, 2.0), times - 0.5)  # mid-sweep -> point's time
    raw = np.einsum("nij,nj->ni", np.linalg.inv(M)[:, :3, :3], true) + np.linalg.inv(M)[:, :3, 3]
    raw4 = np.c_[raw, rng.uniform(0, 1, 300)]
    fixed = deskew_scan(raw4, T_prev, T_next, 2.0, times=times)
    assert np.max(np.linalg.norm(fixed[:, :3] - true, axis=1)) < 1e-9
    assert np.array_equal(fixed[:, 3], raw4[:, 3])  # intensity kept
    # without motion nothing moves
    assert np.allclose(deskew_scan(raw4, W, W, 2.0, times=times), raw4, atol=1e-12)


def test_azimuth_times_run_from_behind_clockwise():
    # behind: start (-0.5); left (+y) is reached a quarter in; forward is mid-sweep; right last
    P = np.array([[-1.0, 1e-9, 0], [0, 1, 0], [1, 0, 0], [0, -1, 0]])
    assert np.allclose(azimuth_times(P), [-0.5, -0.25, 0.0, 0.25], atol=1e-6)


def test_deskew_rejects_bad_input_with_the_argument_named():
    P = np.zeros((5, 3))
    with pytest.raises(InvalidInputError, match="points"):
        deskew_scan(np.zeros(5), np.eye(4), np.eye(4))
    with pytest.raises(InvalidInputError, match="T_next"):
        deskew_scan(P, np.eye(4), np.full((4, 4), np.nan))
    with pytest.raises(InvalidInputError, match="n_periods"):
        deskew_scan(P, np.eye(4), np.eye(4), 0.0)
    with pytest.raises(InvalidInputError, match="times"):
        deskew_scan(P, np.eye(4), np.eye(4), times=np.full(5, 1.5))
    with pytest.raises(InvalidInputError, match="poses"):
        deskew_in_sequence(P, np.eye(4), 0)
    with pytest.raises(InvalidInputError, match="out of range"):
        deskew_in_sequence(P, np.stack([np.eye(4)] * 3), 3)


def test_deskew_in_sequence_uses_the_neighbours_and_leaves_a_single_scan():
    P = np.random.default_rng(0).uniform(-20, 20, (50, 3))
    poses = np.stack([_pose([0, 0, np.radians(5.0 * k)], [k * 1.0, 0, 0]) for k in range(4)])
    assert np.array_equal(deskew_in_sequence(P, poses[:1], 0), P)
    assert np.allclose(deskew_in_sequence(P, poses, 2), deskew_scan(P, poses[1], poses[3], 2.0))
    assert np.allclose(deskew_in_sequence(P, poses, 0), deskew_scan(P, poses[0], poses[1], 1.0))
    assert np.allclose(deskew_in_sequence(P, poses, 3), deskew_scan(P, poses[2], poses[3], 1.0))


class _Drive:
    """A minimal Dataset: three scans of random points with poses."""

    name = "tiny"

    def __init__(self) -> None:
        rng = np.random.default_rng(1)
        self._pts = [rng.uniform(-20, 20, (100, 4)).astype(np.float32) for _ in range(3)]
        self._poses = np.stack([_pose([0, 0, np.radians(8.0 * k)], [k * 1.0, 0, 0]) for k in range(3)])

    def __len__(self) -> int:
        return 3

    def __getitem__(self, i: int) -> Scan:
        return Scan(self._pts[i], None, self._poses[i], float(i), i, Path(f"{i}.bin"))

    @property
    def poses(self) -> np.ndarray:
        return self._poses

    def scan_path(self, i: int) -> Path:
        return Path(f"{i}.bin")

    def label_path(self, i: int) -> Path | None:
        return None


def test_deskewed_dataset_moves_points_only_and_takes_an_odometry():
    raw = _Drive()
    d = Deskewed(raw)
    s = d[1]
    assert d.name == "tiny+deskew" and len(d) == 3 and s.points.dtype == np.float32
    assert np.allclose(s.points[:, :3], deskew_scan(raw[1].points, raw.poses[0], raw.poses[2])[:, :3], atol=1e-5)
    assert np.max(np.abs(s.points[:, :3] - raw[1].points[:, :3])) > 0.1  # 8 deg per sweep moves points
    assert np.array_equal(s.points[:, 3], raw[1].points[:, 3]) and np.array_equal(d.poses, raw.poses)
    # only the relative motion matters: the same odometry in another world frame, same points
    W = _pose([0.1, 0.2, 0.3], [500.0, -20.0, 3.0])
    d2 = Deskewed(raw, W[None] @ raw.poses)
    assert np.allclose(d2[1].points, s.points, atol=1e-4)
    with pytest.raises(InvalidInputError, match="motion_poses"):
        Deskewed(raw, raw.poses[:2])
