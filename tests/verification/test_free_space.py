"""Free-space evidence: points put in front of what the other sensor saw through conflict;
points behind it (occluded) or in cells without a return (unknown) do not."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from graffmatch.geometry.transforms import random_transform
from graffmatch.verification.free_space import RangeImage, conflict_fraction


def _wall(x: float, half_width: float = 5.0, step: float = 0.1) -> np.ndarray:
    """A wall facing the sensor at distance x (y in [-w, w], z in [-1, 2])."""
    y, z = np.meshgrid(np.arange(-half_width, half_width, step), np.arange(-1.0, 2.0, step))
    return np.c_[np.full(y.size, x), y.ravel(), z.ravel()]


def test_points_in_front_of_a_wall_conflict_and_behind_it_do_not() -> None:
    img = RangeImage.from_points(_wall(10.0))
    front = np.c_[np.full(50, 5.0), np.linspace(-1, 1, 50), np.zeros(50)]  # where the beams passed
    behind = front * np.array([3.0, 3.0, 1.0])  # 15 m: hidden by the wall
    near_wall = front * np.array([1.96, 1.96, 1.0])  # 9.8 m: within the 1 m margin
    assert img.conflicts(front, margin=1.0) == (50, 50)
    assert img.conflicts(behind, margin=1.0) == (0, 50)
    assert img.conflicts(near_wall, margin=1.0) == (0, 50)


def test_cells_without_a_return_are_unknown_not_free() -> None:
    img = RangeImage.from_points(_wall(10.0))  # the wall spans about +-27 deg of azimuth
    side = np.c_[np.zeros(20), np.full(20, 5.0), np.linspace(-0.5, 0.5, 20)]  # 90 deg: no return there
    assert img.conflicts(side, margin=1.0) == (0, 0)


def test_a_thin_pole_shadows_the_neighbouring_beams() -> None:
    """A 0.3 m pole at 20 m seen in one cell: a point 1 cell aside at the pole's range is not
    judged free (the neighbourhood minimum), one far aside is."""
    bg = _wall(40.0, half_width=20.0, step=0.2)
    z = np.arange(-1.0, 2.0, 0.1)
    pole = np.c_[np.full(z.size, 20.0), np.zeros(z.size), z]
    img = RangeImage.from_points(np.r_[bg, pole])
    beside = np.array([[20.0, 20.0 * np.tan(np.radians(1.2)), 0.5]])
    far_aside = np.array([[20.0, 20.0 * np.tan(np.radians(8.0)), 0.5]])
    assert img.conflicts(beside, margin=1.0)[0] == 0
    assert img.conflicts(far_aside, margin=1.0)[0] == 1


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_the_true_transform_of_one_scene_has_no_conflict(seed: int) -> None:
    """Two views of the same walls (one moved by a random planar motion): the true transform
    conflicts with nothing, a 90 deg turn of it with a large share."""
    rng = np.random.default_rng(seed)
    scene = np.r_[_wall(12.0), _wall(-9.0), _wall(15.0)[:, [1, 0, 2]], _wall(-11.0)[:, [1, 0, 2]]]
    T = random_transform(rng, max_translation=2.0)
    yaw = rng.uniform(-np.pi, np.pi)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    T[2, 3] = 0.0
    target = scene
    source = (scene - T[:3, 3]) @ T[:3, :3]  # the scene in the source sensor's frame
    img_s, img_t = RangeImage.from_points(source), RangeImage.from_points(target)
    c_st, c_ts = conflict_fraction(source, target, img_s, img_t, T, margin=1.0)
    assert max(c_st, c_ts) < 0.02
    turn = np.eye(4)
    turn[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    w_st, w_ts = conflict_fraction(source, target, img_s, img_t, turn @ T, margin=1.0)
    assert max(w_st, w_ts) > 0.2


def test_the_sensor_pose_moves_with_the_set_and_survives_files(tmp_path) -> None:
    from graffmatch.geometry.landmarks import LandmarkSet

    rng = np.random.default_rng(3)
    ls = LandmarkSet.from_arrays([1, 2], rng.normal(size=(2, 3)), rng.normal(size=(2, 3)),
                                 points=rng.normal(size=(6, 3)), point_offsets=[0, 3, 6])
    assert np.array_equal(ls.sensor_pose, np.eye(4))  # a scan's own frame
    T = random_transform(rng, max_translation=50.0)
    moved = ls.transform(T)
    assert np.allclose(moved.sensor_pose, T, atol=1e-12)
    assert np.allclose(moved[[1]].sensor_pose, T) and np.allclose(moved.without_points().sensor_pose, T)
    back = LandmarkSet.load(moved.save(tmp_path / "m.npz", include_points=True))
    assert np.allclose(back.sensor_pose, T, atol=1e-12)
    assert np.array_equal(LandmarkSet.load(ls.save(tmp_path / "o.npz")).sensor_pose, np.eye(4))
    merged = LandmarkSet.concatenate([ls, moved])  # two viewpoints: a map
    assert merged.sensor_pose is None
    assert LandmarkSet.load(merged.save(tmp_path / "map.npz")).sensor_pose is None
    assert LandmarkSet.concatenate([ls, ls[[0]]]).sensor_pose is not None


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_conflict_is_invariant_to_moving_either_frame(seed: int) -> None:
    """Moving the source set (and its sensor) by X and the hypothesis by X^-1 changes nothing."""
    from graffmatch.geometry.landmarks import LandmarkSet
    from graffmatch.geometry.transforms import invert
    from graffmatch.verification.evidence import SupportCloud, support_cloud

    rng = np.random.default_rng(seed)
    walls = np.r_[_wall(12.0), _wall(-9.0), _wall(15.0)[:, [1, 0, 2]]]
    n = len(walls) // 3
    ls = LandmarkSet.from_arrays([2, 2, 2], np.eye(3), walls[[0, n, 2 * n]], points=walls,
                                 point_offsets=[0, n, 2 * n, len(walls)])
    X = random_transform(rng, max_translation=100.0)
    T = random_transform(rng, max_translation=3.0)
    a = support_cloud(ls)

    def move(P: np.ndarray) -> np.ndarray:
        return P @ X[:3, :3].T + X[:3, 3]

    # the same evidence points, moved (voxel downsampling itself depends on the frame's axes)
    b = SupportCloud(move(a.points), free_points=move(a.free_points), sensor_pose=X @ a.sensor_pose)
    img = a.range_image(1.0, 1.0, 1)
    img_b = b.range_image(1.0, 1.0, 1)
    c1 = conflict_fraction(a.points, a.points, img, img, T, 1.0, 0.05, a.sensor_pose, a.sensor_pose)
    c2 = conflict_fraction(b.points, a.points, img_b, img, T @ invert(X), 1.0, 0.05, b.sensor_pose, a.sensor_pose)
    assert abs(c1[0] - c2[0]) < 1e-9 and abs(c1[1] - c2[1]) < 1e-9


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(0, 400),
       st.sampled_from([(1.0, 1.0, 1.0, 2.0), (2.0, 2.0, 4.0, 6.0), (1.0, 1.0, 5.0, 5.0)]), st.integers(0, 2))
def test_whole_scan_cell_minima_equal_the_points_image(seed: int, n: int, cells: tuple, nb: int) -> None:
    """The stored per-cell nearest returns, pooled to a coarser grid and min-filtered, give the
    very image the points give at that grid (NaN points skipped)."""
    from graffmatch.verification.free_space import cell_minimum_ranges

    az, el, az2, el2 = cells
    rng = np.random.default_rng(seed)
    P = rng.normal(scale=15.0, size=(n, 3))
    P[: n // 5, 2] = rng.choice([-1e3, 1e3], n // 5)  # the top and bottom elevation rows
    if n > 3:
        P[1] = [np.nan, 1.0, 0.0]
    minima = cell_minimum_ranges(P, az, el)
    assert minima.shape == (int(360 / az), int(180 / el)) and minima.dtype == np.float32
    want = RangeImage.from_points(P, az2, el2, nb).ranges.astype(np.float32)
    got = RangeImage.from_cell_minima(minima, az2, el2, nb)
    np.testing.assert_array_equal(got.ranges.astype(np.float32), want)
    assert RangeImage.from_cell_minima(minima, 1.5 * az, el) is None  # not a multiple: no image


def test_an_object_without_a_landmark_still_blocks_the_beams() -> None:
    """The target scan sees a tree trunk 10 m ahead of a wall at 20 m but makes no landmark of
    it; the source (same place) has the trunk as a pole. The target's support points alone call
    the trunk's points free space (the false conflict that failed right sim-downtown matches);
    its whole-scan image knows the beams stopped at the trunk."""
    from graffmatch.geometry.landmarks import LandmarkSet
    from graffmatch.verification.evidence import support_cloud
    from graffmatch.verification.free_space import cell_minimum_ranges

    wall = _wall(20.0, half_width=12.0, step=0.1)
    ang = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    z = np.arange(-1.5, 2.0, 0.1)
    trunk = np.c_[(10.0 + 0.2 * np.cos(ang))[:, None].repeat(len(z), 1).ravel(),
                  (0.2 * np.sin(ang))[:, None].repeat(len(z), 1).ravel(), np.tile(z, len(ang))]
    scan = np.r_[wall, trunk]
    n = len(wall)
    target = LandmarkSet.from_arrays([2], [[1.0, 0, 0]], [[20.0, 0, 0]], points=wall, point_offsets=[0, n])
    source = LandmarkSet.from_arrays([2, 1], [[1.0, 0, 0], [0, 0, 1.0]], [[20.0, 0, 0], [10.0, 0, 0]],
                                     points=scan, point_offsets=[0, n, len(scan)])
    s = support_cloud(source)
    t_sparse = support_cloud(target)
    target.scan_ranges = cell_minimum_ranges(scan)
    t_full = support_cloud(target)
    T = np.eye(4)
    img_s = s.range_image(1.0, 1.0, 1)
    sparse, _ = conflict_fraction(s.points, t_sparse.points, img_s, t_sparse.range_image(1.0, 1.0, 1), T, 1.0, 0.1)
    full, _ = conflict_fraction(s.points, t_full.points, img_s, t_full.range_image(1.0, 1.0, 1, 0), T, 1.0, 0.1)
    assert sparse > 0.02 and full == 0.0  # the trunk is ~3 % of the evidence points
    shifted = np.eye(4)
    shifted[0, 3] = -8.0  # a wrong translation: the source's wall 8 m in front of the target's
    wrong, _ = conflict_fraction(s.points, t_full.points, img_s, t_full.range_image(1.0, 1.0, 1, 0), shifted, 1.0, 0.1)
    assert wrong > 0.8


def test_whole_scan_cell_minima_at_the_poles_origin_and_far_out() -> None:
    """The compiled binning (elevation by boundary tangents) agrees with the angle formula where
    it has no ratio: straight up and down, the sensor's own position, overflowing squares."""
    import warnings

    from graffmatch.verification.free_space import cell_minimum_ranges

    P = np.array([[1e200, 1e200, 5.0], [3e300, -2e300, 1e300], [0.0, 0.0, 0.0], [0.0, 0.0, 5.0],
                  [0.0, 0.0, -5.0], [np.nan, 1.0, 1.0], [10.0, 0.0, 10.0 * np.tan(np.radians(-12.0))]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # float32 of 1e200 ranges: inf, in both
        want = RangeImage._from_points_reference(P, 1.0, 1.0, 0).ranges.astype(np.float32)
    np.testing.assert_array_equal(cell_minimum_ranges(P), want)


def _cell_minima_reference(P: np.ndarray, az: float, el: float) -> np.ndarray:
    """numpy specification of cell_minimum_ranges: the azimuth cell of ``_cells``, the elevation
    cell as the number of boundaries the point lies on or above (z >= r tan b; arctan2 straight
    up, down and at the sensor), the nearest horizontal range per cell, finite points only."""
    na, ne = int(round(360.0 / az)), int(round(180.0 / el))
    P = P[np.isfinite(P).all(axis=1)]
    with np.errstate(invalid="ignore", over="ignore"):
        a = np.floor((np.degrees(np.arctan2(P[:, 1], P[:, 0])) + 180.0) / az)
        r = np.sqrt(P[:, 0] * P[:, 0] + P[:, 1] * P[:, 1])
    a = np.where(np.isfinite(a), a, 0.0).astype(np.int64) % na
    r = np.where(np.isfinite(r), r, np.hypot(P[:, 0], P[:, 1]))
    tan_edges = np.tan(np.radians(-90.0 + np.arange(1, ne) * el))
    with np.errstate(invalid="ignore", over="ignore"):
        e = (P[:, 2, None] >= r[:, None] * tan_edges[None]).sum(axis=1)
    at = np.clip(np.floor((np.degrees(np.arctan2(P[:, 2], r)) + 90.0) / el).astype(np.int64), 0, ne - 1)
    e = np.where(r > 0, e, at)
    img = np.full((na, ne), np.inf, np.float32)
    with np.errstate(over="ignore"):  # ranges beyond float32 become inf, as in the image
        np.minimum.at(img, (a, e), r.astype(np.float32))
    return img


@pytest.mark.parametrize("seed", range(6))
def test_cell_minimum_ranges_equal_their_numpy_specification(seed: int) -> None:
    """Bit for bit, on clouds with NaN/inf rows, points on the azimuth and elevation boundaries,
    at the sensor, straight up/down and far out (squares that overflow)."""
    from graffmatch.verification.free_space import cell_minimum_ranges

    rng = np.random.default_rng(seed)
    for scale in (1e-3, 1.0, 30.0, 1e160):
        n = 3000
        P = rng.normal(size=(n, 3)) * scale
        P[:200, :2] = np.round(P[:200, :2])  # axis directions, exact 45 deg
        P[200:210] = [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [-0.0, 0.0, 2.0], [0.0, -0.0, 3.0],
                      [-0.0, -0.0, 1.0], [np.nan, 1.0, 0.0], [np.inf, 0.0, 1.0], [1.0, -np.inf, 0.0], [2.0, 1.0, np.nan]]
        t = np.tan(np.radians(-90.0 + rng.integers(1, 180, 300)))
        P[300:600, 2] = np.hypot(P[300:600, 0], P[300:600, 1]) * t  # on (or next to) elevation boundaries
        for az, el in ((1.0, 1.0), (2.0, 0.5), (0.7, 3.0)):
            got = cell_minimum_ranges(P, az, el)
            np.testing.assert_array_equal(got.view(np.uint32), _cell_minima_reference(P, az, el).view(np.uint32))
