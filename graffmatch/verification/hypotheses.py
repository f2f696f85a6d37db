"""Distinct candidate solutions from one consistency graph.

The densest clique is not always the right one: in a symmetric courtyard or a street seen
180 degrees flipped, the wrong clique can be denser. So the matcher keeps several:
CLIPPER's clique, greedy cliques from the best-connected vertices, re-solves with earlier
winners removed, and explicitly the best clique among the associations that disagree with the
winner's transform (its symmetric alternative). All are registered together
(:func:`register_batch`) and near-identical transforms are merged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from graffmatch.association.clipper import ClipperConfig, solve_clipper
from graffmatch.association.cliques import clique_objective, greedy_cliques
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.verification.config import VerificationConfig


@dataclass
class Candidate:
    """A clique (indices into the graph's associations) and where it came from."""

    vertices: NDArray[np.int64]
    origin: str


def residuals(
    source: LandmarkSet, target: LandmarkSet, associations: NDArray[np.int64],
    T_target_source: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(angle [deg], offset [m]) of each association under a transform (points: angle 0)."""
    R, t = T_target_source[:3, :3], T_target_source[:3, 3]
    a, b = associations[:, 0], associations[:, 1]
    ts = source.types[a]
    ds = source.directions[a] @ R.T
    dt = target.directions[b]
    r = target.anchors[b] - (source.anchors[a] @ R.T + t)
    along = np.einsum("ij,ij->i", dt, r)
    off = np.where(
        ts == LandmarkType.PLANE, np.abs(along),
        np.where(ts == LandmarkType.LINE, np.linalg.norm(r - along[:, None] * dt, axis=1),
                 np.linalg.norm(r, axis=1)),
    )
    cosang = np.clip(np.abs(np.einsum("ij,ij->i", ds, dt)), 0.0, 1.0)
    ang = np.where(ts == LandmarkType.POINT, 0.0, np.degrees(np.arccos(cosang)))
    return ang, off


def consistent_with(
    source: LandmarkSet, target: LandmarkSet, associations: NDArray[np.int64],
    T_target_source: NDArray[np.float64], max_deg: float, max_m: float,
) -> NDArray[np.bool_]:
    """Which associations agree with a transform (direction within max_deg, offset within max_m)."""
    ang, off = residuals(source, target, associations, T_target_source)
    return (ang <= max_deg) & (off <= max_m)


def reassociate(
    source: LandmarkSet, target: LandmarkSet, associations: NDArray[np.int64],
    T_target_source: NDArray[np.float64], max_deg: float, max_m: float,
) -> NDArray[np.int64]:
    """Every putative association that agrees with a transform, one-to-one (smallest residual
    wins): the chosen hypothesis's final correspondences, beyond its own clique."""
    ang, off = residuals(source, target, associations, T_target_source)
    ok = np.flatnonzero((ang <= max_deg) & (off <= max_m))
    if len(ok) == 0:
        return associations[:0]
    cost = off[ok] / max_m + ang[ok] / max_deg
    ok = ok[np.argsort(cost, kind="stable")]
    A = associations[ok]
    _, first_s = np.unique(A[:, 0], return_index=True)
    keep = np.zeros(len(A), bool)
    keep[first_s] = True
    A2 = A[keep]
    order_kept = np.flatnonzero(keep)
    _, first_t = np.unique(A2[:, 1], return_index=True)
    sel = np.sort(order_kept[first_t])  # back in cost order
    return A[sel]


def translation_redundancy(
    target: LandmarkSet, associations: NDArray[np.int64],
) -> tuple[float, NDArray[np.float64], float, NDArray[np.float64]]:
    """How well explained landmarks pin the translation, and whether any one of them is spared.

    Each association constrains the translation along its target landmark's normal (plane),
    across its axis (line) or fully (point); the information matrix is the sum of those
    projectors. Returns (its smallest eigenvalue and direction; the smallest horizontal
    eigenvalue with any single association left out, and its direction). A direction held by
    one landmark alone has a zero residual whatever that landmark is matched to, so a wrong
    match there is invisible: a translation off by metres along it explains as much.
    Horizontal only (frames are z-up): the height usually rests on the one ground plane.
    """
    if len(associations) == 0:
        e = np.array([1.0, 0.0, 0.0])
        return 0.0, e, 0.0, e
    b = associations[:, 1]
    ty, d = target.types[b], target.directions[b]
    P = np.einsum("ki,kj->kij", d, d)
    C = np.where((ty == LandmarkType.PLANE)[:, None, None], P,
                 np.where((ty == LandmarkType.LINE)[:, None, None], np.eye(3) - P, np.eye(3)))
    M = C.sum(axis=0)
    w, V = np.linalg.eigh(M)
    wl, Vl = np.linalg.eigh((M[None] - C)[:, :2, :2])  # every leave-one-out matrix at once
    k = int(np.argmin(wl[:, 0]))
    return float(max(w[0], 0.0)), V[:, 0], float(max(wl[k, 0], 0.0)), np.r_[Vl[k, :, 0], 0.0]


def local_perturbations(
    T_target_source: NDArray[np.float64], centre: NDArray[np.float64], step_m: float, reach_m: float,
    yaw_deg: float,
) -> NDArray[np.float64]:
    """(H, 4, 4) starts around a transform: a horizontal grid of offsets (every ``step_m`` up to
    ``reach_m``) times yaws of (-yaw_deg, 0, +yaw_deg) about the vertical through ``centre``
    (the transformed source centroid, so a yaw does not swing far points away).

    Point alignment from a landmark registration that is 1-2 m off (plane fits on partial,
    noisy views) converges to a nearby local optimum; scoring these starts finds the basin of
    the better one. Frames are z-up."""
    g = np.arange(-reach_m, reach_m + 1e-9, step_m)
    dx, dy, yaw = np.meshgrid(g, g, np.radians([-yaw_deg, 0.0, yaw_deg]), indexing="ij")
    dx, dy, yaw = dx.ravel(), dy.ravel(), yaw.ravel()
    c, s_ = np.cos(yaw), np.sin(yaw)
    D = np.zeros((len(yaw), 4, 4))
    D[:, 0, 0], D[:, 0, 1], D[:, 1, 0], D[:, 1, 1] = c, -s_, s_, c
    D[:, 2, 2] = D[:, 3, 3] = 1.0
    # rotate about the centre, then shift: x -> R (x - c) + c + d
    D[:, :3, 3] = centre - np.einsum("hij,j->hi", D[:, :3, :3], centre) + np.c_[dx, dy, np.zeros_like(dx)]
    return D @ T_target_source


def candidate_cliques(
    W: sp.csr_matrix, winner: NDArray[np.int64], cfg: VerificationConfig, solver: ClipperConfig,
) -> list[Candidate]:
    """CLIPPER's winner, greedy cliques and re-solves without earlier winners (no registration)."""
    m = W.shape[0]
    out = [Candidate(np.asarray(winner, np.int64), "clipper")]
    if m == 0:
        return out
    wdeg = np.asarray(W.sum(axis=1)).ravel()
    order = np.argsort(-wdeg, kind="stable")
    if m <= cfg.greedy_all_below:  # small graphs: a greedy clique from every vertex
        out += [Candidate(c, "greedy") for c in greedy_cliques(W, order)]
    elif cfg.greedy_starts:
        in_winner = np.zeros(m, bool)
        in_winner[winner] = True
        # half the starts among the best-connected vertices, half outside the winner
        outside = order[~in_winner[order]]
        starts = np.unique(np.r_[order[: cfg.greedy_starts // 2 + 1],
                                 outside[: cfg.greedy_starts - cfg.greedy_starts // 2]])
        starts = starts[np.argsort(-wdeg[starts], kind="stable")]
        out += [Candidate(c, "greedy") for c in greedy_cliques(W, starts)]
    removed = np.zeros(m, bool)
    removed[winner] = True
    for _ in range(cfg.resolves):
        allowed = ~removed
        if allowed.sum() < 3:
            break
        if cfg.resolve_with_clipper:
            keep = np.flatnonzero(allowed)
            sub = W[keep][:, keep]
            sel = keep[solve_clipper(sub, solver).selected] if sub.nnz else keep[:0]
        else:  # the densest of a few greedy cliques grown outside the earlier winners
            starts = order[allowed[order]][:4]
            found = greedy_cliques(W, starts, allowed)
            sel = max(found, key=lambda c: clique_objective(W, c)) if found else order[:0]
        if len(sel) < 2:
            break
        out.append(Candidate(np.sort(sel), "resolve"))
        removed[sel] = True
    return out


def rival_cliques(
    W: sp.csr_matrix, consistent: NDArray[np.bool_], n_starts: int
) -> list[Candidate]:
    """Greedy cliques among the associations that disagree with the winner's transform."""
    allowed = ~consistent
    if allowed.sum() < 2:
        return []
    wdeg = np.asarray(W[allowed].sum(axis=1)).ravel()
    idx = np.flatnonzero(allowed)
    starts = idx[np.argsort(-wdeg, kind="stable")[: max(n_starts, 1)]]
    return [Candidate(c, "rival") for c in greedy_cliques(W, starts, allowed)]
