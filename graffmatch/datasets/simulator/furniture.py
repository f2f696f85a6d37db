"""Street furniture: street lights, utility poles, sign posts, street trees and sidewalk clutter.

Every street side between two crossings is walked once; poles, trees, signs, parked cars and
clutter are placed in that order (the order fixes the random draws of a seed).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from graffmatch.datasets.simulator.mesh import (
    CURB_HEIGHT,
    OTHER_OBJECT,
    POLE,
    TRAFFIC_SIGN,
    _box,
    _cylinder,
)


class StreetFurnitureMixin:
    """Pole-like objects and clutter along every street side of the world generator."""

    # -- pole-like objects, cars, clutter along every street side -----------------------------
    def _street_furniture(self) -> None:
        """Walk both sides of every street segment between intersections."""
        for axis in (0, 1):  # 0: streets along y at x = X[i]; 1: streets along x at y = Y[j]
            centres = self.X if axis == 0 else self.Y
            cross = self.Y if axis == 0 else self.X
            for c in centres:
                for k in range(len(cross) - 1):
                    s0, s1 = cross[k] + self.cw, cross[k + 1] - self.cw
                    for side in (-1.0, 1.0):
                        self._segment_side(axis, c, side, s0, s1)

    def _xy(self, axis: int, c: float, side: float, s, u):
        """World (x, y) of along-street coordinate s and lateral distance u from the centre."""
        if axis == 0:
            return c + side * u, s
        return s, c + side * u

    def _segment_side(self, axis: int, c: float, side: float, s0: float, s1: float) -> None:
        cfg, rng = self.cfg, self.rng
        L = s1 - s0
        taken: list[float] = []
        sw = cfg.sidewalk_width
        pole_u = self.hw + (0.6 if sw >= 1.5 else 1.0)

        def free(s: float, gap: float = 2.0) -> bool:
            return all(abs(s - t) > gap for t in taken)

        def slots(spacing: float, lo: float, margin: float) -> NDArray:
            """Regular slots with +-15% jitter: planted rows are regular, but not exactly."""
            base = np.arange(s0 + rng.uniform(lo, max(lo + 0.1, spacing / 2)), s1 - margin, spacing)
            return np.clip(base + rng.uniform(-0.15, 0.15, len(base)) * spacing, s0 + 0.5, s1 - 0.5)

        # street lights (arm toward the road)
        for s in slots(cfg.street_light_spacing, 2.0, 2.0):
            if rng.random() < cfg.street_light_prob:
                taken.append(s)
                self._street_light(axis, c, side, s, pole_u)
        for s in slots(cfg.utility_pole_spacing, 2.0, 2.0):
            if side > 0 and rng.random() < cfg.utility_pole_prob and free(s):
                taken.append(s)
                x, y = self._xy(axis, c, side, s, self.cw + 1.5)
                r, hgt = self.u((0.12, 0.18)), self.u((8.0, 11.0))
                self._pole((x, y), r, hgt, POLE, "utility_pole", arm=(axis, side, 1.2, 0.4))
        p_tree = cfg.tree_prob
        if cfg.tree_prob_spread > 0:
            d = self.block_rng.uniform(-cfg.tree_prob_spread, cfg.tree_prob_spread)
            p_tree = float(np.clip(p_tree + d, 0.0, 1.0))
        for s in slots(cfg.tree_spacing, 1.0, 1.5):
            if rng.random() < p_tree and free(s):
                taken.append(s)
                u = self.hw + (sw * 0.6 if sw >= 2.0 else sw + 2.0)
                self._tree(self._xy(axis, c, side, s, u), trunk_radius=self.u((0.1, 0.25)))
        for _ in range(rng.poisson(cfg.sign_rate * L / 100)):
            s = rng.uniform(s0 + 0.5, s1 - 0.5)
            if free(s, 1.0):
                taken.append(s)
                self._sign(axis, c, side, s, self.hw + 0.35)
        # parked cars
        if cfg.parking_width >= 1.0 and cfg.car_prob > 0:
            s = s0 + rng.uniform(0.5, 3.0)
            while s < s1 - 5.0:
                length = self.u((3.8, 4.9))
                if rng.random() < cfg.car_prob:
                    self._car(
                        axis, c, side, s + length / 2, self.hw - cfg.parking_width / 2 - 0.1, length
                    )
                s += length + self.u((0.6, 2.0))
        # clutter on the sidewalk (or shoulder)
        for _ in range(rng.poisson(cfg.clutter_rate * L / 100)):
            s = rng.uniform(s0 + 0.5, s1 - 0.5)
            if not free(s, 1.0):
                continue
            u = self.hw + (
                rng.uniform(0.3, max(0.4, sw - 0.5)) if sw >= 1.0 else rng.uniform(0.5, 2.5)
            )
            self._clutter(self._xy(axis, c, side, s, u))

    def _pole(
        self, xy, radius: float, height: float, cls: int, category: str, arm=None, inst=None
    ) -> int:
        """A vertical GT pole standing on the raised ground; returns its instance id."""
        x, y = xy
        zg = float(self.h(x, y)) + CURB_HEIGHT
        base = np.array([x, y, zg - 0.2])
        inst = inst or self.mb.new_instance()
        V, F = _cylinder(base, radius, height + 0.2, n_seg=12 if radius > 0.06 else 8)
        k = self.mb.add_pole((x, y, zg), radius, height, cls, category, inst)
        n_side = 2 * (12 if radius > 0.06 else 8)
        lm = np.full(len(F), -1, np.int32)
        lm[:n_side] = k
        self.mb.add(V, F, cls, inst, lm)
        if arm is not None:
            axis, side, length, drop = arm
            d = -side  # toward the street centre
            top = zg + height
            t = 0.06
            if axis == 0:
                lo, hi = (
                    (min(x, x + d * length), y - t, top - drop - t),
                    (max(x, x + d * length), y + t, top - drop + t),
                )
            else:
                lo, hi = (
                    (x - t, min(y, y + d * length), top - drop - t),
                    (x + t, max(y, y + d * length), top - drop + t),
                )
            V, F = _box(np.array(lo), np.array(hi))
            self.mb.add(V, F, cls, inst)
        return inst

    def _street_light(self, axis, c, side, s, u) -> None:
        x, y = self._xy(axis, c, side, s, u)
        r, hgt = self.u((0.08, 0.14)), self.u((6.0, 10.0))
        arm = self.u((0.8, 2.0))
        inst = self._pole((x, y), r, hgt, POLE, "street_light", arm=(axis, side, arm, 0.25))
        # lamp head at the arm tip
        hx, hy = self._xy(axis, c, side, s, u - arm)
        zt = float(self.h(x, y)) + CURB_HEIGHT + hgt - 0.25
        V, F = _box(
            np.array([hx - 0.3, hy - 0.3, zt - 0.25]), np.array([hx + 0.3, hy + 0.3, zt + 0.05])
        )
        self.mb.add(V, F, POLE, inst)

    def _sign(self, axis, c, side, s, u) -> None:
        x, y = self._xy(axis, c, side, s, u)
        r, hgt = self.u((0.03, 0.05)), self.u((2.2, 3.2))
        inst = self._pole((x, y), r, hgt, POLE, "sign_post")
        zt = float(self.h(x, y)) + CURB_HEIGHT + hgt
        w, hh, t = self.u((0.5, 0.9)), self.u((0.5, 0.8)), 0.03
        # the plate faces traffic: its normal is along the street
        if axis == 0:
            lo, hi = (x - w / 2, y + r, zt - hh), (x + w / 2, y + r + t, zt)
        else:
            lo, hi = (x + r, y - w / 2, zt - hh), (x + r + t, y + w / 2, zt)
        V, F = _box(np.array(lo), np.array(hi))
        self.mb.add(V, F, TRAFFIC_SIGN, inst)

    def _clutter(self, xy) -> None:
        x, y = xy
        zg = float(self.h(x, y)) + CURB_HEIGHT
        inst = self.mb.new_instance()
        kind = self.rng.integers(4)
        if kind == 0:  # bin
            a = self.u((0.4, 0.7))
            V, F = _box(
                np.array([x - a / 2, y - a / 2, zg - 0.1]),
                np.array([x + a / 2, y + a / 2, zg + self.u((0.8, 1.2))]),
            )
        elif kind == 1:  # bench / box
            a, b = self.u((0.5, 2.0)), self.u((0.4, 0.8))
            V, F = _box(
                np.array([x - a / 2, y - b / 2, zg - 0.1]),
                np.array([x + a / 2, y + b / 2, zg + self.u((0.4, 0.9))]),
            )
        elif kind == 2:  # bollard: a short pole that is NOT a landmark
            V, F = _cylinder(
                np.array([x, y, zg - 0.1]), self.u((0.07, 0.12)), self.u((0.7, 1.0)), 8
            )
        else:  # hydrant / post box
            V, F = _cylinder(
                np.array([x, y, zg - 0.1]), self.u((0.15, 0.3)), self.u((0.6, 1.3)), 10
            )
        self.mb.add(V, F, OTHER_OBJECT, inst)
