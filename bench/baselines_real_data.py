"""Every registered method on a few real pairs: the "sanity check on real data" of docs/baselines.md.

    PYTHONPATH=. .venv/bin/python bench/baselines_real_data.py [--data ../shared/data]
        [--balm-pairs 8] [--seed 0] [--methods GraffMatch ClusterMatch ...] [--json out.json]
        [--sweep] [--sweep-balm-pairs 12]

docs/baselines.md's tables come from
    bench/baselines_real_data.py --sweep --json bench/results/baselines_real_data.json

KITTI 00 pairs 0->5, 0->3, 1->5 and ``--balm-pairs`` BALM courtyard pairs drawn with ``--seed``
among the pairs 3-12 m apart and >= 10 scans apart; default front end (no labels); no
initial guess. Recall: rotation < 5 deg and translation < 1 m against the dataset's poses;
AUC: mean output inlier ratio (LMR AUC, tau_d = 6 deg) of the landmark methods. This is a smoke
test, not a benchmark: 3 + 8 pairs.

``--sweep`` also runs the parameter studies behind the defaults of docs/baselines.md on the
same KITTI pairs and ``--sweep-balm-pairs`` BALM pairs (same rule, same seed): CLIPPER-R^n and
CLIPPER-CP at epsilon 1.0 / 2.0 / 4.0 / 8.1 m (sigma = epsilon / 4) and LiPMatch with the
centroid-distance tolerance at 2.0 and 4.0 m.
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings
from pathlib import Path

import numpy as np

from graffmatch.datasets.folder import KittiFolder
from graffmatch.evaluation.methods import PairInput, get_method, list_methods
from graffmatch.evaluation.metrics import (
    association_inlier_mask,
    output_inlier_ratio,
    registration_errors,
)
from graffmatch.geometry.transforms import invert
from graffmatch.lidar.extractor import LandmarkExtractor

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def balm_pairs(poses: np.ndarray, n: int, seed: int) -> list[tuple[int, int]]:
    p = poses[:, :3, 3]
    d = np.linalg.norm(p[:, None] - p[None], axis=2)
    i, j = np.nonzero((d >= 3.0) & (d <= 12.0) & (np.arange(len(p))[None] - np.arange(len(p))[:, None] >= 10))
    pick = np.random.default_rng(seed).choice(len(i), size=min(n, len(i)), replace=False)
    return sorted((int(i[k]), int(j[k])) for k in pick)


#: The parameter studies of ``--sweep``: (row label, method, parameters).
SWEEP: tuple[tuple[str, str, dict], ...] = tuple(
    (f"{m} epsilon {eps:g}", m, {"epsilon": eps, "sigma": eps / 4})
    for m in ("CLIPPER-Rn", "CLIPPER-CP")
    for eps in (1.0, 2.0, 4.0, 8.1)
) + tuple(
    (f"LiPMatch centroid tol {tol:g}", "LiPMatch", {"max_centroid_distance_diff": tol})
    for tol in (2.0, 4.0)
)


def run(seq, pairs, methods, ex, params: dict[str, tuple[str, dict]] | None = None) -> dict:
    """Each method (or each labelled ``params`` entry: label -> (method, parameters)) on
    ``pairs`` of ``seq``; recall, LMR AUC and median time per label."""
    cache: dict[int, tuple] = {}

    def scan(k):
        if k not in cache:
            pts = seq[k].points
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                cache[k] = (pts, ex.extract(pts))
        return cache[k]

    params = params or {m: (m, {}) for m in methods}
    out = {m: {"ok": [], "oir": [], "ms": []} for m in params}
    for a, b in pairs:
        (pa, la), (pb, lb) = scan(a), scan(b)
        T_gt = invert(seq.poses[a]) @ seq.poses[b]  # source b into target a
        for m, (name, kw) in params.items():
            meth = get_method(name, **kw)
            t0 = time.perf_counter()
            res = meth.run(PairInput(source=lb, target=la, source_scan=pb, target_scan=pa))
            out[m]["ms"].append(1000 * (time.perf_counter() - t0))
            rot, tr = registration_errors(res.T_target_source, T_gt)
            out[m]["ok"].append(bool(rot < 5.0 and tr < 1.0))
            if getattr(meth, "kind", "landmark") == "landmark":
                mask = association_inlier_mask(lb, la, res.associations, T_gt)
                out[m]["oir"].append(output_inlier_ratio(mask))
    return {
        m: {
            "recall": float(np.mean(v["ok"])),
            "auc": float(np.mean(v["oir"])) if v["oir"] else None,
            "median_ms": float(np.median(v["ms"])),
            "pairs": len(v["ok"]),
        }
        for m, v in out.items()
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--balm-pairs", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--methods", nargs="*", default=None)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--sweep", action="store_true", help="also the parameter studies (SWEEP)")
    ap.add_argument("--sweep-balm-pairs", type=int, default=12)
    args = ap.parse_args()
    methods = args.methods or [m for m in list_methods() if m != "GT-matches"]
    ex = LandmarkExtractor()
    kitti = KittiFolder(args.data / "kitti00_first6")
    res = {"kitti": run(kitti, [(0, 5), (0, 3), (1, 5)], methods, ex)}
    balm = KittiFolder(args.data / "balm_courtyard")
    res["balm"] = run(balm, balm_pairs(balm.poses, args.balm_pairs, args.seed), methods, ex)
    print("| method | KITTI recall / AUC / median ms | BALM recall / AUC / median ms |")
    print("|---|---|---|")
    for m in methods:
        cells = []
        for k in ("kitti", "balm"):
            r = res[k][m]
            auc = "–" if r["auc"] is None else f"{r['auc']:.2f}"
            cells.append(f"{r['recall']:.2f} / {auc} / {r['median_ms']:,.0f}")
        print(f"| {m} | {cells[0]} | {cells[1]} |")
    if args.sweep:
        study = {label: (m, kw) for label, m, kw in SWEEP}
        pairs = balm_pairs(balm.poses, args.sweep_balm_pairs, args.seed)
        res["sweep"] = {
            "kitti": run(kitti, [(0, 5), (0, 3), (1, 5)], [], ex, study),
            "balm": run(balm, pairs, [], ex, study),
            "balm_pairs": pairs,
        }
        print("\n| setting | KITTI recall / AUC | BALM recall / AUC |")
        print("|---|---|---|")
        for label in study:
            k, b = res["sweep"]["kitti"][label], res["sweep"]["balm"][label]
            print(f"| {label} | {k['recall']:.2f} / {k['auc']:.2f} | {b['recall']:.2f} / {b['auc']:.2f} |")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                         "load_avg": load, "results": res}, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
