"""Why lines-only (poles only) matching fails on a simulated suite: per test pair of
``bench/verification.py`` (same data, same pairs), the poles of each scan, the true pole
correspondences (``ground_truth_matches`` under the ground-truth pose), whether registration
from those true associations is right (the ceiling of any association search), with and without
the upright rule of the registration, and whether the lines-only matcher's hypotheses hold a
right one (oracle) with and without the pole-pair hypotheses. Right: within 5 deg and 1 m.

    python bench/lines_diagnosis.py --out /tmp/gm-verify --suite sim-downtown \
        --json bench/results/lines_diagnosis.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from verification import lines_sources, load_sources, make_pairs

from graffmatch.evaluation.places import ground_truth_matches
from graffmatch.geometry.landmarks import LandmarkType
from graffmatch.geometry.transforms import invert, transform_errors
from graffmatch.matcher import GraffMatchConfig, GraffMatcher
from graffmatch.registration.closed_form import register_batch
from graffmatch.verification.config import VerificationConfig

ROT_OK, TRANS_OK = 5.0, 1.0


def right(T: np.ndarray, T_gt: np.ndarray) -> bool:
    r, t = transform_errors(T, T_gt)
    return bool(r <= ROT_OK and t <= TRANS_OK)


def diagnose(src: dict, pairs: list[dict], suite: str, split: str) -> list[dict]:
    open_v = dict(min_overlap=0.0, max_rival_ratio=1.0, min_landmark_overlap=0.0, lines_only=None)
    matchers = {
        "cliques": GraffMatcher(GraffMatchConfig(landmark_types=["line"], verification=VerificationConfig(
            pair_hypotheses=0, **open_v))),
        "pairs": GraffMatcher(GraffMatchConfig(landmark_types=["line"], verification=VerificationConfig(**open_v))),
    }
    rows = []
    for p in pairs:
        if not (p["positive"] and p["split"] == split and p["ds"] == suite):
            continue
        s = src[suite]
        T, S = s["lms"][p["i"]], s["lms"][p["j"]]
        T_gt = invert(s["poses"][p["i"]]) @ s["poses"][p["j"]]
        ls, lt = np.flatnonzero(S.types == LandmarkType.LINE), np.flatnonzero(T.types == LandmarkType.LINE)
        gt, _ = ground_truth_matches(S[ls], T[lt], T_gt)
        row = dict(i=p["i"], j=p["j"], distance_m=float(np.linalg.norm(T_gt[:3, 3])), poles_source=len(ls),
                   poles_target=len(lt), true_pole_matches=len(gt))
        if len(gt) >= 2:
            A = np.stack([ls[gt[:, 0]], lt[gt[:, 1]]], 1)
            for name, um in (("gt_registration_right", 0.5), ("gt_registration_right_without_upright", 2.0)):
                row[name] = right(register_batch(S, T, A, upright_min=um).T_target_source[0], T_gt)
        else:
            row["gt_registration_right"] = row["gt_registration_right_without_upright"] = False
        for name, m in matchers.items():
            if len(ls) < 2 or len(lt) < 2:
                row[f"{name}_best_right"] = row[f"{name}_any_right"] = False
                continue
            r = m.match(S, T)
            row[f"{name}_best_right"] = r.T_target_source is not None and right(r.T_target_source, T_gt)
            row[f"{name}_any_right"] = any(right(h.T_target_source, T_gt) for h in r.hypotheses)
            row[f"{name}_message"] = r.message
            row[f"{name}_associations"] = len(r.associations)
            if r.T_target_source is not None:
                row[f"{name}_upside_down"] = bool(r.T_target_source[2, 2] < 0)
        rows.append(row)
    return rows


def summary(rows: list[dict]) -> dict:
    n = len(rows)
    out = {"pairs": n}
    for k in ("gt_registration_right", "gt_registration_right_without_upright", "cliques_best_right",
              "cliques_any_right", "pairs_best_right", "pairs_any_right"):
        out[k] = sum(bool(r.get(k)) for r in rows)
    out["cliques_upside_down"] = sum(bool(r.get("cliques_upside_down")) for r in rows)
    out["true_pole_matches_hist"] = {str(k): sum(min(r["true_pole_matches"], 8) == k for r in rows) for k in range(9)}
    for k in ("poles_source", "poles_target", "true_pole_matches"):
        out[f"median_{k}"] = float(np.median([r[k] for r in rows])) if rows else float("nan")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="/tmp/gm-verify")
    ap.add_argument("--suite", action="append", default=None, help="sim-downtown (default) and/or sim-suburban")
    ap.add_argument("--split", default="test")
    ap.add_argument("--json", default=None)
    ap.add_argument("--one-layer", action="store_true",
                    help="the full matcher's landmarks (one-layer pole detector) instead of the pole-only front end")
    a = ap.parse_args()
    t0 = time.perf_counter()
    src = load_sources(Path(a.out), True)
    pairs = make_pairs(src, 120, 180)
    if not a.one_layer:  # the landmarks the lines-only pass of bench/verification.py matches
        src = lines_sources(Path(a.out))
    report = {"split": a.split, "suites": {}}
    for suite in a.suite or ["sim-downtown"]:
        rows = diagnose(src, pairs, suite, a.split)
        s = summary(rows)
        report["suites"][suite] = {"summary": s, "rows": rows}
        print(f"{suite} ({a.split}): {json.dumps(s)}")
    print(f"{time.perf_counter() - t0:.0f} s")
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=1, default=float))


if __name__ == "__main__":
    main()
