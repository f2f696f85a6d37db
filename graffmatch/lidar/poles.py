"""Pole (vertical line) landmarks: a semantic mode (SemanticKITTI labels) and a geometric one.

Semantic mode follows the paper: points of pole-like classes are clustered with DBSCAN
(Open3D) and a line is fitted to each cluster by PCA. Geometric mode needs no labels (NCLT-like
data): points in a height band above the local ground are binned into a 2-D xy occupancy grid,
connected components of occupied cells are clusters (clustering "in voxels"), and a cluster is a
pole when it is thin (small footprint and radius), tall and vertical. With ``layer_height`` set
(:data:`LAYERED_POLES`), the grid is clustered per height layer and the thin components of
neighbouring layers are stacked, so a tree's trunk, which joins its crown in the layers they
share, keeps the layers below it (and a post beside a hedge those above it). Both modes share the same
PCA fit and the same acceptance tests, so a pole means the same thing whichever mode found it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numba as nb
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

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
    layer_height: float | None = Field(
        None,
        gt=0,
        description="Cluster the grid per height layer of this thickness and stack thin layers, "
        "so a trunk under its crown or a post beside a hedge keeps its clear part; None: one "
        "layer over the band. 0.5 for pole-only matching (LAYERED_POLES) [m].",
    )
    max_base_height: float = Field(
        1.5,
        ge=0,
        description="A layered pole's lowest thin layer starts at most this far above "
        "min_height (poles stand on the ground; pillars between windows do not) [m].",
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


#: Pole settings of the layered geometric detector, for pole-only matching
#: (``GraffMatchConfig(landmark_types=["line"])``): on the simulated suburban drive it finds
#: 0.46 of the visible true poles where one layer finds 0.30 (``bench/pole_extraction_recall.py``).
#: Not the default: with it the full matcher's thresholds, chosen on the calibration split, gave
#: held-out precision 0.992 instead of 0.998 at the same recall (``bench/verification.py``,
#: docs/frontend.md).
LAYERED_POLES: dict[str, float] = {"layer_height": 0.5}


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
    import open3d as o3d  # here, not at import: the matcher alone should not load Open3D (~100 MB)

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
    return _fit_candidates(points, cand, lab, k, cfg)


def poles_geometric(
    points: Array, height: Array, is_ground: NDArray[np.bool_], cfg: PoleConfig
) -> PoleResult:
    """Geometric mode: thin, tall, isolated stacks of an xy occupancy grid per height layer.

    ``height`` is the height above the local ground (see :mod:`graffmatch.lidar.ground`).
    """
    n = points.shape[0]
    P = np.ascontiguousarray(points, dtype=np.float64)
    idx, lab, k = pole_candidates(P, height, is_ground, cfg)
    if k == 0:
        return _empty(n)
    return _fit_candidates(P, idx, lab, k, cfg)


def _fit_candidates(points: Array, idx: NDArray[np.int64], lab: NDArray[np.int64], k: int,
                    cfg: PoleConfig) -> PoleResult:
    """Fit and filter the ``k`` candidate clusters of ``points[idx]`` (either mode), with the
    pole labels scattered back to every point of the scan (-1: no pole)."""
    res = _fit_and_filter(points[idx], lab, k, cfg)
    full = np.full(points.shape[0], -1, dtype=np.int64)
    full[idx] = res.labels
    return PoleResult(
        res.anchors, res.directions, res.extent, res.radius, res.support, res.rms, full
    )


def pole_candidates(
    P: Array, height: Array, is_ground: NDArray[np.bool_], cfg: PoleConfig
) -> tuple[NDArray[np.int64], NDArray[np.int64], int]:
    """The clusters the geometric mode fits: (point indices, candidate id of each, count),
    before the acceptance tests (see :func:`_layered_clusters`)."""
    none = np.zeros(0, np.int64)
    band = _band(P, height, is_ground, cfg.min_height, cfg.max_height)
    if band.size < cfg.min_support:
        return none, none, 0
    x0, y0, x1, y1 = _band_bounds(P, band)
    inv = 1.0 / cfg.cell_size  # the same product as in _band_cells, so indices fit the shape
    shape = (int((x1 - x0) * inv) + 1, int((y1 - y0) * inv) + 1)
    if shape[0] * shape[1] > cfg.max_grid_cells:
        raise InvalidInputError(
            f"pole grid of {shape[0]} x {shape[1]} cells is too large; crop the cloud (max_range)"
        )
    flat = _band_cells(P, band, x0, y0, inv, shape[1])
    if cfg.layer_height is None:
        nz, iz, base = 1, np.zeros(band.size, np.int64), 0
    else:
        nz = max(1, int(np.ceil((cfg.max_height - cfg.min_height) / cfg.layer_height - 1e-9)))
        iz = ((height[band] - cfg.min_height) / cfg.layer_height).astype(np.int64)
        iz = np.clip(iz, 0, nz - 1)
        base = int(cfg.max_base_height / cfg.layer_height + 1e-9)
    lab, k = _layered_clusters(
        flat, iz, shape[0], shape[1], nz, cfg.min_cell_points, cfg.max_footprint_cells, base
    )
    sel = np.flatnonzero(lab >= 0)
    return band[sel], lab[sel], int(k)


@nb.njit(cache=True)
def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@nb.njit(cache=True)
def _union(parent, a, b):
    ra, rb = _find(parent, a), _find(parent, b)
    if ra < rb:
        parent[rb] = ra
    elif rb < ra:
        parent[ra] = rb


@nb.njit(cache=True)
def _layered_clusters(flat, iz, nx, ny, nz, min_cell_points, max_fp, max_base_layer):
    """Pole candidates of the band points: per point its candidate id (-1: none), and the count.

    A cell (``flat``: x * ny + y) is occupied when it holds >= ``min_cell_points`` band points;
    its voxel in layer ``iz`` when a point of it lies there. In each layer, 8-connected occupied
    voxels form components; those of at most ``max_fp`` cells are thin. Thin components of
    neighbouring layers (3 x 3 cells, one layer up) are joined into a candidate, kept when it
    covers at most ``max_fp`` cells and starts at layer <= ``max_base_layer`` (a pole stands on
    the ground: a pillar between shop windows starts higher). So a trunk whose upper layers run
    into the crown, a hedge or a car keeps its clear layers. Candidates are numbered by their
    first cell in raster order (one layer: exactly the connected components of the 2-D grid).
    """
    n = flat.shape[0]
    cellmap = np.full(nx * ny, -1, np.int64)
    cell_flat = np.empty(n, np.int64)
    pc = np.empty(n, np.int64)
    nc = 0
    for k in range(n):
        c = cellmap[flat[k]]
        if c < 0:
            c = nc
            cellmap[flat[k]] = c
            cell_flat[c] = flat[k]
            nc += 1
        pc[k] = c
    ccount = np.zeros(nc, np.int64)
    for k in range(n):
        ccount[pc[k]] += 1
    nv = nc * nz
    occ = np.zeros(nv, np.bool_)
    for k in range(n):
        if ccount[pc[k]] >= min_cell_points:
            occ[pc[k] * nz + iz[k]] = True
    parent = np.arange(nv)
    dxs = (0, 1, 1, 1)
    dys = (1, -1, 0, 1)
    for c in range(nc):
        x, y = cell_flat[c] // ny, cell_flat[c] % ny
        for j in range(4):
            xx, yy = x + dxs[j], y + dys[j]
            if xx >= nx or yy < 0 or yy >= ny:
                continue
            c2 = cellmap[xx * ny + yy]
            if c2 < 0:
                continue
            for z in range(nz):
                if occ[c * nz + z] and occ[c2 * nz + z]:
                    _union(parent, c * nz + z, c2 * nz + z)
    size = np.zeros(nv, np.int64)
    for v in range(nv):
        if occ[v]:
            size[_find(parent, v)] += 1
    small = np.zeros(nv, np.bool_)
    for v in range(nv):
        small[v] = occ[v] and size[_find(parent, v)] <= max_fp
    up = np.arange(nv)  # candidates: thin components joined across layers
    for v in range(nv):
        if small[v]:
            _union(up, v, _find(parent, v))
    if nz > 1:
        for c in range(nc):
            x, y = cell_flat[c] // ny, cell_flat[c] % ny
            for z in range(nz - 1):
                if not small[c * nz + z]:
                    continue
                for dx in range(-1, 2):
                    for dy in range(-1, 2):
                        xx, yy = x + dx, y + dy
                        if xx < 0 or xx >= nx or yy < 0 or yy >= ny:
                            continue
                        c2 = cellmap[xx * ny + yy]
                        if c2 >= 0 and small[c2 * nz + z + 1]:
                            _union(up, c * nz + z, c2 * nz + z + 1)
    last = np.full(nv, -1, np.int64)
    fp = np.zeros(nv, np.int64)
    low = np.full(nv, nz, np.int64)
    first = np.full(nv, nx * ny, np.int64)
    for c in range(nc):
        for z in range(nz):
            v = c * nz + z
            if not small[v]:
                continue
            r = _find(up, v)
            if last[r] != c:
                last[r] = c
                fp[r] += 1
            low[r] = min(low[r], z)
            first[r] = min(first[r], cell_flat[c])
    roots = np.empty(nv, np.int64)
    m = 0
    for v in range(nv):
        if small[v] and _find(up, v) == v and fp[v] <= max_fp and low[v] <= max_base_layer:
            roots[m] = v
            m += 1
    roots = roots[:m]
    roots = roots[np.argsort(first[roots], kind="mergesort")]
    rid = np.full(nv, -1, np.int64)
    for j in range(m):
        rid[roots[j]] = j
    lab = np.full(n, -1, np.int64)
    for k in range(n):
        v = pc[k] * nz + iz[k]
        if small[v]:
            lab[k] = rid[_find(up, v)]
    return lab, m


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
