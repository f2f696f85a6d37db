"""Retrieval recall@k of the landmark descriptor, apart from verification (issue 15).

    PYTHONPATH=$PWD nice -n 19 python bench/loops_retrieval.py --data /tmp/loops9-cal-data \\
        --out /tmp/loops9-cal-out --json bench/results/loops_retrieval_calibration.json

For each drive of a loop run (its stored landmark tables, ``OUT/<drive>+deskew/ours/landmarks``)
and each descriptor variant: the descriptors of every scan, the exact kNN over the scans older
than the exclusion window (the detector's retrieval), and recall@k = the share of positive
queries (a ground-truth partner within 5 m among the candidates) with such a partner among the
first k retrieved. Ground truth is used only to score, never to retrieve. Untimed.

``--union``: the ``descriptor+radius`` retriever instead (descriptor top-20, then the scans
within R m + f x odometry path of the drifting odometry estimate, ``prepare_drive(..., 'drift')``
as the benchmark de-skews with): recall and candidates a query for a grid of (R, f).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json

KS = [1, 5, 10, 20, 30, 40, 60]
VARIANTS: dict[str, dict] = {
    "default": {},
    "bins32": {"bins": 32},
    "no-range": {"block_weights": (1.0, 1.0, 1.0, 0.5, 0.0, 0.0)},
    "range-half": {"block_weights": (1.0, 1.0, 1.0, 0.5, 0.5, 0.5)},
    "dist32m": {"max_distance": 32.0},
    "bins32-dist32m": {"bins": 32, "max_distance": 32.0},
}


def recall_at_k(D: np.ndarray, P: np.ndarray, times: np.ndarray, retrieval, ks: list[int]) -> dict:
    from graffmatch.loops.retrieval import eligible_count

    hits = {k: 0 for k in ks}
    n_pos = 0
    for q in range(len(D)):
        m = eligible_count(times, q, retrieval)
        if m <= 0:
            continue
        d_gt = np.linalg.norm(P[:m] - P[q], axis=1)
        if d_gt.min() > 5.0:
            continue
        n_pos += 1
        dd = np.linalg.norm(D[:m] - D[q], axis=1)
        order = np.argsort(dd, kind="stable")
        near = d_gt[order] <= 5.0
        first = int(np.argmax(near))
        for k in ks:
            hits[k] += first < k
    return {"n_pos": n_pos, **{f"R@{k}": hits[k] / max(n_pos, 1) for k in ks}}


UNION_GRID = [(5.0, 0.0), (10.0, 0.0), (5.0, 0.02), (5.0, 0.05), (10.0, 0.05), (5.0, 0.1), (10.0, 0.1)]


def union_recall(D: np.ndarray, P: np.ndarray, odo_pos: np.ndarray, times: np.ndarray, retrieval,
                 radius_m: float, drift_fraction: float, top_k: int = 20) -> dict:
    """Recall of descriptor top-k plus the drift-aware odometry radius (at most top_k more)."""
    from graffmatch.loops.retrieval import eligible_count

    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(odo_pos, axis=0), axis=1))])
    n_pos = hit_desc = hit_union = 0
    n_cands = []
    for q in range(len(D)):
        m = eligible_count(times, q, retrieval)
        if m <= 0:
            continue
        d_gt = np.linalg.norm(P[:m] - P[q], axis=1)
        dd = np.linalg.norm(D[:m] - D[q], axis=1)
        top = np.argsort(dd, kind="stable")[:top_k]
        d_odo = np.linalg.norm(odo_pos[:m] - odo_pos[q], axis=1)
        keep = np.flatnonzero(d_odo <= radius_m + drift_fraction * (path[q] - path[:m]))
        keep = keep[~np.isin(keep, top)]
        keep = keep[np.argsort(d_odo[keep], kind="stable")][:top_k]
        n_cands.append(len(top) + len(keep))
        if d_gt.min() > 5.0:
            continue
        n_pos += 1
        hit_desc += bool((d_gt[top] <= 5.0).any())
        hit_union += bool((d_gt[top] <= 5.0).any() or (d_gt[keep] <= 5.0).any())
    return {"n_pos": n_pos, "R@desc": hit_desc / max(n_pos, 1), "R@union": hit_union / max(n_pos, 1),
            "candidates_per_query": float(np.mean(n_cands)) if n_cands else 0.0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS))
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--union", action="store_true", help="score the descriptor+radius retriever grid")
    args = ap.parse_args()

    from graffmatch.datasets.registry import open_dataset
    from graffmatch.evaluation.sequence_benchmark import benchmark_config
    from graffmatch.loops.database import load_landmarks
    from graffmatch.loops.descriptor import DescriptorConfig, landmark_descriptor

    cfg = benchmark_config()
    rows = []
    for p in sorted(args.data.iterdir()):
        lm_dir = args.out / f"{p.name}+deskew" / "ours" / "landmarks"
        if not (p / "poses.txt").is_file() or not lm_dir.is_dir():
            continue
        ds = open_dataset("folder", p)
        P = np.asarray(ds.poses)[:, :3, 3]
        times = np.asarray(ds.timestamps, float)
        files = sorted(lm_dir.glob("[0-9]" * 6 + ".npz"))
        if len(files) != len(P):
            continue
        lms = [load_landmarks(f) for f in files]
        if args.union:
            from graffmatch.loops.sequence import prepare_drive

            _, odo = prepare_drive(ds, "drift", True)
            D = np.stack([landmark_descriptor(ls, DescriptorConfig()) for ls in lms])
            for R, f in UNION_GRID:
                r = {"drive": p.name, "radius_m": R, "drift_fraction": f,
                     **union_recall(D, P, odo[:, :3, 3], times, cfg.retrieval, R, f)}
                rows.append(r)
                print(p.name, f"R {R} f {f}: n_pos {r['n_pos']} desc {r['R@desc']:.3f} union {r['R@union']:.3f} "
                      f"cands/query {r['candidates_per_query']:.1f}", flush=True)
            continue
        for name in args.variants:
            dc = DescriptorConfig(**VARIANTS[name])
            D = np.stack([landmark_descriptor(ls, dc) for ls in lms])
            r = {"drive": p.name, "variant": name, **recall_at_k(D, P, times, cfg.retrieval, KS)}
            rows.append(r)
            print(p.name, name, r["n_pos"], " ".join(f"R@{k} {r[f'R@{k}']:.3f}" for k in KS), flush=True)
    for R, f in UNION_GRID if args.union else []:
        sel = [r for r in rows if r.get("radius_m") == R and r.get("drift_fraction") == f]
        print(f"mean R {R} f {f}: desc {np.mean([r['R@desc'] for r in sel]):.3f} union "
              f"{np.mean([r['R@union'] for r in sel]):.3f} cands/query {np.mean([r['candidates_per_query'] for r in sel]):.1f}")
    for name in args.variants if not args.union else []:
        sel = [r for r in rows if r["variant"] == name]
        if sel:
            print("mean", name, " ".join(f"R@{k} {np.mean([r[f'R@{k}'] for r in sel]):.3f}" for k in KS))
    write_json(str(args.json) if args.json else None, {"machine": machine(), "ks": KS, "variants": VARIANTS,
                                                        "rows": rows})


if __name__ == "__main__":
    main()
