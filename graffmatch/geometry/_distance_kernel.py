"""numba kernel for batched d_Graff: the hot path of every intra-scan distance matrix.

Per pair it builds the two Stiefel frames (at most 4x3) and the small (at most 3x3) Gram
matrices whose eigenvalues are the squared cosines and squared sines of the principal angles,
and diagonalises them with a few Jacobi rotations (sines for small angles, cosines for large). No LAPACK call per pair, so thousands of pairs
cost microseconds. ``graffmatch.geometry.distance.principal_angles_batch`` (SVD based, with
sines for small angles) is the reference it is tested against.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True)
def _jacobi_eigvals(G: np.ndarray, p: int, out: np.ndarray) -> None:
    """Eigenvalues of the symmetric p x p (p <= 3) top-left block of G, in place (cyclic Jacobi).

    Jacobi keeps small eigenvalues accurate, unlike closed-form cubic roots near repeated
    eigenvalues (plane pairs always have two zero principal angles)."""
    for _ in range(12):
        off = 0.0
        for a in range(p):
            for b in range(a + 1, p):
                off += abs(G[a, b])
        if off < 1e-300:
            break
        for a in range(p):
            for b in range(a + 1, p):
                apq = G[a, b]
                if abs(apq) < 1e-300:
                    continue
                theta = (G[b, b] - G[a, a]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                G[a, a] -= t * apq
                G[b, b] += t * apq
                G[a, b] = 0.0
                G[b, a] = 0.0
                for r in range(p):
                    if r != a and r != b:
                        gra = G[r, a]
                        grb = G[r, b]
                        G[r, a] = c * gra - s * grb
                        G[a, r] = G[r, a]
                        G[r, b] = s * gra + c * grb
                        G[b, r] = G[r, b]
    for a in range(p):
        out[a] = G[a, a]


@nb.njit(cache=True)
def _sort_small(v: np.ndarray, p: int) -> None:
    for a in range(p):
        for b in range(a + 1, p):
            if v[b] < v[a]:
                tmp = v[a]
                v[a] = v[b]
                v[b] = tmp


@nb.njit(cache=True, inline="always")
def _angle_from_cos2(c2: float) -> float:
    if c2 >= 1.0:
        return 0.0
    if c2 <= 0.0:
        return math.pi / 2.0
    return math.acos(math.sqrt(c2))


@nb.njit(cache=True)
def _stiefel_into(Y: np.ndarray, k: int, B: np.ndarray, bx: float, by: float, bz: float) -> None:
    """Fill Y (4 x (k+1)) with the Stiefel coordinates of basis B (3x2, k used) + (bx,by,bz)."""
    b0x, b0y, b0z = bx, by, bz
    for c in range(k):
        dot = B[0, c] * bx + B[1, c] * by + B[2, c] * bz
        b0x -= dot * B[0, c]
        b0y -= dot * B[1, c]
        b0z -= dot * B[2, c]
    eta = math.sqrt(1.0 + b0x * b0x + b0y * b0y + b0z * b0z)
    for c in range(k):
        Y[0, c] = B[0, c]
        Y[1, c] = B[1, c]
        Y[2, c] = B[2, c]
        Y[3, c] = 0.0
    Y[0, k] = b0x / eta
    Y[1, k] = b0y / eta
    Y[2, k] = b0z / eta
    Y[3, k] = 1.0 / eta


@nb.njit(cache=True)
def graff_distances_kernel(
    types1: np.ndarray,
    bases1: np.ndarray,
    anchors1: np.ndarray,
    types2: np.ndarray,
    bases2: np.ndarray,
    anchors2: np.ndarray,
    ii: np.ndarray,
    jj: np.ndarray,
    inv_rho: float,
    shift: bool,
) -> np.ndarray:
    """d_Graff of pairs (set1[ii[t]], set2[jj[t]]) after the shift (if ``shift``) and 1/rho scale."""
    n = ii.shape[0]
    out = np.empty(n)
    Y1 = np.zeros((4, 3))
    Y2 = np.zeros((4, 3))
    C = np.zeros((3, 3))
    Gc = np.zeros((3, 3))
    Gs = np.zeros((3, 3))
    Rm = np.zeros((4, 3))
    lc = np.zeros(3)
    ls = np.zeros(3)
    for t in range(n):
        i = ii[t]
        j = jj[t]
        k1 = types1[i]
        k2 = types2[j]
        if shift:
            _stiefel_into(Y1, k1, bases1[i], 0.0, 0.0, 0.0)
            _stiefel_into(
                Y2, k2, bases2[j],
                (anchors2[j, 0] - anchors1[i, 0]) * inv_rho,
                (anchors2[j, 1] - anchors1[i, 1]) * inv_rho,
                (anchors2[j, 2] - anchors1[i, 2]) * inv_rho,
            )
        else:
            _stiefel_into(
                Y1, k1, bases1[i],
                anchors1[i, 0] * inv_rho, anchors1[i, 1] * inv_rho, anchors1[i, 2] * inv_rho,
            )
            _stiefel_into(
                Y2, k2, bases2[j],
                anchors2[j, 0] * inv_rho, anchors2[j, 1] * inv_rho, anchors2[j, 2] * inv_rho,
            )
        p1 = k1 + 1
        p2 = k2 + 1
        for a in range(p1):
            for b in range(p2):
                s = 0.0
                for r in range(4):
                    s += Y1[r, a] * Y2[r, b]
                C[a, b] = s
        # Small side Q (4 x p), other side W; C maps between them.
        # cos^2 = eig(Q^T W W^T Q), sin^2 = eig(R^T R) with R = (I - W W^T) Q.
        if p1 <= p2:
            p = p1
            for a in range(p):
                for b in range(p):
                    s = 0.0
                    for c in range(p2):
                        s += C[a, c] * C[b, c]
                    Gc[a, b] = s
                for r in range(4):
                    s = Y1[r, a]
                    for c in range(p2):
                        s -= Y2[r, c] * C[a, c]
                    Rm[r, a] = s
        else:
            p = p2
            for a in range(p):
                for b in range(p):
                    s = 0.0
                    for c in range(p1):
                        s += C[c, a] * C[c, b]
                    Gc[a, b] = s
                for r in range(4):
                    s = Y2[r, a]
                    for c in range(p1):
                        s -= Y1[r, c] * C[c, a]
                    Rm[r, a] = s
        for a in range(p):
            for b in range(p):
                s = 0.0
                for r in range(4):
                    s += Rm[r, a] * Rm[r, b]
                Gs[a, b] = s
        _jacobi_eigvals(Gc, p, lc)
        _jacobi_eigvals(Gs, p, ls)
        _sort_small(lc, p)  # ascending cos^2 -> descending angles
        _sort_small(ls, p)  # ascending sin^2 -> ascending angles
        d2 = 0.0
        for a in range(p):
            s2 = ls[a]
            if s2 < 0.5:
                th = math.asin(math.sqrt(max(s2, 0.0)))
            else:
                th = _angle_from_cos2(lc[p - 1 - a])
            d2 += th * th
        out[t] = math.sqrt(d2)
    return out
