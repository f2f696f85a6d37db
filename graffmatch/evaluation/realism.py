"""Realism statistics: how much a (simulated) drive looks like real LiDAR data to the matcher.

The statistics compare what the default front end and matcher see in real and simulated scans,
with no labels (issue 13): landmarks per scan, the flatness of the extracted planes, how many
landmarks two scans a few metres apart share, how strictly they repeat, how much of a scan is
ground and how much is scattered clutter (vegetation, people, noise), how dense the
consistency graph is and how far the matcher's transform lands from the truth.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType

#: Gates of the strict repeatability: same direction within 2 deg, same place within 0.3 m.
STRICT_ANGLE_DEG = 2.0
STRICT_OFFSET_M = 0.3
#: Invariant-distance gate of a true shared landmark (the benchmark's LMR tau_d) and its rho.
SHARED_TAU_DEG = 6.0
SHARED_RHO_M = 40.0


def strict_repeatability(
    ls_a: LandmarkSet,
    ls_b_in_a: LandmarkSet,
    max_angle_deg: float = STRICT_ANGLE_DEG,
    max_offset_m: float = STRICT_OFFSET_M,
) -> float:
    """Fraction of a's landmarks with a same-type landmark of b (already in a's frame) within
    ``max_angle_deg`` and ``max_offset_m`` (line: distance of b's anchor to a's axis; plane:
    distance of b's anchor to a's plane). NaN when a has no landmark."""
    if len(ls_a) == 0:
        return float("nan")
    if len(ls_b_in_a) == 0:
        return 0.0
    da, db = ls_a.directions, ls_b_in_a.directions
    ang = np.degrees(np.arccos(np.clip(np.abs(da @ db.T), 0.0, 1.0)))
    q = ls_b_in_a.anchors[None, :, :] - ls_a.anchors[:, None, :]
    along = np.einsum("ijk,ik->ij", q, da)
    perp = np.linalg.norm(q - along[..., None] * da[:, None, :], axis=2)
    is_line = (ls_a.types == LandmarkType.LINE)[:, None]
    off = np.where(is_line, perp, np.abs(along))
    same = ls_a.types[:, None] == ls_b_in_a.types[None, :]
    return float(np.mean(np.any(same & (ang < max_angle_deg) & (off < max_offset_m), axis=1)))


def true_shared_landmarks(
    ls_a: LandmarkSet,
    ls_b_in_a: LandmarkSet,
    tau_deg: float = SHARED_TAU_DEG,
    rho: float = SHARED_RHO_M,
) -> NDArray[np.int64]:
    """(k, 2) mutual-nearest same-type pairs within ``tau_deg`` of the invariant distance,
    b already in a's frame: the landmarks the two scans truly share."""
    from graffmatch.geometry.distance import cross_distances

    if len(ls_a) == 0 or len(ls_b_in_a) == 0:
        return np.zeros((0, 2), np.int64)
    D = cross_distances(ls_a, ls_b_in_a, rho=rho)
    j, i2 = D.argmin(axis=1), D.argmin(axis=0)
    i = np.arange(len(ls_a))
    keep = (D[i, j] <= np.radians(tau_deg)) & (i2[j] == i)
    return np.column_stack([i[keep], j[keep]]).astype(np.int64)


def plane_flatness_rms(ls: LandmarkSet) -> NDArray[np.float64]:
    """Point-to-plane RMS [m] of each non-ground plane the front end extracted."""
    if len(ls) == 0 or "rms" not in ls.attributes:
        return np.zeros(0)
    sel = ls.types == LandmarkType.PLANE
    if "is_ground" in ls.attributes:
        sel &= np.asarray(ls.attributes["is_ground"]) < 0.5
    return np.asarray(ls.attributes["rms"], float)[sel]


