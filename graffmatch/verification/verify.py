"""From one consistency graph to a verified answer: hypotheses -> batched registration ->
evidence -> decision. The matcher calls :func:`verify_graph` after the solver."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from graffmatch.association.clipper import ClipperConfig
from graffmatch.association.cliques import clique_objectives
from graffmatch.errors import DegenerateGeometryError
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.registration.closed_form import register_batch
from graffmatch.verification.config import VerificationConfig
from graffmatch.verification.decision import (
    Hypothesis,
    Verdict,
    confidence_of,
    decide,
    is_settled,
    low_confidence_problem,
    merge_hypotheses,
    transform_gap,
)
from graffmatch.verification.evidence import (
    SupportCloud,
    align_on_evidence,
    landmark_overlap,
    occupancy_overlap,
    point_overlap,
    point_overlaps,
    prepared_support,
    scan_cloud,
    score_on_points,
)
from graffmatch.verification.free_space import conflict_fraction
from graffmatch.verification.hypotheses import (
    Candidate,
    candidate_cliques,
    consistent_with,
    line_consensus,
    local_perturbations,
    pair_candidates,
    pair_transforms,
    reassociate,
    residuals,
    rival_cliques,
    translation_redundancy,
)
from graffmatch.verification.point_hypotheses import point_hypotheses
from graffmatch.verification.translation_vote import vote_translations
from graffmatch.verification.view import check_view, whole_views


@dataclass
class Evidence:
    """What hypotheses are scored against: support clouds of both scans, or none.

    ``kind`` says where the points come from ('support': the landmarks' support points;
    'scans': the raw scans' non-ground voxel clouds), so the decision uses the thresholds
    chosen for that evidence (``VerificationConfig.for_evidence``)."""

    source: SupportCloud | None
    target: SupportCloud | None
    kind: str = "support"
    #: whether the clouds' ``scan_ranges`` show what each sensor looked at (the extractor's
    #: whole-scan image, ground included), so their azimuth coverage is the scan's view
    #: (``view.check_view``); False for images of non-ground clouds (``loops.verify.scan_pass``),
    #: where an open road leaves whole azimuth sectors empty (coverage 0.53-0.62 on sim-openroad)
    view: bool = True
    #: transforms to also try when hypotheses come from the points (``point_hypotheses``), e.g. the
    #: odometry's relative pose of the two scans
    starts: tuple[NDArray[np.float64], ...] = ()

    @property
    def has_points(self) -> bool:
        return self.source is not None and self.target is not None


def evidence_for(source: LandmarkSet, target: LandmarkSet, cfg: VerificationConfig) -> Evidence:
    """Support clouds of both sets, from the per-scan cache (``evidence.evidence_cache``)."""
    return Evidence(prepared_support(source, cfg.voxel, cfg.max_points),
                    prepared_support(target, cfg.voxel, cfg.max_points))


def scan_evidence(source: LandmarkSet, target: LandmarkSet, source_points: NDArray, target_points: NDArray,
                  cfg: VerificationConfig) -> Evidence:
    """Evidence from both scans' non-ground points (``evidence.scan_cloud`` at ``scan_voxel`` /
    ``scan_max_points``); the support points' evidence when either scan leaves too few."""
    s = scan_cloud(source_points, source, cfg.scan_voxel, cfg.scan_max_points)
    t = scan_cloud(target_points, target, cfg.scan_voxel, cfg.scan_max_points)
    if s is None or t is None:
        return evidence_for(source, target, cfg)
    return Evidence(s, t, "scans")


