"""MapClosures (Gupta et al. 2024), the real package, as a baseline of the sequence benchmark.

Two named configurations (issue 15): ``mapclosures`` = its defaults (KISS-ICP odometry, 100 m
local maps) and ``mapclosures-gt`` = ground-truth poses + 50 m local maps (the issue's best);
``mapclosures-gt:R`` is a labelled diagnostic. Driven like the package's own pipeline
(``map_closures.pipeline``); bench/mapclosures_pipeline_gt.py is the reference loop it is
checked against (docs/loops.md, Session 12).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from graffmatch.evaluation.sequence_benchmark import Array, MethodRun, Prediction
from graffmatch.geometry.transforms import invert
from graffmatch.loops.retrieval import RetrievalConfig, eligible_count


def run_mapclosures(dataset, retrieval: RetrievalConfig, poses: Array | None = None, map_range_m: float = 100.0,
                    progress: Callable | None = None, name: str = "MapClosures",
                    invert_closure: bool = True, place_gate_m: float = 5.0,
                    odometry_file: Path | None = None, max_range_m: float = 100.0) -> MethodRun:
    """MapClosures (Gupta et al. 2024), the real package, driven like its own pipeline.

    Scans are integrated into local maps (0.5 m voxels) with ``poses``: KISS-ICP odometry when
    None (its defaults, as ``map_closures_pipeline`` does) or the given (ground-truth) poses. As
    in the pipeline (KISS-ICP's ``max_range`` = ``max_range_m``, 100 m): scans are cropped at
    ``max_range_m`` (KISS-ICP's preprocessor), a local map is closed when the scan is more than
    ``map_range_m`` from the map's origin (the pipeline: = max_range; ``mapclosures-gt``: 50 m,
    the issue's setting, everything else left at 100 m) and the next map starts with the points
    within ``max_range_m`` of that scan. The package compares a map only with maps at least 4
    ids older (its C++ skips the 3 most recent), so a drive needs 5 local maps for a first
    closure. Every closure becomes a prediction for each scan of the later map that the closure
    places within ``place_gate_m`` of a scan of the earlier map (the nearest one is the match;
    the benchmark passes our own place gate, ``max_translation_m - place_margin_m``);
    confidence = the closure's inlier count, ties between the scans of one closure broken by
    how near it places them (+ 0.5 * (1 - distance / gate), below the next inlier count; all
    scans of a closure share its inliers, so one scan placed just inside the gate but a little
    beyond it in truth would otherwise drop the whole closure from recall at 100 %
    precision). ``odometry_file``:
    where the KISS-ICP poses are written (KITTI format, for the pose graph and plots).
    """
    from map_closures.config import MapClosuresConfig
    from map_closures.map_closures import MapClosures
    from map_closures.voxel_map import VoxelMap

    mc_cfg = MapClosuresConfig()
    mc = MapClosures(mc_cfg)
    n = len(dataset)
    t0 = time.perf_counter()
    if poses is None:
        from graffmatch.loops.posegraph import kiss_icp_odometry

        P = kiss_icp_odometry(dataset)
        if odometry_file is not None:
            from graffmatch.geometry.pose_files import write_kitti

            Path(odometry_file).parent.mkdir(parents=True, exist_ok=True)
            write_kitti(odometry_file, P)
        P = np.stack([invert(P[0]) @ T for T in P])
    else:
        P = np.stack([invert(poses[0]) @ T for T in poses])
    vmap = VoxelMap(voxel_size=mc_cfg.density_map_resolution, max_distance=max_range_m)
    map_pose = P[0]
    map_of_scan = np.zeros(n, np.int64)
    map_poses: list[Array] = []
    closures = []
    n_candidates = 0
    map_idx = 0
    for i in range(n):
        T_map_scan = invert(map_pose) @ P[i]
        pts = np.asarray(dataset[i].points[:, :3], np.float64)
        vmap.integrate_frame(pts[np.linalg.norm(pts, axis=1) <= max_range_m], T_map_scan)
        map_of_scan[i] = map_idx
        if np.linalg.norm(T_map_scan[:3, 3]) > map_range_m or i == n - 1:
            for c in mc.get_closures(map_idx, vmap.point_cloud()):
                n_candidates += 1
                if c.number_of_inliers > mc_cfg.inliers_threshold:
                    closures.append((int(c.source_id), int(c.target_id), np.asarray(c.pose, float), int(c.number_of_inliers)))
            map_poses.append(map_pose.copy())
            vmap.remove_far_away_points(T_map_scan[:3, 3])
            keep = vmap.point_cloud()
            vmap.clear()
            vmap.integrate_frame(keep, invert(P[i]) @ map_pose)
            map_pose = P[i].copy()
            map_idx += 1
        if progress:
            progress(name, i + 1, n)
    total = time.perf_counter() - t0
    best: dict[int, Prediction] = {}
    for a, b, T_ab, inl in closures:
        # closure.pose maps source-map (a) coordinates into the target map (b): T_b_a (checked
        # against ground truth on a simulated drive: matches inv(T_a_b) to ~0.5 m, the
        # density-map resolution); we need T_a_b, the pose of map b in map a's frame
        if invert_closure:
            T_ab = invert(T_ab)
        later, earlier = (a, b) if a > b else (b, a)
        T_e_l = T_ab if later == b else invert(T_ab)
        ql = np.flatnonzero(map_of_scan == later)
        ce = np.flatnonzero(map_of_scan == earlier)
        if ql.size == 0 or ce.size == 0:
            continue
        Pe = np.stack([invert(map_poses[earlier]) @ P[j] for j in ce])
        for q in ql:
            m = eligible_count(np.asarray(dataset.timestamps), int(q), retrieval)
            T_l_q = invert(map_poses[later]) @ P[q]
            T_e_q = T_e_l @ T_l_q
            d = np.linalg.norm(Pe[:, :3, 3] - T_e_q[:3, 3], axis=1)
            d[ce >= m] = np.inf
            if not np.isfinite(d).any():
                continue
            k = int(np.argmin(d))
            if d[k] > place_gate_m:  # the closure says q is not near any scan of that map
                continue
            conf = float(inl) + 0.5 * (1.0 - float(d[k]) / place_gate_m)
            pred = Prediction(int(q), int(ce[k]), conf, invert(Pe[k]) @ T_e_q)
            if int(q) not in best or best[int(q)].confidence < pred.confidence:
                best[int(q)] = pred
    pairs = max(map_idx - 3, 0) * max(map_idx - 4, 0) // 2  # (ref, query) with ref <= query - 4
    return MethodRun(name, list(best.values()), total / max(n, 1), None,
                     note=f"{map_idx} local maps of {map_range_m:g} m, "
                     f"{'KISS-ICP odometry (defaults)' if poses is None else 'ground-truth poses'}, "
                     f"{len(closures)} map closures (of {n_candidates} candidates, > "
                     f"{mc_cfg.inliers_threshold} inliers; {pairs} map pairs the package compares, "
                     f"a map with maps >= 4 older); time includes map building")


def map_range(method: str) -> float:
    """``mapclosures-gt`` -> 50 m (the issue's setting); ``mapclosures-gt:R`` -> R m."""
    from graffmatch.errors import InvalidInputError

    if method == "mapclosures-gt":
        return 50.0
    try:
        r = float(method.split(":", 1)[1])
    except ValueError:
        r = float("nan")
    if not np.isfinite(r) or r <= 0:
        raise InvalidInputError(f"method {method!r}: R in mapclosures-gt:R must be a positive number of metres")
    return r


def run_mapclosures_gt(dataset, retrieval: RetrievalConfig, progress: Callable | None = None,
                       map_range_m: float = 50.0, place_gate_m: float = 5.0) -> MethodRun:
    """MapClosures' best configuration on our data: ground-truth poses and 50 m local maps (the
    issue's setting; another ``map_range_m`` is a diagnostic, named so in the row)."""
    name = "MapClosures (GT poses, 50 m maps)" if map_range_m == 50.0 else \
        f"MapClosures (GT poses, {map_range_m:g} m maps; diagnostic, not the issue's setting)"
    return run_mapclosures(dataset, retrieval, np.asarray(dataset.poses), map_range_m, progress, name=name,
                           place_gate_m=place_gate_m)
