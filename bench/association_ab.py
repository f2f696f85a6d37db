"""In-process A/B of the graph build and the solver: an older checkout's modules against this one's.

    python bench/association_ab.py --before /tmp/old-checkout [--workloads W1,W2,W3]
                                   [--seeds 5] [--rounds 40] [--json bench/results/ab.json]

``--before`` is the root of another checkout of this repository (e.g. ``git worktree add
/tmp/x <commit>``). Its ``graffmatch/association/clipper.py`` and ``consistency_graph.py`` are
loaded by path next to this checkout's, and on the same graphs (the matcher's gated
associations and default solver config, W1/W2/W3 seeds 0..seeds-1) the two builds and the two
solves alternate call by call, ``rounds`` times each. A loaded machine (other processes, a
shared cache) then slows both sides alike, which separate runs of ``bench_matcher.py`` minutes
apart do not guarantee. Compiled code goes to a fresh NUMBA_CACHE_DIR (the first
calls compile, untimed). Times are the process CPU time of one call (single thread). Before
timing, each case asserts that both versions build the same CSR arrays and select the same
clique with the same u (bit for bit): it measures pure-speed changes only. With
``--allow-rounding`` it times a change that rounds differently: it then reports, per case,
whether the selection and u are equal, the largest |u_before - u_after| and the mat-vecs.
"""

from __future__ import annotations

import argparse
import atexit
import importlib.util
import os
import shutil
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, peak_rss_mb, print_table, write_json

SIZES = {"W1": (15, 30), "W2": (30, 60), "W3": (60, 120)}


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def run(before: Path, workload: str, seeds: int, rounds: int, allow_rounding: bool = False) -> dict:
    import graffmatch.association.clipper as clipper_after
    import graffmatch.association.consistency_graph as graph_after
    from graffmatch.association.putative import putative_associations
    from graffmatch.datasets.landmark_scene import make_scene_pair
    from graffmatch.geometry.distance import pairwise_distances
    from graffmatch.matcher import GraffMatchConfig

    clipper_before = _load("clipper_before", before / "graffmatch" / "association" / "clipper.py")
    graph_before = _load("consistency_graph_before", before / "graffmatch" / "association" / "consistency_graph.py")
    cfg = GraffMatchConfig()
    times: dict[str, list[float]] = {k: [] for k in ("build_before", "build_after", "solve_before", "solve_after")}
    cases: list[dict] = []
    for seed in range(seeds):
        sc = make_scene_pair(*SIZES[workload], seed=seed)
        assoc = putative_associations(sc.source, sc.target, cfg.gating)
        Di, Dj = pairwise_distances(sc.source, cfg.rho), pairwise_distances(sc.target, cfg.rho)
        kw = dict(types_i=sc.source.types, types_j=sc.target.types)
        gb = graph_before.build_consistency_graph(Di, Dj, assoc, **kw)
        ga = graph_after.build_consistency_graph(Di, Dj, assoc, **kw)
        for name in ("indptr", "indices", "data", "weighted_degrees"):
            assert np.array_equal(getattr(gb, name), getattr(ga, name)), f"graphs differ in {name}"
        gb.__class__ = graph_after.ConsistencyGraph  # the class both solvers recognise
        sb, sa = clipper_before.solve_clipper(gb, cfg.solver), clipper_after.solve_clipper(ga, cfg.solver)
        same_sel = bool(np.array_equal(sb.selected, sa.selected))
        same_u = sb.u.tobytes() == sa.u.tobytes()
        if not allow_rounding:
            assert same_sel and same_u, "solutions differ"
        cases.append({"seed": seed, "same_selection": same_sel, "same_u": same_u,
                      "max_abs_du": float(np.max(np.abs(sb.u - sa.u))) if sb.u.shape == sa.u.shape else None,
                      "matvecs_before": sb.matvecs, "matvecs_after": sa.matvecs,
                      "score_before": sb.score, "score_after": sa.score})
        if not (same_sel and same_u):
            print(f"{workload} seed {seed}: selection {'equal' if same_sel else 'DIFFERS'}, u differs "
                  f"(max |du| {cases[-1]['max_abs_du']:.2e}), mat-vecs {sb.matvecs} -> {sa.matvecs}", flush=True)
        calls = (("build_before", partial(graph_before.build_consistency_graph, Di, Dj, assoc, **kw)),
                 ("build_after", partial(graph_after.build_consistency_graph, Di, Dj, assoc, **kw)),
                 ("solve_before", partial(clipper_before.solve_clipper, gb, cfg.solver)),
                 ("solve_after", partial(clipper_after.solve_clipper, ga, cfg.solver)))
        for _ in range(rounds):
            for key, fn in calls:
                t = time.process_time()
                fn()
                times[key].append(time.process_time() - t)
        calls = gb = ga = sb = sa = None  # a W3 graph pair is ~0.5 GB: free it before the next
    row: dict = {"workload": workload, "cases": seeds, "rounds": rounds}
    for key, v in times.items():
        row[f"{key}_median_cpu_ms"] = round(1e3 * float(np.median(v)), 3)
        row[f"{key}_p95_cpu_ms"] = round(1e3 * float(np.percentile(v, 95)), 3)
    for stage in ("build", "solve"):
        b, a = row[f"{stage}_before_median_cpu_ms"], row[f"{stage}_after_median_cpu_ms"]
        row[f"{stage}_change_pct"] = round(100.0 * (a - b) / b, 1)
    row["peak_rss_mb"] = round(peak_rss_mb(), 1)
    row["selections_equal"] = sum(c["same_selection"] for c in cases)
    row["u_bit_equal"] = sum(c["same_u"] for c in cases)
    row["cases_detail"] = cases
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", required=True, type=Path, help="root of the older checkout")
    ap.add_argument("--workloads", default="W1,W2")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=40)
    ap.add_argument("--json", default=None)
    ap.add_argument("--allow-rounding", action="store_true",
                    help="time a change that may round differently: report (not assert) equal selections and u")
    args = ap.parse_args()
    if not (args.before / "graffmatch" / "association" / "clipper.py").is_file():
        sys.exit(f"--before {args.before}: no graffmatch/association/clipper.py there")
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    # numba's on-disk cache is keyed by file, not by module name: the modules loaded here under
    # other names must not share (and overwrite) the checkouts' own caches, so compile afresh
    cache = tempfile.mkdtemp(prefix="association_ab-")
    atexit.register(shutil.rmtree, cache, True)
    os.environ["NUMBA_CACHE_DIR"] = cache
    load_start = os.getloadavg()[0]
    rows = [run(args.before, w, args.seeds if w != "W3" else min(args.seeds, 2), args.rounds,
                args.allow_rounding) for w in args.workloads.split(",")]
    print_table(rows, ["workload", "cases", "rounds", "build_before_median_cpu_ms", "build_after_median_cpu_ms",
                       "build_change_pct", "solve_before_median_cpu_ms", "solve_after_median_cpu_ms",
                       "solve_change_pct", "selections_equal", "u_bit_equal"])
    mach = machine()
    mach["load_start"], mach["load_end"] = load_start, mach["loadavg_1min"]
    print(f"load average (1 min): {load_start:.2f} at start, {mach['load_end']:.2f} at end")
    write_json(args.json, {"benchmark": "association_ab", "before": str(args.before), "machine": mach, "rows": rows})


if __name__ == "__main__":
    main()
