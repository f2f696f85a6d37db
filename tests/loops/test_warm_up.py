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
from graffmatch.loops.verify import verify_candidate


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
    for n_poles, n_planes, seed, outliers in ((10, 25, 44, 6), (3, 18, 82, 0)):
        sc = make_scene_pair(n_poles, n_planes, seed=seed, yaw_deg=120.0, translation=(4.0, -2.0, 0.0),
                             n_outliers=outliers)
        src, tgt = (decode_landmarks(encode_landmarks(s)) for s in (sc.source, sc.target))
        res = verify_candidate(src, tgt, det.matcher, det.config.verification)
        assert res["matcher_valid"] and res["n_agreeing"] >= 6
        quick_check_many(quick_index(src), [quick_index(tgt)])
    P_t = np.random.default_rng(3).uniform([-25, -25, 0], [25, 25, 5], (1200, 3))
    T_s_t = invert(sc.T_target_source)
    poor = make_scene_pair(3, 5, seed=3, yaw_deg=120.0, translation=(4.0, -2.0, 0.0))
    a = with_evidence_points(decode_landmarks(encode_landmarks(poor.source)),
                             decode_points(encode_points(P_t @ T_s_t[:3, :3].T + T_s_t[:3, 3])))
    b = with_evidence_points(decode_landmarks(encode_landmarks(poor.target)), decode_points(encode_points(P_t)))
    assert verify_candidate(a, b, det.matcher, det.config.verification)["on_points"]
    assert _signatures() - before == set()
