"""The per-process kernel warm-up of the loop layer (docs/loops.md, session 13): done once a
process, before any query is timed, and covering the kernels a verification of stored scans runs."""

from __future__ import annotations

import sys

import numpy as np
from numba.core.dispatcher import Dispatcher

from graffmatch.datasets.landmark_scene import make_scene_pair
from graffmatch.geometry.transforms import invert
from graffmatch.loops import detector as detector_module
from graffmatch.loops.database import (
    decode_landmarks,
    decode_points,
    encode_landmarks,
    encode_points,
    with_evidence_points,
)
from graffmatch.loops.detector import LoopDetector, warm_up_once
from graffmatch.loops.quickcheck import quick_check_many, quick_index
from graffmatch.loops.verify import scan_pass, verify_candidate


def _signatures() -> set[tuple[str, str]]:
    """Every (numba kernel, signature) loaded or compiled so far in this process."""
    out = set()
    for name, mod in list(sys.modules.items()):
        if name.startswith("graffmatch"):
            for v in vars(mod).values():
                if isinstance(v, Dispatcher):
                    out |= {(f"{v.py_func.__module__}.{v.py_func.__name__}", str(s)) for s in v.signatures}
    return out


def test_warm_up_runs_once_a_process_and_the_points_path_only_when_asked(monkeypatch):
    calls: list[bool] = []
    monkeypatch.setattr(detector_module, "_WARMED", set())
    monkeypatch.setattr(LoopDetector, "warm_up", lambda self, points=True: calls.append(points) or 0.25)
    det = LoopDetector()
    assert warm_up_once(det, False)[0] == 0.25 and calls == [False]
    assert warm_up_once(det, False) == (0.0, 0.0) and calls == [False]
    assert warm_up_once(det, True)[0] == 0.25 and calls == [False, True]  # only the points path now
    assert warm_up_once(det, True) == (0.0, 0.0) and warm_up_once(det, False) == (0.0, 0.0)
    assert calls == [False, True]


def test_after_the_warm_up_a_stored_pair_compiles_or_loads_no_kernel():
    """Another scene than the warm-up's, stored as the database stores scans (landmark-rich and
    landmark-poor with evidence points): its verification and quick check run no kernel the warm-up
    did not load (a first query would otherwise pay for loading, or on a fresh install compiling,
    them: ~300 s niced in session 12's KISS-ICP downtown-s1 run)."""
    det = LoopDetector()
    assert det.warm_up(points=True) > 0.0
    before = _signatures()
    scans = []
    for n_poles, n_planes, seed, outliers in ((10, 25, 44, 6), (3, 18, 82, 0)):
        sc = make_scene_pair(n_poles, n_planes, seed=seed, yaw_deg=120.0, translation=(4.0, -2.0, 0.0),
                             n_outliers=outliers)
        src, tgt = (decode_landmarks(encode_landmarks(s)) for s in (sc.source, sc.target))
        res = verify_candidate(src, tgt, det.matcher, det.config.verification)
        assert res["matcher_valid"] and res["n_agreeing"] >= 6
        quick_check_many(quick_index(src), [quick_index(tgt)])
        scans.append((src, tgt))
    # the same scans again, against another candidate and the other way round: their cached
    # (read-only) arrays reach the kernels now (a query's k candidates, a database scan met by
    # later queries); session 13 saw such variants load inside downtown-s1 queries
    (s1, t1), (_, t2) = scans
    other = make_scene_pair(8, 20, seed=45, yaw_deg=60.0, translation=(3.0, 1.0, 0.0))
    t3 = decode_landmarks(encode_landmarks(other.target))
    for x, y in ((s1, t3), (t1, s1), (s1, t1), (s1, t2), (t2, t1)):
        verify_candidate(x, y, det.matcher, det.config.verification)
    P_t = np.random.default_rng(3).uniform([-25, -25, 0], [25, 25, 5], (1200, 3))
    T_s_t = invert(sc.T_target_source)
    poor = make_scene_pair(3, 5, seed=3, yaw_deg=120.0, translation=(4.0, -2.0, 0.0))
    a = with_evidence_points(decode_landmarks(encode_landmarks(poor.source)),
                             decode_points(encode_points(P_t @ T_s_t[:3, :3].T + T_s_t[:3, 3])))
    b = with_evidence_points(decode_landmarks(encode_landmarks(poor.target)), decode_points(encode_points(P_t)))
    assert verify_candidate(a, b, det.matcher, det.config.verification)["on_points"]
    assert verify_candidate(b, a, det.matcher, det.config.verification)["on_points"]
    # the raw-scan pass of two scans that keep scan clouds (session 24: the benchmark's warm-up had skipped it, and on
    # a cold cache its kernels compiled inside a timed query, 0.6-0.8 s)
    clouds = [decode_points(encode_points(P)) for P in (P_t @ T_s_t[:3, :3].T + T_s_t[:3, 3], P_t)]
    scan_pass(a, b, clouds[0], clouds[1], det.matcher, det.config.verification)
    scan_pass(b, a, clouds[1], clouds[0], det.matcher, det.config.verification)
    assert _signatures() - before == set()


def test_the_place_check_is_warmed_up_once_when_it_can_run(monkeypatch, tmp_path):
    """With a place radius and the scans, the warm-up also covers the place check's scan reader; the worker's
    once-a-process bookkeeping asks for it only then."""
    from graffmatch.loops import LoopDetectorConfig

    calls: list[bool] = []
    monkeypatch.setattr(detector_module, "_WARMED", set())
    monkeypatch.setattr(LoopDetector, "warm_up", lambda self, points=True: calls.append(points) or 0.5)
    cfg = LoopDetectorConfig()
    cfg.verification.max_translation_m = 5.0
    assert warm_up_once(LoopDetector(cfg), False)[0] == 0.5  # no scans: landmarks only
    assert warm_up_once(LoopDetector(cfg), False) == (0.0, 0.0)
    scans = [np.random.default_rng(0).uniform(-20, 20, (3000, 3))]
    assert warm_up_once(LoopDetector(cfg, scans=scans), False)[0] == 0.5  # the place check's part is new
    assert warm_up_once(LoopDetector(cfg, scans=scans), False) == (0.0, 0.0)
    off = cfg.model_copy(deep=True)
    off.verification.place_check = False
    monkeypatch.setattr(detector_module, "_WARMED", set())
    warm_up_once(LoopDetector(off, scans=scans), False)
    assert "place" not in detector_module._WARMED


def test_kernel_inputs_are_read_only_views_of_one_dtype():
    """Cached arrays are read-only and fresh ones are not; the kernels get both as read-only
    (one numba signature), without a copy where dtype and layout already fit."""
    from graffmatch.geometry.set_cache import kernel_input

    a = np.arange(12.0).reshape(4, 3)
    v = kernel_input(a, np.float64)
    assert not v.flags.writeable and a.flags.writeable and np.shares_memory(v, a)
    assert np.array_equal(v, a)
    w = kernel_input(a[:, ::2], np.float32)  # strided and another dtype: a C-contiguous copy
    assert w.dtype == np.float32 and w.flags.c_contiguous and not w.flags.writeable
    assert np.array_equal(w, a[:, ::2].astype(np.float32))
