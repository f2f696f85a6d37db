"""Choose the loop detector's place margin and landmark-poor rule on calibration drives (issue 15).

    PYTHONPATH=$PWD nice -n 19 python bench/loops_calibration.py --data /tmp/loops8-cal-data \\
        --out /tmp/loops8-cal-out --json bench/results/loops_calibration.json

The calibration split: other seeds of the benchmark's three environments, never the reported
drives (those are downtown 1/5, suburban 1/4, open road 1/3, ``bench/bench_loops.py``):
downtown 2, 3, 4 and 6, suburban 3 and 5, open road 2 and 5 (seeds with revisits: open road 4
has none; downtown 4 and 6 added because 2 and 3 have almost no landmark-poor scans), simulated with the same realistic preset and de-skewed with the same drifting odometry
(``loops.sequence.prepare_drive``). Our detector runs with the benchmark configuration but
verifies every candidate that passes the quick check (at most ``max_verified``, best quick score
first, no early stop) and records the matcher's verdict per candidate. The detector's default
policy (stop at the first candidate that reaches ``min_confidence``) is then replayed exactly on
these records for every setting of the grid, with the detector's own
:func:`graffmatch.loops.verify.loop_confidence` (one rule for the detector, the CLI, the
benchmark and this replay), and scored with the benchmark's protocol
(:func:`graffmatch.evaluation.sequence_benchmark.evaluate_method`).

Rule of the choice, fixed before looking: the place margin is the smallest grid value with no
loop at the default threshold whose ground-truth distance exceeds the place radius on any
calibration drive; the landmark-poor rule (fewest agreeing landmarks, matcher confidence) the
setting with e2e precision 1.00 at the default threshold on every calibration drive and the
largest summed e2e recall at 100 % precision, ties to the stricter setting.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json
from bench_loops import simulate

CALIBRATION_DRIVES = [("sim-downtown", 2), ("sim-downtown", 3), ("sim-downtown", 4), ("sim-downtown", 6),
                      ("sim-suburban", 3), ("sim-suburban", 5), ("sim-openroad", 2), ("sim-openroad", 5)]
MARGINS = [0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5]
FEW_AGREEING = [6, 5, 4, 3]
FEW_TAU = [0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.99]


def calibration_config():
    """The benchmark configuration, every quick-passing candidate verified (for the replay)."""
    from graffmatch.evaluation.sequence_benchmark import benchmark_config

    cfg = benchmark_config()
    cfg.verification.stop_when_accepted = False
    return cfg


def run(paths: list[Path], out: Path, workers: int) -> list[str]:
    from graffmatch.datasets.registry import open_dataset
    from graffmatch.loops.sequence import prepare_drive, run_loops

    names = []
    for p in paths:
        ds, _ = prepare_drive(open_dataset("folder", p), "drift", True)
        t0 = time.perf_counter()
        run_loops(ds, out / ds.name / "ours", calibration_config(), workers=workers)
        print(f"{ds.name}: {time.perf_counter() - t0:.0f} s", flush=True)
        names.append(ds.name)
    return names


def replay(records: dict[int, dict], vcfg) -> list:
    """The default policy's prediction per query under ``vcfg`` (stop at the first accepted)."""
    from graffmatch.evaluation.sequence_benchmark import Prediction
    from graffmatch.loops.verify import loop_confidence

    preds = []
    for q, r in records.items():
        ver = sorted((c for c in r["candidates"] if c.get("verified", True)),
                     key=lambda c: (-c["quick_score"], c["rank"]))[: vcfg.max_verified]
        seen = []
        for c in ver:
            if c["T"] is None:
                continue
            T = np.asarray(c["T"], float).reshape(4, 4)
            conf = loop_confidence(bool(c["matcher_valid"]), c["matcher_confidence"], int(c["n_agreeing"]),
                                   float(c["overlap"]), float(np.linalg.norm(T[:3, 3])), vcfg,
                                   bool(c.get("on_points", False)))
            seen.append((conf, -c["rank"], c["match"], T))
            if conf >= vcfg.min_confidence:
                break
        if seen:
            conf, _, j, T = max(seen, key=lambda s: (s[0], s[1]))
            preds.append(Prediction(int(q), int(j), conf, T))
    return preds


