"""Distances on the affine Grassmannian: d_Graff, the invariant (shifted, rho-scaled) distance and
the naive (unshifted) one used for the paper's ablation.

An affine subspace Y = A + b in Graff(k, 3) embeds into Gr(k+1, 4) through its Stiefel
coordinates ``Y = [[A, b0/eta], [0, 1/eta]]`` with ``b0 = (I - A A^T) b`` and
``eta = sqrt(1 + |b0|^2)``. d_Graff is the Grassmannian distance of the embeddings:
``sqrt(sum_i theta_i^2)`` over the ``min(k1, k2) + 1`` principal angles.

Proposition 1 of the paper: d_Graff is invariant to SE(3) if both anchors are first shifted
by ``-b1`` (the first landmark's anchor). The distance is then *order dependent* (shifting by
``b1`` or by ``b2`` gives different values for, e.g., two non-parallel planes), so the batched
intra-scan matrices average both orders (``symmetrize=True``, the default): every term is
invariant, hence so is the mean, and the consistency graph needs a symmetric matrix.

Numerics: principal angles use cosines (SVD of Y1^T Y2) for large angles and sines (SVD of the
residual (I - Y2 Y2^T) Y1) for small ones, so small distances keep full precision.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graffmatch.errors import InvalidInputError
from graffmatch.geometry._distance_kernel import graff_distances_kernel
from graffmatch.geometry.landmarks import Landmark, LandmarkSet
from graffmatch.geometry.set_cache import kernel_input

Array = NDArray[np.float64]
Variant = Literal["invariant", "naive"]

DEFAULT_RHO = 40.0


def stiefel_coordinates(A: ArrayLike, b: ArrayLike) -> Array:
    """Stiefel coordinates (4 x (k+1)) of the affine subspace A + b."""
    A = np.asarray(A, dtype=float).reshape(3, -1)
    b = np.asarray(b, dtype=float).reshape(3)
    return _stiefel(A[None], b[None])[0]


def _stiefel(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Batched Stiefel coordinates: A (N,3,k), b (N,3) -> (N,4,k+1)."""
    n, _, k = A.shape
    b0 = b - np.einsum("nik,njk,nj->ni", A, A, b)
    eta = np.sqrt(1.0 + np.einsum("ni,ni->n", b0, b0))
    Y = np.zeros((n, 4, k + 1))
    Y[:, :3, :k] = A
    Y[:, :3, k] = b0 / eta[:, None]
    Y[:, 3, k] = 1.0 / eta
    return Y


def principal_angles_batch(Y1: np.ndarray, Y2: np.ndarray) -> np.ndarray:
    """Principal angles (ascending) between the column spans of orthonormal Y1 (N,d,p) and
    Y2 (N,d,q), p <= q. Returns (N, p)."""
    if Y1.shape[2] > Y2.shape[2]:
        raise InvalidInputError("principal_angles_batch expects p <= q")
    C = np.einsum("nip,niq->npq", Y1, Y2)
    cos_desc = np.linalg.svd(C, compute_uv=False)  # (N,p) descending -> angles ascending
    R = Y1 - np.einsum("niq,npq->nip", Y2, C)  # (I - Y2 Y2^T) Y1
    sin_desc = np.linalg.svd(R, compute_uv=False)  # descending sines -> angles descending
    sin_asc = sin_desc[:, ::-1]
    small = sin_asc < np.sqrt(0.5)
    theta = np.where(
        small,
        np.arcsin(np.clip(sin_asc, 0.0, 1.0)),
        np.arccos(np.clip(cos_desc, 0.0, 1.0)),
    )
    return theta


def principal_angles(Y1: ArrayLike, Y2: ArrayLike) -> Array:
    """Principal angles between the spans of two orthonormal matrices (any order of sizes)."""
    Y1 = np.asarray(Y1, dtype=float)
    Y2 = np.asarray(Y2, dtype=float)
    if Y1.shape[1] > Y2.shape[1]:
        Y1, Y2 = Y2, Y1
    return principal_angles_batch(Y1[None], Y2[None])[0]


def graff_distance(A1: ArrayLike, b1: ArrayLike, A2: ArrayLike, b2: ArrayLike) -> float:
    """Plain d_Graff between A1 + b1 and A2 + b2 (no shift, no scaling: not SE(3)-invariant)."""
    Y1 = stiefel_coordinates(A1, b1)
    Y2 = stiefel_coordinates(A2, b2)
    return float(np.sqrt(np.sum(principal_angles(Y1, Y2) ** 2)))


def invariant_distance(lm1: Landmark, lm2: Landmark, rho: float = DEFAULT_RHO) -> float:
    """Proposition 1: shift both anchors by -b1, scale them by 1/rho, then d_Graff.

    Order dependent: ``invariant_distance(a, b) != invariant_distance(b, a)`` in general.
    """
    _check_rho(rho)
    return graff_distance(lm1.basis, np.zeros(3), lm2.basis, (lm2.anchor - lm1.anchor) / rho)


def naive_distance(lm1: Landmark, lm2: Landmark, rho: float = DEFAULT_RHO) -> float:
    """d_Graff of the rho-scaled landmarks without the shift (the paper's GraffMatch-Naive)."""
    _check_rho(rho)
    return graff_distance(lm1.basis, lm1.anchor / rho, lm2.basis, lm2.anchor / rho)


