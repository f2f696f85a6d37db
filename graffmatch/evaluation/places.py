"""Places, revisits, ground-truth matches, IIR cases and validity: the rules of a loop closure.

:class:`LoopClosureConfig` holds the paper's rules (Sec. V-A); the functions here apply them to
poses and landmark sets. :mod:`~graffmatch.evaluation.loop_closures` builds a dataset with them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from graffmatch.association.putative import count_all_to_all
from graffmatch.errors import DegenerateGeometryError
from graffmatch.geometry.distance import cross_distances
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.transforms import transform_errors
from graffmatch.lidar.extractor import LandmarkExtractorConfig

Array = NDArray[np.float64]


class LoopClosureConfig(BaseModel):
    """Every rule of the dataset preparation; defaults are the paper's."""

    model_config = ConfigDict(extra="forbid")

    place_spacing: float = Field(
        2.0, gt=0, description="Path length between consecutive places [m] (paper: 2 m)."
    )
    min_path_length: float = Field(
        50.0, ge=0, description="A revisit needs more path than this between the places [m] (50 m)."
    )
    max_distance: float = Field(
        16.0, gt=0, description="A revisit needs the sensors closer than this [m] (paper: 16 m)."
    )
    wide_baseline_min_distance: float | None = Field(
        None,
        gt=0,
        description="Also accept pairs at least this far apart (and < max_distance) whatever the "
        "path between them: wide-baseline pairs of short walks. None: the paper's rule only [m].",
    )
    tau_d_deg: float = Field(
        6.0, gt=0, description="Gate on the GT-aligned invariant d_Graff of a true match [deg]."
    )
    rho: float = Field(
        40.0, gt=0, description="Scale rho of the invariant d_Graff [m] (paper: 40)."
    )
    min_true_matches: int = Field(
        4, ge=0, description="A loop closure needs MORE than this many true matches (paper: 4)."
    )
    kappa_max: float = Field(
        1e3, gt=1, description="A loop closure needs a registration condition number below this."
    )
    max_rotation_error_deg: float = Field(
        5.0, gt=0, description="Registration with the true matches must be within this [deg]."
    )
    max_translation_error: float = Field(
        1.0, gt=0, description="Registration with the true matches must be within this [m]."
    )
    case_thresholds: tuple[float, float] = Field(
        (0.05, 0.03),
        description="IIR bounds: case 1 if IIR >= [0], case 2 if >= [1], else case 3.",
    )
    max_places: int | None = Field(
        None, ge=2, description="Keep only the first places (quick builds and tests)."
    )
    max_pairs: int | None = Field(
        None, ge=1, description="Keep at most this many revisits, evenly spaced (None: all)."
    )
    negative_min_distance: float | None = Field(
        60.0,
        gt=0,
        description="Negative pairs: places at least this far apart [m], which share nothing; "
        "None: no negatives. Every method's validity flag is scored on them.",
    )
    max_negatives: int | None = Field(
        None,
        ge=0,
        description="At most this many negative pairs, evenly spaced (None: as many as there "
        "are loop closures).",
    )
    max_landmarks_per_type: int | None = Field(
        None,
        ge=1,
        description="Keep at most this many lines and this many planes per place, the largest "
        "by 'extent' (length / area); None keeps all (the paper). Fewer, more salient landmarks "
        "raise the IIR: with n planes per scan the IIR cannot exceed about 1/n.",
    )
    use_labels: bool = Field(
        True, description="Pass the dataset's semantic labels to the extractor when it has them."
    )
    store_support_points: bool = Field(
        True, description="Store the support points in the landmark files (ICP, BruteForceRMSE)."
    )
    workers: int = Field(
        2, ge=1, description="Processes extracting landmarks (1: in this process)."
    )
    extractor: LandmarkExtractorConfig = Field(
        default_factory=LandmarkExtractorConfig, description="Front-end configuration."
    )

    @model_validator(mode="after")
    def _check(self) -> LoopClosureConfig:
        hi, lo = self.case_thresholds
        if not 0 <= lo <= hi <= 1:
            raise ValueError(
                "case_thresholds must be (case-1 bound, case-2 bound), 1 >= hi >= lo >= 0"
            )
        wb = self.wide_baseline_min_distance
        if wb is not None and wb >= self.max_distance:
            raise ValueError("wide_baseline_min_distance must be below max_distance")
        return self


