"""Tests of the simulated LiDAR world: determinism, KITTI layout, GT consistency, sensor, routes."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from graffmatch.datasets.simulator import (
    CATEGORIES,
    KITTI00_TR,
    PROFILES,
    SUITES,
    build_world,
    camera_to_lidar_poses,
    extraction_accuracy,
    get_profile,
    gt_landmarks_in_scan,
    lidar_to_camera_poses,
    plan_route,
    render_scan,
    revisit_pairs,
    scan_ground_truth,
    simulate_dataset,
    simulate_scan_pair,
    world_preset,
)
from graffmatch.datasets.simulator.world import POLE, ROAD, TRUNK
from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet, fit_landmark
from graffmatch.geometry.transforms import invert, random_transform, transform_points

CLASSES = {10, 40, 48, 50, 51, 70, 71, 72, 80, 81, 99}


@pytest.fixture(scope="module")
def worlds():
    return {s: build_world(s, 3) for s in ("downtown", "suburban", "open-road")}


@pytest.fixture(scope="module")
def scans(worlds):
    """One HDL-64 scan per style from the middle of a planned route."""
    out = {}
    for style, w in worlds.items():
        T = plan_route(w, 30, 3).T_world_lidar[15]
        pts, labels, lm = render_scan(w, T, "hdl64", 0, return_landmarks=True)
        out[style] = (T, pts, labels, lm)
    return out


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "seq"
    t = time.perf_counter()
    simulate_dataset(out, style="open-road", seed=5, n_scans=8)
    return out, time.perf_counter() - t


# ---- world --------------------------------------------------------------------------------
def test_world_is_deterministic_and_seed_dependent():
    a, b, c = build_world("open-road", 7), build_world("open-road", 7), build_world("open-road", 8)
    for name in ("vertices", "triangles", "tri_class", "tri_instance", "tri_landmark"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.landmarks.approx_equal(b.landmarks, atol=0)
    assert not np.array_equal(a.street_x, c.street_x)


def test_styles_have_their_character(worlds):
    def per_km(w, *cats, area=False):
        c = w.landmarks.attributes["category"]
        street_km = (
            np.ptp(w.street_x) * len(w.street_y) + np.ptp(w.street_y) * len(w.street_x)
        ) / 1e3
        sel = np.isin(c, [CATEGORIES[k] for k in cats])
        return (w.landmarks.attributes["extent"][sel].sum() if area else sel.sum()) / street_km

    dt, sub, road = worlds["downtown"], worlds["suburban"], worlds["open-road"]
    poles = ("street_light", "sign_post", "trunk", "utility_pole")
    # downtown: many facades, few poles; suburban: trees and poles; open road: sparse
    assert per_km(dt, "facade", area=True) > 3 * per_km(sub, "facade", area=True)
    assert per_km(dt, *poles) < 0.6 * per_km(sub, *poles)
    assert per_km(sub, "trunk") > 3 * per_km(dt, "trunk")
    assert per_km(road, "facade", area=True) < 0.05 * per_km(dt, "facade", area=True)
    assert per_km(road, "utility_pole") > 5
    for w in worlds.values():
        assert set(np.unique(w.tri_class).tolist()) <= CLASSES
        assert np.all(w.tri_instance[w.tri_class == ROAD] == 0)
        radius = w.landmarks.attributes["radius"][w.landmarks.types == 1]
        height = w.landmarks.attributes["extent"][w.landmarks.types == 1]
        assert radius.min() >= 0.03 and radius.max() <= 0.3
        assert height.min() >= 2.0 and height.max() <= 11.0


#: sha256 prefixes of world arrays (seed 0) and, per style, the HDL-64E scan 10 of a 20-scan route:
#: point count and coordinate sum. Recorded before world.py was split by concept (issue 10);
#: any change to what a seed produces must be deliberate (and bump SIMULATOR_VERSION).
GOLDEN_WORLDS = {
    "downtown": ("12e4549a15df58b4", 126123, -174464.68437),
    "suburban": ("228752c317ef85dd", 127352, -268498.43565),
    "open-road": ("2a1e934150d42048", 109897, -118800.53715),
}


@pytest.mark.parametrize("style", sorted(GOLDEN_WORLDS))
def test_seed_reproduces_the_recorded_world_and_scan(style):
    import hashlib

    w = build_world(style, 0)
    h = hashlib.sha256()
    for a in (w.vertices, w.triangles, w.tri_class, w.tri_instance, w.tri_landmark):
        h.update(np.ascontiguousarray(a).tobytes())
    digest, n_points, coord_sum = GOLDEN_WORLDS[style]
    assert h.hexdigest()[:16] == digest
    pts, _ = render_scan(w, plan_route(w, 20, 0).T_world_lidar[10], "hdl64", 0)
    assert len(pts) == n_points
    assert float(pts[:, :3].astype(np.float64).sum()) == pytest.approx(coord_sum, abs=1e-2)


@settings(max_examples=6, deadline=None)
@given(st.integers(0, 10_000), st.sampled_from(["downtown", "suburban", "open-road"]))
def test_world_layout_is_physically_consistent(seed, style):
    w = build_world(style, seed)
    L = w.landmarks
    cat, inst = L.attributes["category"], L.attributes["instance"]
    # building footprints from their four GT facades; no two buildings overlap
    fac = np.flatnonzero(cat == CATEGORIES["facade"])
    boxes = []
    for b in np.unique(inst[fac]):
        faces = fac[inst[fac] == b]
        assert len(faces) == 4
        a = L.anchors[faces]
        boxes.append((a[:, 0].min(), a[:, 0].max(), a[:, 1].min(), a[:, 1].max()))
    B = np.array(boxes)
    ov = (
        (B[:, None, 0] < B[None, :, 1] - 1e-6)
        & (B[None, :, 0] < B[:, None, 1] - 1e-6)
        & (B[:, None, 2] < B[None, :, 3] - 1e-6)
        & (B[None, :, 2] < B[:, None, 3] - 1e-6)
    )
    np.fill_diagonal(ov, False)
    assert not ov.any()
    # poles stand on the (raised) ground, outside every building and off the roadway
    poles = np.flatnonzero(L.types == 1)
    a = L.anchors[poles]
    base = a[:, 2] - L.attributes["extent"][poles] / 2
    assert np.allclose(base, w.ground_height(a[:, 0], a[:, 1]) + 0.15, atol=1e-9)
    inside = (
        (a[:, None, 0] > B[None, :, 0]) & (a[:, None, 0] < B[None, :, 1])
        & (a[:, None, 1] > B[None, :, 2]) & (a[:, None, 1] < B[None, :, 3])
    )  # fmt: skip
    assert not inside.any()
    dx = np.abs(a[:, None, 0] - w.street_x[None]).min(axis=1)
    dy = np.abs(a[:, None, 1] - w.street_y[None]).min(axis=1)
    assert np.all(np.maximum(np.minimum(dx, dy), 0) >= w.road_half_width - 1e-9)


def test_ground_is_gently_sloped_and_planar_patches(worlds):
    w = worlds["suburban"]
    g = w.ground_gradient(np.linspace(-150, 150, 301), np.linspace(-150, 150, 301))
    assert np.abs(g).max() <= w.config.max_slope + 1e-12
    assert np.abs(g).max() > 0.2 * w.config.max_slope  # not flat
    ground = w.landmarks.attributes["category"] == CATEGORIES["ground"]
    normals = w.landmarks.directions[ground]
    assert np.all(normals[:, 2] > np.cos(np.deg2rad(3.0)))


# ---- rays vs. ground truth ------------------------------------------------------------------
@pytest.mark.parametrize("style", ["downtown", "suburban", "open-road"])
def test_points_lie_on_their_gt_landmarks(worlds, scans, style):
    w = worlds[style]
    T, pts, labels, lm = scans[style]
    P = transform_points(T, pts[:, :3])
    L = w.landmarks
    on = lm >= 0
    d = P[on] - L.anchors[lm[on]]
    u = L.directions[lm[on]]
    t = L.types[lm[on]]
    # planes: facades, walls, fences, ground patches within noise (5 sigma) of their GT plane
    dist = np.abs(np.einsum("ij,ij->i", d[t == 2], u[t == 2]))
    assert (t == 2).sum() > 10_000
    assert dist.max() < 0.1 and np.median(dist) < 0.02
    # poles: within radius + noise + facet error of the GT axis, and within its extent
    dl, ul = d[t == 1], u[t == 1]
    along = np.einsum("ij,ij->i", dl, ul)
    radial = np.linalg.norm(dl - along[:, None] * ul, axis=1)
    r = L.attributes["radius"][lm[on]][t == 1]
    ext = L.attributes["extent"][lm[on]][t == 1]
    assert (t == 1).sum() > 100
    assert np.all(np.abs(radial - r) < 0.1)
    assert np.all(np.abs(along) <= ext / 2 + 0.1)
    # every point on a GT pole carries a pole-like class; most pole/trunk points are on GT poles
    cls = labels & 0xFFFF
    assert set(np.unique(cls[on][t == 1]).tolist()) <= {POLE, TRUNK}
    polelike = np.isin(cls, [POLE, TRUNK])
    assert np.mean(lm[polelike] >= 0) > 0.5


def test_pca_fits_of_visible_gt_landmarks_recover_them(worlds, scans):
    w = worlds["suburban"]
    T, pts, _, lm = scans["suburban"]
    vis = gt_landmarks_in_scan(w, lm, T, min_points=40)
    assert vis.counts()["lines"] >= 3 and vis.counts()["planes"] >= 10
    checked = lines_checked = 0
    for k in range(len(vis)):
        gid = int(vis.attributes["gt_id"][k])
        sup = pts[lm == gid, :3]
        if vis.types[k] == 1 and np.ptp(sup[:, 2]) < 1.5:
            continue  # a pole seen by a few rings only: PCA has no axis to find
        fit, _ = fit_landmark(sup, int(vis.types[k]))
        B = fit.basis
        u = B[:, 0] if B.shape[1] == 1 else np.cross(B[:, 0], B[:, 1])
        ang = np.degrees(np.arccos(min(1.0, abs(float(u @ vis.directions[k])))))
        if vis.types[k] == 2:
            assert ang < 1.5, (gid, ang)
            assert abs(float(vis.directions[k] @ (fit.anchor - vis.anchors[k]))) < 0.03
        else:
            assert ang < 5.0, (gid, ang)
            off = fit.anchor - vis.anchors[k]
            off -= (off @ vis.directions[k]) * vis.directions[k]
            assert np.linalg.norm(off) < 0.1 + vis.attributes["radius"][k]
        checked += 1
        lines_checked += int(vis.types[k] == 1)
    assert checked >= 12 and lines_checked >= 2


# ---- sensor -----------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(PROFILES))
def test_range_limits_and_beams(worlds, name):
    prof = get_profile(name)
    w = worlds["open-road"]
    T = plan_route(w, 5, 1).T_world_lidar[2]
    pts, labels = render_scan(w, T, prof, 1)
    r = np.linalg.norm(pts[:, :3].astype(float), axis=1)
    assert r.min() >= prof.min_range - 5 * prof.range_noise_std
    assert r.max() <= prof.max_range + 5 * prof.range_noise_std
    assert r.max() > 0.5 * prof.max_range  # the flat open road is seen far away
    elev = np.degrees(np.arcsin(pts[:, 2] / r))
    beams = prof.beam_elevations_deg()
    nearest = np.abs(elev[:, None] - beams[None]).min(axis=1)
    assert nearest.max() < 1e-3  # noise is along the ray: every point keeps its beam
    ring = np.abs(elev[:, None] - beams[None]).argmin(axis=1)
    per_ring = np.bincount(ring, minlength=prof.n_beams)
    assert len(beams) == prof.n_beams and per_ring.max() <= prof.n_columns
    assert len(pts) <= prof.n_beams * prof.n_columns
    assert pts.dtype == np.float32 and labels.dtype == np.uint32
    assert 0.0 <= pts[:, 3].min() and pts[:, 3].max() <= 1.0 and pts[:, 3].std() > 0.02


def test_hdl64_profile_matches_the_spec():
    p = get_profile("hdl64")
    el = p.beam_elevations_deg()
    assert p.n_beams == 64 and el.max() == pytest.approx(2.0) and el.min() == pytest.approx(-24.9)
    assert 0.1 <= p.azimuth_step_deg <= 0.2 and p.max_range == 120.0
    assert p.range_noise_std == pytest.approx(0.02)


def test_noise_and_dropout_statistics(worlds):
    w = worlds["downtown"]
    T = plan_route(w, 5, 0).T_world_lidar[2]
    clean = get_profile("hdl64").model_copy(update={"range_noise_std": 0.0, "dropout_prob": 0.0})
    noisy = get_profile("hdl64").model_copy(update={"dropout_prob": 0.1})
    a, _ = render_scan(w, T, clean, 0)
    b, _ = render_scan(w, T, noisy, 0)
    assert 0.85 < len(b) / len(a) < 0.95
    # same rays: compare ranges of the points both kept (matched by direction)
    da = a[:, :3] / np.linalg.norm(a[:, :3], axis=1, keepdims=True)
    db = b[:, :3] / np.linalg.norm(b[:, :3], axis=1, keepdims=True)
    key = lambda d: np.round(d * 1e4).astype(np.int64) @ np.array([1, 10**5, 10**10])  # noqa: E731
    _, ia, ib = np.intersect1d(key(da), key(db), return_indices=True)
    dr = np.linalg.norm(b[ib, :3], axis=1) - np.linalg.norm(a[ia, :3], axis=1)
    assert abs(dr.mean()) < 0.002 and 0.017 < dr.std() < 0.023


# ---- KITTI layout, determinism, poses -------------------------------------------------------
def _read_rows(path: Path) -> np.ndarray:
    return np.array([[float(v) for v in ln.split()] for ln in path.read_text().splitlines()])


def test_kitti_layout_is_written_and_readable(dataset):
    out, _ = dataset
    bins = sorted((out / "velodyne").glob("*.bin"))
    labs = sorted((out / "labels").glob("*.label"))
    assert [p.name for p in bins] == [f"{i:06d}.bin" for i in range(8)]
    assert [p.stem for p in labs] == [p.stem for p in bins]
    for b, lab in zip(bins, labs, strict=True):
        pts = np.fromfile(b, dtype=np.float32).reshape(-1, 4)
        labels = np.fromfile(lab, dtype=np.uint32)
        assert len(pts) == len(labels) > 50_000
        assert set(np.unique(labels & 0xFFFF).tolist()) <= CLASSES
    poses = _read_rows(out / "poses.txt")
    assert poses.shape == (8, 12)
    calib = (out / "calib.txt").read_text().split()
    assert calib[0] == "Tr:" and len(calib) == 13
    Tr = np.vstack([np.array(calib[1:], float).reshape(3, 4), [0, 0, 0, 1]])
    assert np.allclose(Tr, KITTI00_TR, atol=0)
    times = _read_rows(out / "times.txt")[:, 0]
    assert np.allclose(np.diff(times), 0.1)
    meta = json.loads((out / "sim_meta.json").read_text())
    assert meta["seed"] == 5 and meta["style"] == "open-road" and meta["n_scans"] == 8
    gt = LandmarkSet.load(out / "landmarks_gt.npz")
    assert gt.approx_equal(build_world("open-road", 5).landmarks, atol=1e-9)


def test_poses_recover_the_lidar_trajectory(dataset):
    out, _ = dataset
    P = np.zeros((8, 4, 4))
    P[:, :3] = _read_rows(out / "poses.txt").reshape(-1, 3, 4)
    P[:, 3, 3] = 1
    calib = (out / "calib.txt").read_text().split()
    Tr = np.vstack([np.array(calib[1:], float).reshape(3, 4), [0, 0, 0, 1]])
    U, _, Vt = np.linalg.svd(Tr[:3, :3])
    Tr[:3, :3] = U @ Vt  # what a careful reader does with printed rotations
    T_rec = np.linalg.inv(Tr) @ P @ Tr
    T_true = plan_route(build_world("open-road", 5), 8, 5).T_world_lidar
    assert np.abs(T_rec - T_true).max() < 1e-8
    steps = np.linalg.norm(np.diff(T_true[:, :3, 3], axis=0), axis=1)
    assert np.all((steps > 0.85) & (steps < 1.15))


def test_scan_ground_truth_matches_the_scan(dataset):
    out, _ = dataset
    T = plan_route(build_world("open-road", 5), 8, 5).T_world_lidar[4]
    vis = scan_ground_truth(out, 4, T, min_points=20)
    assert len(vis) >= 3 and np.all(vis.attributes["support"] >= 20)
    pts = np.fromfile(out / "velodyne" / "000004.bin", dtype=np.float32).reshape(-1, 4)
    # every visible GT plane has >= 20 scan points within 10 cm of it (in the LiDAR frame)
    for k in np.flatnonzero(vis.types == 2):
        d = np.abs((pts[:, :3] - vis.anchors[k]) @ vis.directions[k])
        assert np.sum(d < 0.1) >= 20


def test_same_seed_gives_identical_bytes(dataset, tmp_path):
    out, elapsed = dataset
    again = simulate_dataset(tmp_path / "again", style="open-road", seed=5, n_scans=8)
    files = [
        p.relative_to(out) for p in sorted(out.rglob("*")) if p.is_file() and p.suffix != ".npz"
    ]
    assert len(files) == 2 * 8 + 4
    for f in files:
        assert (out / f).read_bytes() == (again / f).read_bytes(), f
    # reuse keeps a finished identical simulation untouched, and redoes a different request
    stamp = (out / "velodyne/000000.bin").stat().st_mtime_ns
    simulate_dataset(out, style="open-road", seed=5, n_scans=8, reuse=True)
    assert (out / "velodyne/000000.bin").stat().st_mtime_ns == stamp
    other = simulate_dataset(tmp_path / "other", style="open-road", seed=6, n_scans=1)
    assert (out / "velodyne/000000.bin").read_bytes() != (
        other / "velodyne/000000.bin"
    ).read_bytes()
    assert elapsed < 15.0


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_camera0_pose_convention_round_trip(seed):
    T = random_transform(np.random.default_rng(seed), max_translation=500.0)
    P = lidar_to_camera_poses(T)[0]
    Tr = KITTI00_TR
    assert np.allclose(np.linalg.inv(Tr) @ P @ Tr, T, atol=1e-5)  # with the raw digits
    assert np.allclose(camera_to_lidar_poses(P)[0], T, atol=1e-9)
    # a camera pose is the LiDAR pose seen through Tr: same motion, rotated axes
    assert np.isclose(np.trace(P[:3, :3]), np.trace(T[:3, :3]), atol=1e-9)


def test_calib_matches_real_kitti00(shared_data):
    calib = (shared_data / "kitti00_first6" / "calib.txt").read_text()
    line = next(ln for ln in calib.splitlines() if ln.startswith("Tr:"))
    Tr = np.array(line.split()[1:], float).reshape(3, 4)
    assert np.allclose(Tr, KITTI00_TR[:3], atol=1e-15)


# ---- trajectories, scan pair, suites, errors --------------------------------------------------
@pytest.mark.parametrize("style", ["downtown", "suburban", "open-road"])
def test_routes_have_revisits_of_all_rotations(worlds, style):
    w = worlds[style]
    traj = plan_route(w, 300, 1)
    places, pairs, dyaw = revisit_pairs(traj.T_world_lidar)
    assert len(places) == pytest.approx(150, abs=3)
    p = traj.positions
    dist = np.linalg.norm(p[pairs[:, 0]] - p[pairs[:, 1]], axis=1)
    assert np.all(dist < 16.0) and np.all(np.abs(np.diff(traj.arc_length[pairs], axis=1)) > 50)
    assert len(pairs) >= 200
    assert (
        np.sum(dyaw > 150) >= 20
        and np.sum(dyaw < 30) >= 20
        and np.sum((dyaw > 60) & (dyaw < 120)) >= 5
    )
    assert dist.max() > 12.0

    # revisits in other lanes: opposite-direction passes use the other side of the street, and
    # on multi-lane streets same-direction passes also come back in another lane
    def lateral(sel):
        pr = pairs[sel]
        head = traj.T_world_lidar[pr[:, 0], :3, 0]
        off = p[pr[:, 1]] - p[pr[:, 0]]
        return np.linalg.norm(off - np.einsum("ij,ij->i", off, head)[:, None] * head, axis=1)

    assert lateral(dyaw > 170).max() > 0.8 * w.config.lane_width
    if w.config.lanes_per_direction > 1:
        assert lateral(dyaw < 10).max() > 0.8 * w.config.lane_width


def test_scan_pair_for_the_demo():
    t = time.perf_counter()
    d = simulate_scan_pair("downtown", seed=0, yaw_deg=180, offset_m=14)
    assert time.perf_counter() - t < 10.0
    Ta, Tb = d["T_world_lidar"]
    T_ab = d["T_a_b"]
    assert np.allclose(T_ab, invert(Ta) @ Tb)
    ang = np.degrees(np.arccos(np.clip((np.trace(T_ab[:3, :3]) - 1) / 2, -1, 1)))
    assert ang == pytest.approx(180.0, abs=3.0)
    assert np.linalg.norm(T_ab[:3, 3]) == pytest.approx(14.0, abs=0.2)
    va, vb = d["visible_gt"]
    common = np.intersect1d(va.attributes["gt_id"], vb.attributes["gt_id"])
    assert len(common) >= 10
    assert va.counts()["lines"] >= 2 and va.counts()["planes"] >= 10
    # the visible GT of B, moved into A's frame, is A's visible GT for the shared landmarks
    gid_a = {int(g): k for k, g in enumerate(va.attributes["gt_id"])}
    vb_in_a = vb.transform(T_ab)
    for k, g in enumerate(vb.attributes["gt_id"]):
        if int(g) in gid_a:
            assert np.allclose(vb_in_a.anchors[k], va.anchors[gid_a[int(g)]], atol=1e-6)


def test_extraction_accuracy_scores_a_front_end(worlds, scans):
    w = worlds["suburban"]
    T, pts, _, lm = scans["suburban"]
    gt = gt_landmarks_in_scan(w, lm, T, min_points=40)
    # a "front end" that fits every GT landmark's own points recovers all of them, accurately
    fits = [
        fit_landmark(pts[lm == int(g), :3], int(k))[0]
        for g, k in zip(gt.attributes["gt_id"], gt.types, strict=True)
    ]
    perfect = LandmarkSet.from_landmarks(fits)
    acc = extraction_accuracy(perfect, gt)
    for kind in ("lines", "planes"):
        assert acc[kind]["recovered"] == 1.0 and acc[kind]["precision"] == 1.0
        assert acc[kind]["angle_deg"]["p90"] < 5.0
    assert acc["planes"]["anchor_m"]["p90"] < 0.03
    assert acc["lines"]["anchor_m"]["p90"] < 0.35  # surface centroid is ~ a radius off the axis
    # moving everything 2 m sideways and tilting it loses the matches
    from graffmatch.geometry.transforms import make_transform, rot_x

    moved = perfect.transform(make_transform(rot_x(np.radians(20)), [0.0, 2.0, 0.0]))
    bad = extraction_accuracy(moved, gt)
    assert bad["lines"]["recovered"] < 0.2 and bad["planes"]["recovered"] < 0.5


def test_suites_are_three_distinct_named_datasets():
    assert set(SUITES) == {"sim-downtown", "sim-suburban", "sim-openroad"}
    assert len({s.style for s in SUITES.values()}) == 3
    for s in SUITES.values():
        assert 100 <= s.n_scans <= 600
        cfg = s.world_config()
        assert cfg.style == s.style
        for key, value in s.world_overrides.items():
            assert getattr(cfg, key) == value
        get_profile(s.sensor)
    bad = SUITES["sim-downtown"].model_copy(update={"world_overrides": {"towers": 3}})
    with pytest.raises(ValueError, match="towers"):
        bad.world_config()


def _facade_area_per_block(world):
    """Facade area of each block, found by the street lines around its anchor."""
    lm = world.landmarks
    sel = lm.attributes["category"] == CATEGORIES["facade"]
    x, y = lm.anchors[sel, 0], lm.anchors[sel, 1]
    bx = np.searchsorted(world.street_x, x) - 1
    by = np.searchsorted(world.street_y, y) - 1
    n = len(world.street_y) - 1
    area = np.zeros((len(world.street_x) - 1) * n)
    np.add.at(area, bx * n + by, lm.attributes["extent"][sel])
    return area


def test_block_variety_makes_parks_and_uneven_blocks():
    base = world_preset("downtown").model_copy(update={"frontage": 0.5})
    parks = build_world(base.model_copy(update={"open_block_prob": 1.0}), 4)
    assert _facade_area_per_block(parks).max() == 0.0  # every block is a park: no facade
    cat = parks.landmarks.attributes["category"]
    assert np.sum(cat == CATEGORIES["trunk"]) > np.sum(
        build_world(base, 4).landmarks.attributes["category"] == CATEGORIES["trunk"]
    )
    even = _facade_area_per_block(build_world(base, 4))
    uneven = _facade_area_per_block(
        build_world(base.model_copy(update={"frontage_spread": 1.0}), 4)
    )
    assert even.min() > 0  # frontage 0.5 on every block: each block has some facade
    assert uneven.min() == 0.0 and uneven.std() > 1.3 * even.std()


def test_tree_prob_spread_alternates_tree_lined_and_bare_stretches():
    base = world_preset("open-road").model_copy(update={"tree_prob": 0.5, "tree_spacing": 8.0})

    def trunks(cfg):
        return int(
            np.sum(build_world(cfg, 2).landmarks.attributes["category"] == CATEGORIES["trunk"])
        )

    assert trunks(base.model_copy(update={"tree_prob": 1.0})) > trunks(base)
    assert trunks(base.model_copy(update={"tree_prob_spread": 0.5})) != trunks(base)


def test_bad_inputs_raise_clear_errors(worlds, tmp_path):
    with pytest.raises(InvalidInputError, match="style"):
        build_world("moon-base", 0)
    with pytest.raises(InvalidInputError, match="sensor"):
        get_profile("hdl32")
    with pytest.raises(InvalidInputError):
        plan_route(worlds["downtown"], 0)
    with pytest.raises(InvalidInputError):
        render_scan(worlds["downtown"], np.diag([1.0, 1.0, 2.0, 1.0]))
    with pytest.raises(InvalidInputError):
        simulate_dataset(tmp_path / "x", n_scans=0)
    with pytest.raises(InvalidInputError):
        simulate_scan_pair(offset_m=100.0)


# ---- realism (issue 13) ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def realistic():
    """A realistic suburban world, its route and one scan with and without motion."""
    from graffmatch.datasets.simulator.realism import get_realism
    from graffmatch.datasets.simulator.simulate import realistic_world_config

    cfg = realistic_world_config(world_preset("suburban"), get_realism("realistic"))
    w = build_world(cfg, 3)
    traj = plan_route(w, 30, 3)
    return w, traj


def test_realism_presets_exist_and_ideal_is_the_old_simulator(tmp_path):
    from graffmatch.datasets.simulator.realism import REALISM_PRESETS, get_realism

    assert {"ideal", "realistic", "kitti-gt"} <= set(REALISM_PRESETS)
    assert get_realism(None).is_ideal and not get_realism("realistic").is_ideal
    with pytest.raises(InvalidInputError, match="realism"):
        get_realism("photoreal")
    a = simulate_dataset(tmp_path / "a", style="open-road", seed=5, n_scans=3)
    b = simulate_dataset(tmp_path / "b", style="open-road", seed=5, n_scans=3, realism="ideal")
    c = simulate_dataset(tmp_path / "c", style="open-road", seed=5, n_scans=3, realism="realistic")
    for name in ("velodyne/000001.bin", "labels/000001.label", "poses.txt", "sim_meta.json"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    assert (a / "velodyne/000001.bin").read_bytes() != (c / "velodyne/000001.bin").read_bytes()
    assert json.loads((c / "sim_meta.json").read_text())["realism"]["name"] == "realistic"
    # the suites run the realistic simulator
    assert all(s.realism == "realistic" for s in SUITES.values())


def test_realistic_facades_are_rough_and_vegetation_scatters(worlds, realistic):
    import warnings

    from graffmatch.evaluation.realism import plane_flatness_rms, scattered_mask
    from graffmatch.lidar.extractor import LandmarkExtractor

    w, _traj = realistic
    ideal = worlds["suburban"]
    ex = LandmarkExtractor()
    rms, scat = {}, {}
    for name, world in (("ideal", ideal), ("realistic", w)):
        T = plan_route(world, 30, 3).T_world_lidar[15]
        pts, labels = render_scan(world, T, "hdl64", 0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rms[name] = float(np.median(plane_flatness_rms(ex.extract(pts))))
        veg = (labels & 0xFFFF) == 70
        scat[name] = float(scattered_mask(pts)[veg].mean())
    assert rms["realistic"] > 0.02 and rms["ideal"] < 0.015, rms
    assert scat["realistic"] > 0.1 and scat["ideal"] < 0.01, scat  # measured 0.15 vs 0.0
    # glass: windows exist and none of their returns claims a GT landmark
    assert (w.tri_material == 1).sum() > 1000 and np.all(w.tri_landmark[w.tri_material == 1] == -1)


def test_motion_distortion_is_present_and_deskew_removes_it(realistic):
    from graffmatch.datasets.simulator.motion import deskew_scan, sweep_poses, sweep_twist

    w, traj = realistic
    T = traj.T_world_lidar
    i = 12
    twist = sweep_twist(T[i - 1], T[i + 1])
    sweep = sweep_poses(T[i], twist, PROFILES["hdl64"].n_columns)
    pts, _, lm = render_scan(w, T[i], "hdl64", 0, sweep=sweep, return_landmarks=True)
    # where each point really is: taken from its column's pose
    n = PROFILES["hdl64"].n_columns
    az = np.arctan2(pts[:, 1], pts[:, 0])
    col = np.clip((np.mod(np.pi - az, 2 * np.pi) / (2 * np.pi) * n).astype(int), 0, n - 1)
    true = np.einsum("nij,nj->ni", sweep[col, :3, :3], pts[:, :3]) + sweep[col, :3, 3]
    raw_err = np.linalg.norm(transform_points(T[i], pts[:, :3]) - true, axis=1)
    fixed = deskew_scan(pts, T[i - 1], T[i + 1])
    fix_err = np.linalg.norm(transform_points(T[i], fixed[:, :3]) - true, axis=1)
    # 1 m per 0.1 s sweep: up to 0.5 m at the start and end of the sweep
    assert np.percentile(raw_err, 90) > 0.35 and np.median(raw_err) > 0.15
    assert np.percentile(fix_err, 99) < 0.02
    assert np.array_equal(fixed[:, 3], pts[:, 3])
    # the rendering really moved: on GT planes facing the driving direction, the points placed
    # with their column's pose lie on the plane, placed with the scan's pose they do not
    L = w.landmarks
    drive = T[i + 1][:3, 3] - T[i - 1][:3, 3]
    drive /= np.linalg.norm(drive)
    on = (lm >= 0) & (L.types[np.maximum(lm, 0)] == 2)
    facing = on & (np.abs(L.directions[np.maximum(lm, 0)] @ drive) > 0.9)
    n, a = L.directions[lm[facing]], L.anchors[lm[facing]]
    d_true = np.abs(np.einsum("ij,ij->i", true[facing] - a, n))
    d_naive = np.abs(np.einsum("ij,ij->i", transform_points(T[i], pts[facing, :3]) - a, n))
    assert facing.sum() > 200
    assert np.median(d_true) < 0.05 and np.median(d_naive) > 0.15


def test_movers_move_and_label_noise_hits_poles(realistic):
    from graffmatch.datasets.simulator.movers import MOVING_CAR, MOVING_PERSON, place_movers
    from graffmatch.datasets.simulator.realism import get_realism, noisy_labels

    w, traj = realistic
    mv = place_movers(w, np.random.default_rng(0), 6.0, 15.0)
    assert (mv.cls == MOVING_CAR).sum() > 10 and (mv.cls == MOVING_PERSON).sum() > 10
    step = np.linalg.norm(mv.positions(1.0) - mv.positions(0.0), axis=1)
    assert np.median(step) > 0.7 and np.all(step <= 12.0 + 1e-9)  # some turn at a street end
    T = traj.T_world_lidar[10]
    dyn = mv.mesh(w, 0.0, T[:2, 3], radius=200.0)
    _pts, labels = render_scan(w, T, "hdl64", 0, dynamic=dyn)
    assert np.isin(labels & 0xFFFF, [MOVING_CAR, MOVING_PERSON]).sum() > 50
    # label noise: about label_miss of the pole points lose their class, whole objects swap
    _, clean = render_scan(w, T, "hdl64", 0)
    cfg = get_realism("realistic")
    noisy = noisy_labels(clean, cfg, np.random.default_rng(1))
    pole = np.isin(clean & 0xFFFF, [80, 81, 71])
    kept = np.mean((noisy[pole] & 0xFFFF) == (clean[pole] & 0xFFFF))
    assert 1 - cfg.label_miss - 0.2 < kept < 1 - cfg.label_miss / 2
    assert np.array_equal(noisy >> 16, clean >> 16)


def test_gt_pose_noise_like_kitti(tmp_path):
    from graffmatch.datasets.folder import KittiFolder

    a = KittiFolder(simulate_dataset(tmp_path / "r", style="open-road", seed=2, n_scans=12,
                                     realism="realistic"))  # fmt: skip
    b = KittiFolder(simulate_dataset(tmp_path / "k", style="open-road", seed=2, n_scans=12,
                                     realism="kitti-gt"))  # fmt: skip
    err = np.linalg.norm(a.poses[:, :3, 3] - b.poses[:, :3, 3], axis=1)
    assert 0.1 < np.median(err) < 1.0
    assert (tmp_path / "r/labels/000005.label").read_bytes() == (
        tmp_path / "k/labels/000005.label"
    ).read_bytes()  # same scans; only poses differ (and kitti-gt scans are de-skewed)


def test_realistic_drive_slows_in_turns():
    """The ideal route keeps 1 m per scan through U-turns (~70 deg of yaw between two scans,
    which made KISS-ICP diverge); the realistic one slows to keep lateral acceleration low."""
    from graffmatch.datasets.simulator import TrajectoryConfig

    w = build_world("suburban", 1)

    def yaw_steps(cfg):
        T = plan_route(w, 400, 1, cfg).T_world_lidar
        yaw = np.arctan2(T[:, 1, 0], T[:, 0, 0])
        return np.degrees(np.abs(np.angle(np.exp(1j * np.diff(yaw))))), T

    ideal, _ = yaw_steps(TrajectoryConfig())
    real, T = yaw_steps(TrajectoryConfig(max_lateral_accel=2.0))
    assert ideal.max() > 40.0
    assert real.max() < 20.0
    step = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    assert step.max() <= 1.01 and step.min() < 0.4  # 10 m/s on straights (3D), slow in turns


def test_panel_relief_is_fixed_per_panel_and_has_its_sigma():
    """The relief survives voxel averaging: it is one depth per (object, panel), the same in
    every scan, with the configured sigma; a depth along the normal is longer along a slant ray."""
    from graffmatch.datasets.simulator.sensor import _panel_relief

    rng = np.random.default_rng(0)
    n = 20000
    y, z = rng.uniform(-20, 20, n), rng.uniform(0, 10, n)
    hits = np.c_[np.full(n, 10.0), y, z]  # points on the wall x = 10 (normal -x)
    origin = np.zeros(3)
    d = hits - origin
    t = np.linalg.norm(d, axis=1)
    rays = np.c_[np.tile(origin, (n, 1)), d / t[:, None]].astype(np.float32)
    normals = np.tile([-1.0, 0.0, 0.0], (n, 1)).astype(np.float32)
    inst = np.full(n, 7, np.uint32)
    off = _panel_relief(rays, t.astype(np.float32), normals, inst, 0.04, 1.0)
    depth = off * np.abs(rays[:, 3])  # back along the normal
    # one depth per 1 m panel: points of the same panel agree, panels differ
    panel = np.floor(y).astype(int) * 100 + np.floor(z).astype(int)
    for p in np.unique(panel)[:20]:
        assert np.ptp(depth[panel == p]) < 1e-5
    per_panel = np.array([depth[panel == p][0] for p in np.unique(panel)])
    assert 0.034 < per_panel.std() < 0.046 and abs(per_panel.mean()) < 0.01
    # the same wall seen from elsewhere: same depths; another object: other depths
    o2 = np.array([3.0, -4.0, 1.0])
    d2 = hits - o2
    t2 = np.linalg.norm(d2, axis=1)
    rays2 = np.c_[np.tile(o2, (n, 1)), d2 / t2[:, None]].astype(np.float32)
    off2 = _panel_relief(rays2, t2.astype(np.float32), normals, inst, 0.04, 1.0)
    np.testing.assert_allclose(off2 * np.abs(rays2[:, 3]), depth, atol=1e-5)
    other = _panel_relief(rays, t.astype(np.float32), normals, inst + 1, 0.04, 1.0)
    assert np.corrcoef(other, off)[0, 1] < 0.2


def test_building_line_and_scattered_parked_cars():
    """With a building line the facades of a block side stand within +-jitter of one line (an
    ideal downtown side spreads over metres); scattered parked cars stand askew with glass
    cabins."""
    from graffmatch.datasets.simulator.mesh import GLASS

    def side_spreads(cfg) -> list[float]:
        w = build_world(cfg, 2)
        L, cw = w.landmarks, w.corner_half_width
        fac = (L.attributes["category"] == CATEGORIES["facade"]) & (L.directions[:, 1] < -0.99)
        spreads = []
        for i in range(len(w.street_x) - 1):
            for j in range(len(w.street_y) - 1):
                y0 = w.street_y[j] + cw
                sel = fac & (L.anchors[:, 1] >= y0) & (L.anchors[:, 1] < y0 + 5.0)
                sel &= (L.anchors[:, 0] > w.street_x[i] + cw) & (L.anchors[:, 0] < w.street_x[i + 1] - cw)
                if sel.sum() >= 2:
                    spreads.append(float(np.ptp(L.anchors[sel, 1])))
        return spreads

    base = world_preset("downtown")
    lined = base.model_copy(update={"building_line": True, "building_line_jitter": 0.1})
    ideal, line = side_spreads(base), side_spreads(lined)
    # (a side's window also catches the odd corner building of the cross street)
    assert len(line) >= 5 and np.mean(np.array(line) <= 0.2 + 1e-9) >= 0.8, line
    # measured (seed 2): 14 of 15 lined sides within 0.2 m, mean spread 0.21 m; ideal 0.85 m
    assert np.mean(ideal) > 2.5 * np.mean(line) and np.mean(np.array(ideal) > 0.5) >= 0.4, ideal
    w = build_world(base.model_copy(update={"parked_car_scatter": True}), 2)
    car = w.tri_class == 10
    assert np.any(w.tri_material[car] == GLASS)
    V = w.vertices[w.triangles[car]]
    nrm = np.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    askew = (np.abs(nrm[:, 2]) < 0.1) & (np.abs(nrm[:, :2]).max(axis=1) < 0.9995)
    assert askew.mean() > 0.15  # measured 0.26: |yaw| > 1.8 deg on about a third of the cars
    plain = build_world(base, 2)
    assert not np.any(plain.tri_material[plain.tri_class == 10] == GLASS)
