"""A drive whose scans are de-skewed on read, with the motion of an odometry.

Raw scans of a moving spinning LiDAR are distorted by up to metres (see
:mod:`graffmatch.lidar.deskew`); matched as they are, two scans taken in a turn have no rigid
transform that is right to the metre. Wrap the drive before extracting landmarks:

    drive = Deskewed(open_dataset("sim", "/data/drive"), odometry)

``motion_poses`` are any poses whose *relative* motion between neighbouring scans is right:
an odometry (KISS-ICP, wheel, a drifting estimate), or the ground truth. Do not wrap KITTI
odometry: its scans ship de-skewed.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graffmatch.datasets.base import Dataset, Scan, has_ground_truth
from graffmatch.errors import InvalidInputError
from graffmatch.lidar.deskew import deskew_in_sequence


class Deskewed:
    """``dataset`` with every scan moved into its mid-sweep frame (constant velocity between
    the neighbouring ``motion_poses``; default: the dataset's own poses). Poses, times, paths
    and labels are the dataset's; only the points change."""

    def __init__(self, dataset: Dataset, motion_poses: ArrayLike | None = None) -> None:
        n = len(dataset)
        poses = np.asarray(dataset.poses if motion_poses is None else motion_poses, dtype=float)
        if poses.shape != (n, 4, 4) or not np.all(np.isfinite(poses)):
            raise InvalidInputError(
                f"motion_poses must be ({n}, 4, 4) finite poses for {getattr(dataset, 'name', 'the dataset')}, "
                f"got shape {poses.shape}"
            )
        self.dataset = dataset
        self.motion_poses = poses
        #: a different name and cache tag, so caches never mix raw and de-skewed landmarks
        self.name = f"{getattr(dataset, 'name', 'dataset')}+deskew"
        self.cache_tag = "deskew:" + hashlib.sha1(np.ascontiguousarray(poses).tobytes()).hexdigest()[:16]
        #: the point of this wrapper (see ScanSequence.motion_compensated)
        self.motion_compensated = True

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, i: int) -> Scan:
        scan = self.dataset[i]
        pts = deskew_in_sequence(scan.points, self.motion_poses, scan.index).astype(scan.points.dtype)
        return Scan(pts, scan.labels, scan.T_world_lidar, scan.timestamp, scan.index, scan.path)

    def points_subset(self, i: int, rows: Callable[[NDArray], NDArray[np.int64]]) -> NDArray:
        """The de-skewed points of the rows of raw scan i that ``rows(raw points)`` picks: the same points as
        ``self[i].points[rows(...)]`` up to which rows are picked, for a fraction of the de-skewing cost (de-skewing
        moves each point on its own). Why: the loop place check needs a voxel sample of two scans, not all points."""
        read = getattr(self.dataset, "read_points", None)
        if read is not None:  # points alone, without the labels
            points, index = read(i), int(i) % len(self)
        else:
            scan = self.dataset[i]
            points, index = scan.points, scan.index
        sel = points[np.asarray(rows(points), dtype=np.int64)]
        return deskew_in_sequence(sel, self.motion_poses, index).astype(points.dtype)

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    @property
    def poses(self) -> NDArray[np.float64]:
        return self.dataset.poses

    @property
    def has_poses(self) -> bool:
        return has_ground_truth(self.dataset)

    @property
    def times_assumed(self) -> bool:
        return bool(getattr(self.dataset, "times_assumed", False))

    @property
    def timestamps(self) -> NDArray[np.float64]:
        return np.asarray(getattr(self.dataset, "timestamps", np.arange(len(self), dtype=float)), float)

    def scan_path(self, i: int) -> Path:
        return self.dataset.scan_path(i)

    def label_path(self, i: int) -> Path | None:
        return self.dataset.label_path(i)

    def __repr__(self) -> str:
        return f"Deskewed({self.dataset!r})"
