"""KISS-ICP's de-skew on raw simulated drives: which time convention (session 13, issue 15).

    PYTHONPATH=$PWD python bench/kiss_icp_deskew.py --drives sim-downtown:2 sim-suburban:3 \\
        --scans 150 --modes none kiss-az kiss-az-mid --json out.json [--split]

Simulates each drive (``realistic`` preset: motion-distorted raw scans, the suite's world and
sensor) and runs KISS-ICP 1.x with its defaults (max range 100 m, voxel 1 m) three ways:

* ``none``: the raw scans as they are (``kiss_icp_odometry(deskew=False)``, session 12);
* ``kiss-az``: KISS-ICP's own de-skew with per-point times from the azimuth, its poses as it
  returns them: at the END of each sweep (its ``Preprocessor`` moves a point by
  exp((t - 1) log delta)), while the ground truth is at mid-sweep (the session-12 trial);
* ``kiss-az-mid``: the same, each pose moved back half a sweep with the motion KISS-ICP
  de-skewed that scan with (``kiss_icp_odometry(deskew=True)``'s convention).

``own-mid`` (optional) de-skews to mid-sweep with :func:`graffmatch.lidar.deskew.deskew_scan`
and KISS-ICP's constant-velocity prediction, then registers without KISS-ICP's de-skew.
ATE/RPE as the benchmark scores odometry (evo, SE(3)-aligned; RPE over 10 frames); ``--split``
also prints the per-pose ATE on straight and turning scans (|yaw rate| > 1 deg/scan).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine

MODES = ("none", "kiss-az", "kiss-az-mid", "own-mid")


def run(seq, mode: str) -> np.ndarray:
    """(n, 4, 4) KISS-ICP world poses of ``seq`` for one ``mode`` (see the module docstring)."""
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    from graffmatch.lidar.deskew import azimuth_times, deskew_scan
    from graffmatch.loops.posegraph import kiss_end_to_mid

    cfg = KISSConfig()
    cfg.data.max_range = 100.0
    cfg.data.deskew = mode.startswith("kiss-az")
    cfg.mapping.voxel_size = 1.0  # max_range / 100, as kiss_icp_odometry
    odo = KissICP(cfg)
    poses = []
    for i in range(len(seq)):
        pts = np.asarray(seq[i].points[:, :3], np.float64)
        delta = np.asarray(odo.last_delta, float).copy()
        if mode == "own-mid":
            odo.register_frame(deskew_scan(pts, np.eye(4), delta, 1.0), np.zeros(0))
        else:
            odo.register_frame(pts, azimuth_times(pts) + 0.5 if cfg.data.deskew else np.zeros(0))
        T = np.asarray(odo.last_pose, float).copy()
        poses.append(T @ kiss_end_to_mid(delta) if mode == "kiss-az-mid" else T)
    P0 = np.asarray(seq.poses[0], float)
    return np.stack([P0 @ T for T in poses])


def split_errors(est: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """Per-pose ATE (evo SE(3) alignment) RMSE over straight and turning scans."""
    from evo.core.trajectory import PosePath3D

    yaw = np.unwrap(np.arctan2(gt[:, 1, 0], gt[:, 0, 0]))
    turn = np.degrees(np.abs(np.gradient(yaw))) > 1.0
    e_path, r_path = PosePath3D(poses_se3=list(est)), PosePath3D(poses_se3=list(gt))
    e_path.align(r_path, correct_scale=False)
    err = np.linalg.norm(e_path.positions_xyz - r_path.positions_xyz, axis=1)
    rms = lambda m: float(np.sqrt(np.mean(err[m] ** 2))) if m.any() else float("nan")  # noqa: E731
    return {"ate_straight_m": rms(~turn), "ate_turning_m": rms(turn), "n_turning": int(turn.sum())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--drives", nargs="+", required=True, metavar="SUITE:SEED")
    ap.add_argument("--scans", type=int, default=150)
    ap.add_argument("--data", type=Path, default=Path("/tmp/kiss_icp_deskew"))
    ap.add_argument("--modes", nargs="+", default=list(MODES[:3]), choices=MODES)
    ap.add_argument("--split", action="store_true")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    from graffmatch.datasets.folder import KittiFolder
    from graffmatch.datasets.simulator import SUITES, simulate_dataset
    from graffmatch.loops.posegraph import trajectory_errors

    rows = []
    for d in args.drives:
        name, seed = d.rsplit(":", 1)
        s = SUITES[name]
        root = args.data / f"{name}-s{seed}-n{args.scans}"
        simulate_dataset(root, style=s.style, seed=int(seed), n_scans=args.scans, sensor=s.sensor,
                         world_config=s.world_config(), reuse=True, realism="realistic")  # fmt: skip
        seq = KittiFolder(root)
        gt = np.asarray(seq.poses, float)
        for mode in args.modes:
            t0 = time.perf_counter()
            P = run(seq, mode)
            row = {"drive": f"{name}-s{seed}", "scans": args.scans, "mode": mode, **trajectory_errors(P, gt),
                   "kiss_wall_s": time.perf_counter() - t0}  # fmt: skip
            if args.split:
                row.update(split_errors(P, gt))
            rows.append(row)
            print(f"{row['drive']:<18} {mode:<12} ATE {row['ate_rmse_m']:.3f} max {row['ate_max_m']:.3f} "
                  f"RPE {row['rpe_rmse_m']:.3f} m" + (f"  straight {row['ate_straight_m']:.3f} turning "
                  f"{row['ate_turning_m']:.3f}" if args.split else ""), flush=True)  # fmt: skip
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"machine": machine(), "args": {k: str(v) for k, v in vars(args).items()},
                                         "rows": rows}, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
