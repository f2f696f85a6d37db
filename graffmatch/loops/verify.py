"""Verification of a loop candidate: match the two landmark maps, then check the answer.

The matcher's ``valid`` says the registration is well-posed; a loop edge that a pose graph will
trust needs more, so every candidate is also scored by *landmark agreement*: after moving the
query's landmarks into the candidate's frame with the estimate, the fraction of them that lie
on a landmark of the same type there (direction within ``agree_deg``, axis/plane offset within
``agree_m``, plane anchors within ``plane_anchor_m`` in the plane). When the matcher reports its
own ``confidence`` (the verified matcher), that is combined with it. A pair of two landmark-poor
scans is verified again on their stored scan clouds (:func:`scan_pass`). Which candidates of a
query get here, in which order, is :mod:`.plan`'s.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from graffmatch.errors import GraffMatchError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.loops.verification_config import VerificationConfig
from graffmatch.matcher import GraffMatcher
from graffmatch.pipeline import ScanMatcher
from graffmatch.verification.evidence import scan_cloud
from graffmatch.verification.free_space import cell_minimum_ranges
from graffmatch.verification.point_hypotheses import prior_contrast
from graffmatch.verification.verify import scan_evidence


@dataclass
class LoopClosure:
    """A verified loop: ``T_match_query`` maps query-frame points into the match's frame."""

    query: int
    match: int
    T_match_query: NDArray[np.float64]
    confidence: float
    overlap: float
    n_associations: int
    n_agreeing: int
    retrieval_rank: int
    retrieval_distance: float
    valid: bool
    info: dict = field(default_factory=dict)

    def __repr__(self) -> str:
        t = self.T_match_query[:3, 3]
        yaw = np.degrees(np.arctan2(self.T_match_query[1, 0], self.T_match_query[0, 0]))
        return (
            f"LoopClosure(query={self.query}, match={self.match}, confidence={self.confidence:.2f}, "
            f"overlap={self.overlap:.2f}, associations={self.n_associations}, "
            f"t=[{t[0]:.2f}, {t[1]:.2f}, {t[2]:.2f}] m, yaw={yaw:.1f} deg)"
        )


def landmark_agreement(
    source: LandmarkSet, target: LandmarkSet, T_target_source: NDArray, config: VerificationConfig
) -> tuple[int, float]:
    """(agreeing source landmarks, their fraction of min(n_source, n_target)) after T."""
    if len(source) == 0 or len(target) == 0:
        return 0, 0.0
    agree = int(np.count_nonzero(agreeing_mask(source, target, T_target_source, config)))
    return agree, agree / min(len(source), len(target))


def agreeing_mask(
    source: LandmarkSet, target: LandmarkSet, T_target_source: NDArray, config: VerificationConfig
) -> NDArray[np.bool_]:
    """Which source landmarks, moved by T, lie on a same-type landmark of ``target`` (the gates of
    :func:`landmark_agreement`; also what makes two landmarks of a local map one)."""
    out = np.zeros(len(source), bool)
    if len(source) == 0 or len(target) == 0:
        return out
    # only anchors and directions move (R d is the moved line direction / plane normal): no
    # transformed LandmarkSet (its bases, attributes and checks) is needed for the gates
    T = np.asarray(T_target_source, float)
    R, t = T[:3, :3], T[:3, 3]
    anchors_s = source.anchors @ R.T + t
    ds, dt = source.directions @ R.T, target.directions
    cos_gate = np.cos(np.radians(config.agree_deg))
    for kind in (LandmarkType.LINE, LandmarkType.PLANE, LandmarkType.POINT):
        i = np.flatnonzero(source.types == kind)
        j = np.flatnonzero(target.types == kind)
        if i.size == 0 or j.size == 0:
            continue
        diff = anchors_s[i][:, None, :] - target.anchors[j][None, :, :]  # (a, b, 3)
        if kind == LandmarkType.POINT:
            ok = np.linalg.norm(diff, axis=2) < config.agree_m
        else:
            cosang = np.abs(ds[i] @ dt[j].T)
            n = dt[j][None, :, :]
            along = np.einsum("abk,abk->ab", diff, np.broadcast_to(n, diff.shape))
            if kind == LandmarkType.LINE:  # perpendicular distance to the target axis
                off = np.linalg.norm(diff - along[..., None] * n, axis=2)
                ok = (cosang > cos_gate) & (off < config.agree_m)
            else:  # plane offset along the normal, anchors not too far apart in the plane
                inplane = np.linalg.norm(diff - along[..., None] * n, axis=2)
                ok = (cosang > cos_gate) & (np.abs(along) < config.agree_m) & (
                    inplane < config.plane_anchor_m
                )
        out[i] = ok.any(axis=1)
    return out


