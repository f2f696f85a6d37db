"""GraffMatch in one call: ``GraffMatcher(config).match(source, target) -> MatchResult``.

Pipeline (paper, Sec. Method): intra-scan invariant distance matrices (once per scan) ->
all-to-all same-type putative associations -> sparse consistency graph -> CLIPPER densest
clique -> closed-form line/plane registration with its condition number. Beyond the paper,
the verification layer turns the graph into several distinct hypotheses, scores each by
point-level evidence and sets ``valid`` only when the best is clearly right and clearly beats
its best rival (``graffmatch.verification``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.association.clipper import ClipperConfig, solve_clipper
from graffmatch.association.consistency_graph import build_consistency_graph
from graffmatch.association.putative import GatingConfig, putative_associations
from graffmatch.errors import DegenerateGeometryError, InvalidInputError
from graffmatch.geometry.distance import pairwise_distances
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.geometry.set_cache import derived_cache
from graffmatch.registration.closed_form import register_landmarks
from graffmatch.verification.config import VerificationConfig
from graffmatch.verification.decision import Hypothesis
from graffmatch.verification.verify import Evidence, evidence_for, verify_graph

TypeName = Literal["point", "line", "plane"]
_TYPE_IDS = {"point": LandmarkType.POINT, "line": LandmarkType.LINE, "plane": LandmarkType.PLANE}


class GraffMatchConfig(BaseModel):
    """Matcher parameters; defaults are the paper's (eps 0.2, sigma 0.05, rho 40 m)."""

    model_config = ConfigDict(extra="forbid")

    rho: float = Field(40.0, gt=0, description="scale of the affine part [m] (Sec. Selection of Scaling Parameter)")
    epsilon: float = Field(0.2, gt=0, description="consistency threshold on |d_i - d_j| [rad]")
    sigma: float = Field(0.05, gt=0, description="edge weight exp(-c^2 / 2 sigma^2) [rad]")
    variant: Literal["invariant", "naive"] = Field(
        "invariant", description="invariant: shift by the first anchor (Prop. 1); naive: no shift (ablation)"
    )
    landmark_types: list[TypeName] = Field(
        default_factory=lambda: ["point", "line", "plane"],
        description="landmark types used (e.g. ['line'] for the line-only variant)",
    )
    solver: ClipperConfig = Field(
        default_factory=lambda: ClipperConfig(greedy_starts=64, d_schedule="mean", rescale_u0=True,
                                              tol_u=1e-3, tol_F=1e-4, line_search="backtracking_linear",
                                              step_cap=8.0),
        description=(
            "CLIPPER settings; GraffMatch also lets 64 greedy cliques compete on the same "
            "densest-clique objective (greedy_starts=0 for CLIPPER alone), and uses the current "
            "reference C++ homotopy (mean d steps, rescaled start): 3-4x fewer mat-vecs on "
            "~30 %-dense landmark graphs, same selections in bench/bench_matcher.py; the same "
            "backtracking with one mat-vec per step instead of one per trial (20-35 % fewer, "
            "same selections: bench/solver_selections.py). line_search='exact' halves them but "
            "changed 3 of 16 W2 selections (denser cliques, one true association fewer in 2), "
            "so it is not the default; the step size is capped at 8 / F (step_cap: 17-40 % less "
            "solver work, same selections on W1/W2/W3 and the reference graphs)"
        ),
    )
    gating: GatingConfig = Field(
        default_factory=GatingConfig,
        description="putative associations: same-type pairs whose view-robust attributes agree",
    )
    kappa_max: float = Field(1e3, gt=1, description="condition number above which the estimate is degenerate")
    min_associations: int = Field(3, ge=1, description="fewest selected associations for a valid result")
    min_line_associations: int = Field(
        2, ge=1,
        description="fewest associations when every one is a line and the result is verified on support "
        "points: two poles fix the yaw and the horizontal translation, the points the rest (lines-only "
        "recall on sim-downtown, calibration split: 12 of 20 misses were right 2-pole answers)",
    )
    weighted_registration: bool = Field(
        True, description="weight the least squares by the solver's u entries"
    )
    reject_residual_m: float | None = Field(
        1.0,
        description=(
            "after a first registration, drop selected associations whose offset residual "
            "exceeds this [m] (or whose angle residual exceeds reject_residual_deg) and "
            "register again; None disables. The solver's associations are reported unchanged."
        ),
    )
    reject_residual_deg: float = Field(5.0, gt=0, description="angle residual gate [deg]")
    verification: VerificationConfig = Field(
        default_factory=VerificationConfig,
        description="multi-hypothesis verification: what valid=True rests on",
    )