def _check_rho(rho: float) -> None:
    if not np.isfinite(rho) or rho <= 0:
        raise InvalidInputError(f"rho must be a positive finite scale in metres, got {rho}")


def directed_distances(
    types1: np.ndarray,
    bases1: np.ndarray,
    anchors1: np.ndarray,
    types2: np.ndarray,
    bases2: np.ndarray,
    anchors2: np.ndarray,
    rho: float = DEFAULT_RHO,
    variant: Variant = "invariant",
) -> Array:
    """Distances of N aligned landmark pairs (row i of set 1 with row i of set 2), shifting by the
    first landmark's anchor when ``variant == "invariant"``. Uses the numba kernel."""
    n = len(types1)
    idx = np.arange(n)
    return _kernel(types1, bases1, anchors1, types2, bases2, anchors2, idx, idx, rho, variant)


def directed_distances_reference(
    types1: np.ndarray,
    bases1: np.ndarray,
    anchors1: np.ndarray,
    types2: np.ndarray,
    bases2: np.ndarray,
    anchors2: np.ndarray,
    rho: float = DEFAULT_RHO,
    variant: Variant = "invariant",
) -> Array:
    """SVD-based reference of :func:`directed_distances` (batched numpy, sines for small angles).

    Slower; kept to test the fast kernel against an independent computation."""
    _check(rho, variant)
    N = len(types1)
    out = np.zeros(N)
    if variant == "invariant":
        b1 = np.zeros_like(anchors1)
        b2 = (anchors2 - anchors1) / rho
    else:
        b1 = anchors1 / rho
        b2 = anchors2 / rho
    for k1 in (0, 1, 2):
        for k2 in (0, 1, 2):
            sel = np.flatnonzero((types1 == k1) & (types2 == k2))
            if sel.size == 0:
                continue
            Y1 = _stiefel(bases1[sel, :, :k1], b1[sel])
            Y2 = _stiefel(bases2[sel, :, :k2], b2[sel])
            th = principal_angles_batch(Y1, Y2) if k1 <= k2 else principal_angles_batch(Y2, Y1)
            out[sel] = np.sqrt(np.sum(th * th, axis=1))
    return out


def _check(rho: float, variant: str) -> None:
    _check_rho(rho)
    if variant not in ("invariant", "naive"):
        raise InvalidInputError(f"unknown distance variant {variant!r}")


def _kernel(types1, bases1, anchors1, types2, bases2, anchors2, ii, jj, rho, variant) -> Array:
    _check(rho, variant)
    return graff_distances_kernel(
        kernel_input(types1, np.int64),
        kernel_input(bases1, np.float64),
        kernel_input(anchors1, np.float64),
        kernel_input(types2, np.int64),
        kernel_input(bases2, np.float64),
        kernel_input(anchors2, np.float64),
        kernel_input(ii, np.int64),
        kernel_input(jj, np.int64),
        1.0 / float(rho),
        variant == "invariant",
    )


def pairwise_distances(
    ls: LandmarkSet,
    rho: float = DEFAULT_RHO,
    variant: Variant = "invariant",
    symmetrize: bool = True,
) -> Array:
    """The n x n intra-scan matrix of every landmark pair, across types, in one call.

    ``D[a, a']`` shifts by landmark a's anchor; with ``symmetrize`` the matrix is
    ``(D + D^T) / 2`` (still invariant, see the module docstring). Diagonal is zero.
    Cost: O(n^2) small SVDs, once per scan.
    """
    n = len(ls)
    D = np.zeros((n, n))
    if n < 2:
        return D
    if symmetrize:
        i, j = np.triu_indices(n, k=1)
        ii = np.concatenate([i, j])
        jj = np.concatenate([j, i])
    else:
        ii, jj = np.nonzero(~np.eye(n, dtype=bool))
    d = _kernel(ls.types, ls.bases, ls.anchors, ls.types, ls.bases, ls.anchors, ii, jj, rho, variant)
    D[ii, jj] = d
    if symmetrize:
        D = 0.5 * (D + D.T)
    return D


def cross_distances(
    ls_a: LandmarkSet,
    ls_b: LandmarkSet,
    rho: float = DEFAULT_RHO,
    variant: Variant = "invariant",
    same_type_only: bool = True,
) -> Array:
    """(na, nb) distances between the landmarks of two sets expressed in the same frame.

    Used to decide whether a match is correct after ground-truth alignment (LMR's tau_d) and
    to build ground-truth matches. Symmetrised over the shift order; +inf across types when
    ``same_type_only``.
    """
    na, nb = len(ls_a), len(ls_b)
    D = np.full((na, nb), np.inf)
    if na == 0 or nb == 0:
        return D
    ia, ib = np.meshgrid(np.arange(na), np.arange(nb), indexing="ij")
    ia, ib = ia.ravel(), ib.ravel()
    if same_type_only:
        keep = ls_a.types[ia] == ls_b.types[ib]
        ia, ib = ia[keep], ib[keep]
    a = (ls_a.types, ls_a.bases, ls_a.anchors)
    b = (ls_b.types, ls_b.bases, ls_b.anchors)
    d_ab = _kernel(*a, *b, ia, ib, rho, variant)
    d_ba = _kernel(*b, *a, ib, ia, rho, variant)
    D[ia, ib] = 0.5 * (d_ab + d_ba)
    return D