def required_agreeing(matcher_confidence: float | None, config: VerificationConfig, on_points: bool = False) -> int:
    """Fewest agreeing landmarks for a non-zero confidence: ``min_agreeing``, or the smaller
    ``few_landmarks_min_agreeing`` when the verified matcher's own evidence is strong (a
    landmark-poor scan cannot show six agreeing landmarks however right its pose is), or
    ``points_min_agreeing`` when the matcher verified the pair on points (``on_points``)."""
    need = config.min_agreeing
    tau = config.few_landmarks_matcher_confidence
    if tau is not None and matcher_confidence is not None and matcher_confidence >= tau:
        need = min(need, config.few_landmarks_min_agreeing)
    if on_points:
        need = min(need, config.points_min_agreeing)
    return need


def loop_confidence(
    matcher_valid: bool,
    matcher_confidence: float | None,
    n_agreeing: int,
    agreement: float,
    distance_m: float,
    config: VerificationConfig,
    on_points: bool = False,
) -> float:
    """The confidence of a verified candidate (0: not a loop), from the matcher's verdict, the
    landmark agreement and the estimated sensor distance (``on_points``: both scans carry
    evidence points). One rule for ``graffmatch loops``, :class:`LoopDetector` and the benchmark
    (and its calibration replay)."""
    if not matcher_valid or n_agreeing < required_agreeing(matcher_confidence, config, on_points):
        return 0.0
    if config.max_translation_m is not None and distance_m > config.max_translation_m - config.place_margin_m:
        return 0.0
    conf = float(agreement) if matcher_confidence is None else float(np.sqrt(agreement * float(matcher_confidence)))
    return float(np.clip(conf, 0.0, 1.0))


def scans_loop_confidence(
    scan_valid: bool, scan_confidence: float | None, n_agreeing: int, distance_m: float, config: VerificationConfig,
    from_points: bool = False,
) -> float:
    """The confidence of a pair verified again on the two scan clouds (0: not a loop): the raw-scan
    verdict's own confidence when it is valid, reaches ``scans_min_confidence``, has
    ``scans_min_agreeing`` agreeing landmarks and lies inside the place radius less the margin.
    ``from_points``: the verdict's winner came from the points (``scans_points_min_agreeing``).
    One rule for ``graffmatch loops``, :class:`LoopDetector`, the benchmark and the calibration."""
    if not scan_valid or scan_confidence is None or scan_confidence < config.scans_min_confidence:
        return 0.0
    if n_agreeing < (config.scans_points_min_agreeing if from_points else config.scans_min_agreeing):
        return 0.0
    if config.max_translation_m is not None and distance_m > config.max_translation_m - config.place_margin_m:
        return 0.0
    return float(np.clip(scan_confidence, 0.0, 1.0))


def _verification_config(matcher: GraffMatcher | ScanMatcher):
    """The verified matcher's own verification settings (scan_voxel, scan_max_points, ...)."""
    cfg = matcher.config
    return cfg.matcher.verification if isinstance(matcher, ScanMatcher) else cfg.verification


def _scan_pass_matcher(matcher: GraffMatcher | ScanMatcher, max_conflict: float | None) -> GraffMatcher | ScanMatcher:
    """The matcher the scan pass decides with: ``matcher`` itself, or with ``max_conflict`` as its raw-scan
    free-space bar (a shallow configuration copy, ~10 us: the scan pass costs ~25 ms)."""
    if max_conflict is None:
        return matcher
    gcfg = matcher.config.matcher if isinstance(matcher, ScanMatcher) else matcher.config
    v = gcfg.verification
    update = ({"scans": v.scans.model_copy(update={"max_conflict": float(max_conflict)})} if v.scans is not None
              else {"max_conflict": float(max_conflict)})
    return GraffMatcher(gcfg.model_copy(update={"verification": v.model_copy(update=update)}))


