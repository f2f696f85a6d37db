"""Two raw scans to a verified, ICP-refined pose, against KISS-Matcher in the same run (issue 14).

    OMP_NUM_THREADS=1 flock /tmp/bench.lock python bench/bench_end_to_end.py \
        [--pairs 1-0 3-0 5-0 5-2] [--repeats 5] [--kiss-repeats 2] [--no-kiss] [--json out.json]

Per KITTI 00 pair (source b -> target a, no initial guess): ``ScanMatcher.register`` with ICP
refinement (extract x2 + verified match + ICP, the path of ``graffmatch register --refine icp``)
and KISS-Matcher (the ``graffmatch.evaluation.baselines`` wrapper) on the same raw scans.
Reports wall and process-CPU medians / p95 per pair and over all runs, the stage medians
(extraction for both scans, match, ICP), peak RSS, and the errors against the official poses and
against an ICP-refined ground truth (point-to-plane ICP of the full scans at 0.2 m voxels started
at the official pose; the official KITTI poses are off by decimetres here, see
../shared/data/README.md).

``--legacy`` also times the previous configuration in the same run: Open3D's patch detector
and ICP on re-voxelised raw scans with the former criteria (30 iterations, 1e-6).
The script runs against older checkouts too (PYTHONPATH=<old tree>): settings an older
``RefinementConfig`` does not have are left out.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy / Open3D: one thread for ours
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import machine, peak_rss_mb, print_table, write_json
from frontend_real_data import icp_refine

from graffmatch.datasets.folder import KittiFolder
from graffmatch.geometry.transforms import invert, transform_errors
from graffmatch.pipeline import RefinementConfig, ScanMatcher, ScanMatcherConfig

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def scan_matcher(legacy: bool, evidence: str | None = None) -> ScanMatcher:
    """Default ScanMatcher with ICP; ``legacy``: the pre-issue-14 detector and ICP settings;
    ``evidence``: what verification scores on ('support' or 'scans'; None: the default)."""
    fields = RefinementConfig.model_fields
    ref = {"method": "icp"}
    ext = None
    if legacy:
        ref.update(max_iterations=30)
        for k, v in (("reuse_extractor_cloud", False), ("relative_change", 1e-6)):
            if k in fields:
                ref[k] = v
        ext = {"planes": {"detector": "open3d"}}
    cfg = ScanMatcherConfig.model_validate({"refinement": ref, **({"extractor": ext} if ext else {}),
                                            **({"evidence": evidence} if evidence else {})})
    return ScanMatcher(cfg)


def run_ours(sm: ScanMatcher, src: np.ndarray, tgt: np.ndarray) -> dict:
    w, c = time.perf_counter(), time.process_time()
    reg = sm.register(src, tgt)
    wall, cpu = time.perf_counter() - w, time.process_time() - c
    t = reg.result.timings
    match = sum(v for k, v in t.items() if k not in ("extraction", "icp", "total"))
    return {"wall": wall, "cpu": cpu, "T": reg.T_target_source, "valid": bool(reg.valid),
            "extraction": t.get("extraction", np.nan), "match": match, "icp": t.get("icp", np.nan)}


def time_scan_pass(scans: dict, pairs: list, reps: int) -> dict:
    """Per pair: median wall / CPU ms of match() on the support points and of the raw-scan pass
    (``verify.scan_evidence`` from the extractor's clouds + match() on it), interleaved."""
    from graffmatch.verification.verify import scan_evidence

    sm = scan_matcher(False)
    out = {}
    for b, t in pairs:
        src = sm.extract(scans[b])
        cs = sm.extractor.last_cloud
        tgt = sm.extract(scans[t])
        ct = sm.extractor.last_cloud
        vcfg = sm.config.matcher.verification
        ts: dict[str, list] = {"support_wall": [], "support_cpu": [], "scans_wall": [], "scans_cpu": []}
        for k in range(reps + 1):
            w, c = time.perf_counter(), time.process_time()
            sm.match(src, tgt)
            w1, c1 = time.perf_counter(), time.process_time()
            r = sm.match(src, tgt, scan_evidence(src, tgt, cs.points, ct.points, vcfg))
            w2, c2 = time.perf_counter(), time.process_time()
            if k:  # the first round warms up
                ts["support_wall"].append(w1 - w)
                ts["support_cpu"].append(c1 - c)
                ts["scans_wall"].append(w2 - w1)
                ts["scans_cpu"].append(c2 - c1)
        out[f"{b}->{t}"] = {**{k: round(float(np.median(v)) * 1e3, 1) for k, v in ts.items()},
                            "scans_valid": bool(r.valid), "scans_evidence": r.info.get("evidence_source")}
    return out


def run_kiss(src: np.ndarray, tgt: np.ndarray) -> dict:
    from graffmatch.evaluation.baselines.kiss_matcher import KissMatcher
    from graffmatch.evaluation.methods import PairInput

    w, c = time.perf_counter(), time.process_time()
    out = KissMatcher().run(PairInput(source=None, target=None, source_scan=src, target_scan=tgt))
    return {"wall": time.perf_counter() - w, "cpu": time.process_time() - c,
            "T": out.T_target_source, "valid": bool(out.valid)}


def summary(name: str, runs: list[dict], truth: dict, rss: float) -> dict:
    wall = np.array([r["wall"] for r in runs]) * 1e3
    cpu = np.array([r["cpu"] for r in runs]) * 1e3
    row = {"method": name, "runs": len(runs),
           "wall_med_ms": round(float(np.median(wall)), 1), "wall_p95_ms": round(float(np.percentile(wall, 95)), 1),
           "cpu_med_ms": round(float(np.median(cpu)), 1), "cpu_p95_ms": round(float(np.percentile(cpu, 95)), 1)}
    for k in ("extraction", "match", "icp"):
        if k in runs[0]:
            row[f"{k}_med_ms"] = round(float(np.median([r[k] for r in runs])) * 1e3, 1)
    errs = []
    for pair, T_gt, T_icp in truth.values():
        last = [r for r in runs if r["pair"] == pair][-1]
        if last["T"] is None:
            errs.append((np.inf, np.inf, np.inf, np.inf, last["valid"]))
            continue
        r0, t0 = transform_errors(last["T"], T_gt)
        r1, t1 = transform_errors(last["T"], T_icp)
        errs.append((r0, t0, r1, t1, last["valid"]))
    e = np.array([x[:4] for x in errs])
    row.update({"valid": f"{sum(x[4] for x in errs)}/{len(errs)}",
                "rot_vs_icp_gt_med_deg": round(float(np.median(e[:, 2])), 3),
                "trans_vs_icp_gt_med_m": round(float(np.median(e[:, 3])), 3),
                "rot_vs_icp_gt_max_deg": round(float(np.max(e[:, 2])), 3),
                "trans_vs_icp_gt_max_m": round(float(np.max(e[:, 3])), 3),
                "rot_vs_official_med_deg": round(float(np.median(e[:, 0])), 3),
                "trans_vs_official_med_m": round(float(np.median(e[:, 1])), 3),
                "peak_rss_mb": round(rss, 1)})
    row["per_pair"] = {p: {"rot_vs_icp_gt_deg": float(x[2]), "trans_vs_icp_gt_m": float(x[3]),
                           "valid": bool(x[4]),
                           "wall_med_ms": float(np.median([r["wall"] for r in runs if r["pair"] == p]) * 1e3)}
                       for p, x in zip(truth, errs, strict=True)}
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--pairs", nargs="+", default=["1-0", "3-0", "5-0", "5-2"], help="source-target frames")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per pair (after one warm-up)")
    ap.add_argument("--kiss-repeats", type=int, default=2)
    ap.add_argument("--no-kiss", action="store_true")
    ap.add_argument("--legacy", action="store_true", help="also time the pre-issue-14 settings")
    ap.add_argument("--evidence", nargs="+", default=None, choices=("support", "support_then_scans"),
                    help="time these evidences of ScanMatcherConfig.evidence in the same run (session 14); "
                         "default: the configured one only")
    ap.add_argument("--scan-pass", action="store_true",
                    help="also time, per pair, the raw-scan verification pass alone (scan evidence + match(), "
                         "what support_then_scans adds after an invalid support pass) against match() on the "
                         "support points, in-process, wall and CPU")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    folder = a.data / "kitti00_first6"
    if not folder.is_dir():
        raise SystemExit(f"no KITTI scans under {folder}")
    seq = KittiFolder(folder)
    pairs = [tuple(int(x) for x in p.split("-")) for p in a.pairs]
    scans = {i: seq[i].points for p in pairs for i in p}
    truth = {}
    for b, t in pairs:  # source b into target t
        T_gt = invert(seq.poses[t]) @ seq.poses[b]
        T_icp, _ = icp_refine(folder, t, b, T_gt)
        truth[f"{b}->{t}"] = (f"{b}->{t}", T_gt, T_icp)
    load0 = os.getloadavg()[0]
    methods = {"GraffMatch (ScanMatcher + ICP)": (scan_matcher(False), a.repeats)}
    if a.evidence:
        methods = {f"GraffMatch (ScanMatcher + ICP), {e} evidence": (scan_matcher(False, e), a.repeats)
                   for e in a.evidence}
    if a.legacy:
        methods["GraffMatch, pre-issue-14 settings"] = (scan_matcher(True), a.repeats)
    rows = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name, (sm, reps) in methods.items():
            runs = []
            for b, t in pairs:
                run_ours(sm, scans[b], scans[t])  # warm-up (numba, caches)
                for _ in range(reps):
                    runs.append({**run_ours(sm, scans[b], scans[t]), "pair": f"{b}->{t}"})
            rows.append(summary(name, runs, truth, peak_rss_mb()))
        if not a.no_kiss:
            runs = []
            for b, t in pairs:
                for _ in range(a.kiss_repeats):
                    runs.append({**run_kiss(scans[b], scans[t]), "pair": f"{b}->{t}"})
            rows.append(summary("KISS-Matcher", runs, truth, peak_rss_mb()))
    scan_pass = time_scan_pass(scans, pairs, a.repeats) if a.scan_pass else None
    load1 = os.getloadavg()[0]
    print(f"KITTI 00 pairs {', '.join(truth)}; load average {load0:.2f} -> {load1:.2f}; "
          f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')}")
    cols = ["method", "runs", "wall_med_ms", "wall_p95_ms", "cpu_med_ms", "extraction_med_ms", "match_med_ms",
            "icp_med_ms", "valid", "rot_vs_icp_gt_med_deg", "trans_vs_icp_gt_med_m", "rot_vs_icp_gt_max_deg",
            "trans_vs_icp_gt_max_m", "rot_vs_official_med_deg", "trans_vs_official_med_m", "peak_rss_mb"]
    print_table(rows, cols)
    print("peak RSS is the whole process so far (KISS-Matcher runs last: its value includes ours)")
    if scan_pass:
        print("raw-scan verification pass vs support-point match() per pair (median ms, wall / CPU):")
        for k, v in scan_pass.items():
            print(f"  {k}: {v}")
    write_json(a.json, {"benchmark": "end_to_end", "machine": machine(), "load_before": load0, "load_after": load1,
                        "pairs": list(truth), "target_ms": 100, "rows": rows, "scan_pass": scan_pass})


if __name__ == "__main__":
    main()
