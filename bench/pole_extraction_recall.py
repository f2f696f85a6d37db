"""Pole extraction recall and precision against the simulator's ground-truth poles.

The simulator writes every pole-like object (street lights, sign posts, trunks) of its world
(``landmarks_gt.npz``) and an instance id per point (``labels/``, ``instance << 16``). On the
de-skewed drives of ``bench/verification.py`` (same odometry), each scan's *visible* true poles
are the instances with at least ``--min-hits`` points inside the extractor's range crop; an
extracted pole is *right* when it lies within ``--match-radius`` (horizontally) of a true pole's
axis. Recall (right extracted / visible) and precision (right / extracted) per range band, and,
for every missed visible pole, the first stage of the geometric detector that loses it:

* ``band``       fewer than min_support points in the height band above the local ground;
* ``merged``     none of its band points is in a pole candidate (every layer of it runs into an
  occupancy-grid component wider than max_footprint_cells: a crown, a hedge, a car, a wall;
  or its cells are too sparse, or its thin part starts too high);
* ``support`` / ``linearity`` / ``tilt`` / ``length`` / ``radius``: the acceptance test that
  the candidate holding most of its points fails;
* ``offset``     that candidate is accepted but lies further than --match-radius from it.

    python bench/pole_extraction_recall.py --out /tmp/gm-verify --suite sim-suburban \
        --json bench/results/pole_extraction_recall.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from graffmatch.datasets.deskewed import Deskewed
from graffmatch.evaluation.suites import SIM_EXTRACTORS, SUITES
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.geometry.transforms import invert
from graffmatch.lidar._stats import axis_spans, cluster_stats
from graffmatch.lidar.extractor import LandmarkExtractor, LandmarkExtractorConfig
from graffmatch.lidar.ground import segment_ground
from graffmatch.lidar.poles import PoleConfig, pole_candidates
from graffmatch.loops.posegraph import OdometryDriftConfig, drifted_odometry

BANDS = [(0.0, 10.0), (10.0, 20.0), (20.0, 30.0), (30.0, 45.0), (45.0, 80.0)]
DRIVES = ("sim-downtown", "sim-suburban", "sim-openroad")  # the odometry seed is the index


def first_failure(P: np.ndarray, height: np.ndarray, is_ground: np.ndarray, on_pole: np.ndarray,
                  cfg: PoleConfig) -> str:
    """The first stage of :func:`graffmatch.lidar.poles.poles_geometric` that loses the true pole
    whose surface points are ``on_pole`` (bool per point)."""
    band = ~is_ground & (height >= cfg.min_height) & (height <= cfg.max_height)
    if np.sum(on_pole & band) < cfg.min_support:
        return "band"
    idx, lab, _ = pole_candidates(P, height, is_ground, cfg)
    mine = on_pole[idx]
    if mine.sum() == 0:
        return "merged"  # no thin stack holds its points: every layer runs into something wide
    c = np.bincount(lab[mine]).argmax()
    pts = P[idx[lab == c]]
    one = np.zeros(len(pts), np.int64)
    st = cluster_stats(pts, one, 1)
    axes = st.major_axis().copy()
    axes[axes[:, 2] < 0] *= -1
    lo, hi, radius = axis_spans(pts, one, 1, axes, st.centroids)
    tilt = np.degrees(np.arccos(np.clip(abs(axes[0, 2]), 0, 1)))
    for name, bad in (("support", st.counts[0] < cfg.min_support),
                      ("linearity", st.linearity()[0] < cfg.min_linearity),
                      ("tilt", tilt > cfg.max_tilt_deg),
                      ("length", not (cfg.min_length <= hi[0] - lo[0] <= cfg.max_length)),
                      ("radius", radius[0] > cfg.max_radius)):
        if bad:
            return name
    return "offset"  # accepted, but its axis lies further than --match-radius from the true one


def run_drive(name: str, seed: int, out: Path, scans: range | list, cfg: LandmarkExtractorConfig,
              min_hits: int, match_radius: float, reasons: bool) -> dict:
    ds = SUITES[name].make_dataset(out / f"suite-{name}", False, None)
    drive = Deskewed(ds, drifted_odometry(ds.poses, OdometryDriftConfig(seed=seed)))
    root = Path(ds.scan_path(0)).parent.parent
    gt = LandmarkSet.load(root / "landmarks_gt.npz")
    line = np.flatnonzero(gt.types == LandmarkType.LINE)
    g_inst = gt.attributes["instance"][line].astype(np.int64)
    g_cat = gt.attributes["category"][line].astype(np.int64)
    g_anchor_w, g_dir_w = gt.anchors[line], gt.bases[line][:, :, 0]
    vis_file = np.load(root / "landmarks_visible.npz")
    v_scan, v_lm, v_cnt = vis_file["scan"], vis_file["landmark"], vis_file["count"]
    g_index = np.full(len(gt), -1, np.int64)  # GT landmark id -> row of ``line``
    g_index[line] = np.arange(len(line))
    keep_v = g_index[v_lm] >= 0
    v_scan, v_lm, v_cnt = v_scan[keep_v], v_lm[keep_v], v_cnt[keep_v]
    ex = LandmarkExtractor(cfg)
    rec: list[dict] = []
    ext: list[dict] = []
    for i in scans:
        scan = drive[i]
        T_lw = invert(ds.poses[i])
        a = g_anchor_w @ T_lw[:3, :3].T + T_lw[:3, 3]
        d = g_dir_w @ T_lw[:3, :3].T
        pts = np.asarray(scan.points[:, :3], np.float64)
        inst_all = (np.asarray(scan.labels, np.uint32) >> np.uint32(16)).astype(np.int64)
        r = np.linalg.norm(pts, axis=1)
        keep = (r >= cfg.min_range) & (r <= (cfg.max_range or np.inf))
        P, inst = pts[keep], inst_all[keep]
        cls = (np.asarray(scan.labels, np.uint32)[keep] & np.uint32(0xFFFF)).astype(np.int64)
        L = ex.extract(scan.points, None)
        poles = np.flatnonzero(L.types == LandmarkType.LINE)
        E = L.anchors[poles]
        # horizontal distance from each extracted pole to each true pole's axis (at its height)
        t = np.einsum("pgk,gk->pg", E[:, None, :] - a[None], d)
        foot = a[None] + t[..., None] * d[None]
        dh = np.linalg.norm((E[:, None, :] - foot)[..., :2], axis=2) if len(E) else np.zeros((0, len(a)))
        hits = np.zeros(len(line), np.int64)
        sel = v_scan == i
        hits[g_index[v_lm[sel]]] = v_cnt[sel]
        hits[np.hypot(a[:, 0], a[:, 1]) > (cfg.max_range or np.inf)] = 0
        vis = np.flatnonzero(hits >= min_hits)
        found = np.zeros(len(a), bool)
        if len(E):
            near = dh <= match_radius
            found = near.any(axis=0)
            tree = cKDTree(P)
            for p in range(len(E)):
                gi = int(np.argmin(dh[p])) if dh.shape[1] else -1
                ok = bool(near[p].any())
                around = tree.query_ball_point(E[p], 0.5)
                what = int(np.bincount(cls[around]).argmax()) if len(around) else -1
                ext.append(dict(scan=i, range=float(np.hypot(*E[p, :2])), right=ok,
                                category=int(g_cat[gi]) if ok else -1, semantic_class=what))
        ground = None
        for g in vis:
            row = dict(scan=i, gt=int(line[g]), category=int(g_cat[g]), hits=int(hits[g]),
                       range=float(np.hypot(*a[g, :2])), found=bool(found[g]),
                       radius=float(gt.attributes["radius"][line[g]]), extent=float(gt.attributes["extent"][line[g]]))
            if reasons and not found[g]:
                if ground is None:
                    ground = segment_ground(P, cfg.ground)
                # the trunk's own surface: its instance, within its radius of the axis (not the crown)
                q = P - a[g]
                radial = np.linalg.norm(q - np.outer(q @ d[g], d[g]), axis=1)
                on_pole = (inst == g_inst[g]) & (radial <= row["radius"] + 0.1)
                row["reason"] = first_failure(P, ground.height, ground.is_ground, on_pole, cfg.poles)
            rec.append(row)
    return summarise(rec, ext)


def summarise(rec: list[dict], ext: list[dict]) -> dict:
    out: dict = {"scans": len({r["scan"] for r in rec} | {e["scan"] for e in ext}), "bands": {}}
    n_scans = max(out["scans"], 1)
    for lo, hi in [*BANDS, (0.0, 80.0)]:
        rv = [r for r in rec if lo <= r["range"] < hi]
        ev = [e for e in ext if lo <= e["range"] < hi]
        why: dict[str, int] = {}
        for r in rv:
            if not r["found"] and "reason" in r:
                why[r["reason"]] = why.get(r["reason"], 0) + 1
        out["bands"][f"{lo:g}-{hi:g}"] = {
            "visible": len(rv), "found": sum(r["found"] for r in rv),
            "recall": sum(r["found"] for r in rv) / len(rv) if rv else float("nan"),
            "extracted": len(ev), "right": sum(e["right"] for e in ev),
            "precision": sum(e["right"] for e in ev) / len(ev) if ev else float("nan"),
            "visible_per_scan": len(rv) / n_scans, "found_per_scan": sum(r["found"] for r in rv) / n_scans,
            "missed_by_stage": dict(sorted(why.items(), key=lambda kv: -kv[1])),
        }
    wrong: dict[str, int] = {}
    for e in ext:
        if not e["right"]:
            wrong[str(e["semantic_class"])] = wrong.get(str(e["semantic_class"]), 0) + 1
    out["wrong_by_semantic_class"] = dict(sorted(wrong.items(), key=lambda kv: -kv[1]))
    cats: dict[str, dict] = {}
    for c in sorted({r["category"] for r in rec}):
        rv = [r for r in rec if r["category"] == c]
        cats[str(c)] = {"visible": len(rv), "recall": sum(r["found"] for r in rv) / len(rv)}
    out["by_category"] = cats  # 10 street light, 11 sign post, 12 trunk
    per_scan = {}
    for r in rec:
        per_scan.setdefault(r["scan"], [0, 0])
        per_scan[r["scan"]][0] += 1
        per_scan[r["scan"]][1] += r["found"]
    v = np.array(list(per_scan.values())) if per_scan else np.zeros((0, 2))
    out["median_visible_per_scan"] = float(np.median(v[:, 0])) if len(v) else float("nan")
    out["median_found_per_scan"] = float(np.median(v[:, 1])) if len(v) else float("nan")
    out["rows"] = rec
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="/tmp/gm-verify", help="bench/verification.py's --out (simulated drives)")
    ap.add_argument("--suite", action="append", default=None)
    ap.add_argument("--half", choices=("cal", "test", "all"), default="test")
    ap.add_argument("--stride", type=int, default=3, help="every k-th scan")
    ap.add_argument("--min-hits", type=int, default=15, help="points on a true pole that make it visible")
    ap.add_argument("--match-radius", type=float, default=0.5, help="[m], horizontal")
    ap.add_argument("--no-reasons", action="store_true")
    ap.add_argument("--poles", default=None, help="JSON overrides of the pole config, e.g. '{\"max_footprint_cells\": 20}'")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    report: dict = {"args": vars(a), "drives": {}}
    for name in a.suite or ["sim-suburban"]:
        over = dict(SIM_EXTRACTORS.get(name, {}))
        if a.poles:
            over["poles"] = {**over.get("poles", {}), **json.loads(a.poles)}
        cfg = LandmarkExtractorConfig.model_validate(over)
        n = len(SUITES[name].make_dataset(Path(a.out) / f"suite-{name}", False, None))
        lo, hi = {"cal": (0, n // 2), "test": (n // 2, n), "all": (0, n)}[a.half]
        t0 = time.perf_counter()
        res = run_drive(name, DRIVES.index(name), Path(a.out), range(lo, hi, a.stride), cfg, a.min_hits,
                        a.match_radius, not a.no_reasons)
        report["drives"][name] = res
        print(f"{name} ({a.half}, every {a.stride}th scan, {res['scans']} scans, {time.perf_counter() - t0:.0f} s): "
              f"median visible true poles per scan {res['median_visible_per_scan']:.1f}, found "
              f"{res['median_found_per_scan']:.1f}; by category {res['by_category']}; wrong extracted poles by "
              f"(noisy) semantic class {res['wrong_by_semantic_class']}")
        print(f"{'range [m]':<10}{'visible':>8}{'/scan':>7}{'found':>7}{'recall':>8}{'extr':>6}{'prec':>7}  missed by stage")
        for band, b in res["bands"].items():
            print(f"{band:<10}{b['visible']:>8}{b['visible_per_scan']:>7.2f}{b['found']:>7}{b['recall']:>8.3f}"
                  f"{b['extracted']:>6}{b['precision']:>7.3f}  {b['missed_by_stage']}")
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        slim = {k: {kk: vv for kk, vv in v.items() if kk != "rows"} for k, v in report["drives"].items()}
        Path(a.json).write_text(json.dumps({"args": report["args"], "drives": slim}, indent=1, default=float))


if __name__ == "__main__":
    main()
