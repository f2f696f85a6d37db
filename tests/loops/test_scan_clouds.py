"""Scan clouds of landmark-poor scans in the loop database (session 15): stored compactly, exact
on their grid, and a landmark-poor pair verified through them (``verify.scan_pass``: raw-scan
evidence, the same ``scan_evidence`` / ``match(..., evidence=)`` path as ``ScanMatcher``)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from graffmatch.datasets.folder import KittiFolder
from graffmatch.geometry.transforms import transform_errors
from graffmatch.loops import LandmarkDatabase, LoopDetector, LoopDetectorConfig
from graffmatch.loops.database import (
    POINT_QUANTUM_M,
    decode_points,
    encode_points,
    load_landmarks,
    load_scan_cloud,
    save_landmarks,
)
from graffmatch.loops.verify import VerificationConfig, scans_loop_confidence, verify_candidate
from graffmatch.pipeline import ScanMatcher


def _poor_config(**update) -> LoopDetectorConfig:
    """Landmark-poor maps from real scans: at most 2 landmarks a type are kept (4-6 a scan, as on
    a downtown street of plain facades), and every scan below 12 keeps its scan cloud."""
    cfg = LoopDetectorConfig()
    cfg.verification.max_landmarks_per_type = 2
    cfg.verification.scan_cloud_below = 12
    for k, v in update.items():
        setattr(cfg.verification, k, v)
    return cfg


@pytest.fixture(scope="module")
def poor_db(shared_data):
    kitti, court = shared_data / "kitti00_first6", shared_data / "balm_courtyard"
    if not court.is_dir():
        pytest.skip(f"no courtyard scans under {court}")
    k, c = KittiFolder(kitti), KittiFolder(court)
    det = LoopDetector(_poor_config(scans_min_confidence=0.9, scans_min_agreeing=2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for t, scan in enumerate((k[0], k[5], c[10])):
            det.add(scan.points, timestamp=100.0 * t)  # far apart in time: no query sees a candidate
    return det, k


def test_scan_cloud_round_trips_on_its_grid(tmp_path, poor_db):
    """The stored scan cloud: <= scan_max_points points, one per 0.6 m voxel up to the grid's
    2.5 cm, decoded bit for bit again, and saved / loaded beside the landmark table."""
    det, _ = poor_db
    v = det.config.matcher.verification
    scan = det.db.extra["scan"][0]
    assert scan is not None and 10 <= len(scan) <= v.scan_max_points
    assert np.array_equal(decode_points(encode_points(scan)), scan)  # on the storage grid already
    assert np.allclose(scan / POINT_QUANTUM_M, np.round(scan / POINT_QUANTUM_M), atol=1e-3)
    keys = np.floor(scan / v.scan_voxel + 1e-6).astype(np.int64)
    assert len(np.unique(keys, axis=0)) >= 0.97 * len(scan)  # ~one point a voxel (grid moves a few)
    save_landmarks(tmp_path / "a.npz", det.db.landmarks[0], scan)
    assert np.array_equal(load_scan_cloud(tmp_path / "a.npz"), scan)
    assert load_landmarks(tmp_path / "a.npz").approx_equal(det.db.landmarks[0], atol=1e-5)
    save_landmarks(tmp_path / "b.npz", det.db.landmarks[0])
    assert load_scan_cloud(tmp_path / "b.npz") is None


def test_database_bytes_count_the_scan_cloud(poor_db):
    """A whole KITTI scan's cloud (2,000 points at 5 cm) costs < 10.5 kB with its table,
    points and descriptor; without clouds the same maps cost < 5 kB (the evidence points)."""
    det, _ = poor_db
    sizes = det.db.stored_bytes()
    assert len(sizes) == 3 and sizes.max() < 10_500 and det.db.bytes_per_scan() == pytest.approx(sizes.mean())
    bare = LandmarkDatabase()
    for ls, d in zip(det.db.landmarks, det.db.descriptors, strict=True):
        bare.add(ls, d, 0.0)
    assert bare.stored_bytes().max() < 5000 and (sizes - bare.stored_bytes()).min() > 3000
    off = LoopDetector(_poor_config(scan_cloud_below=0))
    assert off.stored_scan(det.db.landmarks[0], det.db.extra["scan"][0]) is None


def test_landmark_poor_pair_verified_through_the_stored_clouds(poor_db):
    """KITTI 0 <- 5 (4.3 m) with 4 landmarks a scan: the landmark rule cannot accept it (<= 1
    agreeing landmark); the scan pass on the stored clouds is valid and recovers the pose of the
    whole landmark maps' verified match within 0.5 deg / 20 cm (measured 0.15 deg / 7 cm; the
    official pose is itself ~0.7 m off these scans). A courtyard scan against KITTI: no loop."""
    det, k = poor_db
    (a, b, c), (sa, sb, sc) = det.db.landmarks, det.db.extra["scan"]
    assert max(len(a), len(b)) <= 6
    v = verify_candidate(b, a, det.matcher, det.config.verification, sb, sa)
    assert v["on_scans"] and v["scan_valid"] and v["scan_confidence"] >= 0.9, v
    assert v["confidence"] == pytest.approx(v["scan_confidence"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sm = ScanMatcher()
        full = sm.match(sm.extract(k[5].points), sm.extract(k[0].points))
    assert full.valid
    rot, tr = transform_errors(v["T_match_query"], full.T_target_source)
    assert rot < 0.5 and tr < 0.2, (rot, tr)
    no_clouds = verify_candidate(b, a, det.matcher, det.config.verification)
    assert no_clouds["confidence"] < 0.5 and "scan_valid" not in no_clouds  # the landmark rule alone
    neg = verify_candidate(c, a, det.matcher, det.config.verification, sc, sa)
    assert neg["confidence"] == 0.0 and not neg.get("on_scans")


def test_scan_pass_conflict_bar(poor_db):
    """``scans_max_conflict`` is the scan pass's own free-space bar: KITTI 0 <- 5 on the stored clouds reports its
    conflict (a few % on this right pose) and stays valid with the same pose at a bar above it; a bar below it
    makes the verdict invalid with a message naming the bar, the pose and conflict unchanged; None is the
    matcher's raw-scan bar (the matcher itself)."""
    from graffmatch.loops.verify import _scan_pass_matcher, scan_pass

    det, _ = poor_db
    (a, b, _c), (sa, sb, _sc) = det.db.landmarks, det.db.extra["scan"]
    v = det.config.verification
    assert _scan_pass_matcher(det.matcher, None) is det.matcher
    assert _scan_pass_matcher(det.matcher, 0.12).config.verification.scans.max_conflict == 0.12
    base = scan_pass(b, a, sb, sa, det.matcher, v.model_copy(update={"scans_max_conflict": None}))
    conflict = base["scan_conflict"]
    assert base["scan_valid"] and 0.0 < conflict < det.matcher.config.matcher.verification.scans.max_conflict
    above = scan_pass(b, a, sb, sa, det.matcher, v.model_copy(update={"scans_max_conflict": min(1.0, 2 * conflict)}))
    assert above["scan_valid"] and np.allclose(above["scan_T"], base["scan_T"], atol=1e-9)
    below = scan_pass(b, a, sb, sa, det.matcher, v.model_copy(update={"scans_max_conflict": conflict / 2}))
    assert not below["scan_valid"] and f"(> {conflict / 2:.0%})" in below["scan_message"], below["scan_message"]
    assert below["scan_conflict"] == pytest.approx(conflict, abs=1e-12)


