"""Simulate whole KITTI-layout datasets, the demo's scan pair, and the named benchmark suites."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.datasets.simulator import writer
from graffmatch.datasets.simulator.motion import (
    perturb_poses,
    sweep_poses,
    sweep_twist,
)
from graffmatch.datasets.simulator.movers import place_movers
from graffmatch.datasets.simulator.realism import RealismConfig, get_realism, noisy_labels
from graffmatch.datasets.simulator.sensor import SensorProfile, get_profile, render_scan
from graffmatch.datasets.simulator.trajectory import (
    TrajectoryConfig,
    plan_route,
    poses_on_ground,
)
from graffmatch.datasets.simulator.world import World, WorldConfig, build_world, world_preset
from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet
from graffmatch.geometry.transforms import invert
from graffmatch.lidar.deskew import deskew_in_sequence

#: Bumped whenever the world, sensor or trajectory model changes what a seed produces.
SIMULATOR_VERSION = "1.2"
DEFAULT_N_SCANS = 300


def _scan_rng(seed: int, index: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), 0x5CA9, int(index)])


def realistic_world_config(cfg: WorldConfig, realism: RealismConfig) -> WorldConfig:
    """``cfg`` with the realism preset's world overrides for its style."""
    over = realism.world_overrides(cfg.style)
    if not over:
        return cfg
    return WorldConfig.model_validate({**cfg.model_dump(), **over})


def _sweep_twists(T: NDArray) -> NDArray:
    """(n, 6) constant-velocity motion per sweep at every scan, from its neighbours."""
    n = len(T)
    if n == 1:
        return np.zeros((1, 6))
    out = np.empty((n, 6))
    for i in range(n):
        a, b = max(i - 1, 0), min(i + 1, n - 1)
        out[i] = sweep_twist(T[a], T[b], float(b - a))
    return out


def gt_landmarks_in_scan(
    world: World,
    landmark_of_point: NDArray[np.int32],
    T_world_lidar: NDArray,
    min_points: int = 1,
) -> LandmarkSet:
    """The GT landmarks a scan sampled with >= ``min_points`` points, in the LiDAR frame.

    Adds a ``support`` attribute (points of the scan on the landmark) and keeps ``gt_id``, so
    extracted landmarks can be scored against exactly what the sensor saw.
    """
    lm = np.asarray(landmark_of_point)
    counts = np.bincount(lm[lm >= 0], minlength=len(world.landmarks))
    idx = np.flatnonzero(counts >= max(1, int(min_points)))
    sub = world.landmarks[idx]
    sub.attributes["support"] = counts[idx].astype(np.int64)
    view = sub.transform(invert(T_world_lidar))
    view.sensor_pose = np.eye(4)  # what the lidar saw, from where it stood
    return view


def _clear_scans(out: Path) -> None:
    """Remove scan files of an earlier run so no stale NNNNNN files survive (ours only)."""
    pat = re.compile(r"^\d{6}\.(bin|label)$")
    for sub in ("velodyne", "labels"):
        d = out / sub
        if d.is_dir():
            for p in d.iterdir():
                if pat.match(p.name):
                    p.unlink(missing_ok=True)


