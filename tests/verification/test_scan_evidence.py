"""Raw-scan evidence (``ScanMatcherConfig.evidence='scans'``): real KITTI / courtyard scans
verified on the extractor's non-ground voxel clouds; skips without ../shared/data."""

from __future__ import annotations

import numpy as np
import pytest

from graffmatch.datasets.folder import KittiFolder
from graffmatch.geometry.transforms import invert, transform_errors
from graffmatch.pipeline import RefinementConfig, ScanMatcher, ScanMatcherConfig
from graffmatch.verification.config import VerificationConfig


@pytest.fixture(scope="module")
def scans(shared_data):
    kitti = KittiFolder(shared_data / "kitti00_first6")
    court = shared_data / "balm_courtyard"
    if not court.is_dir():
        pytest.skip(f"no courtyard scans under {court}")
    return kitti, KittiFolder(court)


def _matcher(evidence: str) -> ScanMatcher:
    return ScanMatcher(ScanMatcherConfig(evidence=evidence, refinement=RefinementConfig(method="icp")))


def test_kitti_pair_valid_on_scan_evidence(scans) -> None:
    """KITTI 0 <- 5 (4.3 m): valid on the scans' clouds, at the same ICP optimum as the support
    points' path, and within the official pose's own disagreement with the scans (~0.7 m)."""
    kitti, _ = scans
    src, tgt = kitti[5].points, kitti[0].points
    a = _matcher("scans").register(src, tgt)
    b = _matcher("support").register(src, tgt)
    assert a.valid, a.message
    assert a.info["evidence_source"] == "scans" and b.info["evidence_source"] == "support"
    rot, tr = transform_errors(a.T_target_source, b.T_target_source)
    assert rot < 0.1 and tr < 0.05, (rot, tr)  # the same ICP optimum (deg, m)
    T_gt = invert(kitti.poses[0]) @ kitti.poses[5]
    rot, tr = transform_errors(a.T_target_source, T_gt)
    assert rot < 1.0 and tr < 1.0, (rot, tr)
    assert a.timings["scan_evidence"] > 0


def test_kitti_vs_courtyard_invalid_on_scan_evidence(scans) -> None:
    """Scans of two different places (KITTI street, hand-held courtyard) share no view: invalid."""
    kitti, court = scans
    sm = _matcher("scans")
    for k, c in ((0, 10), (5, 60)):
        r = sm.register(court[c].points, kitti[k].points)
        assert not r.valid, (k, c, r.message)


def test_switch_changes_the_evidence_and_thresholds(scans) -> None:
    """evidence='scans' scores on more points than the support, and decides at the scans'
    thresholds (VerificationConfig.scans) instead of the support points'."""
    kitti, _ = scans
    cfg = VerificationConfig()
    assert cfg.scans is not None
    th = cfg.for_evidence(["line", "plane"], "scans")
    assert (th.min_overlap, th.max_rival_ratio, th.max_conflict) == (
        cfg.scans.min_overlap, cfg.scans.max_rival_ratio, cfg.scans.max_conflict)
    assert cfg.for_evidence(["line", "plane"], "support").min_overlap == cfg.min_overlap
    assert cfg.for_evidence(["line"], "scans").min_overlap == cfg.lines_only.min_overlap  # type: ignore[union-attr]
    a = _matcher("scans").register(kitti[3].points, kitti[0].points)
    b = _matcher("support").register(kitti[3].points, kitti[0].points)
    assert abs(a.overlap - b.overlap) > 0.05, (a.overlap, b.overlap)
    assert np.isfinite(a.confidence) and 0.0 <= a.confidence <= 1.0
