"""Smoke tests of every ``graffmatch`` subcommand through the real CLI (typer's runner, in process).

Each test checks numbers, not only exit codes: the transforms written equal the library's, the
errors reported equal the errors recomputed, files round-trip.
"""

from __future__ import annotations

import json
import shutil
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from graffmatch.cli.main import app
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.pose_files import parse_pose_line
from graffmatch.geometry.transforms import transform_errors
from tests.viz.conftest import make_scene

RUNNER = CliRunner()


def run(*args: str, env: dict | None = None, code: int | None = 0):
    res = RUNNER.invoke(app, [str(a) for a in args], env=env)
    if code is not None:
        assert res.exit_code == code, (
            f"exit {res.exit_code}\nstdout:\n{res.stdout}\nstderr:\n{res.stderr}\n{res.exception!r}"
        )
    return res


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> dict:
    """Landmark files of a synthetic street seen from two poses 180° / 14 m apart."""
    d = tmp_path_factory.mktemp("synth")
    sc = make_scene()
    src = sc.source.save(d / "source.npz", include_points=True)
    tgt = sc.target.save(d / "target.npz", include_points=True)
    np.savetxt(d / "gt.txt", sc.T_target_source)
    return {"dir": d, "source": src, "target": tgt, "gt": d / "gt.txt", "T": sc.T_target_source}


@pytest.fixture(scope="module")
def kitti(shared_data) -> dict:
    from graffmatch.datasets.folder import KittiFolder

    root = shared_data / "kitti00_first6"
    ds = KittiFolder(root)
    L = ds.poses
    return {"root": root, "scans": sorted((root / "velodyne").glob("*.bin")), "L": L}


# ---- global behaviour ---------------------------------------------------------------------------
def test_version_and_help():
    assert run("--version").stdout.strip() == f"graffmatch {version('graffmatch')}"
    text = run("--help").stdout
    for cmd in (
        "demo",
        "extract",
        "register",
        "view",
        "simulate",
        "build-dataset",
        "benchmark",
        "report",
        "calibrate",
        "config",
    ):
        assert cmd in text
    assert "Examples" in text and "Exit codes" in text
    assert "Examples" in run("register", "--help").stdout


@pytest.mark.parametrize(
    "args",
    [
        ("register", "missing_a.npz", "missing_b.npz"),
        ("extract", "missing.bin"),
        ("view", "missing.json"),
        ("--config", "missing.yaml", "config", "dump"),
        ("report", "missing_folder"),
    ],
)
def test_missing_files_give_one_clear_line(tmp_path, monkeypatch, args):
    monkeypatch.chdir(tmp_path)
    res = run(*args, code=1)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("error") and "missing" in lines[0]
    assert "Traceback" not in res.output
    assert not (tmp_path / "runs").exists()  # nothing half-written


def test_verbose_shows_the_exception(tmp_path, monkeypatch):
    from graffmatch.errors import MalformedFileError

    monkeypatch.chdir(tmp_path)
    res = run("-v", "register", "a.npz", "b.npz", code=None)
    assert res.exit_code != 0 and isinstance(res.exception, MalformedFileError)


def test_bad_gt_and_bad_usage(synth):
    res = run("register", synth["source"], synth["target"], "--gt", "1 2 3", code=1)
    assert "12 (3x4) or 16 (4x4)" in res.stderr
    run("register", synth["source"], code=2)  # missing argument: click's usage error