def _with_scan_ranges(ls: LandmarkSet, scan: NDArray) -> LandmarkSet:
    """``ls`` (same arrays) carrying the range image of its scan cloud as ``scan_ranges``.

    Why: free space from the support points alone is a sparse image in which every surface the
    extractor did not make a landmark (a parked car, a tree) looks transparent; a right pose then
    puts the other scan's cloud "in free space" (20-30 % conflicts on right pairs of a calibration
    drive, docs/loops.md session 15). The scan cloud's own nearest return per cell is the
    whole-scan image raw-scan evidence was calibrated with (ground cells unknown: no free space
    claimed there). Only the scan pass sees it; the landmark pass keeps its calibrated image."""
    if ls.sensor_pose is None:
        return ls
    return LandmarkSet(ls.types, ls.bases, ls.anchors, ls.attributes, ls.points, ls.point_offsets, validate=False,
                       sensor_pose=ls.sensor_pose, scan_ranges=cell_minimum_ranges(np.asarray(scan, float)))


def _scored(res, query: LandmarkSet, candidate: LandmarkSet, config: VerificationConfig
            ) -> tuple[float | None, NDArray | None, int, float]:
    """A match result's confidence (None if it has none), its transform (None if none) and the
    landmarks that agree under it (count, overlap): what both passes record of a verdict."""
    mconf = getattr(res, "confidence", None)
    if res.T_target_source is None:
        return (None if mconf is None else float(mconf)), None, 0, 0.0
    T = np.asarray(res.T_target_source, float)
    n_agree, overlap = landmark_agreement(query, candidate, T, config)
    return (None if mconf is None else float(mconf)), T, n_agree, float(overlap)


def scan_pass(
    query: LandmarkSet,
    candidate: LandmarkSet,
    query_scan: NDArray,
    candidate_scan: NDArray,
    matcher: GraffMatcher | ScanMatcher,
    config: VerificationConfig,
    starts: tuple[NDArray, ...] = (),
) -> dict:
    """Match ``query`` to ``candidate`` again, verified on their stored scan clouds (the raw-scan
    evidence of ``ScanMatcher(evidence='support_then_scans')``: the same ``scan_evidence`` and
    ``match(..., evidence=)`` path, at ``VerificationConfig.scans``' thresholds).

    Returns scan_valid, scan_confidence, scan_T (or None), scan_n_agreeing, scan_overlap,
    scan_message, scan_origin (the winner's, 'points' for a point hypothesis), scan_seconds. Why: a landmark-poor pair cannot show the agreeing landmarks the
    landmark rule wants, however right its pose; the whole scans can show it is right. ``starts``
    (T_candidate_query, e.g. the odometry's) join the point hypotheses (``Evidence.starts``)."""
    t0 = time.perf_counter()
    out = {"scan_valid": False, "scan_confidence": None, "scan_T": None, "scan_n_agreeing": 0,
           "scan_overlap": 0.0, "scan_message": "", "scan_origin": None, "scan_conflict": None}
    query, candidate = _with_scan_ranges(query, query_scan), _with_scan_ranges(candidate, candidate_scan)
    ev = scan_evidence(query, candidate, np.asarray(query_scan, float), np.asarray(candidate_scan, float),
                       _verification_config(matcher))
    ev.view = False  # the range images are the non-ground clouds': their empty azimuths are no partial view
    ev.starts = tuple(np.asarray(T, np.float64) for T in starts)
    if ev.kind != "scans":
        out["scan_message"] = "too few scan points"
    else:
        try:
            res = _scan_pass_matcher(matcher, config.scans_max_conflict).match(query, candidate, evidence=ev)
        except GraffMatchError as exc:
            res = None
            out["scan_message"] = str(exc)
        if res is not None:
            out.update(scan_valid=bool(res.valid), scan_message=res.message, scan_origin=res.info.get("origin"))
            conflict = res.info.get("free_space_conflict")
            if conflict is not None:
                out["scan_conflict"] = float(max(conflict))
            mconf, T, n_agree, overlap = _scored(res, query, candidate, config)
            out["scan_confidence"] = mconf
            if T is not None:
                out.update(scan_T=T, scan_n_agreeing=n_agree, scan_overlap=overlap)
    out["scan_seconds"] = time.perf_counter() - t0
    return out


