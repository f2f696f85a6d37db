"""The front end on real KITTI HDL-64E scans (kitti00_first6); skips without ../shared/data."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from graffmatch.geometry import distance
from graffmatch.geometry.landmarks import LandmarkType
from graffmatch.geometry.transforms import invert, make_transform, rot_z
from graffmatch.lidar import LandmarkExtractor, read_points
from graffmatch.matcher import GraffMatcher
from graffmatch.registration.closed_form import register_landmarks


def _lidar_poses(folder) -> np.ndarray:
    raw = np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)
    P = np.tile(np.eye(4), (len(raw), 1, 1))
    P[:, :3] = raw
    line = next(s for s in (folder / "calib.txt").read_text().splitlines() if s.startswith("Tr:"))
    Tr = np.eye(4)
    Tr[:3] = np.array(line.split()[1:], float).reshape(3, 4)
    P = np.einsum("ij,njk,kl->nil", invert(Tr), P, Tr)
    U, _, Vt = np.linalg.svd(P[:, :3, :3])
    P[:, :3, :3] = U @ Vt
    return P


@pytest.fixture(scope="module")
def kitti(shared_data):
    folder = shared_data / "kitti00_first6"
    ex = LandmarkExtractor()
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for i in (0, 3, 5):
            out[i] = ex.extract(read_points(folder / "velodyne" / f"{i:06d}.bin"))
    return folder, out


def test_counts_plausible(kitti) -> None:
    _, lss = kitti
    for ls in lss.values():
        c = ls.counts()
        assert 2 <= c["lines"] <= 40, c
        assert 5 <= c["planes"] <= 60, c
        ground = ls.attributes["is_ground"] > 0
        assert ground.sum() == 1
        # the ground is below the sensor (HDL-64E ~1.73 m above the road) and near-level
        n, d = ls[np.flatnonzero(ground)].hesse()[0, :3], ls[np.flatnonzero(ground)].hesse()[0, 3]
        assert n[2] > 0.99 and -2.0 < d < -1.5
        lines = ls.of_type(LandmarkType.LINE)
        assert np.all(np.abs(lines.directions[:, 2]) > np.cos(np.radians(15)))


def test_landmark_file_is_compact(kitti, tmp_path) -> None:
    folder, lss = kitti
    size = len(lss[0].to_bytes(include_points=False))
    raw = (folder / "velodyne" / "000000.bin").stat().st_size
    assert size < 10_000 and raw / size > 100


@pytest.mark.parametrize("other,min_rep", [(3, 0.7), (5, 0.65)])
def test_repeatability_after_gt_alignment(kitti, other: int, min_rep: float) -> None:
    """Landmarks of frame 0 with a counterpart in frame `other` within 6 deg (rho = 40 m)."""
    dist = distance
    folder, lss = kitti
    P = _lidar_poses(folder)
    b_in_0 = lss[other].transform(invert(P[0]) @ P[other])
    D = dist.cross_distances(lss[0], b_in_0, rho=40.0)
    hit = D.min(axis=1) <= np.radians(6.0)
    assert hit.mean() >= min_rep
    # ... and not trivially permissive: after a wrong alignment (GT then 30 deg of yaw about the
    # sensor) only landmarks yaw barely moves (ground, horizontal patches, near poles) match.
    wrong = lss[other].transform(
        make_transform(rot_z(np.radians(30)), np.zeros(3)) @ invert(P[0]) @ P[other]
    )
    hit_wrong = dist.cross_distances(lss[0], wrong, rho=40.0).min(axis=1) <= np.radians(6.0)
    assert hit_wrong.mean() < 0.5 * hit.mean()


def _gt_associations(src_in_tgt, tgt, dist) -> np.ndarray:
    D = dist.cross_distances(src_in_tgt, tgt, rho=40.0)
    j, i2 = D.argmin(axis=1), D.argmin(axis=0)
    i = np.arange(len(src_in_tgt))
    keep = (D[i, j] <= np.radians(6.0)) & (i2[j] == i)
    return np.column_stack([i[keep], j[keep]])


def test_gt_associations_register_frame5_to_frame0(kitti) -> None:
    """The landmarks themselves support registration: with the ground-truth associations the
    closed-form line/plane registration recovers 0 <- 5 (4.3 m) within 2 deg and 1 m."""
    dist = distance
    folder, lss = kitti
    P = _lidar_poses(folder)
    T_true = invert(P[0]) @ P[5]
    gt = _gt_associations(lss[5].transform(T_true), lss[0], dist)
    assert len(gt) >= 8
    est = register_landmarks(lss[5], lss[0], gt)
    from graffmatch.geometry.transforms import transform_errors

    rot, trans = transform_errors(est.T_target_source, T_true)
    assert rot < 2.0 and trans < 1.0


@pytest.mark.parametrize("other", [3, 5])
def test_end_to_end_match_with_extra_motion(kitti, other: int) -> None:
    """Extract, then GraffMatcher on 0 <- other after 180 deg yaw + 10 m: within 3 deg, 1.5 m."""
    from graffmatch.geometry.transforms import transform_errors

    folder, lss = kitti
    P = _lidar_poses(folder)
    X = make_transform(rot_z(np.pi), np.array([10.0, 0.0, 0.0]))
    res = GraffMatcher().match(lss[other].transform(X), lss[0])
    assert res.valid and res.T_target_source is not None
    rot, trans = transform_errors(res.T_target_source, invert(P[0]) @ P[other] @ invert(X))
    assert rot < 3.0 and trans < 1.5


def _returned_overlap(res, source, target, vcfg) -> float:
    """The point overlap of the transform the matcher returned, on the matcher's own evidence."""
    from graffmatch.verification.evidence import point_overlap
    from graffmatch.verification.verify import evidence_for

    ev = evidence_for(source, target, vcfg)
    return float(np.mean(point_overlap(ev.source, ev.target, res.T_target_source, vcfg.inlier_m)))


