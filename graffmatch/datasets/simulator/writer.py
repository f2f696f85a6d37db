"""Write simulated scans in the KITTI odometry layout, exactly as the real loaders read it.

<out>/velodyne/NNNNNN.bin   float32 x y z intensity, LiDAR frame
<out>/labels/NNNNNN.label   uint32 SemanticKITTI labels, (instance << 16) | class
<out>/poses.txt             camera-0 poses, P = Tr @ T_world_lidar @ inv(Tr), 12 values a line
<out>/calib.txt             "Tr: " + 12 values (LiDAR -> camera-0; KITTI sequence 00)
<out>/times.txt             seconds
<out>/landmarks_gt.npz      world-frame GT LandmarkSet (graffmatch landmark file)
<out>/landmarks_visible.npz per-scan GT visibility: (scan, landmark, count) triplets
<out>/sim_meta.json         generator version, seed, configs
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from graffmatch.errors import InvalidInputError, MalformedFileError
from graffmatch.geometry.transforms import invert

#: Velodyne -> camera-0 of KITTI odometry sequence 00 (the calib.txt of ../shared/data/kitti00_first6).
KITTI00_TR = np.array(
    [
        [4.276802385584e-04, -9.999672484946e-01, -8.084491683471e-03, -1.198459927713e-02],
        [-7.210626507497e-03, 8.081198471645e-03, -9.999413164504e-01, -5.403984729748e-02],
        [9.999738645903e-01, 4.859485810390e-04, -7.206933692422e-03, -2.921968648686e-01],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


def _snap_rotation(T: NDArray) -> NDArray:
    """Project the rotation block onto SO(3) (SVD), as pose readers do with printed matrices."""
    T = np.array(T, dtype=float)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    if np.linalg.det(U @ Vt) < 0:
        U[:, 2] *= -1
    T[:3, :3] = U @ Vt
    return T


#: The rigid transform the poses are written with. calib.txt holds the raw KITTI digits
#: (orthonormal to ~1e-7); a reader that snaps them to SO(3) gets exactly this matrix back,
#: so inv(Tr) @ P @ Tr recovers T_world_lidar to ~1e-12.
KITTI00_TR_RIGID = _snap_rotation(KITTI00_TR)


def scan_name(i: int) -> str:
    return f"{i:06d}"


def write_scan(out_dir: Path, index: int, points: NDArray, labels: NDArray) -> None:
    """One scan: ``velodyne/NNNNNN.bin`` (float32 x4) and ``labels/NNNNNN.label`` (uint32)."""
    points = np.ascontiguousarray(points, dtype=np.float32)
    labels = np.ascontiguousarray(labels, dtype=np.uint32)
    if points.ndim != 2 or points.shape[1] != 4 or labels.shape != (len(points),):
        raise InvalidInputError("points must be (N, 4) and labels (N,)")
    (out_dir / "velodyne").mkdir(parents=True, exist_ok=True)
    (out_dir / "labels").mkdir(parents=True, exist_ok=True)
    points.tofile(out_dir / "velodyne" / f"{scan_name(index)}.bin")
    labels.tofile(out_dir / "labels" / f"{scan_name(index)}.label")


def lidar_to_camera_poses(T_world_lidar: NDArray, Tr: NDArray = KITTI00_TR_RIGID) -> NDArray:
    """KITTI camera-0 convention: P_i = Tr @ T_world_lidar_i @ inv(Tr)."""
    T = np.asarray(T_world_lidar, float).reshape(-1, 4, 4)
    return Tr @ T @ invert(Tr)  # Tr must be rigid here (see KITTI00_TR_RIGID)


def camera_to_lidar_poses(P_cam: NDArray, Tr: NDArray = KITTI00_TR_RIGID) -> NDArray:
    """Inverse of :func:`lidar_to_camera_poses`: T_world_lidar = inv(Tr) @ P @ Tr."""
    P = np.asarray(P_cam, float).reshape(-1, 4, 4)
    return invert(Tr) @ P @ Tr


def _fmt_row(v: NDArray) -> str:
    return " ".join(f"{x:.12e}" for x in v)


def write_poses(path: Path, T_world_lidar: NDArray, Tr: NDArray = KITTI00_TR_RIGID) -> None:
    P = lidar_to_camera_poses(T_world_lidar, Tr)
    path.write_text("".join(_fmt_row(p[:3].reshape(-1)) + "\n" for p in P))


def write_calib(path: Path, Tr: NDArray = KITTI00_TR) -> None:
    path.write_text("Tr: " + _fmt_row(np.asarray(Tr)[:3].reshape(-1)) + "\n")


def write_times(path: Path, times: NDArray) -> None:
    path.write_text("".join(f"{t:.6e}\n" for t in np.asarray(times, float)))


def write_visibility(path: Path, scans: NDArray, landmarks: NDArray, counts: NDArray) -> None:
    np.savez_compressed(
        path,
        scan=np.asarray(scans, np.int32),
        landmark=np.asarray(landmarks, np.int32),
        count=np.asarray(counts, np.int32),
    )


def read_visibility(seq_dir: str | Path) -> dict[str, NDArray]:
    """The (scan, landmark, count) triplets of ``landmarks_visible.npz``."""
    path = Path(seq_dir) / "landmarks_visible.npz"
    try:
        with np.load(path) as z:
            return {k: z[k] for k in ("scan", "landmark", "count")}
    except (OSError, KeyError, ValueError) as exc:
        raise MalformedFileError(f"{path}: cannot read landmark visibility ({exc})") from exc


def write_meta(path: Path, meta: dict) -> None:
    path.write_text(json.dumps(meta, indent=2, sort_keys=True, default=_json_default) + "\n")


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.integer, np.floating)):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o)}")
