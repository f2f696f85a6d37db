"""Loop-closure building blocks: descriptor invariance, compact database, file round-trips,
exclusion window, retrieval exactness, pose graph."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from graffmatch.errors import InvalidInputError, MalformedFileError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.geometry.pose_files import read_kitti, read_tum, write_kitti, write_tum
from graffmatch.geometry.transforms import invert
from graffmatch.loops import (
    DescriptorConfig,
    LandmarkDatabase,
    LoopClosure,
    LoopDetector,
    RetrievalConfig,
    eligible_count,
    landmark_descriptor,
    make_retriever,
)
from graffmatch.loops.database import decode_landmarks, encode_landmarks, landmarks_to_bytes
from graffmatch.loops.io import loop_edges, read_g2o, read_loops_csv, write_g2o, write_loops_csv
from graffmatch.loops.posegraph import drifted_odometry, optimize_pose_graph, trajectory_errors


def _place(seed: int, n_poles: int = 14, n_planes: int = 10) -> LandmarkSet:
    rng = np.random.default_rng(seed)
    types = [LandmarkType.LINE] * n_poles + [LandmarkType.PLANE] * n_planes
    dirs = np.concatenate(
        [np.tile([0.0, 0.0, 1.0], (n_poles, 1)) + 0.02 * rng.standard_normal((n_poles, 3)),
         np.c_[np.cos(a := rng.uniform(0, np.pi, n_planes)), np.sin(a), 0.05 * rng.standard_normal(n_planes)]]
    )
    anchors = rng.uniform([-30, -30, -1], [30, 30, 4], (n_poles + n_planes, 3))
    attrs = {"extent": rng.uniform(1, 50, n_poles + n_planes), "support": rng.integers(30, 900, n_poles + n_planes).astype(float)}
    return LandmarkSet.from_arrays(types, dirs, anchors, attrs)


def _T(yaw_deg: float, t, tilt_deg: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zx", [yaw_deg, tilt_deg], degrees=True).as_matrix()
    T[:3, 3] = t
    return T


def test_descriptor_is_rotation_invariant_and_separates_places():
    ls = _place(0)
    d0 = landmark_descriptor(ls)
    assert d0.shape == (DescriptorConfig().size,) and d0.dtype == np.float32
    for yaw, tilt in ((180.0, 0.0), (37.0, 0.0), (90.0, 20.0)):
        d1 = landmark_descriptor(ls.transform(_T(yaw, [0, 0, 0], tilt)))
        assert np.max(np.abs(d1 - d0)) < 1e-5
    # a 3 m move changes only the range blocks, a little; another place changes everything
    near = np.linalg.norm(landmark_descriptor(ls.transform(_T(180, [3.0, 0, 0]))) - d0)
    other = min(np.linalg.norm(landmark_descriptor(_place(s)) - d0) for s in range(1, 6))
    assert near < 0.5 * other


def test_compact_database_round_trip_and_size():
    ls = _place(1)
    back = decode_landmarks(encode_landmarks(ls))
    assert back.approx_equal(ls, atol=1e-5)
    np.testing.assert_allclose(back.attributes["extent"], ls.attributes["extent"], rtol=1e-6)
    assert len(landmarks_to_bytes(ls)) < 2500  # 24 landmarks
    with pytest.raises(MalformedFileError):
        decode_landmarks(np.zeros((3, 5)))


def test_exclusion_window_in_seconds_and_frames():
    t = np.arange(100) * 0.5
    cfg = RetrievalConfig(exclude_seconds=10.0)
    assert eligible_count(t, 50, cfg) == 31  # scans 0..30 are >= 10 s older than scan 50
    assert eligible_count(t, 10, cfg) == 0
    cfg = RetrievalConfig(exclude_seconds=0.0, exclude_frames=25)
    assert eligible_count(t, 50, cfg) == 25


def test_descriptor_retrieval_is_exact_knn_over_eligible_prefix():
    rng = np.random.default_rng(0)
    db = LandmarkDatabase()
    ls = _place(2)
    X = rng.standard_normal((300, 8)).astype(np.float32)
    for i in range(300):
        db.add(ls, X[i], float(i))
    cfg = RetrievalConfig(top_k=5, exclude_seconds=20.0)
    r = make_retriever(cfg)
    for q in (30, 100, 101, 180, 299):
        m = eligible_count(db.timestamps, q, cfg)
        idx, _ = r.candidates(db, q, m)
        brute = np.argsort(np.linalg.norm(X[:m] - X[q], axis=1), kind="stable")[:5]
        assert idx.tolist() == brute.tolist()
        assert np.all(idx < q - 19)
    with pytest.raises(InvalidInputError):
        db.add(ls, np.zeros(3, np.float32), 301.0)


def _loop(q, m, T, conf=0.8):
    return LoopClosure(q, m, T, conf, 0.7, 12, 9, 0, 0.1, True, info={"rms_offset": 0.08})


def test_files_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    Ts = [_T(rng.uniform(-180, 180), rng.uniform(-10, 10, 3), rng.uniform(-3, 3)) for _ in range(4)]
    loops = [_loop(50 + k, k, T, 0.5 + 0.1 * k) for k, T in enumerate(Ts)]
    back = read_loops_csv(write_loops_csv(tmp_path / "loops.csv", loops))
    assert [(b.query, b.match, b.n_associations) for b in back] == [(a.query, a.match, 12) for a in loops]
    for a, b in zip(loops, back, strict=True):
        np.testing.assert_allclose(b.T_match_query, a.T_match_query, atol=1e-7)
        assert b.confidence == pytest.approx(a.confidence, abs=1e-6)
    poses = np.stack([_T(10 * i, [i, 2 * i, 0.1 * i]) for i in range(60)])
    edges = loop_edges(loops)
    verts, e2 = read_g2o(write_g2o(tmp_path / "l.g2o", edges, poses))
    assert len(verts) == 60 and len(e2) == 4
    np.testing.assert_allclose(verts[7], poses[7], atol=1e-7)
    for (i, j, T, info), (i2, j2, T2, info2) in zip(edges, e2, strict=True):
        assert (i, j) == (i2, j2)
        np.testing.assert_allclose(T2, T, atol=1e-7)
        np.testing.assert_allclose(info2, info, rtol=1e-6)
        assert np.all(np.linalg.eigvalsh(info2) > 0)
    np.testing.assert_allclose(read_kitti(write_kitti(tmp_path / "k.txt", poses)), poses, atol=1e-7)
    t, P = read_tum(write_tum(tmp_path / "t.txt", poses, np.arange(60) * 0.1))
    np.testing.assert_allclose(P, poses, atol=1e-7)
    np.testing.assert_allclose(t, np.arange(60) * 0.1)
    (tmp_path / "bad.g2o").write_text("EDGE_SE3:QUAT 1 2 0 0 0\n")
    with pytest.raises(MalformedFileError, match="bad.g2o:1"):
        read_g2o(tmp_path / "bad.g2o")


def _square_drive(laps: int = 2, side: int = 40) -> np.ndarray:
    """A square loop driven ``laps`` times, 1 m a step."""
    poses = []
    for _ in range(laps):
        for k in range(4):
            for s in range(side):
                x, y = [(s, 0), (side, s), (side - s, side), (0, side - s)][k]
                poses.append(_T(90 * k, [x, y, 0]))
    return np.stack(poses)


def test_pose_graph_removes_drift_with_true_loops():
    gt = _square_drive()
    odo = drifted_odometry(gt)
    n = len(gt)
    edges = []
    for q in range(160, n, 4):  # second lap: same place one lap earlier
        Tmq = invert(gt[q - 160]) @ gt[q]
        edges.append(_loop(q, q - 160, Tmq))
    opt, info = optimize_pose_graph(odo, loop_edges(edges))
    before, after = trajectory_errors(odo, gt), trajectory_errors(opt, gt)
    assert before["ate_rmse_m"] > 0.3
    assert after["ate_rmse_m"] < before["ate_rmse_m"] / 3
    assert info["error_after"] < info["error_before"]
    # one wrong loop (30 m off) is absorbed by the Cauchy kernel
    bad = _loop(300, 20, _T(90, [30, 0, 0]))
    opt2, _ = optimize_pose_graph(odo, loop_edges([*edges, bad]))
    assert trajectory_errors(opt2, gt)["ate_rmse_m"] < before["ate_rmse_m"] / 2


def _drive_with_loops_at_its_end() -> np.ndarray:
    """120 m of road (straight, a bend, straight), then a 30 m square driven twice: every
    revisit, hence every loop, lies in the last third of the drive."""
    poses, yaw, xy = [], 0.0, np.zeros(2)
    turns = [0.0] * 50 + [90.0 / 20] * 20 + [0.0] * 50 + ([0.0] * 29 + [90.0]) * 8
    for dyaw in turns:
        poses.append(_T(yaw, [xy[0], xy[1], 0.0]))
        xy = xy + [np.cos(np.radians(yaw)), np.sin(np.radians(yaw))]
        yaw += dyaw
    return np.stack(poses)


def test_pose_graph_estimates_the_heading_bias_that_loops_at_the_end_observe():
    """Loops only at the end of a drive: a plain pose graph cannot correct the stretch before
    them (ATE stays above a third of the odometry's); with the drive's heading-rate bias
    estimated from those loops (the default) it does, and the bias comes out near the
    simulated 3 deg / 100 m."""
    from graffmatch.loops.posegraph import OdometryDriftConfig, PoseGraphConfig

    gt = _drive_with_loops_at_its_end()
    n = len(gt)
    edges = []
    for q in range(120 + 120, n, 3):  # second lap of the square: the same place one lap earlier
        edges.append(_loop(q, q - 120, invert(gt[q - 120]) @ gt[q]))
    odo = drifted_odometry(gt, OdometryDriftConfig(seed=1))
    before = trajectory_errors(odo, gt)["ate_rmse_m"]
    plain, _ = optimize_pose_graph(odo, loop_edges(edges), PoseGraphConfig(estimate_odometry_bias=False))
    biased, info = optimize_pose_graph(odo, loop_edges(edges))
    after_plain = trajectory_errors(plain, gt)["ate_rmse_m"]
    after = trajectory_errors(biased, gt)["ate_rmse_m"]
    assert before > 0.5
    assert after_plain > before / 3  # the limitation the bias fixes
    assert after < before / 3 and after < after_plain / 2
    assert info["odometry_heading_bias_deg_per_100m"] == pytest.approx(3.0, abs=1.0)
    # without loops nothing is estimated and the odometry comes back unchanged
    same, info0 = optimize_pose_graph(odo, [])
    assert "odometry_heading_bias_deg_per_100m" not in info0
    np.testing.assert_allclose(same[:, :3, 3], odo[:, :3, 3], atol=1e-6)


def test_bias_projection_solver_matches_the_joint_custom_factor_graph():
    """The default bias solver (plain C++ graphs + a secant on the bias, which scales like the
    plain graph) reaches the joint graph's optimum (one Python custom factor per odometry edge,
    O(n^2) in GTSAM): same bias to 0.01 deg / 100 m and poses to 2 mm, in a few solves."""
    from graffmatch.loops.posegraph import OdometryDriftConfig, PoseGraphConfig

    gt = _drive_with_loops_at_its_end()
    edges = loop_edges([_loop(q, q - 120, invert(gt[q - 120]) @ gt[q]) for q in range(240, len(gt), 3)])
    odo = drifted_odometry(gt, OdometryDriftConfig(seed=3))
    proj, info = optimize_pose_graph(odo, edges)
    joint, info_j = optimize_pose_graph(odo, edges, PoseGraphConfig(bias_solver="joint"))
    assert info["bias_converged"] and info["bias_solves"] <= 6
    assert info["odometry_heading_bias_deg_per_100m"] == pytest.approx(
        info_j["odometry_heading_bias_deg_per_100m"], abs=0.01)
    np.testing.assert_allclose(proj[:, :3, 3], joint[:, :3, 3], atol=2e-3)
    assert info["error_after"] == pytest.approx(info_j["error_after"], rel=1e-4)
    assert trajectory_errors(proj, gt)["ate_rmse_m"] < trajectory_errors(odo, gt)["ate_rmse_m"] / 3


def test_bias_odometry_factor_jacobians_match_finite_differences():
    import gtsam

    from graffmatch.loops.posegraph import BIAS_KEY, _odometry_bias_factor

    rng = np.random.default_rng(4)
    Z, Xi, Xj = (_T(rng.uniform(-180, 180), rng.normal(size=3) * 3, rng.uniform(-10, 10)) for _ in range(3))
    f = _odometry_bias_factor(gtsam, 0, 1, Z, 1.3, gtsam.noiseModel.Unit.Create(6))

    def values(d):
        v = gtsam.Values()
        v.insert(0, gtsam.Pose3(Xi).retract(d[:6]))
        v.insert(1, gtsam.Pose3(Xj).retract(d[6:12]))
        v.insert(BIAS_KEY, np.array([5e-3 + d[12]]))
        return v

    A, _ = f.linearize(values(np.zeros(13))).jacobian()
    e0 = f.unwhitenedError(values(np.zeros(13)))
    num = np.stack([(f.unwhitenedError(values(1e-6 * np.eye(13)[k])) - e0) / 1e-6 for k in range(13)], axis=1)
    np.testing.assert_allclose(A, num, atol=1e-4)


def test_quick_check_finds_a_moved_place_and_rejects_another():
    """The BEV voting check: the same place seen after a yaw (incl. reverse direction), a
    translation and a small tilt scores nearly every landmark and recovers the motion; an
    unrelated place scores a small fraction; the index never depends on the query."""
    from graffmatch.loops.quickcheck import quick_check, quick_index

    a = _place(0)
    ia = quick_index(a)
    assert len(ia.poles) == 14 and len(ia.facade_angle) == 10
    for yaw, t, tilt in ((0.0, [0, 0, 0], 0.0), (180.0, [3.0, -2.0, 0.1], 0.0), (73.0, [-4.0, 1.0, 0.0], 1.5)):
        T = _T(yaw, t, tilt)  # pose of the second sensor in the first one's frame
        b = a.transform(invert(T))
        score, est = quick_check(quick_index(b), ia)
        assert score >= 0.9 * ia.size, (yaw, score)
        # est maps b's BEV into a's: the yaw and translation of T (levelling absorbs the tilt)
        assert abs(np.angle(np.exp(1j * (est[0] - np.radians(yaw))))) < np.radians(3.0)
        assert np.hypot(*(est[1:] - np.asarray(t[:2]))) < 0.5
    other = quick_index(_place(1))
    s_other, _ = quick_check(other, ia)
    assert s_other < 0.4 * min(other.size, ia.size), s_other


def test_quick_gate_and_early_stop_keep_the_accepted_candidate():
    """verify_query: a candidate the quick check rejects is not verified; the true place is
    verified first whatever its retrieval rank, and verification stops once it is accepted."""
    from graffmatch.datasets.landmark_scene import make_scene_pair
    from graffmatch.loops.detector import LoopDetector, LoopDetectorConfig
    from graffmatch.loops.plan import verify_query
    from graffmatch.loops.quickcheck import quick_index

    pair = make_scene_pair(seed=0, translation=(3.0, 1.0, 0.0))  # reverse direction, 3 m apart
    maps = {0: pair.source, 1: make_scene_pair(seed=10).target, 2: make_scene_pair(seed=12).target,
            3: pair.target}
    det = LoopDetector(LoopDetectorConfig())
    cands = [(1, 0.1), (2, 0.2), (3, 0.3)]  # the true place retrieved last
    recs = verify_query(0, cands, maps.__getitem__, lambda i: quick_index(maps[i]), det.matcher,
                        det.config.verification)
    by = {r["match"]: r for r in recs}
    assert [r["rank"] for r in recs] == [0, 1, 2]
    assert by[3]["verified"] and by[3]["confidence"] >= 0.5
    assert not by[1]["quick_pass"] and not by[1]["verified"] and by[1]["T"] is None
    assert not by[2]["verified"] and by[3]["quick_score"] > 3 * max(by[1]["quick_score"], by[2]["quick_score"])
    off = det.config.verification.model_copy(update={"quick_check": False, "stop_when_accepted": False})
    recs_all = verify_query(0, cands, maps.__getitem__, None, det.matcher, off)
    assert all(r["verified"] for r in recs_all)
    assert max(recs_all, key=lambda r: r["confidence"])["match"] == 3


def test_batched_quick_check_equals_the_numpy_reference():
    """The compiled batch pass (quick_check_many) gives the NumPy reference's score and estimate
    for every candidate: moved copies, unrelated places, facade-only, pole-only and empty maps,
    and a Manhattan layout (all corners at 90 deg: thousands of tied corner votes)."""
    from graffmatch.loops.quickcheck import quick_check_many, quick_check_numpy, quick_index

    def manhattan(seed: int) -> LandmarkSet:
        ls = _place(seed, n_poles=8, n_planes=14)
        rng = np.random.default_rng(seed)
        d = ls.directions.copy()
        planes = ls.types == LandmarkType.PLANE
        ang = rng.choice([0.0, np.pi / 2], planes.sum()) + 0.3
        d[planes] = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], axis=1)
        bases = ls.bases.copy()
        bases[planes, :, 0] = np.stack([-np.sin(ang), np.cos(ang), np.zeros_like(ang)], axis=1)
        bases[planes, :, 1] = [0.0, 0.0, 1.0]
        return LandmarkSet(ls.types, bases, ls.anchors, dict(ls.attributes))

    q = _place(0)
    maps = [q.transform(invert(_T(yaw, t, 0.0))) for yaw, t in ((0, [0, 0, 0]), (180, [3, -2, 0]), (73, [-4, 1, 0]))]
    maps += [_place(s) for s in (1, 2, 3)] + [_place(4, n_poles=0), _place(5, n_planes=0), _place(6, 0, 0)]
    maps += [manhattan(s) for s in (7, 8)]
    idx = [quick_index(m) for m in maps]
    for qi in (quick_index(q), quick_index(manhattan(7)), idx[-3]):
        scores, est = quick_check_many(qi, idx)
        assert len(scores) == len(idx)
        for c, s, e in zip(idx, scores, est, strict=True):
            s_ref, e_ref = quick_check_numpy(qi, c)
            assert s == s_ref
            np.testing.assert_allclose(e, e_ref, atol=1e-9)
    assert scores[:3].min() >= 0 and quick_check_many(quick_index(q), [])[0].shape == (0,)
    s_moved = quick_check_many(quick_index(q), idx[:3])[0]
    assert s_moved.min() >= 0.9 * idx[0].size


def test_worker_scan_cache_is_bounded_and_reset_per_database():
    """A worker keeps each scan's landmarks/index across chunks (made once), drops the least
    recently used beyond its bound, and forgets everything when the run or database changes."""
    from collections import OrderedDict

    from graffmatch.loops.sequence import _ScanCache

    c = _ScanCache(max_scans=3)
    c.reset(("run", "db1"))
    made = []
    get = lambda i: c.get(c.landmarks, i, lambda: made.append(i) or f"map{i}")  # noqa: E731
    assert [get(i) for i in (0, 1, 0, 2, 3)] == ["map0", "map1", "map0", "map2", "map3"]
    assert made == [0, 1, 2, 3] and list(c.landmarks) == [0, 2, 3]  # 1 was the least recently used
    get(0)
    assert made == [0, 1, 2, 3]
    c.reset(("run", "db1"))
    assert len(c.landmarks) == 3
    c.reset(("run", "db2"))
    assert c.landmarks == OrderedDict() and c.quick == OrderedDict()


def test_loop_confidence_place_margin_and_landmark_poor_rule():
    """loop_confidence (the one rule of the detector, the CLI and the benchmark): a loop estimated
    inside the place radius but within place_margin_m of it scores 0; with few agreeing
    landmarks a loop scores only when the verified matcher's confidence reaches the gate."""
    from graffmatch.loops.verify import VerificationConfig, loop_confidence, required_agreeing

    cfg = VerificationConfig(max_translation_m=5.0, place_margin_m=0.1, min_agreeing=6,
                             few_landmarks_min_agreeing=3, few_landmarks_matcher_confidence=0.9)
    # geometric mean of the agreement fraction and the matcher's confidence
    assert loop_confidence(True, 0.81, 8, 0.64, 4.85, cfg) == pytest.approx(0.72)
    assert loop_confidence(True, 0.81, 8, 0.64, 4.95, cfg) == 0.0  # inside 5 m, not by the margin
    assert loop_confidence(True, 0.81, 8, 0.64, 5.2, cfg) == 0.0
    assert loop_confidence(False, 0.81, 8, 0.64, 2.0, cfg) == 0.0  # the matcher said invalid
    # 3 agreeing landmarks of a 4-landmark map: enough only when the matcher is confident
    assert required_agreeing(0.95, cfg) == 3 and required_agreeing(0.85, cfg) == 6
    assert required_agreeing(None, cfg) == 6
    assert loop_confidence(True, 0.95, 3, 0.75, 2.0, cfg) == pytest.approx(np.sqrt(0.75 * 0.95))
    assert loop_confidence(True, 0.85, 3, 0.75, 2.0, cfg) == 0.0
    assert loop_confidence(True, 0.95, 2, 0.5, 2.0, cfg) == 0.0
    # without a place radius the margin plays no part; without the gate min_agreeing always holds
    free = cfg.model_copy(update={"max_translation_m": None, "few_landmarks_matcher_confidence": None})
    assert loop_confidence(True, 0.81, 8, 0.64, 40.0, free) == pytest.approx(0.72)
    assert loop_confidence(True, 0.99, 5, 0.9, 2.0, free) == 0.0
    with pytest.raises(ValueError):
        VerificationConfig(place_margin_m=-0.1)
    # verified on points (both scans kept their evidence points): points_min_agreeing applies
    pts = free.model_copy(update={"points_min_agreeing": 3})
    assert required_agreeing(0.5, pts, on_points=True) == 3 and required_agreeing(0.5, pts) == 6
    assert loop_confidence(True, 0.64, 3, 1.0, 2.0, pts, on_points=True) == pytest.approx(0.8)
    assert loop_confidence(True, 0.64, 3, 1.0, 2.0, pts) == 0.0
    # the default (chosen on the calibration drives: 4 let a wrong downtown loop through) is min_agreeing
    assert VerificationConfig().points_min_agreeing == VerificationConfig().min_agreeing == 6


