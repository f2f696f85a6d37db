"""Driving routes through the street grid, with the revisits that loop closures need.

A route is a walk on the grid's intersections. At each intersection the planner prefers
streets it has driven least, and especially streets it has driven only in the *other* direction,
so the same street comes back in the same and in the opposite direction. Lanes are drawn per
street (right-hand traffic), and occasional mid-block U-turns add opposite-direction passes a
few metres apart. The lane polyline is densified, Gaussian-smoothed (rounded turns) and
resampled at ``step_m`` (or, with ``max_lateral_accel``, every ``scan_period_s`` of a drive
that slows down in curves); the sensor is placed ``mount_height`` above the road and tilted with
the local ground slope.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy.ndimage import gaussian_filter1d
from scipy.spatial import cKDTree

from graffmatch.datasets.simulator.world import World
from graffmatch.errors import InvalidInputError


class TrajectoryConfig(BaseModel):
    """How the car drives: spacing of scans, lane changes, U-turns and turn smoothness."""

    model_config = ConfigDict(extra="forbid")

    step_m: float = Field(1.0, gt=0.05, le=10.0, description="distance between scans [m]")
    scan_period_s: float = Field(0.1, gt=0.0, description="time between scans written to times.txt")
    mount_height: float = Field(1.73, gt=0.0, description="sensor height above the road [m]")
    uturn_prob: float = Field(0.2, ge=0.0, le=1.0, description="P(mid-block U-turn) per street")
    lane_change_prob: float = Field(0.3, ge=0.0, le=1.0, description="P(new lane) going straight")
    smoothing_m: float = Field(2.5, gt=0.0, description="Gaussian sigma of the path smoothing [m]")
    revisit_bias: float = Field(
        1.0, ge=0.0, description="preference for streets already driven (0 = uniform random walk)"
    )
    candidates: int = Field(
        8,
        ge=1,
        le=64,
        description="random routes drawn; the one with the most varied revisits wins",
    )
    inner_only: bool = Field(
        True, description="drive only on streets with blocks on both sides (when the grid allows)"
    )
    max_lateral_accel: float | None = Field(
        None,
        gt=0,
        description="slow down in curves so that v^2 * curvature stays below this [m/s^2]; "
        "scans are then taken every scan_period_s, not every step_m (None: a constant "
        "step_m per scan, as the ideal simulator does, even through U-turns)",
    )
    min_speed: float = Field(1.5, gt=0, description="lowest speed in the tightest turns [m/s]")


@dataclass(frozen=True)
class Trajectory:
    """Sensor poses T_world_lidar (n, 4, 4), their times [s] and the lane driven at each."""

    T_world_lidar: NDArray[np.float64]
    times: NDArray[np.float64]
    lane: NDArray[np.int64]
    arc_length: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.T_world_lidar)

    @property
    def positions(self) -> NDArray[np.float64]:
        return self.T_world_lidar[:, :3, 3]


_DIRS = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])  # E N W S


def _node_route(world: World, length_m: float, cfg: TrajectoryConfig, rng: np.random.Generator):
    """Sequence of (node_from, node_to, lane, uturn_at) street traversals covering length_m."""
    nx, ny = len(world.street_x), len(world.street_y)
    lo_x, hi_x = (1, nx - 2) if cfg.inner_only and nx >= 4 else (0, nx - 1)
    lo_y, hi_y = (1, ny - 2) if cfg.inner_only and ny >= 4 else (0, ny - 1)
    if hi_x - lo_x < 1 and hi_y - lo_y < 1:
        raise InvalidInputError("the street grid is too small to drive on")

    def inside(n):
        return lo_x <= n[0] <= hi_x and lo_y <= n[1] <= hi_y

    def pos(n):
        return np.array([world.street_x[n[0]], world.street_y[n[1]]])

    node = (int(rng.integers(lo_x, hi_x + 1)), int(rng.integers(lo_y, hi_y + 1)))
    heading = None
    visits: dict[tuple, int] = {}
    legs = []
    total = 0.0
    lanes = world.config.lanes_per_direction
    lane = int(rng.integers(lanes))
    while total < length_m:
        options = []
        for k in range(4):
            if heading is not None and k == (heading + 2) % 4:
                continue  # no U-turns at intersections
            nxt = (node[0] + _DIRS[k][0], node[1] + _DIRS[k][1])
            if inside(nxt):
                options.append((k, nxt))
        if not options:  # dead end: turn around
            k = (heading + 2) % 4
            options = [(k, (node[0] + _DIRS[k][0], node[1] + _DIRS[k][1]))]
        # revisits make loop closures: favour streets already driven, most of all those
        # driven only the other way; tire of streets driven often in this direction
        w = np.array(
            [
                (
                    1.0
                    + cfg.revisit_bias
                    * (
                        3.0 * bool(visits.get((nxt, node), 0))
                        + 1.5 * bool(visits.get((node, nxt), 0))
                    )
                )
                / (1.0 + 0.5 * visits.get((node, nxt), 0))
                for _, nxt in options
            ]
        )
        k, nxt = options[int(rng.choice(len(options), p=w / w.sum()))]
        if heading is None or k != heading or rng.random() < cfg.lane_change_prob:
            lane = int(rng.integers(lanes))
        uturn = rng.random() < cfg.uturn_prob
        a, b = pos(node), pos(nxt)
        seg = float(np.linalg.norm(b - a))
        if uturn:
            frac = float(rng.uniform(0.35, 0.65))
            new_lane = int(rng.integers(lanes))
            legs.append((a, b, lane, frac, new_lane))
            visits[(node, nxt)] = visits.get((node, nxt), 0) + 1
            visits[(nxt, node)] = visits.get((nxt, node), 0) + 1
            total += 2 * frac * seg
            heading = (k + 2) % 4
            lane = new_lane
            continue  # back at `node`, facing the other way
        legs.append((a, b, lane, None, None))
        visits[(node, nxt)] = visits.get((node, nxt), 0) + 1
        total += seg
        node, heading = nxt, k
    return legs


def plan_route(
    world: World,
    n_scans: int,
    seed: int = 0,
    config: TrajectoryConfig | None = None,
) -> Trajectory:
    """A route of ``n_scans`` poses spaced ``step_m`` apart, deterministic from ``seed``.

    ``config.candidates`` random routes are drawn and the one whose revisits best cover the
    three rotation bins (< 30 deg, 30-150 deg, > 150 deg) is kept, so that every seed gives
    same-direction, crossing and opposite-direction loop closures.
    """
    cfg = config or TrajectoryConfig()
    if n_scans < 1:
        raise InvalidInputError("n_scans must be >= 1")
    best, best_score = None, -1.0
    for c in range(cfg.candidates):
        traj = _plan_one(world, n_scans, np.random.default_rng([int(seed), 0x7EA1, c]), cfg)
        if n_scans < 30 or cfg.candidates == 1:
            return traj
        _, _, dyaw = revisit_pairs(traj.T_world_lidar, stride_m=2.0)
        bins = np.histogram(dyaw, bins=[0.0, 30.0, 150.0, 180.1])[0]
        score = float(np.sum(np.log1p(bins)))
        if score > best_score:
            best, best_score = traj, score
    return best  # type: ignore[return-value]


def _plan_one(
    world: World, n_scans: int, rng: np.random.Generator, cfg: TrajectoryConfig
) -> Trajectory:
    length = 1.3 * n_scans * cfg.step_m + 150.0
    legs = _node_route(world, length, cfg, rng)
    inset = world.corner_half_width
    pts: list[NDArray] = []
    lane_of: list[int] = []
    for a, b, lane, frac, new_lane in legs:
        d = (b - a) / np.linalg.norm(b - a)
        right = np.array([d[1], -d[0]])
        o = world.lane_offset(lane)
        start = a + d * inset + right * o
        if frac is None:
            pts += [start, b - d * inset + right * o]
            lane_of += [lane, lane]
        else:
            mid = a + (b - a) * frac
            o2 = world.lane_offset(new_lane)
            # a tight three-point-turn-like manoeuvre back toward a
            pts += [start, mid - d * 4.0 + right * o, mid + right * o * 0.3, mid - right * o2 * 0.3,
                    mid - d * 4.0 - right * o2, a + d * inset - right * o2]  # fmt: skip
            lane_of += [lane, lane, lane, new_lane, new_lane, new_lane]
    P = np.array(pts)
    # densify at 0.1 m, smooth, resample at step_m
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    dense_s = np.arange(0.0, s[-1], 0.1)
    D = np.stack([np.interp(dense_s, s, P[:, 0]), np.interp(dense_s, s, P[:, 1])], 1)
    lane_dense = np.asarray(lane_of)[
        np.clip(np.searchsorted(s, dense_s, side="right") - 1, 0, len(P) - 1)
    ]
    D = gaussian_filter1d(D, cfg.smoothing_m / 0.1, axis=0, mode="nearest")
    ds = np.linalg.norm(np.diff(D, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(ds)])
    start = 30.0  # skip the smoothing transient at the start
    if cfg.max_lateral_accel is None:
        q = start + np.arange(n_scans) * cfg.step_m
    else:
        q = start + _timed_arc(D, arc, start, n_scans, cfg)
    if q[-1] > arc[-1]:
        raise InvalidInputError("route too short for the requested number of scans")
    xy = np.stack([np.interp(q, arc, D[:, 0]), np.interp(q, arc, D[:, 1])], 1)
    ahead = np.stack([np.interp(q + 0.5, arc, D[:, 0]), np.interp(q + 0.5, arc, D[:, 1])], 1)
    behind = np.stack([np.interp(q - 0.5, arc, D[:, 0]), np.interp(q - 0.5, arc, D[:, 1])], 1)
    fwd2 = ahead - behind
    fwd2 /= np.linalg.norm(fwd2, axis=1, keepdims=True)
    lane_q = lane_dense[np.clip(np.searchsorted(arc, q), 0, len(lane_dense) - 1)]
    T = poses_on_ground(world, xy, fwd2, cfg.mount_height)
    times = np.arange(n_scans) * cfg.scan_period_s
    return Trajectory(T, times, lane_q.astype(np.int64), q - start)


def _timed_arc(D: NDArray, arc: NDArray, start: float, n_scans: int, cfg: TrajectoryConfig):
    """Arc lengths (from ``start``) of scans every ``scan_period_s`` when the car drives at
    ``step_m / scan_period_s`` on straights and slows so that v^2 kappa <= max_lateral_accel."""
    heading = np.unwrap(np.arctan2(np.gradient(D[:, 1]), np.gradient(D[:, 0])))
    kappa = np.abs(np.gradient(heading, arc))
    # look ahead and behind one second of driving: brake before a curve, not in it
    kappa = gaussian_filter1d(kappa, 5.0 / 0.1, mode="nearest")
    v_max = cfg.step_m / cfg.scan_period_s
    v = np.clip(np.sqrt(cfg.max_lateral_accel / np.maximum(kappa, 1e-9)), cfg.min_speed, v_max)
    t = np.concatenate([[0.0], np.cumsum(np.diff(arc) / (0.5 * (v[1:] + v[:-1])))])
    t_start = np.interp(start, arc, t)
    q = np.interp(t_start + np.arange(n_scans) * cfg.scan_period_s, t, arc)
    return q - start


def poses_on_ground(world: World, xy: NDArray, forward_xy: NDArray, mount_height: float) -> NDArray:
    """(n, 4, 4) poses at xy, heading along forward_xy, z-axis along the local road normal."""
    xy = np.atleast_2d(np.asarray(xy, float))
    f2 = np.atleast_2d(np.asarray(forward_xy, float))
    g = world.ground_gradient(xy[:, 0], xy[:, 1])
    n = np.concatenate([-g, np.ones((len(xy), 1))], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    f = np.concatenate([f2, (g * f2).sum(1, keepdims=True)], 1)
    y = np.cross(n, f)
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    x = np.cross(y, n)
    T = np.tile(np.eye(4), (len(xy), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = x, y, n
    z = world.ground_height(xy[:, 0], xy[:, 1])
    T[:, :3, 3] = np.concatenate([xy, z[:, None]], 1) + n * mount_height
    return T


def revisit_pairs(
    T_world_lidar: NDArray,
    stride_m: float = 2.0,
    min_path_m: float = 50.0,
    max_dist_m: float = 16.0,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """The paper's revisits: places every ``stride_m``; pairs > min_path apart along the path and
    < max_dist apart in space.

    Returns (place scan indices (p,), pairs (k, 2) of scan indices (earlier, later), yaw
    difference of each pair in degrees [0, 180]).
    """
    T = np.asarray(T_world_lidar, float)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise InvalidInputError("T_world_lidar must be (n, 4, 4)")
    p = T[:, :3, 3]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    marks = np.arange(0.0, arc[-1] + 1e-9, stride_m)
    places = np.unique(np.searchsorted(arc, marks - 1e-9))
    places = places[places < len(T)]
    tree = cKDTree(p[places])
    pr = np.array(sorted(tree.query_pairs(max_dist_m)), dtype=np.int64).reshape(-1, 2)
    pairs = places[pr] if len(pr) else np.zeros((0, 2), np.int64)
    if len(pairs):
        pairs = pairs[np.abs(arc[pairs[:, 1]] - arc[pairs[:, 0]]) > min_path_m]
        pairs = np.sort(pairs, axis=1)
    yaw = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    dyaw = np.abs(np.rad2deg(np.angle(np.exp(1j * (yaw[pairs[:, 1]] - yaw[pairs[:, 0]])))))
    return places, pairs, dyaw