def _register(
    source: LandmarkSet, target: LandmarkSet, assoc: NDArray[np.int64], W: sp.csr_matrix,
    cands: list[Candidate], kappa_max: float,
) -> list[Hypothesis]:
    """Register candidates (cliques of >= 2 associations) in one batch."""
    cands = [c for c in cands if len(c.vertices) >= 2]
    if not cands:
        return []
    verts = [c.vertices for c in cands]
    lengths = np.fromiter(map(len, verts), np.int64, len(verts))
    groups = np.repeat(np.arange(len(cands)), lengths)
    A = assoc[np.concatenate(verts)]
    try:
        b = register_batch(source, target, A, groups, None, kappa_max, len(cands), reference_degenerate=False)
    except DegenerateGeometryError:
        return []
    bounds = [0, *np.cumsum(lengths).tolist()]
    objectives = clique_objectives(W, verts).tolist()
    kappa, degenerate = b.kappa.tolist(), b.degenerate.tolist()
    Ts, off, ang = list(b.T_target_source), b.offset_residuals, b.angle_residuals_deg
    hyps = []
    for i, c in enumerate(cands):  # per-hypothesis arrays are views of the batch's
        lo, hi = bounds[i], bounds[i + 1]
        h = Hypothesis(Ts[i], A[lo:hi], c.origin, objectives[i], kappa[i], degenerate[i],
                       info={"vertices": c.vertices, "residuals": (off[lo:hi], ang[lo:hi])})
        if c.T_target_source is not None:  # the pole pair's own transform, first (it wins the
            # merge of equal cliques): with a wrong but consistent association in the clique, the
            # clique's least squares can land degrees and metres off where the pair itself was
            # right (sim-suburban / sim-downtown lines only, bench/verification.py)
            d = Hypothesis(np.asarray(c.T_target_source, np.float64), A[lo:hi], c.origin + "+pair",
                           objectives[i], kappa[i], degenerate[i])
            d.info["vertices"] = c.vertices
            ang, off = residuals(source, target, A[lo:hi], d.T_target_source)
            d.info["residuals"] = (off, ang)
            hyps.append(d)
        hyps.append(h)
    return hyps


def _gated(hyps: list[Hypothesis], gate: tuple[float, float], min_assoc: int) -> list[Candidate]:
    """Residual-gated variants: drop associations off by more than the gate (the clique may hold
    a few wrong ones). The ungated hypothesis stays a candidate, so the gate can never remove
    the constraints that fix the rotation without verification noticing."""
    if not hyps:
        return []
    res = [h.info["residuals"] for h in hyps]  # the masks of all hypotheses in one pass
    lengths = np.array([len(r[0]) for r in res], dtype=np.int64)
    keep = (np.concatenate([r[0] for r in res]) <= gate[0]) & (np.concatenate([r[1] for r in res]) <= gate[1])
    bounds = np.concatenate(([0], np.cumsum(lengths)))
    kept = np.bincount(np.repeat(np.arange(len(hyps)), lengths), weights=keep, minlength=len(hyps))
    out = []
    for i in np.flatnonzero((kept >= min_assoc) & (kept < lengths)).tolist():
        h = hyps[i]
        out.append(Candidate(h.info["vertices"][keep[bounds[i]:bounds[i + 1]]], h.origin + "+gate"))
    return out


