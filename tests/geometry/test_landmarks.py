"""LandmarkSet construction, representations, transformation law, persistence and validation."""

from __future__ import annotations

import numpy as np
import pytest

from graffmatch.errors import InvalidInputError, MalformedFileError
from graffmatch.geometry.landmarks import Landmark, LandmarkSet, LandmarkType, fit_landmark
from graffmatch.geometry.transforms import invert, make_transform, random_transform, rot_z


def _random_set(rng, n=20):
    types = rng.integers(0, 3, n)
    return LandmarkSet.from_arrays(types, rng.normal(size=(n, 3)), rng.uniform(-30, 30, (n, 3)),
                                   {"support": rng.integers(10, 1000, n).astype(float)})


def test_constructors_and_representations():
    line = Landmark.line([1, 2, 3], [0, 0, 2])
    assert np.allclose(line.direction, [0, 0, 1])
    assert np.allclose(line.vector_form(), [0, 0, 1, 1, 2, 3])
    plane = Landmark.plane_from_hesse([0, 0, 1], 2.0, anchor=[5, 5, 7])
    assert np.allclose(plane.anchor, [5, 5, 2])  # anchor projected onto the plane
    assert np.allclose(plane.hesse(), [0, 0, 1, 2])
    ls = LandmarkSet.from_landmarks([line, plane, Landmark.point([1, 1, 1])])
    cp = ls.cp_vectors()
    assert np.allclose(cp[0], [1, 2, 0])  # closest point of the vertical line to the origin
    assert np.allclose(cp[1], [0, 0, 2])
    assert np.allclose(cp[2], [1, 1, 1])
    assert ls.counts() == {"points": 1, "lines": 1, "planes": 1}


def test_transformation_law_matches_hesse_inverse_transpose(rng):
    ls = _random_set(rng)
    T = random_transform(rng, 20)
    moved = ls.transform(T)
    pi = np.concatenate([ls.hesse()[:, :3], -ls.hesse()[:, 3:]], axis=1)  # n.x - d = 0
    pi_moved = (np.linalg.inv(T).T @ pi.T).T
    got = np.concatenate([moved.hesse()[:, :3], -moved.hesse()[:, 3:]], axis=1)
    assert np.allclose(pi_moved, got, atol=1e-9)
    # lines: [RA; Rb + t]
    vf, vf2 = ls.vector_forms(), moved.vector_forms()
    assert np.allclose(vf2[:, :3], vf[:, :3] @ T[:3, :3].T)
    assert np.allclose(vf2[:, 3:], vf[:, 3:] @ T[:3, :3].T + T[:3, 3])
    assert moved.transform(invert(T)).approx_equal(ls, atol=1e-9)


def test_slicing_concatenation_and_points(rng):
    ls = _random_set(rng, 6)
    pts = rng.normal(size=(30, 3)).astype(np.float32)
    ls = LandmarkSet(ls.types, ls.bases, ls.anchors, ls.attributes, pts, [0, 5, 5, 12, 20, 26, 30])
    sub = ls[[1, 3]]
    assert len(sub) == 2 and np.allclose(sub.support_points(1), pts[12:20])
    both = LandmarkSet.concatenate([ls, sub])
    assert len(both) == 8 and np.allclose(both.support_points(7), pts[12:20])


def test_save_load_roundtrip_is_compact(tmp_path, rng):
    ls = _random_set(rng, 40)
    path = ls.save(tmp_path / "lm.npz")
    back = LandmarkSet.load(path)
    assert back.approx_equal(ls, atol=1e-12)
    assert np.allclose(back.bases, ls.bases)
    assert np.allclose(back.attributes["support"], ls.attributes["support"])
    assert path.stat().st_size < 4096  # a few kB for 40 landmarks


