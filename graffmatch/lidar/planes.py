"""Plane landmarks: Open3D planar patches (Araujo & Oliveira 2020), merged into infinite planes.

``PointCloud.detect_planar_patches`` returns bounded patches (oriented boxes). A wall seen
through a tree or split by a door gives several patches of one infinite plane; the paper merges
such "similar" planes, and so do we: two patches merge when their normals are within
``merge_angle_deg``, each centroid is within ``merge_offset`` of the other's plane, and their
supports come within ``merge_max_gap`` (so that two distant, coplanar facades stay distinct
landmarks with their own anchors). The merged plane is refitted by PCA on the union of supports.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from graffmatch.lidar._stats import cluster_stats
from graffmatch.lidar.voxels import VoxelCloud, VoxelGrid, build_voxel_grid, grow_planes

Array = NDArray[np.float64]


class PlaneConfig(BaseModel):
    """Planar-patch detection (Open3D) and merging; see docs/frontend.md for the tuning."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(True, description="Extract plane landmarks (besides the ground).")
    detector: Literal["voxel", "open3d"] = Field(
        "voxel",
        description="voxel: region growing over the voxel grid (graffmatch.lidar.voxels, ~10x "
        "faster); open3d: Open3D's detect_planar_patches (the normal_knn ... patch_knn fields).",
    )
    max_variation: float = Field(
        0.02,
        gt=0,
        le=1 / 3,
        description="voxel detector: a voxel is planar when the surface variation "
        "l0 / (l0 + l1 + l2) of its 3x3x3 neighbourhood is at most this.",
    )
    min_flatness: float = Field(
        0.05,
        ge=0,
        le=1,
        description="voxel detector: ... and l1 / l2 is at least this (a scan line or a pole "
        "is not a plane).",
    )
    grow_angle_deg: float = Field(
        20.0,
        gt=0,
        le=90,
        description="voxel detector: a voxel joins a region when its normal is within this of "
        "the region's and its centroid within max_residual of the region's plane [deg].",
    )
    min_region_voxels: int = Field(
        10, ge=1, description="voxel detector: smaller regions are no patch (before merging)."
    )
    max_range: float | None = Field(
        50.0,
        gt=0,
        description="Only points within this xy range of the sensor feed the patch detector "
        "(None: all); beyond ~50 m HDL-64E voxels are sparse, rarely repeatable and cost ~15% of "
        "the Open3D time [m].",
    )
    voxel_size: float = Field(
        0.4,
        gt=0,
        description="Voxel down-sampling before patch detection; sets speed and detail [m].",
    )
    normal_knn: int = Field(8, ge=3, description="Neighbours used to estimate point normals.")
    normal_variance_threshold_deg: float = Field(
        60.0, gt=0, le=90, description="Open3D: max spread of point normals in a patch [deg]."
    )
    coplanarity_deg: float = Field(
        75.0,
        gt=0,
        le=90,
        description="Open3D: min coplanarity of a patch (larger = flatter) [deg].",
    )
    outlier_ratio: float = Field(
        0.75, gt=0, le=1, description="Open3D: max fraction of outliers before a patch is rejected."
    )
    min_plane_edge_length: float = Field(
        1.0, ge=0, description="Open3D: patches whose largest edge is shorter are discarded [m]."
    )
    min_num_points: int = Field(
        20, ge=0, description="Open3D: min points to try fitting a patch (0 = Open3D's default)."
    )
    patch_knn: int = Field(20, ge=3, description="Open3D: neighbours used to grow patches.")
    box_inflation: float = Field(
        0.1,
        ge=0,
        description="Support = down-sampled points inside the patch box grown by this margin [m].",
    )
    max_residual: float = Field(
        0.2,
        gt=0,
        description="Support points must lie within this distance of the patch plane [m].",
    )
    merge_angle_deg: float = Field(
        6.0, ge=0, le=90, description="Merge patches whose normals differ by less than this [deg]."
    )
    merge_offset: float = Field(
        0.3,
        ge=0,
        description="... and whose centroids lie within this distance of the other plane [m].",
    )
    merge_max_gap: float = Field(
        2.0, ge=0, description="... and whose supports come within this distance of each other [m]."
    )
    ground_duplicate_offset: float = Field(
        0.3,
        ge=0,
        description="Drop planes parallel to the ground landmark (within merge_angle_deg) whose "
        "offset differs by less than this: road pieces left by the ground step, kerbs [m].",
    )
    min_support: int = Field(30, ge=3, description="Minimum support points of a final plane.")
    min_area: float = Field(
        10.0, ge=0, description="Minimum area (OBB sides product) of a final plane [m^2]."
    )
    max_rms: float = Field(0.1, gt=0, description="Maximum RMS residual of a final plane [m].")


@dataclass(frozen=True)
class PlaneResult:
    anchors: Array  # (k, 3) centroids of support
    normals: Array  # (k, 3) unit, canonical sign (pointing towards the sensor origin)
    box: Array  # (k, 2) OBB sides in the plane [m]
    area: Array  # (k,) product of box sides [m^2]
    support: NDArray[np.int64]  # (k,) support points (down-sampled cloud)
    rms: Array  # (k,)
    points: Array  # (M, 3) the down-sampled cloud the labels refer to
    labels: NDArray[np.int64]  # (M,) plane id, -1 when unassigned
    n_patches: int  # patches found by Open3D before merging

    def __len__(self) -> int:
        return int(self.anchors.shape[0])


