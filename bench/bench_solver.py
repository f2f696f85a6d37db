"""CLIPPER solver on the reference graphs of ../shared/bench/clipper_graphs, next to the C++ one.

    python bench/bench_solver.py [--json bench/results/solver.json] [--repeats 20]

Single-threaded (NUMBA_NUM_THREADS=1). For each graph: the matcher's default solver config
(``GraffMatchConfig().solver``: the reference C++'s homotopy, greedy cliques, tol_u 1e-3 /
tol_F 1e-4) and the paper's schedule with the reference tolerances, each with the float32
weights the graph builder produces and the float64 weights as stored in the .npz; time,
precision and recall against gt_inliers, and the reference C++ CLIPPER's time and recall on
the same graph. The C++ is not built here (no network access to mit-acl/clipper in this
environment): its numbers are read from reference_cpp.json (measured on a machine of this kind).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
import scipy.sparse as sp
from _common import machine, print_table, time_calls, write_json

from graffmatch.association.clipper import ClipperConfig, solve_clipper
from graffmatch.matcher import GraffMatchConfig

GRAPHS = Path(__file__).resolve().parents[2] / "shared" / "bench" / "clipper_graphs"


def configs() -> dict[str, ClipperConfig]:
    return {
        "matcher-default": GraffMatchConfig().solver,
        "paper (min d, tol 1e-8)": ClipperConfig(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--graphs", default=str(GRAPHS))
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    root = Path(args.graphs)
    ref = json.loads((root / "reference_cpp.json").read_text())
    rows = []
    for name in sorted(ref, key=lambda n: (int(n.split("_")[0][1:]), n)):
        z = np.load(root / name)
        W64 = sp.csr_matrix((z["M_data"], z["M_indices"], z["M_indptr"]), shape=tuple(z["M_shape"]))
        gt = set(z["gt_inliers"].tolist())
        for label, cfg in configs().items():
            for dtype in (np.float32, np.float64):
                W = W64.astype(dtype) if dtype is np.float32 else W64
                sol = solve_clipper(W, cfg)
                times = time_calls(lambda cfg=cfg, W=W: solve_clipper(W, cfg), args.repeats)
                sel = set(sol.selected.tolist())
                tp = len(sel & gt)
                r = ref[name]["nonzero"]  # the matcher keeps every positive entry (then a clique)
                med = float(np.median(times))
                rows.append({
                    "graph": name.replace("_s0.npz", ""), "m": W.shape[0], "nnz/2": W.nnz // 2,
                    "config": label, "weights": np.dtype(dtype).name,
                    "median_ms": round(1e3 * med, 2), "p95_ms": round(1e3 * float(np.percentile(times, 95)), 2),
                    "precision": round(tp / max(len(sel), 1), 3), "recall": round(tp / len(gt), 3),
                    "matvecs": sol.matvecs, "chosen": sol.info.get("chosen", "clipper"),
                    "greedy_work/nnz": round(sol.info.get("greedy_work", 0) / max(W.nnz, 1), 2),
                    "cpp_ms": round(1e3 * r["solver_seconds_median"], 2), "cpp_recall": r["recall"],
                    "vs_cpp": round(med / r["solver_seconds_median"], 2),
                })
    print_table(rows, ["graph", "m", "nnz/2", "config", "weights", "median_ms", "p95_ms", "precision", "recall",
                       "matvecs", "chosen", "greedy_work/nnz", "cpp_ms", "cpp_recall", "vs_cpp"])
    write_json(args.json, {"benchmark": "solver", "machine": machine(), "cpp_source": "reference_cpp.json",
                           "rows": rows})


if __name__ == "__main__":
    main()
