"""Gated putative associations: a subset of all-to-all in its order, gates that pass what they
cannot judge, gravity gates only on level pairs, and a graph equal to the induced subgraph."""

from __future__ import annotations

import numpy as np

from graffmatch.association.consistency_graph import build_consistency_graph
from graffmatch.association.putative import (
    GatingConfig,
    all_to_all,
    gated_associations,
    is_level_pair,
    putative_associations,
)
from graffmatch.datasets.landmark_scene import make_scene_pair
from graffmatch.geometry.distance import pairwise_distances
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.transforms import make_transform, rot_x


def _scene(tilt_deg: float = 0.0, seed: int = 0) -> LandmarkSet:
    """Poles (vertical lines), a facade, a roof and a ground plane flagged 'is_ground',
    optionally seen by a sensor tilted about x."""
    rng = np.random.default_rng(seed)
    types = [1, 1, 1, 2, 2, 2, 2]
    dirs = [[0, 0, 1], [0, 0.05, 1], [1, 0, 0.02], [0, 1, 0], [1, 0, 0], [0, 0, 1], [0, 0.3, 1]]
    anchors = rng.uniform(-10, 10, (7, 3))
    attrs = {
        "radius": [0.10, 0.12, 0.30, np.nan, np.nan, np.nan, np.nan],
        "extent": [6.0, 5.0, 12.0, 80.0, 60.0, 300.0, 20.0],
        "is_ground": [0, 0, 0, 0, 0, 1, 0],
    }
    ls = LandmarkSet.from_arrays(types, np.asarray(dirs, float), anchors, attrs)
    return ls.transform(make_transform(rot_x(np.radians(tilt_deg)), np.zeros(3)))


def test_disabled_gating_is_all_to_all_and_gated_is_an_ordered_subset():
    sc = make_scene_pair(10, 20, seed=2)
    full = all_to_all(sc.source.types, sc.target.types)
    off = gated_associations(sc.source, sc.target, GatingConfig(enabled=False))
    assert np.array_equal(off, full)
    assert putative_associations(sc.source, sc.target, None) is None
    assert putative_associations(sc.source, sc.target, GatingConfig(enabled=False)) is None
    on = gated_associations(sc.source, sc.target, GatingConfig(level_sensor=True))
    rows = {tuple(r): i for i, r in enumerate(full.tolist())}
    pos = [rows[tuple(r)] for r in on.tolist()]
    assert np.all(np.diff(pos) > 0)  # a subset, in all_to_all's order
    truth = set(map(tuple, sc.true_matches.tolist()))
    assert truth <= set(map(tuple, on.tolist()))  # no true association is gated away
    assert len(on) < len(full)


def test_level_pair_gates_by_tilt_ground_and_ratios():
    s, t = _scene(), _scene(seed=1)
    assert is_level_pair(s, t, GatingConfig())
    A = set(map(tuple, gated_associations(s, t, GatingConfig(radius_ratio=3.0, length_ratio=3.0)).tolist()))
    assert (0, 0) in A and (0, 1) in A  # vertical poles with close radii and lengths
    assert (0, 2) not in A  # a vertical pole never with a horizontal line
    assert (3, 3) in A and (3, 4) in A  # facades
    assert (3, 5) not in A and (5, 3) not in A  # ground only with ground
    assert (5, 5) in A
    assert (3, 6) not in A  # a facade never with a 17-degree slope
    # length ratio 6/12 passes at 3, fails at 1.5; NaN radii never gate planes
    tight = GatingConfig(length_ratio=1.5, radius_ratio=None)
    assert (0, 2) not in set(map(tuple, gated_associations(s, t, tight.model_copy(update={"tilt_deg": None})).tolist()))
    assert (0, 1) in set(map(tuple, gated_associations(s, t, tight).tolist()))


def test_tilted_sensor_keeps_every_tilt():
    """A hand-held scan tilted by 20 degrees: its ground normal is off z, so neither the tilt
    nor the ground gate applies (they would drop true matches), only the ratio gates."""
    s, t = _scene(20.0), _scene(seed=1)
    assert not is_level_pair(s, t, GatingConfig())
    A = set(map(tuple, gated_associations(s, t).tolist()))
    assert (3, 5) in A and (0, 2) in A
    forced = set(map(tuple, gated_associations(s, t, GatingConfig(level_sensor=True)).tolist()))
    assert (0, 0) not in forced  # assuming level on a tilted scan would gate a true match


def test_gated_graph_is_the_induced_subgraph():
    sc = make_scene_pair(8, 14, seed=5)
    Di, Dj = pairwise_distances(sc.source), pairwise_distances(sc.target)
    kw = {"types_i": sc.source.types, "types_j": sc.target.types}
    full = build_consistency_graph(Di, Dj, **kw)
    A = gated_associations(sc.source, sc.target, GatingConfig(level_sensor=True))
    g = build_consistency_graph(Di, Dj, A, **kw)
    rows = {tuple(r): i for i, r in enumerate(full.associations.tolist())}
    idx = np.array([rows[tuple(r)] for r in A.tolist()])
    expected = full.weights[idx][:, idx].toarray()
    assert np.array_equal(g.weights.toarray(), expected)
    # and without the types (single window group) the same graph
    g2 = build_consistency_graph(Di, Dj, A)
    assert np.array_equal(g2.weights.toarray(), expected)


def test_explicit_association_lists_are_checked_for_duplicates_anywhere_in_them():
    """A repeated (a, b) pair is refused wherever it sits (the check sorts a n_j + b keys);
    pairs that share one index only, or whose keys would collide without the range check, pass."""
    import pytest

    from graffmatch.association.putative import check_associations
    from graffmatch.errors import InvalidInputError

    rng = np.random.default_rng(5)
    A = all_to_all(rng.integers(0, 3, 40), rng.integers(0, 3, 50))
    perm = rng.permutation(len(A))
    assert np.array_equal(check_associations(A[perm], 40, 50), A[perm])
    for i, j in ((0, 1), (0, len(A) - 1), (len(A) // 2, 3)):
        B = A[perm].copy()
        B[j] = B[i]
        with pytest.raises(InvalidInputError, match="duplicates"):
            check_associations(B, 40, 50)
    # (0, 7) and (1, 0) differ; with n_j = 7 their keys 7 and 7 would collide, but b = 7 is out of range
    with pytest.raises(InvalidInputError, match="out of range"):
        check_associations(np.array([[0, 7], [1, 0]]), 2, 7)
    assert check_associations(np.array([[0, 6], [1, 0]]), 2, 7).shape == (2, 2)
    assert check_associations(np.zeros((0, 2), dtype=np.int64), 2, 7).shape == (0, 2)
