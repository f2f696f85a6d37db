"""Two candidate evidences for the decision of the verified matcher, evaluated offline on the rows
of ``bench/verification.py`` (each pair's matched transform, both passes), with thresholds chosen
on the calibration split as that script chooses them (session 10, issue 11: sim-downtown recall).

* **Moved-object discount of the free-space conflict** (``--movable L,W,H``): the largest cluster
  of conflicting points (single linkage 1 m) is not counted when it holds at least half of them
  and fits in an L x W x H box (principal horizontal axes, height along z): one car that moved
  between the scans is no evidence against a right match. Reported: the thresholds chosen on
  the calibration split with this conflict, both splits per suite, the raw drives' test pairs,
  the support points' image; and a calibration-only **stress test**: the ground truth of every
  calibration positive turned 90 / 180 / 270 deg about the target sensor or slid 3 / 6 m,
  counting the wrong transforms whose conflict the discount brings from above 0.10 to below.
* **Co-visible overlap**: each scan's points explained (within 0.3 m) over the points the other
  scan could see (their cell holds a return no nearer than the point minus the free-space
  margin), as a second way past ``min_overlap``: valid also when overlap >= ``mo2`` and
  co-visible overlap >= ``mcv`` (grid on the calibration split only).
* **Diagnosis** of the calibration sim-downtown pairs rejected by the free-space check at the
  ground truth: the largest conflicting cluster and the simulator's labels of the raw scan
  points there.
* **Sets without the whole-scan image** (the support points' image): its neighbourhood
  (``free_space_neighbours`` 0-3, each with ``max_conflict_support_points`` chosen on the
  calibration split) and an image of the ground returns alone.
* **Raw (not de-skewed) sim-downtown, calibration pairs** (``--raw-cal``, matched here as
  ``bench/verification.py`` matches the test pairs): the valid answers' translation errors, and
  whether the disagreement of the source's two halves (split by the sign of x, then of y),
  each aligned on the target from the answer, separates the wrong valid answers.

    python bench/evidence_variants.py --rows bench/results/verification.json --out /tmp/gm-verify \\
        --movable 6,3,2.5 --raw-cal --json bench/results/evidence_variants_session10.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from verification import (
    answered,
    choose_support_conflict,
    choose_thresholds,
    decide,
    free_space_conflicts,
    load_sources,
    make_pairs,
    metrics,
    outcome,
    run_both,
)

from graffmatch.geometry.transforms import invert
from graffmatch.verification.config import VerificationConfig
from graffmatch.verification.evidence import support_cloud, voxel_downsample
from graffmatch.verification.free_space import RangeImage, _cells, conflict_fraction

SUITES = ("courtyard", "kitti", "sim-downtown", "sim-suburban", "sim-openroad", "cross",
          "sim-downtown raw", "sim-suburban raw", "sim-openroad raw")


def moved_object(Q: np.ndarray, movable: tuple[float, float, float], link: float = 1.0,
                 min_share: float = 0.5) -> int:
    """Points of the largest single-linkage cluster of ``Q`` when it holds >= ``min_share`` of
    them and fits in ``movable`` (length, width, height), else 0."""
    if len(Q) == 0:
        return 0
    pairs = cKDTree(Q).query_pairs(link, output_type="ndarray")
    A = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(Q), len(Q)))
    _, lab = connected_components(A, directed=False)
    big = np.bincount(lab).argmax()
    M = Q[lab == big]
    if len(M) < min_share * len(Q) or np.ptp(M[:, 2]) > movable[2]:
        return 0
    xy = M[:, :2] - M[:, :2].mean(axis=0)
    span = np.ptp(xy @ np.linalg.eigh(xy.T @ xy)[1], axis=0) if len(M) > 1 else np.zeros(2)
    return len(M) if span[1] <= movable[0] and span[0] <= movable[1] else 0


def conflict_points(P: np.ndarray, img: RangeImage, M: np.ndarray, margin: float, rel: float
                    ) -> tuple[np.ndarray, int, np.ndarray]:
    """(conflicting points in the image's frame, points in known cells, mask of points the image's
    sensor could see), for points ``P`` moved by ``M`` into that frame (the matcher's rule)."""
    q = P @ M[:3, :3].T + M[:3, 3]
    na, ne = img.ranges.shape
    a, e, r = _cells(q, img.az_deg, img.el_deg, na, ne)
    R = img.ranges[a, e]
    known = np.isfinite(R) & (r > 2.0)
    tol = np.maximum(margin, rel * np.where(np.isfinite(R), R, 0.0))
    with np.errstate(invalid="ignore"):
        bad = known & (r < R - tol)
        seen = np.isfinite(R) & (r <= R + tol)
    return q[bad], int(known.sum()), seen


class Scorer:
    """Per-scan clouds (the matcher's support clouds) and the free-space image the defaults use."""

    def __init__(self, src: dict) -> None:
        self.src, self.clouds, self.trees = src, {}, {}
        c = VerificationConfig()
        self.cell = (c.free_space_az_deg, c.free_space_el_deg, c.free_space_neighbours, c.free_space_scan_neighbours)
        self.margin, self.rel = c.free_space_margin, c.free_space_margin_rel

    def cloud(self, ds: str, i: int):
        if (ds, i) not in self.clouds:
            self.clouds[ds, i] = cs = support_cloud(self.src[ds]["lms"][i])
            if cs is not None:
                self.trees[ds, i] = cKDTree(cs.points)
        return self.clouds[ds, i]

    def clouds_of(self, r: dict):
        return self.cloud(r["ds2"], r["j"]), self.cloud(r["ds"], r["i"])

    def conflict(self, cs, ct, T: np.ndarray, movable=None, whole: bool = True) -> float:
        """max over both directions of the (discounted) conflicting share; 0 without images."""
        img_s, img_t = cs.range_image(*self.cell, whole), ct.range_image(*self.cell, whole)
        if img_s is None or img_t is None:
            return 0.0
        out = 0.0
        for P, img, M in ((cs.points, img_t, invert(ct.sensor_pose) @ T),
                          (ct.points, img_s, invert(cs.sensor_pose) @ invert(T))):
            Q, known, _ = conflict_points(P, img, M, self.margin, self.rel)
            n = len(Q) - (moved_object(Q, movable) if movable is not None else 0)
            out = max(out, n / known if known else 0.0)
        return out

    def row_conflict(self, r: dict, movable=None, whole: bool = True) -> float:
        if r.get("T") is None:
            return 0.0
        cs, ct = self.clouds_of(r)
        if cs is None or ct is None:
            return 0.0
        return self.conflict(cs, ct, np.asarray(r["T"]), movable, whole)

    def covisible(self, r: dict) -> float:
        """Mean over both directions of explained / co-visible points (explained count as seen)."""
        if r.get("T") is None:
            return 0.0
        cs, ct = self.clouds_of(r)
        if cs is None or ct is None:
            return 0.0
        img_s, img_t = cs.range_image(*self.cell), ct.range_image(*self.cell)
        if img_s is None or img_t is None:
            return 0.0
        T = np.asarray(r["T"])
        out = []
        for P, tree, img, M_set, M_sensor in (
                (cs.points, self.trees[r["ds"], r["i"]], img_t, T, invert(ct.sensor_pose) @ T),
                (ct.points, self.trees[r["ds2"], r["j"]], img_s, invert(T), invert(cs.sensor_pose) @ invert(T))):
            q = P @ M_set[:3, :3].T + M_set[:3, 3]
            hit = tree.query(q, distance_upper_bound=0.3)[0] < 0.3
            _, _, seen = conflict_points(P, img, M_sensor, self.margin, self.rel)
            out.append(hit.sum() / max((seen | hit).sum(), 1))
        return float(np.mean(out))


def suite_of(r: dict) -> str:
    return r["ds"] if r["ds"] == r["ds2"] else "cross"


def per_suite(rows: list[dict], th: tuple) -> dict:
    v, ans = decide(rows, *th), answered(rows, *th)
    out = {}
    for name in SUITES:
        idx = [k for k, r in enumerate(rows) if suite_of(r) == name]
        if idx:
            out[name] = metrics([ans[k] for k in idx], v[idx])
    out["ALL"] = metrics(ans, v)
    return out


def show(label: str, res: dict) -> None:
    print(f"  {label}: " + "; ".join(f"{k} {m['precision']:.3f}/{m['recall']:.3f}/{m['valid_negatives']}"
                                       for k, m in res.items()), flush=True)


def with_conflicts(rows: list[dict], c: np.ndarray, cw: np.ndarray) -> list[dict]:
    return [dict(r, conflict=float(a), wide=dict(r["wide"], conflict=float(b))) for r, a, b in zip(rows, c, cw, strict=True)]


def moved_object_variant(sc: Scorer, rows: list[dict], movable) -> dict:
    """Thresholds chosen on the calibration rows with the (discounted) conflict; both splits
    (``movable`` None: the matcher's own conflict, i.e. bench/verification.py's choice)."""
    base = [r for r in rows if not r["ds"].endswith(" raw")]
    raw = [r for r in rows if r["ds"].endswith(" raw")]
    out: dict = {"movable": movable}
    for whole in (True, False):
        B = with_conflicts(base, np.array([sc.row_conflict(r, movable, whole) for r in base]),
                           np.array([sc.row_conflict(r["wide"], movable, whole) for r in base]))
        cal = [r for r in B if r["split"] == "cal"]
        groups = np.array([suite_of(r) for r in cal])
        if whole:
            mo, mr, mc, _ = choose_thresholds(cal, groups=groups)
            R = with_conflicts(raw, np.array([sc.row_conflict(r, movable) for r in raw]),
                               np.array([sc.row_conflict(r["wide"], movable) for r in raw]))
            out["thresholds"] = {"min_overlap": mo, "max_rival_ratio": mr, "max_conflict": mc}
            th = (mo, mr, mc)
            out["raw_drives_test"] = per_suite(R, th)
            key = ""
        else:
            mcs = choose_support_conflict(cal, mo, mr, groups=groups)
            out["thresholds"]["max_conflict_support_points"] = mcs
            th = (mo, mr, mcs)
            key = "support-point image "
        out[key + "calibration"] = per_suite(cal, th)
        out[key + "test"] = per_suite([r for r in B if r["split"] == "test"], th)
    print(f"{'the matcher (no discount)' if movable is None else f'moved-object discount {movable}'}: "
          f"chosen {out['thresholds']}")
    for k in ("calibration", "test", "raw_drives_test", "support-point image calibration", "support-point image test"):
        show(k, out[k])
    return out


def stress(sc: Scorer, src: dict, movable) -> dict:
    """Calibration positives: the ground truth and 11 wrong transforms around it."""
    def rz(deg: float) -> np.ndarray:
        c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
        T = np.eye(4)
        T[:2, :2] = [[c, -s], [s, c]]
        return T

    def slide(x: float, y: float) -> np.ndarray:
        T = np.eye(4)
        T[:2, 3] = x, y
        return T

    perts = [rz(a) for a in (90, 180, 270)] + [slide(x, y) for x, y in
                                               ((3, 0), (-3, 0), (0, 3), (0, -3), (6, 0), (-6, 0), (0, 6), (0, -6))]
    pairs = [p for p in make_pairs(src, 120, 180) if p["split"] == "cal" and p["ds"] == p["ds2"] and p["positive"]]
    out: dict = {}
    for p in pairs:
        cs, ct = sc.clouds_of(p)
        if cs is None or ct is None:
            continue
        P = src[p["ds"]]["poses"]
        G = invert(P[p["i"]]) @ P[p["j"]]
        for k, X in enumerate([np.eye(4), *perts]):
            before = sc.conflict(cs, ct, X @ G)
            after = sc.conflict(cs, ct, X @ G, movable) if before > 0.10 else before
            s = out.setdefault(f"{p['ds']} {'ground truth' if k == 0 else 'wrong'}",
                               {"transforms": 0, "conflict_above_0.10": 0, "brought_below": 0})
            s["transforms"] += 1
            s["conflict_above_0.10"] += int(before > 0.10)
            s["brought_below"] += int(before > 0.10 and after <= 0.10)
            if before > 0.10 and after <= 0.10:
                s.setdefault("discounted_clusters", []).extend(
                    {"pair": [p["i"], p["j"]], "transform": k, **d} for d in discounted(sc, cs, ct, X @ G, movable))
    print("stress test (calibration positives):", json.dumps(out, indent=None))
    return out


def discounted(sc: Scorer, cs, ct, T: np.ndarray, movable) -> list[dict]:
    """The clusters the discount drops at ``T`` (each direction): size, horizontal spans, height
    extent, |z| of their normal (1: horizontal patch), distance from the observing sensor."""
    out = []
    for name, P, img, M in (("source->target", cs.points, ct.range_image(*sc.cell), T),
                            ("target->source", ct.points, cs.range_image(*sc.cell), invert(T))):
        Q, _, _ = conflict_points(P, img, M, sc.margin, sc.rel)
        if len(Q) == 0 or not moved_object(Q, movable):
            continue
        pairs = cKDTree(Q).query_pairs(1.0, output_type="ndarray")
        A = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(Q), len(Q)))
        _, lab = connected_components(A, directed=False)
        C = Q[lab == np.bincount(lab).argmax()]
        xy = C[:, :2] - C[:, :2].mean(axis=0)
        span = np.ptp(xy @ np.linalg.eigh(xy.T @ xy)[1], axis=0)
        normal = np.linalg.eigh((C - C.mean(axis=0)).T @ (C - C.mean(axis=0)))[1][:, 0]
        out.append({"direction": name, "points": len(C), "of": len(Q), "spans_m": span.round(2).tolist(),
                    "height_m": round(float(np.ptp(C[:, 2])), 2), "normal_z": round(abs(float(normal[2])), 2),
                    "range_m": round(float(np.hypot(*C[:, :2].mean(axis=0))), 1)})
    return out


