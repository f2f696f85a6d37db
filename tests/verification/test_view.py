"""Partial views (``verification/view.py``, ``view.check_view``): a scan's azimuth coverage,
the co-visible overlap, and the stricter decision for pairs where one scan sees only a sector
(docs/verification.md, Session 15). Courtyard tests skip without ../shared/data."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from graffmatch.datasets.folder import KittiFolder
from graffmatch.geometry.transforms import invert, transform_errors
from graffmatch.pipeline import ScanMatcher, ScanMatcherConfig
from graffmatch.verification.config import VerificationConfig
from graffmatch.verification.evidence import SupportCloud, point_overlap
from graffmatch.verification.free_space import cell_minimum_ranges
from graffmatch.verification.view import azimuth_mask, coverage, covisible_overlap


def _ring(n: int = 20000, seed: int = 0) -> np.ndarray:
    """Points on a cylinder of radius 10-30 m around the sensor, all azimuths."""
    rng = np.random.default_rng(seed)
    a, r, z = rng.uniform(-np.pi, np.pi, n), rng.uniform(10, 30, n), rng.uniform(-1.5, 3.0, n)
    return np.c_[r * np.cos(a), r * np.sin(a), z]


def _sector(X: np.ndarray, a0_deg: float, width_deg: float) -> np.ndarray:
    return X[(np.degrees(np.arctan2(X[:, 1], X[:, 0])) - a0_deg) % 360.0 < width_deg]


def test_coverage_of_whole_and_cropped_scans() -> None:
    """Whole scan: 1.0; a 90 deg sector 0.25 and a 200 deg one 0.556, to one 1 deg cell per edge;
    no image: 1.0 (unknown, no check)."""
    X = _ring()
    assert coverage(azimuth_mask(cell_minimum_ranges(X))) == 1.0
    for a0, w in ((-180.0, 90.0), (37.3, 90.0), (100.0, 200.0)):
        c = coverage(azimuth_mask(cell_minimum_ranges(_sector(X, a0, w))))
        assert abs(c - w / 360.0) <= 2 / 360.0, (a0, w, c)
    assert coverage(None) == 1.0 and azimuth_mask(None) is None


def test_covisible_overlap_is_the_overlap_on_whole_views_and_undiluted_on_sectors() -> None:
    """With both masks all True the co-visible overlap is ``point_overlap`` exactly; with the
    source cut to 90 deg at the true pose (identity), its target direction counts only the
    target's points in that sector: ~1 instead of ~0.25."""
    X = _ring(4000)
    Y = X + np.random.default_rng(1).normal(0, 0.02, X.shape)
    S, T = SupportCloud(X, sensor_pose=np.eye(4)), SupportCloud(Y, sensor_pose=np.eye(4))
    full = np.ones(360, bool)
    p0, p1, n0, n1 = covisible_overlap(S, T, np.eye(4), 0.3, full, full)
    assert (p0, p1) == point_overlap(S, T, np.eye(4), 0.3) and (n0, n1) == (len(X), len(Y))
    Xs = _sector(X, 0.0, 90.0)
    Ss = SupportCloud(Xs, sensor_pose=np.eye(4))
    ms = azimuth_mask(cell_minimum_ranges(Xs))
    q0, q1 = point_overlap(Ss, T, np.eye(4), 0.3)
    c0, c1, m0, m1 = covisible_overlap(Ss, T, np.eye(4), 0.3, ms, full)
    assert q0 > 0.95 and q1 < 0.3 and c0 == q0 and c1 > 0.95 and m0 == len(Xs)
    assert abs(m1 / len(Y) - 0.25) < 0.03


def test_whole_scan_defaults_are_unchanged() -> None:
    """The partial-view thresholds apply below view_whole only and are at least as strict as the
    whole-scan ones for both evidences (support points, partial / narrow: co-visible overlap
    0.325 / 0.275, rival 0.85 / 0.45; raw scans 0.175 / 0.175, 0.75 / 0.775)."""
    cfg = VerificationConfig()
    assert cfg.view_check and (cfg.view_whole, cfg.view_narrow) == (0.9, 0.5)
    for c in (cfg, cfg.for_evidence(["plane", "line"], "scans")):
        for o, q in ((c.partial_min_overlap, c.partial_max_rival_ratio), (c.narrow_min_overlap, c.narrow_max_rival_ratio)):
            assert o > c.min_overlap and q <= c.max_rival_ratio
    sc = cfg.for_evidence(["plane"], "scans")
    assert (sc.partial_min_overlap, sc.narrow_min_overlap, sc.partial_max_rival_ratio) == (0.175, 0.175, 0.75)
    assert (cfg.partial_min_overlap, cfg.narrow_min_overlap, cfg.narrow_max_rival_ratio) == (0.325, 0.275, 0.45)


