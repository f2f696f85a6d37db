"""The demo over seeds 0-19 in both modes: how often it passes (valid and within its bounds),
how often it is honestly invalid, and how often it is valid but wrong (must be 0).

    python bench/bench_demo.py --seeds 20 --json bench/results/demo_seeds.json
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

from graffmatch.demo import run_demo


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    rows = []
    for mode in ("landmarks", "lidar"):
        for s in range(a.seeds):
            r = run_demo(seed=s, mode=mode)
            rows.append({"mode": mode, "seed": s, "outcome": r.outcome, "valid": r.result.valid,
                         "rotation_error_deg": r.rotation_error_deg, "translation_error_m": r.translation_error_m,
                         "confidence": r.result.confidence, "message": r.result.message})
            print(f"{mode:<10}{s:>3}  {r.outcome:<28}{r.rotation_error_deg:8.3f} deg {r.translation_error_m:7.3f} m"
                  f"  conf {r.result.confidence:.2f}  {r.result.message[:70]}", flush=True)
    for mode in ("landmarks", "lidar"):
        c = Counter(r["outcome"] for r in rows if r["mode"] == mode)
        print(f"{mode}: " + ", ".join(f"{k} {v}" for k, v in sorted(c.items())))
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