def covisible_variant(sc: Scorer, rows: list[dict]) -> dict:
    """Grid (mo2, mcv) on the calibration split: a pair is past the overlap check when overlap >=
    the chosen min_overlap, or overlap >= mo2 and co-visible overlap >= mcv; the rival ratio and
    conflict thresholds as chosen. Feasible: precision >= 99.5 % on every recording, no valid
    wrong negative. Test not evaluated."""
    cal = [r for r in rows if r["split"] == "cal" and not r["ds"].endswith(" raw")]
    cv = np.array([sc.covisible(r) for r in cal])
    cvw = np.array([sc.covisible(r["wide"]) for r in cal])
    c0 = VerificationConfig()
    grid = []
    for mo2 in np.round(np.arange(0.1, 0.1875, 0.0125), 4):
        for mcv in (0.3, 0.4, 0.5, 0.6, 0.7):
            def passed(r: dict, c: float, mo2: float = mo2, mcv: float = mcv) -> float:
                return 1.0 if r["score"] >= c0.min_overlap or (r["score"] >= mo2 and c >= mcv) else 0.0
            R = [dict(r, score=passed(r, a), wide=dict(r["wide"], score=passed(r["wide"], b)))
                 for r, a, b in zip(cal, cv, cvw, strict=True)]
            res = per_suite(R, (0.5, c0.max_rival_ratio, c0.max_conflict))
            ok = all(m["valid_negatives"] == 0 and (not m["valid"] or m["precision"] >= 0.995)
                     for k, m in res.items() if k != "ALL")
            grid.append({"mo2": float(mo2), "mcv": mcv, "feasible": ok, "recall": res["ALL"]["recall"],
                         "sim-downtown recall": res["sim-downtown"]["recall"]})
    base = per_suite(cal, (c0.min_overlap, c0.max_rival_ratio, c0.max_conflict))["ALL"]["recall"]
    best = max((g for g in grid if g["feasible"]), key=lambda g: g["recall"], default=None)
    # the answers past the rival and conflict checks whatever their overlap: the wrong ones' best co-visible overlap
    R = [dict(r, score=float(a), wide=dict(r["wide"], score=float(b))) for r, a, b in zip(cal, cv, cvw, strict=True)]
    th = (0.0, c0.max_rival_ratio, c0.max_conflict)
    wrong = [a["score"] for a, ok in zip(answered(R, *th), decide(R, *th), strict=True) if ok and not a["correct"]]
    top = float(max(wrong, default=0.0))
    print(f"co-visible overlap: calibration recall {base:.3f} without; best feasible {best}; "
          f"highest co-visible overlap of a wrong answer past the rival / conflict checks {top:.3f}")
    return {"calibration_recall_without": base, "best_feasible": best, "grid": grid, "wrong_max_covisible": top}


