"""Reading what users pass on the command line: scans, landmark files, transforms; writing poses.

Every failure raises a :mod:`graffmatch.errors` exception whose message names the file, so the
CLI can show it as one line.
"""

from __future__ import annotations

import json
import re
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from graffmatch.errors import InvalidInputError, MalformedFileError
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.pose_files import snap_to_se3

#: Suffixes read as point clouds (mirrors graffmatch.lidar.io.POINT_SUFFIXES, kept here so that
#: ``graffmatch --help`` does not import Open3D).
SCAN_SUFFIXES = (".bin", ".pcd", ".ply", ".npy", ".npz")


def is_landmark_file(path: Path) -> bool:
    """A graffmatch landmark file is an ``.npz`` with a ``meta`` entry naming the format."""
    if path.suffix.lower() != ".npz":
        return False
    if path.is_file() and not zipfile.is_zipfile(path):
        raise MalformedFileError(f"{path}: not a valid .npz file (not a zip archive)")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "meta" not in z.files:
                return False
            meta = json.loads(str(z["meta"]))
    except (OSError, ValueError, EOFError) as exc:
        raise MalformedFileError(f"{path}: cannot read ({exc})") from exc
    return isinstance(meta, dict) and meta.get("format") == "graffmatch-landmarks"


def require_file(path: Path, what: str = "input") -> Path:
    if not path.exists():
        raise MalformedFileError(f"{path}: {what} not found")
    if path.is_dir():
        raise MalformedFileError(f"{path}: {what} is a folder, expected a file")
    return path


def list_scans(folder: Path) -> list[Path]:
    """Scan files of a folder (or of its ``velodyne/`` subfolder, KITTI layout), sorted."""
    if (folder / "velodyne").is_dir():
        folder = folder / "velodyne"
    files = sorted(
        p
        for p in folder.iterdir()
        if p.is_file() and p.suffix.lower() in SCAN_SUFFIXES and not is_landmark_file(p)
    )
    if not files:
        raise MalformedFileError(
            f"{folder}: no scan files ({', '.join(SCAN_SUFFIXES)}) in this folder"
        )
    return files


def find_labels(scan: Path, explicit: Path | None, mode: str) -> Path | None:
    """The SemanticKITTI label file of a scan: explicit file/folder, else auto-discovered."""
    if explicit is not None:
        cand = explicit / (scan.stem + ".label") if explicit.is_dir() else explicit
        if not cand.exists():
            raise MalformedFileError(f"{cand}: label file not found")
        return cand
    if mode == "never":
        return None
    from graffmatch.lidar.io import label_path_for

    cand = label_path_for(scan)
    return cand if cand.exists() else None


def read_scan(
    path: Path, labels: Path | None = None, scale: float | str = 1.0
) -> tuple[NDArray, NDArray | None]:
    """(N, 4) float32 points in the file's frame (times ``scale``) and optional (N,) labels.

    For two clouds whose relative pose matters as stored (calibration); far (UTM) clouds warn
    about float32 precision here, :func:`read_cloud` recentres them instead.
    """
    from graffmatch.lidar.io import read_label, read_points

    require_file(path, "scan")
    pts = read_points(path, scale=scale)
    lab = None if labels is None else read_label(labels, n_points=len(pts))
    return pts, lab


def read_cloud(path: Path, labels: Path | None = None, scale: float | str = 1.0) -> Any:
    """A :class:`graffmatch.lidar.io.Scan`: float32 points around a float64 origin (zero for
    sensor-frame scans), so that UTM clouds keep their precision."""
    from graffmatch.lidar.io import read_scan as read_recentred

    require_file(path, "scan")
    return read_recentred(path, scale=scale, labels=labels)


#: A scan with fewer points cannot hold a landmark: an input error, not a result to compute.
MIN_SCAN_POINTS = 4
#: Landmarks an input needs before matching (the matcher's minimum).
MIN_LANDMARKS = 2


@dataclass
class LoadedInput:
    """A command-line input resolved to landmarks (and the scan points when it was a scan).

    ``points`` and ``landmarks`` are relative to ``origin`` (float64, zeros unless the file
    held far coordinates such as UTM): ``file frame = local + origin``.
    """

    path: Path
    kind: Literal["scan", "landmarks"]
    landmarks: LandmarkSet
    points: NDArray | None = None
    labels_path: Path | None = None
    timings: dict[str, float] | None = None
    origin: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    #: the extractor's non-ground voxel cloud of a scan (``LandmarkExtractor.last_cloud``): the
    #: raw-scan evidence of ``ScanMatcher.match_scans``
    cloud: Any = None


