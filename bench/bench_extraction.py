"""Front-end latency per stage on the real HDL-64E scans (issue #3 target: <= 100 ms per
~120k-point scan for poles + planes on one core).

KITTI scans here have no SemanticKITTI labels, so the main rows use the geometric pole mode.
The semantic mode is timed on the same scans with synthetic labels: points within 0.3 m of the
geometric poles' axes get class 80 (pole), so the DBSCAN input has a realistic size.

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_extraction.py [--repeats 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import warnings
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data"
    )
    ap.add_argument("--repeats", type=int, default=5, help="runs per scan (after one warm-up)")
    ap.add_argument("--threads", type=int, default=1, help="OpenMP threads for Open3D (default 1)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    os.environ["OMP_NUM_THREADS"] = str(args.threads)  # before Open3D is imported

    import numpy as np

    from graffmatch.geometry.landmarks import LandmarkType
    from graffmatch.lidar import LandmarkExtractor, LandmarkExtractorConfig, read_points

    scans = sorted((args.data / "kitti00_first6" / "velodyne").glob("*.bin"))
    if not scans:
        raise SystemExit(f"no scans under {args.data / 'kitti00_first6'}")
    clouds = [read_points(p) for p in scans]
    ex = LandmarkExtractor(LandmarkExtractorConfig())

    def synthetic_labels(pts: np.ndarray) -> np.ndarray:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ls = ex.extract(pts).of_type(LandmarkType.LINE)
        lab = np.zeros(len(pts), np.uint32)
        P = pts[:, :3].astype(float)
        for a, d in zip(ls.anchors, ls.directions, strict=True):  # a handful of poles
            q = P - a
            dist = np.linalg.norm(q - np.outer(q @ d, d), axis=1)
            lab[(dist < 0.3) & (np.abs(q @ d) < 4.0)] = 80
        return lab

    results = {}
    for mode in ("geometric", "semantic"):
        rows: dict[str, list[float]] = {}
        counts = []
        for pts in clouds:
            labels = synthetic_labels(pts) if mode == "semantic" else None
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ex.extract(pts, labels)  # warm-up (numpy / Open3D first-call costs)
                for _ in range(args.repeats):
                    ls = ex.extract(pts, labels)
                    for k, v in ex.last_timings.items():
                        rows.setdefault(k, []).append(1000 * v)
                    for k, v in ex.last_cpu_timings.items():
                        rows.setdefault("cpu_" + k, []).append(1000 * v)
            counts.append(ls.counts())
        results[mode] = {
            k: {
                "median_ms": float(np.median(v)),
                "p95_ms": float(np.percentile(v, 95)),
                "n": len(v),
            }
            for k, v in rows.items()
        }
        results[mode]["_counts"] = counts
    print(
        f"front-end latency on {len(clouds)} KITTI HDL-64E scans (~{np.mean([len(c) for c in clouds]):.0f} "
        f"points), {args.repeats} runs each, OMP_NUM_THREADS={args.threads}, load {os.getloadavg()[0]:.2f}"
    )
    print("wall = elapsed time (inflated when the machine is loaded); cpu = process CPU time")
    head = f"{'stage':<10} |"
    for mode in ("geometric", "semantic"):
        head += f" {mode + ' wall med':>19} {'p95':>6} {'cpu med':>8} {'p95':>6} |"
    print(head + "  [ms]")
    for stage in ("validate", "ground", "poles", "planes", "assemble", "total"):
        line = f"{stage:<10} |"
        for mode in ("geometric", "semantic"):
            w, c = results[mode][stage], results[mode]["cpu_" + stage]
            line += f" {w['median_ms']:19.1f} {w['p95_ms']:6.1f} {c['median_ms']:8.1f} {c['p95_ms']:6.1f} |"
        print(line)
    meta = {
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "load_1min": os.getloadavg()[0],
        "threads": args.threads,
        "repeats": args.repeats,
        "config": json.loads(ex.config.model_dump_json()),
    }
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"meta": meta, "results": results}, indent=1))


if __name__ == "__main__":
    main()