def diagnose(sc: Scorer, src: dict, out_dir: Path) -> list[dict]:
    """Calibration sim-downtown positives whose ground truth conflicts above 0.10: the largest
    conflicting cluster and the simulator's labels of the raw scan points under it."""
    from graffmatch.evaluation.suites import SUITES as BENCH_SUITES

    ds = BENCH_SUITES["sim-downtown"].make_dataset(out_dir / "suite-sim-downtown", False, None)
    pairs = [p for p in make_pairs(src, 120, 180)
             if p["split"] == "cal" and p["ds"] == p["ds2"] == "sim-downtown" and p["positive"]]
    P = src["sim-downtown"]["poses"]
    found = []
    for p in pairs:
        cs, ct = sc.clouds_of(p)
        G = invert(P[p["i"]]) @ P[p["j"]]
        if cs is None or ct is None or sc.conflict(cs, ct, G) <= 0.10:
            continue
        for name, pts, img, M, owner in (("source->target", cs.points, ct.range_image(*sc.cell), G, p["j"]),
                                         ("target->source", ct.points, cs.range_image(*sc.cell), invert(G), p["i"])):
            Q, known, _ = conflict_points(pts, img, M, sc.margin, sc.rel)
            if len(Q) == 0:
                continue
            n_obj = moved_object(Q, (1e9, 1e9, 1e9), min_share=0.0)  # the largest cluster, any size
            pairs_ = cKDTree(Q).query_pairs(1.0, output_type="ndarray")
            A = coo_matrix((np.ones(len(pairs_)), (pairs_[:, 0], pairs_[:, 1])), shape=(len(Q), len(Q)))
            _, lab = connected_components(A, directed=False)
            C = Q[lab == np.bincount(lab).argmax()].mean(axis=0)
            # the cluster's centre in the owner scan's frame, and the raw scan's labels within 2.5 m of it
            frame = p["i"] if name == "source->target" else p["j"]
            X = invert(P[owner]) @ P[frame]
            c_owner = X[:3, :3] @ C + X[:3, 3]
            scan = ds[owner]
            near = np.linalg.norm(scan.xyz[:, :2] - c_owner[:2], axis=1) < 2.5
            labels, counts = np.unique(np.asarray(scan.labels)[near] & 0xFFFF, return_counts=True)
            found.append({"pair": [p["i"], p["j"]], "direction": name, "conflict": len(Q) / known,
                          "largest_cluster_points": n_obj, "conflicting_points": len(Q),
                          "cluster_centre_owner_frame": c_owner.round(2).tolist(),
                          "raw_labels_near": dict(zip(labels.tolist(), counts.tolist(), strict=True))})
    for f in found:
        print("diagnosis:", f)
    return found


