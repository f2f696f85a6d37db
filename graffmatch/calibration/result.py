"""Shared core of both calibrations: GraffMatch on plane landmarks, registration, residuals.

Choice of ρ. The paper picks ρ so that the largest landmark separations land at the end of the
linear regime of the principal angle (~2 after scaling: ρ = 40 m for 80 m in KITTI). A
calibration rig is a room-sized scene: boards 2–8 m from the sensors, 1–12 m apart (mean
~6 m), so ρ = 4 m maps the largest separations to ~2–3 and keeps pairwise distances
discriminative. Anchor noise (board centres agree to ~1–3 cm between modalities) then moves a
distance by < 0.01, well under σ = 0.05 and ε = 0.2. With KITTI's ρ = 40 every separation
would shrink to < 0.3 and the consistency test would rest on the normals alone.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.errors import DegenerateGeometryError, GraffMatchError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.matcher import GraffMatchConfig, GraffMatcher, MatchResult
from graffmatch.registration.closed_form import register_landmarks
from graffmatch.verification.config import VerificationConfig

Array = NDArray[np.float64]

CALIBRATION_RHO = 4.0


def _plane_matcher_config() -> GraffMatchConfig:
    # A board rig has a handful of planes and no support points: verification may rest on 4
    # explained boards, without a spare board per direction, in a frame that need not be z-up
    # (the calibration adds its own residual and normal-spread gates).
    return GraffMatchConfig(landmark_types=["plane"], rho=CALIBRATION_RHO,
                            verification=VerificationConfig(min_landmarks_explained=4,
                                                            min_translation_redundancy=0.0))


class CalibrationConfig(BaseModel):
    """GraffMatch (planes only) and validity gates for an extrinsic calibration."""

    model_config = ConfigDict(extra="forbid")

    matcher: GraffMatchConfig = Field(
        default_factory=_plane_matcher_config,
        description="GraffMatch settings; planes only, rho = 4 m for a room-sized rig "
        "(see module docstring), epsilon/sigma as in the paper.",
    )
    min_planes: int = Field(
        3, ge=3, description="Fewer matched planes cannot fix rotation and translation."
    )
    reassociate: bool = Field(
        True,
        description="After GraffMatch, add every plane pair that agrees with the estimate "
        "(mutual nearest, within the gates below) and re-register: boards CLIPPER left out "
        "then still contribute. It can only add pairs consistent with the GraffMatch estimate.",
    )
    gate_angle_deg: float = Field(
        3.0, gt=0, description="Re-association gate on the normal angle [deg]."
    )
    gate_offset: float = Field(
        0.10, gt=0, description="Re-association gate on the plane offset [m]."
    )
    valid_angle_deg: float = Field(
        1.5,
        gt=0,
        description="Validity: median normal residual of the matched planes must not exceed "
        "this [deg] (boards: ~0.3 deg; a wrong or smeared match shows several degrees).",
    )
    valid_offset: float = Field(
        0.05, gt=0, description="Validity: median plane-offset residual must not exceed this [m]."
    )
    min_normal_spread: float = Field(
        0.15,
        ge=0,
        description="Smallest singular value of the matched unit normals / sqrt(k): below it "
        "the normals do not span 3D and the translation is unobservable (e.g. parallel boards).",
    )


@dataclass
class CalibrationResult:
    """An extrinsic ``T_target_source`` (maps source-sensor points into the target frame).

    ``residual_angle_deg`` / ``residual_offset`` are per matched plane, after alignment: the
    angle between normals [deg] and the mean distance of each anchor to the other plane [m].
    """

    T_target_source: Array
    source_name: str
    target_name: str
    associations: NDArray[np.int64]  # (k, 2) source index, target index
    kappa: float
    residual_angle_deg: Array
    residual_offset: Array
    n_planes_source: int
    n_planes_target: int
    valid: bool
    degenerate: bool
    message: str
    score: float = float("nan")
    n_graffmatch: int = 0  # associations chosen by GraffMatch (before re-association)
    timings: dict[str, float] = field(default_factory=dict)
    source_planes: LandmarkSet | None = None
    target_planes: LandmarkSet | None = None
    match: MatchResult | None = None

    @property
    def T_b_a(self) -> Array:
        """Alias for LiDAR–LiDAR calibration (source a, target b)."""
        return self.T_target_source

    @property
    def T_depth_camera(self) -> Array:
        """Alias for camera–depth calibration (source camera, target depth)."""
        return self.T_target_source

    @property
    def n_matched(self) -> int:
        return len(self.associations)

    def raise_if_invalid(self) -> CalibrationResult:
        if not self.valid:
            raise DegenerateGeometryError(f"calibration failed: {self.message}")
        return self

    def to_dict(self) -> dict:
        """JSON-friendly summary (no point data)."""
        return {
            f"T_{self.target_name}_{self.source_name}": self.T_target_source.tolist(),
            "associations": self.associations.tolist(),
            "kappa": float(self.kappa),
            "residual_angle_deg": self.residual_angle_deg.tolist(),
            "residual_offset_m": self.residual_offset.tolist(),
            "n_planes": {
                self.source_name: self.n_planes_source,
                self.target_name: self.n_planes_target,
            },
            "n_graffmatch": self.n_graffmatch,
            "valid": self.valid,
            "degenerate": self.degenerate,
            "message": self.message,
            "score": float(self.score),
            "timings_s": dict(self.timings),
        }

    def __repr__(self) -> str:
        ang = self.residual_angle_deg
        off = self.residual_offset
        res = (
            f"{np.median(ang):.2f} deg / {100 * np.median(off):.1f} cm median" if len(ang) else "-"
        )
        return (
            f"CalibrationResult(T_{self.target_name}_{self.source_name}, matched={self.n_matched} "
            f"of {self.n_planes_source}/{self.n_planes_target} planes, kappa={self.kappa:.3g}, "
            f"residuals {res}, valid={self.valid}, degenerate={self.degenerate}, "
            f"'{self.message}', total={1e3 * self.timings.get('total', float('nan')):.0f} ms)"
        )


def plane_residuals(
    source: LandmarkSet,
    target: LandmarkSet,
    associations: NDArray[np.int64],
    T_target_source: Array,
) -> tuple[Array, Array]:
    """Per associated pair: normal angle [deg] and mean anchor-to-other-plane distance [m]."""
    if len(associations) == 0:
        return np.zeros(0), np.zeros(0)
    s = source.transform(T_target_source)[associations[:, 0]]
    t = target[associations[:, 1]]
    ns, nt = s.directions, t.directions
    ang = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", ns, nt)), 0.0, 1.0)))
    d = s.anchors - t.anchors
    off = 0.5 * (np.abs(np.einsum("ij,ij->i", nt, d)) + np.abs(np.einsum("ij,ij->i", ns, d)))
    return ang, off


def _reassociate(
    source: LandmarkSet, target: LandmarkSet, T: Array, cfg: CalibrationConfig
) -> NDArray[np.int64]:
    """Mutual-nearest plane pairs under T within the angle and offset gates."""
    s = source.transform(T)
    ns, nt = s.directions, target.directions
    ang = np.degrees(np.arccos(np.clip(np.abs(ns @ nt.T), 0.0, 1.0)))
    d = s.anchors[:, None, :] - target.anchors[None, :, :]
    off = 0.5 * (np.abs(np.einsum("jk,ijk->ij", nt, d)) + np.abs(np.einsum("ik,ijk->ij", ns, d)))
    # Anchor distance breaks ties between parallel boards: nearest board centre wins.
    cost = np.linalg.norm(d, axis=2)
    ok = (ang <= cfg.gate_angle_deg) & (off <= cfg.gate_offset)
    cost = np.where(ok, cost, np.inf)
    i = np.arange(len(s))
    j = np.argmin(cost, axis=1)
    mutual = np.isfinite(cost[i, j]) & (np.argmin(cost, axis=0)[j] == i)
    return np.stack([i[mutual], j[mutual]], axis=1).astype(np.int64)


def _normal_spread(planes: LandmarkSet) -> float:
    if len(planes) == 0:
        return 0.0
    return float(np.linalg.svd(planes.directions, compute_uv=False)[-1] / np.sqrt(len(planes)))


def calibrate_planes(
    source: LandmarkSet,
    target: LandmarkSet,
    config: CalibrationConfig | None = None,
    source_name: str = "source",
    target_name: str = "target",
) -> CalibrationResult:
    """GraffMatch the two plane sets (no initial guess), register, and report residuals.

    Raises :class:`DegenerateGeometryError` when either side has fewer than ``min_planes``
    planes or when no transform can be estimated at all; a transform that exists but is badly
    conditioned (e.g. parallel boards) is returned with ``valid=False, degenerate=True``.
    """
    cfg = config or CalibrationConfig()
    source = source.of_type(LandmarkType.PLANE)
    target = target.of_type(LandmarkType.PLANE)
    ns, nt = len(source), len(target)
    if ns < cfg.min_planes or nt < cfg.min_planes:
        raise DegenerateGeometryError(
            f"need at least {cfg.min_planes} planes on each side, got {source_name}={ns}, "
            f"{target_name}={nt}: show more boards to the sensors"
        )
    t0 = time.perf_counter()
    try:
        match = GraffMatcher(cfg.matcher).match(source, target)
    except DegenerateGeometryError:
        raise
    except GraffMatchError as exc:
        raise DegenerateGeometryError(f"GraffMatch could not match the planes: {exc}") from exc
    t1 = time.perf_counter()
    assoc = np.asarray(match.associations, dtype=np.int64).reshape(-1, 2)
    if len(assoc) == 0 or match.T_target_source is None:
        raise DegenerateGeometryError(f"GraffMatch found no usable plane matches ({match.message})")
    T = np.asarray(match.T_target_source, dtype=float)
    kappa = float(match.kappa)
    degenerate = bool(match.degenerate)
    n_gm = len(assoc)
    if cfg.reassociate and not degenerate:
        extra = _reassociate(source, target, T, cfg)
        if len(extra) >= len(assoc):
            est = register_landmarks(source, target, extra, kappa_max=cfg.matcher.kappa_max)
            assoc, T = extra, np.asarray(est.T_target_source, float)
            kappa, degenerate = float(est.kappa), bool(est.degenerate)
    t2 = time.perf_counter()
    ang, off = plane_residuals(source, target, assoc, T)
    spread = _normal_spread(source[assoc[:, 0]])
    problems = []
    if len(assoc) < cfg.min_planes:
        problems.append(f"only {len(assoc)} planes matched (< {cfg.min_planes})")
    if spread < cfg.min_normal_spread:
        degenerate = True
        problems.append(
            f"matched board normals do not span 3D (spread {spread:.3f} < {cfg.min_normal_spread})"
        )
    if degenerate and not problems:
        problems.append(f"registration degenerate (kappa={kappa:.3g})")
    if not match.valid and not problems:
        problems.append(f"GraffMatch: {match.message}")
    if len(ang) and (np.median(ang) > cfg.valid_angle_deg or np.median(off) > cfg.valid_offset):
        problems.append(
            f"median residuals {np.median(ang):.2f} deg / {100 * np.median(off):.1f} cm exceed "
            f"{cfg.valid_angle_deg} deg / {100 * cfg.valid_offset:.0f} cm"
        )
    valid = not problems
    message = "ok" if valid else "; ".join(problems)
    timings = {"graffmatch": t1 - t0, "register": t2 - t1}
    return CalibrationResult(
        T_target_source=T,
        source_name=source_name,
        target_name=target_name,
        associations=assoc,
        kappa=kappa,
        residual_angle_deg=ang,
        residual_offset=off,
        n_planes_source=ns,
        n_planes_target=nt,
        valid=valid,
        degenerate=degenerate,
        message=message,
        score=float(getattr(match, "score", float("nan"))),
        n_graffmatch=n_gm,
        timings=timings,
        source_planes=source,
        target_planes=target,
        match=match,
    )