class LazyExtractor:
    """One landmark extractor, built on first use: landmark files need none, and the LiDAR
    front end (Open3D) is slow to import."""

    def __init__(self, config: Any = None) -> None:
        self.config = config
        self._extractor: Any = None

    def get(self) -> Any:
        if self._extractor is None:
            from graffmatch.lidar.extractor import LandmarkExtractor

            self._extractor = LandmarkExtractor(self.config)
        return self._extractor


def load_input(
    path: Path,
    labels: Path | None,
    label_mode: str,
    extractor: LazyExtractor,
    scale: float | str = 1.0,
) -> LoadedInput:
    """A scan (extracted now, with its timings) or a landmark file, as a LoadedInput.

    Raises an error naming the file when it cannot be matched: an empty or near-empty scan, or
    fewer than two landmarks (the warnings printed before it say why, e.g. ``--scale``).
    """
    if not path.exists():
        raise MalformedFileError(f"{path}: input not found")
    if path.is_dir():
        raise MalformedFileError(f"{path}: input is a folder; give one scan or one landmark file")
    if is_landmark_file(path):
        loaded = LoadedInput(path, "landmarks", LandmarkSet.load(path))
    else:
        label_path = find_labels(path, labels, label_mode)
        scan = read_cloud(path, label_path, scale)
        if len(scan) < MIN_SCAN_POINTS:
            what = "is empty (0 points)" if len(scan) == 0 else f"has only {len(scan)} point(s)"
            raise InvalidInputError(f"{path}: the scan {what}; nothing to extract landmarks from")
        ex = extractor.get()
        t0 = time.perf_counter()
        ls = ex.extract(scan.points, scan.labels)
        timings = dict(ex.last_timings)
        timings.setdefault("total", time.perf_counter() - t0)
        loaded = LoadedInput(path, "scan", ls, scan.points, label_path, timings, scan.origin, ex.last_cloud)
    if len(loaded.landmarks) < MIN_LANDMARKS:
        raise InvalidInputError(
            f"{path}: {len(loaded.landmarks)} landmark(s) ({counts_text(loaded.landmarks)}); "
            f"at least {MIN_LANDMARKS} are needed to match"
        )
    return loaded


def counts_text(ls: LandmarkSet) -> str:
    """'12 poles, 30 planes' (and points when there are any)."""
    c = ls.counts()
    parts = [f"{c['lines']} poles", f"{c['planes']} planes"]
    if c["points"]:
        parts.append(f"{c['points']} points")
    return ", ".join(parts)


# ----------------------------------------------------------------------------------------------
# transforms and pose files
# ----------------------------------------------------------------------------------------------
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def parse_transform(text: str, source: str = "transform") -> NDArray[np.float64]:
    """16 numbers (4x4) or 12 numbers (KITTI 3x4, row-major) -> a 4x4 rigid transform."""
    values = [float(v) for v in _NUMBER.findall(text)]
    if len(values) == 12:
        T = np.eye(4)
        T[:3, :] = np.reshape(values, (3, 4))
    elif len(values) == 16:
        T = np.reshape(values, (4, 4))
    else:
        raise InvalidInputError(
            f"{source}: expected 12 (3x4) or 16 (4x4) numbers, found {len(values)}"
        )
    return snap_to_se3(T, source)


def read_transform(arg: str) -> NDArray[np.float64]:
    """``--gt`` value: a text file holding a 4x4/3x4 matrix, or the 12/16 numbers inline."""
    path = Path(arg)
    if path.exists():
        if path.suffix.lower() == ".json":
            try:
                data = json.loads(path.read_text())
            except json.JSONDecodeError as exc:
                raise MalformedFileError(f"{path}: not valid JSON ({exc})") from exc
            mat = data.get("T_target_source", data) if isinstance(data, dict) else data
            return parse_transform(json.dumps(mat), str(path))
        return parse_transform(path.read_text(), str(path))
    if re.fullmatch(r"[\d\s.,;eE+\-\[\]]+", arg) and _NUMBER.search(arg):
        return parse_transform(arg, "--gt")  # inline numbers (says so if their count is wrong)
    raise MalformedFileError(f"{arg}: ground-truth transform file not found")