def simulate_dataset(
    out_dir: str | Path,
    style: str = "downtown",
    seed: int = 0,
    n_scans: int | None = None,
    sensor: str | SensorProfile = "hdl64",
    world_config: WorldConfig | None = None,
    trajectory_config: TrajectoryConfig | None = None,
    overwrite: bool = True,
    reuse: bool = False,
    progress: Callable[[int, int], None] | None = None,
    profile: str | SensorProfile | None = None,
    realism: str | RealismConfig | None = None,
) -> Path:
    """Simulate a drive and write it as a KITTI-layout folder; returns ``out_dir``.

    Same (style or world_config, seed, n_scans, sensor, trajectory_config, realism) ->
    identical bytes of every scan, label, pose and calib file. ``profile`` is an alias of
    ``sensor``. ``realism``: ``ideal`` (default: clean world, static, exact labels and poses),
    ``realistic`` or ``kitti-gt`` (see ``realism.py``). With ``reuse``, a folder already
    holding a complete simulation of the same request is kept as is.
    """
    out = Path(out_dir)
    n = DEFAULT_N_SCANS if n_scans is None else int(n_scans)
    if n < 1:
        raise InvalidInputError("n_scans must be >= 1")
    cfg = world_config if world_config is not None else world_preset(style)
    real = get_realism(realism)
    cfg = realistic_world_config(cfg, real)
    prof = get_profile(profile if profile is not None else sensor)
    tcfg = trajectory_config or TrajectoryConfig(mount_height=prof.mount_height)
    if real.trajectory:
        tcfg = TrajectoryConfig.model_validate({**tcfg.model_dump(), **real.trajectory})
    request = {
        "generator": "graffmatch.datasets.simulator",
        "version": SIMULATOR_VERSION,
        "style": cfg.style,
        "seed": int(seed),
        "n_scans": n,
        "world_config": cfg.model_dump(mode="json"),
        "sensor": prof.model_dump(mode="json"),
        "trajectory_config": tcfg.model_dump(mode="json"),
    }
    if not real.is_ideal:  # ideal requests keep the exact metadata they always had
        request["realism"] = real.model_dump(mode="json")
    if reuse and _is_complete(out, request):
        return out
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise InvalidInputError(f"{out} is not empty (pass overwrite=True)")
        _clear_scans(out)
    out.mkdir(parents=True, exist_ok=True)
    world = build_world(cfg, seed)
    traj = plan_route(world, n, seed, tcfg)
    movers = None
    if real.moving_cars_per_km > 0 or real.pedestrians_per_km > 0:
        movers = place_movers(
            world, np.random.default_rng([int(seed), 0x3077]), real.moving_cars_per_km,
            real.pedestrians_per_km,
        )  # fmt: skip
    twists = _sweep_twists(traj.T_world_lidar) if real.motion_distortion else None
    poses = traj.T_world_lidar
    if real.gt_pose_noise_m > 0 or real.gt_pose_noise_deg > 0:
        poses = perturb_poses(
            poses, np.random.default_rng([int(seed), 0x9057]), real.gt_pose_noise_m,
            real.gt_pose_noise_deg,
        )  # fmt: skip
    vis_scan, vis_lm, vis_cnt = [], [], []
    for i, T in enumerate(traj.T_world_lidar):
        sweep = None if twists is None else sweep_poses(T, twists[i], prof.n_columns)
        dyn = None if movers is None else movers.mesh(world, float(traj.times[i]), T[:2, 3])
        pts, labels, lm = render_scan(
            world, T, prof, _scan_rng(seed, i), return_landmarks=True, sweep=sweep, dynamic=dyn
        )
        labels = noisy_labels(labels, real, np.random.default_rng([int(seed), 0x1AB, i]))
        if real.deskew:
            pts = deskew_in_sequence(pts, poses, i)
        writer.write_scan(out, i, pts, labels)
        c = np.bincount(lm[lm >= 0], minlength=len(world.landmarks))
        nz = np.flatnonzero(c)
        vis_scan.append(np.full(len(nz), i))
        vis_lm.append(nz)
        vis_cnt.append(c[nz])
        if progress is not None:
            progress(i + 1, n)
    writer.write_poses(out / "poses.txt", poses)
    writer.write_calib(out / "calib.txt")
    writer.write_times(out / "times.txt", traj.times)
    world.landmarks.save(out / "landmarks_gt.npz")
    writer.write_visibility(
        out / "landmarks_visible.npz",
        np.concatenate(vis_scan),
        np.concatenate(vis_lm),
        np.concatenate(vis_cnt),
    )
    writer.write_meta(
        out / "sim_meta.json",
        {
            **request,
            "world": world.summary(),
            "label_encoding": "uint32 (instance << 16) | SemanticKITTI class",
            "poses": "camera-0: P = Tr @ T_world_lidar @ inv(Tr); T_world_lidar = inv(Tr) @ P @ Tr",
            "landmarks_gt": "world frame; attributes gt_id, category, class_id, instance, extent, "
            "radius (poles), box (planes); landmarks_visible.npz maps scans to GT ids",
        },
    )
    return out


