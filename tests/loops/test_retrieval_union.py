"""The descriptor+radius retriever: the descriptor's top-k, then the scans near the odometry
estimate within a radius that grows with the odometry path between the two scans."""

from __future__ import annotations

import numpy as np
import pytest

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.loops import LandmarkDatabase, RetrievalConfig, eligible_count, make_retriever


def _ls() -> LandmarkSet:
    return LandmarkSet.from_arrays([LandmarkType.LINE] * 2, np.tile([0.0, 0.0, 1.0], (2, 1)),
                                   np.array([[1.0, 0, 0], [0, 1.0, 0]]), {})


def _drive(positions: bool = True) -> tuple[LandmarkDatabase, np.ndarray]:
    """200 scans 1 m apart around a 100 m ring (scan i + 100 passes scan i again), random descriptors."""
    rng = np.random.default_rng(3)
    X = rng.standard_normal((200, 8)).astype(np.float32)
    a = 2 * np.pi * np.arange(200) / 100
    P = np.c_[15.9 * np.cos(a), 15.9 * np.sin(a), np.zeros(200)]
    db = LandmarkDatabase()
    for i in range(200):
        db.add(_ls(), X[i], float(i), P[i] if positions else None)
    return db, X


def test_union_adds_the_scans_near_the_odometry_estimate_after_the_descriptor_top_k() -> None:
    db, X = _drive()
    q = 150
    desc = make_retriever(RetrievalConfig(method="descriptor", top_k=5, exclude_seconds=20.0))
    m = eligible_count(db.timestamps, q, desc.config)
    top, _ = desc.candidates(db, q, m)
    union = make_retriever(RetrievalConfig(method="descriptor+radius", top_k=5, exclude_seconds=20.0, union_radius_m=2.5,
                                           drift_fraction=0.0))
    idx, dist = union.candidates(db, q, m)
    assert idx[:5].tolist() == top.tolist()  # the descriptor's ranks come first, unchanged
    extra = idx[5:].tolist()
    # scans within 2.5 m of scan 150's position among the eligible ones: 48-52 (1 m apart on the ring)
    assert sorted(extra) == sorted(set(range(48, 53)) - set(top.tolist()))
    assert extra[0] == 50  # nearest first
    np.testing.assert_allclose(dist[5:], np.linalg.norm(X[extra] - X[q], axis=1), rtol=1e-6)
    # the drift term: 2 % of the ~100 m travelled since scans 48-52 widens 2.5 m to ~4.5 m
    wide = make_retriever(RetrievalConfig(method="descriptor+radius", top_k=20, exclude_seconds=20.0,
                                          union_radius_m=2.5, drift_fraction=0.02))
    idx_w, _ = wide.candidates(db, q, m)
    near = set(idx_w.tolist()) - set(wide._desc.candidates(db, q, m)[0].tolist())
    assert set(range(46, 55)) - set(idx_w.tolist()) == set()
    assert all(abs(j - 50) <= 4 for j in near)


def test_union_without_positions_is_the_descriptor_retriever() -> None:
    db, _ = _drive(positions=False)
    cfg = RetrievalConfig(method="descriptor+radius", top_k=5, exclude_seconds=20.0)
    m = eligible_count(db.timestamps, 150, cfg)
    idx, _ = make_retriever(cfg).candidates(db, 150, m)
    ref, _ = make_retriever(RetrievalConfig(method="descriptor", top_k=5, exclude_seconds=20.0)).candidates(db, 150, m)
    assert idx.tolist() == ref.tolist()


def test_union_with_some_positions_missing_names_them() -> None:
    db, _ = _drive()
    db.positions[10] = None
    cfg = RetrievalConfig(method="descriptor+radius", top_k=5, exclude_seconds=20.0)
    with pytest.raises(InvalidInputError, match="positions"):
        make_retriever(cfg).candidates(db, 150, eligible_count(db.timestamps, 150, cfg))


def test_the_default_is_the_union_chosen_on_the_calibration_drives() -> None:
    cfg = RetrievalConfig()
    assert (cfg.method, cfg.union_radius_m, cfg.drift_fraction, cfg.top_k) == ("descriptor+radius", 5.0, 0.02, 20)
    assert cfg.radius_m == 10.0  # the plain radius retriever keeps its own radius
