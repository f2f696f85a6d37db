"""Simulated LiDAR world: a procedural city, a ray-cast spinning LiDAR and KITTI-layout output.

Quick use::

    from graffmatch.datasets.simulator import simulate_dataset, simulate_scan_pair, SUITES
    simulate_dataset("out/sim", style="downtown", seed=0, n_scans=100)
    pair = simulate_scan_pair("downtown", seed=0, yaw_deg=180, offset_m=14)

See docs/simulator.md for the world and sensor models.
"""

from graffmatch.datasets.simulator.scoring import extraction_accuracy
from graffmatch.datasets.simulator.sensor import (
    PROFILES,
    SensorProfile,
    get_profile,
    render_scan,
)
from graffmatch.datasets.simulator.simulate import (
    DEFAULT_N_SCANS,
    SIMULATOR_VERSION,
    SUITES,
    SuiteSpec,
    gt_landmarks_in_scan,
    load_ground_truth,
    scan_ground_truth,
    simulate_dataset,
    simulate_scan_pair,
    simulate_suite,
)
from graffmatch.datasets.simulator.trajectory import (
    Trajectory,
    TrajectoryConfig,
    plan_route,
    poses_on_ground,
    revisit_pairs,
)
from graffmatch.datasets.simulator.world import (
    CATEGORIES,
    STYLES,
    World,
    WorldConfig,
    build_world,
    world_preset,
)
from graffmatch.datasets.simulator.writer import (
    KITTI00_TR,
    KITTI00_TR_RIGID,
    camera_to_lidar_poses,
    lidar_to_camera_poses,
    read_visibility,
)

__all__ = [
    "CATEGORIES",
    "DEFAULT_N_SCANS",
    "KITTI00_TR",
    "KITTI00_TR_RIGID",
    "PROFILES",
    "SIMULATOR_VERSION",
    "STYLES",
    "SUITES",
    "SensorProfile",
    "SuiteSpec",
    "Trajectory",
    "TrajectoryConfig",
    "World",
    "WorldConfig",
    "build_world",
    "camera_to_lidar_poses",
    "extraction_accuracy",
    "get_profile",
    "gt_landmarks_in_scan",
    "lidar_to_camera_poses",
    "load_ground_truth",
    "plan_route",
    "poses_on_ground",
    "read_visibility",
    "render_scan",
    "revisit_pairs",
    "scan_ground_truth",
    "simulate_dataset",
    "simulate_scan_pair",
    "simulate_suite",
    "world_preset",
]
