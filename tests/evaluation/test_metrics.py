"""Metrics on planted cases with hand-computed LMR, AUC, recall and errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from graffmatch.errors import InvalidInputError
from graffmatch.evaluation import metrics as M
from graffmatch.geometry.landmarks import Landmark, LandmarkSet
from graffmatch.geometry.transforms import make_transform, rot_x, rot_z

# ----------------------------------------------------------------------------------------------
# LMR and AUC
# ----------------------------------------------------------------------------------------------
# Four pairs; distances [deg] of their selected associations (tau_d = 6):
PLANTED = [
    np.array([1.0, 2.0, 10.0]),  # 2/3 inliers
    np.array([]),  # nothing selected: OIR 0
    np.array([0.5, 0.5, 0.5, 0.5]),  # 1.0
    np.array([7.0, 8.0, 1.0, 2.0]),  # 0.5
]
OIRS = np.array([2 / 3, 0.0, 1.0, 0.5])


def test_planted_oirs_and_lmr() -> None:
    oirs = [M.oir_from_distances(d) for d in PLANTED]
    assert np.allclose(oirs, OIRS)
    assert M.lmr(OIRS, 0.8) == pytest.approx(0.25)  # only the OIR-1 pair
    assert M.lmr(OIRS, 0.5) == pytest.approx(0.5)  # strict: 0.5 is not > 0.5
    assert M.lmr(OIRS, 0.0) == pytest.approx(0.75)  # the empty pair never counts
    _taus, curve = M.lmr_curve(OIRS, [0.0, 0.5, 0.6, 0.7, 1.0])
    assert np.allclose(curve, [0.75, 0.5, 0.5, 0.25, 0.0])


def test_planted_auc_is_mean_oir() -> None:
    assert M.lmr_auc(OIRS) == pytest.approx((2 / 3 + 0 + 1 + 0.5) / 4)
    # The sampled-curve trapezoid agrees to within the grid step.
    assert abs(M.lmr_auc_trapezoid(OIRS) - M.lmr_auc(OIRS)) <= 0.01


@given(st.lists(st.floats(0.0, 1.0), min_size=1, max_size=30))
def test_auc_matches_fine_trapezoid(oirs: list[float]) -> None:
    fine = np.linspace(0, 1, 20001)
    assert M.lmr_auc_trapezoid(oirs, fine) == pytest.approx(M.lmr_auc(oirs), abs=2e-4)


def test_lmr_vs_tau_d_planted() -> None:
    _tds, curve = M.lmr_vs_tau_d(PLANTED, [0.4, 0.6, 1.5, 3.0, 9.0, 11.0], tau_oir=0.8)
    # pair 3 (all 0.5 deg) is above 0.8 from tau_d > 0.5; pair 1 needs all three < tau_d (>10);
    # pair 4 needs 4/4 (> 0.8) i.e. tau_d > 8.
    assert np.allclose(curve, [0.0, 0.25, 0.25, 0.25, 0.5, 0.75])


def test_lmr_rejects_bad_input() -> None:
    with pytest.raises(InvalidInputError):
        M.lmr([0.5, 1.2])
    with pytest.raises(InvalidInputError):
        M.lmr([])


# ----------------------------------------------------------------------------------------------
# association inliers with d_Graff after ground-truth alignment
# ----------------------------------------------------------------------------------------------
def _landmarks() -> LandmarkSet:
    return LandmarkSet.from_landmarks(
        [
            Landmark.line([5.0, 2.0, 1.0], [0, 0, 1]),
            Landmark.line([-4.0, 7.0, 1.0], [0.1, 0, 1]),
            Landmark.plane([10.0, 0.0, 2.0], [1, 0, 0]),
            Landmark.plane([0.0, -12.0, 2.0], [0, 1, 0.05]),
            Landmark.plane([0.0, 0.0, -1.8], [0, 0, 1]),
        ]
    )


def test_association_inlier_mask_against_ground_truth() -> None:
    src = _landmarks()
    T = make_transform(rot_z(np.radians(70)) @ rot_x(np.radians(5)), [12.0, -3.0, 0.4])
    tgt = src.transform(T)
    # Correct matches -> distance 0; wrong pairs of the same type and a cross-type pair -> not.
    assoc = np.array([[0, 0], [1, 1], [2, 2], [3, 3], [4, 4], [0, 1], [2, 3], [0, 2]])
    d = M.association_distances_deg(src, tgt, assoc, T)
    assert np.allclose(d[:5], 0.0, atol=1e-5)
    assert np.all(d[5:7] > 6.0) and np.isinf(d[7])
    mask = M.association_inlier_mask(src, tgt, assoc, T)
    assert mask.tolist() == [True] * 5 + [False] * 3
    assert M.output_inlier_ratio(mask) == pytest.approx(5 / 8)
    assert M.output_inlier_ratio(np.zeros(0, bool)) == 0.0


def test_tau_d_threshold_on_a_tilted_line() -> None:
    src = LandmarkSet.from_landmarks([Landmark.line([3.0, 0, 0], [0, 0, 1])])

    def tilted(deg: float) -> LandmarkSet:
        a = np.radians(deg)
        return LandmarkSet.from_landmarks([Landmark.line([3.0, 0, 0], [np.sin(a), 0, np.cos(a)])])

    a = np.array([[0, 0]])
    assert M.association_inlier_mask(src, tilted(3.0), a, np.eye(4))[0]
    assert not M.association_inlier_mask(src, tilted(10.0), a, np.eye(4))[0]
    # the invariant distance of two lines through the same anchor is their angle
    assert M.association_distances_deg(src, tilted(4.0), a, np.eye(4))[0] == pytest.approx(
        4.0, abs=1e-6
    )


def test_associations_out_of_range() -> None:
    src = _landmarks()
    with pytest.raises(InvalidInputError, match="out of range"):
        M.association_inlier_mask(src, src, [[0, 9]], np.eye(4))


# ----------------------------------------------------------------------------------------------
# registration recall and errors
# ----------------------------------------------------------------------------------------------
def _T(yaw_deg: float, t: float) -> np.ndarray:
    return make_transform(rot_z(np.radians(yaw_deg)), [t, 0.0, 0.0])


def test_registration_recall_planted() -> None:
    gt = _T(30, 5.0)
    ests = [_T(34, 5.9), _T(24, 5.0), _T(30, 6.5), None, _T(31, 5.2)]
    recs = [
        M.PairRecord(f"p{i}", "m", gt, e, timings={"total": 0.01 * (i + 1)})
        for i, e in enumerate(ests)
    ]
    res = M.RegistrationRecall().compute(recs)
    assert res.statistics["recall"] == pytest.approx(2 / 5)
    assert res.statistics["n_success"] == 2
    assert res.statistics["estimate_rate"] == pytest.approx(4 / 5)
    assert res.statistics["rotation_error_deg_mean"] == pytest.approx((4 + 1) / 2, abs=1e-9)
    assert res.statistics["translation_error_m_mean"] == pytest.approx((0.9 + 0.2) / 2, abs=1e-9)
    assert res.arrays["success"].tolist() == [True, False, False, False, True]
    assert np.isinf(res.arrays["rotation_error_deg"][3])


def test_rotation_error_formula() -> None:
    R1 = rot_z(0.3) @ rot_x(0.2)
    R2 = rot_x(-0.4)
    r, _ = M.registration_errors(make_transform(R1, np.zeros(3)), make_transform(R2, np.zeros(3)))
    ref = np.degrees(np.arccos((np.trace(R1.T @ R2) - 1) / 2))
    assert r == pytest.approx(ref)


def test_runtime_stats() -> None:
    v = np.arange(1, 101) / 1000.0
    s = M.runtime_stats(v)
    assert s["median"] == pytest.approx(np.median(v))
    assert s["p5"] == pytest.approx(np.percentile(v, 5))
    assert s["p95"] == pytest.approx(np.percentile(v, 95))
    assert s["n"] == 100
    assert M.runtime_stats([]) == {"n": 0}


# ----------------------------------------------------------------------------------------------
# serialisation and the Metric interface
# ----------------------------------------------------------------------------------------------
def test_records_and_results_round_trip_json(tmp_path) -> None:
    src = _landmarks()
    T = _T(40, 3.0)
    rec = M.PairRecord.from_output(
        "pair-7", "GraffMatch", src, src.transform(T), T, T, [[0, 0], [1, 2]], {"total": 0.02}
    )
    assert rec.n_associations == 2 and np.isinf(rec.association_distances_deg[1])
    rec2 = M.PairRecord.from_dict(json.loads(json.dumps(rec.to_dict())))
    assert np.allclose(rec2.T_target_source_est, T)
    assert np.array_equal(rec2.association_distances_deg, rec.association_distances_deg)
    none = M.PairRecord("pair-8", "GraffMatch", T, None, timings={"total": 0.5})
    recs = [rec, rec2, none]
    results = M.evaluate(recs)
    assert set(results) == {"lmr", "registration", "runtime"}
    assert all(isinstance(m, M.Metric) for m in M.default_metrics())
    assert results["lmr"].statistics["auc"] == pytest.approx(1 / 3)  # OIRs 0.5, 0.5, 0
    assert results["registration"].statistics["recall"] == pytest.approx(2 / 3)
    for r in results.values():
        p = r.save(tmp_path / f"{r.name}.json")
        back = M.MetricResult.load(p)
        assert back.name == r.name
        for k, v in r.arrays.items():
            assert np.allclose(back.arrays[k].astype(float), v.astype(float), equal_nan=True)
    assert results["runtime"].statistics["total"]["median"] == pytest.approx(0.02)


def test_lmr_metric_result() -> None:
    T = np.eye(4)
    recs = [
        M.PairRecord(f"p{i}", "m", T, T, association_distances_deg=d) for i, d in enumerate(PLANTED)
    ]
    res = M.LandmarkMatchRecall().compute(recs)
    assert res.statistics["lmr"] == pytest.approx(0.25)
    assert res.statistics["auc"] == pytest.approx(OIRS.mean())
    assert np.allclose(res.arrays["oir"], OIRS)
    assert res.arrays["lmr_curve"][0] == pytest.approx(0.75)


@given(st.lists(st.floats(0.0, 1.0), min_size=1, max_size=40))
def test_lmr_curve_is_non_increasing_and_bounded(oirs: list[float]) -> None:
    _, curve = M.lmr_curve(oirs)
    assert np.all(np.diff(curve) <= 0) and curve[0] <= 1 and curve[-1] == 0.0
