"""Why the verified matcher misses calibration positives, and whether better hypotheses, a better
registration or other evidence could recover them (session 11, issue 11: sim-downtown recall).
Calibration split only; it re-decides the rows of ``bench/verification.py`` (``--rows``, both
passes, each pair's transform) and re-matches the misses it studies.

* **Ceiling** (every calibration positive): the overlap of the returned answer, of the ground
  truth, of the ground truth aligned on the evidence points (the matcher's long schedule,
  ``local_search_distances``), and the best of a local search around the ground truth (the
  matcher's 75 starts, +-2 m / +-3 deg, the 5 best by occupancy aligned). If no transform near
  the ground truth explains ``min_overlap`` of the points, no hypothesis or registration can
  make the pair valid at today's evidence.
* **Stages** (calibration misses whose answer is wrong): the ground truth's associations (all
  same-type pairs within 5 deg / 1 m of it, those the gating keeps, those in the graph and their
  edge density), their own registration, and at each stage of the wide pass (``_register``:
  cliques, rivals, gated; ``_trimmed``; each ``merge_hypotheses``) whether a right hypothesis
  exists, the closest one and the cliques holding the most true associations.
* **Evidence variants** (thresholds chosen on the calibration split as ``bench/verification.py``
  chooses them, the rows' rival ratios kept): a surface overlap (a point also counts when its
  nearest neighbour in the other cloud, within ``r_far``, lies on a local plane that passes
  within ``tol`` of it), and the free-space conflict aggregated over the two directions by the
  mean or the minimum instead of the maximum. Stress set: each calibration positive's ground
  truth turned 90 / 180 / 270 deg about the target sensor or slid 3 / 6 m, aligned on the
  evidence as the matcher aligns a hypothesis, still wrong (> 5 deg or 1 m) after it; counted:
  those past each variant's overlap and conflict thresholds (the rival check aside). And the
  landmarks as a second evidence below ``min_overlap``: valid also when the overlap is at least
  ``mo2`` and the landmark-level evidence of bare sets (graded share, or landmarks explained)
  reaches ``L`` (grid; feasible: precision >= 99.5 % on every recording, no valid wrong negative).
  And whether the free-space check saw the answers below ``min_overlap`` at all (the share of
  points landing in cells of the other scan's image that hold a return).

    python bench/verification_misses.py --rows bench/results/verification.json --out /tmp/gm-verify \\
        --json bench/results/verification_misses_session11.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from verification import (
    ROT_OK,
    TRANS_OK,
    answered,
    choose_thresholds,
    decide,
    load_sources,
    make_pairs,
)

import graffmatch.verification.verify as V
from graffmatch.association.consistency_graph import build_consistency_graph
from graffmatch.association.putative import putative_associations
from graffmatch.geometry.transforms import invert, transform_errors
from graffmatch.matcher import GraffMatchConfig, GraffMatcher
from graffmatch.registration.closed_form import register_batch
from graffmatch.verification.config import VerificationConfig
from graffmatch.verification.evidence import (
    align_on_evidence,
    landmark_overlap,
    occupancy_overlap,
    point_overlap,
    point_overlaps,
    support_cloud,
)
from graffmatch.verification.free_space import conflict_fraction
from graffmatch.verification.hypotheses import local_perturbations, residuals

C0 = VerificationConfig()
SUITES = ("courtyard", "sim-downtown", "sim-suburban", "sim-openroad")


def right(T: np.ndarray, G: np.ndarray) -> bool:
    rot, tr = transform_errors(T, G)
    return bool(rot <= ROT_OK and tr <= TRANS_OK)


class Clouds:
    """The matcher's support clouds of every scan used (built once)."""

    def __init__(self, src: dict) -> None:
        self.src, self.c = src, {}

    def __call__(self, ds: str, i: int):
        if (ds, i) not in self.c:
            self.c[ds, i] = support_cloud(self.src[ds]["lms"][i])
        return self.c[ds, i]

    def pair(self, r: dict):
        return self(r["ds2"], r["j"]), self(r["ds"], r["i"])

    def gt(self, r: dict) -> np.ndarray:
        P = self.src[r["ds"]]["poses"]
        return invert(P[r["i"]]) @ P[r["j"]]


