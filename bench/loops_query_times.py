"""Per-query time distribution of recorded `graffmatch loops` / `bench/bench_loops.py` runs (session 13).

    python bench/loops_query_times.py LABEL=OUT/DRIVE/ours ... --json bench/results/....json

Reads each run's ``queries.jsonl`` (one record a query: ``verify_s`` wall, ``verify_cpu_s`` CPU
since session 13, the workers' kernel warm-up ``warmup_s``) and ``loops.csv``, and reports what a
mean hides: the benchmark's figure (mean over every query, the ones without candidates at 0), the
median / p95 / max of the queries with candidates, the slowest queries with their verifications
(on points or landmarks, ms each), and whether the accepted loops are byte-identical to the first
run's.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json


def summarize(run: Path, slowest: int = 4) -> dict:
    """The distribution of one run's query times (ms) and its slowest queries."""
    recs = sorted((json.loads(line) for line in open(run / "queries.jsonl")), key=lambda r: r["query"])
    wall = 1e3 * np.array([r["verify_s"] for r in recs])
    withc = [r for r in recs if r["candidates"]]
    w = 1e3 * np.array([r["verify_s"] for r in withc])
    out = {"queries": len(recs), "with_candidates": len(withc), "ms_mean_all": float(wall.mean()),
           "ms_median": float(np.median(w)), "ms_p95": float(np.percentile(w, 95)), "ms_max": float(w.max()),
           "candidates_per_query": float(np.mean([len(r["candidates"]) for r in withc])),
           "verified_per_query": float(np.mean([sum(c.get("verified", False) for c in r["candidates"]) for r in withc])),
           "verified_on_points_per_query": float(np.mean(
               [sum(bool(c.get("on_points")) for c in r["candidates"] if c.get("verified")) for r in withc]))}
    if all("verify_cpu_s" in r for r in withc):
        c = 1e3 * np.array([r["verify_cpu_s"] for r in withc])
        out.update(cpu_ms_mean_all=float(c.sum() / len(recs)), cpu_ms_median=float(np.median(c)),
                   cpu_ms_p95=float(np.percentile(c, 95)), cpu_ms_max=float(c.max()))
    out["worker_warmup"] = [{"wall_s": r["warmup_s"], "cpu_s": r.get("warmup_cpu_s")} for r in recs if r.get("warmup_s")]
    out["slowest"] = [{"query": r["query"], "ms": 1e3 * r["verify_s"], "candidates": len(r["candidates"]),
                       "verified": [{"match": c["match"], "on_points": bool(c.get("on_points")),
                                     "ms": 1e3 * c.get("verify_seconds", 0.0)} for c in r["candidates"] if c.get("verified")]}
                      for r in sorted(withc, key=lambda r: -r["verify_s"])[:slowest]]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="LABEL=FOLDER (the folder holding queries.jsonl and loops.csv)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    rows, first = [], None
    for spec in args.runs:
        label, folder = spec.split("=", 1)
        row = {"label": label, "folder": folder, **summarize(Path(folder))}
        loops = (Path(folder) / "loops.csv").read_bytes()
        first = first if first is not None else loops
        row["loops_csv_identical_to_first"] = loops == first
        rows.append(row)
        print(f"{label}: mean (all queries) {row['ms_mean_all']:.1f} ms, median / p95 / max {row['ms_median']:.1f} / "
              f"{row['ms_p95']:.1f} / {row['ms_max']:.0f} ms, CPU mean {row.get('cpu_ms_mean_all', float('nan')):.1f} ms, "
              f"warm-up {[round(x['wall_s'], 1) for x in row['worker_warmup']]} s, slowest "
              f"{[round(s['ms']) for s in row['slowest']]} ms, loops identical {row['loops_csv_identical_to_first']}")
    write_json(str(args.json) if args.json else None, {"machine": machine(), "rows": rows})


if __name__ == "__main__":
    main()