# ----------------------------------------------------------------------------------------------
# camera-depth calibration inputs
# ----------------------------------------------------------------------------------------------
def read_intrinsics(arg: str, what: str = "intrinsics") -> NDArray[np.float64]:
    """3x3 K from a text file (9 numbers) or inline 'fx,fy,cx,cy' (or 9 numbers) [px]."""
    path = Path(arg)
    text = path.read_text() if path.is_file() else arg
    if not path.is_file() and not re.fullmatch(r"[\d\s.,;eE+\-\[\]]+", arg):
        raise MalformedFileError(f"{arg}: {what} file not found")
    vals = [float(v) for v in _NUMBER.findall(text)]
    if len(vals) == 4:
        fx, fy, cx, cy = vals
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    elif len(vals) == 9:
        K = np.reshape(vals, (3, 3))
    else:
        raise InvalidInputError(
            f"{what}: expected 4 (fx,fy,cx,cy) or 9 (3x3) numbers, got {len(vals)}"
        )
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
        raise InvalidInputError(f"{what}: not a pinhole camera matrix {K.tolist()}")
    return K


def read_image(path: Path) -> NDArray[np.uint8]:
    """An RGB image (H, W, 3) uint8 via OpenCV (which reads BGR)."""
    import cv2

    require_file(path, "image")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise MalformedFileError(f"{path}: not an image OpenCV can read")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth_image(path: Path, scale: float = 0.001) -> NDArray[np.float32]:
    """A z-depth image [m]: float .npy as is, integer images (e.g. 16-bit PNG in mm) * scale."""
    require_file(path, "depth image")
    if path.suffix.lower() == ".npy":
        try:
            D = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise MalformedFileError(f"{path}: cannot read ({exc})") from exc
    else:
        import cv2

        D = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH)
        if D is None:
            raise MalformedFileError(f"{path}: not a depth image OpenCV can read")
    if D.ndim != 2:
        raise MalformedFileError(f"{path}: depth must be one channel, got shape {D.shape}")
    if np.issubdtype(D.dtype, np.integer):  # e.g. 16-bit PNG in millimetres
        return (D.astype(np.float64) * scale).astype(np.float32)
    return D.astype(np.float32)


def parse_board(spec: str):
    """'7x5x0.07[x0.05]' -> Chessboard(cols=7, rows=5, square=0.07[, margin=0.05]) [m].

    Inner corners (columns x rows), the square side and optionally the white margin.
    """
    from graffmatch.calibration.rig import Chessboard

    num = r"\s*[xX]\s*([0-9.eE+-]+)"
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)" + num + f"(?:{num})?\\s*", spec)
    if not m:
        raise InvalidInputError(
            f"--board {spec!r}: expected COLSxROWSxSQUARE[xMARGIN], e.g. 7x5x0.07"
        )
    extra = {} if m[4] is None else {"margin": float(m[4])}
    return Chessboard(cols=int(m[1]), rows=int(m[2]), square=float(m[3]), **extra)


# ----------------------------------------------------------------------------------------------
# result files
# ----------------------------------------------------------------------------------------------
RESULT_FORMAT = "graffmatch-register-result"


def path_record(path: Path | None, base: Path) -> dict[str, str] | None:
    """Store a path both absolute and relative to the result's folder (folders move)."""
    if path is None:
        return None
    path = Path(path).resolve()
    try:
        rel = str(path.relative_to(base.resolve()))
    except ValueError:
        rel = None
    rec = {"absolute": str(path)}
    if rel is not None:
        rec["relative"] = rel
    return rec


def resolve_path_record(rec: dict[str, str] | str | None, base: Path) -> Path | None:
    if rec is None:
        return None
    if isinstance(rec, str):
        rec = {"absolute": rec}
    if "relative" in rec and (base / rec["relative"]).exists():
        return base / rec["relative"]
    return Path(rec["absolute"])


def load_result(path: Path) -> dict:
    require_file(path, "result file")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise MalformedFileError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(data, dict) or data.get("format") != RESULT_FORMAT:
        raise MalformedFileError(
            f"{path}: not a graffmatch register result (format {RESULT_FORMAT})"
        )
    return data
