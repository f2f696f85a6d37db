"""Vegetation: trees (a GT trunk pole under a canopy) and bushes."""

from __future__ import annotations

import numpy as np

from graffmatch.datasets.simulator.mesh import CURB_HEIGHT, TRUNK, VEGETATION, _unit_sphere


class VegetationMixin:
    """Trees and canopies of the world generator."""

    def _tree(self, xy, trunk_radius: float, yard: bool = False) -> None:
        x, y = xy
        trunk_h = self.u((2.0, 3.5))
        inst = self._pole((x, y), trunk_radius, trunk_h, TRUNK, "trunk")
        zg = float(self.h(x, y)) + CURB_HEIGHT
        rh = self.u((1.8, 3.2)) * (1.3 if yard else 1.0)
        rv = rh * self.u((0.8, 1.3))
        # trunk continues into the canopy so the canopy base sits on it
        self._ellipsoid(np.array([x, y, zg + trunk_h + rv * 0.9]), (rh, rh, rv), VEGETATION, inst)

    def _ellipsoid(self, centre, radii, cls: int, inst: int) -> None:
        V, F = _unit_sphere(1)
        jitter = 1.0 + 0.15 * (self.rng.random(len(V)) - 0.5)
        self.mb.add(V * jitter[:, None] * np.asarray(radii) + centre, F, cls, inst)
