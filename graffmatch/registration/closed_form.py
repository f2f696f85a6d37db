"""Closed-form least-squares registration of matched points, lines and planes (paper eq. reg).

Rotation: weighted SVD (Arun/Kabsch) of the correlation of matched line directions, plane
normals and centred points. Directions and normals have no sign, so the signs are resolved by
trying the four sign combinations of the two most independent directions, re-assigning every
sign from each candidate rotation, and keeping the candidate with the smallest total residual
(rotation and translation); translation is what separates a rotation from its 180 degree twin
when every direction is vertical or horizontal.

Translation: linear least squares on the anchors, which makes it sign free:
planes ``n_t^T (R b_s + t - b_t) = 0`` (one row), lines ``P_t (R b_s + t - b_t) = 0`` with
``P_t = I - d_t d_t^T`` (two independent rows), points ``R b_s + t = b_t`` (three rows).
Anchors need not correspond: only their offsets across the landmark are constrained.

Conditioning: ``kappa_rotation = s1 / s2`` of the correlation matrix (a rotation is unique from
two independent directions, so rank 2 suffices) and ``kappa_translation = s1 / s3`` of the
translation system. ``kappa = max`` of both; ``degenerate`` when it exceeds ``kappa_max``, e.g.
all planes parallel or all lines parallel.

Implementation: :func:`register_batch` runs one compiled loop over the groups (3x3 Jacobi SVDs
and eigen-decompositions, no per-operation overhead); :func:`_register_batch_reference` is the
batched numpy specification it is tested against, and it re-solves the few groups whose result
hangs on rounding (see :data:`FRAGILE_REASONS`). The module runs past 500 lines for that
reason: the compiled kernel and the reference it falls back to must stay side by side.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from graffmatch.errors import DegenerateGeometryError, InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.geometry.set_cache import kernel_input

Array = NDArray[np.float64]

# Parallel lines alone (poles) fit a turn about their common direction and a half-turn across
# it equally well; the half-turn turns the scene upside down, which no sensor motion between two
# scans of a z-up frame does. When the common direction is within 60 deg of z (|d_z| >= this),
# a candidate that maps up to down is kept only if every candidate does. On the sim-downtown
# test pairs, registration from the ground-truth pole associations was right on 83 of 120 pairs
# without this rule and on 96 with it (bench/lines_diagnosis.py).
UPRIGHT_MIN = 0.5


@dataclass
class RegistrationEstimate:
    """Least-squares transform with its conditioning and per-association residuals."""

    T_target_source: Array
    kappa: float
    kappa_rotation: float
    kappa_translation: float
    degenerate: bool
    rotation_rank: int
    translation_rank: int
    angle_residuals_deg: Array  # per association (0 for points)
    offset_residuals: Array  # per association [m]
    signs: Array  # +-1 per association (direction sign used)
    info: dict = field(default_factory=dict)

    @property
    def rms_offset(self) -> float:
        r = self.offset_residuals
        return float(np.sqrt(np.mean(r**2))) if r.size else 0.0


@dataclass
class BatchRegistration:
    """Registrations of G association groups (hypotheses) solved together.

    Per group: ``T_target_source`` (G, 4, 4), ``kappa``/``kappa_rotation``/``kappa_translation``,
    ``degenerate``, ranks and the least-squares ``cost``. Per association (in input order):
    ``angle_residuals_deg``, ``offset_residuals`` and ``signs``. ``used_line_positions`` marks
    groups whose directions alone could not fix the rotation (e.g. only vertical poles), where
    the lines' positions in the plane across them did.
    """

    T_target_source: NDArray[np.float64]
    kappa: NDArray[np.float64]
    kappa_rotation: NDArray[np.float64]
    kappa_translation: NDArray[np.float64]
    degenerate: NDArray[np.bool_]
    rotation_rank: NDArray[np.int64]
    translation_rank: NDArray[np.int64]
    cost: NDArray[np.float64]
    used_line_positions: NDArray[np.bool_]
    angle_residuals_deg: NDArray[np.float64]
    offset_residuals: NDArray[np.float64]
    signs: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.kappa)


def _group_sum(X: Array, g: NDArray[np.int64], G: int) -> Array:
    """Sum rows of ``X`` (C, k, F) per group ``g`` (k,) -> (C, G, F), one bincount."""
    C, _k, F = X.shape
    idx = (np.arange(C)[:, None, None] * G + g[None, :, None]) * F + np.arange(F)[None, None, :]
    return np.bincount(idx.ravel(), weights=X.ravel(), minlength=C * G * F).reshape(C, G, F)


def _kabsch_batch(H: Array) -> tuple[Array, Array]:
    """R maximising sum w dt^T R ds for stacked correlations H = sum w ds dt^T (..., 3, 3)."""
    U, S, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
    d[d == 0] = 1.0
    V = V.copy()
    V[..., :, 2] *= d[..., None]
    return V @ np.swapaxes(U, -1, -2), S


def _seed_pairs(ds: Array, w: Array, g: NDArray[np.int64], G: int) -> tuple[Array, Array]:
    """Per group, the two most independent weighted directions (indices into ds, -1 if none)."""
    first = np.full(G, -1, np.int64)
    second = np.full(G, -1, np.int64)
    if len(ds) == 0:
        return first, second
    bounds = np.searchsorted(g, np.arange(G + 1))
    for gi in np.flatnonzero(np.diff(bounds) > 0):
        lo, hi = bounds[gi], bounds[gi + 1]
        if hi - lo == 1:
            first[gi] = second[gi] = lo
            continue
        D = ds[lo:hi]
        c = np.abs(D @ D.T)
        sines = np.sqrt(np.clip(1 - c**2, 0, 1)) * np.sqrt(np.outer(w[lo:hi], w[lo:hi]))
        i, j = np.unravel_index(np.argmax(sines), sines.shape)
        first[gi], second[gi] = lo + i, lo + j
    return first, second


_DIRECTIONS: OrderedDict[tuple[int, int], tuple[Array, NDArray[np.int8], Array]] = OrderedDict()


def _directions_of(ls: LandmarkSet) -> Array:
    """``ls.directions`` (a cross product per plane), computed once per set of bases: one
    verification registers the same two sets 4-5 times. Keyed by the identity of ``bases`` and
    ``types`` and checked against copies of them, so a reused id or bases changed in place are
    recomputed; at most 32 sets. The returned array is shared: read it, never write it."""
    key = (id(ls.bases), id(ls.types))
    e = _DIRECTIONS.get(key)
    if e is not None and np.array_equal(e[0], ls.bases) and np.array_equal(e[1], ls.types):
        return e[2]
    d = ls.directions
    d.setflags(write=False)
    _DIRECTIONS[key] = (ls.bases.copy(), ls.types.copy(), d)
    while len(_DIRECTIONS) > 32:
        try:
            _DIRECTIONS.popitem(last=False)
        except KeyError:  # emptied meanwhile by another thread
            break
    return d


def _register_batch_reference(
    source: LandmarkSet,
    target: LandmarkSet,
    associations: ArrayLike,
    groups: ArrayLike | None = None,
    weights: ArrayLike | None = None,
    kappa_max: float = 1e3,
    n_groups: int | None = None,
    parallel_spread: float = 0.03,
    line_anchor_weight: float = 0.01,
    weak_ratio: float = 1e-2,
    upright_min: float = UPRIGHT_MIN,
) -> BatchRegistration:
    """Reference (numpy, batched 3x3 SVDs and solves) of :func:`register_batch`.

    Kept as the specification of the numba path and as its fallback for numerically fragile
    groups (rank-deficient correlations, sign or candidate ties), where only the same LAPACK
    arithmetic reproduces the same arbitrary choice.

    Each group is one hypothesis. Directions and normals have no sign: each group tries the
    four sign combinations of its two most independent directions, re-assigns every sign twice
    from the refined rotation and keeps the candidate with the smallest cost. When a group's
    directions are (nearly) parallel -- their second principal spread below ``parallel_spread``
    of the first, e.g. vertical poles only -- the rotation about them is fixed by the lines'
    centred positions across the common direction, which the directions alone cannot do.
    ``line_anchor_weight`` weights the along-axis agreement of line anchors in the translation
    (a weak prior that fixes the height of pole-only matches; 0 disables it). It acts only on
    translation directions whose geometric eigenvalue is below ``weak_ratio`` of the largest.
    """
    A = np.asarray(associations, dtype=np.int64).reshape(-1, 2)
    k = len(A)
    g = np.zeros(k, np.int64) if groups is None else np.asarray(groups, dtype=np.int64).reshape(-1)
    if g.shape != (k,):
        raise InvalidInputError(f"groups must have one entry per association ({k}), got {g.shape}")
    if k == 0:
        raise DegenerateGeometryError("no associations to register")
    if g.min() < 0:
        raise InvalidInputError("group indices must be non-negative")
    G = int(g.max()) + 1 if n_groups is None else int(n_groups)
    if g.max() >= G:
        raise InvalidInputError("group index out of range")
    if A[:, 0].max() >= len(source) or A[:, 1].max() >= len(target) or A.min() < 0:
        raise InvalidInputError("association index out of range")
    ts = source.types[A[:, 0]]
    if np.any(ts != target.types[A[:, 1]]):
        raise InvalidInputError("associations must pair landmarks of the same type")
    w = np.ones(k) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    if w.shape != (k,) or not np.all(np.isfinite(w)) or np.any(w < 0):
        raise InvalidInputError("weights must be finite, non-negative, one per association")
    wsum_g = np.bincount(g, weights=w, minlength=G)
    if np.any((np.bincount(g, minlength=G) > 0) & (wsum_g <= 0)):
        raise InvalidInputError("every group needs a positive weight")

    order = np.argsort(g, kind="stable")
    inv = np.empty(k, np.int64)
    inv[order] = np.arange(k)
    A, g, w, ts = A[order], g[order], w[order], ts[order]
    ds = _directions_of(source)[A[:, 0]]
    dt = _directions_of(target)[A[:, 1]]
    bs = source.anchors[A[:, 0]]
    bt = target.anchors[A[:, 1]]
    is_dir = ts > 0

    # Centred point correspondences, scaled to unit spread (per group), mix with directions.
    corr_s = np.zeros((k, 3))
    corr_t = np.zeros((k, 3))
    corr_w = np.zeros(k)
    is_pt = ~is_dir
    n_pt = np.bincount(g[is_pt], minlength=G)
    use_pt = is_pt & (n_pt[g] >= 3)
    if use_pt.any():
        _add_centred(corr_s, corr_t, corr_w, use_pt, bs, bt, w, g, G)

    # Groups whose directions are (nearly) parallel: add the lines' positions across them.
    wd = w * is_dir
    Cov = _group_sum((wd[:, None, None] * ds[:, :, None] * ds[:, None, :]).reshape(1, k, 9), g, G)
    ev = np.linalg.eigvalsh(Cov.reshape(G, 3, 3))  # ascending
    parallel = ev[:, 1] <= parallel_spread * np.maximum(ev[:, 2], 1e-300)
    is_line = ts == LandmarkType.LINE
    n_line = np.bincount(g[is_line], minlength=G)
    use_pos = is_line & parallel[g] & (n_line[g] >= 2) & ~use_pt
    if use_pos.any():
        ps = bs - np.einsum("ij,ij->i", bs, ds)[:, None] * ds
        pt = bt - np.einsum("ij,ij->i", bt, dt)[:, None] * dt
        _add_centred(corr_s, corr_t, corr_w, use_pos, ps, pt, w, g, G)
    used_pos = np.bincount(g[use_pos], minlength=G) > 0

    # Sign candidates from the two most independent directions of each group.
    dir_idx = np.flatnonzero(is_dir)
    i1, i2 = _seed_pairs(ds[dir_idx], w[dir_idx], g[dir_idx], G)
    has_dir = i1 >= 0
    i1 = np.where(has_dir, dir_idx[np.maximum(i1, 0)] if len(dir_idx) else 0, 0)
    i2 = np.where(has_dir, dir_idx[np.maximum(i2, 0)] if len(dir_idx) else 0, 0)
    combos = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]])
    C = 4
    if len(dir_idx):
        Hs = (combos[:, None, 0, None, None] * ds[i1][None, :, :, None] * dt[i1][None, :, None, :]
              + combos[:, None, 1, None, None] * ds[i2][None, :, :, None] * dt[i2][None, :, None, :])
        R0, _ = _kabsch_batch(Hs)  # (C, G, 3, 3)
        signs = _assign_signs(R0, ds, dt, g, is_dir)
    else:
        signs = np.ones((C, k))

    def correlation(sg: Array) -> Array:
        v = np.where(is_dir[None, :, None], ds[None] * sg[:, :, None], 0.0)
        H = (w * is_dir)[None, :, None, None] * v[:, :, :, None] * dt[None, :, None, :]
        H = H + (corr_w[:, None, None] * corr_s[:, :, None] * corr_t[:, None, :])[None]
        return _group_sum(H.reshape(C, k, 9), g, G).reshape(C, G, 3, 3)

    for _ in range(2):
        R, _S = _kabsch_batch(correlation(signs))
        signs = _assign_signs(R, ds, dt, g, is_dir)
    R, S = _kabsch_batch(correlation(signs))
    return _reference_tail(R, S, signs, g, w, ts, ds, dt, bs, bt, G, wsum_g, has_dir, i1, used_pos, inv,
                           kappa_max, line_anchor_weight, weak_ratio, upright_min)


def _reference_tail(R: Array, S: Array, signs: Array, g: NDArray[np.int64], w: Array, ts: NDArray,
                    ds: Array, dt: Array, bs: Array, bt: Array, G: int, wsum_g: Array,
                    has_dir: NDArray[np.bool_], i1: NDArray[np.int64], used_pos: NDArray[np.bool_],
                    inv: NDArray[np.int64], kappa_max: float, line_anchor_weight: float,
                    weak_ratio: float, upright_min: float) -> BatchRegistration:
    """The reference from the refined rotations on: translations, costs, the candidate chosen
    per group, conditioning and residuals. Inputs are group-sorted (``inv`` restores the input
    order); R (C, G, 3, 3), S (C, G, 3) and signs (C, k) are the candidates' Kabsch results.
    Shared by :func:`_register_batch_reference` and :func:`_solve_exactly`, so both compute the
    same numbers from the same rotations."""
    C, k = R.shape[0], len(g)
    is_dir = ts > 0
    is_line = ts == LandmarkType.LINE

    # Translation: normal equations sum M_i t = sum M_i r_i with M_i the row space of each type.
    eye = np.eye(3)
    ddT = dt[:, :, None] * dt[:, None, :]
    M_geo = np.where(
        (ts == LandmarkType.PLANE)[:, None, None], ddT,
        np.where(is_line[:, None, None], eye - ddT, eye),
    ) * w[:, None, None]
    # Weak prior: a pole's anchor (its support centroid) roughly corresponds along its axis.
    # Negligible where planes fix the translation; it fixes the height when only near-parallel
    # poles are matched. kappa is computed from the geometric constraints alone.
    M = M_geo + (line_anchor_weight * w * is_line)[:, None, None] * ddT
    AtA_geo = _group_sum(M_geo.reshape(1, k, 9), g, G).reshape(G, 3, 3)
    AtA = _group_sum(M.reshape(1, k, 9), g, G).reshape(G, 3, 3)
    r = bt[None] - np.einsum("cgij,cgj->cgi", R[:, g], np.broadcast_to(bs, (C, k, 3)))  # (C, k, 3)
    Mr_geo = np.einsum("kij,ckj->cki", M_geo, r)
    Atb_geo = _group_sum(Mr_geo, g, G)  # (C, G, 3)
    rMr = _group_sum(np.einsum("cki,cki->ck", r, Mr_geo)[:, :, None], g, G)[..., 0]
    lam_geo, Q = np.linalg.eigh(AtA_geo)  # ascending
    lam_max = np.maximum(lam_geo[:, 2], 1e-300)
    # Directions the geometry fixes come from it alone; weakly fixed ones (e.g. along parallel
    # poles) from the full system with the anchor prior.
    strong = lam_geo >= weak_ratio * lam_max[:, None]
    inv_lam = np.where(strong, 1.0 / np.where(lam_geo > 0, lam_geo, 1.0), 0.0)
    t = np.einsum("gik,gk,gjk,cgj->cgi", Q, inv_lam, Q, Atb_geo)
    if not strong.all():
        Atb = _group_sum(np.einsum("kij,ckj->cki", M, r), g, G)
        lam, Qf = np.linalg.eigh(AtA)
        lam_f_max = np.maximum(lam[:, 2], 1e-300)
        inv_f = np.where(lam > 1e-18 * lam_f_max[:, None], 1.0 / np.where(lam > 0, lam, 1.0), 0.0)
        t_full = np.einsum("gik,gk,gjk,cgj->cgi", Qf, inv_f, Qf, Atb)
        P_weak = np.einsum("gik,gk,gjk->gij", Q, (~strong).astype(float), Q)
        t = t + np.einsum("gij,cgj->cgi", P_weak, t_full)
    tres = rMr - 2 * np.einsum("cgi,cgi->cg", t, Atb_geo) + np.einsum("cgi,gij,cgj->cg", t, AtA_geo, t)
    cos = np.abs(np.einsum("ki,cki->ck", dt, np.einsum("ckij,kj->cki", R[:, g], ds)))
    rot_res = _group_sum(((w * is_dir)[None] * (1.0 - cos))[:, :, None], g, G)[..., 0]
    cost = rot_res + np.maximum(tres, 0.0) / (1.0 + wsum_g[None])
    key = cost + 1e-12 * np.arange(C)[:, None]
    if has_dir.any():  # parallel lines: a half-turn across them (upside down) only as a last resort
        j = i1
        up = used_pos & has_dir & (np.abs(ds[j, 2]) >= upright_min) & (np.abs(dt[j, 2]) >= upright_min)
        dots = np.einsum("gi,cgi->cg", dt[j], np.einsum("cgij,gj->cgi", R, ds[j]))
        flipped = up[None] & (dots * np.sign(ds[j, 2])[None] * np.sign(dt[j, 2])[None] < 0)
        flipped &= ~flipped.all(axis=0)[None]
        key = np.where(flipped, np.inf, key)
    best = np.argmin(key, axis=0)  # ties: first candidate
    gi = np.arange(G)
    R, S, t, cost = R[best, gi], S[best, gi], t[best, gi], cost[best, gi]
    signs = signs[best[g], np.arange(k)]

    tol = 1e-9
    S0 = np.maximum(S[:, 0], 1e-300)
    rot_rank = np.sum(S > tol * S0[:, None], axis=1) * (S[:, 0] > 0)
    k_rot = np.where(S[:, 1] > tol * S0, S[:, 0] / np.where(S[:, 1] > 0, S[:, 1], 1.0), np.inf)
    sv = np.sqrt(np.clip(lam_geo[:, ::-1], 0, None))  # singular values of the geometric rows
    sv0 = np.maximum(sv[:, 0], 1e-300)
    tr_rank = np.sum(sv > tol * sv0[:, None], axis=1) * (sv[:, 0] > 0)
    k_tr = np.where(sv[:, 2] > tol * sv0, sv[:, 0] / np.where(sv[:, 2] > 0, sv[:, 2], 1.0), np.inf)
    kappa = np.maximum(k_rot, k_tr)
    T = np.tile(np.eye(4), (G, 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = t

    Rk, tk = R[g], t[g]
    cosang = np.abs(np.einsum("ki,ki->k", dt, np.einsum("kij,kj->ki", Rk, ds)))
    ang = np.where(is_dir, np.degrees(np.arccos(np.clip(cosang, -1, 1))), 0.0)
    res = bt - (np.einsum("kij,kj->ki", Rk, bs) + tk)
    along = np.einsum("ij,ij->i", dt, res)
    off = np.where(
        ts == LandmarkType.PLANE, np.abs(along),
        np.where(is_line, np.linalg.norm(res - along[:, None] * dt, axis=1), np.linalg.norm(res, axis=1)),
    )
    return BatchRegistration(
        T_target_source=T, kappa=kappa, kappa_rotation=k_rot, kappa_translation=k_tr,
        degenerate=~np.isfinite(kappa) | (kappa > kappa_max),
        rotation_rank=rot_rank.astype(np.int64), translation_rank=tr_rank.astype(np.int64),
        cost=cost, used_line_positions=used_pos,
        angle_residuals_deg=ang[inv], offset_residuals=off[inv],
        signs=np.where(is_dir, signs, 1.0)[inv],
    )


def _assign_signs(R: Array, ds: Array, dt: Array, g: NDArray[np.int64], is_dir: NDArray[np.bool_]) -> Array:
    """Per candidate rotation (C, G, 3, 3): the sign of each source direction that matches it."""
    s = np.sign(np.einsum("ki,cki->ck", dt, np.einsum("ckij,kj->cki", R[:, g], ds)))
    s[s == 0] = 1.0
    return np.where(is_dir[None], s, 1.0)


def _add_centred(cs: Array, ct: Array, cw: Array, mask: NDArray[np.bool_], ps: Array, pt: Array,
                 w: Array, g: NDArray[np.int64], G: int) -> None:
    """Write weighted, per-group centred and unit-spread point pairs into the correlation rows."""
    wm = w * mask
    ws = np.bincount(g, weights=wm, minlength=G)
    ws_safe = np.where(ws > 0, ws, 1.0)
    ms = _group_sum((wm[:, None] * ps)[None], g, G)[0] / ws_safe[:, None]
    mt = _group_sum((wm[:, None] * pt)[None], g, G)[0] / ws_safe[:, None]
    qs, qt = ps - ms[g], pt - mt[g]
    n = np.bincount(g, weights=mask.astype(float), minlength=G)
    spread = np.sqrt(np.bincount(g, weights=mask * np.sum(qs**2, 1), minlength=G) / np.maximum(n, 1))
    scale = spread[g] + 1e-12
    cs[mask] = (qs / scale[:, None])[mask]
    ct[mask] = (qt / scale[:, None])[mask]
    cw[mask] = w[mask]


# ---------------------------------------------------------------------------------------------
# Numba path: one loop over groups, 3x3 Jacobi SVD / eigen-decompositions, no per-op overhead.
# Every decision that the reference takes on a knife edge (rank-deficient correlation, a sign
# dot near zero, an ambiguous seed pair, a cost tie between different solutions, a threshold
# met within rounding) marks the group *fragile*; fragile groups are re-solved by the reference,
# so results agree with it to rounding and arbitrary choices are the reference's own.

_COND_MIN = 1e-3  # (s2 + s3) / s1 below this: the Kabsch rotation is rounding-sensitive
_DOT_MIN = 1e-8  # |dt . R ds| below this: the sign of a direction is rounding-sensitive
_EIG_MIN = 1e-6  # smallest / largest eigenvalue of a translation system below this: fragile
FRAGILE_REASONS = {
    1: "empty group", 2: "parallel-spread threshold met within rounding",
    4: "seed pair ambiguous or all directions parallel", 8: "seed correlation is zero",
    16: "seed sign dot near zero", 32: "correlation rank-deficient (s2 + s3 < 1e-3 s1)",
    64: "sign dot near zero", 128: "weak-direction threshold met within rounding",
    256: "translation system near-singular", 512: "prior translation system near-singular",
    1024: "cost tie between different sign assignments", 2048: "rank threshold met within rounding",
    4096: "kappa at kappa_max within rounding",
}
#: Fragility that only says a group is ill-conditioned (a rank-deficient correlation, a
#: near-singular translation system): ``register_batch(..., reference_degenerate=False)`` keeps
#: the kernel's result for a degenerate group fragile for these reasons alone.
CONDITIONING_REASONS = 32 | 256 | 512


@nb.njit(cache=True)
def _order3(x: Array, descending: bool) -> tuple[int, int, int]:
    """Indices sorting three values (ties keep index order)."""
    i0, i1, i2 = 0, 1, 2
    sgn = -1.0 if descending else 1.0
    if sgn * x[i1] < sgn * x[i0]:
        i0, i1 = i1, i0
    if sgn * x[i2] < sgn * x[i1]:
        i1, i2 = i2, i1
        if sgn * x[i1] < sgn * x[i0]:
            i0, i1 = i1, i0
    return i0, i1, i2


@nb.njit(cache=True)
def _svd3(H: Array, R: Array, S: Array, u0: Array, v0: Array, wk: Array, sig: Array) -> None:
    """Kabsch rotation ``R`` (maps source to target), descending singular values ``S`` and the
    leading singular pair of ``H = U diag(S) V^T`` by one-sided Jacobi (H V = U S).
    ``wk`` (4, 3, 3) and ``sig`` (3,) are scratch."""
    A = wk[0]
    V = wk[1]
    U = wk[2]
    Vs = wk[3]
    for i in range(3):
        for j in range(3):
            A[i, j] = H[i, j]
            V[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(60):
        rotated = False
        for pq in range(3):
            p = 0 if pq < 2 else 1
            q = 1 if pq == 0 else 2
            alpha = A[0, p] * A[0, p] + A[1, p] * A[1, p] + A[2, p] * A[2, p]
            beta = A[0, q] * A[0, q] + A[1, q] * A[1, q] + A[2, q] * A[2, q]
            gamma = A[0, p] * A[0, q] + A[1, p] * A[1, q] + A[2, p] * A[2, q]
            if gamma == 0.0 or abs(gamma) <= 1e-15 * np.sqrt(alpha * beta):
                continue
            rotated = True
            zeta = (beta - alpha) / (2.0 * gamma)
            t = (1.0 if zeta >= 0 else -1.0) / (abs(zeta) + np.sqrt(1.0 + zeta * zeta))
            c = 1.0 / np.sqrt(1.0 + t * t)
            s = c * t
            for i in range(3):
                ap, aq = A[i, p], A[i, q]
                A[i, p] = c * ap - s * aq
                A[i, q] = s * ap + c * aq
                vp, vq = V[i, p], V[i, q]
                V[i, p] = c * vp - s * vq
                V[i, q] = s * vp + c * vq
        if not rotated:
            break
    for j in range(3):
        sig[j] = np.sqrt(A[0, j] * A[0, j] + A[1, j] * A[1, j] + A[2, j] * A[2, j])
    o0, o1, o2 = _order3(sig, True)
    for jj in range(3):
        j = o0 if jj == 0 else (o1 if jj == 1 else o2)
        S[jj] = sig[j]
        for i in range(3):
            Vs[i, jj] = V[i, j]
            U[i, jj] = A[i, j] / sig[j] if (jj < 2 and sig[j] > 0) else 0.0
    if S[0] > 0 and not S[1] > 0:  # rank 1: complete U with a unit vector across u0 (any
        # would do; the axis least along u0 keeps it well conditioned), so R stays a rotation
        k = 0
        for i in range(1, 3):
            if abs(U[i, 0]) < abs(U[k, 0]):
                k = i
        n = 0.0
        for i in range(3):
            e = 1.0 if i == k else 0.0
            U[i, 1] = e - U[k, 0] * U[i, 0]
            n += U[i, 1] * U[i, 1]
        n = np.sqrt(n)
        for i in range(3):
            U[i, 1] /= n
    elif not S[0] > 0:  # H = 0 (V the identity): the identity rotation
        for i in range(3):
            for j in range(2):
                U[i, j] = Vs[i, j]
    U[0, 2] = U[1, 0] * U[2, 1] - U[2, 0] * U[1, 1]
    U[1, 2] = U[2, 0] * U[0, 1] - U[0, 0] * U[2, 1]
    U[2, 2] = U[0, 0] * U[1, 1] - U[1, 0] * U[0, 1]
    d = (Vs[0, 0] * (Vs[1, 1] * Vs[2, 2] - Vs[2, 1] * Vs[1, 2])
         - Vs[0, 1] * (Vs[1, 0] * Vs[2, 2] - Vs[2, 0] * Vs[1, 2])
         + Vs[0, 2] * (Vs[1, 0] * Vs[2, 1] - Vs[2, 0] * Vs[1, 1]))
    d = 1.0 if d >= 0 else -1.0
    for a in range(3):
        for b in range(3):
            R[a, b] = Vs[a, 0] * U[b, 0] + Vs[a, 1] * U[b, 1] + d * Vs[a, 2] * U[b, 2]
    for i in range(3):
        u0[i] = U[i, 0]
        v0[i] = Vs[i, 0]


@nb.njit(cache=True)
def _eigh3(M: Array, lam: Array, Q: Array, wk: Array, dg: Array) -> None:
    """Ascending eigenvalues ``lam`` and eigenvectors (columns of ``Q``) of a symmetric 3x3 by
    cyclic Jacobi. ``wk`` (4, 3, 3) and ``dg`` (3,) are scratch."""
    a = wk[0]
    Qw = wk[1]
    scale = 0.0
    for i in range(3):
        for j in range(3):
            a[i, j] = M[i, j]
            Qw[i, j] = 1.0 if i == j else 0.0
            scale += M[i, j] * M[i, j]
    scale = np.sqrt(scale)
    for _sweep in range(60):
        rotated = False
        for pq in range(3):
            p = 0 if pq < 2 else 1
            q = 1 if pq == 0 else 2
            apq = a[p, q]
            if apq == 0.0 or abs(apq) <= 1e-18 * scale:
                continue
            rotated = True
            theta = (a[q, q] - a[p, p]) / (2.0 * apq)
            t = (1.0 if theta >= 0 else -1.0) / (abs(theta) + np.sqrt(1.0 + theta * theta))
            c = 1.0 / np.sqrt(1.0 + t * t)
            s = c * t
            for k in range(3):
                akp, akq = a[k, p], a[k, q]
                a[k, p] = c * akp - s * akq
                a[k, q] = s * akp + c * akq
            for k in range(3):
                apk, aqk = a[p, k], a[q, k]
                a[p, k] = c * apk - s * aqk
                a[q, k] = s * apk + c * aqk
            a[p, q] = 0.0
            a[q, p] = 0.0
            for k in range(3):
                qp, qq = Qw[k, p], Qw[k, q]
                Qw[k, p] = c * qp - s * qq
                Qw[k, q] = s * qp + c * qq
        if not rotated:
            break
    for i in range(3):
        dg[i] = a[i, i]
    o0, o1, o2 = _order3(dg, False)
    for jj in range(3):
        j = o0 if jj == 0 else (o1 if jj == 1 else o2)
        lam[jj] = dg[j]
        for i in range(3):
            Q[i, jj] = Qw[i, j]


@nb.njit(cache=True)
def _centred(lo: int, hi: int, mask: NDArray[np.bool_], w: Array, ps: Array, pt: Array, off: int,
             cs: Array, ct: Array, cw: Array) -> None:
    """As :func:`_add_centred` for one group (rows lo..hi; ``mask`` indexed from lo, ``ps``/``pt``
    from ``off``)."""
    ws = 0.0
    ms = np.zeros(3)
    mt = np.zeros(3)
    nm = 0
    for i in range(lo, hi):
        if mask[i - lo]:
            ws += w[i]
            nm += 1
            for a in range(3):
                ms[a] += w[i] * ps[i - off, a]
                mt[a] += w[i] * pt[i - off, a]
    if ws <= 0:
        ws = 1.0
    for a in range(3):
        ms[a] /= ws
        mt[a] /= ws
    ss = 0.0
    for i in range(lo, hi):
        if mask[i - lo]:
            ss += ((ps[i - off, 0] - ms[0]) ** 2 + (ps[i - off, 1] - ms[1]) ** 2) + (ps[i - off, 2] - ms[2]) ** 2
    scale = np.sqrt(ss / max(nm, 1)) + 1e-12
    for i in range(lo, hi):
        if mask[i - lo]:
            for a in range(3):
                cs[i - lo, a] = (ps[i - off, a] - ms[a]) / scale
                ct[i - lo, a] = (pt[i - off, a] - mt[a]) / scale
            cw[i - lo] = w[i]


@nb.njit(cache=True)
def _dot_r(R: Array, x: Array, y: Array) -> float:
    """y . (R x)."""
    return ((y[0] * (R[0, 0] * x[0] + R[0, 1] * x[1] + R[0, 2] * x[2])
             + y[1] * (R[1, 0] * x[0] + R[1, 1] * x[1] + R[1, 2] * x[2]))
            + y[2] * (R[2, 0] * x[0] + R[2, 1] * x[1] + R[2, 2] * x[2]))


@nb.njit(cache=True)
def _same_row(ds: Array, w: Array, i: int, j: int) -> bool:
    return w[i] == w[j] and ds[i, 0] == ds[j, 0] and ds[i, 1] == ds[j, 1] and ds[i, 2] == ds[j, 2]


@nb.njit(cache=True)
def _same_pair(ds: Array, w: Array, i: int, j: int, a: int, b: int) -> bool:
    """Pairs (i, j) and (a, b) of bitwise equal directions and weights: every implementation
    computes the same sine for both, so their tie is broken by index order alike."""
    return ((_same_row(ds, w, i, a) and _same_row(ds, w, j, b))
            or (_same_row(ds, w, i, b) and _same_row(ds, w, j, a)))


@nb.njit(cache=True)
def _sine(c: float, sqrt_ww: float) -> float:
    """Weighted sine of two unit directions from |cos|, as in :func:`_seed_pairs`."""
    return np.sqrt(min(max(1.0 - c * c, 0.0), 1.0)) * sqrt_ww


@nb.njit(cache=True)
def _norm_cross(x: Array, y: Array) -> float:
    c0 = x[1] * y[2] - x[2] * y[1]
    c1 = x[2] * y[0] - x[0] * y[2]
    c2 = x[0] * y[1] - x[1] * y[0]
    return np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)


@nb.njit(cache=True)
def _register_kernel(bounds: NDArray[np.int64], w: Array, ts: NDArray[np.int64], ds: Array, dt: Array,
                     bs: Array, bt: Array, parallel_spread: float, line_anchor_weight: float,
                     weak_ratio: float, upright_min: float, R_out: Array, t_out: Array, S_out: Array,
                     lam_out: Array,
                     cost_out: Array, used_pos: NDArray[np.bool_], signs_out: Array, ang_out: Array,
                     off_out: Array, fragile: NDArray[np.int64], seeds_out: NDArray[np.int64],
                     centred_out: NDArray[np.bool_]) -> None:
    """Per group (rows bounds[g]..bounds[g+1] of the group-sorted inputs): the reference's
    algorithm, writing the selected candidate's results and the group's fragility (bits of
    :data:`FRAGILE_REASONS`, 0 when the result does not hang on rounding); for
    :func:`_solve_exactly`, the seed pair (sorted rows, -1 if none) and whether centred points
    or line positions entered the correlation."""
    G = len(bounds) - 1
    combos = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]])
    H = np.empty((3, 3))
    Rc = np.empty((4, 3, 3))
    Sc = np.empty((4, 3))
    tc = np.empty((4, 3))
    costc = np.empty(4)
    flipc = np.empty(4, np.bool_)
    scalec = np.empty(4)
    u0 = np.empty(3)
    v0 = np.empty(3)
    lam = np.empty(3)
    Q = np.empty((3, 3))
    lamf = np.empty(3)
    Qf = np.empty((3, 3))
    AtA_geo = np.empty((3, 3))
    AtA = np.empty((3, 3))
    wk = np.empty((4, 3, 3))
    sc3 = np.empty(3)
    inv_lam = np.empty(3)
    inv_f = np.empty(3)
    Atb_geo = np.empty(3)
    Atb = np.empty(3)
    r = np.empty(3)
    t = np.empty(3)
    tf = np.empty(3)
    res = np.empty(3)
    n_max = 0
    for gi in range(G):
        n_max = max(n_max, bounds[gi + 1] - bounds[gi])
    cs = np.empty((n_max, 3))
    ct = np.empty((n_max, 3))
    cw = np.empty(n_max)
    mask = np.empty(n_max, np.bool_)
    ps = np.empty((n_max, 3))
    pt = np.empty((n_max, 3))
    signs = np.empty((4, n_max))
    prev = np.empty((4, n_max))
    dup = np.empty(4, np.int64)
    for gi in range(G):
        lo = bounds[gi]
        hi = bounds[gi + 1]
        n = hi - lo
        if n == 0:
            fragile[gi] = 1
            continue
        frag = 0
        n_pt = 0
        n_line = 0
        n_dir = 0
        wsum = 0.0
        for i in range(lo, hi):
            wsum += w[i]
            if ts[i] == 0:
                n_pt += 1
            else:
                n_dir += 1
                if ts[i] == 1:
                    n_line += 1
        cs[:n] = 0.0
        ct[:n] = 0.0
        cw[:n] = 0.0
        if n_pt >= 3:
            for i in range(lo, hi):
                mask[i - lo] = ts[i] == 0
            _centred(lo, hi, mask, w, bs, bt, 0, cs, ct, cw)
        # parallel directions: positions of the lines across them
        for a in range(3):
            for b in range(3):
                H[a, b] = 0.0
        for i in range(lo, hi):
            if ts[i] > 0:
                for a in range(3):
                    for b in range(3):
                        H[a, b] += w[i] * ds[i, a] * ds[i, b]
        _eigh3(H, lam, Q, wk, sc3)
        thr = parallel_spread * max(lam[2], 1e-300)
        parallel = lam[1] <= thr
        used = False
        if n_line >= 2:
            if abs(lam[1] - thr) <= 1e-12 * lam[2]:
                frag |= 2
            if parallel:
                used = True
                ps[:n] = 0.0
                pt[:n] = 0.0
                for i in range(lo, hi):
                    mask[i - lo] = ts[i] == 1
                    if ts[i] == 1:
                        es = (bs[i, 0] * ds[i, 0] + bs[i, 1] * ds[i, 1]) + bs[i, 2] * ds[i, 2]
                        et = (bt[i, 0] * dt[i, 0] + bt[i, 1] * dt[i, 1]) + bt[i, 2] * dt[i, 2]
                        for a in range(3):
                            ps[i - lo, a] = bs[i, a] - es * ds[i, a]
                            pt[i - lo, a] = bt[i, a] - et * dt[i, a]
                    else:
                        mask[i - lo] = False
                _centred(lo, hi, mask, w, ps, pt, lo, cs, ct, cw)
        used_pos[gi] = used
        centred_out[gi] = used or n_pt >= 3
        # seed pair: the two most independent weighted directions
        i1 = -1
        i2 = -1
        if n_dir == 1:
            for i in range(lo, hi):
                if ts[i] > 0:
                    i1 = i
                    i2 = i
        elif n_dir > 1:
            best = -1.0
            for i in range(lo, hi):
                if ts[i] == 0:
                    continue
                for j in range(lo, hi):
                    if ts[j] == 0:
                        continue
                    c = abs((ds[i, 0] * ds[j, 0] + ds[i, 1] * ds[j, 1]) + ds[i, 2] * ds[j, 2])
                    sn = _sine(c, np.sqrt(w[i] * w[j]))
                    if sn > best:
                        best = sn
                        i1 = i
                        i2 = j
            # Ties decide the seeds by index order: safe only when the tied sines come out the
            # same under any rounding of the cosines (e.g. 1.0 for near-perpendicular pairs) or
            # come from the same two directions (a landmark associated twice).
            cb = abs((ds[i1, 0] * ds[i2, 0] + ds[i1, 1] * ds[i2, 1]) + ds[i1, 2] * ds[i2, 2])
            wb = np.sqrt(w[i1] * w[i2])
            robust_b = _sine(cb + 1e-15, wb) == best and _sine(max(cb - 1e-15, 0.0), wb) == best
            ambiguous = best < 1e-6 * wb
            # rounding of a cosine (< 1e-15 absolute) moves its sine by < 1e-15 / sine
            tie = 8e-15 / max(best / wb, 1e-300) + 8e-15
            for i in range(lo, hi):
                if ts[i] == 0:
                    continue
                for j in range(i, hi):
                    if ts[j] == 0 or (i == min(i1, i2) and j == max(i1, i2)):
                        continue
                    c = abs((ds[i, 0] * ds[j, 0] + ds[i, 1] * ds[j, 1]) + ds[i, 2] * ds[j, 2])
                    wij = np.sqrt(w[i] * w[j])
                    sn = _sine(c, wij)
                    if best - sn <= tie * max(wb, wij) and not (
                            sn == best and (_same_pair(ds, w, i, j, i1, i2) or (
                                robust_b and _sine(c + 1e-15, wij) == sn
                                and _sine(max(c - 1e-15, 0.0), wij) == sn))):
                        ambiguous = True
            if ambiguous:
                frag |= 4
        seeds_out[gi, 0] = i1
        seeds_out[gi, 1] = i2
        signs[:, :n] = 1.0
        if i1 >= 0:
            for c in range(4):
                for a in range(3):
                    for b in range(3):
                        H[a, b] = (combos[c, 0] * ds[i1, a] * dt[i1, b]
                                   + combos[c, 1] * ds[i2, a] * dt[i2, b])
                _svd3(H, Rc[c], Sc[c], u0, v0, wk, sc3)
                if Sc[c, 0] == 0:
                    frag |= 8
                well = Sc[c, 1] + Sc[c, 2] >= _COND_MIN * Sc[c, 0]
                for i in range(lo, hi):
                    if ts[i] == 0:
                        continue
                    dot = _dot_r(Rc[c], ds[i], dt[i])
                    if well:
                        if abs(dot) <= _DOT_MIN:
                            frag |= 16
                    else:
                        # a rank-deficient seed fixes only R u0 = v0: any rotation about v0 is as good, and
                        # dt . R ds ranges over center +- |ds x u0| |dt x v0|. The sign is the kernel's own
                        # arbitrary choice unless that whole range lies on one side of zero (seed 38 of
                        # tests/registration/test_batch_equivalence.py: dot 0.67 here, -0.62 by LAPACK).
                        center = (ds[i, 0] * u0[0] + ds[i, 1] * u0[1] + ds[i, 2] * u0[2]) * (
                            dt[i, 0] * v0[0] + dt[i, 1] * v0[1] + dt[i, 2] * v0[2])
                        if abs(center) <= _norm_cross(ds[i], u0) * _norm_cross(dt[i], v0) + _DOT_MIN:
                            frag |= 16
                    signs[c, i - lo] = -1.0 if dot < 0 else 1.0
        # refine: correlation of signed directions and centred positions, Kabsch, re-sign
        # (candidates whose signs coincide share the result: copied, not recomputed)
        for it in range(3):
            prev[:, :n] = signs[:, :n]
            for c in range(4):
                dup[c] = -1
                for c2 in range(c):
                    same = True
                    for i in range(n):
                        if prev[c2, i] != prev[c, i]:
                            same = False
                            break
                    if same:
                        dup[c] = c2
                        break
                if dup[c] >= 0:
                    Rc[c] = Rc[dup[c]]
                    Sc[c] = Sc[dup[c]]
                    signs[c, :n] = signs[dup[c], :n]
                    continue
                for a in range(3):
                    for b in range(3):
                        H[a, b] = 0.0
                for i in range(lo, hi):
                    wd = w[i] if ts[i] > 0 else 0.0
                    sg = signs[c, i - lo]
                    for a in range(3):
                        va = ds[i, a] * sg if ts[i] > 0 else 0.0
                        for b in range(3):
                            H[a, b] += wd * va * dt[i, b] + cw[i - lo] * cs[i - lo, a] * ct[i - lo, b]
                _svd3(H, Rc[c], Sc[c], u0, v0, wk, sc3)
                if not (Sc[c, 1] + Sc[c, 2] >= _COND_MIN * Sc[c, 0]) or Sc[c, 0] == 0:
                    frag |= 32
                if it < 2:
                    for i in range(lo, hi):
                        if ts[i] == 0:
                            continue
                        dot = _dot_r(Rc[c], ds[i], dt[i])
                        if abs(dot) <= _DOT_MIN:
                            frag |= 64
                        signs[c, i - lo] = -1.0 if dot < 0 else 1.0
        # translation: normal equations of the geometric rows (+ weak along-axis anchor prior)
        for a in range(3):
            for b in range(3):
                AtA_geo[a, b] = 0.0
                AtA[a, b] = 0.0
        for i in range(lo, hi):
            for a in range(3):
                for b in range(3):
                    ddt = dt[i, a] * dt[i, b]
                    if ts[i] == 2:
                        m = ddt * w[i]
                    elif ts[i] == 1:
                        m = ((1.0 if a == b else 0.0) - ddt) * w[i]
                    else:
                        m = (1.0 if a == b else 0.0) * w[i]
                    AtA_geo[a, b] += m
                    AtA[a, b] += m + (line_anchor_weight * w[i] if ts[i] == 1 else 0.0) * ddt
        _eigh3(AtA_geo, lam, Q, wk, sc3)
        lam_max = max(lam[2], 1e-300)
        all_strong = True
        inv_lam[:] = 0.0
        for j in range(3):
            if abs(lam[j] - weak_ratio * lam_max) <= 1e-12 * lam_max:
                frag |= 128
            if lam[j] >= weak_ratio * lam_max:
                inv_lam[j] = 1.0 / lam[j] if lam[j] > 0 else 1.0
            else:
                all_strong = False
        if lam[0] < _EIG_MIN * lam_max:
            frag |= 256
        for j in range(3):
            lam_out[gi, j] = lam[j]
        inv_f[:] = 0.0
        if not all_strong:
            _eigh3(AtA, lamf, Qf, wk, sc3)
            lamf_max = max(lamf[2], 1e-300)
            if lamf[0] < _EIG_MIN * lamf_max:
                frag |= 512
            for j in range(3):
                if lamf[j] > 1e-18 * lamf_max:
                    inv_f[j] = 1.0 / lamf[j] if lamf[j] > 0 else 1.0
        for c in range(4):
            if dup[c] >= 0:
                costc[c] = costc[dup[c]]
                scalec[c] = scalec[dup[c]]
                tc[c] = tc[dup[c]]
                continue
            R = Rc[c]
            Atb_geo[:] = 0.0
            Atb[:] = 0.0
            rMr = 0.0
            rot_res = 0.0
            for i in range(lo, hi):
                for a in range(3):
                    r[a] = bt[i, a] - ((R[a, 0] * bs[i, 0] + R[a, 1] * bs[i, 1]) + R[a, 2] * bs[i, 2])
                for a in range(3):
                    mr = 0.0
                    mrf = 0.0
                    for b in range(3):
                        ddt = dt[i, a] * dt[i, b]
                        if ts[i] == 2:
                            m = ddt * w[i]
                        elif ts[i] == 1:
                            m = ((1.0 if a == b else 0.0) - ddt) * w[i]
                        else:
                            m = (1.0 if a == b else 0.0) * w[i]
                        mr += m * r[b]
                        mrf += (m + (line_anchor_weight * w[i] if ts[i] == 1 else 0.0) * ddt) * r[b]
                    Atb_geo[a] += mr
                    Atb[a] += mrf
                    rMr += r[a] * mr
                if ts[i] > 0:
                    rot_res += w[i] * (1.0 - abs(_dot_r(R, ds[i], dt[i])))
            # t = Q diag(inv_lam) Q^T Atb_geo + P_weak Qf diag(inv_f) Qf^T Atb
            t[:] = 0.0
            for j in range(3):
                proj = (Q[0, j] * Atb_geo[0] + Q[1, j] * Atb_geo[1]) + Q[2, j] * Atb_geo[2]
                for a in range(3):
                    t[a] += Q[a, j] * inv_lam[j] * proj
            if not all_strong:
                tf[:] = 0.0
                for j in range(3):
                    proj = (Qf[0, j] * Atb[0] + Qf[1, j] * Atb[1]) + Qf[2, j] * Atb[2]
                    for a in range(3):
                        tf[a] += Qf[a, j] * inv_f[j] * proj
                for j in range(3):
                    if lam[j] >= weak_ratio * lam_max:
                        continue
                    proj = (Q[0, j] * tf[0] + Q[1, j] * tf[1]) + Q[2, j] * tf[2]
                    for a in range(3):
                        t[a] += Q[a, j] * proj
            tAt = 0.0
            for a in range(3):
                tAt += t[a] * ((AtA_geo[a, 0] * t[0] + AtA_geo[a, 1] * t[1]) + AtA_geo[a, 2] * t[2])
            tres = rMr - 2.0 * ((t[0] * Atb_geo[0] + t[1] * Atb_geo[1]) + t[2] * Atb_geo[2]) + tAt
            costc[c] = rot_res + max(tres, 0.0) / (1.0 + wsum)
            scalec[c] = (abs(rMr) + abs(tAt)) / (1.0 + wsum)
            for a in range(3):
                tc[c, a] = t[a]
        # parallel lines: a half-turn across them (upside down) only when every candidate is one
        n_flip = 0
        for c in range(4):
            flipc[c] = False
            if used and i1 >= 0 and abs(ds[i1, 2]) >= upright_min and abs(dt[i1, 2]) >= upright_min:
                up = _dot_r(Rc[c], ds[i1], dt[i1]) * np.sign(ds[i1, 2]) * np.sign(dt[i1, 2])
                flipc[c] = up < 0
                if flipc[c]:
                    n_flip += 1
        if n_flip == 4:
            flipc[:] = False
        bi = -1
        for c in range(4):
            if flipc[c]:
                continue
            if bi < 0 or costc[c] + 1e-12 * c < costc[bi] + 1e-12 * bi:
                bi = c
        for c in range(4):
            if c == bi or flipc[c]:
                continue
            tol = 1e-10 + 1e-12 * (scalec[c] + scalec[bi])
            if abs(costc[c] + 1e-12 * c - costc[bi] - 1e-12 * bi) <= tol:
                for i in range(n):
                    if signs[c, i] != signs[bi, i]:
                        frag |= 1024
        R = Rc[bi]
        if abs(Sc[bi, 2] - 1e-9 * Sc[bi, 0]) <= 1e-13 * Sc[bi, 0]:
            frag |= 2048
        for a in range(3):
            t_out[gi, a] = tc[bi, a]
            S_out[gi, a] = Sc[bi, a]
            for b in range(3):
                R_out[gi, a, b] = R[a, b]
        cost_out[gi] = costc[bi]
        for i in range(lo, hi):
            if ts[i] > 0:
                signs_out[i] = signs[bi, i - lo]
                cosang = min(abs(_dot_r(R, ds[i], dt[i])), 1.0)
                ang_out[i] = np.degrees(np.arccos(cosang))
            else:
                signs_out[i] = 1.0
                ang_out[i] = 0.0
            for a in range(3):
                res[a] = bt[i, a] - (((R[a, 0] * bs[i, 0] + R[a, 1] * bs[i, 1]) + R[a, 2] * bs[i, 2])
                                     + tc[bi, a])
            along = (dt[i, 0] * res[0] + dt[i, 1] * res[1]) + dt[i, 2] * res[2]
            if ts[i] == 2:
                off_out[i] = abs(along)
            elif ts[i] == 1:
                e0 = res[0] - along * dt[i, 0]
                e1 = res[1] - along * dt[i, 1]
                e2 = res[2] - along * dt[i, 2]
                off_out[i] = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
            else:
                off_out[i] = np.sqrt(res[0] * res[0] + res[1] * res[1] + res[2] * res[2])
        fragile[gi] = frag


@nb.njit(cache=True)
def _scan_batch(A: NDArray[np.int64], g: NDArray[np.int64], w: Array, ts: NDArray[np.int8], tt: NDArray[np.int8],
                check_w: bool) -> tuple[int, int, bool, bool, bool]:
    """The input checks of :func:`_register_batch_reference` in one pass: (min group, max group,
    an association index out of range, a pair of different types (among in-range pairs), a
    weight not finite or negative)."""
    k = A.shape[0]
    g_min = g[0]
    g_max = g[0]
    a_bad = False
    type_bad = False
    w_bad = False
    for i in range(k):
        if g[i] < g_min:
            g_min = g[i]
        if g[i] > g_max:
            g_max = g[i]
        a, b = A[i, 0], A[i, 1]
        if a < 0 or b < 0 or a >= ts.shape[0] or b >= tt.shape[0]:
            a_bad = True
        elif ts[a] != tt[b]:
            type_bad = True
        if check_w and not (np.isfinite(w[i]) and w[i] >= 0):
            w_bad = True
    return g_min, g_max, a_bad, type_bad, w_bad


@nb.njit(cache=True)
def _sort_groups(g: NDArray[np.int64], w: Array, G: int) -> tuple[NDArray[np.int64], NDArray[np.int64], bool]:
    """``np.argsort(g, kind="stable")`` (a counting sort: the same permutation), the group bounds
    of the sorted rows, and whether a non-empty group has no positive weight (the sums in input
    order, as ``np.bincount``)."""
    k = g.shape[0]
    count = np.zeros(G, np.int64)
    wsum = np.zeros(G)
    for i in range(k):
        count[g[i]] += 1
        wsum[g[i]] += w[i]
    bounds = np.empty(G + 1, np.int64)
    bounds[0] = 0
    for j in range(G):
        bounds[j + 1] = bounds[j] + count[j]
    pos = bounds[:-1].copy()
    order = np.empty(k, np.int64)
    for i in range(k):
        order[pos[g[i]]] = i
        pos[g[i]] += 1
    bad = False
    for j in range(G):
        if count[j] > 0 and wsum[j] <= 0:
            bad = True
    return order, bounds, bad


@nb.njit(cache=True)
def _gather_batch(order: NDArray[np.int64], A: NDArray[np.int64], w: Array, ts: NDArray[np.int8], dir_s: Array,
                  dir_t: Array, anc_s: Array, anc_t: Array) -> tuple:
    """The kernel's group-sorted inputs: weights, types, directions and anchors of each pair."""
    k = order.shape[0]
    ws = np.empty(k)
    tso = np.empty(k, np.int64)
    ds = np.empty((k, 3))
    dt = np.empty((k, 3))
    bs = np.empty((k, 3))
    bt = np.empty((k, 3))
    for j in range(k):
        i = order[j]
        a, b = A[i, 0], A[i, 1]
        ws[j] = w[i]
        tso[j] = ts[a]
        for c in range(3):
            ds[j, c] = dir_s[a, c]
            dt[j, c] = dir_t[b, c]
            bs[j, c] = anc_s[a, c]
            bt[j, c] = anc_t[b, c]
    return ws, tso, ds, dt, bs, bt


