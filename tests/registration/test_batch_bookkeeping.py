"""The compiled bookkeeping of register_batch (group sort, kappa / ranks / transforms, residual
order) against the numpy formulas it replaced: bit for bit, on random and edge-case inputs."""

from __future__ import annotations

import numpy as np
import pytest

from graffmatch.registration import closed_form as cf


def _finish_numpy(R, t, S, lam, kappa_max, reasons):
    """The numpy post-processing of register_batch before it was compiled (the specification)."""
    tol = 1e-9
    S0 = np.maximum(S[:, 0], 1e-300)
    rot_rank = np.sum(S > tol * S0[:, None], axis=1) * (S[:, 0] > 0)
    k_rot = np.where(S[:, 1] > tol * S0, S[:, 0] / np.where(S[:, 1] > 0, S[:, 1], 1.0), np.inf)
    sv = np.sqrt(np.clip(lam[:, ::-1], 0, None))
    sv0 = np.maximum(sv[:, 0], 1e-300)
    tr_rank = np.sum(sv > tol * sv0[:, None], axis=1) * (sv[:, 0] > 0)
    k_tr = np.where(sv[:, 2] > tol * sv0, sv[:, 0] / np.where(sv[:, 2] > 0, sv[:, 2], 1.0), np.inf)
    kappa = np.maximum(k_rot, k_tr)
    reasons = reasons | np.where(np.abs(kappa - kappa_max) <= 1e-8 * abs(kappa_max), 4096, 0)
    T = np.tile(np.eye(4), (len(R), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    return T, kappa, k_rot, k_tr, rot_rank.astype(np.int64), tr_rank.astype(np.int64), \
        ~np.isfinite(kappa) | (kappa > kappa_max), reasons


@pytest.mark.parametrize("seed", range(5))
def test_finish_batch_equals_the_numpy_formulas(seed):
    rng = np.random.default_rng(seed)
    G = 400
    S = np.sort(rng.uniform(0, 10, (G, 3)), axis=1)[:, ::-1].copy()
    lam = np.sort(rng.uniform(-1e-12, 10, (G, 3)), axis=1)
    # edge cases: zero / tiny singular values, all zero, NaN, kappa exactly at kappa_max
    S[:40, 1:] = 0.0
    S[40:60] = 0.0
    S[60:70, 2] = 1e-10 * S[60:70, 0]
    lam[70:90, :2] = 0.0
    lam[90:100] = -0.0
    S[100:105, 1] = np.nan
    lam[105:110, 0] = np.nan
    S[110:120, 1] = S[110:120, 0] / 1e3  # kappa_rotation = 1000 = kappa_max
    lam[110:120] = 1.0
    R = rng.normal(size=(G, 3, 3))
    t = rng.normal(size=(G, 3))
    reasons = rng.integers(0, 4, G) * 2
    ref = _finish_numpy(R, t, S, lam, 1e3, reasons.copy())
    got_reasons = reasons.copy()
    got = cf._finish_batch(R, t, S, lam, 1e3, got_reasons)
    for a, b in zip(got, ref[:7], strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)  # NaN == NaN here; bitwise equal otherwise
    np.testing.assert_array_equal(got_reasons, ref[7])
    assert (got_reasons[110:120] & 4096).all()


@pytest.mark.parametrize("seed", range(5))
def test_group_sort_and_residual_order(seed):
    rng = np.random.default_rng(seed)
    G = int(rng.integers(1, 60))
    g = rng.integers(0, G, int(rng.integers(1, 500)))
    w = rng.uniform(0, 1, len(g))
    order, bounds, bad = cf._sort_groups(g, w, G)
    np.testing.assert_array_equal(order, np.argsort(g, kind="stable"))
    np.testing.assert_array_equal(bounds, np.searchsorted(g[order], np.arange(G + 1)))
    count, wsum = np.bincount(g, minlength=G), np.bincount(g, weights=w, minlength=G)
    assert bad == bool(np.any((count > 0) & (wsum <= 0)))
    w[g == g[0]] = 0.0
    assert cf._sort_groups(g, w, G)[2]
    x = rng.normal(size=len(g))
    inv = np.empty(len(g), np.int64)
    inv[order] = np.arange(len(g))
    np.testing.assert_array_equal(cf._unsort(x, order), x[inv])
