"""A procedural urban world made of labelled triangles, with its ground-truth landmarks.

The world is an axis-aligned street grid. Every triangle carries a SemanticKITTI class id, an
object instance id and (when it lies on one) the index of the ground-truth landmark it belongs
to, so that a ray hit knows both its label and the true pole/plane it sampled. The ground is
piecewise planar on purpose: its height is ``f(x) + g(y)`` with piecewise-linear ``f`` and ``g``
whose kinks lie on block centre lines, so every street patch is an exact plane (a true GT
plane), while the slopes still vary gently from street to street.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

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

#: Height of sidewalks and lots above the road surface [m].
CURB_HEIGHT = 0.15


class WorldConfig(BaseModel):
    """Statistics of a procedural world. Lengths in metres, rates per 100 m of street side."""

    model_config = ConfigDict(extra="forbid")

    style: str = Field("custom", description="name of the preset this config came from")
    n_blocks_x: int = Field(4, ge=1, le=12, description="blocks along x (streets = blocks + 1)")
    n_blocks_y: int = Field(4, ge=1, le=12, description="blocks along y")
    block_size: tuple[float, float] = Field(
        (40.0, 70.0), description="range of block side lengths between sidewalks"
    )
    lanes_per_direction: int = Field(1, ge=1, le=3, description="driving lanes per direction")
    lane_width: float = Field(3.5, gt=2.0, description="width of a driving lane")
    parking_width: float = Field(2.3, ge=0.0, description="parking lane / shoulder at each curb")
    sidewalk_width: float = Field(3.5, ge=0.0, description="sidewalk width on each side")
    max_slope: float = Field(0.02, ge=0.0, le=0.1, description="max ground slope (rise/run)")
    margin: float = Field(60.0, ge=0.0, description="terrain beyond the outermost streets")
    # buildings
    frontage: float = Field(0.85, ge=0.0, le=1.0, description="fraction of lot sides built")
    frontage_spread: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="per-block frontage is frontage + U(-spread, spread): real streets alternate "
        "dense and gappy blocks, which spreads the landmark count (and the IIR) between places",
    )
    open_block_prob: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="P(a block is unbuilt: a park, plaza or car park with trees, no buildings)",
    )
    building_width: tuple[float, float] = Field((10.0, 30.0), description="facade width range")
    building_height: tuple[float, float] = Field((10.0, 40.0), description="height range")
    building_depth: tuple[float, float] = Field((10.0, 20.0), description="depth range")
    setback: tuple[float, float] = Field((0.0, 2.0), description="facade distance to lot edge")
    gap: tuple[float, float] = Field((2.0, 10.0), description="length of unbuilt stretches")
    wall_prob: float = Field(0.3, ge=0, le=1, description="P(wall) in an unbuilt stretch")
    fence_prob: float = Field(0.2, ge=0, le=1, description="P(fence) in an unbuilt stretch")
    wall_height: tuple[float, float] = Field((1.8, 3.0), description="wall height range")
    fence_height: tuple[float, float] = Field((1.0, 1.8), description="fence height range")
    front_fences: float = Field(0.0, ge=0, le=1, description="P(fence in front of a building)")
    # pole-like objects
    street_light_spacing: float = Field(35.0, gt=5.0, description="spacing of street lights")
    street_light_prob: float = Field(0.7, ge=0, le=1, description="P(light at a slot)")
    sign_rate: float = Field(1.5, ge=0, description="sign posts per 100 m of street side")
    tree_spacing: float = Field(20.0, gt=3.0, description="spacing of street trees")
    tree_prob: float = Field(0.2, ge=0, le=1, description="P(tree at a slot)")
    tree_prob_spread: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="per street side between crossings, P(tree) is tree_prob + U(-spread, "
        "spread): tree-lined stretches alternate with bare ones",
    )
    yard_tree_rate: float = Field(0.0, ge=0, description="trees in lots per 100 m of lot side")
    utility_pole_spacing: float = Field(40.0, gt=5.0, description="spacing of utility poles")
    utility_pole_prob: float = Field(0.0, ge=0, le=1, description="P(utility pole at a slot)")
    # cars and clutter
    car_prob: float = Field(0.6, ge=0, le=1, description="P(a parking slot is occupied)")
    clutter_rate: float = Field(4.0, ge=0, description="clutter objects per 100 m of sidewalk")
    bush_rate: float = Field(0.0, ge=0, description="bushes per 100 m of lot side")


_PRESETS: dict[str, dict] = {
    "downtown": {},
    "suburban": dict(
        block_size=(60.0, 100.0),
        lanes_per_direction=1,
        parking_width=2.2,
        sidewalk_width=2.5,
        max_slope=0.04,
        frontage=0.45,
        building_width=(8.0, 15.0),
        building_height=(5.0, 9.0),
        building_depth=(8.0, 14.0),
        setback=(4.0, 9.0),
        gap=(4.0, 14.0),
        wall_prob=0.15,
        fence_prob=0.45,
        front_fences=0.4,
        street_light_spacing=30.0,
        street_light_prob=0.8,
        sign_rate=1.5,
        tree_spacing=12.0,
        tree_prob=0.65,
        yard_tree_rate=3.0,
        car_prob=0.3,
        clutter_rate=2.0,
        bush_rate=4.0,
    ),
    "open-road": dict(
        n_blocks_x=2,
        n_blocks_y=2,
        block_size=(110.0, 160.0),
        lanes_per_direction=1,
        parking_width=2.5,  # a wide shoulder: the odd parked car stays out of the lane
        sidewalk_width=0.0,
        max_slope=0.03,
        margin=120.0,
        frontage=0.12,
        building_width=(8.0, 20.0),
        building_height=(4.0, 8.0),
        building_depth=(8.0, 15.0),
        setback=(8.0, 25.0),
        gap=(20.0, 60.0),
        wall_prob=0.05,
        fence_prob=0.5,
        fence_height=(1.0, 1.5),
        street_light_spacing=60.0,
        street_light_prob=0.25,
        sign_rate=2.0,
        tree_spacing=25.0,
        tree_prob=0.3,
        yard_tree_rate=1.0,
        utility_pole_spacing=35.0,
        utility_pole_prob=0.9,
        car_prob=0.03,
        clutter_rate=0.5,
        bush_rate=2.0,
    ),
}
_PRESETS["downtown"] = dict(
    n_blocks_x=4,
    n_blocks_y=4,
    block_size=(35.0, 60.0),
    lanes_per_direction=2,
    lane_width=3.3,
    parking_width=2.3,
    sidewalk_width=4.0,
    max_slope=0.02,
    frontage=0.8,
    # narrow, individually set-back buildings: an articulated street wall with many facades
    building_width=(6.0, 18.0),
    building_height=(10.0, 40.0),
    building_depth=(10.0, 18.0),
    setback=(0.0, 4.0),
    gap=(2.0, 8.0),
    street_light_spacing=25.0,
    street_light_prob=0.8,
    sign_rate=3.0,
    tree_spacing=18.0,
    tree_prob=0.25,
    car_prob=0.6,
    clutter_rate=4.0,
)

STYLES: tuple[str, ...] = tuple(_PRESETS)


def world_preset(style: str) -> WorldConfig:
    """The named preset ``downtown`` | ``suburban`` | ``open-road`` as a WorldConfig."""
    key = style.replace("_", "-").lower()
    if key == "openroad":
        key = "open-road"
    if key not in _PRESETS:
        raise InvalidInputError(f"unknown world style {style!r}; choose one of {list(_PRESETS)}")
    return WorldConfig(style=key, **_PRESETS[key])


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
        self.nv = 0
        self.next_instance = 1
        self.landmarks: list[dict] = []

    def new_instance(self) -> int:
        i = self.next_instance
        self.next_instance += 1
        if self.next_instance >= 1 << 16:
            raise InvalidInputError("world has more than 65535 object instances")
        return i

    def add(self, V: NDArray, F: NDArray, cls, inst, lm=-1) -> None:
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


# ---- the world ---------------------------------------------------------------------------
@dataclass
class World:
    """Labelled triangle soup plus the layout the trajectory planner needs.

    vertices (V, 3) float32 and triangles (M, 3) uint32 in the world frame [m];
    tri_class (M,) uint16 SemanticKITTI class; tri_instance (M,) uint32 instance id (0 = stuff);
    tri_landmark (M,) int32 index into ``landmarks`` or -1.
    street_x / street_y: centre lines of the streets running along y / along x.
    """

    config: WorldConfig
    seed: int
    vertices: NDArray[np.float32]
    triangles: NDArray[np.uint32]
    tri_class: NDArray[np.uint16]
    tri_instance: NDArray[np.uint32]
    tri_landmark: NDArray[np.int32]
    landmarks: LandmarkSet
    street_x: NDArray[np.float64]
    street_y: NDArray[np.float64]
    knots_x: NDArray[np.float64]
    heights_x: NDArray[np.float64]
    knots_y: NDArray[np.float64]
    heights_y: NDArray[np.float64]

    @property
    def road_half_width(self) -> float:
        c = self.config
        return c.lanes_per_direction * c.lane_width + c.parking_width

    @property
    def corner_half_width(self) -> float:
        """Half the size of an intersection including its sidewalks."""
        return self.road_half_width + self.config.sidewalk_width

    def lane_offset(self, lane: int) -> float:
        """Lateral offset of lane ``lane`` (0 = innermost) right of the street centre line."""
        return (lane + 0.5) * self.config.lane_width

    def ground_height(self, x, y) -> NDArray:
        """Road-surface height at (x, y); sidewalks and lots are CURB_HEIGHT higher."""
        return _pwl(x, self.knots_x, self.heights_x) + _pwl(y, self.knots_y, self.heights_y)

    def ground_gradient(self, x, y) -> NDArray:
        """(..., 2) slopes dh/dx, dh/dy of the road surface."""
        return np.stack(
            [
                _pwl_slope(x, self.knots_x, self.heights_x),
                _pwl_slope(y, self.knots_y, self.heights_y),
            ],
            axis=-1,
        )

    @cached_property
    def scene(self):
        """Open3D/Embree raycasting scene (built once, on first use)."""
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(self.vertices)),
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(self.triangles)),
        )
        # Embree builds its BVH lazily on the first query: do it now, not inside scan 0
        scene.cast_rays(o3d.core.Tensor(np.array([[0, 0, 100, 0, 0, -1]], np.float32)))
        return scene

    def to_open3d(self):
        """Legacy Open3D TriangleMesh coloured by class (for viewing)."""
        import open3d as o3d

        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.vertices.astype(float)),
            o3d.utility.Vector3iVector(self.triangles.astype(np.int32)),
        )
        # objects do not share vertices, so a vertex takes the class colour of its triangles
        colours = np.full((len(self.vertices), 3), 0.5)
        for k in range(3):
            colours[self.triangles[:, k]] = CLASS_COLOURS.get_many(self.tri_class)
        mesh.vertex_colors = o3d.utility.Vector3dVector(colours)
        mesh.compute_vertex_normals()
        return mesh

    def summary(self) -> dict:
        c = self.landmarks.attributes["category"] if len(self.landmarks) else np.zeros(0)
        cats = {k: int(np.sum(c == v)) for k, v in CATEGORIES.items()}
        return {
            "style": self.config.style,
            "seed": self.seed,
            "triangles": len(self.triangles),
            "instances": int(self.tri_instance.max(initial=0)),
            "landmarks": cats,
        }


def _pwl(x, knots: NDArray, values: NDArray) -> NDArray:
    """Piecewise-linear function; the end knots lie 200 m beyond the world's terrain, so
    interpolation (np.interp, fast for scalars too) covers every place that exists."""
    return np.interp(x, knots, values)


def _pwl_slope(x, knots: NDArray, values: NDArray) -> NDArray:
    x = np.asarray(x, float)
    i = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, len(knots) - 2)
    return (values[i + 1] - values[i]) / (knots[i + 1] - knots[i])


def build_world(config: WorldConfig | str = "downtown", seed: int = 0) -> World:
    """Generate the world of ``config`` (or a preset name) deterministically from ``seed``."""
    cfg = world_preset(config) if isinstance(config, str) else config
    if cfg.block_size[0] > cfg.block_size[1] or cfg.block_size[0] <= 5.0:
        raise InvalidInputError("block_size must be an increasing range above 5 m")
    rng = np.random.default_rng([int(seed), 0x5EED])
    return _Generator(cfg, rng, int(seed)).run()


class _Generator:
    """One-shot world generation; Python loops run over objects (hundreds), never points."""

    def __init__(self, cfg: WorldConfig, rng: np.random.Generator, seed: int) -> None:
        self.cfg, self.rng, self.seed = cfg, rng, seed
        # Block character comes from its own stream, so worlds without block variation keep
        # exactly the draws (and bytes) they had before it existed.
        self.block_rng = np.random.default_rng([seed, 0xB10C])
        self.mb = _MeshBuilder()
        self.hw = cfg.lanes_per_direction * cfg.lane_width + cfg.parking_width
        self.cw = self.hw + cfg.sidewalk_width

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

    def run(self) -> World:
        cfg = self.cfg
        self.X = self._streets(cfg.n_blocks_x)
        self.Y = self._streets(cfg.n_blocks_y)
        self.kx, self.vx = self._ground_fn(self.X)
        self.ky, self.vy = self._ground_fn(self.Y)
        self._ground()
        for i in range(len(self.X) - 1):
            for j in range(len(self.Y) - 1):
                self._block(i, j)
        self._street_furniture()
        mb = self.mb
        V = np.concatenate(mb.V).astype(np.float32)
        F = np.concatenate(mb.F).astype(np.uint32)
        return World(
            config=cfg, seed=self.seed, vertices=V, triangles=F,
            tri_class=np.concatenate(mb.cls), tri_instance=np.concatenate(mb.inst),
            tri_landmark=np.concatenate(mb.lm), landmarks=mb.landmark_set(),
            street_x=self.X, street_y=self.Y, knots_x=self.kx, heights_x=self.vx,
            knots_y=self.ky, heights_y=self.vy,
        )  # fmt: skip

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
        while pos < s1 - 4.0:
            if self.rng.random() < frontage:
                w = min(self.u(cfg.building_width), s1 - pos)
                if w < 6.0:
                    break
                sb = self.u(cfg.setback)
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

    # -- pole-like objects, cars, clutter along every street side -----------------------------
    def _street_furniture(self) -> None:
        """Walk both sides of every street segment between intersections."""
        for axis in (0, 1):  # 0: streets along y at x = X[i]; 1: streets along x at y = Y[j]
            centres = self.X if axis == 0 else self.Y
            cross = self.Y if axis == 0 else self.X
            for c in centres:
                for k in range(len(cross) - 1):
                    s0, s1 = cross[k] + self.cw, cross[k + 1] - self.cw
                    for side in (-1.0, 1.0):
                        self._segment_side(axis, c, side, s0, s1)

    def _xy(self, axis: int, c: float, side: float, s, u):
        """World (x, y) of along-street coordinate s and lateral distance u from the centre."""
        if axis == 0:
            return c + side * u, s
        return s, c + side * u

    def _segment_side(self, axis: int, c: float, side: float, s0: float, s1: float) -> None:
        cfg, rng = self.cfg, self.rng
        L = s1 - s0
        taken: list[float] = []
        sw = cfg.sidewalk_width
        pole_u = self.hw + (0.6 if sw >= 1.5 else 1.0)

        def free(s: float, gap: float = 2.0) -> bool:
            return all(abs(s - t) > gap for t in taken)

        def slots(spacing: float, lo: float, margin: float) -> NDArray:
            """Regular slots with +-15% jitter: planted rows are regular, but not exactly."""
            base = np.arange(s0 + rng.uniform(lo, max(lo + 0.1, spacing / 2)), s1 - margin, spacing)
            return np.clip(base + rng.uniform(-0.15, 0.15, len(base)) * spacing, s0 + 0.5, s1 - 0.5)

        # street lights (arm toward the road)
        for s in slots(cfg.street_light_spacing, 2.0, 2.0):
            if rng.random() < cfg.street_light_prob:
                taken.append(s)
                self._street_light(axis, c, side, s, pole_u)
        for s in slots(cfg.utility_pole_spacing, 2.0, 2.0):
            if side > 0 and rng.random() < cfg.utility_pole_prob and free(s):
                taken.append(s)
                x, y = self._xy(axis, c, side, s, self.cw + 1.5)
                r, hgt = self.u((0.12, 0.18)), self.u((8.0, 11.0))
                self._pole((x, y), r, hgt, POLE, "utility_pole", arm=(axis, side, 1.2, 0.4))
        p_tree = cfg.tree_prob
        if cfg.tree_prob_spread > 0:
            d = self.block_rng.uniform(-cfg.tree_prob_spread, cfg.tree_prob_spread)
            p_tree = float(np.clip(p_tree + d, 0.0, 1.0))
        for s in slots(cfg.tree_spacing, 1.0, 1.5):
            if rng.random() < p_tree and free(s):
                taken.append(s)
                u = self.hw + (sw * 0.6 if sw >= 2.0 else sw + 2.0)
                self._tree(self._xy(axis, c, side, s, u), trunk_radius=self.u((0.1, 0.25)))
        for _ in range(rng.poisson(cfg.sign_rate * L / 100)):
            s = rng.uniform(s0 + 0.5, s1 - 0.5)
            if free(s, 1.0):
                taken.append(s)
                self._sign(axis, c, side, s, self.hw + 0.35)
        # parked cars
        if cfg.parking_width >= 1.0 and cfg.car_prob > 0:
            s = s0 + rng.uniform(0.5, 3.0)
            while s < s1 - 5.0:
                length = self.u((3.8, 4.9))
                if rng.random() < cfg.car_prob:
                    self._car(
                        axis, c, side, s + length / 2, self.hw - cfg.parking_width / 2 - 0.1, length
                    )
                s += length + self.u((0.6, 2.0))
        # clutter on the sidewalk (or shoulder)
        for _ in range(rng.poisson(cfg.clutter_rate * L / 100)):
            s = rng.uniform(s0 + 0.5, s1 - 0.5)
            if not free(s, 1.0):
                continue
            u = self.hw + (
                rng.uniform(0.3, max(0.4, sw - 0.5)) if sw >= 1.0 else rng.uniform(0.5, 2.5)
            )
            self._clutter(self._xy(axis, c, side, s, u))

    def _pole(
        self, xy, radius: float, height: float, cls: int, category: str, arm=None, inst=None
    ) -> int:
        """A vertical GT pole standing on the raised ground; returns its instance id."""
        x, y = xy
        zg = float(self.h(x, y)) + CURB_HEIGHT
        base = np.array([x, y, zg - 0.2])
        inst = inst or self.mb.new_instance()
        V, F = _cylinder(base, radius, height + 0.2, n_seg=12 if radius > 0.06 else 8)
        k = self.mb.add_pole((x, y, zg), radius, height, cls, category, inst)
        n_side = 2 * (12 if radius > 0.06 else 8)
        lm = np.full(len(F), -1, np.int32)
        lm[:n_side] = k
        self.mb.add(V, F, cls, inst, lm)
        if arm is not None:
            axis, side, length, drop = arm
            d = -side  # toward the street centre
            top = zg + height
            t = 0.06
            if axis == 0:
                lo, hi = (
                    (min(x, x + d * length), y - t, top - drop - t),
                    (max(x, x + d * length), y + t, top - drop + t),
                )
            else:
                lo, hi = (
                    (x - t, min(y, y + d * length), top - drop - t),
                    (x + t, max(y, y + d * length), top - drop + t),
                )
            V, F = _box(np.array(lo), np.array(hi))
            self.mb.add(V, F, cls, inst)
        return inst

    def _street_light(self, axis, c, side, s, u) -> None:
        x, y = self._xy(axis, c, side, s, u)
        r, hgt = self.u((0.08, 0.14)), self.u((6.0, 10.0))
        arm = self.u((0.8, 2.0))
        inst = self._pole((x, y), r, hgt, POLE, "street_light", arm=(axis, side, arm, 0.25))
        # lamp head at the arm tip
        hx, hy = self._xy(axis, c, side, s, u - arm)
        zt = float(self.h(x, y)) + CURB_HEIGHT + hgt - 0.25
        V, F = _box(
            np.array([hx - 0.3, hy - 0.3, zt - 0.25]), np.array([hx + 0.3, hy + 0.3, zt + 0.05])
        )
        self.mb.add(V, F, POLE, inst)

    def _sign(self, axis, c, side, s, u) -> None:
        x, y = self._xy(axis, c, side, s, u)
        r, hgt = self.u((0.03, 0.05)), self.u((2.2, 3.2))
        inst = self._pole((x, y), r, hgt, POLE, "sign_post")
        zt = float(self.h(x, y)) + CURB_HEIGHT + hgt
        w, hh, t = self.u((0.5, 0.9)), self.u((0.5, 0.8)), 0.03
        # the plate faces traffic: its normal is along the street
        if axis == 0:
            lo, hi = (x - w / 2, y + r, zt - hh), (x + w / 2, y + r + t, zt)
        else:
            lo, hi = (x + r, y - w / 2, zt - hh), (x + r + t, y + w / 2, zt)
        V, F = _box(np.array(lo), np.array(hi))
        self.mb.add(V, F, TRAFFIC_SIGN, inst)

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

    def _clutter(self, xy) -> None:
        x, y = xy
        zg = float(self.h(x, y)) + CURB_HEIGHT
        inst = self.mb.new_instance()
        kind = self.rng.integers(4)
        if kind == 0:  # bin
            a = self.u((0.4, 0.7))
            V, F = _box(
                np.array([x - a / 2, y - a / 2, zg - 0.1]),
                np.array([x + a / 2, y + a / 2, zg + self.u((0.8, 1.2))]),
            )
        elif kind == 1:  # bench / box
            a, b = self.u((0.5, 2.0)), self.u((0.4, 0.8))
            V, F = _box(
                np.array([x - a / 2, y - b / 2, zg - 0.1]),
                np.array([x + a / 2, y + b / 2, zg + self.u((0.4, 0.9))]),
            )
        elif kind == 2:  # bollard: a short pole that is NOT a landmark
            V, F = _cylinder(
                np.array([x, y, zg - 0.1]), self.u((0.07, 0.12)), self.u((0.7, 1.0)), 8
            )
        else:  # hydrant / post box
            V, F = _cylinder(
                np.array([x, y, zg - 0.1]), self.u((0.15, 0.3)), self.u((0.6, 1.3)), 10
            )
        self.mb.add(V, F, OTHER_OBJECT, inst)
