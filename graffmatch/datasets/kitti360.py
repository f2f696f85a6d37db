"""KITTI-360 raw Velodyne scans with the LiDAR-frame ground truth.

Layout (as downloaded)::

    <root>/data_3d_raw/<seq>/velodyne_points/data/NNNNNNNNNN.bin
    <root>/data_3d_raw/<seq>/velodyne_points/timestamps.txt      optional
    <root>/data_poses/<seq>/poses.txt          'frame r11 r12 r13 t1 ... r33 t3' (IMU/GPS pose)
    <root>/calibration/calib_cam_to_pose.txt   'image_00: 12 values' = T_pose_cam0
    <root>/calibration/calib_cam_to_velo.txt   12 values              = T_velo_cam0

``poses.txt`` holds the pose of the IMU/GPS ("pose") frame in the world for a subset of the
frames only (the vehicle's standstills are left out), so only frames that have both a scan and
a pose are served. The LiDAR pose is composed as
``T_world_velo = T_world_pose @ T_pose_cam0 @ inv(T_velo_cam0)``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from graffmatch.datasets.base import (
    ScanSequence,
    calib_transform,
    numbered_files,
    read_kitti_calib,
)
from graffmatch.errors import InvalidInputError, MalformedFileError
from graffmatch.geometry.pose_files import orthonormalize, read_pose_file, rows_to_poses


def kitti360_sequence_name(sequence: str | int) -> str:
    """0 / "00" / "0000" -> "2013_05_28_drive_0000_sync"; full names pass through."""
    s = str(sequence).strip()
    if s.isdigit():
        return f"2013_05_28_drive_{int(s):04d}_sync"
    return s


def _read_cam_to_velo(path: Path) -> np.ndarray:
    if not path.is_file():
        raise InvalidInputError(f"KITTI-360 calibration not found: {path}")
    vals = path.read_text().split()
    try:
        v = np.array([float(x) for x in vals], dtype=float)
    except ValueError as exc:
        raise MalformedFileError(f"{path}: not a number ({exc})") from exc
    if v.size != 12:
        raise MalformedFileError(f"{path}: expected 12 values (3x4 T_velo_cam0), got {v.size}")
    return rows_to_poses(v[None], str(path))[0]


def _read_timestamps(path: Path) -> np.ndarray | None:
    """'YYYY-MM-DD hh:mm:ss.nnnnnnnnn' per line -> seconds since the first line."""
    if not path.is_file():
        return None
    lines = [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]
    try:
        t = np.array([np.datetime64(ln.replace(" ", "T"), "ns") for ln in lines])
    except ValueError as exc:
        raise MalformedFileError(f"{path}: malformed timestamp ({exc})") from exc
    return (t - t[0]).astype("timedelta64[ns]").astype(np.int64) * 1e-9


class Kitti360(ScanSequence):
    """One KITTI-360 sequence; ``len`` counts only the frames with a ground-truth pose."""

    def __init__(self, root: str | Path, sequence: str | int = 0) -> None:
        root = Path(root)
        seq = kitti360_sequence_name(sequence)
        self.name = f"kitti360-{seq}"
        self.root = root
        self.sequence = seq
        velo_dir = root / "data_3d_raw" / seq / "velodyne_points"
        scan_dir = velo_dir / "data"
        if not scan_dir.is_dir():
            raise InvalidInputError(f"KITTI-360 scan folder not found: {scan_dir}")
        pose_file = root / "data_poses" / seq / "poses.txt"
        rows = read_pose_file(pose_file, n_columns=13)
        frames_pose = rows[:, 0]
        if np.any(frames_pose != np.round(frames_pose)) or np.any(frames_pose < 0):
            raise MalformedFileError(f"{pose_file}: first column must be a frame number")
        frames_pose = frames_pose.astype(np.int64)
        if np.any(np.diff(frames_pose) <= 0):
            raise MalformedFileError(f"{pose_file}: frame numbers must increase")
        T_world_pose = rows_to_poses(rows[:, 1:], str(pose_file))

        calib_dir = root / "calibration"
        c2p_file = calib_dir / "calib_cam_to_pose.txt"
        T_pose_cam0 = calib_transform(read_kitti_calib(c2p_file), "image_00", c2p_file)
        if T_pose_cam0 is None:
            raise MalformedFileError(f"{c2p_file}: no 'image_00' entry")
        T_velo_cam0 = _read_cam_to_velo(calib_dir / "calib_cam_to_velo.txt")
        self.T_pose_velo = T_pose_cam0 @ np.linalg.inv(T_velo_cam0)

        files = numbered_files(scan_dir, ".bin")
        if not files:
            raise InvalidInputError(f"KITTI-360: no scans in {scan_dir}")
        frames_scan = np.array([f for f, _ in files], dtype=np.int64)
        keep_scan = np.isin(frames_scan, frames_pose)
        if not np.any(keep_scan):
            raise MalformedFileError(f"{self.name}: no scan has a ground-truth pose in {pose_file}")
        self._frames = frames_scan[keep_scan]
        self._paths = [files[i][1] for i in np.flatnonzero(keep_scan)]
        pose_row = np.searchsorted(frames_pose, self._frames)
        self._poses = orthonormalize(T_world_pose[pose_row] @ self.T_pose_velo)
        stamps = _read_timestamps(velo_dir / "timestamps.txt")
        if stamps is not None:
            if self._frames.max() >= len(stamps):
                raise MalformedFileError(
                    f"{velo_dir / 'timestamps.txt'}: {len(stamps)} lines, frame "
                    f"{int(self._frames.max())} has no time"
                )
            self._times = stamps[self._frames]
        else:
            self._times = self._frames.astype(float)
        self._finish()

    @property
    def frame_numbers(self) -> np.ndarray:
        """KITTI-360 frame number of each served scan (scans without pose are skipped)."""
        return self._frames
