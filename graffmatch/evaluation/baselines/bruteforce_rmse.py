"""BruteForceRMSE: exhaustive point-to-landmark RMSE association (Zhou et al., PLC-LiSLAM, 2022).

PLC-LiSLAM associates a detected landmark with the map landmark of the same type whose model
best explains its points: the point-to-line / point-to-plane RMSE of the support points. As the
GraffMatch paper describes it, the RMSE of *every* potential (same-type) match is computed and
the low-RMSE correspondences are selected. Like CPMatch it uses the current pose estimate -- the
identity here, as there is no prior between places -- so it is a *local* method.

For a pair (i, j) we use the symmetric RMSE: the support points of source landmark i against the
model of target landmark j, pooled with the support points of j against the model of i,
``sqrt((SSD_ij + SSD_ji) / (N_i + N_j))``. Sums of squared distances come exactly from each
landmark's point moments (count, centroid, scatter matrix):
``SSD(points_i, model_j) = tr(P_j C_i) + N_i |P_j (c_i - b_j)|^2`` with ``P_j = I - A_j A_j^T``,
so all n_s x n_t pairs cost O(n_s n_t) 3x3 operations and no per-point loop.

Selection: one-to-one, greedily by increasing RMSE, keeping pairs with RMSE below the type's
threshold: ``max_rmse_line`` 0.5 m (pole points lie at the pole radius from the axis, up to
~0.3 m for trunks) and ``max_rmse_plane`` 0.2 m; points (type 0) use ``max_rmse_point`` 1.0 m.
PLC-LiSLAM does not publish these values; they are generous for LiDAR landmarks. Landmarks
without support points cannot be scored and are skipped.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from graffmatch.errors import InvalidInputError
from graffmatch.evaluation.methods import (
    LocalMethod,
    MethodKind,
    Timer,
)
from graffmatch.geometry.landmarks import LandmarkSet

Array = NDArray[np.float64]


def point_moments(ls: LandmarkSet) -> tuple[Array, Array, Array]:
    """(counts (n,), centroids (n,3), centred scatter matrices (n,3,3)) of the support points."""
    if ls.points is None or ls.point_offsets is None:
        raise InvalidInputError("BruteForceRMSE needs landmark support points (LandmarkSet.points)")
    P = ls.points.astype(np.float64)
    off = ls.point_offsets
    n = len(ls)
    counts = np.diff(off).astype(float)
    owner = np.repeat(np.arange(n), np.diff(off))
    sums = np.stack([np.bincount(owner, weights=P[:, k], minlength=n) for k in range(3)], axis=1)
    cent = np.divide(sums, counts[:, None], out=np.zeros((n, 3)), where=counts[:, None] > 0)
    Q = P - cent[owner]
    scat = np.empty((n, 3, 3))
    for a in range(3):  # 6 weighted bincounts over all points, no per-landmark loop
        for b in range(a, 3):
            scat[:, a, b] = scat[:, b, a] = np.bincount(
                owner, weights=Q[:, a] * Q[:, b], minlength=n
            )
    return counts, cent, scat


def _ssd(counts: Array, cent: Array, scat: Array, proj: Array, anchors: Array) -> Array:
    """(n_a, n_b) sums of squared distances of the points of a-landmarks to b-models."""
    tr = np.einsum("bij,aji->ab", proj, scat)
    diff = cent[:, None, :] - anchors[None, :, :]  # (a, b, 3)
    pd = np.einsum("bij,abj->abi", proj, diff)
    return tr + counts[:, None] * np.einsum("abi,abi->ab", pd, pd)


def symmetric_rmse(source: LandmarkSet, target: LandmarkSet) -> Array:
    """(n_s, n_t) symmetric point-to-model RMSE [m]; inf across types or without points."""
    cs, ms, Ss = point_moments(source)
    ct, mt, St = point_moments(target)
    Ps = np.eye(3) - np.einsum("nik,njk->nij", source.bases, source.bases)
    Pt = np.eye(3) - np.einsum("nik,njk->nij", target.bases, target.bases)
    ssd = _ssd(cs, ms, Ss, Pt, target.anchors) + _ssd(ct, mt, St, Ps, source.anchors).T
    n = cs[:, None] + ct[None, :]
    rmse = np.sqrt(np.maximum(ssd, 0.0) / np.maximum(n, 1.0))
    bad = (source.types[:, None] != target.types[None, :]) | (cs[:, None] == 0) | (ct[None, :] == 0)
    rmse[bad] = np.inf
    return rmse


def greedy_one_to_one(cost: Array, max_cost_per_row: Array) -> NDArray[np.intp]:
    """(k, 2) pairs by increasing cost, each row and column used once, cost below the row's gate."""
    rows, cols = np.nonzero(cost < max_cost_per_row[:, None])
    if len(rows) == 0:
        return np.zeros((0, 2), np.intp)
    order = np.lexsort((cols, rows, cost[rows, cols]))  # deterministic tie-breaking
    rows, cols = rows[order], cols[order]
    used_r = np.zeros(cost.shape[0], bool)
    used_c = np.zeros(cost.shape[1], bool)
    keep = []
    for r, c in zip(rows.tolist(), cols.tolist(), strict=True):  # over candidates, not points
        if not used_r[r] and not used_c[c]:
            used_r[r] = used_c[c] = True
            keep.append((r, c))
    return np.asarray(keep, dtype=np.intp).reshape(-1, 2)


@dataclass
class BruteForceRMSE(LocalMethod):
    moves_points = True  # the RMSE is computed on the support points
    max_rmse_point: float = 1.0
    max_rmse_line: float = 0.5
    max_rmse_plane: float = 0.2
    kappa_max: float = 1e3
    T_init: Array = field(default_factory=lambda: np.eye(4))
    name: str = "BruteForceRMSE"
    kind: MethodKind = "landmark"

    def associate(
        self, moved_source: LandmarkSet, target: LandmarkSet, timer: Timer
    ) -> tuple[NDArray[np.intp], dict[str, Any]]:
        with timer.stage("rmse"):
            rmse = symmetric_rmse(moved_source, target)
        with timer.stage("selection"):
            gates = np.array([self.max_rmse_point, self.max_rmse_line, self.max_rmse_plane])
            a = greedy_one_to_one(rmse, gates[moved_source.types.astype(np.intp)])
        mean = float(rmse[a[:, 0], a[:, 1]].mean()) if len(a) else float("nan")
        return a, {"mean_rmse": mean}
