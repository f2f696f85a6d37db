"""A cheap geometric pre-screen of loop candidates, run before the verified matcher.

The verified matcher costs tens of milliseconds a candidate; most retrieved candidates are not
the same place. This check costs a fraction of a millisecond a candidate: it levels each landmark
map once (``up`` from the pole directions, else the ground normal), reduces it to a bird's-eye
view of pole positions and facade lines (:class:`QuickIndex`, computed once per scan and kept in
the database), and registers two views by voting:

* hypotheses (yaw, 2-D translation) from matched *pairs* whose invariant agrees: two poles
  (their distance), a pole and a facade (the pole's distance from it), two facades (their angle;
  the corner is the anchor);
* the votes are binned (``yaw_bin_deg``, ``t_bin_m``) and the best bins' hypotheses are scored by
  *inliers*: query poles within ``inlier_m`` of a candidate pole plus query facades within
  ``inlier_deg`` and ``inlier_m`` of a candidate facade.

The score is that inlier count. :func:`quick_check_many` scores all candidates of a query in
one compiled pass (:mod:`.quick_kernel`); :func:`quick_check_numpy` is the readable NumPy
version it is tested against. The score is rotation-invariant (every hypothesis is built from
invariants), so a reverse-direction revisit scores like a same-direction one. A gate on it is
only a pre-screen: the candidates that pass are still verified by the matcher; the gate's
threshold is chosen so that (measured, ``bench/bench_loops_speed.py``) no candidate the matcher
accepts is screened out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.loops.quick_kernel import pack, quick_scores

Array = NDArray[np.float64]


class QuickCheckConfig(BaseModel):
    """Tolerances of the bird's-eye-view voting pre-screen."""

    model_config = ConfigDict(extra="forbid")

    vertical_deg: float = Field(20.0, gt=0, lt=90, description="a line this close to up is a pole [deg]")
    pair_tol_m: float = Field(0.3, gt=0, description="invariant distances of matched pairs agree within [m]")
    pair_tol_deg: float = Field(4.0, gt=0, description="facade-pair angles agree within [deg]")
    min_pair_m: float = Field(1.0, ge=0, description="shortest pole-pole distance used for a hypothesis [m]")

    min_corner_deg: float = Field(30.0, gt=0, lt=90, description="facade pairs at least this far from parallel")
    max_range_m: float = Field(80.0, gt=0, description="ignore BEV elements farther than this [m]")
    yaw_bin_deg: float = Field(6.0, gt=0, description="vote bin of the yaw [deg]")
    t_bin_m: float = Field(1.5, gt=0, description="vote bin of the translation [m]")
    top_bins: int = Field(6, ge=1, description="best vote bins whose hypotheses are scored")
    inlier_m: float = Field(0.75, gt=0, description="inlier distance of poles / facade offsets [m]")
    inlier_deg: float = Field(5.0, gt=0, description="inlier angle of facades [deg]")
    facade_anchor_m: float = Field(15.0, gt=0, description="facade anchors this close in the plane [m]")


@dataclass
class QuickIndex:
    """The levelled bird's-eye view of one scan's landmarks (computed once per scan)."""

    poles: Array  # (p, 2) axis positions
    facade_angle: Array  # (f,) normal angle mod pi
    facade_normal: Array  # (f, 2) unit normals (angle as above)
    facade_offset: Array  # (f,) c in n . x = c
    facade_anchor: Array  # (f, 2)
    pp: Array  # (P, 4): i, j, distance, direction angle of poles i->j
    pf: Array  # (Q, 3): pole i, facade k, unsigned distance
    ff: Array  # (F, 5): facade k, facade l, signed angle l - k mod pi, corner x, y
    packed: Array = field(init=False, repr=False)  # the same, flat, with sorted invariants (quick_kernel)

    def __post_init__(self) -> None:
        self.packed = pack(self.poles, self.facade_angle, self.facade_normal, self.facade_offset,
                           self.facade_anchor, self.pp, self.pf, self.ff)

    @property
    def size(self) -> int:
        return len(self.poles) + len(self.facade_angle)


