"""Dataset loaders: real KITTI-layout scans and tiny fixture datasets built on the fly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from graffmatch.datasets import (
    NCLT,
    Dataset,
    Kitti360,
    KittiFolder,
    KittiOdometry,
    available,
    open_dataset,
    register,
)
from graffmatch.datasets.folder import ground_truth_between
from graffmatch.datasets.nclt import nclt_body_to_velo, ssc_to_transform, write_nclt_bin
from graffmatch.errors import InvalidInputError, MalformedFileError, MissingPosesError
from graffmatch.geometry.transforms import (
    invert,
    make_transform,
    random_transform,
    rot_z,
    transform_points,
)


def _rows(T: np.ndarray) -> str:
    return "\n".join(" ".join(f"{v:.12e}" for v in M[:3].reshape(-1)) for M in T) + "\n"


def _write_bin(path: Path, pts: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    pts.astype(np.float32).tofile(path)


def _random_scans(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    return [rng.normal(0, 10, size=(50 + 7 * i, 4)).astype(np.float32) for i in range(n)]


def _random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.stack([random_transform(rng, max_translation=50.0) for _ in range(n)])


def _median_nn(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.median(cKDTree(b).query(a)[0]))


# ---- real data --------------------------------------------------------------------------
def test_kitti00_first6_lidar_poses(shared_data: Path) -> None:
    ds = open_dataset("folder", shared_data / "kitti00_first6")
    assert isinstance(ds, Dataset)
    assert len(ds) == 6 and ds.poses.shape == (6, 4, 4)
    assert np.allclose(ds.poses[0], np.eye(4), atol=1e-6)
    d = np.linalg.norm(ds.poses[5, :3, 3] - ds.poses[0, :3, 3])
    assert 4.2 < d < 4.4
    # LiDAR x points forward: the car drove ~4.3 m along the first scan's x axis.
    assert ds.poses[5, 0, 3] > 4.2
    s0, s5 = ds[0], ds[5]
    assert s5.points.dtype == np.float32 and s5.points.shape[1] == 4 and s5.labels is None
    assert s5.path == ds.scan_path(5) and s5.index == 5
    # The converted poses register scan 5 onto scan 0; the raw camera poses would not.
    a = s5.xyz[::10]
    a = a[(np.linalg.norm(a, axis=1) < 30) & (a[:, 2] > -1.2)]  # near, above the road
    T_05 = invert(ds.poses[0]) @ ds.poses[5]
    good = _median_nn(transform_points(T_05, a), s0.xyz)
    still = _median_nn(a.astype(float), s0.xyz)
    cam = np.loadtxt(shared_data / "kitti00_first6" / "poses.txt").reshape(-1, 3, 4)
    P5 = np.vstack([cam[5], [0, 0, 0, 1]])
    bad = _median_nn(transform_points(P5, a), s0.xyz)
    assert good < 0.25 and good < 0.5 * still and bad > 1.0


def test_balm_courtyard_poses_are_lidar_to_world(shared_data: Path) -> None:
    ds = KittiFolder(shared_data / "balm_courtyard")
    assert len(ds) == 89 and not ds.poses_are_camera and not ds.has_labels
    assert np.isclose(ds.timestamps[1], 0.999227) and ds[10].timestamp == ds.timestamps[10]
    path_len = np.linalg.norm(np.diff(ds.poses[:, :3, 3], axis=0), axis=1).sum()
    assert 70 < path_len < 78  # "walked for 74 m"
    # Scans 20 and 24 (4 s apart) overlap to a few cm when put into the world by their poses.
    a, b = ds[20], ds[24]
    sub = a.xyz[:: max(1, len(a.points) // 8000)]
    pa = transform_points(ds.poses[20], sub)
    pb = transform_points(ds.poses[24], b.xyz)
    good = _median_nn(pa, pb)
    assert good < 0.12
    # ... and not when the poses are ignored.
    assert _median_nn(sub.astype(float), b.xyz) > 2 * good


# ---- KITTI odometry fixture ----------------------------------------------------------------
@pytest.fixture
def kitti_root(tmp_path: Path, rng: np.random.Generator):
    root = tmp_path / "kitti"
    seq = root / "sequences" / "03"
    scans = _random_scans(rng, 3)
    for i, s in enumerate(scans):
        _write_bin(seq / "velodyne" / f"{i:06d}.bin", s)
        (seq / "labels").mkdir(parents=True, exist_ok=True)
        np.arange(len(s), dtype=np.uint32).__add__(80 << 16).tofile(seq / "labels" / f"{i:06d}.label")
    Tr = random_transform(rng, 1.0)
    T_lidar = _random_poses(rng, 3)
    P_cam = Tr @ T_lidar @ invert(Tr)
    (root / "poses").mkdir(parents=True)
    (root / "poses" / "03.txt").write_text(_rows(P_cam))
    calib = "P0: " + " ".join(["1.0"] * 12) + "\nTr: " + _rows(Tr[None]).strip() + "\n"
    (seq / "calib.txt").write_text(calib)
    (seq / "times.txt").write_text("0.0\n0.1\n0.2\n")
    return root, scans, T_lidar


def test_kitti_odometry_roundtrip(kitti_root) -> None:
    root, scans, T_lidar = kitti_root
    ds = open_dataset("kitti", root, sequence=3)
    assert isinstance(ds, KittiOdometry) and ds.name == "kitti-03" and len(ds) == 3
    assert np.allclose(ds.poses, T_lidar, atol=1e-9)
    for i, scan in enumerate(ds):
        assert np.array_equal(scan.points, scans[i])
        assert scan.labels is not None and np.all((scan.labels >> 16) == 80)
        assert np.array_equal(scan.labels & 0xFFFF, np.arange(len(scans[i])))
    assert ds[-1].index == 2 and np.isclose(ds[2].timestamp, 0.2)
    with pytest.raises(IndexError):
        ds[3]


def test_kitti_layout_errors(kitti_root, tmp_path: Path) -> None:
    root, _, _ = kitti_root
    with pytest.raises(InvalidInputError, match="sequences/07"):
        KittiOdometry(root, "07")
    seq = root / "sequences" / "03"
    # A scan without a pose.
    _write_bin(seq / "velodyne" / "000003.bin", np.zeros((4, 4)))
    with pytest.raises(MalformedFileError, match="3 poses for 4 scans"):
        KittiOdometry(root, "03")
    (seq / "velodyne" / "000003.bin").unlink()
    # A malformed pose line names the file and line.
    good = (root / "poses" / "03.txt").read_text()
    (root / "poses" / "03.txt").write_text(good + "1 2 3\n")
    with pytest.raises(MalformedFileError, match=r"03.txt:4: expected 12 numbers"):
        KittiOdometry(root, "03")
    (root / "poses" / "03.txt").write_text(good.replace("e", "x", 1))
    with pytest.raises(MalformedFileError, match="not a number"):
        KittiOdometry(root, "03")
    (root / "poses" / "03.txt").write_text(good)
    (seq / "calib.txt").write_text("P0: " + " ".join(["1"] * 12) + "\n")
    with pytest.raises(MalformedFileError, match="no 'Tr'"):
        KittiOdometry(root, "03")
    with pytest.raises(InvalidInputError, match="not found"):
        KittiFolder(tmp_path / "nowhere")
    with pytest.raises(InvalidInputError, match="unknown dataset kind"):
        open_dataset("tum", root)


def test_scans_without_poses_load_and_say_what_needs_them(kitti_root, tmp_path: Path, rng) -> None:
    """A user's folder of scans alone, and a KITTI test sequence (11-21: no poses), load; asking for the ground truth
    raises MissingPosesError naming the file looked for, never a silent identity."""
    for i, s in enumerate(_random_scans(rng, 3)):
        _write_bin(tmp_path / "velodyne" / f"{i:06d}.bin", s)
    (tmp_path / "times.txt").write_text("0.0\n0.1\n0.2\n")
    ds = KittiFolder(tmp_path)
    assert not ds.has_poses and not ds.times_assumed and len(ds) == 3
    assert ds[1].T_world_lidar is None and np.isclose(ds[1].timestamp, 0.1) and "unknown" in repr(ds[1])
    with pytest.raises(MissingPosesError, match=r"poses.txt not found.*--odometry kiss-icp"):
        _ = ds.poses
    root, _, _ = kitti_root
    (root / "poses" / "03.txt").unlink()
    k = KittiOdometry(root, "03")
    assert not k.has_poses and k[0].T_world_lidar is None
    with pytest.raises(MissingPosesError, match=r"poses/03.txt or .*sequences/03/poses.txt not found"):
        _ = k.poses


def test_folder_without_calib_and_truncated_scan(tmp_path: Path, rng) -> None:
    T = _random_poses(rng, 2)
    for i, s in enumerate(_random_scans(rng, 2)):
        _write_bin(tmp_path / "velodyne" / f"{i:06d}.bin", s)
    (tmp_path / "poses.txt").write_text(_rows(T))
    ds = KittiFolder(tmp_path)
    # no times.txt: frame numbers at the assumed 10 Hz, said, so a window in seconds never counts frames
    assert np.allclose(ds.poses, T, atol=1e-9) and np.allclose(ds.timestamps, [0.0, 0.1]) and ds.times_assumed
    with open(tmp_path / "velodyne" / "000001.bin", "ab") as f:
        f.write(b"\x00\x00")
    with pytest.raises(MalformedFileError):
        ds[1]
    bad = T.copy()
    bad[1, :3, :3] *= 1.1
    (tmp_path / "poses.txt").write_text(_rows(bad))
    with pytest.raises(MalformedFileError, match="non-orthonormal"):
        KittiFolder(tmp_path)


def test_ground_truth_between_two_scan_files(tmp_path: Path, rng) -> None:
    """``register --gt auto``'s library call: inv(T_world_target) @ T_world_source, or a clear error."""
    T = _random_poses(rng, 3)
    for i, s in enumerate(_random_scans(rng, 3)):
        _write_bin(tmp_path / "velodyne" / f"{i:06d}.bin", s)
    (tmp_path / "poses.txt").write_text(_rows(T))
    scan = [tmp_path / "velodyne" / f"{i:06d}.bin" for i in range(3)]
    G = ground_truth_between(scan[2], scan[0])
    np.testing.assert_allclose(G, np.linalg.inv(T[0]) @ T[2], atol=1e-9)
    np.testing.assert_allclose(ground_truth_between(scan[0], scan[2]) @ G, np.eye(4), atol=1e-9)
    other = tmp_path / "elsewhere" / "velodyne" / "000000.bin"
    _write_bin(other, _random_scans(rng, 1)[0])
    with pytest.raises(InvalidInputError, match="needs both scans in the velodyne/ folder"):
        ground_truth_between(scan[0], other)
    extra = tmp_path / "velodyne" / "notes.bin"
    _write_bin(extra, _random_scans(rng, 1)[0])
    with pytest.raises(InvalidInputError, match="notes.bin: not a scan of"):
        ground_truth_between(extra, scan[0])
    (tmp_path / "poses.txt").unlink()
    with pytest.raises(MalformedFileError, match="poses.txt: not found"):
        ground_truth_between(scan[1], scan[0])


