"""The place check (loops/place_check.py): a loop refused by the place radius alone is re-measured on the scans."""

from __future__ import annotations

import numpy as np
import pytest

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.transforms import rotation_error_deg
from graffmatch.loops.place_check import (
    place_check_candidates,
    place_cloud,
    remeasure,
    run_place_check,
)
from graffmatch.loops.verify import VerificationConfig


def _street(rng: np.random.Generator, n: int = 40_000) -> np.ndarray:
    """A street scene in the world frame: ground, two facades with recesses, a cross wall and poles."""
    parts = []
    k = n // 8
    parts.append(np.c_[rng.uniform(-30, 30, k), rng.uniform(-7, 7, k), rng.normal(0, 0.01, k)])
    for y in (-7.0, 7.0):
        x = rng.uniform(-30, 30, 2 * k)
        recess = (np.floor(x / 6) % 2 == 0) * np.sign(y) * 1.5
        parts.append(np.c_[x, y + recess + rng.normal(0, 0.01, 2 * k), rng.uniform(0, 8, 2 * k)])
    parts.append(np.c_[30 + rng.normal(0, 0.01, k), rng.uniform(-7, 7, k), rng.uniform(0, 8, k)])
    for px, py in ((-12, -4), (-3, 4.5), (6, -4), (15, 4.5), (22, -4)):
        a, z = rng.uniform(0, 2 * np.pi, k // 4), rng.uniform(0, 5, k // 4)
        parts.append(np.c_[px + 0.15 * np.cos(a), py + 0.15 * np.sin(a), z])
    return np.concatenate(parts)


def _pose(yaw_deg: float, t: tuple[float, float, float]) -> np.ndarray:
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = t
    return T


def _scans(distance: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(query scan, match scan, true T_match_query): two sensors ``distance`` apart along the street, each seeing
    its own sample of the scene within 25 m."""
    rng = np.random.default_rng(seed)
    W_match, W_query = _pose(0.0, (0.0, 0.0, 1.7)), _pose(8.0, (distance, 0.0, 1.7))

    def scan(W: np.ndarray) -> np.ndarray:
        P = _street(rng)
        P = P[np.linalg.norm(P[:, :2] - W[:2, 3], axis=1) < 25]
        return (P - W[:3, 3]) @ W[:3, :3]

    return scan(W_query), scan(W_match), np.linalg.solve(W_match, W_query)


def _config(**kw) -> VerificationConfig:
    base = {"max_translation_m": 5.0, "place_margin_m": 0.25, "place_check": True, "place_check_band_m": 0.5,
            "place_check_margin_m": 0.1}
    return VerificationConfig(**{**base, **kw})


def _record(match: int, T: np.ndarray, rank: int = 0, confidence: float = 0.9) -> dict:
    return {"match": match, "rank": rank, "T": T.ravel().tolist(), "confidence": 0.0, "seconds": 0.0,
            "radius_confidence": confidence, "radius_T": T.ravel().tolist()}


def _slid(T: np.ndarray, along: float) -> np.ndarray:
    """``T`` with its translation lengthened by ``along`` metres (a landmark estimate just beyond the radius)."""
    S = T.copy()
    S[:3, 3] *= 1 + along / np.linalg.norm(T[:3, 3])
    return S


@pytest.mark.parametrize("distance", [4.6, 4.85])
def test_remeasure_recovers_the_distance_to_centimetres(distance):
    """ICP from an estimate 0.2 m too long (and 1 deg off) lands within 5 cm and 0.2 deg of the true pose (the 0.4 m
    voxels leave a few centimetres along a street: 3 cm here, at most 3.6 cm on three calibration drives)."""
    q, m, T_true = _scans(distance)
    T0 = _slid(T_true, 0.2) @ _pose(1.0, (0.0, 0.0, 0.0))
    T, fit = remeasure(place_cloud(q), place_cloud(m), T0)
    assert abs(np.linalg.norm(T[:3, 3]) - distance) < 0.05
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.05
    assert rotation_error_deg(T[:3, :3], T_true[:3, :3]) < 0.2
    assert fit > 0.5


def test_place_check_accepts_inside_and_refuses_beyond_the_checked_radius():
    """True 4.8 m, estimated 5.05 m: a loop (re-measured <= 4.9 m), with the ICP pose and the verified one kept;
    true 5.0 m, estimated 5.05 m: refused (re-measured > 4.9 m), the record says why."""
    cfg = _config()
    for distance, accepted in ((4.8, True), (5.0, False)):
        q, m, T_true = _scans(distance, seed=1)
        clouds = {0: place_cloud(q), 7: place_cloud(m)}
        T0 = _slid(T_true, 5.05 - distance)
        recs = [_record(7, T0)]
        run_place_check(0, recs, cfg, clouds.get)
        r = recs[0]
        assert r["place_accepted"] is accepted
        assert abs(r["place_distance_m"] - distance) < 0.05
        assert r["place_moved_m"] == pytest.approx(5.05 - distance, abs=0.05)
        if accepted:
            assert r["confidence"] == 0.9
            assert np.linalg.norm(np.asarray(r["T"]).reshape(4, 4)[:3, 3] - T_true[:3, 3]) < 0.05
            assert r["place_T0"] == T0.ravel().tolist()
        else:
            assert r["confidence"] == 0.0 and r["T"] == T0.ravel().tolist()


def test_place_check_refuses_a_pose_the_scans_move_too_far():
    """An estimate 0.45 m off converges onto the true 4.6 m, but the move exceeds a 0.3 m limit: refused."""
    q, m, T_true = _scans(4.6, seed=2)
    clouds = {0: place_cloud(q), 3: place_cloud(m)}
    recs = [_record(3, _slid(T_true, 0.45))]
    run_place_check(0, recs, _config(place_check_max_move_m=0.3), clouds.get)
    assert recs[0]["place_accepted"] is False and recs[0]["confidence"] == 0.0
    assert abs(recs[0]["place_distance_m"] - 4.6) < 0.05


def test_candidates_nearest_first_capped_and_none_when_a_loop_exists():
    """Only records refused by the radius alone and estimated in (4.75, 5.25] (a 0.5 m band from the 4.75 m gate) are
    re-measured, nearest first, at most place_check_max; the default 0.2 m band stops at 4.95 m; a query that already
    has a loop, or a config without the check, re-measures none."""
    cfg = _config(place_check_max=2)
    T = [_pose(0.0, (d, 0.0, 0.0)) for d in (5.2, 4.8, 5.3, 4.7, 5.0)]
    recs = [_record(i, t, rank=i) for i, t in enumerate(T)]
    recs.append({**_record(9, T[1], rank=5), "radius_confidence": 0.3})  # below min_confidence inside the radius too
    assert [r["match"] for r in place_check_candidates(recs, cfg)] == [1, 4]
    assert [r["match"] for r in place_check_candidates(recs, cfg.model_copy(update={"place_check_max": 5}))] == [1, 4, 0]
    assert [r["match"] for r in place_check_candidates(recs, cfg.model_copy(update={"place_check_band_m": 0.2}))] == [1]
    assert VerificationConfig().place_check_band_m == 0.2 and VerificationConfig().place_check  # the default (session 24)
    assert place_check_candidates(recs, cfg.model_copy(update={"place_check": False})) == []
    assert place_check_candidates(recs, cfg.model_copy(update={"max_translation_m": None})) == []
    assert place_check_candidates([*recs, {**_record(8, T[3]), "confidence": 0.8}], cfg) == []


def test_place_check_is_deterministic_and_reads_no_scan_it_does_not_need():
    """The same records give the same pose twice; only the query and the re-measured candidates are read."""
    q, m, T_true = _scans(4.8, seed=3)
    clouds = {0: place_cloud(q), 5: place_cloud(m)}
    read = []

    def cloud_of(i):
        read.append(i)
        return clouds.get(i)

    out = []
    for _ in range(2):
        recs = [_record(5, _slid(T_true, 0.15)), {**_record(6, T_true), "radius_confidence": 0.0}]
        run_place_check(0, recs, _config(), cloud_of)
        out.append(recs[0]["T"])
    assert out[0] == out[1]
    assert sorted(set(read)) == [0, 5]


def test_place_cloud_names_bad_input():
    from graffmatch.loops.place_check import scan_place_cloud

    with pytest.raises(InvalidInputError, match="place check"):
        place_cloud(np.zeros((10, 2)))
    with pytest.raises(InvalidInputError, match="scan 3 is not in the scans given"):
        scan_place_cloud([np.zeros((20, 3))] * 2, 3)
    with pytest.raises(InvalidInputError, match="scan 0 is not in the scans given"):
        scan_place_cloud(None, 0)
    with pytest.raises(InvalidInputError, match="place check"):
        place_cloud(np.array(["a", "b", "c"]).reshape(1, 3))


def test_deskewed_subset_equals_the_rows_of_the_deskewed_scan(shared_data):
    """Deskewed.points_subset de-skews only the picked rows: bit-equal to those rows of the whole de-skewed scan; the
    place check's cloud of a de-skewed drive is made of de-skewed points (KITTI 0-5 wrapped with its own poses)."""
    from graffmatch.datasets.deskewed import Deskewed
    from graffmatch.datasets.folder import KittiFolder
    from graffmatch.loops.place_check import _voxel_rows, scan_place_cloud

    ds = Deskewed(KittiFolder(shared_data / "kitti00_first6"))
    for i in (0, 3, 5):
        assert np.array_equal(ds.dataset.read_points(i), ds.dataset[i].points)  # points alone: the same points
        full = ds[i].points
        rows = _voxel_rows(ds.dataset[i].points)
        assert np.array_equal(ds.points_subset(i, _voxel_rows), full[rows])
        pc = scan_place_cloud(ds, i)
        assert 1000 < len(pc) <= 8000
        full_rows = {tuple(r) for r in np.asarray(full[:, :3], np.float64)}
        assert all(tuple(p) in full_rows for p in pc.points[:200])
    with pytest.raises(InvalidInputError, match="scan 6 is not in the scans given"):
        scan_place_cloud(ds, 6)


@pytest.mark.slow
def test_run_loops_re_measures_a_loop_estimated_beyond_the_radius(tmp_path):
    """A simulated drive with revisits (ground truth known): with the radius set 0.2 m beyond one verified loop's
    estimate, the place check reads the two scans through run_loops' workers and reports that query's loop with the
    ICP pose (within 5 cm of the truth, inside the radius less the check's margin); without the check it stays
    refused; no reported loop lies beyond the radius in truth."""
    import json
    import shutil
    import warnings

    from graffmatch.datasets.registry import open_dataset
    from graffmatch.datasets.simulator import SUITES, TrajectoryConfig, simulate_dataset
    from graffmatch.loops import LoopDetector, LoopDetectorConfig
    from graffmatch.loops.database import load_landmarks
    from graffmatch.loops.io import read_loops_csv
    from graffmatch.loops.sequence import run_loops

    s = SUITES["sim-suburban"]
    ds = open_dataset("folder", simulate_dataset(tmp_path / "d", style=s.style, seed=1, n_scans=70, sensor=s.sensor,
                                                 world_config=s.world_config(),
                                                 trajectory_config=TrajectoryConfig(step_m=2.0)))
    P = np.asarray(ds.poses)
    cfg = LoopDetectorConfig()
    cfg.retrieval.exclude_seconds, cfg.retrieval.exclude_frames = 0.0, 30
    first = run_loops(ds, tmp_path / "any", cfg, workers=1)
    loops = read_loops_csv(tmp_path / "any" / "loops.csv")
    assert first["n_loops"] > 0
    def nearest(q: int) -> int:  # the eligible scan nearest in truth
        return int(np.argmin(np.linalg.norm(P[: q - 29, :3, 3] - P[q, :3, 3], axis=1)))

    # a place (2-8 m), whose match is the query's nearest eligible scan: every other candidate lies beyond it
    near = [c for c in loops if 2.0 <= np.linalg.norm(c.T_match_query[:3, 3]) <= 8.0 and c.match == nearest(c.query)]
    assert near
    lc = max(near, key=lambda c: np.linalg.norm(c.T_match_query[:3, 3]))
    radius = float(np.linalg.norm(lc.T_match_query[:3, 3])) + 0.2

    def config(check: bool) -> LoopDetectorConfig:
        c = cfg.model_copy(deep=True)
        c.verification.max_translation_m, c.verification.place_check = radius, check
        return c

    def run(check: bool) -> tuple[list, dict]:
        out = tmp_path / f"check{check}"
        shutil.copytree(tmp_path / "any" / "landmarks", out / "landmarks")
        run_loops(ds, out, config(check), workers=1)
        recs = {json.loads(line)["query"]: json.loads(line) for line in open(out / "queries.jsonl")}
        return read_loops_csv(out / "loops.csv"), recs

    on, recs_on = run(True)
    off, _ = run(False)
    accepted = [r for r in recs_on[lc.query]["candidates"] if r.get("place_accepted")]
    assert len(accepted) == 1, recs_on[lc.query]
    got = {c.query: c for c in on}[lc.query]
    assert got.match == accepted[0]["match"]
    T_true = np.linalg.solve(P[got.match], P[got.query])
    assert np.linalg.norm(got.T_match_query[:3, 3] - T_true[:3, 3]) < 0.05
    assert np.linalg.norm(got.T_match_query[:3, 3]) <= radius - cfg.verification.place_check_margin_m
    assert lc.query not in {c.query for c in off}
    assert {(c.query, c.match) for c in off} <= {(c.query, c.match) for c in on}
    for c in on:
        assert np.linalg.norm(np.linalg.solve(P[c.match], P[c.query])[:3, 3]) <= radius

    # online: the detector given the drive's scans finds the same loop with the same pose
    det = LoopDetector(config(True), scans=ds)
    online = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for i in range(len(ds)):
            for c in det.add(load_landmarks(tmp_path / "any" / "landmarks" / f"{i:06d}.npz"),
                             timestamp=float(ds.timestamps[i])):
                online[(c.query, c.match)] = c
    assert not [w for w in caught if "no scans were given" in str(w.message)]
    assert np.allclose(online[(got.query, got.match)].T_match_query, got.T_match_query, atol=1e-6)
    blind = LoopDetector(config(True))  # without the scans the check cannot run, and the detector says so, once
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for i in range(lc.query + 1):
            res = blind.add(load_landmarks(tmp_path / "any" / "landmarks" / f"{i:06d}.npz"),
                            timestamp=float(ds.timestamps[i]))
    assert not res
    said = [w for w in caught if "no scans were given" in str(w.message)]
    assert len(said) == 1 and f"{radius} m place radius" in str(said[0].message)


def test_scans_that_say_they_are_motion_smeared_are_not_re_measured(tmp_path):
    """The check's 0.1 m margin rests on motion-compensated scans (session 24: on a raw, smeared drive ICP measured a
    loop 23.5 cm short). Scans that declare smear are refused, with a warning; scans that say nothing are used; no
    scans at all, with the check on, is said too."""
    import json
    import warnings

    from graffmatch.datasets.folder import _simulated_motion_compensated
    from graffmatch.loops.place_check import place_check_scans

    class Scans(list):
        motion_compensated: bool | None = None

    cfg = _config()
    smeared, clean, unknown = Scans([np.zeros((5, 3))]), Scans([np.zeros((5, 3))]), Scans([np.zeros((5, 3))])
    smeared.motion_compensated, clean.motion_compensated = False, True
    with pytest.warns(UserWarning, match="motion-distorted and not de-skewed"):
        assert place_check_scans(smeared, cfg) is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert place_check_scans(clean, cfg) is clean and place_check_scans(unknown, cfg) is unknown
        assert place_check_scans(smeared, cfg.model_copy(update={"place_check": False})) is None
        assert place_check_scans(clean, cfg.model_copy(update={"max_translation_m": None})) is None
    with pytest.warns(UserWarning, match="no scans were given"):  # the check is on but has nothing to read
        assert place_check_scans(None, cfg) is None

    # what a simulated drive's sim_meta.json says
    def meta(d: dict | None, name: str):
        root = tmp_path / name
        root.mkdir()
        if d is not None:
            (root / "sim_meta.json").write_text(json.dumps(d))
        return _simulated_motion_compensated(root)

    assert meta({"realism": {"motion_distortion": True, "deskew": False}}, "raw") is False
    assert meta({"realism": {"motion_distortion": True, "deskew": True}}, "deskewed") is True
    assert meta({"realism": {"motion_distortion": False}}, "ideal") is True
    assert meta({"generator": "x"}, "old") is True
    assert meta(None, "real") is None
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "sim_meta.json").write_text("{not json")
    assert _simulated_motion_compensated(tmp_path / "bad") is None
