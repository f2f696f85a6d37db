"""Ground segmentation and the explicit ground-plane landmark.

Why a grid of local minima rather than one RANSAC plane: a road over 80 m is not one plane
(slopes, camber, kerbs), so the height of a point *above the local ground* is what separates
ground from poles and walls. The ground *landmark* is then a single plane fitted robustly to
the ground points near the sensor, where the plane model holds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage

from graffmatch.errors import InvalidInputError

Array = NDArray[np.float64]


class GroundConfig(BaseModel):
    """Ground removal (grid of local minima) and ground-plane landmark fit."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(True, description="Segment the ground and emit it as a plane landmark.")
    cell_size: float = Field(
        1.0,
        gt=0,
        description="Side of the square xy cells whose lowest point estimates the local ground [m].",
    )
    min_filter_cells: int = Field(
        5,
        ge=1,
        description="Window (cells) of the minimum filter over the cell minima; it lets cells "
        "covered by cars or walls take the ground height of a neighbour.",
    )
    height_threshold: float = Field(
        0.25, gt=0, description="Points at most this high above the local ground are ground [m]."
    )
    max_grid_cells: int = Field(
        16_000_000, gt=0, description="Refuse grids larger than this (guards against huge extents)."
    )
    emit_landmark: bool = Field(True, description="Add the ground plane as a PLANE landmark.")
    landmark_radius: float = Field(
        30.0,
        gt=0,
        description="Fit the ground plane to ground points within this xy range of the sensor [m].",
    )
    inlier_threshold: float = Field(
        0.15, gt=0, description="Residual below which a ground point supports the ground plane [m]."
    )
    refit_iterations: int = Field(
        3,
        ge=1,
        description="Iterations of fit -> keep inliers -> refit (a deterministic robust fit).",
    )
    max_tilt_deg: float = Field(
        20.0,
        ge=0,
        le=90,
        description="Reject a ground plane whose normal is further from +z [deg].",
    )
    min_support: int = Field(200, ge=3, description="Minimum number of ground-plane inliers.")
    relabel_with_plane: bool = Field(
        True,
        description="Within landmark_radius, also label as ground every point within "
        "inlier_threshold of the fitted ground plane (repairs cells whose minimum is an outlier).",
    )
    fit_max_points: int = Field(
        5000,
        ge=3,
        description="The robust fit uses an even stride of at most this many ground points.",
    )


@dataclass(frozen=True)
class GroundResult:
    is_ground: NDArray[np.bool_]  # (N,)
    height: Array  # (N,) height above the local ground [m]
    plane_inliers: NDArray[np.int64]  # indices of the points supporting the ground plane
    normal: Array | None  # (3,) unit, z >= 0
    centroid: Array | None  # (3,)
    rms: float


def _grid_index(
    xy: Array, cell: float, max_cells: int
) -> tuple[NDArray[np.int64], tuple[int, int], Array]:
    lo = np.array([xy[:, 0].min(), xy[:, 1].min()])
    i = ((xy[:, 0] - lo[0]) / cell).astype(np.int64)  # non-negative: truncation == floor
    j = ((xy[:, 1] - lo[1]) / cell).astype(np.int64)
    ij = np.column_stack([i, j])
    shape = (int(i.max()) + 1, int(j.max()) + 1)
    if shape[0] * shape[1] > max_cells:
        raise InvalidInputError(
            f"cloud spans {shape[0]} x {shape[1]} cells of {cell} m (> {max_cells}); crop it "
            "(max_range) or increase the cell size"
        )
    return ij, shape, lo


def local_ground_height(points: Array, config: GroundConfig) -> Array:
    """Height of every point above the local ground (min filter of the cell minima)."""
    xy = points[:, :2]
    ij, shape, _ = _grid_index(xy, config.cell_size, config.max_grid_cells)
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    zmin = np.full(shape[0] * shape[1], np.inf)
    np.minimum.at(zmin, flat, points[:, 2])
    zmin = ndimage.minimum_filter(zmin.reshape(shape), size=config.min_filter_cells, mode="nearest")
    return points[:, 2] - zmin.reshape(-1)[flat]


def robust_plane_fit(
    points: Array, inlier_threshold: float, iterations: int
) -> tuple[Array, Array, NDArray[np.int64], float] | None:
    """PCA plane fit, then refit on points within ``inlier_threshold``; deterministic."""
    idx = np.arange(points.shape[0])
    normal = centroid = None
    rms = np.inf
    for _ in range(iterations):
        if idx.size < 3:
            return None
        P = points[idx]
        c = P.mean(axis=0)
        _, V = np.linalg.eigh(np.cov((P - c).T, bias=True))
        n = V[:, 0]
        if n[2] < 0:
            n = -n
        res = np.abs((points - c) @ n)
        new_idx = np.flatnonzero(res <= inlier_threshold)
        normal, centroid = n, c
        rms = float(np.sqrt(np.mean(res[idx] ** 2)))
        if np.array_equal(new_idx, idx):
            break
        idx = new_idx
    assert normal is not None and centroid is not None
    return normal, centroid, idx, rms


def segment_ground(points: Array, config: GroundConfig) -> GroundResult:
    """Label ground points and (optionally) fit the ground plane near the sensor origin."""
    n = points.shape[0]
    if n == 0:
        return GroundResult(
            np.zeros(0, bool), np.zeros(0), np.zeros(0, np.int64), None, None, np.nan
        )
    height = local_ground_height(points, config)
    is_ground = height <= config.height_threshold
    if not config.emit_landmark:
        return GroundResult(is_ground, height, np.zeros(0, np.int64), None, None, np.nan)
    within = points[:, 0] ** 2 + points[:, 1] ** 2 <= config.landmark_radius**2
    near = np.flatnonzero(is_ground & within)
    if near.size < config.min_support:
        return GroundResult(is_ground, height, np.zeros(0, np.int64), None, None, np.nan)
    stride = max(1, near.size // config.fit_max_points)
    fit = robust_plane_fit(points[near[::stride]], config.inlier_threshold, config.refit_iterations)
    if fit is None:
        return GroundResult(is_ground, height, np.zeros(0, np.int64), None, None, np.nan)
    normal, c0, _, _ = fit
    inl = np.flatnonzero(np.abs((points[near] - c0) @ normal) <= config.inlier_threshold)
    tilt = np.degrees(np.arccos(np.clip(normal[2], -1.0, 1.0)))
    if tilt > config.max_tilt_deg or inl.size < config.min_support:
        return GroundResult(is_ground, height, np.zeros(0, np.int64), None, None, np.nan)
    sup = near[inl]
    P = points[sup]
    c = P.mean(axis=0)
    rms = float(np.sqrt(np.mean(((P - c) @ normal) ** 2)))
    if config.relabel_with_plane:
        # Points below the road (multipath) lower a cell's minimum and leave real road points
        # "above ground"; near the sensor, the fitted plane is the better ground model.
        cand = np.flatnonzero(~is_ground & within)
        on_plane = np.abs((points[cand] - c) @ normal) <= config.inlier_threshold
        is_ground = is_ground.copy()
        is_ground[cand[on_plane]] = True
    return GroundResult(is_ground, height, sup, normal, c, rms)
