"""Point-cloud I/O: round trips of every format and clear errors on malformed files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from graffmatch.errors import InvalidInputError, MalformedFileError, PrecisionLossWarning
from graffmatch.lidar import (
    Scan,
    instance_id,
    label_path_for,
    read_bin,
    read_label,
    read_pcd,
    read_ply,
    read_points,
    read_scan,
    resolve_scale,
    semantic_class,
    write_bin,
    write_label,
    write_pcd,
    write_ply,
    write_points,
)


@pytest.fixture
def cloud(rng) -> np.ndarray:
    pts = rng.normal(scale=20.0, size=(257, 4)).astype(np.float32)
    pts[:, 3] = rng.uniform(0, 1, 257)
    return pts


@pytest.mark.parametrize("suffix", [".bin", ".pcd", ".ply", ".npy", ".npz"])
def test_round_trip_binary_formats(tmp_path: Path, cloud: np.ndarray, suffix: str) -> None:
    path = write_points(tmp_path / f"scan{suffix}", cloud)
    back = read_points(path)
    assert back.dtype == np.float32 and back.shape == (257, 4)
    np.testing.assert_array_equal(back, cloud)


@pytest.mark.parametrize("suffix", [".bin", ".pcd", ".ply", ".npy", ".npz", ".label"])
def test_writers_replace_whole_files_and_leave_no_temporaries(
    tmp_path: Path, cloud: np.ndarray, suffix: str
) -> None:
    """Every writer goes through one atomic write: the exact path (no '.npy' appended), the
    new content over an old file, and no temporary left beside it."""
    path = tmp_path / "sub" / f"scan{suffix}"
    for k in (1.0, 2.0):
        if suffix == ".label":
            labels = (np.arange(len(cloud)) * int(k)).astype(np.uint32)
            assert write_label(path, labels) == path
            np.testing.assert_array_equal(read_label(path, len(cloud)), labels)
        else:
            assert write_points(path, cloud * k) == path
            np.testing.assert_array_equal(read_points(path), (cloud * k).astype(np.float32))
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]


@pytest.mark.parametrize("writer,reader", [(write_pcd, read_pcd), (write_ply, read_ply)])
def test_round_trip_ascii(tmp_path: Path, cloud: np.ndarray, writer, reader) -> None:
    path = writer(tmp_path / "a", cloud, binary=False)
    back = reader(path)
    # repr() of a float32 widened to float64 is exact, so ASCII round trips are lossless.
    np.testing.assert_array_equal(back, cloud)


def test_xyz_only_gets_zero_intensity(tmp_path: Path, rng) -> None:
    xyz = rng.normal(size=(10, 3))
    back = read_points(write_points(tmp_path / "x.npy", xyz))
    np.testing.assert_allclose(back[:, :3], xyz.astype(np.float32))
    assert np.all(back[:, 3] == 0)


def test_pcd_with_extra_fields_and_counts(tmp_path: Path) -> None:
    """PCL files often carry rgb, normals or padding; only x y z intensity are kept."""
    rec = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("pad", "<u1", (3,)),
                             ("intensity", "<f4"), ("ring", "<u2")])  # fmt: skip
    rec["x"], rec["y"], rec["z"], rec["intensity"] = (
        [1, 2, 3],
        [4, 5, 6],
        [7, 8, 9],
        [0.1, 0.2, 0.3],
    )
    head = (
        "VERSION 0.7\nFIELDS x y z pad intensity ring\nSIZE 4 4 4 1 4 2\nTYPE F F F U F U\n"
        "COUNT 1 1 1 3 1 1\nWIDTH 3\nHEIGHT 1\nPOINTS 3\nDATA binary\n"
    )
    p = tmp_path / "extra.pcd"
    p.write_bytes(head.encode() + rec.tobytes())
    out = read_pcd(p)
    np.testing.assert_allclose(out, [[1, 4, 7, 0.1], [2, 5, 8, 0.2], [3, 6, 9, 0.3]], rtol=1e-6)


def test_ply_big_endian_double(tmp_path: Path) -> None:
    head = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty double x\n"
        "property double y\nproperty double z\nelement face 0\nproperty list uchar int vertex_indices\n"
        "end_header\n"
    )
    p = tmp_path / "be.ply"
    p.write_bytes(head.encode() + np.array([[1, 2, 3], [4, 5, 6]], ">f8").tobytes())
    np.testing.assert_array_equal(read_ply(p)[:, :3], [[1, 2, 3], [4, 5, 6]])


def test_labels_round_trip_and_split(tmp_path: Path) -> None:
    labels = (np.array([80, 81, 71, 40], np.uint32)) | (np.array([1, 2, 0, 65535], np.uint32) << 16)
    back = read_label(write_label(tmp_path / "x.label", labels), n_points=4)
    np.testing.assert_array_equal(back, labels)
    np.testing.assert_array_equal(semantic_class(back), [80, 81, 71, 40])
    np.testing.assert_array_equal(instance_id(back), [1, 2, 0, 65535])
    assert label_path_for("/d/seq/velodyne/000007.bin") == Path("/d/seq/labels/000007.label")


# Sensor-frame values: 0, or 1 mm .. 100 km (read_bin rejects files made mostly of others).
_SENSOR = st.floats(-1e5, 1e5, width=32).filter(lambda v: v == 0 or abs(v) >= 1e-3)


@settings(max_examples=25, deadline=None)
@given(arrays(np.float32, st.tuples(st.integers(0, 40), st.just(4)), elements=_SENSOR))
def test_bin_round_trip_property(tmp_path_factory, pts: np.ndarray) -> None:
    path = tmp_path_factory.mktemp("h") / "s.bin"
    np.testing.assert_array_equal(read_bin(write_bin(path, pts)), pts)


# ------------------------------------------------------------------------------------------
# malformed files: always MalformedFileError naming the file
# ------------------------------------------------------------------------------------------
def _assert_names_file(exc: pytest.ExceptionInfo, path: Path) -> None:
    assert str(path) in str(exc.value)


def test_truncated_bin(tmp_path: Path, cloud) -> None:
    p = write_bin(tmp_path / "t.bin", cloud)
    p.write_bytes(p.read_bytes()[:-3])
    with pytest.raises(MalformedFileError, match="multiple of 16") as exc:
        read_points(p)
    _assert_names_file(exc, p)


@pytest.mark.parametrize("suffix", [".pcd", ".ply"])
@pytest.mark.parametrize("binary", [True, False])
def test_truncated_pcd_ply(tmp_path: Path, cloud, suffix: str, binary: bool) -> None:
    writer = write_pcd if suffix == ".pcd" else write_ply
    p = writer(tmp_path / f"t{suffix}", cloud, binary=binary)
    p.write_bytes(p.read_bytes()[:-200])
    with pytest.raises(MalformedFileError, match="truncated") as exc:
        read_points(p)
    _assert_names_file(exc, p)


@pytest.mark.parametrize(
    "name,content,match",
    [
        ("nohead.pcd", b"VERSION 0.7\nFIELDS x y z\n", "header"),
        (
            "noxyz.pcd",
            b"FIELDS a b\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nPOINTS 1\nDATA ascii\n1 2\n",
            "'x'",
        ),
        (
            "comp.pcd",
            b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\nDATA binary_compressed\n",
            "not supported",
        ),
        (
            "text.pcd",
            b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\nDATA ascii\n1 two 3\n",
            "non-numeric",
        ),
        ("magic.ply", b"plx\nformat ascii 1.0\nend_header\n", "not a PLY"),
        (
            "fmt.ply",
            b"ply\nformat weird 1.0\nelement vertex 1\nproperty float x\nend_header\n",
            "format",
        ),
        ("junk.npy", b"\x00\x01garbage", "cannot read"),
        ("scan.xyz", b"1 2 3\n", "unknown point-cloud suffix"),
    ],
)
def test_malformed_files(tmp_path: Path, name: str, content: bytes, match: str) -> None:
    p = tmp_path / name
    p.write_bytes(content)
    with pytest.raises(MalformedFileError, match=match) as exc:
        read_points(p)
    _assert_names_file(exc, p)


def test_missing_file_and_label_mismatch(tmp_path: Path) -> None:
    with pytest.raises(MalformedFileError, match="not found"):
        read_points(tmp_path / "nope.bin")
    p = write_label(tmp_path / "a.label", np.arange(5, dtype=np.uint32))
    with pytest.raises(MalformedFileError, match="5 labels for a scan of 6"):
        read_label(p, n_points=6)
    p.write_bytes(b"\x00" * 7)
    with pytest.raises(MalformedFileError, match="multiple of 4"):
        read_label(p)


def test_npz_ambiguous_and_bad_shape(tmp_path: Path) -> None:
    p = tmp_path / "two.npz"
    np.savez(p, a=np.zeros((2, 3)), b=np.zeros((2, 3)))
    with pytest.raises(MalformedFileError, match="pass key"):
        read_points(p)
    q = tmp_path / "flat.npy"
    np.save(q, np.zeros(5))
    with pytest.raises(MalformedFileError, match="shape"):
        read_points(q)


def test_writer_rejects_bad_arrays(tmp_path: Path) -> None:
    with pytest.raises(InvalidInputError):
        write_points(tmp_path / "x.bin", np.zeros((3, 2)))
    with pytest.raises(InvalidInputError):
        write_label(tmp_path / "x.label", np.array([-1]))


@pytest.mark.parametrize("name", ["o3d.pcd", "o3d_ascii.pcd", "o3d.ply", "o3d_ascii.ply"])
def test_reads_files_written_by_open3d(tmp_path: Path, rng, name: str) -> None:
    """Cross-check the own parsers against an independent writer (Open3D)."""
    o3d = pytest.importorskip("open3d")
    xyz = rng.normal(scale=5.0, size=(100, 3))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    pc.colors = o3d.utility.Vector3dVector(rng.uniform(0, 1, size=(100, 3)))  # extra fields
    path = tmp_path / name
    assert o3d.io.write_point_cloud(str(path), pc, write_ascii="ascii" in name)
    back = read_points(path)
    np.testing.assert_allclose(back[:, :3], xyz, rtol=1e-5, atol=1e-5)


# ------------------------------------------------------------------------------------------
# far (UTM) coordinates: recentred in float64, origin kept (issue 12)
# ------------------------------------------------------------------------------------------
UTM = np.array([500000.0, 4600000.0, 0.0])


def test_real_scans_with_utm_offset_read_back_exactly(shared_data: Path, tmp_path: Path) -> None:
    """Two KITTI scans + (500000, 4600000, 0) as float64 .npy: read_scan gives them back to the
    last bit of float64; read_points would move them by ~0.25 m, and says so."""
    for i in (0, 5):
        raw = read_bin(shared_data / "kitti00_first6" / "velodyne" / f"{i:06d}.bin")
        world = raw.astype(np.float64)
        world[:, :3] += UTM
        path = tmp_path / f"{i:06d}.npy"
        np.save(path, world)
        scan = read_scan(path)
        assert isinstance(scan, Scan) and scan.points.dtype == np.float32
        np.testing.assert_array_equal(scan.origin, UTM)
        np.testing.assert_array_equal(scan.world_points(), world[:, :3])  # exact
        # The sensor-frame scan itself, up to the float64 rounding of `world` (2^-31 m at 4.6e6).
        np.testing.assert_allclose(scan.points, raw, rtol=0, atol=2.0**-31)
        with pytest.warns(PrecisionLossWarning, match=str(path)) as rec:
            naive = read_points(path)
        err = np.abs(naive[:, :3].astype(np.float64) - world[:, :3]).max()
        assert 0.1 < err <= 0.25  # float32 spacing at 4.6e6 m is 0.5 m
        assert "0.25 m" in str(rec[0].message) and "read_scan" in str(rec[0].message)


@pytest.mark.parametrize("fmt", ["npy", "pcd_binary", "pcd_ascii", "ply_binary", "ply_ascii"])
def test_read_scan_recentres_double_files(tmp_path: Path, rng, fmt: str) -> None:
    """Any float64 format: world = points + origin within float32 rounding of the *local*
    coordinates (~1e-5 m), where a plain cast errs by up to 0.25 m."""
    offset = np.array([512345.678, 5432109.123, 87.6])
    world = rng.normal(scale=30.0, size=(500, 3)) + offset
    path = tmp_path / f"c.{fmt.split('_')[0]}"
    if fmt == "npy":
        np.save(path, world)
    elif fmt.startswith("pcd"):
        head = (f"VERSION 0.7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\n"
                f"WIDTH 500\nHEIGHT 1\nPOINTS 500\nDATA {fmt.split('_')[1]}\n").encode()  # fmt: skip
        body = (world.astype("<f8").tobytes() if fmt.endswith("binary")
                else "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in world.tolist()).encode())  # fmt: skip
        path.write_bytes(head + body)
    else:
        kind = "binary_little_endian" if fmt.endswith("binary") else "ascii"
        head = (f"ply\nformat {kind} 1.0\nelement vertex 500\nproperty double x\n"
                "property double y\nproperty double z\nend_header\n").encode()  # fmt: skip
        body = (world.astype("<f8").tobytes() if fmt.endswith("binary")
                else "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in world.tolist()).encode())  # fmt: skip
        path.write_bytes(head + body)
    scan = read_scan(path)
    np.testing.assert_array_equal(scan.origin, np.round(np.median(world, axis=0) / 100) * 100)
    local = world - scan.origin
    assert np.abs(local).max() < 250
    err = np.abs(scan.world_points() - world).max()
    assert err <= np.abs(local).max() * 2.0**-24 and err < 1e-5
    with pytest.warns(PrecisionLossWarning):
        read_points(path)


def test_read_scan_keeps_sensor_frames(tmp_path: Path, cloud: np.ndarray) -> None:
    """Sensor-frame scans are not moved (the extractor's range crop needs the sensor at 0)."""
    for suffix in (".bin", ".pcd", ".npy"):
        path = write_points(tmp_path / f"s{suffix}", cloud)
        scan = read_scan(path)
        np.testing.assert_array_equal(scan.origin, 0.0)
        np.testing.assert_array_equal(scan.points, read_points(path))
        assert not scan.recentred and scan.path == path
    far = cloud.astype(np.float64)
    far[:, 0] += 3000.0  # a Livox-like one-sided scan, still in float64 without loss
    np.save(tmp_path / "f.npy", far)
    assert not read_scan(tmp_path / "f.npy").recentred


def test_read_scan_labels_and_key(tmp_path: Path, cloud: np.ndarray) -> None:
    path = write_points(tmp_path / "s.bin", cloud)
    lab = write_label(tmp_path / "s.label", np.arange(len(cloud), dtype=np.uint32))
    scan = read_scan(path, labels=lab)
    np.testing.assert_array_equal(scan.labels, np.arange(len(cloud)))
    with pytest.raises(MalformedFileError, match="labels for a scan"):
        read_scan(path, labels=write_label(tmp_path / "t.label", np.arange(3, dtype=np.uint32)))
    np.savez(tmp_path / "two.npz", a=cloud, b=cloud[:5])
    assert len(read_scan(tmp_path / "two.npz", key="b")) == 5
    with pytest.raises(InvalidInputError, match="npz"):
        read_scan(path, key="b")


def test_float64_values_beyond_float32_are_malformed(tmp_path: Path) -> None:
    np.save(tmp_path / "huge.npy", np.array([[1e39, 0, 0], [1, 2, 3]]))
    for reader in (read_points, read_scan):
        with pytest.raises(MalformedFileError, match="float32's range") as exc:
            reader(tmp_path / "huge.npy")
        _assert_names_file(exc, tmp_path / "huge.npy")


# ------------------------------------------------------------------------------------------
# garbage named .bin (issue 12)
# ------------------------------------------------------------------------------------------
def _trim16(data: bytes) -> bytes:
    return data[: len(data) // 16 * 16]


@pytest.mark.parametrize(
    "content",
    [
        pytest.param(
            lambda rng: "\n".join(
                f"{x:.4f} {y:.4f} {z:.4f} 0.5" for x, y, z in rng.normal(scale=20, size=(300, 3))
            ).encode(),
            id="numbers-as-text",
        ),
        pytest.param(
            lambda rng: b"the quick brown fox jumps over the lazy dog; " * 60, id="prose"
        ),
        pytest.param(
            lambda rng: np.c_[rng.normal(size=(100, 3)) * 1e7, np.zeros(100)].astype("<f4").tobytes(),
            id="absurd-far",
        ),
        pytest.param(
            lambda rng: np.full((100, 4), np.nan, "<f4").tobytes(), id="all-nan"
        ),
        pytest.param(
            lambda rng: (rng.integers(1, 2**23, size=400, dtype=np.uint32)).astype("<u4").tobytes(),
            id="denormal",
        ),
        pytest.param(lambda rng: rng.bytes(16 * 500), id="random-bytes"),
    ],
)
def test_garbage_bin_is_malformed(tmp_path: Path, rng, content) -> None:
    path = tmp_path / "scan.bin"
    path.write_bytes(_trim16(content(rng)))
    with pytest.raises(MalformedFileError, match="implausible") as exc:
        read_points(path)
    _assert_names_file(exc, path)
    with pytest.raises(MalformedFileError):
        read_scan(path)


def test_bin_with_some_nan_or_zero_rows_still_reads(tmp_path: Path, cloud: np.ndarray) -> None:
    pts = cloud.copy()
    pts[:100, :3] = np.nan  # 100 of 257: a minority
    pts[100:120] = 0.0  # no-return rows some drivers write
    back = read_points(write_bin(tmp_path / "n.bin", pts))
    np.testing.assert_array_equal(back[120:], pts[120:])
    assert np.isnan(back[:100, :3]).all()


def test_float64_bin_variant_is_read_with_warning(tmp_path: Path, cloud: np.ndarray) -> None:
    world = cloud.astype(np.float64)
    world[:, :3] += UTM
    path = tmp_path / "d.bin"
    path.write_bytes(world.astype("<f8").tobytes())
    with pytest.warns(RuntimeWarning, match="float64"):
        scan = read_scan(path)
    np.testing.assert_array_equal(scan.origin, UTM)
    np.testing.assert_array_equal(scan.world_points(), world[:, :3])


# ------------------------------------------------------------------------------------------
# units (issue 12)
# ------------------------------------------------------------------------------------------
def test_scale_converts_integer_centimetres(tmp_path: Path, cloud: np.ndarray) -> None:
    cm = np.round(cloud[:, :3].astype(np.float64) * 100).astype(np.int32)
    path = tmp_path / "cm.npy"
    np.save(path, cm)
    for scale in (0.01, "cm", "CM "):
        np.testing.assert_allclose(read_points(path, scale=scale)[:, :3], cm / 100.0, rtol=1e-7)
        assert read_scan(path, scale=scale).scale == 0.01
    assert resolve_scale("mm") == 0.001 and resolve_scale(2) == 2.0


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf"), "furlong", True, None, [1]])
def test_bad_scale_is_rejected(tmp_path: Path, cloud: np.ndarray, bad) -> None:
    path = write_points(tmp_path / "s.npy", cloud)
    with pytest.raises(InvalidInputError, match="scale"):
        read_points(path, scale=bad)
    with pytest.raises(InvalidInputError, match="scale"):
        read_scan(path, scale=bad)


def _implausible_reference(xyz: np.ndarray, limit: float) -> np.ndarray:
    """The numpy expression the compiled row check replaced (its specification)."""
    from graffmatch.lidar import io

    with np.errstate(invalid="ignore", over="ignore"):
        a = np.abs(xyz.astype(np.float64, copy=False))
        m = a.max(axis=1) if a.shape[0] else np.zeros(0)
        bad = ~np.isfinite(m) | (m > limit) | ((m > 0) & (m < io.SENSOR_MIN_RANGE))
        bad |= ((a > 0) & (a < io._F32_TINY)).any(axis=1)
    return bad


def test_implausible_rows_kernel_equals_its_numpy_specification():
    """On 400 random blocks (float32 and float64, scales 1e-3..1e6) salted with NaN, +-Inf, zeros, denormals, tiny
    and huge values, the compiled row check flags exactly the rows the numpy expression does."""
    from graffmatch.lidar import io

    rng = np.random.default_rng(7)
    specials = (np.nan, np.inf, -np.inf, 0.0, 1e-40, -1e-39, 1e-310, 1e5, 1e-3, -0.0)
    for k in range(400):
        dt = (np.float32, np.float64)[k % 2]
        X = rng.normal(0, 10 ** rng.uniform(-3, 6), (int(rng.integers(0, 300)), 3)).astype(dt)
        for v in specials:
            if len(X):
                X[rng.integers(0, len(X), 4), rng.integers(0, 3)] = v
        for limit in (io.SENSOR_FRAME_LIMIT, 1e8):
            assert np.array_equal(io._implausible_rows(X, limit), _implausible_reference(X, limit)), (k, limit)
        assert np.array_equal(io._implausible_rows(X[:, :3][::2], 1e8), _implausible_reference(X[::2], 1e8))