# ---- places and revisits -------------------------------------------------------------------
def path_lengths(poses: Array) -> Array:
    """Cumulative path length (n,) along the trajectory of (n, 4, 4) poses [m]."""
    P = np.asarray(poses, dtype=float)[:, :3, 3]
    steps = np.linalg.norm(np.diff(P, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def select_places(poses: Array, spacing: float = 2.0) -> NDArray[np.int64]:
    """Scan indices of the places: the first scan, then the first scan at least ``spacing`` of
    path after the previous place (greedy, as Scan Context's place sampling)."""
    s = path_lengths(poses)
    if len(s) == 0:
        return np.zeros(0, np.int64)
    places = [0]
    nxt = s[0] + spacing
    # Each place is found by a binary search, so this is O(places log n), not a loop over scans.
    while True:
        j = int(np.searchsorted(s, nxt - 1e-9, side="left"))
        if j >= len(s):
            break
        places.append(j)
        nxt = s[j] + spacing
    return np.asarray(places, dtype=np.int64)


def find_revisits(
    poses: Array,
    places: NDArray[np.int64],
    min_path_length: float = 50.0,
    max_distance: float = 16.0,
    wide_baseline_min_distance: float | None = None,
) -> NDArray[np.int64]:
    """(m, 2) scan indices (later place p, earlier place p') of the revisits, sorted."""
    places = np.asarray(places, dtype=np.int64)
    if len(places) < 2:
        return np.zeros((0, 2), np.int64)
    s = path_lengths(poses)[places]
    X = np.asarray(poses, dtype=float)[places, :3, 3]
    pairs = cKDTree(X).query_pairs(r=max_distance, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 2), np.int64)
    a, b = np.minimum(pairs[:, 0], pairs[:, 1]), np.maximum(pairs[:, 0], pairs[:, 1])
    d = np.linalg.norm(X[b] - X[a], axis=1)
    keep = (d < max_distance) & (s[b] - s[a] > min_path_length)
    if wide_baseline_min_distance is not None:
        keep |= (d >= wide_baseline_min_distance) & (d < max_distance)
    out = np.stack([places[b[keep]], places[a[keep]]], axis=1)
    order = np.lexsort((out[:, 1], out[:, 0]))
    return out[order]


def find_negatives(
    poses: Array, places: NDArray[np.int64], min_distance: float, max_count: int
) -> NDArray[np.int64]:
    """(m, 2) scan indices (later place, earlier place) of places at least ``min_distance``
    apart: pairs without overlap. At most ``max_count``, evenly spaced over all such pairs."""
    places = np.asarray(places, dtype=np.int64)
    if len(places) < 2 or max_count <= 0:
        return np.zeros((0, 2), np.int64)
    X = np.asarray(poses, dtype=float)[places, :3, 3]
    a, b = np.triu_indices(len(places), 1)
    far = np.flatnonzero(np.linalg.norm(X[b] - X[a], axis=1) >= min_distance)
    if len(far) > max_count:
        far = far[np.unique(np.linspace(0, len(far) - 1, max_count).round().astype(np.int64))]
    return np.stack([places[b[far]], places[a[far]]], axis=1).reshape(-1, 2)


# ---- ground-truth matches, IIR, validity ---------------------------------------------------
def ground_truth_matches(
    source: LandmarkSet,
    target: LandmarkSet,
    T_target_source: Array,
    tau_d_deg: float = 6.0,
    rho: float = 40.0,
) -> tuple[NDArray[np.int64], Array]:
    """True matches (k, 2) (source, target) and their GT-aligned distances [rad].

    Linear-sum assignment on the invariant d_Graff of the aligned sets; only same-type pairs
    below the gate are kept, so every landmark is matched at most once.
    """
    if len(source) == 0 or len(target) == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0)
    aligned = source.without_points().transform(T_target_source)
    D = cross_distances(aligned, target.without_points(), rho=rho)
    gate = np.deg2rad(tau_d_deg)
    feasible = D < gate
    if not feasible.any():
        return np.zeros((0, 2), np.int64), np.zeros(0)
    # Infeasible entries get a cost above any feasible sum so the assignment never trades a
    # gated match for them; they are dropped afterwards.
    cost = np.where(feasible, D, gate * (min(D.shape) + 1))
    r, c = linear_sum_assignment(cost)
    ok = feasible[r, c]
    matches = np.stack([r[ok], c[ok]], axis=1).astype(np.int64)
    return matches, D[r[ok], c[ok]]


