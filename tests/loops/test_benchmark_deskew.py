"""``graffmatch benchmark-loops --deskew``: raw (motion-distorted) simulated scans are de-skewed
for the benchmark through the same function as ``graffmatch loops --deskew`` (same scans, same
landmark tables), under their own name and cache keys."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from graffmatch.cli.main import app
from graffmatch.datasets.deskewed import Deskewed
from graffmatch.datasets.registry import open_dataset
from graffmatch.datasets.simulator import SUITES, TrajectoryConfig, simulate_dataset
from graffmatch.errors import InvalidInputError
from graffmatch.loops.database import load_landmarks
from graffmatch.loops.sequence import prepare_drive

N_SCANS = 6
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def raw_drive(tmp_path_factory):
    s = SUITES["sim-suburban"]
    root = simulate_dataset(
        tmp_path_factory.mktemp("raw") / "raw-drive", style=s.style, seed=2, n_scans=N_SCANS, sensor=s.sensor,
        world_config=s.world_config(), trajectory_config=TrajectoryConfig(step_m=1.5), realism="realistic",
    )
    return open_dataset("folder", root)


def test_prepare_drive_deskews_with_the_odometry_and_names_it(raw_drive):
    ds, odo = prepare_drive(raw_drive, "gt", deskew=True)
    np.testing.assert_array_equal(odo, raw_drive.poses)
    assert isinstance(ds, Deskewed) and ds.name.endswith("+deskew")
    raw, fixed = raw_drive[3].points[:, :3], ds[3].points[:, :3]
    np.testing.assert_array_equal(fixed, Deskewed(raw_drive, raw_drive.poses)[3].points[:, :3])
    # 1.5 m a scan in 0.1 s: the sweep smears the scan by up to ~1.5 m, and de-skewing moves points
    assert np.abs(fixed - raw).max() > 0.3
    same, none = prepare_drive(raw_drive)
    assert same is raw_drive and none is None
    with pytest.raises(InvalidInputError, match="deskew needs an odometry"):
        prepare_drive(raw_drive, None, deskew=True)


def test_benchmark_loops_deskew_uses_the_loops_pipeline(raw_drive, tmp_path):
    runner = CliRunner()
    bench = tmp_path / "bench"
    res = runner.invoke(app, ["-q", "benchmark-loops", str(raw_drive.root), "-o", str(bench), "-m", "ours",
                              "--workers", "1", "--deskew", "--odometry", "gt"])
    assert res.exit_code == 0, res.output
    name = f"{raw_drive.name}+deskew"
    rows = json.loads((bench / "results.json").read_text())
    assert [r["sequence"] for r in rows] == [name] and rows[0]["n_scans"] == N_SCANS
    assert rows[0]["bytes_per_scan"] > 0
    loops_out = tmp_path / "loops"
    res = runner.invoke(app, ["-q", "loops", str(raw_drive.root), "-o", str(loops_out), "--workers", "1",
                              "--deskew", "--odometry", "gt"])
    assert res.exit_code == 0, res.output
    # the same de-skewed scans through the same front end: the same landmark tables
    for i in range(N_SCANS):
        a = load_landmarks(bench / name / "ours" / "landmarks" / f"{i:06d}.npz")
        b = load_landmarks(loops_out / "landmarks" / f"{i:06d}.npz")
        assert len(a) == len(b) > 0
        np.testing.assert_allclose(a.anchors, b.anchors, atol=1e-6)


def test_benchmark_kiss_icp_odometry_is_computed_once_per_drive_and_scored(raw_drive, tmp_path, monkeypatch):
    """``--odometry kiss-icp``: one KISS-ICP run per drive, kept as a KITTI file that the
    extract-only and the scoring run both read (same poses, same landmark cache keys); redone
    when a scan file changes. Every row records the odometry's ATE against the ground truth."""
    import os

    import graffmatch.loops.posegraph as pg
    from graffmatch.evaluation.sequence_benchmark import benchmark_odometry, run_sequence_benchmark
    from graffmatch.geometry.pose_files import read_kitti

    calls = []
    shifted = np.asarray(raw_drive.poses, float).copy()
    shifted[:, 0, 3] += 0.1 * np.arange(N_SCANS)  # an odometry 0.1 m a scan off, so the ATE is not 0
    shifted[:, 1, 3] += 0.05 * np.arange(N_SCANS) ** 2  # bent: evo aligns a curve, not a straight line

    def fake_kiss(ds, deskew=False):
        assert deskew  # the drive's scans are raw: KISS-ICP de-skews them itself
        calls.append(ds.name)
        return shifted

    monkeypatch.setattr(pg, "kiss_icp_odometry", fake_kiss)
    out = tmp_path / "bench"
    path = benchmark_odometry(raw_drive, "kiss-icp", out)
    assert path == str(out / raw_drive.name / "kiss_icp_kitti.txt") and calls == [raw_drive.name]
    np.testing.assert_allclose(read_kitti(path), shifted, atol=1e-6)
    assert benchmark_odometry(raw_drive, "kiss-icp", out) == path and len(calls) == 1  # cached
    assert benchmark_odometry(raw_drive, "drift", out) == "drift" and len(calls) == 1
    st = os.stat(raw_drive.scan_path(2))
    os.utime(raw_drive.scan_path(2), ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    benchmark_odometry(raw_drive, "kiss-icp", out)
    assert len(calls) == 2  # a scan changed: KISS-ICP again
    run_sequence_benchmark([raw_drive.root], out, methods=["ours"], workers=1, deskew=True, odometry="kiss-icp")
    assert len(calls) == 2
    row = json.loads((out / "results.json").read_text())[0]
    assert row["odometry"]["source"] == "kiss-icp" and row["odometry"]["file"] == path
    assert 0.05 < row["odometry"]["ate_rmse_m"] < 0.5
    # the de-skew used the file's poses: the landmark cache keys are those of Deskewed(raw, file)
    meta = json.loads((out / f"{raw_drive.name}+deskew" / "ours" / "queries.meta.json").read_text())
    assert meta["fingerprint"]