# ---- configuration --------------------------------------------------------------------------------
def test_config_dump_yaml_roundtrip_and_env(tmp_path):
    text = run("config", "dump").stdout
    data = yaml.safe_load(text)
    assert data["matcher"]["rho"] == 40.0 and data["matcher"]["epsilon"] == 0.2
    assert data["extractor"]["poles"]["semantic_classes"] == [80, 81, 71]
    assert "# " in text  # documented
    data["matcher"]["rho"] = 20.0
    data["icp"]["max_iterations"] = 7
    cfg = tmp_path / "my.yaml"
    cfg.write_text(yaml.safe_dump(data))
    again = yaml.safe_load(run("--config", cfg, "config", "dump").stdout)
    assert again == data  # everything else kept its value
    run("config", "check", cfg)
    env = yaml.safe_load(
        run("--config", cfg, "config", "dump", env={"GRAFFMATCH_MATCHER__RHO": "25"}).stdout
    )
    assert env["matcher"]["rho"] == 25.0 and env["icp"]["max_iterations"] == 7
    bad = run("config", "dump", env={"GRAFFMATCH_MATCHER__RHO": "-1"}, code=1)
    assert "matcher.rho" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    typo = run("config", "dump", env={"GRAFFMATCH_MATCHER__RHOO": "3"}, code=1)
    assert "matcher.rhoo" in typo.stderr
    # a partial file keeps the other defaults; GRAFFMATCH_CONFIG is the same as --config
    cfg.write_text("matcher:\n  rho: 30\n")
    part = yaml.safe_load(run("config", "dump", env={"GRAFFMATCH_CONFIG": str(cfg)}).stdout)
    assert part["matcher"]["rho"] == 30 and part["matcher"]["epsilon"] == 0.2
    assert part["extractor"] == yaml.safe_load(text)["extractor"]
    cfg.write_text("matcher: [1, 2]\n")
    assert "matcher" in run("config", "check", cfg, code=1).stderr


# ---- register / view ----------------------------------------------------------------------------
def test_register_landmark_files_with_ground_truth(synth, tmp_path):
    from graffmatch.matcher import GraffMatcher

    out = tmp_path / "res" / "result.json"
    res = run(
        "register",
        synth["source"],
        synth["target"],
        "--gt",
        synth["gt"],
        "-o",
        out,
        "--pose-format",
        "tum",
        "--view",
        tmp_path / "v.html",
    )
    data = json.loads(out.read_text())
    T = np.asarray(data["T_target_source"])
    # the CLI reports exactly what the library computes ...
    direct = GraffMatcher().match(
        LandmarkSet.load(synth["source"]), LandmarkSet.load(synth["target"])
    )
    np.testing.assert_allclose(T, direct.T_target_source, atol=1e-12)
    np.testing.assert_array_equal(data["associations"], direct.associations)
    # ... recovers the 180° / 14 m transform of the noise-free scene ...
    rot, trans = transform_errors(T, synth["T"])
    assert rot < 0.5 and trans < 0.05 and data["valid"]
    gt = data["ground_truth"]
    assert gt["rotation_error_deg"] == pytest.approx(rot, abs=1e-9)
    assert gt["translation_error_m"] == pytest.approx(trans, abs=1e-9)
    assert gt["success"] and gt["n_inliers"] == sum(gt["inlier_mask"]) >= 10
    # ... prints them, writes the pose line, the config and the view.
    assert f"{rot:.3f}°" in res.stdout and "inliers" in res.stdout
    pose = out.with_suffix(".tum.txt").read_text().strip()
    np.testing.assert_allclose(parse_pose_line(pose, "tum")[1], T, atol=1e-12)
    assert yaml.safe_load(out.with_name("result.config.yaml").read_text())["matcher"]["rho"] == 40
    html = (tmp_path / "v.html").read_text()
    assert "data-graffmatch-rendered" in html and "inliers (" in html
    # determinism: the same command again gives the same transform
    run("register", synth["source"], synth["target"], "-o", tmp_path / "again.json")
    T2 = np.asarray(json.loads((tmp_path / "again.json").read_text())["T_target_source"])
    np.testing.assert_array_equal(T, T2)
    # quiet mode prints the 12 numbers of the 3x4 only
    q = run("-q", "register", synth["source"], synth["target"], "-o", tmp_path / "q.json")
    np.testing.assert_allclose(np.fromstring(q.stdout, sep=" "), T[:3].ravel(), atol=1e-8)

    # graffmatch view redraws the saved result
    run("view", out, "-o", tmp_path / "again.html")
    again = (tmp_path / "again.html").read_text()
    assert "inliers (" in again and "data-graffmatch-rendered" in again