@nb.njit(cache=True)
def _nan_max(a: float, b: float) -> float:
    """``np.maximum`` of two floats (NaN if either is NaN)."""
    if a != a or b != b:
        return np.nan
    return a if a >= b else b


@nb.njit(cache=True)
def _finish_batch(R: Array, t: Array, S: Array, lam: Array, kappa_max: float, reasons: NDArray[np.int64]) -> tuple:
    """Transforms, condition numbers, ranks and degeneracy from the kernel's outputs: the
    reference's elementwise formulas (the same IEEE operations on the same values), per group;
    marks groups whose kappa meets ``kappa_max`` within rounding in ``reasons`` (4096)."""
    G = R.shape[0]
    tol = 1e-9
    T = np.zeros((G, 4, 4))
    kappa = np.empty(G)
    k_rot = np.empty(G)
    k_tr = np.empty(G)
    rot_rank = np.empty(G, np.int64)
    tr_rank = np.empty(G, np.int64)
    degenerate = np.empty(G, np.bool_)
    sv = np.empty(3)
    for gi in range(G):
        s0 = _nan_max(S[gi, 0], 1e-300)
        n = 0
        for j in range(3):
            if S[gi, j] > tol * s0:
                n += 1
        rot_rank[gi] = n if S[gi, 0] > 0 else 0
        s1 = S[gi, 1]
        k_rot[gi] = S[gi, 0] / (s1 if s1 > 0 else 1.0) if s1 > tol * s0 else np.inf
        for j in range(3):
            x = lam[gi, 2 - j]
            sv[j] = np.sqrt(0.0 if x < 0 else x)
        v0 = _nan_max(sv[0], 1e-300)
        n = 0
        for j in range(3):
            if sv[j] > tol * v0:
                n += 1
        tr_rank[gi] = n if sv[0] > 0 else 0
        k_tr[gi] = sv[0] / (sv[2] if sv[2] > 0 else 1.0) if sv[2] > tol * v0 else np.inf
        kp = _nan_max(k_rot[gi], k_tr[gi])
        kappa[gi] = kp
        if abs(kp - kappa_max) <= 1e-8 * abs(kappa_max):
            reasons[gi] |= 4096
        degenerate[gi] = not np.isfinite(kp) or kp > kappa_max
        for a in range(3):
            for b in range(3):
                T[gi, a, b] = R[gi, a, b]
            T[gi, a, 3] = t[gi, a]
        T[gi, 3, 3] = 1.0
    return T, kappa, k_rot, k_tr, rot_rank, tr_rank, degenerate