def score(ds, preds, cfg) -> dict:
    from graffmatch.evaluation.sequence_benchmark import MethodRun, evaluate_method, pose_errors

    res = evaluate_method(MethodRun("ours", preds, 0.0), np.asarray(ds.poses), np.asarray(ds.timestamps),
                          cfg.retrieval)
    poses = np.asarray(ds.poses)
    acc = [p for p in preds if p.confidence >= cfg.verification.min_confidence]
    errs = np.array([pose_errors(poses, p) for p in acc]).reshape(-1, 3)
    e2e = (errs[:, 0] <= 5) & (errs[:, 1] <= 5) & (errs[:, 2] <= 1)
    return {
        "e2e_r100p": res["e2e_5m"]["recall_at_100_precision"],
        "e2e_f1max": res["e2e_5m"]["f1_max"],
        "n_pos": res["e2e_5m"]["n_positive_queries"],
        "accepted": len(acc),
        "accepted_e2e_false": int((~e2e).sum()),
        "accepted_beyond_radius": int((errs[:, 0] > 5).sum()),
        "accepted_pose_wrong": int(((errs[:, 1] > 5) | (errs[:, 2] > 1)).sum()),
        "precision_at_default": float(e2e.mean()) if len(acc) else float("nan"),
        "recall_at_default": float(e2e.sum() / max(res["e2e_5m"]["n_positive_queries"], 1)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("/tmp/loops8-cal-data"))
    ap.add_argument("--out", type=Path, default=Path("/tmp/loops8-cal-out"))
    ap.add_argument("--scans", type=int, default=400)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--replay-only", action="store_true", help="score the grid on an earlier run's records")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    from graffmatch.datasets.registry import open_dataset
    from graffmatch.evaluation.sequence_benchmark import pose_errors
    from graffmatch.loops.sequence import prepare_drive, read_queries

    t0 = time.perf_counter()
    paths = simulate(args.data, args.scans, "realistic", CALIBRATION_DRIVES)
    if not args.replay_only:
        run(paths, args.out, args.workers)
    cfg = calibration_config()
    drives = []
    for p in paths:
        ds, _ = prepare_drive(open_dataset("folder", p), "drift", True)
        drives.append((ds, read_queries(args.out / ds.name / "ours")))

    # distance error of the estimate on every pose-correct verified candidate (the margin's scale)
    derr, near = [], []
    for ds, recs in drives:
        poses = np.asarray(ds.poses)
        for q, r in recs.items():
            for c in r["candidates"]:
                if c["T"] is None or not c.get("matcher_valid"):
                    continue
                T = np.asarray(c["T"], float).reshape(4, 4)
                from graffmatch.evaluation.sequence_benchmark import Prediction

                d, rot, tr = pose_errors(poses, Prediction(int(q), int(c["match"]), 1.0, T))
                if rot <= 5 and tr <= 1:
                    de = float(np.linalg.norm(T[:3, 3])) - d
                    derr.append(de)
                    if 4.75 <= d <= 5.25:  # the candidates a margin decides
                        near.append({"drive": ds.name, "query": int(q), "match": int(c["match"]),
                                     "gt_m": round(d, 4), "est_m": round(float(np.linalg.norm(T[:3, 3])), 4)})
    derr = np.abs(np.array(derr))
    print(f"|estimated - true distance| of {len(derr)} pose-correct valid candidates: median "
          f"{np.median(derr):.3f}, p95 {np.quantile(derr, 0.95):.3f}, p99 {np.quantile(derr, 0.99):.3f}, "
          f"max {derr.max():.3f} m")

    grid = []
    for margin, few, tau in itertools.product(MARGINS, FEW_AGREEING, FEW_TAU):
        if few == 6 and tau != FEW_TAU[0]:
            continue  # few = min_agreeing: tau is irrelevant
        v = cfg.verification.model_copy(update={
            "place_margin_m": margin, "few_landmarks_min_agreeing": few,
            "few_landmarks_matcher_confidence": None if few == 6 else tau})
        c2 = cfg.model_copy(update={"verification": v})
        rows = {ds.name: score(ds, replay(recs, v), c2) for ds, recs in drives}
        grid.append({"place_margin_m": margin, "few_landmarks_min_agreeing": few,
                     "few_landmarks_matcher_confidence": None if few == 6 else tau, "drives": rows})
    # the margin: smallest with no accepted loop beyond the radius (landmark rule as before)
    base = [g for g in grid if g["few_landmarks_min_agreeing"] == 6]
    margin = next(g["place_margin_m"] for g in base
                  if all(r["accepted_beyond_radius"] == 0 for r in g["drives"].values()))
    ok = [g for g in grid if g["place_margin_m"] == margin
          and all(r["accepted_e2e_false"] == 0 for r in g["drives"].values())]
    best = max(ok, key=lambda g: (round(sum(r["e2e_r100p"] for r in g["drives"].values()), 6),
                                  g["few_landmarks_min_agreeing"], g["few_landmarks_matcher_confidence"] or 1.0))
    for g in grid:
        if g["place_margin_m"] in (0.0, margin):
            tot = sum(r["e2e_r100p"] for r in g["drives"].values())
            print(g["place_margin_m"], g["few_landmarks_min_agreeing"], g["few_landmarks_matcher_confidence"],
                  f"sum R@100P {tot:.3f}", " ".join(
                      f"{r['e2e_r100p']:.2f}({r['accepted_e2e_false']}/{r['accepted_beyond_radius']})"
                      for r in g["drives"].values()))
    print("chosen:", {k: best[k] for k in ("place_margin_m", "few_landmarks_min_agreeing",
                                            "few_landmarks_matcher_confidence")})
    for name, r in best["drives"].items():
        print(name, r)
    if args.json:
        write_json(args.json, {
            "machine": machine(), "wall_s": time.perf_counter() - t0, "drives": [ds.name for ds, _ in drives],
            "scans": args.scans, "distance_error_m": {
                "n": len(derr), "median": float(np.median(derr)), "p95": float(np.quantile(derr, 0.95)),
                "p99": float(np.quantile(derr, 0.99)), "max": float(derr.max())},
            "near_radius": near,
            "chosen": {k: best[k] for k in ("place_margin_m", "few_landmarks_min_agreeing",
                                            "few_landmarks_matcher_confidence")},
            "chosen_drives": best["drives"],
            "grid": [{**{k: g[k] for k in ("place_margin_m", "few_landmarks_min_agreeing",
                                            "few_landmarks_matcher_confidence")},
                      "e2e_r100p": {n: round(r["e2e_r100p"], 4) for n, r in g["drives"].items()},
                      "accepted_e2e_false": {n: r["accepted_e2e_false"] for n, r in g["drives"].items()},
                      "accepted_beyond_radius": {n: r["accepted_beyond_radius"] for n, r in g["drives"].items()}}
                     for g in grid]})


if __name__ == "__main__":
    main()
