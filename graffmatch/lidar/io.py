"""Point-cloud and label I/O: KITTI ``.bin``, SemanticKITTI ``.label``, PCD, PLY and numpy.

Every reader returns ``(N, 4) float32`` rows ``x, y, z, intensity`` (intensity 0 when the file has
none) so that the rest of the front end sees one layout whatever the source. Every parse failure
raises :class:`~graffmatch.errors.MalformedFileError` whose message names the file, instead of a
numpy ``ValueError`` from deep inside a reshape.

Far coordinates (UTM, map frames): float32 has a 0.5 m grid at 4.6e6 m. :func:`read_scan` parses
in float64, moves the cloud to a round ``origin`` near its median *before* the float32 cast and
keeps that origin (``world = points + origin``); :func:`~graffmatch.geometry.transforms.
restore_offsets` puts the origins back into a transform estimated on the recentred clouds.
:func:`read_points` keeps its old contract (world coordinates, float32) and therefore cannot
recentre: when the cast moves a point by more than :data:`PRECISION_TOLERANCE` it emits a
:class:`~graffmatch.errors.PrecisionLossWarning` naming the file and pointing to :func:`read_scan`
(a warning, not an error, so that existing callers keep working; make it an error with
``warnings.simplefilter("error", PrecisionLossWarning)``).

The module runs past 500 lines on purpose: each format's reader and writer (KITTI .bin/.label,
PCD, PLY, NPY) shares one set of guards (implausible points, float64 recentring, units), so a
format cannot skip them.
"""

from __future__ import annotations

import io
import tokenize
import warnings
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from graffmatch.atomic_files import write_bytes_atomic
from graffmatch.errors import InvalidInputError, MalformedFileError, PrecisionLossWarning

__all__ = [
    "POINT_SUFFIXES",
    "PRECISION_TOLERANCE",
    "UNITS",
    "Scan",
    "instance_id",
    "label_path_for",
    "read_bin",
    "read_label",
    "read_labels",
    "read_npy",
    "read_pcd",
    "read_ply",
    "read_points",
    "read_scan",
    "resolve_scale",
    "semantic_class",
    "write_bin",
    "write_label",
    "write_npy",
    "write_pcd",
    "write_ply",
    "write_points",
]

Points = NDArray[np.float32]

#: Suffixes understood by :func:`read_points` / :func:`write_points`.
POINT_SUFFIXES = (".bin", ".pcd", ".ply", ".npy", ".npz")

#: Largest shift [m] the float32 cast may apply to a coordinate without notice. Below it lies
#: every sensor-frame scan (a point moves by 1 mm only beyond 16 km); above it, read_scan
#: recentres and read_points warns.
PRECISION_TOLERANCE = 1e-3

#: read_scan's origin is the cloud's median rounded to a multiple of this [m]: a round,
#: readable offset, equal for nearby scans of one drive, and 0 for any cloud whose median lies
#: within 50 m of its frame's origin (so sensor frames stay sensor frames).
ORIGIN_GRID = 100.0

#: A KITTI ``.bin`` holds a sensor frame: a coordinate beyond this [m] is not a LiDAR return.
SENSOR_FRAME_LIMIT = 1e5

#: ... nor is a non-zero point closer than this to the sensor [m] (text files read as float32
#: give 1e-19 .. 1e-4; no LiDAR measures below a few centimetres).
SENSOR_MIN_RANGE = 1e-3

#: A ``.bin`` in which more than this fraction of points is NaN/Inf, beyond
#: :data:`SENSOR_FRAME_LIMIT`, below :data:`SENSOR_MIN_RANGE` or denormal is not a scan.
MAX_IMPLAUSIBLE_FRACTION = 0.5

#: Unit names accepted wherever a ``scale`` is (the factor that converts the file's unit to m).
UNITS = {"m": 1.0, "dm": 0.1, "cm": 0.01, "mm": 0.001, "km": 1000.0}

#: What np.load raises on a corrupt .npy/.npz (a broken zip, a bad header, short data).
_NPY_ERRORS = (
    OSError, ValueError, EOFError, KeyError, TypeError, SyntaxError, zipfile.BadZipFile,
    zlib.error, tokenize.TokenError, NotImplementedError,
)  # fmt: skip

