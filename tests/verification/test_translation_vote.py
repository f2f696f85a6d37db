"""Translation re-estimation by voting: under the right rotation, the strongest vote peak is the
translation that lines the two clouds up, whatever metres the start was off."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from graffmatch.geometry.transforms import make_transform, rot_z
from graffmatch.verification.config import VerificationConfig
from graffmatch.verification.decision import Hypothesis
from graffmatch.verification.evidence import cloud_from_points
from graffmatch.verification.translation_vote import vote_translations
from graffmatch.verification.verify import Evidence, _translation_votes


def _street(rng: np.random.Generator, n: int = 300) -> np.ndarray:
    """Walls, poles and a car-sized box: structure at different heights, no ground."""
    walls = np.c_[rng.uniform(-30, 30, n), rng.choice([-8.0, 9.0], n), rng.uniform(0.5, 6, n)]
    walls[: n // 4, :2] = np.c_[rng.choice([-20.0, 25.0], n // 4), rng.uniform(-8, 9, n // 4)]  # cross streets
    poles = np.c_[np.repeat(rng.uniform(-25, 25, 8), 10), np.repeat(rng.uniform(-6, 6, 8), 10),
                  np.tile(np.linspace(0.3, 4, 10), 8)]
    return np.r_[walls, poles]


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), dx=st.floats(-9, 9), dy=st.floats(-9, 9), yaw=st.floats(-np.pi, np.pi))
def test_top_peak_recovers_the_translation(seed, dx, dy, yaw):
    rng = np.random.default_rng(seed)
    Q = _street(rng)
    T_true = make_transform(rot_z(yaw), np.array([3.0, -2.0, 0.1]))
    P = (Q - T_true[:3, 3]) @ T_true[:3, :3]  # source points: Q = R P + t
    P = P + rng.normal(0, 0.03, P.shape)
    start = T_true.copy()
    start[:2, 3] += (dx, dy)  # right rotation, translation metres off
    out = vote_translations(P, Q, start, reach_m=12.0, height_m=1.0, cell_m=0.5, peaks=3)
    assert 1 <= len(out) <= 3
    assert np.allclose(out[:, :3, :3], start[:3, :3])  # rotation and height kept
    assert np.allclose(out[:, 2, 3], start[2, 3])
    # a cell or two (0.5 m cells, 3x3 smoothing): the alignment that follows does the rest
    assert np.linalg.norm(out[0, :2, 3] - T_true[:2, 3]) < 1.0
    # deterministic
    assert np.array_equal(out, vote_translations(P, Q, start, 12.0, 1.0, 0.5, 3))


def test_offsets_beyond_reach_are_not_voted():
    rng = np.random.default_rng(1)
    Q = _street(rng)
    start = make_transform(np.eye(3), np.array([20.0, 0.0, 0.0]))  # 20 m off, reach 12 m
    out = vote_translations(Q, Q, start, reach_m=12.0, height_m=1.0, cell_m=0.5, peaks=1)
    assert np.abs(out[:, :2, 3] - start[:2, 3]).max() <= 12.0 + 1e-9


def test_no_pair_at_the_same_height_gives_no_hypothesis():
    P = np.c_[np.zeros((5, 2)), np.full(5, 10.0)]
    Q = np.zeros((5, 3))
    assert len(vote_translations(P, Q, np.eye(4), 12.0, 1.0, 0.5, 3)) == 0


def test_verification_votes_turn_a_slid_hypothesis_into_the_right_one():
    """A hypothesis with the right rotation 6 m off: the voted, aligned hypothesis explains the
    evidence and lands within centimetres of the truth."""
    rng = np.random.default_rng(3)
    Q = _street(rng, 600)
    T_true = make_transform(rot_z(0.4), np.array([2.0, 1.0, 0.0]))
    P = (Q - T_true[:3, 3]) @ T_true[:3, :3]
    ev = Evidence(cloud_from_points(P, 0.3, 1500), cloud_from_points(Q, 0.3, 1500))
    slid = T_true.copy()
    slid[:2, 3] += (6.0, -1.5)
    h = Hypothesis(slid, np.zeros((0, 2), np.int64), "clipper", 1.0, 1.0, False, score=0.05)
    cfg = VerificationConfig()
    votes = _translation_votes([h], None, None, ev, cfg)  # type: ignore[arg-type]
    best = max(votes, key=lambda v: v.score)
    assert best.origin == "clipper+vote"
    assert best.score > 0.9
    assert np.linalg.norm(best.T_target_source[:3, 3] - T_true[:3, 3]) < 0.1
