"""Per-query time of `graffmatch loops` (issue 15): retrieval + pre-screen + verification,
extraction and per-scan precomputation excluded, on the benchmark drives' cached landmarks.

    PYTHONPATH=$PWD nice -n 19 python bench/bench_loops_speed.py --prepare   # check inputs (untimed)
    flock /tmp/bench.lock env PYTHONPATH=$PWD python bench/bench_loops_speed.py \\
        --json bench/results/loops_speed.json

Needs the landmark tables of ``bench/bench_loops.py --prepare`` (``--runs``). For each drive the
database (landmark maps, descriptors, quick-check indices) is built once, untimed, like
extraction; then every ``--stride``-th query is timed serially, one process, in each mode
(wall and CPU time of the query: mean, median, p90, p95; its parts: retrieval, the quick check
of all candidates, the verifications; candidates passing the quick check and verified; the load
average before and after the drive):

* ``verify-all-5``: top-5 descriptor candidates, every one verified (the previous pipeline);
* ``quick-5``: top-5 candidates, the BEV quick check, passing ones verified best first, stop at
  the first accepted one;
* ``quick-10`` / ``quick-20``: top-10 / top-20 candidates through the quick check, at most 5
  verified, early stop (``quick-20`` is the default since it lifts retrieval recall).

Also reported per mode: candidates verified per query and the queries with an accepted loop.

With ``--odometry kiss-icp`` (or ``drift`` ... any KITTI file name under ``<runs>/<drive>/``, or a
path) the odometry poses of the recorded run go into the database, so that the default
``descriptor+radius`` retriever adds the scans near the odometry estimate, as in
``bench/bench_loops.py --odometry kiss-icp`` (without it the retriever is the descriptor alone:
sessions 4-10's timings). ``--records`` writes one JSON line per timed query (its time, its
candidates, which were verified, on points or landmarks, and their seconds): the distribution, not
just the mean (session 13).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import apply_verification_overrides, machine, write_json

COURTYARD = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "balm_courtyard"
DRIVES = ["sim-downtown-s1", "sim-downtown-s5", "sim-suburban-s1", "sim-suburban-s4", "sim-openroad-s1",
          "sim-openroad-s3", "balm_courtyard"]
MODES = {
    "verify-all-5": dict(top_k=5, quick_check=False, stop_when_accepted=False),
    "quick-5": dict(top_k=5, quick_check=True, stop_when_accepted=True),
    "quick-10": dict(top_k=10, quick_check=True, stop_when_accepted=True),
    "quick-20": dict(top_k=20, quick_check=True, stop_when_accepted=True),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=Path, default=Path("/tmp/loops_bench/out"))
    ap.add_argument("--data", type=Path, default=Path("/tmp/loops_bench/data"))
    ap.add_argument("--drives", nargs="+", default=DRIVES)
    ap.add_argument("--modes", nargs="+", default=["quick-5", "quick-20"])
    ap.add_argument("--stride", type=int, default=4)
    ap.add_argument("--prepare", action="store_true")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--odometry", default=None,
                    help="'kiss-icp' (<runs>/<raw drive>/kiss_icp_kitti.txt) or a KITTI pose file: positions and "
                    "poses for the descriptor+radius retriever and sequence consistency")
    ap.add_argument("--records", type=Path, default=None, help="one JSON line per timed query")
    ap.add_argument("--scan-source", action=argparse.BooleanOptionalAction, default=True,
                    help="give the detector the drive's scans, as graffmatch loops does (default; --no-scan-source: none) ('+deskew' drives: de-skewed with the drift odometry, bench_loops.py's default), "
                    "which the place check (loops/place_check.py, session 23) reads inside the query's clock")
    ap.add_argument("--verification", nargs="+", default=[], metavar="KEY=VALUE",
                    help="override VerificationConfig fields of our detector (a labelled variant, e.g. "
                    "scans_skip_quick_check=false; 'matcher.KEY': the verified matcher's VerificationConfig; values "
                    "parsed as JSON)")
    args = ap.parse_args()

    import json

    import numpy as np

    from graffmatch.datasets.registry import open_dataset
    from graffmatch.evaluation.sequence_benchmark import benchmark_config
    from graffmatch.geometry.pose_files import read_kitti
    from graffmatch.loops.database import LandmarkDatabase, load_landmarks, load_scan_cloud
    from graffmatch.loops.descriptor import landmark_descriptor
    from graffmatch.loops.detector import LoopDetector, has_point_pairs
    from graffmatch.loops.local_map import attach_local_maps
    from graffmatch.loops.quickcheck import quick_index
    from graffmatch.loops.retrieval import eligible_count

    rows = []
    load0 = os.getloadavg()[0]
    rec_f = open(args.records, "w") if args.records else None
    for drive in args.drives:
        lm_dir = args.runs / drive / "ours" / "landmarks"
        files = sorted(lm_dir.glob("[0-9]" * 6 + ".npz"))
        if not files:
            raise SystemExit(f"{lm_dir}: no landmark tables (run bench/bench_loops.py --prepare)")
        if args.prepare:
            print(drive, len(files), "scans")
            continue
        base = benchmark_config()
        apply_verification_overrides(base, args.verification)  # a labelled variant of the defaults
        db = LandmarkDatabase()
        # a de-skewed drive (bench_loops.py --deskew: "<name>+deskew") has its raw drive's times
        src = COURTYARD if drive == "balm_courtyard" else args.data / drive.removesuffix("+deskew")
        stamps = np.asarray(open_dataset("folder", src).timestamps, float)
        for i, f in enumerate(files):
            ls = load_landmarks(f)
            # the scan cloud of a landmark-poor scan, when the run kept one (scan_cloud_below, session 15)
            db.add(ls, landmark_descriptor(ls, base.descriptor), float(stamps[i]), scan=load_scan_cloud(f))
        poses = None
        if args.odometry:
            odo = Path(args.odometry)
            if args.odometry == "kiss-icp":
                odo = args.runs / drive.removesuffix("+deskew") / "kiss_icp_kitti.txt"
            poses = read_kitti(odo)
            if len(poses) != len(db):
                raise SystemExit(f"{odo}: {len(poses)} poses for {len(db)} scans")
            db.positions = [p[:3, 3].copy() for p in poses]
            # landmark-poor scans matched on their local maps, as run_loops does (untimed, like extraction)
            v = base.matcher.verification
            attach_local_maps(db, poses, base.verification, base.descriptor, v.voxel, v.max_points)
        local = db.extra.get("local") or [None] * len(db)
        db.extra["quick"] = [quick_index(ls if m is None else m, base.quick) for ls, m in zip(db.landmarks, local, strict=True)]
        for mode in args.modes:
            cfg = base.model_copy(deep=True)
            opts = MODES[mode]
            cfg.retrieval.top_k = opts["top_k"]
            cfg.verification.quick_check = opts["quick_check"]
            cfg.verification.stop_when_accepted = opts["stop_when_accepted"]
            scans = None
            if args.scan_source:
                from graffmatch.loops.sequence import prepare_drive

                raw = open_dataset("folder", src)
                ds = prepare_drive(raw, "drift", True)[0] if drive.endswith("+deskew") else raw
                scans = ds
            det = LoopDetector(cfg, scans=scans)
            det.db = db
            if poses is not None:  # sequence consistency reads the poses given to add()
                det._poses = list(poses)
            t_w, c_w = time.perf_counter(), time.process_time()
            # warm-up (numba compilation, caches; the place check's first Open3D call) outside the clock, as
            # run_loops' workers do it: with the evidence-point and raw-scan paths when two scans keep points
            # (until session 24 points=False here, so those kernels loaded, or on a cold cache compiled, inside a
            # timed query: downtown-s1's 260 took 0.6-0.8 s on a cold cache)
            det.warm_up(points=has_point_pairs(db))
            for q in range(len(db) - 1, len(db) - 4, -1):
                det.detect(q)
            warm = (time.perf_counter() - t_w, time.process_time() - c_w)
            qs = [q for q in range(0, len(db), args.stride) if eligible_count(db.timestamps, q, cfg.retrieval) > 0]
            per, cpu, ver_s, nver, nloop = [], [], [], [], 0
            ret_s, quick_s, npass, ncand, nver_pts, nscan, nscreen = [], [], [], [], [], [], []
            place_s, nplace = [], []  # the place check's own time (loops/place_check.py), queries it ran on
            load_a = os.getloadavg()[0]
            for q in qs:
                c0 = time.process_time()
                t0 = time.perf_counter()
                loops = det.detect(q)
                per.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
                recs = det.last_records
                nver.append(sum(r["verified"] for r in recs))
                ver_s.append(sum(r.get("verify_seconds", 0.0) for r in recs))
                ret_s.append(det.timings["retrieve"][-1])
                quick_s.append(sum(r["seconds"] - r.get("verify_seconds", 0.0) for r in recs))
                npass.append(sum(r["quick_pass"] for r in recs))
                nloop += bool(loops)
                ncand.append(len(recs))
                nver_pts.append(sum(bool(r.get("on_points")) for r in recs if r["verified"]))
                nscan.append(sum("scan_valid" in r for r in recs if r["verified"]))
                nscreen.append(sum("screen_prior" in r for r in recs))  # session 16's first screen
                place_s.append(sum(r.get("place_seconds", 0.0) for r in recs))
                nplace.append(sum("place_seconds" in r for r in recs))
                if rec_f:
                    rec_f.write(json.dumps({
                        "drive": drive, "mode": mode, "query": q, "ms": 1e3 * per[-1], "cpu_ms": 1e3 * cpu[-1],
                        "retrieve_ms": 1e3 * ret_s[-1], "quick_ms": 1e3 * quick_s[-1], "loop": bool(loops),
                        "candidates": len(recs), "quick_passing": npass[-1],
                        "place_check_ms": 1e3 * place_s[-1], "place_checked": nplace[-1],
                        "verified": [{"match": r["match"], "rank": r["rank"], "on_points": bool(r.get("on_points")),
                                      "ms": 1e3 * r.get("verify_seconds", 0.0), "confidence": r["confidence"],
                                      "scan_pass": "scan_valid" in r, "on_scans": bool(r.get("on_scans"))}
                                     for r in recs if r["verified"]]}) + "\n")
            per_a, ver_a = 1e3 * np.asarray(per), 1e3 * np.asarray(ver_s)
            row = {"drive": drive, "mode": mode, "queries": len(qs), "ms_per_query_mean": float(per_a.mean()),
                   "ms_per_query_median": float(np.median(per_a)), "ms_per_query_p90": float(np.percentile(per_a, 90)),
                   "ms_per_query_p95": float(np.percentile(per_a, 95)),
                   "cpu_ms_per_query_mean": 1e3 * float(np.mean(cpu)),
                   "verify_ms_per_query_mean": float(ver_a.mean()),
                   "other_ms_per_query_mean": float((per_a - ver_a).mean()),  # retrieval + quick check + records
                   "retrieve_ms_per_query_mean": 1e3 * float(np.mean(ret_s)),
                   "quick_check_ms_per_query_mean": 1e3 * float(np.mean(quick_s)),
                   "quick_passing_per_query": float(np.mean(npass)),
                   "ms_per_verification": float(ver_a.sum() / max(sum(nver), 1)),
                   "verified_per_query": float(np.mean(nver)), "queries_with_loop": nloop,
                   "ms_per_query_max": float(per_a.max()), "cpu_ms_per_query_median": 1e3 * float(np.median(cpu)),
                   "cpu_ms_per_query_p95": 1e3 * float(np.percentile(cpu, 95)),
                   "cpu_ms_per_query_max": 1e3 * float(np.max(cpu)),
                   "candidates_per_query": float(np.mean(ncand)), "candidates_per_query_max": int(np.max(ncand)),
                   "verified_on_points_per_query": float(np.mean(nver_pts)),
                   "scan_passes_per_query": float(np.mean(nscan)),
                   "screens_per_query": float(np.mean(nscreen)),
                   "place_check_ms_per_query_mean": 1e3 * float(np.mean(place_s)),
                   "place_checked_queries": int(np.count_nonzero(nplace)),
                   "scans_with_scan_cloud": sum(x is not None for x in db.extra["scan"]),
                   "retriever": cfg.retrieval.method if poses is not None else "descriptor (no positions)",
                   "odometry": None if poses is None else str(odo),
                   "warmup_s": warm[0], "warmup_cpu_s": warm[1],
                   "load_before": load_a, "load_after": os.getloadavg()[0]}
            rows.append(row)
            print(row, flush=True)
    if rec_f:
        rec_f.close()
    if not args.prepare:
        write_json(str(args.json) if args.json else None,
                   {"machine": machine(), "load_at_start": load0, "load_at_end": os.getloadavg()[0], "rows": rows})


if __name__ == "__main__":
    main()