_F32_MAX = float(np.finfo(np.float32).max)
_F32_TINY = float(np.finfo(np.float32).tiny)


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------
def _read_bytes(path: str | Path) -> tuple[Path, bytes]:
    path = Path(path)
    try:
        return path, path.read_bytes()
    except FileNotFoundError as exc:
        raise MalformedFileError(f"{path}: file not found") from exc
    except OSError as exc:
        raise MalformedFileError(f"{path}: cannot read ({exc})") from exc


def as_points4(points: ArrayLike, name: str = "points") -> Points:
    """Coerce (N,3) or (N,>=4) to (N,4) float32 (intensity 0 when missing)."""
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise InvalidInputError(f"{name} must have shape (N, 3) or (N, 4+), got {arr.shape}")
    if arr.dtype.kind not in "fiu":
        raise InvalidInputError(f"{name} must be numeric, got dtype {arr.dtype}")
    out = np.zeros((arr.shape[0], 4), dtype=np.float32)
    out[:, :3] = arr[:, :3]
    if arr.shape[1] >= 4:
        out[:, 3] = arr[:, 3]
    return out


# --------------------------------------------------------------------------------------------
# KITTI .bin and SemanticKITTI .label
# --------------------------------------------------------------------------------------------
def _implausible_rows(xyz: NDArray, limit: float) -> NDArray[np.bool_]:
    """Rows that cannot be a LiDAR return: NaN/Inf, beyond ``limit``, within
    :data:`SENSOR_MIN_RANGE` of the sensor but not exactly 0, or with a denormal coordinate.
    One compiled pass (~1 ms for a 120k-point scan; the numpy expression it replaces took ~14 ms of every read)."""
    return _implausible_kernel(np.ascontiguousarray(xyz), float(limit), float(SENSOR_MIN_RANGE), _F32_TINY)


@nb.njit(cache=True)
def _implausible_kernel(xyz: NDArray, limit: float, min_range: float, tiny: float) -> NDArray[np.bool_]:
    n = xyz.shape[0]
    bad = np.zeros(n, np.bool_)
    for i in range(n):
        m = 0.0
        finite = True
        denormal = False
        for j in range(3):
            a = abs(np.float64(xyz[i, j]))
            if not np.isfinite(a):
                finite = False
            elif a > m:
                m = a
            if a > 0.0 and a < tiny:
                denormal = True
        bad[i] = (not finite) or m > limit or (m > 0.0 and m < min_range) or denormal
    return bad


def _parse_bin(path: str | Path) -> NDArray:
    """KITTI ``.bin`` as (N, 4) float32, or float64 for a float64 variant (with a warning)."""
    path, raw = _read_bytes(path)
    if len(raw) % 16:
        raise MalformedFileError(
            f"{path}: size {len(raw)} B is not a multiple of 16 B (4 float32 per point); "
            "file truncated or not a KITTI .bin scan"
        )
    arr = np.frombuffer(raw, dtype="<f4").reshape(-1, 4)
    n = arr.shape[0]
    if n == 0:
        return arr.astype(np.float32)
    bad = int(_implausible_rows(arr[:, :3], SENSOR_FRAME_LIMIT).sum())
    if bad <= MAX_IMPLAUSIBLE_FRACTION * n:
        return arr.astype(np.float32)
    if len(raw) % 32 == 0:
        # Same bytes as float64 x y z i records: accept when (nearly) every row is plausible.
        # World coordinates (UTM) are allowed there, hence the larger limit.
        arr64 = np.frombuffer(raw, dtype="<f8").reshape(-1, 4)
        if _implausible_rows(arr64[:, :3], 1e8).sum() <= 0.01 * arr64.shape[0]:
            warnings.warn(
                f"{path}: not float32 KITTI records; read as float64 x y z intensity",
                RuntimeWarning,
                stacklevel=4,
            )
            return arr64.astype(np.float64)
    raise MalformedFileError(
        f"{path}: {bad} of {n} points are implausible for a sensor-frame scan (NaN/Inf, "
        f"|coordinate| > {SENSOR_FRAME_LIMIT:g} m, closer than {SENSOR_MIN_RANGE:g} m or "
        "denormal); not a KITTI float32 .bin scan (a text file or another binary format?)"
    )


