"""Why our loop detector misses a positive query, per drive of a ``bench/bench_loops.py`` run (issue 15).

    PYTHONPATH=$PWD nice -n 19 python bench/loops_misses.py --data /tmp/loops8-data \\
        --out /tmp/loops8-out2 --messages sim-downtown-s1

For every positive query (a ground-truth partner within 5 m among its candidates) without an
end-to-end true positive at the default threshold, the first reason along the pipeline: no
partner among the retrieved candidates; every partner rejected by the quick check; partners
passed but not verified (budget, early stop); the verified matcher's verdict invalid (pose right
or wrong); valid but too few agreeing landmarks; valid but outside the place radius less the
margin (estimated distance); valid on points with enough agreeing landmarks for the sequence-
consistency rule but no neighbouring loop agreeing (the records are read through
``apply_sequence_consistency`` with the run's odometry, ``--odometry``, as the benchmark scores them).
Also the reported loops' ground-truth distance and pose errors.
``--messages DRIVE`` re-matches that drive's invalid partners and counts the matcher's messages.
Untimed; reads the run's records and landmark tables (de-skewed drives as the benchmark made them).
"""

from __future__ import annotations

import argparse
import re
from collections import Counter
from pathlib import Path

import numpy as np

COURTYARD = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "balm_courtyard"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--messages", nargs="*", default=[])
    ap.add_argument("--odometry", default="drift",
                    help="the run's odometry (bench_loops.py --odometry): drift | gt | kiss-icp (the run's cached "
                    "<out>/<drive>/kiss_icp_kitti.txt) | PATH")
    args = ap.parse_args()

    from graffmatch.datasets.registry import open_dataset
    from graffmatch.evaluation.sequence_benchmark import (
        Prediction,
        benchmark_config,
        benchmark_odometry,
        pose_errors,
        positives,
    )
    from graffmatch.loops.consistency import apply_sequence_consistency
    from graffmatch.loops.database import load_landmarks
    from graffmatch.loops.detector import LoopDetector
    from graffmatch.loops.sequence import prepare_drive, read_queries

    cfg = benchmark_config()
    v = cfg.verification
    drives = [(p.name, p, True) for p in sorted(args.data.iterdir()) if (p / "poses.txt").is_file()]
    if COURTYARD.is_dir():
        drives.append(("balm_courtyard", COURTYARD.resolve(), False))
    for name, path, deskew in drives:
        raw = open_dataset("folder", path)
        run = args.out / f"{raw.name}+deskew" / "ours" if deskew else args.out / "as-recorded" / raw.name / "ours"
        if not (run / "summary.json").is_file():
            continue
        ds, odo = prepare_drive(raw, benchmark_odometry(raw, args.odometry, args.out) if deskew else None, deskew)
        recs = apply_sequence_consistency(read_queries(run), odo, v)
        n_cons = sum("consistent_with" in c and c["confidence"] >= v.min_confidence
                     for r in recs.values() for c in r["candidates"])
        n_lm = np.array([len(load_landmarks(run / "landmarks" / f"{i:06d}.npz")) for i in range(len(ds))])
        P = np.asarray(ds.poses)
        pos = positives(P, np.asarray(ds.timestamps), cfg.retrieval, 5.0)
        why: Counter = Counter()
        poor: Counter = Counter()
        invalid = []
        errs = []
        for q, r in recs.items():
            cs = [c for c in r["candidates"] if c["T"] is not None]
            best = max(cs, key=lambda c: (c["confidence"], -c["rank"])) if cs else None
            if best is not None and best["confidence"] >= v.min_confidence:
                errs.append(pose_errors(P, Prediction(q, best["match"], 1.0, np.asarray(best["T"]).reshape(4, 4))))
        for q in np.flatnonzero(pos):
            r = recs[int(q)]
            cs = [c for c in r["candidates"] if c["T"] is not None]
            best = max(cs, key=lambda c: (c["confidence"], -c["rank"])) if cs else None
            if best is not None and best["confidence"] >= v.min_confidence:
                d, rot, tr = pose_errors(P, Prediction(int(q), best["match"], 1.0, np.asarray(best["T"]).reshape(4, 4)))
                if d <= 5 and rot <= 5 and tr <= 1:
                    continue
            near = [c for c in r["candidates"] if np.linalg.norm(P[c["match"], :3, 3] - P[q, :3, 3]) <= 5]
            ver = [c for c in near if c.get("verified") and c["T"] is not None]
            if not near:
                k = "not retrieved (top 20)"
            elif not ver:
                k = "quick check rejected" if not any(c["quick_pass"] for c in near) else "not verified (budget / stop)"
            else:
                c = max(ver, key=lambda c: (bool(c.get("matcher_valid")), c["n_agreeing"]))
                T = np.asarray(c["T"]).reshape(4, 4)
                _, rot, tr = pose_errors(P, Prediction(int(q), c["match"], 1.0, T))
                if not c.get("matcher_valid"):
                    k = f"matcher invalid (pose {'right' if rot <= 5 and tr <= 1 else 'wrong'})"
                    invalid.append((int(q), int(c["match"])))
                elif c["confidence"] == 0 and np.linalg.norm(T[:3, 3]) > v.max_translation_m - v.place_margin_m:
                    k = "valid, estimated beyond radius - margin"
                elif c["confidence"] == 0 and c.get("on_points") and odo is not None and (
                        c["n_agreeing"] >= v.consistency_min_agreeing):
                    k = "valid on points, weak, no agreeing neighbour loop"
                elif c["confidence"] == 0:
                    k = "valid, too few agreeing landmarks"
                else:
                    k = "valid, confidence < min_confidence"
            why[k] += 1
            poor[k] += int(n_lm[q] < 6)
        e = np.array(errs).reshape(-1, 3)
        print(f"{ds.name}: {int(pos.sum())} positives, {sum(why.values())} missed; {len(e)} reported, "
              f"ground truth <= {e[:, 0].max():.2f} m, rotation <= {e[:, 1].max():.2f} deg (median "
              f"{np.median(e[:, 1]):.2f}), translation <= {e[:, 2].max():.2f} m (median {np.median(e[:, 2]):.3f}); "
              f"{n_cons} candidates accepted by sequence consistency")
        for k, n in why.most_common():
            print(f"    {n:3d} {k} (queries with < 6 landmarks: {poor[k]})")
        if name in args.messages or ds.name in args.messages:
            det = LoopDetector(cfg)
            msgs: Counter = Counter()
            for q, j in invalid:
                res = det.matcher.match(load_landmarks(run / "landmarks" / f"{q:06d}.npz"),
                                        load_landmarks(run / "landmarks" / f"{j:06d}.npz"))
                msgs[re.sub(r"-?[0-9][0-9.]*", "#", res.message)] += 1
            for m, n in msgs.most_common():
                print(f"      {n:3d} {m}")


if __name__ == "__main__":
    main()
