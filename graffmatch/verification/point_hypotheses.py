"""Hypotheses from the evidence points alone, for pairs whose landmarks give the graph too few
associations to register (a landmark-poor pair: two or three landmarks a scan).

Why: with two associations no landmark hypothesis exists, so raw-scan evidence has nothing to
verify (17 of sim-downtown-s1's misses after session 15, docs/loops.md session 15b). A yaw sweep
about z (ground vehicles: no roll or pitch) with each yaw's translation voted on the points
(``translation_vote.py``) gives the decision candidates, and every distinct vote peak is also a
rival, so a street that does not pin the translation stays ambiguous.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from graffmatch.verification.config import VerificationConfig
from graffmatch.verification.decision import Hypothesis, merge_hypotheses
from graffmatch.verification.evidence import SupportCloud, align_on_evidence, score_on_points
from graffmatch.verification.translation_vote import vote_translations


def point_hypotheses(source: SupportCloud, target: SupportCloud, cfg: VerificationConfig,
                     starts: tuple[NDArray[np.float64], ...] = ()) -> list[Hypothesis]:
    """Hypotheses without associations (origin 'points'): yaws every ``point_yaw_step_deg`` at
    zero translation and ``starts`` (e.g. odometry), each with its ``point_peaks`` strongest
    translation votes, the starts also as they are; the ``point_align`` best by occupancy
    aligned on the points and scored exactly (the caller merges them with the rest)."""
    yaws = np.radians(np.arange(0.0, 360.0, cfg.point_yaw_step_deg))
    sweep = np.repeat(np.eye(4)[None], len(yaws), axis=0)
    sweep[:, 0, 0] = sweep[:, 1, 1] = np.cos(yaws)
    sweep[:, 1, 0] = np.sin(yaws)
    sweep[:, 0, 1] = -sweep[:, 1, 0]
    first = [np.asarray(T, np.float64) for T in starts]
    P, Q = source.sample(cfg.vote_points), target.sample(cfg.vote_points)
    Ts = [T for S in [*first, *sweep] for T in vote_translations(
        P, Q, S, cfg.vote_reach_m, cfg.vote_height_m, cfg.vote_cell_m, cfg.point_peaks)]
    hyps = [Hypothesis(T, np.zeros((0, 2), np.int64), "points", 0.0, 1.0, False) for T in [*first, *Ts]]
    if not hyps:
        return []
    score_on_points(hyps, source, target, cfg.inlier_m, exact=False)
    hyps = merge_hypotheses(hyps, cfg)[: cfg.point_align]
    for h in hyps:
        h.info["T_landmarks"] = h.T_target_source
        h.T_target_source = align_on_evidence(source, target, h.T_target_source)
    score_on_points(hyps, source, target, cfg.inlier_m, exact=True)
    return hyps


def prior_contrast(source: SupportCloud, target: SupportCloud, cfg: VerificationConfig,
                   T_prior: NDArray[np.float64], yaw_deg: float = 5.0) -> tuple[float, float]:
    """(occupancy near the prior, best occupancy a quarter turn or more away): a cheap first screen.

    Both are the best approximate occupancy (:func:`score_on_points`, ``exact=False``) of the
    ``point_peaks`` strongest translation votes at three yaws ``yaw_deg`` apart, centred on the
    prior's yaw (e.g. a drifting odometry's relative pose, a few degrees off) and on it turned by 90,
    180 and 270 deg. Why a contrast and not the occupancy alone: clouds of streets with many
    returns explain a share of each other under any yaw (sim-downtown-s1: 0.2-0.3 for pairs 5-15 m
    apart), so the level depends on the drive; a place seen again explains itself clearly better
    at the prior's yaw than turned away, and a street that looks alike turned around is what the
    full verification then calls ambiguous anyway. No alignment, no exact score: ~1 ms a pair."""
    T0 = np.asarray(T_prior, np.float64)
    P, Q = source.sample(cfg.vote_points), target.sample(cfg.vote_points)
    best = []
    for turn in (0.0, 90.0, 180.0, 270.0):
        Ts = [T for d in (-yaw_deg, 0.0, yaw_deg) for T in vote_translations(
            P, Q, T0 @ _yaw(np.radians(turn + d)), cfg.vote_reach_m, cfg.vote_height_m, cfg.vote_cell_m,
            cfg.point_peaks)]
        hyps = [Hypothesis(T, np.zeros((0, 2), np.int64), "points", 0.0, 1.0, False) for T in Ts]
        score_on_points(hyps, source, target, cfg.inlier_m, exact=False)
        best.append(max((h.score for h in hyps), default=0.0))
    return float(best[0]), float(max(best[1:]))


def _yaw(a: float) -> NDArray[np.float64]:
    """4x4 rotation about z by ``a`` radians."""
    T = np.eye(4)
    T[0, 0] = T[1, 1] = np.cos(a)
    T[1, 0] = np.sin(a)
    T[0, 1] = -T[1, 0]
    return T