def test_a_saved_set_loads_back_bit_for_bit(tmp_path, rng):
    """Version 2 files: bases, anchors and attributes come back exactly (a version 1 file
    rounded attributes to float32 and re-derived plane bases, so matching a loaded set could
    decide differently from matching the extracted one); version 1 files still load."""
    n = 30
    types = rng.integers(1, 3, n)
    ls = LandmarkSet.from_arrays(types, rng.normal(size=(n, 3)), rng.uniform(-30, 30, (n, 3)),
                                 {"extent": rng.uniform(0.1, 40, n), "radius": np.where(types == 1, 0.13, np.nan)})
    back = LandmarkSet.load(ls.save(tmp_path / "v2.npz"))
    assert np.array_equal(back.bases, ls.bases) and np.array_equal(back.anchors, ls.anchors)
    for k, v in ls.attributes.items():
        assert np.array_equal(back.attributes[k], v, equal_nan=True), k
    import io
    import json

    v1 = {"types": ls.types, "directions": ls.directions, "anchors": ls.anchors, "tangents": ls.bases[:, :, 0],
          "meta": np.array(json.dumps({"format": "graffmatch-landmarks", "version": 1}))}
    v1.update({f"attr.{k}": v.astype(np.float32) for k, v in ls.attributes.items()})
    buf = io.BytesIO()
    np.savez_compressed(buf, **v1)
    (tmp_path / "v1.npz").write_bytes(buf.getvalue())
    old = LandmarkSet.load(tmp_path / "v1.npz")
    assert old.approx_equal(ls, atol=1e-12) and np.allclose(old.bases, ls.bases, atol=1e-12)


def test_whole_scan_ranges_travel_with_the_support_points(tmp_path, rng):
    """``scan_ranges`` (sensor frame) is saved with the points, kept by selection and rigid
    motion, dropped with the points and by a merge of different scans; bad shapes are refused."""
    ls = LandmarkSet.from_arrays([1, 2], rng.normal(size=(2, 3)), rng.normal(size=(2, 3)),
                                 points=rng.normal(size=(6, 3)), point_offsets=[0, 3, 6])
    img = np.full((360, 180), np.inf, np.float32)
    img[10, 90] = 12.5
    ls.scan_ranges = img
    back = LandmarkSet.load(ls.save(tmp_path / "s.npz", include_points=True))
    assert np.array_equal(back.scan_ranges, img)
    assert LandmarkSet.load(ls.save(tmp_path / "c.npz")).scan_ranges is None  # compact file: no evidence
    assert ls[[1]].scan_ranges is img and ls.transform(random_transform(rng)).scan_ranges is img
    assert ls.without_points().scan_ranges is None
    assert LandmarkSet.concatenate([ls, ls[[0]]]).scan_ranges is img
    other = LandmarkSet.from_arrays([1], rng.normal(size=(1, 3)), rng.normal(size=(1, 3)),
                                    points=rng.normal(size=(2, 3)), point_offsets=[0, 2])
    assert LandmarkSet.concatenate([ls, other]).scan_ranges is None
    for bad, match in ((np.zeros((7, 180)), "dividing"), (np.full((360, 180), -1.0), ">= 0"),
                       (np.zeros(5), "dividing")):
        with pytest.raises(InvalidInputError, match=match):
            LandmarkSet(ls.types, ls.bases, ls.anchors, points=ls.points, point_offsets=ls.point_offsets,
                        scan_ranges=bad)


def test_malformed_file(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(MalformedFileError, match="bad.npz"):
        LandmarkSet.load(bad)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(types=[1], bases=np.zeros((1, 3, 2)), anchors=np.zeros((1, 3))), "orthonormal"),
        (dict(types=[2], bases=np.tile(np.eye(3)[:, :2], (1, 1, 1)), anchors=[[np.nan, 0, 0]]), "NaN"),
        (dict(types=[1], bases=np.zeros((1, 3, 2)), anchors=np.zeros((2, 3))), "shape"),
        (dict(types=[5], bases=np.zeros((1, 3, 2)), anchors=np.zeros((1, 3))), "types"),
    ],
)
def test_validation_errors(kwargs, match):
    with pytest.raises(InvalidInputError, match=match):
        LandmarkSet(**kwargs)


