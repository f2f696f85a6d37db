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
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graffmatch.errors import DegenerateGeometryError, InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType

Array = NDArray[np.float64]


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
) -> BatchRegistration:
    """Register many association groups at once (vectorised: batched 3x3 SVDs and solves).

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
    ds = source.directions[A[:, 0]]
    dt = target.directions[A[:, 1]]
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
    best = np.argmin(cost + 1e-12 * np.arange(C)[:, None], axis=0)  # ties: first candidate
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