def overlap(cs, ct, T: np.ndarray) -> float:
    return float(np.mean(point_overlap(cs, ct, T, C0.inlier_m)))


def best_near(cs, ct, G: np.ndarray, top: int = 5) -> float:
    """The best overlap the matcher's local search reaches around ``G`` (its grid of starts,
    the ``top`` best by occupancy and ``G`` itself aligned with the long schedule)."""
    centre = G[:3, :3] @ cs.points.mean(axis=0) + G[:3, 3]
    Ts = local_perturbations(G, centre, C0.local_search_step_m, C0.local_search_m, C0.local_search_deg)
    occ = occupancy_overlap(cs, ct, Ts, C0.inlier_m).mean(axis=1)
    starts = [G, *Ts[np.argsort(-occ, kind="stable")[:top]]]
    al = np.stack([align_on_evidence(cs, ct, T, C0.local_search_distances) for T in starts])
    return float(point_overlaps(cs, ct, al, C0.inlier_m).mean(axis=1).max())


def ceiling(cl: Clouds, cal: list[dict]) -> dict:
    th = (C0.min_overlap, C0.max_rival_ratio, C0.max_conflict)
    pos = [r for r in cal if r["positive"] and r["ds"] == r["ds2"]]
    v, ans = decide(pos, *th), answered(pos, *th)
    out: dict = {}
    for r, ok, a in zip(pos, v, ans, strict=True):
        cs, ct = cl.pair(r)
        if cs is None or ct is None:
            continue
        G = cl.gt(r)
        Gl = align_on_evidence(cs, ct, G, C0.local_search_distances)
        x = {"pair": [r["i"], r["j"]], "valid_right": bool(ok and a["correct"]), "answer_right": bool(a["correct"]),
             "answer_overlap": a["score"], "answer_ratio": a["ratio"], "answer_conflict": a["conflict"],
             "gt_overlap": overlap(cs, ct, G), "gt_aligned_overlap": overlap(cs, ct, Gl),
             "gt_aligned_drift": list(transform_errors(Gl, G))}
        s = out.setdefault(r["ds"], {"positives": 0, "valid_right": 0, "misses": [], "answer_minus_gt_aligned": []})
        s["positives"] += 1
        s["valid_right"] += int(x["valid_right"])
        if x["answer_right"]:
            s["answer_minus_gt_aligned"].append(x["answer_overlap"] - x["gt_aligned_overlap"])
        if not x["valid_right"]:
            x["best_near_gt"] = best_near(cs, ct, G)
            x["kind"] = ("no right answer" if not x["answer_right"] else
                         "overlap below min_overlap" if x["answer_overlap"] < C0.min_overlap else
                         "free-space conflict" if x["answer_conflict"] > C0.max_conflict else "rival")
            s["misses"].append(x)
    for name, s in out.items():
        d = np.array(s.pop("answer_minus_gt_aligned"))
        s["right_answers_minus_gt_aligned_p10_50_90"] = np.percentile(d, [10, 50, 90]).tolist() if len(d) else []
        print(f"{name}: {s['valid_right']}/{s['positives']} valid and right; right answers' overlap minus the "
              f"aligned ground truth's (10/50/90 %): {np.round(s['right_answers_minus_gt_aligned_p10_50_90'], 3)}")
        for x in s["misses"]:
            print(f"  miss {x['pair']}: {x['kind']}; answer {x['answer_overlap']:.3f} (right {x['answer_right']}), "
                  f"ground truth {x['gt_overlap']:.3f}, aligned {x['gt_aligned_overlap']:.3f}, best near it "
                  f"{x['best_near_gt']:.3f} (min_overlap {C0.min_overlap})", flush=True)
    return out


