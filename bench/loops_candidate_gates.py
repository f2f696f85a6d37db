"""Which candidates could the loop detector skip? (issue 15, query time on balm_courtyard)

    PYTHONPATH=$PWD nice -n 19 python bench/loops_candidate_gates.py --runs /tmp/loops6/ours2 \\
        --json bench/results/loops_candidate_gates.json

Verifies every one of the top-20 retrieved candidates of every query of one sequence (default:
balm_courtyard; quick-check gates off, no early stop; the benchmark configuration otherwise) on
the landmark tables of a ``bench/bench_loops.py`` run (``--runs``), and records per candidate
the quick check (inliers, fraction, estimated distance), the verified matcher's answer and our
confidence, and the ground-truth distance. Then it replays the detector's candidate policy on
these records (quick fraction gate, translation gate from ``n`` inliers, at most ``max_verified``
verified best quick score first, stop at the first accepted) for several settings: verifications
a query, queries with a loop, wrong loops (ground truth > 5 m), and queries that lose the loop
the default policy finds. Untimed: the cost of a setting is its verifications a query.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json

COURTYARD = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "balm_courtyard"
# (top_k, quick_min_fraction, translation-gate min inliers, margin m, max_verified); first = default
POLICIES = [(20, 0.4, 6, 2.0, 5), (5, 0.4, 6, 2.0, 5), (20, 0.4, 5, 2.0, 5), (5, 0.4, 5, 2.0, 5),
            (20, 0.4, 4, 2.0, 5), (5, 0.4, 4, 2.0, 5), (20, 0.4, 6, 2.0, 3), (5, 0.4, 6, 2.0, 3),
            (20, 0.5, 6, 2.0, 5), (5, 0.5, 6, 2.0, 5)]


def replay(recs: list[dict], policy: tuple, max_translation_m: float = 5.0) -> dict:
    top_k, fmin, smin, margin, max_verified = policy
    by_q: dict[int, list[dict]] = {}
    for r in recs:
        by_q.setdefault(r["query"], []).append(r)
    n_ver, found = 0, {}
    for q, cs in by_q.items():
        cs = [c for c in cs if c["rank"] < top_k and c["quick_fraction"] >= fmin
              and not (c["quick_score"] >= smin and c["quick_translation_m"] > max_translation_m + margin)]
        cs.sort(key=lambda c: (-c["quick_score"], c["rank"]))
        for c in cs[:max_verified]:
            n_ver += 1
            if c["confidence"] >= 0.5:
                found[q] = c
                break
    return {"top_k": top_k, "quick_min_fraction": fmin, "translation_min_inliers": smin, "margin_m": margin,
            "max_verified": max_verified, "verified_per_query": n_ver / max(len(by_q), 1),
            "queries_with_loop": len(found), "wrong_loops": sum(c["gt_distance_m"] > 5.0 for c in found.values()),
            "found": sorted(found)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=Path, required=True)
    ap.add_argument("--sequence", default="balm_courtyard")
    ap.add_argument("--data", type=Path, default=Path("/tmp/loops_bench/data"))
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    import numpy as np

    from graffmatch.datasets.registry import open_dataset
    from graffmatch.evaluation.sequence_benchmark import benchmark_config
    from graffmatch.loops.database import LandmarkDatabase, load_landmarks
    from graffmatch.loops.descriptor import landmark_descriptor
    from graffmatch.loops.detector import LoopDetector
    from graffmatch.loops.quickcheck import quick_index
    from graffmatch.loops.retrieval import eligible_count

    src = COURTYARD if args.sequence == "balm_courtyard" else args.data / args.sequence
    ds = open_dataset("folder", src)
    P = np.asarray(ds.poses)[:, :3, 3]
    base = benchmark_config()
    db = LandmarkDatabase()
    files = sorted((args.runs / args.sequence / "ours" / "landmarks").glob("[0-9]" * 6 + ".npz"))
    if len(files) != len(ds):
        raise SystemExit(f"{args.runs / args.sequence}: {len(files)} landmark tables for {len(ds)} scans")
    for i, f in enumerate(files):
        ls = load_landmarks(f)
        db.add(ls, landmark_descriptor(ls, base.descriptor), float(ds.timestamps[i]))
    db.extra["quick"] = [quick_index(ls, base.quick) for ls in db.landmarks]
    cfg = base.model_copy(deep=True)
    cfg.retrieval.top_k = 20
    v = cfg.verification
    v.stop_when_accepted, v.max_verified, v.quick_min_fraction, v.quick_translation_margin_m = False, 100, 0.0, 1e9
    det = LoopDetector(cfg)
    det.db = db
    recs = []
    for q in range(len(db)):
        if eligible_count(db.timestamps, q, cfg.retrieval) <= 0:
            continue
        det.detect(q)
        for r in det.last_records:
            T = None if r["T"] is None else np.asarray(r["T"]).reshape(4, 4)
            recs.append({"query": q, "match": r["match"], "rank": r["rank"], "confidence": r["confidence"],
                         "quick_score": r["quick_score"], "quick_fraction": r["quick_fraction"],
                         "quick_translation_m": r["quick_translation_m"],
                         "estimated_distance_m": None if T is None else float(np.linalg.norm(T[:3, 3])),
                         "gt_distance_m": float(np.linalg.norm(P[q] - P[r["match"]]))})
    acc = [r for r in recs if r["confidence"] >= 0.5]
    print(f"{args.sequence}: {len({r['query'] for r in recs})} queries, {len(recs)} candidates verified, "
          f"{len(acc)} accepted ({sum(r['gt_distance_m'] > 5 for r in acc)} of them > 5 m in ground truth)")
    err = Counter()
    for r in recs:
        if r["estimated_distance_m"] is not None:
            err[r["quick_score"]] += 1
    reliab = {}
    for s in sorted(err):
        e = [abs(r["quick_translation_m"] - r["gt_distance_m"]) for r in recs if r["quick_score"] == s]
        reliab[int(s)] = {"n": len(e), "median_m": float(np.median(e)), "p90_m": float(np.percentile(e, 90))}
        print(f"  quick estimate with {s} inliers: |distance error| median {reliab[s]['median_m']:.1f} m, "
              f"p90 {reliab[s]['p90_m']:.1f} m ({len(e)} candidates)")
    rows = [replay(recs, p) for p in POLICIES]
    default = set(rows[0]["found"])
    for r in rows:
        r["lost_vs_default"] = sorted(default - set(r["found"]))
        print(f"  top {r['top_k']:2d}, fraction >= {r['quick_min_fraction']}, translation gate from "
              f"{r['translation_min_inliers']} inliers, <= {r['max_verified']} verified: "
              f"{r['verified_per_query']:.2f} verified a query, {r['queries_with_loop']} queries with a loop "
              f"({r['wrong_loops']} wrong), lost vs default: {r['lost_vs_default']}")
    write_json(str(args.json) if args.json else None,
               {"machine": machine(), "runs": str(args.runs), "sequence": args.sequence,
                "quick_estimate_error_by_inliers": reliab, "policies": rows})


if __name__ == "__main__":
    main()
