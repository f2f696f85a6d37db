"""Precision of ``valid`` on partial views: scan pairs whose source is cropped to a random
azimuth sector and turned by a random yaw, registered as ``ScanMatcher`` does with each evidence
setting (support points only; support points, then the raw scans when not valid). A valid result
is right when it is within 5 deg and 1 m of the ground truth.

Why: ``bench/verification.py`` matches whole scans. A user's scans are partial (occlusion, a
sensor's field of view, a cropped map), and the thresholds were chosen on whole scans.

Data, split as ``bench/verification.py`` splits it (``--split``):
* ``courtyard`` (real, bundle-adjusted poses): pairs 3-16 m apart, both scans in the first half
  of the walk (``cal``) or both in the second (``test``);
* ``--sims``: the de-skewed simulated drives of ``bench/verification.py`` (``--out``: its
  extraction directory, reused), pairs 3-16 m apart in the drive's first / second half;
* negatives, cropped the same way: sources of the split's half against scans of another dataset
  (courtyard x KITTI, courtyard x sims, sims x each other; KITTI scans 0-2 are ``cal``, 3-5
  ``test``), and, on the simulated drives, places > 60 m apart (judged by pose: only a valid
  *wrong* answer counts).
Views (``--views``): the whole scan, a 180-270 deg sector, 90-180 deg, 60-90 deg. The crop's
seed differs by split (``--seed``, default 1501 for cal and 1502 for test).

Each pair is matched once on the support points and once on the raw scans (the second pass of
``evidence='support_then_scans'``; with ``--report`` only when the first is not valid, as the
pipeline runs it). Rows keep each pass's evidence (overlap, rival ratio, conflict, view coverage,
co-visible overlap), so ``--choose`` can pick the partial-view thresholds offline on a ``cal``
file (run it with ``--open``: the partial-view thresholds open, every other decision as shipped):

    python bench/verification_partial_views.py --split cal --sims --open --json bench/results/partial_views_cal_session15.json
    python bench/verification_partial_views.py --choose bench/results/partial_views_cal_session15.json
    python bench/verification_partial_views.py --split test --sims --report --json bench/results/partial_views_test_session15.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
import warnings
from pathlib import Path

import numpy as np

from graffmatch.errors import GraffMatchError
from graffmatch.geometry.transforms import invert, transform_errors
from graffmatch.lidar.extractor import LandmarkExtractorConfig
from graffmatch.lidar.io import read_scan
from graffmatch.pipeline import ScanMatcher, ScanMatcherConfig
from graffmatch.verification.verify import scan_evidence

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
VIEWS = {"whole": (360.0, 360.0), "180-270": (180.0, 270.0), "90-180": (90.0, 180.0), "60-90": (60.0, 90.0)}
ROT_OK, TRANS_OK = 5.0, 1.0


def yaw(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def crop(X: np.ndarray, a0: float, width_deg: float) -> np.ndarray:
    """The points of X within the azimuth sector [a0, a0 + width) (radians, degrees)."""
    if width_deg >= 360.0:
        return X
    return X[(np.arctan2(X[:, 1], X[:, 0]) - a0) % (2 * np.pi) < np.radians(width_deg)]


class Source:
    """One recording: raw scans on demand, true poses, its ScanMatcher (extractor settings), and
    each whole scan's landmarks and extractor cloud, extracted once."""

    def __init__(self, name: str, scan, poses: np.ndarray, cfg: ScanMatcherConfig) -> None:
        self.name, self.scan, self.poses = name, scan, poses
        self.sm = ScanMatcher(cfg)
        self._whole: dict[int, tuple] = {}

    def whole(self, i: int) -> tuple:
        if i not in self._whole:
            ls = self.sm.extract(self.scan(i))
            c = self.sm.extractor.last_cloud
            self._whole[i] = (ls, None if c is None else c.points)
        return self._whole[i]