def stages(src: dict, cl: Clouds, ds: str, i: int, j: int) -> dict:
    """Where the right answer of one pair is lost (the wide pass, as ``wide_search="always"``)."""
    cfg = GraffMatchConfig(verification=VerificationConfig(
        min_overlap=0.0, max_rival_ratio=1.0, max_conflict=1.0, max_conflict_support_points=1.0,
        min_landmark_overlap=0.0, wide_search="always"))
    m = GraffMatcher(cfg)
    T, S = src[ds]["lms"][i], src[ds]["lms"][j]
    G = cl.gt({"ds": ds, "i": i, "j": j})
    same = np.array([(a, b) for a in range(len(S)) for b in range(len(T)) if S.types[a] == T.types[b]], np.int64)
    ang, off = residuals(S, T, same, G)
    n_true_all = int(((ang <= 5.0) & (off <= 1.0)).sum())
    A = putative_associations(S, T, cfg.gating)
    A = same if A is None else A
    ang, off = residuals(S, T, A, G)
    n_true_put = int(((ang <= 5.0) & (off <= 1.0)).sum())
    g = build_consistency_graph(m.distance_matrix(S), m.distance_matrix(T), A, cfg.epsilon, cfg.sigma,
                                types_i=S.types, types_j=T.types, compact=False)
    ang, off = residuals(S, T, g.associations, G)
    tv = np.flatnonzero((ang <= 5.0) & (off <= 1.0))
    W = g.weights.tocsr()
    sub = (W[tv][:, tv].toarray() > 0)
    cs, ct = cl(ds, j), cl(ds, i)
    out: dict = {"pair": [i, j], "landmarks": [len(S), len(T)],
                 "true_associations": {"same_type_pairs": n_true_all, "putative": n_true_put, "in_graph": len(tv),
                                       "types": np.bincount(S.types[g.associations[tv, 0]], minlength=3).tolist(),
                                       "edge_density": float(sub.sum() / max(len(tv) * (len(tv) - 1), 1))},
                 "graph_associations": int(len(g.associations)), "gt_overlap": overlap(cs, ct, G)}
    if len(tv) >= 2:
        b = register_batch(S, T, g.associations[tv], None, None, cfg.kappa_max, 1)
        Tt = b.T_target_source[0]
        out["true_set_registration"] = {"error": list(transform_errors(Tt, G)), "overlap": overlap(cs, ct, Tt),
                                        "degenerate": bool(b.degenerate[0])}
    rec: list = []
    orig = (V._register, V._trimmed, V.merge_hypotheses)

    def reg(*a, **k):
        h = orig[0](*a, **k)
        rec.append(("register", list(h)))
        return h

    def trim(*a, **k):
        h = orig[1](*a, **k)
        rec.append(("trimmed", list(h)))
        return h

    def merge(h, c, by="score"):
        o = orig[2](h, c, by)
        rec.append((f"merge by {by}", list(o)))
        return o

    V._register, V._trimmed, V.merge_hypotheses = reg, trim, merge
    try:
        r = m.match(S, T)
    finally:
        V._register, V._trimmed, V.merge_hypotheses = orig
    out["answer"] = {"error": list(transform_errors(r.T_target_source, G)), "overlap": r.overlap}
    out["stages"] = []
    for name, hyps in rec:
        errs = [transform_errors(h.T_target_source, G) for h in hyps]
        n_right = sum(e[0] <= ROT_OK and e[1] <= TRANS_OK for e in errs)
        close = min(errs, key=lambda e: e[1] + e[0] / 5.0) if errs else None
        most = sorted(((int(np.isin(h.info.get("vertices", []), tv).sum()), h.n_associations, h.origin,
                        [round(float(x), 2) for x in e]) for h, e in zip(hyps, errs, strict=True)),
                      key=lambda x: -x[0])[:3]
        out["stages"].append({"stage": name, "hypotheses": len(hyps), "origins": sorted({h.origin for h in hyps}),
                              "right": int(n_right), "closest": None if close is None else [float(x) for x in close],
                              "most_true_associations": most})
    s = out["true_associations"]
    print(f"  {ds} {i}/{j}: true associations {s['same_type_pairs']} same-type, {s['putative']} putative, "
          f"{s['in_graph']} in the graph (types {s['types']}, edge density {s['edge_density']:.2f}); registered alone "
          f"{np.round(out.get('true_set_registration', {}).get('error', []), 2)}, overlap "
          f"{out.get('true_set_registration', {}).get('overlap', float('nan')):.3f}; ground truth {out['gt_overlap']:.3f}; "
          f"right hypotheses at any stage: {sum(x['right'] for x in out['stages'])}", flush=True)
    for x in out["stages"]:
        if x["stage"] == "register" or x["stage"] == "trimmed":
            print(f"     {x['stage']} {x['origins']}: {x['hypotheses']}, closest {np.round(x['closest'] or [], 2)}, "
                  f"most true associations {x['most_true_associations'][:2]}")
    return out


