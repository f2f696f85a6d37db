"""Hypotheses from the points for landmark-poor pairs (session 15b): with two landmarks a scan the
graph gives the matcher < 3 associations, so no landmark hypothesis reaches the raw-scan evidence;
``VerificationConfig.point_hypotheses`` (the matcher's, off by default) adds a yaw sweep with
translation votes on the scan clouds (``verification.verify._point_hypotheses``)."""

from __future__ import annotations

import numpy as np

from graffmatch.geometry.transforms import transform_errors
from graffmatch.loops.verify import scan_pass
from tests.loops.conftest import _detector


def test_point_hypotheses_recover_a_two_landmark_pair(two_landmark_pair):
    """KITTI 5 -> 0 with two landmarks a scan: without point hypotheses the scan pass has nothing
    to verify (invalid); with them it is valid, its winner from the points, within 0.5 deg / 20 cm
    of the whole scans' verified match (measured 0.16 deg / 7 cm; off: "only 2 associations", degenerate)."""
    (a, b, _), (sa, sb, _), T_full = two_landmark_pair
    cfg = _detector(True).config.verification
    off = scan_pass(b, a, sb, sa, _detector(False).matcher, cfg)
    assert not off["scan_valid"], off
    on = scan_pass(b, a, sb, sa, _detector(True).matcher, cfg)
    assert on["scan_valid"] and on["scan_origin"] == "points" and on["scan_confidence"] >= 0.99, on
    rot, tr = transform_errors(on["scan_T"], T_full)
    assert rot < 0.5 and tr < 0.2, (rot, tr)


def test_point_hypotheses_no_loop_across_places_and_deterministic(two_landmark_pair):
    """A courtyard scan against KITTI stays invalid with point hypotheses; the same pair twice
    gives the same transform bit for bit."""
    (a, b, c), (sa, sb, sc), _ = two_landmark_pair
    det = _detector(True)
    neg = scan_pass(c, a, sc, sa, det.matcher, det.config.verification)
    assert not neg["scan_valid"], neg
    one = scan_pass(b, a, sb, sa, det.matcher, det.config.verification)
    two = scan_pass(b, a, sb, sa, _detector(True).matcher, det.config.verification)
    assert np.array_equal(one["scan_T"], two["scan_T"]) and one["scan_confidence"] == two["scan_confidence"]
