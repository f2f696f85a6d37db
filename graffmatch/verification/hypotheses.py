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

import numba as nb
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from graffmatch.association.clipper import ClipperConfig, solve_clipper
from graffmatch.association.cliques import clique_objective, greedy_cliques
from graffmatch.errors import DegenerateGeometryError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.registration.closed_form import _directions_of, register_batch
from graffmatch.verification.config import VerificationConfig


@dataclass
class Candidate:
    """A clique (indices into the graph's associations) and where it came from; ``T_target_source``
    is the transform it was found by, if any (a pole pair's), which competes as a hypothesis of
    its own next to the clique's registration."""

    vertices: NDArray[np.int64]
    origin: str
    T_target_source: NDArray[np.float64] | None = None


def residuals(
    source: LandmarkSet, target: LandmarkSet, associations: NDArray[np.int64],
    T_target_source: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(angle [deg], offset [m]) of each association under a transform (points: angle 0)."""
    R, t = T_target_source[:3, :3], T_target_source[:3, 3]
    a, b = associations[:, 0], associations[:, 1]
    ts = source.types[a]
    ds = _directions_of(source)[a] @ R.T  # (cached per set: verification calls this 3-4 times)
    dt = _directions_of(target)[b]
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


def _one_to_one(associations: NDArray[np.int64], ok: NDArray[np.int64], cost: NDArray[np.float64]) -> NDArray[np.int64]:
    """Indices ``ok`` thinned to one association per source and per target landmark (smallest
    cost wins), in cost order."""
    ok = ok[np.argsort(cost, kind="stable")]
    A = associations[ok]
    _, first_s = np.unique(A[:, 0], return_index=True)
    keep = np.zeros(len(A), bool)
    keep[first_s] = True
    A2 = A[keep]
    order_kept = np.flatnonzero(keep)
    _, first_t = np.unique(A2[:, 1], return_index=True)
    return ok[np.sort(order_kept[first_t])]  # back in cost order


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
    return associations[_one_to_one(associations, ok, off[ok] / max_m + ang[ok] / max_deg)]


def pair_transforms(
    source: LandmarkSet, target: LandmarkSet, associations: NDArray[np.int64], W: sp.csr_matrix,
    cfg: VerificationConfig, kappa_max: float, with_edges: bool = False,
) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Graphs of lines only (poles): the transform of every consistent pair of associations,
    registered on its own (two poles fix the yaw and the horizontal translation).

    Dense wrong cliques beat the true one in pole-only graphs (downtown: many poles, regularly
    spaced along the street, agree by chance); this RANSAC-like enumeration over the graph's
    edges reaches the true transform whenever two of its poles are matched. Returns (E, 4, 4)
    transforms (and with ``with_edges`` the (E, 2) association pair of each); empty when the
    graph holds other types or ``pair_hypotheses`` is 0."""
    none = np.zeros((0, 4, 4))
    m = len(associations)
    if cfg.pair_hypotheses == 0 or m < 2 or np.any(source.types[associations[:, 0]] != LandmarkType.LINE):
        return (none, np.zeros((0, 2), np.int64)) if with_edges else none
    U = sp.triu(W, k=1).tocoo()
    r, c, v = U.row.astype(np.int64), U.col.astype(np.int64), U.data
    keep = (associations[r, 0] != associations[c, 0]) & (associations[r, 1] != associations[c, 1])
    r, c, v = r[keep], c[keep], v[keep]
    if len(r) == 0:
        return (none, np.zeros((0, 2), np.int64)) if with_edges else none
    if len(r) > cfg.pair_max_edges:  # the most consistent edges
        top = np.sort(np.argsort(-v, kind="stable")[: cfg.pair_max_edges])
        r, c = r[top], c[top]
    Ts, vertical, used = _vertical_pair_transforms(source, target, associations, r, c, cfg.pair_vertical_deg)
    edges = np.stack([r, c], 1)[vertical][used]
    if not vertical.all():  # other lines: the general registration, upright rule included
        r, c = r[~vertical], c[~vertical]
        E = len(r)
        try:
            b = register_batch(source, target, associations[np.stack([r, c], 1).ravel()],
                               np.repeat(np.arange(E), 2), None, kappa_max, E)
            usable = b.used_line_positions & np.isfinite(b.T_target_source).all(axis=(1, 2))
            Ts = np.concatenate([Ts, b.T_target_source[usable]])
            edges = np.concatenate([edges, np.stack([r, c], 1)[usable]])
        except DegenerateGeometryError:
            pass
    Ts = np.ascontiguousarray(Ts)
    return (Ts, edges.astype(np.int64)) if with_edges else Ts


def line_consensus(
    source: LandmarkSet, target: LandmarkSet, associations: NDArray[np.int64], Ts: NDArray[np.float64],
    cfg: VerificationConfig,
) -> NDArray[np.int64]:
    """(E,) how many line associations agree with each transform (within ``consistent_deg`` /
    ``consistent_m``): the ranking of pole pairs when no evidence points exist."""
    a_s, a_t = associations[:, 0], associations[:, 1]
    count, _ = _line_consensus(
        np.ascontiguousarray(Ts), np.ascontiguousarray(source.directions[a_s]),
        np.ascontiguousarray(target.directions[a_t]), np.ascontiguousarray(source.anchors[a_s]),
        np.ascontiguousarray(target.anchors[a_t]), float(np.cos(np.radians(cfg.consistent_deg))),
        float(cfg.consistent_m))
    return count




def _vertical_pair_transforms(
    source: LandmarkSet, target: LandmarkSet, associations: NDArray[np.int64], r: NDArray[np.int64],
    c: NDArray[np.int64], max_deg: float,
) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_]]:
    """Edges whose four lines are within ``max_deg`` of z (poles in z-up frames): the yaw turns
    the source's pole-to-pole vector onto the target's (positions where the axes cross z = 0),
    the horizontal translation matches their midpoints and the height the mean along-axis
    anchor offset, in closed form for all edges at once (the general batched registration costs
    ~10 us an edge). Returns (transforms of the usable vertical edges, which edges are vertical,
    which vertical edges are usable); edges whose poles are closer than 0.2 m fix no yaw and are
    dropped."""
    i = np.stack([r, c], 1)
    ds, dt = source.directions[associations[i, 0]], target.directions[associations[i, 1]]  # (E, 2, 3)
    cos_min = np.cos(np.radians(max_deg))
    vertical = (np.abs(ds[..., 2]) >= cos_min).all(axis=1) & (np.abs(dt[..., 2]) >= cos_min).all(axis=1)
    bs, bt = source.anchors[associations[i, 0]][vertical], target.anchors[associations[i, 1]][vertical]
    ds, dt = ds[vertical], dt[vertical]
    ps = bs[..., :2] - (bs[..., 2] / ds[..., 2])[..., None] * ds[..., :2]  # axis at z = 0
    pt = bt[..., :2] - (bt[..., 2] / dt[..., 2])[..., None] * dt[..., :2]
    vs, vt = ps[:, 1] - ps[:, 0], pt[:, 1] - pt[:, 0]
    ok = (np.linalg.norm(vs, axis=1) >= 0.2) & (np.linalg.norm(vt, axis=1) >= 0.2)
    yaw = np.arctan2(vt[ok, 1], vt[ok, 0]) - np.arctan2(vs[ok, 1], vs[ok, 0])
    co, si = np.cos(yaw), np.sin(yaw)
    T = np.tile(np.eye(4), (len(yaw), 1, 1))
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = co, -si, si, co
    ms, mt = ps[ok].mean(axis=1), pt[ok].mean(axis=1)
    T[:, 0, 3] = mt[:, 0] - (co * ms[:, 0] - si * ms[:, 1])
    T[:, 1, 3] = mt[:, 1] - (si * ms[:, 0] + co * ms[:, 1])
    T[:, 2, 3] = (bt[ok, :, 2] - bs[ok, :, 2]).mean(axis=1)
    return T, vertical, ok


