"""Sequence consistency: a weak loop is accepted only when a neighbouring query's loop agrees.

A landmark-poor pair (both scans keep evidence points, so the verified matcher decided on points)
often shows fewer agreeing landmarks than ``points_min_agreeing`` however right its pose is: a
street of plain facades has three to five landmarks. Such a *weak* loop q -> m is accepted when
another query q' at most ``consistency_window`` frames away has a verified loop q' -> m' (accepted
or weak) that agrees with it through the odometry: the odometry's motion q -> q' and the chain
q -> m -> m' -> q' (the two loops and the odometry's motion m -> m') must give the same relative
pose within ``consistency_max_m`` / ``consistency_max_deg``. Only short odometry segments enter
(q -> q', m -> m'), so a drifting odometry suffices. Two independent verifications of different
scans rarely agree on a wrong place by chance. Without odometry nothing changes.

Before either, a loop on fewer than ``min_agreeing`` agreeing landmarks must lie within the odometry's drift allowance
(the one below) of where the odometry puts its query (:func:`gate_weak_loops`): weak evidence may not move a query
tens of metres from its odometry, and slid loops of consecutive queries could otherwise confirm one another.

With every candidate verified (``--all-loops``) a query can have several loops; each says where the query was (the
match's odometry pose times the loop). A loop whose place disagrees with more of the query's other loops than agree
with it (beyond the odometry's drift between the two matches: ``OUTVOTE_M`` + ``OUTVOTE_PATH_FRACTION`` of the path, and
``OUTVOTE_DEG`` + ``OUTVOTE_DEG_PER_M`` of it) is dropped (:func:`drop_outvoted_loops`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.transforms import invert, rotation_error_deg
from graffmatch.loops.verify import VerificationConfig, loop_confidence


def loop_pair_residual(
    odometry: NDArray, q: int, m: int, T_m_q: NDArray, q2: int, m2: int, T_m2_q2: NDArray
) -> tuple[float, float]:
    """(translation m, rotation deg) by which two loops q -> m, q2 -> m2 disagree through the
    odometry poses (world <- scan): odometry q -> q2 against T_m_q^-1 (odometry m -> m2) T_m2_q2."""
    A = invert(odometry[q]) @ odometry[q2]
    B = invert(T_m_q) @ invert(odometry[m]) @ odometry[m2] @ T_m2_q2
    E = invert(A) @ B
    cos = np.clip((np.trace(E[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(np.arccos(cos)))


def _base_confidence(c: dict, config: VerificationConfig, relaxed: VerificationConfig | None = None) -> float:
    T = np.asarray(c["T"], float).reshape(4, 4)
    return loop_confidence(
        bool(c.get("matcher_valid", False)), c.get("matcher_confidence"), int(c["n_agreeing"]),
        float(c["overlap"]), float(np.linalg.norm(T[:3, 3])), relaxed or config, bool(c.get("on_points", False)),
    )


#: The drift allowed between two matches' odometry poses when a query's loops are compared: the radius retriever's
#: 5 m + 2 % of the path (calibrated, bench/loops_calibration_union.py) and the drift model's 3 deg / 100 m over 10 deg.
#: Not tuned: on the every-candidate stress sets of downtown 4, downtown-s1 and downtown-s5 (3,701 right accepted loops,
#: 1 wrong: downtown 4's 345 -> 11, 117 m and 91 deg off) it drops the wrong one and no right one (docs/loops.md s. 19).
OUTVOTE_M = 5.0
OUTVOTE_PATH_FRACTION = 0.02
OUTVOTE_DEG = 10.0
OUTVOTE_DEG_PER_M = 0.03


def drop_outvoted_loops(records: dict[int, dict], odometry: NDArray | None, min_confidence: float) -> dict[int, dict]:
    """Records in which a query's accepted loop that more of its other accepted loops contradict than confirm (through
    the odometry, within the drift allowance above) has confidence 0 and ``outvoted_by`` (the contradicting matches).
    One loop a query (the default early stop) and ties change nothing. The records are not modified in place."""
    if odometry is None:
        return records
    P, path = _odometry_path(odometry)
    out = dict(records)
    for q, r in records.items():
        acc = [k for k, c in enumerate(r["candidates"]) if c.get("T") is not None and c["confidence"] >= min_confidence]
        if len(acc) < 3:
            continue
        if max(int(r["candidates"][k]["match"]) for k in acc) >= len(P):
            raise InvalidInputError(f"odometry has {len(P)} poses; the loops of query {q} reach beyond it")
        place = {k: P[int(r["candidates"][k]["match"])] @ np.asarray(r["candidates"][k]["T"], float).reshape(4, 4)
                 for k in acc}
        for k in acc:
            m = int(r["candidates"][k]["match"])
            against = []
            for k2 in acc:
                if k2 == k:
                    continue
                m2 = int(r["candidates"][k2]["match"])
                if beyond_drift(place[k], place[k2], abs(path[m] - path[m2])) is not None:
                    against.append(m2)
            if len(against) > len(acc) - 1 - len(against):
                if out[q] is records[q]:
                    out[q] = {**records[q], "candidates": list(records[q]["candidates"])}
                out[q]["candidates"][k] = {**r["candidates"][k], "confidence": 0.0, "outvoted_by": against}
    return out if any(out[q] is not records[q] for q in records) else records


def _odometry_path(odometry: NDArray) -> tuple[NDArray, NDArray]:
    P = np.asarray(odometry, float)
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise InvalidInputError(f"odometry must be (n, 4, 4) poses, got shape {P.shape}")
    return P, np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1))])


def beyond_drift(place: NDArray, where: NDArray, along_m: float) -> tuple[float, float] | None:
    """(m, deg) by which two poses of one scan disagree when that exceeds the odometry's drift over ``along_m`` of
    path (``OUTVOTE_*``), else None."""
    dt = float(np.linalg.norm(place[:3, 3] - where[:3, 3]))
    dr = rotation_error_deg(place[:3, :3], where[:3, :3])
    if dt > OUTVOTE_M + OUTVOTE_PATH_FRACTION * along_m or dr > OUTVOTE_DEG + OUTVOTE_DEG_PER_M * along_m:
        return dt, dr
    return None


def gate_weak_loops(records: dict[int, dict], odometry: NDArray | None, config: VerificationConfig) -> dict[int, dict]:
    """Records in which every verified candidate on fewer than ``config.min_agreeing`` agreeing landmarks that puts its
    query beyond the odometry's drift allowance of the odometry's own pose (:func:`beyond_drift`, over the odometry path
    between the two scans) has confidence 0 and ``odometry_disagrees`` = [m, deg]; such a candidate confirms no other
    (:func:`_confirm_weak_loops`). Without odometry, or with ``config.odometry_gate`` off, nothing changes. The records
    are not modified in place."""
    if odometry is None or not config.odometry_gate:
        return records
    P, path = _odometry_path(odometry)
    out = dict(records)
    for q, r in records.items():
        for k, c in enumerate(r["candidates"]):
            if c.get("T") is None or int(c.get("n_agreeing", 0)) >= config.min_agreeing:
                continue
            m = int(c["match"])
            if max(int(q), m) >= len(P):
                raise InvalidInputError(f"odometry has {len(P)} poses; the records reach scan {max(int(q), m)}")
            off = beyond_drift(P[m] @ np.asarray(c["T"], float).reshape(4, 4), P[int(q)], abs(path[int(q)] - path[m]))
            if off is None:
                continue
            if out[q] is records[q]:
                out[q] = {**records[q], "candidates": list(records[q]["candidates"])}
            out[q]["candidates"][k] = {**c, "confidence": 0.0, "odometry_disagrees": [round(off[0], 3), round(off[1], 3)]}
    return out if any(out[q] is not records[q] for q in records) else records


def refused_by_odometry(before: dict[int, dict], after: dict[int, dict], min_confidence: float) -> int:
    """How many verified loops (confidence >= ``min_confidence`` in ``before``) :func:`gate_weak_loops` refused in
    ``after``: weak evidence tens of metres from the odometry."""
    return sum(c.get("odometry_disagrees") is not None and float(before[q]["candidates"][k]["confidence"]) >= min_confidence
               for q, r in after.items() for k, c in enumerate(r["candidates"]))


def apply_sequence_consistency(
    records: dict[int, dict], odometry: NDArray | None, config: VerificationConfig
) -> dict[int, dict]:
    """Records with weak loops far from the odometry refused (:func:`gate_weak_loops`), the weak loops that a
    neighbouring query's loop confirms accepted, then the loops their query's other loops outvote dropped
    (:func:`drop_outvoted_loops`).

    ``records``: query -> record (``queries.jsonl``), candidates as :func:`verify_query` wrote
    them; only verified ones count. A candidate is weak when its confidence is below
    ``min_confidence`` but reaches it with ``consistency_min_agreeing`` agreeing landmarks for a
    pair verified on points. A confirmed weak candidate gets that confidence and
    ``consistent_with`` = [q', m']; nothing else changes. The records are not modified in place.
    """
    gated = gate_weak_loops(records, odometry, config)
    return drop_outvoted_loops(_confirm_weak_loops(gated, odometry, config), odometry, config.min_confidence)


def _confirm_weak_loops(records: dict[int, dict], odometry: NDArray | None, config: VerificationConfig
                        ) -> dict[int, dict]:
    if odometry is None or config.consistency_window <= 0:
        return records
    P, _ = _odometry_path(odometry)
    relaxed = config.model_copy(update={"points_min_agreeing": min(config.points_min_agreeing,
                                                                   config.consistency_min_agreeing)})
    strong: dict[int, list[tuple[int, NDArray]]] = {}
    weak: dict[tuple[int, int], float] = {}
    for q, r in records.items():
        for k, c in enumerate(r["candidates"]):
            if (c.get("T") is None or not c.get("verified", True) or not c.get("matcher_valid", False)
                    or c.get("odometry_disagrees") is not None):
                continue
            if int(q) >= len(P) or int(c["match"]) >= len(P):
                raise InvalidInputError(f"odometry has {len(P)} poses; the records reach scan "
                                        f"{max(int(q), int(c['match']))}")
            conf = float(c["confidence"])
            if conf < config.min_confidence and c.get("on_points", False):
                conf_w = _base_confidence(c, config, relaxed)
                if conf_w >= config.min_confidence:
                    weak[(int(q), k)] = conf_w
                    conf = conf_w
            if conf >= config.min_confidence:
                strong.setdefault(int(q), []).append((int(c["match"]), np.asarray(c["T"], float).reshape(4, 4)))
    if not weak:
        return records
    out = dict(records)
    W = config.consistency_window
    for (q, k), conf_w in sorted(weak.items()):
        c = records[q]["candidates"][k]
        m, T = int(c["match"]), np.asarray(c["T"], float).reshape(4, 4)
        hit = None
        for q2 in range(q - W, q + W + 1):
            if q2 == q:
                continue
            for m2, T2 in strong.get(q2, []):
                dt, dr = loop_pair_residual(P, q, m, T, q2, m2, T2)
                if dt <= config.consistency_max_m and dr <= config.consistency_max_deg:
                    hit = [q2, m2]
                    break
            if hit:
                break
        if hit is None:
            continue
        if out[q] is records[q]:
            out[q] = {**records[q], "candidates": list(records[q]["candidates"])}
        out[q]["candidates"][k] = {**c, "confidence": conf_w, "consistent_with": hit}
    return out