class Surface:
    """Surface overlap: a point counts when within ``inlier_m`` of the other cloud (today's), or
    when its nearest neighbour within ``r_far`` has a planar neighbourhood whose plane passes
    within ``tol`` of it (sparse rings of a far wall explain each other)."""

    def __init__(self, cl: Clouds) -> None:
        self.cl, self.c = cl, {}

    def cloud(self, ds: str, i: int):
        if (ds, i) not in self.c:
            cs = self.cl(ds, i)
            if cs is None:
                self.c[ds, i] = None
                return None
            P = cs.points
            tree = cKDTree(P)
            dist, idx = tree.query(P, k=8, distance_upper_bound=0.9)
            N, ok = np.zeros_like(P), np.zeros(len(P), bool)
            for k in range(len(P)):
                nb = idx[k][np.isfinite(dist[k])]
                if len(nb) >= 4:
                    X = P[nb] - P[nb].mean(axis=0)
                    w, Vv = np.linalg.eigh(X.T @ X)
                    if w[0] < 0.05 * w.sum():
                        N[k], ok[k] = Vv[:, 0], True
            self.c[ds, i] = (P, tree, N, ok)
        return self.c[ds, i]

    @staticmethod
    def share(a, b, T: np.ndarray, r_far: float, tol: float) -> float:
        P, Q, tq, N, ok = a[0], b[0], b[1], b[2], b[3]
        q = P @ T[:3, :3].T + T[:3, 3]
        d, idx = tq.query(q, distance_upper_bound=r_far)
        hit = d < C0.inlier_m
        f = np.isfinite(d) & ~hit
        jj = idx[f]
        hit[np.flatnonzero(f)[ok[jj] & (np.abs(np.einsum("ij,ij->i", q[f] - Q[jj], N[jj])) <= tol)]] = True
        return float(hit.mean())

    def score(self, ds2: str, j: int, ds: str, i: int, T: np.ndarray | None, r_far: float, tol: float) -> float:
        a, b = self.cloud(ds2, j), self.cloud(ds, i)
        if T is None or a is None or b is None:
            return 0.0
        T = np.asarray(T)
        return 0.5 * (self.share(a, b, T, r_far, tol) + self.share(b, a, invert(T), r_far, tol))


def per_suite(rows: list[dict], th: tuple) -> dict:
    v, a = decide(rows, *th), answered(rows, *th)
    out = {n: int(sum(v[k] and a[k]["correct"] for k, r in enumerate(rows)
                      if r["ds"] == r["ds2"] == n and r["positive"])) for n in SUITES}
    out["valid_wrong"] = int(sum(v[k] and not a[k]["correct"] for k in range(len(rows))))
    return out


def stress_set(src: dict, cl: Clouds) -> list[dict]:
    """Wrong transforms around the calibration positives' ground truths, aligned as the matcher
    aligns a hypothesis; those that stay wrong, with both conflict directions and the overlap."""
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
    cell = (C0.free_space_az_deg, C0.free_space_el_deg, C0.free_space_neighbours, C0.free_space_scan_neighbours)
    out = []
    for p in make_pairs(src, 120, 180):
        if not (p["split"] == "cal" and p["ds"] == p["ds2"] and p["positive"]):
            continue
        cs, ct = cl.pair(p)
        if cs is None or ct is None:
            continue
        G = cl.gt(p)
        img_s, img_t = cs.range_image(*cell), ct.range_image(*cell)
        for X in perts:
            Ta = align_on_evidence(cs, ct, X @ G)
            if right(Ta, G):
                continue
            c = (0.0, 0.0) if img_s is None or img_t is None else conflict_fraction(
                cs.points, ct.points, img_s, img_t, Ta, C0.free_space_margin, C0.free_space_margin_rel,
                cs.sensor_pose, ct.sensor_pose)
            parts = point_overlap(cs, ct, Ta, C0.inlier_m)
            out.append({"ds": p["ds"], "i": p["i"], "j": p["j"], "T": Ta, "conflict": c, "overlap": float(np.mean(parts)),
                        "parts": (*parts, len(cs), len(ct))})
    return out


