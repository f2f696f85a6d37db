"""Labelled triangles: SemanticKITTI classes, primitive meshes and the world's mesh builder.

Every triangle of the world carries a class id, an instance id and (when it lies on one) the
index of its ground-truth landmark; ``_MeshBuilder`` collects them with the GT landmarks and
concatenates once at the end.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType

# ---- SemanticKITTI classes -----------------------------------------------------------------
CAR = 10
ROAD = 40
SIDEWALK = 48
BUILDING = 50
FENCE = 51
VEGETATION = 70
TRUNK = 71
TERRAIN = 72
POLE = 80
TRAFFIC_SIGN = 81
OTHER_OBJECT = 99


class _Palette:
    """SemanticKITTI-like RGB colours in [0, 1] for viewing."""

    def __init__(self) -> None:
        self.table = np.full((256, 3), 0.6)
        for cls, rgb in {
            CAR: (0.39, 0.59, 0.96), ROAD: (1.0, 0.0, 1.0), SIDEWALK: (0.29, 0.0, 0.29),
            BUILDING: (1.0, 0.78, 0.0), FENCE: (1.0, 0.47, 0.2), VEGETATION: (0.0, 0.69, 0.0),
            TRUNK: (0.53, 0.24, 0.0), TERRAIN: (0.59, 0.94, 0.31), POLE: (1.0, 0.94, 0.59),
            TRAFFIC_SIGN: (1.0, 0.0, 0.0), OTHER_OBJECT: (0.2, 0.2, 0.2),
        }.items():  # fmt: skip
            self.table[cls] = rgb

    def get_many(self, classes: NDArray) -> NDArray:
        return self.table[np.asarray(classes, int) & 0xFF]


CLASS_COLOURS = _Palette()

#: Landmark categories stored in the ``category`` attribute of the GT landmarks.
CATEGORIES = {
    "ground": 0,
    "facade": 1,
    "wall": 2,
    "fence": 3,
    "street_light": 10,
    "sign_post": 11,
    "trunk": 12,
    "utility_pole": 13,
}

#: Surface materials (``World.tri_material``): how the sensor treats a hit.
OPAQUE = 0
GLASS = 1  # windows: many rays drop out, the rest return from inside the building
FOLIAGE = 2  # leaves: rays return from a random depth inside the crown or hedge

#: Height of sidewalks and lots above the road surface [m].
CURB_HEIGHT = 0.15


# ---- primitive meshes ------------------------------------------------------------------------
_BOX_TRIS = np.array(
    [
        [0, 4, 6], [0, 6, 2],  # -x
        [1, 3, 7], [1, 7, 5],  # +x
        [0, 1, 5], [0, 5, 4],  # -y
        [2, 6, 7], [2, 7, 3],  # +y
        [0, 2, 3], [0, 3, 1],  # -z
        [4, 5, 7], [4, 7, 6],  # +z
    ],
    dtype=np.int64,
)  # fmt: skip
_QUAD_A = np.array([0, 1, 3])
_QUAD_B = np.array([0, 3, 2])
_BOX_FACE = {"-x": 0, "+x": 1, "-y": 2, "+y": 3, "-z": 4, "+z": 5}


_BOX_BITS = np.array([[(i >> k) & 1 for k in range(3)] for i in range(8)])
_BOX_AXES = np.broadcast_to(np.arange(3), (8, 3))


def _box(lo: NDArray, hi: NDArray) -> tuple[NDArray, NDArray]:
    """Axis-aligned box; triangles 2f, 2f+1 belong to face f in the order -x +x -y +y -z +z."""
    LH = np.array([lo, hi], dtype=float)
    return LH[_BOX_BITS, _BOX_AXES], _BOX_TRIS


def _boxes(lo: NDArray, hi: NDArray) -> tuple[NDArray, NDArray]:
    """Many axis-aligned boxes at once: (8n, 3) vertices and (12n, 3) triangles."""
    lo, hi = np.atleast_2d(lo).astype(float), np.atleast_2d(hi).astype(float)
    LH = np.stack([lo, hi], axis=1)  # (n, 2, 3)
    V = LH[:, _BOX_BITS, _BOX_AXES].reshape(-1, 3)
    F = (_BOX_TRIS[None] + 8 * np.arange(len(lo))[:, None, None]).reshape(-1, 3)
    return V, F


def _cylinder(base: NDArray, radius: float, height: float, n_seg: int = 12):
    """Vertical cylinder (sides + top cap); side triangles come first (2 * n_seg of them)."""
    a = np.arange(n_seg) * (2 * np.pi / n_seg)
    ring = np.stack([np.cos(a) * radius, np.sin(a) * radius, np.zeros(n_seg)], axis=1)
    top = base + np.array([0.0, 0.0, height])
    V = np.concatenate([ring + base, ring + top, top[None]])
    k = np.arange(n_seg)
    k1 = (k + 1) % n_seg
    sides = np.concatenate(
        [np.stack([k, k1, k1 + n_seg], 1), np.stack([k, k1 + n_seg, k + n_seg], 1)]
    )
    cap = np.stack([np.full(n_seg, 2 * n_seg), k + n_seg, k1 + n_seg], 1)
    return V, np.concatenate([sides, cap])


_SPHERE_CACHE: dict[int, tuple[NDArray, NDArray]] = {}


def _unit_sphere(subdiv: int = 1) -> tuple[NDArray, NDArray]:
    """Icosphere (80 triangles at subdiv=1): enough for tree canopies and bushes."""
    if subdiv not in _SPHERE_CACHE:
        t = (1 + 5**0.5) / 2
        V = np.array(
            [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
             [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
            dtype=float,
        )  # fmt: skip
        F = np.array(
            [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
             [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
             [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
        )  # fmt: skip
        for _ in range(subdiv):
            edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
            uniq, inv = np.unique(edges, axis=0, return_inverse=True)
            mids = (V[uniq[:, 0]] + V[uniq[:, 1]]) / 2
            m = inv.reshape(3, -1).T + len(V)
            V = np.concatenate([V, mids])
            a, b, c = F.T
            ab, bc, ca = m.T
            F = np.concatenate(
                [np.stack(x, 1) for x in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))]
            )
        V = V / np.linalg.norm(V, axis=1, keepdims=True)
        _SPHERE_CACHE[subdiv] = (V, F)
    return _SPHERE_CACHE[subdiv]


class _MeshBuilder:
    """Collects labelled triangles and GT landmarks; one concatenation at the end."""

    def __init__(self) -> None:
        self.V: list[NDArray] = []
        self.F: list[NDArray] = []
        self.cls: list[NDArray] = []
        self.inst: list[NDArray] = []
        self.lm: list[NDArray] = []
        self.mat: list[NDArray] = []
        self.nv = 0
        self.next_instance = 1
        self.landmarks: list[dict] = []

    def new_instance(self) -> int:
        i = self.next_instance
        self.next_instance += 1
        if self.next_instance >= 1 << 16:
            raise InvalidInputError("world has more than 65535 object instances")
        return i

    def add(self, V: NDArray, F: NDArray, cls, inst, lm=-1, material: int = OPAQUE) -> None:
        m = len(F)
        self.V.append(np.asarray(V, float))
        self.F.append(np.asarray(F, np.int64) + self.nv)
        self.nv += len(V)
        for store, v, dt in (
            (self.cls, cls, np.uint16),
            (self.inst, inst, np.uint32),
            (self.lm, lm, np.int32),
        ):
            store.append(np.full(m, v, dt) if np.isscalar(v) else np.asarray(v, dt).reshape(m))
        self.mat.append(np.full(m, material, np.uint8))

    def add_plane(self, normal, anchor, box, class_id: int, category: str, instance: int) -> int:
        n = np.asarray(normal, float)
        self.landmarks.append(
            dict(
                type=LandmarkType.PLANE, direction=n / np.linalg.norm(n), anchor=np.asarray(anchor, float),
                extent=float(box[0] * box[1]), radius=np.nan, box=np.asarray(box, float),
                class_id=class_id, category=CATEGORIES[category], instance=instance,
            )
        )  # fmt: skip
        return len(self.landmarks) - 1

    def add_pole(self, base, radius, height, class_id: int, category: str, instance: int) -> int:
        self.landmarks.append(
            dict(
                type=LandmarkType.LINE, direction=np.array([0.0, 0.0, 1.0]),
                anchor=np.asarray(base, float) + np.array([0.0, 0.0, height / 2]), extent=float(height),
                radius=float(radius), box=np.array([np.nan, np.nan]),
                class_id=class_id, category=CATEGORIES[category], instance=instance,
            )
        )  # fmt: skip
        return len(self.landmarks) - 1

    def landmark_set(self) -> LandmarkSet:
        L = self.landmarks
        n = len(L)
        if n == 0:
            return LandmarkSet.empty()
        attrs = {
            "extent": np.array([d["extent"] for d in L]),
            "radius": np.array([d["radius"] for d in L]),
            "box": np.stack([d["box"] for d in L]),
            "class_id": np.array([d["class_id"] for d in L], np.int32),
            "category": np.array([d["category"] for d in L], np.int32),
            "instance": np.array([d["instance"] for d in L], np.int32),
            "gt_id": np.arange(n, dtype=np.int32),
        }
        return LandmarkSet.from_arrays(
            np.array([int(d["type"]) for d in L]),
            np.stack([d["direction"] for d in L]),
            np.stack([d["anchor"] for d in L]),
            attrs,
        )
