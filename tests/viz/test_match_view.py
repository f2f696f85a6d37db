"""The interactive match view: geometry of the drawn primitives and the self-contained HTML."""

from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.viz.match_view import (
    DEFAULT_POLE_LENGTH,
    downsample,
    match_figure,
    plane_quads,
    pole_segments,
    write_match_view,
)


def test_pole_segments_span_the_support_points(scene):
    idx, s, e = pole_segments(scene.target)
    assert len(idx) == 8
    for k, i in enumerate(idx):
        P = scene.target.support_points(i)
        # the poles stand on z=0 and are 5 m tall: the segment spans the support heights
        lo, hi = sorted([s[k, 2], e[k, 2]])
        assert lo == pytest.approx(P[:, 2].min(), abs=0.05)
        assert hi == pytest.approx(P[:, 2].max(), abs=0.05)


def test_pole_segments_fall_back_to_extent_and_default():
    ls = LandmarkSet.from_arrays(
        [1, 1], [[0, 0, 1], [1, 0, 0]], [[0, 0, 0], [5, 5, 5]], {"extent": np.array([4.0, np.nan])}
    )
    _, s, e = pole_segments(ls)
    lengths = np.linalg.norm(e - s, axis=1)
    np.testing.assert_allclose(lengths, [4.0, DEFAULT_POLE_LENGTH])
    np.testing.assert_allclose((s + e) / 2, ls.anchors)  # centred on the anchor


def test_plane_quads_lie_on_the_planes_and_cover_the_support(scene):
    ls = scene.source  # a transformed set: bases are rotated, not axis aligned
    idx, corners = plane_quads(ls)
    assert len(idx) == 6
    n = ls.directions[idx]
    d = np.einsum("ij,ij->i", n, ls.anchors[idx])
    dist = np.einsum("ikj,ij->ik", corners, n) - d[:, None]
    assert np.abs(dist).max() < 1e-9  # corners on the plane
    for k, i in enumerate(idx):
        P = ls.support_points(i).astype(float)
        # every support point projects inside the rectangle (within rounding)
        c0, c1, c3 = corners[k, 0], corners[k, 1], corners[k, 3]
        u, v = c1 - c0, c3 - c0
        a = (P - c0) @ u / (u @ u)
        b = (P - c0) @ v / (v @ v)
        assert a.min() > -1e-4 and a.max() < 1 + 1e-4
        assert b.min() > -1e-4 and b.max() < 1 + 1e-4
    # facade 8 m x ~6 m: area matches the support to a few percent
    areas = np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 3] - corners[:, 0]), axis=1
    )
    assert areas[:5] == pytest.approx(np.full(5, 48.0), rel=0.03)


def test_plane_quads_without_points_stand_upright():
    # a wall with normal +x: box 8 m x 3 m -> the 8 m side is horizontal, the 3 m side vertical
    ls = LandmarkSet.from_arrays([2], [[1, 0, 0]], [[5, 0, 1.5]], {"box": np.array([[3.0, 8.0]])})
    _, corners = plane_quads(ls)
    c = corners[0]
    np.testing.assert_allclose(np.ptp(c[:, 1]), 8.0)
    np.testing.assert_allclose(np.ptp(c[:, 2]), 3.0)
    np.testing.assert_allclose(c[:, 0], 5.0)


def test_plane_quads_use_box_without_points():
    ls = LandmarkSet.from_arrays([2], [[0, 0, 1]], [[1, 2, 3]], {"box": np.array([[6.0, 2.0]])})
    _, corners = plane_quads(ls)
    sides = np.linalg.norm(np.diff(corners[0], axis=0, append=corners[0][:1]), axis=1)
    np.testing.assert_allclose(sorted(sides), [2, 2, 6, 6])
    np.testing.assert_allclose(corners[0].mean(axis=0), [1, 2, 3])


@given(n=st.integers(0, 5000), cap=st.integers(1, 3000), seed=st.integers(0, 5))
def test_downsample_is_bounded_deterministic_and_a_subset(n, cap, seed):
    P = np.arange(n * 4, dtype=np.float32).reshape(n, 4)
    a = downsample(P, cap, seed)
    b = downsample(P, cap, seed)
    assert a.shape == (min(n, cap), 3)
    np.testing.assert_array_equal(a, b)
    if len(a):
        assert np.isin(a[:, 0], P[:, 0]).all()