def load(args, cfg_for) -> dict[str, Source]:
    P = np.loadtxt(DATA / "balm_courtyard" / "poses.txt").reshape(-1, 3, 4)
    P = np.concatenate([P, np.tile([[[0.0, 0.0, 0.0, 1.0]]], (len(P), 1, 1))], 1)
    src = {"courtyard": Source("courtyard", lambda i: read_scan(DATA / "balm_courtyard" / "velodyne" / f"{i:06d}.bin")
                               .points[:, :3], P, cfg_for(None))}
    from graffmatch.datasets.folder import KittiFolder

    kitti = KittiFolder(DATA / "kitti00_first6")
    src["kitti"] = Source("kitti", lambda i: kitti[i].points[:, :3], kitti.poses, cfg_for(None))
    if args.sims:
        from graffmatch.datasets.deskewed import Deskewed
        from graffmatch.evaluation.suites import SIM_EXTRACTORS, SUITES
        from graffmatch.loops.posegraph import OdometryDriftConfig, drifted_odometry

        for k, name in enumerate(("sim-downtown", "sim-suburban", "sim-openroad")):
            ds = SUITES[name].make_dataset(Path(args.out) / f"suite-{name}", False, None)
            dsk = Deskewed(ds, drifted_odometry(ds.poses, OdometryDriftConfig(seed=k)))  # as bench/verification.py
            src[name] = Source(name, (lambda d: lambda i: d[i].points[:, :3])(dsk), ds.poses,
                               cfg_for(SIM_EXTRACTORS.get(name, {})))
    return src


