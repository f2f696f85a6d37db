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
from graffmatch.geometry.transforms import make_transform

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


def _kabsch(ds: Array, dt: Array, w: Array) -> tuple[Array, Array]:
    """R maximising sum w dt^T R ds; also returns the singular values of the correlation."""
    H = (ds * w[:, None]).T @ dt  # sum w ds dt^T
    U, S, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    return Vt.T @ D @ U.T, S


def _translation_system(
    R: Array, ts: NDArray[np.int8], bs: Array, bt: Array, dt: Array, w: Array
) -> tuple[Array, Array]:
    """Stacked weighted rows (vectorised per landmark type)."""
    r = bt - bs @ R.T
    sw = np.sqrt(w)
    rows, rhs = [], []
    pl = ts == LandmarkType.PLANE
    if pl.any():
        rows.append(sw[pl, None] * dt[pl])
        rhs.append(sw[pl] * np.einsum("ij,ij->i", dt[pl], r[pl]))
    ln = ts == LandmarkType.LINE
    if ln.any():
        d = dt[ln]
        P = np.eye(3)[None] - np.einsum("ni,nj->nij", d, d)
        rows.append((sw[ln, None, None] * P).reshape(-1, 3))
        rhs.append((sw[ln, None] * np.einsum("nij,nj->ni", P, r[ln])).reshape(-1))
    po = ts == LandmarkType.POINT
    if po.any():
        rows.append((sw[po, None, None] * np.eye(3)[None]).reshape(-1, 3))
        rhs.append((sw[po, None] * r[po]).reshape(-1))
    return np.concatenate(rows), np.concatenate(rhs)


def _solve_translation(R, ts, bs, bt, dt, w) -> tuple[Array, Array, float]:
    A, y = _translation_system(R, ts, bs, bt, dt, w)
    S = np.linalg.svd(A, compute_uv=False)
    t, *_ = np.linalg.lstsq(A, y, rcond=None)
    return t, S, float(np.sum((A @ t - y) ** 2))


