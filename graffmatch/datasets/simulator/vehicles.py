"""Vehicles: parked cars (body, cabin, wheels)."""

from __future__ import annotations

import numpy as np

from graffmatch.datasets.simulator.mesh import CAR, GLASS, OPAQUE, _box


class VehiclesMixin:
    """Parked cars of the world generator."""

    def _car(self, axis, c, side, s, u, length: float) -> None:
        yaw = 0.0
        if self.cfg.parked_car_scatter:
            # real cars park 0-0.5 m from the curb and a little askew (detail stream: the
            # layout draws stay the same)
            u = u + self.detail_rng.uniform(-0.25, 0.25)
            yaw = float(np.clip(self.detail_rng.normal(0.0, np.radians(2.0)), -0.07, 0.07))
        x, y = self._xy(axis, c, side, s, u)
        zg = float(self.h(x, y))
        w = self.u((1.7, 1.9))
        hb, hc = self.u((0.9, 1.1)), self.u((1.35, 1.6))
        half = np.array([length / 2, w / 2]) if axis == 1 else np.array([w / 2, length / 2])
        inst = self.mb.new_instance()
        V, F = _box(
            np.array([x - half[0], y - half[1], zg + 0.25]),
            np.array([x + half[0], y + half[1], zg + hb]),
        )
        self._add_car_part(V, F, inst, x, y, yaw)
        cab = half * (np.array([0.55, 0.92]) if axis == 1 else np.array([0.92, 0.55]))
        V, F = _box(
            np.array([x - cab[0], y - cab[1], zg + hb]), np.array([x + cab[0], y + cab[1], zg + hc])
        )
        # a scattered car's cabin is glass: rays drop out or return from the seats behind it
        self._add_car_part(V, F, inst, x, y, yaw, GLASS if self.cfg.parked_car_scatter else OPAQUE)
        # wheels as short boxes so the body does not float
        for sx in (-0.7, 0.7):
            for sy in (-0.9, 0.9):
                off = (
                    np.array([sx * half[0], sy * half[1]])
                    if axis == 1
                    else np.array([sy * half[0], sx * half[1]])
                )
                V, F = _box(np.array([x + off[0] - 0.3, y + off[1] - 0.12, zg]),
                            np.array([x + off[0] + 0.3, y + off[1] + 0.12, zg + 0.6]))  # fmt: skip
                self._add_car_part(V, F, inst, x, y, yaw)

    def _add_car_part(self, V, F, inst, x: float, y: float, yaw: float, material: int = OPAQUE):
        """Add one box of a car turned by ``yaw`` about the car's centre (x, y)."""
        if yaw != 0.0:
            c, s = np.cos(yaw), np.sin(yaw)
            V = V.copy()
            dx, dy = V[:, 0] - x, V[:, 1] - y
            V[:, 0], V[:, 1] = x + c * dx - s * dy, y + s * dx + c * dy
        self.mb.add(V, F, CAR, inst, -1, material)
