"""Putative associations: which landmark of the source may correspond to which of the target.

The paper associates every same-type pair (:func:`all_to_all`). :class:`GatingConfig` drops the
pairs whose view-robust attributes disagree (ground vs not, tilt to gravity, pole radius, loose
length and area ratios) before the consistency graph is built: fewer vertices, and the edges fall
roughly with the square of the kept fraction.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType


def all_to_all(types_i: ArrayLike, types_j: ArrayLike) -> NDArray[np.int64]:
    """Every same-type pair (a, b), the paper's default (lines never match planes).

    Ordered by type, then source index, then target index. Returns (m, 2).
    """
    ti = np.asarray(types_i).reshape(-1)
    tj = np.asarray(types_j).reshape(-1)
    blocks = []
    for t in np.union1d(np.unique(ti), np.unique(tj)):
        a = np.flatnonzero(ti == t)
        b = np.flatnonzero(tj == t)
        if a.size and b.size:
            aa, bb = np.meshgrid(a, b, indexing="ij")
            blocks.append(np.stack([aa.ravel(), bb.ravel()], axis=1))
    if not blocks:
        return np.zeros((0, 2), dtype=np.int64)
    return np.concatenate(blocks).astype(np.int64)


def check_associations(associations: ArrayLike, n_i: int, n_j: int) -> NDArray[np.int64]:
    """Validate an explicit (m, 2) association list against the set sizes."""
    A = np.asarray(associations)
    if A.ndim != 2 or A.shape[1] != 2:
        raise InvalidInputError(f"associations must have shape (m, 2), got {A.shape}")
    if A.size and not np.issubdtype(A.dtype, np.integer):
        raise InvalidInputError("associations must be integer indices")
    A = A.astype(np.int64)
    if A.size and (A.min() < 0 or A[:, 0].max() >= n_i or A[:, 1].max() >= n_j):
        raise InvalidInputError("association index out of range")
    # a pair (a, b) in range is the key a n_j + b: duplicates are equal neighbours of the sorted
    # keys (np.unique(A, axis=0) sorted a structured view: 0.6 ms for W1's 708 pairs)
    keys = np.sort(A[:, 0] * n_j + A[:, 1])
    if keys.size > 1 and bool(np.any(keys[1:] == keys[:-1])):
        raise InvalidInputError("associations contain duplicates")
    return A


def count_all_to_all(types_i: ArrayLike, types_j: ArrayLike) -> int:
    """m = sum over types of n_i(type) * n_j(type), without building the list."""
    ti = np.asarray(types_i).reshape(-1)
    tj = np.asarray(types_j).reshape(-1)
    return int(sum(np.sum(ti == t) * np.sum(tj == t) for t in np.unique(ti)))


class GatingConfig(BaseModel):
    """Which same-type associations to keep, from attributes that survive partial views.

    Every gate is loose on purpose (thresholds above the largest disagreement seen among the
    true matches of sim-downtown and balm_courtyard, see docs/performance.md), lets a landmark
    pair pass when either attribute is missing or NaN, and can be switched off (None). The pole
    radius and line length gates are off by default: on held-out sim-suburban, true matches
    disagreed by up to 8.5x in radius and 3.3x in length (thin trunks, partial views), so
    ratios chosen on the training suites (5x, 3x) dropped 1.3 % of its true associations.

    The tilt and ground gates compare directions with gravity, which the sensor's z axis only is
    when the sensor is level. ``level_sensor=None`` decides per scan pair: both scans must have
    a ground landmark ('is_ground') whose normal is within ``level_tolerance_deg`` of z (a
    hand-held scan tilted by 10-30 degrees then keeps every tilt)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(True, description="False: all same-type associations (the paper's)")
    level_sensor: bool | None = Field(
        None, description="None: detect from the ground landmarks; True/False: assume"
    )
    level_tolerance_deg: float = Field(5.0, gt=0, description="ground normal vs z for 'level'")
    ground: bool = Field(True, description="ground only with ground (level pairs)")
    tilt_deg: float | None = Field(
        10.0, gt=0, description="largest difference of tilt to the z axis [deg] (level pairs)"
    )
    radius_ratio: float | None = Field(
        None, ge=1, description="largest ratio of pole radii ('radius'), beyond radius_slack_m"
    )
    radius_slack_m: float = Field(0.05, ge=0, description="radii closer than this always pass [m]")
    length_ratio: float | None = Field(
        None, ge=1, description="largest ratio of line lengths ('extent' of lines)"
    )
    area_ratio: float | None = Field(
        40.0, ge=1, description="largest ratio of plane areas ('extent' of planes)"
    )


def _ground_tilt_deg(ls: LandmarkSet, directions: NDArray[np.float64]) -> float:
    """Tilt of the scan's ground normal to its z axis [deg]; inf without a ground landmark."""
    g = ls.attributes.get("is_ground")
    if g is None or len(ls) == 0:
        return float("inf")
    idx = np.flatnonzero((np.asarray(g, dtype=float).reshape(len(ls), -1)[:, 0] > 0.5)
                        & (ls.types == LandmarkType.PLANE))
    if idx.size == 0:
        return float("inf")
    return float(np.degrees(np.arccos(np.clip(np.abs(directions[idx, 2]).max(), 0.0, 1.0))))


