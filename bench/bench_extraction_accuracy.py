"""Front-end accuracy against the simulator's ground-truth landmarks, per built-in suite.

    python bench/bench_extraction_accuracy.py [--scans 12] [--root /tmp/gm-sim] [--json out.json]
        [--detector voxel open3d]

For each simulated suite, a few scans are simulated (or reused from ``--root``), landmarks are
extracted with the suite's own front-end config (the one its loop-closure build uses; semantic
pole mode, since the simulator writes SemanticKITTI labels), and matched one-to-one to the ground-truth landmarks the scan saw with at
least ``--min-points`` points (linear assignment on the invariant distance, 6 degree gate).
Reports the fraction of GT landmarks recovered, the precision of the extraction, the angle
error, and the offset error (plane: distance of the extracted anchor to the GT plane; pole:
distance of the extracted anchor to the GT axis) and the anchor distance along the landmark.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import machine, print_table, write_json
from scipy.optimize import linear_sum_assignment

from graffmatch.datasets import open_dataset
from graffmatch.datasets.simulator import SUITES, simulate_dataset
from graffmatch.datasets.simulator.simulate import scan_ground_truth
from graffmatch.evaluation.suites import suite_config
from graffmatch.geometry.distance import cross_distances
from graffmatch.lidar import LandmarkExtractor


def evaluate_scan(est, gt):
    D = np.degrees(cross_distances(est, gt))
    Dg = np.where(np.isfinite(D), D, 1e6)
    r, c = linear_sum_assignment(Dg)
    ok = Dg[r, c] < 6.0
    r, c = r[ok], c[ok]
    de, dg = est.directions[r], gt.directions[c]
    ang = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", de, dg)), 0, 1)))
    diff = est.anchors[r] - gt.anchors[c]
    along = np.einsum("ij,ij->i", diff, dg)
    planes = gt.types[c] == 2
    offset = np.where(planes, np.abs(along), np.linalg.norm(diff - along[:, None] * dg, axis=1))
    anchor = np.linalg.norm(diff, axis=1)
    return len(r), ang, offset, anchor, gt.types[c]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scans", type=int, default=12)
    ap.add_argument("--min-points", type=int, default=100)
    ap.add_argument("--root", default="/tmp/graffmatch-extraction-accuracy")
    ap.add_argument("--json", default=None)
    ap.add_argument(
        "--detector",
        nargs="+",
        default=["voxel"],
        choices=["voxel", "open3d"],
        help="plane detector(s), each on the same scans (a same-run comparison)",
    )
    args = ap.parse_args()
    rows = []
    for name, spec in SUITES.items():
        for det in args.detector:
            base = suite_config(name).extractor
            ex = LandmarkExtractor(
                base.model_copy(update={"planes": base.planes.model_copy(update={"detector": det})})
            )
            seq = Path(args.root) / name
            simulate_dataset(
                seq,
                style=spec.style,
                seed=spec.seed,
                n_scans=args.scans * 3,
                sensor=spec.sensor,
                world_config=spec.world_config(),
                reuse=True,
            )
            ds = open_dataset("folder", seq)
            n_gt = {1: 0, 2: 0}
            n_est = {1: 0, 2: 0}
            angs, offs, anchors, kinds = [], [], [], []
            for i in range(0, len(ds), 3):
                scan = ds[i]
                est = ex.extract(scan.points, scan.labels)
                gt = scan_ground_truth(seq, i, scan.T_world_lidar, min_points=args.min_points)
                _, a, o, an, t = evaluate_scan(est, gt)
                for kind in (1, 2):
                    n_gt[kind] += int(np.sum(gt.types == kind))
                    n_est[kind] += int(np.sum(est.types == kind))
                angs.append(a)
                offs.append(o)
                anchors.append(an)
                kinds.append(t)
            a, o, an, t = map(np.concatenate, (angs, offs, anchors, kinds))
            for label, kind in (("poles", 1), ("planes", 2)):
                sel = t == kind
                rows.append(
                    {
                        "suite": name,
                        "detector": det,
                        "type": label,
                        "gt_seen": n_gt[kind],
                        "extracted": n_est[kind],
                        "matched": int(sel.sum()),
                        "recovered_of_gt": round(int(sel.sum()) / max(n_gt[kind], 1), 3),
                        "precision": round(int(sel.sum()) / max(n_est[kind], 1), 3),
                        "angle_med_deg": round(float(np.median(a[sel])), 2) if sel.any() else "",
                        "angle_p90_deg": round(float(np.percentile(a[sel], 90)), 2)
                        if sel.any()
                        else "",
                        "offset_med_m": round(float(np.median(o[sel])), 3) if sel.any() else "",
                        "offset_p90_m": round(float(np.percentile(o[sel], 90)), 3)
                        if sel.any()
                        else "",
                        "anchor_med_m": round(float(np.median(an[sel])), 2) if sel.any() else "",
                    }
                )
        print(f"{name}: done", flush=True)
    print_table(rows, list(rows[0]))
    write_json(
        args.json,
        {
            "benchmark": "extraction_accuracy",
            "machine": machine(),
            "rows": rows,
            "min_points": args.min_points,
            "scans_per_suite": args.scans,
        },
    )


if __name__ == "__main__":
    main()
