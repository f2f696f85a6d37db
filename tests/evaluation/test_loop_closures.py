"""Loop-closure dataset builder: places, revisits, GT matches, IIR cases, validity, format."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from graffmatch.datasets import KittiFolder
from graffmatch.errors import InvalidInputError, MalformedFileError
from graffmatch.evaluation.loop_closures import (
    LoopClosureConfig,
    LoopClosureDataset,
    build_loop_closure_dataset,
    check_validity,
    find_revisits,
    ground_truth_matches,
    iir_case,
    keep_most_salient,
    path_lengths,
    possible_matches,
    select_places,
)
from graffmatch.evaluation.suites import SUITES, build_suite, suite_config
from graffmatch.geometry.distance import cross_distances
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.geometry.transforms import (
    invert,
    make_transform,
    random_transform,
    rot_x,
    rot_z,
)


def _trajectory(xy: np.ndarray, yaw: np.ndarray | None = None) -> np.ndarray:
    T = np.tile(np.eye(4), (len(xy), 1, 1))
    T[:, :2, 3] = xy
    if yaw is not None:
        T[:, :3, :3] = np.stack([rot_z(a) for a in yaw])
    return T


def _square_loop(side: float = 30.0, step: float = 0.5, laps: float = 1.5) -> np.ndarray:
    """Counter-clockwise square, sampled every ``step`` of path."""
    perim = 4 * side
    s = np.arange(0, laps * perim + 1e-9, step)
    u = np.mod(s, perim)
    k, r = np.floor(u / side), np.mod(u, side)
    corners = np.array([[0, 0], [side, 0], [side, side], [0, side], [0, 0]], dtype=float)
    d = corners[k.astype(int) + 1] - corners[k.astype(int)]
    return corners[k.astype(int)] + d / side * r[:, None]


# ---- places and revisits -----------------------------------------------------------------
def test_places_every_2m_and_revisits_match_brute_force() -> None:
    poses = _trajectory(_square_loop())
    places = select_places(poses, 2.0)
    s = path_lengths(poses)
    assert np.allclose(s[places], 2.0 * np.arange(len(places)))  # exact on a 0.5 m grid
    assert len(places) == 91  # 180 m of path
    revisits = find_revisits(poses, places, 50.0, 16.0)
    X = poses[:, :3, 3]
    expected = sorted(
        (int(p), int(q))
        for p in places
        for q in places
        if q < p and s[p] - s[q] > 50.0 and np.linalg.norm(X[p] - X[q]) < 16.0
    )
    assert [tuple(r) for r in revisits.tolist()] == expected
    # The second half lap revisits the first (same positions, 120 m of path apart) ...
    assert (int(np.flatnonzero(s == 130.0)[0]), int(np.flatnonzero(s == 10.0)[0])) in expected
    # ... and neighbours along one side (< 16 m apart, < 50 m of path) are not revisits.
    assert all(s[p] - s[q] > 50.0 for p, q in expected)
    # A straight drive has no revisits; the wide-baseline rule adds pairs 5-16 m apart.
    line = _trajectory(np.column_stack([np.arange(0, 100, 0.5), np.zeros(200)]))
    pl = select_places(line, 2.0)
    assert len(find_revisits(line, pl)) == 0
    wide = find_revisits(line, pl, 50.0, 16.0, wide_baseline_min_distance=5.0)
    d = np.linalg.norm(line[wide[:, 0], :3, 3] - line[wide[:, 1], :3, 3], axis=1)
    assert len(wide) > 0 and d.min() >= 5.0 and d.max() < 16.0 and np.all(wide[:, 0] > wide[:, 1])


@given(
    steps=st.lists(st.floats(0.0, 1.5), min_size=2, max_size=200),
    spacing=st.floats(0.5, 5.0),
)
def test_place_spacing_property(steps: list[float], spacing: float) -> None:
    x = np.concatenate([[0.0], np.cumsum(steps)])
    poses = _trajectory(np.column_stack([x, np.zeros_like(x)]))
    places = select_places(poses, spacing)
    gaps = np.diff(x[places])
    assert places[0] == 0 and np.all(np.diff(places) > 0)
    assert np.all(gaps >= spacing - 1e-6) and np.all(gaps < spacing + 1.5 + 1e-6)
    # No scan after the last place is a full spacing away from it.
    assert x[-1] - x[places[-1]] < spacing + 1.5


# ---- ground-truth matches ----------------------------------------------------------------
def _scene(rng: np.random.Generator, n_lines: int = 6, n_planes: int = 8) -> LandmarkSet:
    """Lines (poles) and planes (walls in 4 orientations + ground) spread over 40 m."""
    types = [LandmarkType.LINE] * n_lines + [LandmarkType.PLANE] * n_planes
    dirs = np.zeros((len(types), 3))
    dirs[:n_lines] = [0, 0, 1]
    dirs[:n_lines, :2] = rng.normal(0, 0.03, (n_lines, 2))
    yaw = rng.uniform(0, np.pi, n_planes)
    dirs[n_lines:] = np.column_stack([np.cos(yaw), np.sin(yaw), np.zeros(n_planes)])
    dirs[n_lines] = [0, 0, 1]  # one ground plane
    anchors = rng.uniform(-20, 20, (len(types), 3))
    anchors[:, 2] = rng.uniform(0, 3, len(types))
    return LandmarkSet.from_arrays(types, dirs, anchors)


def test_ground_truth_matches_recover_permutation(rng: np.random.Generator) -> None:
    target = _scene(rng)
    T_ts = make_transform(rot_z(2.5) @ rot_x(0.05), [9.0, -4.0, 0.3])
    perm = rng.permutation(len(target))
    source = target[perm].transform(invert(T_ts))
    # Distractors: the same geometry rotated 20 deg about z in the source, and a point.
    extra = _scene(np.random.default_rng(7), 3, 3).transform(
        make_transform(rot_z(0.35), [50, 0, 0])
    )
    source = LandmarkSet.concatenate([source, extra])
    matches, d = ground_truth_matches(source, target, T_ts, tau_d_deg=6.0, rho=40.0)
    assert len(matches) == len(target)
    assert np.array_equal(np.sort(matches[:, 0]), np.arange(len(target)))
    assert np.array_equal(matches[:, 1], perm[matches[:, 0]])
    assert d.max() < 1e-6
    # Same type only, never an index twice.
    assert np.all(source.types[matches[:, 0]] == target.types[matches[:, 1]])
    assert len(np.unique(matches[:, 1])) == len(matches)
    # A landmark tilted beyond the gate is not matched; within it, it still is.
    for tilt_deg, kept in ((10.0, False), (2.0, True)):
        bent = target.transform(np.eye(4))
        i = 2  # a line
        R = rot_x(np.deg2rad(tilt_deg))
        bent.bases[i] = R @ bent.bases[i]
        m, _ = ground_truth_matches(bent.transform(invert(T_ts)), target, T_ts, 6.0)
        assert ((m[:, 0] == i) & (m[:, 1] == i)).any() == kept
    # With a wrong ground truth there is (almost) nothing to match.
    wrong, _ = ground_truth_matches(source, target, T_ts @ make_transform(rot_z(0.6), [3, 0, 0]))
    assert len(wrong) <= 2


def test_gate_is_applied_on_invariant_distance(rng: np.random.Generator) -> None:
    target = _scene(rng)
    source = target.transform(np.eye(4))
    source.anchors[:] += rng.normal(0, 0.05, source.anchors.shape)
    D = cross_distances(source, target)
    m, d = ground_truth_matches(source, target, np.eye(4), tau_d_deg=6.0)
    assert np.all(d < np.deg2rad(6.0)) and np.allclose(d, D[m[:, 0], m[:, 1]])
    m_tight, _ = ground_truth_matches(source, target, np.eye(4), tau_d_deg=1e-4)
    assert len(m_tight) < len(m)


def test_keep_most_salient(rng: np.random.Generator) -> None:
    ls = _scene(rng, 6, 8)
    ls.attributes["extent"] = np.array([5, 1, 9, 3, 7, 2, 10, 40, 20, 30, 50, 60, 5, 1], float)
    kept = keep_most_salient(ls, 3)
    assert kept.counts() == {"points": 0, "lines": 3, "planes": 3}
    assert sorted(kept.attributes["extent"].tolist()) == [5, 7, 9, 40, 50, 60]
    assert keep_most_salient(ls, None) is ls and len(keep_most_salient(ls, 100)) == len(ls)


# ---- IIR and cases ----------------------------------------------------------------------------
def test_iir_cases_and_possible_matches(rng: np.random.Generator) -> None:
    assert iir_case(0.05) == 1 and iir_case(0.2) == 1
    assert iir_case(0.0499) == 2 and iir_case(0.03) == 2
    assert iir_case(0.0299) == 3 and iir_case(0.0) == 3
    a, b = _scene(rng, 6, 8), _scene(rng, 3, 11)
    assert possible_matches(a, b) == 6 * 3 + 8 * 11
    assert possible_matches(a, LandmarkSet.empty()) == 0
    assert iir_case(0.04, (0.1, 0.05)) == 3
    with pytest.raises(ValueError, match="case_thresholds"):
        LoopClosureConfig(case_thresholds=(0.03, 0.05))
    with pytest.raises(ValueError, match="wide_baseline"):
        LoopClosureConfig(wide_baseline_min_distance=20.0)


# ---- validity -----------------------------------------------------------------------------------
def test_validity_rules(rng: np.random.Generator) -> None:
    cfg = LoopClosureConfig()
    target = _scene(rng)
    T_ts = random_transform(rng, 12.0)
    source = target.transform(invert(T_ts))
    all_m = np.column_stack([np.arange(len(target))] * 2)
    v = check_validity(source, target, all_m, T_ts, cfg)
    assert v.valid and v.kappa < 1e3 and v.rotation_error_deg < 1e-3 and v.translation_error < 1e-3
    assert check_validity(source, target, all_m[:4], T_ts, cfg).reason == "few_matches"
    # Degenerate: only parallel walls (no rotation about their normal, no translation along them).
    walls = LandmarkSet.from_arrays(
        [LandmarkType.PLANE] * 6,
        np.tile([1.0, 0, 0], (6, 1)),
        np.column_stack([np.arange(6.0), rng.uniform(-5, 5, 6), rng.uniform(0, 3, 6)]),
    )
    six = np.column_stack([np.arange(6)] * 2)
    v_deg = check_validity(walls.transform(invert(T_ts)), walls, six, T_ts, cfg)
    assert not v_deg.valid and v_deg.reason in ("degenerate", "ill_conditioned")
    # A ground truth that disagrees with the matches fails the 5 deg / 1 m test.
    v_bad = check_validity(source, target, all_m, T_ts @ make_transform(rot_z(0.2), [0, 0, 0]), cfg)
    assert not v_bad.valid and v_bad.reason == "registration_error" and v_bad.rotation_error_deg > 5


# ---- building on real data and the on-disk format ------------------------------------------------
@pytest.fixture(scope="module")
def balm_build(shared_data: Path, tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("balm_lc")
    ds = KittiFolder(shared_data / "balm_courtyard")
    cfg = LoopClosureConfig(
        place_spacing=3.0,
        max_places=10,
        min_path_length=10.0,
        wide_baseline_min_distance=5.0,
        workers=2,
    )
    # Through the suite entry point (quick, with the test's smaller config) to cover both.
    summary = build_suite(
        "balm_courtyard", out, quick=True, data_root=shared_data, progress=False, config=cfg
    )
    assert summary["suite"] == "balm_courtyard" and summary["quick"]
    return ds, out / "balm_courtyard-quick", cfg, summary


def test_balm_build_and_round_trip(balm_build) -> None:
    ds, out, cfg, summary = balm_build
    assert summary["n_places"] == 10 and summary["cache"]["extracted"] == 10
    assert summary["n_valid"] >= 3, summary
    assert sum(c["pairs"] for c in summary["cases"].values()) == summary["n_valid"]
    assert summary["landmarks_per_place"]["planes"]["mean"] >= 5
    assert (out / "dataset_details.png").stat().st_size > 10_000
    assert len(list((out / "landmarks").glob("*.npz"))) == 10

    lc = LoopClosureDataset.load(out)
    assert len(lc) == summary["n_valid"] and lc.config == cfg
    doc = json.loads((out / "pairs.json").read_text())
    assert doc["format"] == "graffmatch-loop-closures" and doc["version"] == 1
    for pair, raw in zip(lc, doc["pairs"], strict=True):
        src, tgt = pair.source, pair.target
        assert src.points is not None and len(src.points) > 0  # support points for ICP
        assert pair.source_scan_path == ds.scan_path(pair.source_scan).resolve()
        T = invert(ds.poses[pair.target_scan]) @ ds.poses[pair.source_scan]
        assert np.allclose(pair.T_target_source, T, atol=1e-8)
        assert 0 < pair.distance < 16.0 and np.isclose(pair.distance, np.linalg.norm(T[:3, 3]))
        assert pair.n_possible == possible_matches(src, tgt)
        assert np.isclose(pair.iir, len(pair.true_matches) / pair.n_possible)
        assert pair.case == iir_case(pair.iir)
        assert len(pair.true_matches) > 4
        assert pair.n_true_lines + pair.n_true_planes == len(pair.true_matches)
        # The stored matches are the GT-aligned assignment, recomputed from the stored sets.
        m, _ = ground_truth_matches(src, tgt, pair.T_target_source, cfg.tau_d_deg, cfg.rho)
        assert np.array_equal(m, pair.true_matches) and raw["true_matches"] == m.tolist()
        assert check_validity(src, tgt, m, pair.T_target_source, cfg).valid


def test_cache_reuse_and_malformed_files(balm_build, tmp_path: Path) -> None:
    ds, out, cfg, summary = balm_build
    again = build_loop_closure_dataset(ds, out, cfg, progress=False, figure=False)
    assert again["cache"] == {"extracted": 0, "cached": 10}
    assert again["n_valid"] == summary["n_valid"] and again["cases"] == summary["cases"]
    with pytest.raises(InvalidInputError, match=r"no pairs\.json"):
        LoopClosureDataset.load(tmp_path)
    doc = json.loads((out / "pairs.json").read_text())
    doc["version"] = 99
    (tmp_path / "pairs.json").write_text(json.dumps(doc))
    with pytest.raises(MalformedFileError, match="newer"):
        LoopClosureDataset.load(tmp_path)
    doc["version"] = 1
    del doc["pairs"][0]["iir"]
    (tmp_path / "pairs.json").write_text(json.dumps(doc))
    with pytest.raises(MalformedFileError, match="pair 0"):
        LoopClosureDataset.load(tmp_path)


def test_suites_registry(shared_data: Path, tmp_path: Path) -> None:
    assert {"balm_courtyard", "sim-downtown", "sim-suburban", "sim-openroad"} <= set(SUITES)
    for name in ("sim-downtown", "sim-suburban", "sim-openroad"):
        cfg = suite_config(name)
        # the paper's rules; only the front end looks further than the default one
        assert cfg.model_copy(update={"extractor": LoopClosureConfig().extractor}) == LoopClosureConfig()
        assert cfg.extractor.planes.max_range >= 65 and cfg.extractor.planes.min_area <= 8
    cfg = suite_config("balm_courtyard")
    assert cfg.min_path_length == 10.0 and cfg.wide_baseline_min_distance == 5.0
    assert suite_config("balm_courtyard", quick=True).max_places == 16
    with pytest.raises(InvalidInputError, match="unknown suite"):
        build_suite("nope", tmp_path)
