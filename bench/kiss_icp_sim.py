"""KISS-ICP odometry on simulated drives: does a standard odometry run through the simulator?

    PYTHONPATH=. .venv/bin/python bench/kiss_icp_sim.py [--scans 200] [--style suburban]
        [--realism ideal realistic] [--sensor hdl64] [--json out.json] [--data ../shared/data]

Simulates one drive per realism preset (KITTI layout, read back with the loader), runs
KISS-ICP with its default configuration (max range 100 m, voxel 1 m, adaptive threshold;
de-skewing with per-point times from the azimuth when the scans are raw, poses at mid-sweep:
``graffmatch.loops.posegraph.kiss_icp_odometry``), and reports the
drift: position error after aligning the first pose, at the end and its maximum, the first
scan where it exceeds 2 m, and the relative translation error over 50 m segments [%].
With --data it also runs KITTI 00 frames 0-5 as a sanity check.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from graffmatch.datasets.folder import KittiFolder
from graffmatch.datasets.simulator import simulate_dataset
from graffmatch.datasets.simulator.realism import get_realism
from graffmatch.geometry.transforms import invert


def run_kiss(seq, deskew: bool) -> np.ndarray:
    """(n, 4, 4) KISS-ICP poses of the scans of ``seq`` (first pose = identity), through the
    library's ``kiss_icp_odometry`` (with ``deskew``: KISS-ICP's own de-skew from azimuth
    times, poses moved to mid-sweep; session 13)."""
    from graffmatch.loops.posegraph import kiss_icp_odometry

    P = kiss_icp_odometry(seq, deskew=deskew)
    return np.einsum("ij,njk->nik", invert(P[0]), P)


def drift(est: np.ndarray, gt: np.ndarray, segment_m: float = 50.0) -> dict:
    """Errors of ``est`` against ``gt`` after expressing both relative to their first pose."""
    g = np.einsum("ij,njk->nik", invert(gt[0]), gt)
    err = np.linalg.norm(est[:, :3, 3] - g[:, :3, 3], axis=1)
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(g[:, :3, 3], axis=0), axis=1))])
    rel = []
    for a in range(len(g)):
        b = int(np.searchsorted(path, path[a] + segment_m))
        if b >= len(g):
            break
        dg = invert(g[a]) @ g[b]
        de = invert(est[a]) @ est[b]
        rel.append(np.linalg.norm((invert(dg) @ de)[:3, 3]) / segment_m * 100.0)
    over = np.flatnonzero(err > 2.0)
    return {
        "path_m": float(path[-1]),
        "final_err_m": float(err[-1]),
        "max_err_m": float(err.max()),
        "first_scan_over_2m": int(over[0]) if len(over) else None,
        "rel_trans_err_pct": float(np.mean(rel)) if rel else float("nan"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scans", type=int, default=200)
    ap.add_argument("--style", default="suburban")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--sensor", default="hdl64")
    ap.add_argument("--realism", nargs="*", default=["ideal", "realistic"])
    ap.add_argument("--data", type=Path, default=None, help="../shared/data for a KITTI check")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    rows = []
    if args.data is not None and (args.data / "kitti00_first6").is_dir():
        seq = KittiFolder(args.data / "kitti00_first6")
        rows.append({"run": "kitti00 0-5 (deskewed by KITTI)", **drift(run_kiss(seq, False), seq.poses)})
    for realism in args.realism:
        raw = get_realism(realism).motion_distortion and not get_realism(realism).deskew
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            simulate_dataset(Path(tmp) / "s", style=args.style, seed=args.seed, n_scans=args.scans,
                             sensor=args.sensor, realism=realism)  # fmt: skip
            t_sim = time.perf_counter() - t0
            seq = KittiFolder(Path(tmp) / "s")
            modes = [False, True] if raw else [False]
            for deskew in modes:
                t0 = time.perf_counter()
                est = run_kiss(seq, deskew)
                rows.append({
                    "run": f"{args.style}/{realism} {args.sensor}, KISS deskew={deskew}",
                    "simulate_s": t_sim, "kiss_s": time.perf_counter() - t0,
                    **drift(est, seq.poses),
                })  # fmt: skip
    print(f"KISS-ICP (default config) on {args.scans}-scan drives, seed {args.seed}")
    print(f"{'run':<48} {'path m':>7} {'final m':>8} {'max m':>7} {'>2 m at':>8} {'RTE %':>6}")
    for r in rows:
        first = "-" if r["first_scan_over_2m"] is None else str(r["first_scan_over_2m"])
        print(f"{r['run']:<48} {r['path_m']:>7.1f} {r['final_err_m']:>8.2f} {r['max_err_m']:>7.2f} "
              f"{first:>8} {r['rel_trans_err_pct']:>6.2f}")  # fmt: skip
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                         "rows": rows}, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
