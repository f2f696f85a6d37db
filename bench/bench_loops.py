"""Sequence-level loop-closure benchmark (issue 15): ours vs Scan Context + ICP (and MapClosures
with ground-truth poses), on simulated drives with revisits and on balm_courtyard.

    PYTHONPATH=$PWD python bench/bench_loops.py --prepare            # simulate + extract (untimed)
    flock /tmp/bench.lock env PYTHONPATH=$PWD python bench/bench_loops.py --json bench/results/loops.json

Drives (300 scans each, 1 m apart; routes chosen for revisits incl. reverse-direction ones):
downtown seeds 1 and 5, suburban 1 and 4, open-road 1 and 3 (1800 scans), each with its
suite's world and sensor.

Raw, motion-distorted drives (session 7): ``--realism realistic`` simulates the same seeds with
the suites' realistic preset (motion distortion within the sweep, movers, noisy labels; the car
slows in turns, so a scan every 0.1 s is < 1 m apart: ``--scans 400``), and ``--deskew
--odometry drift`` de-skews every simulated scan for every method with the same function as
``graffmatch loops --deskew`` (``loops.sequence.prepare_drive``); ``balm_courtyard`` (real,
a slow hand-held walk) is benchmarked as it is, in the same invocation:

    PYTHONPATH=$PWD python bench/bench_loops.py --realism realistic --scans 400 --deskew \
        --data /tmp/loops7-data --out /tmp/loops7-out --json bench/results/loops_session7.json

Our own odometry (session 11): ``--odometry kiss-icp`` runs KISS-ICP once per drive on its raw
scans (kept in ``<out>/<drive>/kiss_icp_kitti.txt``); the de-skew, our retrieval's positions and
the sequence-consistency rule all read it, and every row records its evo ATE (``odometry``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import apply_verification_overrides, machine, peak_rss_mb

DRIVES = [("sim-downtown", 1), ("sim-downtown", 5), ("sim-suburban", 1), ("sim-suburban", 4),
          ("sim-openroad", 1), ("sim-openroad", 3)]
N_SCANS = 300
COURTYARD = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "balm_courtyard"


def simulate(root: Path, n_scans: int, realism: str = "ideal",
             drives: list[tuple[str, int]] | None = None) -> list[Path]:
    """The six drives (or ``drives``: (suite, seed) pairs) under ``root`` (``realism``: 'ideal' =
    session 1-6's clean, undistorted scans; 'realistic' = the suites' preset: motion-distorted
    raw scans, movers, noisy labels)."""
    from graffmatch.datasets.simulator import SUITES, simulate_dataset

    out = []
    for name, seed in drives or DRIVES:
        s = SUITES[name]
        d = root / f"{name}-s{seed}"
        if (d / "poses.txt").is_file() and len(list((d / "velodyne").glob("*.bin"))) == n_scans:
            out.append(d)  # already simulated (kept as is: a newer simulator version would
            continue  # rewrite the files and invalidate the landmark cache)
        out.append(simulate_dataset(root / f"{name}-s{seed}", style=s.style, seed=seed, n_scans=n_scans,
                                    sensor=s.sensor, world_config=s.world_config(), reuse=True,
                                    realism=realism))
    return out


def _strip_curves(res: list[dict]) -> list[dict]:
    for r in res:
        for k in list(r):
            if isinstance(r[k], dict) and "curve" in r[k]:
                r[k] = {kk: vv for kk, vv in r[k].items() if kk != "curve"}
    return res


def merge(dirs: list[Path], json_path: Path | None, timed: list[Path]) -> None:
    """One table from several runs on the same scans, rows ordered by sequence, then run.

    A method that appears in several runs is labelled with its run folder's name; our rows of the
    first run take their ms/query from the timed runs (mode quick-20, the default).
    """
    from graffmatch.evaluation.sequence_benchmark import format_table, plot_pr

    res, walls = [], {}
    keep: dict[Path, list[str]] = {}
    for k, d in enumerate(dirs):  # FOLDER::PREFIX,PREFIX keeps only those methods of a run
        if "::" in str(d):
            folder, prefixes = str(d).split("::", 1)
            dirs[k] = Path(folder)
            keep[dirs[k]] = prefixes.split(",")
    for d in dirs:
        rows = json.loads((d / "results.json").read_text())
        if d in keep:
            rows = [r for r in rows if any(r["method"].startswith(p) for p in keep[d])]
        for r in rows:
            r["run_dir"] = str(d)
        res += rows
    count: dict[tuple[str, str], int] = {}
    for r in res:
        count[(r["sequence"], r["method"])] = count.get((r["sequence"], r["method"]), 0) + 1
    for r in res:
        if count[(r["sequence"], r["method"])] > 1:
            r["method"] = f"{r['method']} [{Path(r['run_dir']).name}]"
    ms = {}
    for t in timed:
        for row in json.loads(t.read_text())["rows"]:
            if row["mode"] == "quick-20":
                ms[row["drive"]] = (row["ms_per_query_mean"], str(t))
    for r in res:
        if r["method"].startswith("ours") and r["sequence"] in ms and r["run_dir"] == str(dirs[0]):
            r["seconds_per_query_run"] = r["seconds_per_query"]
            r["seconds_per_query"] = ms[r["sequence"]][0] / 1e3
            r["seconds_per_query_source"] = ms[r["sequence"]][1]
        log = d / "wall_s.json"
        if log.is_file():
            walls[str(d)] = json.loads(log.read_text())
    for r in res:  # precision / recall at our default threshold, read off the PR curves
        if r["method"].startswith("ours"):
            for key in ("place_5m", "e2e_5m"):
                c = r[key]["curve"]
                i = [k for k, t in enumerate(c["threshold"]) if t >= 0.5]
                r[key]["at_min_confidence_0.5"] = (
                    {"precision": c["precision"][i[-1]], "recall": c["recall"][i[-1]]} if i else None
                )
    seq_order = list(dict.fromkeys(r["sequence"] for r in res))
    res.sort(key=lambda r: (seq_order.index(r["sequence"]), [str(d) for d in dirs].index(r["run_dir"])))
    (dirs[0].parent / "merged").mkdir(exist_ok=True)
    plot_pr(res, dirs[0].parent / "merged")
    table = format_table(res)
    print(table)
    for r in res:
        if "at_min_confidence_0.5" in r["place_5m"]:
            print(r["sequence"], r["method"], "at confidence >= 0.5: place", r["place_5m"]["at_min_confidence_0.5"],
                  "e2e", r["e2e_5m"]["at_min_confidence_0.5"])
    if json_path:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps({"machine": machine(), "runs": walls, "table": table,
                                         "results": _strip_curves(res)}, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("/tmp/loops_bench/data"))
    ap.add_argument("--out", type=Path, default=Path("/tmp/loops_bench/out"))
    ap.add_argument("--scans", type=int, default=N_SCANS)
    ap.add_argument("--prepare", action="store_true", help="only simulate and extract (untimed)")
    ap.add_argument("--methods", nargs="+", default=["ours", "scan-context-icp", "mapclosures-gt"])
    ap.add_argument("--no-courtyard", action="store_true")
    ap.add_argument("--timed", type=Path, nargs="*", default=None,
                    help="with --merge: bench_loops_speed.py JSONs whose quick-20 means replace our "
                    "rows' ms/query (the runs here are niced and loaded)")
    ap.add_argument("--drives", nargs="+", default=None, metavar="SUITE:SEED",
                    help="simulate and run these drives instead of the six reported ones (e.g. sim-openroad:4, "
                    "a drive without revisits)")
    ap.add_argument("--only", nargs="+", default=None,
                    help="run only these sequences (folder names), in this order")
    ap.add_argument("--realism", default="ideal", help="simulator realism preset of the drives (ideal, realistic)")
    ap.add_argument("--deskew", action="store_true", help="de-skew the simulated drives (not the courtyard)")
    ap.add_argument("--odometry", default="drift", help="--deskew: drift | gt | kiss-icp | PATH")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--union", default=None, metavar="R:F",
                    help="ours with the descriptor+radius retriever at R m + F x odometry path (the default is 5:0.02, "
                    "bench/loops_calibration_union.py), or 'off' for the descriptor alone; the courtyard has no "
                    "odometry, so descriptor only there")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--verification", nargs="+", default=[], metavar="KEY=VALUE",
                    help="override VerificationConfig fields of our detector (a labelled variant, e.g. "
                    "scans_skip_quick_check=false; 'matcher.KEY': the verified matcher's VerificationConfig; values "
                    "parsed as JSON)")
    ap.add_argument("--merge", type=Path, nargs="+", default=None,
                    help="only merge the results.json of these --out folders (same scans, methods run "
                    "in separate processes) into one table and --json; FOLDER::PREFIX,... keeps only the "
                    "methods of that run whose names start so")
    args = ap.parse_args()
    if args.merge:
        merge(args.merge, args.json, args.timed or [])
        return

    from graffmatch.evaluation.sequence_benchmark import (
        benchmark_config,
        format_table,
        run_sequence_benchmark,
    )

    drives = None
    if args.drives:
        drives = [(d.rsplit(":", 1)[0], int(d.rsplit(":", 1)[1])) for d in args.drives]
    seqs = simulate(args.data, args.scans, args.realism, drives)
    if not args.no_courtyard:
        if COURTYARD.is_dir():
            seqs.append(COURTYARD.resolve())
        else:  # said, not silent: a worktree outside the checkout has no ../shared (session 24 lost it so once)
            print(f"balm_courtyard skipped: {COURTYARD} is not a folder (../shared/data absent)", flush=True)
    if args.only:
        by_name = {p.name: p for p in seqs}
        seqs = [by_name[n] for n in args.only]
    t0 = time.perf_counter()
    methods = ["ours"] if args.prepare else args.methods
    groups = [(seqs, False)]
    if args.deskew:  # the simulated drives de-skewed; the courtyard as it is, its results beside them
        groups = [([p for p in seqs if p.name != "balm_courtyard"], True),
                  ([p for p in seqs if p.name == "balm_courtyard"], False)]
    config = benchmark_config()
    apply_verification_overrides(config, args.verification)  # a labelled variant of the defaults
    if args.union == "off":
        config.retrieval.method = "descriptor"  # the default before session 10's end
    elif args.union:
        R, F = (float(x) for x in args.union.split(":"))
        config.retrieval.method = "descriptor+radius"
        config.retrieval.union_radius_m, config.retrieval.drift_fraction = R, F
    results = []
    for k, (group, deskew) in enumerate(groups):
        if not group:
            continue
        out = args.out if k == 0 else args.out / "as-recorded"
        run_sequence_benchmark(group, out, methods=methods, workers=args.workers, config=config,
                               extract_only=args.prepare, deskew=deskew,
                               odometry=args.odometry if deskew else None)
        if not args.prepare:
            results += json.loads((out / "results.json").read_text())
    if len(groups) > 1 and results:
        (args.out / "results.json").write_text(json.dumps(results, indent=1))
    table = format_table(results) if results else ""
    wall = time.perf_counter() - t0
    print(table)
    print(f"wall {wall:.0f} s, peak RSS {peak_rss_mb():.0f} MB (driver)")
    if not args.prepare:
        (args.out / "wall_s.json").write_text(json.dumps({"methods": methods, "wall_s": wall, **machine()}))
    if args.json and not args.prepare:
        res = _strip_curves(json.loads((args.out / "results.json").read_text()))
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"machine": machine(), "wall_s": wall, "table": table, "results": res}, indent=1))


if __name__ == "__main__":
    main()
