"""Point, line and plane landmarks as elements of the affine Grassmannian Graff(k, 3).

A landmark of dimension k (0 point, 1 line, 2 plane) is an orthonormal basis ``A`` (3 x k) plus
an *anchor* ``b``: a physical point on the landmark (for example the centroid of the points that
support it). The anchor matters: the invariant distance shifts by it (Proposition 1 of the paper),
so it must be a repeatable, physical point, not an arbitrary point of the infinite subspace.

:class:`LandmarkSet` stores many landmarks as arrays so that the hot path never loops over
Python objects. Bases are padded to 3 x 2; column j >= k is zero.

The module runs past 500 lines on purpose: ``LandmarkSet`` is one array-backed class whose
validation, transformation and compact file format must stay in step; the single ``Landmark``
and type coercion live beside it because its constructors use them.
"""

from __future__ import annotations

import io
import json
import tokenize
import zipfile
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graffmatch.errors import InvalidInputError, MalformedFileError
from graffmatch.geometry.transforms import check_transform

Array = NDArray[np.float64]

FILE_FORMAT_VERSION = 2
ORTHONORMAL_ATOL = 1e-6


class LandmarkType(IntEnum):
    """Landmark dimension k: the value is the dimension of the affine subspace."""

    POINT = 0
    LINE = 1
    PLANE = 2


_TYPE_NAMES = {"point": 0, "line": 1, "plane": 2}
_TYPE_HELP = "use 0 / 'point', 1 / 'line' or 2 / 'plane'"


def _one_type(value: object, where: str) -> int:
    """One landmark type from a code, a name or a LandmarkType; never truncates 1.7 to 1."""
    if isinstance(value, LandmarkType):
        return int(value)
    if isinstance(value, bytes):
        value = value.decode("ascii", errors="replace")
    if isinstance(value, str):
        key = value.strip().lower()
        if key in _TYPE_NAMES:
            return _TYPE_NAMES[key]
        if key in ("0", "1", "2"):
            return int(key)
        raise InvalidInputError(f"{where} = {value!r} is not a landmark type; {_TYPE_HELP}")
    if isinstance(value, (bool, np.bool_)):
        raise InvalidInputError(
            f"{where} = {value!r} is a boolean, not a landmark type; {_TYPE_HELP}"
        )
    if isinstance(value, (int, np.integer)):
        if 0 <= int(value) <= 2:
            return int(value)
        raise InvalidInputError(f"{where} = {value!r} is not a landmark type code; {_TYPE_HELP}")
    if isinstance(value, (float, np.floating)):
        if np.isfinite(value) and float(value).is_integer() and 0 <= value <= 2:
            return int(value)
        raise InvalidInputError(
            f"{where} = {value!r} is not an integer landmark type code; {_TYPE_HELP}"
        )
    raise InvalidInputError(f"{where} = {value!r} is not a landmark type; {_TYPE_HELP}")


def coerce_types(types: ArrayLike, name: str = "types") -> NDArray[np.int8]:
    """(n,) int8 type codes from codes, names ('point', 'line', 'plane') or LandmarkTypes.

    Non-integer codes (1.7), unknown codes (257, -1), booleans and unknown names raise
    :class:`InvalidInputError`; nothing is truncated or wrapped around.
    """
    try:
        arr = np.asarray(types)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name} must be a sequence of landmark types ({exc})") from exc
    arr = arr.reshape(-1)
    kind = arr.dtype.kind
    if kind in "iu":
        bad = np.flatnonzero((arr < 0) | (arr > 2))
        if bad.size:
            i = int(bad[0])
            raise InvalidInputError(
                f"{name}[{i}] = {arr[i].item()!r} is not a landmark type code "
                f"({bad.size} bad); {_TYPE_HELP}"
            )
        return arr.astype(np.int8)
    if kind == "f":
        ok = np.isfinite(arr) & (arr >= 0) & (arr <= 2)
        ok[ok] &= arr[ok] == np.round(arr[ok])
        bad = np.flatnonzero(~ok)
        if bad.size:
            i = int(bad[0])
            raise InvalidInputError(
                f"{name}[{i}] = {arr[i].item()!r} is not an integer landmark type code "
                f"({bad.size} bad); {_TYPE_HELP}"
            )
        return arr.astype(np.int8)
    if kind in "USO":
        return np.array(
            [_one_type(v, f"{name}[{i}]") for i, v in enumerate(arr.tolist())], dtype=np.int8
        ).reshape(-1)
    if kind == "b":
        raise InvalidInputError(f"{name} are booleans, not landmark types; {_TYPE_HELP}")
    raise InvalidInputError(f"{name} has dtype {arr.dtype}, not landmark types; {_TYPE_HELP}")