def evidence_variants(src: dict, cl: Clouds, cal: list[dict], stress: list[dict]) -> dict:
    groups = np.array([r["ds"] if r["ds"] == r["ds2"] else "cross" for r in cal])
    cell = (C0.free_space_az_deg, C0.free_space_el_deg, C0.free_space_neighbours, C0.free_space_scan_neighbours)

    def dirs(r: dict) -> tuple[float, float]:
        cs, ct = cl.pair(r)
        if r.get("T") is None or cs is None or ct is None:
            return (0.0, 0.0)
        a, b = cs.range_image(*cell), ct.range_image(*cell)
        if a is None or b is None:
            return (0.0, 0.0)
        return conflict_fraction(cs.points, ct.points, a, b, np.asarray(r["T"]), C0.free_space_margin,
                                 C0.free_space_margin_rel, cs.sensor_pose, ct.sensor_pose)

    D1 = np.array([dirs(r) for r in cal])
    D2 = np.array([dirs(r["wide"]) for r in cal])
    assert np.allclose(D1.max(axis=1), [r["conflict"] for r in cal], atol=1e-9), "rows' conflicts differ"
    S1 = np.array([r["score"] for r in cal])
    S2 = np.array([r["wide"]["score"] for r in cal])
    Sst = np.array([x["overlap"] for x in stress])
    Cst = np.array([x["conflict"] for x in stress]).reshape(-1, 2)
    out: dict = {"stress_wrong_transforms": len(stress)}
    sf = Surface(cl)
    def parts(r: dict) -> tuple:
        cs, ct = cl.pair(r)
        if r.get("T") is None or cs is None or ct is None:
            return (0.0, 0.0, 1, 1)
        return (*point_overlap(cs, ct, np.asarray(r["T"]), C0.inlier_m), len(cs), len(ct))

    P1, P2 = np.array([parts(r) for r in cal]), np.array([parts(r["wide"]) for r in cal])
    Pst = np.array([x["parts"] for x in stress]).reshape(-1, 4)
    # the overlap of two scans' evidence aggregated otherwise (at the returned transform: the rows'
    # overlap is that of the transform before _refine, which may replace it); counts / 1000 points
    aggregations = {
        "mean share at the returned transform": lambda p: p[:, :2].mean(axis=1),
        "larger share": lambda p: p[:, :2].max(axis=1),
        "smaller share": lambda p: p[:, :2].min(axis=1),
        "geometric mean of the shares": lambda p: np.sqrt(p[:, 0] * p[:, 1]),
        "explained points / 1000 (mean of both)": lambda p: (p[:, 0] * p[:, 2] + p[:, 1] * p[:, 3]) / 2000,
        "explained points / 1000 (smaller)": lambda p: np.minimum(p[:, 0] * p[:, 2], p[:, 1] * p[:, 3]) / 1000,
    }
    gap = np.abs(P1[:, :2].mean(axis=1) - S1)
    out["rows_overlap_vs_returned_transform"] = {"max": float(gap.max()), "above_0.01": int((gap > 0.01).sum()),
                                                 "rows": len(gap)}
    print(f"rows' overlap vs the overlap at the returned transform: max {gap.max():.3f}, "
          f"{int((gap > 0.01).sum())} of {len(gap)} differ by > 0.01")
    variants: list[tuple[str, object, object]] = [("today (max conflict)", np.max, None),
                                                  ("mean conflict", np.mean, None),
                                                  ("min conflict", np.min, None),
                                                  ("surface overlap 0.6 m / 0.1 m", np.max, (0.6, 0.1)),
                                                  ("surface overlap 0.9 m / 0.1 m", np.max, (0.9, 0.1)),
                                                  *((k, np.max, f) for k, f in aggregations.items())]
    for name, agg, surf in variants:
        s1, s2, sst = S1, S2, Sst
        if callable(surf):
            s1, s2, sst = surf(P1), surf(P2), surf(Pst)
        elif surf is not None:
            s1 = np.array([sf.score(r["ds2"], r["j"], r["ds"], r["i"], r.get("T"), *surf) for r in cal])
            s2 = np.array([sf.score(r["ds2"], r["j"], r["ds"], r["i"], r["wide"].get("T"), *surf) for r in cal])
            sst = np.array([sf.score(x["ds"], x["j"], x["ds"], x["i"], x["T"], *surf) for x in stress])
        R = [dict(r, score=float(a), conflict=float(agg(c)), wide=dict(r["wide"], score=float(b), conflict=float(agg(d))))
             for r, a, b, c, d in zip(cal, s1, s2, D1, D2, strict=True)]
        mo, mr, mc, m = choose_thresholds(R, groups=groups)
        passed = (sst >= mo) & (agg(Cst, axis=1) <= mc)
        out[name] = {"thresholds": [mo, mr, mc], "calibration_recall": m.get("recall"),
                     "right_valid_positives": per_suite(R, (mo, mr, mc)),
                     "stress_past_overlap_and_conflict": int(passed.sum()),
                     "stress_past_by_suite": {n: int(sum(p and x["ds"] == n for p, x in zip(passed, stress, strict=True)))
                                              for n in SUITES}}
        print(f"{name}: chosen {mo} / {mr} / {mc}, calibration recall {m.get('recall', 0):.4f}, "
              f"{out[name]['right_valid_positives']}; stress: {int(passed.sum())} of {len(stress)} wrong transforms "
              f"past overlap and conflict", flush=True)
    return out


