"""GNC rule v1 (docs/loops.md, session 25): the default LM pose graph against GTSAM's GNC (TLS, only the prior a known
inlier), evo ATE on the 8 calibration drives: (a) scans-alone KISS-ICP runs (/tmp/s25/jc-*), (b) the benchmark run's
records (/tmp/s25/calb) under the default simulated drift, seeds 0-2. Writes the rows to the JSON path given.

    PYTHONPATH=$PWD python bench/loops_gnc_calibration.py bench/results/loops_gnc_calibration_session25.json
"""
import json
import sys

import gtsam
import numpy as np
import yaml

import graffmatch.loops.posegraph as pg
from graffmatch.datasets.registry import open_dataset
from graffmatch.geometry.pose_files import read_kitti
from graffmatch.loops.consistency import apply_sequence_consistency
from graffmatch.loops.detector import LoopDetectorConfig
from graffmatch.loops.io import loop_edges
from graffmatch.loops.posegraph import OdometryDriftConfig, drifted_odometry
from graffmatch.loops.sequence import loops_from_records, read_queries

cfg = pg.PoseGraphConfig()
def gnc(P, E):
    initial = gtsam.Values()
    for i in range(len(P)):
        initial.insert(i, gtsam.Pose3(P[i]))
    steps = pg._odometry_steps(gtsam, P, cfg)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(P[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    for i, (Z3, _, _step, sig) in enumerate(steps):
        graph.add(gtsam.BetweenFactorPose3(i, i + 1, Z3, gtsam.noiseModel.Diagonal.Sigmas(sig)))
    perm = np.r_[3:6, 0:3]
    for i, j, T, info in E:
        graph.add(gtsam.BetweenFactorPose3(int(i), int(j), gtsam.Pose3(T), gtsam.noiseModel.Gaussian.Information(np.asarray(info)[np.ix_(perm, perm)])))
    params = gtsam.GncLMParams(gtsam.LevenbergMarquardtParams())
    params.setLossType(gtsam.GncLossType.TLS)
    params.setKnownInliers([0])
    res = gtsam.GncLMOptimizer(graph, initial, params).optimize()
    return np.stack([res.atPose3(i).matrix() for i in range(len(P))])
def ate(X, gt):
    return round(pg.trajectory_errors(X, gt)["ate_rmse_m"], 3)


rows = []
drives = ["downtown-s2", "downtown-s3", "downtown-s4", "downtown-s6", "suburban-s3", "suburban-s5", "openroad-s2", "openroad-s5"]
for d in drives:
    gt = open_dataset("folder", f"/tmp/s25/cal400/sim-{d}").poses
    run = f"/tmp/s25/jc-{d}"
    P = read_kitti(run + "/odometry_kitti.txt")
    c = LoopDetectorConfig.model_validate(yaml.safe_load(open(run + "/config.yaml")))
    E = loop_edges(loops_from_records(apply_sequence_consistency(read_queries(run), P, c.verification), c.verification.min_confidence))
    lm, _ = pg.optimize_pose_graph(P, E)
    r = {"drive": d, "setup": "a", "odo": ate(P, gt), "lm": ate(lm, gt), "gnc": ate(gnc(P, E), gt)}
    print(json.dumps(r), flush=True)
    rows.append(r)
    run = f"/tmp/s25/calb/sim-{d}+deskew/ours"
    c = LoopDetectorConfig.model_validate(yaml.safe_load(open(run + "/config.yaml")))
    recs = read_queries(run)
    for seed in (0, 1, 2):
        P = drifted_odometry(gt, OdometryDriftConfig(seed=seed))
        E = loop_edges(loops_from_records(apply_sequence_consistency(recs, P, c.verification), c.verification.min_confidence))
        lm, _ = pg.optimize_pose_graph(P, E)
        r = {"drive": d, "setup": f"b{seed}", "odo": ate(P, gt), "lm": ate(lm, gt), "gnc": ate(gnc(P, E), gt)}
        print(json.dumps(r), flush=True)
        rows.append(r)
json.dump(rows, open(sys.argv[1], "w"), indent=1)
