"""Trust of ``valid``: precision, recall and false positives of the verified matcher, with the
decision thresholds chosen on a calibration split and reported on a separate test split.

Data (all from one command, cached under --out):
* ``balm_courtyard`` (real): pairs 3-16 m apart. Calibration split: both scans in the first
  half of the walk; test split: both in the second half.
* ``kitti00_first6`` (real): every pair of the six scans (test only).
* the simulated drives of ``graffmatch benchmark``'s suites (sim-downtown, sim-suburban,
  sim-openroad: the realistic simulator, HDL-64): pairs 3-16 m apart (positives), split by the
  first / second half of each drive. Their raw scans are motion-distorted (up to 1 m per sweep
  at 10 m/s, 10 deg in a U-turn), so they are de-skewed with a drifting odometry
  (``datasets.Deskewed``, ``loops.posegraph.drifted_odometry``) as a user's drive is;
  ``--raw-drives`` also reports the same test pairs on the raw scans (not calibrated on).
* negatives, split by pair parity: places > 60 m apart on one recording, and cross-dataset
  pairs: courtyard x KITTI, simulated x real, simulated style x style (``--cross-per`` of each,
  half of them test). A far pair on one recording can still share a view (an 80 m lidar on an
  open road): it is judged by its pose like a positive, so only a valid *wrong* result counts
  as a false positive on any negative.

Each pair is matched once with a permissive decision (every threshold open) and the raw
evidence is recorded (best score, rival ratio, free-space conflict, structural problems, the
transform); any threshold's outcome is then computed offline. A result is *correct* when it is within 5 deg and
1 m of the ground-truth relative pose. Thresholds (min overlap, max rival ratio, max free-space
conflict) and the free-space range image (cell size, neighbourhood, margin; recomputed offline
from each pair's transform): the largest recall on the calibration split with precision
>= 99.5 % on each recording (no valid cross-dataset negative) and at most 0.5 % valid-and-wrong
negatives; the confidence is a logistic fit on the
calibration split. The lines-only pass (GraffMatch-lines, poles only) runs on the simulated drives
extracted with the pole-only front end (``poles.LAYERED_POLES``, cached apart). Prints the tables
and writes JSON (``--json``).

    python bench/verification.py --out /tmp/gm-verify --raw-drives --json bench/results/verification.json

``--evidence scans`` (session 14) does the same for the raw-scan evidence of ``ScanMatcher``:
each pair, negatives included, verified on both scans' non-ground voxel clouds from the
extractor and again on the support points; the raw-scan thresholds chosen by the same rule on
the calibration split, for scans alone and for ``evidence='support_then_scans'`` (the support
points' answer when valid, else the scans'), reported on the test split (``main_scans``):

    python bench/verification.py --out /tmp/gm-verify --evidence scans --json bench/results/verification_scans_session14.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from graffmatch.datasets.deskewed import Deskewed
from graffmatch.datasets.folder import KittiFolder
from graffmatch.errors import InvalidInputError
from graffmatch.evaluation.suites import SIM_EXTRACTORS, shared_data_root, suite_config
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.transforms import invert, transform_errors
from graffmatch.lidar.extractor import LandmarkExtractor, LandmarkExtractorConfig
from graffmatch.lidar.poles import LAYERED_POLES
from graffmatch.matcher import GraffMatchConfig, GraffMatcher
from graffmatch.verification.config import VerificationConfig

ROT_OK, TRANS_OK = 5.0, 1.0


#: the evidence hypotheses are scored on (``--evidence``): support (the landmarks' support
#: points) or scans (the extractor's non-ground voxel cloud of each scan, as ``ScanMatcher``
#: with ``evidence='scans'``); set by :func:`main`
EVIDENCE = "support"
#: each loaded set's scan cloud with ``--evidence scans``, by ``id`` of the set (alive in ``src``)
SCAN_CLOUDS: dict[int, np.ndarray] = {}
_EVIDENCE_CLOUDS: dict = {}


def extract_all(ds, cfg: LandmarkExtractorConfig, cache: Path, name: str) -> list[LandmarkSet]:
    """Landmarks of every scan, cached per (dataset, extractor config and code version, scan file)
    state; with ``EVIDENCE == 'scans'`` each set's scan cloud, the extractor's voxel cloud of the
    scan (``LandmarkExtractor.last_cloud.points``, cached next to it), goes to ``SCAN_CLOUDS``."""
    import hashlib

    key = hashlib.sha1((cfg.config_hash() + str(ds.scan_path(0).stat().st_mtime_ns)).encode()).hexdigest()[:10]
    cache = cache / f"{name}-{key}"
    cache.mkdir(parents=True, exist_ok=True)
    ex = LandmarkExtractor(cfg)
    clouds = EVIDENCE == "scans"
    out = []
    for i in range(len(ds)):
        f = cache / f"{name}_{i:06d}.npz"
        fc = cache / f"{name}_{i:06d}_cloud.npy"
        if f.exists() and (not clouds or fc.exists()):
            ls = LandmarkSet.load(f)
            if clouds:
                SCAN_CLOUDS[id(ls)] = np.load(fc)
            out.append(ls)
            continue
        scan = ds[i]
        ls = ex.extract(scan.points, None)
        ls.save(f, include_points=True)
        if clouds:
            c = ex.last_cloud
            pts = np.zeros((0, 3)) if c is None else c.points
            np.save(fc, pts)
            ls = LandmarkSet.load(f)  # as a cached run sees it
            SCAN_CLOUDS[id(ls)] = np.load(fc)
        out.append(ls)
    return out


def scan_evidence_of(src: dict, cfg: VerificationConfig, ds_s: str, j: int, ds_t: str, i: int):
    """The raw-scan evidence of a pair (``verify.scan_evidence``, as ``ScanMatcher.register``
    builds it); each scan's cloud is built once and reused (its cell hashes too), as the
    support points' per-scan cache does."""
    from graffmatch.verification.evidence import scan_cloud
    from graffmatch.verification.verify import Evidence, scan_evidence

    cache = _EVIDENCE_CLOUDS
    for key in ((ds_s, j), (ds_t, i)):
        if key not in cache:
            ls = src[key[0]]["lms"][key[1]]
            cache[key] = scan_cloud(SCAN_CLOUDS[id(ls)], ls, cfg.scan_voxel, cfg.scan_max_points)
    cs, ct = cache[ds_s, j], cache[ds_t, i]
    if cs is None or ct is None:  # what scan_evidence falls back to
        return scan_evidence(src[ds_s]["lms"][j], src[ds_t]["lms"][i], np.zeros((0, 3)), np.zeros((0, 3)), cfg)
    return Evidence(cs, ct, "scans")


