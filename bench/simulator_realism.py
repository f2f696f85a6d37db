"""How realistic is the simulator? The realism table of issue 13, real KITTI vs simulated drives.

    PYTHONPATH=. .venv/bin/python bench/simulator_realism.py [--json out.json]
        [--styles downtown suburban open-road] [--pairs 8] [--scans 40] [--seeds 1 2 3]
        [--data ../shared/data] [--realism ideal realistic]

For ../shared/data/kitti00_first6 and for short simulated HDL-64E drives of each style (one
per seed, pooled)
(written to a temporary KITTI-layout folder and read back with the same loader), takes pairs
of scans 4-5 m apart (KITTI: every pair 3.4-5 m apart, as its six scans allow, and all six
scans for the per-scan statistics), runs the default front end
without labels and the default GraffMatcher (source moved by 180 deg and 10 m), and prints
one row per statistic (``graffmatch.evaluation.realism``). Matcher errors are against each
dataset's own ground-truth poses (KITTI's are decimetres off near frame 0; see
../shared/data/README.md).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
import warnings
from pathlib import Path

from graffmatch.datasets.folder import KittiFolder
from graffmatch.datasets.simulator import STYLES, simulate_dataset
from graffmatch.evaluation.realism import (
    REALISM_COLUMNS,
    pairs_at_distance,
    sequence_realism,
    summarize_realism,
)

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def kitti_column(data: Path, max_pairs: int) -> dict:
    """KITTI 00 with all it offers: every pair of its six scans 3.4-5 m apart (0-4, 0-5, 1-5)
    and the per-scan statistics of all six scans."""
    seq = KittiFolder(data / "kitti00_first6")
    pairs = pairs_at_distance(seq.poses, 3.4, 5.0, max_pairs, every_b=True)
    return sequence_realism(seq, pairs, extra_frames=range(len(seq)))


def sim_column(style: str, seeds: list[int], n_scans: int, max_pairs: int, **sim_kwargs) -> dict:
    """One drive per seed; the summary pools the scans and pairs of all of them (one 40-scan
    drive is a few street segments: its statistics vary by tens of percent from seed to seed)."""
    scans, pairs, per_seed, t_sim = [], [], {}, 0.0
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            simulate_dataset(Path(tmp) / style, style=style, seed=seed, n_scans=n_scans,
                             sensor="hdl64", **sim_kwargs)  # fmt: skip
            t_sim += time.perf_counter() - t0
            seq = KittiFolder(Path(tmp) / style)
            out = sequence_realism(seq, pairs_at_distance(seq.poses, 4.0, 5.0, max_pairs))
        per_seed[seed] = out["summary"]
        scans += [{"seed": seed, **r} for r in out["scans"]]
        pairs += [{"seed": seed, **r} for r in out["pairs"]]
    summary = summarize_realism(scans, pairs)
    summary["simulate_s"] = t_sim
    return {"summary": summary, "per_seed": per_seed, "scans": scans, "pairs": pairs}


def print_table(cols: dict[str, dict]) -> None:
    names = list(cols)
    width = max(len(lbl) for _, lbl, _ in REALISM_COLUMNS)
    print(f"{'statistic':<{width}} " + " ".join(f"{n:>14}" for n in names))
    print("-" * (width + 15 * len(names)))
    for key, label, fmt in REALISM_COLUMNS:
        print(f"{label:<{width}} " + " ".join(
            f"{format(cols[n]['summary'][key], fmt):>14}" for n in names))  # fmt: skip
    print(f"{'pairs / scans':<{width}} " + " ".join(
        f"{cols[n]['summary']['n_pairs']:>8d} / {cols[n]['summary']['n_scans']:<3d}" for n in names
    ))  # fmt: skip
    ref = cols.get("kitti00")
    if ref is not None:
        print("\nratio to KITTI (target 0.7-1.3)")
        for key, label, _ in REALISM_COLUMNS:
            r = [cols[n]["summary"][key] / ref["summary"][key] if ref["summary"][key] else
                 float("nan") for n in names if n != "kitti00"]  # fmt: skip
            print(f"{label:<{width}} " + " ".join(f"{x:>14.2f}" for x in r))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--styles", nargs="*", default=list(STYLES))
    ap.add_argument(
        "--seeds", type=int, nargs="*", default=[1, 2, 3],
        help="simulated drives per column (pooled: one drive's statistics vary by tens of "
        "percent from seed to seed)",
    )
    ap.add_argument("--scans", type=int, default=40, help="scans of each simulated drive (1 m)")
    ap.add_argument("--pairs", type=int, default=8, help="pairs per simulated drive")
    ap.add_argument(
        "--realism", nargs="*", default=["ideal", "realistic"],
        help="simulator realism presets to compare (graffmatch.datasets.simulator.realism)",
    )
    ap.add_argument("--json", type=Path, default=None, help="write the table and records here")
    args = ap.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)
    cols: dict[str, dict] = {}
    if (args.data / "kitti00_first6").is_dir():
        cols["kitti00"] = kitti_column(args.data, args.pairs)
    else:
        print(f"(no KITTI data at {args.data}: simulated columns only)")
    for realism in args.realism:
        for style in args.styles:
            key = style if len(args.realism) == 1 else f"{style}/{realism}"
            cols[key] = sim_column(style, args.seeds, args.scans, args.pairs, realism=realism)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"realism table (HDL-64E, default front end without labels, default GraffMatcher; "
          f"seeds {args.seeds}, load avg {load:.1f})")  # fmt: skip
    print_table(cols)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        report = {"args": {k: str(v) for k, v in vars(args).items()}, "columns": cols}
        args.json.write_text(json.dumps(report, indent=1, default=float))


if __name__ == "__main__":
    main()
