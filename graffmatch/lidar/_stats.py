"""Vectorised per-cluster statistics (moments, PCA) shared by the pole and plane steps.

Clusters are given as an integer label per point; every statistic is computed with
``np.bincount`` so that the cost is O(N) whatever the number of clusters, with no Python loop
over points or clusters.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ClusterStats:
    """PCA of each cluster: eigenvalues ascending in ``evals`` and matching ``evecs[:, :, j]``."""

    counts: NDArray[np.int64]  # (k,)
    centroids: Array  # (k, 3)
    covariances: Array  # (k, 3, 3), population covariance
    evals: Array  # (k, 3) ascending, clipped at 0
    evecs: Array  # (k, 3, 3) columns are eigenvectors

    @property
    def sigmas(self) -> Array:
        """Standard deviations along the principal axes, descending (s1 >= s2 >= s3)."""
        return np.sqrt(self.evals[:, ::-1])

    def linearity(self) -> Array:
        s = self.sigmas
        return (s[:, 0] - s[:, 1]) / np.maximum(s[:, 0], 1e-12)

    def planarity(self) -> Array:
        s = self.sigmas
        return (s[:, 1] - s[:, 2]) / np.maximum(s[:, 0], 1e-12)

    def major_axis(self) -> Array:
        return self.evecs[:, :, 2]

    def normal(self) -> Array:
        return self.evecs[:, :, 0]


def cluster_stats(points: Array, labels: NDArray[np.integer], k: int) -> ClusterStats:
    """Moments of clusters ``0..k-1`` of ``points`` (labels < 0 are ignored)."""
    P = np.asarray(points, dtype=np.float64)
    lab = np.asarray(labels).astype(np.int64)
    keep = (lab >= 0) & (lab < k)
    P, lab = P[keep], lab[keep]
    counts = np.bincount(lab, minlength=k).astype(np.int64)
    safe = np.maximum(counts, 1).astype(np.float64)
    # Shift by a per-cluster reference point first: moments about the origin lose precision
    # for far-away clusters (catastrophic cancellation in E[x^2] - E[x]^2).
    first = np.full(k, -1, dtype=np.int64)
    order = np.arange(lab.size)[::-1]
    first[lab[order]] = order
    ref = np.zeros((k, 3))
    has = first >= 0
    ref[has] = P[first[has]]
    Q = P - ref[lab]
    mean_q = (
        np.stack([np.bincount(lab, Q[:, j], minlength=k) for j in range(3)], axis=1) / safe[:, None]
    )
    cov = np.empty((k, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            m = np.bincount(lab, Q[:, a] * Q[:, b], minlength=k) / safe
            cov[:, a, b] = cov[:, b, a] = m - mean_q[:, a] * mean_q[:, b]
    evals, evecs = np.linalg.eigh(cov)
    evals = np.maximum(evals, 0.0)
    return ClusterStats(counts, ref + mean_q, cov, evals, evecs)


def axis_spans(
    points: Array, labels: NDArray[np.integer], k: int, axes: Array, centroids: Array
) -> tuple[Array, Array, Array]:
    """Per cluster: min and max of the projection onto ``axes`` and the mean distance to it."""
    P = np.asarray(points, dtype=np.float64)
    lab = np.asarray(labels).astype(np.int64)
    keep = (lab >= 0) & (lab < k)
    P, lab = P[keep], lab[keep]
    Q = P - centroids[lab]
    t = np.einsum("ij,ij->i", Q, axes[lab])
    lo = np.full(k, np.inf)
    hi = np.full(k, -np.inf)
    np.minimum.at(lo, lab, t)
    np.maximum.at(hi, lab, t)
    perp = np.linalg.norm(Q - t[:, None] * axes[lab], axis=1)
    counts = np.maximum(np.bincount(lab, minlength=k), 1)
    mean_perp = np.bincount(lab, perp, minlength=k) / counts
    return lo, hi, mean_perp


def subsample_groups(
    labels: NDArray[np.integer], selected: NDArray[np.integer], cap: int
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Indices of at most ``cap`` points of each selected cluster, evenly spread, in order.

    Returns (point indices, offsets) in the order of ``selected``. Deterministic: a stride over
    each cluster's points, not a random draw.
    """
    lab = np.asarray(labels).astype(np.int64)
    sel = np.asarray(selected, dtype=np.int64)
    if sel.size == 0 or cap <= 0:
        return np.zeros(0, np.int64), np.zeros(sel.size + 1, np.int64)
    rank = np.full(max(int(lab.max(initial=-1)), int(sel.max())) + 1, -1, dtype=np.int64)
    rank[sel] = np.arange(sel.size)
    valid = lab >= 0
    idx = np.flatnonzero(valid)
    r = rank[lab[idx]]
    idx, r = idx[r >= 0], r[r >= 0]
    order = np.lexsort((idx, r))
    idx, r = idx[order], r[order]
    counts = np.bincount(r, minlength=sel.size)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    pos = np.arange(idx.size) - np.repeat(starts, counts)
    n_of = np.repeat(counts, counts)
    take = np.minimum(n_of, cap)
    # keep position p when floor(p * take / n) increases: an even stride of `take` samples
    keep = (pos * take) // np.maximum(n_of, 1) != ((pos - 1) * take) // np.maximum(n_of, 1)
    out = idx[keep]
    kept_counts = np.bincount(r[keep], minlength=sel.size)
    return out, np.concatenate([[0], np.cumsum(kept_counts)]).astype(np.int64)
