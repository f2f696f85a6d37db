"""MapClosures' own pipeline loop with ground-truth poses instead of KISS-ICP (issue 15).

A reference to check ``run_mapclosures`` (graffmatch.evaluation.mapclosures_baseline) against:
this script drives the installed package's Python API (``MapClosures``, ``VoxelMap``) the way
``map_closures.pipeline.MapClosurePipeline`` does, written from reading it, with one change: the
pose of scan i is the ground truth, not KISS-ICP's. Its one range knob (``--max-range``, KISS-ICP's
``data.max_range``, 100 m in the pipeline) sets three things at once, as in the pipeline: the
scans are cropped to it (KISS-ICP's preprocessor), a local map is cut when the scan is farther
than it from the map's origin, and ``VoxelMap.remove_far_away_points`` keeps the map's points
within it for the next map. Every candidate ``get_closures`` returns is recorded with its inlier
count and its error against the ground-truth relative pose of the two local maps; the ones with
more than ``inliers_threshold`` inliers are the pipeline's closures.

``--id-stride K`` (a diagnostic, NOT the package's behaviour) hands local map k to the package
as id K*k: the package only compares a map with maps at least 4 ids older (the C++
``no_of_local_maps_to_skip = 3``), so K = 4 shows what that skip hides on short drives.

    PYTHONPATH=$PWD python bench/mapclosures_pipeline_gt.py /tmp/loops10-data/sim-suburban-s1 \
        --max-range 50 --deskew --json bench/results/x.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, peak_rss_mb

from graffmatch.geometry.transforms import invert, rotation_error_deg


def gt_overlap(P: np.ndarray, map_of_scan: np.ndarray, a: int, b: int, radius: float = 5.0) -> int:
    """Scans of map b within ``radius`` of a scan of map a (ground truth): a revisit."""
    A, B = P[map_of_scan == a, :3, 3], P[map_of_scan == b, :3, 3]
    if not len(A) or not len(B):
        return 0
    return int((np.linalg.norm(B[:, None] - A[None], axis=2).min(axis=1) <= radius).sum())


def reachable_positives(ds, map_of_scan: np.ndarray, min_gap: int) -> tuple[int, int]:
    """(queries with a GT partner within 5 m in a map the package compares theirs with, i.e. at
    least ``min_gap`` maps older; the benchmark's positives): an upper bound of the scan-level
    recall any closure-to-scan conversion can reach."""
    from graffmatch.evaluation.sequence_benchmark import benchmark_config, positives
    from graffmatch.loops.retrieval import eligible_count

    ret = benchmark_config().retrieval
    X, t = np.asarray(ds.poses, float)[:, :3, 3], np.asarray(ds.timestamps, float)
    pos = positives(np.asarray(ds.poses, float), t, ret, 5.0)
    reach = 0
    for q in np.flatnonzero(pos):
        e = eligible_count(t, int(q), ret)
        near = np.linalg.norm(X[:e] - X[q], axis=1) <= 5.0
        reach += bool((near & (map_of_scan[:e] <= map_of_scan[q] - min_gap)).any())
    return reach, int(pos.sum())


def run_drive(ds, max_range: float, id_stride: int = 1, crop_m: float | None = None,
              keep_m: float | None = None) -> dict:
    """One drive through the pipeline's loop; ``crop_m`` / ``keep_m`` override the scan crop and
    the kept radius (both ``max_range`` in the pipeline; crop_m <= 0: no crop)."""
    from map_closures.config import MapClosuresConfig
    from map_closures.map_closures import MapClosures
    from map_closures.voxel_map import VoxelMap

    cfg = MapClosuresConfig()
    mc = MapClosures(cfg)
    P = np.asarray(ds.poses, float)
    P = np.stack([invert(P[0]) @ T for T in P])  # the pipeline's odometry starts at identity
    n = len(P)
    keep_m = max_range if keep_m is None else keep_m
    crop_m = max_range if crop_m is None else crop_m
    vmap = VoxelMap(voxel_size=cfg.density_map_resolution, max_distance=keep_m)
    map_pose, start, k = np.eye(4), 0, 0
    map_of_scan = np.zeros(n, np.int64)
    maps, candidates = [], []
    t0 = time.perf_counter()
    for i in range(n):
        pts = np.asarray(ds[i].points[:, :3], np.float64)
        if crop_m > 0:
            pts = pts[np.linalg.norm(pts, axis=1) <= crop_m]
        T_map_scan = invert(map_pose) @ P[i]
        vmap.integrate_frame(pts, T_map_scan)
        map_of_scan[i] = k
        if np.linalg.norm(T_map_scan[:3, 3]) > max_range or i == n - 1:
            cloud = vmap.point_cloud()
            for c in mc.get_closures(id_stride * k, cloud):
                s, t = int(c.source_id) // id_stride, int(c.target_id) // id_stride
                T_gt = invert(maps[t]["pose"] if t < k else map_pose) @ maps[s]["pose"]
                E = invert(T_gt) @ np.asarray(c.pose, float)
                candidates.append({"source": s, "target": t, "inliers": int(c.number_of_inliers),
                                   "err_m": float(np.linalg.norm(E[:3, 3])),
                                   "err_deg": float(rotation_error_deg(E, np.eye(3)))})
            maps.append({"pose": map_pose.copy(), "scans": [start, i + 1], "points": len(cloud)})
            vmap.remove_far_away_points(T_map_scan[:3, 3])
            keep = vmap.point_cloud()
            vmap.clear()
            vmap.integrate_frame(keep, invert(P[i]) @ map_pose)
            map_pose, start, k = P[i].copy(), i, k + 1
    seconds = time.perf_counter() - t0
    reach, n_pos = reachable_positives(ds, map_of_scan, -(-4 // id_stride))
    pairs = [{"a": a, "b": b, "scans_of_b_within_5m": gt_overlap(P, map_of_scan, a, b)}
             for a in range(k) for b in range(a + 1, k)]
    closures = [c for c in candidates if c["inliers"] > cfg.inliers_threshold]
    return {
        "sequence": ds.name, "n_scans": n, "max_range_m": max_range, "id_stride": id_stride, "crop_m": crop_m, "keep_m": keep_m,
        "path_m": float(np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1).sum()),
        "n_maps": k, "maps": [{"scans": m["scans"], "points": m["points"]} for m in maps],
        "revisit_pairs": [p for p in pairs if p["scans_of_b_within_5m"] > 0],
        "candidates": candidates, "inliers_threshold": cfg.inliers_threshold,
        "n_closures": len(closures),
        "positives_5m": n_pos, "positives_in_compared_maps": reach,
        "n_closures_within_2m_5deg": sum(c["err_m"] <= 2.0 and c["err_deg"] <= 5.0 for c in closures),
        "seconds": seconds,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("drives", nargs="+", type=Path, help="drive folders (KITTI layout, simulated or real)")
    ap.add_argument("--max-range", type=float, nargs="+", default=[100.0],
                    help="KISS-ICP max_range as the pipeline uses it (100 = its default; 50 = the issue's)")
    ap.add_argument("--id-stride", type=int, default=1, help="diagnostic: local map k is package id K*k")
    ap.add_argument("--no-crop", action="store_true", help="diagnostic: integrate the whole scan (no crop)")
    ap.add_argument("--crop-m", type=float, help="diagnostic: crop scans at this range (the pipeline: max_range)")
    ap.add_argument("--keep-m", type=float, help="diagnostic: VoxelMap max_distance (the pipeline: = max_range)")
    ap.add_argument("--deskew", action="store_true",
                    help="the benchmark's de-skew (drift odometry), as bench_loops.py --deskew; not for real data")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    from graffmatch.datasets.registry import open_dataset
    from graffmatch.loops.sequence import prepare_drive

    rows = []
    for d in args.drives:
        raw = open_dataset("folder", d)
        ds, _ = prepare_drive(raw, "drift", True) if args.deskew else (raw, None)
        for r in args.max_range:
            row = run_drive(ds, r, args.id_stride, 0.0 if args.no_crop else args.crop_m, args.keep_m)
            rows.append(row)
            cand = ", ".join(f"{c['source']}-{c['target']}:{c['inliers']}" for c in row["candidates"])
            print(f"{row['sequence']} max_range {r:g} m: {row['n_maps']} maps, path {row['path_m']:.0f} m, "
                  f"{row['n_closures']} closures ({row['n_closures_within_2m_5deg']} within 2 m / 5 deg), "
                  f"positives {row['positives_in_compared_maps']} of {row['positives_5m']} in compared maps, "
                  f"candidates source-target:inliers [{cand}], {row['seconds']:.0f} s", flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"machine": machine(), "peak_rss_mb": peak_rss_mb(),
                                         "argv": sys.argv[1:], "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