def scattered_mask(
    points: NDArray,
    radius: float = 0.5,
    k: int = 12,
    min_neighbours: int = 6,
    roughness_m: float = 0.08,
    max_range: float = 30.0,
) -> NDArray[np.bool_]:
    """Points (within ``max_range``) that lie on no surface: scattered returns.

    A point is scattered when its neighbourhood (its ``k`` nearest neighbours within
    ``radius``, at least ``min_neighbours`` of them) is not flat: the smallest principal
    standard deviation exceeds ``roughness_m``, which a wall, a car body or a pole seen with
    2 cm range noise never does, but foliage, bushes and people do. Points beyond
    ``max_range`` (rings too sparse to tell) or with too few neighbours are not counted.
    """
    P = np.asarray(points, float)[:, :3]
    out = np.zeros(len(P), bool)
    near = np.linalg.norm(P, axis=1) <= max_range
    Q = P[near]
    if len(Q) < k + 1:
        return out
    d, nn = cKDTree(Q).query(Q, k=k + 1, distance_upper_bound=radius)
    valid = np.isfinite(d)
    n_valid = valid.sum(1)
    idx = np.where(valid, nn, np.arange(len(Q))[:, None])
    N = Q[idx] - Q[:, None, :]  # (n, k+1, 3); missing neighbours sit at the point itself
    w = valid[..., None].astype(float)
    cnt = np.maximum(n_valid, 1)[:, None]
    mu = (N * w).sum(1) / cnt
    X = (N - mu[:, None, :]) * w
    C = np.einsum("nki,nkj->nij", X, X) / cnt[..., None]
    s_min = np.sqrt(np.clip(np.linalg.eigvalsh(C)[:, 0], 0.0, None))
    out[np.flatnonzero(near)] = (n_valid >= min_neighbours) & (s_min > roughness_m)
    return out


def graph_density(n_putative: int, n_edges: int) -> float:
    """Edges of the consistency graph over the pairs of its putative associations."""
    m = int(n_putative)
    return float(n_edges) / (m * (m - 1) / 2) if m > 1 else float("nan")


def pairs_at_distance(
    T_world_lidar: NDArray,
    lo_m: float = 4.0,
    hi_m: float = 5.0,
    max_pairs: int = 8,
    every_b: bool = False,
) -> list[tuple[int, int]]:
    """Up to ``max_pairs`` scan pairs (a < b) whose positions are ``lo_m``-``hi_m`` apart,
    spread evenly over the drive; each a is paired with the first b far enough from it, or
    with every such b when ``every_b`` (a short sequence such as KITTI's six scans)."""
    p = np.asarray(T_world_lidar, float)[:, :3, 3]
    cand = []
    for a in range(len(p)):
        d = np.linalg.norm(p[a + 1 :] - p[a], axis=1)
        ok = np.flatnonzero((d >= lo_m) & (d <= hi_m))
        for k in ok if every_b else ok[:1]:
            cand.append((a, a + 1 + int(k)))
    if len(cand) <= max_pairs:
        return cand
    pick = np.linspace(0, len(cand) - 1, max_pairs).round().astype(int)
    return [cand[k] for k in pick]


#: The arbitrary motion applied to the source of every matched pair: 180 deg yaw and 10 m,
#: so that the matcher gets no help from the initial guess.
def _extra_motion() -> NDArray:
    from graffmatch.geometry.transforms import make_transform, rot_z

    return make_transform(rot_z(np.pi), np.array([10.0, 0.0, 0.0]))


def scan_realism(points: NDArray, extractor) -> tuple[LandmarkSet, dict]:
    """The landmarks of one unlabelled scan and its per-scan statistics."""
    from graffmatch.lidar.ground import segment_ground

    P = np.asarray(points)
    ls = extractor.extract(P)
    is_ground = segment_ground(P[:, :3].astype(float), extractor.config.ground).is_ground
    scat = scattered_mask(P)
    c = ls.counts()
    rms = plane_flatness_rms(ls)
    rng_ = np.linalg.norm(P[:, :3].astype(float), axis=1)
    return ls, {
        "points": int(len(P)),
        "range_median_m": float(np.median(rng_)) if len(P) else float("nan"),
        "intensity_mean": float(np.mean(P[:, 3])) if len(P) and P.shape[1] > 3 else float("nan"),
        "poles": int(c["lines"]),
        "planes": int(c["planes"]),
        "plane_rms_m": rms.tolist(),
        "ground_share": float(np.mean(is_ground)) if len(P) else float("nan"),
        "scattered_share": float(scat[~is_ground].mean()) if (~is_ground).any() else float("nan"),
    }


