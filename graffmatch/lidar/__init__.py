"""LiDAR front end: point-cloud I/O and pole / plane landmark extraction."""

from graffmatch.lidar.cache import LandmarkCache
from graffmatch.lidar.extractor import LandmarkExtractor, LandmarkExtractorConfig
from graffmatch.lidar.ground import GroundConfig
from graffmatch.lidar.io import (
    Scan,
    instance_id,
    label_path_for,
    read_bin,
    read_label,
    read_labels,
    read_npy,
    read_pcd,
    read_ply,
    read_points,
    read_scan,
    resolve_scale,
    semantic_class,
    write_bin,
    write_label,
    write_npy,
    write_pcd,
    write_ply,
    write_points,
)
from graffmatch.lidar.planes import PlaneConfig
from graffmatch.lidar.poles import PoleConfig

__all__ = [
    "GroundConfig",
    "LandmarkCache",
    "LandmarkExtractor",
    "LandmarkExtractorConfig",
    "PlaneConfig",
    "PoleConfig",
    "Scan",
    "instance_id",
    "label_path_for",
    "read_bin",
    "read_label",
    "read_labels",
    "read_npy",
    "read_pcd",
    "read_ply",
    "read_points",
    "read_scan",
    "resolve_scale",
    "semantic_class",
    "write_bin",
    "write_label",
    "write_npy",
    "write_pcd",
    "write_ply",
    "write_points",
]
