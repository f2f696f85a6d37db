"""Translation re-estimation under a hypothesis' rotation, by voting on the evidence points.

A landmark registration can get the rotation right (plane normals agree) and the translation
metres wrong (plane offsets matched to the wrong wall, a street's repeating facades): on
sim-downtown 5 of 13 test positives without a right hypothesis had one 0.7-2.8 deg off with
the translation 2-10 m off (bench/verification.py). Alignment on the points starts from that
translation and stops in a local optimum. Under a fixed rotation R, the translation that
explains the most evidence is where the most differences ``q - (R p + t0)`` of source points p
and target points q pile up (the cross-correlation of the two clouds): each pair votes in a
horizontal grid of ``cell`` metres around the hypothesis' own translation (pairs at about the
same height only), and the grid's peaks (box smoothed over 3x3 cells, non-maximum suppressed)
are new starts with the same rotation and height.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray


@nb.njit(cache=True)
def _votes(P: NDArray[np.float64], Q: NDArray[np.float64], T: NDArray[np.float64], reach: float,
           height: float, cell: float, peaks: int, suppress: int) -> NDArray[np.float64]:
    """(peaks, 2) horizontal offsets (added to T's translation) of the strongest vote peaks;
    only pairs within ``height`` of each other vertically vote (the height rests on the ground
    plane, which the landmark registration fits well)."""
    nx = int(2.0 * reach / cell) + 1
    grid = np.zeros((nx + 2, nx + 2), np.float64)  # a border cell each side: smoothing needs no bounds
    R = T[:3, :3]
    for a in range(P.shape[0]):
        m0 = R[0, 0] * P[a, 0] + R[0, 1] * P[a, 1] + R[0, 2] * P[a, 2] + T[0, 3] - reach
        m1 = R[1, 0] * P[a, 0] + R[1, 1] * P[a, 1] + R[1, 2] * P[a, 2] + T[1, 3] - reach
        m2 = R[2, 0] * P[a, 0] + R[2, 1] * P[a, 1] + R[2, 2] * P[a, 2] + T[2, 3]
        for b in range(Q.shape[0]):
            if abs(Q[b, 2] - m2) >= height:
                continue
            d0 = Q[b, 0] - m0
            d1 = Q[b, 1] - m1
            if d0 < 0.0 or d1 < 0.0:
                continue
            i, j = int(d0 / cell), int(d1 / cell)
            if i < nx and j < nx:
                grid[i + 1, j + 1] += 1.0
    rows = np.zeros_like(grid)  # 3x3 box sum, separable
    for i in range(1, nx + 1):
        for j in range(nx + 2):
            rows[i, j] = grid[i - 1, j] + grid[i, j] + grid[i + 1, j]
    smooth = np.zeros((nx, nx), np.float64)
    for i in range(nx):
        for j in range(nx):
            smooth[i, j] = rows[i + 1, j] + rows[i + 1, j + 1] + rows[i + 1, j + 2]
    out = np.full((peaks, 2), np.nan)
    for p in range(peaks):
        best, bi, bj = 0.0, -1, -1
        for i in range(nx):
            for j in range(nx):
                if smooth[i, j] > best:
                    best, bi, bj = smooth[i, j], i, j
        if bi < 0:
            break
        out[p, 0] = (bi + 0.5) * cell - reach
        out[p, 1] = (bj + 0.5) * cell - reach
        for i in range(max(bi - suppress, 0), min(bi + suppress + 1, nx)):
            for j in range(max(bj - suppress, 0), min(bj + suppress + 1, nx)):
                smooth[i, j] = 0.0
    return out


def vote_translations(P: NDArray[np.float64], Q: NDArray[np.float64], T_target_source: NDArray[np.float64],
                      reach_m: float, height_m: float, cell_m: float, peaks: int,
                      suppress_m: float = 2.0) -> NDArray[np.float64]:
    """(k <= peaks, 4, 4): ``T_target_source`` with its horizontal translation moved to the
    ``peaks`` strongest vote peaks of source points ``P`` against target points ``Q`` (offsets
    within ``reach_m`` of its own translation, pairs within ``height_m`` vertically; peaks at
    least ``suppress_m`` apart). Frames are z-up."""
    T = np.ascontiguousarray(T_target_source, dtype=np.float64)
    d = _votes(np.ascontiguousarray(P, dtype=np.float64), np.ascontiguousarray(Q, dtype=np.float64), T,
               float(reach_m), float(height_m), float(cell_m), int(peaks), int(np.ceil(suppress_m / cell_m)))
    d = d[~np.isnan(d[:, 0])]
    out = np.repeat(T[None], len(d), axis=0)
    out[:, :2, 3] += d
    return out