def _trimmed(hyps: list[Hypothesis], source: LandmarkSet, target: LandmarkSet, associations: NDArray[np.int64],
             W: sp.csr_matrix, gate: tuple[float, float], min_assoc: int, kappa_max: float,
             rounds: int) -> list[Hypothesis]:
    """Iteratively trimmed variants: drop the association with the worst residual (offset over
    the gate's metres or angle over its degrees, whichever is larger), re-register, and repeat
    until every residual is within the gate or ``min_assoc`` remain (at most ``rounds`` drops);
    the last variant of each chain becomes a hypothesis. All chains advance together, one batched
    registration a round; chains that reach the same association set continue as one.

    A greedy clique grown from true associations usually picks up one or two wrong but
    consistent ones (a facade across the street, a pole one spacing along) that pull the least
    squares metres off and spread the residuals, so the one-shot gate (:func:`_gated`) keeps or
    drops the wrong set: on sim-downtown's calibration pairs the true associations registered
    right where every clique was 1-5 m off (bench/verification.py, docs/verification.md)."""
    res = [h.info["residuals"] for h in hyps]
    lengths = np.array([len(r[0]) for r in res], dtype=np.int64)
    if len(hyps) == 0 or lengths.sum() == 0:
        return []
    off = np.concatenate([r[0] for r in res])
    ang = np.concatenate([r[1] for r in res])
    verts = np.concatenate([h.info["vertices"] for h in hyps]).astype(np.int64)
    origin = np.arange(len(hyps))  # each chain's first hypothesis
    Ts = kappa = degenerate = None
    found: list[tuple[int, NDArray[np.int64], int, NDArray[np.float64], float, bool, tuple]] = []
    seen: set[bytes] = set()
    for r in range(rounds + 1):
        starts = np.r_[0, np.cumsum(lengths)[:-1]]
        gid = np.repeat(np.arange(len(lengths)), lengths)
        z = np.maximum(off / gate[0], ang / gate[1])
        worst = np.lexsort((-z, gid))[starts]  # each chain's largest residual (its first, on ties)
        go = (z[worst] > 1.0) & (lengths > min_assoc)
        if r > 0:  # chains at their end (within the gate, at min_assoc, or out of rounds)
            ends = np.flatnonzero(~go) if r < rounds else np.arange(len(lengths))
            for c in ends.tolist():
                lo, hi = starts[c], starts[c] + lengths[c]
                found.append((int(origin[c]), verts[lo:hi], c, Ts[c], float(kappa[c]), bool(degenerate[c]),
                              (off[lo:hi], ang[lo:hi])))
        if r == rounds or not go.any():
            break
        keep = go[gid]
        keep[worst] = False
        chains = np.flatnonzero(go)
        verts, lengths, origin = verts[keep], lengths[chains] - 1, origin[chains]
        bounds = np.r_[0, np.cumsum(lengths)]
        uniq = []  # one chain per association set
        for c in range(len(lengths)):
            key = np.sort(verts[bounds[c]:bounds[c + 1]]).tobytes()
            if key not in seen:
                seen.add(key)
                uniq.append(c)
        if not uniq:
            break
        if len(uniq) < len(lengths):
            sel = np.zeros(len(lengths), bool)
            sel[uniq] = True
            verts = verts[np.repeat(sel, lengths)]
            lengths, origin = lengths[sel], origin[sel]
        try:
            b = register_batch(source, target, associations[verts], np.repeat(np.arange(len(lengths)), lengths),
                               None, kappa_max, len(lengths), reference_degenerate=False)
        except DegenerateGeometryError:
            break
        Ts, kappa, degenerate = b.T_target_source, b.kappa, b.degenerate
        off, ang = b.offset_residuals, b.angle_residuals_deg
    if not found:
        return []
    objectives = clique_objectives(W, [f[1] for f in found]).tolist()
    out = []
    for (o, v, _, T, k, deg, res_), obj in zip(found, objectives, strict=True):
        h = Hypothesis(np.array(T), associations[v], hyps[o].origin + "+trim", obj, k, deg,
                       info={"vertices": v, "residuals": res_})
        out.append(h)
    return out


def _refine(best: Hypothesis, source: LandmarkSet, target: LandmarkSet, associations: NDArray[np.int64],
            kappa_max: float, gate: tuple[float, float], min_associations: int,
            ev: Evidence, cfg: VerificationConfig, min_score: float) -> None:
    """Re-associate under the winner's transform (all putative associations within the residual
    gate, one-to-one) and re-register from the landmarks: more correspondences, usually a more
    accurate rotation (plane normals) than the point alignment. The re-registration is kept when
    well-conditioned and close to the verified transform; with evidence points only when it
    explains at most ``refine_tolerance`` less of them; and never when its score (points, else
    landmarks: the decision's own score) is below ``min_score`` where the verified transform's
    was not, so a valid answer's transform explains what the decision requires. (Without points
    no tolerance: there the verified transform is itself a landmark registration, and on the
    loop benchmark's drives a 0.02 landmark tolerance lost loops.)

    A kept re-registration's score becomes ``best.score`` (the verified one goes to
    ``info["verified_overlap"]``), so the reported overlap is that of the returned transform;
    the decision's confidence, margin and runner-up stay computed on the verified score, which
    they are calibrated on."""
    A = reassociate(source, target, associations, best.T_target_source, gate[1], gate[0])
    if len(A) < max(min_associations, best.n_associations):
        return
    try:
        b = register_batch(source, target, A, None, None, kappa_max, 1)
    except DegenerateGeometryError:
        return
    if b.degenerate[0]:
        return
    T_new = b.T_target_source[0]
    rot, tr = transform_gap(best.T_target_source, T_new)
    if rot > 2 * gate[1] or tr > 2 * gate[0]:
        return
    best.info["clique_associations"] = best.n_associations
    best.associations = A
    counts: list = []
    if ev.has_points:
        parts = point_overlap(ev.source, ev.target, T_new, cfg.inlier_m)  # type: ignore[arg-type]
    else:
        parts = tuple(landmark_overlap(source, target, T_new, cfg.landmark_deg, cfg.landmark_m, counts).tolist())
    score = 0.5 * (parts[0] + parts[1])
    if ev.has_points and score < best.score - cfg.refine_tolerance:
        return  # the verified transform explains the evidence clearly better
    if score < min_score <= best.score:
        return  # the re-registration would return a pose that explains less than the decision requires
    best.info["verified_overlap"] = best.score
    best.T_target_source = T_new
    best.kappa = float(b.kappa[0])
    best.score_parts = (float(parts[0]), float(parts[1]))
    best.score = float(score)
    if counts:
        best.info["verified_landmarks_explained"] = best.info.get("landmarks_explained", 0)
        best.info["landmarks_explained"] = int(counts[0][0])


