"""LandmarkExtractor on synthetic scenes with known poles and planes, and on bad input.

Tolerances stated: direction / normal angle < 1 deg, pole axis to anchor < 5 cm, plane offset
< 5 cm (1 cm point noise, ~0.1-0.3 m voxels).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.geometry.transforms import make_transform, rot_z, transform_points
from graffmatch.lidar import LandmarkExtractor, LandmarkExtractorConfig, PoleConfig
from graffmatch.lidar._stats import subsample_groups
from tests.lidar.scene import make_scene

ANGLE_TOL_DEG = 1.0
POS_TOL_M = 0.05


@pytest.fixture(scope="module")
def scene():
    return make_scene(seed=1)


@pytest.fixture(scope="module")
def extracted(scene):
    ex = LandmarkExtractor()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean scene must not warn
        geo = ex.extract(scene.points)
        sem = ex.extract(scene.points, scene.labels)
    return geo, sem


def _angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(abs(float(u @ v)), 0.0, 1.0))))


def _match_poles(ls: LandmarkSet, truth) -> list[tuple[float, float]]:
    lines = ls.of_type(LandmarkType.LINE)
    out = []
    for p, d in truth:
        # distance from each detected anchor to the true axis
        q = lines.anchors - p
        dist = np.linalg.norm(q - np.outer(q @ d, d), axis=1)
        j = int(np.argmin(dist))
        out.append((float(dist[j]), _angle_deg(lines.directions[j], d)))
    return out


@pytest.mark.parametrize("mode", [0, 1], ids=["geometric", "semantic"])
def test_poles_recovered(extracted, scene, mode: int) -> None:
    ls = extracted[mode]
    assert ls.counts()["lines"] == len(scene.poles)
    for dist, ang in _match_poles(ls, scene.poles):
        assert dist < POS_TOL_M
        assert ang < ANGLE_TOL_DEG
    lines = ls.of_type(LandmarkType.LINE)
    np.testing.assert_allclose(lines.attributes["radius"], 0.12, atol=0.03)
    assert np.all(lines.attributes["extent"] > 3.0)


def test_planes_recovered_and_split_wall_merged(extracted, scene) -> None:
    ls = extracted[0]
    planes = ls.of_type(LandmarkType.PLANE)
    hesse = planes.hesse()
    truth = [*scene.walls, scene.ground]
    # the wall split by a door gap must be ONE landmark: one plane per true plane exactly
    assert len(planes) == len(truth)
    for n, d in truth:
        cosines = hesse[:, :3] @ n
        ang = np.degrees(np.arccos(np.clip(np.abs(cosines), 0, 1)))
        off_err = np.abs(np.sign(cosines) * hesse[:, 3] - d)
        j = int(np.argmin(off_err + 1e3 * (ang > ANGLE_TOL_DEG)))  # parallel walls: use offset
        assert ang[j] < ANGLE_TOL_DEG
        assert off_err[j] < POS_TOL_M
    ground = planes[np.flatnonzero(planes.attributes["is_ground"] > 0)]
    assert len(ground) == 1 and abs(ground.hesse()[0, 3] + 1.7) < POS_TOL_M


def test_support_points_capped_and_on_landmark(extracted) -> None:
    ls = extracted[0]
    cap = LandmarkExtractorConfig().max_points_per_landmark
    counts = np.diff(ls.point_offsets)
    assert np.all(counts > 0) and np.all(counts <= cap)
    for i in range(len(ls)):
        P = ls.support_points(i).astype(float) - ls.anchors[i]
        A = ls.bases[i, :, : ls.types[i]]
        resid = np.linalg.norm(P - P @ A @ A.T, axis=1)
        tol = 0.3 if ls.types[i] == LandmarkType.LINE else 0.2
        assert np.percentile(resid, 95) < tol


def test_whole_scan_ranges_kept_with_the_support(extracted, scene) -> None:
    """Every in-range return leaves its nearest range in its 1 deg cell (what verification's
    free-space check reads), including the returns no landmark owns; the option turns it off."""
    from graffmatch.verification.free_space import cell_minimum_ranges

    ls = extracted[0]
    assert ls.scan_ranges is not None and ls.scan_ranges.shape == (360, 180)
    P = scene.points[:, :3]
    r = np.hypot(P[:, 0], P[:, 1])
    cfg = LandmarkExtractorConfig()
    keep = (np.linalg.norm(P, axis=1) >= cfg.min_range) & (np.linalg.norm(P, axis=1) <= cfg.max_range)
    want = cell_minimum_ranges(P[keep])
    np.testing.assert_allclose(ls.scan_ranges, want, rtol=1e-6)
    owned = np.isfinite(cell_minimum_ranges(ls.points))
    assert np.isfinite(ls.scan_ranges).sum() > owned.sum()  # more cells than the support points reach
    assert np.nanmin(np.where(np.isfinite(ls.scan_ranges), ls.scan_ranges, np.nan)) >= r[keep].min() - 1e-4
    off = LandmarkExtractor(LandmarkExtractorConfig(scan_ranges=False)).extract(scene.points)
    assert off.scan_ranges is None and len(off) == len(ls)


def test_deterministic(scene) -> None:
    a = LandmarkExtractor().extract(scene.points)
    b = LandmarkExtractor().extract(scene.points)
    np.testing.assert_array_equal(a.anchors, b.anchors)
    np.testing.assert_array_equal(a.bases, b.bases)
    np.testing.assert_array_equal(a.points, b.points)


@settings(max_examples=4, deadline=None)
@given(yaw=st.floats(-np.pi, np.pi), tx=st.floats(-2, 2), ty=st.floats(-2, 2))
def test_equivariant_to_rigid_motion(scene, yaw: float, tx: float, ty: float) -> None:
    """extract(T P) equals T extract(P) up to the tolerances (planes and poles)."""
    T = make_transform(rot_z(yaw), np.array([tx, ty, 0.0]))
    ex = LandmarkExtractor()
    base = ex.extract(scene.points).transform(T)
    moved_pts = scene.points.copy()
    moved_pts[:, :3] = transform_points(T, scene.points[:, :3].astype(float))
    moved = ex.extract(moved_pts)
    assert moved.counts() == base.counts()
    for t in (LandmarkType.LINE, LandmarkType.PLANE):
        A, B = base.of_type(t), moved.of_type(t)
        for i in range(len(A)):
            q = B.anchors - A.anchors[i]
            d = A.directions[i]
            off = np.linalg.norm(q - np.outer(q @ d, d), axis=1) if t == 1 else np.abs(q @ d)
            ang = np.degrees(np.arccos(np.clip(np.abs(B.directions @ d), 0, 1)))
            ok = (off < POS_TOL_M) & (ang < ANGLE_TOL_DEG)
            assert ok.any(), f"type {t} landmark {i} not reproduced"


def test_huge_coordinates(scene) -> None:
    """A georeferenced cloud (1e6 m offsets, float64) gives the same landmarks, shifted."""
    offset = np.array([4.5e6, 5.2e5, 120.0])
    P = scene.points[:, :3].astype(np.float64) + offset
    ex = LandmarkExtractor(LandmarkExtractorConfig(min_range=0.0))
    near = LandmarkExtractor(LandmarkExtractorConfig(min_range=0.0)).extract(scene.points)
    far = ex.extract(P)
    assert far.counts() == near.counts()
    np.testing.assert_allclose(far.anchors - offset, near.anchors, atol=1e-6)


def test_subsample_groups_even_stride() -> None:
    labels = np.array([0] * 10 + [1] * 3 + [-1] * 4 + [2] * 5)
    idx, offs = subsample_groups(labels, np.array([2, 0]), cap=4)
    np.testing.assert_array_equal(offs, [0, 4, 8])
    assert set(labels[idx[:4]]) == {2} and set(labels[idx[4:]]) == {0}
    np.testing.assert_array_equal(idx[4:], [0, 3, 5, 8])  # floor(p*4/10) steps


# ------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------
def test_empty_cloud_warns_and_returns_empty() -> None:
    with pytest.warns(RuntimeWarning, match="valid points"):
        ls = LandmarkExtractor().extract(np.zeros((0, 4), np.float32))
    assert len(ls) == 0


def test_nan_inf_rows_dropped_with_warning(scene) -> None:
    P = scene.points.copy()
    P[::97, 0] = np.nan
    P[5::97, 2] = np.inf
    clean = P[np.all(np.isfinite(P[:, :3]), axis=1)]
    with pytest.warns(RuntimeWarning, match="NaN/Inf"):
        got = LandmarkExtractor().extract(P)
    ref = LandmarkExtractor().extract(clean)
    np.testing.assert_array_equal(got.anchors, ref.anchors)
    with pytest.warns(RuntimeWarning):
        assert len(LandmarkExtractor().extract(np.full((100, 3), np.nan))) == 0


def test_structureless_cloud_gives_empty_set_with_warning(rng) -> None:
    P = rng.uniform(-20, 20, size=(20000, 3))  # a fog of points: no pole, no plane
    with pytest.warns(RuntimeWarning, match="no pole or plane"):
        ls = LandmarkExtractor().extract(P)
    assert len(ls) == 0


def test_tiny_cloud_warns() -> None:
    P = np.random.default_rng(0).normal(scale=1e-5, size=(500, 3)) + np.array([5.0, 0, 0])
    with pytest.warns(RuntimeWarning, match="min_extent"):
        assert len(LandmarkExtractor().extract(P)) == 0


@pytest.mark.parametrize(
    "points,labels,match",
    [
        (np.zeros((10, 2)), None, "shape"),
        (np.zeros(10), None, "shape"),
        (np.array([["a", "b", "c"]]), None, "numeric"),
        (np.zeros((10, 3)), np.zeros(9, np.uint32), "9 labels for 10"),
        (np.zeros((10, 3)), np.zeros(10, float), "integers"),
    ],
)
def test_invalid_input_raises(points, labels, match) -> None:
    with pytest.raises(InvalidInputError, match=match):
        LandmarkExtractor().extract(points, labels)


def test_semantic_mode_requires_labels(scene) -> None:
    cfg = LandmarkExtractorConfig(poles=PoleConfig(mode="semantic"))
    with pytest.raises(InvalidInputError, match="needs labels"):
        LandmarkExtractor(cfg).extract(scene.points)


def test_config_rejects_unknown_and_bad_values() -> None:
    with pytest.raises(ValueError):
        LandmarkExtractorConfig(max_range=-1)
    with pytest.raises(ValueError):
        LandmarkExtractorConfig(poles={"not_a_field": 1})
    a, b = LandmarkExtractorConfig(), LandmarkExtractorConfig(poles={"min_length": 2.0})
    assert a.config_hash() != b.config_hash()


@settings(max_examples=15, deadline=None)
@given(
    tilt=st.floats(0.0, 10.0),
    azimuth=st.floats(0.0, 360.0),
    radius=st.floats(0.05, 0.3),
    x=st.floats(4.0, 30.0),
    y=st.floats(-30.0, 30.0),
    seed=st.integers(0, 2**16),
)
def test_semantic_pole_fit_property(tilt, azimuth, radius, x, y, seed) -> None:
    """Any labelled, tilted (<= 10 deg) pole is recovered: axis within 1 deg (or 5 sigma of the
    sampling noise for thick poles), anchor on the axis within 5 cm, radius within 30%."""
    rng = np.random.default_rng(seed)
    t, a = np.radians(tilt), np.radians(azimuth)
    d = np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)])
    u = np.cross(d, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    n = 600
    s = rng.uniform(0, 5.0, n)
    ang = rng.uniform(0, 2 * np.pi, n)
    base = np.array([x, y, -1.7])
    pts = base + s[:, None] * d + radius * (np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * v)
    pts += rng.normal(scale=0.005, size=pts.shape)
    cfg = LandmarkExtractorConfig(
        poles=PoleConfig(mode="semantic"), planes={"enabled": False}, ground={"enabled": False}
    )
    ls = LandmarkExtractor(cfg).extract(pts, np.full(n, 80, np.uint32))
    assert ls.counts()["lines"] == 1
    q = ls.anchors[0] - base
    assert np.linalg.norm(q - (q @ d) * d) < POS_TOL_M
    # PCA tilt from sampling a thick cylinder has std ~ (r/sqrt 2) / (L/sqrt 12) / sqrt(n)
    # (0.34 deg for r = 0.3 m, L = 5 m, n = 600): allow 5 sigma when that exceeds 1 deg.
    sampling_deg = np.degrees(radius / np.sqrt(2) / (5.0 / np.sqrt(12)) / np.sqrt(n))
    assert _angle_deg(ls.directions[0], d) < max(ANGLE_TOL_DEG, 5 * sampling_deg)
    assert abs(ls.attributes["radius"][0] - radius) < 0.3 * radius + 0.01


def test_support_point_cap_zero_and_small(scene) -> None:
    for cap in (0, 5):
        cfg = LandmarkExtractorConfig(max_points_per_landmark=cap)
        ls = LandmarkExtractor(cfg).extract(scene.points)
        counts = np.diff(ls.point_offsets)
        assert len(ls) == 10 and np.all(counts == cap)


def test_ground_outliers_and_kerb_do_not_duplicate_ground(scene) -> None:
    """Multipath points below the road and a 12 cm sidewalk must not become extra horizontal
    planes next to the ground landmark (they would be ambiguous landmarks)."""
    rng = np.random.default_rng(7)
    below = np.column_stack([rng.uniform(-25, 25, (300, 2)), np.full(300, -2.9)])
    kerb = np.column_stack(
        [rng.uniform(4, 14, 4000), rng.uniform(-8, -5, 4000), np.full(4000, -1.58)]
    )
    extra = np.concatenate([below, kerb])
    pts = np.concatenate([scene.points[:, :3], extra]).astype(np.float32)
    ls = LandmarkExtractor().extract(pts)
    planes = ls.of_type(LandmarkType.PLANE)
    horizontal = np.abs(planes.directions[:, 2]) > np.cos(np.radians(10))
    assert horizontal.sum() == 1  # the ground landmark only
    ground = planes[np.flatnonzero(horizontal)]
    assert ground.attributes["is_ground"][0] == 1
    assert abs(ground.hesse()[0, 3] + 1.7) < 0.05
    assert ls.counts()["lines"] == len(scene.poles)
