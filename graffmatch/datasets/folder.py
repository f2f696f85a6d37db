"""Generic KITTI-layout folder: the data in ``../shared/data`` and the simulator's output.

Layout::

    <root>/velodyne/NNNNNN.bin     float32 x y z intensity
    <root>/labels/NNNNNN.label     optional SemanticKITTI labels (uint32)
    <root>/poses.txt               optional: one 3x4 pose per line, one line per scan (sorted by number);
                                   without it the scans have no ground truth (``has_poses`` False)
    <root>/calib.txt               optional; when it holds ``Tr`` the poses are camera-0 poses
                                   (KITTI convention) and are converted to the LiDAR frame
    <root>/times.txt               optional, seconds, one per scan (without it: frame number / 10 Hz)

Without ``Tr`` the poses are read as LiDAR-to-world directly (e.g. ``balm_courtyard``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from graffmatch.datasets.base import (
    ASSUMED_SCAN_RATE_HZ,
    ScanSequence,
    calib_transform,
    camera_to_lidar_poses,
    numbered_files,
    read_kitti_calib,
    read_times,
)
from graffmatch.errors import InvalidInputError, MalformedFileError
from graffmatch.geometry.pose_files import read_pose_file, rows_to_poses


class KittiLayoutSequence(ScanSequence):
    """A folder with ``velodyne/`` and optional ``labels/``; poses/calib/times given as paths (``pose_file`` None:
    scans without ground truth)."""

    def __init__(
        self,
        scan_dir: Path,
        pose_file: Path | None,
        calib_file: Path | None,
        times_file: Path | None,
        label_dir: Path | None,
        name: str,
        require_tr: bool = False,
    ) -> None:
        self.name = name
        if not scan_dir.is_dir():
            raise InvalidInputError(f"{name}: scan folder not found: {scan_dir}")
        files = numbered_files(scan_dir, ".bin")
        if not files:
            raise InvalidInputError(f"{name}: no NNNNNN.bin scans in {scan_dir}")
        self._paths = [p for _, p in files]
        self._frames = np.array([f for f, _ in files], dtype=np.int64)
        n = len(self._paths)
        poses = None
        if pose_file is not None:
            rows = read_pose_file(pose_file, n_columns=12)
            if rows.shape[0] != n:
                raise MalformedFileError(
                    f"{name}: {pose_file} has {rows.shape[0]} poses for {n} scans in {scan_dir}"
                )
            poses = rows_to_poses(rows, str(pose_file))
        self.T_cam_lidar: np.ndarray | None = None
        if calib_file is not None and calib_file.is_file():
            self.T_cam_lidar = calib_transform(read_kitti_calib(calib_file), "Tr", calib_file)
        if require_tr and self.T_cam_lidar is None:
            raise MalformedFileError(f"{name}: calibration {calib_file} has no 'Tr' entry")
        self.poses_are_camera = self.T_cam_lidar is not None
        if self.T_cam_lidar is not None and poses is not None:
            poses = camera_to_lidar_poses(poses, self.T_cam_lidar)
        self._poses = poses
        if times_file is not None and times_file.is_file():
            self._times = read_times(times_file, n)
        else:  # seconds all the same: frame numbers at the usual 10 Hz, and said (times_assumed)
            self._times = self._frames.astype(float) / ASSUMED_SCAN_RATE_HZ
            self.times_assumed = True
        self._label_dir = label_dir if label_dir is not None and label_dir.is_dir() else None
        self._finish()

    @property
    def has_labels(self) -> bool:
        return self._label_dir is not None

    @property
    def frame_numbers(self) -> np.ndarray:
        """The NNNNNN numbers of the scan files, in dataset order."""
        return self._frames

    def label_path(self, i: int) -> Path | None:
        if self._label_dir is None:
            return None
        p = self._label_dir / (self._paths[self._check_index(i)].stem + ".label")
        return p if p.is_file() else None


class KittiFolder(KittiLayoutSequence):
    """Generic KITTI-layout folder (see the module docstring)."""

    def __init__(self, root: str | Path, name: str | None = None) -> None:
        root = Path(root)
        if not root.is_dir():
            raise InvalidInputError(f"dataset folder not found: {root}")
        self._pose_source = str(root / "poses.txt")
        super().__init__(
            scan_dir=root / "velodyne",
            pose_file=root / "poses.txt" if (root / "poses.txt").exists() else None,
            calib_file=root / "calib.txt",
            times_file=root / "times.txt",
            label_dir=root / "labels",
            name=name or root.name,
        )
        self.root = root
        self.motion_compensated = _simulated_motion_compensated(root)


def _simulated_motion_compensated(root: Path) -> bool | None:
    """What a simulated drive's ``sim_meta.json`` says of motion smear: False for the ``realistic`` preset's
    distorted, not de-skewed scans, True for any other simulated drive, None without the file (not simulated) or when
    it cannot be read."""
    import json

    try:
        meta = json.loads((root / "sim_meta.json").read_text())
    except (OSError, ValueError):
        return None
    realism = meta.get("realism") if isinstance(meta, dict) else None
    if not isinstance(realism, dict):
        return True if isinstance(meta, dict) else None
    return not (bool(realism.get("motion_distortion")) and not bool(realism.get("deskew")))


def ground_truth_between(source: str | Path, target: str | Path) -> np.ndarray:
    """T_target_source of two scan files from the poses of the KITTI-layout folder holding both.

    What ``graffmatch register --gt auto`` uses, so a Python user scores a pair the same way.

    ``<root>/velodyne/NNNNNN.bin`` with ``<root>/poses.txt`` (and ``calib.txt`` for KITTI's
    camera-0 poses): T_target_source = inv(T_world_target) @ T_world_source.
    """
    source, target = Path(source), Path(target)
    roots = {p.resolve().parent.parent for p in (source, target)}
    if len(roots) != 1 or any(p.resolve().parent.name != "velodyne" for p in (source, target)):
        raise InvalidInputError(
            f"{source}, {target}: ground truth needs both scans in the velodyne/ folder of one "
            "KITTI-layout dataset (with poses.txt)"
        )
    root = roots.pop()
    if not (root / "poses.txt").is_file():
        raise MalformedFileError(f"{root / 'poses.txt'}: not found (needed for the ground truth)")
    ds = KittiFolder(root)
    index = {ds.scan_path(i).resolve(): i for i in range(len(ds))}
    try:
        i, j = index[source.resolve()], index[target.resolve()]
    except KeyError as exc:
        raise InvalidInputError(f"{exc.args[0]}: not a scan of {root}") from exc
    L = ds.poses
    return np.linalg.inv(L[j]) @ L[i]
