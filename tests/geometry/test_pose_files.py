"""Pose files: one reader/writer for the CLI, the loops and the datasets (KITTI and TUM)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from graffmatch.errors import GraffMatchError, InvalidInputError, MalformedFileError
from graffmatch.geometry.pose_files import (
    parse_pose_line,
    pose_line,
    pose_to_xyzq,
    read_kitti,
    read_poses,
    read_tum,
    rows_to_poses,
    snap_to_se3,
    write_kitti,
    write_poses,
    write_tum,
    xyzq_to_pose,
)
from graffmatch.geometry.transforms import random_transform, rot_z


def _poses(seed: int, n: int, scale: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([random_transform(rng, max_translation=scale) for _ in range(n)])


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 12), scale=st.sampled_from([1.0, 1e3, 5e6]))
def test_kitti_round_trip_is_bit_exact(tmp_path_factory, seed: int, n: int, scale: float) -> None:
    """Written at 17 digits and not re-projected on load: even UTM-sized coordinates come back exactly."""
    P = _poses(seed, n, scale)
    path = write_kitti(tmp_path_factory.mktemp("k") / "poses.txt", P)
    assert np.array_equal(read_kitti(path), P)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 12))
def test_tum_round_trip_and_canonical_quaternion(tmp_path_factory, seed: int, n: int) -> None:
    P = _poses(seed, n, 100.0)
    t = np.cumsum(np.random.default_rng(seed).uniform(0.05, 0.2, n)) + 1.6e9  # epoch seconds
    path = write_tum(tmp_path_factory.mktemp("t") / "traj.txt", P, t)
    t2, P2 = read_tum(path)
    np.testing.assert_array_equal(t2, t)
    np.testing.assert_allclose(P2, P, atol=1e-12)
    assert all(pose_to_xyzq(T)[6] >= 0.0 for T in P)  # one of q's two signs: reproducible lines


def test_quaternion_sign_is_canonical() -> None:
    """R and the quaternion -q are the same rotation; both print qw >= 0."""
    T = np.eye(4)
    T[:3, :3] = rot_z(np.deg2rad(359.0))  # scipy gives qw < 0 for angles past 180 deg
    q = pose_to_xyzq(T)[3:]
    assert q[3] >= 0 and np.isclose(abs(q[2]), np.sin(np.deg2rad(359.0) / 2))
    np.testing.assert_allclose(xyzq_to_pose(pose_to_xyzq(T)), T, atol=1e-12)


def test_single_pose_line_both_formats() -> None:
    T = _poses(3, 1, 20.0)[0]
    t, T_kitti = parse_pose_line(pose_line(T, "kitti"), "kitti")
    assert t == 0.0 and np.array_equal(T_kitti, T)
    t, T_tum = parse_pose_line(pose_line(T, "tum", 12.5), "tum")
    assert t == 12.5 and np.allclose(T_tum, T, atol=1e-12)


def test_printed_rotations_are_snapped_but_reflections_refused() -> None:
    T = _poses(5, 1, 10.0)[0]
    rows = np.round(T[:3, :4].reshape(1, 12), 6)  # a file printed with 6 decimals
    S = rows_to_poses(rows, "gt.txt")[0]
    np.testing.assert_allclose(S[:3, :3].T @ S[:3, :3], np.eye(3), atol=1e-12)
    assert np.abs(S[:3, :3] - T[:3, :3]).max() < 2e-6
    F = T.copy()
    F[:3, 0] *= -1  # a reflection: orthonormal, det -1
    with pytest.raises(MalformedFileError, match=r"gt.txt: pose 0 has a non-orthonormal"):
        rows_to_poses(F[:3, :4].reshape(1, 12), "gt.txt")
    with pytest.raises(InvalidInputError, match="--gt: pose 0 has a non-orthonormal"):
        snap_to_se3(np.diag([2.0, 2.0, 2.0, 1.0]), "--gt")  # a scale
    bad = T.copy()
    bad[3] = [0, 0, 1, 1]
    with pytest.raises(InvalidInputError, match="last row must be 0 0 0 1"):
        snap_to_se3(bad, "T")
    with pytest.raises(MalformedFileError, match="NaN or Inf"):
        rows_to_poses(np.full((1, 12), np.nan), "x.txt")


def test_bad_files_name_the_file_and_line(tmp_path) -> None:
    p = tmp_path / "traj.txt"
    p.write_text("0 1 2 3 0 0 0 1\n1 1 2 3 0 0 0 0\n")
    with pytest.raises(MalformedFileError, match=r"traj.txt: pose 1: the quaternion is zero"):
        read_tum(p)
    p.write_text("0 1 2 3 0 0 0\n")
    with pytest.raises(MalformedFileError, match=r"traj.txt:1: expected 8 numbers, got 7"):
        read_tum(p)
    with pytest.raises(InvalidInputError, match="pose file not found"):
        read_kitti(tmp_path / "missing.txt")
    with pytest.raises(InvalidInputError, match="unknown pose format 'g2o'"):
        read_poses(p, "g2o")  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match="2 poses but 3 timestamps"):
        write_poses(tmp_path / "x.txt", _poses(1, 2, 1.0), "tum", [0.0, 1.0, 2.0])


@settings(max_examples=200, deadline=None)
@given(text=st.text(alphabet="0123456789.-e nan inf#,\t", max_size=60), fmt=st.sampled_from(["kitti", "tum"]))
def test_fuzzed_lines_raise_only_our_errors(text: str, fmt: str) -> None:
    try:
        t, T = parse_pose_line(text, fmt)  # type: ignore[arg-type]
    except GraffMatchError:
        return
    assert np.isfinite(t) and np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-9)
