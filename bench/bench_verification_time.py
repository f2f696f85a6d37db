"""Cost of verification: ``match()`` with and without it, in the same run, on real KITTI and
courtyard landmark sets (support points as evidence) and on W1/W2 (landmark-level evidence),
plus raw-scan ICP refinement in ``ScanMatcher.register``. Medians, p95 and the targets.

    python bench/bench_verification_time.py --json bench/results/verification_time.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from graffmatch.datasets.folder import KittiFolder
from graffmatch.datasets.landmark_scene import make_scene_pair
from graffmatch.evaluation.suites import shared_data_root, suite_config
from graffmatch.lidar.extractor import LandmarkExtractor, LandmarkExtractorConfig
from graffmatch.matcher import GraffMatchConfig, GraffMatcher
from graffmatch.pipeline import RefinementConfig, ScanMatcher, ScanMatcherConfig
from graffmatch.verification.config import VerificationConfig


def timed(fn, repeat: int) -> np.ndarray:
    fn()  # warm-up (numba, caches)
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return np.array(out) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    root = shared_data_root()
    on = GraffMatcher()
    off = GraffMatcher(GraffMatchConfig(verification=VerificationConfig(enabled=False)))
    rows = []
    kitti = KittiFolder(root / "kitti00_first6")
    ex = LandmarkExtractor(LandmarkExtractorConfig())
    k0, k5 = ex.extract(kitti[0].points), ex.extract(kitti[5].points)
    court = KittiFolder(root / "balm_courtyard")
    exc = LandmarkExtractor(suite_config("balm_courtyard").extractor)
    c = {i: exc.extract(court[i].points) for i in (10, 16, 40, 47, 70, 75)}
    cases = {"KITTI 5->0": (k5, k0, 10.0, None), "courtyard 16->10": (c[16], c[10], 10.0, None),
             "courtyard 47->40": (c[47], c[40], 10.0, None), "courtyard 75->70": (c[75], c[70], 10.0, None)}
    for name, (n_poles, n_planes, target) in {"W1": (15, 30, None), "W2": (30, 60, None)}.items():
        sc = make_scene_pair(n_poles, n_planes, seed=0)
        cases[name] = (sc.source, sc.target, None, target)
    print(f"load average {os.getloadavg()[0]:.2f}")
    print(f"{'workload':<20}{'m':>6}{'without':>12}{'with':>12}{'p95 with':>10}{'extra':>9}  target")
    for name, (s, t, target_abs, _) in cases.items():
        t_off = timed(lambda s=s, t=t: off.match(s, t), a.repeat)
        t_on = timed(lambda s=s, t=t: on.match(s, t), a.repeat)
        r = on.match(s, t)
        extra = np.median(t_on) - np.median(t_off)
        tgt = f"<= {target_abs:.0f} ms with" if target_abs else ("<= +5 ms" if name == "W1" else "-")
        print(f"{name:<20}{r.n_putative:>6}{np.median(t_off):>10.1f}ms{np.median(t_on):>10.1f}ms"
              f"{np.percentile(t_on, 95):>8.1f}ms{extra:>7.1f}ms  {tgt}")
        rows.append({"workload": name, "m": r.n_putative, "median_without_ms": float(np.median(t_off)),
                     "median_with_ms": float(np.median(t_on)), "p95_with_ms": float(np.percentile(t_on, 95)),
                     "valid": r.valid, "timings_ms": {k: v * 1e3 for k, v in r.timings.items()}})
    sm = ScanMatcher(ScanMatcherConfig(refinement=RefinementConfig(method="icp")))
    t_reg = timed(lambda: sm.register(kitti[5].points, kitti[0].points), max(3, a.repeat // 3))
    reg = sm.register(kitti[5].points, kitti[0].points)
    print(f"\nScanMatcher.register KITTI 5->0 (2 extractions + verified match + ICP on the scans): "
          f"median {np.median(t_reg):.0f} ms; ICP {reg.timings.get('icp', 0) * 1e3:.1f} ms (target <= 30 ms), "
          f"valid={reg.valid}")
    rows.append({"workload": "register KITTI 5->0", "median_ms": float(np.median(t_reg)),
                 "icp_ms": reg.timings.get("icp", 0) * 1e3, "timings_ms": {k: v * 1e3 for k, v in reg.timings.items()}})
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({"load_average": os.getloadavg()[0], "rows": rows}, indent=1, default=float))


if __name__ == "__main__":
    main()
