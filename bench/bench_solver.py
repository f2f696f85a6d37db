"""CLIPPER solver on the reference graphs of ../shared/bench/clipper_graphs, next to the C++ one.

    python bench/bench_solver.py [--json bench/results/solver.json] [--repeats 20]
                                 [--cpp /tmp/clipper/clipper_bench]

Single-threaded (NUMBA_NUM_THREADS=1). For each graph: the matcher's default solver config
(``GraffMatchConfig().solver``) and the paper's schedule with the reference tolerances, with
the float32 weights the graph builder produces (float64, as stored in the .npz, with
``--float64``); time, precision and recall against gt_inliers, and the reference C++ CLIPPER's.

``--cpp``: a timing program for the reference C++ CLIPPER (mit-acl/clipper), which is not part
of this repository and is not built by it: the program takes ``GRAPH.bin REPEATS nonzero|dsd_heu``,
reads the graph in the format of :func:`write_graph` and prints one JSON line with CLIPPER's
own timer per repeat and the selection. It then runs in this same run, on the same graphs
and the same seeded start vector, in blocks interleaved with the Python timings so that both
see the same machine load; its time is its own timer (``soln.t``: the solve and the rounding,
not the graph setup), ours is the whole ``solve_clipper`` call (input checks, pruning, greedy
cliques, rounding). Without ``--cpp``, the C++ numbers are read from reference_cpp.json
(measured on another machine state).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
import scipy.sparse as sp
from _common import machine, print_table, write_json

from graffmatch.association.clipper import ClipperConfig, solve_clipper
from graffmatch.matcher import GraffMatchConfig

GRAPHS = Path(__file__).resolve().parents[2] / "shared" / "bench" / "clipper_graphs"
BLOCK = 5  # timings per interleaved block


def configs() -> dict[str, ClipperConfig]:
    return {
        "matcher-default": GraffMatchConfig().solver,
        "paper (min d, tol 1e-8)": ClipperConfig(),
    }


def write_graph(path: Path, W: sp.csr_matrix, u0: np.ndarray) -> None:
    """The graph for the --cpp program: int64 m, int64 nnz, int32 rows, int32 cols, float64 weights
    (upper triangle, zero diagonal), float64 u0[m] (the same start vector as ours)."""
    U = sp.triu(W, k=1).tocoo()
    with path.open("wb") as f:
        np.array([W.shape[0], U.nnz], dtype=np.int64).tofile(f)
        U.row.astype(np.int32).tofile(f)
        U.col.astype(np.int32).tofile(f)
        U.data.astype(np.float64).tofile(f)
        np.asarray(u0, dtype=np.float64).tofile(f)


def run_cpp(binary: str, graph: Path, repeats: int, rounding: str) -> dict:
    out = subprocess.run([binary, str(graph), str(repeats), rounding], capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout)


def time_once(fn) -> float:
    import time

    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--graphs", default=str(GRAPHS))
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--cpp", default=None, help="path to a timing program for the reference C++ CLIPPER (not in this repository)")
    ap.add_argument("--float64", action="store_true", help="also time the float64 weights")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    root = Path(args.graphs)
    ref = json.loads((root / "reference_cpp.json").read_text())
    load_start = os.getloadavg()[0]
    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="bench_solver_"))
    for name in sorted(ref, key=lambda n: (int(n.split("_")[0][1:]), n)):
        z = np.load(root / name)
        W64 = sp.csr_matrix((z["M_data"], z["M_indices"], z["M_indptr"]), shape=tuple(z["M_shape"]))
        gt = set(z["gt_inliers"].tolist())
        m = W64.shape[0]
        u0 = np.random.default_rng(0).uniform(0.0, 1.0, m)  # = ClipperConfig(seed=0)'s start
        cases = [(label, cfg, dt) for label, cfg in configs().items()
                 for dt in ((np.float32, np.float64) if args.float64 else (np.float32,))]
        mats = {np.float32: W64.astype(np.float32), np.float64: W64}
        sols = {c[0] + str(c[2]): solve_clipper(mats[c[2]], c[1]) for c in cases}  # also compiles
        times: dict[str, list[float]] = {c[0] + str(c[2]): [] for c in cases}
        cpp_times: dict[str, list[float]] = {"nonzero": [], "dsd_heu": []}
        cpp_nodes: dict[str, list[int]] = {}
        if args.cpp:
            write_graph(tmp / "g.bin", W64, u0)
            for rnd in cpp_times:
                run_cpp(args.cpp, tmp / "g.bin", 1, rnd)  # warm the page cache
        for _ in range(max(1, args.repeats // BLOCK)):  # interleaved blocks: same load for both
            for label, cfg, dt in cases:
                W = mats[dt]
                times[label + str(dt)] += [time_once(lambda W=W, cfg=cfg: solve_clipper(W, cfg))
                                           for _ in range(BLOCK)]
            if args.cpp:
                for rnd in cpp_times:
                    res = run_cpp(args.cpp, tmp / "g.bin", BLOCK, rnd)
                    cpp_times[rnd] += res["seconds"]
                    cpp_nodes[rnd] = res["nodes"]
        for label, _cfg, dt in cases:
            key = label + str(dt)
            sol, t = sols[key], np.array(times[key])
            sel = set(sol.selected.tolist())
            tp = len(sel & gt)
            med = float(np.median(t))
            row = {
                "graph": name.replace("_s0.npz", ""), "m": m, "nnz/2": W64.nnz // 2, "config": label,
                "weights": np.dtype(dt).name, "median_ms": round(1e3 * med, 2),
                "p95_ms": round(1e3 * float(np.percentile(t, 95)), 2),
                "precision": round(tp / max(len(sel), 1), 3), "recall": round(tp / len(gt), 3),
                "selected": len(sel), "matvecs": sol.matvecs, "chosen": sol.info.get("chosen", "clipper"),
                "greedy_work/nnz": round(sol.info.get("greedy_work", 0) / max(W64.nnz, 1), 2),
            }
            if args.cpp:  # the matcher keeps every positive entry (then a clique): NONZERO rounding
                ct = np.array(cpp_times["nonzero"])
                csel = set(cpp_nodes["nonzero"])
                row.update(cpp_source="same run", cpp_ms=round(1e3 * float(np.median(ct)), 2),
                           cpp_p95_ms=round(1e3 * float(np.percentile(ct, 95)), 2),
                           cpp_dsd_heu_ms=round(1e3 * float(np.median(cpp_times["dsd_heu"])), 2),
                           cpp_precision=round(len(csel & gt) / max(len(csel), 1), 3),
                           cpp_recall=round(len(csel & gt) / len(gt), 3), same_selection=csel == sel,
                           vs_cpp=round(med / float(np.median(ct)), 2))
            else:
                r = ref[name]["nonzero"]
                row.update(cpp_source="reference_cpp.json", cpp_ms=round(1e3 * r["solver_seconds_median"], 2),
                           cpp_precision=r["precision"], cpp_recall=r["recall"],
                           vs_cpp=round(med / r["solver_seconds_median"], 2))
            rows.append(row)
    print_table(rows, ["graph", "m", "nnz/2", "config", "weights", "median_ms", "p95_ms", "precision", "recall",
                       "selected", "matvecs", "chosen", "greedy_work/nnz", "cpp_ms", "cpp_p95_ms", "cpp_recall",
                       "same_selection", "vs_cpp"])
    mach = machine()
    mach["loadavg_1min_start"] = load_start
    print(f"load average (1 min): {load_start:.2f} at start, {mach['loadavg_1min']:.2f} at end")
    write_json(args.json, {"benchmark": "solver", "machine": mach,
                           "cpp_source": "same run: " + args.cpp if args.cpp else "reference_cpp.json",
                           "rows": rows})


if __name__ == "__main__":
    main()
