"""Synthetic street scenes of pole and plane landmarks, seen from two views.

A light-weight generator for the demo, tests and benchmarks of the matcher: it produces two
LandmarkSets of the same street (each view misses some landmarks, anchors and directions are
noisy, anchors also drift within the landmark as a real segmentation's centroid would) plus the
ground-truth transform and matches. The ray-cast LiDAR world lives in ``datasets.simulator``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.geometry.transforms import invert, make_transform, rot_z


@dataclass
class LandmarkScenePair:
    source: LandmarkSet
    target: LandmarkSet
    T_target_source: NDArray[np.float64]
    true_matches: NDArray[np.int64]  # (k, 2) source index, target index
    world: LandmarkSet

    @property
    def input_inlier_ratio(self) -> float:
        from graffmatch.association.putative import count_all_to_all

        m = count_all_to_all(self.source.types, self.target.types)
        return len(self.true_matches) / max(m, 1)


def street_world(n_poles: int, n_planes: int, rng: np.random.Generator, length: float = 80.0) -> LandmarkSet:
    """Poles along both sidewalks, facades/walls along and across the street, one ground plane.

    The ground anchor lies near the sensors (a LiDAR ground centroid does), so 1 degree of
    normal noise does not tilt the only height reference by metres at the sensors."""
    half = length / 2
    # Poles: near-vertical, on sidewalks at y = +-(6..9) m, heights 3-8 m.
    side = rng.choice([-1.0, 1.0], n_poles)
    px = rng.uniform(-half, half, n_poles)
    py = side * rng.uniform(5.5, 9.0, n_poles)
    h = rng.uniform(3.0, 8.0, n_poles)
    tilt = np.radians(rng.uniform(0, 3.0, n_poles))
    az = rng.uniform(0, 2 * np.pi, n_poles)
    pdir = np.stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)], 1)
    panchor = np.stack([px, py, h / 2], 1)
    # Planes: 1 ground, ~60% facades parallel to the street, the rest cross / oblique walls.
    n_ground = 1 if n_planes else 0  # one merged ground plane, as the front end produces
    n_fac = round(0.6 * (n_planes - n_ground))
    n_other = n_planes - n_ground - n_fac
    fx = rng.uniform(-half, half, n_fac)
    fside = rng.choice([-1.0, 1.0], n_fac)
    fy = fside * rng.uniform(8.0, 30.0, n_fac)
    fz = rng.uniform(2.0, 9.0, n_fac)
    fyaw = np.radians(rng.normal(0, 2.0, n_fac))
    fn = np.stack([-np.sin(fyaw) * fside, np.cos(fyaw) * fside, np.zeros(n_fac)], 1)
    ox = rng.uniform(-half, half, n_other)
    oy = rng.uniform(-25, 25, n_other)
    oz = rng.uniform(1.0, 8.0, n_other)
    oyaw = rng.uniform(0, np.pi, n_other)
    on = np.stack([np.cos(oyaw), np.sin(oyaw), np.zeros(n_other)], 1)
    gx = rng.uniform(0.0, 14.0, n_ground)
    gy = rng.uniform(-3, 3, n_ground)
    gz = rng.normal(0, 0.3, n_ground)
    gslope = np.radians(rng.uniform(0, 2, n_ground))
    gn = np.stack([np.sin(gslope), np.zeros(n_ground), np.cos(gslope)], 1)
    types = np.concatenate([np.full(n_poles, 1), np.full(n_planes, 2)])
    dirs = np.concatenate([pdir, fn, on, gn])
    anchors = np.concatenate([panchor, np.stack([fx, fy, fz], 1), np.stack([ox, oy, oz], 1),
                              np.stack([gx, gy, gz], 1)])
    extent = np.concatenate([h, rng.uniform(20, 200, n_planes)])
    return LandmarkSet.from_arrays(types, dirs, anchors, {"extent": extent})


def _perturb(ls: LandmarkSet, rng: np.random.Generator, anchor_noise: float,
             angle_noise_deg: float, anchor_drift: float) -> LandmarkSet:
    n = len(ls)
    dirs = ls.directions
    # Rotate each direction by a small random rotation of ~angle_noise_deg.
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    ang = np.radians(rng.normal(0.0, angle_noise_deg, n))
    c, s = np.cos(ang)[:, None], np.sin(ang)[:, None]
    dirs = dirs * c + np.cross(axis, dirs) * s + axis * np.sum(axis * dirs, 1, keepdims=True) * (1 - c)
    anchors = ls.anchors + rng.normal(0.0, anchor_noise, (n, 3))
    if anchor_drift > 0:
        # Drift within the landmark: a view-dependent centroid.
        coef = rng.normal(0.0, anchor_drift, (n, 2))
        anchors = anchors + np.einsum("nik,nk->ni", ls.bases, coef)
    return LandmarkSet.from_arrays(ls.types, dirs, anchors, ls.attributes)


def make_scene_pair(
    n_poles: int = 15,
    n_planes: int = 30,
    seed: int = 0,
    overlap: float = 0.8,
    anchor_noise: float = 0.1,
    angle_noise_deg: float = 1.0,
    anchor_drift: float = 0.0,
    yaw_deg: float = 180.0,
    translation: tuple[float, float, float] = (14.0, 0.0, 0.0),
    n_outliers: int = 0,
) -> LandmarkScenePair:
    """Two views of one street: each view keeps a random ``overlap`` fraction of the world's
    landmarks (plus ``n_outliers`` landmarks of its own), shuffled, with noise.

    The target frame is the world frame; the source frame is moved by ``yaw_deg`` and
    ``translation``, so ``T_target_source`` is that pose.
    """
    if n_poles < 0 or n_planes < 0 or n_poles + n_planes < 1 or n_outliers < 0:
        raise InvalidInputError(
            f"need n_poles, n_planes, n_outliers >= 0 and at least one landmark, got "
            f"{n_poles}, {n_planes}, {n_outliers}"
        )
    if not 0.0 < overlap <= 1.0:
        raise InvalidInputError(f"overlap must be in (0, 1], got {overlap}")
    rng = np.random.default_rng(seed)
    world = street_world(n_poles, n_planes, rng)
    n = len(world)
    T_target_source = make_transform(rot_z(np.radians(yaw_deg)), translation)
    views = []
    keep_sets = []
    for _ in range(2):
        keep = np.sort(rng.choice(n, size=max(1, round(overlap * n)), replace=False))
        ground = n - 1  # the ground plane is last and always seen
        if ground not in keep:
            keep[0] = ground
            keep = np.sort(keep)
        extra = street_world(
            round(n_outliers * n_poles / max(n, 1)),
            n_outliers - round(n_outliers * n_poles / max(n, 1)),
            rng,
        ) if n_outliers else LandmarkSet.empty()
        view = LandmarkSet.concatenate([_perturb(world[keep], rng, anchor_noise, angle_noise_deg,
                                                 anchor_drift), extra])
        origin = np.full(len(view), -1)
        origin[: len(keep)] = keep
        perm = rng.permutation(len(view))
        views.append(view[perm])
        keep_sets.append(origin[perm])
    source = views[0].transform(invert(T_target_source))
    target = views[1]
    src_of = {w: i for i, w in enumerate(keep_sets[0]) if w >= 0}
    matches = [(src_of[w], j) for j, w in enumerate(keep_sets[1]) if w >= 0 and w in src_of]
    true = np.array(sorted(matches), dtype=np.int64).reshape(-1, 2)
    return LandmarkScenePair(source, target, T_target_source, true, world)


__all__ = ["LandmarkScenePair", "LandmarkType", "make_scene_pair", "street_world"]