def _up_vector(ls: LandmarkSet, vertical_deg: float) -> Array:
    """The sensor's up: mean pole direction (poles are vertical), else the ground normal, else z."""
    d = ls.directions
    z = np.array([0.0, 0.0, 1.0])
    lines = d[ls.types == LandmarkType.LINE]
    if len(lines) >= 2:
        s = np.sign(lines @ z)
        s[s == 0] = 1.0
        lines = lines * s[:, None]
        # the dominant direction: eigenvector of the scatter, robust to a few slanted lines
        _w, v = np.linalg.eigh(lines.T @ lines)
        u = v[:, -1] * (1.0 if v[2, -1] >= 0 else -1.0)
        if u @ z > np.cos(np.radians(45.0)):
            return u / np.linalg.norm(u)
    planes = d[ls.types == LandmarkType.PLANE]
    if len(planes):
        c = np.abs(planes @ z)
        k = int(np.argmax(c))
        if c[k] > np.cos(np.radians(vertical_deg)):
            return planes[k] * np.sign(planes[k] @ z)
    return z


def _rotation_to_z(u: Array) -> Array:
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(u, z)
    s, c = np.linalg.norm(v), float(u @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = v / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * K @ K


def quick_index(ls: LandmarkSet, config: QuickCheckConfig | None = None) -> QuickIndex:
    """Level the map and tabulate the pairs the voting uses."""
    cfg = config or QuickCheckConfig()
    R = _rotation_to_z(_up_vector(ls, cfg.vertical_deg))
    d = ls.directions @ R.T
    a = np.asarray(ls.anchors, float) @ R.T
    cos_v = np.cos(np.radians(cfg.vertical_deg))
    li = np.flatnonzero((ls.types == LandmarkType.LINE) & (np.abs(d[:, 2]) > cos_v))
    # pole axis at the sensor's height (z = 0 of the levelled frame)
    dl, al = d[li], a[li]
    poles = al[:, :2] - (al[:, 2] / dl[:, 2])[:, None] * dl[:, :2]
    poles = poles[np.linalg.norm(poles, axis=1) < cfg.max_range_m]
    pi_ = np.flatnonzero((ls.types == LandmarkType.PLANE) & (np.abs(d[:, 2]) < np.sin(np.radians(cfg.vertical_deg))))
    n2 = d[pi_, :2]
    n2 = n2 / np.maximum(np.linalg.norm(n2, axis=1, keepdims=True), 1e-12)
    ang = np.mod(np.arctan2(n2[:, 1], n2[:, 0]), np.pi)
    n2 = np.stack([np.cos(ang), np.sin(ang)], axis=1)  # the representative of the line's normal
    anc = a[pi_, :2]
    off = np.einsum("ij,ij->i", n2, anc)
    keep = np.linalg.norm(anc, axis=1) < cfg.max_range_m
    n2, ang, anc, off = n2[keep], ang[keep], anc[keep], off[keep]

    i, j = np.triu_indices(len(poles), 1)
    v = poles[j] - poles[i]
    dist = np.linalg.norm(v, axis=1)
    ok = dist >= cfg.min_pair_m
    pp = np.stack([i[ok], j[ok], dist[ok], np.arctan2(v[ok, 1], v[ok, 0])], axis=1) if ok.any() else np.zeros((0, 4))

    pf_i, pf_k = np.meshgrid(np.arange(len(poles)), np.arange(len(ang)), indexing="ij")
    pf_i, pf_k = pf_i.ravel(), pf_k.ravel()
    pf = np.stack([pf_i, pf_k, np.abs(np.einsum("ij,ij->i", poles[pf_i], n2[pf_k]) - off[pf_k])], axis=1)

    k, l_ = np.triu_indices(len(ang), 1)
    delta = np.mod(ang[l_] - ang[k], np.pi)
    sharp = np.sin(delta) >= np.sin(np.radians(cfg.min_corner_deg))
    k, l_, delta = k[sharp], l_[sharp], delta[sharp]
    A = np.stack([n2[k], n2[l_]], axis=1)  # (F, 2, 2)
    b = np.stack([off[k], off[l_]], axis=1)
    corner = np.linalg.solve(A, b[..., None])[..., 0] if len(k) else np.zeros((0, 2))
    ff = np.column_stack([k, l_, delta, corner]) if len(k) else np.zeros((0, 5))
    return QuickIndex(poles, ang, n2, off, anc, pp, pf.reshape(-1, 3), ff)


def _rot(theta: Array) -> Array:
    c, s = np.cos(theta), np.sin(theta)
    R = np.empty((*np.shape(theta), 2, 2))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1] = c, -s, s, c
    return R


