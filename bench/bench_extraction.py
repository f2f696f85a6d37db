"""Front-end latency per stage on the real HDL-64E scans (issue #3 target: <= 100 ms per
~120k-point scan for poles + planes on one core).

KITTI scans here have no SemanticKITTI labels, so the main rows use the geometric pole mode.
The semantic mode is timed on the same scans with synthetic labels: points within 0.3 m of the
geometric poles' axes get class 80 (pole), so the DBSCAN input has a realistic size.

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_extraction.py [--repeats 5] [--json out.json]
        [--compare-detectors]

``--compare-detectors`` also runs the geometric mode with each plane detector (the voxel
region growing of graffmatch.lidar.voxels, the default, and Open3D's detect_planar_patches) in the
same run and reports their plane-stage CPU time next to their repeatability on real data: the
fraction of landmarks of scan a with a same-type counterpart in scan b within 6 deg (rho 40 m)
after ground-truth alignment, and the strict version (2 deg, 0.3 m), over the 15 KITTI pairs of
kitti00_first6 and 16 balm_courtyard pairs 5-16 m apart (``frontend_real_data.repeatability``).
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
    ap.add_argument("--compare-detectors", action="store_true")
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
    if args.compare_detectors:
        results["detectors"] = compare_detectors(args.data, args.repeats)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"meta": meta, "results": results}, indent=1))


def compare_detectors(data: Path, repeats: int) -> list[dict]:
    """Plane-stage CPU time and repeatability of both plane detectors, same run."""
    import sys

    import numpy as np

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from frontend_real_data import balm_pairs, load_poses, repeatability

    from graffmatch.geometry.transforms import invert
    from graffmatch.lidar import LandmarkExtractor, LandmarkExtractorConfig, read_bin

    sets = {"kitti00_first6": None, "balm_courtyard": None}
    k_poses = load_poses(data / "kitti00_first6")
    sets["kitti00_first6"] = (k_poses, [(a, b) for a in range(6) for b in range(a + 1, 6)])
    b_poses = load_poses(data / "balm_courtyard")
    sets["balm_courtyard"] = (b_poses, balm_pairs(b_poses, 16))
    rows = []
    for det in ("voxel", "open3d"):
        for name, (poses, pairs) in sets.items():
            base = LandmarkExtractorConfig() if name.startswith("kitti") else LandmarkExtractorConfig.short_range()
            cfg = base.model_copy(update={"planes": base.planes.model_copy(update={"detector": det})})
            ex = LandmarkExtractor(cfg)
            lss, cpu_planes, cpu_total, n_planes = {}, [], [], []
            for i in sorted({i for p in pairs for i in p}):
                pts = read_bin(data / name / "velodyne" / f"{i:06d}.bin")
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    ex.extract(pts)  # warm-up
                    for _ in range(max(1, repeats // 2)):
                        lss[i] = ex.extract(pts)
                        cpu_planes.append(1e3 * ex.last_cpu_timings["planes"])
                        cpu_total.append(1e3 * ex.last_cpu_timings["total"])
                n_planes.append(lss[i].counts()["planes"])
            reps = [repeatability(lss[a], lss[b].transform(invert(poses[a]) @ poses[b])) for a, b in pairs]

            def mean(key: str, reps: list[dict] = reps) -> float:
                return round(float(np.nanmean([r.get(key, np.nan) for r in reps])), 3)

            rows.append({"detector": det, "data": name, "pairs": len(pairs),
                         "cpu_planes_med_ms": round(float(np.median(cpu_planes)), 1),
                         "cpu_total_med_ms": round(float(np.median(cpu_total)), 1),
                         "planes_per_scan": round(float(np.mean(n_planes)), 1),
                         "rep_all": mean("all"), "rep_planes": mean("planes"), "rep_strict": mean("strict_all")})
    print("\nplane detectors, same run (repeatability: mean over pairs, after GT alignment)")
    cols = list(rows[0])
    print("  ".join(f"{c:>17}" for c in cols))
    for r in rows:
        print("  ".join(f"{r[c]!s:>17}" for c in cols))
    return rows


if __name__ == "__main__":
    main()