def test_registry_is_explicit() -> None:
    assert {"kitti", "kitti360", "nclt", "folder"} <= set(available())
    with pytest.raises(InvalidInputError, match="already registered"):
        register("kitti", KittiFolder)
    register("my-folder", KittiFolder)
    assert "my-folder" in available()


# ---- KITTI-360 fixture ----------------------------------------------------------------------
def test_kitti360_composes_calibration_and_skips_frames_without_pose(tmp_path: Path, rng) -> None:
    seq = "2013_05_28_drive_0004_sync"
    scans = _random_scans(rng, 5)
    data = tmp_path / "data_3d_raw" / seq / "velodyne_points" / "data"
    for i, s in enumerate(scans):
        _write_bin(data / f"{i:010d}.bin", s)
    (data.parent / "timestamps.txt").write_text(
        "\n".join(f"2013-05-28 08:46:0{i}.500000000" for i in range(5)) + "\n"
    )
    T_pose_cam0 = random_transform(rng, 2.0)
    T_velo_cam0 = random_transform(rng, 2.0)
    T_world_velo = _random_poses(rng, 5)
    T_world_pose = T_world_velo @ invert(T_pose_cam0 @ invert(T_velo_cam0))
    frames = [1, 2, 4, 7]  # frame 7 has no scan, frames 0 and 3 no pose
    lines = [f"{f} " + _rows(T_world_pose[f][None] if f < 5 else np.eye(4)[None]) for f in frames]
    (tmp_path / "data_poses" / seq).mkdir(parents=True)
    (tmp_path / "data_poses" / seq / "poses.txt").write_text("".join(lines))
    cal = tmp_path / "calibration"
    cal.mkdir()
    (cal / "calib_cam_to_pose.txt").write_text("image_00: " + _rows(T_pose_cam0[None]))
    (cal / "calib_cam_to_velo.txt").write_text(_rows(T_velo_cam0[None]))

    ds = open_dataset("kitti360", tmp_path, sequence=4)
    assert isinstance(ds, Kitti360) and len(ds) == 3
    assert np.array_equal(ds.frame_numbers, [1, 2, 4])
    assert np.allclose(ds.poses, T_world_velo[[1, 2, 4]], atol=1e-9)
    assert np.array_equal(ds[2].points, scans[4])
    assert np.allclose(ds.timestamps, [1.0, 2.0, 4.0])
    (cal / "calib_cam_to_velo.txt").write_text("1 2 3\n")
    with pytest.raises(MalformedFileError, match="12 values"):
        Kitti360(tmp_path, seq)
    with pytest.raises(InvalidInputError, match="scan folder not found"):
        Kitti360(tmp_path, 9)