def with_poles(cfg: LandmarkExtractorConfig, poles: dict | None) -> LandmarkExtractorConfig:
    """``cfg`` with its pole settings overridden (``--poles``: front-end experiments)."""
    if not poles:
        return cfg
    d = cfg.model_dump()
    d["poles"] = {**d["poles"], **poles}
    return LandmarkExtractorConfig.model_validate(d)


def load_sources(out: Path, sims: bool, raw_drives: bool = False, poles: dict | None = None) -> dict[str, dict]:
    root = shared_data_root()
    src: dict[str, dict] = {}
    court = KittiFolder(root / "balm_courtyard")
    src["courtyard"] = {
        "lms": extract_all(court, with_poles(suite_config("balm_courtyard").extractor, poles), out / "cache",
                           "courtyard"),
        "poses": court.poses,
    }
    kitti = KittiFolder(root / "kitti00_first6")
    src["kitti"] = {"lms": extract_all(kitti, with_poles(LandmarkExtractorConfig(), poles), out / "cache", "kitti"),
                    "poses": kitti.poses}
    if sims:
        src.update(load_sims(out, raw_drives, poles))
    return src


def load_sims(out: Path, raw_drives: bool = False, poles: dict | None = None) -> dict[str, dict]:
    """The simulated drives' landmarks (de-skewed; raw too with ``raw_drives``)."""
    from graffmatch.evaluation.suites import SUITES
    from graffmatch.loops.posegraph import OdometryDriftConfig, drifted_odometry

    src: dict[str, dict] = {}
    for k, name in enumerate(("sim-downtown", "sim-suburban", "sim-openroad")):  # the report's drives
        ds = SUITES[name].make_dataset(out / f"suite-{name}", False, None)
        cfg = with_poles(LandmarkExtractorConfig.model_validate(SIM_EXTRACTORS.get(name, {})), poles)
        # raw (motion-distorted) scans, de-skewed with a drifting odometry as a user's drive is
        odometry = drifted_odometry(ds.poses, OdometryDriftConfig(seed=k))
        src[name] = {"lms": extract_all(Deskewed(ds, odometry), cfg, out / "cache", f"{name}-deskew"),
                     "poses": ds.poses}
        if raw_drives:
            src[f"{name} raw"] = {"lms": extract_all(ds, cfg, out / "cache", name), "poses": ds.poses}
    return src


def raw_drive_pairs(pairs: list[dict]) -> list[dict]:
    """The test pairs of each de-skewed simulated drive again, on its raw scans."""
    return [dict(p, ds=f"{p['ds']} raw", ds2=f"{p['ds2']} raw") for p in pairs
            if p["split"] == "test" and p["ds"] == p["ds2"] and p["ds"].startswith("sim-")]


def make_pairs(src: dict[str, dict], max_per: int, cross_per: int = 180, seed: int = 0) -> list[dict]:
    """Positive and negative pairs with their split ('cal' or 'test'): up to ``max_per``
    positives per dataset and split, ``cross_per`` negatives per pair of datasets and per
    dataset (places > 60 m apart), alternately calibration and test. Raw drives (``--raw-drives``)
    get none here: :func:`raw_drive_pairs` repeats their de-skewed twin's test pairs."""
    rng = np.random.default_rng(seed)
    src = {k: v for k, v in src.items() if not k.endswith(" raw")}
    pairs: list[dict] = []

    def take(lst: list, k: int) -> list:
        if len(lst) <= k:
            return lst
        return [lst[i] for i in np.sort(rng.choice(len(lst), k, replace=False))]

    for name, s in src.items():
        P = s["poses"]
        n = len(P)
        pos = P[:, :3, 3]
        D = np.linalg.norm(pos[:, None] - pos[None], axis=2)
        half = n // 2
        if name == "kitti":
            for i in range(n):
                for j in range(i + 1, n):
                    pairs.append(dict(ds=name, i=i, j=j, ds2=name, split="test", positive=True))
            continue
        for split, lo, hi in (("cal", 0, half), ("test", half, n)):
            cand = [(i, j) for i in range(lo, hi) for j in range(i + 1, hi) if 3.0 <= D[i, j] <= 16.0]
            for i, j in take(cand, max_per):
                pairs.append(dict(ds=name, i=i, j=j, ds2=name, split=split, positive=True))
    for name, s in src.items():  # places > 60 m apart anywhere on the recording, split by parity
        pos = s["poses"][:, :3, 3]
        D = np.linalg.norm(pos[:, None] - pos[None], axis=2)
        far = [(i, j) for i in range(len(pos)) for j in range(i + 1, len(pos)) if D[i, j] > 60.0]
        for k, (i, j) in enumerate(take(far, cross_per)):
            pairs.append(dict(ds=name, i=i, j=j, ds2=name, split="cal" if k % 2 == 0 else "test", positive=False))
    names = list(src)
    for a in range(len(names)):
        for b in range(a + 1, len(names)):
            na, nb_ = names[a], names[b]
            cross = [(i, j) for i in range(len(src[na]["lms"])) for j in range(len(src[nb_]["lms"]))]
            for k, (i, j) in enumerate(take(cross, cross_per)):
                pairs.append(dict(ds=na, i=i, j=j, ds2=nb_, split="cal" if k % 2 == 0 else "test",
                                  positive=False))
    return pairs