@dataclass
class MatchResult:
    """Outcome of one match. ``T_target_source`` maps source-frame points into the target frame.

    ``valid`` is True only when the verified evidence says the transform is right: the best
    hypothesis explains enough of both scans (``overlap``) and beats its best distinct rival
    (``runner_up``) by ``margin`` (1 - rival score / best score). Otherwise ``message`` says why,
    e.g. "ambiguous: a 178 deg / 0.4 m alternative ... scores 0.93 of the best", and
    ``T_target_source`` is the best effort, or None when no estimate exists. Never a silent
    identity. ``confidence`` is the calibrated probability that the transform is right.
    ``overlap`` is the score of ``T_target_source`` itself; when the final landmark
    re-registration replaced the verified transform, the score the decision (``margin``,
    ``confidence``, ``runner_up``) was made on is ``info["verified_overlap"]``.
    """

    T_target_source: NDArray[np.float64] | None
    associations: NDArray[np.int64]
    weights: NDArray[np.float64]
    score: float
    kappa: float
    degenerate: bool
    valid: bool
    message: str
    timings: dict[str, float] = field(default_factory=dict)
    n_putative: int = 0
    n_edges: int = 0
    info: dict = field(default_factory=dict)
    confidence: float = 0.0
    overlap: float = 0.0
    margin: float = 0.0
    runner_up: Hypothesis | None = None
    hypotheses: list[Hypothesis] = field(default_factory=list)

    def __repr__(self) -> str:
        T = "None" if self.T_target_source is None else np.array2string(
            self.T_target_source, precision=3, suppress_small=True, separator=", "
        ).replace("\n", "")
        ms = ", ".join(f"{k}={v * 1e3:.1f}ms" for k, v in self.timings.items())
        return (
            f"MatchResult(valid={self.valid}, confidence={self.confidence:.3f}, "
            f"overlap={self.overlap:.3f}, margin={self.margin:.3f}, hypotheses={len(self.hypotheses)}, "
            f"associations={len(self.associations)}, "
            f"score={self.score:.2f}, kappa={self.kappa:.3g}, degenerate={self.degenerate}, "
            f"putative={self.n_putative}, edges={self.n_edges}, message={self.message!r},\n"
            f"  T_target_source={T},\n  timings: {ms})"
        )

    def to_dict(self) -> dict:
        return {
            "T_target_source": None if self.T_target_source is None else self.T_target_source.tolist(),
            "associations": self.associations.tolist(),
            "weights": self.weights.tolist(),
            "score": self.score,
            "kappa": self.kappa if np.isfinite(self.kappa) else None,
            "degenerate": self.degenerate,
            "valid": self.valid,
            "message": self.message,
            "timings": self.timings,
            "n_putative": self.n_putative,
            "n_edges": self.n_edges,
            "confidence": self.confidence,
            "overlap": self.overlap,
            "margin": self.margin,
            "runner_up": None if self.runner_up is None else self.runner_up.to_dict(),
            "hypotheses": [h.to_dict() for h in self.hypotheses],
        }


def _filter_types(ls: LandmarkSet, types: list[TypeName]) -> tuple[LandmarkSet, NDArray[np.int64]]:
    ids = np.array([int(_TYPE_IDS[t]) for t in types], dtype=ls.types.dtype)
    keep = np.flatnonzero((ls.types[:, None] == ids[None, :]).any(axis=1))  # np.isin, without its setup
    if keep.size == len(ls):
        return ls, keep
    return ls[keep], keep


def _validate_input(ls: LandmarkSet, name: str) -> None:
    if not isinstance(ls, LandmarkSet):
        raise InvalidInputError(f"{name} must be a LandmarkSet, got {type(ls).__name__}")
    if len(ls) < 2:
        raise InvalidInputError(f"{name} has {len(ls)} landmark(s); at least 2 are needed to match")


