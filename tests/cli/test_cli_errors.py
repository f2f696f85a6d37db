"""Every bad input of issue 12 through the CLI: the exit code (2 usage, 1 input, 3 invalid
result), ONE error line on stderr naming the file, and no traceback without -v."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from graffmatch.cli.main import app
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.transforms import make_transform, transform_errors
from tests.viz.conftest import make_scene

RUNNER = CliRunner()


def run(*args: object, code: int) -> object:
    res = RUNNER.invoke(app, [str(a) for a in args])
    assert res.exit_code == code, f"exit {res.exit_code}\n{res.stdout}\n{res.stderr}"
    assert "Traceback" not in res.output, res.output
    return res


def error_line(res: object, names: str) -> str:
    """The single 'error' line of stderr; it must name ``names``."""
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("error")]
    assert len(errors) == 1, res.stderr
    assert names in errors[0], errors[0]
    return errors[0]


@pytest.fixture(scope="module")
def target(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("target")
    return make_scene().target.save(d / "target.npz", include_points=True)


def _save_points(path: Path, points: np.ndarray) -> Path:
    np.save(path, points)
    return path


@pytest.mark.parametrize(
    ("name", "points", "expect"),
    [
        ("empty.npy", np.zeros((0, 3), np.float32), "empty"),
        ("one.npy", np.ones((1, 3), np.float32), "only 1 point"),
        ("three.npy", np.arange(9, dtype=np.float32).reshape(3, 3) + 1, "only 3 point"),
    ],
)
def test_empty_and_tiny_scans_name_the_file(tmp_path, target, name, points, expect):
    scan = _save_points(tmp_path / name, points)
    res = run("register", scan, target, "-o", tmp_path / "r.json", code=1)
    assert expect in error_line(res, name)
    assert not (tmp_path / "r.json").exists()


def test_text_file_named_bin_is_malformed(tmp_path, target):
    scan = tmp_path / "notes.bin"
    scan.write_text("hello world 1234" * 64)  # a multiple of 16 bytes
    res = run("register", scan, target, code=1)
    assert "implausible" in error_line(res, "notes.bin")


def test_collinear_cloud_gives_no_qhull_text(tmp_path, target):
    rng = np.random.default_rng(0)
    line = np.c_[np.linspace(0, 10, 6000), np.zeros(6000), np.zeros(6000)]
    scan = _save_points(tmp_path / "line.npy", line + 1e-6 * rng.random((6000, 3)))
    res = run("register", scan, target, code=1)
    assert "0 landmark" in error_line(res, "line.npy")
    assert "QH" not in res.output and "qhull" not in res.output.lower()


def test_landmark_types_that_are_not_codes_are_rejected(tmp_path, target):
    ls = make_scene().source
    path = ls.save(tmp_path / "lm.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    key = next(k for k in arrays if "type" in k)
    arrays[key] = arrays[key].astype(np.float64) + 0.7  # 1.7, 2.7: not landmark codes
    np.savez(path, **arrays)
    res = run("register", path, target, code=1)
    error_line(res, "lm.npz")


def test_usage_errors_exit_2(tmp_path, target):
    res = run("demo", "--mode", "foo", code=2)
    assert "foo" in res.output
    run("register", target, target, "--scale", "parsecs", code=2)
    run("register", target, target, "--scale", "-1", code=2)
    run("register", target, code=2)


def test_simulate_speaks_cli_not_python(tmp_path):
    out = tmp_path / "sim"
    out.mkdir()
    (out / "something.txt").write_text("x")
    res = run("simulate", out, "--scans", "2", "--sensor", "vlp16", code=1)
    line = error_line(res, str(out))
    assert "--overwrite" in line and "overwrite=True" not in line


def test_invalid_result_exits_3(tmp_path):
    """Two planes of one wall cannot fix a pose: the command runs, the result is not valid."""
    wall = LandmarkSet.from_arrays(  # two parallel walls, normals along y
        [2, 2], directions=[[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]], anchors=[[0, 5.0, 0], [0, 9.0, 0]]
    )
    a = wall.save(tmp_path / "a.npz")
    b = wall.transform(make_transform(np.eye(3), [1.0, 0.0, 0.0])).save(tmp_path / "b.npz")
    res = run("register", a, b, "-o", tmp_path / "r.json", code=3)
    assert json.loads((tmp_path / "r.json").read_text())["valid"] is False
    assert "NOT valid" in res.stdout


# ---- real scans: units, far coordinates, deterministic ICP ---------------------------------------
@pytest.fixture(scope="module")
def kitti_pair(shared_data) -> tuple[np.ndarray, np.ndarray]:
    root = shared_data / "kitti00_first6" / "velodyne"
    return tuple(np.fromfile(root / f"{i:06d}.bin", np.float32).reshape(-1, 4) for i in (0, 5))


def _register(tmp_path: Path, a: Path, b: Path, *extra: object, code: int = 0) -> np.ndarray:
    out = tmp_path / f"{a.stem}-{b.stem}-{len(extra)}.json"
    run("--config", _no_labels(tmp_path), "register", a, b, "-o", out, *extra, code=code)
    return np.asarray(json.loads(out.read_text())["T_target_source"])


def _no_labels(tmp_path: Path) -> Path:
    cfg = tmp_path / "nolabels.yaml"
    cfg.write_text("input:\n  labels: never\n")
    return cfg


def test_centimetre_cloud_says_scale_and_registers_with_it(tmp_path, kitti_pair):
    s, t = kitti_pair
    # the same clouds in metres, on the centimetre grid the integer files hold
    metres = [
        _save_points(tmp_path / f"m{i}.npy", np.round(p[:, :3] * 100) / 100)
        for i, p in enumerate((s, t))
    ]
    cm = [
        _save_points(tmp_path / f"cm{i}.npy", np.round(p[:, :3] * 100).astype(np.int32))
        for i, p in enumerate((s, t))
    ]
    res = run("--config", _no_labels(tmp_path), "register", *cm, code=1)
    error_line(res, "cm0.npy")
    assert "--scale 0.01" in res.stderr
    T_m = _register(tmp_path, *metres)
    T_cm = _register(tmp_path, *cm, "--scale", "0.01")
    rot, trans = transform_errors(T_cm, T_m)
    assert rot < 1e-3 and trans < 1e-3  # the same registration


def test_far_utm_clouds_keep_their_precision(tmp_path, kitti_pair):
    s, t = kitti_pair
    offset = np.array([500_000.0, 4_600_000.0, 0.0])
    near = [_save_points(tmp_path / f"n{i}.npy", p[:, :3].astype(np.float64)) for i, p in
            enumerate((s, t))]  # fmt: skip
    far = [
        _save_points(tmp_path / f"utm{i}.npy", p[:, :3].astype(np.float64) + offset)
        for i, p in enumerate((s, t))
    ]
    T_near = _register(tmp_path, *near)
    T_far = _register(tmp_path, *far)
    shift = make_transform(np.eye(3), offset)
    expected = shift @ T_near @ np.linalg.inv(shift)  # the same motion, in UTM coordinates
    rot, trans = transform_errors(T_far, expected)
    assert rot < 0.1 and trans < 0.1, (rot, trans)  # was 0.84 deg and 1.67 m (issue 12)


def test_refine_icp_is_deterministic(tmp_path, kitti_pair):
    s, t = kitti_pair
    a = _save_points(tmp_path / "a.npy", s)
    b = _save_points(tmp_path / "b.npy", t)
    T1 = _register(tmp_path, a, b, "--refine", "icp")
    T2 = _register(tmp_path, a, b, "--refine", "icp", "--pose-format", "kitti")
    np.testing.assert_array_equal(T1, T2)


# ---- long commands ------------------------------------------------------------------------------
def test_finished_benchmark_returns_at_once(tmp_path, monkeypatch):
    """A rerun checks completeness first: no suite is loaded or built."""
    from graffmatch.evaluation import benchmark, suites

    data = tmp_path / "data"
    folder = data / "tiny"
    folder.mkdir(parents=True)
    (folder / "pairs.json").write_text("{}")
    out = tmp_path / "bench"
    (out / "results").mkdir(parents=True)
    (out / "report").mkdir()
    (out / "report" / "summary.md").write_text("# report\n")
    (out / "results" / "runs.jsonl").write_text(json.dumps({"complete": True}) + "\n")
    request = benchmark.benchmark_request(["tiny"], True, ["GraffMatch"], data, None)
    log = {
        "request": request,
        "ended_utc": "2026-11-22T00:00:00Z",
        "build": {"tiny": {"folder": str(folder), "pairs_mtime_ns": os.stat(folder / "pairs.json").st_mtime_ns}},
    }  # fmt: skip
    (out / "benchmark.json").write_text(json.dumps(log))

    def no_build(*a, **k):
        raise AssertionError("a finished benchmark must not build suites")

    monkeypatch.setattr(suites, "build_suite", no_build)
    t0 = time.perf_counter()
    res = run("benchmark", "tiny", "--quick", "-m", "GraffMatch", "-o", out, "--data-dir", data,
              code=0)  # fmt: skip
    assert time.perf_counter() - t0 < 5.0
    assert "complete" in res.stdout
    # a rebuilt suite makes it incomplete again
    time.sleep(0.01)
    (folder / "pairs.json").write_text("{ }")
    assert not benchmark.is_benchmark_complete(out, ["tiny"], True, ["GraffMatch"], data)


def test_progress_bars_draw_on_stderr():
    from graffmatch.evaluation.progress import NullProgress, progress_bar

    bar = progress_bar(True)
    assert bar.console.stderr and bar.console.file is not None
    assert isinstance(progress_bar(False), NullProgress)


def test_build_dataset_summary_is_readable():
    from graffmatch.evaluation.loop_closures import summary_text

    summary = {
        "n_scans": 160,
        "n_places": 80,
        "n_revisits": 40,
        "n_valid": 30,
        "cases": {"1": {"pairs": 20}, "2": {"pairs": 6}, "3": {"pairs": 4}},
        "rejected": {"too_few_matches": 10},
        "landmarks_per_place": {"lines": {"mean": 12.0}, "planes": {"mean": 20.5}},
        "total_s": 12.3,
    }
    text = summary_text(summary)
    assert "30 loop closures (case 1: 20, case 2: 6, case 3: 4)" in text
    assert "{" not in text and "too_few_matches 10" in text