def run_pairs(src: dict, pairs: list[dict], cfg: GraffMatchConfig) -> list[dict]:
    matcher = GraffMatcher(cfg)
    rows = []
    t_start = time.perf_counter()
    for n, p in enumerate(pairs):
        T = src[p["ds"]]["lms"][p["i"]]  # target: scan i of ds; source: scan j of ds2
        S = src[p["ds2"]]["lms"][p["j"]]
        row = dict(p)
        if len(S) < 2 or len(T) < 2:
            row.update(structural=False, score=0.0, ratio=1.0, correct=False, t=0.0, message="too few landmarks")
            rows.append(row)
            continue
        ev = None
        if EVIDENCE == "scans":
            ev = scan_evidence_of(src, cfg.verification, p["ds2"], p["j"], p["ds"], p["i"])
        t0 = time.perf_counter()
        try:
            r = matcher.match(S, T, evidence=ev)
        except InvalidInputError as exc:  # e.g. lines only: a scan with a single pole
            row.update(structural=False, score=0.0, ratio=1.0, correct=False, t=0.0, message=str(exc))
            rows.append(row)
            continue
        row["t"] = time.perf_counter() - t0
        # what the decision compares with min_overlap: the verified transform's overlap (the
        # returned one differs when the landmark re-registration replaced it, ``overlap``)
        row["score"] = float(r.info.get("verified_overlap", r.overlap))
        row["overlap"] = float(r.overlap)
        row["ratio"] = float(r.info.get("rival_ratio", 1.0)) if r.runner_up is not None else 0.0
        row["structural"] = bool(r.T_target_source is not None and r.valid)
        row["message"] = r.message
        row["n_hyp"] = len(r.hypotheses)
        row["n_assoc"] = len(r.associations)
        row["slide"] = float(r.info.get("slide_ratio", 0.0))
        row["conflict"] = float(max(r.info.get("free_space_conflict", (0.0, 0.0))))
        row["evidence"] = r.info.get("evidence_source")
        row["view"] = float(min(r.info.get("view_coverage", (1.0, 1.0))))  # partial views: session 15
        row["view_problem"] = " view: coverage" in r.message
        row["T"] = None if r.T_target_source is None else np.asarray(r.T_target_source).tolist()
        row["correct"] = False
        if p["ds"] == p["ds2"] and r.T_target_source is not None:  # far pairs too: judged by pose
            Pi, Pj = src[p["ds"]]["poses"][p["i"]], src[p["ds"]]["poses"][p["j"]]
            T_gt = invert(Pi) @ Pj  # maps scan j (source) into scan i (target)
            rot, tr = transform_errors(r.T_target_source, T_gt)
            row.update(rot=rot, tr=tr, correct=bool(rot <= ROT_OK and tr <= TRANS_OK))
            if r.runner_up is not None:
                rr, rt = transform_errors(r.runner_up.T_target_source, T_gt)
                row["runner_up_correct"] = bool(rr <= ROT_OK and rt <= TRANS_OK)
        rows.append(row)
        if (n + 1) % 100 == 0:
            el = time.perf_counter() - t_start
            print(f"  {n + 1}/{len(pairs)} pairs, {el:.0f} s", flush=True)
    return rows


def run_both(src: dict, pairs: list[dict]) -> list[dict]:
    """Each pair matched with every threshold open, first pass only (``wide_search="never"``),
    and again with the wide pass after it (``"always"``), kept as the row's ``wide``: the matcher
    returns the first pass when it is valid, else the wide one (``wide_search="when_invalid"``),
    which :func:`decide` and :func:`answered` reproduce at any thresholds."""
    def open_cfg(mode: str) -> GraffMatchConfig:
        return GraffMatchConfig(verification=VerificationConfig(
            min_overlap=0.0, max_rival_ratio=1.0, max_conflict=1.0, max_conflict_support_points=1.0,
            min_landmark_overlap=0.0, wide_search=mode, scans=None))

    rows = run_pairs(src, pairs, open_cfg("never"))
    print("  the wide pass:", flush=True)
    for r, w in zip(rows, run_pairs(src, pairs, open_cfg("always")), strict=True):
        r["wide"] = w
    return rows


def passes(rows: list[dict], min_overlap: float, max_ratio: float, max_conflict: float = 1.0,
           max_slide: float | None = None) -> np.ndarray:
    """Which rows of one verification pass are valid at these thresholds."""
    s = np.array([r["score"] for r in rows])
    q = np.array([r["ratio"] for r in rows])
    c = np.array([r.get("conflict", 0.0) for r in rows])
    st = np.array([r["structural"] for r in rows], bool)
    if max_slide is not None:
        st = st & (np.array([r.get("slide", 0.0) for r in rows]) <= max_slide)
    return st & (s >= min_overlap) & (q <= max_ratio) & (c <= max_conflict)


def decide(rows: list[dict], min_overlap: float, max_ratio: float, max_conflict: float = 1.0,
           max_slide: float | None = None) -> np.ndarray:
    """Valid at these thresholds: the first pass, or else (rows with a ``wide`` pass, the
    matcher's ``wide_search="when_invalid"``) the wide pass."""
    v = passes(rows, min_overlap, max_ratio, max_conflict, max_slide)
    if rows and "wide" in rows[0]:
        v = v | passes([r["wide"] for r in rows], min_overlap, max_ratio, max_conflict, max_slide)
    return v


def answered(rows: list[dict], min_overlap: float, max_ratio: float, max_conflict: float = 1.0,
             max_slide: float | None = None) -> list[dict]:
    """The row the matcher returns for each pair at these thresholds: the first pass when it is
    valid, else its wide pass (rows without one: themselves)."""
    if not rows or "wide" not in rows[0]:
        return rows
    v = passes(rows, min_overlap, max_ratio, max_conflict, max_slide)
    return [r if ok else r["wide"] for r, ok in zip(rows, v, strict=True)]


def outcome(rows: list[dict], *th) -> dict:
    """metrics of ``rows`` decided at thresholds ``th`` (both passes)."""
    return metrics(answered(rows, *th), decide(rows, *th))


def metrics(rows: list[dict], valid: np.ndarray) -> dict:
    pos = np.array([r["positive"] for r in rows], bool)
    cor = np.array([r["correct"] for r in rows], bool)
    tp = valid & cor
    n_valid = int(valid.sum())
    return {
        "pairs": len(rows), "positives": int(pos.sum()), "negatives": int((~pos).sum()),
        "valid": n_valid, "valid_correct": int(tp.sum()),
        "precision": float(tp.sum() / n_valid) if n_valid else float("nan"),
        "recall": float((tp & pos).sum() / pos.sum()) if pos.sum() else float("nan"),
        "valid_negatives": int((valid & ~pos & ~cor).sum()),
        "valid_negatives_right_pose": int((valid & ~pos & cor).sum()),
        "fpr_negatives": float((valid & ~pos & ~cor).sum() / (~pos).sum()) if (~pos).sum() else float("nan"),
        "oracle_recall": float((cor & pos).sum() / pos.sum()) if pos.sum() else float("nan"),
    }