def read_bin(path: str | Path) -> Points:
    """KITTI Velodyne scan: little-endian float32 ``x y z intensity`` records.

    Raises :class:`MalformedFileError` when most records are not LiDAR returns (see
    :data:`MAX_IMPLAUSIBLE_FRACTION`); a file of float64 records is read with a warning.
    """
    return _world_float32(Path(path), _parse_bin(path), 1.0)


def write_bin(path: str | Path, points: ArrayLike) -> Path:
    return write_bytes_atomic(path, as_points4(points).astype("<f4").tobytes())


def _write_xyzi(path: str | Path, head: bytes, pts: np.ndarray, binary: bool) -> Path:
    """Header plus x y z intensity rows, float32 little endian or ``repr`` text (exact floats)."""
    if binary:
        body = pts.astype("<f4").tobytes()
    else:
        body = "".join(
            f"{x!r} {y!r} {z!r} {i!r}\n" for x, y, z, i in pts.astype(float).tolist()
        ).encode("ascii")
    return write_bytes_atomic(path, head + body)


def read_label(path: str | Path, n_points: int | None = None) -> NDArray[np.uint32]:
    """SemanticKITTI labels: one little-endian uint32 per point (class low 16 bits).

    ``n_points`` (when given) must match, as labels are meaningless for another scan.
    """
    path, raw = _read_bytes(path)
    if len(raw) % 4:
        raise MalformedFileError(
            f"{path}: size {len(raw)} B is not a multiple of 4 (uint32 labels)"
        )
    labels = np.frombuffer(raw, dtype="<u4").astype(np.uint32)
    if n_points is not None and labels.shape[0] != n_points:
        raise MalformedFileError(
            f"{path}: {labels.shape[0]} labels for a scan of {n_points} points"
        )
    return labels


read_labels = read_label


def write_label(path: str | Path, labels: ArrayLike) -> Path:
    lab = np.asarray(labels).reshape(-1)
    if lab.dtype.kind not in "iu" or (lab.size and (lab.min() < 0 or lab.max() > 0xFFFFFFFF)):
        raise InvalidInputError("labels must be non-negative integers that fit in uint32")
    return write_bytes_atomic(path, lab.astype("<u4").tobytes())


def semantic_class(labels: ArrayLike) -> NDArray[np.uint32]:
    """Semantic class: the low 16 bits of a SemanticKITTI label."""
    return (np.asarray(labels).astype(np.uint32) & np.uint32(0xFFFF)).astype(np.uint32)


def instance_id(labels: ArrayLike) -> NDArray[np.uint32]:
    """Instance id: the high 16 bits of a SemanticKITTI label."""
    return (np.asarray(labels).astype(np.uint32) >> np.uint32(16)).astype(np.uint32)


# --------------------------------------------------------------------------------------------
# PCD
# --------------------------------------------------------------------------------------------
_PCD_TYPES = {
    ("F", 4): "f4", ("F", 8): "f8",
    ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
    ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8",
}  # fmt: skip


def _fields_to_points(
    path: Path, names: list[str], columns: dict[str, np.ndarray]
) -> NDArray[np.float64]:
    """(N, 4) float64 x y z intensity: no precision is lost before recentring."""
    for c in ("x", "y", "z"):
        if c not in columns:
            raise MalformedFileError(f"{path}: no '{c}' field (fields: {names})")
    n = columns["x"].shape[0]
    out = np.zeros((n, 4), dtype=np.float64)
    out[:, 0], out[:, 1], out[:, 2] = columns["x"], columns["y"], columns["z"]
    for key in ("intensity", "i", "reflectance", "scalar_intensity"):
        if key in columns:
            out[:, 3] = columns[key]
            break
    return out


def read_pcd(path: str | Path) -> Points:
    """PCL PCD v0.7 (``DATA ascii`` or ``DATA binary``; fields x y z [intensity])."""
    return _world_float32(Path(path), _parse_pcd(path), 1.0)


