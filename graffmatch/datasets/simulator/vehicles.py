"""Vehicles: parked cars (body, cabin, wheels)."""

from __future__ import annotations

import numpy as np

from graffmatch.datasets.simulator.mesh import CAR, _box


class VehiclesMixin:
    """Parked cars of the world generator."""

    def _car(self, axis, c, side, s, u, length: float) -> None:
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
        self.mb.add(V, F, CAR, inst)
        cab = half * (np.array([0.55, 0.92]) if axis == 1 else np.array([0.92, 0.55]))
        V, F = _box(
            np.array([x - cab[0], y - cab[1], zg + hb]), np.array([x + cab[0], y + cab[1], zg + hc])
        )
        self.mb.add(V, F, CAR, inst)
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
                self.mb.add(V, F, CAR, inst)
