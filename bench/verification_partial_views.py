"""Precision of ``valid`` on partial views: real courtyard scan pairs 3-16 m apart (bundle-adjusted
poses), the source scan cropped to a random sector and turned by a random yaw, registered by
``ScanMatcher`` with each evidence setting (support points only; support points, then the raw
scans). A valid result is right when it is within 5 deg and 1 m of the ground truth.

Why: ``bench/verification.py`` matches whole scans. A user's scans are partial (occlusion, a
sensor's field of view, a cropped map), and the raw-scan fallback (session 14) was chosen on
whole scans. This is a stress check, not a calibration: nothing is tuned on it.

    python bench/verification_partial_views.py --pairs 300 --seed 13 --json bench/results/partial_views.json
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np

from graffmatch.errors import GraffMatchError
from graffmatch.geometry.transforms import invert, transform_errors
from graffmatch.lidar.io import read_scan
from graffmatch.pipeline import ScanMatcher, ScanMatcherConfig

ROOT = Path(__file__).resolve().parents[2] / "shared" / "data" / "balm_courtyard"


def yaw(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def crop(X: np.ndarray, rng: np.random.Generator, lo: float, hi: float) -> np.ndarray:
    """The points of X within a random azimuth sector of width in [lo, hi] radians."""
    a0, w = rng.uniform(-np.pi, np.pi), rng.uniform(lo, hi)
    return X[(np.arctan2(X[:, 1], X[:, 0]) - a0) % (2 * np.pi) < w]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=ROOT)
    ap.add_argument("--pairs", type=int, default=300)
    ap.add_argument("--seed", type=int, default=13)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    P = np.loadtxt(a.data / "poses.txt").reshape(-1, 3, 4)
    P = np.concatenate([P, np.tile([[[0.0, 0.0, 0.0, 1.0]]], (len(P), 1, 1))], 1)
    scans = {i: read_scan(a.data / "velodyne" / f"{i:06d}.bin").points[:, :3] for i in range(len(P))}
    matchers = {e: ScanMatcher(ScanMatcherConfig(evidence=e)) for e in ("support", "support_then_scans")}
    views = {"whole scan": (2 * np.pi, 2 * np.pi), "sector 180-270 deg": (np.pi, 1.5 * np.pi),
             "sector 90-180 deg": (0.5 * np.pi, np.pi)}
    report: dict = {"pairs": a.pairs, "seed": a.seed, "rows": []}
    t0 = time.perf_counter()
    for view, (lo, hi) in views.items():
        rng = np.random.default_rng(a.seed)
        stats = {e: {"valid": 0, "wrong": 0, "errors": 0} for e in matchers}
        for _ in range(a.pairs):
            i = int(rng.integers(0, len(P)))
            near = [j for j in range(len(P)) if 3.0 < np.linalg.norm(P[i][:3, 3] - P[j][:3, 3]) < 16.0]
            j = int(rng.choice(near))
            Y = yaw(rng.uniform(-np.pi, np.pi))
            A = crop(scans[i], rng, lo, hi) @ Y[:3, :3].T if lo < 2 * np.pi else scans[i] @ Y[:3, :3].T
            T_true = invert(P[j]) @ P[i] @ invert(Y)
            for e, m in matchers.items():
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        r = m.register(A, scans[j])
                except GraffMatchError:
                    stats[e]["errors"] += 1
                    continue
                if r.valid:
                    rot, tr = transform_errors(r.T_target_source, T_true)
                    stats[e]["valid"] += 1
                    if rot > 5.0 or tr > 1.0:
                        stats[e]["wrong"] += 1
                        report["rows"].append({"view": view, "evidence": e, "source": i, "target": j,
                                               "rot_deg": rot, "trans_m": tr, "confidence": r.confidence,
                                               "overlap": r.overlap, "margin": r.margin,
                                               "evidence_source": r.result.info.get("evidence_source", "support")})
        report[view] = stats
        for e, s in stats.items():
            prec = (s["valid"] - s["wrong"]) / s["valid"] if s["valid"] else float("nan")
            print(f"{view:<20} {e:<20} pairs {a.pairs}  valid {s['valid']:>4}  wrong {s['wrong']:>3}  "
                  f"precision {prec:.3f}  recall {(s['valid'] - s['wrong']) / a.pairs:.3f}  errors {s['errors']}",
                  flush=True)
    report["seconds"] = time.perf_counter() - t0
    if a.json:
        a.json.write_text(json.dumps(report, indent=1, default=float))
        print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
