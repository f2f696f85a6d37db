"""LiDAR–LiDAR extrinsic calibration: board planes from two sweeps, matched with GraffMatch.

No initial guess and no target IDs: the two sweeps' board planes are associated globally by the
consistency of their pairwise (anchor-shifted, ρ-scaled) Grassmannian distances, then the
closed-form plane registration gives ``T_b_a`` with its conditioning κ.
"""

from __future__ import annotations

import time

from numpy.typing import ArrayLike
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.calibration.planes import PlaneExtractionConfig, planes_from_points
from graffmatch.calibration.result import CalibrationConfig, CalibrationResult, calibrate_planes


class LidarLidarConfig(BaseModel):
    """Plane extraction (both sweeps) and GraffMatch calibration settings."""

    model_config = ConfigDict(extra="forbid")

    extraction: PlaneExtractionConfig = Field(
        default_factory=PlaneExtractionConfig, description="Board-plane extraction per sweep."
    )
    calibration: CalibrationConfig = Field(
        default_factory=CalibrationConfig, description="GraffMatch (planes only) + registration."
    )


def calibrate_lidar_lidar(
    cloud_a: ArrayLike, cloud_b: ArrayLike, config: LidarLidarConfig | None = None
) -> CalibrationResult:
    """Estimate ``T_b_a``: maps points of LiDAR A's frame into LiDAR B's frame.

    ``cloud_a``/``cloud_b`` are (N, 3) sweeps [m] in their own sensor frames, taken at the same
    time of a scene with several planar boards at varied orientations (their normals must span
    3D, otherwise the result is flagged degenerate).
    """
    cfg = config or LidarLidarConfig()
    t0 = time.perf_counter()
    planes_a = planes_from_points(cloud_a, cfg.extraction)
    t1 = time.perf_counter()
    planes_b = planes_from_points(cloud_b, cfg.extraction)
    t2 = time.perf_counter()
    result = calibrate_planes(planes_a, planes_b, cfg.calibration, source_name="a", target_name="b")
    result.timings = {"planes_a": t1 - t0, "planes_b": t2 - t1, **result.timings}
    result.timings["total"] = time.perf_counter() - t0
    return result
