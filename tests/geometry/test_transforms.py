"""restore_offsets: a transform estimated on recentred clouds, returned for the original frames."""

from __future__ import annotations

import numpy as np
import pytest

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.transforms import (
    invert,
    make_transform,
    random_transform,
    restore_offsets,
    transform_points,
)


def test_restore_offsets_composes_exactly(rng) -> None:
    """T = Trans(o_t) T_c Trans(-o_s): world points map to world points within 1e-9 m."""
    for _ in range(50):
        o_s = rng.uniform(-1, 1, 3) * [6e5, 5e6, 100.0]
        o_t = o_s + rng.uniform(-50, 50, 3)
        T_c = random_transform(rng, max_translation=30.0)
        local_s = rng.normal(scale=40.0, size=(100, 3))
        local_t = transform_points(T_c, local_s)
        T = restore_offsets(T_c, o_s, o_t)
        # World points pass through coordinates of 5e6 m, where float64 spacing is 9.3e-10 m:
        # a few roundings are all the error there is.
        mapped = transform_points(T, local_s + o_s) - o_t
        assert np.abs(mapped - local_t).max() < 1e-8
        Te = make_transform(np.eye(3), o_t) @ T_c @ make_transform(np.eye(3), -o_s)
        np.testing.assert_allclose(T, Te, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(T[:3, :3], T_c[:3, :3])


def test_restore_offsets_identities(rng) -> None:
    T_c = random_transform(rng)
    np.testing.assert_array_equal(restore_offsets(T_c, None, None), T_c)
    np.testing.assert_array_equal(restore_offsets(T_c, [0, 0, 0], np.zeros(3)), T_c)
    o = np.array([500000.0, 4600000.0, 0.0])
    # Same origin, identity local transform -> identity world transform.
    np.testing.assert_array_equal(restore_offsets(np.eye(4), o, o), np.eye(4))
    # Inverse consistency: swapping the roles inverts the transform.
    o2 = o + [3.0, -4.0, 0.5]
    T = restore_offsets(T_c, o, o2)
    # (two world translations of 4.6e6 m: each carries float64 rounding of 4.7e-10 m)
    np.testing.assert_allclose(restore_offsets(invert(T_c), o2, o) @ T, np.eye(4), atol=5e-9)


@pytest.mark.parametrize(
    "T,o_s,o_t,match",
    [
        (np.eye(3), None, None, "4x4"),
        (np.eye(4) * 2, None, None, "SO\\(3\\)"),
        (np.eye(4), [1, 2], None, "origin_source"),
        (np.eye(4), None, [np.nan, 0, 0], "origin_target"),
        (np.eye(4), "abc", None, "origin_source"),
    ],
)
def test_restore_offsets_rejects_bad_input(T, o_s, o_t, match) -> None:
    with pytest.raises(InvalidInputError, match=match):
        restore_offsets(T, o_s, o_t)
