"""Benchmark the simulated LiDAR: time per scan (median / p95) per style and sensor profile.

    .venv/bin/python bench/bench_simulator.py                 # all styles, all profiles
    .venv/bin/python bench/bench_simulator.py --scans 50 --json out.json
    .venv/bin/python bench/bench_simulator.py --write         # include writing KITTI files
    .venv/bin/python bench/bench_simulator.py --accuracy      # also score the front end vs GT
    .venv/bin/python bench/bench_simulator.py --realism realistic  # rough facades, movers, motion

The target is <= 0.2 s per 64-beam scan. "render" is ray casting + noise + labels;
"write" adds the .bin/.label files (with --write). World build and Embree scene build are
one-off costs per dataset and are reported separately. Also reported per style: the GT
landmarks each scan sees (>= 30 points), which bounds what a front end can extract.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from graffmatch.datasets.simulator import (
    PROFILES,
    STYLES,
    TrajectoryConfig,
    build_world,
    extraction_accuracy,
    get_profile,
    gt_landmarks_in_scan,
    plan_route,
    render_scan,
    world_preset,
)
from graffmatch.datasets.simulator.motion import sweep_poses
from graffmatch.datasets.simulator.movers import place_movers
from graffmatch.datasets.simulator.realism import get_realism, noisy_labels
from graffmatch.datasets.simulator.simulate import _sweep_twists, realistic_world_config
from graffmatch.datasets.simulator.writer import write_scan


def accuracy(style: str, profile: str, n_scans: int, seed: int, min_points: int) -> dict:
    """Default LandmarkExtractor (semantic poles) vs the GT landmarks each scan saw."""
    from graffmatch.lidar.extractor import LandmarkExtractor

    world = build_world(style, seed)
    traj = plan_route(world, n_scans, seed)
    ex = LandmarkExtractor()
    tot = {
        k: {"n_gt": 0, "n_extracted": 0, "n_matched": 0, "ang": [], "off": []}
        for k in ("lines", "planes")
    }
    for i, T in enumerate(traj.T_world_lidar):
        pts, labels, lm = render_scan(world, T, profile, i, return_landmarks=True)
        acc = extraction_accuracy(
            ex.extract(pts, labels), gt_landmarks_in_scan(world, lm, T, min_points)
        )
        for k, t in tot.items():
            for key in ("n_gt", "n_extracted", "n_matched"):
                t[key] += acc[k][key]
            t["ang"].append(acc[k]["angle_deg"]["median"])
            t["off"].append(acc[k]["anchor_m"]["median"])
    out = {"style": style, "profile": profile, "scans": n_scans, "min_points": min_points}
    for k, t in tot.items():
        out[k] = {
            "n_gt": t["n_gt"],
            "n_extracted": t["n_extracted"],
            "recovered": t["n_matched"] / max(1, t["n_gt"]),
            "precision": t["n_matched"] / max(1, t["n_extracted"]),
            "angle_deg_median": float(np.nanmedian(t["ang"])),
            "anchor_m_median": float(np.nanmedian(t["off"])),
        }
    return out


def bench(
    style: str, profile: str, n_scans: int, seed: int, write: bool, realism: str = "ideal"
) -> dict:
    """Time per scan as ``simulate_dataset`` renders it (sweep poses, movers, label noise)."""
    real = get_realism(realism)
    cfg = realistic_world_config(world_preset(style), real)
    t0 = time.perf_counter()
    world = build_world(cfg, seed)
    t_world = time.perf_counter() - t0
    t0 = time.perf_counter()
    _ = world.scene
    t_scene = time.perf_counter() - t0
    n_cols = get_profile(profile).n_columns
    tcfg = TrajectoryConfig.model_validate({**TrajectoryConfig().model_dump(), **real.trajectory})
    traj = plan_route(world, n_scans, seed, tcfg)
    movers = None
    if real.moving_cars_per_km > 0 or real.pedestrians_per_km > 0:
        movers = place_movers(world, np.random.default_rng(seed), real.moving_cars_per_km,
                              real.pedestrians_per_km)  # fmt: skip
    twists = _sweep_twists(traj.T_world_lidar) if real.motion_distortion else None
    times, n_pts, lines, planes = [], [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i, T in enumerate(traj.T_world_lidar):
            t0 = time.perf_counter()
            sweep = None if twists is None else sweep_poses(T, twists[i], n_cols)
            dyn = None if movers is None else movers.mesh(world, float(traj.times[i]), T[:2, 3])
            pts, labels, lm = render_scan(
                world, T, profile, i, return_landmarks=True, sweep=sweep, dynamic=dyn
            )
            labels = noisy_labels(labels, real, np.random.default_rng(i))
            if write:
                write_scan(Path(tmp), i, pts, labels)
            times.append(time.perf_counter() - t0)
            n_pts.append(len(pts))
            vis = gt_landmarks_in_scan(world, lm, T, min_points=30).counts()
            lines.append(vis["lines"])
            planes.append(vis["planes"])
    t = np.array(times)
    return {
        "style": style,
        "realism": realism,
        "profile": profile,
        "scans": n_scans,
        "median_s": float(np.median(t)),
        "p95_s": float(np.percentile(t, 95)),
        "points_median": int(np.median(n_pts)),
        "world_build_s": t_world,
        "scene_build_s": t_scene,
        "triangles": len(world.triangles),
        "gt_lines_per_scan": float(np.mean(lines)),
        "gt_planes_per_scan": float(np.mean(planes)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scans", type=int, default=30, help="scans per (style, profile)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--styles", nargs="*", default=list(STYLES))
    ap.add_argument("--profiles", nargs="*", default=list(PROFILES))
    ap.add_argument("--write", action="store_true", help="include writing the KITTI files")
    ap.add_argument("--accuracy", action="store_true", help="score the default front end vs GT")
    ap.add_argument("--min-points", type=int, default=30, help="GT seen with >= this many points")
    ap.add_argument("--realism", default="ideal", help="realism preset: ideal | realistic")
    ap.add_argument("--json", type=Path, default=None, help="write results as JSON here")
    args = ap.parse_args()
    rows = [
        bench(s, p, args.scans, args.seed, args.write, args.realism)
        for s in args.styles
        for p in args.profiles
    ]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    hdr = (
        f"{'style':<10} {'profile':<7} {'median s':>9} {'p95 s':>7} {'points':>7} "
        f"{'world s':>7} {'scene s':>7} {'tris':>7} {'GT lines':>8} {'GT planes':>9}"
    )
    print(f"simulator benchmark ({args.scans} scans each, realism={args.realism}, "
          f"write={args.write}, load avg {load:.1f})")  # fmt: skip
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        print(
            f"{r['style']:<10} {r['profile']:<7} {r['median_s']:>9.3f} {r['p95_s']:>7.3f} "
            f"{r['points_median']:>7d} {r['world_build_s']:>7.2f} {r['scene_build_s']:>7.2f} "
            f"{r['triangles']:>7d} {r['gt_lines_per_scan']:>8.1f} {r['gt_planes_per_scan']:>9.1f}"
        )
    worst64 = max((r["p95_s"] for r in rows if PROFILES[r["profile"]].n_beams == 64), default=0.0)
    print(f"target <= 0.2 s per 64-beam scan: worst p95 {worst64:.3f} s -> "
          f"{'OK' if worst64 <= 0.2 else 'TOO SLOW'}")  # fmt: skip
    acc_rows = []
    if args.accuracy:
        acc_rows = [
            accuracy(s, p, args.scans, args.seed, args.min_points)
            for s in args.styles
            for p in args.profiles
        ]
        print(f"\nfront end vs GT (GT seen with >= {args.min_points} points; medians per scan)")
        h = f"{'style':<10} {'profile':<7} {'type':<6} {'GT':>5} {'found':>5} {'recov':>6} {'prec':>6} {'angle deg':>9} {'anchor m':>8}"
        print(h)
        print("-" * len(h))
        for r in acc_rows:
            for k in ("lines", "planes"):
                a = r[k]
                print(
                    f"{r['style']:<10} {r['profile']:<7} {k:<6} {a['n_gt']:>5d} {a['n_extracted']:>5d} "
                    f"{a['recovered']:>6.2f} {a['precision']:>6.2f} {a['angle_deg_median']:>9.2f} "
                    f"{a['anchor_m_median']:>8.3f}"
                )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(
            json.dumps(
                {"rows": rows, "accuracy": acc_rows, "load_avg": load, "write": args.write},
                indent=2,
            )
        )


if __name__ == "__main__":
    main()
