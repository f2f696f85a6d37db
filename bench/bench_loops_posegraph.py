"""Pose graph on the loop benchmark's drives (issue 15): ATE/RPE before and after, with evo.

    PYTHONPATH=$PWD python bench/bench_loops_posegraph.py --runs /tmp/loops_bench/out \\
        --json bench/results/loops_posegraph.json --plots docs/img

For every simulated drive of bench/bench_loops.py, the loops that run found (``--runs``:
its ``--out`` folder, ``<drive>/ours/loops.csv``) go into the GTSAM pose graph together with
simulated odometry drift (``OdometryDriftConfig``), for several drift seeds and drift models:

* ``default``: the library's default drift (3 deg/100 m heading bias, heading noise
  0.05 deg/sqrt(m), 0.2 % scale, 0.5 % translation noise);
* ``no-bias``: the same without the heading bias (noise and scale only);
* ``bias-neg``: -5 deg/100 m heading bias and a 1 % scale error.

Each is optimised twice: the plain graph (``estimate_odometry_bias=False``) and the default
graph (a heading-rate bias estimated for the drive). ``oracle`` rows put a ground-truth loop
edge at every query that has an earlier scan within 5 m (outside the 10 s window): what the
graph gives with perfect loops, to tell the loops' quality from what the graph can observe.
ATE = evo's APE RMSE (translation, SE(3)-aligned); RPE over 10 frames. With ``--kiss-icp DIR``
the KISS-ICP odometry that ``bench_loops.py --odometry kiss-icp`` (``DIR/<drive>/kiss_icp_kitti.txt``)
or ``--methods mapclosures`` (``DIR/<drive>/mapclosures/kiss_icp_kitti.txt``) wrote is used as
well (drift ``kiss-icp``; ``--drifts`` with no value: only it). ``--suffix +deskew`` reads the
loops of a ``bench_loops.py --deskew`` run (``<drive>+deskew/ours/loops.csv``).
``--synthetic N`` only times the graphs on a synthetic drive of about N poses (a 40 m
square driven again and again, a loop edge every 4th scan of every lap after the first): the
plain graph, the default graph (bias solver ``projection``) and, up to ``--joint-max`` poses,
the joint custom-factor graph (bias solver ``joint``, O(n^2)); with the ATE, the bias, the
number of plain solves and the peak RSS.
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

DRIFTS = {
    "default": {},
    "no-bias": {"yaw_bias_deg_per_100m": 0.0},
    "bias-neg": {"yaw_bias_deg_per_100m": -5.0, "scale_error": 0.01},
}
DRIVES = ["sim-downtown-s1", "sim-downtown-s5", "sim-suburban-s1", "sim-suburban-s4", "sim-openroad-s1",
          "sim-openroad-s3"]


def oracle_edges(poses: np.ndarray, timestamps: np.ndarray, window_s: float = 10.0, radius: float = 5.0):
    """Ground-truth loop edges: each query to its nearest earlier scan within ``radius``."""
    from graffmatch.geometry.transforms import invert

    edges = []
    for q in range(len(poses)):
        d = np.linalg.norm(poses[:q, :3, 3] - poses[q, :3, 3], axis=1)
        ok = np.flatnonzero((d < radius) & (timestamps[q] - timestamps[:q] > window_s))
        if ok.size:
            m = int(ok[np.argmin(d[ok])])
            edges.append((m, q, invert(poses[m]) @ poses[q], np.diag([1e4] * 3 + [1e6] * 3)))
    return edges


def time_synthetic(n: int, joint_max: int = 0) -> list[dict]:
    """Wall/CPU seconds of the plain, the default and (n <= joint_max) the joint graph on a
    ~n-pose square drive."""
    from graffmatch.geometry.transforms import invert
    from graffmatch.loops.posegraph import (
        PoseGraphConfig,
        drifted_odometry,
        optimize_pose_graph,
        trajectory_errors,
    )

    poses = []
    for k in range(n):
        side, s = divmod(k % 160, 40)
        x, y = [(s, 0), (40, s), (40 - s, 40), (0, 40 - s)][side]
        T = np.eye(4)
        a = np.radians(90 * side)
        T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        T[:2, 3] = x, y
        poses.append(T)
    gt = np.stack(poses)
    info = np.diag([1e4] * 3 + [1e6] * 3)
    edges = [(q - 160, q, invert(gt[q - 160]) @ gt[q], info) for q in range(160, n, 4)]
    odo = drifted_odometry(gt)
    rows = []
    runs = [("plain", False, "projection"), ("projection", True, "projection")]
    if n <= joint_max:
        runs.append(("joint", True, "joint"))
    for label, bias, solver in runs:
        t, c = time.perf_counter(), time.process_time()
        opt, info = optimize_pose_graph(odo, edges, PoseGraphConfig(estimate_odometry_bias=bias, bias_solver=solver))
        rows.append({"poses": n, "loop_edges": len(edges), "graph": label, "estimate_odometry_bias": bias,
                     "bias_solver": solver if bias else None,
                     "wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c,
                     "ate_before_m": trajectory_errors(odo, gt)["ate_rmse_m"],
                     "ate_after_m": trajectory_errors(opt, gt)["ate_rmse_m"],
                     "bias_deg_per_100m": info.get("odometry_heading_bias_deg_per_100m"),
                     "bias_solves": info.get("bias_solves"), "lm_iterations": info["iterations"],
                     "peak_rss_mb": peak_rss_mb()})
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("/tmp/loops_bench/data"))
    ap.add_argument("--runs", type=Path, default=None, help="bench_loops.py --out folder with the loops")
    ap.add_argument("--synthetic", type=int, nargs="+", default=None, help="only time graphs of these sizes")
    ap.add_argument("--joint-max", type=int, default=0, help="--synthetic: also time the joint graph up to this size")
    ap.add_argument("--drives", nargs="+", default=DRIVES)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--drifts", nargs="*", default=list(DRIFTS), choices=list(DRIFTS))
    ap.add_argument("--kiss-icp", type=Path, default=None,
                    help="bench_loops.py --out folder with KISS-ICP odometry: <drive>/kiss_icp_kitti.txt "
                    "(--odometry kiss-icp) or <drive>/mapclosures/kiss_icp_kitti.txt (--methods mapclosures)")
    ap.add_argument("--suffix", default="",
                    help="the drives' folder suffix in --runs, e.g. '+deskew' for bench_loops.py --deskew runs")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--plots", type=Path, default=None, help="trajectory_<drive>.png (default drift, seed 0)")
    args = ap.parse_args()
    if args.synthetic:
        rows = [r for n in args.synthetic for r in time_synthetic(n, args.joint_max)]
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps({"machine": machine(), "rows": rows}, indent=1))
        return
    if args.runs is None:
        ap.error("--runs is needed (or --synthetic)")

    from graffmatch.datasets.registry import open_dataset
    from graffmatch.geometry.pose_files import read_kitti
    from graffmatch.loops.io import loop_edges, read_loops_csv
    from graffmatch.loops.posegraph import (
        OdometryDriftConfig,
        PoseGraphConfig,
        drifted_odometry,
        optimize_pose_graph,
        plot_trajectories,
        trajectory_errors,
    )

    rows = []
    t0 = time.perf_counter()
    for name in args.drives:
        ds = open_dataset("folder", args.data / name)
        gt, ts = np.asarray(ds.poses, float), np.asarray(ds.timestamps, float)
        loops = read_loops_csv(args.runs / f"{name}{args.suffix}" / "ours" / "loops.csv")
        sources = {"ours": loop_edges(loops), "oracle": oracle_edges(gt, ts)}
        kiss = None
        if args.kiss_icp is not None:
            kiss = args.kiss_icp / name / "kiss_icp_kitti.txt"
            if not kiss.is_file():
                kiss = args.kiss_icp / f"{name}{args.suffix}" / "mapclosures" / "kiss_icp_kitti.txt"
        runs = [(d, s) for d in args.drifts for s in args.seeds]
        if kiss is not None and kiss.is_file():
            runs.append(("kiss-icp", args.seeds[0]))
        for drift, seed in runs:
            if drift == "kiss-icp":
                odo = read_kitti(kiss)
            else:
                odo = drifted_odometry(gt, OdometryDriftConfig(seed=seed, **DRIFTS[drift]))
            before = trajectory_errors(odo, gt)
            for src, edges in sources.items():
                if src == "oracle" and seed != args.seeds[0]:
                    continue
                for graph, bias in (("plain", False), ("heading-bias", True)):
                    t = time.perf_counter()
                    opt, info = optimize_pose_graph(odo, edges, PoseGraphConfig(estimate_odometry_bias=bias))
                    after = trajectory_errors(opt, gt)
                    row = {"drive": name, "drift": drift, "seed": seed, "loops": src, "graph": graph,
                           "n_loop_edges": len(edges), "first_loop_query": min((e[1] for e in edges), default=None),
                           "ate_before_m": before["ate_rmse_m"], "ate_after_m": after["ate_rmse_m"],
                           "ratio": after["ate_rmse_m"] / before["ate_rmse_m"],
                           "rpe_before_m": before["rpe_rmse_m"], "rpe_after_m": after["rpe_rmse_m"],
                           "heading_bias_deg_per_100m": info.get("odometry_heading_bias_deg_per_100m"),
                           "iterations": info["iterations"], "optimize_s": time.perf_counter() - t}
                    rows.append(row)
                    print(f"{name:16s} {drift:8s} s{seed} {src:6s} {graph:12s} edges {len(edges):3d} "
                          f"ATE {row['ate_before_m']:.2f} -> {row['ate_after_m']:.2f} m ({row['ratio']:.2f}) "
                          f"RPE {row['rpe_before_m']:.3f} -> {row['rpe_after_m']:.3f} m"
                          + (f" bias {row['heading_bias_deg_per_100m']:+.2f} deg/100m" if bias else ""),
                          flush=True)
                    if (args.plots and src == "ours" and bias and drift in ("default", "kiss-icp")
                            and seed == args.seeds[0]):
                        args.plots.mkdir(parents=True, exist_ok=True)
                        tag = "" if drift == "default" else "_kiss_icp"
                        plot_trajectories(args.plots / f"loops_trajectory_{name}{tag}.png", gt, odo, opt, loops)
    ours = [r for r in rows if r["loops"] == "ours"]
    print("\nsummary (ours' loops): ATE after / before, mean and max over seeds")
    for drift in [*args.drifts, *(["kiss-icp"] if any(r["drift"] == "kiss-icp" for r in ours) else [])]:
        for name in args.drives:
            if not any(x["drive"] == name and x["drift"] == drift for x in ours):
                continue
            cells = []
            for graph in ("plain", "heading-bias"):
                r = [x["ratio"] for x in ours if x["drive"] == name and x["drift"] == drift and x["graph"] == graph]
                cells.append(f"{graph} {np.mean(r):.2f} (max {np.max(r):.2f})")
            print(f"  {drift:8s} {name:16s} " + "  ".join(cells))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"machine": machine(), "args": {k: str(v) for k, v in vars(args).items()},
                                         "wall_s": time.perf_counter() - t0, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