def _empty(points: Array, n_patches: int = 0) -> PlaneResult:
    z = np.zeros(0)
    return PlaneResult(
        np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 2)), z, np.zeros(0, np.int64), z,
        points, np.full(points.shape[0], -1, np.int64), n_patches,
    )  # fmt: skip


def downsample(points: Array, voxel_size: float) -> Array:
    """Voxel centroids (Open3D); deterministic."""
    import open3d as o3d  # here, not at import: the matcher alone should not load Open3D (~100 MB)

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    return np.asarray(pc.voxel_down_sample(voxel_size).points)


def detect_patches(points: Array, cfg: PlaneConfig) -> NDArray[np.int64]:
    """Run Open3D's planar-patch detector; return a patch id per point (-1 none).

    Open3D returns oriented boxes, not inliers; a point supports the first (largest) patch whose
    box, grown by ``box_inflation``, contains it and whose plane is within ``max_residual``.
    """
    import open3d as o3d  # here, not at import (see downsample)

    m = points.shape[0]
    labels = np.full(m, -1, dtype=np.int64)
    if m < max(cfg.min_num_points, cfg.patch_knn, cfg.normal_knn, cfg.min_support):
        return labels
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(cfg.normal_knn))
    boxes = pc.detect_planar_patches(
        normal_variance_threshold_deg=cfg.normal_variance_threshold_deg,
        coplanarity_deg=cfg.coplanarity_deg,
        outlier_ratio=cfg.outlier_ratio,
        min_plane_edge_length=cfg.min_plane_edge_length,
        min_num_points=cfg.min_num_points,
        search_param=o3d.geometry.KDTreeSearchParamKNN(cfg.patch_knn),
    )
    if len(boxes) == 0:
        return labels
    centers = np.array([b.center for b in boxes])
    Rs = np.array([b.R for b in boxes])
    half = np.array([b.extent for b in boxes]) / 2.0 + cfg.box_inflation
    # The box's thinnest axis is the patch normal; bound it by max_residual instead.
    thin = np.argmin(half, axis=1)
    half[np.arange(len(boxes)), thin] = cfg.max_residual
    order = np.argsort(-np.prod(np.sort(half, axis=1)[:, 1:], axis=1), kind="stable")
    # (M, P, 3) local box coordinates of every point for every patch: M*P is small (~1e5-1e6).
    R_o = Rs[order]
    local = (points @ R_o.transpose(1, 0, 2).reshape(3, -1)).reshape(m, len(order), 3)
    local -= np.einsum("pk,pkj->pj", centers[order], R_o)[None]
    np.abs(local, out=local)
    h = half[order]
    # explicit per-axis tests: a numpy reduce over a length-3 axis is several times slower
    inside = (local[:, :, 0] <= h[:, 0]) & (local[:, :, 1] <= h[:, 1]) & (local[:, :, 2] <= h[:, 2])
    hit = inside.any(axis=1)
    labels[hit] = order[np.argmax(inside[hit], axis=1)]
    return labels


