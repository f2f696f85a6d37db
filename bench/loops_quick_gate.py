"""Does the quick check lose loops? (issue 15) Replays the BEV quick check on every candidate
of a run in which every candidate was verified, and counts what each gate would have skipped.

    PYTHONPATH=$PWD nice -n 19 python bench/loops_quick_gate.py --runs /tmp/loops_bench/out \\
        --json bench/results/loops_quick_gate.json

``--runs``: the output folder of a ``bench/bench_loops.py`` run made with verification of all
top-5 candidates (``queries.jsonl`` per sequence, before the quick check existed). For every
candidate it records the matcher's confidence, the quick-check inliers, their fraction of the
smaller BEV map and the estimated distance; then, per gate and per sequence: candidates
verified a query, queries whose accepted loop (confidence >= 0.5) would be lost, and queries
whose reported match changes (early stop picks the first accepted, not the most confident).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json

COURTYARD = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "balm_courtyard"
GATES = [  # (min fraction, translation gate [m] or None, min inliers for it, early stop)
    (0.0, None, 0, False), (0.4, None, 0, False), (0.4, None, 0, True), (0.4, 7.0, 6, True),
    (0.5, 7.0, 6, True), (0.4, 7.0, 5, True), (0.4, 7.0, 4, True), (0.4, 6.0, 5, True),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=Path, default=Path("/tmp/loops_bench/out"))
    ap.add_argument("--data", type=Path, default=Path("/tmp/loops_bench/data"))
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    import numpy as np

    from graffmatch.datasets.registry import open_dataset
    from graffmatch.loops.database import load_landmarks
    from graffmatch.loops.quickcheck import quick_check, quick_index

    rows = []
    seqs = sorted(p.name for p in args.runs.iterdir() if (p / "ours" / "queries.jsonl").is_file())
    for name in seqs:
        src = COURTYARD if name == "balm_courtyard" else args.data / name
        P = np.asarray(open_dataset("folder", src).poses)[:, :3, 3]
        d = args.runs / name / "ours"
        qi = {}
        for line in (d / "queries.jsonl").read_text().splitlines():
            r = json.loads(line)
            for c in r["candidates"]:
                for i in (r["query"], c["match"]):
                    if i not in qi:
                        qi[i] = quick_index(load_landmarks(d / "landmarks" / f"{i:06d}.npz"))
                s, est = quick_check(qi[r["query"]], qi[c["match"]])
                rows.append({"sequence": name, "query": r["query"], "match": c["match"], "rank": c["rank"],
                             "confidence": c["confidence"], "gt_distance_m": float(np.linalg.norm(P[r["query"]] - P[c["match"]])),
                             "quick_score": s, "quick_fraction": s / max(1, min(qi[r["query"]].size, qi[c["match"]].size)),
                             "quick_translation_m": float(np.hypot(est[1], est[2]))})
        print(name, "done", flush=True)
    out = {"machine": machine(), "runs": str(args.runs), "gates": []}
    for name in seqs:
        cs = [r for r in rows if r["sequence"] == name]
        acc = [r for r in cs if r["confidence"] >= 0.5]
        out.setdefault("min_fraction_of_accepted", {})[name] = min((r["quick_fraction"] for r in acc), default=None)
    for fg, tg, s_min, stop in GATES:
        per = {}
        for name in seqs:
            by_q: dict[int, list[dict]] = {}
            for r in rows:
                if r["sequence"] == name:
                    by_q.setdefault(r["query"], []).append(r)
            n_ver = lost = changed = n_acc = 0
            for cs in by_q.values():
                best = max(cs, key=lambda c: (c["confidence"], -c["rank"]))
                passing = [c for c in cs if c["quick_fraction"] >= fg
                           and (tg is None or c["quick_score"] < s_min or c["quick_translation_m"] <= tg)]
                passing.sort(key=lambda c: (-c["quick_score"], c["rank"]))
                got = []
                for c in passing:
                    got.append(c)
                    if stop and c["confidence"] >= 0.5:
                        break
                n_ver += len(got)
                if best["confidence"] >= 0.5:
                    n_acc += 1
                    mine = max(got, key=lambda c: (c["confidence"], -c["rank"])) if got else None
                    if mine is None or mine["confidence"] < 0.5:
                        lost += 1
                    elif mine["match"] != best["match"]:
                        changed += 1
            per[name] = {"verified_per_query": n_ver / max(len(by_q), 1), "queries_with_accepted_loop": n_acc,
                         "lost": lost, "match_changed": changed}
        out["gates"].append({"min_fraction": fg, "translation_gate_m": tg, "translation_min_inliers": s_min,
                             "early_stop": stop, "per_sequence": per})
        print(fg, tg, s_min, stop, per, flush=True)
    write_json(str(args.json) if args.json else None, out)


if __name__ == "__main__":
    main()
