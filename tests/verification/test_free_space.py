"""Free-space evidence: points put in front of what the other sensor saw through conflict;
points behind it (occluded) or in cells without a return (unknown) do not."""

from __future__ import annotations

import numpy as np
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
