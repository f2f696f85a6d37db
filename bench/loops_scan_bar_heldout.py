"""The scan pass's conflict bar on drives never used to choose it (issue 15, session 17): held-out safety.

    PYTHONPATH=$PWD nice -n 5 python bench/loops_scan_bar_heldout.py --data /tmp/loops15-data \\
        --out /tmp/loops17-heldout --json bench/results/loops_scan_bar_heldout_session17.json

``scans_max_conflict`` (0.12) was chosen on 26 calibration drives with a stress set: every verified pair of two
landmark-poor scans, the scan rule's accepts counted right or wrong. This is that stress set on the reported
drives (and any other drive under ``--data``): each is recorded as the calibration drives are (every retrieved
candidate verified, every cloud pair's scan pass recorded: ``run_config(12)`` with point hypotheses, drift
odometry, de-skewed), every scan pass of a pair of two scans with clouds (< 8 landmarks) runs again at the
matcher's bar (None) and at the default, and the scan rule's accepts (session 15's rule with 16's point-won
verdicts) are tallied against the ground truth (e2e: <= 5 m apart, pose within 5 deg / 1 m). Nothing is
chosen here; the policy's own loops on these drives are ``bench/bench_loops.py``'s.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json
from loops_calibration_points15b import K, candidate_confidence, policy_base, rescanned
from loops_calibration_scans import run_config, stress_tally


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True, help="simulated drives (folders with poses.txt)")
    ap.add_argument("--out", type=Path, required=True, help="the recording runs and the rescans' caches")
    ap.add_argument("--only", nargs="+", default=None, help="only these drive folders, in this order")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    from graffmatch.datasets.registry import open_dataset
    from graffmatch.loops.database import load_landmarks, load_scan_cloud
    from graffmatch.loops.sequence import prepare_drive, read_queries, run_loops
    from graffmatch.loops.verification_config import SCANS_MAX_CONFLICT, SCANS_POINTS_MIN_AGREEING

    t0 = time.perf_counter()
    cfg = run_config(12)
    cfg.matcher.verification.point_hypotheses = True
    names = args.only or sorted(p.name for p in args.data.iterdir() if (p / "poses.txt").is_file())
    drives = []
    for name in names:
        ds, odo = prepare_drive(open_dataset("folder", args.data / name), "drift", True)
        out = args.out / ds.name / "ours"
        t1 = time.perf_counter()
        run_loops(ds, out, cfg, workers=args.workers, odometry=odo)  # resumes / reuses a finished run
        files = [out / "landmarks" / f"{i:06d}.npz" for i in range(len(ds))]
        has = np.array([len(load_landmarks(f)) < K and load_scan_cloud(f) is not None for f in files])
        drives.append((ds, odo, np.asarray(ds.poses), read_queries(out), has, []))
        print(f"{ds.name}: recorded ({time.perf_counter() - t1:.0f} s), {int(has.sum())} scans with clouds", flush=True)
    v = policy_base(cfg).model_copy(update={"scans_points_min_agreeing": SCANS_POINTS_MIN_AGREEING})
    where = SimpleNamespace(out=args.out, contrast_cache=None)
    result: dict = {}
    for t in (None, SCANS_MAX_CONFLICT):
        per = {}
        for ds, _odo, poses, recs, has, _ in rescanned(where, cfg, drives, t):
            right, wrong, rows = stress_tally(ds.name, recs, has, poses, lambda c: candidate_confidence(c, True, v, True))
            n = sum(1 for q, r in recs.items() for c in r["candidates"]
                    if c.get("verified") and has[q] and has[int(c["match"])])
            per[ds.name] = {"cloud_pairs_verified": n, "scan_rule_right": right, "scan_rule_wrong": wrong,
                            "wrong_rows": rows[:20]}
            print(f"t {t} {ds.name}: {n} verified cloud pairs, scan-rule accepts right {right} wrong {wrong}", flush=True)
        result["matcher" if t is None else str(t)] = per
    if args.json:
        write_json(args.json, {"machine": machine(), "wall_s": time.perf_counter() - t0, "drives": names,
                               "scans_max_conflict": SCANS_MAX_CONFLICT, "stress": result})


if __name__ == "__main__":
    main()
