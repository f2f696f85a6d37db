"""Point-cloud and label I/O: KITTI ``.bin``, SemanticKITTI ``.label``, PCD, PLY and numpy.

Every reader returns ``(N, 4) float32`` rows ``x, y, z, intensity`` (intensity 0 when the file has
none) so that the rest of the front end sees one layout whatever the source. Every parse failure
raises :class:`~graffmatch.errors.MalformedFileError` whose message names the file, instead of a
numpy ``ValueError`` from deep inside a reshape.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graffmatch.errors import InvalidInputError, MalformedFileError

__all__ = [
    "POINT_SUFFIXES",
    "instance_id",
    "label_path_for",
    "read_bin",
    "read_label",
    "read_labels",
    "read_npy",
    "read_pcd",
    "read_ply",
    "read_points",
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
def read_bin(path: str | Path) -> Points:
    """KITTI Velodyne scan: little-endian float32 ``x y z intensity`` records."""
    path, raw = _read_bytes(path)
    if len(raw) % 16:
        raise MalformedFileError(
            f"{path}: size {len(raw)} B is not a multiple of 16 B (4 float32 per point); "
            "file truncated or not a KITTI .bin scan"
        )
    return np.frombuffer(raw, dtype="<f4").reshape(-1, 4).astype(np.float32)


def write_bin(path: str | Path, points: ArrayLike) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(as_points4(points).astype("<f4").tobytes())
    return path


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
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(lab.astype("<u4").tobytes())
    return path


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


def _fields_to_points(path: Path, names: list[str], columns: dict[str, np.ndarray]) -> Points:
    for c in ("x", "y", "z"):
        if c not in columns:
            raise MalformedFileError(f"{path}: no '{c}' field (fields: {names})")
    n = columns["x"].shape[0]
    out = np.zeros((n, 4), dtype=np.float32)
    out[:, 0], out[:, 1], out[:, 2] = columns["x"], columns["y"], columns["z"]
    for key in ("intensity", "i", "reflectance", "scalar_intensity"):
        if key in columns:
            out[:, 3] = columns[key]
            break
    return out


def read_pcd(path: str | Path) -> Points:
    """PCL PCD v0.7 (``DATA ascii`` or ``DATA binary``; fields x y z [intensity])."""
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
    if binary:
        body = pts.astype("<f4").tobytes()
    else:
        body = "".join(
            f"{x!r} {y!r} {z!r} {i!r}\n" for x, y, z, i in pts.astype(float).tolist()
        ).encode("ascii")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(head + body)
    return path


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
    if binary:
        body = pts.astype("<f4").tobytes()
    else:
        body = "".join(
            f"{x!r} {y!r} {z!r} {i!r}\n" for x, y, z, i in pts.astype(float).tolist()
        ).encode("ascii")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(head + body)
    return path


# --------------------------------------------------------------------------------------------
# numpy
# --------------------------------------------------------------------------------------------
def read_npy(path: str | Path, key: str | None = None) -> Points:
    """``.npy`` array (N,3|4+) or ``.npz`` (``key``, else 'points', else the only array)."""
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
    except (OSError, ValueError, EOFError) as exc:
        raise MalformedFileError(f"{path}: cannot read numpy file ({exc})") from exc
    try:
        return as_points4(arr)
    except InvalidInputError as exc:
        raise MalformedFileError(f"{path}: {exc}") from exc


def write_npy(path: str | Path, points: ArrayLike) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    pts = as_points4(points)
    if path.suffix == ".npz":
        np.savez_compressed(path, points=pts)
    else:
        np.save(path, pts)
    return path


# --------------------------------------------------------------------------------------------
# dispatch
# --------------------------------------------------------------------------------------------
_READERS = {
    ".bin": read_bin,
    ".pcd": read_pcd,
    ".ply": read_ply,
    ".npy": read_npy,
    ".npz": read_npy,
}


def read_points(path: str | Path) -> Points:
    """Read any supported point cloud as (N, 4) float32 ``x y z intensity`` (by suffix)."""
    path = Path(path)
    reader = _READERS.get(path.suffix.lower())
    if reader is None:
        raise MalformedFileError(
            f"{path}: unknown point-cloud suffix {path.suffix!r} (known: {', '.join(POINT_SUFFIXES)})"
        )
    return reader(path)


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
