"""Facade relief: windows, sills, pilasters, balconies and shop signs on the buildings.

Real facades are not the flat boxes of the ideal world: in KITTI the planes the front end
extracts have a point-to-plane RMS of about 6 cm, glass returns from inside the rooms or not
at all, and balconies and signs break a facade into patches. Every detail is a separate box in
front of the facade plane (so the facade's own GT plane stays exact) with no GT landmark;
windows are thin glass panes (``mesh.GLASS``) that the sensor treats as see-through.
"""

from __future__ import annotations

import numpy as np

from graffmatch.datasets.simulator.mesh import BUILDING, GLASS, _boxes

_OPPOSITE = {"-x": "+x", "+x": "-x", "-y": "+y", "+y": "-y"}


def _steps(rng: np.random.Generator, n: int) -> np.ndarray:
    """How far each bay stands out: mostly a few cm (render, cladding: the facade stays one
    rough plane), sometimes 20-40 cm (a bay window or a set-back shop front: the plane splits)."""
    small = np.where(rng.random(n) < 0.8, rng.uniform(0.03, 0.15, n), 0.0)
    return np.where(rng.random(n) < 0.12, rng.uniform(0.2, 0.4, n), small)


class FacadeDetailMixin:
    """Relief on the faces of each building of the world generator (own random stream)."""

    def _facade_details(self, fp, side: str, z_ground: float, z_top: float, inst: int) -> None:
        """Details on every face but the back one (the street face and the two visible in gaps)."""
        x0, x1, y0, y1 = fp
        for face in ("-x", "+x", "-y", "+y"):
            if face == _OPPOSITE[side]:
                continue
            axis = 0 if face[1] == "x" else 1  # the face's normal axis
            sign = 1.0 if face[0] == "+" else -1.0
            plane = {"-x": x0, "+x": x1, "-y": y0, "+y": y1}[face]
            a0, a1 = (y0, y1) if axis == 0 else (x0, x1)
            self._face_relief(axis, sign, plane, a0, a1, z_ground, z_top, inst, face == side)

    def _face_relief(self, axis, sign, plane, a0, a1, z0, z1, inst, street_face: bool) -> None:
        cfg, rng = self.cfg, self.detail_rng
        lo: list[list[float]] = []  # boxes as (along lo, along hi, out lo, out hi, z lo, z hi)
        glass: list[list[float]] = []
        width = a1 - a0
        pitch = rng.uniform(2.4, 3.6)
        n_bays = max(1, int(width // pitch))
        pitch = width / n_bays
        centres = a0 + pitch * (np.arange(n_bays) + 0.5)
        win_w = pitch * rng.uniform(0.45, 0.7)
        floor_h = rng.uniform(3.0, 3.4)
        ground_h = rng.uniform(3.6, 4.5)
        floors = [
            z0 + ground_h + k * floor_h for k in range(int((z1 - z0 - ground_h - 1.0) // floor_h))
        ]
        # stepped facade: bays (and with them their windows) stand out by a few cm, as
        # cladding, render and brick of real buildings do
        step = _steps(rng, n_bays)
        for c, dz in zip(centres, step, strict=True):
            if dz > 0:
                lo.append([c - pitch / 2, c + pitch / 2, 0.0, dz, z0, z1])
        win_h = rng.uniform(1.3, 1.8)
        # ground floor: shop fronts (glass across most of each bay, maybe a sign band above)
        # or, on houses, ordinary windows; the glass sits on the bay's face, in front of it
        shop_h = rng.uniform(2.0, 2.8)
        shop = street_face and rng.random() < cfg.shop_front_prob
        for c, dz in zip(centres, step, strict=True):
            if not shop:
                glass.append([c - win_w / 2, c + win_w / 2, dz, dz + 0.004, z0 + 0.9, z0 + 0.9 + win_h])
                continue
            glass.append(
                [c - 0.42 * pitch, c + 0.42 * pitch, dz, dz + 0.004, z0 + 0.4, z0 + 0.4 + shop_h]
            )
            if rng.random() < cfg.shop_sign_prob:
                glass_top = z0 + 0.4 + shop_h
                lo.append([c - 0.45 * pitch, c + 0.45 * pitch, dz, dz + rng.uniform(0.15, 0.35),
                           glass_top + 0.2, glass_top + rng.uniform(0.8, 1.2)])  # fmt: skip
        sill = rng.random() < 0.7
        for zf in floors:
            for c, dz in zip(centres, step, strict=True):
                zw = zf + 0.9
                glass.append([c - win_w / 2, c + win_w / 2, dz, dz + 0.004, zw, zw + win_h])
                if sill:
                    lo.append([c - win_w / 2 - 0.1, c + win_w / 2 + 0.1, dz, dz + 0.12, zw - 0.08, zw])
                if street_face and rng.random() < cfg.balcony_prob:
                    d = rng.uniform(0.9, 1.5)
                    lo.append([c - win_w / 2 - 0.4, c + win_w / 2 + 0.4, 0.0, d, zf, zf + 1.05])
        # pilasters between some bays and a cornice at the top
        if rng.random() < 0.4:
            for e in a0 + pitch * np.arange(0, n_bays + 1, 2):
                lo.append([e - 0.25, e + 0.25, 0.0, rng.uniform(0.1, 0.25), z0, z1 - 0.3])
        if rng.random() < 0.5:
            lo.append([a0, a1, 0.0, rng.uniform(0.2, 0.5), z1 - 0.6, z1])
        for boxes, material in ((lo, 0), (glass, GLASS)):
            if not boxes:
                continue
            B = np.asarray(boxes, float)
            B[:, 0:2] = np.clip(B[:, 0:2], a0, a1)
            B[:, 4:6] = np.clip(B[:, 4:6], z0, z1)
            out = plane + sign * (B[:, 2:4] + 0.002)  # a hair in front of the facade
            lo_xyz = np.empty((len(B), 3))
            hi_xyz = np.empty((len(B), 3))
            other = 1 - axis
            lo_xyz[:, axis], hi_xyz[:, axis] = out.min(1), out.max(1)
            lo_xyz[:, other], hi_xyz[:, other] = B[:, 0], B[:, 1]
            lo_xyz[:, 2], hi_xyz[:, 2] = B[:, 4], B[:, 5]
            V, F = _boxes(lo_xyz, hi_xyz)
            self.mb.add(V, F, BUILDING, inst, -1, material)