@nb.njit(cache=True)
def _unsort(x: Array, order: NDArray[np.int64]) -> Array:
    """Rows of group-sorted ``x`` back in input order (``x[inv]`` with ``inv[order] = arange``)."""
    out = np.empty_like(x)
    for j in range(order.shape[0]):
        out[order[j]] = x[j]
    return out


def register_batch(
    source: LandmarkSet,
    target: LandmarkSet,
    associations: ArrayLike,
    groups: ArrayLike | None = None,
    weights: ArrayLike | None = None,
    kappa_max: float = 1e3,
    n_groups: int | None = None,
    parallel_spread: float = 0.03,
    line_anchor_weight: float = 0.01,
    weak_ratio: float = 1e-2,
    upright_min: float = UPRIGHT_MIN,
    reference_degenerate: bool = True,
) -> BatchRegistration:
    """Register many association groups at once (one compiled loop over groups).

    Each group is one hypothesis. Directions and normals have no sign: each group tries the
    four sign combinations of its two most independent directions, re-assigns every sign twice
    from the refined rotation and keeps the candidate with the smallest cost. When a group's
    directions are (nearly) parallel -- their second principal spread below ``parallel_spread``
    of the first, e.g. vertical poles only -- the rotation about them is fixed by the lines'
    centred positions across the common direction, which the directions alone cannot do.
    ``line_anchor_weight`` weights the along-axis agreement of line anchors in the translation
    (a weak prior that fixes the height of pole-only matches; 0 disables it). It acts only on
    translation directions whose geometric eigenvalue is below ``weak_ratio`` of the largest.
    Parallel lines within 60 deg of z keep up up (``upright_min``, :data:`UPRIGHT_MIN`; above 1
    disables it): their half-turn twin is chosen only when no other candidate exists.

    Groups whose result hangs on rounding (rank-deficient correlations, near-zero sign dots,
    ties, thresholds met within rounding, empty groups) are solved by the numpy reference, so
    the arbitrary choices there are the same as in that (LAPACK) implementation.

    ``reference_degenerate=False`` keeps the kernel's own result for a fragile group that is
    degenerate at ``kappa_max`` and fragile only because it is ill-conditioned
    (:data:`CONDITIONING_REASONS`): a rotation the directions leave free (parallel walls, one
    pole) or a translation they leave free (walls only: the height). What such a group gives
    along its free axes is an arbitrary choice in any implementation (LAPACK's is no better than
    the kernel's), and a degenerate hypothesis can never be a valid answer, only a rival.
    Verification registers ~90 hypotheses a match and takes this (the reference costs ~1.5 ms a
    call); the default keeps every result equal to the reference's.
    """
    return _register_batch_numba(source, target, associations, groups, weights, kappa_max, n_groups,
                                 parallel_spread, line_anchor_weight, weak_ratio, upright_min,
                                 reference_degenerate)[0]


