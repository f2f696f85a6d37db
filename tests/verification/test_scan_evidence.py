"""Raw-scan evidence: real KITTI / courtyard scans verified on the extractor's non-ground voxel
clouds (``verify.scan_evidence``, ``ScanMatcherConfig.evidence='support_then_scans'``); skips
without ../shared/data."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from graffmatch.datasets.folder import KittiFolder
from graffmatch.evaluation.suites import suite_config
from graffmatch.geometry.transforms import invert, transform_errors
from graffmatch.pipeline import RefinementConfig, ScanMatcher, ScanMatcherConfig
from graffmatch.verification.config import VerificationConfig
from graffmatch.verification.evidence import prepared_support
from graffmatch.verification.verify import scan_evidence


@pytest.fixture(scope="module")
def scans(shared_data):
    court = shared_data / "balm_courtyard"
    if not court.is_dir():
        pytest.skip(f"no courtyard scans under {court}")
    return KittiFolder(shared_data / "kitti00_first6"), KittiFolder(court)


def _matcher(evidence: str, extractor=None) -> ScanMatcher:
    cfg = ScanMatcherConfig(evidence=evidence, refinement=RefinementConfig(method="icp"))
    if extractor is not None:
        cfg = cfg.model_copy(update={"extractor": extractor})
    return ScanMatcher(cfg)


def test_kitti_pair_valid_on_scan_evidence(scans) -> None:
    """KITTI 0 <- 5 (4.3 m) verified on the scans' clouds alone: valid, decided at the scans'
    thresholds, and within a degree and a metre of the official pose (itself ~0.7 m from the
    scans, ../shared/data/README.md) and 0.2 deg / 10 cm of the support points' answer."""
    kitti, _ = scans
    sm = _matcher("support")
    src = sm.extract(kitti[5].points)
    cs = sm.extractor.last_cloud
    tgt = sm.extract(kitti[0].points)
    ct = sm.extractor.last_cloud
    ev = scan_evidence(src, tgt, cs.points, ct.points, sm.config.matcher.verification)
    assert ev.kind == "scans" and len(ev.source) > len(prepared_support(src))  # more than the support
    a, b = sm.match(src, tgt, ev), sm.match(src, tgt)
    assert a.valid, a.message
    assert a.info["evidence_source"] == "scans" and b.info["evidence_source"] == "support"
    T_gt = invert(kitti.poses[0]) @ kitti.poses[5]
    rot, tr = transform_errors(a.T_target_source, T_gt)
    assert rot < 1.0 and tr < 1.0, (rot, tr)
    rot, tr = transform_errors(a.T_target_source, b.T_target_source)
    assert rot < 0.2 and tr < 0.1, (rot, tr)


def test_kitti_vs_courtyard_invalid_after_both_passes(scans) -> None:
    """Scans of two different places (KITTI street, hand-held courtyard) share no view: invalid
    on the support points and again on the raw scans."""
    kitti, court = scans
    sm = _matcher("support_then_scans")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for k, c in ((0, 10), (5, 60)):
            r = sm.register(court[c].points, kitti[k].points)
            assert not r.valid, (k, c, r.message)
            assert "raw scans:" in r.message and "scan_pass" in r.timings


def test_switch_falls_back_to_scan_evidence(scans) -> None:
    """Courtyard 1 <- 41 (a calibration pair): the support points explain less than min_overlap
    at the right pose (0.18, docs/verification.md Session 11), the raw scans verify it; with
    evidence='support' it stays invalid."""
    _, court = scans
    ext = suite_config("balm_courtyard").extractor
    a = _matcher("support_then_scans", ext).register(court[41].points, court[1].points)
    b = _matcher("support", ext).register(court[41].points, court[1].points)
    assert not b.valid and b.info["evidence_source"] == "support"
    # the default falls back on whole scans (both cover >= scan_fallback_min_view)
    c = ScanMatcher(ScanMatcherConfig(extractor=ext)).register(court[41].points, court[1].points)
    assert c.valid and c.info["evidence_source"] == "scans", c.message
    assert a.valid, a.message
    assert a.info["evidence_source"] == "scans" and "support_message" in a.info
    T_gt = invert(court.poses[1]) @ court.poses[41]
    for r in (a, c):
        rot, tr = transform_errors(r.T_target_source, T_gt)
        assert rot < 1.0 and tr < 0.3, (rot, tr)


def test_scan_thresholds_apply_to_scan_evidence_only() -> None:
    """The raw scans' thresholds replace the support points' for that evidence only; lines-only
    keeps its own."""
    cfg = VerificationConfig()
    assert cfg.scans is not None
    th = cfg.for_evidence(["line", "plane"], "scans")
    assert (th.min_overlap, th.max_rival_ratio, th.max_conflict) == (
        cfg.scans.min_overlap, cfg.scans.max_rival_ratio, cfg.scans.max_conflict)
    if cfg.scans.confidence_coef is not None:
        assert th.confidence_coef == cfg.scans.confidence_coef
    assert cfg.for_evidence(["line", "plane"], "support").min_overlap == cfg.min_overlap
    assert cfg.for_evidence(["line"], "scans").min_overlap == cfg.lines_only.min_overlap  # type: ignore[union-attr]
    assert np.isclose(VerificationConfig(scans=None).for_evidence(["plane"], "scans").min_overlap, cfg.min_overlap)


def test_no_scan_fallback_on_partial_views(scans) -> None:
    """The raw-scan thresholds were chosen on whole scans: a source cut to a 120 deg sector
    (coverage ~0.33 < 0.9) is verified on the support points only, unless
    scan_fallback_min_view is 0 (docs/verification.md, Session 15)."""
    from graffmatch.verification.view import set_coverage

    _, court = scans
    ext = suite_config("balm_courtyard").extractor
    P = court[41].points
    az = np.degrees(np.arctan2(P[:, 1], P[:, 0]))
    part = P[(az > -60.0) & (az < 60.0)]
    sm = _matcher("support_then_scans", ext)
    src = sm.extractor.extract(part)
    cov = set_coverage(src)
    assert cov is not None and 0.25 < cov < 0.45, cov
    assert set_coverage(sm.extractor.extract(P)) > 0.95
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = sm.register(part, court[1].points)
        assert "scan_pass" not in r.timings and "scan_evidence" not in r.timings
        open_cfg = ScanMatcherConfig(evidence="support_then_scans", scan_fallback_min_view=0.0, extractor=ext,
                                     refinement=RefinementConfig(method="icp"))
        r0 = ScanMatcher(open_cfg).register(part, court[1].points)
    assert not r.valid and r.info["evidence_source"] == "support", r.message  # the support points refuse
    assert "scan_evidence" in r0.timings, r0.timings  # without the gate the raw scans are tried