def possible_matches(source: LandmarkSet, target: LandmarkSet) -> int:
    """Number of putative all-to-all (same-type) associations: sum n_i(type) n_j(type)."""
    return count_all_to_all(source.types, target.types)


def iir_case(iir: float, thresholds: Sequence[float] = (0.05, 0.03)) -> int:
    """Case 1 (IIR >= 0.05), 2 (0.03 <= IIR < 0.05) or 3 (IIR < 0.03)."""
    hi, lo = thresholds
    if iir >= hi:
        return 1
    if iir >= lo:
        return 2
    return 3


@dataclass
class Validity:
    """Outcome of the loop-closure rules for one revisit."""

    valid: bool
    reason: str
    kappa: float = float("nan")
    rotation_error_deg: float = float("nan")
    translation_error: float = float("nan")


def check_validity(
    source: LandmarkSet,
    target: LandmarkSet,
    matches: NDArray[np.int64],
    T_target_source: Array,
    config: LoopClosureConfig,
) -> Validity:
    """Apply the paper's rules: > 4 matches, kappa < kappa_max, errors < 5 deg and 1 m."""
    from graffmatch.registration.closed_form import register_landmarks

    if len(matches) <= config.min_true_matches:
        return Validity(False, "few_matches")
    try:
        est = register_landmarks(
            source.without_points(), target.without_points(), matches, kappa_max=config.kappa_max
        )
    except DegenerateGeometryError:
        return Validity(False, "degenerate")
    kappa = float(est.kappa)
    if (
        bool(getattr(est, "degenerate", False))
        or not np.isfinite(kappa)
        or kappa >= config.kappa_max
    ):
        return Validity(False, "ill_conditioned", kappa=kappa)
    rot, trans = transform_errors(est.T_target_source, T_target_source)
    v = Validity(False, "registration_error", kappa, float(rot), float(trans))
    if rot < config.max_rotation_error_deg and trans < config.max_translation_error:
        v.valid, v.reason = True, "valid"
    return v


# ---- per-place landmark extraction (parallel, cached) ---------------------------------------
def keep_most_salient(ls: LandmarkSet, max_per_type: int | None) -> LandmarkSet:
    """At most ``max_per_type`` landmarks of each type, the largest by ``extent`` (ties and
    missing extents: support, then original order); the original order is kept."""
    if max_per_type is None or len(ls) == 0:
        return ls
    n = len(ls)
    extent = np.nan_to_num(np.asarray(ls.attributes.get("extent", np.zeros(n)), float).reshape(n))
    support = np.nan_to_num(np.asarray(ls.attributes.get("support", np.zeros(n)), float).reshape(n))
    keep = np.zeros(n, bool)
    for t in np.unique(ls.types):
        idx = np.flatnonzero(ls.types == t)
        order = np.lexsort((idx, -support[idx], -extent[idx]))
        keep[idx[order[:max_per_type]]] = True
    return ls[np.flatnonzero(keep)]
