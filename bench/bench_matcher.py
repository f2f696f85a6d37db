"""End-to-end GraffMatcher.match() on synthetic street landmark scenes W1/W2/W3.

    python bench/bench_matcher.py [--json bench/results/matcher.json] [--workloads W1,W2]

Each workload runs in a fresh subprocess (single thread) so that its peak RSS is its own.
W1: 15 poles + 30 planes per scan; W2: 30 + 60; W3: 60 + 120; 80 % landmark overlap,
180 deg yaw and 14 m between the views, 0.1 m / 1 deg noise.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, print_table, write_json

WORKLOADS = {"W1": (15, 30, 5.0, None), "W2": (30, 60, 30.0, None), "W3": (60, 120, 300.0, 1024.0)}


def run_one(name: str, repeats: int, seeds: int) -> dict:
    import numpy as np
    from _common import peak_rss_mb, time_calls

    from graffmatch.datasets.landmark_scene import make_scene_pair
    from graffmatch.geometry.transforms import transform_errors
    from graffmatch.matcher import GraffMatcher

    n_poles, n_planes, _, _ = WORKLOADS[name]
    base_rss = peak_rss_mb()
    matcher = GraffMatcher()
    times, stages, errs, prec, rec, ms, edges = [], {}, [], [], [], [], []
    for seed in range(seeds):
        sc = make_scene_pair(n_poles, n_planes, seed=seed)
        res = matcher.match(sc.source, sc.target)
        t = time_calls(lambda sc=sc: matcher.match(sc.source, sc.target), repeats, warmup=0)
        times += list(t)
        for k, v in res.timings.items():
            stages.setdefault(k, []).append(v)
        errs.append(transform_errors(res.T_target_source, sc.T_target_source))
        truth = set(map(tuple, sc.true_matches.tolist()))
        sel = set(map(tuple, res.associations.tolist()))
        prec.append(len(sel & truth) / max(len(sel), 1))
        rec.append(len(sel & truth) / len(truth))
        ms.append(res.n_putative)
        edges.append(res.n_edges)
    errs = np.array(errs)
    return {
        "workload": name, "m_mean": int(np.mean(ms)), "edges_mean": int(np.mean(edges)),
        "median_ms": round(1e3 * float(np.median(times)), 1),
        "p95_ms": round(1e3 * float(np.percentile(times, 95)), 1),
        "peak_rss_mb": round(peak_rss_mb(), 1), "rss_increase_mb": round(peak_rss_mb() - base_rss, 1),
        "stage_median_ms": {k: round(1e3 * float(np.median(v)), 2) for k, v in stages.items()},
        "precision": round(float(np.mean(prec)), 3), "recall": round(float(np.mean(rec)), 3),
        "rot_err_deg_median": round(float(np.median(errs[:, 0])), 3),
        "trans_err_m_median": round(float(np.median(errs[:, 1])), 3),
        "success_rate": round(float(np.mean((errs[:, 0] < 5) & (errs[:, 1] < 1))), 3),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--workloads", default="W1,W2,W3")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--json", default=None)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(run_one(args.child, args.repeats, args.seeds)))
        return
    rows = []
    env = dict(os.environ, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    for name in args.workloads.split(","):
        out = subprocess.run(
            [sys.executable, __file__, "--child", name, "--repeats", str(args.repeats), "--seeds", str(args.seeds)],
            capture_output=True, text=True, env=env, check=True,
        )
        row = json.loads(out.stdout.strip().splitlines()[-1])
        row["target_ms"] = WORKLOADS[name][2]
        row["target_mb"] = WORKLOADS[name][3] or ""
        rows.append(row)
    print_table(rows, ["workload", "m_mean", "edges_mean", "median_ms", "p95_ms", "target_ms", "peak_rss_mb",
                       "target_mb", "precision", "recall", "rot_err_deg_median", "trans_err_m_median", "success_rate"])
    for r in rows:
        print(r["workload"], "stage medians [ms]:", r["stage_median_ms"])
    write_json(args.json, {"benchmark": "matcher", "machine": machine(), "rows": rows})


if __name__ == "__main__":
    main()