def match_with_distances(
    source: LandmarkSet,
    target: LandmarkSet,
    D_source: ArrayLike,
    D_target: ArrayLike,
    config: GraffMatchConfig | None = None,
    associations: ArrayLike | None = None,
    timings: dict[str, float] | None = None,
    evidence: Evidence | None = None,
) -> MatchResult:
    """Graph + solver + registration (+ verification) for any pair of intra-scan distance matrices.

    GraffMatch passes d_Graff matrices; CLIPPER-R^n or CLIPPER-CP pass Euclidean ones.
    """
    cfg = config or GraffMatchConfig()
    timings = dict(timings or {})
    t0 = time.perf_counter()
    graph = build_consistency_graph(
        D_source, D_target, associations, cfg.epsilon, cfg.sigma,
        types_i=source.types, types_j=target.types,
        # verification reads graph.weights (scipy, int32 indices): build those directly rather
        # than widen compact (uint16) ones later next to them (+86 MB for a moment at W3)
        compact=not cfg.verification.enabled,
    )
    t1 = time.perf_counter()
    timings["graph"] = t1 - t0
    sol = solve_clipper(graph, cfg.solver)
    t2 = time.perf_counter()
    timings["solver"] = t2 - t1
    sel = sol.selected
    assoc = graph.associations[sel]
    weights = sol.u[sel]
    common = dict(
        associations=assoc, weights=weights, score=sol.score, n_putative=graph.m,
        n_edges=graph.n_edges,
        info={"solver": repr(sol), "m_after_pruning": sol.info.get("m_after_pruning")},
    )
    points_only = (cfg.verification.enabled and cfg.verification.point_hypotheses and evidence is not None
                   and evidence.kind == "scans" and evidence.has_points)  # hypotheses need no associations
    if len(assoc) == 0 and not points_only:
        timings["registration"] = 0.0
        timings["total"] = sum(timings.values())
        return MatchResult(None, kappa=np.inf, degenerate=True, valid=False,
                           message="no consistent associations", timings=timings, **common)
    if cfg.verification.enabled:
        return _verified_result(source, target, graph, sol, cfg, timings, common, evidence)
    try:
        est, inliers = _register(source, target, assoc, weights, cfg)
    except DegenerateGeometryError as exc:
        timings["registration"] = time.perf_counter() - t2
        timings["total"] = sum(timings.values())
        return MatchResult(None, kappa=np.inf, degenerate=True, valid=False, message=str(exc),
                           timings=timings, **common)
    timings["registration"] = time.perf_counter() - t2
    timings["total"] = sum(timings.values())
    problems = []
    if len(assoc) < cfg.min_associations:
        problems.append(f"only {len(assoc)} associations (< {cfg.min_associations})")
    if est.degenerate:
        problems.append(f"degenerate geometry (kappa={est.kappa:.3g} > {cfg.kappa_max:.3g})")
    problems += reach_problems(source, target, est.T_target_source)
    common["info"].update(
        kappa_rotation=est.kappa_rotation, kappa_translation=est.kappa_translation,
        rms_offset=est.rms_offset, registration_inliers=inliers,
    )
    return MatchResult(
        est.T_target_source, kappa=est.kappa, degenerate=est.degenerate, valid=not problems,
        message="; ".join(problems) or "ok", timings=timings, **common,
    )


def _verified_result(source, target, graph, sol, cfg: GraffMatchConfig, timings, common,
                     evidence: Evidence | None) -> MatchResult:
    """Hypotheses from the graph, registered, scored and decided (``graffmatch.verification``).
    An invalid first pass is searched again wider (``VerificationConfig.wide_search``), whose
    result is returned; a valid one is returned as it is."""
    vcfg = cfg.verification.for_evidence(cfg.landmark_types, "support" if evidence is None else evidence.kind)
    W = graph.weights.tocsr()
    vt: dict[str, float] = {}
    res = _verified_once(source, target, graph, W, sol, cfg, vcfg, vt, dict(common, info=dict(common["info"])),
                         evidence, False, None)
    mode = vcfg.wide_search
    if (mode != "never" and (mode == "always" or not res.valid) and res.T_target_source is not None
            and res.info.get("wide_differs")):
        res = _verified_once(source, target, graph, W, sol, cfg, vcfg, vt, common, evidence, True, res.hypotheses)
    timings["registration"] = vt.get("registration", 0.0)
    timings["verification"] = vt.get("hypotheses", 0.0) + vt.get("evidence", 0.0)
    timings["total"] = sum(timings.values())
    res.timings = timings
    return res


