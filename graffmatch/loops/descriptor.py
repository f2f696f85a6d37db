"""A compact global place descriptor computed from a scan's landmark map.

Rotation invariance is by construction: every feature is a distance or an angle that a rigid
motion of the sensor leaves unchanged, so a street driven in reverse gives the same descriptor.

Blocks (each a soft-binned histogram, L1-normalised, then square-rooted so that the Euclidean
distance between descriptors is the Hellinger distance, which cKDTree searches exactly):

* ``line-line``: distance between the axes of near-parallel line pairs (pole spacing) [m];
* ``plane-plane``: separation of near-parallel plane pairs along their normal (street width);
* ``line-plane``: distance of each line's anchor from each plane (pole to facade / ground) [m];
* ``angles``: the angle between the directions/normals of every same-type pair [deg];
* ``range-lines`` / ``range-planes``: distance of each landmark from the sensor (invariant to
  the sensor's rotation, not to its translation: it makes places a few metres apart similar
  and far-apart places with similar layouts different).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType

Array = NDArray[np.float64]


class DescriptorConfig(BaseModel):
    """Bins of the landmark descriptor; the size is ``6 * bins`` float32 values."""

    model_config = ConfigDict(extra="forbid")

    bins: int = Field(16, ge=4, le=128, description="bins per histogram block")
    max_distance: float = Field(48.0, gt=0, description="upper edge of the distance blocks [m]")
    max_range: float = Field(64.0, gt=0, description="upper edge of the range blocks [m]")
    parallel_deg: float = Field(
        15.0, gt=0, lt=90, description="pairs closer than this in angle count as parallel [deg]"
    )
    block_weights: tuple[float, float, float, float, float, float] = Field(
        (1.0, 1.0, 1.0, 0.5, 1.0, 1.0),
        description="weights of line-line, plane-plane, line-plane, angles, range-lines, range-planes",
    )

    @property
    def size(self) -> int:
        return 6 * self.bins


def _soft_hist(values: Array, bins: int, hi: float) -> Array:
    """Linear-interpolation histogram on [0, hi]: a value moves mass smoothly between bins."""
    h = np.zeros(bins)
    v = np.asarray(values, float).ravel()
    v = v[np.isfinite(v) & (v >= 0) & (v < hi)]
    if v.size == 0:
        return h
    x = v / hi * bins - 0.5
    lo = np.floor(x).astype(np.int64)
    w = x - lo
    np.add.at(h, np.clip(lo, 0, bins - 1), 1.0 - w)
    np.add.at(h, np.clip(lo + 1, 0, bins - 1), w)
    return h


def _normalise(h: Array) -> Array:
    s = h.sum()
    return np.sqrt(h / s) if s > 0 else h


def landmark_descriptor(ls: LandmarkSet, config: DescriptorConfig | None = None) -> NDArray[np.float32]:
    """(6 * bins,) float32 descriptor of a scan's landmarks (sensor frame)."""
    cfg = config or DescriptorConfig()
    b = cfg.bins
    dirs = ls.directions  # lines: direction; planes: normal; points: zeros
    anchors = np.asarray(ls.anchors, float)
    li = np.flatnonzero(ls.types == LandmarkType.LINE)
    pi = np.flatnonzero(ls.types == LandmarkType.PLANE)
    cos_par = np.cos(np.radians(cfg.parallel_deg))
    iu_l = np.triu_indices(li.size, 1)
    iu_p = np.triu_indices(pi.size, 1)

    # line-line: axis distance of near-parallel pairs
    dl, al = dirs[li], anchors[li]
    c_ll = np.abs(dl @ dl.T)[iu_l]
    diff = al[:, None, :] - al[None, :, :]
    along = np.einsum("ijk,ik->ij", diff, dl)
    perp = np.linalg.norm(diff - along[..., None] * dl[:, None, :], axis=2)[iu_l]
    h_ll = _soft_hist(perp[c_ll > cos_par], b, cfg.max_distance)

    # plane-plane: separation along the normal of near-parallel pairs
    n_p, a_p = dirs[pi], anchors[pi]
    c_pp = np.abs(n_p @ n_p.T)[iu_p]
    sep = np.abs(np.einsum("ijk,ik->ij", a_p[:, None, :] - a_p[None, :, :], n_p))[iu_p]
    h_pp = _soft_hist(sep[c_pp > cos_par], b, cfg.max_distance)

    # line-plane: distance of line anchors from planes
    lp = np.abs(np.einsum("ijk,jk->ij", al[:, None, :] - a_p[None, :, :], n_p)).ravel()
    h_lp = _soft_hist(lp, b, cfg.max_distance)

    # angles between same-type pairs, folded to [0, 90] deg
    ang = np.degrees(np.arccos(np.clip(np.concatenate([c_ll, c_pp]), 0.0, 1.0)))
    h_ang = _soft_hist(ang, b, 90.0 + 1e-9)

    # ranges from the sensor: lines by the distance of the axis, planes by the plane's offset
    r_l = np.linalg.norm(al - np.einsum("ij,ij->i", al, dl)[:, None] * dl, axis=1)
    r_p = np.abs(np.einsum("ij,ij->i", a_p, n_p))
    h_rl = _soft_hist(r_l, b, cfg.max_range)
    h_rp = _soft_hist(r_p, b, cfg.max_range)

    blocks = [h_ll, h_pp, h_lp, h_ang, h_rl, h_rp]
    out = np.concatenate([w * _normalise(h) for w, h in zip(cfg.block_weights, blocks, strict=True)])
    return out.astype(np.float32)
