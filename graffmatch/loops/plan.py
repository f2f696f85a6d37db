"""Which retrieved candidates of one query are verified, in which order, within what budget.

:func:`verify_query` runs the cheap quick check (:mod:`.quickcheck`) on every retrieved candidate,
orders those that pass (:func:`verification_plan`), adds the quick-rejected pairs of two
landmark-poor scans that the first screen at the odometry's relative pose lets through
(:func:`screens_in`), and verifies them one by one (:func:`run_plan`, :func:`.verify.verify_candidate`)
until one is accepted or the budget is spent. The calibration replay (``bench/loops_calibration_points15b.py``)
runs the same plan on recorded verdicts, so what it chooses is what the detector does.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.loops.place_check import PlaceCloud, run_place_check
from graffmatch.loops.quickcheck import QuickCheckConfig, QuickIndex, quick_check_many
from graffmatch.loops.verify import VerificationConfig, prior_contrast_of, verify_candidate
from graffmatch.matcher import GraffMatcher
from graffmatch.pipeline import ScanMatcher


def quick_gate(score: int, fraction: float, translation_m: float, config: VerificationConfig) -> bool:
    """Whether a candidate with this quick-check result goes on to the verified matcher."""
    if fraction < config.quick_min_fraction:
        return False
    if (
        config.max_translation_m is not None
        and score >= config.quick_translation_min_inliers
        and translation_m > config.max_translation_m + config.quick_translation_margin_m
    ):
        return False
    return True


def verification_plan(
    recs: list[dict], config: VerificationConfig, has_scan: Callable[[int], bool],
    odometry_distance: Callable[[int], float | None],
) -> tuple[list[dict], list[dict]]:
    """(candidates passing the quick check in the order they are verified, quick-rejected cloud pairs
    that may follow): one rule for :func:`verify_query` and the calibration replay.

    Passing candidates: best quick score first, then retrieval rank (with ``quick_order_odometry`` the
    odometry-nearest, rank without odometry); with ``quick_order_radius``
    those whose quick estimate (``quick_translation_min_inliers`` or more inliers) lies beyond the
    place radius less the margin go last, the least beyond first. Quick-rejected pairs of two scans with clouds
    (``scans_skip_quick_check``): with ``scans_screen_min_ratio`` only those with odometry, nearest by
    the odometry first (a landmark-poor query has no quick score to rank by); else best quick score
    first; at most ``scans_skip_max``. ``has_scan(j)``: both the query and j keep scan clouds."""
    def tie(r: dict) -> float:
        d = odometry_distance(r["match"]) if config.quick_order_odometry else None
        return r["rank"] if d is None else d

    def key(r: dict) -> tuple:
        t = r.get("quick_translation_m", 0.0)
        beyond = bool(
            config.quick_order_radius and config.max_translation_m is not None
            and r["quick_score"] >= config.quick_translation_min_inliers
            and t > config.max_translation_m - config.place_margin_m)
        # beyond ones nearest first: the quick estimate is off by decimetres to metres (balm_courtyard:
        # 4.76 m quick, 4.66 m verified), so the least beyond is the likeliest to lie inside after all
        return (1, t, -r["quick_score"], r["rank"]) if beyond else (0, 0.0, -r["quick_score"], tie(r), r["rank"])

    order = sorted((r for r in recs if r["quick_pass"]), key=key)
    extra: list[dict] = []
    if config.scans_skip_quick_check:
        extra = [r for r in recs if not r["quick_pass"] and has_scan(r["match"])]
        for r in extra:
            r["quick_pass_scans"] = True
        if config.scans_screen_min_ratio is not None:
            dist = {r["match"]: odometry_distance(r["match"]) for r in extra}
            extra = sorted((r for r in extra if dist[r["match"]] is not None),
                           key=lambda r: (dist[r["match"]], r["rank"]))
        else:
            extra = sorted(extra, key=lambda r: (-r["quick_score"], r["rank"]))
        if config.scans_skip_max is not None:
            extra = extra[: config.scans_skip_max]
    return order, extra


def screens_in(contrast: tuple[float, float], config: VerificationConfig) -> bool:
    """Whether a quick-rejected cloud pair with this :func:`prior_contrast` goes on to the scan pass."""
    prior, turned = contrast
    return config.scans_screen_min_ratio is None or (prior > 0 and prior >= config.scans_screen_min_ratio * turned)


def run_plan(order: list[dict], extra: list[dict], config: VerificationConfig, verify: Callable[[dict], float],
             screen: Callable[[dict], bool] | None) -> None:
    """Verify ``order`` then ``extra`` (:func:`verification_plan`), at most ``max_verified``, stopping at
    the first accepted with ``stop_when_accepted``; with ``scans_screen_min_ratio`` an extra pair is
    verified only when ``screen`` lets it through (no screen: none). ``verify(rec)`` returns the
    confidence; one loop for :func:`verify_query` and the calibration replay."""
    extras = {id(r) for r in extra}
    n = 0
    for rec in order + extra:
        if n >= config.max_verified:
            break
        if id(rec) in extras and config.scans_screen_min_ratio is not None and (screen is None or not screen(rec)):
            continue
        n += 1
        if verify(rec) >= config.min_confidence and config.stop_when_accepted:
            break


def on_own_maps(a: LandmarkSet, b: LandmarkSet, own_of: Callable[[int], LandmarkSet] | None,
                config: VerificationConfig) -> bool:
    """Whether a pair whose maps (local where a scan has one) are ``a`` and ``b`` is screened and verified on the
    two scans' own maps instead: with ``local_map_on_points_only``, when a map lacks evidence points. Why: verified
    on landmarks alone, local maps accepted loops 3-8 m off along the real courtyard's walls (merged facade
    fragments each agree under a slid pose); verified on points, none (docs/loops.md, session 19)."""
    return own_of is not None and config.local_map_on_points_only and (a.points is None or b.points is None)


def pair_maps(query: int, match: int, landmarks_of: Callable[[int], LandmarkSet],
              own_of: Callable[[int], LandmarkSet] | None, config: VerificationConfig) -> tuple[LandmarkSet, LandmarkSet]:
    """The two maps a pair is quick-checked and verified on (:func:`on_own_maps`)."""
    a, b = landmarks_of(query), landmarks_of(match)
    if on_own_maps(a, b, own_of, config):
        return own_of(query), own_of(match)  # type: ignore[misc]
    return a, b


def verify_query(
    query: int,
    candidates: list[tuple[int, float]],
    landmarks_of: Callable[[int], LandmarkSet],
    quick_of: Callable[[int], QuickIndex] | None,
    matcher: GraffMatcher | ScanMatcher,
    config: VerificationConfig,
    quick_config: QuickCheckConfig | None = None,
    scan_of: Callable[[int], NDArray | None] | None = None,
    odometry_of: Callable[[int], NDArray | None] | None = None,
    own_of: Callable[[int], LandmarkSet] | None = None,
    own_quick_of: Callable[[int], QuickIndex] | None = None,
    place_cloud_of: Callable[[int], PlaceCloud | None] | None = None,
) -> list[dict]:
    """Pre-screen and verify the retrieved candidates of one query; one record a candidate.

    With ``config.quick_check`` all candidates get the quick BEV check in one compiled pass
    (:func:`quick_check_many`, a fraction of a millisecond a candidate) and only those passing
    :func:`quick_gate` are verified, best quick score first; with ``stop_when_accepted``
    verification stops at the first accepted candidate. Records keep the retrieval order
    (``rank``); skipped candidates have ``verified`` False and no ``T``; a record's ``seconds``
    holds its share of the batched quick check plus its verification. ``scan_of(i)``: scan i's stored
    scan cloud or None (landmark-poor scans keep one): a pair of two such scans is verified again
    on them when the landmark rule does not accept it (:func:`verify_candidate`), and with
    ``scans_skip_quick_check`` it is verified even when the quick check rejected it (after the
    passing candidates; :func:`verification_plan`). ``odometry_of(i)``: scan i's odometry pose (world
    <- scan, drift allowed) or None: with ``scans_screen_min_ratio`` the quick-rejected cloud pairs go
    through the first screen at the odometry's relative pose (:func:`screens_in`). ``own_of(i)``: scan i's own
    landmarks when ``landmarks_of`` gives local maps: with ``local_map_on_points_only`` a pair of which a map lacks
    evidence points is quick-checked (``own_quick_of``: the own maps' indices) and verified on the two own maps
    instead (:func:`pair_maps`), so the pre-screen reads the maps the verifier reads. ``place_cloud_of(i)``: scan i's
    :func:`.place_check.place_cloud` (None: unreadable): a query left without a loop because the place radius alone
    refused its verified candidates gets them re-measured on the scans (:func:`.place_check.run_place_check`).
    """
    recs: list[dict] = []
    for rank, (j, dist) in enumerate(candidates):
        recs.append({
            "match": int(j), "rank": rank, "retrieval_distance": float(dist), "T": None,
            "confidence": 0.0, "overlap": 0.0, "n_associations": 0, "n_agreeing": 0,
            "rms_offset": None, "seconds": 0.0, "verified": False, "quick_score": 0, "quick_pass": True,
        })
    if config.quick_check and quick_of is not None and recs:
        t0 = time.perf_counter()
        q_ls = landmarks_of(query)
        own = [on_own_maps(q_ls, landmarks_of(r["match"]), own_of, config) for r in recs]
        for fallback in (False, True):  # one compiled pass a kind of map (own maps: only with local maps)
            group = [r for r, o in zip(recs, own, strict=True) if o == fallback]
            if not group:
                continue
            index_of = (own_quick_of or quick_of) if fallback else quick_of
            qi = index_of(query)
            cis = [index_of(r["match"]) for r in group]
            scores, est = quick_check_many(qi, cis, quick_config)
            for rec, ci, score, e in zip(group, cis, scores.tolist(), est, strict=True):
                frac = score / max(1, min(qi.size, ci.size))
                rec.update(quick_score=score, quick_fraction=float(frac), quick_translation_m=float(np.hypot(e[1], e[2])))
                rec["quick_pass"] = quick_gate(score, frac, rec["quick_translation_m"], config)
        share = (time.perf_counter() - t0) / len(recs)
        for rec in recs:
            rec["seconds"] = share
    qscan = None if scan_of is None else scan_of(query)
    scan = {r["match"]: (None if qscan is None else scan_of(r["match"])) for r in recs}  # type: ignore[misc]
    qpose = None if odometry_of is None else odometry_of(query)
    T_odo = {}
    if qpose is not None:
        for r in recs:
            cpose = odometry_of(r["match"])  # type: ignore[misc]
            if cpose is not None:
                T_odo[r["match"]] = np.linalg.solve(np.asarray(cpose, float), np.asarray(qpose, float))
    order, extra = verification_plan(recs, config, lambda j: scan[j] is not None,
                                     lambda j: None if j not in T_odo else float(np.linalg.norm(T_odo[j][:3, 3])))

    def screen(rec: dict) -> bool:
        t0 = time.perf_counter()
        c = prior_contrast_of(qscan, scan[rec["match"]], *pair_maps(query, rec["match"], landmarks_of, own_of, config),
                              T_odo[rec["match"]], matcher)
        dt = time.perf_counter() - t0
        rec.update(screen_prior=c[0], screen_turned=c[1], screen_seconds=dt, seconds=rec["seconds"] + dt)
        return screens_in(c, config)

    def verify(rec: dict) -> float:
        v = verify_candidate(*pair_maps(query, rec["match"], landmarks_of, own_of, config), matcher, config,
                             qscan, scan[rec["match"]])
        T = v["T_match_query"]
        rec.update(
            T=None if T is None else np.asarray(T).ravel().tolist(), confidence=v["confidence"],
            overlap=v["overlap"], n_associations=v["n_associations"], n_agreeing=v["n_agreeing"],
            rms_offset=v.get("rms_offset"), seconds=rec["seconds"] + v["seconds"], verified=True,
            verify_seconds=v["seconds"], matcher_valid=v["matcher_valid"],
            matcher_confidence=v["matcher_confidence"], on_points=v["on_points"],
        )
        if "scan_valid" in v:
            rec.update({k: v[k] for k in ("scan_valid", "scan_confidence", "scan_n_agreeing", "scan_overlap",
                                          "scan_message", "scan_origin", "scan_seconds")})
            rec["scan_T"] = None if v["scan_T"] is None else np.asarray(v["scan_T"]).ravel().tolist()
        if "radius_T" in v:  # refused by the place radius alone (loops/place_check.py)
            rec.update(radius_confidence=v["radius_confidence"], radius_T=np.asarray(v["radius_T"]).ravel().tolist())
        if v.get("on_scans"):
            rec["on_scans"] = True
            rec["support_T"] = None if v["support_T"] is None else np.asarray(v["support_T"]).ravel().tolist()
        return v["confidence"]

    run_plan(order, extra, config, verify, screen if T_odo else None)
    if place_cloud_of is not None:
        run_place_check(query, recs, config, place_cloud_of)
    return recs
