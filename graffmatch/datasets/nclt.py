"""NCLT (University of Michigan North Campus Long-Term) Velodyne HDL-32E scans.

Layout (as extracted from the NCLT downloads; the session folder may also be the root)::

    <root>/<date>/velodyne_sync/<utime>.bin      packed points (below)
    <root>/groundtruth_<date>.csv                utime,x,y,z,roll,pitch,yaw  (body frame)
        (also searched: <root>/<date>/ and <root>/ground_truth/)

``velodyne_sync`` points are 8 bytes each: x, y, z as little-endian uint16 with a scale of
0.005 m and an offset of -100 m, then intensity (uint8) and laser id (uint8), as in NCLT's
``read_vel_sync.py``.

The ground truth is the pose of the robot *body* in the world (angles in radians,
R = Rz(yaw) Ry(pitch) Rx(roll)); it is interpolated to each scan time (linear in position,
slerp in rotation). Scans outside the ground-truth time span, or in a gap of the ground truth
longer than ``max_gap_s``, are not served. The LiDAR pose is ``T_world_body @ T_body_velo``
with the body -> Velodyne extrinsic documented by NCLT (Carlevaris-Bianco et al., IJRR 2016,
"University of Michigan North Campus long-term vision and lidar dataset", sensor
transformation table / ``x_body_velo`` in the dataset's development kit):
x=0.002 m, y=-0.004 m, z=-0.957 m, roll=0.807 deg, pitch=0.166 deg, yaw=-90.703 deg.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from graffmatch.datasets.base import ScanSequence, numbered_files
from graffmatch.errors import InvalidInputError, MalformedFileError
from graffmatch.geometry.pose_files import orthonormalize

#: NCLT body -> Velodyne extrinsic: x, y, z [m], roll, pitch, yaw [deg] (see module docstring).
NCLT_X_BODY_VELO = (0.002, -0.004, -0.957, 0.807, 0.166, -90.703)
NCLT_SCALE = 0.005
NCLT_OFFSET = -100.0
_NCLT_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("i", "u1"), ("l", "u1")])


def ssc_to_transform(x: float, y: float, z: float, roll: float, pitch: float, yaw: float) -> NDArray:
    """NCLT 6-DOF 'ssc' pose (angles in radians) -> 4x4, R = Rz(yaw) Ry(pitch) Rx(roll)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
    T[:3, 3] = [x, y, z]
    return T


def nclt_body_to_velo() -> NDArray:
    """T_body_velo from :data:`NCLT_X_BODY_VELO`."""
    x, y, z, r, p, h = NCLT_X_BODY_VELO
    return ssc_to_transform(x, y, z, *np.deg2rad([r, p, h]))


