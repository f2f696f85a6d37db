"""Scale run of `graffmatch loops` (issue 15): one 5,000-scan simulated drive on this machine.

    PYTHONPATH=$PWD nice -n 19 python bench/bench_loops_scale.py --json bench/results/loops_scale.json

Simulates a 5 km suburban drive (seed 7, OS1-64, 1 m between scans; ~80 % of its scans revisit
an earlier place), then runs ``run_loops`` on it with the default configuration and executor
(local processes). Reports the wall time of each phase, the CPU time and the peak memory of the
whole process tree (driver + workers, sampled every 0.5 s from /proc) and the database bytes
per scan. The run is niced (it is long), so its wall times are upper bounds on a shared
machine; the load average is sampled alongside.

A run may be split (``--extract-only`` first, or a kill): every invocation appends its own
record (phase, wall, CPU, peak memory, load, queries done before and after) to
``<out>/scale_runs.jsonl``, and the JSON reports all of them, so a resumed run is stated as
such. ``run_loops`` itself decides what a resume keeps (landmark tables whose scan file,
labels and extractor config are unchanged; query records of the same database and config).

``--posegraph`` only times the pose graph of a finished run (``--out``: its ``loops.csv``; the
folder is only read) with the drive's poses under the default simulated drift (seeds
``--drift-seeds``): the plain graph and the default graph (heading-rate bias), wall and CPU
seconds, the process's peak RSS before and after, ATE/RPE before and after; run it timed:

    flock /tmp/bench.lock env PYTHONPATH=$PWD python bench/bench_loops_scale.py --posegraph \
        --json bench/results/loops_scale_posegraph.json
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, peak_rss_mb, write_json


def _process_tree(root: int) -> dict[int, tuple[int, float]]:
    """(resident pages, user + system CPU seconds) of ``root`` and each descendant now, by pid,
    from one pass over /proc."""
    children: dict[int, list[int]] = {}
    stat: dict[int, tuple[int, float]] = {}
    tick = os.sysconf("SC_CLK_TCK")
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                parts = f.read().rsplit(")", 1)[1].split()
            ppid, ut, st, pages = int(parts[1]), int(parts[11]), int(parts[12]), int(parts[21])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(d))
        stat[int(d)] = (pages, (ut + st) / tick)
    out, stack = {}, [root]
    while stack:
        p = stack.pop()
        if p in stat:
            out[p] = stat[p]
        stack.extend(children.get(p, []))
    return out


def _tree_rss_mb(root: int) -> float:
    """Resident memory of ``root`` and all its descendants [MB]."""
    return sum(pages for pages, _ in _process_tree(root).values()) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _tree_cpu_s(root: int) -> dict[int, float]:
    """User + system CPU seconds of ``root`` and each descendant now, by pid."""
    return {p: cpu for p, (_, cpu) in _process_tree(root).items()}


class PeakMemory:
    """Samples the process tree's RSS, its CPU time and the load average in a background thread.

    CPU time: the last sample of every process of the tree ever seen, summed (a worker that
    exits loses at most its last 0.5 s).
    """

    def __init__(self, period: float = 0.5) -> None:
        self.period, self.peak, self.loads = period, 0.0, []
        self.cpu: dict[int, float] = {}
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    @property
    def cpu_s(self) -> float:
        return float(sum(self.cpu.values()))

    def _run(self) -> None:
        k = 0
        while not self._stop.is_set():
            self.peak = max(self.peak, _tree_rss_mb(os.getpid()))
            self.cpu.update(_tree_cpu_s(os.getpid()))
            if k % 20 == 0:
                self.loads.append(os.getloadavg()[0])
            k += 1
            self._stop.wait(self.period)

    def __enter__(self) -> PeakMemory:
        self._t.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._t.join()
        self.cpu.update(_tree_cpu_s(os.getpid()))


def status(out: Path) -> dict:
    """What a run folder holds now, from its files (sizes, modification times, query log)."""
    import json

    import numpy as np

    tabs = sorted((out / "landmarks").glob("[0-9]" * 6 + ".npz"))
    mt = np.array([p.stat().st_mtime for p in tabs])
    sizes = np.array([p.stat().st_size for p in tabs])
    q = out / "queries.jsonl"
    lines = q.read_text().splitlines() if q.is_file() else []
    recs = []
    for line in lines:
        try:
            recs.append(json.loads(line))
        except json.JSONDecodeError:
            pass
    desc_bytes = 96 * 4
    running = {}
    for d in os.listdir("/proc"):  # a scale run still going: its process tree's memory now
        if d.isdigit() and int(d) != os.getpid():
            try:
                cmd = open(f"/proc/{d}/cmdline", "rb").read().replace(b"\0", b" ").decode()
            except OSError:
                continue
            if "bench_loops_scale.py" in cmd and "--status" not in cmd:
                running[d] = _tree_rss_mb(int(d))
    res = {
        "machine": machine(),
        "out": str(out),
        "landmark_tables": len(tabs),
        "table_bytes_mean": float(sizes.mean()) if len(tabs) else None,
        "table_bytes_max": int(sizes.max()) if len(tabs) else None,
        "database_bytes_per_scan": float(sizes.mean() + desc_bytes) if len(tabs) else None,
        "extraction_first_to_last_table_s": float(mt.max() - mt.min()) if len(tabs) else None,
        "queries_done": len(recs),
        "queries_file_age_s": float(time.time() - q.stat().st_mtime) if q.is_file() else None,
        "verified_per_query": float(np.mean([sum(c.get("verified", True) for c in r["candidates"]) for r in recs]))
        if recs else None,
        "running_scale_runs_rss_tree_mb": running,
        "queries_with_loop_ge_0.5": int(sum(any(c["confidence"] >= 0.5 for c in r["candidates"]) for r in recs)),
    }
    print(res)
    return res


def _load_stats(loads: list[float]) -> dict:
    import numpy as np

    a = np.asarray(loads or [os.getloadavg()[0]])
    return {"min": float(a.min()), "mean": float(a.mean()), "max": float(a.max())}


def time_posegraph(drive: Path, out: Path, seeds: list[int]) -> dict:
    """The plain and the default pose graph of a finished run's loops, timed (see the docstring)."""
    import numpy as np

    from graffmatch.datasets.registry import open_dataset
    from graffmatch.loops.io import loop_edges, read_loops_csv
    from graffmatch.loops.posegraph import (
        OdometryDriftConfig,
        PoseGraphConfig,
        drifted_odometry,
        optimize_pose_graph,
        trajectory_errors,
    )

    ds = open_dataset("folder", drive)
    gt = np.asarray(ds.poses, float)
    edges = loop_edges(read_loops_csv(out / "loops.csv"))
    rows = []
    for seed in seeds:
        odo = drifted_odometry(gt, OdometryDriftConfig(seed=seed))
        before = trajectory_errors(odo, gt)
        for graph, bias in (("plain", False), ("default (heading-rate bias)", True)):
            rss0 = peak_rss_mb()
            t, c = time.perf_counter(), time.process_time()
            opt, info = optimize_pose_graph(odo, edges, PoseGraphConfig(estimate_odometry_bias=bias))
            wall, cpu = time.perf_counter() - t, time.process_time() - c
            after = trajectory_errors(opt, gt)
            rows.append({"seed": seed, "graph": graph, "poses": len(gt), "loop_edges": len(edges),
                         "wall_s": wall, "cpu_s": cpu, "peak_rss_mb_before": rss0, "peak_rss_mb_after": peak_rss_mb(),
                         "ate_before_m": before["ate_rmse_m"], "ate_after_m": after["ate_rmse_m"],
                         "rpe_before_m": before["rpe_rmse_m"], "rpe_after_m": after["rpe_rmse_m"],
                         "bias_deg_per_100m": info.get("odometry_heading_bias_deg_per_100m"),
                         "bias_solves": info.get("bias_solves"), "lm_iterations": info["iterations"],
                         "load_avg_1min": os.getloadavg()[0]})
            print(rows[-1], flush=True)
    return {"machine": machine(), "drive": str(drive), "run": str(out), "niced": os.nice(0), "rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("/tmp/loops_scale/data"))
    ap.add_argument("--out", type=Path, default=Path("/tmp/loops_scale/out"))
    ap.add_argument("--scans", type=int, default=5000)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--executor", default="local")
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--extract-only", action="store_true",
                    help="simulate and build the landmark database, then stop (a later run resumes from it)")
    ap.add_argument("--status", action="store_true",
                    help="do not run: report the state of a run folder (--out), e.g. one still running "
                    "or cut by a deadline: tables extracted and their size, extraction span, queries done")
    ap.add_argument("--posegraph", action="store_true",
                    help="do not run: time the pose graph of the finished run in --out (read only)")
    ap.add_argument("--drift-seeds", type=int, nargs="+", default=[0])
    args = ap.parse_args()
    if args.posegraph:
        drive = args.data / f"suburban-s{args.seed}-{args.scans}"
        write_json(str(args.json) if args.json else None, time_posegraph(drive, args.out, args.drift_seeds))
        return
    if args.status:
        write_json(str(args.json) if args.json else None, status(args.out))
        return

    import json

    from graffmatch.datasets.registry import open_dataset
    from graffmatch.datasets.simulator import SIMULATOR_VERSION, SUITES, simulate_dataset
    from graffmatch.loops.detector import LoopDetectorConfig
    from graffmatch.loops.sequence import build_database, read_queries, run_loops

    s = SUITES["sim-suburban"]
    t_start = time.time()
    phases: dict[str, float] = {}
    last = [0.0]

    def sim_progress(i: int, n: int) -> None:
        if time.perf_counter() - last[0] > 60:
            last[0] = time.perf_counter()
            print(f"simulate {i}/{n} load {os.getloadavg()[0]:.1f}", flush=True)

    def progress(stage: str, done: int, total: int) -> None:
        phases[stage] = time.perf_counter()
        if done % 250 == 0 or done == total:
            print(f"{stage} {done}/{total} load {os.getloadavg()[0]:.1f}", flush=True)

    args.out.mkdir(parents=True, exist_ok=True)
    queries_before = len(read_queries(args.out))
    with PeakMemory() as mem:
        t0 = time.perf_counter()
        drive = simulate_dataset(args.data / f"suburban-s{args.seed}-{args.scans}", style=s.style, seed=args.seed,
                                 n_scans=args.scans, sensor=s.sensor, world_config=s.world_config(), reuse=True,
                                 progress=sim_progress)
        t1 = time.perf_counter()
        ds = open_dataset("folder", drive)
        config = LoopDetectorConfig()
        if args.extract_only:
            _, stats = build_database(ds, args.out, config, args.executor, args.workers, progress=progress)
            summary = None
        else:
            summary = run_loops(ds, args.out, config, executor=args.executor, workers=args.workers,
                                progress=progress)
            stats = summary["landmarks"]
        t2 = time.perf_counter()
    record = {
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t_start)),
        "command": " ".join(sys.argv),
        "niced": os.nice(0),
        "phase": "extract-only" if args.extract_only else "full",
        "simulator_version": SIMULATOR_VERSION,
        "simulate_s": t1 - t0,
        "wall_s": t2 - t0,
        "loops_wall_s": t2 - t1,
        "extract_wall_s": (phases["landmarks"] - t1) if "landmarks" in phases else 0.0,
        "tables_extracted": stats["extracted"],
        "tables_cached": stats["cached"],
        "queries_done_before": queries_before,
        "queries_done_after": len(read_queries(args.out)),
        "cpu_s_tree": mem.cpu_s,
        "peak_rss_tree_mb": mem.peak,
        "load_avg": _load_stats(mem.loads),
    }
    with open(args.out / "scale_runs.jsonl", "a") as f:
        f.write(json.dumps(record) + "\n")
    runs = [json.loads(line) for line in (args.out / "scale_runs.jsonl").read_text().splitlines() if line.strip()]
    payload = {
        "machine": machine(),
        "drive": str(drive),
        "n_scans": len(ds),
        "invocations": runs,
        "totals_over_invocations": {
            "wall_s": float(sum(r["wall_s"] for r in runs)),
            "cpu_s_tree": float(sum(r["cpu_s_tree"] for r in runs)),
            "peak_rss_tree_mb": float(max(r["peak_rss_tree_mb"] for r in runs)),
        },
        "summary": summary,
    }
    print(json.dumps({k: v for k, v in payload.items() if k != "summary"}, indent=1))
    write_json(str(args.json) if args.json else None, payload)


if __name__ == "__main__":
    main()
