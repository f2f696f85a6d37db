"""Sequence consistency of weak point-verified loops (loops/consistency.py): a weak loop that a
neighbouring query's loop confirms through a drifting odometry is accepted, a wrong one is not."""

from __future__ import annotations

import numpy as np
import pytest

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.transforms import invert
from graffmatch.loops.consistency import (
    apply_sequence_consistency,
    loop_pair_residual,
    refused_by_odometry,
)
from graffmatch.loops.verify import VerificationConfig


def _rz(yaw: float, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T[:3, 3] = t
    return T


def _drive() -> tuple[np.ndarray, np.ndarray]:
    """Ground truth: 60 scans 1 m apart east, a U-turn, back west 1.5 m to the side (scans
    60-119 pass scans 59-0 again, reverse direction); odometry: the same with a heading drift
    of 0.03 deg a scan (3 deg / 100 m, as the benchmark's drift) and 1 % scale."""
    gt, odo = [], []
    for i in range(120):
        if i < 60:
            gt.append(_rz(0.0, (float(i), 0.0, 0.0)))
        else:
            gt.append(_rz(np.pi, (float(119 - i), 1.5, 0.0)))
    gt = np.array(gt)
    pose = gt[0].copy()
    odo.append(pose.copy())
    for i in range(1, 120):
        step = invert(gt[i - 1]) @ gt[i]
        step[:3, 3] *= 1.01
        pose = pose @ _rz(np.radians(0.03)) @ step
        odo.append(pose.copy())
    return gt, np.array(odo)


def _cand(match: int, T: np.ndarray, n_agreeing: int, rank: int = 0, on_points: bool = True,
          confidence: float = 0.0, overlap: float = 0.8) -> dict:
    return {"match": match, "rank": rank, "T": T.ravel().tolist(), "confidence": confidence, "overlap": overlap,
            "n_agreeing": n_agreeing, "matcher_valid": True, "matcher_confidence": 0.95, "on_points": on_points,
            "verified": True, "n_associations": 5, "retrieval_distance": 0.1}


def _config(**kw) -> VerificationConfig:
    base = {"consistency_window": 2, "consistency_min_agreeing": 4, "consistency_max_m": 0.5,
            "consistency_max_deg": 2.0, "max_translation_m": 5.0}
    return VerificationConfig(**{**base, **kw})


def test_residual_of_consistent_and_wrong_loops_through_drifting_odometry() -> None:
    gt, odo = _drive()
    true = {q: invert(gt[119 - q]) @ gt[q] for q in range(60, 120)}  # q passes 119 - q, 1.5 m aside
    # two right loops two frames apart: the drifted odometry's short segments agree to centimetres
    dt, dr = loop_pair_residual(odo, 80, 39, true[80], 82, 37, true[82])
    assert dt < 0.05 and dr < 0.15  # 4 steps of 0.03 deg drift
    # a loop slid 3 m along the street (the classic aliasing of plain facades) against a right one
    slid = true[80]  # the pose relative to scan 39, reported as a loop to scan 36
    dt, dr = loop_pair_residual(odo, 80, 36, slid, 82, 37, true[82])
    assert dt > 2.9
    # the residual does not depend on the odometry's accumulated drift: ground truth gives the same
    dt_gt, _ = loop_pair_residual(gt, 80, 36, slid, 82, 37, true[82])
    assert abs(dt - dt_gt) < 0.05


def test_weak_loop_confirmed_by_neighbour_and_wrong_one_rejected() -> None:
    gt, odo = _drive()
    T = {q: invert(gt[119 - q]) @ gt[q] for q in range(60, 120)}
    cfg = _config()
    recs = {
        79: {"query": 79, "candidates": [_cand(40, T[79], 9, confidence=0.85, on_points=False)]},  # strong
        80: {"query": 80, "candidates": [_cand(39, T[80], 4)]},  # weak, right: consistent with 79 and 81
        81: {"query": 81, "candidates": [_cand(38, T[81], 4)]},  # weak, right
        # weak and wrong: scan 16 taken for scan 19, its true partner (aliasing 3 m along the street;
        # estimated 1.5 m apart, inside the place radius)
        100: {"query": 100, "candidates": [_cand(16, T[100], 4)]},
        101: {"query": 101, "candidates": [_cand(18, T[101], 9, confidence=0.8, on_points=False)]},
        # weak and right, but alone: no neighbouring loop within the window
        110: {"query": 110, "candidates": [_cand(9, T[110], 5)]},
        # weak with 3 agreeing landmarks: below consistency_min_agreeing, never a loop
        60: {"query": 60, "candidates": [_cand(59, T[60], 3)]},
        61: {"query": 61, "candidates": [_cand(58, T[61], 4)]},
        62: {"query": 62, "candidates": [_cand(57, T[62], 4)]},
    }
    out = apply_sequence_consistency(recs, odo, cfg)
    conf = {q: out[q]["candidates"][0]["confidence"] for q in out}
    assert conf[80] >= 0.5 and conf[81] >= 0.5
    assert out[80]["candidates"][0]["consistent_with"] in ([79, 40], [81, 38])
    assert conf[100] == 0.0 and "consistent_with" not in out[100]["candidates"][0]
    assert conf[110] == 0.0
    assert conf[60] == 0.0
    assert conf[61] >= 0.5 and conf[62] >= 0.5  # two weak right loops confirm each other
    # the strong loops are untouched, and the input records were not modified
    assert conf[79] == 0.85 and recs[80]["candidates"][0]["confidence"] == 0.0
    # the weak confidence is the usual one: sqrt(agreement * matcher confidence) = sqrt(0.8 * 0.95)
    assert conf[80] == pytest.approx(np.sqrt(0.8 * 0.95))


def test_consistency_off_without_odometry_or_window_and_stricter_tolerance() -> None:
    gt, odo = _drive()
    T = {q: invert(gt[119 - q]) @ gt[q] for q in range(60, 120)}
    recs = {80: {"query": 80, "candidates": [_cand(39, T[80], 4)]},
            81: {"query": 81, "candidates": [_cand(38, T[81], 4)]}}
    assert apply_sequence_consistency(recs, None, _config()) is recs
    assert apply_sequence_consistency(recs, odo, _config(consistency_window=0)) is recs
    # the odometry's heading drift over the two 1-frame segments (0.06 deg): a 0.01 deg tolerance rejects
    assert loop_pair_residual(odo, 80, 39, T[80], 81, 38, T[81])[1] == pytest.approx(0.06, abs=0.005)
    tight = apply_sequence_consistency(recs, odo, _config(consistency_max_deg=0.01))
    assert tight[80]["candidates"][0]["confidence"] == 0.0
    # beyond the place radius less the margin: not a loop however consistent
    far = {q: {"query": q, "candidates": [_cand(m, _rz(0.0, (4.9, 0.0, 0.0)) @ T[q], 4)]}
           for q, m in ((80, 39), (81, 38))}
    assert apply_sequence_consistency(far, odo, _config())[80]["candidates"][0]["confidence"] == 0.0


def test_bad_odometry_names_the_argument() -> None:
    _, odo = _drive()
    recs = {80: {"query": 80, "candidates": [_cand(39, np.eye(4), 4)]}}
    with pytest.raises(InvalidInputError, match="odometry"):
        apply_sequence_consistency(recs, odo[:, :3, :], _config())
    with pytest.raises(InvalidInputError, match="odometry"):
        apply_sequence_consistency(recs, odo[:50], _config())


def test_online_detector_confirms_from_earlier_queries_only() -> None:
    from graffmatch.loops.detector import LoopDetector, LoopDetectorConfig

    gt, odo = _drive()
    T = {q: invert(gt[119 - q]) @ gt[q] for q in range(60, 120)}
    cfg = LoopDetectorConfig()
    cfg.verification = _config()
    det = LoopDetector(cfg)
    det._poses = list(odo)
    # query 80: weak, no earlier loop yet -> rejected online; query 81: weak, 80's weak loop agrees
    first = det._consistent(80, [_cand(39, T[80], 4)])
    second = det._consistent(81, [_cand(38, T[81], 4)])
    assert first[0]["confidence"] == 0.0
    assert second[0]["confidence"] >= 0.5 and second[0]["consistent_with"] == [80, 39]
    # the window forgets: query 90 (9 frames later) finds no partner
    assert det._consistent(90, [_cand(29, T[90], 4)])[0]["confidence"] == 0.0
    assert set(det._recent) == {90}


def test_a_loop_its_query_s_other_loops_outvote_is_dropped_ties_and_single_loops_are_kept() -> None:
    """Every candidate verified (--all-loops): query 110 has right loops to scans 9, 10 and 11 (through the drifting
    odometry) and one to scan 50 that claims the same relative pose as its loop to 10, 40 m away: it is outvoted 3 to
    0 (confidence 0, ``outvoted_by`` the three matches); the right ones stay. Two loops that disagree (a tie), one
    loop a query, or no odometry change nothing."""
    from graffmatch.loops.consistency import drop_outvoted_loops

    gt, odo = _drive()
    q = 110
    right = {m: invert(gt[m]) @ gt[q] for m in (9, 10, 11)}
    cands = [_cand(m, T, 8, rank=k, confidence=0.8) for k, (m, T) in enumerate(right.items())]
    cands.append(_cand(50, right[10], 8, rank=3, confidence=0.9))
    out = drop_outvoted_loops({q: {"query": q, "candidates": cands}}, odo, 0.5)[q]["candidates"]
    assert [c["confidence"] for c in out] == [0.8, 0.8, 0.8, 0.0]
    assert sorted(out[3]["outvoted_by"]) == [9, 10, 11] and all("outvoted_by" not in c for c in out[:3])
    assert cands[3]["confidence"] == 0.9  # not modified in place
    # through apply_sequence_consistency too (the one path of loops, the detector and the benchmark)
    full = apply_sequence_consistency({q: {"query": q, "candidates": cands}}, odo, _config())[q]["candidates"]
    assert full[3]["confidence"] == 0.0
    for recs in ({q: {"query": q, "candidates": [cands[0], cands[3]]}}, {q: {"query": q, "candidates": cands[3:]}}):
        assert drop_outvoted_loops(recs, odo, 0.5) == recs
    assert drop_outvoted_loops({q: {"query": q, "candidates": cands}}, None, 0.5)[q]["candidates"] == cands
    with pytest.raises(InvalidInputError, match="odometry"):
        drop_outvoted_loops({q: {"query": q, "candidates": cands}}, odo[:20], 0.5)


def _slid(T: np.ndarray, metres: float) -> np.ndarray:
    """A loop pose that puts the query ``metres`` farther along the street than it was."""
    S = np.eye(4)
    S[0, 3] = metres
    return S @ T


@pytest.mark.parametrize("n_agreeing", [0, 4, 5])
def test_odometry_gate_refuses_weak_loops_far_from_the_odometry_and_keeps_right_ones(n_agreeing) -> None:
    """Rule v1 (docs/loops.md, session 25): a loop on fewer than min_agreeing agreeing landmarks that puts its query
    35 m from the drifting odometry's pose (the suburban-s1 slide) is refused, with the disagreement recorded; the
    same loop with 6 agreeing landmarks, a right weak loop 60 scans of drift later, and runs without odometry or with
    the gate off are untouched."""
    gt, odo = _drive()
    T = {q: invert(gt[119 - q]) @ gt[q] for q in range(60, 120)}
    cfg = _config()
    recs = {
        100: {"query": 100, "candidates": [_cand(19, _slid(T[100], 35.0), n_agreeing, confidence=0.7)]},
        101: {"query": 101, "candidates": [_cand(18, _slid(T[101], 35.0), 6, confidence=0.7, on_points=False)]},
        110: {"query": 110, "candidates": [_cand(9, T[110], n_agreeing, confidence=0.7)]},
    }
    out = apply_sequence_consistency(recs, odo, cfg)
    gated = out[100]["candidates"][0]
    assert gated["confidence"] == 0.0 and 34.0 < gated["odometry_disagrees"][0] < 36.5
    assert out[101]["candidates"][0]["confidence"] == 0.7 and "odometry_disagrees" not in out[101]["candidates"][0]
    assert out[110]["candidates"][0]["confidence"] == 0.7  # right: within 5 m + 2 % of ~100 m of 3 deg/100 m drift
    assert recs[100]["candidates"][0]["confidence"] == 0.7  # not modified in place
    assert refused_by_odometry(recs, out, cfg.min_confidence) == 1  # what run_loops' summary reports
    assert apply_sequence_consistency(recs, None, cfg)[100]["candidates"][0]["confidence"] == 0.7
    off = apply_sequence_consistency(recs, odo, _config(odometry_gate=False))
    assert off[100]["candidates"][0]["confidence"] == 0.7


def test_slid_weak_loops_of_consecutive_queries_no_longer_confirm_one_another() -> None:
    """The suburban-s1 failure: five consecutive queries slid the same 35 m along the road agree with one another
    through the odometry, so sequence consistency confirmed them all; gated, none is accepted, and a right weak loop
    beside them is still confirmed by its right neighbour."""
    gt, odo = _drive()
    T = {q: invert(gt[119 - q]) @ gt[q] for q in range(60, 120)}
    cfg = _config(max_translation_m=None)  # `graffmatch loops`' default: no place radius
    recs = {q: {"query": q, "candidates": [_cand(119 - q, _slid(T[q], 35.0), 4)]} for q in range(90, 95)}
    recs[70] = {"query": 70, "candidates": [_cand(49, T[70], 4)]}
    recs[71] = {"query": 71, "candidates": [_cand(48, T[71], 9, confidence=0.85, on_points=False)]}
    ungated = apply_sequence_consistency(recs, odo, _config(max_translation_m=None, odometry_gate=False))
    assert all(ungated[q]["candidates"][0]["confidence"] >= cfg.min_confidence for q in range(90, 95))
    out = apply_sequence_consistency(recs, odo, cfg)
    assert all(out[q]["candidates"][0]["confidence"] == 0.0 for q in range(90, 95))
    assert out[70]["candidates"][0]["confidence"] >= cfg.min_confidence
    assert out[70]["candidates"][0]["consistent_with"] == [71, 48]


def test_online_detector_gates_weak_loops_also_without_sequence_consistency() -> None:
    """`LoopDetector.add(..., pose=)` applies the same post-pass; the gate does not hang on the consistency window."""
    from graffmatch.loops import LoopDetector, LoopDetectorConfig

    gt, odo = _drive()
    T = invert(gt[19]) @ gt[100]
    cfg = LoopDetectorConfig()
    cfg.verification.consistency_window = 0
    det = LoopDetector(cfg)
    det._poses = list(odo[:101])
    slid = det._consistent(100, [_cand(19, _slid(T, 35.0), 5, confidence=0.7)])
    right = det._consistent(100, [_cand(19, T, 5, confidence=0.7)])
    assert slid[0]["confidence"] == 0.0 and slid[0]["odometry_disagrees"][0] > 34.0
    assert right[0]["confidence"] == 0.7