def _register_batch_numba(
    source: LandmarkSet, target: LandmarkSet, associations: ArrayLike, groups: ArrayLike | None,
    weights: ArrayLike | None, kappa_max: float, n_groups: int | None, parallel_spread: float,
    line_anchor_weight: float, weak_ratio: float, upright_min: float = UPRIGHT_MIN,
    reference_degenerate: bool = True,
) -> tuple[BatchRegistration, NDArray[np.int64]]:
    """:func:`register_batch` plus each group's fragility bits (:data:`FRAGILE_REASONS`)."""
    A = np.ascontiguousarray(np.asarray(associations, dtype=np.int64).reshape(-1, 2))
    k = len(A)
    g = np.zeros(k, np.int64) if groups is None else np.ascontiguousarray(np.asarray(groups, dtype=np.int64).reshape(-1))
    if g.shape != (k,):
        raise InvalidInputError(f"groups must have one entry per association ({k}), got {g.shape}")
    if k == 0:
        raise DegenerateGeometryError("no associations to register")
    w = np.ones(k) if weights is None else np.ascontiguousarray(np.asarray(weights, dtype=float).reshape(-1))
    # every array the kernels read goes in read-only: one compiled signature, whether it is a
    # caller's fresh array or a cached one (kernel_input)
    A, g, w = kernel_input(A, np.int64), kernel_input(g, np.int64), kernel_input(w, np.float64)
    ts_s, tt_s = kernel_input(source.types, np.int8), kernel_input(target.types, np.int8)
    # the checks of the reference, in its order, from one compiled pass over the inputs
    w_shape_ok = w.shape == (k,)
    g_min, g_max, a_bad, type_bad, w_bad = _scan_batch(A, g, w if w_shape_ok else kernel_input(np.ones(k), np.float64),
                                                       ts_s, tt_s,
                                                       weights is not None and w_shape_ok)
    if g_min < 0:
        raise InvalidInputError("group indices must be non-negative")
    G = int(g_max) + 1 if n_groups is None else int(n_groups)
    if g_max >= G:
        raise InvalidInputError("group index out of range")
    if a_bad:
        raise InvalidInputError("association index out of range")
    if type_bad:
        raise InvalidInputError("associations must pair landmarks of the same type")
    if not w_shape_ok or w_bad:
        raise InvalidInputError("weights must be finite, non-negative, one per association")
    order, bounds, empty_weight = _sort_groups(g, w, G)
    if empty_weight:
        raise InvalidInputError("every group needs a positive weight")
    ws, tso, ds, dt, bs, bt = _gather_batch(order, A, w, ts_s, _directions_of(source), _directions_of(target),
                                            kernel_input(source.anchors, np.float64),
                                            kernel_input(target.anchors, np.float64))
    R = np.empty((G, 3, 3))
    t = np.empty((G, 3))
    S = np.zeros((G, 3))
    lam = np.zeros((G, 3))
    cost = np.zeros(G)
    used_pos = np.zeros(G, np.bool_)
    signs = np.empty(k)
    ang = np.empty(k)
    off = np.empty(k)
    reasons = np.zeros(G, np.int64)
    seeds = np.full((G, 2), -1, np.int64)
    centred = np.zeros(G, np.bool_)
    _register_kernel(
        bounds, ws, tso, ds, dt, bs, bt,
        float(parallel_spread), float(line_anchor_weight), float(weak_ratio), float(upright_min),
        R, t, S, lam, cost, used_pos, signs, ang, off, reasons, seeds, centred,
    )
    T, kappa, k_rot, k_tr, rot_rank, tr_rank, degenerate = _finish_batch(R, t, S, lam, float(kappa_max), reasons)
    fragile = reasons != 0
    if not reference_degenerate:  # see register_batch
        fragile &= ~(((reasons & ~CONDITIONING_REASONS) == 0) & (kappa > kappa_max))
    out = BatchRegistration(
        T_target_source=T, kappa=kappa, kappa_rotation=k_rot, kappa_translation=k_tr,
        degenerate=degenerate, rotation_rank=rot_rank, translation_rank=tr_rank,
        cost=cost, used_line_positions=used_pos,
        angle_residuals_deg=_unsort(ang, order), offset_residuals=_unsort(off, order),
        signs=_unsort(signs, order),
    )
    frag_idx = np.flatnonzero(fragile)
    if len(frag_idx) == 1 and not reasons[frag_idx[0]] & 7 and not centred[frag_idx[0]]:
        # one fragile group whose parallel test and seed pair the kernel shares with the
        # reference: the reference's own arithmetic from there on, without its numpy overheads
        gi = int(frag_idx[0])
        lo, hi = int(bounds[gi]), int(bounds[gi + 1])
        sub = _solve_exactly(ws[lo:hi], tso[lo:hi], ds[lo:hi], dt[lo:hi], bs[lo:hi], bt[lo:hi],
                             int(seeds[gi, 0]) - lo, int(seeds[gi, 1]) - lo, kappa_max,
                             line_anchor_weight, weak_ratio, upright_min)
        if sub is not None:
            _write_group(out, sub, gi, order[lo:hi])
            fragile[gi] = False
    if fragile.any():
        _solve_by_reference(out, source, target, A, g, w, G, fragile, kappa_max,
                            parallel_spread, line_anchor_weight, weak_ratio, upright_min)
    return out, reasons


