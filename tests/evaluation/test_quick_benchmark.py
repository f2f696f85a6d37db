"""`graffmatch benchmark --quick`: the whole study in small, end to end (issue: the tests run it).

Builds the quick versions of the default suites (simulated worlds, and balm_courtyard when
../shared/data is present), runs every quick method on a few pairs per case, and writes the
report. Checks that the report's tables, figures and claim checks exist and hold numbers, and
that GraffMatch registers at least a floor of the quick pairs correctly.
"""

from __future__ import annotations

import json
import math

import numpy as np

from graffmatch.evaluation.benchmark import run_benchmark
from tests.conftest import _shared_data_dir

#: Floors of GraffMatch's correct-registration recall (rotation < 5 deg and translation < 1 m,
#: whatever its ``valid`` flag says) on the quick suites (realistic simulator, 3-9 pairs each).
#: Measured on 2026-11-22 with SIMULATOR_VERSION 1.2 and the voxel plane detector (240 quick
#: scans): downtown 2/8, suburban 3/3, open road 8/9 positive pairs (simulator 1.1 with the
#: Open3D detector gave 4/6, 5/6, 7/9: the 1.2 worlds, with one street wall per downtown block
#: side, panel relief and visible shop fronts, are other places with other pairs); each floor
#: allows one more failure. Precision is asserted separately: no valid-and-wrong result.
#: Session 5: the free-space check and the thresholds chosen on the suites' realistic drives
#: (min_overlap 0.225, max_conflict 0.11) reject all 6 downtown quick pairs (0/6; parked cars and
#: shop fronts change between passes, docs/verification.md), so downtown has no floor here; its
#: held-out recall is tracked by bench/verification.py (0.575 on 120 test pairs).
RECALL_FLOORS = {"sim-suburban": 0.6, "sim-openroad": 0.75}


def correct_registration_recall(results, suite: str, method: str = "GraffMatch") -> tuple[float, int]:
    """(fraction of positive pairs within 5 deg / 1 m, number of them) from the run's records;
    negative pairs (case 0: different places) have no correct transform and are left out."""
    recs = [json.loads(p.read_text()) for p in (results / "records" / suite / method).glob("*.json")]
    recs = [r for r in recs if int(r.get("case", 1)) > 0]
    ok = [float(r["rotation_error_deg"]) < 5.0 and float(r["translation_error_m"]) < 1.0 for r in recs]
    return (float(np.mean(ok)) if ok else float("nan")), len(ok)


def valid_and_wrong(results, suite: str, method: str = "GraffMatch") -> list[str]:
    """Pairs the method calls valid whose pose is not within 5 deg / 1 m of the ground truth
    (or that have no ground truth: cross-dataset negatives)."""
    out = []
    for p in sorted((results / "records" / suite / method).glob("*.json")):
        r = json.loads(p.read_text())
        if not r.get("valid"):
            continue
        rot, tra = float(r.get("rotation_error_deg", math.nan)), float(r.get("translation_error_m", math.nan))
        if suite == "cross-dataset" or not (rot < 5.0 and tra < 1.0):
            out.append(str(r["pair_id"]))
    return out


def test_quick_benchmark_produces_the_report(tmp_path):
    suites = ["sim-downtown", "sim-openroad", "sim-suburban"]
    if (_shared_data_dir() / "balm_courtyard").is_dir():
        suites.append("balm_courtyard")
    if (_shared_data_dir() / "kitti00_first6").is_dir():
        suites.append("cross-dataset")  # negatives only: no row in Table I
    out = run_benchmark(suites, tmp_path / "bench", quick=True, workers=2, progress=False)
    report = out / "report"
    for name in (
        "summary.md",
        "table1.md",
        "table1.json",
        "table2.md",
        "expectations.json",
        "rho.json",
        "metrics.json",
        "config.json",
    ):
        assert (report / name).is_file(), name
    assert any((report / "figures").glob("lmr_*.png"))
    assert any((report / "figures").glob("errors_*.png"))
    t1 = json.loads((report / "table1.json").read_text())
    assert {"GraffMatch", "GraffMatch-Naive", "CLIPPER-Rn", "CPMatch"} <= set(t1["methods"])
    assert {r["suite"] for r in t1["rows"]} == set(suites) - {"cross-dataset"}
    recalls = [r["methods"]["GraffMatch"]["recall_pct"] for r in t1["rows"]]
    assert all(0.0 <= x <= 100.0 for x in recalls if not math.isnan(float(x)))
    assert max(recalls) > 0.0  # GraffMatch registers some pair
    # every suite's recall first, so that a failure shows all of them
    got = {suite: correct_registration_recall(out / "results", suite) for suite in RECALL_FLOORS}
    for suite, (recall, n) in got.items():
        print(f"GraffMatch correct-registration recall on {suite}: {recall:.3f} of {n} pairs")
    for suite, floor in RECALL_FLOORS.items():
        recall, n = got[suite]
        assert n >= 3, (suite, n, got)
        assert recall >= floor, (suite, recall, n, got)
    claims = json.loads((report / "expectations.json").read_text())
    assert {c["id"] for c in claims} >= {"graffmatch_best"}
    # every suite's validity numbers, negatives included (at most 3 per suite in quick mode;
    # a drive whose places all lie within 60 m of each other has none)
    validity = json.loads((report / "validity.json").read_text())
    ours = {r["suite"]: r for r in validity if r["method"] == "GraffMatch"}
    assert set(ours) == {*suites, "all"}
    built = json.loads((out / "benchmark.json").read_text())["build"]
    for suite in suites:
        assert ours[suite]["n_negatives"] == min(3, built[suite]["negatives"]), suite
        if ours[suite]["n_negatives"]:
            assert 0.0 <= ours[suite]["fpr_negatives"] <= 1.0
    if "cross-dataset" in suites:
        assert (
            ours["cross-dataset"]["n_negatives"] == 3 and ours["cross-dataset"]["n_positives"] == 0
        )
    assert (report / "figures" / "reliability_graffmatch.png").is_file()
    # precision of valid: every result GraffMatch calls valid is right (5 deg / 1 m against the
    # ground truth). A simulated "negative" (places > 60 m apart) can still overlap on the open
    # road, where the same poles are seen 60-80 m away: it counts as right only when its pose is;
    # a cross-dataset pair has no right pose, so any valid result there is wrong.
    wrong_valid = {suite: valid_and_wrong(out / "results", suite) for suite in suites}
    print(f"GraffMatch valid-and-wrong per suite: {wrong_valid}")
    assert not any(wrong_valid.values()), wrong_valid