def fallback_variants(sc: Scorer, src: dict, rows: list[dict]) -> list[dict]:
    """Calibration only: the support points' image with 0-3 shadowing neighbours, and an image of
    the ground returns alone (0 / 1 neighbours), each with its max_conflict chosen as
    bench/verification.py chooses max_conflict_support_points (rival / overlap thresholds fixed)."""
    c0 = VerificationConfig()
    cal = [r for r in rows if r["split"] == "cal" and not r["ds"].endswith(" raw")]
    groups = np.array([suite_of(r) for r in cal])
    th = (c0.min_overlap, c0.max_rival_ratio)
    ground_images: dict = {}

    def ground_conflicts(rs: list[dict], nb_: int) -> np.ndarray:
        def image(ds: str, i: int):
            if (ds, i, nb_) not in ground_images:
                ls = src[ds]["lms"][i]
                g = np.repeat(np.asarray(ls.attributes["is_ground"]).reshape(-1) > 0.5, np.diff(ls.point_offsets))
                G = voxel_downsample(ls.points[g], 0.3, 3000) if g.any() else np.zeros((0, 3))
                ground_images[ds, i, nb_] = RangeImage.from_points(G, c0.free_space_az_deg, c0.free_space_el_deg, nb_)
            return ground_images[ds, i, nb_]

        out = np.zeros(len(rs))
        for k, r in enumerate(rs):
            cs, ct = sc.clouds_of(r)
            if r.get("T") is None or cs is None or ct is None:
                continue
            out[k] = max(conflict_fraction(cs.points, ct.points, image(r["ds2"], r["j"]), image(r["ds"], r["i"]),
                                           np.asarray(r["T"]), c0.free_space_margin, c0.free_space_margin_rel))
        return out

    res = []
    for image, nb_ in [("support points", n) for n in range(4)] + [("ground returns", n) for n in range(2)]:
        if image == "support points":
            var = (c0.free_space_az_deg, c0.free_space_el_deg, nb_, c0.free_space_margin, c0.free_space_margin_rel, 0)
            c = free_space_conflicts(src, cal, var, use_scan_ranges=False)
            cw = free_space_conflicts(src, [r["wide"] for r in cal], var, use_scan_ranges=False)
        else:
            c, cw = ground_conflicts(cal, nb_), ground_conflicts([r["wide"] for r in cal], nb_)
        S = with_conflicts(cal, c, cw)
        mcs = choose_support_conflict(S, *th, groups=groups)
        m = per_suite(S, (*th, mcs))
        feasible = all(x["valid_negatives"] == 0 and (not x["valid"] or x["precision"] >= 0.995)
                       for k, x in m.items() if k != "ALL")
        res.append({"image": image, "neighbours": nb_, "max_conflict": mcs, "feasible": feasible,
                    "calibration": {k: {"precision": x["precision"], "recall": x["recall"],
                                        "valid_negatives": x["valid_negatives"]} for k, x in m.items()}})
        print(f"fallback {image}, {nb_} neighbours: max_conflict {mcs}, calibration recall {m['ALL']['recall']:.3f}, "
              f"precision {m['ALL']['precision']:.3f}, feasible {feasible}", flush=True)
    return res