def test_scans_loop_confidence_rule():
    """A scan-verified pair is a loop only when valid, confident, with enough agreeing landmarks
    and inside the place radius less the margin; its confidence is the scan verdict's."""
    cfg = VerificationConfig(max_translation_m=5.0, scans_min_confidence=0.9, scans_min_agreeing=2)
    assert scans_loop_confidence(True, 0.95, 2, 3.0, cfg) == pytest.approx(0.95)
    assert scans_loop_confidence(False, 0.95, 2, 3.0, cfg) == 0.0
    assert scans_loop_confidence(True, 0.85, 2, 3.0, cfg) == 0.0
    assert scans_loop_confidence(True, None, 2, 3.0, cfg) == 0.0
    assert scans_loop_confidence(True, 0.95, 1, 3.0, cfg) == 0.0
    assert scans_loop_confidence(True, 0.95, 2, 4.8, cfg) == 0.0  # beyond 5 m - 0.25 m
    assert scans_loop_confidence(True, 0.95, 2, 40.0, cfg.model_copy(update={"max_translation_m": None})) > 0


def test_defaults_are_the_calibrated_scan_rule():
    """Session 15's choice on the calibration drives (bench/loops_calibration_scans.py): clouds for
    scans with < 8 landmarks, scan verdicts from confidence 0.99 with 3 agreeing landmarks; session
    16's (bench/loops_calibration_points15b.py --grid 16): cloud pairs the quick check rejects are
    verified only behind the first screen (contrast 2.5, at most 2 a query since session 16b; point-won verdicts with 0
    agreeing landmarks), passing candidates beyond the radius last, point hypotheses in the loop
    matcher only. (ScanMatcher's own default, raw scans after the support points on whole views, is
    the verification bench's.)"""
    from graffmatch.loops import LoopDetectorConfig
    from graffmatch.matcher import GraffMatchConfig
    from graffmatch.pipeline import ScanMatcherConfig

    v = VerificationConfig()
    assert (v.scan_cloud_below, v.scans_min_confidence, v.scans_min_agreeing, v.scans_skip_quick_check) == (
        8, 0.99, 3, True)
    assert (v.scans_screen_min_ratio, v.scans_skip_max, v.scans_points_min_agreeing, v.quick_order_radius) == (
        2.5, 2, 0, True)
    assert v.quick_order_odometry  # session 16b
    assert v.scans_max_conflict == 0.12  # session 17
    assert (v.local_map_frames, v.local_map_below, v.local_map_on_points_only) == (5, 6, True)  # session 19
    assert LoopDetectorConfig().matcher.verification.point_hypotheses
    assert not GraffMatchConfig().verification.point_hypotheses
    assert ScanMatcherConfig().evidence == "support_then_scans"
