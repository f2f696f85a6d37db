"""Settings of the verification layer, with where each default comes from."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

#: lines-only (min_overlap, max_rival_ratio, max_conflict, max_slide_ratio): chosen on the lines-only
#: calibration split of bench/verification.py (de-skewed drives extracted with poles.LAYERED_POLES,
#: whole-scan free space at the full matcher's range image; bench/results/verification.json; session 8
#: chose the same at its 1 x 2 deg, 2 m image). On the default one-layer poles the same values keep
#: test precision 1.000 with no valid negative (session 7 rows)
LINES_ONLY = (0.2, 0.875, 0.18, 0.85)

#: raw-scan evidence (min_overlap, max_rival_ratio, max_conflict) and its confidence coefficients, for
#: ScanMatcher's evidence='support_then_scans' (decided only where the support points gave no valid
#: answer): chosen on the calibration split of bench/verification.py --evidence scans by the support
#: points' rule (bench/results/verification_scans_session14.json; docs/verification.md, Session 14).
#: Calibration recall is the same for any min_overlap in 0.05-0.125 (the rule's tie-break takes the
#: lowest); the rival ratio and the free-space conflict do the separating
SCANS = (0.05, 0.775, 0.08)
SCANS_CONFIDENCE = (-4.504, 29.926, 12.028, -46.712)

#: partial views (co-visible overlap, rival ratio) for views in [0.5, 0.9) and below 0.5, support
#: points and raw scans: chosen by the support points' rule (most recall with precision >= 99.5 % on
#: each recording, no valid wrong negative; ties: the stricter) on cropped pairs of the calibration
#: split, courtyard and the three simulated drives (bench/verification_partial_views.py --split cal
#: --sims --open; bench/results/partial_views_cal_open_session15.json; docs/verification.md, Session 15)
PARTIAL, NARROW = (0.325, 0.85), (0.275, 0.45)
SCANS_PARTIAL, SCANS_NARROW = (0.175, 0.75), (0.175, 0.775)


class DecisionThresholds(BaseModel):
    """The decision's thresholds for one matching mode (what ``VerificationConfig`` holds for
    the full landmark sets)."""

    model_config = ConfigDict(extra="forbid")

    min_overlap: float = Field(ge=0, le=1, description="the best hypothesis must explain at least this share")
    max_rival_ratio: float = Field(gt=0, le=1, description="ambiguous above this rival / best score ratio")
    max_conflict: float = Field(ge=0, le=1, description="invalid above this free-space conflict")
    max_slide_ratio: float | None = Field(
        None, gt=0, description="invalid above this slide ratio (see VerificationConfig.max_slide_ratio)"
    )
    confidence_coef: tuple[float, float, float, float] | None = Field(
        None, description="the confidence's logistic coefficients for this mode (None: VerificationConfig's)"
    )
    partial_min_overlap: float | None = Field(
        None, ge=0, le=1, description="partial views: co-visible overlap needed (None: VerificationConfig's)"
    )
    partial_max_rival_ratio: float | None = Field(
        None, gt=0, le=1, description="partial views: rival ratio allowed (None: VerificationConfig's)"
    )
    narrow_min_overlap: float | None = Field(
        None, ge=0, le=1, description="narrow views: co-visible overlap needed (None: VerificationConfig's)"
    )
    narrow_max_rival_ratio: float | None = Field(
        None, gt=0, le=1, description="narrow views: rival ratio allowed (None: VerificationConfig's)"
    )

    def thresholds(self) -> dict:
        """The fields a :class:`VerificationConfig` takes over (the confidence only when set)."""
        d = self.model_dump()
        for key in ("confidence_coef", "partial_min_overlap", "partial_max_rival_ratio", "narrow_min_overlap",
                    "narrow_max_rival_ratio"):
            if d[key] is None:
                del d[key]
        return d


class VerificationConfig(BaseModel):
    """Hypothesis generation, evidence and decision.

    The decision thresholds and the confidence calibration were chosen on the calibration split
    of ``bench/verification.py`` (courtyard scans of the first half of the walk, simulated
    suites' even places, and their negatives) and are reported on the other split.
    """

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(True, description="False: the paper's single-clique matcher, valid = well-conditioned")
    greedy_starts: int = Field(12, ge=0, description="greedy cliques grown from the highest-degree vertices")
    greedy_all_below: int = Field(
        300, ge=0, description="graphs with at most this many associations grow a greedy clique from every vertex"
    )
    resolves: int = Field(2, ge=0, description="re-solves with the previous winners' associations removed")
    resolve_with_clipper: bool = Field(
        False, description="re-solve with CLIPPER (slow on dense graphs) instead of greedy cliques"
    )
    rival_search: bool = Field(
        True, description="also search the best clique among associations inconsistent with the winner"
    )
    pair_hypotheses: int = Field(
        24, ge=0,
        description="graphs of lines only (poles): the best distinct transforms by consensus from every "
        "consistent pair of associations become candidates (0: off)",
    )
    pair_max_edges: int = Field(4000, ge=1, description="... from at most this many most consistent pairs")
    pair_vertical_deg: float = Field(
        10.0, gt=0, le=90, description="... pole pairs within this of z get the closed-form yaw (z-up frames) [deg]"
    )
    pair_points: int = Field(128, ge=8, description="... ranked by the occupancy of this many evidence points per scan")
    pair_align_top: int = Field(
        8, ge=0,
        description="... and this many leaders aligned on the evidence points (instead of align_top): a "
        "tree-lined road slid by a few trees scores like the truth until both are aligned (sim-openroad)",
    )
    wide_search: Literal["never", "when_invalid", "always"] = Field(
        "when_invalid",
        description="with support points (graphs without pole pairs): when the first pass finds no valid answer, "
        "search again wider (wide_greedy_all_below, trim_rounds; the first pass's hypotheses stay candidates and "
        "rivals) and return that pass's result ('always': after every first pass, 'never': the first pass only). "
        "A street's cliques hold wrong but consistent associations that pull every registration metres off "
        "(sim-downtown, docs/verification.md, session 9)",
    )
    wide_greedy_all_below: int = Field(
        512, ge=0, description="... the wide pass grows a greedy clique from every vertex of graphs up to this size"
    )
    trim_rounds: int = Field(
        10, ge=0,
        description="... and trims every clique iteratively (its worst association beyond the residual gate "
        "dropped, re-registered) for up to this many rounds (0: off)",
    )
    max_hypotheses: int = Field(8, ge=1, description="distinct hypotheses scored exactly (after a fast first pass over all)")
    merge_deg: float = Field(3.0, gt=0, description="hypotheses closer than this rotation merge [deg]")
    merge_m: float = Field(0.5, gt=0, description="... and this translation [m]")
    rival_deg: float = Field(
        5.0, gt=0, description="a rival must differ from the best by more than this rotation [deg] ..."
    )
    rival_m: float = Field(1.0, gt=0, description="... or this translation [m] (else it is the same answer)")
    consistent_deg: float = Field(10.0, gt=0, description="an association agrees with a transform within this angle")
    consistent_m: float = Field(1.0, gt=0, description="... and this offset [m]")
    # evidence
    voxel: float = Field(0.3, gt=0, description="voxel size of the support points used as evidence [m]")
    max_points: int = Field(1500, ge=10, description="most support points per scan used as evidence")
    align_top: int = Field(3, ge=0, description="leading hypotheses aligned on the evidence points before exact scoring")
    refine_tolerance: float = Field(
        0.02, ge=0, description="keep the landmark re-registration unless it explains this much less evidence"
    )
    local_search_m: float = Field(
        2.0, ge=0, description="the leader is re-aligned from starts up to this far around it (0: off) [m]"
    )
    local_search_step_m: float = Field(1.0, gt=0, description="... on a grid with this step [m]")
    local_search_deg: float = Field(3.0, ge=0, description="... and yawed by +-this [deg]")
    local_search_top: int = Field(2, ge=1, description="... the best starts by occupancy are aligned and scored")
    local_search_distances: tuple[float, ...] = Field(
        (2.0, 1.5, 1.0, 0.8, 0.6, 0.5, 0.4, 0.3, 0.3, 0.3),
        description="correspondence distances of the leader's longer re-alignment (one step each) [m]",
    )
    local_search_gain: float = Field(
        0.01, ge=0, description="a re-aligned leader replaces the leader when it explains this much more"
    )
    settled_overlap: float | None = Field(
        0.4, ge=0, le=1,
        description="speed: on a whole-view pair (both coverages known and >= view_whole), when stage 2's exact "
        "leader explains at least this share and no distinct hypothesis scores more than settled_rival_ratio of "
        "it, the voted translations and the local search (which rescue near misses and find translation aliases) "
        "are skipped; None: never. 0.4 / 0.6: of (0.3, 0.5) and (0.4, 0.6), the faster with no decision change "
        "on the calibration split (bench/verification_rows.py) and its whole-view crops; ungated, both let wrong "
        "answers through on cropped calibration views, hence the gate (docs/performance.md, Session 15)",
    )
    settled_rival_ratio: float = Field(0.6, ge=0, le=1, description="... see settled_overlap")
    vote_rotations: int = Field(
        1, ge=0, description="the leading distinct rotations whose translation is re-estimated by voting on "
        "the evidence points (0: off; full matcher only): right rotation, translation metres off (sim-downtown)",
    )
    vote_peaks: int = Field(3, ge=1, description="... the strongest vote peaks of each become hypotheses")
    vote_align: int = Field(3, ge=1, description="... the best voted starts by occupancy are aligned and scored")
    vote_points: int = Field(256, ge=8, description="... from this many evidence points of each scan")
    vote_reach_m: float = Field(12.0, gt=0, description="... within this horizontal distance of its translation [m]")
    vote_height_m: float = Field(1.0, gt=0, description="... from point pairs within this height of each other [m]")
    vote_cell_m: float = Field(0.5, gt=0, description="... in cells of this size [m]")
    point_hypotheses: bool = Field(
        False, description="raw-scan evidence only: when the landmark graph's winner has fewer associations than "
        "the matcher needs (a landmark-poor pair: two or three landmarks a scan), add hypotheses from the points "
        "themselves: a yaw sweep (z-up frames; ground vehicles, no roll or pitch) with each yaw's translation voted "
        "on the points (translation_vote.py), plus the evidence's own starts (e.g. odometry); the landmarks alone "
        "give such pairs nothing to verify (docs/loops.md, session 15b)",
    )
    point_yaw_step_deg: float = Field(10.0, gt=0, le=90, description="... the sweep's yaw step [deg]")
    point_peaks: int = Field(2, ge=1, description="... the strongest vote peaks of each yaw become starts")
    point_align: int = Field(4, ge=1, description="... the best starts by occupancy are aligned and scored exactly")
    inlier_m: float = Field(0.3, gt=0, description="a point is explained within this distance [m]")
    landmark_deg: float = Field(5.0, gt=0, description="landmark-level evidence: angle tolerance [deg]")
    landmark_m: float = Field(0.4, gt=0, description="landmark-level evidence: offset tolerance [m]")
    scan_voxel: float = Field(
        0.6, gt=0, description="raw-scan evidence (ScanMatcher's evidence='support_then_scans'): voxel size of the "
        "extractor's non-ground voxel cloud used as evidence [m]",
    )
    scan_max_points: int = Field(2000, ge=10, description="... most points per scan (even stride)")
    # decision
    min_overlap: float = Field(
        0.1875, ge=0, le=1,
        description="the best hypothesis must explain at least this share (chosen on the calibration split)",
    )
    max_rival_ratio: float = Field(
        0.85, gt=0, le=1,
        description="ambiguous when a distinct rival scores more than this fraction of the best (calibration split)",
    )
    max_rival_ratio_landmarks: float = Field(
        0.825, gt=0, le=1,
        description="... in place of max_rival_ratio with landmark-level evidence (bare landmarks, no support "
        "points): session 7's value, which bench/fuzz_validity.py checks; bench/verification.py's pairs all "
        "carry points and choose only max_rival_ratio",
    )
    free_space: bool = Field(
        True,
        description="reject hypotheses that put one scan's points where the other's beams saw through "
        "(needs landmarks in their sensor's frame, as the extractor gives; False for maps in a world frame)",
    )
    # the range image below was chosen among 24 variants on the calibration split (bench/verification.py)
    free_space_az_deg: float = Field(1.0, gt=0, le=30, description="free-space range image: azimuth cell [deg]")
    free_space_el_deg: float = Field(2.0, gt=0, le=30, description="... elevation cell [deg]")
    free_space_neighbours: int = Field(1, ge=0, le=5, description="... cells around each cell that shadow it")
    free_space_margin: float = Field(2.0, ge=0, description="a point conflicts this far in front of the return [m] ...")
    free_space_margin_rel: float = Field(0.05, ge=0, description="... or this fraction of the return's range")
    free_space_scan_neighbours: int = Field(
        0, ge=0, le=5, description="... cells that shadow each cell in the whole scan's image (LandmarkSet.scan_ranges, "
        "used when a set carries it; free_space_neighbours applies to the support points' image)",
    )
    max_conflict: float = Field(
        0.1, ge=0, le=1,
        description="invalid when more than this share of either scan's points lies in the other's observed "
        "free space (chosen on the calibration split of bench/verification.py)",
    )
    max_conflict_support_points: float = Field(
        0.07, ge=0, le=1,
        description="... in place of max_conflict when either image comes from support points (a set without scan_ranges: "
        "a sparser image, more false conflicts; chosen apart on the calibration split of bench/verification.py, since "
        "session 9 with precision >= 99.5 % on each recording and no valid cross-dataset negative)",
    )
    max_slide_ratio: float | None = Field(
        None, gt=0,
        description="invalid when the evidence points, aligned from starts slide_m away in 16 horizontal "
        "directions, settle at least rival_m from the winner with more than this fraction of its score: "
        "nothing pins the translation (None: not checked; the lines-only decision sets it)",
    )
    slide_m: float = Field(1.5, gt=0, description="... the starts' distance [m]")
    view_check: bool = Field(
        True,
        description="partial views (verification/view.py): the view of a pair is the smaller azimuth coverage of "
        "its two scans (the share of 1 deg azimuth cells of the whole-scan range image, LandmarkSet.scan_ranges, "
        "that hold a return). Below view_whole the winner must also pass a co-visible overlap (each direction "
        "counted only over the points inside the other scan's observed azimuths) and a rival ratio of its tier "
        "(partial_*: view in [view_narrow, view_whole); narrow_*: below view_narrow). Whole-scan pairs, and sets "
        "without scan_ranges (view unknown), are decided as before. Thresholds chosen on courtyard and simulated "
        "partial views of the calibration split (bench/verification_partial_views.py --split cal; "
        "docs/verification.md, Session 15)",
    )
    view_whole: float = Field(
        0.9, ge=0, le=1,
        description="... a pair whose view is at least this is a whole-scan pair (every whole scan of "
        "bench/verification.py's five recordings covers >= 0.95; a 270 deg sector 0.75)",
    )
    view_narrow: float = Field(0.5, ge=0, le=1, description="... below this (a sector under 180 deg) a narrow view")
    partial_min_overlap: float = Field(
        PARTIAL[0], ge=0, le=1, description="... views in [view_narrow, view_whole): the co-visible overlap needed",
    )
    partial_max_rival_ratio: float = Field(
        PARTIAL[1], gt=0, le=1, description="... views in [view_narrow, view_whole): the rival ratio allowed",
    )
    narrow_min_overlap: float = Field(
        NARROW[0], ge=0, le=1, description="... views below view_narrow: the co-visible overlap needed",
    )
    narrow_max_rival_ratio: float = Field(
        NARROW[1], gt=0, le=1, description="... views below view_narrow: the rival ratio allowed",
    )
    min_landmark_overlap: float = Field(
        0.2, ge=0, le=1, description="without support points: graded share of landmarks with a counterpart"
    )
    min_landmarks_explained: int = Field(
        6, ge=1, description="without support points: fewest landmarks that must land on a counterpart"
    )
    min_translation_redundancy: float = Field(
        0.1, ge=0,
        description="without support points: every translation direction must be constrained, and every "
        "horizontal one with any one explained landmark left out (information eigenvalue >= this; chosen "
        "on fuzz seed 1 of bench/fuzz_validity.py, reported on seed 0)",
    )
    confidence_coef: tuple[float, float, float, float] = Field(
        (-7.761, 40.899, 6.718, -39.706),
        description="logistic calibration: sigmoid(c0 + c1 * overlap + c2 * (1 - rival_ratio) + c3 * conflict), "
        "fitted on the calibration split of bench/verification.py (conflict 0 without support points)",
    )
    min_valid_confidence: float = Field(
        0.5, ge=0, le=1,
        description="a result is valid only when its confidence reaches this. Why: the confidence is the calibrated "
        "probability that the answer is right, and a valid answer should be the likelier one; the thresholds alone "
        "let 180-deg flips of real courtyard pairs through at 0.13-0.40 (docs/verification.md, sessions 20-21). "
        "0.5 is the probability's midpoint, not fitted to any pairs",
    )
    lines_only: DecisionThresholds | None = Field(
        default_factory=lambda: DecisionThresholds(min_overlap=LINES_ONLY[0], max_rival_ratio=LINES_ONLY[1],
                                                   max_conflict=LINES_ONLY[2], max_slide_ratio=LINES_ONLY[3]),
        description="replace min_overlap / max_rival_ratio / max_conflict when the matcher matches lines only "
        "(landmark_types=['line']): poles alone leave more aliased answers that explain the points "
        "(chosen on the lines-only calibration split of bench/verification.py; None: the same "
        "thresholds for every mode)",
    )

    scans: DecisionThresholds | None = Field(
        default_factory=lambda: DecisionThresholds(
            min_overlap=SCANS[0], max_rival_ratio=SCANS[1], max_conflict=SCANS[2], confidence_coef=SCANS_CONFIDENCE,
            partial_min_overlap=SCANS_PARTIAL[0], partial_max_rival_ratio=SCANS_PARTIAL[1],
            narrow_min_overlap=SCANS_NARROW[0], narrow_max_rival_ratio=SCANS_NARROW[1]),
        description="replace min_overlap / max_rival_ratio / max_conflict (and the confidence) when the "
        "evidence is the raw scans' voxel clouds (ScanMatcher's evidence='support_then_scans'); chosen on the "
        "calibration split of bench/verification.py --evidence scans (None: the support points' thresholds)",
    )

    def for_landmark_types(self, types: list[str] | tuple[str, ...]) -> VerificationConfig:
        """The configuration the decision uses for a matcher restricted to ``types``."""
        if self.lines_only is None or set(types) != {"line"}:
            return self
        return self.model_copy(update=self.lines_only.thresholds())

    def for_evidence(self, types: list[str] | tuple[str, ...], kind: str) -> VerificationConfig:
        """The configuration the decision uses for ``types`` and an evidence of ``kind``
        ('support' or 'scans'): the raw scans' own thresholds replace the support points' ones
        (a denser, larger cloud explains other shares); lines-only keeps its own."""
        if kind == "scans" and self.scans is not None and set(types) != {"line"}:
            return self.model_copy(update=self.scans.thresholds())
        return self.for_landmark_types(types)
