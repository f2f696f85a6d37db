"""A settled leader skips the voted translations and the local search on whole views
(``VerificationConfig.settled_overlap``; docs/performance.md, Session 15): on real KITTI pairs the
searches are skipped and the answer is the same; a leader with a close rival is not settled, nor
is a cropped view."""

from __future__ import annotations

import numpy as np
import pytest

import graffmatch.verification.verify as verify
from graffmatch.datasets.folder import KittiFolder
from graffmatch.lidar.extractor import LandmarkExtractor
from graffmatch.matcher import GraffMatchConfig, GraffMatcher
from graffmatch.verification.config import VerificationConfig
from graffmatch.verification.decision import Hypothesis, is_settled


@pytest.fixture(scope="module")
def kitti_sets(shared_data):
    root = shared_data / "kitti00_first6"
    if not root.is_dir():
        pytest.skip(f"no KITTI scans under {root}")
    ds = KittiFolder(root)
    ex = LandmarkExtractor()
    return [ex.extract(ds[i].points) for i in (0, 2, 5)]


def _counting(monkeypatch) -> dict:
    calls = {"local_search": 0, "votes": 0}
    ls, tv = verify._local_search, verify._translation_votes

    def local_search(*a, **k):
        calls["local_search"] += 1
        return ls(*a, **k)

    def votes(*a, **k):
        calls["votes"] += 1
        return tv(*a, **k)

    monkeypatch.setattr(verify, "_local_search", local_search)
    monkeypatch.setattr(verify, "_translation_votes", votes)
    return calls


def test_settled_kitti_pairs_skip_the_searches_with_the_same_answer(kitti_sets, monkeypatch) -> None:
    calls = _counting(monkeypatch)
    full = GraffMatcher(GraffMatchConfig(verification=VerificationConfig(settled_overlap=None)))
    fast = GraffMatcher()  # the default: settled at 0.4 / 0.6 on whole views
    assert (VerificationConfig().settled_overlap, VerificationConfig().settled_rival_ratio) == (0.4, 0.6)
    for s, t in ((2, 0), (1, 0), (2, 1)):
        a = full.match(kitti_sets[s], kitti_sets[t])
        before = dict(calls)
        b = fast.match(kitti_sets[s], kitti_sets[t])
        assert before["local_search"] >= 1 and before["votes"] >= 1  # the full matcher searched
        assert calls == before, (s, t, calls, before)  # the settled one did not
        assert a.valid and b.valid
        assert np.array_equal(a.T_target_source, b.T_target_source)
        calls["local_search"] = calls["votes"] = 0


def test_a_close_rival_is_not_settled() -> None:
    cfg = VerificationConfig(settled_overlap=0.3, settled_rival_ratio=0.5)
    T = np.eye(4)
    far = np.eye(4)
    far[:3, 3] = (5.0, 0.0, 0.0)  # 5 m away: a distinct rival
    lead = Hypothesis(T, np.zeros((3, 2), np.int64), "clipper", 1.0, 1.0, False)
    lead.score = 0.6
    rival = Hypothesis(far, np.zeros((3, 2), np.int64), "greedy", 1.0, 1.0, False)
    for rival_score, settled in ((0.29, True), (0.31, False)):
        rival.score = rival_score
        assert is_settled([lead, rival], lead, cfg) is settled
    lead.score = 0.29  # below settled_overlap
    rival.score = 0.0
    assert not is_settled([lead, rival], lead, cfg)
    assert not is_settled([lead, rival], lead, VerificationConfig(settled_overlap=None))  # None: off


def test_a_cropped_view_is_not_settled(shared_data, monkeypatch) -> None:
    """KITTI 1 -> 0 with the source cut to a 120 deg sector (coverage ~0.33): its leader would be
    settled (with the gate opened, view_whole 0, neither search runs) but the whole-view gate keeps
    both searches, because on cropped calibration views the settled path let wrong answers through."""
    root = shared_data / "kitti00_first6"
    if not root.is_dir():
        pytest.skip(f"no KITTI scans under {root}")
    ds = KittiFolder(root)
    P = ds[1].points
    az = np.degrees(np.arctan2(P[:, 1], P[:, 0]))
    ex = LandmarkExtractor()
    src, tgt = ex.extract(P[(az > -60.0) & (az < 60.0)]), ex.extract(ds[0].points)
    calls = _counting(monkeypatch)
    GraffMatcher(GraffMatchConfig(verification=VerificationConfig(view_whole=0.0))).match(src, tgt)
    assert calls == {"local_search": 0, "votes": 0}, calls  # settled when the crop counts as whole
    GraffMatcher().match(src, tgt)
    assert calls["local_search"] >= 1 and calls["votes"] >= 1, calls
