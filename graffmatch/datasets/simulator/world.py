"""A procedural urban world made of labelled triangles, with its ground-truth landmarks.

The world is an axis-aligned street grid. Every triangle carries a SemanticKITTI class id, an
object instance id and (when it lies on one) the index of the ground-truth landmark it belongs
to, so that a ray hit knows both its label and the true pole/plane it sampled.

The generator is split by concept: ``config`` (styles), ``mesh`` (classes, primitives),
``layout`` (streets, ground, curbs), ``buildings``, ``furniture`` (poles, signs, clutter),
``vegetation`` and ``vehicles``. This module assembles them and holds the ``World`` result.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from graffmatch.datasets.simulator.buildings import BuildingsMixin
from graffmatch.datasets.simulator.config import STYLES, WorldConfig, world_preset
from graffmatch.datasets.simulator.facades import FacadeDetailMixin
from graffmatch.datasets.simulator.furniture import StreetFurnitureMixin
from graffmatch.datasets.simulator.layout import LayoutMixin, _pwl, _pwl_slope
from graffmatch.datasets.simulator.mesh import (
    BUILDING,
    CAR,
    CATEGORIES,
    CLASS_COLOURS,
    CURB_HEIGHT,
    FENCE,
    FOLIAGE,
    GLASS,
    OPAQUE,
    OTHER_OBJECT,
    POLE,
    ROAD,
    SIDEWALK,
    TERRAIN,
    TRAFFIC_SIGN,
    TRUNK,
    VEGETATION,
    _MeshBuilder,
)
from graffmatch.datasets.simulator.vegetation import VegetationMixin
from graffmatch.datasets.simulator.vehicles import VehiclesMixin
from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet

__all__ = [
    "BUILDING", "CAR", "CATEGORIES", "CLASS_COLOURS", "CURB_HEIGHT", "FENCE", "FOLIAGE", "GLASS", "OPAQUE", "OTHER_OBJECT",
    "POLE", "ROAD", "SIDEWALK", "STYLES", "TERRAIN", "TRAFFIC_SIGN", "TRUNK", "VEGETATION",
    "World", "WorldConfig", "build_world", "world_preset",
]  # fmt: skip


# ---- the world ---------------------------------------------------------------------------
@dataclass
class World:
    """Labelled triangle soup plus the layout the trajectory planner needs.

    vertices (V, 3) float32 and triangles (M, 3) uint32 in the world frame [m];
    tri_class (M,) uint16 SemanticKITTI class; tri_instance (M,) uint32 instance id (0 = stuff);
    tri_landmark (M,) int32 index into ``landmarks`` or -1; tri_material (M,) uint8
    (``mesh.OPAQUE``, ``mesh.GLASS`` or ``mesh.FOLIAGE``).
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
    tri_material: NDArray[np.uint8] | None = None

    def __post_init__(self) -> None:
        if self.tri_material is None:
            self.tri_material = np.zeros(len(self.triangles), np.uint8)

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


def build_world(config: WorldConfig | str = "downtown", seed: int = 0) -> World:
    """Generate the world of ``config`` (or a preset name) deterministically from ``seed``."""
    cfg = world_preset(config) if isinstance(config, str) else config
    if cfg.block_size[0] > cfg.block_size[1] or cfg.block_size[0] <= 5.0:
        raise InvalidInputError("block_size must be an increasing range above 5 m")
    rng = np.random.default_rng([int(seed), 0x5EED])
    return _Generator(cfg, rng, int(seed)).run()


class _Generator(LayoutMixin, BuildingsMixin, FacadeDetailMixin, StreetFurnitureMixin, VegetationMixin, VehiclesMixin):
    """One-shot world generation; Python loops run over objects (hundreds), never points."""

    def __init__(self, cfg: WorldConfig, rng: np.random.Generator, seed: int) -> None:
        self.cfg, self.rng, self.seed = cfg, rng, seed
        # Block character comes from its own stream, so worlds without block variation keep
        # exactly the draws (and bytes) they had before it existed.
        self.block_rng = np.random.default_rng([seed, 0xB10C])
        self.mb = _MeshBuilder()
        # Realism details (facade relief, leaves) draw from their own stream, so a world with
        # them has exactly the layout of the same world without them.
        self.detail_rng = np.random.default_rng([seed, 0xFACADE])
        self.hw = cfg.lanes_per_direction * cfg.lane_width + cfg.parking_width
        self.cw = self.hw + cfg.sidewalk_width

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
            knots_y=self.ky, heights_y=self.vy, tri_material=np.concatenate(mb.mat),
        )  # fmt: skip