def is_level_pair(source: LandmarkSet, target: LandmarkSet, cfg: GatingConfig,
                  dirs: tuple[NDArray, NDArray] | None = None) -> bool:
    """Whether the gravity gates apply to this pair (see :class:`GatingConfig`)."""
    if cfg.level_sensor is not None:
        return cfg.level_sensor
    ds, dt = dirs if dirs is not None else (source.directions, target.directions)
    return max(_ground_tilt_deg(source, ds), _ground_tilt_deg(target, dt)) <= cfg.level_tolerance_deg


def _attribute(ls: LandmarkSet, key: str, idx: NDArray[np.int64]) -> NDArray[np.float64] | None:
    v = ls.attributes.get(key)
    if v is None:
        return None
    v = np.asarray(v, dtype=float)
    return v.reshape(v.shape[0], -1)[idx, 0] if v.ndim > 1 else v[idx]


def _ratio_ok(x: NDArray, y: NDArray, ratio: float, slack: float = 0.0) -> NDArray[np.bool_]:
    """|x| and |y| (broadcast) within ``ratio`` of each other, or closer than ``slack``; NaN passes."""
    lo = np.minimum(x[:, None], y[None, :])
    hi = np.maximum(x[:, None], y[None, :])
    ok = (hi <= ratio * lo) | (hi - lo <= slack)
    return ok | np.isnan(lo) | np.isnan(hi)


def gate_mask(source: LandmarkSet, target: LandmarkSet, a: NDArray[np.int64], b: NDArray[np.int64],
              kind: int, cfg: GatingConfig, level: bool = False,
              dirs: tuple[NDArray, NDArray] | None = None) -> NDArray[np.bool_]:
    """(len(a), len(b)) mask of the associations of type ``kind`` that pass the gates; the
    ground and tilt gates only when ``level``."""
    keep = np.ones((a.size, b.size), dtype=bool)
    if level and cfg.ground:
        gi, gj = _attribute(source, "is_ground", a), _attribute(target, "is_ground", b)
        if gi is not None and gj is not None:
            same = (gi[:, None] > 0.5) == (gj[None, :] > 0.5)
            keep &= same | np.isnan(gi)[:, None] | np.isnan(gj)[None, :]
    if level and cfg.tilt_deg is not None and kind in (LandmarkType.LINE, LandmarkType.PLANE):
        ds, dt = dirs if dirs is not None else (source.directions, target.directions)
        ti = np.degrees(np.arccos(np.clip(np.abs(ds[a, 2]), 0.0, 1.0)))
        tj = np.degrees(np.arccos(np.clip(np.abs(dt[b, 2]), 0.0, 1.0)))
        keep &= np.abs(ti[:, None] - tj[None, :]) <= cfg.tilt_deg
    if kind == LandmarkType.LINE:
        if cfg.radius_ratio is not None:
            ri, rj = _attribute(source, "radius", a), _attribute(target, "radius", b)
            if ri is not None and rj is not None:
                keep &= _ratio_ok(ri, rj, cfg.radius_ratio, cfg.radius_slack_m)
        if cfg.length_ratio is not None:
            li, lj = _attribute(source, "extent", a), _attribute(target, "extent", b)
            if li is not None and lj is not None:
                keep &= _ratio_ok(li, lj, cfg.length_ratio)
    if kind == LandmarkType.PLANE and cfg.area_ratio is not None:
        ai, aj = _attribute(source, "extent", a), _attribute(target, "extent", b)
        if ai is not None and aj is not None:
            keep &= _ratio_ok(ai, aj, cfg.area_ratio)
    return keep


def gated_associations(source: LandmarkSet, target: LandmarkSet,
                       config: GatingConfig | None = None) -> NDArray[np.int64]:
    """The same-type associations that pass the gates, in :func:`all_to_all`'s order (type,
    source index, target index); with the gating disabled, exactly :func:`all_to_all`."""
    cfg = config or GatingConfig()
    if not cfg.enabled:
        return all_to_all(source.types, target.types)
    dirs = (source.directions, target.directions)
    level = is_level_pair(source, target, cfg, dirs)
    blocks = []
    for t in np.union1d(np.unique(source.types), np.unique(target.types)):
        a = np.flatnonzero(source.types == t)
        b = np.flatnonzero(target.types == t)
        if a.size and b.size:
            r, c = np.nonzero(gate_mask(source, target, a, b, int(t), cfg, level, dirs))
            blocks.append(np.stack([a[r], b[c]], axis=1))
    if not blocks:
        return np.zeros((0, 2), dtype=np.int64)
    return np.concatenate(blocks).astype(np.int64)


def putative_associations(source: LandmarkSet, target: LandmarkSet,
                          config: GatingConfig | None) -> NDArray[np.int64] | None:
    """What the matcher hands to the graph: the gated list, or None (all same-type
    associations, the graph's own fast path) when gating is off."""
    if config is None or not config.enabled:
        return None
    return gated_associations(source, target, config)