def verify_candidate(
    query: LandmarkSet,
    candidate: LandmarkSet,
    matcher: GraffMatcher | ScanMatcher,
    config: VerificationConfig,
    query_scan: NDArray | None = None,
    candidate_scan: NDArray | None = None,
) -> dict:
    """Match ``query`` (source) to ``candidate`` (target) and score the estimate.

    Returns a dict: T_match_query (or None), confidence, overlap, n_associations, n_agreeing,
    matcher_valid, matcher_confidence, on_points (both sets carry evidence points), message, seconds.
    With a place radius and ``place_check``, a candidate that only the radius refused also gets ``radius_confidence``
    (its confidence inside the radius) and ``radius_T`` (the pose it refers to), for :mod:`.place_check`.
    With both scan clouds given (landmark-poor scans, ``scan_cloud_below``) and the landmark rule
    not accepting, the pair is verified again on them (:func:`scan_pass`, its fields added); when
    :func:`scans_loop_confidence` accepts, T_match_query and confidence are the scan pass's
    (``on_scans`` True) and the landmark pass's transform stays in ``support_T``.
    """
    t0 = time.perf_counter()
    on_points = query.points is not None and candidate.points is not None
    out = {
        "on_points": on_points,
        "T_match_query": None,
        "confidence": 0.0,
        "overlap": 0.0,
        "n_associations": 0,
        "n_agreeing": 0,
        "matcher_valid": False,
        "matcher_confidence": None,
        "message": "",
    }
    try:
        res = matcher.match(query, candidate)
    except GraffMatchError as exc:  # too few landmarks or degenerate input: not a loop
        out["message"] = str(exc)
        out["seconds"] = time.perf_counter() - t0
        return out
    out["message"] = res.message
    out["matcher_valid"] = bool(res.valid)
    inl = res.info.get("registration_inliers")
    if inl is None:
        out["n_associations"] = len(res.associations)
    else:  # a boolean mask or an index array of the associations the registration kept
        inl = np.asarray(inl)
        out["n_associations"] = int(np.count_nonzero(inl) if inl.dtype == bool else inl.size)
    out["rms_offset"] = res.info.get("rms_offset")
    mconf, T, n_agree, overlap = _scored(res, query, candidate, config)
    out["matcher_confidence"] = mconf
    if T is not None:
        out.update(T_match_query=T, n_agreeing=n_agree, overlap=overlap)
        out["confidence"] = loop_confidence(
            bool(res.valid), out["matcher_confidence"], n_agree, overlap,
            float(np.linalg.norm(T[:3, 3])), config, on_points,
        )
        if config.place_check and config.max_translation_m is not None and out["confidence"] < config.min_confidence:
            inside = loop_confidence(bool(res.valid), mconf, n_agree, overlap, 0.0, config, on_points)
            if inside >= config.min_confidence:
                out.update(radius_confidence=inside, radius_T=T)
    if query_scan is not None and candidate_scan is not None and out["confidence"] < config.min_confidence:
        sp = scan_pass(query, candidate, query_scan, candidate_scan, matcher, config)
        out.update(sp)
        sT = sp["scan_T"]
        sconf = 0.0 if sT is None else scans_loop_confidence(
            sp["scan_valid"], sp["scan_confidence"], sp["scan_n_agreeing"], float(np.linalg.norm(sT[:3, 3])), config,
            sp["scan_origin"] == "points")
        if sconf >= config.min_confidence and sconf > out["confidence"]:
            out.update(support_T=out["T_match_query"], T_match_query=sT, confidence=sconf, on_scans=True)
        elif sT is not None and config.place_check and config.max_translation_m is not None:
            inside = scans_loop_confidence(sp["scan_valid"], sp["scan_confidence"], sp["scan_n_agreeing"], 0.0, config,
                                           sp["scan_origin"] == "points")
            if inside >= config.min_confidence and inside > out.get("radius_confidence", 0.0):
                out.update(radius_confidence=inside, radius_T=sT)
    out["seconds"] = time.perf_counter() - t0
    return out


def prior_contrast_of(query_scan: NDArray, candidate_scan: NDArray, query: LandmarkSet, candidate: LandmarkSet,
                      T_prior: NDArray, matcher: GraffMatcher | ScanMatcher) -> tuple[float, float]:
    """:func:`prior_contrast` of two stored scan clouds at the matcher's raw-scan evidence settings
    ((0, 0) when either leaves too few points)."""
    cfg = _verification_config(matcher)
    s = scan_cloud(np.asarray(query_scan, float), query, cfg.scan_voxel, cfg.scan_max_points)
    t = scan_cloud(np.asarray(candidate_scan, float), candidate, cfg.scan_voxel, cfg.scan_max_points)
    if s is None or t is None:
        return 0.0, 0.0
    return prior_contrast(s, t, cfg, T_prior)