def _verified_score(best: Hypothesis) -> float:
    """The winner's score as the decision saw it (before :func:`_refine`): what confidence and
    the slide ratio are calibrated on."""
    return float(best.info.get("verified_overlap", best.score))


def _local_search(lead: Hypothesis, ev: Evidence, cfg: VerificationConfig) -> None:
    """Re-align the leader, longer (from 2 m correspondences down), from itself and from a grid
    of starts around it (one vectorised occupancy pass picks the ``local_search_top`` starts);
    keep the best re-alignment when it explains clearly more. The short alignment of a landmark
    registration that is 1-2 m off stops in a nearby local optimum: on the courtyard this turned
    near misses (about 1-2 m, 1-3 deg off) into right answers (bench/verification.py)."""
    src, tgt = ev.source, ev.target
    T0 = lead.T_target_source
    centre = T0[:3, :3] @ src.points.mean(axis=0) + T0[:3, 3]  # type: ignore[union-attr]
    Ts = local_perturbations(T0, centre, cfg.local_search_step_m, cfg.local_search_m, cfg.local_search_deg)
    occ = occupancy_overlap(src, tgt, Ts, cfg.inlier_m).mean(axis=1)  # type: ignore[arg-type]
    starts = [T0, *Ts[np.argsort(-occ, kind="stable")[: cfg.local_search_top]]]
    # the unshifted, unturned start is T0 bit for bit and usually among the best by occupancy:
    # a start equal to an earlier one takes that one's alignment (the same steps, the same T)
    first = [next(j for j in range(i + 1) if np.array_equal(starts[j], starts[i])) for i in range(len(starts))]
    uniq = sorted(set(first))
    done = {i: align_on_evidence(src, tgt, starts[i], cfg.local_search_distances)  # type: ignore[arg-type]
            for i in uniq}
    parts_u = point_overlaps(src, tgt, np.stack([done[i] for i in uniq]), cfg.inlier_m)  # type: ignore[arg-type]
    aligned = np.stack([done[f] for f in first])
    all_parts = parts_u[[uniq.index(f) for f in first]]
    best_score, best_T, best_parts = lead.score + cfg.local_search_gain, None, None
    for T, parts in zip(aligned, all_parts, strict=True):
        score = 0.5 * (parts[0] + parts[1])
        if score > best_score:
            best_score, best_T, best_parts = score, T, parts
    if best_T is not None:
        lead.info["T_before_local_search"] = T0
        lead.T_target_source = best_T
        lead.score_parts = (float(best_parts[0]), float(best_parts[1]))  # type: ignore[index]
        lead.score = float(best_score)


