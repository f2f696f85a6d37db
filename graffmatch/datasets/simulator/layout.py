"""Layout of the world: the street grid, the piecewise-planar ground and the curbs.

The ground is piecewise planar on purpose: its height is ``f(x) + g(y)`` with piecewise-linear
``f`` and ``g`` whose kinks lie on block centre lines, so every street patch is an exact plane
(a true GT plane), while the slopes still vary gently from street to street.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from graffmatch.datasets.simulator.mesh import (
    _QUAD_A,
    _QUAD_B,
    CURB_HEIGHT,
    ROAD,
    SIDEWALK,
    TERRAIN,
)


def _pwl(x, knots: NDArray, values: NDArray) -> NDArray:
    """Piecewise-linear function; the end knots lie 200 m beyond the world's terrain, so
    interpolation (np.interp, fast for scalars too) covers every place that exists."""
    return np.interp(x, knots, values)


def _pwl_slope(x, knots: NDArray, values: NDArray) -> NDArray:
    x = np.asarray(x, float)
    i = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, len(knots) - 2)
    return (values[i + 1] - values[i]) / (knots[i + 1] - knots[i])


class LayoutMixin:
    """Streets, ground and curbs of the world generator (``_Generator`` in ``world.py``).

    Uses the generator's ``cfg``, ``rng``, ``mb``, ``hw`` (road half width) and ``cw`` (road
    plus sidewalk); sets ``X``/``Y`` (street centre lines) and the ground knots ``kx, vx, ky, vy``.
    """

    def u(self, r: tuple[float, float]) -> float:
        return float(self.rng.uniform(r[0], r[1]))

    # -- layout -------------------------------------------------------------------------
    def _streets(self, n_blocks: int) -> NDArray:
        blocks = self.rng.uniform(*self.cfg.block_size, size=n_blocks)
        pitch = blocks + 2 * self.cw
        pos = np.concatenate([[0.0], np.cumsum(pitch)])
        return pos - pos[n_blocks // 2]  # a central street passes through the origin

    def _ground_fn(self, streets: NDArray) -> tuple[NDArray, NDArray]:
        mids = (streets[:-1] + streets[1:]) / 2
        lo = streets[0] - self.cw - self.cfg.margin - 200.0
        hi = streets[-1] + self.cw + self.cfg.margin + 200.0
        knots = np.concatenate([[lo], mids, [hi]])
        slopes = self.rng.uniform(-self.cfg.max_slope, self.cfg.max_slope, size=len(knots) - 1)
        vals = np.concatenate([[0.0], np.cumsum(slopes * np.diff(knots))])
        # zero height at the origin keeps coordinates small
        vals -= _pwl(0.0, knots, vals)
        return knots, vals

    def h(self, x, y):
        return _pwl(x, self.kx, self.vx) + _pwl(y, self.ky, self.vy)

    # -- ground ---------------------------------------------------------------------------
    def _ground(self) -> None:
        """Rectangles between all street/sidewalk/kink breakpoints; each is an exact plane."""
        cfg = self.cfg
        lo_x, hi_x = self.X[0] - self.cw - cfg.margin, self.X[-1] + self.cw + cfg.margin
        lo_y, hi_y = self.Y[0] - self.cw - cfg.margin, self.Y[-1] + self.cw + cfg.margin

        def breaks(S, knots, lo, hi):
            b = np.concatenate(
                [S - self.cw, S - self.hw, S + self.hw, S + self.cw, knots, [lo, hi]]
            )
            b = np.unique(np.round(b[(b >= lo) & (b <= hi)], 6))
            return b

        bx = breaks(self.X, self.kx, lo_x, hi_x)
        by = breaks(self.Y, self.ky, lo_y, hi_y)
        cx, cy = (bx[:-1] + bx[1:]) / 2, (by[:-1] + by[1:]) / 2
        dx = np.min(np.abs(cx[:, None] - self.X[None]), axis=1)
        dy = np.min(np.abs(cy[:, None] - self.Y[None]), axis=1)
        road = (dx[:, None] < self.hw) | (dy[None, :] < self.hw)
        walk = ~road & ((dx[:, None] < self.cw) | (dy[None, :] < self.cw))
        cls = np.where(road, ROAD, np.where(walk, SIDEWALK, TERRAIN)).astype(np.uint16)
        raised = np.where(road, 0.0, CURB_HEIGHT)
        # ground-patch landmark per (kink cell, raised?) group
        ix = np.searchsorted(self.kx, cx) - 1
        iy = np.searchsorted(self.ky, cy) - 1
        nxr, nyr = len(cx), len(cy)
        ii, jj = np.meshgrid(np.arange(nxr), np.arange(nyr), indexing="ij")
        x0, x1 = bx[ii], bx[ii + 1]
        y0, y1 = by[jj], by[jj + 1]
        corners_x = np.stack([x0, x1, x0, x1], -1)
        corners_y = np.stack([y0, y0, y1, y1], -1)
        z = self.h(corners_x, corners_y) + raised[..., None]
        V = np.stack([corners_x, corners_y, z], -1).reshape(-1, 4, 3)
        base = 4 * np.arange(V.shape[0])[:, None]
        F = np.concatenate([base + _QUAD_A, base + _QUAD_B], axis=1).reshape(-1, 3)
        group = (ix[ii] * len(self.ky) + iy[jj]) * 2 + (~road).astype(int)
        gflat = group.reshape(-1)
        lm_of_group: dict[int, int] = {}
        area = ((x1 - x0) * (y1 - y0)).reshape(-1)
        ctr = V.mean(axis=1)
        for g in np.unique(gflat):
            sel = gflat == g
            A = area[sel].sum()
            if A < 50.0:
                continue
            anchor = (ctr[sel] * area[sel, None]).sum(0) / A
            gx = _pwl_slope(anchor[0], self.kx, self.vx)
            gy = _pwl_slope(anchor[1], self.ky, self.vy)
            side = (np.ptp(np.concatenate([x0.reshape(-1)[sel], x1.reshape(-1)[sel]])),
                    np.ptp(np.concatenate([y0.reshape(-1)[sel], y1.reshape(-1)[sel]])))  # fmt: skip
            cls_g = int(cls.reshape(-1)[sel][np.argmax(area[sel])])
            lm_of_group[int(g)] = self.mb.add_plane(
                [-gx, -gy, 1.0], anchor, side, cls_g, "ground", 0
            )
        lm_rect = np.array([lm_of_group.get(int(g), -1) for g in gflat], np.int32)
        self.mb.add(V.reshape(-1, 3), F, np.repeat(cls.reshape(-1), 2), 0, np.repeat(lm_rect, 2))
        self._curbs(bx, by, road)

    def _curbs(self, bx: NDArray, by: NDArray, road: NDArray) -> None:
        """Vertical curb faces where road meets a raised rectangle (closes the 15 cm step)."""
        quads = []
        ex = np.argwhere(road[:-1, :] != road[1:, :])  # faces at x = bx[i+1]
        for i, j in ex:
            x = bx[i + 1]
            quads.append(([x, by[j]], [x, by[j + 1]]))
        ey = np.argwhere(road[:, :-1] != road[:, 1:])
        for i, j in ey:
            y = by[j + 1]
            quads.append(([bx[i], y], [bx[i + 1], y]))
        if not quads:
            return
        P = np.array(quads, float)  # (q, 2, 2)
        zb = self.h(P[..., 0], P[..., 1])
        V = np.concatenate(
            [
                np.concatenate([P, zb[..., None]], -1),
                np.concatenate([P, zb[..., None] + CURB_HEIGHT], -1),
            ],
            axis=1,
        )  # (q, 4, 3): p0 p1 p0' p1'
        base = 4 * np.arange(len(P))[:, None]
        F = np.concatenate([base + _QUAD_A, base + _QUAD_B], axis=1).reshape(-1, 3)
        self.mb.add(V.reshape(-1, 3), F, SIDEWALK, 0)