def pair_candidates(
    source: LandmarkSet, target: LandmarkSet, associations: NDArray[np.int64], Ts: NDArray[np.float64],
    order: NDArray[np.int64], cfg: VerificationConfig, edges: NDArray[np.int64] | None = None,
) -> list[Candidate]:
    """The first ``pair_hypotheses`` distinct transforms of ``Ts`` in ``order`` (closer than
    merge_deg / merge_m to an earlier one: skipped), each as the clique of the associations
    consistent with it (one-to-one; at least 2), or, when fewer agree and ``edges`` are given,
    of its own pair: one true pole and a wrong one whose spacing differs by 2 m still give a
    transform that the points confirm (sim-downtown, bench/verification.py)."""
    R, t = Ts[:, :3, :3], Ts[:, :3, 3]
    out: list[Candidate] = []
    kept = np.zeros(0, np.int64)
    tr_min = 1.0 + 2.0 * (np.cos(np.radians(cfg.merge_deg)) - 1.0)  # trace(R_a^T R_b) at merge_deg
    for e in order:
        if len(kept):
            tr = np.einsum("kij,ij->k", R[kept], R[e])
            if np.any((tr >= tr_min) & (np.linalg.norm(t[kept] - t[e], axis=1) <= cfg.merge_m)):
                continue
        ang, off = residuals(source, target, associations, Ts[e])
        ok = np.flatnonzero((ang <= cfg.consistent_deg) & (off <= cfg.consistent_m))
        sel = _one_to_one(associations, ok, off[ok])
        if len(sel) < 2:
            if edges is None:
                continue
            sel = edges[e]
        out.append(Candidate(np.sort(sel), "pairs", Ts[e]))
        kept = np.r_[kept, e]
        if len(out) >= cfg.pair_hypotheses:
            break
    return out