@pytest.fixture(scope="module")
def court(shared_data):
    path = shared_data / "balm_courtyard"
    if not path.is_dir():
        pytest.skip(f"no courtyard scans under {path}")
    return KittiFolder(path)


def _yaw(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def _opened(evidence: str) -> ScanMatcherConfig:
    """Today's decision with the partial-view thresholds open (what session 14 shipped)."""
    cfg = ScanMatcherConfig(evidence=evidence)
    vc = cfg.matcher.verification
    opened = {"partial_min_overlap": 0.0, "partial_max_rival_ratio": 1.0, "narrow_min_overlap": 0.0,
              "narrow_max_rival_ratio": 1.0}
    vc = vc.model_copy(update={**opened, "scans": vc.scans.model_copy(update=opened)})  # type: ignore[union-attr]
    return cfg.model_copy(update={"matcher": cfg.matcher.model_copy(update={"verification": vc})})


#: calibration pairs of bench/verification_partial_views.py --split cal (seed 1501) whose support
#: points gave a wrong valid answer with the whole-scan thresholds: (source, target, sector start
#: [rad], sector width [deg], yaw [rad], tier)
WRONG_BEFORE = [
    (17, 26, 0.8507947251321117, 153.72081916217104, -1.5233234116346646, "narrow"),  # slid 5.9 m
    (19, 35, 1.8192945898655681, 185.71398886264015, -0.1270058835977319, "partial"),  # turned 89 deg
]


@pytest.mark.parametrize("case", WRONG_BEFORE, ids=["slide-154deg", "turn-186deg"])
def test_cropped_courtyard_pair_wrong_before_is_invalid_now(court, case) -> None:
    """A cropped courtyard pair that the whole-scan thresholds accepted with a wrong transform
    (metres or 90 deg off) is invalid now, and the message names the view; the view coverage is
    the sector's share (to 0.02) and the whole target's ~1."""
    i, j, a0, width, y, tier = case
    X = court[i].points[:, :3]
    X = X[(np.arctan2(X[:, 1], X[:, 0]) - a0) % (2 * np.pi) < np.radians(width)] @ _yaw(y)[:3, :3].T
    T_true = invert(court.poses[j]) @ court.poses[i] @ invert(_yaw(y))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        before = ScanMatcher(_opened("support")).register(X, court[j].points)
        now = ScanMatcher(ScanMatcherConfig(evidence="support")).register(X, court[j].points)
    rot, tr = transform_errors(before.T_target_source, T_true)
    assert before.valid and (rot > 5.0 or tr > 1.0), (before.message, rot, tr)
    assert not now.valid and f"{tier} view: coverage" in now.message, now.message
    c_s, c_t = now.info["view_coverage"]
    assert abs(c_s - width / 360.0) < 0.02 and c_t > 0.95


def test_whole_courtyard_pair_unchanged_and_deterministic(court) -> None:
    """Whole scans (coverage ~1): the view check records the coverage and decides nothing; two
    runs give the same transform, confidence and message."""
    sm = ScanMatcher(ScanMatcherConfig(evidence="support"))
    a = sm.register(court[44].points, court[80].points)
    b = ScanMatcher(_opened("support")).register(court[44].points, court[80].points)
    c = sm.register(court[44].points, court[80].points)
    assert a.valid and min(a.info["view_coverage"]) > 0.95 and "covisible_overlap" not in a.info
    assert np.array_equal(a.T_target_source, b.T_target_source) and a.confidence == b.confidence
    assert np.array_equal(a.T_target_source, c.T_target_source) and a.message == c.message == "ok"


def test_view_unknown_for_non_ground_images() -> None:
    """``Evidence.view`` False (the loops' scan pass, whose range images are built from non-ground
    clouds: an open road leaves azimuth sectors empty) skips the check; True on a 90 deg sector
    records the coverage and applies the narrow tier."""
    from graffmatch.verification.decision import Hypothesis, Verdict
    from graffmatch.verification.verify import Evidence
    from graffmatch.verification.view import check_view

    X = _ring(4000)
    Xs = _sector(X, 0.0, 90.0)
    S = SupportCloud(Xs, sensor_pose=np.eye(4), scan_ranges=cell_minimum_ranges(Xs))
    T = SupportCloud(X, sensor_pose=np.eye(4), scan_ranges=cell_minimum_ranges(X))
    cfg = VerificationConfig()
    for view in (False, True):
        h = Hypothesis(np.eye(4), np.zeros((3, 2), np.int64), "test", 1.0, 1.0, False)
        v = Verdict(h, None, True, 0.9, 1.0, 0.0, [])
        check_view(v, Evidence(S, T, view=view), cfg)
        assert v.valid and v.problems == []
        if view:
            assert abs(h.info["view_coverage"][0] - 0.25) < 0.01 and h.info["covisible_overlap"][1] == 1.0
        else:
            assert "view_coverage" not in h.info