# ---- NCLT fixture ---------------------------------------------------------------------------
def test_nclt_packed_points_and_interpolated_poses(tmp_path: Path, rng) -> None:
    date = "2012-04-29"
    t0 = 1335704127712909
    # Ground truth at 10 Hz: constant velocity and constant yaw rate, so linear interpolation
    # and slerp are exact and the expected pose is known in closed form.
    tg = t0 + np.arange(0, 50) * 100_000
    s = (tg - t0) * 1e-6

    def body(sec):
        return np.stack([ssc_to_transform(2 * u, -1 * u, 0.1 * u, 0.0, 0.0, 0.3 * u) for u in sec])

    T_gt = body(s)
    gt = np.column_stack([tg, T_gt[:, 0, 3], T_gt[:, 1, 3], T_gt[:, 2, 3], 0 * s, 0 * s, 0.3 * s])
    lines = ["nan,nan,nan,nan,nan,nan,nan"] + [",".join(f"{v:.9f}" for v in r) for r in gt]
    (tmp_path / f"groundtruth_{date}.csv").write_text("\n".join(lines) + "\n")
    scan_dir = tmp_path / date / "velodyne_sync"
    scan_dir.mkdir(parents=True)
    ts = [t0 - 50_000, t0 + 123_456, t0 + 2_345_678, t0 + 4_999_999, t0 + 6_000_000]
    pts = [np.column_stack([rng.uniform(-50, 50, (40, 3)), rng.integers(0, 255, 40)]) for _ in ts]
    for t, p in zip(ts, pts, strict=True):
        write_nclt_bin(scan_dir / f"{t}.bin", p)

    ds = open_dataset("nclt", tmp_path, date=date)
    assert isinstance(ds, NCLT) and len(ds) == 2  # first and last two are outside the GT span
    assert np.array_equal(ds.utimes, ts[1:3])
    expected = body((np.array(ts[1:3]) - t0) * 1e-6) @ nclt_body_to_velo()
    assert np.allclose(ds.poses, expected, atol=1e-7)
    scan = ds[0]
    assert np.abs(scan.points[:, :3] - pts[1][:, :3]).max() <= 0.0026
    assert np.array_equal(scan.points[:, 3], pts[1][:, 3])
    assert np.isclose(scan.timestamp, ts[1] * 1e-6)
    # The documented extrinsic: the Velodyne sits ~0.96 m above the body, yawed by -90.7 deg.
    Tbv = nclt_body_to_velo()
    assert np.allclose(Tbv[:3, 3], [0.002, -0.004, -0.957])
    assert np.allclose(Tbv[:3, :3], rot_z(np.deg2rad(-90.703)), atol=0.02)
    (scan_dir / f"{ts[1]}.bin").write_bytes(b"\x01\x02\x03")
    with pytest.raises(MalformedFileError, match="multiple of 8"):
        ds[0]
    with pytest.raises(InvalidInputError, match="no velodyne_sync"):
        NCLT(tmp_path, "2013-01-10")
    (tmp_path / "2013-01-10" / "velodyne_sync").mkdir(parents=True)
    with pytest.raises(InvalidInputError, match="ground truth not found"):
        NCLT(tmp_path, "2013-01-10")


def test_scan_repr_and_pose_readonly(tmp_path: Path) -> None:
    _write_bin(tmp_path / "velodyne" / "000000.bin", np.ones((3, 4)))
    (tmp_path / "poses.txt").write_text(_rows(make_transform(np.eye(3), [1, 2, 3])[None]))
    ds = KittiFolder(tmp_path, name="tiny")
    assert "tiny" in repr(ds) and "points=3" in repr(ds[0])
    with pytest.raises(ValueError):
        ds.poses[0, 0, 3] = 5.0
