"""Extrinsic calibration with GraffMatch plane matching (LiDAR–LiDAR and camera–depth).

Typical use::

    from graffmatch.calibration import calibrate_lidar_lidar
    result = calibrate_lidar_lidar(cloud_a, cloud_b)   # (N, 3) arrays, metres
    print(result.T_b_a, result.kappa, result.valid)
"""

from graffmatch.calibration.camera_depth import (
    BoardDetection,
    CameraDepthConfig,
    calibrate_camera_depth,
    detect_board_planes,
    extract_depth_planes,
)
from graffmatch.calibration.demo import format_demo_report, run_calibration_demo
from graffmatch.calibration.lidar_lidar import LidarLidarConfig, calibrate_lidar_lidar
from graffmatch.calibration.planes import PlaneExtractionConfig, planes_from_points
from graffmatch.calibration.result import CalibrationConfig, CalibrationResult, calibrate_planes
from graffmatch.calibration.rig import Chessboard

__all__ = [
    "BoardDetection",
    "CalibrationConfig",
    "CalibrationResult",
    "CameraDepthConfig",
    "Chessboard",
    "LidarLidarConfig",
    "PlaneExtractionConfig",
    "calibrate_camera_depth",
    "calibrate_lidar_lidar",
    "calibrate_planes",
    "detect_board_planes",
    "extract_depth_planes",
    "format_demo_report",
    "planes_from_points",
    "run_calibration_demo",
]
