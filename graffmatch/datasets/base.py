"""The ``Dataset`` protocol shared by every loader, and the small parsers they share.

Every loader serves :class:`Scan` objects lazily (points are read from disk on ``ds[i]``) and
exposes the ground-truth poses of the LiDAR in the world (``T_world_lidar``), already converted
from whatever frame the dataset publishes (camera-0 for KITTI, IMU for KITTI-360, body for NCLT).
That way the loop-closure builder and every metric only ever see LiDAR-frame poses.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from graffmatch.errors import InvalidInputError, MalformedFileError, MissingPosesError
from graffmatch.geometry.pose_files import orthonormalize, read_pose_file, rows_to_poses
from graffmatch.lidar.io import read_bin, read_label

Array = NDArray[np.float64]

#: the scan rate assumed for a folder without times.txt: spinning LiDARs (Velodyne, Ouster, Hesai) and Livox
#: default to 10 Hz, and a time window in seconds (the loop exclusion window) must not silently count frames
ASSUMED_SCAN_RATE_HZ = 10.0


@dataclass(frozen=True, repr=False)
class Scan:
    """One LiDAR scan with its ground-truth pose.

    points : (N, 4) float32, x y z intensity in the LiDAR frame [m].
    labels : (N,) uint32 SemanticKITTI labels (class in the low 16 bits) or None.
    T_world_lidar : (4, 4) ground-truth pose of the LiDAR in the world, or None when the dataset
        has no poses (a folder of scans alone).
    timestamp : seconds (since the start of the sequence when the dataset gives times; otherwise
        the frame number at ``ASSUMED_SCAN_RATE_HZ``, and the dataset's ``times_assumed`` is True).
    index : position of the scan in its dataset (0..len-1).
    path : file the points were read from.
    """

    points: NDArray[np.float32]
    labels: NDArray[np.uint32] | None
    T_world_lidar: Array | None
    timestamp: float
    index: int
    path: Path

    @property
    def xyz(self) -> NDArray[np.float32]:
        return self.points[:, :3]

    def __repr__(self) -> str:
        return (
            f"Scan(index={self.index}, points={len(self.points)}, "
            f"labels={'yes' if self.labels is not None else 'no'}, t={self.timestamp:.3f}, "
            f"position={'unknown' if self.T_world_lidar is None else np.round(self.T_world_lidar[:3, 3], 2).tolist()}, "
            f"path='{self.path.name}')"
        )


@runtime_checkable
class Dataset(Protocol):
    """What the loop-closure builder and the evaluation need from a dataset."""

    name: str

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> Scan: ...

    @property
    def poses(self) -> Array:
        """(n, 4, 4) ground-truth ``T_world_lidar`` of every scan (``MissingPosesError`` when it has none)."""
        ...

    def scan_path(self, i: int) -> Path: ...

    def label_path(self, i: int) -> Path | None:
        """Label file of scan i, or None (no labels); part of the landmark-cache key."""
        ...


class ScanSequence:
    """Common machinery of the loaders: an ordered list of scan files with poses and times.

    Subclasses fill ``_paths``, ``_poses`` and ``_times`` in their constructor and implement
    :meth:`_read_points` (and optionally :meth:`_read_labels`); everything else is shared.
    Only the listing and the poses are read eagerly; points are read on access. ``_poses`` is None
    for scans without ground truth (a user's own drive): loop detection needs none, and what does
    (an evaluation, simulated drift) raises :class:`MissingPosesError` naming ``_pose_source``.
    """

    name: str
    #: Encoding of the files returned by :meth:`scan_path` ("kitti-bin": float32 x y z i).
    scan_format: str = "kitti-bin"
    _paths: list[Path]
    _poses: Array | None
    _times: Array
    #: where the poses were looked for, for the message when there are none
    _pose_source: str = "poses.txt"
    #: True when the dataset gave no times and they are frame numbers at ``ASSUMED_SCAN_RATE_HZ``
    times_assumed: bool = False

    def _finish(self) -> None:
        """Validate what a subclass constructor assembled (called at its end)."""
        n = len(self._paths)
        if n == 0:
            raise InvalidInputError(f"{self.name}: no scans found")
        if self._poses is not None and self._poses.shape != (n, 4, 4):
            raise MalformedFileError(
                f"{self.name}: {n} scans but poses of shape {self._poses.shape}"
            )
        if self._times.shape != (n,):
            raise MalformedFileError(f"{self.name}: {n} scans but {self._times.shape[0]} times")
        if self._poses is not None:
            self._poses.setflags(write=False)

    #: Whether the scans are free of motion smear (de-skewed, or taken without motion distortion): True, False,
    #: or None when the dataset does not say (most real data). Readers that rely on centimetre geometry of whole
    #: scans (the loop place check) refuse scans that say False.
    motion_compensated: bool | None = None

    # ---- protocol ------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._paths)

    def _check_index(self, i: int) -> int:
        n = len(self._paths)
        if not isinstance(i, (int, np.integer)):
            raise TypeError(f"scan index must be an int, got {type(i).__name__}")
        i = int(i)
        if i < -n or i >= n:
            raise IndexError(f"{self.name}: scan index {i} out of range for {n} scans")
        return i % n

    def __getitem__(self, i: int) -> Scan:
        i = self._check_index(i)
        path = self._paths[i]
        points = self._read_points(path)
        labels = self._read_labels(i)
        if labels is not None and labels.shape[0] != points.shape[0]:
            raise MalformedFileError(
                f"{self.name}: scan {path.name} has {points.shape[0]} points "
                f"but {labels.shape[0]} labels"
            )
        pose = None if self._poses is None else self._poses[i].copy()
        return Scan(points, labels, pose, float(self._times[i]), i, path)

    def __iter__(self) -> Iterator[Scan]:
        return (self[i] for i in range(len(self)))

    def read_points(self, i: int) -> NDArray[np.float32]:
        """Scan i's points alone: no labels read (~4 instead of ~10 ms for a 120k-point simulated scan), for readers
        that need none (the loop place check)."""
        return self._read_points(self._paths[self._check_index(i)])

    @property
    def has_poses(self) -> bool:
        """Whether the dataset has ground-truth poses (a folder of scans alone has none)."""
        return self._poses is not None

    @property
    def poses(self) -> Array:
        if self._poses is None:
            raise MissingPosesError(
                f"{self.name}: no ground-truth poses ({self._pose_source} not found). Loop detection runs without "
                "them; an evaluation or simulated drift needs them, and odometry can come from the scans "
                "(--odometry kiss-icp) or a pose file (--odometry PATH)"
            )
        return self._poses

    @property
    def timestamps(self) -> Array:
        """(n,) seconds (frame numbers at ``ASSUMED_SCAN_RATE_HZ`` when the dataset has no times)."""
        return self._times

    def scan_path(self, i: int) -> Path:
        return self._paths[self._check_index(i)]

    def label_path(self, i: int) -> Path | None:
        """Path of the label file of scan i, or None when the dataset has none."""
        return None

    def _read_points(self, path: Path) -> NDArray[np.float32]:
        return read_kitti_bin(path)

    def _read_labels(self, i: int) -> NDArray[np.uint32] | None:
        p = self.label_path(i)
        return None if p is None else read_kitti_labels(p)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, scans={len(self)})"


def has_ground_truth(dataset: object) -> bool:
    """Whether ``dataset`` has ground-truth poses (datasets that do not say, e.g. wrappers of arrays, have)."""
    return bool(getattr(dataset, "has_poses", True))


# ---- readers of the files the loaders share ---------------------------------------------
def read_kitti_bin(path: Path) -> NDArray[np.float32]:
    """KITTI .bin scan -> (N, 4) float32 (the front end's reader: one parser in the code base)."""
    return read_bin(path)


def read_kitti_labels(path: Path) -> NDArray[np.uint32]:
    """SemanticKITTI .label file -> (N,) uint32 (class in the low 16 bits)."""
    return read_label(path)


def read_kitti_calib(path: Path) -> dict[str, Array]:
    """KITTI-style ``key: v1 v2 ...`` calibration file -> {key: values}."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"calibration file not found: {path}")
    out: dict[str, Array] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        if ":" not in line:
            raise MalformedFileError(f"{path}:{lineno}: expected 'key: values'")
        key, vals = line.split(":", 1)
        try:
            out[key.strip()] = np.array([float(v) for v in vals.split()], dtype=float)
        except ValueError as exc:
            raise MalformedFileError(f"{path}:{lineno}: not a number ({exc})") from exc
    return out


def calib_transform(calib: dict[str, Array], key: str, path: Path) -> Array | None:
    """A 3x4 entry of a calibration dict as a 4x4 transform, or None when absent."""
    if key not in calib:
        return None
    v = calib[key]
    if v.size != 12:
        raise MalformedFileError(f"{path}: {key} must have 12 values, got {v.size}")
    return rows_to_poses(v[None], f"{path} ({key})")[0]


def camera_to_lidar_poses(P_world_cam: Array, T_cam_lidar: Array) -> Array:
    """KITTI convention: LiDAR pose = inv(Tr) @ P @ Tr with Tr = T_cam0_lidar.

    The world frame is then the LiDAR frame of the first scan (like the camera poses are
    relative to the first camera), so scan 0 of KITTI has T_world_lidar = I.
    """
    Tr = np.asarray(T_cam_lidar, dtype=float)
    Tr_inv = np.linalg.inv(Tr)
    return orthonormalize(Tr_inv @ P_world_cam @ Tr)


def numbered_files(folder: Path, suffix: str) -> list[tuple[int, Path]]:
    """Files ``<number><suffix>`` of a folder sorted by number (other files are ignored)."""
    out = []
    for p in folder.iterdir():
        if p.suffix == suffix and p.stem.isdigit():
            out.append((int(p.stem), p))
    out.sort()
    return out


def read_times(path: Path, n: int) -> Array:
    """One time per line (seconds); the count must match the scans."""
    t = read_pose_file(path, n_columns=1)[:, 0]
    if t.shape[0] != n:
        raise MalformedFileError(f"{path}: {t.shape[0]} times for {n} scans")
    return t
