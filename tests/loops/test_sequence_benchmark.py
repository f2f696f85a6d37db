"""The sequence-level protocol: positives, place / end-to-end TPs, PR, F1-max, R@100%P."""

from __future__ import annotations

import numpy as np
import pytest

from graffmatch.evaluation.sequence_benchmark import (
    MethodRun,
    Prediction,
    evaluate_method,
    pr_metrics,
)
from graffmatch.geometry.transforms import invert
from graffmatch.loops import RetrievalConfig


def test_pr_metrics_numbers():
    correct = np.array([True, True, False, True, False])
    conf = np.array([0.9, 0.8, 0.7, 0.6, 0.1])
    m = pr_metrics(correct, conf, n_pos=4)
    assert m["recall_at_100_precision"] == pytest.approx(0.5)  # 2 TPs before the first FP
    # F1 at each threshold: 2/5, 4/6, 4/7, 6/8 (3 TP, 1 FP, 4 pos), 6/9
    assert m["f1_max"] == pytest.approx(0.75)
    assert pr_metrics(np.array([False]), np.array([0.5]), 3)["recall_at_100_precision"] == 0.0


def test_evaluate_method_on_a_two_lap_drive():
    # 2 laps of a 100-scan straight out-and-back line, 1 m a scan, 1 s a scan
    x = np.r_[np.arange(50), np.arange(50)[::-1]].astype(float)
    n = len(x)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = x
    poses[50:, :2, :2] = [[-1, 0], [0, -1]]  # driving back: reversed heading
    t = np.arange(n, dtype=float)
    cfg = RetrievalConfig(exclude_seconds=20.0)
    preds = []
    for q in range(70, n):
        j = 99 - q  # same place on the way out
        T = invert(poses[j]) @ poses[q]
        if q % 2:
            T = T.copy()
            T[0, 3] += 2.0  # a 2 m pose error: right place, wrong pose
        preds.append(Prediction(q, j, 0.9, T))
    preds.append(Prediction(60, 10, 0.95, np.eye(4)))  # wrong place (40 m apart)
    res = evaluate_method(MethodRun("x", preds, 0.01), poses, t, cfg)
    pos = res["place_5m"]["n_positive_queries"]
    # query q (x = 99 - q on the way back) sees scans 0..q-20: within 5 m from q = 57 on
    assert pos == 43
    assert res["place_5m"]["recall_at_100_precision"] == 0.0  # the wrong one is most confident
    assert res["place_5m"]["f1_max"] == pytest.approx(2 * (30 / 31) * (30 / pos) / (30 / 31 + 30 / pos))
    assert res["e2e_5m"]["f1_max"] < res["place_5m"]["f1_max"]
