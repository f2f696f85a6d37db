"""Pole (vertical line) landmarks: a semantic mode (SemanticKITTI labels) and a geometric one.

Semantic mode follows the paper: points of pole-like classes are clustered with DBSCAN
(Open3D) and a line is fitted to each cluster by PCA. Geometric mode needs no labels (NCLT-like
data): points in a height band above the local ground are binned into a 2-D xy occupancy grid,
connected components of occupied cells are clusters (clustering "in voxels"), and a cluster is a
pole when it is thin (small footprint and radius), tall and vertical. Both modes share the same
PCA fit and the same acceptance tests, so a pole means the same thing whichever mode found it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numba as nb
import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage

from graffmatch.errors import InvalidInputError
from graffmatch.lidar._stats import axis_spans, cluster_stats

Array = NDArray[np.float64]

PoleMode = Literal["semantic", "geometric", "auto"]


class PoleConfig(BaseModel):
    """Pole detection; every threshold of both modes is here."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(True, description="Extract pole (LINE) landmarks.")
    mode: PoleMode = Field(
        "auto",
        description="'semantic' (needs labels), 'geometric' or 'auto' (semantic if labels given).",
    )
    # --- semantic mode
    semantic_classes: list[int] = Field(
        [80, 81, 71],
        description="SemanticKITTI classes treated as pole-like (pole, traffic-sign, trunk).",
    )
    dbscan_eps: float = Field(
        0.5, gt=0, description="DBSCAN neighbourhood radius (semantic mode) [m]."
    )
    dbscan_min_points: int = Field(
        5, ge=1, description="DBSCAN core-point minimum (semantic mode)."
    )
    # --- geometric mode
    cell_size: float = Field(
        0.25,
        gt=0,
        description="xy cell side of the occupancy grid used to cluster (geometric mode) [m].",
    )
    min_height: float = Field(
        0.4,
        ge=0,
        description="Lower edge of the height band above local ground (skips kerbs, bushes) [m].",
    )
    max_height: float = Field(
        4.0, gt=0, description="Upper edge of the height band (skips tree crowns, lamp heads) [m]."
    )
    max_footprint_cells: int = Field(
        12, ge=1, description="A pole's connected component covers at most this many xy cells."
    )
    max_grid_cells: int = Field(
        64_000_000, gt=0, description="Refuse occupancy grids larger than this (huge extents)."
    )
    min_cell_points: int = Field(
        2, ge=1, description="Cells with fewer band points are empty (suppresses isolated noise)."
    )
    # --- shared acceptance tests
    min_support: int = Field(15, ge=2, description="Minimum number of points of a pole.")
    min_linearity: float = Field(
        0.75, ge=0, le=1, description="Minimum (s1 - s2) / s1 of the PCA standard deviations."
    )
    max_tilt_deg: float = Field(
        15.0, ge=0, le=90, description="Maximum angle between the pole axis and the vertical [deg]."
    )
    min_length: float = Field(1.5, gt=0, description="Minimum extent along the axis [m].")
    max_length: float = Field(30.0, gt=0, description="Maximum extent along the axis [m].")
    max_radius: float = Field(
        0.4, gt=0, description="Maximum mean distance of the points to the axis [m]."
    )


@dataclass(frozen=True)
class PoleResult:
    """Accepted poles and the index of each input point's pole (-1: none)."""

    anchors: Array  # (k, 3) centroids
    directions: Array  # (k, 3) unit, z >= 0
    extent: Array  # (k,) length along the axis [m]
    radius: Array  # (k,) [m]
    support: NDArray[np.int64]  # (k,)
    rms: Array  # (k,) RMS distance to the axis [m]
    labels: NDArray[np.int64]  # (N,) pole id per input point, -1 when not on a pole

    def __len__(self) -> int:
        return int(self.anchors.shape[0])


def _fit_and_filter(
    points: Array, labels: NDArray[np.int64], k: int, cfg: PoleConfig
) -> PoleResult:
    """PCA line fit per cluster, then the linearity/verticality/length/radius/support tests."""
    if k == 0:
        return _empty(points.shape[0])
    st = cluster_stats(points, labels, k)
    axes = st.major_axis().copy()
    axes[axes[:, 2] < 0] *= -1
    lo, hi, radius = axis_spans(points, labels, k, axes, st.centroids)
    length = hi - lo
    tilt = np.degrees(np.arccos(np.clip(np.abs(axes[:, 2]), 0.0, 1.0)))
    rms = np.sqrt(st.evals[:, 0] + st.evals[:, 1])
    ok = (
        (st.counts >= cfg.min_support)
        & (st.linearity() >= cfg.min_linearity)
        & (tilt <= cfg.max_tilt_deg)
        & (length >= cfg.min_length)
        & (length <= cfg.max_length)
        & (radius <= cfg.max_radius)
    )
    keep = np.flatnonzero(ok)
    remap = np.full(k, -1, dtype=np.int64)
    remap[keep] = np.arange(keep.size)
    new_labels = np.where(labels >= 0, remap[np.maximum(labels, 0)], -1)
    return PoleResult(
        st.centroids[keep],
        axes[keep],
        length[keep],
        radius[keep],
        st.counts[keep],
        rms[keep],
        new_labels.astype(np.int64),
    )