def test_downsample_drops_non_finite_rows():
    P = np.array([[0, 0, 0], [np.nan, 1, 1], [1, 1, np.inf], [2, 2, 2]], np.float32)
    assert downsample(P, 10).tolist() == [[0, 0, 0], [2, 2, 2]]


def test_figure_states_and_correspondences(scene):
    fig = match_figure(
        scene.source,
        scene.target,
        scene.T_target_source,
        scene.associations,
        scene.source_points,
        scene.target_points,
        scene.inlier_mask,
    )
    buttons = fig.layout.updatemenus[0].buttons
    assert [b.label.split(":")[0] for b in buttons] == ["After", "Before", "Before"]
    vis = np.array([b.args[0]["visible"] for b in buttons])
    assert vis.shape == (3, len(fig.data))
    always = vis.all(axis=0)
    assert any("target scan" == fig.data[i].name for i in np.flatnonzero(always))
    # each source trace belongs to exactly one state
    assert np.all(vis[:, ~always].sum(axis=0) == 1)
    # initial visibility = the "after" button
    np.testing.assert_array_equal([bool(t.visible) for t in fig.data], vis[0])
    by_state = {}
    for s in range(3):
        for i in np.flatnonzero(vis[s] & ~always):
            by_state.setdefault(s, {})[fig.data[i].name.split(" (")[0]] = fig.data[i]
    inl = by_state[0]["inliers"]
    seg = np.c_[inl.x, inl.y, inl.z].reshape(-1, 3, 3)[:, :2]
    # after alignment by the true transform the inlier lines have zero length ...
    assert np.linalg.norm(seg[:, 0] - seg[:, 1], axis=1).max() < 1e-6
    assert by_state[0]["outliers"].name == "outliers (1)"
    assert by_state[0]["outliers"].text[0] == "association 3: source #3 ↔ target #5"
    # ... and before alignment they span the 14 m / 180 deg offset
    seg_raw = np.c_[by_state[1]["inliers"].x, by_state[1]["inliers"].y, by_state[1]["inliers"].z]
    seg_raw = seg_raw.reshape(-1, 3, 3)[:, :2]
    assert np.linalg.norm(seg_raw[:, 0] - seg_raw[:, 1], axis=1).max() > 10
    # side by side: the source scan lies entirely beyond the target along y
    src_side = by_state[2]["source scan"]
    assert np.min(src_side.y) > np.max(fig.data[0].y)


def test_write_match_view_is_one_offline_file(scene, tmp_path):
    path = write_match_view(
        tmp_path / "sub" / "view.html",
        scene.source,
        scene.target,
        scene.T_target_source,
        scene.associations,
        scene.source_points,
        scene.target_points,
        scene.inlier_mask,
        title="test view",
        info={"inliers": 13},
    )
    html = path.read_text()
    assert path.stat().st_size > 3_000_000  # plotly.js is embedded
    assert not re.search(r"<script[^>]+src=", html)  # no external scripts (no CDN)
    assert not re.search(r"<link[^>]+href=[\"']https?:", html)  # no external stylesheets
    assert "test view" in html and "data-graffmatch-rendered" in html


def test_view_without_points_or_associations(scene, tmp_path):
    path = write_match_view(
        tmp_path / "v.html",
        scene.source.without_points(),
        scene.target.without_points(),
        np.eye(4),
        np.zeros((0, 2), int),
    )
    assert path.is_file()


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"associations": np.array([[0, 99]])}, "beyond"),
        ({"inlier_mask": np.ones(3, bool)}, "inlier_mask"),
        ({"T_target_source": np.diag([1.0, 1.0, -1.0, 1.0])}, "SO"),
        ({"source_points": np.zeros((5, 2))}, "points"),
    ],
)
def test_bad_input_raises_clear_errors(scene, kwargs, match):
    args = {
        "source_landmarks": scene.source,
        "target_landmarks": scene.target,
        "T_target_source": scene.T_target_source,
        "associations": scene.associations,
    }
    args.update(kwargs)
    with pytest.raises(InvalidInputError, match=match):
        match_figure(**args)


def test_point_landmarks_are_drawn():
    ls = LandmarkSet.from_arrays([0, 0], np.zeros((2, 3)), [[0, 0, 0], [1, 1, 1]])
    fig = match_figure(ls, ls, np.eye(4), [[0, 0], [1, 1]])
    names = [t.name for t in fig.data]
    assert "target points (2)" in names and "source points (2)" in names
    assert int(np.sum(ls.types == LandmarkType.POINT)) == 2
