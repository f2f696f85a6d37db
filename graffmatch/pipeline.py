"""One configured scan-to-scan path: ``ScanMatcher(config).register(source, target)``.

Extraction, verified matching and refinement in one object that holds the extractor and the
matcher once. It is the single code path for :func:`register_scans`, ``graffmatch register``,
the demo, the evaluation's GraffMatch methods and ``graffmatch loops``; its config is a nested
pydantic model, written next to every result.

With raw scans at hand, ``evidence='support_then_scans'`` (the default) verifies again on the scans' non-ground
voxel clouds (the extractor's ``last_cloud``) when the landmarks' support points give no valid
answer and both scans are whole views (``scan_fallback_min_view``), at thresholds chosen for that
evidence on whole scans (``VerificationConfig.scans``). A valid answer of the support points is re-aligned by ICP on
the scans' non-ground clouds (``scan_realign_m``): support points cannot pin the pose of real scans 8-16 m apart
(courtyard answers 1-2 m off), the scans can. With ``refinement.method='icp'`` the winner is refined by ICP on the
voxel-downsampled non-ground scans (or on the matched landmarks' points). ``register`` hands ICP the extractor's own voxel cloud
of each scan with its normals (``LandmarkExtractor.last_cloud``), so nothing is voxelised or
normal-estimated twice (``refine`` called with raw scans only re-voxelises them). A refinement
that moves the verified answer by more than a rival would differ (``verification.rival_deg`` /
``rival_m``) makes the result invalid: landmarks and points then disagree about where the scans
are.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.transforms import rotation_error_deg
from graffmatch.lidar.extractor import LandmarkExtractor, LandmarkExtractorConfig
from graffmatch.lidar.voxels import VoxelCloud
from graffmatch.matcher import GraffMatchConfig, GraffMatcher, MatchResult
from graffmatch.verification.evidence import point_overlaps, reach_shares, voxel_downsample
from graffmatch.verification.verify import Evidence, evidence_for, scan_evidence
from graffmatch.verification.view import set_coverage


class RefinementConfig(BaseModel):
    """ICP after the verified landmark registration (the paper's GraffMatch+ICP)."""

    model_config = ConfigDict(extra="forbid")

    method: Literal["none", "icp"] = Field("none", description="none, or icp")
    points: Literal["scans", "landmarks"] = Field(
        "scans",
        description="scans: the raw scans without their ground (when given); landmarks: the matched "
        "landmarks' support points only",
    )
    reuse_extractor_cloud: bool = Field(
        True,
        description="scans: run ICP on the extractor's voxelised non-ground cloud and its normals "
        "(computed once during extraction) instead of re-voxelising the raw scans",
    )
    voxel: float = Field(0.4, gt=0, description="voxel size of the scans used by ICP when they are re-voxelised [m]")
    max_points: int = Field(8000, ge=10, description="most points per scan used by ICP")
    max_source_points: int = Field(
        3000, ge=10, description="most source points used with the extractor's cloud (even stride)"
    )
    ground_clearance: float = Field(0.3, ge=0, description="points this close above the ground plane are ground [m]")
    max_correspondence_distance: float = Field(0.5, gt=0, description="ICP correspondence distance [m]")
    max_iterations: int = Field(15, ge=1, description="ICP iterations")
    relative_change: float = Field(
        1e-4, gt=0, description="stop when fitness and inlier RMSE change by less than this (relative)"
    )
    point_to_plane: bool = Field(True, description="point-to-plane (else point-to-point)")
    normal_radius: float = Field(1.0, gt=0, description="radius of the target normals [m]")


class ScanMatcherConfig(BaseModel):
    """Every setting of the scan-to-scan path, nested by stage."""

    model_config = ConfigDict(extra="forbid")

    extractor: LandmarkExtractorConfig = Field(default_factory=LandmarkExtractorConfig)
    matcher: GraffMatchConfig = Field(default_factory=GraffMatchConfig)
    refinement: RefinementConfig = Field(default_factory=RefinementConfig)
    evidence: Literal["support", "support_then_scans"] = Field(
        "support_then_scans",
        description="what register() verifies hypotheses on: support (the landmarks' support points only, as "
        "match() on landmark sets) or support_then_scans (the default: when the support points give no valid "
        "answer and both scans are whole views, see scan_fallback_min_view, verify again on the scans' non-ground "
        "voxel clouds from the extractor, matcher.verification.scan_voxel / scan_max_points, at "
        "verification.scans' thresholds, chosen on the whole-scan calibration split of bench/verification.py "
        "--evidence scans: sim-downtown test recall 0.917 -> 0.967 at precision 1.000, docs/verification.md "
        "Sessions 14-15; a lines-only matcher keeps the support points only)",
    )
    scan_fallback_min_view: float = Field(
        0.9, ge=0, le=1,
        description="the raw-scan pass runs only when both scans cover at least this share of azimuths "
        "(verification.view.set_coverage; unknown coverage: no raw-scan pass). Its thresholds were chosen on "
        "whole scans, and on cropped views its extra answers were right less often (test crops: 7 wrong against "
        "the support points' 3, bench/verification_partial_views.py, docs/verification.md Session 15); every "
        "whole scan of the verification bench covers >= 0.953. 0: on every pair",
    )
    scan_realign_m: float | None = Field(
        1.0, gt=0,
        description="with the scans at hand: a valid answer of the support points is re-aligned by point-to-plane "
        "ICP on the two scans' non-ground voxel clouds, correspondences up to this distance [m] (the rival "
        "distance, verification.rival_m: an answer closer to the truth than a rival would be is the same place); "
        "the re-aligned pose is returned when it puts at least as many of the source's points within that distance "
        "of the target's. Support points cannot pin the pose of scans 8-16 m apart in the real courtyard: 19 of "
        "its 3,275 valid answers were 1-2.2 m off (turned 1-5 deg about a horizontal axis); the scans fix 16 and "
        "turn none of the 3,256 right ones wrong (docs/verification.md Session 22). None: off",
    )
    scan_realign_iterations: int = Field(30, ge=1, description="ICP iterations of the re-alignment")


@dataclass
class ScanRegistration:
    """A :class:`MatchResult` plus the landmarks it was computed from."""

    result: MatchResult
    source_landmarks: LandmarkSet
    target_landmarks: LandmarkSet

    def __getattr__(self, name: str):  # T_target_source, valid, confidence, ... of the result
        if name == "result":  # not yet set (e.g. during unpickling)
            raise AttributeError(name)
        return getattr(self.result, name)

    def __repr__(self) -> str:
        return (
            f"ScanRegistration(source={self.source_landmarks.counts()}, "
            f"target={self.target_landmarks.counts()},\n {self.result!r})"
        )


def _as_points(points: ArrayLike, name: str) -> NDArray[np.float64]:
    try:
        P = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name} must be an (N, 3|4) array of numbers: {exc}") from None
    if P.ndim != 2 or P.shape[1] < 3:
        raise InvalidInputError(f"{name} must be an (N, 3|4) array, got shape {P.shape}")
    return P[:, :3]