def auc(score: np.ndarray, label: np.ndarray) -> float:
    pos, neg = score[label], score[~label]
    if len(pos) == 0 or len(neg) == 0:
        return float("nan")
    order = np.argsort(np.r_[pos, neg], kind="stable")
    ranks = np.empty(len(order))
    ranks[order] = np.arange(1, len(order) + 1)
    return float((ranks[: len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


#: Free-space range images compared on the calibration split: (azimuth deg, elevation deg,
#: neighbour cells of the support points' image, margin m, relative margin, neighbour cells of
#: the whole scan's image). Every set here comes from the extractor and carries its whole scan's
#: image (``LandmarkSet.scan_ranges``), so the support points' neighbourhood stays at session 6's
#: choice (1; it serves sets without that image). No shadowing neighbour first: with every return
#: in the image a thin pole is in its own cell, and ties go to the earlier variant.
FREE_SPACE_VARIANTS = [(az, el, 1, mg, rel, snb) for snb in (0, 1) for az, el in ((1.0, 1.0), (1.0, 2.0), (2.0, 2.0))
                       for mg in (1.0, 2.0) for rel in (0.05, 0.1)]


def free_space_conflicts(src: dict, rows: list[dict], variant: tuple, use_scan_ranges: bool = True) -> np.ndarray:
    """Each pair's free-space conflict (max of both directions) at its matched transform, for
    one range-image variant: what the matcher computes with those settings
    (``use_scan_ranges=False``: what it computes for sets without the whole scan's image)."""
    from graffmatch.verification.evidence import support_cloud
    from graffmatch.verification.free_space import conflict_fraction

    az, el, nb, mg, rel, snb = variant
    clouds: dict = {}

    def cloud(ds: str, i: int):
        if (ds, i) not in clouds:
            clouds[ds, i] = support_cloud(src[ds]["lms"][i])
        return clouds[ds, i]

    out = np.zeros(len(rows))
    for k, r in enumerate(rows):
        if r.get("T") is None:
            continue
        cs, ct = cloud(r["ds2"], r["j"]), cloud(r["ds"], r["i"])
        if cs is None or ct is None:
            continue
        img_s = cs.range_image(az, el, nb, snb, use_scan_ranges)
        img_t = ct.range_image(az, el, nb, snb, use_scan_ranges)
        if img_s is None or img_t is None:
            continue
        out[k] = max(conflict_fraction(cs.points, ct.points, img_s, img_t, np.asarray(r["T"]), mg, rel,
                                       cs.sensor_pose, ct.sensor_pose))
    return out


def choose_thresholds(cal: list[dict], conflicts: np.ndarray | None = None, groups: np.ndarray | None = None,
                      max_neg_fpr: float = 0.005, loose_conflict: bool = True,
                      wide_conflicts: np.ndarray | None = None,
                      prior: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[float, float, float, dict]:
    """Most calibration recall with precision >= 99.5 % (in each of ``groups`` when given) and
    <= ``max_neg_fpr`` valid-and-wrong negatives (vectorised over the grid); ties, in this
    order: the lower overlap, the stricter (lower) ratio, the looser conflict
    (``loose_conflict``) or the stricter. (Until session 14 this said "the stricter overlap"; the
    code has always kept the lower one, and every shipped threshold was chosen by the code.) Rows with a
    ``wide`` pass are decided as the matcher does: the first pass when valid, else the wide one.
    ``prior`` (valid, correct per row): a decision taken before these rows' (the support points'
    at their thresholds); a row counts as valid when it is valid or the prior is, with the
    prior's answer when the prior is valid (``--evidence support_then_scans``). The returned
    metrics are then those of the rows alone."""
    def arrays(rs: list[dict], C: np.ndarray | None) -> tuple:
        return (np.array([r["score"] for r in rs]), np.array([r["ratio"] for r in rs]),
                np.array([r["structural"] for r in rs], bool), np.array([r["correct"] for r in rs], bool),
                np.array([r.get("conflict", 0.0) for r in rs]) if C is None else C)

    S, Q, ST, COR, C = arrays(cal, conflicts)
    wide = bool(cal) and "wide" in cal[0]
    if wide:
        Sw, Qw, STw, CORw, Cw = arrays([r["wide"] for r in cal], wide_conflicts)
    POS = np.array([r["positive"] for r in cal], bool)
    n_pos, n_neg = max(POS.sum(), 1), max((~POS).sum(), 1)
    G = [] if groups is None else [groups == g for g in np.unique(groups)]
    best = None
    for mc in [*np.round(np.arange(0.04, 0.40, 0.01), 3), 1.0]:
        b1 = ST & (C <= mc)
        if wide:
            w1 = STw & (Cw <= mc)
        for mo in np.round(np.arange(0.05, 0.71, 0.0125), 4):
            b2 = b1 & (S >= mo)
            if wide:
                w2 = w1 & (Sw >= mo)
            for mr in np.round(np.arange(0.5, 0.96, 0.025), 3):
                v = b2 & (Q <= mr)
                cor = COR
                if wide:
                    cor = np.where(v, COR, CORw)
                    v = v | (w2 & (Qw <= mr))
                if prior is not None:
                    cor = np.where(prior[0], prior[1], cor)
                    v = v | prior[0]
                nv = v.sum()
                tp = (v & cor).sum()
                if (nv and tp / nv < 0.995) or (v & ~POS & ~cor).sum() / n_neg > max_neg_fpr:
                    continue
                if groups is not None and any((v & g).sum() and (v & g & cor).sum() / (v & g).sum() < 0.995
                                              for g in G):
                    continue
                key = ((v & cor & POS).sum() / n_pos, -mo, -mr, mc if loose_conflict else -mc)
                if best is None or key > best[0]:
                    best = (key, float(mo), float(mr), float(mc))
    if best is None:
        return 0.7, 0.5, 0.0, {}
    rows = [dict(r, conflict=float(c)) for r, c in zip(cal, C, strict=True)]
    if wide:
        for r, cw in zip(rows, Cw, strict=True):
            r["wide"] = dict(r["wide"], conflict=float(cw))
    return best[1], best[2], best[3], outcome(rows, best[1], best[2], best[3])


def choose_support_conflict(cal: list[dict], min_overlap: float, max_ratio: float,
                            max_neg_fpr: float = 0.005, groups: np.ndarray | None = None) -> float:
    """``max_conflict`` for the support points' image at fixed overlap / rival thresholds: the
    most calibration recall with precision >= 99.5 % (in each of ``groups`` when given: each
    recording, and the cross-dataset negatives, where any valid result is wrong) and <=
    ``max_neg_fpr`` valid-and-wrong negatives; ties: the stricter."""
    best = None
    n_neg = max(sum(not r["positive"] for r in cal), 1)
    n_pos = max(sum(r["positive"] for r in cal), 1)
    pos = np.array([r["positive"] for r in cal], bool)
    G = [] if groups is None else [groups == g for g in np.unique(groups)]
    for mc in np.round(np.arange(0.0, 0.40, 0.005), 3):
        v = decide(cal, min_overlap, max_ratio, float(mc))
        cor = np.array([r["correct"] for r in answered(cal, min_overlap, max_ratio, float(mc))], bool)
        nv = v.sum()
        if (nv and (v & cor).sum() / nv < 0.995) or (v & ~pos & ~cor).sum() / n_neg > max_neg_fpr:
            continue
        if any((v & g).sum() and (v & g & cor).sum() / (v & g).sum() < 0.995 for g in G):
            continue
        key = ((v & cor & pos).sum() / n_pos, -mc)
        if best is None or key > best[0]:
            best = (key, float(mc))
    return 0.0 if best is None else best[1]


def fit_confidence(cal: list[dict]) -> tuple[float, float, float, float]:
    rows = [r for r in cal if r["structural"]]
    x1 = np.array([r["score"] for r in rows])
    x2 = 1.0 - np.array([r["ratio"] for r in rows])
    x3 = np.array([r.get("conflict", 0.0) for r in rows])
    y = np.array([r["correct"] for r in rows], float)

    def nll(c: np.ndarray) -> float:
        z = c[0] + c[1] * x1 + c[2] * x2 + c[3] * x3
        return float(np.sum(np.logaddexp(0, z) - y * z) + 1e-3 * np.sum(c**2))

    res = minimize(nll, np.array([-4.0, 10.0, 4.0, -10.0]), method="BFGS")
    return tuple(float(v) for v in res.x)  # type: ignore[return-value]


def reliability(rows: list[dict], coef, valid: np.ndarray, bins: int = 5) -> list[dict]:
    c0, c1, c2, c3 = coef
    s = np.array([r["score"] for r in rows])
    q = np.array([r["ratio"] for r in rows])
    c = np.array([r.get("conflict", 0.0) for r in rows])
    conf = 1 / (1 + np.exp(-(c0 + c1 * s + c2 * (1 - q) + c3 * c)))
    cor = np.array([r["correct"] for r in rows])
    st = np.array([r["structural"] for r in rows])
    out = []
    edges = np.linspace(0, 1, bins + 1)
    for lo, hi in itertools.pairwise(edges):
        m = st & (conf >= lo) & ((conf < hi) | (hi == 1.0))
        if m.any():
            out.append({"bin": f"{lo:.1f}-{hi:.1f}", "n": int(m.sum()), "mean_confidence": float(conf[m].mean()),
                        "fraction_correct": float(cor[m].mean())})
    return out


def lines_only(src: dict, pairs: list[dict], variant: tuple) -> tuple[dict, list[dict]]:
    """GraffMatch-lines (poles only) with its own thresholds: every simulated pair of both splits
    (positives and the simulated negatives) matched once with the decision open, the thresholds
    chosen on the calibration split (precision >= 99.5 % on every suite, no valid-and-wrong
    negative), reported on the test split. ``src``: the drives extracted with the pole-only
    front end (:func:`lines_sources`)."""
    sel = [p for p in pairs if p["ds"].startswith("sim") and p["ds2"].startswith("sim")]
    cfg = GraffMatchConfig(landmark_types=["line"], verification=VerificationConfig(
        min_overlap=0.0, max_rival_ratio=1.0, max_conflict=1.0, max_conflict_support_points=1.0,
        min_landmark_overlap=0.0, max_slide_ratio=1e9, lines_only=None))
    rows = run_pairs(src, sel, cfg)
    for r, c in zip(rows, free_space_conflicts(src, rows, variant), strict=True):
        r["conflict"] = float(c)
    return lines_only_report(rows), rows


def lines_sources(out: Path, poles: dict | None = None) -> dict[str, dict]:
    """The simulated drives with the pole-only front end (``LAYERED_POLES``: the geometric poles
    clustered per height layer, so trunks under crowns count), for the lines-only pass."""
    return load_sims(out, False, {**LAYERED_POLES, **(poles or {})})


def lines_only_report(rows: list[dict]) -> dict:
    """Thresholds on the calibration rows (the slide ratio too: for each of its values the
    other three are chosen; ties: the stricter slide ratio), metrics per suite on both splits."""
    cal = [r for r in rows if r["split"] == "cal"]
    groups = np.array([r["ds"] if r["ds"] == r["ds2"] else "cross" for r in cal])
    best = None
    for ms in [*np.round(np.arange(0.6, 1.001, 0.05), 3), None]:
        sub = [dict(r, structural=bool(r["structural"] and (ms is None or r.get("slide", 0.0) <= ms))) for r in cal]
        mo, mr, mc, m = choose_thresholds(sub, groups=groups, max_neg_fpr=0.0, loose_conflict=False)
        key = (m.get("recall", 0.0), -(ms or 9.0))
        if best is None or key > best[0]:
            best = (key, mo, mr, mc, None if ms is None else float(ms))
    _, mo, mr, mc, ms = best  # type: ignore[misc]
    out: dict = {"thresholds": {"min_overlap": mo, "max_rival_ratio": mr, "max_conflict": mc,
                                "max_slide_ratio": ms}, "calibration": {}, "test": {}}
    print(f"\nlines only: chosen on the calibration split ({len(cal)} pairs): min_overlap={mo}, "
          f"max_rival_ratio={mr}, max_conflict={mc}, max_slide_ratio={ms}")
    for split in ("cal", "test"):
        sub = [r for r in rows if r["split"] == split]
        v = decide(sub, mo, mr, mc, ms)
        label = "calibration" if split == "cal" else "test"
        print(f"{'lines only (' + label + ')':<30}{'pairs':>6}{'pos':>5}{'neg':>5}{'valid':>6}{'prec':>7}"
              f"{'recall':>7}{'oracle':>7}{'FP neg':>8}")
        names = [r["ds"] if r["ds"] == r["ds2"] else f"{r['ds']} x {r['ds2']}" for r in sub]
        for name in [*sorted(set(names)), "ALL"]:
            idx = [k for k, n in enumerate(names) if name in (n, "ALL")]
            m = metrics([sub[k] for k in idx], v[idx])
            out[label][name] = m
            print(f"{name + ' lines':<30}{m['pairs']:>6}{m['positives']:>5}{m['negatives']:>5}{m['valid']:>6}"
                  f"{m['precision']:>7.3f}{m['recall']:>7.3f}{m['oracle_recall']:>7.3f}{m['valid_negatives']:>8}")
    return out


def fallback(rows_s: list[dict], th_s: tuple, rows_c: list[dict], th_c: tuple) -> tuple[list[dict], np.ndarray]:
    """``ScanMatcher``'s ``evidence='support_then_scans'``: the support points' answer when it is
    valid at ``th_s``, else the raw scans' at ``th_c``: (answered rows, valid)."""
    vs, vc = decide(rows_s, *th_s), decide(rows_c, *th_c)
    a_s, a_c = answered(rows_s, *th_s), answered(rows_c, *th_c)
    return [x if ok else y for x, y, ok in zip(a_s, a_c, vs, strict=True)], vs | vc


def print_table(title: str, rows: list[dict], answers: list[dict], valid: np.ndarray, out: dict) -> None:
    """Metrics per dataset (pair of datasets for negatives) and over all, printed and kept in ``out``."""
    print(f"\n{title:<30}{'pairs':>6}{'pos':>5}{'neg':>5}{'valid':>6}{'prec':>7}{'recall':>7}{'oracle':>7}{'FP neg':>8}")
    for ds, ds2 in [*sorted({(r["ds"], r["ds2"]) for r in rows}), ("ALL", "ALL")]:
        idx = [k for k, r in enumerate(rows) if ds == "ALL" or (r["ds"] == ds and r["ds2"] == ds2)]
        m = metrics([answers[k] for k in idx], valid[idx])
        name = ds if ds == ds2 else f"{ds} x {ds2}"
        out[name] = m
        print(f"{name:<30}{m['pairs']:>6}{m['positives']:>5}{m['negatives']:>5}{m['valid']:>6}"
              f"{m['precision']:>7.3f}{m['recall']:>7.3f}{m['oracle_recall']:>7.3f}{m['valid_negatives']:>8}")


def main_scans(a) -> None:
    """``--evidence scans``: every pair (positives and negatives, both passes) matched twice with
    every threshold open, on the support points and through the raw-scan evidence
    (``scan_evidence_of``). Thresholds of the raw-scan evidence chosen on the calibration split by
    :func:`choose_thresholds` (the same rule as the support points'), for two uses: *scans*
    (instead of the support points) and *support_then_scans* (the support points' answer at the
    configured thresholds when valid, else the scans'; ``ScanMatcherConfig.evidence``); the
    free-space image is the configured one (recorded by the matcher per pair). Reported on the
    test split next to the support points' own decision at the configured thresholds."""
    global EVIDENCE
    out = Path(a.out)
    t0 = time.perf_counter()
    src = load_sources(out, not a.no_sim, False, json.loads(a.poles) if a.poles else None)
    print(f"landmarks and scan clouds ready in {time.perf_counter() - t0:.0f} s: "
          + ", ".join(f"{k} {len(v['lms'])}" for k, v in src.items()), flush=True)
    pairs = make_pairs(src, a.max_per, a.cross_per)
    rows_c = run_both(src, pairs)  # EVIDENCE == "scans"
    EVIDENCE = "support"
    print("  support points:", flush=True)
    rows_s = run_both(src, pairs)
    EVIDENCE = "scans"
    base = VerificationConfig()
    th_s = (base.min_overlap, base.max_rival_ratio, base.max_conflict)
    cal_c = [r for r in rows_c if r["split"] == "cal"]
    cal_s = [r for r in rows_s if r["split"] == "cal"]
    groups = np.array([r["ds"] if r["ds"] == r["ds2"] else "cross" for r in cal_c])
    report: dict = {"evidence": "scans", "scan_voxel": base.scan_voxel, "scan_max_points": base.scan_max_points,
                    "support_thresholds": dict(zip(("min_overlap", "max_rival_ratio", "max_conflict"), th_s,
                                                   strict=True)),
                    "calibration": {}, "test": {}}
    th_alone = choose_thresholds(cal_c, groups=groups)[:3]
    prior = (decide(cal_s, *th_s), np.array([r["correct"] for r in answered(cal_s, *th_s)], bool))
    th_fb = choose_thresholds(cal_c, groups=groups, prior=prior)[:3]
    # the fallback's confidence: fitted on the calibration pairs it decides (support invalid)
    coef_fb = fit_confidence([r for r, p in zip(answered(cal_c, *th_fb), prior[0], strict=True) if not p])
    coef_alone = fit_confidence(answered(cal_c, *th_alone))
    for name, th, coef in (("scans", th_alone, coef_alone), ("support_then_scans", th_fb, coef_fb)):
        report[f"thresholds_{name}"] = {"min_overlap": th[0], "max_rival_ratio": th[1], "max_conflict": th[2],
                                        "confidence_coef": coef}
        print(f"raw-scan evidence (voxel {base.scan_voxel} m, <= {base.scan_max_points} points), {name}: chosen on "
              f"the calibration split ({len(cal_c)} pairs): min_overlap={th[0]}, max_rival_ratio={th[1]}, "
              f"max_conflict={th[2]}; confidence coef={tuple(round(c, 3) for c in coef)}")
    for split in ("cal", "test"):
        rs = [r for r in rows_s if r["split"] == split]
        rc = [r for r in rows_c if r["split"] == split]
        label = "calibration" if split == "cal" else "test"
        for name, (ans, v) in {"support": (answered(rs, *th_s), decide(rs, *th_s)),
                               "scans": (answered(rc, *th_alone), decide(rc, *th_alone)),
                               "support_then_scans": fallback(rs, th_s, rc, th_fb)}.items():
            print_table(f"{label}: {name}", rc, ans, v, report[label].setdefault(name, {}))
    test_c = [r for r in rows_c if r["split"] == "test"]
    first_only = [{k: v for k, v in r.items() if k != "wide"} for r in test_c]
    report["test_scans_variants"] = {
        "support-point thresholds": outcome(test_c, *th_s),
        "without free space": outcome(test_c, th_alone[0], th_alone[1], 1.0),
        "first pass only": outcome(first_only, *th_alone)}
    ta = answered(test_c, *th_alone)
    st = np.array([r["structural"] for r in ta])
    report["test_auc_overlap_scans"] = auc(np.array([r["score"] for r in ta])[st],
                                           np.array([r["correct"] for r in ta], bool)[st])
    for key, rows in (("scans", rows_c), ("support", rows_s)):
        t = np.array([r["t"] for r in rows if r.get("t")])
        report[f"match_ms_first_pass_{key}"] = {"median": float(np.median(t) * 1e3),
                                                "p95": float(np.percentile(t, 95) * 1e3)}
    print(f"\nmatch() first pass: scans median {report['match_ms_first_pass_scans']['median']:.1f} ms, support "
          f"median {report['match_ms_first_pass_support']['median']:.1f} ms (niced, shared host)")
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({**report, "rows_scans": rows_c, "rows_support": rows_s}, indent=1,
                                           default=float))
        print(f"wrote {a.json}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="/tmp/gm-verify")
    ap.add_argument("--no-sim", action="store_true", help="real data only (no simulated drives)")
    ap.add_argument("--max-per", type=int, default=120, help="positives per dataset and split")
    ap.add_argument("--cross-per", type=int, default=180,
                    help="negatives per pair of datasets (and per dataset, > 60 m apart), half of them test")
    ap.add_argument("--raw-drives", action="store_true",
                    help="also report the simulated drives' test pairs on their raw (not de-skewed) scans")
    ap.add_argument("--json", default=None)
    ap.add_argument("--poles", default=None,
                    help="JSON overrides of every extractor's pole settings (front-end experiments)")
    ap.add_argument("--lines-only", action="store_true",
                    help="only the lines-only pass (rows to OUT/lines_only_rows.json; --json is not written)")
    ap.add_argument("--evidence", choices=("support", "scans"), default="support",
                    help="scans: verify every pair on the scans' non-ground voxel clouds (ScanMatcher's "
                         "evidence='scans') and choose its thresholds; the free-space image is the "
                         "configured one, and the lines-only, raw-drive and support-image passes are skipped")
    a = ap.parse_args()
    global EVIDENCE
    EVIDENCE = a.evidence
    if EVIDENCE == "scans":
        main_scans(a)
        return
    out = Path(a.out)
    t0 = time.perf_counter()
    poles = json.loads(a.poles) if a.poles else None
    src = load_sources(out, not a.no_sim, a.raw_drives, poles)
    print(f"landmarks ready in {time.perf_counter() - t0:.0f} s: "
          + ", ".join(f"{k} {len(v['lms'])}" for k, v in src.items()), flush=True)
    pairs = make_pairs(src, a.max_per, a.cross_per)
    if a.lines_only:  # the lines-only pass alone, at the configured free-space range image
        base = VerificationConfig()
        variant = (base.free_space_az_deg, base.free_space_el_deg, base.free_space_neighbours,
                   base.free_space_margin, base.free_space_margin_rel, base.free_space_scan_neighbours)
        _, lines_rows = lines_only(lines_sources(out, poles), pairs, variant)
        (out / "lines_only_rows.json").write_text(json.dumps(lines_rows, default=float))
        print(f"wrote {out / 'lines_only_rows.json'}")
        return
    rows = run_both(src, pairs)
    cal = [r for r in rows if r["split"] == "cal"]
    test = [r for r in rows if r["split"] == "test"]
    # precision >= 99.5 % in each recording's calibration pairs (the targets are per suite; cross-dataset
    # negatives form one group, in which any valid result is wrong), as the lines-only pass chooses
    groups = np.array([r["ds"] if r["ds"] == r["ds2"] else "cross" for r in cal])
    is_cal = np.array([r["split"] == "cal" for r in rows])
    variants = []
    for variant in FREE_SPACE_VARIANTS:  # the range image, chosen on the calibration split too
        c_all = free_space_conflicts(src, rows, variant)
        w_all = free_space_conflicts(src, [r["wide"] for r in rows], variant)
        mo, mr, mc, cal_m = choose_thresholds(cal, c_all[is_cal], groups, wide_conflicts=w_all[is_cal])
        variants.append({"variant": variant, "min_overlap": mo, "max_rival_ratio": mr, "max_conflict": mc,
                         "calibration_recall": cal_m.get("recall", 0.0), "conflicts": c_all, "wide_conflicts": w_all})
        print(f"  free space {variant}: calibration recall {cal_m.get('recall', 0.0):.3f} at "
              f"min_overlap={mo}, max_rival_ratio={mr}, max_conflict={mc}", flush=True)
    chosen = max(variants, key=lambda v: (v["calibration_recall"], -FREE_SPACE_VARIANTS.index(v["variant"])))
    for r, c, cw in zip(rows, chosen["conflicts"], chosen["wide_conflicts"], strict=True):
        r["conflict"] = float(c)
        r["wide"]["conflict"] = float(cw)
    mo, mr, mc, cal_m = choose_thresholds(cal, groups=groups)
    coef = fit_confidence(answered(cal, mo, mr, mc))
    print(f"free-space variant chosen on the calibration split: {chosen['variant']}")
    print(f"\nchosen on the calibration split ({len(cal)} pairs): min_overlap={mo}, max_rival_ratio={mr}, "
          f"max_conflict={mc}; confidence coef={tuple(round(c, 3) for c in coef)}")
    report: dict = {"thresholds": {"min_overlap": mo, "max_rival_ratio": mr, "max_conflict": mc},
                    "free_space_variant": dict(zip(("az_deg", "el_deg", "neighbours", "margin", "margin_rel",
                                                    "scan_neighbours"),
                                                   chosen["variant"], strict=True)),
                    "free_space_variants": [{k: v for k, v in d.items() if k not in ("conflicts", "wide_conflicts")}
                                            for d in variants],
                    "confidence_coef": coef, "calibration": cal_m, "test": {}, "test_by_dataset": {}}
    base = VerificationConfig()
    first_only = [{k: v for k, v in r.items() if k != "wide"} for r in test]
    for label, (rs, th) in {"chosen": (test, (mo, mr, mc)),
                            "defaults": (test, (base.min_overlap, base.max_rival_ratio, base.max_conflict)),
                            "without free space": (test, (mo, mr, 1.0)),
                            "first pass only": (first_only, (mo, mr, mc))}.items():
        report["test"][label] = outcome(rs, *th)
    v = decide(test, mo, mr, mc)
    test_answer = answered(test, mo, mr, mc)
    print(f"\n{'test split':<30}{'pairs':>6}{'pos':>5}{'neg':>5}{'valid':>6}{'prec':>7}{'recall':>7}"
          f"{'oracle':>7}{'FP neg':>8}")
    keys = sorted({(r["ds"], r["ds2"]) for r in test})
    for ds, ds2 in keys:
        idx = [k for k, r in enumerate(test) if r["ds"] == ds and r["ds2"] == ds2]
        m = metrics([test_answer[k] for k in idx], v[idx])
        name = ds if ds == ds2 else f"{ds} x {ds2}"
        report["test_by_dataset"][name] = m
        print(f"{name:<30}{m['pairs']:>6}{m['positives']:>5}{m['negatives']:>5}{m['valid']:>6}"
              f"{m['precision']:>7.3f}{m['recall']:>7.3f}{m['oracle_recall']:>7.3f}{m['valid_negatives']:>8}")
    m = report["test"]["chosen"]
    print(f"{'ALL (test)':<30}{m['pairs']:>6}{m['positives']:>5}{m['negatives']:>5}{m['valid']:>6}"
          f"{m['precision']:>7.3f}{m['recall']:>7.3f}{m['oracle_recall']:>7.3f}{m['valid_negatives']:>8}")
    # sets without the whole scan's image (e.g. older landmark files) get the support points'
    # image, sparser: its own max_conflict, chosen on the calibration split at the same overlap and
    # rival thresholds, reported on the test split
    c_sup = free_space_conflicts(src, rows, chosen["variant"], use_scan_ranges=False)
    w_sup = free_space_conflicts(src, [r["wide"] for r in rows], chosen["variant"], use_scan_ranges=False)
    sup = [dict(r, conflict=float(c), wide=dict(r["wide"], conflict=float(cw)))
           for r, c, cw in zip(rows, c_sup, w_sup, strict=True)]
    mc_sup = choose_support_conflict([r for r in sup if r["split"] == "cal"], mo, mr, groups=groups)
    report["thresholds"]["max_conflict_support_points"] = mc_sup
    fallback = [r for r in sup if r["split"] == "test"]
    report["test"]["support-point image"] = outcome(fallback, mo, mr, mc_sup)
    print(f"support-point image (sets without scan_ranges): max_conflict={mc_sup} chosen on the calibration split")
    for label in ("defaults", "without free space", "first pass only", "support-point image"):
        m = report["test"][label]
        print(f"{'ALL (test), ' + label:<30}{m['pairs']:>6}{m['positives']:>5}{m['negatives']:>5}{m['valid']:>6}"
              f"{m['precision']:>7.3f}{m['recall']:>7.3f}{m['oracle_recall']:>7.3f}{m['valid_negatives']:>8}")
    if a.raw_drives:  # the same test pairs without de-skewing, at the thresholds chosen above
        raw = run_both(src, raw_drive_pairs(pairs))
        for r, c, cw in zip(raw, free_space_conflicts(src, raw, chosen["variant"]),
                            free_space_conflicts(src, [r["wide"] for r in raw], chosen["variant"]), strict=True):
            r["conflict"] = float(c)
            r["wide"]["conflict"] = float(cw)
        vr = decide(raw, mo, mr, mc)
        raw_answer = answered(raw, mo, mr, mc)
        report["raw_drives_test"] = {}
        for name in sorted({r["ds"] for r in raw}):
            idx = [k for k, r in enumerate(raw) if r["ds"] == name]
            m = report["raw_drives_test"][name] = metrics([raw_answer[k] for k in idx], vr[idx])
            print(f"{name:<30}{m['pairs']:>6}{m['positives']:>5}{m['negatives']:>5}{m['valid']:>6}"
                  f"{m['precision']:>7.3f}{m['recall']:>7.3f}{m['oracle_recall']:>7.3f}{m['valid_negatives']:>8}")
        rows = rows + raw
    if a.json:  # the full matcher's rows first: the lines-only pass below takes a while
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({**report, "rows": rows}, indent=1, default=float))
    lines, lines_rows = lines_only(lines_sources(out, poles), pairs, chosen["variant"])
    report["lines_only_thresholds"] = lines["thresholds"]
    report["lines_only_calibration"] = lines["calibration"]
    report["lines_only_test"] = lines["test"]
    st = np.array([r["structural"] for r in test_answer])
    lab = np.array([r["correct"] for r in test_answer])
    sc = np.array([r["score"] for r in test_answer])
    report["test_auc_overlap"] = auc(sc[st], lab[st])
    court = np.array([r["ds"] == "courtyard" and r["ds2"] == "courtyard" for r in test])
    report["test_auc_overlap_courtyard"] = auc(sc[st & court], lab[st & court])
    report["reliability_test"] = reliability(test_answer, coef, v)
    times = np.array([r["t"] + r["wide"].get("t", 0.0) * (not ok) for r, ok in
                      zip(rows, decide([{k: x for k, x in r.items() if k != "wide"} for r in rows], mo, mr, mc),
                          strict=True) if r.get("t")])
    report["match_ms"] = {"median": float(np.median(times) * 1e3), "p95": float(np.percentile(times, 95) * 1e3)}
    print(f"\nAUC of overlap (correct vs wrong, structurally valid, test): {report['test_auc_overlap']:.3f}"
          f" (courtyard {report['test_auc_overlap_courtyard']:.3f})")
    print("reliability (test):", report["reliability_test"])
    print(f"match() with verification: median {report['match_ms']['median']:.1f} ms, "
          f"p95 {report['match_ms']['p95']:.1f} ms over {len(times)} pairs")
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        slim = [{k: v for k, v in r.items() if k != "T"} for r in lines_rows]  # conflicts already computed
        Path(a.json).write_text(json.dumps({**report, "rows": rows, "lines_only_rows": slim}, indent=1,
                                           default=float))
        print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