def _apply(theta: Array, p: Array) -> Array:
    """Rotate points p (H, 2) by the angles theta (H,)."""
    c, s = np.cos(theta), np.sin(theta)
    return np.column_stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]])


def _matches(x: Array, y: Array, tol: float) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Index pairs (a, b) with |x[a] - y[b]| < tol (sorted sweep, no full matrix)."""
    if len(x) == 0 or len(y) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order = np.argsort(y, kind="stable")
    ys = y[order]
    lo = np.searchsorted(ys, x - tol, side="left")
    hi = np.searchsorted(ys, x + tol, side="right")
    cnt = hi - lo
    a = np.repeat(np.arange(len(x)), cnt)
    start = np.repeat(lo - np.r_[0, np.cumsum(cnt)[:-1]], cnt)
    b = order[np.arange(cnt.sum()) + start]
    return a, b


def _hypotheses(q: QuickIndex, c: QuickIndex, cfg: QuickCheckConfig) -> tuple[Array, Array]:
    """(yaw (H,), translation (H, 2)) of every pair match, both assignments each."""
    yaws, ts = [], []
    # pole pairs: i->a, j->b, or i->b, j->a (the candidate's direction reversed)
    a, b = _matches(q.pp[:, 2], c.pp[:, 2], cfg.pair_tol_m)
    if len(a):
        for flip in (0.0, np.pi):
            th = c.pp[b, 3] + flip - q.pp[a, 3]
            src = q.poles[q.pp[a, 0].astype(int)]
            dst = c.poles[np.where(flip == 0.0, c.pp[b, 0], c.pp[b, 1]).astype(int)]
            yaws.append(th)
            ts.append(dst - _apply(th, src))
    # pole + facade: the pole maps to the pole, the facade's line to the facade's line (two yaws)
    a, b = _matches(q.pf[:, 2], c.pf[:, 2], cfg.pair_tol_m)
    if len(a):
        base = c.facade_angle[c.pf[b, 1].astype(int)] - q.facade_angle[q.pf[a, 1].astype(int)]
        src = q.poles[q.pf[a, 0].astype(int)]
        dst = c.poles[c.pf[b, 0].astype(int)]
        for flip in (0.0, np.pi):
            th = base + flip
            yaws.append(th)
            ts.append(dst - _apply(th, src))
    # facade pairs (corners): k->k', l->l' when the angles agree, k->l', l->k' when mirrored
    if len(q.ff) and len(c.ff):
        tol = np.radians(cfg.pair_tol_deg)
        for swap in (False, True):
            cd = np.pi - c.ff[:, 2] if swap else c.ff[:, 2]
            a, b = _matches(q.ff[:, 2], cd, tol)
            if not len(a):
                continue
            first = c.ff[b, 1] if swap else c.ff[b, 0]
            base = c.facade_angle[first.astype(int)] - q.facade_angle[q.ff[a, 0].astype(int)]
            for flip in (0.0, np.pi):
                th = base + flip
                yaws.append(th)
                ts.append(c.ff[b, 3:5] - _apply(th, q.ff[a, 3:5]))
    if not yaws:
        return np.zeros(0), np.zeros((0, 2))
    return np.mod(np.concatenate(yaws), 2 * np.pi), np.concatenate(ts)


def _inliers(q: QuickIndex, c: QuickIndex, th: Array, t: Array, cfg: QuickCheckConfig) -> NDArray[np.int64]:
    """Inlier counts of H hypotheses (poles + facades of the query that land on the candidate's)."""
    R = _rot(th)  # (H, 2, 2)
    score = np.zeros(len(th), np.int64)
    if len(q.poles) and len(c.poles):
        p = np.einsum("hij,nj->hni", R, q.poles) + t[:, None, :]  # (H, n, 2)
        d2 = ((p[:, :, None, :] - c.poles[None, None, :, :]) ** 2).sum(-1)  # (H, n, m)
        score += (d2.min(axis=2) < cfg.inlier_m**2).sum(axis=1)
    if len(q.facade_angle) and len(c.facade_angle):
        nq = np.einsum("hij,nj->hni", R, q.facade_normal)  # (H, n, 2)
        cq = q.facade_offset[None, :] + np.einsum("hni,hi->hn", nq, t)
        dot = np.einsum("hni,mi->hnm", nq, c.facade_normal)  # cos of the normal angle, signed
        sign = np.sign(dot)
        off = np.abs(cq[:, :, None] - sign * c.facade_offset[None, None, :])
        aq = np.einsum("hij,nj->hni", R, q.facade_anchor) + t[:, None, :]
        near = ((aq[:, :, None, :] - c.facade_anchor[None, None, :, :]) ** 2).sum(-1) < cfg.facade_anchor_m**2
        ok = (np.abs(dot) > np.cos(np.radians(cfg.inlier_deg))) & (off < cfg.inlier_m) & near
        score += ok.any(axis=2).sum(axis=1)
    return score


_DEFAULT = QuickCheckConfig()


def quick_check_many(
    q: QuickIndex, candidates: Sequence[QuickIndex], config: QuickCheckConfig | None = None
) -> tuple[NDArray[np.int64], Array]:
    """(inlier counts (C,), (yaw, tx, ty) of each best hypothesis (C, 3)) of ``q`` against every
    candidate, in one compiled pass."""
    cfg = config or _DEFAULT
    return quick_scores(
        q.packed, [c.packed for c in candidates], cfg.pair_tol_m, cfg.pair_tol_deg, cfg.yaw_bin_deg, cfg.t_bin_m,
        cfg.top_bins, cfg.inlier_m, cfg.inlier_deg, cfg.facade_anchor_m,
    )


def quick_check(q: QuickIndex, c: QuickIndex, config: QuickCheckConfig | None = None) -> tuple[int, Array]:
    """(inlier count, (yaw, tx, ty) of the best hypothesis) of query ``q`` against candidate ``c``."""
    score, est = quick_check_many(q, [c], config)
    return int(score[0]), est[0]


def quick_check_numpy(q: QuickIndex, c: QuickIndex, config: QuickCheckConfig | None = None) -> tuple[int, Array]:
    """:func:`quick_check` in NumPy (the reference of the compiled kernel; same result)."""
    cfg = config or _DEFAULT
    th, t = _hypotheses(q, c, cfg)
    if len(th) == 0:
        return 0, np.zeros(3)
    # one integer key a (yaw, tx, ty) bin; translations beyond +-half_span share the edge bins
    half = 256
    yb = np.floor(th / np.radians(cfg.yaw_bin_deg)).astype(np.int64)
    tb = np.clip(np.floor(t / cfg.t_bin_m).astype(np.int64) + half, 0, 2 * half - 1)
    key = (yb * (2 * half) + tb[:, 0]) * (2 * half) + tb[:, 1]
    _uniq, first, counts = np.unique(key, return_index=True, return_counts=True)
    best = np.argsort(-counts, kind="stable")[: cfg.top_bins]
    reps = first[best]  # one representative a bin: its first hypothesis (a bin holds near-identical ones)
    score = _inliers(q, c, th[reps], t[reps], cfg)
    k = int(np.argmax(score))
    return int(score[k]), np.array([th[reps[k]], *t[reps[k]]])
