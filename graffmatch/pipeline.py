"""Scan-to-scan registration in one call: extract landmarks from both scans, match, register.

This is the layer above the matcher and the LiDAR front end; the evaluation and the CLI use it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.lidar.extractor import LandmarkExtractor, LandmarkExtractorConfig
from graffmatch.matcher import GraffMatchConfig, GraffMatcher, MatchResult


@dataclass
class ScanRegistration:
    """A :class:`MatchResult` plus the landmarks it was computed from."""

    result: MatchResult
    source_landmarks: LandmarkSet
    target_landmarks: LandmarkSet

    def __getattr__(self, name: str):  # T_target_source, valid, kappa, ... of the result
        return getattr(self.result, name)

    def __repr__(self) -> str:
        return (
            f"ScanRegistration(source={self.source_landmarks.counts()}, "
            f"target={self.target_landmarks.counts()},\n {self.result!r})"
        )


def register_scans(
    source_points: ArrayLike,
    target_points: ArrayLike,
    source_labels: ArrayLike | None = None,
    target_labels: ArrayLike | None = None,
    extractor_config: LandmarkExtractorConfig | None = None,
    matcher_config: GraffMatchConfig | None = None,
    refine_icp: bool = False,
) -> ScanRegistration:
    """Register two LiDAR scans ((N, 3|4) arrays, sensor frames) without an initial guess.

    ``result.T_target_source`` maps source-frame points into the target frame. With
    ``refine_icp`` the landmark estimate is refined by ICP on the matched landmarks' points.
    """
    extractor = LandmarkExtractor(extractor_config)
    t0 = time.perf_counter()
    src = extractor.extract(source_points, source_labels)
    tgt = extractor.extract(target_points, target_labels)
    t_extract = time.perf_counter() - t0
    result = GraffMatcher(matcher_config).match(src, tgt)
    result.timings = {"extraction": t_extract, **result.timings}
    if refine_icp and result.valid and result.T_target_source is not None:
        from graffmatch.registration.icp import matched_support_points
        from graffmatch.registration.icp import refine_icp as icp

        t1 = time.perf_counter()
        inl = result.info.get("registration_inliers")
        assoc = result.associations if inl is None else result.associations[inl]
        ps, pt = matched_support_points(src, tgt, assoc)
        T, fitness, rmse = icp(ps, pt, result.T_target_source, max_correspondence_distance=0.5)
        result.T_target_source = np.asarray(T)
        result.info.update(icp_fitness=fitness, icp_rmse=rmse)
        result.timings["icp"] = time.perf_counter() - t1
    result.timings["total"] = sum(v for k, v in result.timings.items() if k != "total")
    return ScanRegistration(result, src, tgt)
