"""Choose which scans keep their evidence points in the loop database, on calibration drives (issue 15).

    PYTHONPATH=$PWD nice -n 19 python bench/loops_calibration_points.py --data /tmp/loops9-cal-data \\
        --out /tmp/loops9-cal-out --json bench/results/loops_calibration_points.json

Landmark-poor scans (three to five landmarks: a downtown street of plain facades) cannot be
verified on landmarks alone: the verified matcher wants six explained landmarks without support
points. ``VerificationConfig.evidence_points_below`` = K keeps the matcher's evidence cloud
(quantised, ``loops/database.py``) for every scan with fewer than K landmarks, so that a pair
of two such scans is verified on points. The calibration split and the detector are those of
``bench/loops_calibration.py`` (other seeds than the reported drives; every quick-passing
candidate verified, at most ``max_verified``, no early stop). One run with K = ``--k-max``;
every verified candidate whose two scans carry points is verified again on landmarks only
(points stripped), so that the verdict under any K <= k-max is known: points when both scans
have fewer than K landmarks, landmarks otherwise. The default policy (stop at the first
accepted) is replayed for each K and scored with the benchmark's protocol.

Rule of the choice, fixed before looking: the K with e2e precision 1.00 at the default
threshold (no accepted loop that is not an end-to-end true positive) on every calibration drive
and the largest summed e2e recall at 100 % precision; ties to the smaller K (fewer bytes).
Also reported: database bytes per scan (mean and max) and verification time per K.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json
from bench_loops import simulate
from loops_calibration import CALIBRATION_DRIVES, calibration_config, replay, score

K_GRID = [0, 6, 7, 8, 10, 12]
TOP_K = [20, 30, 40]
GATE_INLIERS = [6, 5, 4]
POINTS_AGREEING = [6, 5, 4, 3, 2, 1]
SHIPPED_TOP_K = 20
DEFAULT_MAX_VERIFIED = 5


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("/tmp/loops9-cal-data"))
    ap.add_argument("--out", type=Path, default=Path("/tmp/loops9-cal-out"))
    ap.add_argument("--scans", type=int, default=400)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--k-max", type=int, default=max(K_GRID))
    ap.add_argument("--top-k", type=int, default=max(TOP_K))
    ap.add_argument("--replay-only", action="store_true")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    from graffmatch.datasets.registry import open_dataset
    from graffmatch.loops.database import load_landmarks
    from graffmatch.loops.detector import LoopDetector
    from graffmatch.loops.plan import quick_gate
    from graffmatch.loops.sequence import prepare_drive, read_queries, run_loops
    from graffmatch.loops.verify import verify_candidate

    t0 = time.perf_counter()
    cfg = calibration_config()
    cfg.verification.evidence_points_below = args.k_max
    cfg.retrieval.top_k = args.top_k  # every quick-passing candidate of the top-k verified: any
    cfg.verification.max_verified = args.top_k  # smaller k, gate and budget replay exactly
    paths = simulate(args.data, args.scans, "realistic", CALIBRATION_DRIVES)
    det = LoopDetector(cfg)
    drives = []
    for p in paths:
        ds, _ = prepare_drive(open_dataset("folder", p), "drift", True)
        out = args.out / ds.name / "ours"
        if not args.replay_only:
            t1 = time.perf_counter()
            run_loops(ds, out, cfg, workers=args.workers)
            print(f"{ds.name}: {time.perf_counter() - t1:.0f} s", flush=True)
        recs = read_queries(out)
        lms = [load_landmarks(out / "landmarks" / f"{i:06d}.npz") for i in range(len(ds))]
        n_lm = np.array([len(x) for x in lms])
        sizes = np.array([(out / "landmarks" / f"{i:06d}.npz").stat().st_size for i in range(len(ds))])
        # the landmark-only verdict of every verified candidate that was verified on points
        alt: dict[tuple[int, int], dict] = {}
        t_pts, t_lm = [], []
        for q, r in recs.items():
            for c in r["candidates"]:
                j = int(c["match"])
                if not c.get("verified", True) or lms[q].points is None or lms[j].points is None:
                    continue
                v = verify_candidate(lms[q].without_points(), lms[j].without_points(), det.matcher, cfg.verification)
                T = v["T_match_query"]
                alt[(q, j)] = {**c, "T": None if T is None else np.asarray(T).ravel().tolist(),
                               "matcher_valid": v["matcher_valid"], "matcher_confidence": v["matcher_confidence"],
                               "n_agreeing": v["n_agreeing"], "overlap": v["overlap"], "confidence": v["confidence"],
                               "on_points": False}
                t_pts.append(c.get("verify_seconds", 0.0))
                t_lm.append(v["seconds"])
        drives.append((ds, recs, n_lm, sizes, alt, t_pts, t_lm))
        print(f"{ds.name}: {int((n_lm < args.k_max).sum())} scans with points, {len(alt)} candidates on points; "
              f"bytes/scan mean {sizes.mean():.0f} max {sizes.max()}", flush=True)

    def policy(K: int, top_k: int, n_in: int, pts_agree: int = 6) -> tuple[dict, float]:
        """Scores of the default policy (top-k retrieval, quick gate from n_in inliers, at most
        max_verified verified best quick score first, stop at the first accepted) with the
        evidence points of scans below K landmarks; and verifications a query."""
        rows, n_ver, n_q = {}, 0, 0
        for ds, recs, n_lm, _sizes, alt, _, _ in drives:
            c2 = cfg.model_copy(deep=True)
            c2.verification.stop_when_accepted = True
            c2.verification.max_verified = DEFAULT_MAX_VERIFIED
            c2.verification.quick_translation_min_inliers = n_in
            c2.verification.points_min_agreeing = pts_agree
            use = {}
            for q, r in recs.items():
                cands = []
                for c in r["candidates"]:
                    if c["rank"] >= top_k:
                        continue
                    key = (q, int(c["match"]))
                    on_points = key in alt and n_lm[q] < K and n_lm[int(c["match"])] < K
                    c = {**c, "on_points": True} if on_points else alt.get(key, c)
                    if c.get("verified", True) and not quick_gate(int(c["quick_score"]), float(c["quick_fraction"]),
                                                                 float(c["quick_translation_m"]), c2.verification):
                        c = {**c, "verified": False}
                    cands.append(c)
                use[q] = {**r, "candidates": cands}
                ver = sorted((c for c in cands if c.get("verified", True)), key=lambda c: (-c["quick_score"], c["rank"]))
                for c in ver[: c2.verification.max_verified]:
                    n_ver += 1
                    if c["T"] is not None and c["confidence"] >= c2.verification.min_confidence:
                        break
                n_q += 1
            rows[ds.name] = score(ds, replay(use, c2.verification), c2)
            rows[ds.name]["scans_with_points"] = int((n_lm < K).sum())
        return rows, n_ver / max(n_q, 1)

    def entry(K: int, top_k: int, n_in: int, pts_agree: int = 6) -> dict:
        rows, vpq = policy(K, top_k, n_in, pts_agree)
        g = {"k": K, "top_k": top_k, "quick_translation_min_inliers": n_in, "points_min_agreeing": pts_agree,
             "drives": rows,
             "sum_e2e_r100p": round(sum(r["e2e_r100p"] for r in rows.values()), 6),
             "accepted_e2e_false": sum(r["accepted_e2e_false"] for r in rows.values()), "verified_per_query": vpq}
        print(f"K {K} top-{top_k} gate {n_in} points-agree {pts_agree}: sum R@100P {g['sum_e2e_r100p']:.3f} false {g['accepted_e2e_false']} "
              f"verified/query {vpq:.2f} |", " ".join(f"{n}:{r['e2e_r100p']:.2f}({r['accepted_e2e_false']})"
                                                     for n, r in rows.items()), flush=True)
        return g

    grid = [entry(K, 20, 6) for K in K_GRID if K <= args.k_max]
    best = max((g for g in grid if g["accepted_e2e_false"] == 0), key=lambda g: (g["sum_e2e_r100p"], -g["k"]))
    print("chosen K:", best["k"])
    tops = [entry(best["k"], t, 6) for t in TOP_K if t <= args.top_k]
    top = max((g for g in tops if g["accepted_e2e_false"] == 0), key=lambda g: (g["sum_e2e_r100p"], -g["top_k"]))
    print("chosen top-k:", top["top_k"])
    gates = [entry(best["k"], top["top_k"], n) for n in GATE_INLIERS]
    gate = min((g for g in gates if g["accepted_e2e_false"] == 0 and g["sum_e2e_r100p"] >= gates[0]["sum_e2e_r100p"] - 1e-9),
               key=lambda g: g["quick_translation_min_inliers"])
    print("chosen gate:", gate["quick_translation_min_inliers"])
    gates_k5 = [entry(best["k"], 5, n) for n in GATE_INLIERS]  # the time target's k = 5
    # last, with the shipped retrieval (top-20: top-30 reported a wrong courtyard loop, docs/loops.md
    # session 9) and that gate: fewest agreeing landmarks for pairs the matcher verified on points
    # (both scans below K); most summed recall at precision 1.00 everywhere, ties to the stricter
    pts = [entry(best["k"], SHIPPED_TOP_K, gate["quick_translation_min_inliers"], a) for a in POINTS_AGREEING]
    pbest = max((g for g in pts if g["accepted_e2e_false"] == 0),
                key=lambda g: (g["sum_e2e_r100p"], g["points_min_agreeing"]))
    print("chosen points_min_agreeing:", pbest["points_min_agreeing"])
    t_pts = np.concatenate([np.asarray(d[5]) for d in drives]) if drives else np.zeros(0)
    t_lm = np.concatenate([np.asarray(d[6]) for d in drives]) if drives else np.zeros(0)
    if args.json:
        write_json(args.json, {
            "machine": machine(), "wall_s": time.perf_counter() - t0, "k_max": args.k_max,
            "drives": [d[0].name for d in drives], "chosen_k": best["k"],
            "chosen_top_k": top["top_k"], "top_k_grid": tops,
            "chosen_quick_translation_min_inliers": gate["quick_translation_min_inliers"], "gates": gates,
            "gates_top5": gates_k5, "shipped_top_k": SHIPPED_TOP_K,
            "points_min_agreeing_grid": pts, "chosen_points_min_agreeing": pbest["points_min_agreeing"],
            "file_bytes_per_scan": {d[0].name: {"mean": float(d[3].mean()), "max": int(d[3].max())} for d in drives},
            "verify_ms_on_points": {"n": len(t_pts), "mean": 1e3 * float(t_pts.mean()) if len(t_pts) else None},
            "verify_ms_landmarks_only_same_pairs": {"n": len(t_lm), "mean": 1e3 * float(t_lm.mean()) if len(t_lm) else None},
            "grid": grid})


if __name__ == "__main__":
    main()