def test_register_kitti_pose_and_icp_refinement(synth, tmp_path):
    out = tmp_path / "icp.json"
    run(
        "register",
        synth["source"],
        synth["target"],
        "--gt",
        synth["gt"],
        "-o",
        out,
        "--refine",
        "icp",
        "--pose-format",
        "kitti",
        "--pose-out",
        tmp_path / "T.txt",
    )
    data = json.loads(out.read_text())
    ref = data["refine"]
    assert ref["method"] == "icp" and ref["fitness"] > 0.9
    T = np.asarray(data["T_target_source"])
    np.testing.assert_allclose(T, ref["T_target_source"])
    rot, trans = transform_errors(T, synth["T"])
    assert rot < 0.5 and trans < 0.05
    line = (tmp_path / "T.txt").read_text().strip()
    assert len(line.split()) == 12
    np.testing.assert_allclose(parse_pose_line(line, "kitti")[1], T, atol=1e-12)


def test_icp_without_support_points_is_a_clear_error(synth, tmp_path):
    bare = LandmarkSet.load(synth["source"]).without_points().save(tmp_path / "bare.npz")
    res = run(
        "register", bare, synth["target"], "--refine", "icp", "-o", tmp_path / "r.json", code=1
    )
    assert "support points" in res.stderr


def test_extract_and_register_real_scans(kitti, tmp_path):
    s0, s5 = kitti["scans"][0], kitti["scans"][5]
    res = run("extract", s0, "-o", tmp_path / "lm0.npz")
    ls0 = LandmarkSet.load(tmp_path / "lm0.npz")
    c = ls0.counts()
    assert c["lines"] >= 2 and c["planes"] >= 5
    assert f"{c['lines']} poles, {c['planes']} planes" in res.stdout
    assert (tmp_path / "lm0.npz").stat().st_size < 20_000  # compact without points

    L = kitti["L"]
    T_gt = np.linalg.inv(L[5]) @ L[0]
    # scans 0 and 5 overlap (4.3 m apart): the pair must register, valid (exit 0) and right
    # (measured: 0.92 deg, 0.99 m from landmarks alone, inside the paper's 5 deg / 1 m)
    res = run("--runs-dir", tmp_path / "runs", "register", s0, s5, "--gt", "auto", code=0)
    (folder,) = list((tmp_path / "runs").glob("*_register"))
    data = json.loads((folder / "result.json").read_text())
    assert (folder / "config.yaml").is_file()
    assert data["valid"] and data["ground_truth"]["success"], res.output
    assert data["ground_truth"]["rotation_error_deg"] < 2.0
    # the support points' answer was re-aligned on the scans (session 22), and the record says how far
    realign = data["scan_realign"]
    assert realign["enabled"] and realign["fitness_after"] >= realign["fitness_before"]
    assert len(realign["T_support"]) == 4 or not realign["applied"]
    # landmarks of the scans were saved (with points) next to the result, and are the same
    saved = LandmarkSet.load(folder / "result_source_landmarks.npz")
    assert saved.points is not None and saved.approx_equal(ls0)
    np.testing.assert_allclose(data["ground_truth"]["T_target_source"], T_gt, atol=1e-9)
    rot, trans = transform_errors(np.asarray(data["T_target_source"]), T_gt)
    assert data["ground_truth"]["rotation_error_deg"] == pytest.approx(rot, abs=1e-9)
    assert data["ground_truth"]["translation_error_m"] == pytest.approx(trans, abs=1e-9)
    # the result folder can move: view finds its files through relative paths
    moved = tmp_path / "moved"
    shutil.copytree(folder, moved)
    shutil.rmtree(folder)
    run("view", moved / "result.json", "--no-points", "--png", tmp_path / "top.png")
    assert (moved / "result.html").stat().st_size > 1_000_000
    assert (tmp_path / "top.png").read_bytes()[:4] == b"\x89PNG"


def test_register_without_scan_realignment(kitti, tmp_path):
    """--no-scan-realign returns the support points' answer as it is (no re-alignment record)."""
    s0, s5 = kitti["scans"][0], kitti["scans"][5]
    run("register", s0, s5, "--gt", "auto", "--no-scan-realign", "-o", tmp_path / "r.json", code=0)
    data = json.loads((tmp_path / "r.json").read_text())
    assert data["valid"] and data["scan_realign"] is None
    assert data["T_target_source"] == data["T_target_source_matcher"]