def _check_translation(verdict: Verdict, source: LandmarkSet, target: LandmarkSet,
                       associations: NDArray[np.int64], cfg: VerificationConfig) -> None:
    """Landmark-level evidence cannot see a translation error along a direction that no
    explained landmark constrains, nor one that a single explained landmark holds (its residual
    is zero whatever it is matched to): invalid unless every direction is constrained and every
    horizontal one survives leaving any one explained landmark out."""
    best = verdict.best
    A = reassociate(source, target, associations, best.T_target_source, cfg.landmark_deg, cfg.landmark_m)
    full, weak, loo, weak_loo = translation_redundancy(target, A)
    best.info["translation_information"] = (full, loo)
    tau = cfg.min_translation_redundancy
    for value, d, what in ((full, weak, "unconstrained"), (loo, weak_loo, "held by a single landmark")):
        if value < tau:
            d = d * np.sign(d[np.argmax(np.abs(d))])
            verdict.valid = False
            verdict.problems.append(
                f"translation along ({d[0]:.2f}, {d[1]:.2f}, {d[2]:.2f}) {what} without support points "
                f"(information {value:.2f} < {tau:.2f})"
            )
            return


def _pair_candidates(source: LandmarkSet, target: LandmarkSet, associations: NDArray[np.int64],
                     W: sp.csr_matrix, cfg: VerificationConfig, kappa_max: float, ev: Evidence) -> list[Candidate]:
    """Pole-pair transforms (lines-only graphs), ranked by the evidence points they explain
    (one vectorised occupancy pass over all of them), or by pole consensus without points
    (which alone favours the street's sliding twins: downtown)."""
    Ts, edges = pair_transforms(source, target, associations, W, cfg, kappa_max, with_edges=True)
    if len(Ts) == 0:
        return []
    if ev.has_points:
        occ = occupancy_overlap(ev.source, ev.target, Ts, cfg.inlier_m, cfg.pair_points).mean(axis=1)  # type: ignore[arg-type]
        order = np.argsort(-occ, kind="stable")
    else:
        count = line_consensus(source, target, associations, Ts, cfg)
        order = np.argsort(-count, kind="stable")
        order = order[count[order] >= 2]
    return pair_candidates(source, target, associations, Ts, order, cfg, edges if ev.has_points else None)


def _check_free_space(verdict: Verdict, ev: Evidence, cfg: VerificationConfig) -> None:
    """Invalid when the winner puts more than ``max_conflict`` of either scan's points where the
    other scan's beams saw through (``free_space.py``); the conflict also lowers the confidence.
    On sim-openroad this rejects the aliased matches of two different tree-lined roads that
    overlap alone accepted (bench/verification.py)."""
    best = verdict.best
    src, tgt = ev.source, ev.target
    cell = (cfg.free_space_az_deg, cfg.free_space_el_deg, cfg.free_space_neighbours, cfg.free_space_scan_neighbours)
    img_s = src.range_image(*cell)  # type: ignore[union-attr]
    img_t = tgt.range_image(*cell)  # type: ignore[union-attr]
    if img_s is None or img_t is None:
        return
    c_st, c_ts = conflict_fraction(src.points, tgt.points, img_s, img_t,  # type: ignore[union-attr]
                                   best.T_target_source, cfg.free_space_margin, cfg.free_space_margin_rel,
                                   src.sensor_pose, tgt.sensor_pose)  # type: ignore[union-attr]
    conflict = max(c_st, c_ts)
    best.info["free_space_conflict"] = (c_st, c_ts)
    whole = img_s.whole_scan and img_t.whole_scan
    best.info["free_space_image"] = "whole scans" if whole else "support points"
    if not best.degenerate:
        verdict.confidence = confidence_of(_verified_score(best), verdict.rival_ratio, cfg, conflict)
    limit = cfg.max_conflict if whole else min(cfg.max_conflict, cfg.max_conflict_support_points)
    if conflict > limit:
        which, other = ("source", "target") if c_st >= c_ts else ("target", "source")
        verdict.valid = False
        verdict.problems.append(
            f"free-space conflict: {conflict:.0%} of the {which}'s points lie where the {other} "
            f"saw through (> {limit:.0%})"
        )