#: |dt . R ds| at or below this: :func:`_solve_exactly` leaves the group to the reference (the
#: sign of a dot product of unit vectors computed in another order is certain above ~1e-15).
_EXACT_DOT_MIN = 1e-9


def _solve_exactly(w: Array, ts: NDArray[np.int64], ds: Array, dt: Array, bs: Array, bt: Array,
                   i1: int, i2: int, kappa_max: float, line_anchor_weight: float, weak_ratio: float,
                   upright_min: float) -> BatchRegistration | None:
    """What :func:`_register_batch_reference` returns for this one group (rows group-sorted, as
    the reference sorts them), bit for bit, at a fraction of its numpy calls: for a group
    without centred points or line positions whose seed pair (``i1``, ``i2``; negative: no
    directions) the kernel found robustly. The rank-deficient Kabsch steps whose arbitrary
    choices only LAPACK reproduces go through the reference's own :func:`_kabsch_batch` on
    the same (4, 1, 3, 3) correlations (summed in the reference's order by
    :func:`_correlation_exact`), the rest through :func:`_reference_tail`. None when a sign
    hangs on rounding (then the reference decides it)."""
    k = len(w)
    g = np.zeros(k, np.int64)
    is_dir = ts > 0
    has_dir = np.array([i1 >= 0])
    i1a = np.array([max(i1, 0)], np.int64)
    i2a = np.array([max(i2, 0)], np.int64)
    combos = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]])
    if has_dir[0]:
        Hs = (combos[:, None, 0, None, None] * ds[i1a][None, :, :, None] * dt[i1a][None, :, None, :]
              + combos[:, None, 1, None, None] * ds[i2a][None, :, :, None] * dt[i2a][None, :, None, :])
        signs, ok = _signs_exact(_kabsch_batch(Hs)[0], ds, dt, is_dir, _EXACT_DOT_MIN)
        if not ok:
            return None
    else:
        signs = np.ones((4, k))
    for _ in range(2):
        R, _S = _kabsch_batch(_correlation_exact(signs, w, is_dir, ds, dt))
        signs, ok = _signs_exact(R, ds, dt, is_dir, _EXACT_DOT_MIN)
        if not ok:
            return None
    R, S = _kabsch_batch(_correlation_exact(signs, w, is_dir, ds, dt))
    wsum_g = np.bincount(g, weights=w, minlength=1)
    return _reference_tail(R, S, signs, g, w, ts, ds, dt, bs, bt, 1, wsum_g, has_dir, i1a,
                           np.zeros(1, np.bool_), np.arange(k), kappa_max, line_anchor_weight,
                           weak_ratio, upright_min)


