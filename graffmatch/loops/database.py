"""The landmark database of a drive: compact per-scan landmark maps, descriptors and times.

A scan's landmarks are stored as one (n, 12) float32 table (type, direction or normal,
tangent, anchor, extent, support): about 50 bytes a landmark, 1-3 kB a scan compressed, where
a raw scan is ~2 MB. Directions are re-orthonormalised on load, so float32 loses nothing the
matcher can see (1e-7 rad).

A landmark-poor scan may also keep its *evidence cloud* (the voxelised non-ground support points
the verified matcher scores hypotheses against), quantised to int16 at ``POINT_QUANTUM_M``,
sorted and delta-coded (modulo 2^16, so decoding is exact): ~2-4 kB for 1,500 points. Landmarks
alone cannot verify a scan with three or four of them; its points can.

A landmark-poor scan may further keep its *scan cloud* (``scan``: the extractor's non-ground voxel
cloud re-voxelised at the raw-scan evidence's 0.6 m and capped at its 2,000 points, same codec):
the support points of three landmarks are a few facades, where true poses explain as little as
0.06-0.18 of them on a plain downtown street; every non-ground surface of the scan separates the
right pose from a slid one (``verification.verify.scan_evidence``, docs/loops.md session 15).
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from graffmatch.atomic_files import write_bytes_atomic
from graffmatch.errors import InvalidInputError, MalformedFileError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType

COLUMNS = 12
#: Grid of the stored evidence points [m]: +-2.5 cm, a twelfth of the matcher's 0.3 m inlier gate.
POINT_QUANTUM_M = 0.05
#: Coordinates beyond this are dropped from a stored cloud (int16 at 5 cm reaches 1,638 m).
POINT_MAX_ABS_M = 1600.0


def encode_landmarks(ls: LandmarkSet) -> NDArray[np.float32]:
    """(n, 12) float32 table of a LandmarkSet (support points are dropped)."""
    n = len(ls)
    tab = np.zeros((n, COLUMNS), np.float32)
    tab[:, 0] = ls.types
    tab[:, 1:4] = ls.directions
    tab[:, 4:7] = ls.bases[:, :, 0]
    tab[:, 7:10] = ls.anchors
    for col, key in ((10, "extent"), (11, "support")):
        v = ls.attributes.get(key)
        if v is not None:
            tab[:, col] = np.nan_to_num(np.asarray(v, float).reshape(n))
    return tab


def decode_landmarks(tab: NDArray) -> LandmarkSet:
    """Inverse of :func:`encode_landmarks` (bases re-orthonormalised in float64)."""
    tab = np.asarray(tab, float)
    if tab.ndim != 2 or tab.shape[1] != COLUMNS:
        raise MalformedFileError(f"landmark table must be (n, {COLUMNS}), got {tab.shape}")
    types = tab[:, 0].astype(np.int8)
    d = tab[:, 1:4] / np.maximum(np.linalg.norm(tab[:, 1:4], axis=1, keepdims=True), 1e-12)
    t = tab[:, 4:7]
    planes = types == LandmarkType.PLANE
    # tangent orthogonal to the normal, then unit
    t = t - np.einsum("ij,ij->i", t, d)[:, None] * d * planes[:, None]
    t = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    n = len(types)
    bases = np.zeros((n, 3, 2))
    lines = types == LandmarkType.LINE
    bases[lines, :, 0] = d[lines]
    bases[planes, :, 0] = t[planes]
    bases[planes, :, 1] = np.cross(d[planes], t[planes])
    attrs = {"extent": tab[:, 10].copy(), "support": tab[:, 11].copy()}
    return LandmarkSet(types, bases, tab[:, 7:10].copy(), attrs)


def encode_points(points: NDArray, quantum: float = POINT_QUANTUM_M) -> NDArray[np.int16]:
    """(3, m) int16: the points on a ``quantum`` grid, sorted (x, y, z) and delta-coded along
    each axis modulo 2^16 (small, repetitive numbers that deflate well; decoding is exact)."""
    P = np.asarray(points, np.float64).reshape(-1, 3)
    P = P[np.all(np.isfinite(P), axis=1) & np.all(np.abs(P) <= POINT_MAX_ABS_M, axis=1)]
    q = np.round(P / quantum).astype(np.int64)
    q = q[np.lexsort((q[:, 2], q[:, 1], q[:, 0]))]
    d = np.diff(q, axis=0, prepend=np.zeros((1, 3), np.int64))
    return np.ascontiguousarray(((d + 2**15) % 2**16 - 2**15).astype(np.int16).T)


def decode_points(code: NDArray, quantum: float = POINT_QUANTUM_M) -> NDArray[np.float32]:
    """Inverse of :func:`encode_points`: (m, 3) float32 on the ``quantum`` grid."""
    code = np.asarray(code)
    if code.ndim != 2 or code.shape[0] != 3 or code.dtype != np.int16:
        raise MalformedFileError(f"point code must be (3, m) int16, got {code.shape} {code.dtype}")
    q = np.cumsum(code.astype(np.int64), axis=1)
    q = (q + 2**15) % 2**16 - 2**15
    return (q.T * quantum).astype(np.float32)


def with_evidence_points(ls: LandmarkSet, points: NDArray | None) -> LandmarkSet:
    """``ls`` carrying ``points`` as its support (all owned by its first landmark; the verified
    matcher pools every landmark's support into one cloud, so ownership does not matter)."""
    if points is None or len(ls) == 0:
        return ls
    P = np.asarray(points, np.float32).reshape(-1, 3)
    off = np.full(len(ls) + 1, len(P), np.int64)
    off[0] = 0
    return LandmarkSet(ls.types, ls.bases, ls.anchors, ls.attributes, P, off, validate=False,
                       sensor_pose=ls.sensor_pose)


def landmarks_to_bytes(ls: LandmarkSet, scan: NDArray | None = None) -> bytes:
    """The stored form: the landmark table, the support points (quantised) when ``ls`` has any,
    and the scan cloud ``scan`` (quantised) when given."""
    buf = io.BytesIO()
    arrays = {"landmarks": encode_landmarks(ls)}
    if ls.points is not None and len(ls.points):
        arrays["points"] = encode_points(ls.points)
    if scan is not None and len(scan):
        arrays["scan"] = encode_points(scan)
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def save_landmarks(path: str | Path, ls: LandmarkSet, scan: NDArray | None = None) -> Path:
    """Write atomically (a killed run never leaves a half-written file behind)."""
    return write_bytes_atomic(path, landmarks_to_bytes(ls, scan))


def load_scan_cloud(path: str | Path) -> NDArray[np.float32] | None:
    """The stored scan cloud of a landmark file (None when it keeps none)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            code = z["scan"] if "scan" in z.files else None
    except (OSError, ValueError, KeyError, EOFError) as exc:
        raise MalformedFileError(f"{path}: cannot read landmark table ({exc})") from exc
    try:
        return None if code is None else decode_points(code)
    except MalformedFileError as exc:
        raise MalformedFileError(f"{path}: {exc}") from exc


def load_landmarks(path: str | Path) -> LandmarkSet:
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            tab = z["landmarks"]
            code = z["points"] if "points" in z.files else None
    except (OSError, ValueError, KeyError, EOFError) as exc:
        raise MalformedFileError(f"{path}: cannot read landmark table ({exc})") from exc
    try:
        points = None if code is None else decode_points(code)
    except MalformedFileError as exc:
        raise MalformedFileError(f"{path}: {exc}") from exc
    return with_evidence_points(decode_landmarks(tab), points)


@dataclass
class LandmarkDatabase:
    """Scans added in order: landmarks, descriptor, timestamp and (optional) position."""

    landmarks: list[LandmarkSet] = field(default_factory=list)
    descriptors: list[NDArray[np.float32]] = field(default_factory=list)
    timestamps: list[float] = field(default_factory=list)
    positions: list[NDArray[np.float64] | None] = field(default_factory=list)
    extra: dict[str, list] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.landmarks)

    def add(
        self,
        landmarks: LandmarkSet,
        descriptor: NDArray[np.float32],
        timestamp: float,
        position: NDArray[np.float64] | None = None,
        **extra: object,
    ) -> int:
        if not isinstance(landmarks, LandmarkSet):
            raise InvalidInputError(f"landmarks must be a LandmarkSet, got {type(landmarks).__name__}")
        if self.descriptors and descriptor.shape != self.descriptors[0].shape:
            raise InvalidInputError(
                f"descriptor shape {descriptor.shape} differs from the database's "
                f"{self.descriptors[0].shape}"
            )
        self.landmarks.append(landmarks)
        self.descriptors.append(np.asarray(descriptor, np.float32))
        self.timestamps.append(float(timestamp))
        self.positions.append(None if position is None else np.asarray(position, float))
        for k, v in extra.items():
            self.extra.setdefault(k, [None] * (len(self) - 1)).append(v)
        return len(self) - 1

    def descriptor_matrix(self, upto: int | None = None) -> NDArray[np.float32]:
        d = self.descriptors[: len(self) if upto is None else upto]
        if not d:
            return np.zeros((0, 0), np.float32)
        return np.stack(d)

    def stored_bytes(self) -> NDArray[np.int64]:
        """Stored size of every scan: its compressed landmark table (and evidence points and
        scan cloud, when kept) plus its descriptor."""
        if not len(self):
            return np.zeros(0, np.int64)
        scans = self.extra.get("scan", [None] * len(self))
        return np.array([len(landmarks_to_bytes(ls, sc)) + self.descriptors[0].nbytes
                         for ls, sc in zip(self.landmarks, scans, strict=True)], np.int64)

    def bytes_per_scan(self) -> float:
        """Mean of :meth:`stored_bytes`."""
        return float(self.stored_bytes().mean()) if len(self) else 0.0
