"""The odometry gate on weak loops (docs/loops.md, session 25), off and on, replayed on a run's own records (exact: the
gate is a post-pass on them in the product too), scored against the ground truth of GT_DIR.

    PYTHONPATH=$PWD python bench/loops_odometry_gate_replay.py a GT_DIR RUN_DIR [GT_DIR RUN_DIR ...]
        runs of `graffmatch loops --optimize` (odometry: RUN_DIR/odometry_kitti.txt)
    ... b GT_DIR OURS_DIR [...]   benchmark runs (bench_loops.py --deskew): the default simulated drift
    ... k GT_DIR OURS_DIR [...]   benchmark runs with --odometry kiss-icp (odometry: <drive>/kiss_icp_kitti.txt)
"""

import json
import sys

import numpy as np
import yaml

from graffmatch.datasets.registry import open_dataset
from graffmatch.evaluation.sequence_benchmark import (
    MethodRun,
    Prediction,
    best_predictions,
    evaluate_method,
    pose_errors,
)
from graffmatch.geometry.pose_files import read_kitti
from graffmatch.loops.consistency import apply_sequence_consistency
from graffmatch.loops.detector import LoopDetectorConfig
from graffmatch.loops.sequence import loops_from_records, prepare_drive, read_queries


def odometry(mode: str, ds, run: str) -> np.ndarray:
    if mode == "a":
        return read_kitti(run + "/odometry_kitti.txt")
    if mode == "k":
        return read_kitti(run.replace("+deskew/ours", "") + "/kiss_icp_kitti.txt")
    return prepare_drive(ds, "drift", True)[1]


def score(mode: str, ds, gt, records, odo, cfg, gate: bool) -> tuple[dict, set]:
    v = cfg.verification.model_copy(update={"odometry_gate": gate})
    final = apply_sequence_consistency(records, odo, v)
    loops = loops_from_records(final, v.min_confidence)
    preds = [Prediction(lc.query, lc.match, lc.confidence, lc.T_match_query) for lc in loops]
    errs = np.array([pose_errors(gt, p) for p in preds]).reshape(-1, 3)
    right = (errs[:, 1] <= 5) & (errs[:, 2] <= 1)
    out = {"loops": len(loops), "pose_right": int(right.sum()), "pose_wrong": int((~right).sum()),
           "gated": sum(c.get("odometry_disagrees") is not None for r in final.values() for c in r["candidates"])}
    if mode in "bk":  # the benchmark's protocol: the most confident candidate per query
        best = best_predictions(final)
        res = evaluate_method(MethodRun("ours", best, 0.0), gt, np.asarray(ds.timestamps), cfg.retrieval)
        out["e2e_r100p"] = round(res["e2e_5m"]["recall_at_100_precision"], 4)
        e = np.array([pose_errors(gt, p) for p in best if p.confidence >= v.min_confidence]).reshape(-1, 3)
        out["not_e2e_tp"] = int((~((e[:, 0] <= 5) & (e[:, 1] <= 5) & (e[:, 2] <= 1))).sum())
    return out, {(lc.query, lc.match) for lc, ok in zip(loops, right, strict=True) if ok}


def main() -> None:
    mode, args = sys.argv[1], sys.argv[2:]
    total: dict = {"off": {}, "on": {}, "right_loops_removed": 0}
    for gtdir, run in zip(args[::2], args[1::2], strict=True):
        ds = open_dataset("folder", gtdir)
        gt = ds.poses
        cfg = LoopDetectorConfig.model_validate(yaml.safe_load(open(run + "/config.yaml")))
        records, odo = read_queries(run), odometry(mode, ds, run)
        off, right_off = score(mode, ds, gt, records, odo, cfg, False)
        on, right_on = score(mode, ds, gt, records, odo, cfg, True)
        row = {"off": off, "on": on, "right_loops_removed": sorted(right_off - right_on)}
        print(run.split("/")[-2 if run.endswith("ours") else -1], json.dumps(row), flush=True)
        for g in ("off", "on"):
            for k, val in row[g].items():
                total[g][k] = total[g].get(k, 0) + val
        total["right_loops_removed"] += len(row["right_loops_removed"])
    print("TOTAL", json.dumps(total))


if __name__ == "__main__":
    main()