def _parse_pcd(path: str | Path) -> NDArray[np.float64]:
    path, raw = _read_bytes(path)
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise MalformedFileError(f"{path}: PCD header ends before DATA")
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key.upper()] = vals
        if key.upper() == "DATA":
            break
    try:
        names = header["FIELDS"]
        sizes = [int(s) for s in header["SIZE"]]
        types = [t.upper() for t in header["TYPE"]]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(names))]
        n = (
            int(header["POINTS"][0])
            if "POINTS" in header
            else (int(header["WIDTH"][0]) * int(header.get("HEIGHT", ["1"])[0]))
        )
        data_kind = header["DATA"][0].lower()
    except (KeyError, ValueError, IndexError) as exc:
        raise MalformedFileError(f"{path}: bad PCD header ({exc!r})") from exc
    if n < 0 or any(c < 1 for c in counts):
        raise MalformedFileError(f"{path}: bad PCD header (negative POINTS or COUNT < 1)")
    if not (len(names) == len(sizes) == len(types) == len(counts)):
        raise MalformedFileError(f"{path}: FIELDS/SIZE/TYPE/COUNT lengths differ")
    try:
        dt = np.dtype(
            [
                (f"{nm}_{j}" if c > 1 else nm, "<" + _PCD_TYPES[(t, s)])
                for nm, s, t, c in zip(names, sizes, types, counts, strict=True)
                for j in range(c)
            ]
        )
    except KeyError as exc:
        raise MalformedFileError(f"{path}: unsupported PCD field type {exc}") from exc
    if data_kind == "binary":
        need = n * dt.itemsize
        if len(raw) - pos < need:
            raise MalformedFileError(
                f"{path}: truncated binary PCD ({len(raw) - pos} B of data, {need} B expected)"
            )
        rec = np.frombuffer(raw, dtype=dt, count=n, offset=pos)
        cols = {nm: rec[nm].astype(np.float64) for nm in dt.names or ()}
    elif data_kind == "ascii":
        text = raw[pos:].decode("ascii", errors="replace").split()
        width = len(dt.names or ())
        if len(text) < n * width:
            raise MalformedFileError(
                f"{path}: truncated ASCII PCD ({len(text)} values, {n * width} expected)"
            )
        try:
            arr = np.array(text[: n * width], dtype=np.float64).reshape(n, width)
        except ValueError as exc:
            raise MalformedFileError(f"{path}: non-numeric value in ASCII PCD data") from exc
        cols = {nm: arr[:, j] for j, nm in enumerate(dt.names or ())}
    else:
        raise MalformedFileError(
            f"{path}: PCD 'DATA {data_kind}' is not supported (use ascii or binary)"
        )
    return _fields_to_points(path, names, cols)


def write_pcd(path: str | Path, points: ArrayLike, binary: bool = True) -> Path:
    """Write x y z intensity as float32 PCD v0.7 (binary by default)."""
    pts = as_points4(points)
    n = pts.shape[0]
    head = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        "FIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
        f"DATA {'binary' if binary else 'ascii'}\n"
    ).encode("ascii")
    return _write_xyzi(path, head, pts, binary)


# --------------------------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------------------------
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def read_ply(path: str | Path) -> Points:
    """PLY (ascii, binary_little_endian, binary_big_endian); reads the ``vertex`` element.

    Own parser (no Open3D) so that intensity survives and errors name the file.
    """
    return _world_float32(Path(path), _parse_ply(path), 1.0)