def register_landmarks(
    source: LandmarkSet,
    target: LandmarkSet,
    associations: ArrayLike,
    weights: ArrayLike | None = None,
    kappa_max: float = 1e3,
) -> RegistrationEstimate:
    """Estimate ``T_target_source`` from matched landmarks (same type per association).

    Raises :class:`DegenerateGeometryError` only when nothing can be estimated (no association);
    otherwise returns the estimate with ``degenerate`` set when it is ill-conditioned.
    """
    A = np.asarray(associations, dtype=np.int64).reshape(-1, 2)
    if len(A) == 0:
        raise DegenerateGeometryError("no associations to register")
    if A[:, 0].max() >= len(source) or A[:, 1].max() >= len(target) or A.min() < 0:
        raise InvalidInputError("association index out of range")
    ts = source.types[A[:, 0]]
    if np.any(ts != target.types[A[:, 1]]):
        raise InvalidInputError("associations must pair landmarks of the same type")
    w = np.ones(len(A)) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    if w.shape != (len(A),) or not np.all(np.isfinite(w)) or np.any(w < 0) or not np.any(w > 0):
        raise InvalidInputError("weights must be finite, non-negative, one per association")
    ds = source.directions[A[:, 0]]
    dt = target.directions[A[:, 1]]
    bs = source.anchors[A[:, 0]]
    bt = target.anchors[A[:, 1]]
    is_dir = ts > 0
    is_pt = ~is_dir

    # Point correlation (centred), scaled to unit spread so it mixes with unit directions.
    pt_vs = pt_vt = np.zeros((0, 3))
    pt_w = np.zeros(0)
    if is_pt.sum() >= 3:
        ps, pt = bs[is_pt], bt[is_pt]
        cs, ct = np.average(ps, 0, w[is_pt]), np.average(pt, 0, w[is_pt])
        scale = np.sqrt(np.mean(np.sum((ps - cs) ** 2, 1))) + 1e-12
        pt_vs, pt_vt, pt_w = (ps - cs) / scale, (pt - ct) / scale, w[is_pt]

    dir_idx = np.flatnonzero(is_dir)
    ds_d, dt_d, w_d = ds[dir_idx], dt[dir_idx], w[dir_idx]

    def evaluate(signs_d: Array) -> tuple[float, Array, Array, Array, Array, float]:
        vs = np.concatenate([ds_d * signs_d[:, None], pt_vs])
        vt = np.concatenate([dt_d, pt_vt])
        ww = np.concatenate([w_d, pt_w])
        R, S = _kabsch(vs, vt, ww)
        t, St, tres = _solve_translation(R, ts, bs, bt, dt, w)
        rot_res = float(np.sum(w_d * (1.0 - np.abs(np.einsum("ij,ij->i", dt_d, ds_d @ R.T)))))
        return rot_res + tres / (1.0 + float(np.sum(w))), R, t, S, St, 0.0

    candidates: list[Array] = []
    if len(dir_idx) >= 2:
        # The two most independent directions seed the sign search.
        G = np.abs(ds_d @ ds_d.T)
        sines = np.sqrt(np.clip(1 - G**2, 0, 1)) * np.sqrt(np.outer(w_d, w_d))
        i, j = np.unravel_index(np.argmax(sines), sines.shape)
        for si in (1.0, -1.0):
            for sj in (1.0, -1.0):
                R0, _ = _kabsch(
                    np.stack([ds_d[i] * si, ds_d[j] * sj]), np.stack([dt_d[i], dt_d[j]]),
                    np.array([1.0, 1.0]),
                )
                signs = np.sign(np.einsum("ij,ij->i", dt_d, ds_d @ R0.T))
                signs[signs == 0] = 1.0
                candidates.append(signs)
    elif len(dir_idx) == 1:
        candidates += [np.ones(1), -np.ones(1)]
    else:
        candidates.append(np.zeros(0))

    best = None
    for signs in candidates:
        for _ in range(2):  # re-assign signs from the refined rotation
            cost, R, t, S, St, _ = evaluate(signs)
            new = np.sign(np.einsum("ij,ij->i", dt_d, ds_d @ R.T))
            new[new == 0] = 1.0
            if np.array_equal(new, signs):
                break
            signs = new
        cost, R, t, S, St, _ = evaluate(signs)
        if best is None or cost < best[0] - 1e-12:
            best = (cost, R, t, S, St, signs)
    assert best is not None
    _, R, t, S, St, signs_d = best

    tol = 1e-9
    rot_rank = int(np.sum(S > tol * max(S[0], 1e-300))) if S[0] > 0 else 0
    k_rot = float(S[0] / S[1]) if S[1] > tol * max(S[0], 1e-300) else np.inf
    tr_rank = int(np.sum(St > tol * max(St[0], 1e-300))) if St.size and St[0] > 0 else 0
    k_tr = float(St[0] / St[2]) if St.size >= 3 and St[2] > tol * max(St[0], 1e-300) else np.inf
    kappa = max(k_rot, k_tr)

    signs = np.ones(len(A))
    signs[dir_idx] = signs_d
    cosang = np.abs(np.einsum("ij,ij->i", dt, ds @ R.T))
    ang = np.where(is_dir, np.degrees(np.arccos(np.clip(cosang, -1, 1))), 0.0)
    r = bt - (bs @ R.T + t)
    along = np.einsum("ij,ij->i", dt, r)
    off = np.where(
        ts == LandmarkType.PLANE,
        np.abs(along),
        np.where(
            ts == LandmarkType.LINE,
            np.linalg.norm(r - along[:, None] * dt, axis=1),
            np.linalg.norm(r, axis=1),
        ),
    )
    return RegistrationEstimate(
        T_target_source=make_transform(R, t),
        kappa=float(kappa),
        kappa_rotation=k_rot,
        kappa_translation=k_tr,
        degenerate=bool(not np.isfinite(kappa) or kappa > kappa_max),
        rotation_rank=rot_rank,
        translation_rank=tr_rank,
        angle_residuals_deg=ang,
        offset_residuals=off,
        signs=signs,
    )
