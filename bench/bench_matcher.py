"""End-to-end GraffMatcher.match() on KITTI 0->5 and synthetic street landmark scenes W1/W2/W3.

    python bench/bench_matcher.py [--json bench/results/matcher.json] [--workloads KITTI,W1,W2]
                                  [--no-verification] [--max-dense-block-mb MB]

Each workload runs in a fresh subprocess (single thread) so that its peak RSS is its own
(``peak_rss_mb``: the whole process, imports included; ``rss_increase_mb``: above the RSS
after the warm-up match). KITTI: scans 0 and 5 of kitti00_first6 with the default extractor
(extraction not timed here, see bench_extraction.py), true associations from the official
poses (tau_d 6 deg). W1: 15 poles + 30 planes per scan; W2: 30 + 60; W3: 60 + 120; 80 %
landmark overlap, 180 deg yaw and 14 m between the views, 0.1 m / 1 deg noise. Stage medians are
over the timed calls (not the first call of a case, which may load compiled code).
``--no-verification``: the paper's single-clique matcher (association, graph, solver,
registration; ``VerificationConfig(enabled=False)``), the configuration of the speed targets.
``median_cpu_ms``: the process CPU time of the same calls (one thread), which a loaded machine
inflates far less than the wall time; ``load_start``/``load_end``: the 1-min load average.
``--max-dense-block-mb``: the solver's ``max_dense_block_mb`` (default: the matcher's).
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

WORKLOADS = {"KITTI": (0, 0, 3.0, None), "W1": (15, 30, 5.0, None), "W2": (30, 60, 40.0, None),
             "W3": (60, 120, 1000.0, 600.0)}
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def kitti_case():
    """Landmarks of KITTI 00 scans 0 (source) and 5 (target), the official relative pose and the
    true associations, as a scene-pair-like object."""
    import warnings
    from types import SimpleNamespace

    from graffmatch.datasets.folder import KittiFolder
    from graffmatch.evaluation.loop_closures import ground_truth_matches
    from graffmatch.geometry.transforms import invert
    from graffmatch.lidar import LandmarkExtractor, LandmarkExtractorConfig

    ds = KittiFolder(DATA / "kitti00_first6")
    ex = LandmarkExtractor(LandmarkExtractorConfig())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        src, tgt = (ex.extract(ds[i].xyz).without_points() for i in (0, 5))
    T = invert(ds.poses[5]) @ ds.poses[0]
    M, _ = ground_truth_matches(src, tgt, T)
    return SimpleNamespace(source=src, target=tgt, T_target_source=T, true_matches=M)


def run_one(name: str, repeats: int, seeds: int, verification: bool = True,
            max_dense_block_mb: float | None = None) -> dict:
    import time

    import numpy as np
    from _common import peak_rss_mb

    from graffmatch.datasets.landmark_scene import make_scene_pair
    from graffmatch.geometry.transforms import transform_errors
    from graffmatch.matcher import GraffMatchConfig, GraffMatcher
    from graffmatch.verification.config import VerificationConfig

    n_poles, n_planes, _, _ = WORKLOADS[name]
    cfg = GraffMatchConfig(verification=VerificationConfig(enabled=verification))
    if max_dense_block_mb is not None:
        cfg.solver = cfg.solver.model_copy(update={"max_dense_block_mb": max_dense_block_mb})
    matcher = GraffMatcher(cfg)
    warm = make_scene_pair(5, 10, seed=0)
    matcher.match(warm.source, warm.target)  # compiled code loaded before the baseline
    cases = [kitti_case()] if name == "KITTI" else [make_scene_pair(n_poles, n_planes, seed=s) for s in range(seeds)]
    base_rss = peak_rss_mb()
    times, cpu, stages, errs, prec, rec, ms, edges, dens = [], [], {}, [], [], [], [], [], []
    for sc in cases:
        res = matcher.match(sc.source, sc.target)  # the first call may load compiled code
        timed: list = []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            timed.append(matcher.match(sc.source, sc.target))
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        for r in timed:  # stage times of the timed calls, not of the first one
            for k, v in r.timings.items():
                stages.setdefault(k, []).append(v)
        errs.append(transform_errors(res.T_target_source, sc.T_target_source))
        truth = set(map(tuple, sc.true_matches.tolist()))
        sel = set(map(tuple, res.associations.tolist()))
        prec.append(len(sel & truth) / max(len(sel), 1))
        rec.append(len(sel & truth) / len(truth))
        ms.append(res.n_putative)
        edges.append(res.n_edges)
        dens.append(2.0 * res.n_edges / max(res.n_putative * (res.n_putative - 1), 1))
    errs = np.array(errs)
    return {
        "workload": name, "cases": len(cases), "m_mean": int(np.mean(ms)), "edges_mean": int(np.mean(edges)),
        "density": round(float(np.mean(dens)), 3),
        "verification": verification,
        "median_ms": round(1e3 * float(np.median(times)), 1),
        "median_cpu_ms": round(1e3 * float(np.median(cpu)), 1),
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
    ap.add_argument("--workloads", default="KITTI,W1,W2,W3")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--no-verification", action="store_true", help="time match() without verification")
    ap.add_argument("--max-dense-block-mb", type=float, default=None, help="the solver's max_dense_block_mb")
    ap.add_argument("--json", default=None)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(run_one(args.child, args.repeats, args.seeds, not args.no_verification,
                                 args.max_dense_block_mb)))
        return
    rows = []
    load_start = os.getloadavg()[0]
    env = dict(os.environ, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    ap_seeds = {"W3": min(args.seeds, 2)}  # a W3 match takes seconds
    for name in args.workloads.split(","):
        if name == "KITTI" and not (DATA / "kitti00_first6").is_dir():
            print(f"KITTI skipped: {DATA / 'kitti00_first6'} not found")
            continue
        reps = str(min(args.repeats, 2) if name == "W3" else 10 * args.repeats if name == "KITTI" else args.repeats)
        out = subprocess.run(
            [sys.executable, __file__, "--child", name, "--repeats", reps, "--seeds", str(ap_seeds.get(name, args.seeds))]
            + (["--no-verification"] if args.no_verification else [])
            + (["--max-dense-block-mb", str(args.max_dense_block_mb)] if args.max_dense_block_mb is not None else []),
            capture_output=True, text=True, env=env, check=True,
        )
        row = json.loads(out.stdout.strip().splitlines()[-1])
        row["target_ms"] = WORKLOADS[name][2]
        row["target_mb"] = WORKLOADS[name][3] or ""
        rows.append(row)
    print_table(rows, ["workload", "cases", "m_mean", "density", "median_ms", "median_cpu_ms", "p95_ms", "target_ms", "peak_rss_mb",
                       "rss_increase_mb", "target_mb", "precision", "recall", "rot_err_deg_median",
                       "trans_err_m_median", "success_rate"])
    for r in rows:
        print(r["workload"], "stage medians [ms]:", r["stage_median_ms"])
    mach = machine()
    mach["load_start"], mach["load_end"] = load_start, mach["loadavg_1min"]
    print(f"load average (1 min): {load_start:.2f} at start, {mach['load_end']:.2f} at end")
    write_json(args.json, {"benchmark": "matcher", "machine": mach, "verification": not args.no_verification,
                           "max_dense_block_mb": args.max_dense_block_mb, "rows": rows})


if __name__ == "__main__":
    main()
