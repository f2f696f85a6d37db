"""ICP refinement (Open3D) on the support points of matched landmarks.

The paper's GraffMatch+ICP (Table II) refines the landmark registration with ICP that uses only
the points of the matched landmarks: a few thousand points instead of the whole scan.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.transforms import check_transform


def _cloud(points: ArrayLike, name: str):
    import open3d as o3d

    P = np.asarray(points, dtype=np.float64).reshape(-1, np.asarray(points).shape[-1])[:, :3]
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) < 10:
        raise InvalidInputError(f"{name} has {len(P)} finite points; ICP needs at least 10")
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    return pc


def refine_icp(
    source_points: ArrayLike,
    target_points: ArrayLike,
    T_init: ArrayLike,
    max_correspondence_distance: float = 1.0,
    max_iterations: int = 30,
    point_to_plane: bool = True,
    normal_radius: float = 1.0,
    target_normals: ArrayLike | None = None,
    relative_fitness: float = 1e-6,
    relative_rmse: float = 1e-6,
) -> tuple[NDArray[np.float64], float, float]:
    """Refine ``T_target_source`` by ICP; returns (T, fitness, inlier_rmse).

    Point-to-plane by default, which converges in a few iterations on the planar structure
    landmarks come from. The target's normals are estimated (``normal_radius``) unless given as
    ``target_normals`` (one per target point, e.g. the extractor's voxel normals; zero rows are
    points without a normal). ICP stops after ``max_iterations`` or when fitness and inlier RMSE
    change by less than ``relative_fitness`` / ``relative_rmse`` between iterations.
    """
    import open3d as o3d

    T0 = check_transform(T_init, "T_init")
    src = _cloud(source_points, "source")
    given = point_to_plane and target_normals is not None
    tgt = None if given else _cloud(target_points, "target")
    reg = o3d.pipelines.registration
    # One thread: Open3D's parallel sums change the last bits from run to run otherwise, and the
    # same inputs must give the same pose.
    o3d.utility.set_max_threads(1)
    if given:
        N = np.asarray(target_normals, dtype=np.float64).reshape(-1, 3)
        tp = np.asarray(target_points, dtype=np.float64).reshape(-1, 3)
        if N.shape[0] != tp.shape[0]:
            raise InvalidInputError(f"{N.shape[0]} target normals for {tp.shape[0]} target points")
        ok = np.all(np.isfinite(tp), axis=1) & (np.einsum("ij,ij->i", N, N) > 0.5)
        tgt = _cloud(tp[ok], "target")
        tgt.normals = o3d.utility.Vector3dVector(N[ok])
        est = reg.TransformationEstimationPointToPlane()
    elif point_to_plane:
        tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius, max_nn=30))
        est = reg.TransformationEstimationPointToPlane()
    else:
        est = reg.TransformationEstimationPointToPoint()
    try:
        res = reg.registration_icp(
            src, tgt, float(max_correspondence_distance), T0, est,
            reg.ICPConvergenceCriteria(
                relative_fitness=float(relative_fitness),
                relative_rmse=float(relative_rmse),
                max_iteration=int(max_iterations),
            ),
        )
    finally:
        o3d.utility.set_max_threads(0)
    return np.asarray(res.transformation, dtype=np.float64).copy(), float(res.fitness), float(res.inlier_rmse)


def matched_support_points(
    source: LandmarkSet, target: LandmarkSet, associations: ArrayLike
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Support points of the matched landmarks of both sets (for GraffMatch+ICP)."""
    A = np.asarray(associations, dtype=np.int64).reshape(-1, 2)
    if source.points is None or target.points is None:
        raise InvalidInputError("ICP refinement needs landmark support points (extract with points)")
    src = source[np.unique(A[:, 0])].points
    tgt = target[np.unique(A[:, 1])].points
    return src, tgt  # type: ignore[return-value]
