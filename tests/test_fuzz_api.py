"""A standing guard over the public API (issue 12): whatever the input, only
``graffmatch.errors`` exceptions escape, results are finite, and nothing hangs.

Hypothesis draws the inputs (about 300 examples in all; bench/fuzz.py runs 10,000+ per kind).
"""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from graffmatch.errors import GraffMatchError
from graffmatch.geometry.landmarks import Landmark, LandmarkSet
from graffmatch.lidar.extractor import LandmarkExtractor
from graffmatch.lidar.io import read_points, read_scan, write_points
from graffmatch.matcher import GraffMatcher, MatchResult
from graffmatch.pipeline import register_scans

pytestmark = pytest.mark.timeout(120)

def fuzz(n: int) -> settings:
    """Deterministic (derandomized) runs of n examples; pytest-timeout guards against hangs."""
    return settings(
        max_examples=n,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=list(HealthCheck),
    )

# Every float there is: NaN, +-Inf, subnormals, 1e308 ... and ordinary values.
ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True, allow_subnormal=True)
SMALL_FLOAT = st.floats(-100, 100, allow_nan=False)
TYPE_VALUES = st.one_of(
    st.integers(-3, 300),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from(["point", "line", "plane", "PLANE", "cylinder", "", "1"]),
    st.booleans(),
    st.none(),
)


