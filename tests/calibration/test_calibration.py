"""Extrinsic calibration on the simulated rigs: bounds, detection, degeneracy, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from graffmatch.calibration import (
    CalibrationConfig,
    Chessboard,
    calibrate_camera_depth,
    calibrate_lidar_lidar,
    calibrate_planes,
    detect_board_planes,
    extract_depth_planes,
    format_demo_report,
    run_calibration_demo,
)
from graffmatch.calibration.rig import make_camera_depth_scenario, make_lidar_lidar_scenario
from graffmatch.errors import DegenerateGeometryError, GraffMatchError, InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.geometry.transforms import invert, random_transform, transform_errors

ROT_BOUND_DEG = 1.0
TRANS_BOUND_M = 0.05


@pytest.fixture(scope="module", params=[0, 3])
def lidar_scenario(request):
    return make_lidar_lidar_scenario(request.param)


@pytest.fixture(scope="module", params=[0, 2])
def camera_scenario(request):
    return make_camera_depth_scenario(request.param)


def _nearest(anchors: np.ndarray, truth: LandmarkSet) -> tuple[np.ndarray, np.ndarray]:
    d = np.linalg.norm(anchors[:, None, :] - truth.anchors[None], axis=2)
    return d.argmin(axis=1), d.min(axis=1)


# ---- LiDAR-LiDAR ---------------------------------------------------------------------------
def test_lidar_lidar_recovers_extrinsic(lidar_scenario):
    sc = lidar_scenario
    res = calibrate_lidar_lidar(sc.cloud_a, sc.cloud_b)
    rot, trans = transform_errors(res.T_b_a, sc.T_b_a)
    assert res.valid, res.message
    assert not res.degenerate
    assert rot <= ROT_BOUND_DEG and trans <= TRANS_BOUND_M, (rot, trans)
    assert res.n_matched >= 6 and res.kappa < 100
    assert res.residual_angle_deg.shape == (res.n_matched,)
    assert np.median(res.residual_offset) < 0.03
    # Every association pairs the same physical board (ground truth by board centres).
    truth_a = sc.scene.board_planes(invert(sc.T_world_a))
    truth_b = sc.scene.board_planes(invert(sc.T_world_b))
    ia, da = _nearest(res.source_planes.anchors[res.associations[:, 0]], truth_a)
    ib, db = _nearest(res.target_planes.anchors[res.associations[:, 1]], truth_b)
    assert np.all(da < 0.15) and np.all(db < 0.15)
    np.testing.assert_array_equal(ia, ib)
    # The extracted planes of A: every board found, normals within 2 deg, facing the sensor.
    planes = res.source_planes
    j, d = _nearest(planes.anchors, truth_a)
    on_board = d < 0.15
    assert len(set(j[on_board])) == sc.scene.n_boards
    cos = np.abs(
        np.einsum("ij,ij->i", planes.directions[on_board], truth_a.directions[j[on_board]])
    )
    assert np.degrees(np.arccos(np.clip(cos, 0, 1))).max() < 2.0
    assert np.all(np.einsum("ij,ij->i", planes.directions, planes.anchors) < 0)


def test_lidar_too_few_boards_raises():
    sc = make_lidar_lidar_scenario(1, n_boards=2, ground=False)
    with pytest.raises(DegenerateGeometryError, match="at least 3 planes"):
        calibrate_lidar_lidar(sc.cloud_a, sc.cloud_b)


def test_lidar_parallel_boards_flagged_degenerate():
    sc = make_lidar_lidar_scenario(0, n_boards=6, parallel_boards=True, ground=False)
    try:
        res = calibrate_lidar_lidar(sc.cloud_a, sc.cloud_b)
    except DegenerateGeometryError:
        return
    assert res.degenerate and not res.valid
    assert "span 3D" in res.message
    assert not np.allclose(res.T_b_a, np.eye(4))  # never a silent identity


def test_lidar_bad_input():
    with pytest.raises(InvalidInputError):
        calibrate_lidar_lidar(np.zeros((10, 2)), np.zeros((10, 3)))
    with pytest.raises(InvalidInputError):
        calibrate_lidar_lidar(np.full((100, 3), np.nan), np.zeros((100, 3)))


# ---- camera-depth ----------------------------------------------------------------------------
def test_chessboard_detection_finds_all_boards(camera_scenario):
    sc = camera_scenario
    dets = detect_board_planes(sc.image, sc.camera.K, sc.board)
    truth = sc.scene.board_planes(invert(sc.T_world_camera))
    j, d = _nearest(np.array([x.anchor for x in dets]), truth)
    assert len(dets) == sc.scene.n_boards
    assert len(set(j)) == sc.scene.n_boards
    assert d.max() < 0.03  # PnP board centre within 3 cm
    cos = np.abs(np.einsum("ij,ij->i", np.array([x.normal for x in dets]), truth.directions[j]))
    assert np.degrees(np.arccos(np.clip(cos, 0, 1))).max() < 1.5
    assert max(x.reprojection_rms for x in dets) < 0.5
    # The (cols, rows, square) tuple form gives the same planes.
    b = sc.board
    dets2 = detect_board_planes(sc.image, sc.camera.K, (b.cols, b.rows, b.square))
    np.testing.assert_allclose(
        np.array([x.anchor for x in dets2]), np.array([x.anchor for x in dets]), atol=1e-9
    )


def test_depth_planes_match_truth(camera_scenario):
    sc = camera_scenario
    planes = extract_depth_planes(sc.depth, sc.depth_camera.K)
    truth = sc.scene.board_planes(invert(sc.T_world_depth))
    j, d = _nearest(planes.anchors, truth)
    assert len(planes) >= sc.scene.n_boards - 1
    assert d.max() < 0.05
    cos = np.abs(np.einsum("ij,ij->i", planes.directions, truth.directions[j]))
    assert np.degrees(np.arccos(np.clip(cos, 0, 1))).max() < 2.0


def test_camera_depth_recovers_extrinsic(camera_scenario):
    sc = camera_scenario
    res = calibrate_camera_depth(sc.image, sc.camera.K, sc.depth, sc.depth_camera.K, sc.board)
    rot, trans = transform_errors(res.T_depth_camera, sc.T_depth_camera)
    assert res.valid, res.message
    assert rot <= ROT_BOUND_DEG and trans <= TRANS_BOUND_M, (rot, trans)
    assert res.n_matched >= 5
    assert set(res.timings) >= {"detect_boards", "depth_planes", "graffmatch", "total"}


def test_camera_depth_parallel_boards_flagged():
    sc = make_camera_depth_scenario(1, n_boards=5, parallel_boards=True)
    try:
        res = calibrate_camera_depth(sc.image, sc.camera.K, sc.depth, sc.depth_camera.K, sc.board)
    except DegenerateGeometryError:
        return
    assert res.degenerate and not res.valid


def test_camera_depth_no_boards_raises():
    blank = np.full((480, 640, 3), 120, np.uint8)
    depth = np.zeros((480, 640), np.float32)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    assert detect_board_planes(blank, K, (7, 5, 0.07)) == []
    with pytest.raises(DegenerateGeometryError):
        calibrate_camera_depth(blank, K, np.ones((480, 640), np.float32), K, (7, 5, 0.07))
    with pytest.raises(InvalidInputError):
        detect_board_planes(blank, np.eye(2), (7, 5, 0.07))
    with pytest.raises(InvalidInputError):
        extract_depth_planes(depth[0], K)
    with pytest.raises(InvalidInputError):
        Chessboard(cols=1, rows=5)


# ---- the matching core, on exact planes ----------------------------------------------------
@st.composite
def _board_sets(draw):
    seed = draw(st.integers(0, 10_000))
    rng = np.random.default_rng(seed)
    n = draw(st.integers(5, 9))
    az = np.sort(rng.uniform(-np.pi, np.pi, n)) + np.linspace(0, 0.5, n)
    r = rng.uniform(2.0, 8.0, n)
    anchors = np.stack([r * np.cos(az), r * np.sin(az), rng.uniform(-0.5, 1.0, n)], axis=1)
    normals = -anchors + rng.normal(0, 1.5, (n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return seed, LandmarkSet.from_arrays(np.full(n, LandmarkType.PLANE), normals, anchors)


@settings(max_examples=15, deadline=None)
@given(_board_sets())
def test_calibrate_planes_recovers_any_transform(data):
    """Any rigid transform, shuffled target order, extra clutter plane: exact recovery."""
    seed, src = data
    rng = np.random.default_rng(seed + 1)
    if np.linalg.svd(src.directions, compute_uv=False)[-1] / np.sqrt(len(src)) < 0.2:
        return  # normals too close to coplanar for a well-posed calibration
    T = random_transform(rng, max_translation=2.0)
    perm = rng.permutation(len(src))
    clutter = LandmarkSet.from_arrays([LandmarkType.PLANE], [[0.0, 0.0, 1.0]], [[3.0, -1.0, -1.7]])
    tgt = LandmarkSet.concatenate([src.transform(T)[perm], clutter])
    res = calibrate_planes(src, tgt, CalibrationConfig())
    rot, trans = transform_errors(res.T_target_source, T)
    assert res.valid, res.message
    assert rot < 1e-4 and trans < 1e-6  # arccos near 1 limits the angle to ~1e-6 deg
    assert res.n_matched == len(src)
    np.testing.assert_array_equal(perm[res.associations[:, 1]], res.associations[:, 0])
    assert res.residual_offset.max() < 1e-9


# ---- rig determinism and demo ------------------------------------------------------------------
def test_rig_is_deterministic():
    a = make_lidar_lidar_scenario(7, n_boards=4, ground=False)
    b = make_lidar_lidar_scenario(7, n_boards=4, ground=False)
    np.testing.assert_array_equal(a.cloud_a, b.cloud_a)
    np.testing.assert_array_equal(a.T_b_a, b.T_b_a)
    c = make_lidar_lidar_scenario(8, n_boards=4, ground=False)
    assert not np.allclose(a.T_b_a, c.T_b_a)


def test_demo_report():
    rep = run_calibration_demo("camera-depth", seed=1)
    assert rep["within_bounds"] and rep["valid"]
    assert rep["rotation_error_deg"] <= ROT_BOUND_DEG
    assert rep["translation_error_m"] <= TRANS_BOUND_M
    assert {"simulate", "detect_boards", "graffmatch", "total"} <= set(rep["timings_s"])
    assert "error vs truth" in format_demo_report(rep)
    assert rep["T_depth_camera"] and np.allclose(np.array(rep["T_true"])[3], [0, 0, 0, 1])
    with pytest.raises(GraffMatchError):
        run_calibration_demo("lidar-camera")  # type: ignore[arg-type]


# ---- real scans: no boards, so the honest outcome is "accurate or flagged" ------------------
def _balm_pose(lines: list[str], i: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :] = np.array(lines[i].split(), float).reshape(3, 4)
    U, _, Vt = np.linalg.svd(T[:3, :3])  # poses.txt is rounded: re-orthonormalise
    T[:3, :3] = U @ Vt
    return T


@pytest.mark.parametrize("pair", [(20, 21)])
def test_real_scans_accurate_or_flagged(shared_data, pair):
    """BALM courtyard scans (real 360° LiDAR, walls and ground, no boards) as the two
    'sensors': all planes kept, a wrong extrinsic must never be reported as valid."""
    from graffmatch.calibration import LidarLidarConfig
    from graffmatch.lidar.io import read_bin

    root = shared_data / "balm_courtyard"
    if not root.is_dir():
        pytest.skip(f"{root} not present")
    lines = (root / "poses.txt").read_text().splitlines()
    i, j = pair
    a = read_bin(root / "velodyne" / f"{i:06d}.bin")[:, :3]
    b = read_bin(root / "velodyne" / f"{j:06d}.bin")[:, :3]
    T_true = invert(_balm_pose(lines, j)) @ _balm_pose(lines, i)
    cfg = LidarLidarConfig()
    cfg.extraction.max_side = 1e9  # walls and ground too: there are no boards
    cfg.extraction.max_range = 30.0
    res = calibrate_lidar_lidar(a, b, cfg)
    assert res.n_planes_source >= 10 and res.n_planes_target >= 10
    rot, trans = transform_errors(res.T_b_a, T_true)
    # scans 20 and 21 overlap almost fully: the extrinsic must be found, valid and right
    # (measured 1.1 deg / 0.17 m; reference poses ~0.3 deg / 8 cm, walls seen partially)
    assert res.valid, res.message
    assert rot < 2.0 and trans < 0.25, (rot, trans)
