"""ICP refinement: given target normals, and ScanMatcher reusing the extractor's voxel cloud."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.transforms import make_transform, rot_z, transform_errors, transform_points
from graffmatch.pipeline import RefinementConfig, ScanMatcher, ScanMatcherConfig
from graffmatch.registration.icp import refine_icp


def _room(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Floor and two walls (a corner): points and their exact normals."""
    n = 3000
    u, v = rng.uniform(0, 8, (2, n))
    floor = np.column_stack([u, v, np.zeros(n)])
    wall_x = np.column_stack([np.zeros(n), u, v / 2])
    wall_y = np.column_stack([u, np.zeros(n), v / 2])
    P = np.vstack([floor, wall_x, wall_y])
    N = np.repeat(np.eye(3)[[2, 0, 1]], n, axis=0)
    return P, N


def test_refine_icp_with_given_normals_recovers_the_motion(rng) -> None:
    P, N = _room(rng)
    T_true = make_transform(rot_z(np.radians(2.0)), np.array([0.15, -0.1, 0.05]))
    src = transform_points(np.linalg.inv(T_true), P[::3])  # T_true maps source into target
    T, fitness, _ = refine_icp(src, P, np.eye(4), 0.5, 30, True, 1.0, N, 1e-8, 1e-8)
    rot, tr = transform_errors(T, T_true)
    assert rot < 0.01 and tr < 0.005 and fitness > 0.95
    T_est, _, _ = refine_icp(src, P, np.eye(4), 0.5, 30, True, 1.0)  # normals estimated
    assert transform_errors(T, T_est)[1] < 0.01


def test_refine_icp_rejects_mismatched_normals(rng) -> None:
    P, N = _room(rng)
    with pytest.raises(InvalidInputError, match="normals"):
        refine_icp(P, P, np.eye(4), target_normals=N[:10])


def test_scan_matcher_icp_reuses_the_extractor_cloud(shared_data) -> None:
    root = shared_data / "kitti00_first6" / "velodyne"
    s, t = (np.fromfile(root / f"{i:06d}.bin", np.float32).reshape(-1, 4) for i in (5, 0))
    reuse = ScanMatcher(ScanMatcherConfig(refinement=RefinementConfig(method="icp")))
    raw = ScanMatcher(ScanMatcherConfig(refinement=RefinementConfig(method="icp", reuse_extractor_cloud=False)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = reuse.register(s, t)
        n_target = len(reuse.extractor.last_cloud)  # the target was extracted last
        b = reuse.register(s, t)
        c = raw.register(s, t)
    assert a.valid and c.valid
    assert a.info["icp_n_source"] == 3000 and a.info["icp_n_target"] <= n_target
    assert a.info["icp_n_target"] > 0.9 * n_target  # voxels without a normal are left out
    np.testing.assert_array_equal(a.T_target_source, b.T_target_source)  # deterministic
    # the same pose as ICP on the re-voxelised raw scans (they agree to ~1 cm here)
    rot, tr = transform_errors(a.T_target_source, c.T_target_source)
    assert rot < 0.1 and tr < 0.05, (rot, tr)
