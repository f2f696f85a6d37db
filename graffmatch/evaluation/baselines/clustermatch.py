"""ClusterMatch: pairwise-centroid-distance hypotheses with inlier validation (Cao et al., 2020).

Cao et al. match poles and building planes between a scan and a map by searching for landmark
*pairs* whose centroid distance agrees, hypothesising the transform each agreeing pair implies,
and accepting the transform that a large number of landmark matches supports. The GraffMatch
paper summarises it as "putative correspondences using pairwise landmark centroid distances
followed by inlier validation". Our 3-D re-implementation:

1. **Pair signatures.** For every source pair (a, a') and every ordered target pair (b, b') of
   the same types, the centroid (anchor) distances must agree: ``|d_s - d_t| < pair_tolerance``
   (1.0 m); pairs shorter than ``min_pair_distance`` (2 m) are ignored (ill-conditioned).
   Candidates are found by sorting the target distances per type pair and binary search.
2. **Hypotheses.** Up to ``max_hypotheses`` (5000) candidates are drawn uniformly at random
   (seeded). Each gives a rigid transform: the rotation aligns the centroid baseline and the two
   landmarks' directions (line direction / plane normal, both signs tried; batched Kabsch), the
   translation aligns the centroid midpoints. The original is 2-D (gravity known); using the
   landmark directions is the natural 3-D extension.
3. **Inlier validation.** A source landmark supports a hypothesis if a target landmark of the same
   type lies within ``inlier_distance`` (2.0 m, centroids move with the detection) and
   ``inlier_angle_deg`` (10 deg) after transforming. The search stops early once a hypothesis is
   supported by ``stop_ratio`` (60 %) of min(n_s, n_t) landmarks.
4. **Matches.** The best hypothesis's inliers (one-to-one, nearest first) are registered in closed
   form; the association is redone once with the refined transform.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graffmatch.evaluation.baselines.bruteforce_rmse import greedy_one_to_one
from graffmatch.evaluation.methods import (
    MethodBase,
    MethodKind,
    MethodOutput,
    PairInput,
    Timer,
    no_estimate,
    register_associations,
    too_few_landmarks,
)
from graffmatch.geometry.landmarks import LandmarkSet

Array = NDArray[np.float64]
_KEY_SCALE = 1e6  # separates type-pair keys in one sorted array (distances are << 1e6 m)


def _pairs(ls: LandmarkSet, ordered: bool, min_dist: float) -> tuple[NDArray[np.intp], Array]:
    n = len(ls)
    i, j = np.triu_indices(n, k=1)
    if ordered:
        i, j = np.concatenate([i, j]), np.concatenate([j, i])
    d = np.linalg.norm(ls.anchors[i] - ls.anchors[j], axis=1)
    keep = d >= min_dist
    return np.stack([i[keep], j[keep]], axis=1), d[keep]


def candidate_pair_matches(
    source: LandmarkSet,
    target: LandmarkSet,
    tolerance: float,
    min_dist: float,
    max_samples: int,
    rng: np.random.Generator,
) -> tuple[NDArray[np.intp], NDArray[np.intp], int]:
    """Random sample (without enumeration) of pair matches with agreeing centroid distances.

    Returns (source pairs (h,2), target pairs (h,2), number of agreeing candidates in total).
    """
    sp, sd = _pairs(source, ordered=False, min_dist=min_dist)
    tp, td = _pairs(target, ordered=True, min_dist=min_dist)
    if len(sp) == 0 or len(tp) == 0:
        return np.zeros((0, 2), np.intp), np.zeros((0, 2), np.intp), 0
    skey = source.types[sp[:, 0]].astype(float) * 3 + source.types[sp[:, 1]]
    tkey = target.types[tp[:, 0]].astype(float) * 3 + target.types[tp[:, 1]]
    tval = tkey * _KEY_SCALE + td
    order = np.argsort(tval, kind="stable")
    tval, tp = tval[order], tp[order]
    sval = skey * _KEY_SCALE + sd
    lo = np.searchsorted(tval, sval - tolerance, side="left")
    hi = np.searchsorted(tval, sval + tolerance, side="right")
    counts = hi - lo
    total = int(counts.sum())
    if total == 0:
        return np.zeros((0, 2), np.intp), np.zeros((0, 2), np.intp), 0
    h = min(max_samples, total)
    flat = np.arange(total) if h == total else np.sort(rng.choice(total, size=h, replace=False))
    cum = np.concatenate([[0], np.cumsum(counts)])
    which = np.searchsorted(cum, flat, side="right") - 1
    tidx = lo[which] + (flat - cum[which])
    sel_s, sel_t = sp[which], tp[tidx]
    if h < total:
        perm = rng.permutation(h)  # evaluation order random, so early stopping is unbiased
        sel_s, sel_t = sel_s[perm], sel_t[perm]
    return sel_s, sel_t, total


def _batched_kabsch(X: Array, Y: Array) -> Array:
    """Rotations R (h,3,3) minimising sum ||R x_k - y_k||^2 for vector sets X, Y (h, m, 3)."""
    H = np.einsum("hki,hkj->hij", X, Y)
    U, _, Vt = np.linalg.svd(H)
    D = np.ones((len(H), 3))
    D[:, 2] = np.sign(np.linalg.det(np.einsum("hij,hjk->hik", U, Vt)).T)
    D[D[:, 2] == 0, 2] = 1.0
    return np.einsum("hji,hj,hkj->hik", Vt, D, U)


def pair_hypotheses(
    source: LandmarkSet, target: LandmarkSet, sp: NDArray[np.intp], tp: NDArray[np.intp]
) -> tuple[Array, NDArray[np.bool_]]:
    """Transforms (h,4,4) from pair matches, and a mask of well-conditioned hypotheses."""
    cs, ct = source.anchors, target.anchors
    ds, dt = source.directions, target.directions
    u = cs[sp[:, 1]] - cs[sp[:, 0]]
    v = ct[tp[:, 1]] - ct[tp[:, 0]]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    best_R = np.zeros((len(sp), 3, 3))
    best_err = np.full(len(sp), np.inf)
    for s1 in (1.0, -1.0):
        for s2 in (1.0, -1.0):
            X = np.stack([u, ds[sp[:, 0]], ds[sp[:, 1]]], axis=1)
            Y = np.stack([v, s1 * dt[tp[:, 0]], s2 * dt[tp[:, 1]]], axis=1)
            R = _batched_kabsch(X, Y)
            err = np.linalg.norm(np.einsum("hij,hkj->hki", R, X) - Y, axis=(1, 2))
            better = err < best_err
            best_R[better], best_err[better] = R[better], err[better]
    # Conditioning: the source vectors must span at least a plane (not all collinear).
    X = np.stack([u, ds[sp[:, 0]], ds[sp[:, 1]]], axis=1)
    sv = np.linalg.svd(X, compute_uv=False)
    ok = sv[:, 1] > 0.1
    mid_s = 0.5 * (cs[sp[:, 0]] + cs[sp[:, 1]])
    mid_t = 0.5 * (ct[tp[:, 0]] + ct[tp[:, 1]])
    T = np.tile(np.eye(4), (len(sp), 1, 1))
    T[:, :3, :3] = best_R
    T[:, :3, 3] = mid_t - np.einsum("hij,hj->hi", best_R, mid_s)
    return T, ok


def support_masks(
    source: LandmarkSet,
    target: LandmarkSet,
    T: Array,
    max_distance: float,
    max_angle_deg: float,
) -> tuple[NDArray[np.bool_], Array]:
    """For hypotheses T (h,4,4): compatibility (h, n_s, n_t) and centroid distances."""
    A = np.einsum("hij,nj->hni", T[:, :3, :3], source.anchors) + T[:, None, :3, 3]
    B = target.anchors
    # |a - b|^2 expanded: no (h, n_s, n_t, 3) temporary.
    D2 = (
        (A * A).sum(-1)[:, :, None]
        + (B * B).sum(-1)[None, None]
        - 2 * np.einsum("hni,mi->hnm", A, B)
    )
    D = np.sqrt(np.maximum(D2, 0.0))
    dirs = np.einsum("hij,nj->hni", T[:, :3, :3], source.directions)
    cos = np.abs(np.einsum("hni,mi->hnm", dirs, target.directions))
    same = source.types[:, None] == target.types[None, :]
    is_pt = (source.types == 0)[:, None]
    ang_ok = is_pt | (cos >= np.cos(np.radians(max_angle_deg)))
    return same[None] & (D < max_distance) & ang_ok, D


@dataclass
class ClusterMatch(MethodBase):
    pair_tolerance: float = 1.0
    min_pair_distance: float = 2.0
    max_hypotheses: int = 5000
    inlier_distance: float = 2.0
    inlier_angle_deg: float = 10.0
    stop_ratio: float = 0.6
    batch_size: int = 64
    kappa_max: float = 1e3
    seed: int = 0
    name: str = "ClusterMatch"
    kind: MethodKind = "landmark"

    def _associate(self, src: LandmarkSet, tgt: LandmarkSet, T: Array) -> NDArray[np.intp]:
        ok, D = support_masks(src, tgt, T[None], self.inlier_distance, self.inlier_angle_deg)
        cost = np.where(ok[0], D[0], np.inf)
        return greedy_one_to_one(cost, np.full(len(src), np.inf))

    def run(self, pair: PairInput) -> MethodOutput:
        src, tgt = pair.source.without_points(), pair.target.without_points()
        rng = np.random.default_rng(self.seed)
        timer = Timer()
        problem = too_few_landmarks(pair)
        if problem:
            return no_estimate(problem, timer)
        with timer.stage("signatures"):
            sp, tp, n_cand = candidate_pair_matches(
                src, tgt, self.pair_tolerance, self.min_pair_distance, self.max_hypotheses, rng
            )
        best_T, best_support, n_eval = None, -1, 0
        stop = max(3, int(np.ceil(self.stop_ratio * min(len(src), len(tgt)))))
        with timer.stage("validation"):
            for b in range(0, len(sp), self.batch_size):
                T, ok = pair_hypotheses(
                    src, tgt, sp[b : b + self.batch_size], tp[b : b + self.batch_size]
                )
                T = T[ok]
                n_eval += len(T)
                if len(T) == 0:
                    continue
                comp, _ = support_masks(src, tgt, T, self.inlier_distance, self.inlier_angle_deg)
                support = comp.any(axis=2).sum(axis=1)
                k = int(np.argmax(support))
                if support[k] > best_support:
                    best_support, best_T = int(support[k]), T[k]
                if best_support >= stop:
                    break
        a = np.zeros((0, 2), np.intp)
        T_est, valid, info = None, False, {"message": "no consistent pair hypothesis"}
        if best_T is not None:
            with timer.stage("registration"):
                a = self._associate(src, tgt, best_T)
                T_est, valid, info = register_associations(src, tgt, a, self.kappa_max)
                if T_est is not None:  # one refinement: re-associate with the refined transform
                    a2 = self._associate(src, tgt, T_est)
                    if len(a2) >= len(a):
                        T2, valid2, info2 = register_associations(src, tgt, a2, self.kappa_max)
                        if T2 is not None:
                            a, T_est, valid, info = a2, T2, valid2, info2
        info.update(n_candidates=n_cand, n_hypotheses=n_eval, best_support=max(best_support, 0))
        return MethodOutput(T_est, a, timer.finish(), valid, info)