def _empty(n: int) -> PoleResult:
    z = np.zeros(0)
    return PoleResult(
        np.zeros((0, 3)), np.zeros((0, 3)), z, z, np.zeros(0, np.int64), z, np.full(n, -1, np.int64)
    )


def poles_semantic(points: Array, semantic: NDArray[np.integer], cfg: PoleConfig) -> PoleResult:
    """Semantic mode: DBSCAN (Open3D) on points whose class is in ``cfg.semantic_classes``."""
    n = points.shape[0]
    sem = np.asarray(semantic).reshape(-1)
    if sem.shape[0] != n:
        raise InvalidInputError(f"{sem.shape[0]} labels for {n} points")
    cand = np.flatnonzero(np.isin(sem, np.asarray(cfg.semantic_classes, dtype=sem.dtype)))
    if cand.size < cfg.dbscan_min_points:
        return _empty(n)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[cand]))
    lab = np.asarray(
        pc.cluster_dbscan(eps=cfg.dbscan_eps, min_points=cfg.dbscan_min_points), dtype=np.int64
    )
    k = int(lab.max(initial=-1)) + 1
    res = _fit_and_filter(points[cand], lab, k, cfg)
    full = np.full(n, -1, dtype=np.int64)
    full[cand] = res.labels
    return PoleResult(
        res.anchors, res.directions, res.extent, res.radius, res.support, res.rms, full
    )


def poles_geometric(
    points: Array, height: Array, is_ground: NDArray[np.bool_], cfg: PoleConfig
) -> PoleResult:
    """Geometric mode: thin, tall, isolated connected components of an xy occupancy grid.

    ``height`` is the height above the local ground (see :mod:`graffmatch.lidar.ground`).
    """
    n = points.shape[0]
    P = np.ascontiguousarray(points, dtype=np.float64)
    band = _band(P, height, is_ground, cfg.min_height, cfg.max_height)
    if band.size < cfg.min_support:
        return _empty(n)
    x0, y0, x1, y1 = _band_bounds(P, band)
    inv = 1.0 / cfg.cell_size  # the same product as in _band_cells, so indices fit the shape
    shape = (int((x1 - x0) * inv) + 1, int((y1 - y0) * inv) + 1)
    if shape[0] * shape[1] > cfg.max_grid_cells:
        raise InvalidInputError(
            f"pole grid of {shape[0]} x {shape[1]} cells is too large; crop the cloud (max_range)"
        )
    flat = _band_cells(P, band, x0, y0, inv, shape[1])
    cnt = np.bincount(flat, minlength=shape[0] * shape[1]).reshape(shape)
    occ = cnt >= cfg.min_cell_points
    comp, k = ndimage.label(occ, structure=np.ones((3, 3), dtype=bool))
    if k == 0:
        return _empty(n)
    comp_flat = comp.reshape(-1)
    sizes = np.bincount(comp_flat, minlength=k + 1)
    small = sizes <= cfg.max_footprint_cells
    small[0] = False
    # Only the points of small components are fitted; component ids start at 1.
    pid = comp_flat[flat]
    sel = np.flatnonzero(small[pid])
    ids = np.flatnonzero(small)
    remap = np.full(k + 1, -1, dtype=np.int64)
    remap[ids] = np.arange(ids.size)
    idx = band[sel]
    res = _fit_and_filter(P[idx], remap[pid[sel]], ids.size, cfg)
    full = np.full(n, -1, dtype=np.int64)
    full[idx] = res.labels
    return PoleResult(
        res.anchors, res.directions, res.extent, res.radius, res.support, res.rms, full
    )


@nb.njit(cache=True)
def _band(P, height, is_ground, lo, hi):
    """Indices of the non-ground points in the height band [lo, hi] above the local ground."""
    out = np.empty(P.shape[0], np.int64)
    m = 0
    for i in range(P.shape[0]):
        if not is_ground[i] and lo <= height[i] <= hi:
            out[m] = i
            m += 1
    return out[:m].copy()


@nb.njit(cache=True)
def _band_bounds(P, band):
    x0 = y0 = np.inf
    x1 = y1 = -np.inf
    for i in band:
        x0 = min(x0, P[i, 0])
        x1 = max(x1, P[i, 0])
        y0 = min(y0, P[i, 1])
        y1 = max(y1, P[i, 1])
    return x0, y0, x1, y1


@nb.njit(cache=True)
def _band_cells(P, band, x0, y0, inv, ny):
    flat = np.empty(band.shape[0], np.int64)
    for k in range(band.shape[0]):
        i = band[k]
        flat[k] = int((P[i, 0] - x0) * inv) * ny + int((P[i, 1] - y0) * inv)
    return flat
