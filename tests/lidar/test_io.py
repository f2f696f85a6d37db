"""Point-cloud I/O: round trips of every format and clear errors on malformed files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from graffmatch.errors import InvalidInputError, MalformedFileError
from graffmatch.lidar import (
    instance_id,
    label_path_for,
    read_bin,
    read_label,
    read_pcd,
    read_ply,
    read_points,
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


@settings(max_examples=25, deadline=None)
@given(arrays(np.float32, st.tuples(st.integers(0, 40), st.just(4)),
              elements=st.floats(-1e6, 1e6, width=32)))  # fmt: skip
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