def test_extract_folder(kitti, tmp_path):
    scans = tmp_path / "scans"
    scans.mkdir()
    for p in kitti["scans"][:2]:
        shutil.copy(p, scans / p.name)
    run("extract", scans, "-o", tmp_path / "lm", "--with-points")
    summary = json.loads((tmp_path / "lm" / "summary.json").read_text())
    assert [Path(r["scan"]).name for r in summary["scans"]] == ["000000.bin", "000001.bin"]
    for r in summary["scans"]:
        ls = LandmarkSet.load(r["landmarks"])
        assert ls.points is not None
        assert (r["poles"], r["planes"]) == (ls.counts()["lines"], ls.counts()["planes"])
    assert (tmp_path / "lm" / "config.yaml").is_file()


# ---- datasets, evaluation, calibration, demo ------------------------------------------------------
def _labels_never(tmp_path: Path) -> Path:
    cfg = tmp_path / "never.yaml"
    cfg.write_text("input:\n  labels: never\n")
    return cfg


def test_simulate_tiny(tmp_path):
    out = tmp_path / "sim"
    run("simulate", out, "--scans", "2", "--sensor", "vlp16", "--style", "suburban")
    bins = sorted((out / "velodyne").glob("*.bin"))
    assert len(bins) == 2
    pts = np.fromfile(bins[0], np.float32).reshape(-1, 4)
    assert len(pts) > 1000
    assert len((out / "poses.txt").read_text().splitlines()) == 2
    # the simulator's SemanticKITTI labels are found next to the scans: semantic pole mode
    run("extract", out, "-o", tmp_path / "lm")
    rows = json.loads((tmp_path / "lm" / "summary.json").read_text())["scans"]
    assert [Path(r["labels"]).name for r in rows] == ["000000.label", "000001.label"]
    run("--config", _labels_never(tmp_path), "extract", out, "-o", tmp_path / "lm2")
    rows2 = json.loads((tmp_path / "lm2" / "summary.json").read_text())["scans"]
    assert all(r["labels"] is None for r in rows2)
    res = run("simulate", out, "--scans", "2", "--sensor", "vlp16", code=1)  # not empty
    assert "overwrite" in res.stderr
    run("simulate", out, "--style", "nowhere", code=1)


def test_build_dataset_benchmark_and_report(kitti, tmp_path):
    from graffmatch.datasets.folder import KittiFolder
    from graffmatch.evaluation.loop_closures import LoopClosureConfig
    from graffmatch.evaluation.suites import SUITES, Suite, register_suite

    cfg = LoopClosureConfig(place_spacing=0.8, min_path_length=0.0, max_pairs=2, workers=1)
    register_suite(
        Suite(
            "cli-tiny-kitti",
            "KITTI 00 first scans, short revisits (CLI test)",
            lambda d, q, r: KittiFolder(kitti["root"]),
            cfg,
            {},
        ),
        overwrite=True,
    )
    try:
        assert "cli-tiny-kitti" in run("build-dataset", "--list").stdout
        run("build-dataset", "cli-tiny-kitti", "-o", tmp_path / "data")
        summary = json.loads((tmp_path / "data" / "cli-tiny-kitti" / "summary.json").read_text())
        assert summary["n_valid"] >= 1
        run(
            "benchmark",
            "cli-tiny-kitti",
            "-o",
            tmp_path / "bench",
            "--executor",
            "serial",
            "-m",
            "GraffMatch",
            "--data-dir",
            tmp_path / "data",
        )
        assert json.loads((tmp_path / "bench" / "results" / "config.json").read_text())
        built = yaml.safe_load((tmp_path / "data" / "cli-tiny-kitti" / "config.yaml").read_text())
        assert built["place_spacing"] == 0.8 and built["max_pairs"] == 2
        assert (tmp_path / "bench" / "report" / "table1.md").is_file()
        run("report", tmp_path / "bench" / "results", "-o", tmp_path / "rep")
        assert "GraffMatch" in (tmp_path / "rep" / "table1.md").read_text()
        # the benchmark folder itself is accepted too; the report goes to <folder>/report
        (tmp_path / "bench" / "report" / "table1.md").unlink()
        run("report", tmp_path / "bench", "--views", "1")
        rep = tmp_path / "bench" / "report"
        assert (rep / "table1.md").read_text() == (tmp_path / "rep" / "table1.md").read_text()
        # ... with sample 3D views sharing one offline plotly.js, linked from the summary
        index = json.loads((rep / "views" / "index.json").read_text())
        assert len(index) == sum(1 for c in summary["cases"].values() if c.get("pairs"))
        for e in index:
            html = (rep / e["html"]).read_text()
            assert 'src="plotly.min.js"' in html and "data-graffmatch-rendered" in html
            assert (rep / e["png"]).read_bytes()[:4] == b"\x89PNG"
            assert e["html"] in (rep / "summary.md").read_text()
        assert (rep / "views" / "plotly.min.js").stat().st_size > 1_000_000
    finally:
        SUITES.pop("cli-tiny-kitti", None)


