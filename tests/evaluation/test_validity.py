"""Validity of the validity flags: precision, negatives, recall at full precision, reliability."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from graffmatch.evaluation import validity as V
from graffmatch.evaluation.loop_closure_dataset import LoopClosureDataset
from graffmatch.evaluation.places import find_negatives
from graffmatch.evaluation.report import make_report
from graffmatch.evaluation.runner import StudyConfig, load_records, run_study
from graffmatch.evaluation.tables import summarize, table1
from tests.evaluation.test_runner import make_pairs


def rec(valid, success, negative=False, score=None, suite="s", method="m", case=1):
    return {
        "suite": suite,
        "method": method,
        "case": 0 if negative else case,
        "valid": valid,
        "success": success,
        "negative": negative,
        "validity_score": score,
    }


def test_pr_curve_and_recall_at_full_precision():
    scores = [0.9, 0.8, 0.8, 0.6, 0.3]
    correct = [True, True, False, True, False]
    c = V.pr_curve(scores, correct, n_positives=4)
    # ties at 0.8 are accepted together: thresholds 0.9, 0.8, 0.6, 0.3
    np.testing.assert_allclose(c["threshold"], [0.9, 0.8, 0.6, 0.3])
    np.testing.assert_allclose(c["precision"], [1.0, 2 / 3, 3 / 4, 3 / 5])
    np.testing.assert_allclose(c["recall"], [0.25, 0.5, 0.75, 0.75])
    assert V.recall_at_full_precision(scores, correct, 4) == pytest.approx(0.25)
    assert V.recall_at_full_precision([0.9, 0.5], [False, True], 1) == 0.0
    assert V.recall_at_full_precision([0.9, 0.5], [True, True], 2) == 1.0


def test_reliability_bins_and_calibration_error():
    conf = np.r_[np.full(10, 0.95), np.full(10, 0.15)]
    correct = np.r_[np.ones(9, bool), [False], np.zeros(8, bool), [True, True]]
    r = V.reliability(conf, correct, n_bins=10)
    assert r["counts"][9] == 10 and r["counts"][1] == 10
    assert r["fraction_correct"][9] == pytest.approx(0.9)
    assert r["fraction_correct"][1] == pytest.approx(0.2)
    assert r["ece"] == pytest.approx(0.5 * 0.05 + 0.5 * 0.05)


def test_validity_stats_count_negatives_as_wrong():
    records = [
        rec(True, True),  # right
        rec(True, False),  # valid but wrong
        rec(False, True),  # right but not claimed
        rec(True, True, negative=True),  # a valid negative is wrong, whatever its errors
        rec(False, False, negative=True),
    ]
    s = V.validity_stats(records)
    assert (s["n_positives"], s["n_negatives"], s["n_valid"]) == (3, 2, 3)
    assert s["precision"] == pytest.approx(1 / 3)
    assert s["fpr_negatives"] == pytest.approx(0.5)
    assert s["valid_recall"] == pytest.approx(1 / 3)
    assert s["signal"] == "valid"


def test_find_negatives_are_far_apart_and_evenly_spread():
    poses = np.tile(np.eye(4), (101, 1, 1))
    poses[:, 0, 3] = np.arange(101) * 2.0  # a straight 200 m drive
    places = np.arange(0, 101, 2)
    neg = find_negatives(poses, places, 60.0, 25)
    assert len(neg) == 25 and len({tuple(p) for p in neg}) == 25
    d = np.abs(poses[neg[:, 0], 0, 3] - poses[neg[:, 1], 0, 3])
    assert d.min() >= 60.0
    np.testing.assert_array_equal(neg, find_negatives(poses, places, 60.0, 25))  # deterministic
    assert len(find_negatives(poses, places, 500.0, 25)) == 0


def _with_negatives(n_pos: int, n_neg: int, seed: int) -> list:
    pairs = make_pairs(n_pos + 2 * n_neg, seed=seed)
    positives, rest = pairs[:n_pos], pairs[n_pos:]
    negatives = []
    for k in range(n_neg):  # the source of one scene against the target of another
        a, b = rest[2 * k], rest[2 * k + 1]
        a.target, a.true_matches, a.case = b.target, np.zeros((0, 2), np.intp), 0
        a.negative = True
        a.pair_id = f"neg-{k}"
        negatives.append(a)
    return positives + negatives


def test_summary_tables_and_report_carry_precision_and_negatives(tmp_path: Path):
    out = run_study(
        {"synth": _with_negatives(6, 4, seed=3)},
        ["GraffMatch", "CPMatch"],
        tmp_path / "study",
        executor="serial",
        progress=False,
        config=StudyConfig(rho_values=[]),
    )
    records = load_records(out)
    assert sum(r["negative"] for r in records) == 3 * 4  # GT-matches + 2 methods
    ours = [r for r in records if r["method"] == "GraffMatch"]
    assert all(r["validity_signal"] in ("confidence", "valid") for r in ours)
    rows = summarize(records)
    assert not any(r["case"] == 0 for r in rows)  # negatives are not a case of recall
    all_row = next(r for r in rows if r["method"] == "GraffMatch" and r["case"] == "all")
    expect = V.validity_stats(ours)
    assert all_row["n"] == 6 and all_row["n_negatives"] == 4
    assert all_row["precision"] == pytest.approx(expect["precision"], nan_ok=True)
    assert all_row["fpr_negatives"] == pytest.approx(expect["fpr_negatives"])
    t1 = table1(rows)
    cell = next(r for r in t1["rows"] if r["case"] == "all")["methods"]["GraffMatch"]
    assert cell["precision_pct"] == pytest.approx(100 * all_row["precision"], nan_ok=True)

    rep = make_report(out, tmp_path / "report")
    vt = json.loads((rep / "validity.json").read_text())
    row = next(r for r in vt if r["suite"] == "synth" and r["method"] == "GraffMatch")
    assert row["n_negatives"] == 4 and row["n_positives"] == 6
    assert "precision [%]" in (rep / "table1.md").read_text()
    summary = (rep / "summary.md").read_text()
    assert "FPR on negatives" in summary and "reliability_graffmatch.png" in summary
    assert (rep / "figures" / "precision_recall_synth.png").read_bytes()[:4] == b"\x89PNG"


def test_cross_dataset_negatives(shared_data, tmp_path):
    from graffmatch.evaluation.suites import build_suite, cross_sources_available

    if len(cross_sources_available(shared_data)) < 1:
        pytest.skip("no real dataset to pair with the simulated one")
    summary = build_suite("cross-dataset", tmp_path, quick=True, data_root=shared_data)
    ds = LoopClosureDataset.load(tmp_path / "cross-dataset-quick")
    assert len(ds) == 0 and len(ds.negatives) == summary["n_negatives"] == 12
    source_of = {p["scan"]: p["source"] for p in ds.doc["places"]}
    assert len(set(source_of.values())) == len(cross_sources_available(shared_data)) + 1
    for p in ds.negatives:
        assert p.negative and p.case == 0 and len(p.true_matches) == 0
        assert source_of[p.source_scan] != source_of[p.target_scan]
        assert len(p.source) >= 2 and len(p.target) >= 2