def test_reported_overlap_is_the_returned_transforms(kitti) -> None:
    """``overlap`` is the overlap of ``T_target_source`` even when the final landmark
    re-registration replaced the verified transform (on 3 <- 0 and 0 <- 3 it does: the verified
    transform explains 0.716 / 0.718, the returned one 0.704 / 0.701), and a valid result's
    returned transform explains at least ``min_overlap``."""
    _, lss = kitti
    m = GraffMatcher()
    vcfg = m.config.verification
    swapped = 0
    for a, b in ((3, 0), (0, 3), (5, 3), (3, 5)):
        res = m.match(lss[a], lss[b])
        assert res.valid, res.message
        assert res.overlap == pytest.approx(_returned_overlap(res, lss[a], lss[b], vcfg), abs=1e-9)
        assert res.overlap >= vcfg.min_overlap
        if "verified_overlap" in res.info:
            swapped += 1
            assert res.overlap >= res.info["verified_overlap"] - vcfg.refine_tolerance
    assert swapped >= 2


def test_re_registration_never_drops_the_returned_overlap_below_min_overlap(kitti) -> None:
    """With ``min_overlap`` between the re-registration's overlap (0.704) and the verified
    transform's (0.716) on 3 <- 0, the verified transform is returned, with its own overlap."""
    _, lss = kitti
    default = GraffMatcher().match(lss[3], lss[0])
    verified = default.info["verified_overlap"]
    assert default.overlap < verified - 0.005
    base = GraffMatcher().config
    vcfg = base.verification.model_copy(update={"min_overlap": 0.5 * (default.overlap + verified)})
    cfg = base.model_copy(update={"verification": vcfg})
    res = GraffMatcher(cfg).match(lss[3], lss[0])
    assert res.valid, res.message
    assert "verified_overlap" not in res.info and res.overlap == pytest.approx(verified, abs=1e-12)
    assert res.overlap == pytest.approx(_returned_overlap(res, lss[3], lss[0], cfg.verification), abs=1e-9)
    assert not np.array_equal(res.T_target_source, default.T_target_source)