@nb.njit(cache=True)
def _correlation_exact(signs: Array, w: Array, is_dir: NDArray[np.bool_], ds: Array, dt: Array) -> Array:
    """(C, 1, 3, 3) correlations of one group without centred rows, as the reference's
    ``correlation`` computes them: each term ``((w is_dir) v) dt + (0 0) 0`` (its zero centred
    term included: it turns -0.0 into 0.0), summed in row order from 0.0 like ``np.bincount``."""
    C, k = signs.shape
    H = np.zeros((C, 1, 3, 3))
    zero = 0.0
    for c in range(C):
        for i in range(k):
            wd = w[i] * (1.0 if is_dir[i] else 0.0)
            for a in range(3):
                v = ds[i, a] * signs[c, i] if is_dir[i] else 0.0
                for b in range(3):
                    H[c, 0, a, b] += (wd * v) * dt[i, b] + (zero * zero) * zero
    return H


@nb.njit(cache=True)
def _signs_exact(R: Array, ds: Array, dt: Array, is_dir: NDArray[np.bool_], dot_min: float) -> tuple:
    """The reference's ``_assign_signs`` for one group (R (C, 1, 3, 3)), and False when a dot
    is within ``dot_min`` of zero (where another summation order could flip the sign)."""
    C, k = R.shape[0], ds.shape[0]
    s = np.ones((C, k))
    ok = True
    for c in range(C):
        for i in range(k):
            if not is_dir[i]:
                continue
            d = 0.0
            for a in range(3):
                d += dt[i, a] * ((R[c, 0, a, 0] * ds[i, 0] + R[c, 0, a, 1] * ds[i, 1]) + R[c, 0, a, 2] * ds[i, 2])
            if abs(d) <= dot_min:
                ok = False
            s[c, i] = -1.0 if d < 0 else 1.0
    return s, ok


