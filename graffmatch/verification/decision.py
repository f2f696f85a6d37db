"""Hypotheses with their evidence, and the decision: valid only when the best one is clearly
right (absolute evidence) and clearly better than its best distinct rival (margin)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numba as nb
import numpy as np
from numpy.typing import NDArray

from graffmatch.geometry.transforms import rotation_error_deg
from graffmatch.verification.config import VerificationConfig


@dataclass
class Hypothesis:
    """One candidate solution: its associations, registration and evidence score."""

    T_target_source: NDArray[np.float64]
    associations: NDArray[np.int64]  # (k, 2) indices into the matched landmark sets
    origin: str  # clipper | greedy | resolve | rival (+ '+gate' when residual-gated)
    objective: float  # densest-clique objective of its clique
    kappa: float
    degenerate: bool
    score: float = 0.0  # evidence: share of evidence explained (both directions)
    score_parts: tuple[float, float] = (0.0, 0.0)
    info: dict = field(default_factory=dict)

    @property
    def n_associations(self) -> int:
        return int(len(self.associations))

    def __repr__(self) -> str:
        return (f"Hypothesis({self.origin}, associations={self.n_associations}, score={self.score:.3f}, "
                f"objective={self.objective:.2f}, kappa={self.kappa:.3g})")

    def to_dict(self) -> dict:
        return {
            "T_target_source": self.T_target_source.tolist(), "origin": self.origin,
            "n_associations": self.n_associations, "score": self.score,
            "score_parts": list(self.score_parts), "objective": self.objective,
            "kappa": self.kappa if np.isfinite(self.kappa) else None, "degenerate": self.degenerate,
        }


def transform_gap(T_a: NDArray[np.float64], T_b: NDArray[np.float64]) -> tuple[float, float]:
    """(rotation difference [deg], translation difference [m]) between two transforms.

    The arithmetic of :func:`rotation_error_deg` and ``np.linalg.norm`` (the same float64
    operations, so the same bits) without their conversions and scalar ``np.clip``:
    verification compares transforms about ten times per match."""
    A, B = np.asarray(T_a, dtype=float), np.asarray(T_b, dtype=float)
    c = (np.trace(A[:3, :3].T @ B[:3, :3]) - 1.0) / 2.0
    c = min(max(c, -1.0), 1.0)  # np.clip of a scalar; NaN stays NaN
    d = T_a[:3, 3] - T_b[:3, 3]
    return float(np.degrees(np.arccos(c))), float(np.sqrt(d.dot(d)))


def _transform_gap_reference(T_a: NDArray[np.float64], T_b: NDArray[np.float64]) -> tuple[float, float]:
    """Specification of :func:`transform_gap`."""
    return rotation_error_deg(T_a[:3, :3], T_b[:3, :3]), float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))


def merge_hypotheses(hyps: list[Hypothesis], cfg: VerificationConfig,
                     by: Literal["score", "objective"] = "score") -> list[Hypothesis]:
    """Keep, among hypotheses whose transforms agree within merge_deg / merge_m, the best by
    ``by`` (evidence score, or clique objective before any evidence; ties: well-conditioned,
    more associations). Returns them best first. Vectorised gaps."""
    if not hyps:
        return []

    order = _rank_order(hyps, by)
    Ts = np.ascontiguousarray(np.stack([hyps[i].T_target_source for i in order]), dtype=np.float64)
    kept = _distinct_rows(Ts, float(cfg.merge_deg), float(cfg.merge_m))
    return [hyps[order[a]] for a in kept]


def _rank_order(hyps: list[Hypothesis], by: str) -> list[int]:
    """Indices of ``hyps`` best first by (``by`` desc, well-conditioned first, more associations,
    higher objective), ties in list order: one stable ``np.lexsort`` (Python's ``sorted`` with a
    key tuple, the specification, for lists holding NaN, which the two order differently)."""
    obj = np.array([h.objective for h in hyps], dtype=np.float64)
    first = obj if by == "objective" else np.array([h.score for h in hyps], dtype=np.float64)
    if np.isnan(first).any() or np.isnan(obj).any():
        return _rank_order_reference(hyps, by)
    n = np.array([len(h.associations) for h in hyps], dtype=np.int64)
    degenerate = np.array([bool(h.degenerate) for h in hyps])
    return np.lexsort((-obj, -n, degenerate, -first)).tolist()


def _rank_order_reference(hyps: list[Hypothesis], by: str) -> list[int]:
    def rank(h: Hypothesis) -> tuple:
        first = h.score if by == "score" else h.objective
        return (-first, h.degenerate, -h.n_associations, -h.objective)

    return sorted(range(len(hyps)), key=lambda i: rank(hyps[i]))


@nb.njit(cache=True)
def _distinct_rows(Ts: NDArray[np.float64], max_deg: float, max_m: float) -> NDArray[np.int64]:
    """Greedy in row order: keep a transform unless it is within ``max_deg`` (rotation angle
    from trace(R_a^T R_b)) and ``max_m`` of one kept before it. Compares with the kept rows
    only, never all pairs (verification merges up to a few hundred hypotheses)."""
    H = Ts.shape[0]
    kept = np.empty(H, np.int64)
    nk = 0
    for a in range(H):
        close = False
        for q in range(nk):
            b = kept[q]
            d0 = Ts[a, 0, 3] - Ts[b, 0, 3]
            d1 = Ts[a, 1, 3] - Ts[b, 1, 3]
            d2 = Ts[a, 2, 3] - Ts[b, 2, 3]
            if not np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) <= max_m:
                continue
            tr = 0.0
            for i in range(3):
                for j in range(3):
                    tr += Ts[a, i, j] * Ts[b, i, j]
            c = min(max((tr - 1.0) / 2.0, -1.0), 1.0)
            if np.degrees(np.arccos(c)) <= max_deg:
                close = True
                break
        if not close:
            kept[nk] = a
            nk += 1
    return kept[:nk]


@dataclass
class Verdict:
    """The decision about a set of merged, scored hypotheses (best first)."""

    best: Hypothesis | None
    runner_up: Hypothesis | None
    valid: bool
    confidence: float
    margin: float
    rival_ratio: float
    problems: list[str]


def _distinct(h: Hypothesis, best: Hypothesis, cfg: VerificationConfig) -> bool:
    """A rival differs by more than what counts as the same answer (rival_deg / rival_m)."""
    rot, tr = transform_gap(h.T_target_source, best.T_target_source)
    return rot > cfg.rival_deg or tr > cfg.rival_m


def is_settled(merged: list[Hypothesis], leader: Hypothesis | None, cfg: VerificationConfig) -> bool:
    """The exact leader (first of ``merged``) explains at least ``cfg.settled_overlap`` and every
    distinct hypothesis scores at most ``cfg.settled_rival_ratio`` of it: the searches that rescue
    near misses and find aliases have little left to find (off when ``settled_overlap`` is None)."""
    if cfg.settled_overlap is None or leader is None or not merged or merged[0] is not leader:
        return False
    if leader.score < cfg.settled_overlap:
        return False
    rival = max((h.score for h in merged[1:] if _distinct(h, leader, cfg)), default=0.0)
    return rival <= cfg.settled_rival_ratio * leader.score


def confidence_of(score: float, rival_ratio: float, cfg: VerificationConfig, conflict: float = 0.0) -> float:
    """Calibrated probability that the best hypothesis is right (logistic, see config)."""
    c0, c1, c2, c3 = cfg.confidence_coef
    z = c0 + c1 * score + c2 * (1.0 - rival_ratio) + c3 * conflict
    return float(1.0 / (1.0 + np.exp(-z)))


def decide(hyps: list[Hypothesis], cfg: VerificationConfig, min_score: float,
           max_ratio: float | None = None) -> Verdict:
    """Best valid-looking hypothesis vs. its best distinct rival.

    ``hyps`` are merged and sorted best first. Degenerate hypotheses cannot win, but they
    can be the rival: a poorly constrained alternative that explains the data as well still
    makes the answer ambiguous. ``max_ratio``: the rival limit (default ``cfg.max_rival_ratio``).
    """
    max_ratio = cfg.max_rival_ratio if max_ratio is None else max_ratio
    if not hyps:
        return Verdict(None, None, False, 0.0, 0.0, 1.0, ["no hypothesis could be registered"])
    usable = [h for h in hyps if not h.degenerate]
    best = usable[0] if usable else hyps[0]
    rivals = [h for h in hyps if h is not best and _distinct(h, best, cfg)]
    runner = rivals[0] if rivals else None
    ratio = 0.0 if runner is None or best.score <= 0 else min(runner.score / best.score, 1.0)
    problems: list[str] = []
    if best.degenerate:
        problems.append(f"degenerate geometry (kappa={best.kappa:.3g})")
    if best.score < min_score:
        problems.append(f"overlap {best.score:.2f} < {min_score:.2f}")
    if runner is not None and ratio > max_ratio:
        rot, tr = transform_gap(best.T_target_source, runner.T_target_source)
        problems.append(
            f"ambiguous: a {rot:.0f} deg / {tr:.1f} m alternative ({runner.origin}, "
            f"{runner.n_associations} associations) scores {ratio:.2f} of the best"
        )
    conf = 0.0 if best.degenerate else confidence_of(best.score, ratio, cfg)
    return Verdict(best, runner, not problems, conf, 1.0 - ratio, ratio, problems)


def low_confidence_problem(verdict: Verdict, floor: float) -> str:
    """Why a verdict that passed every threshold is still not valid: its confidence is below ``floor``
    (``VerificationConfig.min_valid_confidence``). Names the rival when there is one."""
    best = verdict.best
    msg = f"low confidence: {verdict.confidence:.2f} < {floor:.2f} (overlap {0.0 if best is None else best.score:.2f}"
    if best is None or verdict.runner_up is None:
        return msg + ", no distinct rival)"
    rot, tr = transform_gap(best.T_target_source, verdict.runner_up.T_target_source)
    return msg + (f"; a {rot:.0f} deg / {tr:.1f} m alternative ({verdict.runner_up.origin}) scores "
                  f"{verdict.rival_ratio:.2f} of the best)")
