"""Vegetation: trees (a GT trunk pole under a canopy) and bushes."""

from __future__ import annotations

import numpy as np

from graffmatch.datasets.simulator.mesh import (
    CURB_HEIGHT,
    FOLIAGE,
    OPAQUE,
    TRUNK,
    VEGETATION,
    _box,
    _unit_sphere,
)


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
        material = FOLIAGE if self.cfg.leafy_vegetation else OPAQUE
        self.mb.add(V * jitter[:, None] * np.asarray(radii) + centre, F, cls, inst, -1, material)

    def _hedges(self, lot, footprints) -> None:
        """Hedges along the lot edges, behind the sidewalk, wherever no footprint is in the way:
        they hide much of what stands behind them."""
        rng = self.detail_rng
        x0, x1, y0, y1 = lot
        for side in ("-y", "+y", "-x", "+x"):
            along_x = side in ("-y", "+y")
            s0, s1 = (x0, x1) if along_x else (y0, y1)
            pos = s0 + rng.uniform(0.5, 4.0)
            while pos < s1 - 3.0:
                length = min(rng.uniform(3.0, 15.0), s1 - pos)
                inset, depth = rng.uniform(0.3, 1.0), rng.uniform(0.6, 1.1)
                if rng.random() < self.cfg.hedge_prob:
                    fp = self._footprint(lot, side, pos, pos + length, inset, inset + depth)
                    free = not any(
                        fp[0] < g[1] and g[0] < fp[1] and fp[2] < g[3] and g[2] < fp[3]
                        for g in footprints
                    )
                    if free:
                        zg = float(self.h((fp[0] + fp[1]) / 2, (fp[2] + fp[3]) / 2)) + CURB_HEIGHT
                        lo = np.array([fp[0], fp[2], zg])
                        hi = np.array([fp[1], fp[3], zg + rng.uniform(0.9, 2.0)])
                        V, F = _box(lo, hi)
                        self.mb.add(V, F, VEGETATION, self.mb.new_instance(), -1, FOLIAGE)
                pos += length + rng.uniform(0.5, 6.0)