def _only_graffmatch_errors(call):
    """Run ``call``; a GraffMatchError is an answer, anything else fails the test."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return call()
        except GraffMatchError:
            return None


def _assert_finite_set(ls: LandmarkSet) -> None:
    assert isinstance(ls, LandmarkSet)
    assert ls.types.dtype == np.int8 and set(ls.types.tolist()) <= {0, 1, 2}
    assert np.isfinite(ls.bases).all() and np.isfinite(ls.anchors).all()


# ----------------------------------------------------------------------------------------------
# LandmarkSet constructors
# ----------------------------------------------------------------------------------------------
@fuzz(80)
@given(
    n=st.integers(0, 6),
    types=st.lists(TYPE_VALUES, max_size=7),
    dirs=arrays(np.float64, st.tuples(st.integers(0, 7), st.sampled_from([2, 3])), elements=ANY_FLOAT),
    anchors=arrays(np.float64, st.tuples(st.integers(0, 7), st.just(3)), elements=ANY_FLOAT),
    with_points=st.booleans(),
    offsets=st.lists(st.integers(-2, 12), max_size=8),
)
def test_from_arrays_and_constructor(n, types, dirs, anchors, with_points, offsets) -> None:
    pts = np.zeros((max(offsets, default=0) if offsets else 0, 3)) if with_points else None
    offs = offsets if with_points else None
    ls = _only_graffmatch_errors(lambda: LandmarkSet.from_arrays(types, dirs, anchors, None, pts, offs))
    if ls is not None:
        _assert_finite_set(ls)
        assert len(ls) == len(types)
        # what from_arrays accepted, the raw constructor accepts too
        again = LandmarkSet(ls.types, ls.bases, ls.anchors)
        _assert_finite_set(again)
    raw = _only_graffmatch_errors(
        lambda: LandmarkSet(types, np.resize(dirs, (len(types), 3, 2)), anchors)
    )
    if raw is not None:
        _assert_finite_set(raw)


@fuzz(40)
@given(
    kind=TYPE_VALUES,
    a=arrays(np.float64, st.integers(0, 4), elements=ANY_FLOAT),
    d=arrays(np.float64, st.integers(0, 4), elements=ANY_FLOAT),
)
def test_single_landmarks(kind, a, d) -> None:
    for make in (
        lambda: Landmark.point(a),
        lambda: Landmark.line(a, d),
        lambda: Landmark.plane(a, d),
        lambda: Landmark(kind, d, a),
    ):
        lm = _only_graffmatch_errors(make)
        if lm is not None:
            _assert_finite_set(LandmarkSet.from_landmarks([lm]))


@fuzz(30)
@given(data=st.binary(max_size=400))
def test_load_random_bytes(data: bytes) -> None:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "lm.npz"
        # half of the cases start like a real zip so that the zip parser is reached
        p.write_bytes(data if len(data) % 2 else b"PK\x03\x04" + data)
        out = _only_graffmatch_errors(lambda: LandmarkSet.load(p))
        if out is not None:
            _assert_finite_set(out)


# ----------------------------------------------------------------------------------------------
# GraffMatcher().match
# ----------------------------------------------------------------------------------------------
def _set_strategy(max_n: int = 10):
    return st.integers(0, max_n).flatmap(
        lambda n: st.tuples(
            st.lists(st.integers(0, 2), min_size=n, max_size=n),
            arrays(np.float64, (n, 3), elements=st.floats(-1, 1)),
            arrays(np.float64, (n, 3), elements=st.one_of(SMALL_FLOAT, st.sampled_from([0.0, 4.6e6, 1e-9]))),
        )
    )


def _make_set(args) -> LandmarkSet | None:
    return _only_graffmatch_errors(lambda: LandmarkSet.from_arrays(*args))


@fuzz(40)
@given(src=_set_strategy(), tgt=_set_strategy(), seed=st.integers(0, 2**16))
def test_match_random_sets(src, tgt, seed) -> None:
    s, t = _make_set(src), _make_set(tgt)
    if s is None or t is None:
        return
    if seed % 3 == 0 and len(s):  # a true transformed copy now and then
        from graffmatch.geometry.transforms import random_transform

        t = s.transform(random_transform(np.random.default_rng(seed), 20.0))
    res = _only_graffmatch_errors(lambda: GraffMatcher().match(s, t))
    if res is not None:
        assert isinstance(res, MatchResult)
        assert res.T_target_source is None or np.isfinite(res.T_target_source).all()
        assert np.isfinite(res.score)
        A = np.asarray(res.associations).reshape(-1, 2)
        assert (A >= 0).all() and (A[:, 0] < len(s)).all() and (A[:, 1] < len(t)).all()


@fuzz(15)
@given(k=st.integers(1, 5), seed=st.integers(0, 2**16))
def test_match_with_valid_associations(k, seed) -> None:
    rng = np.random.default_rng(seed)
    s = LandmarkSet.from_arrays(rng.integers(1, 3, 8), rng.normal(size=(8, 3)), rng.uniform(-20, 20, (8, 3)))
    t = LandmarkSet.from_arrays(rng.integers(1, 3, 9), rng.normal(size=(9, 3)), rng.uniform(-20, 20, (9, 3)))
    assoc = np.c_[rng.integers(0, 8, k), rng.integers(0, 9, k)]
    res = _only_graffmatch_errors(lambda: GraffMatcher().match(s, t, associations=assoc))
    assert res is None or np.isfinite(res.score)


# Found by this guard: GraffMatcher.match re-indexed `associations` unchecked (IndexError/ValueError
# escaped, negative indices wrapped around, 0.5 was truncated to 0); it now validates them.
@pytest.mark.parametrize(
    "assoc",
    [[[0, 999]], [[999, 0]], [[-1, 0]], [[0.5, 1.0]], [["a", 0]], [0, 1, 2], [[2**40, 0]]],
    ids=["target-out-of-range", "source-out-of-range", "negative", "float", "string", "odd-length",
         "huge"],
)  # fmt: skip
def test_match_bad_association_indices(assoc) -> None:
    rng = np.random.default_rng(0)
    # one type only, so that the matcher's same-type check cannot be what raises
    s = LandmarkSet.from_arrays([2] * 6, rng.normal(size=(6, 3)), rng.normal(size=(6, 3)))
    t = LandmarkSet.from_arrays([2] * 6, rng.normal(size=(6, 3)), rng.normal(size=(6, 3)))
    with pytest.raises(GraffMatchError, match="associations"):
        GraffMatcher().match(s, t, associations=assoc)


# ----------------------------------------------------------------------------------------------
# LandmarkExtractor().extract
# ----------------------------------------------------------------------------------------------
CLOUD_ELEMENTS = st.one_of(
    st.floats(-60, 60, allow_nan=False),
    st.sampled_from([0.0, np.nan, np.inf, 1e-300, 1e300, 4.6e6]),
)


@fuzz(40)
@given(
    cloud=arrays(np.float64, st.tuples(st.integers(0, 400), st.sampled_from([3, 4])), elements=CLOUD_ELEMENTS),
    shape=st.sampled_from(["random", "line", "plane", "point", "cm"]),
    labels=st.sampled_from([None, "good", "short", "float"]),
)
def test_extract_random_clouds(cloud, shape, labels) -> None:
    n = cloud.shape[0]
    if shape == "line":
        cloud[:, :3] = np.c_[np.linspace(0, 10, n), np.zeros(n), np.zeros(n)] + 1e-6 * cloud[:, :3] / 60
    elif shape == "plane":
        cloud[:, 2] = -1.7
    elif shape == "point":
        cloud[:, :3] = 5.0
    elif shape == "cm":
        cloud = np.nan_to_num(cloud, posinf=0, neginf=0).clip(-1e4, 1e4).astype(np.int64) * 100
    lab = {
        None: None,
        "good": np.resize(np.array([40, 80, 71], np.uint32), n),
        "short": np.zeros(max(0, n - 1), np.uint32),
        "float": np.zeros(n),
    }[labels]
    out = _only_graffmatch_errors(lambda: LandmarkExtractor().extract(cloud, lab))
    if out is not None:
        _assert_finite_set(out)


@fuzz(10)
@given(bad=st.sampled_from([np.zeros((5, 2)), np.zeros(7), np.array([["a", "b", "c"]]),
                            np.zeros((2, 3), bool), [[1, 2], [3]], "text", None]))  # fmt: skip
def test_extract_wrong_types(bad) -> None:
    assert _only_graffmatch_errors(lambda: LandmarkExtractor().extract(bad)) is None


# ----------------------------------------------------------------------------------------------
# read_points / read_scan on random bytes, for every suffix
# ----------------------------------------------------------------------------------------------
HEADERS = {
    ".bin": [b""],
    ".pcd": [b"", b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nPOINTS 3\nDATA binary\n",
             b"FIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nPOINTS 2\nDATA ascii\n"],
    ".ply": [b"", b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
             b"property float y\nproperty float z\nend_header\n",
             b"ply\nformat ascii 1.0\nelement vertex 2\nproperty double x\nproperty double y\n"
             b"property double z\nend_header\n"],
    ".npy": [b"", b"\x93NUMPY\x01\x00v\x00{'descr': '<f8', 'fortran_order': False, 'shape': (2, 3), }"],
    ".npz": [b"", b"PK\x03\x04"],
}  # fmt: skip


@fuzz(100)
@given(
    suffix=st.sampled_from(sorted(HEADERS)),
    head=st.integers(0, 2),
    body=st.binary(max_size=300),
    scan=st.booleans(),
    scale=st.sampled_from([1.0, 1.0, 0.01, "mm", 0.0, -1.0, "furlong"]),
)
def test_read_random_bytes(suffix, head, body, scan, scale) -> None:
    heads = HEADERS[suffix]
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / f"scan{suffix}"
        p.write_bytes(heads[head % len(heads)] + body)
        out = _only_graffmatch_errors(
            lambda: read_scan(p, scale=scale).points if scan else read_points(p, scale=scale)
        )
    if out is not None:
        assert out.dtype == np.float32 and out.ndim == 2 and out.shape[1] == 4


@fuzz(25)
@given(
    suffix=st.sampled_from([".bin", ".pcd", ".ply", ".npy", ".npz"]),
    pts=arrays(np.float32, st.tuples(st.integers(0, 30), st.just(4)), elements=st.floats(-100, 100, width=32)),
    flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=6),
    cut=st.one_of(st.none(), st.integers(0, 2000)),
)
def test_read_mutated_valid_files(suffix, pts, flips, cut) -> None:
    with tempfile.TemporaryDirectory() as d:
        p = write_points(Path(d) / f"scan{suffix}", pts)
        data = bytearray(p.read_bytes())
        for pos, val in flips:
            if data:
                data[pos % len(data)] = val
        if cut is not None:
            data = data[: cut % (len(data) + 1)]
        p.write_bytes(bytes(data))
        out = _only_graffmatch_errors(lambda: read_points(p))
    if out is not None:
        assert out.dtype == np.float32 and out.shape[1:] == (4,)


# ----------------------------------------------------------------------------------------------
# register_scans
# ----------------------------------------------------------------------------------------------
@fuzz(12)
@given(seed=st.integers(0, 2**16), n=st.sampled_from([2000, 800, 50, 3, 0]), mode=st.sampled_from(["copy", "random", "line"]))
def test_register_small_random_clouds(seed, n, mode) -> None:
    rng = np.random.default_rng(seed)
    A = np.c_[rng.uniform(-20, 20, (n, 2)), rng.choice([-1.7, 0.0, 2.0], n)] + rng.normal(scale=0.02, size=(n, 3))
    if mode == "line":
        A[:, 1:] = 0.0
    if mode == "copy":
        B = A + [0.5, -0.3, 0.0]
    else:
        B = rng.normal(scale=10, size=(max(n, 1), 3))
    res = _only_graffmatch_errors(lambda: register_scans(A, B))
    if res is not None and res.T_target_source is not None:
        assert np.isfinite(res.T_target_source).all()


# ----------------------------------------------------------------------------------------------
# the loop place check's inputs (graffmatch.loops.place_check, opt-in; session 23)
# ----------------------------------------------------------------------------------------------
@fuzz(60)
@given(
    cloud=st.one_of(
        arrays(np.float64, st.tuples(st.integers(0, 40), st.integers(0, 6)), elements=ANY_FLOAT),
        arrays(np.float32, st.tuples(st.integers(0, 40), st.just(4)), elements=st.floats(-1e6, 1e6, width=32)),
        arrays(np.int64, st.tuples(st.integers(0, 40), st.just(3)), elements=st.integers(-10**12, 10**12)),
        st.sampled_from([np.zeros(7), np.zeros((3, 3, 3)), np.array([["a", "b", "c"]]), np.empty((0, 3))]),
    ),
    scans=st.sampled_from(["list", "dict", "none", "int", "short"]),
    seed=st.integers(0, 2**16),
)
def test_place_check_random_clouds_and_scan_sources(cloud, scans, seed) -> None:
    """place_cloud, scan_place_cloud and remeasure on random clouds and scan containers: a finite cloud and pose, or a
    GraffMatchError; never a foreign exception."""
    from graffmatch.loops.place_check import PlaceCloud, place_cloud, remeasure, scan_place_cloud

    pc = _only_graffmatch_errors(lambda: place_cloud(cloud))
    if pc is not None:
        assert isinstance(pc, PlaceCloud) and np.isfinite(pc.points).all()
        if len(pc) >= 10:
            rng = np.random.default_rng(seed)
            T0 = np.eye(4)
            T0[:3, 3] = rng.normal(0, 1, 3)
            out = _only_graffmatch_errors(lambda: remeasure(pc, pc, T0))
            if out is not None:
                assert np.isfinite(out[0]).all() and np.isfinite(out[1])
    source = {"list": [cloud], "dict": {0: cloud}, "none": None, "int": 3, "short": []}[scans]
    got = _only_graffmatch_errors(lambda: scan_place_cloud(source, 0))
    assert got is None or isinstance(got, PlaceCloud)