def landmark_second(src: dict, cal: list[dict]) -> dict:
    """Landmark-level agreement (graded share / landmarks explained, as for bare sets) as a second
    way past ``min_overlap``; the rows past the rival and conflict checks with overlap 0.10 to
    ``min_overlap`` listed with it."""
    def lm(r: dict) -> tuple[float, int]:
        if r.get("T") is None:
            return (0.0, 0)
        counts: list = []
        p = landmark_overlap(src[r["ds2"]]["lms"][r["j"]], src[r["ds"]]["lms"][r["i"]], np.asarray(r["T"]),
                             C0.landmark_deg, C0.landmark_m, counts)
        return (float(np.mean(p)), int(counts[0][0]))

    L1, L2 = [lm(r) for r in cal], [lm(r["wide"]) for r in cal]
    th = (0.0, C0.max_rival_ratio, C0.max_conflict)
    below = []
    for r, a, ok, l1, l2 in zip(cal, answered(cal, *th), decide(cal, *th), L1, L2, strict=True):
        if ok and 0.10 <= a["score"] < C0.min_overlap:
            lx = l1 if a is r else l2
            below.append({"pair": [r["ds"], r["i"], r["ds2"], r["j"]], "positive": r["positive"], "right": a["correct"],
                          "overlap": a["score"], "landmark_share": lx[0], "landmarks_explained": lx[1]})
    best = None
    for mo2 in np.round(np.arange(0.10, C0.min_overlap, 0.0125), 4):
        for kind, grid in ((0, (0.2, 0.25, 0.3, 0.35, 0.4, 0.5)), (1, (4, 5, 6, 7, 8, 10, 12))):
            for L in grid:
                def passed(r: dict, lx: tuple, mo2: float = mo2, kind: int = kind, L: float = L) -> float:
                    return 1.0 if r["score"] >= C0.min_overlap or (r["score"] >= mo2 and lx[kind] >= L) else 0.0
                R = [dict(r, score=passed(r, a), wide=dict(r["wide"], score=passed(r["wide"], b)))
                     for r, a, b in zip(cal, L1, L2, strict=True)]
                th2 = (0.5, C0.max_rival_ratio, C0.max_conflict)
                v, ans = decide(R, *th2), answered(R, *th2)
                groups: dict = {}
                for k, r in enumerate(R):
                    if v[k]:
                        g = groups.setdefault(r["ds"] if r["ds"] == r["ds2"] else "cross", [0, 0])
                        g[0] += 1
                        g[1] += int(ans[k]["correct"])
                if not all(c >= 0.995 * n for n, c in groups.values()):
                    continue
                res = per_suite(R, th2)
                n = sum(res[s] for s in SUITES)
                if best is None or n > best["right_valid"]:
                    best = {"mo2": float(mo2), "evidence": ["share", "explained"][kind], "L": L, "right_valid": n,
                            "right_valid_positives": res}
    print(f"landmarks as a second evidence: best feasible {best}")
    for x in below:
        print(f"   below min_overlap: {x}")
    return {"best_feasible": best, "below_min_overlap": below}


