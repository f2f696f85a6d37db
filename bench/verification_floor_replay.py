"""Replay of bench/verification.py's recorded rows (support points and raw scans, both splits) under the
confidence floor ``VerificationConfig.min_valid_confidence``: which valid answers it removes (docs/verification.md,
session 21). Offline: the rows' overlap, rival ratio and conflict give each answer's confidence.

    PYTHONPATH=$PWD python bench/verification_floor_replay.py --json bench/results/verification_floor_replay.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from verification import answered, decide, metrics

from graffmatch.verification.config import VerificationConfig
from graffmatch.verification.decision import confidence_of

RESULTS = Path(__file__).resolve().parent / "results"
KEYS = ("valid", "valid_correct", "precision", "recall")


def replay(rows: list[dict], thresholds: dict, evidence: str, floor: float) -> dict:
    """Before / after the floor for one split of one evidence, and the valid answers it removes."""
    cfg = VerificationConfig().for_evidence(["line", "plane"], evidence)
    th = (thresholds["min_overlap"], thresholds["max_rival_ratio"], thresholds["max_conflict"])
    ans, valid = answered(rows, *th), decide(rows, *th)
    conf = np.array([confidence_of(r["score"], r["ratio"], cfg, r.get("conflict") or 0.0) for r in ans])
    after = valid & (conf >= floor)
    removed = [{"ds": r["ds"], "i": r["i"], "j": r["j"], "confidence": float(c), "correct": bool(r["correct"]),
                "rot_deg": r.get("rot"), "tr_m": r.get("tr")}
               for r, c, a, b in zip(ans, conf, valid, after, strict=True) if a and not b]
    mb, ma = metrics(ans, valid), metrics(ans, after)
    return {"before": {k: mb[k] for k in KEYS}, "after": {k: ma[k] for k in KEYS}, "removed": removed}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=Path, default=RESULTS / "verification_scans_session15_final.json")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    d = json.loads(args.rows.read_text())
    floor = VerificationConfig().min_valid_confidence
    out: dict = {"source": str(args.rows), "floor": floor}
    for evidence, key, thresholds in (("support", "rows_support", d["support_thresholds"]),
                                      ("scans", "rows_scans", d["thresholds_scans"])):
        for split in ("cal", "test"):
            res = replay([r for r in d[key] if r["split"] == split], thresholds, evidence, floor)
            out[f"{evidence}_{split}"] = res
            print(f"{evidence} {split}: before {res['before']}, after {res['after']}, removed {res['removed']}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