def read_nclt_bin(path: Path) -> NDArray[np.float32]:
    """NCLT ``velodyne_sync`` file -> (N, 4) float32 x y z intensity (laser id dropped)."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"scan file not found: {path}")
    size = path.stat().st_size
    if size % _NCLT_DTYPE.itemsize:
        raise MalformedFileError(f"{path}: size {size} is not a multiple of 8 bytes (NCLT format)")
    raw = np.fromfile(path, dtype=_NCLT_DTYPE)
    out = np.empty((raw.shape[0], 4), dtype=np.float32)
    for c, key in enumerate("xyz"):
        out[:, c] = raw[key] * NCLT_SCALE + NCLT_OFFSET
    out[:, 3] = raw["i"]
    return out


def write_nclt_bin(path: Path, points: NDArray) -> None:
    """Inverse of :func:`read_nclt_bin` (quantised to 5 mm); used by tests and tools."""
    P = np.asarray(points, dtype=float)
    q = np.round((P[:, :3] - NCLT_OFFSET) / NCLT_SCALE)
    if np.any(q < 0) or np.any(q > 65535):
        raise InvalidInputError("NCLT points must lie within [-100, 227.675] m")
    raw = np.zeros(len(P), dtype=_NCLT_DTYPE)
    for c, key in enumerate("xyz"):
        raw[key] = q[:, c].astype(np.uint16)
    if P.shape[1] > 3:
        raw["i"] = np.clip(np.round(P[:, 3]), 0, 255).astype(np.uint8)
    raw.tofile(path)


def read_nclt_groundtruth(path: Path) -> NDArray:
    """``groundtruth_<date>.csv`` -> (n, 7) rows utime,x,y,z,roll,pitch,yaw (NaN rows dropped)."""
    if not path.is_file():
        raise InvalidInputError(f"NCLT ground truth not found: {path}")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line[0].isalpha():  # blank or a header
            continue
        parts = line.split(",")
        if len(parts) != 7:
            raise MalformedFileError(f"{path}:{lineno}: expected 7 comma-separated values")
        try:
            rows.append([float(v) for v in parts])
        except ValueError as exc:
            raise MalformedFileError(f"{path}:{lineno}: not a number ({exc})") from exc
    gt = np.asarray(rows, dtype=float).reshape(-1, 7)
    gt = gt[np.all(np.isfinite(gt), axis=1)]
    if len(gt) < 2:
        raise MalformedFileError(f"{path}: fewer than 2 valid ground-truth rows")
    gt = gt[np.argsort(gt[:, 0], kind="stable")]
    if np.any(np.diff(gt[:, 0]) <= 0):
        raise MalformedFileError(f"{path}: duplicate utime values")
    return gt


def interpolate_poses(gt: NDArray, utimes: NDArray) -> NDArray:
    """Body poses (n, 4, 4) at ``utimes`` (inside the ground-truth span)."""
    t = gt[:, 0]
    R = Rotation.from_euler("ZYX", gt[:, [6, 5, 4]])
    slerp = Slerp(t, R)
    q = np.asarray(utimes, dtype=float)
    T = np.zeros((len(q), 4, 4))
    T[:, :3, :3] = slerp(q).as_matrix()
    for c in range(3):
        T[:, c, 3] = np.interp(q, t, gt[:, 1 + c])
    T[:, 3, 3] = 1.0
    return T


class NCLT(ScanSequence):
    """One NCLT session (e.g. ``"2012-04-29"``); LiDAR-frame ground truth at scan times."""

    scan_format = "nclt-bin"  # packed uint16 points: read with read_nclt_bin

    def __init__(self, root: str | Path, date: str, max_gap_s: float = 1.0) -> None:
        root = Path(root)
        self.root = root
        self.date = str(date)
        self.name = f"nclt-{self.date}"
        scan_dirs = [
            root / self.date / "velodyne_sync",
            root / "velodyne_sync",
            root / "velodyne_data" / self.date / "velodyne_sync",
        ]
        scan_dir = next((d for d in scan_dirs if d.is_dir()), None)
        if scan_dir is None:
            raise InvalidInputError(
                f"NCLT: no velodyne_sync folder (looked in {', '.join(map(str, scan_dirs))})"
            )
        gt_name = f"groundtruth_{self.date}.csv"
        gt_files = [root / gt_name, root / self.date / gt_name, root / "ground_truth" / gt_name]
        gt_file = next((f for f in gt_files if f.is_file()), None)
        if gt_file is None:
            raise InvalidInputError(
                f"NCLT: ground truth not found (looked for {', '.join(map(str, gt_files))})"
            )
        gt = read_nclt_groundtruth(gt_file)
        files = numbered_files(scan_dir, ".bin")
        if not files:
            raise InvalidInputError(f"NCLT: no <utime>.bin scans in {scan_dir}")
        utimes = np.array([u for u, _ in files], dtype=np.int64)
        inside = (utimes >= gt[0, 0]) & (utimes <= gt[-1, 0])
        # Reject scans in a hole of the ground truth: interpolating across it would invent poses.
        k = np.clip(np.searchsorted(gt[:, 0], utimes), 1, len(gt) - 1)
        gap = gt[k, 0] - gt[k - 1, 0]
        keep = inside & (gap <= max_gap_s * 1e6)
        if not np.any(keep):
            raise MalformedFileError(
                f"{self.name}: no scan lies within the ground-truth time span of {gt_file}"
            )
        self._utimes = utimes[keep]
        self._paths = [files[i][1] for i in np.flatnonzero(keep)]
        self.T_body_velo = nclt_body_to_velo()
        self._poses = orthonormalize(interpolate_poses(gt, self._utimes) @ self.T_body_velo)
        self._times = self._utimes * 1e-6
        self._finish()

    @property
    def utimes(self) -> NDArray[np.int64]:
        """Microsecond timestamps of the served scans (their file names)."""
        return self._utimes

    def _read_points(self, path: Path) -> NDArray[np.float32]:
        return read_nclt_bin(path)
