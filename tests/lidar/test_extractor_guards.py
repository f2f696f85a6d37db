"""Extractor guards (issue 12): degenerate clouds never reach Open3D/Qhull, and clouds in the
wrong unit get a message that names the unit."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from graffmatch.errors import GraffMatchError
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.lidar.extractor import LandmarkExtractor, degeneracy, units_hint
from tests.lidar.scene import make_scene


def _degenerate_clouds() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    n = 6000
    t = np.linspace(0, 10, n)
    z = np.zeros(n)
    return {
        # the example (seeded)
        "collinear+1e-6": np.c_[t, z, z] + 1e-6 * rng.random((n, 3)),
        "collinear-exact": np.c_[t + 3, z, z],
        "collinear-diagonal": np.c_[t + 3, t, 0.3 * t],
        "collinear-far": np.c_[t + 500000.0, z + 4600000.0, z],
        "planar-exact": np.c_[rng.uniform(-30, 30, (n, 2)), z - 1.7],
        "planar-vertical": np.c_[rng.uniform(3, 30, n), z + 5, rng.uniform(-2, 5, n)],
        "one-point-repeated": np.tile([[5.0, 5.0, 0.0]], (n, 1)),
        "two-points": np.r_[np.tile([[5.0, 5.0, 0]], (n // 2, 1)), np.tile([[6.0, 5, 3]], (n // 2, 1))],
        "three-points": np.array([[3.0, 0, 0], [0, 4, 0], [0, 0, 5]]),
    }  # fmt: skip


@pytest.mark.parametrize("name", list(_degenerate_clouds()))
def test_degenerate_clouds_are_quiet_and_typed(name: str, capfd) -> None:
    cloud = _degenerate_clouds()[name]
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        try:
            out = LandmarkExtractor().extract(cloud)
        except GraffMatchError:
            out = None
    err = capfd.readouterr().err
    assert err == "", f"stderr not clean for {name}: {err[:300]!r}"
    assert out is None or isinstance(out, LandmarkSet)
    if out is not None:
        assert np.isfinite(out.anchors).all() and np.isfinite(out.bases).all()
    if name.startswith("collinear") and "far" not in name:
        # No plane through a line: no ground, no planar patch, a message that says why.
        assert out is not None and out.counts()["planes"] == 0
        assert any("degenerate" in str(w.message) for w in rec)


def test_degeneracy_ranks() -> None:
    clouds = _degenerate_clouds()
    assert degeneracy(clouds["collinear+1e-6"]) == "line"
    assert degeneracy(clouds["planar-exact"]) == "plane"
    assert degeneracy(clouds["one-point-repeated"]) == "point"
    assert degeneracy(make_scene(seed=0).points[:, :3].astype(float)) == "volume"


def test_scene_still_yields_ground_walls_and_poles() -> None:
    """The guards do not touch a normal scan (same counts as the scene's ground truth)."""
    scene = make_scene(seed=0)
    out = LandmarkExtractor().extract(scene.points)
    assert out.counts()["planes"] >= len(scene.walls)  # walls + ground
    assert out.counts()["lines"] >= 1


@pytest.mark.parametrize("factor,unit,flag", [(100, "centimetres", "0.01"), (1000, "millimetres", "0.001")])  # fmt: skip
def test_integer_cloud_in_wrong_units_names_the_unit(factor: int, unit: str, flag: str) -> None:
    scene = make_scene(seed=0)
    ints = np.round(scene.points[:, :3].astype(np.float64) * factor).astype(np.int64)
    with pytest.warns(RuntimeWarning) as rec:
        out = LandmarkExtractor().extract(ints)
    assert len(out) == 0
    msg = " ".join(str(w.message) for w in rec)
    assert unit in msg and f"scale={flag}" in msg and f"--scale {flag}" in msg
    assert "only 0 valid points" not in msg
    # ... and the suggested factor recovers the landmarks of the metric scan.
    fixed = LandmarkExtractor().extract(ints * float(flag))
    assert fixed.counts() == LandmarkExtractor().extract(scene.points).counts()


def test_units_hint_boundaries() -> None:
    assert units_hint(150.0) is None and units_hint(2000.0) is None
    assert "centimetres (40 m)" in units_hint(4000.0)
    both = units_hint(30000.0)
    assert "centimetres (300 m)" in both and "millimetres (30 m)" in both
    assert "millimetres (160 m)" in units_hint(160000.0)
    assert "far too large" in units_hint(1e9)


def test_out_of_range_message_counts_points(rng) -> None:
    """Points all beyond max_range in metres: the message says how many were cropped."""
    far = np.c_[rng.uniform(100, 200, (500, 2)), rng.uniform(-2, 2, 500)]
    with pytest.warns(RuntimeWarning, match="only 0 of 500 finite points lie within"):
        LandmarkExtractor().extract(far)


def test_far_cloud_support_points_warn_and_read_scan_path_is_exact(tmp_path) -> None:
    """Extracting a UTM cloud directly keeps float64 anchors but float32 support points (0.25 m
    steps at 4.6e6 m): it says so. Through read_scan the landmarks equal the sensor-frame ones."""
    from graffmatch.errors import PrecisionLossWarning
    from graffmatch.lidar.io import read_scan

    scene = make_scene(seed=0)
    utm = np.array([500000.0, 4600000.0, 0.0])
    world = scene.points.astype(np.float64)
    world[:, :3] += utm
    with pytest.warns(PrecisionLossWarning, match="restore_offsets"):
        LandmarkExtractor().extract(world)
    np.save(tmp_path / "w.npy", world)
    scan = read_scan(tmp_path / "w.npy")
    with warnings.catch_warnings():
        warnings.simplefilter("error", PrecisionLossWarning)
        local = LandmarkExtractor().extract(scan.points)
    near = LandmarkExtractor().extract(scene.points)
    np.testing.assert_array_equal(scan.origin, utm)
    assert local.counts() == near.counts()
    np.testing.assert_allclose(local.anchors, near.anchors, atol=1e-6)


def test_absurdly_far_points_are_dropped_not_overflowed(rng) -> None:
    """Finite but absurd coordinates (1e300, 3.5e38) once overflowed the ground grid's int64
    indices (an IndexError from ground.py, found by bench/fuzz.py extract #941)."""
    cloud = np.r_[rng.normal(scale=1e300, size=(300, 3)), rng.normal(scale=3.5e38, size=(300, 3))]
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        try:
            out = LandmarkExtractor().extract(cloud)
            assert len(out) == 0
        except GraffMatchError:
            pass
    utm = make_scene(seed=0).points.astype(np.float64)
    utm[:, :3] += [500000.0, 4600000.0, 0.0]
    utm[:5, :3] = 1e300  # five corrupt rows in an otherwise good UTM cloud
    with pytest.warns(RuntimeWarning, match="dropped 5 of"):
        out = LandmarkExtractor().extract(utm)
    assert out.counts()["planes"] >= 4


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_range_crop_is_the_sqrt_then_compare_definition(dtype) -> None:
    """The compiled crop keeps exactly the rows with min_range^2 <= x^2 + y^2 + z^2 <=
    max_range^2 and min_range <= sqrt(...) <= max_range as numpy computes them (einsum, sqrt),
    also on the bounds and within rounding of them (those rows alone take the numpy test)."""
    ex = LandmarkExtractor()
    lo, hi = ex.config.min_range, ex.config.max_range
    rng = np.random.default_rng(0)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    radii = np.concatenate([rng.uniform(0, 100, 2000), np.repeat([lo, hi], 500),
                            np.repeat([lo, hi], 500) * (1 + rng.integers(-4, 5, 1000) * 2.0**-52)])
    pts = (d * radii[:, None]).astype(dtype)
    pts[:6] = [[lo, 0, 0], [0, -hi, 0], [0, 0, lo], [hi, 0, 0], [0, lo, 0], [0, 0, -hi]]
    P, _, _ = ex._validate(pts, None)
    P64 = pts.astype(np.float64)
    r2 = P64[:, 0] * P64[:, 0] + P64[:, 1] * P64[:, 1] + P64[:, 2] * P64[:, 2]
    r = np.sqrt(np.einsum("ij,ij->i", P64, P64))
    want = P64[(r2 >= lo**2) & (r2 <= hi**2) & (r >= lo) & (r <= hi)]
    assert 0 < len(want) < len(pts)
    np.testing.assert_array_equal(P, want)


def test_a_nan_row_sends_the_cloud_to_the_general_path() -> None:
    """One NaN row anywhere: the fused check-and-crop gives up, and the general path drops the
    row with a warning and keeps the rows whose sqrt(x^2 + y^2 + z^2) is within the range."""
    ex = LandmarkExtractor()
    lo, hi = ex.config.min_range, ex.config.max_range
    rng = np.random.default_rng(1)
    pts = rng.uniform(-90, 90, (3000, 3))
    pts[1777, 1] = np.nan
    with pytest.warns(RuntimeWarning, match="dropped 1 of 3000"):
        P, _, _ = ex._validate(pts, None)
    Q = np.delete(pts, 1777, axis=0)
    r = np.sqrt(Q[:, 0] ** 2 + Q[:, 1] ** 2 + Q[:, 2] ** 2)
    np.testing.assert_array_equal(P, Q[(r >= lo) & (r <= hi)])
