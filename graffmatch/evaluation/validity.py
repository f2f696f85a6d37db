"""Is a method's "valid" right? Precision, false positives on negatives, recall at full precision.

A loop closure accepted by a SLAM back end is trusted blindly, so every method is scored on its
own validity signal (DESIGN.md, "What valid promises"), on positive pairs (places that overlap)
and on negative pairs (places that do not: far apart, or from different datasets):

* a result is **correct** when the pair is positive and the registration succeeded (within the
  study's rotation/translation bounds); a valid result on a negative pair is always wrong;
* **precision** = correct valid results / valid results;
* **false-positive rate on negatives** = valid results on negatives / negatives;
* **recall** = correct valid results / positives;
* the **native score** of each record (``validity_score``, higher = more sure: GraffMatch's
  ``confidence``, KISS-Matcher's inlier count, FPFH+RANSAC's fitness, 1 - Scan Context distance;
  ``float(valid)`` for methods without one) gives a precision-recall curve, the **recall at
  100 % precision** (the largest recall of a threshold that accepts no wrong result), and, for a
  score meant as a probability, a **reliability diagram** (fraction correct per confidence bin).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

#: Records without a native score (older results, methods without one) use float(valid).
DEFAULT_SIGNAL = "valid"


def is_negative(record: Mapping[str, Any]) -> bool:
    return bool(record.get("negative", False))


def is_correct(record: Mapping[str, Any]) -> bool:
    """A positive pair registered within the bounds (a negative pair has no right answer)."""
    return bool(record.get("success")) and not is_negative(record)


def score_of(record: Mapping[str, Any]) -> float:
    s = record.get("validity_score")
    try:
        v = float(s) if s is not None else float(bool(record.get("valid")))
    except (TypeError, ValueError):
        v = float("nan")
    return v if np.isfinite(v) else float("-inf")


def _arrays(records: Sequence[Mapping[str, Any]]) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    valid = np.array([bool(r.get("valid")) for r in records], dtype=bool)
    correct = np.array([is_correct(r) for r in records], dtype=bool)
    negative = np.array([is_negative(r) for r in records], dtype=bool)
    score = np.array([score_of(r) for r in records], dtype=float)
    return valid, correct, negative, score


def pr_curve(
    scores: Sequence[float], correct: Sequence[bool], n_positives: int
) -> dict[str, NDArray[np.float64]]:
    """Precision and recall of accepting every result with score >= t, for each distinct t
    (highest first); ties are accepted together, so a threshold never splits equal scores."""
    s = np.asarray(scores, dtype=float)
    c = np.asarray(correct, dtype=bool)
    if s.size == 0:
        return {"threshold": np.zeros(0), "precision": np.zeros(0), "recall": np.zeros(0)}
    order = np.argsort(-s, kind="stable")
    s, c = s[order], c[order]
    tp = np.cumsum(c)
    k = np.arange(1, len(s) + 1)
    last_of_tie = np.r_[s[1:] != s[:-1], True]
    return {
        "threshold": s[last_of_tie],
        "precision": (tp / k)[last_of_tie],
        "recall": (tp / max(n_positives, 1))[last_of_tie],
    }


def recall_at_full_precision(
    scores: Sequence[float], correct: Sequence[bool], n_positives: int
) -> float:
    """The largest recall of a score threshold that accepts no wrong result (0 if none)."""
    curve = pr_curve(scores, correct, n_positives)
    ok = curve["precision"] >= 1.0
    # thresholds run from high to low: the last one still at full precision before any error
    if not ok.any() or not ok[0]:
        return 0.0
    first_bad = np.argmin(ok) if not ok.all() else len(ok)
    return float(curve["recall"][first_bad - 1])


def reliability(
    confidences: Sequence[float], correct: Sequence[bool], n_bins: int = 10
) -> dict[str, Any]:
    """Fraction correct per confidence bin on [0, 1], and the expected calibration error."""
    p = np.clip(np.asarray(confidences, dtype=float), 0.0, 1.0)
    c = np.asarray(correct, dtype=bool)
    edges = np.linspace(0.0, 1.0, n_bins + 1)
    idx = np.clip(np.searchsorted(edges, p, side="right") - 1, 0, n_bins - 1)
    counts = np.bincount(idx, minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_conf = np.bincount(idx, weights=p, minlength=n_bins) / counts
        frac = np.bincount(idx, weights=c.astype(float), minlength=n_bins) / counts
    filled = counts > 0
    ece = float(np.sum(counts[filled] * np.abs(frac[filled] - mean_conf[filled])) / max(len(p), 1))
    return {
        "bin_edges": edges,
        "counts": counts,
        "mean_confidence": mean_conf,
        "fraction_correct": frac,
        "ece": ece,
    }


def validity_stats(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The validity numbers of one method on a set of records (positives and negatives)."""
    valid, correct, negative, score = _arrays(records)
    n_pos = int((~negative).sum())
    n_neg = int(negative.sum())
    n_valid = int(valid.sum())
    tp = int((valid & correct).sum())
    return {
        "n_positives": n_pos,
        "n_negatives": n_neg,
        "n_valid": n_valid,
        "n_valid_correct": tp,
        "precision": tp / n_valid if n_valid else float("nan"),
        "valid_recall": tp / n_pos if n_pos else float("nan"),
        "fpr_negatives": float((valid & negative).sum() / n_neg) if n_neg else float("nan"),
        "recall_at_full_precision": (
            recall_at_full_precision(score, correct, n_pos) if n_pos else float("nan")
        ),
        "signal": next(
            (str(r["validity_signal"]) for r in records if r.get("validity_signal")),
            DEFAULT_SIGNAL,
        ),
    }


def validity_table(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """One row per (suite, method) over all of the suite's records, plus the pooled 'all'."""
    rows = []
    groups: dict[tuple[str, str], list[Mapping[str, Any]]] = {}
    for r in records:
        groups.setdefault((str(r["suite"]), str(r["method"])), []).append(r)
        groups.setdefault(("all", str(r["method"])), []).append(r)
    for (suite, method), g in sorted(groups.items()):
        rows.append({"suite": suite, "method": method, **validity_stats(g)})
    return rows