def _verified_once(source, target, graph, W, sol, cfg: GraffMatchConfig, vcfg, vt: dict[str, float], common,
                   evidence: Evidence | None, wide: bool, prior) -> MatchResult:
    """One verification pass (``wide``: the wider search, with the first pass's hypotheses
    ``prior``) as a result; ``vt`` accumulates its times."""
    gate = None if cfg.reject_residual_m is None else (cfg.reject_residual_m, cfg.reject_residual_deg)
    t: dict[str, float] = {}
    verdict, hyps = verify_graph(
        source, target, graph.associations, W, sol.selected, vcfg,
        cfg.solver, cfg.kappa_max, gate, cfg.min_associations, evidence, t, wide, prior,
    )
    for k, v in t.items():
        vt[k] = vt.get(k, 0.0) + v
    timings: dict[str, float] = {}
    best = verdict.best
    if best is None:
        return MatchResult(None, kappa=np.inf, degenerate=True, valid=False,
                           message="; ".join(verdict.problems), timings=timings, **common)
    problems = list(verdict.problems)
    need = cfg.min_associations
    if best.info.get("evidence") == "points" and np.all(source.types[best.associations[:, 0]] == LandmarkType.LINE):
        need = min(need, cfg.min_line_associations)
    if best.n_associations < need and best.origin != "points":  # a points hypothesis has none: the
        # raw scans verified it (VerificationConfig.point_hypotheses)
        problems.insert(0, f"only {best.n_associations} associations (< {need})")
    problems += reach_problems(source, target, best.T_target_source)
    common.update(associations=best.associations, score=best.objective,
                  weights=np.ones(best.n_associations))
    common["info"].update(origin=best.origin, rival_ratio=verdict.rival_ratio,
                          score_parts=best.score_parts, clipper_selected=len(sol.selected))
    for key in ("free_space_conflict", "free_space_image", "search", "wide_differs", "verified_overlap",
                "evidence_source", "view_coverage", "covisible_overlap"):
        if key in best.info:
            common["info"][key] = best.info[key]
    if "slide_ratio" in best.info:
        common["info"]["slide_ratio"] = best.info["slide_ratio"]
    valid = not problems
    return MatchResult(
        best.T_target_source, kappa=best.kappa, degenerate=best.degenerate, valid=valid,
        message="; ".join(problems) or "ok", timings=timings,
        confidence=verdict.confidence if valid else min(verdict.confidence, 0.5),
        overlap=best.score, margin=verdict.margin, runner_up=verdict.runner_up,
        hypotheses=hyps, **common,
    )


def reach_problems(source: LandmarkSet, target: LandmarkSet, T_target_source: np.ndarray) -> list[str]:
    """Scans that share landmarks cannot be further apart than the reach of their landmarks
    (the largest anchor distance from each sensor); a longer translation is an artefact of a
    poorly constrained direction that kappa alone did not flag."""
    reach = float(np.linalg.norm(source.anchors, axis=1).max() + np.linalg.norm(target.anchors, axis=1).max())
    t_norm = float(np.linalg.norm(T_target_source[:3, 3]))
    if t_norm > reach:
        return [f"translation {t_norm:.1f} m exceeds the landmarks' reach {reach:.1f} m"]
    return []


def _register(source, target, assoc, weights, cfg: GraffMatchConfig):
    """Closed-form registration, then one residual gate and re-registration on the survivors."""
    w = weights if cfg.weighted_registration else None
    est = register_landmarks(source, target, assoc, w, cfg.kappa_max)
    inliers = np.ones(len(assoc), dtype=bool)
    if cfg.reject_residual_m is not None and len(assoc) > cfg.min_associations:
        keep = (est.offset_residuals <= cfg.reject_residual_m) & (
            est.angle_residuals_deg <= cfg.reject_residual_deg
        )
        if cfg.min_associations <= keep.sum() < len(assoc):
            est2 = register_landmarks(
                source, target, assoc[keep], None if w is None else w[keep], cfg.kappa_max
            )
            if not est2.degenerate or est.degenerate:
                est, inliers = est2, keep
    return est, inliers