def make_pairs(src: dict[str, Source], split: str, n_pos: int, n_neg: int, rng: np.random.Generator) -> list[dict]:
    """(dataset of the cropped source, source scan, dataset of the target, target scan, positive)."""
    pairs: list[dict] = []
    halves = {}
    for name, s in src.items():
        n = len(s.poses)
        half = n // 2
        halves[name] = range(0, half) if split == "cal" else range(half, n)
    for name, s in src.items():
        if name == "kitti":
            continue
        pos = s.poses[:, :3, 3]
        D = np.linalg.norm(pos[:, None] - pos[None], axis=2)
        h = list(halves[name])
        near = [(i, j) for i in h for j in h if i != j and 3.0 <= D[i, j] <= 16.0]
        for k in rng.choice(len(near), min(n_pos, len(near)), replace=False):
            pairs.append(dict(ds=name, i=near[k][0], ds2=name, j=near[k][1], positive=True))
        far = [(i, j) for i in h for j in h if D[i, j] > 60.0]
        if far:
            for k in rng.choice(len(far), min(n_neg // 2, len(far)), replace=False):
                pairs.append(dict(ds=name, i=far[k][0], ds2=name, j=far[k][1], positive=False))
        others = [o for o in src if o != name]
        for _ in range(n_neg - (n_neg // 2 if far else 0)):
            o = others[int(rng.integers(len(others)))]
            pairs.append(dict(ds=name, i=int(rng.choice(h)), ds2=o, j=int(rng.choice(list(halves[o]))),
                              positive=False))
    return pairs


def summary(r, T_true: np.ndarray | None) -> dict:
    info = r.info
    row = dict(valid=bool(r.valid), message=r.message, overlap=float(r.overlap),
               score=float(info.get("verified_overlap", r.overlap)),
               ratio=float(info.get("rival_ratio", 0.0)) if r.runner_up is not None else 0.0,
               conflict=float(max(info.get("free_space_conflict", (0.0, 0.0)))),
               coverage=list(info.get("view_coverage", (1.0, 1.0))),
               covisible=list(info.get("covisible_overlap", (np.nan, np.nan))),
               search=info.get("search"), source=info.get("evidence_source"), confidence=float(r.confidence))
    row["correct"] = False
    if r.T_target_source is not None and T_true is not None:
        rot, tr = transform_errors(r.T_target_source, T_true)
        row.update(rot=rot, tr=tr, correct=bool(rot <= ROT_OK and tr <= TRANS_OK))
    return row


def run(args) -> dict:
    seed = args.seed if args.seed is not None else (1501 if args.split == "cal" else 1502)
    rng = np.random.default_rng(seed)

    def cfg_for(extractor: dict | None) -> ScanMatcherConfig:
        cfg = ScanMatcherConfig(evidence="support_then_scans")
        if extractor:
            cfg = cfg.model_copy(update={"extractor": LandmarkExtractorConfig.model_validate(extractor)})
        if args.open:  # the partial-view thresholds open, for both evidences
            vc = cfg.matcher.verification
            opened = {"partial_min_overlap": 0.0, "partial_max_rival_ratio": 1.0, "narrow_min_overlap": 0.0,
                      "narrow_max_rival_ratio": 1.0}
            vc = vc.model_copy(update={**opened, "scans": vc.scans.model_copy(update=opened)})
            cfg = cfg.model_copy(update={"matcher": cfg.matcher.model_copy(update={"verification": vc})})
        return cfg

    src = load(args, cfg_for)
    pairs = make_pairs(src, args.split, args.pairs, args.negatives, rng)
    rows: list[dict] = []
    t0 = time.perf_counter()
    n = 0
    for view in args.views:
        lo, hi = VIEWS[view]
        for p in pairs:
            n += 1
            S, T = src[p["ds"]], src[p["ds2"]]
            a0, width, y = rng.uniform(-np.pi, np.pi), rng.uniform(lo, hi), rng.uniform(-np.pi, np.pi)
            Y = yaw(y)
            A = crop(S.scan(p["i"]), a0, width) @ Y[:3, :3].T
            T_true = None
            if p["ds"] == p["ds2"]:
                T_true = invert(T.poses[p["j"]]) @ S.poses[p["i"]] @ invert(Y)
            row = dict(p, view=view, width=width, a0=a0, yaw=y)
            sm = S.sm  # the source recording's extractor (the matchers' settings are the same)
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    ls_s = sm.extract(A)
                    cloud_s = sm.extractor.last_cloud
                    ls_t, cloud_t = T.whole(p["j"])
                    if len(ls_s) < 2 or len(ls_t) < 2 or cloud_s is None or cloud_t is None:
                        raise GraffMatchError("too few landmarks")
                    r1 = sm.match(ls_s, ls_t)
                    row["support"] = summary(r1, T_true)
                    if not r1.valid or not args.report:
                        ev = scan_evidence(ls_s, ls_t, cloud_s.points, cloud_t,
                                           sm.config.matcher.verification)
                        if ev.kind == "scans":
                            r2 = sm.matcher.match(ls_s, ls_t, evidence=ev)
                            row["scans"] = summary(r2, T_true)
            except GraffMatchError as exc:
                row["error"] = str(exc)
            rows.append(row)
            if n % 100 == 0:
                print(f"  {n}/{len(pairs) * len(args.views)} pairs, {time.perf_counter() - t0:.0f} s", flush=True)
    return {"split": args.split, "seed": seed, "open": args.open, "report": args.report, "views": args.views,
            "pairs": args.pairs, "negatives": args.negatives, "sims": args.sims,
            "seconds": time.perf_counter() - t0, "rows": rows}


# ---- offline decisions --------------------------------------------------------------------------

WHOLE, NARROW = 0.9, 0.5  # VerificationConfig.view_whole / view_narrow


def view_of(r: dict) -> float:
    """The pair's view: the smaller azimuth coverage of its two scans."""
    for ev in ("support", "scans"):
        if r.get(ev):
            return float(min(r[ev]["coverage"]))
    return 1.0


def tier_of(r: dict) -> str:
    v = view_of(r)
    return "whole" if v >= WHOLE else "partial" if v >= NARROW else "narrow"


def accepts(p: dict | None, tier: str, th: dict | None) -> bool:
    """Whether a pass's result is valid with the partial-view thresholds ``th`` = {tier: (co-visible
    overlap, rival ratio)} applied to it (None: as it was run)."""
    if p is None or not p["valid"]:
        return False
    if th is None or tier == "whole":
        return True
    o, q = th[tier][:2]
    cov = 0.5 * (p["covisible"][0] + p["covisible"][1])
    return bool(cov >= o and p["ratio"] <= q)


def outcome(row: dict, mode: str, th_s: dict | None, th_c: dict | None) -> dict | None:
    """The valid answer of ``mode`` ('support' or 'support_then_scans'), or None."""
    t = tier_of(row)
    if accepts(row.get("support"), t, th_s):
        return row["support"]
    if mode == "support_then_scans" and accepts(row.get("scans"), t, th_c):
        return row["scans"]
    return None


def table(rows: list[dict], mode: str, th_s=None, th_c=None) -> dict:
    """Per view and recording: positives, valid, wrong, precision, recall; negatives valid-wrong."""
    out: dict = {}
    for r in rows:
        key = (r["view"], r["ds"] if r["positive"] else "negatives")
        s = out.setdefault(key, {"pairs": 0, "valid": 0, "wrong": 0})
        s["pairs"] += 1
        a = outcome(r, mode, th_s, th_c)
        if a is not None:
            s["valid"] += 1
            s["wrong"] += int(not a["correct"])
    res = {}
    for (view, ds), s in sorted(out.items()):
        s["precision"] = (s["valid"] - s["wrong"]) / s["valid"] if s["valid"] else float("nan")
        s["recall"] = (s["valid"] - s["wrong"]) / s["pairs"]
        res[f"{view} | {ds}"] = s
    return res


def _arrays(rs: list[dict], ev: str) -> tuple:
    """(valid, right, co-visible overlap, rival ratio) of one pass over rows ``rs``."""
    v = np.array([bool(r.get(ev) and r[ev]["valid"]) for r in rs])
    c = np.array([bool(r.get(ev) and r[ev]["correct"]) for r in rs])
    o = np.array([float(np.mean(r[ev]["covisible"])) if v[k] else 0.0 for k, r in enumerate(rs)])
    q = np.array([r[ev]["ratio"] if v[k] else 1.0 for k, r in enumerate(rs)])
    return v, c, np.nan_to_num(o), q


def _fine(grp: np.ndarray, valid: np.ndarray, right: np.ndarray, target: float) -> bool:
    """Precision >= target on every recording, no valid wrong negative."""
    for g in set(grp.tolist()):
        m = grp == g
        v, w = int(valid[m].sum()), int((valid[m] & ~right[m]).sum())
        if (g == "negatives" and w) or (g != "negatives" and v and (v - w) / v < target):
            return False
    return True


def choose(rows: list[dict], target: float = 0.995) -> dict:
    """Partial-view thresholds on calibration rows, per tier (views in [0.5, 0.9), below 0.5):
    for the support points, then for the raw scans given the support points' choice (the second
    pass of 'support_then_scans'), the largest recall of right answers with precision >= ``target``
    on every recording's positives of the tier and no valid wrong negative; ties: the stricter
    (higher overlap, then lower rival ratio)."""
    grid_o = np.round(np.arange(0.0, 0.601, 0.025), 3)
    grid_r = np.round(np.arange(0.3, 1.001, 0.025), 3)
    out: dict = {"support": {}, "scans": {}, "right": {}}
    for tier in ("partial", "narrow"):
        rs = [r for r in rows if tier_of(r) == tier]
        grp = np.array([r["ds"] if r["positive"] else "negatives" for r in rs])

        vs, cs, os_, qs = _arrays(rs, "support")
        vc, cc, oc, qc = _arrays(rs, "scans")
        pos = np.array([r["positive"] for r in rs])

        best = None
        for o, q in itertools.product(grid_o, grid_r):
            a = vs & (os_ >= o) & (qs <= q)
            key = (int((a & cs & pos).sum()), o, -q)
            if (best is None or key > best[0]) and _fine(grp, a, cs, target):
                best = (key, (float(o), float(q)))
        th_s = best[1] if best else (1.0, 0.0)
        a_s = vs & (os_ >= th_s[0]) & (qs <= th_s[1])
        best_c = None
        for o, q in itertools.product(grid_o, grid_r):
            a = a_s | (vc & (oc >= o) & (qc <= q))
            right = np.where(a_s, cs, cc)
            key = (int((a & right & pos).sum()), o, -q)
            if (best_c is None or key > best_c[0]) and _fine(grp, a, right, target):
                best_c = (key, (float(o), float(q)))
        out["support"][tier] = th_s
        out["scans"][tier] = best_c[1] if best_c else (1.0, 0.0)
        out["right"][tier] = {"support": best[0][0] if best else 0, "support_then_scans": best_c[0][0] if best_c else 0,
                              "pairs": len(rs), "positives": int(pos.sum())}
    return out


def print_tables(rows: list[dict], th_s=None, th_c=None, title: str = "") -> dict:
    out = {}
    for mode in ("support", "support_then_scans"):
        t = table(rows, mode, th_s, th_c)
        out[mode] = t
        print(f"-- {title} {mode}")
        for key, s in t.items():
            print(f"   {key:<28} pairs {s['pairs']:>4}  valid {s['valid']:>4}  wrong {s['wrong']:>3}  "
                  f"precision {s['precision']:.3f}  recall {s['recall']:.3f}")
    return out


def gated_table(rows: list[dict], title: str, min_view: float = 0.9) -> None:
    """Valid / wrong per view and sign for support only, support then scans, and the default
    (``ScanMatcherConfig.scan_fallback_min_view``: the scans row only when the support row is not
    valid and the pair's smaller coverage is at least ``min_view``)."""
    count: dict = {}
    for r in rows:
        if "support" not in r:
            continue
        s, sc = r["support"], r.get("scans")
        whole = bool(s.get("coverage")) and min(s["coverage"]) >= min_view
        for mode in ("support", "support_then_scans", "default (gated)"):
            use = sc if (mode != "support" and not s["valid"] and sc is not None
                         and (mode == "support_then_scans" or whole)) else s
            c = count.setdefault((r["view"], r["positive"], mode), [0, 0, 0])
            c[0] += 1
            c[1] += bool(use["valid"])
            c[2] += bool(use["valid"] and not use["correct"])
    print(f"\n{title}: valid / wrong of pairs")
    for view in ("whole", "180-270", "90-180", "60-90"):
        for pos in (True, False):
            if (view, pos, "support") in count:
                cells = "  ".join(f"{m} {count[(view, pos, m)][1]} / {count[(view, pos, m)][2]}"
                                  for m in ("support", "support_then_scans", "default (gated)"))
                print(f"  {view:>8} {'positives' if pos else 'negatives'} ({count[(view, pos, 'support')][0]}): {cells}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", choices=("cal", "test"), default="test")
    ap.add_argument("--views", nargs="+", default=list(VIEWS), choices=list(VIEWS))
    ap.add_argument("--pairs", type=int, default=60, help="positives per recording (each view)")
    ap.add_argument("--negatives", type=int, default=20, help="negatives per recording (each view)")
    ap.add_argument("--seed", type=int, default=None, help="default: 1501 (cal), 1502 (test)")
    ap.add_argument("--sims", action="store_true", help="also the simulated drives (--out)")
    ap.add_argument("--out", default="/tmp/scan14-verify", help="bench/verification.py's extraction directory")
    ap.add_argument("--open", action="store_true", help="partial-view thresholds open (to choose them offline)")
    ap.add_argument("--report", action="store_true", help="the raw-scan pass only after an invalid support pass")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--choose", type=Path, default=None, help="choose thresholds on this cal JSON (no matching)")
    ap.add_argument("--apply", default=None,
                    help="with --choose FILE: print FILE's tables at these thresholds instead, JSON "
                         '{"support": {"partial": [o, q, s], "narrow": [...]}, "scans": {...}}')
    ap.add_argument("--gated", type=Path, nargs="+", default=None,
                    help="re-decide --report files as ScanMatcher's default does (the raw-scan pass only "
                         "when the support points fail and both views cover >= 0.9) and print valid / wrong")
    a = ap.parse_args()
    if a.gated:
        for f in a.gated:
            gated_table(json.loads(f.read_text())["rows"], str(f))
        return
    if a.choose:
        rows = json.loads(a.choose.read_text())["rows"]
        rows = [r for r in rows if "error" not in r]
        print_tables(rows, title="as run")
        if a.apply:
            x = json.loads(a.apply)
            th_s, th_c = x["support"], x["scans"]
            print_tables(rows, th_s, th_c, title=f"at {th_s} / {th_c}")
            return
        c = choose(rows)
        print("chosen:", c)
        print_tables(rows, c["support"], c["scans"], title="chosen")
        return
    rep = run(a)
    rows = [r for r in rep["rows"] if "error" not in r]
    rep["errors"] = len(rep["rows"]) - len(rows)
    rep["tables"] = print_tables(rows, title=a.split)
    if a.json:
        a.json.write_text(json.dumps(rep, indent=1, default=float))
        print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