def warm_up_exact() -> None:
    """Load, or compile, the kernels of :func:`_solve_exactly`, which only a numerically fragile group
    reaches (a noise-free scene no longer does reliably): a loop worker's warm-up calls this so that no
    query's time holds their compilation (docs/loops.md, session 13)."""
    ds = np.eye(3)
    is_dir = np.ones(3, np.bool_)
    R = np.ascontiguousarray(np.broadcast_to(np.eye(3), (4, 1, 3, 3)))
    signs, _ok = _signs_exact(R, ds, ds, is_dir, _EXACT_DOT_MIN)
    _correlation_exact(signs, np.ones(3), is_dir, ds, ds)


def _write_group(out: BatchRegistration, sub: BatchRegistration, gi: int, rows: NDArray[np.int64]) -> None:
    """Group ``gi`` of ``out`` (and its associations ``rows``, input order) from a one-group result."""
    for name in ("T_target_source", "kappa", "kappa_rotation", "kappa_translation", "degenerate",
                 "rotation_rank", "translation_rank", "cost", "used_line_positions"):
        getattr(out, name)[gi] = getattr(sub, name)[0]
    for name in ("angle_residuals_deg", "offset_residuals", "signs"):
        getattr(out, name)[rows] = getattr(sub, name)


def _solve_by_reference(out: BatchRegistration, source: LandmarkSet, target: LandmarkSet,
                        A: NDArray[np.int64], g: NDArray[np.int64], w: Array, G: int,
                        fragile: NDArray[np.bool_], kappa_max: float, parallel_spread: float,
                        line_anchor_weight: float, weak_ratio: float, upright_min: float) -> None:
    """Overwrite the fragile groups of ``out`` with the reference's results for them alone
    (groups are independent, so a subset gives each group the same result)."""
    count = np.bincount(g, minlength=G)
    empty = fragile & (count == 0)
    if empty.any():  # what the reference yields for a group without associations
        out.T_target_source[empty] = np.eye(4)
        out.kappa[empty] = out.kappa_rotation[empty] = out.kappa_translation[empty] = np.inf
        out.degenerate[empty] = True
        out.rotation_rank[empty] = out.translation_rank[empty] = 0
        out.cost[empty] = 0.0
        out.used_line_positions[empty] = False
    redo = np.flatnonzero(fragile & (count > 0))
    if not len(redo):
        return
    remap = np.full(G, -1, np.int64)
    remap[redo] = np.arange(len(redo))
    rows = np.flatnonzero(remap[g] >= 0)
    sub = _register_batch_reference(source, target, A[rows], remap[g[rows]], w[rows], kappa_max,
                                    len(redo), parallel_spread, line_anchor_weight, weak_ratio, upright_min)
    for name in ("T_target_source", "kappa", "kappa_rotation", "kappa_translation", "degenerate",
                 "rotation_rank", "translation_rank", "cost", "used_line_positions"):
        getattr(out, name)[redo] = getattr(sub, name)
    for name in ("angle_residuals_deg", "offset_residuals", "signs"):
        getattr(out, name)[rows] = getattr(sub, name)