def _is_complete(out: Path, request: dict) -> bool:
    """True when ``out`` holds every file of a finished simulation of exactly ``request``."""
    meta_path = out / "sim_meta.json"
    if not meta_path.is_file():
        return False
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, ValueError):
        return False
    # compare through JSON so tuples and lists agree
    if any(json.loads(json.dumps(v)) != meta.get(k) for k, v in request.items()):
        return False
    n = int(request["n_scans"])
    return all(
        (out / sub / f"{n - 1:06d}.{ext}").is_file()
        for sub, ext in (("velodyne", "bin"), ("labels", "label"))
    )


def load_ground_truth(seq_dir: str | Path) -> LandmarkSet:
    """World-frame GT landmarks written by :func:`simulate_dataset`."""
    return LandmarkSet.load(Path(seq_dir) / "landmarks_gt.npz")


def scan_ground_truth(
    seq_dir: str | Path, index: int, T_world_lidar: NDArray, min_points: int = 1
) -> LandmarkSet:
    """GT landmarks seen by scan ``index`` (>= min_points points) in that scan's LiDAR frame."""
    gt = load_ground_truth(seq_dir)
    vis = writer.read_visibility(seq_dir)
    sel = (vis["scan"] == int(index)) & (vis["count"] >= max(1, int(min_points)))
    sub = gt[vis["landmark"][sel]]
    sub.attributes["support"] = vis["count"][sel].astype(np.int64)
    view = sub.transform(invert(T_world_lidar))
    view.sensor_pose = np.eye(4)  # what the lidar saw, from where it stood
    return view


# ---- the demo's scan pair -------------------------------------------------------------------
def simulate_scan_pair(
    style: str = "downtown",
    seed: int = 0,
    yaw_deg: float = 180.0,
    offset_m: float = 14.0,
    sensor: str | SensorProfile = "hdl64",
) -> dict:
    """Two scans of a small street scene, ``offset_m`` apart with ``yaw_deg`` relative heading.

    Scan A drives along a street in its right lane; scan B is further down the same street,
    turned by ``yaw_deg`` and in the lane that matches its heading, at exactly ``offset_m``
    from A. Returns a dict with ``points`` [A, B] ((N, 4) float32), ``labels`` [A, B],
    ``T_world_lidar`` [A, B], ``T_a_b`` (B's frame into A's), ``landmarks_gt`` (world frame),
    ``visible_gt`` [A, B] (GT landmarks each scan sampled, in its LiDAR frame) and ``world``.
    """
    if not 0.0 <= offset_m <= 30.0:
        raise InvalidInputError("offset_m must be within [0, 30] m")
    base = world_preset(style)
    cfg = base.model_copy(
        update={
            "n_blocks_x": min(base.n_blocks_x, 2),
            "n_blocks_y": min(base.n_blocks_y, 2),
            "block_size": (max(base.block_size[0], 45.0), max(base.block_size[1], 50.0)),
            "margin": min(base.margin, 40.0),
        }
    )
    prof = get_profile(sensor)
    world = build_world(cfg, seed)
    ycen = world.street_y[1]
    x_lo, x_hi = (
        world.street_x[1] + world.corner_half_width,
        world.street_x[2] - world.corner_half_width,
    )
    yaw = np.deg2rad(yaw_deg)
    lat_a = -world.lane_offset(0)  # right lane when heading +x
    lat_b = lat_a if np.cos(yaw) >= 0 else -lat_a
    along = float(np.sqrt(max(offset_m**2 - (lat_b - lat_a) ** 2, 0.0)))
    xa = (x_lo + x_hi) / 2 - along / 2
    xy = np.array([[xa, ycen + lat_a], [xa + along, ycen + lat_b]])
    fwd = np.array([[1.0, 0.0], [np.cos(yaw), np.sin(yaw)]])
    T = poses_on_ground(world, xy, fwd, prof.mount_height)
    scans, labels, vis = [], [], []
    for k in range(2):
        p, lab, lm = render_scan(world, T[k], prof, _scan_rng(seed, k), return_landmarks=True)
        scans.append(p)
        labels.append(lab)
        vis.append(gt_landmarks_in_scan(world, lm, T[k], min_points=1))
    return {
        "points": scans,
        "labels": labels,
        "T_world_lidar": [T[0], T[1]],
        "T_a_b": invert(T[0]) @ T[1],
        "landmarks_gt": world.landmarks,
        "visible_gt": vis,
        "world": world,
        "sensor": prof,
    }