def non_ground_points(points: ArrayLike, landmarks: LandmarkSet, clearance: float) -> NDArray[np.float64]:
    """Scan points not on or just above the ground plane landmark (all points if none)."""
    P = _as_points(points, "points")
    P = P[np.all(np.isfinite(P), axis=1)]
    g = landmarks.attributes.get("is_ground")
    if g is None or not np.any(np.asarray(g) > 0.5):
        return P
    i = int(np.flatnonzero(np.asarray(g) > 0.5)[0])
    n = landmarks.directions[i]
    n = n if n[2] >= 0 else -n
    h = (P - landmarks.anchors[i]) @ n
    return P[h > clearance]


class ScanMatcher:
    """Register LiDAR scans without an initial guess: extract, match, verify, refine.

    Example::

        sm = ScanMatcher()
        reg = sm.register(source_points, target_points)
        if reg.valid:
            T = reg.T_target_source  # maps source-frame points into the target frame
    """

    def __init__(self, config: ScanMatcherConfig | None = None) -> None:
        self.config = config or ScanMatcherConfig()
        self.extractor = LandmarkExtractor(self.config.extractor)
        self.matcher = GraffMatcher(self.config.matcher)

    def extract(self, points: ArrayLike, labels: ArrayLike | None = None) -> LandmarkSet:
        """Landmarks of one scan (with support points, which verification uses)."""
        return self.extractor.extract(points, labels)

    def match(self, source: LandmarkSet, target: LandmarkSet, evidence: Evidence | None = None) -> MatchResult:
        """Verified match of two landmark sets (e.g. loaded from compact files); ``evidence``:
        what to verify on instead of their support points (``register`` passes the scans')."""
        return self.matcher.match(source, target, evidence=evidence)

    def refine(
        self, result: MatchResult, source: LandmarkSet, target: LandmarkSet,
        source_points: ArrayLike | None = None, target_points: ArrayLike | None = None,
        source_cloud: VoxelCloud | None = None, target_cloud: VoxelCloud | None = None,
    ) -> MatchResult:
        """ICP from the verified transform (in place); invalid when ICP moves it by more than a
        distinct rival would differ. Needs a transform; a no-op for method 'none'.

        ``source_cloud`` / ``target_cloud`` are the extractor's voxel clouds of the scans
        (:attr:`LandmarkExtractor.last_cloud`); with ``reuse_extractor_cloud`` they replace the
        raw scans, so nothing is voxelised or normal-estimated twice."""
        rc = self.config.refinement
        if rc.method == "none" or result.T_target_source is None:
            return result
        from graffmatch.registration.icp import matched_support_points, refine_icp

        t0 = time.perf_counter()
        scans = (self._scan_icp_points(source, target, source_points, target_points, source_cloud, target_cloud)
                 if rc.points == "scans" else None)
        if scans is not None:
            ps, pt, normals = scans
            used = "scans"  # their voxelised non-ground points (the extractor's, when given)
        else:
            if source.points is None or target.points is None:
                raise InvalidInputError(
                    "ICP refinement needs the scans or the landmarks' support points (extract with points)"
                )
            if len(result.associations) == 0:
                raise InvalidInputError("ICP refinement: the matcher selected no associations")
            ps, pt = matched_support_points(source, target, result.associations)
            normals = None
            used = "landmarks"
        if len(ps) < 10 or len(pt) < 10:
            raise InvalidInputError(f"ICP refinement: too few points ({len(ps)} source, {len(pt)} target)")
        T0 = result.T_target_source
        T, fitness, rmse = refine_icp(ps, pt, T0, rc.max_correspondence_distance, rc.max_iterations,
                                      rc.point_to_plane, rc.normal_radius, normals,
                                      rc.relative_change, rc.relative_change)
        rot = rotation_error_deg(T[:3, :3], T0[:3, :3])
        tr = float(np.linalg.norm(T[:3, 3] - T0[:3, 3]))
        result.info.update(icp_fitness=fitness, icp_rmse=rmse, icp_points=used,
                           icp_n_source=len(ps), icp_n_target=len(pt),
                           icp_correction_deg=rot, icp_correction_m=tr, T_before_icp=T0.tolist())
        result.T_target_source = np.asarray(T, dtype=np.float64)
        result.timings["icp"] = time.perf_counter() - t0
        result.timings["total"] = sum(v for k, v in result.timings.items() if k != "total")
        vcfg = self.config.matcher.verification
        if result.valid and (rot > vcfg.rival_deg or tr > vcfg.rival_m):
            result.valid = False
            result.confidence = min(result.confidence, 0.5)
            result.message = (f"ICP moved the verified answer by {rot:.1f} deg / {tr:.2f} m "
                              f"(> {vcfg.rival_deg} deg / {vcfg.rival_m} m): landmarks and points disagree")
        return result

    def match_scans(
        self, source: LandmarkSet, target: LandmarkSet,
        source_points: ArrayLike | None = None, target_points: ArrayLike | None = None,
        source_cloud: VoxelCloud | None = None, target_cloud: VoxelCloud | None = None,
    ) -> MatchResult:
        """:meth:`match` with the configured ``evidence``: the support points, then, with
        'support_then_scans' and both scans at hand (their extractor clouds, else the raw points),
        the raw scans when the support points give no valid answer."""
        result = self.match(source, target)
        mcfg = self.config.matcher
        have = all(c is not None or p is not None for c, p in ((source_cloud, source_points),
                                                                 (target_cloud, target_points)))
        if (self.config.evidence == "support_then_scans" and have and not result.valid
                and mcfg.verification.enabled and set(mcfg.landmark_types) != {"line"}
                and self._whole_views(source, target)):
            result = self._scan_pass(result, source, target, self._scan_points(source_points, source, source_cloud),
                                     self._scan_points(target_points, target, target_cloud))
        elif (result.valid and self.config.scan_realign_m is not None and result.T_target_source is not None
              and result.info.get("evidence_source") == "support"):
            self._realign_on_scans(result, source, target, source_points, target_points, source_cloud, target_cloud)
        return result

    def _scan_icp_points(
        self, source: LandmarkSet, target: LandmarkSet, source_points: ArrayLike | None,
        target_points: ArrayLike | None, source_cloud: VoxelCloud | None, target_cloud: VoxelCloud | None,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64] | None] | None:
        """(source points, target points, target normals or None) of the two scans for ICP: the extractor's
        voxelised non-ground clouds with their normals (``reuse_extractor_cloud``), else the raw scans without their
        ground, voxelised; None without the scans."""
        rc = self.config.refinement
        if source_cloud is not None and target_cloud is not None and rc.reuse_extractor_cloud:
            ps = source_cloud.points
            if len(ps) > rc.max_source_points:
                ps = ps[np.linspace(0, len(ps) - 1, rc.max_source_points).astype(np.int64)]
            return ps, target_cloud.points, target_cloud.normals
        if source_points is not None and target_points is not None:
            ps = voxel_downsample(non_ground_points(source_points, source, rc.ground_clearance), rc.voxel, rc.max_points)
            pt = voxel_downsample(non_ground_points(target_points, target, rc.ground_clearance), rc.voxel, rc.max_points)
            return ps, pt, None
        return None

    def _realign_on_scans(
        self, result: MatchResult, source: LandmarkSet, target: LandmarkSet, source_points: ArrayLike | None,
        target_points: ArrayLike | None, source_cloud: VoxelCloud | None, target_cloud: VoxelCloud | None,
    ) -> None:
        """Re-align a valid support-point answer on the scans (``scan_realign_m``), in place: the ICP pose replaces it
        when it puts at least as many source points within reach of the target as the answer did. ``overlap`` is then
        the re-aligned pose's own (support points); ``info`` keeps the answer (``T_support``) and the move."""
        from graffmatch.registration.icp import refine_icp

        scans = self._scan_icp_points(source, target, source_points, target_points, source_cloud, target_cloud)
        if scans is None or min(len(scans[0]), len(scans[1])) < 10:
            return
        t0 = time.perf_counter()
        ps, pt, normals = scans
        d = float(self.config.scan_realign_m)  # type: ignore[arg-type]
        rc = self.config.refinement
        T0 = np.asarray(result.T_target_source, dtype=np.float64)
        T, _fit, _rmse = refine_icp(ps, pt, T0, d, self.config.scan_realign_iterations, True, rc.normal_radius,
                                    normals, rc.relative_change, rc.relative_change)
        before, after = (float(f) for f in reach_shares(ps, pt, np.stack([T0, T]), d))
        rot = rotation_error_deg(T[:3, :3], T0[:3, :3])
        tr = float(np.linalg.norm(T[:3, 3] - T0[:3, 3]))
        kept = after >= before
        result.info.update(scan_realign={"applied": kept, "moved_deg": rot, "moved_m": tr,
                                         "fitness_before": before, "fitness_after": after})
        if kept:
            result.info["T_support"] = T0.tolist()
            result.T_target_source = T
            vc = self.config.matcher.verification
            ev = evidence_for(source, target, vc)  # the support points the answer was verified on
            result.overlap = float(point_overlaps(ev.source, ev.target, T[None], vc.inlier_m).mean())  # type: ignore[arg-type]
        result.timings["scan_realign"] = time.perf_counter() - t0
        result.timings["total"] = sum(v for k, v in result.timings.items() if k != "total")

    def _whole_views(self, source: LandmarkSet, target: LandmarkSet) -> bool:
        """Both scans cover at least ``scan_fallback_min_view`` of the azimuths (the raw-scan
        thresholds' calibration domain; 0 accepts any pair, also of unknown coverage)."""
        lo = self.config.scan_fallback_min_view
        if lo <= 0:
            return True
        cov = [set_coverage(source), set_coverage(target)]
        return all(c is not None and c >= lo for c in cov)

    def _scan_pass(self, first: MatchResult, src: LandmarkSet, tgt: LandmarkSet,
                   source_points: NDArray[np.float64], target_points: NDArray[np.float64]) -> MatchResult:
        """Verify again on the raw scans' evidence after an invalid support-point pass: its
        result when valid (``info["support_message"]`` keeps why the support points refused),
        else the first with the scans' reason appended. Where true poses explain too little of
        the landmarks' support (a street of repeating facades, sim-downtown) the whole scans
        still do; the support points stay first, where they are the sharper evidence (courtyard
        rivals, ``docs/verification.md``, Session 14)."""
        t0 = time.perf_counter()
        ev = scan_evidence(src, tgt, source_points, target_points, self.config.matcher.verification)
        t_ev = time.perf_counter() - t0
        if ev.kind != "scans":  # a scan left too few points: nothing new to verify on
            first.timings["scan_evidence"] = t_ev
            return first
        second = self.match(src, tgt, ev)
        if second.valid:
            second.info["support_message"] = first.message
            second.timings = {"scan_evidence": t_ev, **second.timings, "support_pass": first.timings.get("total", 0.0)}
            return second
        first.message = f"{first.message}; raw scans: {second.message}"
        first.info["scan_evidence_message"] = second.message
        first.timings["scan_evidence"] = t_ev
        first.timings["scan_pass"] = second.timings.get("total", 0.0)
        return first

    def _scan_points(self, points: ArrayLike | None, landmarks: LandmarkSet,
                     cloud: VoxelCloud | None) -> NDArray[np.float64]:
        """A scan's non-ground points for raw-scan evidence: the extractor's voxel cloud (no second
        pass over the scan), else the scan without its ground plane."""
        if cloud is not None and len(cloud) >= 10:
            return cloud.points
        assert points is not None
        return non_ground_points(points, landmarks, self.config.refinement.ground_clearance)

    def register(
        self, source_points: ArrayLike, target_points: ArrayLike,
        source_labels: ArrayLike | None = None, target_labels: ArrayLike | None = None,
    ) -> ScanRegistration:
        """Register two scans ((N, 3|4) arrays, sensor frames); ``T_target_source`` maps source
        points into the target frame."""
        t0 = time.perf_counter()
        src = self.extract(source_points, source_labels)
        src_cloud = self.extractor.last_cloud
        tgt = self.extract(target_points, target_labels)
        tgt_cloud = self.extractor.last_cloud
        t_extract = time.perf_counter() - t0
        for name, ls in (("source", src), ("target", tgt)):
            if len(ls) < 2:
                raise InvalidInputError(
                    f"{name} scan gave {len(ls)} landmark(s); at least 2 are needed to match"
                )
        result = self.match_scans(src, tgt, source_points, target_points, src_cloud, tgt_cloud)
        result.timings = {"extraction": t_extract, **result.timings}
        self.refine(result, src, tgt, source_points, target_points, src_cloud, tgt_cloud)
        result.timings["total"] = sum(v for k, v in result.timings.items() if k != "total")
        return ScanRegistration(result, src, tgt)


def register_scans(
    source_points: ArrayLike,
    target_points: ArrayLike,
    source_labels: ArrayLike | None = None,
    target_labels: ArrayLike | None = None,
    extractor_config: LandmarkExtractorConfig | None = None,
    matcher_config: GraffMatchConfig | None = None,
    refine_icp: bool = False,
    config: ScanMatcherConfig | None = None,
) -> ScanRegistration:
    """Register two LiDAR scans ((N, 3|4) arrays, sensor frames) without an initial guess.

    A shortcut for ``ScanMatcher(config).register(...)``; ``extractor_config``,
    ``matcher_config`` and ``refine_icp`` override the matching parts of ``config``.
    """
    cfg = config or ScanMatcherConfig()
    updates: dict = {}
    if extractor_config is not None:
        updates["extractor"] = extractor_config
    if matcher_config is not None:
        updates["matcher"] = matcher_config
    if refine_icp:
        updates["refinement"] = cfg.refinement.model_copy(update={"method": "icp"})
    if updates:
        cfg = cfg.model_copy(update=updates)
    return ScanMatcher(cfg).register(source_points, target_points, source_labels, target_labels)