def register_landmarks(
    source: LandmarkSet,
    target: LandmarkSet,
    associations: ArrayLike,
    weights: ArrayLike | None = None,
    kappa_max: float = 1e3,
) -> RegistrationEstimate:
    """Estimate ``T_target_source`` from matched landmarks (same type per association).

    One hypothesis of :func:`register_batch`. Raises :class:`DegenerateGeometryError` only
    when nothing can be estimated (no association); otherwise returns the estimate with
    ``degenerate`` set when it is ill-conditioned.
    """
    A = np.asarray(associations, dtype=np.int64).reshape(-1, 2)
    if len(A) == 0:
        raise DegenerateGeometryError("no associations to register")
    w = None if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    if w is not None and (w.shape != (len(A),) or not np.all(np.isfinite(w)) or not np.any(w > 0)):
        raise InvalidInputError("weights must be finite, non-negative, one per association")
    b = register_batch(source, target, A, None, w, kappa_max)
    return RegistrationEstimate(
        T_target_source=b.T_target_source[0],
        kappa=float(b.kappa[0]),
        kappa_rotation=float(b.kappa_rotation[0]),
        kappa_translation=float(b.kappa_translation[0]),
        degenerate=bool(b.degenerate[0]),
        rotation_rank=int(b.rotation_rank[0]),
        translation_rank=int(b.translation_rank[0]),
        angle_residuals_deg=b.angle_residuals_deg,
        offset_residuals=b.offset_residuals,
        signs=b.signs,
        info={"used_line_positions": bool(b.used_line_positions[0])},
    )
