"""Shared fixtures of the loop tests: a real landmark-poor pair with its scan clouds."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from graffmatch.datasets.folder import KittiFolder
from graffmatch.loops import LoopDetector, LoopDetectorConfig
from graffmatch.pipeline import ScanMatcher


def _detector(points: bool) -> LoopDetector:
    cfg = LoopDetectorConfig()
    cfg.verification.scan_cloud_below = 12
    cfg.matcher.verification.point_hypotheses = points
    return LoopDetector(cfg)


@pytest.fixture(scope="module")
def two_landmark_pair(shared_data):
    """KITTI 0 and 5 (4.3 m apart) and a courtyard scan, each cut to its first two stored
    landmarks, with their stored scan clouds; the whole scans' verified match as the reference."""
    kitti, court = shared_data / "kitti00_first6", shared_data / "balm_courtyard"
    if not court.is_dir():
        pytest.skip(f"no courtyard scans under {court}")
    k, c = KittiFolder(kitti), KittiFolder(court)
    det = _detector(True)
    two, clouds = [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for s in (k[0], k[5], c[10]):
            ls = det.prepare(det.scan_matcher.extract(s.points))[0][np.arange(2)]
            two.append(ls)
            clouds.append(det.stored_scan(ls, det.extractor.last_cloud.points))
        sm = ScanMatcher()
        full = sm.match(sm.extract(k[5].points), sm.extract(k[0].points))
    assert full.valid and all(cl is not None for cl in clouds)
    return two, clouds, full.T_target_source
