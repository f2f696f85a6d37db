"""Time of lines-only (poles only) ``match()`` with and without the pole-pair hypotheses, on the
simulated test pairs of ``bench/verification.py`` (same data and pairs; landmarks from its
cache). Interleaved per pair (one warm-up call each first), wall clock and process CPU time.
Run under the bench lock, not niced:

    flock /tmp/bench.lock env PYTHONPATH=$PWD python bench/bench_lines_time.py --out /tmp/gm-verify \
        --json bench/results/lines_time.json
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import machine, write_json
from verification import load_sources, make_pairs

from graffmatch.geometry.landmarks import LandmarkType
from graffmatch.matcher import GraffMatchConfig, GraffMatcher
from graffmatch.verification.config import VerificationConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="/tmp/gm-verify")
    ap.add_argument("--pairs", type=int, default=40, help="test positives per simulated suite")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    src = load_sources(Path(a.out), 120)
    pairs = make_pairs(src, 120, 180)
    variants = {"cliques only": 0, "with pole pairs": VerificationConfig().pair_hypotheses}
    matchers = {k: GraffMatcher(GraffMatchConfig(landmark_types=["line"], verification=VerificationConfig(
        pair_hypotheses=v))) for k, v in variants.items()}
    report: dict = {"machine": machine(), "load_before": os.getloadavg(), "suites": {}}
    for suite in ("sim-downtown", "sim-suburban", "sim-openroad"):
        lms = src[suite]["lms"]
        poles = [int(np.sum(ls.types == LandmarkType.LINE)) for ls in lms]
        sel = [p for p in pairs if p["split"] == "test" and p["positive"] and p["ds"] == suite
               and min(poles[p["i"]], poles[p["j"]]) >= 2][: a.pairs]  # matchable: two poles each
        for m in matchers.values():  # warm-up (numba compilation, caches)
            m.match(lms[sel[0]["j"]], lms[sel[0]["i"]])
        wall = {k: [] for k in matchers}
        cpu = {k: [] for k in matchers}
        for p in sel:
            for k, m in matchers.items():
                c0, t0 = time.process_time(), time.perf_counter()
                m.match(lms[p["j"]], lms[p["i"]])
                wall[k].append(time.perf_counter() - t0)
                cpu[k].append(time.process_time() - c0)
        out = {}
        for k in matchers:
            w, c = np.array(wall[k]) * 1e3, np.array(cpu[k]) * 1e3
            out[k] = {"median_ms": float(np.median(w)), "p95_ms": float(np.percentile(w, 95)),
                      "median_cpu_ms": float(np.median(c)), "pairs": len(w)}
            print(f"{suite:<14}{k:<18}median {out[k]['median_ms']:7.1f} ms  p95 {out[k]['p95_ms']:7.1f} ms  "
                  f"CPU median {out[k]['median_cpu_ms']:7.1f} ms  ({len(w)} pairs)")
        report["suites"][suite] = out
    report["load_after"] = os.getloadavg()
    print(f"load average before {report['load_before']}, after {report['load_after']}")
    if a.json:
        write_json(a.json, report)


if __name__ == "__main__":
    main()
