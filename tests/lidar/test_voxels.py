"""The shared voxel grid and the voxel region-growing plane detector (graffmatch.lidar.voxels)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkType
from graffmatch.lidar import LandmarkExtractor, LandmarkExtractorConfig, PlaneConfig
from graffmatch.lidar.planes import extract_planes
from graffmatch.lidar.voxels import _eig3, build_voxel_grid, grow_planes
from tests.lidar.scene import make_scene


def test_grid_moments_centroids_and_neighbours() -> None:
    rng = np.random.default_rng(0)
    P = rng.uniform(-3, 3, (20000, 3))  # ~12 points per voxel: every voxel occupied
    g = build_voxel_grid(P, 0.5)
    assert g.counts.sum() == len(P)
    # every point's voxel holds it, and the centroid is the mean of the voxel's points
    keys = np.floor((P - g.origin) / 0.5).astype(int)
    for v in (0, len(g) // 2, len(g) - 1):
        members = P[g.point_voxel == v]
        assert len(members) == g.counts[v]
        np.testing.assert_allclose(g.centroids[v], members.mean(axis=0), atol=1e-12)
        assert len(np.unique(keys[g.point_voxel == v], axis=0)) == 1
    # the neighbour relation is symmetric and joins voxels one index step apart
    vk = np.array([keys[g.point_voxel == v][0] for v in range(len(g))])
    # (ring2: the neighbours two voxels away, only of the voxels asked for)
    need = np.zeros(len(g), bool)
    need[::37] = True
    ring2 = g.ring2(need)
    assert np.all(ring2[~need] == -1)
    table = np.hstack([g.neighbours, np.where(need[:, None], ring2, -1)])
    full2 = g.ring2(np.ones(len(g), bool))
    for v in np.flatnonzero(need):
        for j, u in enumerate(table[v]):
            if u >= 0:
                assert v in (g.neighbours[u] if j < 26 else full2[u])
                assert np.abs(vk[u] - vk[v]).max() == (1 if j < 26 else 2)
    # and misses none: all 26 + 98 neighbours of an interior voxel of a dense cube exist
    assert np.sum(g.neighbours >= 0, axis=1).max() == 26
    assert np.sum(full2 >= 0, axis=1).max() == 98


def test_grid_is_deterministic_and_order_free() -> None:
    rng = np.random.default_rng(1)
    P = rng.uniform(0, 10, (3000, 3))
    a = build_voxel_grid(P, 0.4)
    b = build_voxel_grid(P[rng.permutation(len(P))], 0.4)
    np.testing.assert_allclose(a.centroids, b.centroids, atol=1e-12)
    np.testing.assert_array_equal(a.counts, b.counts)
    np.testing.assert_array_equal(a.neighbours, b.neighbours)


def test_grid_refuses_absurd_extent() -> None:
    P = np.array([[0.0, 0.0, 0.0], [1e6, 1e6, 0.0]])
    with pytest.raises(InvalidInputError, match="too large"):
        build_voxel_grid(P, 0.01)


@pytest.mark.parametrize("seed", range(5))
def test_eig3_matches_lapack(seed: int) -> None:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3, 3))
    C = A @ A.T
    C[2] *= 1e-3 if seed % 2 else 1.0  # a nearly planar spread too
    C = (C + C.T) / 2
    e0, e1, e2, a, b, c = _eig3(C[0, 0], C[0, 1], C[0, 2], C[1, 1], C[1, 2], C[2, 2])
    w, V = np.linalg.eigh(C)
    np.testing.assert_allclose([e0, e1, e2], np.maximum(w, 0), rtol=1e-6, atol=1e-12)
    assert abs(abs(np.dot([a, b, c], V[:, 0])) - 1.0) < 1e-6


def _wall(rng, origin, u, v, w, h, step=0.05, noise=0.01):
    s, t = np.meshgrid(np.arange(0, w, step), np.arange(0, h, step))
    n = np.cross(u, v)
    pts = origin + s.reshape(-1, 1) * u + t.reshape(-1, 1) * v
    return pts + rng.normal(0, noise, (len(pts), 1)) * n


def test_two_walls_and_a_cylinder() -> None:
    """Two perpendicular walls give two planes; a cylinder (curved) gives none: the region
    plane is refitted as it grows, so a region cannot follow the curve around."""
    rng = np.random.default_rng(2)
    ex, ey, ez = np.eye(3)
    a = _wall(rng, np.array([0.0, 5.0, 0.0]), ex, ez, 10, 4)
    b = _wall(rng, np.array([10.0, 5.0, 0.0]), ey, ez, 8, 4)
    th, z = np.meshgrid(np.linspace(0, 2 * np.pi, 200), np.arange(0, 4, 0.05))
    cyl = np.column_stack([-6 + 1.5 * np.cos(th.ravel()), 1.5 * np.sin(th.ravel()), z.ravel()])
    cfg = PlaneConfig()
    res = extract_planes(np.vstack([a, b, cyl]), cfg)
    assert len(res) == 2
    normals = np.abs(res.normals)
    assert sorted(np.argmax(normals, axis=1).tolist()) == [0, 1]  # +-y wall, +-x wall
    assert np.all(np.max(normals, axis=1) > np.cos(np.radians(1.0)))
    assert np.all(res.rms < 0.03)
    grid = build_voxel_grid(np.vstack([a, b, cyl]), cfg.voxel_size)
    labels, _, _ = grow_planes(grid, cfg.max_variation, cfg.min_flatness, cfg.grow_angle_deg,
                               cfg.max_residual, cfg.min_region_voxels)  # fmt: skip
    on_cyl = grid.centroids[:, 0] < -3
    walls = set(labels[~on_cyl & (labels >= 0)].tolist())
    assert len(walls) == 2 and not walls & set(labels[on_cyl].tolist())
    for r in set(labels[on_cyl & (labels >= 0)].tolist()):  # any region covers < 1/4 of the arc
        c = grid.centroids[labels == r]
        ang = np.arctan2(c[:, 1], c[:, 0] + 6)
        assert np.ptp(np.unwrap(np.sort(ang))) < np.pi / 2


@pytest.mark.parametrize("detector", ["voxel", "open3d"])
def test_both_detectors_recover_the_scene(detector: str) -> None:
    scene = make_scene(seed=1)
    cfg = LandmarkExtractorConfig(planes=PlaneConfig(detector=detector))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ls = LandmarkExtractor(cfg).extract(scene.points)
    planes = ls.of_type(LandmarkType.PLANE)
    assert len(planes) == len(scene.walls) + 1
    for n, _ in scene.walls:
        cos = np.max(np.abs(planes.directions @ n))
        assert cos > np.cos(np.radians(1.0))


def test_extractor_keeps_the_voxel_cloud_with_normals() -> None:
    scene = make_scene(seed=1)
    ex = LandmarkExtractor()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ls = ex.extract(scene.points)
    cloud = ex.last_cloud
    assert cloud is not None and len(cloud) > 100 and cloud.voxel_size == ex.config.planes.voxel_size
    # voxels of each wall carry that wall's normal
    for n, d in scene.walls:
        on = np.abs(cloud.points @ n - d) < 0.05
        assert on.sum() > 20
        assert np.median(np.abs(cloud.normals[on] @ n)) > np.cos(np.radians(3.0))
    # the Open3D detector keeps no cloud (ICP then voxelises the raw scans itself)
    ex2 = LandmarkExtractor(LandmarkExtractorConfig(planes=PlaneConfig(detector="open3d")))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ex2.extract(scene.points)
    assert ex2.last_cloud is None and len(ls) > 0