def _check_slide(verdict: Verdict, ev: Evidence, cfg: VerificationConfig) -> None:
    """Invalid when the evidence does not pin the winner's translation: aligned from starts
    ``slide_m`` away in 16 horizontal directions, the points settle at least ``rival_m`` away
    with more than ``max_slide_ratio`` of the winner's verified score. Poles alone leave streets and
    tree-lined roads where a slide of a metre or two (or a different road) explains the points
    about as well (lines only: sim-downtown near misses 1-2 m off, sim-openroad aliases,
    bench/verification.py)."""
    best = verdict.best
    T0 = best.T_target_source
    ang = np.radians(np.arange(0.0, 360.0, 22.5))
    starts = np.repeat(T0[None], len(ang), axis=0)
    starts[:, 0, 3] += cfg.slide_m * np.cos(ang)
    starts[:, 1, 3] += cfg.slide_m * np.sin(ang)
    aligned = np.stack([align_on_evidence(ev.source, ev.target, T) for T in starts])  # type: ignore[arg-type]
    far = np.linalg.norm(aligned[:, :3, 3] - T0[:3, 3], axis=1) >= cfg.rival_m
    ratio = 0.0
    verified = _verified_score(best)
    if far.any() and verified > 0:
        parts = point_overlaps(ev.source, ev.target, np.ascontiguousarray(aligned[far]), cfg.inlier_m)  # type: ignore[arg-type]
        ratio = float(parts.mean(axis=1).max() / verified)
    best.info["slide_ratio"] = ratio
    if ratio > cfg.max_slide_ratio:  # type: ignore[operator]
        verdict.valid = False
        verdict.problems.append(
            f"translation not pinned: the points aligned from {cfg.slide_m:.1f} m away explain "
            f"{ratio:.2f} of the best (> {cfg.max_slide_ratio:.2f})"
        )


def _translation_votes(merged: list[Hypothesis], source: LandmarkSet, target: LandmarkSet, ev: Evidence,
                       cfg: VerificationConfig) -> list[Hypothesis]:
    """The leading distinct rotations (best exact score first) with their translations
    re-estimated by voting on the evidence points (``translation_vote.py``); the ``vote_align``
    best of the voted starts by occupancy are aligned and scored exactly. Right rotation,
    translation metres off is what the landmark registration gets wrong in a street of
    repeating facades (sim-downtown)."""
    rots: list[Hypothesis] = []
    for h in sorted(merged, key=lambda h: -h.score):
        if all(transform_gap(h.T_target_source, g.T_target_source)[0] > cfg.merge_deg for g in rots):
            rots.append(h)
            if len(rots) == cfg.vote_rotations:
                break
    P, Q = ev.source.sample(cfg.vote_points), ev.target.sample(cfg.vote_points)  # type: ignore[union-attr]
    votes = []
    for h in rots:
        Ts = vote_translations(P, Q, h.T_target_source, cfg.vote_reach_m, cfg.vote_height_m, cfg.vote_cell_m,
                               cfg.vote_peaks)
        far = np.linalg.norm(Ts[:, :3, 3] - h.T_target_source[:3, 3], axis=1) > cfg.rival_m
        for T in Ts[far]:  # a peak within rival_m of the hypothesis is the answer it already is
            v = Hypothesis(T, h.associations, h.origin + "+vote", h.objective, h.kappa, h.degenerate)
            v.info["vertices"] = h.info.get("vertices")
            votes.append(v)
    if not votes:
        return []
    score_hypotheses(votes, source, target, ev, cfg, exact=False)
    votes = merge_hypotheses(votes, cfg)[: cfg.vote_align]
    for v in votes:
        v.info["T_landmarks"] = v.T_target_source
        v.T_target_source = align_on_evidence(ev.source, ev.target, v.T_target_source)  # type: ignore[arg-type]
    score_hypotheses(votes, source, target, ev, cfg, exact=True)
    return votes


