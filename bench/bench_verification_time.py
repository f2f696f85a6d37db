"""Cost of verification: ``match()`` with and without it, in the same run, on real KITTI and
courtyard landmark sets (support points as evidence) and on W1/W2 (landmark-level evidence),
plus the raw-scan path ``ScanMatcher.register`` (ICP on the scans). Medians, p95, the targets,
the process's peak RSS and the load average during the run.

``with (cold)`` clears the per-scan evidence cache (``graffmatch.verification.evidence.
evidence_cache``) and the per-set cache of distances and landmark arrays
(``graffmatch.geometry.set_cache.derived_cache``) before every call: a pair seen for the first
time. ``with (warm)`` keeps it:
a scan verified against several candidates (loop detection) pays for its support cloud once.
Calls of the three variants are interleaved, so load changes hit them alike. Each call is timed
twice: wall clock, and the process's CPU time (``time.process_time``), which leaves out the time
the process waits for a core on a loaded machine (it still includes slow-downs from cores shared
with other processes).

    python bench/bench_verification_time.py --json bench/results/verification_time.json

``--kitti-pairs`` also times every pair of the six KITTI scans (15 pairs, each direction once,
warm): the issue's target is a median over KITTI-size sets, and 5->0 alone is among the
fastest of them.

``--sets DIR`` stores the extracted landmark sets there on the first run and loads them on the
next, so runs of different code versions time verification on the same inputs (the extractor
changes what is matched).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time
from pathlib import Path

import numpy as np

from graffmatch.datasets.folder import KittiFolder
from graffmatch.datasets.landmark_scene import make_scene_pair
from graffmatch.evaluation.suites import shared_data_root, suite_config
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.lidar.extractor import LandmarkExtractor, LandmarkExtractorConfig
from graffmatch.matcher import GraffMatchConfig, GraffMatcher
from graffmatch.pipeline import RefinementConfig, ScanMatcher, ScanMatcherConfig
from graffmatch.verification.config import VerificationConfig

try:
    from graffmatch.verification.evidence import evidence_cache
except ImportError:  # code before the per-scan cache (for before/after runs of this script)
    evidence_cache = None
try:
    from graffmatch.geometry.set_cache import derived_cache
except ImportError:  # code before the per-set cache of distances and landmark arrays
    derived_cache = None


def interleaved(fns: dict, repeat: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Wall and CPU times [ms] of each callable, called in turn ``repeat`` times after one
    warm-up each."""
    for f in fns.values():
        f()  # warm-up (numba, caches)
    wall: dict[str, list[float]] = {k: [] for k in fns}
    cpu: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeat):
        for k, f in fns.items():
            c0, t0 = time.process_time(), time.perf_counter()
            f()
            wall[k].append(time.perf_counter() - t0)
            cpu[k].append(time.process_time() - c0)
    return ({k: np.array(v) * 1e3 for k, v in wall.items()}, {k: np.array(v) * 1e3 for k, v in cpu.items()})


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def kitti_pairs(on: GraffMatcher, off: GraffMatcher, sets: list[LandmarkSet], repeat: int) -> dict:
    """Every pair i > j of the KITTI scans, with and without verification (warm), interleaved;
    the median and p95 over all calls, and each pair's median."""
    pairs = [(i, j) for i in range(len(sets)) for j in range(i)]
    fns = {}
    for i, j in pairs:
        fns[f"{i}->{j} without"] = lambda i=i, j=j: off.match(sets[i], sets[j])
        fns[f"{i}->{j} with"] = lambda i=i, j=j: on.match(sets[i], sets[j])
    ts, cpu = interleaved(fns, repeat)
    w_with = np.concatenate([ts[f"{i}->{j} with"] for i, j in pairs])
    w_without = np.concatenate([ts[f"{i}->{j} without"] for i, j in pairs])
    c_with = np.concatenate([cpu[f"{i}->{j} with"] for i, j in pairs])
    per_pair = {f"{i}->{j}": float(np.median(ts[f"{i}->{j} with"])) for i, j in pairs}
    sizes = [len(s) for s in sets]
    print(f"\nKITTI, all {len(pairs)} pairs ({min(sizes)}-{max(sizes)} landmarks a scan), warm: with verification "
          f"median {np.median(w_with):.1f} ms (CPU {np.median(c_with):.1f}), p95 {np.percentile(w_with, 95):.1f}; "
          f"without {np.median(w_without):.1f} ms; target <= 10 ms median with")
    print("  per pair: " + ", ".join(f"{k} {v:.1f}" for k, v in per_pair.items()))
    return {"workload": f"KITTI all {len(pairs)} pairs", "median_with_ms": float(np.median(w_with)),
            "cpu_median_with_ms": float(np.median(c_with)), "p95_with_ms": float(np.percentile(w_with, 95)),
            "median_without_ms": float(np.median(w_without)), "per_pair_median_with_ms": per_pair,
            "landmarks": sizes}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--json", default=None)
    ap.add_argument("--skip-w2", action="store_true", help="leave out W2 (~1 s per call on a loaded machine)")
    ap.add_argument("--kitti-pairs", action="store_true", help="also time all 15 KITTI pairs (warm)")
    ap.add_argument("--sets", default=None, help="directory to store / load the extracted landmark sets")
    a = ap.parse_args()
    root = shared_data_root()
    on = GraffMatcher()
    off = GraffMatcher(GraffMatchConfig(verification=VerificationConfig(enabled=False)))
    rows = []
    kitti = KittiFolder(root / "kitti00_first6")
    court = KittiFolder(root / "balm_courtyard")
    sets_dir = Path(a.sets) if a.sets else None

    def extracted(name: str, ds, i: int, cfg: LandmarkExtractorConfig) -> LandmarkSet:
        f = sets_dir / f"{name}_{i:03d}.npz" if sets_dir else None
        if f is not None and f.exists():
            return LandmarkSet.load(f)
        ls = LandmarkExtractor(cfg).extract(ds[i].points)
        if f is not None:
            f.parent.mkdir(parents=True, exist_ok=True)
            ls.save(f, include_points=True)
        return ls

    k0, k5 = (extracted("kitti", kitti, i, LandmarkExtractorConfig()) for i in (0, 5))
    c = {i: extracted("courtyard", court, i, suite_config("balm_courtyard").extractor)
         for i in (10, 16, 40, 47, 70, 75)}
    cases = {"KITTI 5->0": (k5, k0, 10.0), "courtyard 16->10": (c[16], c[10], 10.0),
             "courtyard 47->40": (c[47], c[40], 10.0), "courtyard 75->70": (c[75], c[70], 10.0)}
    for name, (n_poles, n_planes) in {"W1": (15, 30), "W2": (30, 60)}.items():
        if name == "W2" and a.skip_w2:
            continue
        sc = make_scene_pair(n_poles, n_planes, seed=0)
        cases[name] = (sc.source, sc.target, None)
    load0 = os.getloadavg()
    rss0 = peak_rss_mb()
    print(f"load average at start {load0[0]:.2f} (1 min) {load0[1]:.2f} (5 min); peak RSS after loading {rss0:.0f} MB")
    print("wall-clock medians [ms]; in brackets the medians of CPU time")
    print(f"{'workload':<18}{'m':>6}{'without':>16}{'cold':>16}{'warm':>16}{'p95 cold':>10}{'p95 warm':>10}"
          f"{'extra warm':>17}  target")
    for name, (s, t, target_abs) in cases.items():
        def cold(s=s, t=t):
            if evidence_cache is not None:
                evidence_cache.clear()
            if derived_cache is not None:
                derived_cache.clear()
            return on.match(s, t)

        ts, cpu = interleaved({"without": lambda s=s, t=t: off.match(s, t), "cold": cold,
                               "warm": lambda s=s, t=t: on.match(s, t)}, a.repeat)
        r = on.match(s, t)
        med = {k: float(np.median(v)) for k, v in ts.items()}
        mc = {k: float(np.median(v)) for k, v in cpu.items()}
        p95 = {k: float(np.percentile(v, 95)) for k, v in ts.items()}
        extra, extra_c = med["warm"] - med["without"], mc["warm"] - mc["without"]
        tgt = f"<= {target_abs:.0f} ms with" if target_abs else ("<= +5 ms" if name == "W1" else "-")
        print(f"{name:<18}{r.n_putative:>6}" + "".join(f"{med[k]:>8.1f} ({mc[k]:>5.1f})" for k in ("without", "cold", "warm"))
              + f"{p95['cold']:>10.1f}{p95['warm']:>10.1f}{extra:>9.1f} ({extra_c:>5.1f})  {tgt}")
        rows.append({"workload": name, "m": r.n_putative, "median_without_ms": med["without"],
                     "median_with_ms": med["warm"], "median_with_cold_ms": med["cold"],
                     "p95_without_ms": p95["without"], "p95_with_ms": p95["warm"], "p95_with_cold_ms": p95["cold"],
                     "cpu_median_without_ms": mc["without"], "cpu_median_with_ms": mc["warm"],
                     "cpu_median_with_cold_ms": mc["cold"],
                     "valid": r.valid, "timings_ms": {k: v * 1e3 for k, v in r.timings.items()}})
    if a.kitti_pairs:
        rows.append(kitti_pairs(on, off, [extracted("kitti", kitti, i, LandmarkExtractorConfig()) for i in range(6)],
                                a.repeat))
    sm = ScanMatcher(ScanMatcherConfig(refinement=RefinementConfig(method="icp")))
    t_reg = interleaved({"register": lambda: sm.register(kitti[5].points, kitti[0].points)},
                        max(3, a.repeat // 3))[0]["register"]
    reg = sm.register(kitti[5].points, kitti[0].points)
    print(f"\nScanMatcher.register KITTI 5->0 (2 extractions + verified match + ICP on the scans): "
          f"median {np.median(t_reg):.0f} ms; ICP {reg.timings.get('icp', 0) * 1e3:.1f} ms (target <= 30 ms), "
          f"valid={reg.valid}")
    rows.append({"workload": "register KITTI 5->0", "median_ms": float(np.median(t_reg)),
                 "icp_ms": reg.timings.get("icp", 0) * 1e3, "timings_ms": {k: v * 1e3 for k, v in reg.timings.items()}})
    load1 = os.getloadavg()
    print(f"load average at end {load1[0]:.2f} (1 min); peak RSS {peak_rss_mb():.0f} MB")
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({
            "load_average": load1[0], "load_average_start": list(load0), "load_average_end": list(load1),
            "peak_rss_mb_after_loading": rss0, "peak_rss_mb": peak_rss_mb(), "rows": rows,
        }, indent=1, default=float))


if __name__ == "__main__":
    main()