@nb.njit(cache=True)
def _line_consensus(Ts: NDArray[np.float64], ds: NDArray[np.float64], dt: NDArray[np.float64],
                    bs: NDArray[np.float64], bt: NDArray[np.float64], cos_min: float,
                    max_m: float) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Per transform: how many line associations agree with it (direction within ``cos_min``,
    axes within ``max_m``) and the sum of their offsets. One compiled pass over E x m."""
    E, m = Ts.shape[0], ds.shape[0]
    count = np.zeros(E, np.int64)
    spread = np.zeros(E)
    for e in range(E):
        T = Ts[e]
        for i in range(m):
            c = 0.0
            for a in range(3):
                c += dt[i, a] * (T[a, 0] * ds[i, 0] + T[a, 1] * ds[i, 1] + T[a, 2] * ds[i, 2])
            if abs(c) < cos_min:
                continue
            r0 = bt[i, 0] - (T[0, 0] * bs[i, 0] + T[0, 1] * bs[i, 1] + T[0, 2] * bs[i, 2] + T[0, 3])
            r1 = bt[i, 1] - (T[1, 0] * bs[i, 0] + T[1, 1] * bs[i, 1] + T[1, 2] * bs[i, 2] + T[1, 3])
            r2 = bt[i, 2] - (T[2, 0] * bs[i, 0] + T[2, 1] * bs[i, 1] + T[2, 2] * bs[i, 2] + T[2, 3])
            al = r0 * dt[i, 0] + r1 * dt[i, 1] + r2 * dt[i, 2]
            p0, p1, p2 = r0 - al * dt[i, 0], r1 - al * dt[i, 1], r2 - al * dt[i, 2]
            off = np.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
            if off <= max_m:
                count[e] += 1
                spread[e] += off
    return count, spread


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
    ty, d = target.types[b], _directions_of(target)[b]
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
    D[:, :3, 3] = centre - np.einsum("hij,j->hi", D[:, :3, :3], centre) + np.stack((dx, dy, np.zeros_like(dx)), axis=1)
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
    wdeg = np.asarray(W.sum(axis=1)).ravel()[allowed]  # (row sums as of W[allowed], without the copy)
    idx = np.flatnonzero(allowed)
    starts = idx[np.argsort(-wdeg, kind="stable")[: max(n_starts, 1)]]
    return [Candidate(c, "rival") for c in greedy_cliques(W, starts, allowed)]
