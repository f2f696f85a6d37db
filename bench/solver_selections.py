"""The solver's selections under solver-config variants, against the true associations.

    python bench/solver_selections.py [--seeds 16] [--workloads W1,W2] [--variants 0,1]
                                      [--no-verification] [--json bench/results/solver_selections.json]

For W1/W2 street scenes (bench_matcher.py's workloads) and each variant of the matcher's solver
config: the associations CLIPPER (+ greedy cliques) selects, their precision and recall against
the scene's true associations, mat-vecs, whether the selection equals the first variant's, and
match()'s final outcome (valid, rotation / translation error) with that solver. Counts only,
no timing (runs anywhere, at any load).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import machine, print_table, write_json

import graffmatch.matcher as gm
from graffmatch.datasets.landmark_scene import make_scene_pair
from graffmatch.geometry.transforms import transform_errors
from graffmatch.verification.config import VerificationConfig

VARIANTS = {
    "linear backtracking tol 1e-3/1e-4 (session 5)": {"line_search": "backtracking_linear", "tol_u": 1e-3,
                                                      "tol_F": 1e-4, "step_cap": 0.0},
    "linear backtracking, step cap 8 / F (default)": {"line_search": "backtracking_linear", "tol_u": 1e-3,
                                                      "tol_F": 1e-4, "step_cap": 8.0},
    "backtracking tol 1e-3/1e-4": {"line_search": "backtracking", "tol_u": 1e-3, "tol_F": 1e-4, "step_cap": 0.0},
    "exact tol 1e-3/1e-4": {"line_search": "exact", "tol_u": 1e-3, "tol_F": 1e-4},
    "exact tol 1e-2/1e-2": {"line_search": "exact", "tol_u": 1e-2, "tol_F": 1e-2},
}
WORKLOADS = {"W1": (15, 30), "W2": (30, 60), "W3": (60, 120)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=16)
    ap.add_argument("--workloads", default="W1,W2")
    ap.add_argument("--variants", default=None, help="comma-separated indices into VARIANTS (default: all)")
    ap.add_argument("--no-verification", action="store_true", help="match() without verification (W3: seconds)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    variants = VARIANTS if args.variants is None else {
        k: v for i, (k, v) in enumerate(VARIANTS.items()) if str(i) in args.variants.split(",")}
    captured: list = []
    solve = gm.solve_clipper

    def spy(W, cfg=None, u0=None):
        sol = solve(W, cfg, u0)
        captured.append(sol)
        return sol

    gm.solve_clipper = spy
    build = gm.build_consistency_graph
    rows, per_case = [], []
    for wl in args.workloads.split(","):
        for seed in range(args.seeds):
            sc = make_scene_pair(*WORKLOADS[wl], seed=seed)
            truth = set(map(tuple, sc.true_matches.tolist()))
            first = None
            for label, upd in variants.items():
                cfg = gm.GraffMatchConfig(solver=gm.GraffMatchConfig().solver.model_copy(update=upd),
                                          verification=VerificationConfig(enabled=not args.no_verification))
                graph: list = []
                gm.build_consistency_graph = lambda *a, graph=graph, **k: graph.append(build(*a, **k)) or graph[-1]
                captured.clear()
                res = gm.GraffMatcher(cfg).match(sc.source, sc.target)
                gm.build_consistency_graph = build
                sol = captured[0]
                sel = set(map(tuple, graph[0].associations[sol.selected].tolist()))
                tp = len(sel & truth)
                rot, trans = transform_errors(res.T_target_source, sc.T_target_source) if res.T_target_source is not None else (np.inf, np.inf)
                first = sel if first is None else first
                per_case.append({"workload": wl, "seed": seed, "variant": label, "matvecs": sol.matvecs,
                                 "selected": len(sel), "precision": tp / max(len(sel), 1),
                                 "recall": tp / len(truth), "same_as_first": sel == first,
                                 "valid": bool(res.valid), "rot_err_deg": float(rot), "trans_err_m": float(trans)})
    for wl in args.workloads.split(","):
        for label in variants:
            cs = [c for c in per_case if c["workload"] == wl and c["variant"] == label]
            rows.append({"workload": wl, "variant": label, "cases": len(cs),
                         "matvecs_mean": round(float(np.mean([c["matvecs"] for c in cs])), 1),
                         "precision": round(float(np.mean([c["precision"] for c in cs])), 4),
                         "recall": round(float(np.mean([c["recall"] for c in cs])), 4),
                         "same_selection": sum(c["same_as_first"] for c in cs),
                         "valid": sum(c["valid"] for c in cs),
                         "ok_5deg_1m": sum(c["valid"] and c["rot_err_deg"] < 5 and c["trans_err_m"] < 1 for c in cs)})
    print_table(rows, ["workload", "variant", "cases", "matvecs_mean", "precision", "recall", "same_selection",
                       "valid", "ok_5deg_1m"])
    diff = [c for c in per_case if not c["same_as_first"]]
    for c in diff:
        print("differs:", c["workload"], "seed", c["seed"], c["variant"],
              f"precision {c['precision']:.3f} recall {c['recall']:.3f}")
    write_json(args.json, {"benchmark": "solver_selections", "machine": machine(),
                            "verification": not args.no_verification, "rows": rows, "cases": per_case})


if __name__ == "__main__":
    main()
