"""The trust of ``valid`` on real scans matched as bare landmark maps (no support points), against the same
pairs matched with their support points: every pair of balm_courtyard's 89 scans (issue "Trustworthy results";
session 20).

    PYTHONPATH=$PWD nice -n 5 python bench/verification_bare_real.py --json bench/results/verification_bare_real.json

Why: compact landmark maps (re-localisation, map merging, the loop database's landmark-rich scans) are matched
on landmark-level evidence, whose thresholds were chosen on generated pairs (``bench/fuzz_validity.py``: at most
0.1 % of valid results wrong). A real, symmetric courtyard with long facades and repeated columns is the case
those pairs do not hold. Each scan is extracted once (``ScanMatcher.extract``, the extractor's support points
kept); each unordered pair is matched with ``GraffMatcher`` twice: on the bare landmarks
(``LandmarkSet.without_points``) and on the landmarks with their points. A valid result is wrong when it is off
the ground truth by more than 5 deg or 1 m (the loop benchmark's end-to-end tolerance). Nothing is chosen here.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json

COURTYARD = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "balm_courtyard"


def summarise(rows: list[dict]) -> dict:
    """Valid, valid-and-right, valid-and-wrong, precision, and the wrong ones (worst first)."""
    valid = [r for r in rows if r["valid"]]
    is_wrong = [r["rot_deg"] > 5.0 or r["tr_m"] > 1.0 for r in valid]
    wrong = [r for r, w in zip(valid, is_wrong, strict=True) if w]
    rr = np.array([r["rival_ratio"] for r, w in zip(valid, is_wrong, strict=True)
                   if not w and r["rival_ratio"] is not None], float)
    return {"pairs": len(rows), "valid": len(valid), "valid_wrong": len(wrong),
            "precision": 1.0 - len(wrong) / max(len(valid), 1),
            "valid_right_rival_ratio_median": float(np.median(rr)) if len(rr) else None,
            "wrong": sorted(({k: r[k] for k in ("query", "match", "gt_distance_m", "rot_deg", "tr_m", "confidence",
                                                "rival_ratio")} for r in wrong), key=lambda r: -r["tr_m"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=COURTYARD)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    from graffmatch.datasets.folder import KittiFolder
    from graffmatch.geometry.transforms import transform_errors
    from graffmatch.matcher import GraffMatcher
    from graffmatch.pipeline import ScanMatcher

    warnings.simplefilter("ignore")
    ds = KittiFolder(args.data)
    P = np.asarray(ds.poses)
    sm, gm = ScanMatcher(), GraffMatcher()
    t0 = time.perf_counter()
    with_points = [sm.extract(ds[i].points) for i in range(len(ds))]
    bare = [ls.without_points() for ls in with_points]
    extract_s = time.perf_counter() - t0
    modes: dict[str, list[dict]] = {"bare": [], "points": []}
    seconds = {}
    for mode, sets in (("bare", bare), ("points", with_points)):
        t0 = time.perf_counter()
        for q in range(len(ds)):
            for m in range(q):
                res = gm.match(sets[q], sets[m])
                Tg = np.linalg.solve(P[m], P[q])
                row = {"query": q, "match": m, "valid": bool(res.valid), "confidence": float(res.confidence),
                       "gt_distance_m": float(np.linalg.norm(Tg[:3, 3])), "rival_ratio": res.info.get("rival_ratio"),
                       "rot_deg": float("inf"), "tr_m": float("inf")}
                if res.T_target_source is not None:  # bench/verification.py's measure
                    rot, tr = transform_errors(res.T_target_source, Tg)
                    row.update(rot_deg=float(rot), tr_m=float(tr))
                modes[mode].append(row)
        seconds[mode] = time.perf_counter() - t0
        s = summarise(modes[mode])
        print(f"{mode}: {s['pairs']} pairs, {s['valid']} valid, {s['valid_wrong']} valid and wrong "
              f"(precision {s['precision']:.4f}), {seconds[mode]:.0f} s", flush=True)
    out = {"machine": machine(), "data": str(args.data), "extract_s": extract_s, "seconds": seconds,
           "tolerance": {"deg": 5.0, "m": 1.0}, **{m: summarise(rows) for m, rows in modes.items()}}
    both = {(r["query"], r["match"]) for r in modes["bare"] if r["valid"]} & {
        (r["query"], r["match"]) for r in modes["points"] if r["valid"]}
    out["valid_in_both"] = len(both)
    write_json(str(args.json) if args.json else None, out)


if __name__ == "__main__":
    main()