def test_calibrate_demo_and_files(tmp_path):
    from graffmatch.calibration.rig import make_lidar_lidar_scenario

    res = run("calibrate", "--demo", "--kind", "camera-depth", "-o", tmp_path / "cd.json")
    rep = json.loads((tmp_path / "cd.json").read_text())["camera-depth"]
    assert rep["within_bounds"] and rep["rotation_error_deg"] <= 1.0
    assert "error vs truth" in res.stdout

    sc = make_lidar_lidar_scenario(1)
    np.save(tmp_path / "a.npy", sc.cloud_a)
    np.save(tmp_path / "b.npy", sc.cloud_b)
    run("calibrate", tmp_path / "a.npy", tmp_path / "b.npy", "-o", tmp_path / "ab.json")
    data = json.loads((tmp_path / "ab.json").read_text())
    T = np.asarray(next(v for k, v in data.items() if k.startswith("T_")))
    rot, trans = transform_errors(T, sc.T_b_a)
    assert rot <= 1.0 and trans <= 0.05
    run("calibrate", code=1)  # neither files nor --demo


def test_demo_exit_code_follows_its_verdict():
    # seed 0 of the landmark demo meets its bounds: PASS and exit 0, nothing else
    res = run("demo", "--mode", "landmarks", "--seed", "0", code=0)
    assert "rotation error" in res.stdout and "PASS" in res.stdout


@pytest.mark.parametrize(
    ("name", "content", "expect"),
    [
        ("bad.npz", b"garbage", "not a valid .npz"),
        ("bad.bin", b"garbage1", "not a multiple of 16"),
        ("empty.npz", None, "0 landmark"),
    ],
)
def test_malformed_inputs_give_one_line_naming_the_file(synth, tmp_path, name, content, expect):
    path = tmp_path / name
    if content is None:
        LandmarkSet.empty().save(path)
    else:
        path.write_bytes(content)
    res = run("register", path, synth["target"], "-o", tmp_path / "r.json", code=1)
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and expect in lines[0], res.stderr
    assert name in lines[0] or "source" in lines[0]


def test_calibrate_camera_depth_from_files(tmp_path):
    import cv2

    from graffmatch.calibration.rig import make_camera_depth_scenario

    sc = make_camera_depth_scenario(1)
    cv2.imwrite(str(tmp_path / "rgb.png"), cv2.cvtColor(sc.image, cv2.COLOR_RGB2BGR))
    depth_mm = np.round(np.nan_to_num(sc.depth, nan=0.0) * 1000).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "depth.png"), depth_mm)  # 16-bit PNG in millimetres
    np.savetxt(tmp_path / "K.txt", sc.camera.K)
    Kd = sc.depth_camera.K
    b = sc.board
    run(
        "calibrate",
        "--image",
        tmp_path / "rgb.png",
        "--camera-k",
        tmp_path / "K.txt",
        "--depth",
        tmp_path / "depth.png",
        "--depth-k",
        f"{Kd[0, 0]},{Kd[1, 1]},{Kd[0, 2]},{Kd[1, 2]}",
        "--board",
        f"{b.cols}x{b.rows}x{b.square}",
        "-o",
        tmp_path / "cd.json",
    )
    data = json.loads((tmp_path / "cd.json").read_text())
    rot, trans = transform_errors(np.asarray(data["T_depth_camera"]), sc.T_depth_camera)
    assert rot <= 1.0 and trans <= 0.05
    res = run("calibrate", "--image", tmp_path / "rgb.png", "--board", "7x5", code=1)
    assert "--camera-k" in res.stderr or "COLSxROWSxSQUARE" in res.stderr
