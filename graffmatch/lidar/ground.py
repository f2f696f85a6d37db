"""Ground segmentation and the explicit ground-plane landmark.

Why a grid of local minima rather than one RANSAC plane: a road over 80 m is not one plane
(slopes, camber, kerbs), so the height of a point *above the local ground* is what separates
ground from poles and walls. The ground *landmark* is then a single plane fitted robustly to
the ground points near the sensor, where the plane model holds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
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
    #: ``points[plane_inliers] - centroid`` (C-ordered; None without a plane): the extractor's
    #: ground landmark reuses it instead of gathering and centring the support again.
    centred_inliers: Array | None = None


@nb.njit(cache=True)
def _centred_rows(P, idx):
    """(numpy's ``P[idx].mean(axis=0)``, ``P[idx] - mean``) without the gathered copy: the
    column sums run over the rows in order from the first row, as numpy's axis-0 reduction of
    a C-ordered array does, then divide by the count."""
    n = idx.shape[0]
    s0, s1, s2 = P[idx[0], 0], P[idx[0], 1], P[idx[0], 2]
    for k in range(1, n):
        i = idx[k]
        s0 += P[i, 0]
        s1 += P[i, 1]
        s2 += P[i, 2]
    c = np.array([s0 / n, s1 / n, s2 / n])
    D = np.empty((n, 3))
    for k in range(n):
        i = idx[k]
        D[k, 0] = P[i, 0] - c[0]
        D[k, 1] = P[i, 1] - c[1]
        D[k, 2] = P[i, 2] - c[2]
    return c, D


@nb.njit(cache=True)
def _xy_bounds(P):
    x0 = y0 = np.inf
    x1 = y1 = -np.inf
    for i in range(P.shape[0]):
        x0 = min(x0, P[i, 0])
        x1 = max(x1, P[i, 0])
        y0 = min(y0, P[i, 1])
        y1 = max(y1, P[i, 1])
    return x0, y0, x1, y1


@nb.njit(cache=True)
def _cell_minima(P, x0, y0, inv, nx, ny):
    """Flat xy cell of every point and the lowest z of every cell (one pass)."""
    flat = np.empty(P.shape[0], np.int64)
    zmin = np.full(nx * ny, np.inf)
    for i in range(P.shape[0]):
        f = int((P[i, 0] - x0) * inv) * ny + int((P[i, 1] - y0) * inv)
        flat[i] = f
        if P[i, 2] < zmin[f]:
            zmin[f] = P[i, 2]
    return flat, zmin


@nb.njit(cache=True)
def _label(P, flat, zfloor, threshold, radius2):
    """Height above the local ground, ground flag, and the ground points within the radius."""
    n = P.shape[0]
    height = np.empty(n)
    is_ground = np.empty(n, np.bool_)
    near = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        h = P[i, 2] - zfloor[flat[i]]
        height[i] = h
        g = h <= threshold
        is_ground[i] = g
        if g and P[i, 0] * P[i, 0] + P[i, 1] * P[i, 1] <= radius2:
            near[m] = i
            m += 1
    return height, is_ground, near[:m].copy()


@nb.njit(cache=True)
def _on_plane(P, idx, c, nrm, threshold):
    """The entries of ``idx`` whose point lies within ``threshold`` of the plane (c, nrm)."""
    out = np.empty(idx.shape[0], np.int64)
    m = 0
    for k in range(idx.shape[0]):
        i = idx[k]
        d = (P[i, 0] - c[0]) * nrm[0] + (P[i, 1] - c[1]) * nrm[1] + (P[i, 2] - c[2]) * nrm[2]
        if abs(d) <= threshold:
            out[m] = i
            m += 1
    return out[:m].copy()


@nb.njit(cache=True)
def _relabel(P, is_ground, c, nrm, threshold, radius2):
    """Near the sensor, points within ``threshold`` of the ground plane become ground."""
    out = is_ground.copy()
    for i in range(P.shape[0]):
        if out[i] or P[i, 0] * P[i, 0] + P[i, 1] * P[i, 1] > radius2:
            continue
        d = (P[i, 0] - c[0]) * nrm[0] + (P[i, 1] - c[1]) * nrm[1] + (P[i, 2] - c[2]) * nrm[2]
        if abs(d) <= threshold:
            out[i] = True
    return out


def _cells(points: Array, config: GroundConfig) -> tuple[NDArray[np.int64], Array, tuple[int, int]]:
    """Flat cell index per point and the cell minima (grid refused above max_grid_cells)."""
    cell = config.cell_size
    inv = 1.0 / cell  # the same product as in _cell_minima, so the last index fits the shape
    x0, y0, x1, y1 = _xy_bounds(points)
    shape = (int((x1 - x0) * inv) + 1, int((y1 - y0) * inv) + 1)
    if shape[0] * shape[1] > config.max_grid_cells:
        raise InvalidInputError(
            f"cloud spans {shape[0]} x {shape[1]} cells of {cell} m (> {config.max_grid_cells}); "
            "crop it (max_range) or increase the cell size"
        )
    flat, zmin = _cell_minima(points, x0, y0, inv, shape[0], shape[1])
    return flat, zmin, shape


def _floor(zmin: Array, shape: tuple[int, int], config: GroundConfig) -> Array:
    return ndimage.minimum_filter(
        zmin.reshape(shape), size=config.min_filter_cells, mode="nearest"
    ).reshape(-1)


def local_ground_height(points: Array, config: GroundConfig) -> Array:
    """Height of every point above the local ground (min filter of the cell minima)."""
    P = np.ascontiguousarray(points, dtype=np.float64)
    flat, zmin, shape = _cells(P, config)
    return P[:, 2] - _floor(zmin, shape, config)[flat]


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
    P = np.ascontiguousarray(points, dtype=np.float64)
    flat, zmin, shape = _cells(P, config)
    radius2 = config.landmark_radius**2
    height, is_ground, near = _label(
        P, flat, _floor(zmin, shape, config), config.height_threshold, radius2
    )
    if not config.emit_landmark:
        return GroundResult(is_ground, height, np.zeros(0, np.int64), None, None, np.nan)
    if near.size < config.min_support:
        return GroundResult(is_ground, height, np.zeros(0, np.int64), None, None, np.nan)
    stride = max(1, near.size // config.fit_max_points)
    fit = robust_plane_fit(P[near[::stride]], config.inlier_threshold, config.refit_iterations)
    if fit is None:
        return GroundResult(is_ground, height, np.zeros(0, np.int64), None, None, np.nan)
    normal, c0, _, _ = fit
    sup = _on_plane(P, near, c0, normal, config.inlier_threshold)
    tilt = np.degrees(np.arccos(np.clip(normal[2], -1.0, 1.0)))
    if tilt > config.max_tilt_deg or sup.size < config.min_support:
        return GroundResult(is_ground, height, np.zeros(0, np.int64), None, None, np.nan)
    c, D = _centred_rows(P, sup)  # sup.size >= min_support >= 3
    rms = float(np.sqrt(np.mean((D @ normal) ** 2)))
    if config.relabel_with_plane:
        # Points below the road (multipath) lower a cell's minimum and leave real road points
        # "above ground"; near the sensor, the fitted plane is the better ground model.
        is_ground = _relabel(P, is_ground, c, normal, config.inlier_threshold, radius2)
    return GroundResult(is_ground, height, sup, normal, c, rms, D)
