"""LiPMatch: interpretation-tree plane matching (Jiang et al., 2020; after Fernandez-Moral 2013).

LiPMatch finds plane correspondences for loop closure with the interpretation tree of
Fernandez-Moral et al.: a depth-first search assigns each source plane either a target plane or
"no match"; a branch survives only while every assignment satisfies the *unary* constraints
(attributes of the two planes agree) and every pair of assignments satisfies the *binary*
constraints (relations between two planes agree in both scans); the largest consistent
interpretation wins. Lines are ignored (LiPMatch matches planes; its line features are not part
of the GraffMatch paper's description). The paper notes these constraints rely on
view-dependent centroids, areas and extents.

Unary constraints (source plane i, target plane j):

* area ratio ``max/min <= max_area_ratio`` (3.0), area = ``extent`` attribute [m^2];
* elongation ratio ``<= max_elongation_ratio`` (3.0), elongation = long/short side of ``box``;
* elevation: ``|angle(n_i, z) - angle(n_j, z)| <= max_elevation_diff_deg`` (10 deg), i.e. the
  scans are assumed gravity-aligned (a vehicle LiDAR), as in LiPMatch. ``use_gravity=False``
  disables it. Missing attributes make the corresponding test pass.

Binary constraints (assignments i->j and k->l):

* angle between normals agrees within ``max_normal_angle_diff_deg`` (10 deg);
* centroid (anchor) distance agrees within ``max_centroid_distance_diff`` (4.0 m: on our real
  pairs the centroid distances of true plane matches differ by a median of 1-3 m);
* for (near) parallel planes (normals within ``parallel_deg`` = 10 deg in both scans), the
  perpendicular distance from each centroid to the other plane agrees within
  ``max_perpendicular_diff`` (1.0 m); for non-parallel planes this distance depends on where
  the centroids are, so it is not tested.

Search: source planes in decreasing area, target candidates by increasing area difference;
branch-and-bound on the number of source planes that can still be matched; at most
``max_nodes`` (20,000) tree nodes (the search returns the best interpretation found so far).
The matches are registered in closed form (``register_landmarks``; needs 3 planes that are not
all parallel).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graffmatch.evaluation.methods import (
    MethodBase,
    MethodKind,
    MethodOutput,
    PairInput,
    Timer,
    register_associations,
)
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType

Array = NDArray[np.float64]


def _attr(ls: LandmarkSet, key: str, width: int | None = None) -> Array:
    n = len(ls)
    if key not in ls.attributes:
        return np.full((n,) if width is None else (n, width), np.nan)
    return np.asarray(ls.attributes[key], dtype=float).reshape(
        (n,) if width is None else (n, width)
    )


def _ratio_ok(x: Array, y: Array, max_ratio: float) -> NDArray[np.bool_]:
    lo, hi = np.minimum(x[:, None], y[None]), np.maximum(x[:, None], y[None])
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = hi <= max_ratio * lo
    return ok | ~np.isfinite(lo) | ~np.isfinite(hi) | (lo <= 0)


def _pair_geometry(ls: LandmarkSet) -> tuple[Array, Array, Array]:
    """Intra-scan (n, n): unsigned normal angle [deg], centroid distance, perpendicular distance."""
    n, c = ls.directions, ls.anchors
    ang = np.degrees(np.arccos(np.clip(np.abs(n @ n.T), 0.0, 1.0)))
    diff = c[None, :, :] - c[:, None, :]  # diff[i, k] = c_k - c_i
    dist = np.linalg.norm(diff, axis=-1)
    perp = np.abs(np.einsum("id,ikd->ik", n, diff))  # distance of c_k to plane i
    return ang, dist, perp


@dataclass
class LiPMatch(MethodBase):
    max_area_ratio: float = 3.0
    max_elongation_ratio: float = 3.0
    max_elevation_diff_deg: float = 10.0
    use_gravity: bool = True
    max_normal_angle_diff_deg: float = 10.0
    max_centroid_distance_diff: float = 4.0
    max_perpendicular_diff: float = 1.0
    parallel_deg: float = 10.0
    max_nodes: int = 20_000
    kappa_max: float = 1e3
    name: str = "LiPMatch"
    kind: MethodKind = "landmark"

    def unary(self, src: LandmarkSet, tgt: LandmarkSet) -> NDArray[np.bool_]:
        """(n_s, n_t) unary compatibility of plane pairs."""
        ok = _ratio_ok(_attr(src, "extent"), _attr(tgt, "extent"), self.max_area_ratio)
        bs, bt = _attr(src, "box", 2), _attr(tgt, "box", 2)
        with np.errstate(divide="ignore", invalid="ignore"):
            es = bs.max(axis=1) / bs.min(axis=1)
            et = bt.max(axis=1) / bt.min(axis=1)
        ok &= _ratio_ok(es, et, self.max_elongation_ratio)
        if self.use_gravity:
            el_s = np.degrees(np.arccos(np.clip(np.abs(src.directions[:, 2]), 0, 1)))
            el_t = np.degrees(np.arccos(np.clip(np.abs(tgt.directions[:, 2]), 0, 1)))
            ok &= np.abs(el_s[:, None] - el_t[None]) <= self.max_elevation_diff_deg
        return ok

    def interpretation_tree(
        self, src: LandmarkSet, tgt: LandmarkSet
    ) -> tuple[NDArray[np.intp], int]:
        """Largest consistent set of plane matches (k, 2) and the number of nodes visited."""
        ns, nt = len(src), len(tgt)
        if ns == 0 or nt == 0:
            return np.zeros((0, 2), np.intp), 0
        U = self.unary(src, tgt)
        As, Ds, Ps = _pair_geometry(src)
        At, Dt, Pt = _pair_geometry(tgt)
        area_s = np.nan_to_num(_attr(src, "extent"), nan=0.0)
        area_t = np.nan_to_num(_attr(tgt, "extent"), nan=0.0)
        order = np.argsort(-area_s, kind="stable")  # big planes first: most reliable
        cache: dict[tuple[int, int], NDArray[np.bool_]] = {}

        def binary(i: int, j: int) -> NDArray[np.bool_]:
            key = (i, j)
            if key not in cache:
                ok = np.abs(As[i][:, None] - At[j][None]) <= self.max_normal_angle_diff_deg
                ok &= np.abs(Ds[i][:, None] - Dt[j][None]) <= self.max_centroid_distance_diff
                # Perpendicular distance is a property of the pair only for (near) parallel
                # planes; for others it moves with the centroids, so it is not tested.
                par = (As[i][:, None] <= self.parallel_deg) & (At[j][None] <= self.parallel_deg)
                perp_ok = np.abs(Ps[i][:, None] - Pt[j][None]) <= self.max_perpendicular_diff
                perp_ok &= np.abs(Ps[:, i][:, None] - Pt[:, j][None]) <= self.max_perpendicular_diff
                ok &= ~par | perp_ok
                cache[key] = ok
            return cache[key]

        best: list[tuple[int, int]] = []
        nodes = 0

        def search(depth: int, M: NDArray[np.bool_], current: list[tuple[int, int]]) -> None:
            nonlocal best, nodes
            if nodes >= self.max_nodes:
                return
            nodes += 1
            if len(current) > len(best):
                best = list(current)
            if depth == ns:
                return
            rest = order[depth:]
            if len(current) + int(M[rest].any(axis=1).sum()) <= len(best):
                return  # bound: even matching every remaining plane cannot beat the best
            i = int(order[depth])
            cands = np.flatnonzero(M[i])
            cands = cands[np.argsort(np.abs(area_t[cands] - area_s[i]), kind="stable")]
            for j in cands.tolist():
                M2 = M & binary(i, j)
                M2[:, j] = False
                M2[i] = False
                current.append((i, j))
                search(depth + 1, M2, current)
                current.pop()
                if nodes >= self.max_nodes:
                    return
            search(depth + 1, M, current)  # the "no match" branch for plane i

        search(0, U.copy(), [])
        return np.asarray(sorted(best), dtype=np.intp).reshape(-1, 2), nodes

    def run(self, pair: PairInput) -> MethodOutput:
        si = pair.source.indices_of_type(LandmarkType.PLANE)
        ti = pair.target.indices_of_type(LandmarkType.PLANE)
        src, tgt = pair.source.without_points(), pair.target.without_points()
        timer = Timer()
        with timer.stage("interpretation_tree"):
            local, nodes = self.interpretation_tree(src[si], tgt[ti])
        a = np.stack([si[local[:, 0]], ti[local[:, 1]]], axis=1) if len(local) else local
        with timer.stage("registration"):
            T, valid, info = register_associations(src, tgt, a, self.kappa_max)
        info.update(n_nodes=nodes, exhausted=nodes < self.max_nodes)
        return MethodOutput(T, a, timer.finish(), valid, info)
