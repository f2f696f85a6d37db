"""World statistics: the ``WorldConfig`` model and the named style presets."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from graffmatch.errors import InvalidInputError


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
    # realism (off in the style presets: the ``ideal`` worlds; see simulator/realism.py)
    facade_detail: bool = Field(
        False,
        description="windows (glass: dropouts and returns from inside), sills, pilasters, "
        "balconies and shop signs on the facades, so that facades are rough as in real scans",
    )
    facade_roughness_m: float = Field(
        0.0,
        ge=0,
        description="sigma of sub-resolution relief on buildings, walls and fences (brick, "
        "render, frames, downpipes), added along the ray by the sensor [m]",
    )
    balcony_prob: float = Field(0.0, ge=0, le=1, description="P(balcony) per upper-floor window")
    shop_sign_prob: float = Field(0.0, ge=0, le=1, description="P(shop sign) per ground-floor bay")
    shop_front_prob: float = Field(
        1.0,
        ge=0,
        le=1,
        description="with facade_detail: P(a street face's ground floor is a shop front, glass "
        "across most of each bay); other ground floors get ordinary windows, as houses do",
    )
    leafy_vegetation: bool = Field(
        False,
        description="canopies, bushes and hedges of foliage: rays return from a random depth "
        "inside them (scattered returns), not from a closed surface",
    )
    hedge_prob: float = Field(
        0.0, ge=0, le=1, description="P(hedge) per stretch of lot edge behind the sidewalk"
    )
    facade_relief_m: float = Field(
        0.0,
        ge=0,
        description="sigma of the depth of panel-sized relief on buildings, walls and fences "
        "(cladding and siding panels, recessed bands, render undulations), added along the "
        "ray by the sensor: unlike facade_roughness_m it is the same in every scan and survives "
        "the front end's voxel averaging [m]",
    )
    facade_relief_cell_m: float = Field(
        1.0, gt=0.1, description="size of a relief panel along the surface [m]"
    )
    building_line: bool = Field(
        False,
        description="the buildings of a block side share one building line (its setback, drawn "
        "once per side) within +-building_line_jitter, as streets are built: adjacent facades "
        "form one long, stepped street wall instead of one plane per building",
    )
    building_line_jitter: float = Field(
        0.1, ge=0, description="half-range of each building's offset from its side's line [m]"
    )
    parked_car_scatter: bool = Field(
        False,
        description="parked cars stand 0-0.5 m from the curb line and up to ~4 deg askew, with "
        "glass cabins: a row of them is not one flat wall",
    )


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
