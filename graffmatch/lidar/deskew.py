"""De-skewing: undo the motion of a spinning LiDAR within one sweep.

A spinning LiDAR on a moving car takes each column of a scan from a different pose: over the
0.1 s sweep of an HDL-64E at 10 m/s the sensor moves 1 m, and in a U-turn at 90 deg/s it yaws
9 deg, which moves a wall 30 m away by almost 5 m. No rigid transform aligns two such scans to
the metre (``bench/verification.py``: on the realistic downtown drive, ICP started *at the
ground truth* of distorted pairs drifts 0.4-3.9 m away from it), so a verified match can be
confidently wrong. KITTI odometry ships its scans de-skewed; raw scans from a ROS bag or the
simulator's ``realistic`` preset are not, and need this before extraction.

The motion is constant velocity over the sweep (as KISS-ICP assumes), from two poses that
bracket the scan (the previous and next scan's odometry). Without per-point times, a point's
time comes from its azimuth: the sweep starts behind the sensor and turns clockwise seen from
above, so the forward-looking column is mid-sweep, when the scan's pose is taken (KITTI's and
the simulator's convention).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.transforms import invert


def _pose(T: ArrayLike, name: str) -> NDArray[np.float64]:
    P = np.asarray(T, dtype=float)
    if P.shape != (4, 4) or not np.all(np.isfinite(P)):
        raise InvalidInputError(f"{name} must be a finite 4x4 pose, got shape {P.shape}")
    return P


def sweep_twist(T_prev: ArrayLike, T_next: ArrayLike, n_periods: float = 2.0) -> NDArray[np.float64]:
    """(6,) constant-velocity motion per sweep [rotation vector, translation] in the sensor
    frame, from the poses ``n_periods`` sweeps apart that bracket the scan."""
    if not np.isfinite(n_periods) or n_periods <= 0:
        raise InvalidInputError(f"n_periods must be > 0, got {n_periods}")
    D = invert(_pose(T_prev, "T_prev")) @ _pose(T_next, "T_next")
    w = Rotation.from_matrix(D[:3, :3]).as_rotvec() / n_periods
    return np.concatenate([w, D[:3, 3] / n_periods])


def sweep_motion(twist: ArrayLike, tau: ArrayLike) -> NDArray[np.float64]:
    """(n, 4, 4) motion from mid-sweep to fraction ``tau`` in [-0.5, 0.5) of the sweep."""
    tw = np.asarray(twist, float)
    tau = np.asarray(tau, float)
    T = np.tile(np.eye(4), (len(tau), 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(tau[:, None] * tw[None, :3]).as_matrix()
    T[:, :3, 3] = tau[:, None] * tw[None, 3:]
    return T


def azimuth_times(points: ArrayLike) -> NDArray[np.float64]:
    """Sweep fraction in [-0.5, 0.5) of each point from its azimuth (sweep from behind,
    clockwise seen from above, forward at mid-sweep), as loaders without timestamps do."""
    P = np.asarray(points, float)
    az = np.arctan2(P[:, 1], P[:, 0])
    return np.mod(np.pi - az, 2 * np.pi) / (2 * np.pi) - 0.5


def deskew_scan(
    points: ArrayLike, T_prev: ArrayLike, T_next: ArrayLike, n_periods: float = 2.0,
    times: ArrayLike | None = None,
) -> NDArray:
    """The scan's points moved into its mid-sweep frame (a copy; columns after x y z kept).

    ``T_prev`` and ``T_next``: poses (any common world frame) ``n_periods`` sweeps apart that
    bracket the scan, e.g. those of the previous and next scan, or an odometry estimate.
    ``times``: per-point sweep fractions in [0, 1] (a driver's timestamps, normalised as
    KISS-ICP takes them); default from the azimuth.
    """
    P = np.asarray(points)
    if P.ndim != 2 or P.shape[1] < 3:
        raise InvalidInputError(f"points must be (N, 3+), got shape {P.shape}")
    twist = sweep_twist(T_prev, T_next, n_periods)
    if times is None:
        tau = azimuth_times(P[:, :3])
    else:
        t = np.asarray(times, float).reshape(-1)
        if t.shape != (len(P),) or not np.all(np.isfinite(t)) or (len(t) and (t.min() < 0 or t.max() > 1)):
            raise InvalidInputError(f"times must be {len(P)} finite sweep fractions in [0, 1]")
        tau = t - 0.5
    T = sweep_motion(twist, tau)
    out = P.copy()
    xyz = P[:, :3].astype(float)
    out[:, :3] = np.einsum("nij,nj->ni", T[:, :3, :3], xyz) + T[:, :3, 3]
    return out


def deskew_in_sequence(points: ArrayLike, poses: ArrayLike, i: int) -> NDArray:
    """Scan ``i`` of a sequence de-skewed with the motion between its neighbours' poses
    (``poses``: (n, 4, 4) odometry or ground truth); a single scan is returned as is."""
    Ps = np.asarray(poses, float)
    if Ps.ndim != 3 or Ps.shape[1:] != (4, 4):
        raise InvalidInputError(f"poses must be (n, 4, 4), got shape {Ps.shape}")
    n = len(Ps)
    if not 0 <= i < n:
        raise InvalidInputError(f"scan index {i} out of range for {n} poses")
    if n < 2:
        return np.array(points, copy=True)
    a, b = max(i - 1, 0), min(i + 1, n - 1)
    return deskew_scan(points, Ps[a], Ps[b], float(b - a))
