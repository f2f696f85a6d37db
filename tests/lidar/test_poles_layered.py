"""Geometric pole mode clustered per height layer (``LAYERED_POLES``, the pole-only front end):
a trunk under its crown, a post beside a hedge and an isolated pole are found; a pillar that
starts high above the ground is not; one layer (the default) is the plain 2-D
connected-component detector."""

from __future__ import annotations

import numpy as np
import pytest

from graffmatch.lidar.poles import LAYERED_POLES, PoleConfig, poles_geometric

GROUND = 0.0


def _cylinder(rng, xy, radius: float, z0: float, z1: float, n: int) -> np.ndarray:
    ang = rng.uniform(0, 2 * np.pi, n)
    z = rng.uniform(z0, z1, n)
    return np.column_stack([xy[0] + radius * np.cos(ang), xy[1] + radius * np.sin(ang), z])


def _ellipsoid(rng, centre, radii, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return np.asarray(centre) + v * np.asarray(radii)


def _box(rng, lo, hi, n: int) -> np.ndarray:
    return rng.uniform(lo, hi, size=(n, 3))


def _layered(**kw) -> PoleConfig:
    return PoleConfig(**{**LAYERED_POLES, **kw})


def _detect(P: np.ndarray, cfg: PoleConfig):
    """Flat ground at z = 0: the height above ground is z, no point is ground."""
    return poles_geometric(P, P[:, 2] - GROUND, np.zeros(len(P), bool), cfg)


def _nearest(res, xy) -> float:
    if len(res) == 0:
        return np.inf
    return float(np.min(np.linalg.norm(res.anchors[:, :2] - np.asarray(xy), axis=1)))


@pytest.fixture(scope="module")
def street() -> tuple[np.ndarray, dict]:
    rng = np.random.default_rng(7)
    parts = {
        # a tree: a trunk of radius 0.15 m up to 3.2 m, a crown from 2.4 m up
        "trunk": _cylinder(rng, (5.0, 0.0), 0.15, 0.0, 3.2, 400),
        "crown": _ellipsoid(rng, (5.0, 0.0, 4.2), (2.2, 2.2, 1.8), 3000),
        # a sign post standing against a 1.2 m hedge (1 x 4 m)
        "post": _cylinder(rng, (-6.0, 3.0), 0.05, 0.0, 3.6, 300),
        "hedge": _box(rng, (-6.95, 1.0, 0.0), (-6.06, 5.0, 1.2), 2500),
        # an isolated street light pole
        "light": _cylinder(rng, (0.0, -8.0), 0.1, 0.0, 4.0, 300),
        # a facade with a 0.24 m pillar between two windows: the wall below 2 m is wide, only
        # the pillar (2 - 4 m) stands alone (window panes let the beams through)
        "wall": _box(rng, (10.0, 6.0, 0.0), (14.0, 6.05, 2.0), 3000),
        "pillar": _box(rng, (11.88, 6.0, 2.0), (12.12, 6.05, 4.0), 400),
    }
    return np.concatenate(list(parts.values())), parts


def test_layers_find_trunk_under_crown(street) -> None:
    P, _ = street
    flat = _detect(P, PoleConfig())
    layered = _detect(P, _layered())
    assert _nearest(flat, (5.0, 0.0)) > 1.0  # one layer: the trunk merges with its crown
    assert _nearest(layered, (5.0, 0.0)) < 0.1
    k = int(np.argmin(np.linalg.norm(layered.anchors[:, :2] - (5.0, 0.0), axis=1)))
    assert layered.radius[k] < 0.25 and layered.directions[k, 2] > np.cos(np.radians(5))


def test_layers_find_post_beside_hedge(street) -> None:
    P, _ = street
    assert _nearest(_detect(P, PoleConfig()), (-6.0, 3.0)) > 1.0
    assert _nearest(_detect(P, _layered()), (-6.0, 3.0)) < 0.1


def test_isolated_pole_found_either_way(street) -> None:
    P, _ = street
    for cfg in (PoleConfig(), _layered()):
        assert _nearest(_detect(P, cfg), (0.0, -8.0)) < 0.05


def test_pillar_starting_high_is_no_pole(street) -> None:
    """The pillar's thin layers start 2 m above min_height (the layer of the wall's top is
    wide), beyond max_base_height = 1.5 m; allowed up to 2.5 m, it is a pole."""
    P, _ = street
    res = _detect(P, _layered())
    assert _nearest(res, (12.0, 6.0)) > 1.0
    assert _nearest(_detect(P, _layered(max_base_height=2.5)), (12.0, 6.0)) < 0.3
    assert len(res) == 3  # trunk, post, light


def test_one_layer_is_the_plain_component_detector(street) -> None:
    """By default (one layer), a pole candidate is a whole connected component of the 2-D
    grid: a pole touching the hedge's or crown's cells is part of a component too wide."""
    assert PoleConfig().layer_height is None
    P, parts = street
    res = _detect(P, PoleConfig())
    assert len(res) == 1 and _nearest(res, (0.0, -8.0)) < 0.05
    on = res.labels >= 0
    n_light = len(parts["light"][(parts["light"][:, 2] >= 0.4) & (parts["light"][:, 2] <= 4.0)])
    assert on.sum() == n_light


def test_layered_detection_is_deterministic(street) -> None:
    P, _ = street
    a, b = _detect(P, _layered()), _detect(P[::-1].copy(), _layered())
    assert len(a) == len(b)
    oa, ob = np.lexsort(a.anchors[:, :2].T), np.lexsort(b.anchors[:, :2].T)
    np.testing.assert_allclose(a.anchors[oa], b.anchors[ob], atol=1e-9)