def test_place_margin_rejects_a_verified_loop_at_the_radius():
    """verify_candidate: a loop 4.95 m away (estimated within centimetres) is reported with a 5 m
    radius and no margin, and rejected with a 0.1 m margin; at 3 m both report it."""
    from graffmatch.datasets.landmark_scene import make_scene_pair
    from graffmatch.loops.detector import LoopDetector, LoopDetectorConfig
    from graffmatch.loops.verify import verify_candidate

    det = LoopDetector(LoopDetectorConfig())
    for dist, want_margin in ((4.95, False), (3.0, True)):
        pair = make_scene_pair(seed=0, translation=(dist, 0.0, 0.0))
        base = det.config.verification.model_copy(update={"max_translation_m": 5.0, "place_margin_m": 0.0})
        v0 = verify_candidate(pair.source, pair.target, det.matcher, base)
        assert abs(np.linalg.norm(v0["T_match_query"][:3, 3]) - dist) < 0.03
        assert v0["confidence"] >= 0.5
        v1 = verify_candidate(pair.source, pair.target, det.matcher, base.model_copy(update={"place_margin_m": 0.1}))
        assert (v1["confidence"] == v0["confidence"]) if want_margin else (v1["confidence"] == 0.0)


def test_loop_database_skips_the_range_image_it_would_drop(shared_data):
    """LoopDetector extracts without the whole-scan range image: the stored tables are byte for
    byte those of an extraction that computes it (the database keeps no points)."""
    from graffmatch.lidar.extractor import LandmarkExtractor
    from graffmatch.lidar.io import read_points

    det = LoopDetector()
    assert det.extractor.config.scan_ranges is False and det.config.extractor.scan_ranges is True
    pts = read_points(shared_data / "kitti00_first6" / "velodyne" / "000000.bin")
    full = LandmarkExtractor(det.config.extractor).extract(pts)
    assert full.scan_ranges is not None
    lean = det.extractor.extract(pts)
    assert lean.scan_ranges is None
    (a, da), (b, db) = det.prepare(full), det.prepare(lean)
    assert landmarks_to_bytes(a) == landmarks_to_bytes(b) and np.array_equal(da, db)



