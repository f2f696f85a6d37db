"""Ablation of the putative-association gating: recall of the true associations, graph size and
match() with and without the gates, on the evaluation suites and the real KITTI scans.

    python bench/bench_gating.py [--suites-root DIR] [--json bench/results/gating.json]

Suites are read from ``<suites-root>/<name>-quick`` (built by ``graffmatch.evaluation.suites.
build_suite(name, root, quick=True)``; missing ones are built first). KITTI: every pair of the six
scans of kitti00_first6, landmarks from the default extractor, true associations from the
official poses (tau_d 6 deg). Single-threaded. Thresholds were read off the true matches of
sim-downtown and balm_courtyard (``--ratios`` prints them); the other rows are held out.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import machine, print_table, write_json

from graffmatch.association.consistency_graph import build_consistency_graph
from graffmatch.association.putative import GatingConfig, gated_associations
from graffmatch.geometry.transforms import invert, transform_errors
from graffmatch.matcher import GraffMatchConfig, GraffMatcher

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SUITES = ("sim-downtown", "balm_courtyard", "sim-suburban", "sim-openroad")
TRAIN = {"sim-downtown", "balm_courtyard"}


def suite_pairs(root: Path, name: str, max_pairs: int) -> list[tuple]:
    from graffmatch.evaluation.loop_closures import LoopClosureDataset
    from graffmatch.evaluation.suites import build_suite

    d = root / f"{name}-quick"
    if not (d / "pairs.json").is_file():
        build_suite(name, root, quick=True, progress=False)
    pairs = list(LoopClosureDataset.load(d))[:max_pairs]
    return [(p.source.without_points(), p.target.without_points(), p.T_target_source, p.true_matches)
            for p in pairs]


def kitti_pairs(data: Path) -> list[tuple]:
    from graffmatch.datasets.folder import KittiFolder
    from graffmatch.evaluation.loop_closures import ground_truth_matches
    from graffmatch.lidar import LandmarkExtractor, LandmarkExtractorConfig

    ds = KittiFolder(data / "kitti00_first6")
    ex = LandmarkExtractor(LandmarkExtractorConfig())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lms = [ex.extract(ds[i].xyz).without_points() for i in range(len(ds))]
    P = ds.poses
    out = []
    for i in range(len(ds)):
        for j in range(i + 1, len(ds)):
            T = invert(P[j]) @ P[i]
            M, _ = ground_truth_matches(lms[i], lms[j], T)
            out.append((lms[i], lms[j], T, M))
    return out


def evaluate(name: str, pairs: list[tuple], gating: GatingConfig, repeats: int) -> list[dict]:
    """Both putative sets on every pair; the two matchers' timings interleaved per pair, so a
    change of machine load hits both alike."""
    variants = {"all-to-all": GatingConfig(enabled=False), "gated": gating}
    matchers = {k: GraffMatcher(GraffMatchConfig(gating=g)) for k, g in variants.items()}
    acc = {k: {"n_true": 0, "kept": 0, "m": 0, "edges": 0, "ok": 0, "sel_true": 0, "sel": 0, "times": []}
           for k in variants}
    for src, tgt, T, M in pairs:
        truth = set(map(tuple, np.asarray(M).tolist()))
        D_s, D_t = GraffMatcher().distance_matrix(src), GraffMatcher().distance_matrix(tgt)
        for label, cfg in variants.items():
            a = acc[label]
            A = gated_associations(src, tgt, cfg)
            a["n_true"] += len(truth)
            a["kept"] += len(truth & set(map(tuple, A.tolist())))
            a["m"] += len(A)
            a["edges"] += build_consistency_graph(D_s, D_t, A, types_i=src.types, types_j=tgt.types).n_edges
            res = matchers[label].match(src, tgt)
            sel = set(map(tuple, res.associations.tolist()))
            a["sel_true"] += len(sel & truth)
            a["sel"] += len(sel)
            if res.valid and res.T_target_source is not None:
                r, t = transform_errors(res.T_target_source, T)
                a["ok"] += bool(r < 5.0 and t < 2.0)
        for _ in range(repeats):
            for label in variants:
                t0 = time.perf_counter()
                matchers[label].match(src, tgt)
                acc[label]["times"].append(time.perf_counter() - t0)
    rows = []
    for label, a in acc.items():
        n = max(len(pairs), 1)
        times = a["times"]
        rows.append({
            "data": name, "split": "train" if name in TRAIN else "test", "putative": label,
            "pairs": len(pairs), "true_assoc": a["n_true"], "true_kept": a["kept"],
            "putative_recall": round(a["kept"] / max(a["n_true"], 1), 4),
            "m_mean": round(a["m"] / n, 1), "edges_mean": round(a["edges"] / n),
            "match_ok": a["ok"], "assoc_recall": round(a["sel_true"] / max(a["n_true"], 1), 3),
            "assoc_precision": round(a["sel_true"] / max(a["sel"], 1), 3),
            "match_median_ms": round(1e3 * float(np.median(times)), 2) if times else None,
            "match_p95_ms": round(1e3 * float(np.percentile(times, 95)), 2) if times else None,
        })
    return rows


def ratios(name: str, pairs: list[tuple]) -> dict:
    """Largest disagreement of each gated attribute among the true matches (threshold choice)."""
    out: dict[str, list[float]] = {"tilt_deg": [], "radius_ratio": [], "length_ratio": [], "area_ratio": []}
    for src, tgt, _, M in pairs:
        ds, dt = src.directions, tgt.directions
        for a, b in np.asarray(M):
            ta = np.degrees(np.arccos(min(1.0, abs(ds[a, 2]))))
            tb = np.degrees(np.arccos(min(1.0, abs(dt[b, 2]))))
            out["tilt_deg"].append(abs(ta - tb))
            for key, attr, kind in (("radius_ratio", "radius", 1), ("length_ratio", "extent", 1),
                                    ("area_ratio", "extent", 2)):
                if src.types[a] == kind and attr in src.attributes and attr in tgt.attributes:
                    x, y = float(src.attributes[attr][a]), float(tgt.attributes[attr][b])
                    if np.isfinite(x) and np.isfinite(y) and min(x, y) > 0:
                        out[key].append(max(x, y) / min(x, y))
    return {"data": name, **{k: round(float(np.max(v)), 2) if v else None for k, v in out.items()},
            **{k + "_q99": round(float(np.quantile(v, 0.99)), 2) if v else None for k, v in out.items()}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--suites-root", type=Path, default=Path("/tmp/graffmatch-suites"))
    ap.add_argument("--suites", default=",".join(SUITES))
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--max-pairs", type=int, default=60)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--ratios", action="store_true", help="also print the attribute disagreements")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    gating = GatingConfig()
    sources = {}
    for name in filter(None, args.suites.split(",")):
        sources[name] = suite_pairs(args.suites_root, name, args.max_pairs)
    if (args.data / "kitti00_first6").is_dir():
        sources["kitti00_first6"] = kitti_pairs(args.data)
    rows = []
    for name, pairs in sources.items():
        rows += evaluate(name, pairs, gating, args.repeats)
    print_table(rows, ["data", "split", "putative", "pairs", "true_assoc", "true_kept", "putative_recall", "m_mean",
                       "edges_mean", "match_ok", "assoc_recall", "assoc_precision", "match_median_ms",
                       "match_p95_ms"])
    rat = [ratios(n, p) for n, p in sources.items()]
    if args.ratios:
        print_table(rat, list(rat[0]))
    write_json(args.json, {"benchmark": "gating", "machine": machine(), "gating": gating.model_dump(),
                           "rows": rows, "true_match_disagreement": rat})


if __name__ == "__main__":
    main()
