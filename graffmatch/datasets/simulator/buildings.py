"""Blocks: buildings along the lot sides, walls and fences in the gaps, yard trees and bushes."""

from __future__ import annotations

import numpy as np

from graffmatch.datasets.simulator.mesh import (
    _BOX_FACE,
    BUILDING,
    CURB_HEIGHT,
    FENCE,
    VEGETATION,
    _box,
)


class BuildingsMixin:
    """Lots of the world generator: each block's four sides, built up or left open."""

    # -- blocks: buildings, walls, fences, yard trees, bushes --------------------------------
    def _block(self, i: int, j: int) -> None:
        lot = (
            self.X[i] + self.cw,
            self.X[i + 1] - self.cw,
            self.Y[j] + self.cw,
            self.Y[j + 1] - self.cw,
        )
        footprints: list[tuple[float, float, float, float]] = []
        cfg = self.cfg
        frontage, trees = cfg.frontage, cfg.yard_tree_rate
        if cfg.open_block_prob > 0 and self.block_rng.random() < cfg.open_block_prob:
            frontage, trees = 0.0, max(2.0 * trees, 3.0)  # a park: trees instead of buildings
        elif cfg.frontage_spread > 0:
            d = self.block_rng.uniform(-cfg.frontage_spread, cfg.frontage_spread)
            frontage = float(np.clip(frontage + d, 0.0, 1.0))
        # south/north sides first, then west/east which avoid existing footprints
        for side in ("-y", "+y", "-x", "+x"):
            self._block_side(lot, side, footprints, frontage)
        perim = 2 * ((lot[1] - lot[0]) + (lot[3] - lot[2]))
        for _ in range(self.rng.poisson(trees * perim / 100)):
            p = self._free_spot(lot, footprints, 1.5)
            if p is not None:
                self._tree(p, trunk_radius=self.u((0.12, 0.3)), yard=True)
        if cfg.hedge_prob > 0:
            self._hedges(lot, footprints)
        for _ in range(self.rng.poisson(cfg.bush_rate * perim / 100)):
            p = self._free_spot(lot, footprints, 1.0)
            if p is not None:
                r = self.u((0.5, 1.3))
                self._ellipsoid(np.array([p[0], p[1], self.h(p[0], p[1]) + CURB_HEIGHT + 0.4 * r]),
                                (r, r, 0.7 * r), VEGETATION, self.mb.new_instance())  # fmt: skip

    def _free_spot(self, lot, footprints, clearance: float):
        for _ in range(6):
            x = self.rng.uniform(lot[0] + 1.0, lot[1] - 1.0)
            y = self.rng.uniform(lot[2] + 1.0, lot[3] - 1.0)
            if not any(f[0] - clearance < x < f[1] + clearance and f[2] - clearance < y < f[3] + clearance
                       for f in footprints):  # fmt: skip
                return (x, y)
        return None

    def _block_side(self, lot, side: str, footprints: list, frontage: float) -> None:
        cfg = self.cfg
        x0, x1, y0, y1 = lot
        along_x = side in ("-y", "+y")
        s0, s1 = (x0, x1) if along_x else (y0, y1)
        depth_room = ((y1 - y0) if along_x else (x1 - x0)) / 2 - 0.5
        # keep the side setback at the lot corners too, so corner buildings leave the
        # cross street's sidewalk/shoulder (and its poles) free
        corner = max(1.0, cfg.setback[0])
        s0, s1 = s0 + corner, s1 - corner
        pos = s0 + self.u((0.0, 3.0))
        # the side's building line comes from the detail stream: the layout draws stay the same
        line = self.detail_rng.uniform(*cfg.setback) if cfg.building_line else None
        while pos < s1 - 4.0:
            if self.rng.random() < frontage:
                w = min(self.u(cfg.building_width), s1 - pos)
                if w < 6.0:
                    break
                sb = self.u(cfg.setback)
                if line is not None:
                    j = cfg.building_line_jitter
                    sb = max(0.0, line + self.detail_rng.uniform(-j, j))
                d = min(self.u(cfg.building_depth), depth_room - sb)
                if d > 4.0:
                    fp = self._footprint(lot, side, pos, pos + w, sb, sb + d)
                    fp = self._clip_against(fp, footprints, along_x)
                    if fp is not None:
                        footprints.append(fp)
                        self._building(fp, side, self.u(cfg.building_height))
                        if sb > 1.5 and self.rng.random() < cfg.front_fences:
                            self._fence_or_wall(lot, side, pos, pos + w, 0.4, "fence", footprints)
                pos += w
            else:
                g = self.u(cfg.gap)
                g = min(g, s1 - pos)
                r = self.rng.random()
                if g > 2.0 and r < cfg.wall_prob:
                    self._fence_or_wall(
                        lot, side, pos + 0.3, pos + g - 0.3, 0.3, "wall", footprints
                    )
                elif g > 2.0 and r < cfg.wall_prob + cfg.fence_prob:
                    self._fence_or_wall(
                        lot, side, pos + 0.3, pos + g - 0.3, 0.3, "fence", footprints
                    )
                pos += g

    @staticmethod
    def _footprint(lot, side, a, b, n0, n1):
        """Footprint (x0, x1, y0, y1) from along-side interval [a, b] and inward depth [n0, n1]."""
        x0, x1, y0, y1 = lot
        if side == "-y":
            return (a, b, y0 + n0, y0 + n1)
        if side == "+y":
            return (a, b, y1 - n1, y1 - n0)
        if side == "-x":
            return (x0 + n0, x0 + n1, a, b)
        return (x1 - n1, x1 - n0, a, b)

    @staticmethod
    def _clip_against(fp, footprints, along_x: bool, margin: float = 1.0, min_len: float = 6.0):
        """Shrink a footprint along its side so it overlaps no earlier footprint (or drop it)."""
        fx0, fx1, fy0, fy1 = fp
        for g in footprints:
            if (
                fx0 < g[1] + margin
                and g[0] - margin < fx1
                and fy0 < g[3] + margin
                and g[2] - margin < fy1
            ):
                if along_x:
                    return None
                # keep the larger free piece along y
                lo_piece = (fy0, g[2] - margin)
                hi_piece = (g[3] + margin, fy1)
                fy0, fy1 = max((lo_piece, hi_piece), key=lambda p: p[1] - p[0])
                if fy1 - fy0 < min_len:
                    return None
        return (fx0, fx1, fy0, fy1)

    def _building(self, fp, side: str, height: float) -> None:
        x0, x1, y0, y1 = fp
        cx = np.array([x0, x1, x0, x1])
        cy = np.array([y0, y0, y1, y1])
        g = self.h(cx, cy) + CURB_HEIGHT
        zb, zt = g.min() - 0.5, g.max() + height
        V, F = _box(np.array([x0, y0, zb]), np.array([x1, y1, zt]))
        inst = self.mb.new_instance()
        lm = np.full(12, -1, np.int32)
        for face, normal, centre_xy, box_w in (
            ("-x", (-1, 0, 0), (x0, (y0 + y1) / 2), y1 - y0),
            ("+x", (1, 0, 0), (x1, (y0 + y1) / 2), y1 - y0),
            ("-y", (0, -1, 0), ((x0 + x1) / 2, y0), x1 - x0),
            ("+y", (0, 1, 0), ((x0 + x1) / 2, y1), x1 - x0),
        ):
            zg = float(self.h(*centre_xy)) + CURB_HEIGHT
            anchor = (centre_xy[0], centre_xy[1], (zg + zt) / 2)
            k = self.mb.add_plane(normal, anchor, (box_w, zt - zg), BUILDING, "facade", inst)
            f = _BOX_FACE[face]
            lm[2 * f : 2 * f + 2] = k
        self.mb.add(V, F, BUILDING, inst, lm)
        if self.cfg.facade_detail:
            self._facade_details(fp, side, float(g.min()), zt, inst)

    def _fence_or_wall(
        self, lot, side: str, a: float, b: float, inset: float, kind: str, footprints: list
    ) -> None:
        cfg = self.cfg
        if b - a < 1.5:
            return
        thick = 0.25 if kind == "wall" else 0.06
        height = self.u(cfg.wall_height if kind == "wall" else cfg.fence_height)
        fp = self._footprint(lot, side, a, b, inset, inset + thick)
        fp = self._clip_against(fp, footprints, side in ("-y", "+y"), margin=0.1, min_len=1.5)
        if fp is None:
            return
        footprints.append(fp)
        x0, x1, y0, y1 = fp
        zs = self.h(np.array([x0, x1, x0, x1]), np.array([y0, y0, y1, y1])) + CURB_HEIGHT
        zb, zt = zs.min() - 0.3, zs.min() + height
        V, F = _box(np.array([x0, y0, zb]), np.array([x1, y1, zt]))
        inst = self.mb.new_instance()
        cls = BUILDING if kind == "wall" else FENCE
        # the street-facing face is the GT plane; the back face stays unlabelled (-1)
        face, normal = {"-y": ("-y", (0, -1, 0)), "+y": ("+y", (0, 1, 0)),
                        "-x": ("-x", (-1, 0, 0)), "+x": ("+x", (1, 0, 0))}[side]  # fmt: skip
        fx = {"-x": x0, "+x": x1}.get(face, (x0 + x1) / 2)
        fy = {"-y": y0, "+y": y1}.get(face, (y0 + y1) / 2)
        zg = float(self.h(fx, fy)) + CURB_HEIGHT
        w = (x1 - x0) if face in ("-y", "+y") else (y1 - y0)
        k = self.mb.add_plane(normal, (fx, fy, (zg + zt) / 2), (w, zt - zg), cls, kind, inst)
        lm = np.full(12, -1, np.int32)
        f = _BOX_FACE[face]
        lm[2 * f : 2 * f + 2] = k
        self.mb.add(V, F, cls, inst, lm)