def pair_realism(ls_a: LandmarkSet, ls_b: LandmarkSet, T_a_b: NDArray, matcher) -> dict:
    """Shared landmarks, strict repeatability, matcher error and graph density of one pair.

    The matcher registers b (moved by 180 deg and 10 m) onto a; its error is measured
    against ``T_a_b`` (the dataset's ground truth).
    """
    from graffmatch.geometry.transforms import invert, transform_errors

    b_in_a = ls_b.transform(T_a_b)
    X = _extra_motion()
    res = matcher.match(ls_b.transform(X), ls_a)
    T_true = T_a_b @ invert(X)
    rot, tr = (
        transform_errors(res.T_target_source, T_true)
        if res.T_target_source is not None
        else (float("nan"), float("nan"))
    )
    return {
        "distance_m": float(np.linalg.norm(np.asarray(T_a_b)[:3, 3])),
        "shared": int(len(true_shared_landmarks(ls_a, b_in_a))),
        "strict_repeatability": strict_repeatability(ls_a, b_in_a),
        "rot_err_deg": float(rot),
        "trans_err_m": float(tr),
        "graph_density": graph_density(res.n_putative, res.n_edges),
    }


#: The statistics of the realism table, in print order: (key, label, format).
REALISM_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("shared_per_pair", "true shared landmarks per pair", ".1f"),
    ("poles_per_scan", "poles per scan", ".1f"),
    ("planes_per_scan", "planes per scan", ".1f"),
    ("plane_rms_cm", "plane flatness RMS [cm] (median)", ".1f"),
    ("strict_repeatability", "strict repeatability (2 deg, 0.3 m)", ".2f"),
    ("scattered_share", "scattered share of non-ground points", ".3f"),
    ("ground_share", "ground share of points", ".2f"),
    ("trans_err_median_m", "matcher translation error, median [m]", ".2f"),
    ("graph_density", "consistency-graph density", ".2f"),
    ("points_per_scan", "points per scan", ".0f"),
    ("range_median_m", "median range [m]", ".1f"),
    ("intensity_mean", "mean intensity", ".2f"),
)


def sequence_realism(
    seq, pairs: list[tuple[int, int]], extractor=None, matcher=None, extra_frames=()
) -> dict:
    """The realism table's statistics of ``pairs`` of a dataset ``seq`` (scans, poses).

    No labels are read: poles come from the geometric front end as for a new user's data.
    The per-scan statistics cover the scans of the pairs and ``extra_frames`` (a small real
    sequence lends all its scans). Returns ``summary`` (the table's numbers), ``scans`` and
    ``pairs`` (the records).
    """
    from graffmatch.geometry.transforms import invert
    from graffmatch.lidar.extractor import LandmarkExtractor
    from graffmatch.matcher import GraffMatcher

    extractor = extractor or LandmarkExtractor()
    matcher = matcher or GraffMatcher()
    frames = sorted({i for p in pairs for i in p} | {int(i) for i in extra_frames})
    lss, scans = {}, []
    for i in frames:
        ls, rec = scan_realism(seq[i].points, extractor)
        lss[i] = ls
        scans.append({"index": i, **rec})
    poses = seq.poses
    recs = [
        {"a": a, "b": b, **pair_realism(lss[a], lss[b], invert(poses[a]) @ poses[b], matcher)}
        for a, b in pairs
    ]
    return {"summary": summarize_realism(scans, recs), "scans": scans, "pairs": recs}


def summarize_realism(scans: list[dict], pairs: list[dict]) -> dict:
    """The table's numbers from per-scan and per-pair records (of one drive or several pooled:
    means over scans and pairs, medians over all planes and all pairs)."""
    rms = np.concatenate([np.asarray(s["plane_rms_m"]) for s in scans] or [np.zeros(0)])

    def mean(key, rows):
        v = np.array([r[key] for r in rows], float)
        return float(np.nanmean(v)) if len(v) and np.isfinite(v).any() else float("nan")

    return {
        "shared_per_pair": mean("shared", pairs),
        "poles_per_scan": mean("poles", scans),
        "planes_per_scan": mean("planes", scans),
        "plane_rms_cm": 100.0 * float(np.median(rms)) if len(rms) else float("nan"),
        "strict_repeatability": mean("strict_repeatability", pairs),
        "scattered_share": mean("scattered_share", scans),
        "ground_share": mean("ground_share", scans),
        "trans_err_median_m": float(np.nanmedian([r["trans_err_m"] for r in pairs]))
        if pairs
        else float("nan"),
        "graph_density": mean("graph_density", pairs),
        "points_per_scan": mean("points", scans),
        "range_median_m": mean("range_median_m", scans),
        "intensity_mean": mean("intensity_mean", scans),
        "n_pairs": len(pairs),
        "n_scans": len(scans),
    }
