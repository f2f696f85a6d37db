"""Score a `graffmatch loops` run against a drive's ground truth (the run itself may have had none): loops off by more
than 1 m / 5 deg, the farthest loop, the odometry and optimised trajectories (start-aligned), and partner recall
(queries with a ground-truth partner within 5 m, older than 10 s, that got a loop).

    PYTHONPATH=$PWD python bench/loops_score_run.py GT_DIR RUN_DIR
"""

import sys

import numpy as np

from graffmatch.datasets.registry import open_dataset
from graffmatch.geometry.pose_files import read_kitti
from graffmatch.geometry.transforms import invert, rotation_error_deg
from graffmatch.loops.io import read_loops_csv


def main() -> None:
    ds = open_dataset("folder", sys.argv[1])
    gt, t, out = ds.poses, ds.timestamps, sys.argv[2]
    loops = read_loops_csv(out + "/loops.csv")
    bad = []
    for c in loops:
        G = invert(gt[c.match]) @ gt[c.query]
        dt = float(np.linalg.norm(G[:3, 3] - c.T_match_query[:3, 3]))
        dr = rotation_error_deg(G[:3, :3], c.T_match_query[:3, :3])
        if dt > 1 or dr > 5:
            d = float(np.linalg.norm(gt[c.match][:3, 3] - gt[c.query][:3, 3]))
            bad.append((c.query, c.match, round(d, 2), round(dt, 2), round(dr, 2), round(c.confidence, 3)))
    print(len(loops), "loops;", len(bad), "off by >1 m or >5 deg:", bad)
    if loops:
        far = max(np.linalg.norm(gt[c.match][:3, 3] - gt[c.query][:3, 3]) for c in loops)
        print(f"place distance of loops: max {far:.1f} m")
    for f in ("odometry_kitti.txt", "optimized_kitti.txt"):
        try:
            P = gt[0] @ read_kitti(f"{out}/{f}")  # scan 0's frame -> the ground truth's
        except Exception:
            continue
        e = np.linalg.norm(P[:, :3, 3] - gt[:, :3, 3], axis=1)
        print(f, f"position error vs GT (start-aligned): rmse {np.sqrt((e**2).mean()):.2f} max {e.max():.2f} m")
    pos = set()
    for q in range(len(gt)):
        m = int(np.searchsorted(t, t[q] - 10.0, side="right"))
        if m > 0 and np.linalg.norm(gt[:m, :3, 3] - gt[q, :3, 3], axis=1).min() <= 5.0:
            pos.add(q)
    hit = {c.query for c in loops}
    print(f"queries with a partner <= 5 m: {len(pos)}; with a loop: {len(pos & hit)} ({len(pos & hit) / max(1, len(pos)):.3f}); "
          f"queries with a loop but no partner <= 5 m: {len(hit - pos)}")


if __name__ == "__main__":
    main()
