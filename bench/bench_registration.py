"""register_batch: numpy reference vs the numba path, for G hypotheses of ~8 associations.

Workload: a noisy street scene (make_scene_pair: 15 poles, 30 planes, 1 deg / 0.1 m noise);
each group draws 6..10 associations, 80 % true matches and 20 % random same-type pairs (as
hypotheses from cliques carry a few wrong ones). Both paths get the same groups; the table shows
median / p95 wall time per call, the speed-up of the medians, the share of groups the numba path
handed to the reference (fragile) and the largest transform difference between the two. Calls
alternate between the two paths so that both see the same machine load.

    flock /tmp/bench.lock env PYTHONPATH=$PWD python bench/bench_registration.py --json out.json
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, print_table, time_calls, write_json

from graffmatch.datasets.landmark_scene import make_scene_pair
from graffmatch.registration import closed_form as cf


def workload(G: int, seed: int) -> tuple:
    sc = make_scene_pair(15, 30, seed=seed)
    rng = np.random.default_rng(seed)
    tm = sc.true_matches
    A, g = [], []
    for gi in range(G):
        n = int(rng.integers(6, 11))
        for _ in range(n):
            if rng.random() < 0.8:
                A.append(tm[rng.integers(len(tm))])
            else:
                i = int(rng.integers(len(sc.source)))
                cand = np.flatnonzero(sc.target.types == sc.source.types[i])
                A.append([i, cand[rng.integers(len(cand))]])
            g.append(gi)
    return sc.source, sc.target, np.array(A, np.int64), np.array(g, np.int64)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 50, 100, 300])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()

    load_before = os.getloadavg()
    rows = []
    for G in args.sizes:
        src, tgt, A, g = workload(G, args.seed)
        ref = cf._register_batch_reference(src, tgt, A, g)
        new, reasons = cf._register_batch_numba(src, tgt, A, g, None, 1e3, None, 0.03, 0.01, 1e-2)
        # interleaved, so both see the same machine load
        t_ref, t_new = [], []
        for _ in range(args.repeats):
            t_ref.append(time_calls(lambda: cf._register_batch_reference(src, tgt, A, g), 1, 0)[0])  # noqa: B023
            t_new.append(time_calls(lambda: cf.register_batch(src, tgt, A, g), 1, 0)[0])  # noqa: B023
        rows.append({
            "G": G, "associations": len(A),
            "ref_median_ms": round(1e3 * float(np.median(t_ref)), 3),
            "ref_p95_ms": round(1e3 * float(np.percentile(t_ref, 95)), 3),
            "numba_median_ms": round(1e3 * float(np.median(t_new)), 3),
            "numba_p95_ms": round(1e3 * float(np.percentile(t_new, 95)), 3),
            "speedup": round(float(np.median(t_ref) / np.median(t_new)), 1),
            "fragile_share": round(float(np.mean(reasons != 0)), 4),
            "max_abs_dT": float(np.abs(new.T_target_source - ref.T_target_source).max()),
        })
    load_after = os.getloadavg()
    print_table(rows, list(rows[0]))
    print(f"load average (1, 5, 15 min) before {load_before}, after {load_after}")
    write_json(args.json, {"rows": rows, "machine": machine(), "loadavg_before": load_before,
                           "loadavg_after": load_after, "repeats": args.repeats, "seed": args.seed})


if __name__ == "__main__":
    main()