def test_empty_set_where_not_allowed():
    with pytest.raises(InvalidInputError, match="empty"):
        LandmarkSet.empty().require_nonempty()


def test_pca_fit_returns_residuals(rng):
    R = rot_z(0.3)
    pts = rng.uniform(-5, 5, (500, 3)) * [1, 1, 0]
    pts = pts + rng.normal(0, 0.01, pts.shape)
    pts = pts @ R.T + [1, 2, 3]
    lm, resid = fit_landmark(pts, LandmarkType.PLANE)
    assert abs(abs(lm.direction @ (R @ [0, 0, 1])) - 1) < 1e-4
    assert resid.shape == (500,) and resid.std() < 0.02
    assert np.allclose(lm.anchor, pts.mean(0))
    with pytest.raises(InvalidInputError):
        fit_landmark(np.ones((10, 3)), LandmarkType.LINE)  # degenerate


def test_transform_rejects_non_rigid(rng):
    ls = _random_set(rng, 3)
    T = make_transform(np.diag([1, 1, 2.0]), [0, 0, 0])
    with pytest.raises(InvalidInputError):
        ls.transform(T)


# ------------------------------------------------------------------------------------------
# landmark type codes (issue 12): no truncation, no wrap-around, names accepted
# ------------------------------------------------------------------------------------------
_DIRS = np.array([[1.0, 0, 0], [0, 0, 1]])
_ANCH = np.array([[0.0, 0, 0], [1, 2, 3]])


@pytest.mark.parametrize(
    "types",
    [[1, 2], ["line", "plane"], ["LINE", " Plane "], [b"line", b"plane"],
     [LandmarkType.LINE, LandmarkType.PLANE], [1.0, 2.0], np.array([1, 2], np.uint64),
     ["1", "2"], np.array(["line", 2], dtype=object)],
)  # fmt: skip
def test_type_names_and_integral_codes_are_accepted(types):
    ls = LandmarkSet.from_arrays(types, _DIRS, _ANCH)
    np.testing.assert_array_equal(ls.types, [1, 2])
    assert ls.types.dtype == np.int8
    again = LandmarkSet(types, ls.bases, ls.anchors)
    np.testing.assert_array_equal(again.types, [1, 2])


@pytest.mark.parametrize(
    "types, match",
    [([1.7, 2], "1.7"), ([1, 2.2], "2.2"), ([257, 1], "257"), ([-1, 1], "-1"),
     ([3, 1], "3"), (["line", "cylinder"], "cylinder"), ([True, False], "boolean"),
     ([np.nan, 1], "nan"), ([1e300, 1], "1e\\+300"), ([2**70, 1], "not a landmark type"),
     ([1 + 1j, 1], "complex"), ([None, 1], "None")],
)  # fmt: skip
def test_bad_type_codes_raise_invalid_input(types, match):
    for make in (
        lambda: LandmarkSet.from_arrays(types, _DIRS, _ANCH),
        lambda: LandmarkSet(types, np.zeros((2, 3, 2)), _ANCH),
    ):
        with pytest.raises(InvalidInputError, match=match):
            make()


def test_single_landmark_kind_is_checked():
    assert Landmark("line", [[0], [0], [1]], [0, 0, 0]).kind is LandmarkType.LINE
    with pytest.raises(InvalidInputError, match="1.7"):
        Landmark(1.7, [[0], [0], [1]], [0, 0, 0])
    with pytest.raises(InvalidInputError, match="basis"):
        Landmark(LandmarkType.PLANE, [[0], [0], [1]], [0, 0, 0])
    with pytest.raises(InvalidInputError, match="1.5"):
        fit_landmark(np.random.default_rng(0).normal(size=(10, 3)), 1.5)
    lm, _ = fit_landmark(np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)], "line")
    assert lm.kind is LandmarkType.LINE