def known_shares(cl: Clouds, cal: list[dict]) -> dict:
    """Whether the free-space check saw the answer at all: the share of each scan's points that
    land in a cell of the other's image holding a return (what the conflict is a share of), for
    the answers past the rival and conflict checks below ``min_overlap`` and the right positives."""
    cell = (C0.free_space_az_deg, C0.free_space_el_deg, C0.free_space_neighbours, C0.free_space_scan_neighbours)

    def known(r: dict) -> tuple[float, float]:
        cs, ct = cl.pair(r)
        if r.get("T") is None or cs is None or ct is None:
            return (0.0, 0.0)
        a, b = cs.range_image(*cell), ct.range_image(*cell)
        if a is None or b is None:
            return (0.0, 0.0)
        T = np.asarray(r["T"])
        M_st, M_ts = invert(ct.sensor_pose) @ T, invert(cs.sensor_pose) @ invert(T)
        _, k1 = b.conflicts(cs.points @ M_st[:3, :3].T + M_st[:3, 3], C0.free_space_margin, C0.free_space_margin_rel)
        _, k2 = a.conflicts(ct.points @ M_ts[:3, :3].T + M_ts[:3, 3], C0.free_space_margin, C0.free_space_margin_rel)
        return (k1 / len(cs), k2 / len(ct))

    th = (0.0, C0.max_rival_ratio, C0.max_conflict)
    below, right_min = [], []
    for r, ok, a in zip(cal, decide(cal, *th), answered(cal, *th), strict=True):
        if a["correct"] and r["positive"]:
            right_min.append(min(known(a)))
        if ok and 0.12 <= a["score"] < C0.min_overlap:
            below.append({"pair": [r["ds"], r["i"], r["ds2"], r["j"]], "right": a["correct"], "overlap": a["score"],
                          "known": known(a)})
    q = np.percentile(right_min, [1, 5, 50]).tolist()
    print(f"known shares (points in observed cells): right positives' smaller share 1/5/50 %: {np.round(q, 2)}")
    for x in below:
        print(f"   {x['pair']} right {x['right']}, overlap {x['overlap']:.3f}, known {np.round(x['known'], 2)}")
    return {"right_positives_smaller_known_1_5_50": q, "below_min_overlap": below}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", default="bench/results/verification.json", help="bench/verification.py --json output")
    ap.add_argument("--out", default="/tmp/gm-verify", help="bench/verification.py's --out (its cache)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    t0 = time.perf_counter()
    src = load_sources(Path(a.out), True, False)
    cal = [r for r in json.loads(Path(a.rows).read_text())["rows"] if r["split"] == "cal" and not r["ds"].endswith(" raw")]
    cl = Clouds(src)
    report: dict = {"rows": a.rows, "ceiling": ceiling(cl, cal)}
    print("stages of the calibration misses whose answer is wrong (sim-downtown):")
    report["stages"] = [stages(src, cl, "sim-downtown", *x["pair"])
                        for x in report["ceiling"].get("sim-downtown", {}).get("misses", [])
                        if x["kind"] == "no right answer"]
    stress = stress_set(src, cl)
    report["evidence_variants"] = evidence_variants(src, cl, cal, stress)
    report["landmarks_second_evidence"] = landmark_second(src, cal)
    report["free_space_known_shares"] = known_shares(cl, cal)
    print(f"{time.perf_counter() - t0:.0f} s")
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=1, default=float))
        print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
