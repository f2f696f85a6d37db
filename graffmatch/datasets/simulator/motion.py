"""Motion within a sweep: per-column sensor poses, de-skewing, and noisy ground-truth poses.

A spinning LiDAR on a moving car takes each column of a scan from a different pose: over the
0.1 s sweep of an HDL-64E at 10 m/s the sensor moves 1 m, so a raw scan is distorted. The
simulator casts every column from the pose at its own time, with the scan's pose (the
ground truth) at mid-sweep, when the sensor looks forward (KITTI sweeps from behind, as
``sensor.render_scan`` does). ``deskew_scan`` undoes it as a loader of real data would:
per-point times from the azimuth and a constant-velocity motion from the neighbouring poses.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.transforms import invert


def sweep_twist(T_prev: NDArray, T_next: NDArray, n_periods: float = 2.0) -> NDArray:
    """(6,) constant-velocity motion per sweep [rotation vector, translation] in the sensor
    frame, from the poses ``n_periods`` sweeps apart that bracket the scan."""
    D = invert(np.asarray(T_prev, float)) @ np.asarray(T_next, float)
    w = Rotation.from_matrix(D[:3, :3]).as_rotvec() / n_periods
    return np.concatenate([w, D[:3, 3] / n_periods])


def _relative_poses(twist: NDArray, tau: NDArray) -> NDArray:
    """(n, 4, 4) motion from mid-sweep to fraction ``tau`` in [-0.5, 0.5) of the sweep."""
    tau = np.asarray(tau, float)
    T = np.tile(np.eye(4), (len(tau), 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(tau[:, None] * twist[None, :3]).as_matrix()
    T[:, :3, 3] = tau[:, None] * twist[None, 3:]
    return T


def column_times(n_columns: int) -> NDArray[np.float64]:
    """Sweep fraction in [-0.5, 0.5) of each azimuth column; 0 is the forward-looking column."""
    return (np.arange(n_columns) + 0.5) / n_columns - 0.5


def sweep_poses(T_world_lidar: NDArray, twist: NDArray, n_columns: int) -> NDArray:
    """(n_columns, 4, 4) pose of the sensor at each column of a sweep centred on the pose."""
    return np.asarray(T_world_lidar, float)[None] @ _relative_poses(twist, column_times(n_columns))


def azimuth_times(points: NDArray) -> NDArray[np.float64]:
    """Sweep fraction in [-0.5, 0.5) of each point from its azimuth (sweep from behind,
    clockwise seen from above, forward at mid-sweep), as loaders without timestamps do."""
    P = np.asarray(points, float)
    az = np.arctan2(P[:, 1], P[:, 0])
    return np.mod(np.pi - az, 2 * np.pi) / (2 * np.pi) - 0.5


def deskew_scan(points: NDArray, T_prev: NDArray, T_next: NDArray, n_periods: float = 2.0) -> NDArray:
    """The scan's points moved into its mid-sweep frame (a copy; intensity kept).

    ``T_prev`` and ``T_next``: poses (any common world frame) ``n_periods`` sweeps apart that
    bracket the scan, e.g. those of the previous and next scan, or an odometry estimate.
    """
    P = np.asarray(points)
    if P.ndim != 2 or P.shape[1] < 3:
        raise InvalidInputError("points must be (N, 3+)")
    twist = sweep_twist(T_prev, T_next, n_periods)
    T = _relative_poses(twist, azimuth_times(P))
    out = P.copy()
    xyz = P[:, :3].astype(float)
    out[:, :3] = np.einsum("nij,nj->ni", T[:, :3, :3], xyz) + T[:, :3, 3]
    return out


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
