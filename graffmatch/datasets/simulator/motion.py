"""Motion within a sweep: per-column sensor poses, de-skewing, and noisy ground-truth poses.

A spinning LiDAR on a moving car takes each column of a scan from a different pose: over the
0.1 s sweep of an HDL-64E at 10 m/s the sensor moves 1 m, so a raw scan is distorted. The
simulator casts every column from the pose at its own time, with the scan's pose (the
ground truth) at mid-sweep, when the sensor looks forward (KITTI sweeps from behind, as
``sensor.render_scan`` does). ``graffmatch.lidar.deskew`` undoes it as a loader of real data would:
per-point times from the azimuth and a constant-velocity motion from the neighbouring poses.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from graffmatch.lidar.deskew import azimuth_times, deskew_scan, sweep_motion, sweep_twist

__all__ = [
    "azimuth_times", "column_times", "deskew_scan", "perturb_poses", "sweep_motion", "sweep_poses", "sweep_twist",
]


def column_times(n_columns: int) -> NDArray[np.float64]:
    """Sweep fraction in [-0.5, 0.5) of each azimuth column; 0 is the forward-looking column."""
    return (np.arange(n_columns) + 0.5) / n_columns - 0.5


def sweep_poses(T_world_lidar: NDArray, twist: NDArray, n_columns: int) -> NDArray:
    """(n_columns, 4, 4) pose of the sensor at each column of a sweep centred on the pose."""
    return np.asarray(T_world_lidar, float)[None] @ sweep_motion(twist, column_times(n_columns))


def perturb_poses(
    T_world_lidar: NDArray,
    rng: np.random.Generator,
    sigma_m: float,
    sigma_deg: float,
    correlation_scans: float = 5.0,
) -> NDArray:
    """Poses with smooth errors like a GPS/INS ground truth: Gaussian noise of ``sigma_m`` and
    ``sigma_deg`` (per axis) smoothed over ``correlation_scans`` scans, applied in the body frame."""
    T = np.asarray(T_world_lidar, float)
    n = len(T)
    if sigma_m <= 0 and sigma_deg <= 0:
        return T.copy()
    s = max(correlation_scans, 1e-6)
    gain = np.sqrt(2 * np.sqrt(np.pi) * s)  # keeps the smoothed noise at unit variance
    dt = gaussian_filter1d(rng.normal(size=(n, 3)), s, axis=0, mode="nearest") * gain * sigma_m
    dr = gaussian_filter1d(rng.normal(size=(n, 3)), s, axis=0, mode="nearest") * gain
    dr *= np.radians(sigma_deg)
    E = np.tile(np.eye(4), (n, 1, 1))
    E[:, :3, :3] = Rotation.from_rotvec(dr).as_matrix()
    E[:, :3, 3] = dt
    return T @ E
