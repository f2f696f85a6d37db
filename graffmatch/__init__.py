"""graffmatch: global LiDAR landmark matching and registration on the affine Grassmannian.

The public names are loaded on first use (PEP 562), so ``import graffmatch`` stays light and
only the parts you touch import Open3D or numba kernels.

>>> from graffmatch import GraffMatcher, make_scene_pair
>>> pair = make_scene_pair(seed=0)
>>> GraffMatcher().match(pair.source, pair.target).valid
True
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_EXPORTS: dict[str, str] = {
    # geometry
    "Landmark": "graffmatch.geometry.landmarks",
    "LandmarkSet": "graffmatch.geometry.landmarks",
    "LandmarkType": "graffmatch.geometry.landmarks",
    "fit_landmark": "graffmatch.geometry.landmarks",
    "make_transform": "graffmatch.geometry.transforms",
    "invert": "graffmatch.geometry.transforms",
    "transform_points": "graffmatch.geometry.transforms",
    "transform_errors": "graffmatch.geometry.transforms",
    "restore_offsets": "graffmatch.geometry.transforms",
    "graff_distance": "graffmatch.geometry.distance",
    "invariant_distance": "graffmatch.geometry.distance",
    "pairwise_distances": "graffmatch.geometry.distance",
    "cross_distances": "graffmatch.geometry.distance",
    # association
    "build_consistency_graph": "graffmatch.association.consistency_graph",
    "ClipperConfig": "graffmatch.association.clipper",
    "solve_clipper": "graffmatch.association.clipper",
    # registration
    "register_landmarks": "graffmatch.registration.closed_form",
    "refine_icp": "graffmatch.registration.icp",
    # matcher
    "GraffMatcher": "graffmatch.matcher",
    "GraffMatchConfig": "graffmatch.matcher",
    "MatchResult": "graffmatch.matcher",
    # lidar
    "LandmarkExtractor": "graffmatch.lidar.extractor",
    "LandmarkExtractorConfig": "graffmatch.lidar.extractor",
    "read_points": "graffmatch.lidar.io",
    "read_scan": "graffmatch.lidar.io",
    "Scan": "graffmatch.lidar.io",
    "read_labels": "graffmatch.lidar.io",
    "write_points": "graffmatch.lidar.io",
    # pipeline
    "register_scans": "graffmatch.pipeline",
    "ScanMatcher": "graffmatch.pipeline",
    "ScanMatcherConfig": "graffmatch.pipeline",
    "ScanRegistration": "graffmatch.pipeline",
    "RefinementConfig": "graffmatch.pipeline",
    # verification
    "VerificationConfig": "graffmatch.verification.config",
    "Hypothesis": "graffmatch.verification.decision",
    # datasets
    "open_dataset": "graffmatch.datasets.registry",
    "make_scene_pair": "graffmatch.datasets.landmark_scene",
    "simulate_dataset": "graffmatch.datasets.simulator",
    # sequences
    "LoopDetector": "graffmatch.loops.detector",
    "LoopDetectorConfig": "graffmatch.loops.detector",
    "LoopClosure": "graffmatch.loops.verify",
    # evaluation
    "LoopClosureDataset": "graffmatch.evaluation.loop_closures",
    "build_suite": "graffmatch.evaluation.suites",
    "run_benchmark": "graffmatch.evaluation.benchmark",
    "make_report": "graffmatch.evaluation.report",
    # tools
    "run_demo": "graffmatch.demo",
    "write_match_view": "graffmatch.viz.match_view",
    "calibrate_lidar_lidar": "graffmatch.calibration",
    "calibrate_camera_depth": "graffmatch.calibration",
    "run_calibration_demo": "graffmatch.calibration",
    # errors
    "GraffMatchError": "graffmatch.errors",
    "InvalidInputError": "graffmatch.errors",
    "DegenerateGeometryError": "graffmatch.errors",
    "MalformedFileError": "graffmatch.errors",
    "PrecisionLossWarning": "graffmatch.errors",
}

__all__ = sorted([*_EXPORTS, "__version__"])


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'graffmatch' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)


def __dir__() -> list[str]:
    return __all__
