"""A small synthetic street scene (poles, facades, ground) seen from two poses, with points."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from graffmatch.geometry.landmarks import LandmarkSet, fit_landmark
from graffmatch.geometry.transforms import invert, make_transform, rot_z


@dataclass
class Scene:
    source: LandmarkSet
    target: LandmarkSet
    T_target_source: np.ndarray
    associations: np.ndarray
    inlier_mask: np.ndarray
    source_points: np.ndarray
    target_points: np.ndarray


def make_scene(seed: int = 0) -> Scene:
    rng = np.random.default_rng(seed)
    lms, pts = [], []
    for _ in range(8):  # poles: 5 m tall, 0.1 m radius
        c = np.r_[rng.uniform(-25, 25, 2), 0.0]
        P = c + np.c_[rng.normal(0, 0.08, (300, 2)), rng.uniform(0, 5, 300)]
        lms.append(fit_landmark(P, 1)[0])
        pts.append(P)
    for k in range(5):  # facades 8 m wide, 6 m tall, facing +-y
        c = np.r_[rng.uniform(-25, 25), 20.0 * (-1) ** k, 0.0]
        P = (
            c
            + np.c_[rng.uniform(-4, 4, (500, 1)), rng.normal(0, 0.02, 500), rng.uniform(0, 6, 500)]
        )
        lms.append(fit_landmark(P, 2)[0])
        pts.append(P)
    ground = np.c_[rng.uniform(-30, 30, (3000, 2)), rng.normal(0, 0.02, 3000)]
    lms.append(fit_landmark(ground, 2)[0])
    pts.append(ground)
    base = LandmarkSet.from_landmarks(lms)
    off = np.r_[0, np.cumsum([len(p) for p in pts])]
    allp = np.concatenate(pts).astype(np.float32)
    target = LandmarkSet(base.types, base.bases, base.anchors, base.attributes, allp, off)
    T = make_transform(rot_z(np.pi), [14.0, 3.0, 0.0])  # 180 deg of yaw and 14 m, as Fig. 1
    source = target.transform(invert(T))
    n = len(target)
    assoc = np.c_[np.arange(n), np.arange(n)]
    assoc[3, 1] = 5  # one wrong association (pole 3 -> pole 5)
    mask = assoc[:, 0] == assoc[:, 1]
    return Scene(source, target, T, assoc, mask, source.points.copy(), allp)


@pytest.fixture
def scene() -> Scene:
    return make_scene()
