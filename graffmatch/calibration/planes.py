"""Board-plane extraction from a point cloud (LiDAR sweep or back-projected depth image).

The detection itself is the LiDAR front-end's (:func:`graffmatch.lidar.planes.extract_planes`:
Open3D planar patches, merged, refitted by PCA), so the logic exists once; this module only
tunes it for calibration targets and turns the result into a plane :class:`LandmarkSet`.

Why keep only board-sized planes: a ground plane or a wall is seen *partially* and differently
by two sensors, so its anchor (the centre of what each sensor sees) differs between them and
the anchor-shifted Grassmannian distance would disagree across the two views. Calibration
targets are seen whole, so their anchors name the same physical point. The filter is on the
plane's in-plane box sides; set it to ``(0, inf)`` to keep every plane.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.lidar.planes import PlaneConfig, extract_planes

Array = NDArray[np.float64]


def _board_detector() -> PlaneConfig:
    """Front-end settings for ~1 m boards at 2–8 m: 5 cm voxels (a board keeps >= ~100 points
    at 8 m), small planes, and merging only across gaps up to a LiDAR ring spacing (a board
    split into two patches is re-joined; two distinct boards are never that close and coplanar)."""
    return PlaneConfig(
        detector="open3d",  # these settings were tuned on Open3D's patches (boards, 5 cm voxels)
        voxel_size=0.05,
        normal_knn=12,
        min_plane_edge_length=0.3,
        min_num_points=10,
        box_inflation=0.03,
        max_residual=0.05,
        merge_angle_deg=5.0,
        merge_offset=0.08,
        merge_max_gap=0.25,
        min_support=30,
        min_area=0.05,
        max_rms=0.04,
    )


class PlaneExtractionConfig(BaseModel):
    """How planar boards are extracted from a point cloud (metres)."""

    model_config = ConfigDict(extra="forbid")

    detector: PlaneConfig = Field(
        default_factory=_board_detector,
        description="LiDAR front-end plane detector (graffmatch.lidar.planes), tuned for boards.",
    )
    max_range: float = Field(
        12.0,
        gt=0,
        description="Points farther than this from the sensor are ignored [m]; boards stand "
        "within ~10 m, and the far ground only costs time.",
    )
    min_side: float = Field(
        0.3, ge=0, description="Both in-plane box sides must be at least this long [m] (boards)."
    )
    max_side: float = Field(
        3.0, gt=0, description="Both in-plane box sides must be at most this long [m] (boards)."
    )
    refine_iterations: int = Field(
        2,
        ge=0,
        description="Refit each plane on the full-resolution points near it (the detector "
        "works on voxel centroids); 0 keeps the detector's fit.",
    )
    refine_distance: float = Field(
        0.03, gt=0, description="Refinement gate: max(this, 3 x RMS) from the plane [m]."
    )


def _refine(
    S: Array, R: Array, iterations: int, gate_min: float
) -> tuple[Array, Array, Array, Array, float]:
    """PCA plane of ``S``, then refitted ``iterations`` times on the points of ``R`` within the
    gate of the plane and inside its in-plane box (grown by the gate). Returns
    (support, centroid, normal, in-plane axes (3, 2), rms)."""
    for it in range(iterations + 1):
        c = S.mean(axis=0)
        _, sv, Vt = np.linalg.svd(S - c, full_matrices=False)
        rms = float(sv[2] / np.sqrt(len(S)))
        if it == iterations:
            break
        n, A = Vt[2], Vt[:2].T
        uv = (S - c) @ A
        gate = max(gate_min, 3.0 * rms)
        lo, hi = uv.min(axis=0) - gate, uv.max(axis=0) + gate
        Q = R - c
        near = np.abs(Q @ n) <= gate
        uvR = Q[near] @ A
        inside = np.all((uvR >= lo) & (uvR <= hi), axis=1)
        cand = R[near][inside]
        if len(cand) < 10:
            break
        S = cand
    return S, c, Vt[2], Vt[:2].T, rms


def planes_from_points(
    points: ArrayLike,
    config: PlaneExtractionConfig | None = None,
    refine_points: ArrayLike | None = None,
) -> LandmarkSet:
    """Extract board planes from an (N, 3) cloud in the sensor frame [m].

    Returns a plane-only :class:`LandmarkSet` in the same frame, normals pointing towards the
    sensor. Anchor = centre of the in-plane bounding box of the support (not the centroid:
    sampling density varies across a tilted board, the box centre does not), with ``support``,
    ``rms``, ``box`` and ``extent`` attributes and the support points attached.
    ``refine_points``: the full-resolution cloud used to refit each plane (default: ``points``;
    a depth image passes all its pixels while the detector runs on a subsample).
    """
    cfg = config or PlaneExtractionConfig()
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InvalidInputError(f"points must be (N, 3), got {P.shape}")
    P = P[np.all(np.isfinite(P), axis=1)]
    P = P[np.linalg.norm(P, axis=1) <= cfg.max_range]
    if len(P) < cfg.detector.min_support:
        raise InvalidInputError(f"only {len(P)} valid points; cannot extract planes")
    if refine_points is None:
        R = P
    else:
        R = np.asarray(refine_points, dtype=np.float64).reshape(-1, 3)
        R = R[np.all(np.isfinite(R), axis=1)]
        R = R[np.linalg.norm(R, axis=1) <= cfg.max_range]
    res = extract_planes(P, cfg.detector)
    pts, labels = res.points, res.labels
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(len(res) + 1))
    anchors, normals, sides, chunks, rmss, keep = [], [], [], [], [], []
    for i in range(len(res)):  # loop over planes (tens), vectorised over their points
        S = pts[order[bounds[i] : bounds[i + 1]]]
        c0 = S.mean(axis=0)
        _, _, Vt0 = np.linalg.svd(S - c0, full_matrices=False)
        side0 = np.ptp((S - c0) @ Vt0[:2].T, axis=0)
        if np.any(side0 < cfg.min_side) or np.any(side0 > cfg.max_side):
            continue  # reject before refining: ground and walls are the bulk of the points
        S, c, n, A, rms = _refine(S, R, cfg.refine_iterations, cfg.refine_distance)
        uv = (S - c) @ A
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        side = hi - lo
        if np.any(side < cfg.min_side) or np.any(side > cfg.max_side):
            continue
        keep.append(i)
        anchors.append(c + A @ ((lo + hi) / 2.0))
        normals.append(n if n @ c <= 0 else -n)  # towards the sensor
        sides.append(np.sort(side)[::-1])
        rmss.append(rms)
        chunks.append(S.astype(np.float32))
    if not keep:
        return _empty_planes()
    k = len(keep)
    box = np.asarray(sides)
    offsets = np.concatenate([[0], np.cumsum([len(ch) for ch in chunks])])
    return LandmarkSet.from_arrays(
        np.full(k, LandmarkType.PLANE),
        np.asarray(normals),
        np.asarray(anchors),
        {
            "support": np.array([len(ch) for ch in chunks], dtype=np.int64),
            "rms": np.asarray(rmss),
            "box": box,
            "extent": box[:, 0] * box[:, 1],
        },
        np.concatenate(chunks),
        offsets,
    )


def _empty_planes() -> LandmarkSet:
    return LandmarkSet(
        np.zeros(0, np.int8),
        np.zeros((0, 3, 2)),
        np.zeros((0, 3)),
        {
            "support": np.zeros(0, np.int64),
            "rms": np.zeros(0),
            "box": np.zeros((0, 2)),
            "extent": np.zeros(0),
        },
        np.zeros((0, 3), np.float32),
        np.zeros(1, np.int64),
    )
