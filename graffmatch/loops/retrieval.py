"""Candidate retrieval: which earlier scans might show the same place as the query.

Three retrievers share one interface (``candidates(db, query, eligible) -> (indices, scores)``,
best first, lower score = more similar):

* ``descriptor``: k nearest neighbours of the landmark descriptor (:mod:`.descriptor`) in a
  scipy cKDTree over the eligible scans (rebuilt as the database grows; the newest eligible
  scans not yet in the tree are searched exhaustively, so the answer is always exact);
* ``scan-context``: the ring key of Scan Context (Kim & Kim 2018) in a cKDTree, re-ranked by
  the full column-shift distance (``graffmatch.evaluation.baselines.scan_context``);
* ``radius``: every eligible scan whose position (odometry estimate) lies within R metres of the
  query's, nearest first;
* ``descriptor+radius``: the descriptor's top-k, then (when odometry positions are given) the
  eligible scans within R metres plus ``drift_fraction`` of the odometry path between the two
  scans (a drifting odometry's error grows with the distance travelled), nearest first, at most
  ``top_k`` more: the descriptor finds places the odometry has drifted away from, the odometry
  finds places whose descriptor is ambiguous (pole-only open road).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree

from graffmatch.errors import InvalidInputError
from graffmatch.loops.database import LandmarkDatabase

RetrieverName = Literal["descriptor", "scan-context", "radius", "descriptor+radius"]


class RetrievalConfig(BaseModel):
    """How candidates are found and which scans are too recent to be a loop."""

    model_config = ConfigDict(extra="forbid")

    method: RetrieverName = Field(
        "descriptor+radius",
        description="descriptor | scan-context | radius | descriptor+radius (the default: the descriptor "
        "alone when no odometry positions are given)",
    )
    top_k: int = Field(
        20, ge=1, le=200,
        description="candidates retrieved per query; all go through the quick check, at most "
        "verification.max_verified are verified (30 gained open-road loops on the calibration drives "
        "but reported a wrong courtyard loop found at rank 28: docs/loops.md, session 9)",
    )
    exclude_seconds: float = Field(
        10.0, ge=0, description="skip scans newer than this before the query [s]"
    )
    exclude_frames: int = Field(0, ge=0, description="also skip this many most recent scans")
    radius_m: float = Field(10.0, gt=0, description="radius retriever: search radius [m]")
    union_radius_m: float = Field(
        5.0, gt=0, description="descriptor+radius: scans within this many metres of the odometry estimate "
        "join the descriptor's top-k (5 m + 2 % chosen on the calibration drives: docs/loops.md, session 10)"
    )
    drift_fraction: float = Field(
        0.02, ge=0, description="descriptor+radius: the radius grows by this fraction of the odometry "
        "path between query and candidate"
    )
    ring_key_candidates: int = Field(
        10, ge=1, description="scan-context retriever: ring-key neighbours re-ranked by SC distance"
    )
    rebuild_fraction: float = Field(
        0.1, gt=0, description="rebuild the KD-tree when the un-indexed tail exceeds this fraction"
    )


def eligible_count(
    timestamps: list[float] | NDArray, query: int, config: RetrievalConfig
) -> int:
    """Number of leading scans (0..m-1) old enough to be a loop candidate of ``query``."""
    t = np.asarray(timestamps[:query], float)
    m = int(np.searchsorted(t, float(timestamps[query]) - config.exclude_seconds, side="right"))
    return max(0, min(m, query - config.exclude_frames))


class _TreeKNN:
    """Exact kNN over a growing prefix: a cKDTree over the first rows plus a brute-force tail."""

    def __init__(self, rebuild_fraction: float) -> None:
        self.rebuild_fraction = rebuild_fraction
        self.tree: cKDTree | None = None
        self.size = 0

    def query(self, X: NDArray, q: NDArray, m: int, k: int) -> tuple[NDArray, NDArray]:
        if m <= 0:
            return np.zeros(0, np.int64), np.zeros(0)
        if self.tree is None or m < self.size or (m - self.size) > self.rebuild_fraction * max(self.size, 50):
            self.tree = cKDTree(X[:m])
            self.size = m
        k_tree = min(k, self.size)
        d, i = self.tree.query(q, k=k_tree)
        d, i = np.atleast_1d(d).astype(float), np.atleast_1d(i).astype(np.int64)
        if m > self.size:
            tail = np.linalg.norm(X[self.size : m] - q, axis=1)
            d = np.concatenate([d, tail])
            i = np.concatenate([i, np.arange(self.size, m)])
        order = np.argsort(d, kind="stable")[:k]
        return i[order], d[order]


class DescriptorRetriever:
    name = "descriptor"

    def __init__(self, config: RetrievalConfig) -> None:
        self.config = config
        self._knn = _TreeKNN(config.rebuild_fraction)
        self._X: NDArray | None = None

    def candidates(self, db: LandmarkDatabase, query: int, eligible: int) -> tuple[NDArray, NDArray]:
        if self._X is None or len(self._X) < eligible:
            self._X = db.descriptor_matrix()
        return self._knn.query(self._X, db.descriptors[query], eligible, self.config.top_k)


class ScanContextRetriever:
    """Needs ``db.extra['scan_context']`` ((rings, sectors) arrays, one per scan)."""

    name = "scan-context"

    def __init__(self, config: RetrievalConfig) -> None:
        self.config = config
        self._knn = _TreeKNN(config.rebuild_fraction)
        self._keys: NDArray | None = None

    def candidates(self, db: LandmarkDatabase, query: int, eligible: int) -> tuple[NDArray, NDArray]:
        from graffmatch.evaluation.baselines.scan_context import ring_key, sc_distance

        sc = db.extra.get("scan_context")
        if sc is None or sc[query] is None:
            raise InvalidInputError("the scan-context retriever needs raw scans (Scan Context per scan)")
        if self._keys is None or len(self._keys) < eligible:
            self._keys = np.stack([ring_key(s) for s in sc])
        idx, _ = self._knn.query(
            self._keys, self._keys[query], eligible, max(self.config.ring_key_candidates, self.config.top_k)
        )
        dist = np.array([sc_distance(sc[query], sc[j])[0] for j in idx])
        order = np.argsort(dist, kind="stable")[: self.config.top_k]
        return idx[order], dist[order]


class RadiusRetriever:
    """Needs positions (odometry estimates) in the database."""

    name = "radius"

    def __init__(self, config: RetrievalConfig) -> None:
        self.config = config

    def candidates(self, db: LandmarkDatabase, query: int, eligible: int) -> tuple[NDArray, NDArray]:
        if db.positions[query] is None:
            raise InvalidInputError("the radius retriever needs a position (pose) for every scan")
        if eligible <= 0:
            return np.zeros(0, np.int64), np.zeros(0)
        P = np.stack(db.positions[:eligible])
        d = np.linalg.norm(P - db.positions[query], axis=1)
        keep = np.flatnonzero(d <= self.config.radius_m)
        order = keep[np.argsort(d[keep], kind="stable")][: self.config.top_k]
        return order.astype(np.int64), d[order]


class DescriptorRadiusRetriever:
    """The descriptor's top-k, then the scans near the odometry estimate (drift-aware radius).

    Without positions it is the descriptor retriever. Scores are descriptor distances for all."""

    name = "descriptor+radius"

    def __init__(self, config: RetrievalConfig) -> None:
        self.config = config
        self._desc = DescriptorRetriever(config)
        self._P: NDArray | None = None
        self._path: NDArray | None = None

    def candidates(self, db: LandmarkDatabase, query: int, eligible: int) -> tuple[NDArray, NDArray]:
        idx, dist = self._desc.candidates(db, query, eligible)
        if eligible <= 0 or query >= len(db.positions) or db.positions[query] is None:
            return idx, dist
        if self._P is None or len(self._P) <= query:
            if any(p is None for p in db.positions[: query + 1]):
                raise InvalidInputError("descriptor+radius: positions must be given for every scan or none")
            self._P = np.stack([np.asarray(p, float) for p in db.positions])
            steps = np.linalg.norm(np.diff(self._P, axis=0), axis=1)
            self._path = np.concatenate([[0.0], np.cumsum(steps)])
        P, path = self._P, self._path
        d = np.linalg.norm(P[:eligible] - P[query], axis=1)
        r = self.config.union_radius_m + self.config.drift_fraction * (path[query] - path[:eligible])
        keep = np.flatnonzero(d <= r)
        keep = keep[~np.isin(keep, idx)]
        keep = keep[np.argsort(d[keep], kind="stable")][: self.config.top_k].astype(np.int64)
        X = self._desc._X if self._desc._X is not None else db.descriptor_matrix()
        dd = np.linalg.norm(X[keep] - db.descriptors[query], axis=1) if keep.size else np.zeros(0)
        return np.concatenate([idx, keep]), np.concatenate([dist, dd])


def make_retriever(
    config: RetrievalConfig,
) -> DescriptorRetriever | ScanContextRetriever | RadiusRetriever | DescriptorRadiusRetriever:
    return {
        "descriptor": DescriptorRetriever,
        "scan-context": ScanContextRetriever,
        "radius": RadiusRetriever,
        "descriptor+radius": DescriptorRadiusRetriever,
    }[config.method](config)