def _float_array(x: ArrayLike, name: str) -> Array:
    """float64 array, or InvalidInputError naming the argument (never a bare ValueError)."""
    try:
        return np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise InvalidInputError(f"{name} must be an array of numbers ({exc})") from exc


#: Attributes with a defined meaning (all optional). Others may be added freely.
KNOWN_ATTRIBUTES = {
    "extent": "lines: length along the direction [m]; planes: area of the support [m^2]",
    "radius": "lines (poles): mean distance of support points to the axis [m]",
    "support": "number of points supporting the landmark",
    "rms": "RMS residual of the fit [m]",
    "box": "planes: (2,) side lengths of the oriented bounding box in the plane [m]",
    "covariance": "(3, 3) covariance of the support points [m^2]",
}


def _as_unit(v: ArrayLike, name: str) -> Array:
    v = _float_array(v, name).reshape(-1)
    if v.shape != (3,):
        raise InvalidInputError(f"{name} must have 3 components, got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise InvalidInputError(f"{name} contains NaN or Inf")
    big = np.abs(v).max()
    if big < 1e-300:
        raise InvalidInputError(f"{name} must be non-zero")
    v = v / big  # no overflow in the norm of 1e200-sized vectors
    n = np.linalg.norm(v)
    if n < 1e-12:
        raise InvalidInputError(f"{name} must be non-zero")
    return v / n


def plane_basis(normal: ArrayLike) -> Array:
    """An orthonormal 3x2 basis of the plane orthogonal to ``normal`` (deterministic)."""
    n = _as_unit(normal, "normal")
    # Pick the coordinate axis least aligned with n to build a stable first tangent.
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2], axis=1)


@dataclass(frozen=True)
class Landmark:
    """One landmark; convenient for construction and inspection, not for the hot path."""

    kind: LandmarkType
    basis: Array  # (3, k)
    anchor: Array  # (3,)
    attributes: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        kind = LandmarkType(_one_type(self.kind, "kind"))
        basis = _float_array(self.basis, "basis")
        anchor = _float_array(self.anchor, "anchor")
        if basis.size != 3 * int(kind):
            raise InvalidInputError(
                f"a {kind.name.lower()} basis has {3 * int(kind)} numbers, got shape {basis.shape}"
            )
        if anchor.size != 3:
            raise InvalidInputError(f"anchor must have 3 components, got shape {anchor.shape}")
        basis = basis.reshape(3, int(kind))
        anchor = anchor.reshape(3)
        _validate_basis(basis[None], np.array([int(kind)]))
        if not np.all(np.isfinite(anchor)):
            raise InvalidInputError("anchor contains NaN or Inf")
        object.__setattr__(self, "kind", kind)
        object.__setattr__(self, "basis", basis)
        object.__setattr__(self, "anchor", anchor)

    # ---- constructors -----------------------------------------------------------------
    @classmethod
    def point(cls, p: ArrayLike, **attributes: ArrayLike) -> Landmark:
        return cls(LandmarkType.POINT, np.zeros((3, 0)), p, _attrs(attributes))

    @classmethod
    def line(cls, point: ArrayLike, direction: ArrayLike, **attributes: ArrayLike) -> Landmark:
        """A line through ``point`` (its anchor) along ``direction``."""
        d = _as_unit(direction, "direction")
        return cls(LandmarkType.LINE, d[:, None], point, _attrs(attributes))

    @classmethod
    def plane(cls, point: ArrayLike, normal: ArrayLike, **attributes: ArrayLike) -> Landmark:
        """A plane through ``point`` (its anchor) with the given normal."""
        return cls(LandmarkType.PLANE, plane_basis(normal), point, _attrs(attributes))

    @classmethod
    def plane_from_hesse(
        cls, normal: ArrayLike, offset: float, anchor: ArrayLike, **attributes: ArrayLike
    ) -> Landmark:
        """Plane n.x = offset; the anchor is projected onto the plane."""
        n = _as_unit(normal, "normal")
        a = _float_array(anchor, "anchor").reshape(-1)
        if a.shape != (3,):
            raise InvalidInputError(f"anchor must have 3 components, got shape {a.shape}")
        try:
            d = float(offset)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"offset must be a number, got {offset!r}") from exc
        a = a - (n @ a - d) * n
        return cls.plane(a, n, **attributes)

    # ---- representations --------------------------------------------------------------
    @property
    def direction(self) -> Array:
        """Line direction or plane normal (unit)."""
        padded = np.zeros((1, 3, 2))
        padded[0, :, : int(self.kind)] = self.basis
        return _directions(padded, np.array([int(self.kind)]))[0]

    def cp_vector(self) -> Array:
        return LandmarkSet.from_landmarks([self]).cp_vectors()[0]

    def vector_form(self) -> Array:
        """Lines: l = [A; b] in R^6 (direction then anchor)."""
        if self.kind != LandmarkType.LINE:
            raise InvalidInputError("vector form [A; b] is defined for lines")
        return np.concatenate([self.basis[:, 0], self.anchor])

    def hesse(self) -> Array:
        """Planes: pi = [n; d] with n.x = d for points x on the plane."""
        if self.kind != LandmarkType.PLANE:
            raise InvalidInputError("Hesse normal form is defined for planes")
        n = self.direction
        return np.concatenate([n, [n @ self.anchor]])


