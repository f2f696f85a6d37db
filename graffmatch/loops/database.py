"""The landmark database of a drive: compact per-scan landmark maps, descriptors and times.

A scan's landmarks are stored as one (n, 12) float32 table (type, direction or normal,
tangent, anchor, extent, support): about 50 bytes a landmark, 1-3 kB a scan compressed, where
a raw scan is ~2 MB. Directions are re-orthonormalised on load, so float32 loses nothing the
matcher can see (1e-7 rad).
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


def landmarks_to_bytes(ls: LandmarkSet) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, landmarks=encode_landmarks(ls))
    return buf.getvalue()


def save_landmarks(path: str | Path, ls: LandmarkSet) -> Path:
    """Write atomically (a killed run never leaves a half-written file behind)."""
    return write_bytes_atomic(path, landmarks_to_bytes(ls))


def load_landmarks(path: str | Path) -> LandmarkSet:
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            tab = z["landmarks"]
    except (OSError, ValueError, KeyError, EOFError) as exc:
        raise MalformedFileError(f"{path}: cannot read landmark table ({exc})") from exc
    return decode_landmarks(tab)


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

    def bytes_per_scan(self) -> float:
        """Mean stored size of a scan: its compressed landmark table plus its descriptor."""
        if not len(self):
            return 0.0
        sizes = [len(landmarks_to_bytes(ls)) for ls in self.landmarks]
        return float(np.mean(sizes) + self.descriptors[0].nbytes)
