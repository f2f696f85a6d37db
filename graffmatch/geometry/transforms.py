"""Rigid transforms in SE(3) as 4x4 homogeneous matrices.

Every transform is named ``T_<to>_<from>``: ``T_target_source @ [p_source; 1] = [p_target; 1]``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graffmatch.errors import InvalidInputError

Array = NDArray[np.float64]


def make_transform(R: ArrayLike, t: ArrayLike) -> Array:
    """Assemble a 4x4 homogeneous transform from a rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=float)
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def check_transform(T: ArrayLike, name: str = "T", atol: float = 1e-6) -> Array:
    """Validate a 4x4 rigid transform and return it as float64."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise InvalidInputError(f"{name} must be 4x4, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise InvalidInputError(f"{name} contains NaN or Inf")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=atol) or np.linalg.det(R) < 0:
        raise InvalidInputError(f"{name} rotation block is not in SO(3)")
    if not np.allclose(T[3], [0, 0, 0, 1], atol=atol):
        raise InvalidInputError(f"{name} last row must be [0, 0, 0, 1]")
    return T


def invert(T: ArrayLike) -> Array:
    """Inverse of a rigid transform, exact (no general matrix inverse)."""
    T = np.asarray(T, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    return make_transform(R.T, -R.T @ t)


def _origin(o: ArrayLike | None, name: str) -> Array:
    if o is None:
        return np.zeros(3)
    try:
        v = np.asarray(o, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name} must be 3 numbers, got {o!r}") from exc
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise InvalidInputError(f"{name} must be 3 finite numbers, got {o!r}")
    return v


def restore_offsets(
    T_target_source_centered: ArrayLike,
    origin_source: ArrayLike | None,
    origin_target: ArrayLike | None,
) -> Array:
    """The transform between the original (e.g. UTM) frames of two recentred clouds.

    With ``world = local + origin`` for each cloud (see ``graffmatch.lidar.io.read_scan``) and
    ``T_c`` mapping local source to local target coordinates,
    ``T = Trans(origin_target) @ T_c @ Trans(-origin_source)``: the rotation is ``R_c`` and the
    translation ``t_c + origin_target - R_c @ origin_source``, summed in float64 (the
    result is exact to ~1e-9 m at 4.6e6 m; ``None`` means a zero origin).
    """
    T_c = check_transform(T_target_source_centered, "T_target_source_centered")
    o_s = _origin(origin_source, "origin_source")
    o_t = _origin(origin_target, "origin_target")
    R = T_c[:3, :3]
    return make_transform(R, T_c[:3, 3] + o_t - R @ o_s)


def transform_points(T: ArrayLike, points: ArrayLike) -> Array:
    """Apply T to an (N, 3) array of points."""
    T = np.asarray(T, dtype=float)
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    return P @ T[:3, :3].T + T[:3, 3]


def rot_x(angle: float) -> Array:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=float)


def rot_y(angle: float) -> Array:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=float)


def rot_z(angle: float) -> Array:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=float)


def random_rotation(rng: np.random.Generator) -> Array:
    """Uniformly distributed rotation (via a random unit quaternion)."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def random_transform(rng: np.random.Generator, max_translation: float = 10.0) -> Array:
    """Random rigid transform: uniform rotation, translation uniform in a cube."""
    return make_transform(random_rotation(rng), rng.uniform(-max_translation, max_translation, 3))


def rotation_error_deg(R_est: ArrayLike, R_true: ArrayLike) -> float:
    """Geodesic rotation error arccos((tr(R_est^T R_true) - 1) / 2), in degrees."""
    R_est = np.asarray(R_est, dtype=float)[:3, :3]
    R_true = np.asarray(R_true, dtype=float)[:3, :3]
    c = (np.trace(R_est.T @ R_true) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def translation_error(T_est: ArrayLike, T_true: ArrayLike) -> float:
    """Euclidean distance between the translation parts, in the units of T (metres)."""
    return float(np.linalg.norm(np.asarray(T_est)[:3, 3] - np.asarray(T_true)[:3, 3]))


def transform_errors(T_est: ArrayLike, T_true: ArrayLike) -> tuple[float, float]:
    """(rotation error in degrees, translation error in metres)."""
    return rotation_error_deg(T_est, T_true), translation_error(T_est, T_true)