def merge_and_fit(
    points: Array, labels: NDArray[np.int64], cfg: PlaneConfig, n_patches: int
) -> PlaneResult:
    """Merge patches of one infinite plane, refit by PCA and apply the final filters."""
    k = int(labels.max(initial=-1)) + 1
    if k == 0:
        return _empty(points, n_patches)
    st = cluster_stats(points, labels, k)
    present = np.flatnonzero(st.counts >= 3)
    if present.size == 0:
        return _empty(points, n_patches)
    nrm = st.normal()[present]
    cen = st.centroids[present]
    cos_max = np.cos(np.radians(cfg.merge_angle_deg))
    dots = np.abs(nrm @ nrm.T)
    off_ij = np.abs(
        np.einsum("jk,ijk->ij", nrm, cen[:, None, :] - cen[None, :, :])
    )  # |n_j.(c_i-c_j)|
    cand = (dots >= cos_max) & (off_ij <= cfg.merge_offset) & (off_ij.T <= cfg.merge_offset)
    np.fill_diagonal(cand, False)
    ii, jj = np.nonzero(np.triu(cand))
    if ii.size:
        gap_ok = np.zeros(ii.size, dtype=bool)
        trees: dict[int, cKDTree] = {}
        for e, (a, b) in enumerate(zip(ii, jj, strict=True)):  # few candidate pairs
            pa = points[labels == present[a]]
            pb = points[labels == present[b]]
            if a not in trees:
                trees[a] = cKDTree(pa)
            d, _ = trees[a].query(pb, k=1, distance_upper_bound=cfg.merge_max_gap + 1e-9)
            gap_ok[e] = bool(np.isfinite(d).any())
        ii, jj = ii[gap_ok], jj[gap_ok]
    g = coo_matrix((np.ones(ii.size), (ii, jj)), shape=(present.size, present.size))
    _, comp = connected_components(g, directed=False)
    to_merged = np.full(k, -1, dtype=np.int64)
    to_merged[present] = comp
    merged = np.where(labels >= 0, to_merged[np.maximum(labels, 0)], -1)
    km = int(comp.max()) + 1
    st = cluster_stats(points, merged, km)
    normals = st.normal().copy()
    # Canonical sign: normals point towards the sensor origin (n . c <= 0), so that the Hesse
    # offset d = n . c is <= 0 and the sign is stable between scans of the same scene.
    flip = np.einsum("ij,ij->i", normals, st.centroids) > 0
    normals[flip] *= -1
    # In-plane extent from the PCA axes of each merged support.
    ax1, ax2 = st.evecs[:, :, 2], st.evecs[:, :, 1]
    q = points - st.centroids[np.maximum(merged, 0)]
    valid = merged >= 0
    box = np.zeros((km, 2))
    for c, ax in enumerate((ax1, ax2)):
        t = np.einsum("ij,ij->i", q[valid], ax[merged[valid]])
        lo = np.full(km, np.inf)
        hi = np.full(km, -np.inf)
        np.minimum.at(lo, merged[valid], t)
        np.maximum.at(hi, merged[valid], t)
        box[:, c] = np.where(np.isfinite(hi - lo), hi - lo, 0.0)
    area = box[:, 0] * box[:, 1]
    rms = np.sqrt(st.evals[:, 0])
    ok = (st.counts >= cfg.min_support) & (area >= cfg.min_area) & (rms <= cfg.max_rms)
    keep = np.flatnonzero(ok)
    remap = np.full(km, -1, dtype=np.int64)
    remap[keep] = np.arange(keep.size)
    final = np.where(merged >= 0, remap[np.maximum(merged, 0)], -1)
    return PlaneResult(
        st.centroids[keep], normals[keep], box[keep], area[keep], st.counts[keep], rms[keep],
        points, final.astype(np.int64), n_patches,
    )  # fmt: skip


def select_planes(res: PlaneResult, keep: NDArray[np.bool_]) -> PlaneResult:
    """The subset ``keep`` of the planes, with point labels renumbered."""
    idx = np.flatnonzero(keep)
    remap = np.full(len(res) + 1, -1, dtype=np.int64)  # last slot maps label -1
    remap[idx] = np.arange(idx.size)
    labels = remap[res.labels]  # -1 indexes the last slot -> -1
    return PlaneResult(
        res.anchors[idx], res.normals[idx], res.box[idx], res.area[idx], res.support[idx],
        res.rms[idx], res.points, labels, res.n_patches,
    )  # fmt: skip


def drop_ground_duplicates(
    res: PlaneResult, ground_normal: Array, ground_point: Array, cfg: PlaneConfig
) -> PlaneResult:
    """Remove planes parallel to the ground landmark and within ``ground_duplicate_offset`` of
    it: a second, near-identical "ground" would be an ambiguous landmark for matching."""
    if len(res) == 0:
        return res
    cos = np.abs(res.normals @ ground_normal)
    off = np.abs((res.anchors - ground_point) @ ground_normal)
    dup = (cos >= np.cos(np.radians(cfg.merge_angle_deg))) & (off <= cfg.ground_duplicate_offset)
    return select_planes(res, ~dup) if dup.any() else res


def voxel_planes(grid: VoxelGrid, cfg: PlaneConfig) -> tuple[PlaneResult, VoxelCloud]:
    """Planes by region growing over ``grid`` (voxel detector), and the grid's voxel centroids
    with their local normals (which ICP reuses as its down-sampled, normal-carrying cloud)."""
    cloud = VoxelCloud(grid.centroids, np.zeros((len(grid), 3)), grid.size)
    if len(grid) < max(cfg.min_region_voxels, cfg.min_support):
        return _empty(grid.centroids), cloud
    labels, normals, _ = grow_planes(
        grid, cfg.max_variation, cfg.min_flatness, cfg.grow_angle_deg, cfg.max_residual,
        cfg.min_region_voxels,
    )  # fmt: skip
    res = merge_and_fit(grid.centroids, labels, cfg, int(labels.max(initial=-1)) + 1)
    return res, VoxelCloud(grid.centroids, normals, grid.size)


def extract_planes(
    points: Array, cfg: PlaneConfig, downsampled: bool = False, grid: VoxelGrid | None = None
) -> PlaneResult:
    """Down-sample (unless already), detect patches, merge and refit.

    With the voxel detector, ``grid`` (the voxel grid of ``points`` at ``cfg.voxel_size``) is
    used when given, else built here; the planes' points are its voxel centroids.
    """
    if cfg.detector == "voxel":
        return voxel_planes(grid or build_voxel_grid(points, cfg.voxel_size), cfg)[0]
    P = points if downsampled else downsample(points, cfg.voxel_size)
    labels = detect_patches(P, cfg)
    n_patches = int(np.unique(labels[labels >= 0]).size)
    return merge_and_fit(P, labels, cfg, n_patches)
