"""Pose files (KITTI and TUM) and the snapping of printed rotations onto SO(3).

One reader and one writer for every place that handles poses: the CLI (``register --pose-out``,
``--gt``, ``view``), the loop-closure trajectories and g2o edges, and the datasets' ground truth.
Printed poses carry few digits, so what is read is checked (a rotation within
:data:`SNAP_TOLERANCE` of SO(3), a rigid last row) and snapped once; a reflection or a scaled
matrix is an error naming the file, never a silent projection.

* KITTI: the 12 values of the top 3x4 of a pose, row-major, a line.
* TUM: ``t x y z qx qy qz qw``; the quaternion is written with ``qw >= 0`` (one of its two
  signs) so that the same pose always prints the same line.

Values are written with 17 significant digits: a KITTI file loads back bit for bit, a TUM
file to ~1e-16 (its quaternion is converted back to a matrix).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graffmatch.atomic_files import write_text_atomic
from graffmatch.errors import GraffMatchError, InvalidInputError, MalformedFileError

Array = NDArray[np.float64]
PoseFormat = Literal["kitti", "tum"]
#: numbers a line of each format
POSE_COLUMNS: dict[str, int] = {"kitti": 12, "tum": 8}
#: how far a printed rotation may be from SO(3) (max entry) before it is refused
SNAP_TOLERANCE = 1e-3
_DIGITS = ".17g"
#: a rotation this close to SO(3) (a pose written by us) is kept as read, not re-projected
_EXACT = 1e-12


def _check_format(fmt: str) -> str:
    if fmt not in POSE_COLUMNS:
        raise InvalidInputError(f"unknown pose format {fmt!r} (kitti or tum)")
    return fmt


def orthonormalize(T: ArrayLike) -> Array:
    """Project the rotation blocks of (n, 4, 4) poses onto SO(3) (nearest in Frobenius norm)."""
    T = np.array(T, dtype=float)
    U, _, Vt = np.linalg.svd(T[:, :3, :3])
    d = np.sign(np.linalg.det(U @ Vt))
    U[:, :, 2] *= d[:, None]
    T[:, :3, :3] = U @ Vt
    T[:, 3] = [0.0, 0.0, 0.0, 1.0]
    return T


def snap_to_se3(
    T: ArrayLike,
    what: str,
    atol: float = SNAP_TOLERANCE,
    error: type[GraffMatchError] = InvalidInputError,
) -> Array:
    """(4, 4) or (n, 4, 4) transforms read from text, checked and snapped onto SE(3).

    Refuses (naming ``what`` and the pose's index) NaN/Inf, a last row other than 0 0 0 1, and
    a rotation block farther than ``atol`` from its projection: a reflection, a scale, a typo.
    ``error`` is the exception raised (a file's content: :class:`MalformedFileError`).
    """
    A = np.asarray(T, dtype=float)
    single = A.ndim == 2
    P = A[None] if single else A
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise error(f"{what}: expected 4x4 transforms, got shape {A.shape}")
    finite = np.isfinite(P).all(axis=(1, 2))
    if not finite.all():
        raise error(f"{what}: pose {int(np.argmin(finite))} contains NaN or Inf")
    bad_row = np.abs(P[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1) > 1e-6
    if bad_row.any():
        raise error(f"{what}: pose {int(np.argmax(bad_row))}: the last row must be 0 0 0 1")
    S = orthonormalize(P)
    off = np.abs(S[:, :3, :3] - P[:, :3, :3]).max(axis=(1, 2)) if len(P) else np.zeros(0)
    exact = off <= _EXACT
    S[exact, :3, :3] = P[exact, :3, :3]  # rotations written at full precision load unchanged
    bad = np.flatnonzero(off > atol)
    if bad.size:
        raise error(
            f"{what}: pose {int(bad[0])} has a non-orthonormal rotation block "
            f"({off[bad[0]]:.2g} from the nearest rotation matrix)"
        )
    return S[0] if single else S


def rows_to_poses(rows: ArrayLike, what: str) -> Array:
    """(n, 12) rows of 3x4 matrices -> (n, 4, 4) poses (validated, snapped to SE(3))."""
    rows = np.asarray(rows, dtype=float).reshape(-1, 12)
    T = np.zeros((len(rows), 4, 4))
    T[:, :3, :] = rows.reshape(-1, 3, 4)
    T[:, 3, 3] = 1.0
    return snap_to_se3(T, what, error=MalformedFileError)


def read_pose_file(path: str | Path, n_columns: int = 12) -> Array:
    """Whitespace-separated pose file, one row of ``n_columns`` numbers per line.

    Returns the raw (n, n_columns) array; blank lines and ``#`` comments are skipped.
    Every malformed line is reported with its number, not as a numpy error.
    """
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"pose file not found: {path}")
    rows: list[list[float]] = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != n_columns:
            raise MalformedFileError(f"{path}:{lineno}: expected {n_columns} numbers, got {len(parts)}")
        try:
            rows.append([float(v) for v in parts])
        except ValueError as exc:
            raise MalformedFileError(f"{path}:{lineno}: not a number ({exc})") from exc
    if not rows:
        raise MalformedFileError(f"{path}: no poses")
    return np.asarray(rows, dtype=float)


def pose_to_xyzq(T: ArrayLike) -> Array:
    """(7,) ``x y z qx qy qz qw`` of a 4x4 transform, with ``qw >= 0``."""
    from scipy.spatial.transform import Rotation

    T = np.asarray(T, float)
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    return np.concatenate([T[:3, 3], -q if q[3] < 0 else q])


def xyzq_to_pose(v: Sequence[float] | ArrayLike, what: str = "pose") -> Array:
    """4x4 transform of ``x y z qx qy qz qw``; the quaternion must be finite and non-zero."""
    from scipy.spatial.transform import Rotation

    v = np.asarray(v, float).reshape(-1)
    if v.size != 7 or not np.all(np.isfinite(v)):
        raise MalformedFileError(f"{what}: expected 7 finite numbers (x y z qx qy qz qw), got {v.size}")
    if np.linalg.norm(v[3:7]) < 1e-9:
        raise MalformedFileError(f"{what}: the quaternion is zero")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(v[3:7]).as_matrix()
    T[:3, 3] = v[:3]
    return T


def pose_line(T: ArrayLike, fmt: PoseFormat, timestamp: float = 0.0) -> str:
    """One pose line: KITTI (12 numbers of the 3x4, row-major) or TUM (t tx ty tz qx qy qz qw)."""
    T = np.asarray(T, float)
    if _check_format(fmt) == "kitti":
        return " ".join(format(v, _DIGITS) for v in T[:3, :4].reshape(-1))
    return " ".join(format(v, _DIGITS) for v in [float(timestamp), *pose_to_xyzq(T)])


def parse_pose_line(line: str, fmt: PoseFormat, what: str = "pose line") -> tuple[float, Array]:
    """(timestamp, 4x4) of one line; the timestamp is 0 for KITTI. Inverse of :func:`pose_line`."""
    parts = line.split("#", 1)[0].replace(",", " ").split()
    n = POSE_COLUMNS[_check_format(fmt)]
    if len(parts) != n:
        raise MalformedFileError(f"{what}: a {fmt.upper()} pose needs {n} numbers, got {len(parts)}")
    try:
        vals = np.array([float(v) for v in parts])
    except ValueError as exc:
        raise MalformedFileError(f"{what}: not a number ({exc})") from exc
    if fmt == "kitti":
        return 0.0, rows_to_poses(vals, what)[0]
    return float(vals[0]), xyzq_to_pose(vals[1:], what)


def write_poses(
    path: str | Path, poses: ArrayLike, fmt: PoseFormat, timestamps: Sequence[float] | ArrayLike | None = None
) -> Path:
    """Write (n, 4, 4) poses (or one 4x4) as a KITTI or TUM file, atomically.

    TUM needs a timestamp a pose; without them the poses are numbered 0, 1, 2, ...
    """
    _check_format(fmt)
    P = np.asarray(poses, float)
    P = P[None] if P.ndim == 2 else P
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise InvalidInputError(f"{path}: expected 4x4 poses, got shape {np.shape(poses)}")
    t = np.arange(len(P), dtype=float) if timestamps is None else np.asarray(timestamps, float).reshape(-1)
    if len(t) != len(P):
        raise InvalidInputError(f"{path}: {len(P)} poses but {len(t)} timestamps")
    return write_text_atomic(path, "\n".join(pose_line(T, fmt, ti) for T, ti in zip(P, t, strict=True)) + "\n")


def read_poses(path: str | Path, fmt: PoseFormat) -> tuple[Array, Array]:
    """(timestamps (n,), poses (n, 4, 4)) of a KITTI or TUM file; KITTI's timestamps are 0..n-1."""
    rows = read_pose_file(Path(path), POSE_COLUMNS[_check_format(fmt)])
    if fmt == "kitti":
        return np.arange(len(rows), dtype=float), rows_to_poses(rows, str(path))
    poses = np.stack([xyzq_to_pose(r[1:], f"{path}: pose {i}") for i, r in enumerate(rows)])
    return rows[:, 0].copy(), poses


def write_kitti(path: str | Path, poses: ArrayLike) -> Path:
    return write_poses(path, poses, "kitti")


def write_tum(path: str | Path, poses: ArrayLike, timestamps: Sequence[float] | ArrayLike) -> Path:
    return write_poses(path, poses, "tum", timestamps)


def read_kitti(path: str | Path) -> Array:
    return read_poses(path, "kitti")[1]


def read_tum(path: str | Path) -> tuple[Array, Array]:
    """(timestamps (n,), poses (n, 4, 4)) of a TUM trajectory file."""
    return read_poses(path, "tum")