def test_evidence_points_codec_is_exact_on_its_grid_and_compact(tmp_path):
    """Stored evidence points: on the 5 cm grid (error <= 2.5 cm), decoded bit for bit again,
    far coordinates survive the modulo-2^16 deltas, and 1,500 points of a street cost < 4 kB."""
    from graffmatch.loops.database import (
        POINT_QUANTUM_M,
        decode_points,
        encode_points,
        load_landmarks,
        save_landmarks,
        with_evidence_points,
    )

    rng = np.random.default_rng(3)
    facade = np.c_[rng.uniform(-40, 40, 1200), np.full(1200, 7.0) + 0.02 * rng.standard_normal(1200),
                   rng.uniform(-1, 8, 1200)]
    poles = np.c_[np.repeat(rng.uniform(-30, 30, (6, 2)), 50, axis=0), np.tile(np.linspace(0, 4, 50), 6)]
    P = np.r_[facade, poles]
    code = encode_points(P)
    assert code.dtype == np.int16 and code.shape == (3, len(P))
    back = decode_points(code)
    assert np.abs(np.sort(back, axis=0) - np.sort(P, axis=0)).max() <= POINT_QUANTUM_M / 2 + 1e-6
    assert np.array_equal(decode_points(encode_points(back)), back)  # idempotent on the grid
    far = np.array([[1599.0, -1599.0, 3.0], [-1599.0, 1599.0, -3.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(np.sort(decode_points(encode_points(far)), axis=0), np.sort(far, axis=0), atol=1e-3)
    assert len(decode_points(encode_points(np.array([[5000.0, 0, 0], [1.0, 2.0, 3.0]])))) == 1  # out of range
    ls = with_evidence_points(_place(4, 4, 2), back)
    assert ls.points is not None and ls.point_offsets[0] == 0 and ls.point_offsets[-1] == len(P)
    assert len(landmarks_to_bytes(ls)) < 4000
    save_landmarks(tmp_path / "a.npz", ls)
    again = load_landmarks(tmp_path / "a.npz")
    assert np.array_equal(again.points, back) and again.approx_equal(ls, atol=1e-5)
    save_landmarks(tmp_path / "b.npz", _place(4))
    assert load_landmarks(tmp_path / "b.npz").points is None
    np.savez(tmp_path / "c.npz", landmarks=encode_landmarks(_place(4)), points=np.zeros((2, 4), np.int16))
    with pytest.raises(MalformedFileError, match="c.npz"):
        load_landmarks(tmp_path / "c.npz")


def test_landmark_poor_scans_keep_their_evidence_points():
    """prepare(): a map with fewer landmarks than evidence_points_below keeps the matcher's
    evidence cloud (voxelised non-ground support, on the storage grid), a richer one does not,
    and 0 turns it off; the database's bytes per scan count the points."""
    from graffmatch.loops import LoopDetectorConfig

    rng = np.random.default_rng(5)
    poor = _place(6, 3, 2)
    pts = np.c_[rng.uniform(-40, 40, 3000), np.where(rng.random(3000) < 0.5, -8.0, 8.0),
                rng.uniform(0, 9, 3000)]  # two facades of a street
    off = np.linspace(0, 3000, len(poor) + 1).astype(np.int64)
    poor = LandmarkSet(poor.types, poor.bases, poor.anchors, poor.attributes, pts, off)
    rich = LandmarkSet(*(getattr(_place(7), k) for k in ("types", "bases", "anchors", "attributes")),
                       pts, np.linspace(0, 3000, 25).astype(np.int64))
    cfg = LoopDetectorConfig()
    det = LoopDetector(cfg)
    assert cfg.verification.evidence_points_below > len(poor)
    kept, _ = det.prepare(poor)
    v = cfg.matcher.verification
    assert kept.points is not None and len(kept.points) == min(v.max_points, len(det.evidence_points(poor)))
    assert 0.9 * v.max_points <= len(kept.points) <= v.max_points
    assert det.prepare(rich)[0].points is None
    off_cfg = LoopDetectorConfig()
    off_cfg.verification.evidence_points_below = 0
    assert LoopDetector(off_cfg).prepare(poor)[0].points is None
    db = LandmarkDatabase()
    db.add(kept, np.zeros(4, np.float32), 0.0)
    assert 2000 < db.bytes_per_scan() < 5000