@pytest.mark.parametrize(
    "call",
    [
        lambda: LandmarkSet.from_arrays([1], [["a", "b", "c"]], [[0, 0, 0]]),
        lambda: LandmarkSet.from_arrays([1, 2], [[1, 0, 0]], _ANCH),
        lambda: LandmarkSet.from_arrays([1], [1, 0], [[0, 0, 0]]),
        lambda: LandmarkSet.from_arrays([1], [[1e308, 1e308, 0]], [[0, 0, "x"]]),
        lambda: LandmarkSet.from_arrays([1], [[1, 0, 0]], [[0, 0]]),
        lambda: LandmarkSet.from_arrays([1], [[1, 0, 0]], [[0, 0, 0]], {"a": [1, 2]}),
        lambda: LandmarkSet.from_arrays([1], [[1, 0, 0]], [[0, 0, 0]], [1, 2]),
        lambda: LandmarkSet.from_arrays([1], [[1, 0, 0]], [[0, 0, 0]], None, [[0, 0]], [0, 1]),
        lambda: LandmarkSet.from_arrays([1], [[1, 0, 0]], [[0, 0, 0]], None, [[0, 0, 0]], [0.5, 1]),
        lambda: LandmarkSet.from_arrays([1], [[1, 0, 0]], [[0, 0, 0]], None, [[np.inf, 0, 0]], [0, 1]),
        lambda: LandmarkSet.from_arrays([1], [[1, 0, 0]], [[0, 0, 0]], None, [[0, 0, 0]], [0, 2**80]),
        lambda: LandmarkSet([1], [[[1, 0], [0, 0]]], [[0, 0, 0]]),
        lambda: Landmark.line([0, 0], [1, 0, 0]),
        lambda: Landmark.plane(["x", 0, 0], [0, 0, 1]),
        lambda: Landmark.plane_from_hesse([0, 0, 1], "d", [0, 0, 0]),
    ],
)
def test_malformed_arrays_raise_invalid_input_only(call):
    with pytest.raises(InvalidInputError):
        call()


def test_huge_directions_are_normalised_without_overflow():
    ls = LandmarkSet.from_arrays([1, 2], [[1e300, 1e300, 0], [0, 0, -1e-200]], _ANCH)
    np.testing.assert_allclose(ls.directions, [[2**-0.5, 2**-0.5, 0], [0, 0, -1]], atol=1e-15)


def test_load_rejects_invalid_content(tmp_path):
    path = tmp_path / "lm.npz"
    np.savez(path, types=np.array([1.5]), directions=np.zeros((1, 3)), tangents=np.zeros((1, 3)),
             anchors=np.zeros((1, 3)), meta=np.array('{"format": "graffmatch-landmarks"}'))  # fmt: skip
    with pytest.raises(MalformedFileError, match="lm.npz"):
        LandmarkSet.load(path)
    path.write_bytes(b"PK\x03\x04" + b"\x00" * 60)
    with pytest.raises(MalformedFileError, match="lm.npz"):
        LandmarkSet.load(path)


def test_plane_normals_are_np_cross_of_the_bases_bit_for_bit():
    """The written-out cross product of ``directions`` rounds exactly as np.cross does (the
    tilt gates and the registration read these normals)."""
    from graffmatch.geometry.landmarks import _directions

    rng = np.random.default_rng(4)
    B = rng.normal(size=(400, 3, 3)) * rng.choice([1e-150, 1e-3, 1.0, 1e150], size=(400, 1, 1))
    T = rng.integers(0, 3, 400)
    D = _directions(B, T)
    np.testing.assert_array_equal(D[T == 2], np.cross(B[T == 2, :, 0], B[T == 2, :, 1]))
    np.testing.assert_array_equal(D[T == 1], B[T == 1, :, 0])
    assert not D[T == 0].any() and _directions(B[:0], T[:0]).shape == (0, 3)
