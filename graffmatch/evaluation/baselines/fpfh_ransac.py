"""FPFH + RANSAC on raw scans with Open3D (the paper's Table II point-based baseline).

The paper: "FPFH local descriptors (downsampled to 0.35 m) with RANSAC (max 100,000 iters.)
implemented in Open3D". The other parameters follow Open3D's global-registration tutorial,
scaled by the voxel size:

* voxel size 0.35 m; normals from a hybrid search of radius 2 x voxel (max 30 neighbours);
* FPFH radius 5 x voxel (max 100 neighbours);
* RANSAC on feature matches: mutual filter off, ``ransac_n = 3``, max correspondence distance
  1.5 x voxel, checkers: edge length 0.9 and distance 1.5 x voxel;
* convergence: at most 100,000 iterations, confidence 0.999;
* Open3D's random seed is set from ``seed`` for reproducibility (Open3D's RANSAC is
  multi-threaded, so identical output is only guaranteed single-threaded).

``valid`` is False when RANSAC found no transformation supported by >= 3 correspondences.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graffmatch.evaluation.methods import (
    MethodBase,
    MethodKind,
    MethodOutput,
    PairInput,
    Timer,
    as_xyz,
)


@dataclass
class FpfhRansac(MethodBase):
    voxel_size: float = 0.35
    normal_radius_factor: float = 2.0
    feature_radius_factor: float = 5.0
    distance_factor: float = 1.5
    edge_length_ratio: float = 0.9
    max_iterations: int = 100_000
    confidence: float = 0.999
    ransac_n: int = 3
    mutual_filter: bool = False
    seed: int = 0
    name: str = "FPFH+RANSAC"
    kind: MethodKind = "point"

    def _features(self, P: np.ndarray):  # type: ignore[no-untyped-def]
        import open3d as o3d

        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
        pcd = pcd.voxel_down_sample(self.voxel_size)
        pcd.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(
                radius=self.normal_radius_factor * self.voxel_size, max_nn=30
            )
        )
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            pcd,
            o3d.geometry.KDTreeSearchParamHybrid(
                radius=self.feature_radius_factor * self.voxel_size, max_nn=100
            ),
        )
        return pcd, fpfh

    def run(self, pair: PairInput) -> MethodOutput:
        import open3d as o3d

        reg = o3d.pipelines.registration
        src_raw, tgt_raw = pair.scans(self.name)
        src, tgt = as_xyz(src_raw, "source_scan"), as_xyz(tgt_raw, "target_scan")
        timer = Timer()
        with timer.stage("features"):
            src_pcd, src_f = self._features(src)
            tgt_pcd, tgt_f = self._features(tgt)
        dist = self.distance_factor * self.voxel_size
        o3d.utility.random.seed(self.seed)
        with timer.stage("ransac"):
            res = reg.registration_ransac_based_on_feature_matching(
                src_pcd,
                tgt_pcd,
                src_f,
                tgt_f,
                self.mutual_filter,
                dist,
                reg.TransformationEstimationPointToPoint(False),
                self.ransac_n,
                [
                    reg.CorrespondenceCheckerBasedOnEdgeLength(self.edge_length_ratio),
                    reg.CorrespondenceCheckerBasedOnDistance(dist),
                ],
                reg.RANSACConvergenceCriteria(self.max_iterations, self.confidence),
            )
        n_corr = len(np.asarray(res.correspondence_set))
        valid = n_corr >= 3
        return MethodOutput(
            np.asarray(res.transformation, float) if valid else None,
            timings=timer.finish(),
            valid=valid,
            info={
                "fitness": float(res.fitness),
                "inlier_rmse": float(res.inlier_rmse),
                "n_correspondences": n_corr,
                "n_source_points": len(src_pcd.points),
                "n_target_points": len(tgt_pcd.points),
                "validity_score": float(res.fitness) if valid else 0.0,
                "validity_signal": "fitness",
            },
        )
