"""How real a simulated drive looks: the ``ideal`` and ``realistic`` presets (issue 13).

``ideal`` is the clean simulator the benchmark started with: flat facades, closed-mesh
vegetation, one pose per sweep, a static world, exact labels and poses. ``realistic`` is
calibrated against KITTI 00 with ``bench/simulator_realism.py`` (docs/simulator.md has the
table): rough facades, foliage, hedges, more parked cars and trees (occlusion), moving cars
and pedestrians, motion distortion within the sweep (raw scans: de-skew them with
``motion.deskew_scan``) and label noise. ``kitti-gt`` is how KITTI odometry ships its data:
ground-truth poses with GPS/INS-like errors, and scans already de-skewed with those poses.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.datasets.simulator.mesh import (
    BUILDING,
    CAR,
    OTHER_OBJECT,
    POLE,
    TRAFFIC_SIGN,
    TRUNK,
    VEGETATION,
)
from graffmatch.errors import InvalidInputError


class RealismConfig(BaseModel):
    """What a simulated drive adds to the ideal world and sensor."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field("custom", description="preset name")
    world: dict[str, Any] = Field(
        default_factory=dict, description="WorldConfig overrides for every style"
    )
    style_world: dict[str, dict[str, Any]] = Field(
        default_factory=dict, description="further WorldConfig overrides per style"
    )
    trajectory: dict[str, Any] = Field(
        default_factory=dict, description="TrajectoryConfig overrides (e.g. slowing in curves)"
    )
    motion_distortion: bool = Field(
        False, description="cast each column from the moving sensor's pose at its time"
    )
    deskew: bool = Field(
        False,
        description="write scans de-skewed with the written poses, as KITTI odometry's scans "
        "are (imperfectly, when those poses carry GT noise)",
    )
    moving_cars_per_km: float = Field(0.0, ge=0, description="moving cars per km of lane")
    pedestrians_per_km: float = Field(0.0, ge=0, description="pedestrians per km of sidewalk")
    label_miss: float = Field(
        0.0, ge=0, le=1, description="fraction of pole/sign/trunk points labelled as their surroundings"
    )
    label_swap: float = Field(
        0.0, ge=0, le=1, description="P(a whole pole-like object is labelled building/vegetation)"
    )
    label_false: float = Field(
        0.0, ge=0, le=1, description="P(a clutter object or parked car is labelled pole)"
    )
    gt_pose_noise_m: float = Field(0.0, ge=0, description="GT position error sigma per axis [m]")
    gt_pose_noise_deg: float = Field(0.0, ge=0, description="GT rotation error sigma per axis")

    def world_overrides(self, style: str) -> dict[str, Any]:
        return {**self.world, **self.style_world.get(style, {})}

    @property
    def is_ideal(self) -> bool:
        return self == RealismConfig(name=self.name)


_REALISTIC = dict(
    world=dict(
        facade_detail=True,
        facade_roughness_m=0.04,
        balcony_prob=0.25,
        shop_sign_prob=0.4,
        leafy_vegetation=True,
        # panel-sized relief (cladding, siding, recessed bands): KITTI's walls are 5-6 cm RMS
        # after the front end's 0.4 m voxels, which per-point roughness alone never gives
        facade_relief_m=0.04,
        facade_relief_cell_m=1.0,
        parked_car_scatter=True,
    ),
    style_world={
        "downtown": dict(
            car_prob=0.85, tree_prob=0.55, clutter_rate=8.0, sidewalk_width=3.0,
            street_light_prob=0.5, sign_rate=1.5, building_width=(14.0, 35.0),
            hedge_prob=0.3,
            # one stepped street wall per block side, shops on most ground floors
            building_line=True, shop_front_prob=0.7,
        ),
        "suburban": dict(
            car_prob=0.55, bush_rate=8.0, clutter_rate=4.0, street_light_prob=0.4, tree_prob=0.45,
            hedge_prob=0.5, shop_front_prob=0.0,
        ),
        "open-road": dict(car_prob=0.1, bush_rate=4.0, shop_front_prob=0.0),
    },
    # a car slows to ~4 m/s at a crossing and ~1.5 m/s in a U-turn (the ideal route keeps
    # 10 m/s: 70 deg of yaw between two scans in a U-turn, which no odometry survives)
    trajectory=dict(max_lateral_accel=2.0),
    motion_distortion=True,
    moving_cars_per_km=6.0,
    pedestrians_per_km=15.0,
    label_miss=0.1,
    label_swap=0.05,
    label_false=0.03,
)

REALISM_PRESETS: dict[str, RealismConfig] = {
    "ideal": RealismConfig(name="ideal"),
    "realistic": RealismConfig(name="realistic", **_REALISTIC),
    "kitti-gt": RealismConfig(
        name="kitti-gt", **_REALISTIC, gt_pose_noise_m=0.35, gt_pose_noise_deg=0.25, deskew=True
    ),
}


def get_realism(realism: str | RealismConfig | None) -> RealismConfig:
    """A preset by name (``ideal`` | ``realistic`` | ``kitti-gt``) or the config itself."""
    if realism is None:
        return REALISM_PRESETS["ideal"]
    if isinstance(realism, RealismConfig):
        return realism
    key = str(realism).lower().replace("_", "-")
    if key not in REALISM_PRESETS:
        raise InvalidInputError(
            f"unknown realism preset {realism!r}; choose one of {list(REALISM_PRESETS)}"
        )
    return REALISM_PRESETS[key]


_POLE_LIKE = np.array([POLE, TRAFFIC_SIGN, TRUNK])


def noisy_labels(labels: NDArray, cfg: RealismConfig, rng: np.random.Generator) -> NDArray:
    """Labels as a semantic segmentation network would give them: some pole points missed,
    some pole-like objects labelled as their surroundings, some clutter and cars as poles."""
    lab = np.asarray(labels, np.uint32).copy()
    if cfg.label_miss <= 0 and cfg.label_swap <= 0 and cfg.label_false <= 0:
        return lab
    cls = lab & np.uint32(0xFFFF)
    inst = lab >> np.uint32(16)
    pole_like = np.isin(cls, _POLE_LIKE)
    # what a missed pole point becomes: trunks melt into the canopy, posts into the facades
    other = np.where(cls == TRUNK, VEGETATION, BUILDING).astype(np.uint32)
    u_inst, inv = np.unique(inst, return_inverse=True)
    p_inst = rng.random(len(u_inst))[inv.reshape(-1)]  # one draw per object
    swap = pole_like & (p_inst < cfg.label_swap)
    miss = pole_like & (rng.random(len(lab)) < cfg.label_miss)
    false = np.isin(cls, [OTHER_OBJECT, CAR]) & (inst > 0) & (p_inst < cfg.label_false)
    new_cls = np.where(swap | miss, other, cls)
    new_cls = np.where(false, np.uint32(POLE), new_cls).astype(np.uint32)
    return (inst << np.uint32(16)) | new_cls