def halves_disagreement(sc: Scorer, r: dict) -> float:
    """Largest distance between the translations of the source's two halves (by the sign of x,
    then of y, in its frame), each aligned on the target's evidence from the answer ``r["T"]``
    (point-to-point ICP, correspondences 1.0, 0.6, 0.3, 0.3, 0.3 m); nan when a half has < 30 points."""
    cs, ct = sc.clouds_of(r)
    tree = sc.trees[r["ds"], r["i"]]
    P, Q = cs.points, ct.points

    def icp(X: np.ndarray, T: np.ndarray) -> np.ndarray | None:
        for dist in (1.0, 0.6, 0.3, 0.3, 0.3):
            q = X @ T[:3, :3].T + T[:3, 3]
            d, idx = tree.query(q, distance_upper_bound=dist)
            m = d < dist
            if m.sum() < 10:
                return None
            A, B = X[m], Q[idx[m]]
            ca, cb = A.mean(axis=0), B.mean(axis=0)
            U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
            R = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, cb - R @ ca
        return T

    out = np.nan
    for axis in (0, 1):
        Ts = [icp(P[side], np.asarray(r["T"])) if side.sum() >= 30 else None
              for side in (P[:, axis] >= 0, P[:, axis] < 0)]
        if Ts[0] is not None and Ts[1] is not None:
            out = np.nanmax([out, float(np.linalg.norm(Ts[0][:3, 3] - Ts[1][:3, 3]))])
    return float(out)


