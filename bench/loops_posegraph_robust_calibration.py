"""Pose-graph rule v2 (docs/loops.md, session 25): the default graph against robust odometry (Cauchy, k = 1) with a
chordal start, both with the heading-rate bias, evo ATE on the 8 calibration drives: (a) scans-alone KISS-ICP runs
(loops with the odometry gate), (b) the benchmark run's records under the default simulated drift, seeds 0-2; and,
with ``--reported``, the reported scans-alone drives and the courtyard. Writes the rows to the JSON path given.

    PYTHONPATH=$PWD python bench/loops_posegraph_robust_calibration.py OUT.json [--reported]
"""

import json
import sys

import yaml

from graffmatch.datasets.registry import open_dataset
from graffmatch.geometry.pose_files import read_kitti
from graffmatch.loops.consistency import apply_sequence_consistency
from graffmatch.loops.detector import LoopDetectorConfig
from graffmatch.loops.io import loop_edges
from graffmatch.loops.posegraph import (
    OdometryDriftConfig,
    PoseGraphConfig,
    drifted_odometry,
    optimize_pose_graph,
    trajectory_errors,
)
from graffmatch.loops.sequence import loops_from_records, read_queries

CAL = ["downtown-s2", "downtown-s3", "downtown-s4", "downtown-s6", "suburban-s3", "suburban-s5", "openroad-s2",
       "openroad-s5"]
REPORTED = [("/tmp/loops-data/sim-downtown-s1", "/tmp/s25/j_opt")] + [
    (f"/tmp/loops-data/sim-{d}", f"/tmp/s25/jo-{d}")
    for d in ("downtown-s5", "suburban-s1", "suburban-s4", "openroad-s1", "openroad-s3")
] + [("/work/shared/data/balm_courtyard", "/tmp/s25/jo-courtyard")]


def edges(run: str, odo, records=None):
    cfg = LoopDetectorConfig.model_validate(yaml.safe_load(open(run + "/config.yaml")))
    recs = read_queries(run) if records is None else records
    final = apply_sequence_consistency(recs, odo, cfg.verification)
    return loop_edges(loops_from_records(final, cfg.verification.min_confidence))


def row(name: str, setup: str, gt, odo, E) -> dict:
    ate = {"odo": trajectory_errors(odo, gt)["ate_rmse_m"]}
    for label, cfg in (("default", PoseGraphConfig()), ("robust", PoseGraphConfig(odometry_kernel_k=1.0, chordal_start=True))):
        X, info = optimize_pose_graph(odo, E, cfg)
        ate[label] = trajectory_errors(X, gt)["ate_rmse_m"]
        ate[label + "_start"] = info.get("start")
    r = {"drive": name, "setup": setup, **{k: round(v, 3) if isinstance(v, float) else v for k, v in ate.items()}}
    print(json.dumps(r), flush=True)
    return r


def main() -> None:
    rows = []
    for d in CAL:
        gt = open_dataset("folder", f"/tmp/s25/cal400/sim-{d}").poses
        odo = read_kitti(f"/tmp/s25/jc-{d}/odometry_kitti.txt")
        rows.append(row(d, "a", gt, odo, edges(f"/tmp/s25/jc-{d}", odo)))
        run = f"/tmp/s25/calb/sim-{d}+deskew/ours"
        recs = read_queries(run)
        for seed in (0, 1, 2):
            odo = drifted_odometry(gt, OdometryDriftConfig(seed=seed))
            rows.append(row(d, f"b{seed}", gt, odo, edges(run, odo, recs)))
    if "--reported" in sys.argv:
        for gtd, run in REPORTED:
            gt = open_dataset("folder", gtd).poses
            odo = read_kitti(run + "/odometry_kitti.txt")
            rows.append(row(run.split("/")[-1], "reported-a", gt, odo, edges(run, odo)))
    json.dump(rows, open(sys.argv[1], "w"), indent=1)


if __name__ == "__main__":
    main()
