"""Where the verified matcher's time goes: process CPU time per stage of ``GraffMatcher.match``
(hypotheses, registration and its reference fallback, solver, scoring, ...), averaged over
real pairs, each pair matched once untimed first (numba, per-scan caches: the warm path).

Workloads:

* ``courtyard-loops``: the candidates `graffmatch loops` verifies on balm_courtyard (top-5
  retrieval, quick check, every ``--stride``-th query; the maps without support points, so
  landmark-level evidence), from a loop run's landmark tables (``--runs``, as
  ``bench/bench_loops_speed.py``);
* ``kitti``: KITTI 00 scans 0-5 (support points as evidence), pairs 5->0, 3->1, 4->2, 2->0,
  5->3, 1->0.

Stages are timed by wrapping the module functions (nested stages are included in their
callers; the wrappers cost ~1 us a call). Untimed-niced is fine for the shares; absolute CPU
times still grow with the machine's load (shared caches and cores).

    python bench/verification_stages.py --runs /tmp/loops6/ours2 --json bench/results/verification_stages.json
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json

COURTYARD = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "balm_courtyard"

STAGES = {
    "graffmatch.verification.verify": ["candidate_cliques", "_pair_candidates", "_register", "rival_cliques",
                                       "consistent_with", "merge_hypotheses", "_gated", "score_hypotheses",
                                       "decide", "_refine", "_check_translation", "_check_free_space",
                                       "_local_search", "align_on_evidence", "evidence_for"],
    "graffmatch.registration.closed_form": ["_solve_by_reference", "_register_kernel"],
    "graffmatch.matcher": ["build_consistency_graph", "solve_clipper", "putative_associations", "_verified_result"],
}


def instrument() -> tuple[dict, collections.Counter]:
    """Wrap the stage functions in their modules; returns the accumulators (seconds, calls)."""
    import importlib

    acc: dict[str, float] = collections.defaultdict(float)
    cnt: collections.Counter = collections.Counter()
    for mod_name, names in STAGES.items():
        mod = importlib.import_module(mod_name)
        for name in names:
            f = getattr(mod, name)

            def wrapped(*a, _f=f, _n=name, **k):
                t0 = time.process_time()
                try:
                    return _f(*a, **k)
                finally:
                    acc[_n] += time.process_time() - t0
                    cnt[_n] += 1

            setattr(mod, name, wrapped)
    import graffmatch.registration.closed_form as cf
    import graffmatch.verification.verify as vv

    vv.register_batch = cf.register_batch  # verify's own reference, so the kernel wrappers see its calls
    return acc, cnt


def courtyard_pairs(runs: Path, stride: int) -> tuple[list, dict]:
    from graffmatch.datasets.registry import open_dataset
    from graffmatch.evaluation.sequence_benchmark import benchmark_config
    from graffmatch.loops.database import LandmarkDatabase, load_landmarks
    from graffmatch.loops.descriptor import landmark_descriptor
    from graffmatch.loops.detector import LoopDetector
    from graffmatch.loops.quickcheck import quick_index
    from graffmatch.loops.retrieval import eligible_count

    files = sorted((runs / "balm_courtyard" / "ours" / "landmarks").glob("[0-9]" * 6 + ".npz"))
    if not files:
        raise SystemExit(f"{runs}: no balm_courtyard landmark tables (bench/bench_loops.py --prepare)")
    cfg = benchmark_config()
    cfg.retrieval.top_k = 5
    db = LandmarkDatabase()
    stamps = np.asarray(open_dataset("folder", COURTYARD).timestamps, float)
    for i, f in enumerate(files):
        ls = load_landmarks(f)
        db.add(ls, landmark_descriptor(ls, cfg.descriptor), float(stamps[i]))
    db.extra["quick"] = [quick_index(ls, cfg.quick) for ls in db.landmarks]
    det = LoopDetector(cfg)
    det.db = db
    pairs = []
    for q in range(0, len(db), stride):
        if eligible_count(db.timestamps, q, cfg.retrieval) > 0:
            det.detect(q)
            pairs += [(q, r["match"]) for r in det.last_records if r["verified"]]
    return pairs, {i: ls for i, ls in enumerate(db.landmarks)}


def kitti_pairs() -> tuple[list, dict]:
    from graffmatch.datasets.folder import KittiFolder
    from graffmatch.lidar.extractor import LandmarkExtractor

    ds = KittiFolder(COURTYARD.parent / "kitti00_first6")
    ex = LandmarkExtractor()
    return [(5, 0), (3, 1), (4, 2), (2, 0), (5, 3), (1, 0)], {i: ex.extract(ds[i].points) for i in range(6)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=Path, default=Path("/tmp/loops6/ours2"))
    ap.add_argument("--stride", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--workloads", nargs="+", default=["courtyard-loops", "kitti"])
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    from graffmatch.matcher import GraffMatcher

    acc, cnt = instrument()
    rows = []
    for wl in a.workloads:
        pairs, sets = courtyard_pairs(a.runs, a.stride) if wl == "courtyard-loops" else kitti_pairs()
        m = GraffMatcher()
        for q, c in pairs:
            m.match(sets[q], sets[c])
        acc.clear()
        cnt.clear()
        load0 = os.getloadavg()[0]
        t0 = time.process_time()
        for _ in range(a.repeat):
            for q, c in pairs:
                m.match(sets[q], sets[c])
        n = a.repeat * len(pairs)
        total = (time.process_time() - t0) / n
        stages = {k: {"cpu_ms": 1e3 * v / n, "calls": cnt[k] / n} for k, v in sorted(acc.items(), key=lambda kv: -kv[1])}
        print(f"{wl}: {len(pairs)} pairs x {a.repeat}, CPU {1e3 * total:.2f} ms a match (load {load0:.1f})")
        for k, v in stages.items():
            print(f"  {k:<26}{v['cpu_ms']:8.3f} ms  ({v['calls']:.1f} calls)")
        rows.append({"workload": wl, "pairs": len(pairs), "repeat": a.repeat, "cpu_ms_per_match": 1e3 * total,
                     "stages": stages, "load_before": load0, "load_after": os.getloadavg()[0]})
    write_json(a.json, {"machine": machine(), "rows": rows})


if __name__ == "__main__":
    main()
