"""``valid`` needs a calibrated confidence of at least ``min_valid_confidence`` (0.5): real courtyard pairs across
the walk's two halves that the thresholds alone returned valid and turned by 180 deg (docs/verification.md,
sessions 20-21). Skips without ../shared/data."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from graffmatch.datasets.folder import KittiFolder
from graffmatch.geometry.transforms import transform_errors
from graffmatch.matcher import GraffMatchConfig, GraffMatcher
from graffmatch.pipeline import ScanMatcher
from graffmatch.verification.decision import Hypothesis, Verdict, low_confidence_problem


def _extracted(ds: KittiFolder, scans: tuple[int, ...]) -> dict:
    """The scans' landmarks with support points, as ``ScanMatcher`` extracts them."""
    sm = ScanMatcher()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return {i: sm.extract(ds[i].points) for i in scans}


@pytest.fixture(scope="module")
def courtyard(shared_data):
    if not (shared_data / "balm_courtyard").is_dir():
        pytest.skip(f"no courtyard scans under {shared_data / 'balm_courtyard'}")
    ds = KittiFolder(shared_data / "balm_courtyard")
    return _extracted(ds, (3, 30, 46, 81)), np.asarray(ds.poses)


def _matcher(floor: float | None = None) -> GraffMatcher:
    cfg = GraffMatchConfig()
    if floor is not None:
        cfg = cfg.model_copy(update={"verification": cfg.verification.model_copy(update={"min_valid_confidence": floor})})
    return GraffMatcher(cfg)


def _errors(res, P: np.ndarray, q: int, m: int) -> tuple[float, float]:
    return transform_errors(res.T_target_source, np.linalg.solve(P[m], P[q]))


def test_default_floor_is_half() -> None:
    assert GraffMatchConfig().verification.min_valid_confidence == 0.5


def test_low_confidence_flip_searched_again_and_right(courtyard) -> None:
    """81 -> 30: without the floor, valid at confidence 0.40 and turned 180 deg (15 m off); with it, the first
    pass is invalid, the wide search runs and returns the right pose (within 1 deg / 0.3 m) at confidence > 0.9."""
    sets, P = courtyard
    off = _matcher(0.0).match(sets[81], sets[30])
    assert off.valid and off.confidence < 0.5
    assert _errors(off, P, 81, 30)[0] > 170  # the flip the floor exists for
    res = _matcher().match(sets[81], sets[30])
    assert res.valid, res.message
    rot, tr = _errors(res, P, 81, 30)
    assert rot < 1.0 and tr < 0.3, (rot, tr)
    assert res.confidence > 0.9


def test_low_confidence_flip_refused_with_its_rival(courtyard) -> None:
    """46 -> 3: valid at confidence 0.13 and turned 178 deg without the floor; with it, not valid, and the
    message gives the confidence and names the rival."""
    sets, P = courtyard
    off = _matcher(0.0).match(sets[46], sets[3])
    assert off.valid and _errors(off, P, 46, 3)[0] > 170
    res = _matcher().match(sets[46], sets[3])
    assert not res.valid
    assert "low confidence" in res.message and "< 0.50" in res.message and "alternative" in res.message
    assert res.confidence < 0.5


def test_low_confidence_problem_message() -> None:
    best = Hypothesis(np.eye(4), np.zeros((0, 2), np.int64), "greedy", 1.0, 1.0, False, score=0.2)
    rival = Hypothesis(np.diag([-1.0, -1.0, 1.0, 1.0]), np.zeros((0, 2), np.int64), "clipper", 1.0, 1.0, False, score=0.15)
    msg = low_confidence_problem(Verdict(best, rival, True, 0.31, 0.25, 0.75, []), 0.5)
    assert msg.startswith("low confidence: 0.31 < 0.50 (overlap 0.20; a 180 deg / 0.0 m alternative (clipper)")
    assert "no distinct rival" in low_confidence_problem(Verdict(best, None, True, 0.2, 1.0, 0.0, []), 0.5)