def _parse_ply(path: str | Path) -> NDArray[np.float64]:
    path, raw = _read_bytes(path)
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise MalformedFileError(f"{path}: not a PLY file (no 'ply' magic or 'end_header')")
    nl = raw.find(b"\n", end)
    body_start = len(raw) if nl < 0 else nl + 1
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in lines[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format" and len(tok) >= 2:
            fmt = tok[1]
        elif tok[0] == "element" and len(tok) == 3:
            try:
                elements.append((tok[1], int(tok[2]), []))
            except ValueError as exc:
                raise MalformedFileError(f"{path}: bad PLY element line {line!r}") from exc
        elif tok[0] == "property" and elements:
            if tok[1] == "list":
                elements[-1][2].append((tok[-1], "list"))
            elif len(tok) == 3 and tok[1] in _PLY_TYPES:
                elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]]))
            else:
                raise MalformedFileError(f"{path}: unsupported PLY property {line!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise MalformedFileError(f"{path}: unknown PLY format {fmt!r}")
    if not elements or elements[0][0] != "vertex":
        raise MalformedFileError(f"{path}: PLY must start with a 'vertex' element")
    _, n, props = elements[0]
    if n < 0:
        raise MalformedFileError(f"{path}: negative PLY vertex count {n}")
    if any(t == "list" for _, t in props):
        raise MalformedFileError(f"{path}: list properties on vertices are not supported")
    names = [p for p, _ in props]
    if fmt == "ascii":
        text = raw[body_start:].decode("ascii", errors="replace").split()
        w = len(props)
        if len(text) < n * w:
            raise MalformedFileError(f"{path}: truncated ASCII PLY ({len(text)} < {n * w} values)")
        try:
            arr = np.array(text[: n * w], dtype=np.float64).reshape(n, w)
        except ValueError as exc:
            raise MalformedFileError(f"{path}: non-numeric value in ASCII PLY data") from exc
        cols = {nm: arr[:, j] for j, nm in enumerate(names)}
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        dt = np.dtype([(nm, order + t) for nm, t in props])
        need = n * dt.itemsize
        if len(raw) - body_start < need:
            raise MalformedFileError(
                f"{path}: truncated binary PLY ({len(raw) - body_start} B, {need} B expected)"
            )
        rec = np.frombuffer(raw, dtype=dt, count=n, offset=body_start)
        cols = {nm: rec[nm].astype(np.float64) for nm in names}
    return _fields_to_points(path, names, cols)


def write_ply(path: str | Path, points: ArrayLike, binary: bool = True) -> Path:
    """Write x y z intensity float32 vertices (binary little endian by default)."""
    pts = as_points4(points)
    n = pts.shape[0]
    head = (
        f"ply\nformat {'binary_little_endian' if binary else 'ascii'} 1.0\n"
        f"comment written by graffmatch\nelement vertex {n}\n"
        "property float x\nproperty float y\nproperty float z\nproperty float intensity\n"
        "end_header\n"
    ).encode("ascii")
    return _write_xyzi(path, head, pts, binary)


# --------------------------------------------------------------------------------------------
# numpy
# --------------------------------------------------------------------------------------------
def read_npy(path: str | Path, key: str | None = None) -> Points:
    """``.npy`` array (N,3|4+) or ``.npz`` (``key``, else 'points', else the only array)."""
    return _world_float32(Path(path), _parse_npy(path, key), 1.0)


def _parse_npy(path: str | Path, key: str | None = None) -> NDArray:
    """(N, 4) float32 for float32 files, float64 for every other numeric dtype (lossless)."""
    path = Path(path)
    if not path.exists():
        raise MalformedFileError(f"{path}: file not found")
    try:
        loaded = np.load(path, allow_pickle=False)
        if isinstance(loaded, np.lib.npyio.NpzFile):
            with loaded as z:
                if key is None:
                    key = (
                        "points"
                        if "points" in z.files
                        else (z.files[0] if len(z.files) == 1 else None)
                    )
                if key is None or key not in z.files:
                    raise MalformedFileError(
                        f"{path}: npz has arrays {z.files}; pass key= or name one 'points'"
                    )
                arr = z[key]
        else:
            arr = loaded
    except MalformedFileError:
        raise
    except _NPY_ERRORS as exc:
        raise MalformedFileError(f"{path}: cannot read numpy file ({exc})") from exc
    arr = np.asarray(arr)
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise MalformedFileError(
            f"{path}: points must have shape (N, 3) or (N, 4+), got {arr.shape}"
        )
    if arr.dtype.kind not in "fiu":
        raise MalformedFileError(f"{path}: points must be numeric, got dtype {arr.dtype}")
    dtype = np.float32 if arr.dtype == np.float32 else np.float64
    out = np.zeros((arr.shape[0], 4), dtype=dtype)
    out[:, :3] = arr[:, :3]
    if arr.shape[1] >= 4:
        out[:, 3] = arr[:, 3]
    return out


def write_npy(path: str | Path, points: ArrayLike) -> Path:
    pts = as_points4(points)
    buf = io.BytesIO()
    if Path(path).suffix == ".npz":
        np.savez_compressed(buf, points=pts)
    else:
        np.save(buf, pts)
    return write_bytes_atomic(path, buf.getvalue())


# --------------------------------------------------------------------------------------------
# dispatch
# --------------------------------------------------------------------------------------------
_PARSERS = {
    ".bin": _parse_bin,
    ".pcd": _parse_pcd,
    ".ply": _parse_ply,
    ".npy": _parse_npy,
    ".npz": _parse_npy,
}


def _parse(path: Path, key: str | None = None) -> NDArray:
    parser = _PARSERS.get(path.suffix.lower())
    if parser is None:
        raise MalformedFileError(
            f"{path}: unknown point-cloud suffix {path.suffix!r} (known: {', '.join(POINT_SUFFIXES)})"
        )
    if key is not None:
        if parser is not _parse_npy:
            raise InvalidInputError(f"{path}: key= only applies to .npz files")
        return _parse_npy(path, key)
    return parser(path)


def resolve_scale(scale: float | str) -> float:
    """The factor converting the file's unit to metres: a positive number or a unit name
    (``'m'``, ``'cm'``, ``'mm'`` ... see :data:`UNITS`)."""
    if isinstance(scale, str):
        try:
            return UNITS[scale.strip().lower()]
        except KeyError:
            raise InvalidInputError(
                f"scale: unknown unit {scale!r} (known: {', '.join(UNITS)}; or a factor to metres)"
            ) from None
    if isinstance(scale, (bool, np.bool_)) or not isinstance(scale, (int, float, np.number)):
        raise InvalidInputError(f"scale must be a positive number or a unit name, got {scale!r}")
    value = float(scale)
    if not np.isfinite(value) or value <= 0:
        raise InvalidInputError(f"scale must be a positive finite factor to metres, got {scale!r}")
    return value


def _check_float32_range(path: Path, values: NDArray[np.float64], what: str) -> None:
    """Finite values beyond float32's range would become Inf: no point cloud has them."""
    with np.errstate(invalid="ignore"):
        big = np.abs(values) > _F32_MAX
    if big.any():
        raise MalformedFileError(
            f"{path}: {int(big.sum())} {what} beyond float32's range (|v| > 3.4e38); "
            "not a point cloud"
        )


def _cast_error(exact: NDArray[np.float64], cast: NDArray[np.float32]) -> float:
    """Largest shift the float32 cast applied to a finite coordinate [m]."""
    with np.errstate(invalid="ignore"):
        d = np.abs(cast.astype(np.float64) - exact)
    d = d[np.isfinite(d)]
    return float(d.max(initial=0.0))


def _world_float32(path: Path, raw: NDArray, scale: float) -> Points:
    """(N, 4) float32 in the file's own frame; warns when the cast loses precision."""
    if raw.dtype == np.float32 and scale == 1.0:
        return np.array(raw, dtype=np.float32)  # a writable copy of a float32 source: exact
    xyz = raw[:, :3].astype(np.float64) * scale
    _check_float32_range(path, xyz, "coordinates")
    _check_float32_range(path, raw[:, 3].astype(np.float64), "intensities")
    out = np.empty((raw.shape[0], 4), dtype=np.float32)
    out[:, :3] = xyz
    out[:, 3] = raw[:, 3]
    err = _cast_error(xyz, out[:, :3])
    if err > PRECISION_TOLERANCE:
        warnings.warn(
            f"{path}: float32 moves points by up to {err:.3g} m (|coordinates| up to "
            f"{float(np.nanmax(np.abs(xyz))):.3g} m); use read_scan(), which recentres in "
            "float64 and keeps the origin",
            PrecisionLossWarning,
            stacklevel=4,
        )
    return out


def read_points(path: str | Path, scale: float | str = 1.0) -> Points:
    """Read any supported point cloud as (N, 4) float32 ``x y z intensity`` (by suffix).

    ``scale`` converts the file's unit to metres (0.01 or ``'cm'`` for centimetre integers).
    Coordinates stay in the file's frame: far (UTM) clouds lose precision in float32, which
    gives a :class:`PrecisionLossWarning`; :func:`read_scan` avoids the loss.
    """
    path = Path(path)
    factor = resolve_scale(scale)
    return _world_float32(path, _parse(path), factor)


@dataclass(frozen=True, eq=False)
class Scan:
    """One point cloud, recentred so that float32 keeps its precision.

    ``world = points[:, :3] + origin`` (in float64) gives the file's coordinates (times
    ``scale``). ``origin`` is all zeros for every sensor-frame scan, so ``points`` is then the
    scan exactly as stored.
    """

    points: NDArray[np.float32]  # (N, 4) x y z intensity; xyz relative to origin [m]
    origin: NDArray[np.float64]  # (3,) [m]
    path: Path | None = None
    labels: NDArray[np.uint32] | None = None
    scale: float = 1.0

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def recentred(self) -> bool:
        return bool(np.any(self.origin != 0))

    def world_points(self) -> NDArray[np.float64]:
        """(N, 3) float64 coordinates in the file's frame [m]."""
        return self.points[:, :3].astype(np.float64) + self.origin

    def __repr__(self) -> str:
        return (
            f"Scan(path={None if self.path is None else str(self.path)!r}, n={len(self)}, "
            f"origin={self.origin.tolist()}, scale={self.scale:g}, "
            f"labels={'no' if self.labels is None else 'yes'})"
        )


#: read_scan recentres a cloud with a coordinate beyond this [m]: there the float32 spacing
#: exceeds 2 * PRECISION_TOLERANCE (2^14 m = 16.4 km: spacing 2 mm).
FAR_COORDINATE = PRECISION_TOLERANCE * 2.0**24


def choose_origin(xyz: NDArray[np.float64]) -> NDArray[np.float64]:
    """A round origin near the median for far clouds; zeros otherwise (see :func:`read_scan`)."""
    finite = np.isfinite(xyz).all(axis=1)
    if not finite.any():
        return np.zeros(3)
    pts = xyz[finite]
    if float(np.abs(pts).max()) <= FAR_COORDINATE:
        return np.zeros(3)
    med = np.median(pts, axis=0)
    return np.round(med / ORIGIN_GRID) * ORIGIN_GRID + 0.0  # + 0.0: no negative zeros


def read_scan(
    path: str | Path,
    scale: float | str = 1.0,
    labels: str | Path | None = None,
    key: str | None = None,
) -> Scan:
    """Read a point cloud without silent precision loss: a :class:`Scan` whose float32 points are
    relative to a float64 ``origin``.

    The file is parsed in float64 (float32 files are exact in it), multiplied by ``scale``
    (metres per file unit, or a unit name such as ``'cm'``), and, when a coordinate lies beyond
    :data:`FAR_COORDINATE`, shifted by its median rounded to :data:`ORIGIN_GRID` before the
    float32 cast. Register recentred scans, then map the transform back with
    :func:`graffmatch.geometry.transforms.restore_offsets`. ``labels`` is an optional
    SemanticKITTI ``.label`` path (its length must match); ``key`` picks an array of an ``.npz``.
    """
    path = Path(path)
    factor = resolve_scale(scale)
    raw = _parse(path, key)
    xyz = raw[:, :3].astype(np.float64)
    if factor != 1.0:
        xyz *= factor
    _check_float32_range(path, xyz, "coordinates")
    _check_float32_range(path, raw[:, 3].astype(np.float64), "intensities")
    origin = choose_origin(xyz)
    local = xyz - origin if np.any(origin) else xyz
    pts = np.empty((raw.shape[0], 4), dtype=np.float32)
    pts[:, :3] = local
    pts[:, 3] = raw[:, 3]
    if raw.dtype != np.float32 or factor != 1.0 or np.any(origin):
        err = _cast_error(local, pts[:, :3])
        if err > PRECISION_TOLERANCE:
            warnings.warn(
                f"{path}: the cloud spans {float(np.nanmax(np.abs(local))):.3g} m around its "
                f"origin; float32 still moves points by up to {err:.3g} m",
                PrecisionLossWarning,
                stacklevel=2,
            )
    lab = None if labels is None else read_label(labels, n_points=pts.shape[0])
    return Scan(pts, origin.astype(np.float64), path, lab, factor)


def write_points(path: str | Path, points: ArrayLike) -> Path:
    """Write (N,3|4) points in the format given by the suffix (binary PCD/PLY)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".bin":
        return write_bin(path, points)
    if suffix == ".pcd":
        return write_pcd(path, points)
    if suffix == ".ply":
        return write_ply(path, points)
    if suffix in (".npy", ".npz"):
        return write_npy(path, points)
    raise InvalidInputError(f"{path}: unknown point-cloud suffix {path.suffix!r}")


def label_path_for(scan_path: str | Path) -> Path:
    """SemanticKITTI layout: ``.../velodyne/000000.bin`` -> ``.../labels/000000.label``."""
    p = Path(scan_path)
    if p.parent.name == "velodyne":
        return p.parent.parent / "labels" / (p.stem + ".label")
    return p.with_suffix(".label")