def score_hypotheses(
    hyps: list[Hypothesis], source: LandmarkSet, target: LandmarkSet, ev: Evidence,
    cfg: VerificationConfig, exact: bool,
) -> None:
    """Fill ``score``: mean share of evidence explained in both directions. ``exact``: KD-tree
    distances; otherwise one vectorised voxel lookup for all hypotheses (stage 1)."""
    if not hyps:
        return
    if ev.has_points:
        score_on_points(hyps, ev.source, ev.target, cfg.inlier_m, exact)  # type: ignore[arg-type]
        return
    counts: list = []
    parts = landmark_overlap(source, target, np.stack([h.T_target_source for h in hyps]), cfg.landmark_deg,
                             cfg.landmark_m, counts)
    for h, c in zip(hyps, counts[0].tolist(), strict=True):
        h.info["landmarks_explained"] = c
    for h, (p0, p1) in zip(hyps, parts.tolist(), strict=True):
        h.score_parts = (p0, p1)
        h.score = 0.5 * (p0 + p1)


def verify_graph(
    source: LandmarkSet, target: LandmarkSet, associations: NDArray[np.int64], W: sp.csr_matrix,
    winner: NDArray[np.int64], cfg: VerificationConfig, solver: ClipperConfig, kappa_max: float,
    gate: tuple[float, float] | None, min_associations: int, evidence: Evidence | None = None,
    timings: dict[str, float] | None = None, wide: bool = False, prior: list[Hypothesis] | None = None,
) -> tuple[Verdict, list[Hypothesis]]:
    """Hypotheses of one graph, registered, scored and decided. Indices refer to source/target.

    ``wide``: the wider search the matcher runs when a first pass finds no valid answer
    (``VerificationConfig.wide_search``): greedy cliques from every vertex of graphs up to
    ``wide_greedy_all_below`` associations and every clique also trimmed iteratively
    (:func:`_trimmed`); ``prior`` (the first pass's scored hypotheses) join the wide pass's
    before the decision, so an answer or rival the first pass found is never lost. With raw-scan
    evidence, ``cfg.point_hypotheses`` and a winner of fewer than ``min_associations``, hypotheses
    from the points join (``point_hypotheses.py``). Graphs with pole pairs ignore ``wide``. The winner's
    ``info["wide_differs"]`` says whether a wide pass would search differently (support points
    as evidence, no pole pairs). ``timings`` (optional) receives 'hypotheses', 'registration'
    and 'evidence' [s]."""
    tm = timings if timings is not None else {}
    t0 = time.perf_counter()
    ev = evidence if evidence is not None else evidence_for(source, target, cfg)
    point_hyps = cfg.point_hypotheses and ev.kind == "scans" and ev.has_points and len(winner) < min_associations
    pair_cands = _pair_candidates(source, target, associations, W, cfg, kappa_max, ev)
    wide = wide and not pair_cands
    if wide:
        cfg = cfg.model_copy(update={"greedy_all_below": max(cfg.greedy_all_below, cfg.wide_greedy_all_below)})
    cands = candidate_cliques(W, winner, cfg, solver) + pair_cands
    t1 = time.perf_counter()
    hyps = _register(source, target, associations, W, cands, kappa_max)
    t2 = time.perf_counter()
    tm["hypotheses"] = t1 - t0
    tm["registration"] = t2 - t1
    if cfg.rival_search and hyps:
        usable = [h for h in hyps if not h.degenerate] or hyps
        lead = max(usable, key=lambda h: (h.objective, h.n_associations))
        ok = consistent_with(source, target, associations, lead.T_target_source,
                             cfg.consistent_deg, cfg.consistent_m)
        t3 = time.perf_counter()
        rivals = rival_cliques(W, ok, max(2, cfg.greedy_starts // 2))
        t4 = time.perf_counter()
        hyps += _register(source, target, associations, W, rivals, kappa_max)
        tm["hypotheses"] += t4 - t3
        tm["registration"] += time.perf_counter() - t4
    if not pair_cands:  # collapse near-identical before scoring; pole pairs are ranked by the
        # points instead: 0.5 deg / 0.2 m from a denser clique is still 0.1 more overlap on a
        # tree-lined road, where the clique's transform loses to trees slid by one spacing
        hyps = merge_hypotheses(hyps, cfg, by="objective")
    if gate is not None:
        t4 = time.perf_counter()
        gated = _register(source, target, associations, W, _gated(hyps, gate, min_associations), kappa_max)
        if wide and cfg.trim_rounds > 0:
            gated += _trimmed(hyps, source, target, associations, W, gate, min_associations, kappa_max,
                              cfg.trim_rounds)
        hyps += gated
        tm["registration"] += time.perf_counter() - t4
    t5 = time.perf_counter()
    score_hypotheses(hyps, source, target, ev, cfg, exact=False)
    merged = merge_hypotheses(hyps, cfg)[: cfg.max_hypotheses]
    if ev.has_points:  # stage 2: align the leaders on the evidence points, exact distances
        n_align = max(cfg.align_top, cfg.pair_align_top) if pair_cands else cfg.align_top
        for h in merged[:n_align]:
            T = align_on_evidence(ev.source, ev.target, h.T_target_source)  # type: ignore[arg-type]
            h.info["T_landmarks"] = h.T_target_source
            h.T_target_source = T
        score_hypotheses(merged, source, target, ev, cfg, exact=True)
        first = next((h for h in merged if not h.degenerate), None)  # stage 1's leader
        settled = is_settled(merged, first, cfg) and whole_views(ev, cfg)  # cropped views: not calibrated
        if settled:
            first.info["settled"] = True  # type: ignore[union-attr]
        if cfg.vote_rotations > 0 and not pair_cands and merged and not settled:
            merged = merge_hypotheses(merged + _translation_votes(merged, source, target, ev, cfg), cfg)
        if point_hyps and not wide:  # the wide pass has them among ``prior``
            pts = point_hypotheses(ev.source, ev.target, cfg, ev.starts)  # type: ignore[arg-type]
            merged = merge_hypotheses(merged + pts, cfg)
        lead = next((h for h in merged if not h.degenerate), None)  # the best exact score
        if cfg.local_search_m > 0 and not settled:
            # both leaders: the exact leader may be a voted answer, and stage 1's leader a near
            # miss that only the local search turns right (courtyard)
            if lead is not None:
                _local_search(lead, ev, cfg)
            if first is not None and first is not lead and any(first is x for x in merged):
                _local_search(first, ev, cfg)
        if wide and prior:  # the first pass's answers and rivals (scored on the same evidence)
            merged += prior
        merged = merge_hypotheses(merged, cfg)
    min_score = cfg.min_overlap if ev.has_points else cfg.min_landmark_overlap
    verdict = decide(merged, cfg, min_score,
                     cfg.max_rival_ratio if ev.has_points else cfg.max_rival_ratio_landmarks)
    if verdict.best is not None:
        verdict.best.info["evidence"] = "points" if ev.has_points else "landmarks"
        verdict.best.info["evidence_source"] = ev.kind if ev.has_points else "landmarks"
    if not ev.has_points and verdict.best is not None:
        n_ok = verdict.best.info.get("landmarks_explained", 0)
        if n_ok < cfg.min_landmarks_explained:
            verdict.valid = False
            verdict.problems.append(
                f"only {n_ok} landmarks explained (< {cfg.min_landmarks_explained}) without support points"
            )
    tm["evidence"] = time.perf_counter() - t5
    if verdict.best is not None and gate is not None and not verdict.best.degenerate:
        t6 = time.perf_counter()
        _refine(verdict.best, source, target, associations, kappa_max, gate, min_associations, ev, cfg, min_score)
        tm["registration"] += time.perf_counter() - t6
    if not ev.has_points and verdict.best is not None:
        _check_translation(verdict, source, target, associations, cfg)
    if ev.has_points and cfg.free_space and verdict.best is not None:
        _check_free_space(verdict, ev, cfg)
    if ev.has_points and cfg.view_check and verdict.best is not None:
        check_view(verdict, ev, cfg)
    if ev.has_points and cfg.max_slide_ratio is not None and verdict.best is not None:
        _check_slide(verdict, ev, cfg)
    if verdict.valid and verdict.confidence < cfg.min_valid_confidence:  # last: the checks above set the confidence
        verdict.valid = False
        verdict.problems.append(low_confidence_problem(verdict, cfg.min_valid_confidence))
    if verdict.best is not None:
        verdict.best.info["wide_differs"] = bool(ev.has_points and not pair_cands)
        verdict.best.info["search"] = "wide" if wide else "first"
    return verdict, merged
