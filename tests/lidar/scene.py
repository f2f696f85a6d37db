"""Synthetic LiDAR-like scenes with known poles and planes (ground truth for the tests)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

GROUND_Z = -1.7  # sensor 1.7 m above a flat ground, as on KITTI's car
POLE_CLASS = 80


@dataclass
class Scene:
    points: np.ndarray  # (N, 4) float32
    labels: np.ndarray  # (N,) uint32, SemanticKITTI-style
    poles: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)  # (point, dir)
    walls: list[tuple[np.ndarray, float]] = field(default_factory=list)  # (normal, offset)
    ground: tuple[np.ndarray, float] = (np.array([0.0, 0.0, 1.0]), GROUND_Z)


def _ground(rng, half: float, density: float) -> np.ndarray:
    n = int(density * (2 * half) ** 2)
    xy = rng.uniform(-half, half, size=(n, 2))
    z = np.full(n, GROUND_Z)
    return np.column_stack([xy, z])


def _wall(rng, p0, p1, height: float, density: float) -> np.ndarray:
    """Vertical rectangle from xy p0 to xy p1, from the ground up to ``height``."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    length = np.linalg.norm(p1 - p0)
    n = int(density * length * height)
    s = rng.uniform(0, 1, n)
    xy = p0 + s[:, None] * (p1 - p0)
    z = GROUND_Z + rng.uniform(0, height, n)
    return np.column_stack([xy, z])


def _pole(rng, xy, radius: float, height: float, n: int) -> np.ndarray:
    ang = rng.uniform(0, 2 * np.pi, n)
    z = GROUND_Z + rng.uniform(0, height, n)
    return np.column_stack([xy[0] + radius * np.cos(ang), xy[1] + radius * np.sin(ang), z])


def make_scene(seed: int = 0, noise: float = 0.01, door_gap: bool = True) -> Scene:
    """Ground, four walls (one split by a 1.5 m gap into two patches), five poles."""
    rng = np.random.default_rng(seed)
    parts, labels = [], []
    g = _ground(rng, 30.0, 40.0)
    parts.append(g)
    labels.append(np.full(len(g), 40, np.uint32))  # road
    walls_xy = [
        ((15.0, -12.0), (15.0, 12.0)),  # x = 15, normal -x
        ((-14.0, -12.0), (-14.0, 12.0)),  # x = -14
        ((-10.0, 18.0), (10.0, 18.0)),  # y = 18
    ]
    walls = []
    for p0, p1 in walls_xy:
        w = _wall(rng, p0, p1, 6.0, 60.0)
        parts.append(w)
        labels.append(np.full(len(w), 50, np.uint32))  # building
        d = np.subtract(p1, p0)
        nrm = np.array([-d[1], d[0], 0.0]) / np.linalg.norm(d)
        walls.append((nrm, float(nrm[:2] @ np.asarray(p0))))
    # y = -20 wall split by a door-like gap: two patches of one infinite plane.
    gap = 1.5 if door_gap else 0.0
    for p0, p1 in (((-10.0, -20.0), (-gap / 2, -20.0)), ((gap / 2, -20.0), (10.0, -20.0))):
        w = _wall(rng, p0, p1, 6.0, 60.0)
        parts.append(w)
        labels.append(np.full(len(w), 50, np.uint32))
    walls.append((np.array([0.0, 1.0, 0.0]), -20.0))
    poles = []
    for xy in ((6.0, 4.0), (-5.0, 7.0), (8.0, -9.0), (-7.0, -6.0), (3.0, 11.0)):
        p = _pole(rng, np.array(xy), 0.12, 5.0, 400)
        parts.append(p)
        labels.append(np.full(len(p), POLE_CLASS, np.uint32) | (np.uint32(len(poles) + 1) << 16))
        poles.append((np.array([xy[0], xy[1], 0.0]), np.array([0.0, 0.0, 1.0])))
    P = np.concatenate(parts)
    P += rng.normal(scale=noise, size=P.shape)
    inten = rng.uniform(0, 1, len(P))
    pts = np.column_stack([P, inten]).astype(np.float32)
    return Scene(pts, np.concatenate(labels), poles, walls)