class GraffMatcher:
    """Global, initial-guess-free matching and registration of two landmark sets.

    Example::

        result = GraffMatcher().match(source, target)
        if result.valid:
            points_in_target = transform_points(result.T_target_source, source_points)
    """

    def __init__(self, config: GraffMatchConfig | None = None) -> None:
        self.config = config or GraffMatchConfig()

    def distance_matrix(self, landmarks: LandmarkSet) -> NDArray[np.float64]:
        """Intra-scan matrix (read-only), computed once per set of arrays (``derived_cache``):
        a scan matched against several candidates pays for it once."""
        rho, variant = self.config.rho, self.config.variant

        def make() -> NDArray[np.float64]:
            D = pairwise_distances(landmarks, rho, variant)
            D.setflags(write=False)
            return D

        return derived_cache.get(("intra_distances", float(rho), variant),
                                 (landmarks.types, landmarks.bases, landmarks.anchors), make)

    def match(
        self,
        source: LandmarkSet,
        target: LandmarkSet,
        associations: ArrayLike | None = None,
        evidence: Evidence | None = None,
    ) -> MatchResult:
        """Match ``source`` to ``target``; indices in the result refer to the inputs.

        ``evidence`` (optional) replaces the landmarks' support points as what hypotheses are
        scored against, e.g. the raw scans (see ``graffmatch.pipeline``)."""
        _validate_input(source, "source")
        _validate_input(target, "target")
        cfg = self.config
        src, src_idx = _filter_types(source, cfg.landmark_types)
        tgt, tgt_idx = _filter_types(target, cfg.landmark_types)
        if associations is not None:
            try:
                raw = np.asarray(associations)
                A = raw.astype(np.int64).reshape(-1, 2)
            except (TypeError, ValueError, OverflowError) as exc:
                raise InvalidInputError(f"associations must be a (k, 2) integer array: {exc}") from None
            if raw.dtype.kind not in "iub" and not (raw.dtype.kind == "f" and np.array_equal(raw, np.round(raw))):
                raise InvalidInputError(f"associations must be integer indices, got dtype {raw.dtype}")
            bad = (A < 0) | (A >= np.array([len(source), len(target)]))
            if bad.any():
                r = int(np.flatnonzero(bad.any(1))[0])
                raise InvalidInputError(
                    f"associations[{r}] = {A[r].tolist()} is out of range for {len(source)} source "
                    f"and {len(target)} target landmarks"
                )
            # Re-index into the filtered sets.
            inv_s = np.full(len(source), -1)
            inv_s[src_idx] = np.arange(len(src_idx))
            inv_t = np.full(len(target), -1)
            inv_t[tgt_idx] = np.arange(len(tgt_idx))
            A = np.stack([inv_s[A[:, 0]], inv_t[A[:, 1]]], 1)
            associations = A[(A >= 0).all(1)]
        if len(src) < 2 or len(tgt) < 2:
            raise InvalidInputError(
                f"too few landmarks of types {cfg.landmark_types}: source {len(src)}, target {len(tgt)}"
            )
        if associations is None:
            associations = putative_associations(src, tgt, cfg.gating)  # None: all same-type
        t0 = time.perf_counter()
        D_s = self.distance_matrix(src)
        D_t = self.distance_matrix(tgt)
        timings = {"distances": time.perf_counter() - t0}
        filtered = len(src_idx) != len(source) or len(tgt_idx) != len(target)
        if evidence is None and filtered and cfg.verification.enabled:
            # the types restrict what is matched, not what verifies it: with poles only, the
            # poles' own points are too few to tell a right answer from a wrong one (lines-only
            # precision 0.77 -> 1.00 on sim-downtown with every landmark's support points)
            t1 = time.perf_counter()
            evidence = evidence_for(source, target, cfg.verification)
            timings["support"] = time.perf_counter() - t1
        res = match_with_distances(src, tgt, D_s, D_t, cfg, associations, timings, evidence)
        if len(src_idx) != len(source) or len(tgt_idx) != len(target):
            def back(a: np.ndarray) -> np.ndarray:
                return np.stack([src_idx[a[:, 0]], tgt_idx[a[:, 1]]], 1).astype(np.int64).reshape(-1, 2)

            res.associations = back(res.associations)
            for h in res.hypotheses:
                h.associations = back(h.associations)
        return res