def _sensor_pose(value: ArrayLike | str | None) -> Array | None:
    """The sensor pose of a set: 'identity' (a scan's own frame), None (unknown) or a rigid 4x4."""
    if value is None:
        return None
    if isinstance(value, str):
        if value != "identity":
            raise InvalidInputError(f"sensor_pose must be 'identity', None or a 4x4 transform, got {value!r}")
        return np.eye(4)
    return check_transform(value, "sensor_pose")


def _pose_from_meta(meta: dict) -> Array | str | None:
    """The sensor pose stored in a landmark file's meta (absent: a scan's own frame)."""
    if "sensor_pose" not in meta:
        return "identity"
    rows = meta["sensor_pose"]
    return None if rows is None else np.r_[np.asarray(rows, dtype=float).reshape(3, 4), [[0.0, 0.0, 0.0, 1.0]]]


def _scan_ranges(value: ArrayLike, validate: bool) -> Array:
    """A whole-scan range image: 2-D float32, its cells tiling the sphere, ranges >= 0 or inf."""
    img = np.asarray(value, dtype=np.float32)
    if not validate:
        return img
    if img.ndim != 2 or img.shape[0] < 1 or img.shape[1] < 1 or 360 % img.shape[0] or 180 % img.shape[1]:
        raise InvalidInputError(
            f"scan_ranges must be (n_azimuth, n_elevation) with n dividing 360 and 180, got {img.shape}")
    if np.isnan(img).any() or (img < 0).any():
        raise InvalidInputError("scan_ranges must hold ranges >= 0 (inf: no return), not NaN or negative")
    return img


def _attrs(attributes: Mapping[str, ArrayLike]) -> dict[str, np.ndarray]:
    out = {}
    for k, v in attributes.items():
        if v is None:
            continue
        try:
            out[k] = np.asarray(v)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"attribute {k!r} is not an array ({exc})") from exc
    return out


def _validate_basis(bases: np.ndarray, types: np.ndarray) -> None:
    if not np.all(np.isfinite(bases)):
        raise InvalidInputError("landmark bases contain NaN or Inf")
    for k in (1, 2):
        sel = types == k
        if not np.any(sel):
            continue
        B = bases[sel][:, :, :k]
        G = np.einsum("nij,nik->njk", B, B)
        err = np.abs(G - np.eye(k)).max(axis=(1, 2))
        bad = np.flatnonzero(err > ORTHONORMAL_ATOL)
        if bad.size:
            raise InvalidInputError(
                f"{bad.size} basis/bases of dimension {k} are not orthonormal "
                f"(max |A^T A - I| = {err.max():.3g})"
            )


def _directions(bases: np.ndarray, types: np.ndarray) -> Array:
    """Line direction (column 0) or plane normal (cross of the columns); zeros for points.

    The cross product written out (np.cross's own formula, the same roundings): np.cross's
    axis handling cost more than the products (35 -> 20 us for a KITTI scan's 17 landmarks)."""
    out = np.zeros((bases.shape[0], 3))
    lines = types == LandmarkType.LINE
    planes = types == LandmarkType.PLANE
    out[lines] = bases[lines, :, 0]
    B = bases[planes]
    a0, a1, a2, b0, b1, b2 = B[:, 0, 0], B[:, 1, 0], B[:, 2, 0], B[:, 0, 1], B[:, 1, 1], B[:, 2, 1]
    out[planes] = np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=1)
    return out


