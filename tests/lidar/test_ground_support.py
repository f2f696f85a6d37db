"""The ground fit's centred support: numpy's own numbers without numpy's temporaries."""

from __future__ import annotations

import numpy as np
import pytest

from graffmatch.lidar.ground import GroundConfig, _centred_rows, segment_ground
from tests.lidar.scene import make_scene


@pytest.mark.parametrize("seed", range(4))
def test_centred_rows_are_numpys_mean_and_difference(seed: int) -> None:
    """Bit for bit ``P[idx].mean(axis=0)`` and ``P[idx] - mean`` (the extractor's ground
    landmark and its rms are made of them), on clouds of any size, scale and sign."""
    rng = np.random.default_rng(seed)
    for n in (3, 7, 8, 9, 1000, 60000):
        P = rng.normal(size=(n + 40, 3)) * rng.choice([1e-3, 1.0, 80.0])
        P[:5] = [[-0.0, 0.0, -0.0], [1e-300, -1e-300, 0.0], [3.0, -3.0, 1e15], [-1e15, 2.0, 0.5], [0.1, 0.2, 0.3]]
        idx = np.sort(rng.choice(n + 40, n, replace=False))
        c, D = _centred_rows(P, idx)
        want_c = P[idx].mean(axis=0)
        assert c.tobytes() == want_c.tobytes()
        assert D.flags.c_contiguous and D.tobytes() == (P[idx] - want_c).tobytes()


def test_segment_ground_keeps_the_centred_support() -> None:
    """segment_ground's centroid, rms and centred inliers are what numpy computes from its inliers."""
    P = make_scene(0).points[:, :3].astype(np.float64)
    g = segment_ground(P, GroundConfig())
    assert g.normal is not None and g.plane_inliers.size >= 200
    S = P[g.plane_inliers]
    assert g.centroid.tobytes() == S.mean(axis=0).tobytes()
    assert g.centred_inliers.tobytes() == (S - g.centroid).tobytes()
    assert g.rms == float(np.sqrt(np.mean(((S - S.mean(axis=0)) @ g.normal) ** 2)))