# ---- named benchmark suites ---------------------------------------------------------------
class SuiteSpec(BaseModel):
    """A named, seeded simulated dataset: everything needed to reproduce it exactly."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(description="suite name, e.g. sim-downtown")
    style: str = Field(description="world preset")
    seed: int = Field(description="seed of world, route and sensor noise")
    n_scans: int = Field(gt=0, description="scans, ~1 m apart")
    sensor: str = Field("hdl64", description="sensor profile name")
    description: str = Field("", description="what makes this suite different")
    world_overrides: dict[str, Any] = Field(
        default_factory=dict,
        description="WorldConfig fields changed from the style's preset (block variety, trees)",
    )
    realism: str = Field(
        "realistic", description="realism preset (simulator/realism.py); 'ideal' = clean worlds"
    )

    def world_config(self) -> WorldConfig:
        """The style's preset with this suite's overrides, validated."""
        base = world_preset(self.style).model_dump()
        return WorldConfig.model_validate({**base, **self.world_overrides})


SUITES: dict[str, SuiteSpec] = {
    s.name: s
    for s in (
        SuiteSpec(
            name="sim-downtown",
            style="downtown",
            seed=1,
            n_scans=400,
            sensor="hdl64",
            description="dense facades, few poles, HDL-64E; plane-rich; blocks vary from "
            "closed street walls to gappy ones, some are plazas",
            world_overrides={"frontage_spread": 0.35, "open_block_prob": 0.15},
        ),
        SuiteSpec(
            name="sim-suburban",
            style="suburban",
            seed=1,
            n_scans=600,
            sensor="os1-64",
            description="houses set back, street trees and lights, fences, OS1-64; pole-rich; "
            "blocks vary in density, some are parks",
            world_overrides={"frontage_spread": 0.35, "open_block_prob": 0.15},
        ),
        SuiteSpec(
            name="sim-openroad",
            style="open-road",
            seed=1,
            n_scans=400,
            sensor="hdl64",
            description="sparse: few buildings and fences; a country road lined with trees "
            "(rows with gaps), utility poles and signs, HDL-64E; line-dominated",
            world_overrides={
                "tree_spacing": 7.0,
                "tree_prob": 0.85,
                "tree_prob_spread": 0.35,
                "yard_tree_rate": 4.0,
                "sign_rate": 4.0,
            },
        ),
    )
}


def simulate_suite(name: str, out_root: str | Path, **kwargs) -> Path:
    """Simulate the named suite into ``out_root/<name>``."""
    if name not in SUITES:
        raise InvalidInputError(f"unknown simulated suite {name!r}; choose one of {list(SUITES)}")
    s = SUITES[name]
    kwargs.setdefault("n_scans", s.n_scans)
    return simulate_dataset(
        Path(out_root) / name,
        style=s.style,
        seed=s.seed,
        sensor=s.sensor,
        world_config=s.world_config(),
        **{"realism": s.realism, **kwargs},
    )