class LandmarkSet:
    """Arrays of landmarks of one scan.

    Attributes
    ----------
    types : (n,) int8, values of :class:`LandmarkType`.
    bases : (n, 3, 2) float64, orthonormal columns ``0..k-1``, zero padding after.
    anchors : (n, 3) float64, a physical point of each landmark, in the scan's frame [m].
    attributes : dict of arrays whose first dimension is n (see ``KNOWN_ATTRIBUTES``).
    points, point_offsets : optional support points, ragged: landmark i owns
        ``points[point_offsets[i]:point_offsets[i+1]]`` (float32, metres). Needed by ICP
        refinement and BruteForceRMSE; not written to the compact file unless asked.
    sensor_pose : (4, 4) float64 or None, the sensor's pose in this frame: identity for a
        scan's landmarks (the default), moved by :meth:`transform`; None when unknown (a map
        merged from many viewpoints). Verification's free-space check needs it.
    scan_ranges : (n_azimuth, n_elevation) float32 or None, the nearest return of the *whole*
        scan per spherical cell around the sensor (inf: none), cell = 360/n_azimuth by
        180/n_elevation degrees. The extractor stores it so that free space is what every
        beam showed, not only the landmarks' support; it lives and dies with the support
        points (in the sensor's frame, so a transform keeps it).
    """

    __slots__ = ("anchors", "attributes", "bases", "point_offsets", "points", "scan_ranges", "sensor_pose",
                 "types")

    def __init__(
        self,
        types: ArrayLike,
        bases: ArrayLike,
        anchors: ArrayLike,
        attributes: Mapping[str, ArrayLike] | None = None,
        points: ArrayLike | None = None,
        point_offsets: ArrayLike | None = None,
        validate: bool = True,
        sensor_pose: ArrayLike | str | None = "identity",
        scan_ranges: ArrayLike | None = None,
    ) -> None:
        self.sensor_pose = _sensor_pose(sensor_pose)
        self.scan_ranges = None if scan_ranges is None else _scan_ranges(scan_ranges, validate)
        if not validate:  # internal fast path: arrays that came out of a validated set
            self.types = np.asarray(types, dtype=np.int8).reshape(-1)
            self.bases = np.asarray(bases, dtype=np.float64)
            self.anchors = np.asarray(anchors, dtype=np.float64)
            self.attributes = {k: np.asarray(v) for k, v in (attributes or {}).items()}
            self.points = None if points is None else np.asarray(points, dtype=np.float32)
            self.point_offsets = (
                None if point_offsets is None else np.asarray(point_offsets, dtype=np.int64)
            )
            return
        self.types = coerce_types(types)
        n = self.types.shape[0]
        self.bases = _float_array(bases, "bases")
        self.anchors = _float_array(anchors, "anchors")
        if self.bases.shape == (0,):
            self.bases = self.bases.reshape(0, 3, 2)
        if self.anchors.shape == (0,):
            self.anchors = self.anchors.reshape(0, 3)
        if attributes is not None and not isinstance(attributes, Mapping):
            raise InvalidInputError(
                f"attributes must be a mapping name -> array, got {type(attributes).__name__}"
            )
        self.attributes = _attrs({str(k): v for k, v in (attributes or {}).items()})
        self.points = None
        if points is not None:
            pts = _float_array(points, "points")
            if pts.ndim != 2 or pts.shape[1] != 3:
                raise InvalidInputError(f"points must have shape (m, 3), got {pts.shape}")
            if not np.all(np.isfinite(pts)) or (pts.size and np.abs(pts).max() > 3.0e38):
                raise InvalidInputError("support points contain NaN/Inf or exceed float32")
            self.points = pts.astype(np.float32)
        self.point_offsets = None
        if point_offsets is not None:
            off = _float_array(point_offsets, "point_offsets").reshape(-1)
            if not np.all(np.isfinite(off)) or np.any(off != np.round(off)):
                raise InvalidInputError("point_offsets must be integers")
            if off.size and np.abs(off).max() > 2.0**62:
                raise InvalidInputError("point_offsets are out of range")
            self.point_offsets = off.astype(np.int64)
        self._validate(n)

    def _validate(self, n: int) -> None:
        if self.bases.shape != (n, 3, 2):
            raise InvalidInputError(f"bases must have shape ({n}, 3, 2), got {self.bases.shape}")
        if self.anchors.shape != (n, 3):
            raise InvalidInputError(f"anchors must have shape ({n}, 3), got {self.anchors.shape}")
        if n and (self.types.min() < 0 or self.types.max() > 2):
            raise InvalidInputError("types must be 0 (point), 1 (line) or 2 (plane)")
        if not np.all(np.isfinite(self.anchors)):
            raise InvalidInputError("landmark anchors contain NaN or Inf")
        _validate_basis(self.bases, self.types)
        for k in range(2):
            pad = self.types <= k
            if np.any(np.abs(self.bases[pad, :, k]) > 0):
                raise InvalidInputError("basis columns beyond the landmark dimension must be zero")
        for key, v in self.attributes.items():
            if v.shape[:1] != (n,):
                raise InvalidInputError(f"attribute {key!r} must have first dimension {n}")
        if (self.points is None) != (self.point_offsets is None):
            raise InvalidInputError("points and point_offsets must be given together")
        if self.point_offsets is not None and self.points is not None:
            off = self.point_offsets
            if off.shape != (n + 1,) or off[0] != 0 or off[-1] != len(self.points):
                raise InvalidInputError("point_offsets must be (n+1,) from 0 to len(points)")
            if np.any(np.diff(off) < 0):
                raise InvalidInputError("point_offsets must be non-decreasing")

    # ---- construction --------------------------------------------------------------
    @classmethod
    def empty(cls) -> LandmarkSet:
        return cls(np.zeros(0, np.int8), np.zeros((0, 3, 2)), np.zeros((0, 3)))

    @classmethod
    def from_landmarks(cls, landmarks: Sequence[Landmark]) -> LandmarkSet:
        n = len(landmarks)
        types = np.array([int(lm.kind) for lm in landmarks], dtype=np.int8)
        bases = np.zeros((n, 3, 2))
        anchors = np.zeros((n, 3))
        keys: set[str] = set()
        for i, lm in enumerate(landmarks):
            bases[i, :, : int(lm.kind)] = lm.basis
            anchors[i] = lm.anchor
            keys |= set(lm.attributes)
        attrs: dict[str, np.ndarray] = {}
        for key in sorted(keys):
            vals = [lm.attributes.get(key) for lm in landmarks]
            proto = next(np.asarray(v) for v in vals if v is not None)
            arr = np.full((n, *proto.shape), np.nan, dtype=float)
            for i, v in enumerate(vals):
                if v is not None:
                    arr[i] = v
            attrs[key] = arr
        return cls(types, bases, anchors, attrs)

    @classmethod
    def from_arrays(
        cls,
        types: ArrayLike,
        directions: ArrayLike,
        anchors: ArrayLike,
        attributes: Mapping[str, ArrayLike] | None = None,
        points: ArrayLike | None = None,
        point_offsets: ArrayLike | None = None,
        sensor_pose: ArrayLike | str | None = "identity",
    ) -> LandmarkSet:
        """Vectorised constructor from line directions / plane normals (any length)."""
        types = coerce_types(types)
        dirs = _float_array(directions, "directions")
        n = len(types)
        if dirs.size != 3 * n or (dirs.ndim > 1 and dirs.shape[-1] != 3):
            raise InvalidInputError(
                f"directions must have shape ({n}, 3) (one row per landmark), got {dirs.shape}"
            )
        dirs = dirs.reshape(n, 3)
        if not np.all(np.isfinite(dirs)):
            raise InvalidInputError("directions contain NaN or Inf")
        needs = types > 0
        big = np.abs(dirs).max(axis=1) if n else np.zeros(0)
        if np.any(big[needs] < 1e-300):
            raise InvalidInputError("line directions and plane normals must be non-zero")
        bases = np.zeros((n, 3, 2))
        u = np.zeros_like(dirs)
        u[needs] = dirs[needs] / big[needs, None]  # scale first: no overflow in the norm
        norms = np.linalg.norm(u, axis=1)
        if np.any(norms[needs] < 1e-12):
            raise InvalidInputError("line directions and plane normals must be non-zero")
        u[needs] = u[needs] / norms[needs, None]
        lines = types == LandmarkType.LINE
        bases[lines, :, 0] = u[lines]
        planes = np.flatnonzero(types == LandmarkType.PLANE)
        if planes.size:
            nrm = u[planes]
            helper = np.eye(3)[np.argmin(np.abs(nrm), axis=1)]
            t1 = np.cross(nrm, helper)
            t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
            bases[planes, :, 0] = t1
            bases[planes, :, 1] = np.cross(nrm, t1)
        return cls(types, bases, anchors, attributes, points, point_offsets, sensor_pose=sensor_pose)

    @classmethod
    def concatenate(cls, sets: Iterable[LandmarkSet]) -> LandmarkSet:
        sets = [s for s in sets]
        if not sets:
            return cls.empty()
        keys = set().union(*(s.attributes for s in sets))
        attrs = {}
        for key in sorted(keys):
            parts = []
            proto = next(s.attributes[key] for s in sets if key in s.attributes)
            for s in sets:
                if key in s.attributes:
                    parts.append(np.asarray(s.attributes[key], dtype=float))
                else:
                    parts.append(np.full((len(s), *proto.shape[1:]), np.nan))
            attrs[key] = np.concatenate(parts)
        pts = offs = None
        if all(s.points is not None for s in sets):
            pts = np.concatenate([s.points for s in sets])  # type: ignore[misc]
            counts = np.concatenate([np.diff(s.point_offsets) for s in sets])  # type: ignore[arg-type]
            offs = np.concatenate([[0], np.cumsum(counts)])
        o0 = sets[0].sensor_pose
        same = o0 is not None and all(s.sensor_pose is not None and np.array_equal(s.sensor_pose, o0) for s in sets)
        return cls(
            np.concatenate([s.types for s in sets]),
            np.concatenate([s.bases for s in sets]),
            np.concatenate([s.anchors for s in sets]),
            attrs,
            pts,
            offs,
            sensor_pose=o0 if same else None,  # one viewpoint, or unknown
            scan_ranges=sets[0].scan_ranges if same and pts is not None and all(
                s.scan_ranges is sets[0].scan_ranges for s in sets) else None,  # parts of one scan
        )

    # ---- container protocol --------------------------------------------------------
    def __len__(self) -> int:
        return int(self.types.shape[0])

    def __getitem__(self, index: int | slice | ArrayLike) -> LandmarkSet:
        """Select landmarks; an int returns a one-element set (use :meth:`landmark`)."""
        idx = np.arange(len(self))[index]
        idx = np.atleast_1d(idx)
        pts = offs = None
        if self.points is not None and self.point_offsets is not None:
            starts, ends = self.point_offsets[idx], self.point_offsets[idx + 1]
            counts = ends - starts
            if counts.sum():
                gather = np.repeat(starts - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
                gather = gather + np.arange(counts.sum())
                pts = self.points[gather]
            else:
                pts = np.zeros((0, 3), np.float32)
            offs = np.concatenate([[0], np.cumsum(counts)])
        return LandmarkSet(
            self.types[idx],
            self.bases[idx],
            self.anchors[idx],
            {k: v[idx] for k, v in self.attributes.items()},
            pts,
            offs,
            validate=False,
            sensor_pose=self.sensor_pose,
            scan_ranges=None if pts is None else self.scan_ranges,
        )

    def landmark(self, i: int) -> Landmark:
        k = int(self.types[i])
        return Landmark(
            LandmarkType(k),
            self.bases[i, :, :k],
            self.anchors[i],
            {key: v[i] for key, v in self.attributes.items()},
        )

    def __iter__(self):
        return (self.landmark(i) for i in range(len(self)))

    def __repr__(self) -> str:
        c = self.counts()
        return (
            f"LandmarkSet(n={len(self)}, points={c['points']}, lines={c['lines']}, "
            f"planes={c['planes']}, attributes={sorted(self.attributes)}, "
            f"support_points={'no' if self.points is None else len(self.points)})"
        )

    def counts(self) -> dict[str, int]:
        return {
            "points": int(np.sum(self.types == LandmarkType.POINT)),
            "lines": int(np.sum(self.types == LandmarkType.LINE)),
            "planes": int(np.sum(self.types == LandmarkType.PLANE)),
        }

    def of_type(self, *kinds: LandmarkType | int | str) -> LandmarkSet:
        return self[np.flatnonzero(np.isin(self.types, coerce_types(list(kinds), "kinds")))]

    def indices_of_type(self, kind: LandmarkType | int | str) -> NDArray[np.intp]:
        return np.flatnonzero(self.types == _one_type(kind, "kind"))

    def require_nonempty(self, what: str = "landmark set") -> LandmarkSet:
        if len(self) == 0:
            raise InvalidInputError(f"{what} is empty")
        return self

    def support_points(self, i: int) -> NDArray[np.float32]:
        if self.points is None or self.point_offsets is None:
            raise InvalidInputError("this LandmarkSet carries no support points")
        return self.points[self.point_offsets[i] : self.point_offsets[i + 1]]

    # ---- representations -------------------------------------------------------------
    @property
    def directions(self) -> Array:
        """(n, 3): line directions, plane normals, zeros for points."""
        return _directions(self.bases, self.types)

    def orthogonal_displacements(self) -> Array:
        """b0 = (I - A A^T) b: the closest point of each landmark to the origin."""
        proj = np.einsum("nik,njk,nj->ni", self.bases, self.bases, self.anchors)
        return self.anchors - proj

    def cp_vectors(self) -> Array:
        """Closest-point vectors (Zhou et al.): the point of the landmark closest to the origin."""
        return self.orthogonal_displacements()

    def vector_forms(self) -> Array:
        """Lines: (n_lines, 6) rows [direction; anchor]."""
        sel = self.types == LandmarkType.LINE
        return np.concatenate([self.bases[sel, :, 0], self.anchors[sel]], axis=1)

    def hesse(self) -> Array:
        """Planes: (n_planes, 4) rows [n; d] with n.x = d on the plane."""
        sel = self.types == LandmarkType.PLANE
        n = self.directions[sel]
        return np.concatenate([n, np.einsum("ij,ij->i", n, self.anchors[sel])[:, None]], axis=1)

    # ---- transformation -------------------------------------------------------------
    def transform(self, T_new_old: ArrayLike) -> LandmarkSet:
        """Apply a rigid transform: A' = R A, b' = R b + t (the paper's transformation law).

        For planes in Hesse form this is exactly pi' = T^{-T} pi.
        """
        T = check_transform(T_new_old, "T_new_old")
        R, t = T[:3, :3], T[:3, 3]
        pts = None
        if self.points is not None:
            pts = (self.points.astype(np.float64) @ R.T + t).astype(np.float32)
        attrs = dict(self.attributes)
        if "covariance" in attrs:
            attrs["covariance"] = np.einsum("ij,njk,lk->nil", R, attrs["covariance"], R)
        return LandmarkSet(
            self.types,
            np.einsum("ij,njk->nik", R, self.bases),
            self.anchors @ R.T + t,
            attrs,
            pts,
            self.point_offsets,
            validate=False,
            sensor_pose=None if self.sensor_pose is None else T @ self.sensor_pose,
            scan_ranges=None if self.sensor_pose is None else self.scan_ranges,  # sensor frame: unchanged
        )

    def without_points(self) -> LandmarkSet:
        return LandmarkSet(self.types, self.bases, self.anchors, self.attributes, validate=False,
                           sensor_pose=self.sensor_pose)

    # ---- persistence ------------------------------------------------------------------
    def to_bytes(self, include_points: bool = False) -> bytes:
        """Compact npz that loads back *bit for bit* (version 2): float64 bases, anchors and
        attributes. Version 1 stored float32 attributes and re-derived a plane's second basis
        column from its normal, so a loaded set differed from the extracted one in the last
        digits, and the matcher's decisions on it could differ (a gate on a rounded extent)."""
        arrays: dict[str, np.ndarray] = {
            "types": self.types,
            "bases": self.bases,
            "anchors": self.anchors,
        }
        for k, v in self.attributes.items():
            arrays[f"attr.{k}"] = v
        if include_points and self.points is not None:
            arrays["points"] = self.points
            arrays["point_offsets"] = self.point_offsets  # type: ignore[assignment]
            if self.scan_ranges is not None:
                arrays["scan_ranges"] = self.scan_ranges
        meta: dict = {"format": "graffmatch-landmarks", "version": FILE_FORMAT_VERSION}
        if self.sensor_pose is None:
            meta["sensor_pose"] = None
        elif not np.array_equal(self.sensor_pose, np.eye(4)):  # the default (a scan's own frame) costs no bytes
            meta["sensor_pose"] = self.sensor_pose[:3].tolist()
        arrays["meta"] = np.array(json.dumps(meta))
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        return buf.getvalue()

    def save(self, path: str | Path, include_points: bool = False) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(self.to_bytes(include_points=include_points))
        return path

    @classmethod
    def load(cls, path: str | Path) -> LandmarkSet:
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"]))
                if meta.get("format") != "graffmatch-landmarks":
                    raise MalformedFileError(f"{path}: not a graffmatch landmark file")
                if int(meta.get("version", 0)) > FILE_FORMAT_VERSION:
                    raise MalformedFileError(f"{path}: landmark file version too new")
                types = z["types"]
                stored_bases = z["bases"] if "bases" in z.files else None
                normals = z["directions"] if stored_bases is None else None
                tangents = z["tangents"] if stored_bases is None else None
                anchors = z["anchors"]
                attrs = {k[5:]: z[k] for k in z.files if k.startswith("attr.")}
                pts = z["points"] if "points" in z.files else None
                offs = z["point_offsets"] if "point_offsets" in z.files else None
                scan_ranges = z["scan_ranges"] if "scan_ranges" in z.files else None
        except MalformedFileError:
            raise
        except (
            OSError, ValueError, KeyError, EOFError, TypeError, SyntaxError,
            zipfile.BadZipFile, zlib.error, tokenize.TokenError, NotImplementedError,
        ) as exc:  # fmt: skip
            raise MalformedFileError(f"{path}: cannot read landmark file ({exc})") from exc
        try:
            types = coerce_types(types)
            n = len(types)
            if stored_bases is not None:
                bases = np.asarray(stored_bases, dtype=np.float64).reshape(n, 3, 2)
            else:  # version 1: the tangent and the normal
                normals = np.asarray(normals, dtype=np.float64).reshape(n, 3)
                tangents = np.asarray(tangents, dtype=np.float64).reshape(n, 3)
                bases = np.zeros((n, 3, 2))
                bases[:, :, 0] = tangents
                planes = types == LandmarkType.PLANE
                bases[planes, :, 1] = np.cross(normals[planes], tangents[planes])
            attrs = {
                k: (v.astype(np.float64) if v.dtype.kind == "f" else v) for k, v in attrs.items()
            }
            return cls(types, bases, anchors, attrs, pts, offs, sensor_pose=_pose_from_meta(meta),
                       scan_ranges=scan_ranges)
        except (InvalidInputError, ValueError, TypeError, IndexError) as exc:
            raise MalformedFileError(f"{path}: invalid landmark file ({exc})") from exc

    def approx_equal(self, other: LandmarkSet, atol: float = 1e-9) -> bool:
        """Same types, same subspaces (A A^T) and same anchors within atol."""
        if len(self) != len(other) or not np.array_equal(self.types, other.types):
            return False
        P1 = np.einsum("nik,njk->nij", self.bases, self.bases)
        P2 = np.einsum("nik,njk->nij", other.bases, other.bases)
        return bool(
            np.allclose(P1, P2, atol=atol) and np.allclose(self.anchors, other.anchors, atol=atol)
        )


def fit_landmark(points: ArrayLike, kind: LandmarkType | int) -> tuple[Landmark, Array]:
    """PCA fit of a line or plane (or a point: the centroid) to a point set.

    Returns the landmark (anchor = centroid, plus ``support``, ``rms`` and ``extent`` attributes)
    and the per-point orthogonal residuals [m].
    """
    P = _float_array(points, "points")
    if P.size % 3:
        raise InvalidInputError(f"points must have shape (N, 3), got {P.shape}")
    P = P.reshape(-1, 3)
    kind = LandmarkType(_one_type(kind, "kind"))
    if not np.all(np.isfinite(P)):
        raise InvalidInputError("points contain NaN or Inf")
    need = int(kind) + 1
    if P.shape[0] < need:
        raise InvalidInputError(f"need at least {need} points to fit a {kind.name.lower()}")
    c = P.mean(axis=0)
    Q = P - c
    _, s, Vt = np.linalg.svd(Q, full_matrices=False)
    k = int(kind)
    if k > 0 and (len(s) < k or s[k - 1] <= 1e-12 * max(1.0, s[0])):
        raise InvalidInputError(f"points are degenerate for a {kind.name.lower()} fit")
    A = Vt[:k].T
    resid_vec = Q - (Q @ A) @ A.T
    resid = np.linalg.norm(resid_vec, axis=1)
    rms = float(np.sqrt(np.mean(resid**2)))
    attrs: dict[str, ArrayLike] = {"support": P.shape[0], "rms": rms}
    if kind == LandmarkType.LINE:
        proj = Q @ A[:, 0]
        attrs["extent"] = float(proj.max() - proj.min())
        attrs["radius"] = float(resid.mean())
        lm = Landmark.line(c, A[:, 0], **attrs)
    elif kind == LandmarkType.PLANE:
        uv = Q @ A
        attrs["box"] = uv.max(axis=0) - uv.min(axis=0)
        attrs["extent"] = float(np.prod(attrs["box"]))
        lm = Landmark(LandmarkType.PLANE, A, c, _attrs(attrs))
    else:
        lm = Landmark.point(c, **attrs)
    return lm, resid
