"""Every evaluation method on constructed cases whose correct answer is known.

Landmark scenes: poles (vertical cylinders), walls and a ground patch sampled as points, seen
from two poses with independent noise; each view fits its own landmarks (PCA, anchor =
centroid) so anchors and directions differ slightly between views, as in real data. Point
scenes: a ground plane and boxes sampled as points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from graffmatch.errors import InvalidInputError
from graffmatch.evaluation.methods import (
    METHODS,
    TABLE_I_METHODS,
    TABLE_II_METHODS,
    MethodOutput,
    PairInput,
    get_method,
    list_methods,
)
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType, fit_landmark
from graffmatch.geometry.transforms import (
    invert,
    make_transform,
    rot_x,
    rot_z,
    transform_errors,
    transform_points,
)


# ----------------------------------------------------------------------------------------------
# constructed scenes
# ----------------------------------------------------------------------------------------------
@dataclass
class Scene:
    source: LandmarkSet
    target: LandmarkSet
    T_target_source: np.ndarray
    true_matches: np.ndarray  # (k, 2)


def _world_point_sets(
    rng: np.random.Generator, n_poles: int, n_walls: int
) -> list[tuple[int, np.ndarray]]:
    """(kind, points) of every world landmark."""
    out: list[tuple[int, np.ndarray]] = []
    for _ in range(n_poles):
        c = rng.uniform(-30, 30, 2)
        h = rng.uniform(4, 8)
        m = 80
        ang = rng.uniform(0, 2 * np.pi, m)
        z = rng.uniform(-1.8, -1.8 + h, m)
        P = np.c_[c[0] + 0.15 * np.cos(ang), c[1] + 0.15 * np.sin(ang), z]
        out.append((1, P))
    for _ in range(n_walls):
        c = rng.uniform(-30, 30, 2)
        yaw = rng.uniform(0, np.pi)
        w, h = rng.uniform(4, 16), rng.uniform(3, 8)
        m = 200
        s = rng.uniform(-0.5, 0.5, m) * w
        z = rng.uniform(-1.8, -1.8 + h, m)
        t = np.array([np.cos(yaw), np.sin(yaw)])
        out.append((2, np.c_[c[0] + s * t[0], c[1] + s * t[1], z]))
    g = rng.uniform(-20, 20, (400, 2))
    out.append((2, np.c_[g, np.full(len(g), -1.8)]))
    return out


def _fit_set(items: list[tuple[int, np.ndarray]]) -> LandmarkSet:
    lms = [fit_landmark(P, kind)[0] for kind, P in items]
    base = LandmarkSet.from_landmarks(lms)
    pts = np.concatenate([P for _, P in items]).astype(np.float32)
    offs = np.concatenate([[0], np.cumsum([len(P) for _, P in items])])
    return LandmarkSet(base.types, base.bases, base.anchors, base.attributes, pts, offs)


def make_scene(
    T_target_source: np.ndarray,
    seed: int = 0,
    n_poles: int = 12,
    n_walls: int = 18,
    noise: float = 0.02,
    keep: float = 1.0,
) -> Scene:
    """Target frame = world; the source sees the world through inv(T_target_source)."""
    rng = np.random.default_rng(seed)
    world = _world_point_sets(rng, n_poles, n_walls)
    n = len(world)
    T_st = invert(T_target_source)
    ks = np.sort(rng.choice(n, round(keep * n), replace=False))
    kt = np.sort(rng.choice(n, round(keep * n), replace=False))
    src_items = [
        (
            world[i][0],
            transform_points(T_st, world[i][1]) + noise * rng.normal(size=world[i][1].shape),
        )
        for i in ks
    ]
    tgt_items = [
        (world[i][0], world[i][1] + noise * rng.normal(size=world[i][1].shape)) for i in kt
    ]
    _common, i_s, i_t = np.intersect1d(ks, kt, return_indices=True)
    return Scene(_fit_set(src_items), _fit_set(tgt_items), T_target_source, np.stack([i_s, i_t], 1))


def _pair(scene: Scene) -> PairInput:
    return PairInput(scene.source, scene.target)


def _assert_recovers(
    out: MethodOutput, T: np.ndarray, rot_deg: float = 1.0, trans_m: float = 0.2
) -> None:
    assert out.T_target_source is not None, out.info
    r, t = transform_errors(out.T_target_source, T)
    assert r < rot_deg and t < trans_m, (r, t, out.info)
    assert out.timings["total"] > 0


def _correct_fraction(out: MethodOutput, scene: Scene) -> float:
    truth = {tuple(m) for m in scene.true_matches.tolist()}
    a = out.associations.tolist()
    return sum(tuple(x) in truth for x in a) / max(len(a), 1)


SMALL = make_transform(rot_z(np.radians(2.0)), [0.3, -0.2, 0.05])
WIDE = make_transform(rot_z(np.radians(75.0)), [9.0, -6.0, 0.3])
TILTED = make_transform(rot_z(np.radians(-120.0)) @ rot_x(np.radians(8.0)), [-7.0, 11.0, 0.5])


@pytest.fixture(scope="module")
def small_scene() -> Scene:
    return make_scene(SMALL, seed=1)


@pytest.fixture(scope="module")
def wide_scene() -> Scene:
    return make_scene(WIDE, seed=2, keep=0.85)


# ----------------------------------------------------------------------------------------------
# registry
# ----------------------------------------------------------------------------------------------
def test_registry_lists_every_method_of_the_paper() -> None:
    names = set(list_methods())
    assert set(TABLE_I_METHODS) <= names and set(TABLE_II_METHODS) <= names
    assert {"GraffMatch-Naive", "GraffMatch-lines", "GraffMatch-planes", "KISS-Matcher"} <= names
    assert set(list_methods("point")) == {
        "FPFH+RANSAC",
        "ScanContext",
        "ScanContext+ICP",
        "KISS-Matcher",
    }
    assert all(METHODS[n].kind in ("landmark", "point") for n in names)
    with pytest.raises(InvalidInputError, match="unknown method"):
        get_method("NoSuchMethod")


@pytest.mark.parametrize("name", ["FPFH+RANSAC", "ScanContext", "ScanContext+ICP", "KISS-Matcher"])
def test_point_methods_need_scans(name: str, small_scene: Scene) -> None:
    m = get_method(name)
    assert m.kind == "point"
    with pytest.raises(InvalidInputError, match=r"needs PairInput\.source_scan"):
        m.run(_pair(small_scene))


# ----------------------------------------------------------------------------------------------
# local landmark baselines: right for small baselines, wrong for wide ones
# ----------------------------------------------------------------------------------------------
def test_cpmatch_small_baseline(small_scene: Scene) -> None:
    out = get_method("CPMatch").run(_pair(small_scene))
    _assert_recovers(out, SMALL, 0.5, 0.3)
    assert _correct_fraction(out, small_scene) >= 0.9
    assert len(out.associations) >= 0.8 * len(small_scene.true_matches)


def _fails(out: MethodOutput, T: np.ndarray) -> bool:
    if not out.valid or out.T_target_source is None:
        return True
    r, t = transform_errors(out.T_target_source, T)
    return r > 5.0 or t > 1.0


def test_cpmatch_is_local(wide_scene: Scene) -> None:
    out = get_method("CPMatch").run(_pair(wide_scene))
    assert _fails(out, WIDE)


def test_cpmatch_uses_given_initial_guess(wide_scene: Scene) -> None:
    near = WIDE @ make_transform(rot_z(np.radians(1.0)), [0.2, 0.1, 0.0])
    out = get_method("CPMatch", T_init=near).run(_pair(wide_scene))
    _assert_recovers(out, WIDE, 0.5, 0.3)


def test_bruteforce_rmse_matches_explicit_point_distances(small_scene: Scene) -> None:
    from graffmatch.evaluation.baselines.bruteforce_rmse import symmetric_rmse

    src, tgt = small_scene.source[:6], small_scene.target[:6]
    R = symmetric_rmse(src, tgt)

    def ssd(P: np.ndarray, ls: LandmarkSet, j: int) -> float:
        A = ls.bases[j]
        Q = P.astype(float) - ls.anchors[j]
        r = Q - (Q @ A) @ A.T
        return float((r**2).sum())

    for i in range(6):
        for j in range(6):
            if src.types[i] != tgt.types[j]:
                assert np.isinf(R[i, j])
                continue
            Pi, Pj = src.support_points(i), tgt.support_points(j)
            ref = np.sqrt((ssd(Pi, tgt, j) + ssd(Pj, src, i)) / (len(Pi) + len(Pj)))
            assert R[i, j] == pytest.approx(ref, rel=1e-6, abs=1e-9)


def test_bruteforce_rmse_small_baseline(small_scene: Scene) -> None:
    out = get_method("BruteForceRMSE").run(_pair(small_scene))
    _assert_recovers(out, SMALL, 0.5, 0.3)
    assert _correct_fraction(out, small_scene) >= 0.9
    # one-to-one
    assert len(np.unique(out.associations[:, 0])) == len(out.associations)
    assert len(np.unique(out.associations[:, 1])) == len(out.associations)


def test_bruteforce_rmse_needs_support_points(small_scene: Scene) -> None:
    pair = PairInput(small_scene.source.without_points(), small_scene.target)
    with pytest.raises(InvalidInputError, match="support points"):
        get_method("BruteForceRMSE").run(pair)


def test_bruteforce_rmse_is_local(wide_scene: Scene) -> None:
    out = get_method("BruteForceRMSE").run(_pair(wide_scene))
    assert _fails(out, WIDE)


# ----------------------------------------------------------------------------------------------
# global landmark baselines: recover a wide baseline
# ----------------------------------------------------------------------------------------------
def test_clustermatch_wide_baseline(wide_scene: Scene) -> None:
    out = get_method("ClusterMatch").run(_pair(wide_scene))
    _assert_recovers(out, WIDE, 1.0, 0.3)
    assert _correct_fraction(out, wide_scene) >= 0.9
    assert out.info["best_support"] >= 0.6 * len(wide_scene.true_matches)


def test_clustermatch_handles_3d_rotation() -> None:
    scene = make_scene(TILTED, seed=4)
    out = get_method("ClusterMatch").run(_pair(scene))
    _assert_recovers(out, TILTED, 1.0, 0.3)


def test_clustermatch_is_deterministic(wide_scene: Scene) -> None:
    a = get_method("ClusterMatch", seed=3).run(_pair(wide_scene))
    b = get_method("ClusterMatch", seed=3).run(_pair(wide_scene))
    assert np.array_equal(a.associations, b.associations)
    assert np.array_equal(a.T_target_source, b.T_target_source)


def test_lipmatch_wide_baseline_planes_only(wide_scene: Scene) -> None:
    out = get_method("LiPMatch").run(_pair(wide_scene))
    _assert_recovers(out, WIDE, 1.0, 0.3)
    assert np.all(wide_scene.source.types[out.associations[:, 0]] == LandmarkType.PLANE)
    assert _correct_fraction(out, wide_scene) >= 0.9
    n_planes = np.sum(wide_scene.source.types[wide_scene.true_matches[:, 0]] == LandmarkType.PLANE)
    assert len(out.associations) >= 0.8 * n_planes


def test_lipmatch_interpretation_tree_rejects_inconsistent_planes() -> None:
    """Three walls and their images; a fourth target wall is a decoy failing the binary test."""
    from graffmatch.evaluation.baselines.lipmatch import LiPMatch

    normals = np.array([[1, 0, 0], [0, 1, 0], [np.sqrt(0.5), np.sqrt(0.5), 0]], float)
    anchors = np.array([[10, 0, 1], [0, 12, 1], [-8, -8, 1]], float)
    attrs = {
        "extent": np.array([40.0, 60.0, 30.0]),
        "box": np.array([[8, 5], [12, 5], [6, 5]], float),
    }
    src = LandmarkSet.from_arrays([2, 2, 2], normals, anchors, attrs)
    T = make_transform(rot_z(np.radians(50)), [3.0, -2.0, 0.0])
    tgt_true = src.transform(T)
    decoy = LandmarkSet.from_arrays(
        [2],
        tgt_true.directions[:1],
        tgt_true.anchors[:1] + np.array([[0.0, 0.0, 30.0]]),
        {"extent": np.array([40.0]), "box": np.array([[8.0, 5.0]])},
    )
    tgt = LandmarkSet.concatenate([decoy, tgt_true])
    a, nodes = LiPMatch().interpretation_tree(src, tgt)
    assert a.tolist() == [[0, 1], [1, 2], [2, 3]]
    assert nodes < 100


# ----------------------------------------------------------------------------------------------
# CLIPPER variants and GraffMatch (need the core matcher)
# ----------------------------------------------------------------------------------------------
def test_clipper_rn_wide_baseline(wide_scene: Scene) -> None:
    out = get_method("CLIPPER-Rn").run(_pair(wide_scene))
    _assert_recovers(out, WIDE, 1.0, 0.3)
    assert _correct_fraction(out, wide_scene) >= 0.9


def test_clipper_cp_recovers_a_pure_rotation() -> None:
    """CP vectors rotate with the sensor but are not translation invariant: a pure rotation
    about the sensor keeps their distances, so CLIPPER-CP must succeed there."""
    T = make_transform(rot_z(np.radians(100.0)), [0.0, 0.0, 0.0])
    scene = make_scene(T, seed=5)
    out = get_method("CLIPPER-CP").run(_pair(scene))
    _assert_recovers(out, T, 1.0, 0.3)
    assert _correct_fraction(out, scene) >= 0.9


@pytest.mark.parametrize("name", ["GraffMatch", "GraffMatch-Naive"])
def test_graffmatch_wide_baseline(name: str, wide_scene: Scene) -> None:
    out = get_method(name).run(_pair(wide_scene))
    if name == "GraffMatch":
        _assert_recovers(out, WIDE, 1.0, 0.3)
        assert _correct_fraction(out, wide_scene) >= 0.9
    assert "total" in out.timings and any(k.startswith("match") for k in out.timings)


@pytest.mark.parametrize(("name", "kind"), [("GraffMatch-lines", 1), ("GraffMatch-planes", 2)])
def test_graffmatch_single_type_variants(name: str, kind: int, wide_scene: Scene) -> None:
    out = get_method(name).run(_pair(wide_scene))
    assert len(out.associations) >= 3
    assert np.all(wide_scene.source.types[out.associations[:, 0]] == kind)
    assert np.all(wide_scene.target.types[out.associations[:, 1]] == kind)
    assert _correct_fraction(out, wide_scene) >= 0.9


def test_graffmatch_icp_refines_on_matched_points(wide_scene: Scene) -> None:
    base = get_method("GraffMatch").run(_pair(wide_scene))
    out = get_method("GraffMatch+ICP").run(_pair(wide_scene))
    _assert_recovers(out, WIDE, 0.5, 0.15)
    assert out.info["icp_points"] > 0 and "icp" in out.timings
    r0, t0 = transform_errors(base.T_target_source, WIDE)
    r1, t1 = transform_errors(out.T_target_source, WIDE)
    assert t1 <= t0 + 0.05 and r1 <= r0 + 0.2


# ----------------------------------------------------------------------------------------------
# point-based methods on sampled boxes
# ----------------------------------------------------------------------------------------------
def box_world(
    seed: int = 0, n_boxes: int = 14, extent: float = 22.0, density: float = 12.0
) -> np.ndarray:
    """A ground plane with boxes of random sizes and yaws, sampled uniformly as points."""
    rng = np.random.default_rng(seed)
    g = rng.uniform(-extent, extent, (int(density * 25 * extent), 2))
    pts = [np.c_[g, np.full(len(g), -1.8)]]
    for _ in range(n_boxes):
        c = rng.uniform(-0.9 * extent, 0.9 * extent, 2)
        sz = rng.uniform([1, 1, 1], [7, 7, 5])
        yaw = rng.uniform(0, np.pi)
        m = int(density * 4 * (sz[0] + sz[1]) * sz[2])
        u = rng.uniform(-0.5, 0.5, (m, 3))
        face = rng.integers(0, 5, m)
        u[face == 0, 0] = -0.5
        u[face == 1, 0] = 0.5
        u[face == 2, 1] = -0.5
        u[face == 3, 1] = 0.5
        u[face == 4, 2] = 0.5
        P = u * sz
        P[:, 2] += sz[2] / 2 - 1.8
        pts.append(P @ rot_z(yaw).T + np.r_[c, 0.0])
    return np.concatenate(pts)


def _scan_pair(T: np.ndarray, seed: int = 0) -> PairInput:
    rng = np.random.default_rng(seed)
    W = box_world(seed)
    tgt = W + 0.01 * rng.normal(size=W.shape)
    src = transform_points(invert(T), W) + 0.01 * rng.normal(size=W.shape)
    # (N, 4) like KITTI: the intensity column must be ignored.
    return PairInput(LandmarkSet.empty(), LandmarkSet.empty(), np.c_[src, np.ones(len(src))], tgt)


def test_scan_context_descriptor_and_yaw() -> None:
    from graffmatch.evaluation.baselines.scan_context import sc_distance, scan_context

    P = box_world(1)
    d = scan_context(P)
    assert d.shape == (20, 60) and d.max() > 0
    # Rotating by exactly k sectors shifts the columns by k.
    d_rot = scan_context(transform_points(make_transform(rot_z(np.radians(36.0)), np.zeros(3)), P))
    _, shift, dists = sc_distance(d, d_rot)
    assert shift == 6 and dists[6] == pytest.approx(0.0, abs=1e-9)
    assert dists.shape == (60,)


def test_scan_context_yaw_only_estimate() -> None:
    T = make_transform(rot_z(np.radians(-100.0)), [0.4, 0.3, 0.0])
    out = get_method("ScanContext").run(_scan_pair(T, seed=2))
    r, _ = transform_errors(out.T_target_source, T)
    assert r <= 3.5  # half a 6-degree sector plus noise
    assert np.allclose(out.T_target_source[:3, 3], 0.0)
    assert out.info["yaw_deg"] == pytest.approx(360.0 - 102.0, abs=6.0)


def test_scan_context_icp_recovers_small_translation() -> None:
    T = make_transform(rot_z(np.radians(50.0)), [1.5, -1.0, 0.0])
    out = get_method("ScanContext+ICP", icp_voxel=0.5).run(_scan_pair(T, seed=3))
    _assert_recovers(out, T, 0.5, 0.1)


def test_fpfh_ransac_recovers_rigid_transform() -> None:
    T = make_transform(rot_z(np.radians(35.0)), [2.0, 1.0, 0.2])
    out = get_method("FPFH+RANSAC", voxel_size=0.5, max_iterations=20_000).run(
        _scan_pair(T, seed=4)
    )
    _assert_recovers(out, T, 2.0, 0.3)
    assert out.valid and out.info["n_correspondences"] >= 3


def test_kiss_matcher_recovers_rigid_transform() -> None:
    pytest.importorskip("kiss_matcher")
    T = make_transform(rot_z(np.radians(-60.0)), [3.0, -2.0, 0.1])
    out = get_method("KISS-Matcher", voxel_size=0.4).run(_scan_pair(T, seed=5))
    _assert_recovers(out, T, 1.0, 0.2)
    assert out.valid and out.info["n_final_inliers"] > 0


@pytest.mark.parametrize("name", list_methods("landmark"))
def test_landmark_methods_report_no_estimate_on_too_few_landmarks(
    name: str, small_scene: Scene
) -> None:
    """A scan without landmarks of the method's types is a failed pair, not an exception."""
    poles_only = small_scene.target[small_scene.target.indices_of_type(LandmarkType.LINE)]
    pair = PairInput(small_scene.source, poles_only[:1])
    out = get_method(name).run(pair)
    assert out.T_target_source is None and not out.valid
    assert len(out.associations) == 0 and out.timings["total"] >= 0


@given(st.integers(0, 59))
@settings(max_examples=15, deadline=None)
def test_scan_context_shift_is_the_rotation_in_sectors(k: int) -> None:
    from graffmatch.evaluation.baselines.scan_context import sc_distance, scan_context

    P = _BOXES
    R = make_transform(rot_z(np.radians(6.0 * k)), np.zeros(3))
    _, shift, _ = sc_distance(scan_context(P), scan_context(transform_points(R, P)))
    assert shift == k


_BOXES = box_world(7, n_boxes=10, density=6.0)


def test_every_method_exposes_json_params_and_pickles() -> None:
    """Parameters are written next to results; methods travel to worker processes."""
    import json
    import pickle

    for name in list_methods():
        m = get_method(name)
        assert m.name == name
        params = json.loads(json.dumps(m.params))
        assert params, name
        assert pickle.loads(pickle.dumps(m)).params == m.params
    assert get_method("CLIPPER-Rn", epsilon=3.0).params["epsilon"] == 3.0
    assert get_method("GraffMatch-Naive").params["variant"] == "naive"
    assert get_method("GraffMatch-lines").params["landmark_types"] == ["line"]
