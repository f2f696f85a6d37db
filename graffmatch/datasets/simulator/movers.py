"""Moving objects: cars driving in the lanes and pedestrians walking on the sidewalks.

They are not part of the static world mesh: at each scan time they are placed along their
street and cast against in a small scene of their own (``sensor.render_scan(dynamic=...)``).
SemanticKITTI labels them moving-car (252) and moving-person (254).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graffmatch.datasets.simulator.mesh import CURB_HEIGHT, _boxes
from graffmatch.datasets.simulator.world import World

MOVING_CAR = 252
MOVING_PERSON = 254
#: Instance ids of movers start here (static objects stay far below).
FIRST_MOVER_INSTANCE = 60000


@dataclass(frozen=True)
class Movers:
    """Straight-line movers along streets: axis (0: along y, 1: along x), street centre,
    lateral offset, start, speed (signed), extent along the street, size and class."""

    axis: NDArray[np.int64]
    centre: NDArray[np.float64]
    lateral: NDArray[np.float64]
    s0: NDArray[np.float64]
    speed: NDArray[np.float64]
    lo: NDArray[np.float64]
    hi: NDArray[np.float64]
    size: NDArray[np.float64]  # (n, 3) length, width, height
    cls: NDArray[np.int64]
    raised: NDArray[np.float64]  # 0 on the road, CURB_HEIGHT on sidewalks

    def __len__(self) -> int:
        return len(self.s0)

    def positions(self, t: float) -> NDArray[np.float64]:
        """(n, 3) base centre of every mover at time ``t`` [s] (bouncing between street ends)."""
        span = self.hi - self.lo
        u = np.mod(self.s0 - self.lo + self.speed * t, 2 * span)
        s = self.lo + np.where(u < span, u, 2 * span - u)
        xy = np.where(
            self.axis[:, None] == 0,
            np.stack([self.centre + self.lateral, s], 1),
            np.stack([s, self.centre + self.lateral], 1),
        )
        return xy

    def mesh(self, world: World, t: float, near: NDArray, radius: float = 80.0, keep_out: float = 4.0):
        """Boxes of the movers within ``radius`` of ``near`` (xy) but not within ``keep_out``
        (the sensor's own car); returns (V, F, tri_class, tri_instance) or None."""
        xy = self.positions(t)
        d = np.linalg.norm(xy - np.asarray(near, float)[:2], axis=1)
        sel = np.flatnonzero((d < radius) & (d > keep_out))
        if len(sel) == 0:
            return None
        xy = xy[sel]
        L, W, H = self.size[sel].T
        along_x = self.axis[sel] == 1
        hx = np.where(along_x, L, W) / 2
        hy = np.where(along_x, W, L) / 2
        z = world.ground_height(xy[:, 0], xy[:, 1]) + self.raised[sel]
        cls = self.cls[sel]
        car = cls == MOVING_CAR
        # cars: body 0.25-1.0 m and a narrower cabin up to H; people: one box
        zb = np.where(car, z + 0.25, z)
        zt = np.where(car, z + 1.0, z + H)
        lo = [np.stack([xy[:, 0] - hx, xy[:, 1] - hy, zb], 1)]
        hi = [np.stack([xy[:, 0] + hx, xy[:, 1] + hy, zt], 1)]
        owner = [np.arange(len(sel))]
        c = np.flatnonzero(car)
        if len(c):
            f = np.where(along_x[c], 0.55, 0.92)[:, None] * np.array([1.0, 0.0]) + np.where(
                along_x[c], 0.92, 0.55
            )[:, None] * np.array([0.0, 1.0])
            cx, cy = hx[c] * f[:, 0], hy[c] * f[:, 1]
            lo.append(np.stack([xy[c, 0] - cx, xy[c, 1] - cy, z[c] + 1.0], 1))
            hi.append(np.stack([xy[c, 0] + cx, xy[c, 1] + cy, z[c] + H[c]], 1))
            owner.append(c)
        own = np.concatenate(owner)
        V, F = _boxes(np.concatenate(lo), np.concatenate(hi))
        tri_cls = np.repeat(cls[own], 12).astype(np.uint16)
        tri_inst = np.repeat(FIRST_MOVER_INSTANCE + sel[own], 12).astype(np.uint32)
        return V.astype(np.float32), F.astype(np.uint32), tri_cls, tri_inst


def place_movers(
    world: World, rng: np.random.Generator, cars_per_km: float, people_per_km: float
) -> Movers:
    """Cars in every lane (both directions) and people on both sidewalks of every street."""
    cfg = world.config
    hw, cw = world.road_half_width, world.corner_half_width
    rows: list[tuple] = []
    for axis, centres, cross in ((0, world.street_x, world.street_y), (1, world.street_y, world.street_x)):
        lo, hi = float(cross[0]), float(cross[-1])
        length = hi - lo
        for c in centres:
            for direction in (-1.0, 1.0):
                for lane in range(cfg.lanes_per_direction):
                    lat = -direction * world.lane_offset(lane)  # right-hand traffic
                    for _ in range(rng.poisson(cars_per_km * length / 1000.0)):
                        size = (rng.uniform(3.9, 4.9), rng.uniform(1.7, 1.9), rng.uniform(1.4, 1.6))
                        rows.append((axis, c, lat, rng.uniform(lo, hi), direction *
                                     rng.uniform(6.0, 12.0), lo, hi, size, MOVING_CAR, 0.0))  # fmt: skip
                if cfg.sidewalk_width >= 1.0:
                    for _ in range(rng.poisson(people_per_km * length / 1000.0)):
                        lat = direction * rng.uniform(hw + 0.4, cw - 0.4)
                        size = (0.5, 0.45, rng.uniform(1.55, 1.9))
                        rows.append((axis, c, lat, rng.uniform(lo, hi), rng.choice([-1.0, 1.0]) *
                                     rng.uniform(0.8, 1.6), lo, hi, size, MOVING_PERSON,
                                     CURB_HEIGHT))  # fmt: skip
    if not rows:
        z = np.zeros(0)
        return Movers(z.astype(np.int64), z, z, z, z, z, z, np.zeros((0, 3)), z.astype(np.int64), z)
    cols = list(zip(*rows, strict=True))
    return Movers(
        axis=np.array(cols[0], np.int64), centre=np.array(cols[1]), lateral=np.array(cols[2]),
        s0=np.array(cols[3]), speed=np.array(cols[4]), lo=np.array(cols[5]), hi=np.array(cols[6]),
        size=np.array(cols[7], float), cls=np.array(cols[8], np.int64), raised=np.array(cols[9]),
    )  # fmt: skip