def raw_calibration(sc: Scorer, src: dict, rows: list[dict]) -> dict:
    """The raw sim-downtown calibration pairs matched with every threshold open (both passes), decided
    at the defaults; translation errors and halves disagreement of the valid answers; the de-skewed
    calibration answers' halves disagreement for comparison."""
    c0 = VerificationConfig()
    th = (c0.min_overlap, c0.max_rival_ratio, c0.max_conflict)
    pairs = [dict(p, ds=f"{p['ds']} raw", ds2=f"{p['ds2']} raw") for p in make_pairs(src, 120, 180)
             if p["split"] == "cal" and p["ds"] == p["ds2"] == "sim-downtown"]
    raw = run_both(src, pairs)
    v, ans = decide(raw, *th), answered(raw, *th)
    out: dict = {"metrics": outcome(raw, *th), "valid": []}
    for a, ok in zip(ans, v, strict=True):
        if ok and a["positive"]:
            out["valid"].append({"pair": [a["i"], a["j"]], "correct": a["correct"], "rot": a["rot"], "tr": a["tr"],
                                 "overlap": a["score"], "rival_ratio": a["ratio"], "conflict": a["conflict"],
                                 "halves": halves_disagreement(sc, a)})
    tr_ok = np.array([x["tr"] for x in out["valid"] if x["correct"]])
    out["tr_right_quantiles_50_90_95_max"] = np.percentile(tr_ok, [50, 90, 95, 100]).tolist()
    out["wrong"] = [x for x in out["valid"] if not x["correct"]]
    deskewed = [r for r in rows if r["split"] == "cal" and r["ds"] == r["ds2"] == "sim-downtown"]
    vd, ad = decide(deskewed, *th), answered(deskewed, *th)
    h = np.array([halves_disagreement(sc, a) for a, ok in zip(ad, vd, strict=True) if ok and a["correct"]])
    hr = np.array([x["halves"] for x in out["valid"] if x["correct"]])
    out["halves_right_raw_50_90_95"] = np.nanpercentile(hr, [50, 90, 95]).tolist()
    out["halves_right_deskewed_50_90_95"] = np.nanpercentile(h, [50, 90, 95]).tolist()
    m = out["metrics"]
    print(f"raw sim-downtown calibration: {m['valid']} valid, precision {m['precision']:.3f}, recall {m['recall']:.3f}; "
          f"right answers' translation error 50/90/95/max % {np.round(out['tr_right_quantiles_50_90_95_max'], 2)}; "
          f"wrong: {[(x['pair'], round(x['rot'], 2), round(x['tr'], 2), round(x['halves'], 2)) for x in out['wrong']]}; "
          f"halves of right answers 50/90/95 %: raw {np.round(out['halves_right_raw_50_90_95'], 2)}, "
          f"de-skewed {np.round(out['halves_right_deskewed_50_90_95'], 2)}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", default="bench/results/verification.json", help="bench/verification.py --json output")
    ap.add_argument("--out", default="/tmp/gm-verify", help="bench/verification.py's --out (its cache)")
    ap.add_argument("--movable", default="6,3,2.5", help="moved-object box: length,width,height [m]")
    ap.add_argument("--raw-cal", action="store_true", help="also match and study the raw sim-downtown calibration pairs")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    t0 = time.perf_counter()
    src = load_sources(Path(a.out), True, True)
    rows = json.loads(Path(a.rows).read_text())["rows"]
    sc = Scorer(src)
    movable = tuple(float(x) for x in a.movable.split(","))
    report = {"rows": a.rows, "diagnosis": diagnose(sc, src, Path(a.out)),
              "stress_test": stress(sc, src, movable),
              "defaults": moved_object_variant(sc, rows, None),
              "moved_object": moved_object_variant(sc, rows, movable),
              "covisible": covisible_variant(sc, rows),
              "fallback": fallback_variants(sc, src, rows)}
    if a.raw_cal:
        report["raw_calibration"] = raw_calibration(sc, src, rows)
    print(f"{time.perf_counter() - t0:.0f} s")
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=1, default=float))
        print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
