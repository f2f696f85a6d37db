"""A spinning multi-beam LiDAR simulated by ray casting the world with Open3D (Embree).

Each scan casts one ray per (beam, column) from the sensor origin; a ray returns the first
triangle hit. Range noise is Gaussian along the ray, so a returned point keeps the exact
elevation of its beam (which is what real spinning LiDARs do to first order). Rays drop out at
random, at grazing incidence, beyond the maximum range, and increasingly beyond half of it
for dark or oblique surfaces (weak echoes). Intensity is a Lambertian-ish reflectivity model:
a per-class albedo times the cosine of the incidence angle, fading with range. With ``sweep`` poses each azimuth column is cast from its own pose (motion distortion, see
``motion.py``); ``dynamic`` adds moving objects; glass (``mesh.GLASS``) drops many rays and
returns the rest from inside the building; foliage (``mesh.FOLIAGE``) returns from a random
depth inside the crown.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.datasets.simulator import world as W
from graffmatch.errors import InvalidInputError
from graffmatch.geometry.transforms import check_transform


class SensorProfile(BaseModel):
    """A spinning LiDAR: beam elevations, azimuth resolution, range limits and noise."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field("hdl64", description="profile name")
    n_beams: int = Field(64, ge=1, le=256, description="number of laser beams (rings)")
    elevation_blocks: tuple[tuple[float, float, int], ...] = Field(
        ((2.0, -8.33, 32), (-8.87, -24.9, 32)),
        description="beam elevations [deg] as blocks (first, last, count) spaced linearly; "
        "HDL-64E has a dense upper block and a sparse lower one",
    )
    n_columns: int = Field(2083, ge=16, description="azimuth steps per revolution")
    min_range: float = Field(2.5, ge=0.0, description="returns closer than this are dropped [m]")
    max_range: float = Field(120.0, gt=1.0, description="returns farther than this are dropped [m]")
    range_noise_std: float = Field(0.02, ge=0.0, description="Gaussian range noise sigma [m]")
    dropout_prob: float = Field(0.02, ge=0.0, lt=1.0, description="random per-ray dropout")
    grazing_cos: float = Field(
        0.03, ge=0.0, lt=1.0, description="rays hitting with |cos(incidence)| below this drop out"
    )
    intensity_noise_std: float = Field(0.03, ge=0.0, description="additive intensity noise")
    mount_height: float = Field(1.73, gt=0.0, description="sensor height above the road [m]")

    def beam_elevations_deg(self) -> NDArray[np.float64]:
        """(n_beams,) elevations in degrees, from the top beam down."""
        el = np.concatenate([np.linspace(a, b, int(n)) for a, b, n in self.elevation_blocks])
        if len(el) != self.n_beams:
            raise InvalidInputError(
                f"profile {self.name!r}: elevation blocks give {len(el)} beams, n_beams={self.n_beams}"
            )
        return el

    @property
    def azimuth_step_deg(self) -> float:
        return 360.0 / self.n_columns

    def ray_directions(self) -> NDArray[np.float32]:
        """(n_beams * n_columns, 3) unit rays in the sensor frame (x fwd, y left, z up)."""
        return _ray_directions(self.beam_elevations_deg().tobytes(), self.n_columns)


@lru_cache(maxsize=8)
def _ray_directions(elev_bytes: bytes, n_columns: int) -> NDArray[np.float32]:
    el = np.deg2rad(np.frombuffer(elev_bytes, dtype=np.float64))
    az = np.pi - np.arange(n_columns) * (2 * np.pi / n_columns)  # KITTI sweeps from behind
    ce, se = np.cos(el)[:, None], np.sin(el)[:, None]
    d = np.stack(
        [ce * np.cos(az)[None], ce * np.sin(az)[None], np.broadcast_to(se, (len(el), n_columns))],
        -1,
    ).reshape(-1, 3)
    d = d.astype(np.float32)
    d.setflags(write=False)
    return d


_COLUMNS_CACHE: dict[int, NDArray[np.float32]] = {}


def _columns(d: NDArray[np.float32]) -> NDArray[np.float32]:
    """(3, N) contiguous copy of the cached (N, 3) ray directions."""
    key = id(d)
    if key not in _COLUMNS_CACHE:
        _COLUMNS_CACHE.clear() if len(_COLUMNS_CACHE) > 8 else None
        _COLUMNS_CACHE[key] = np.ascontiguousarray(d.T)
    return _COLUMNS_CACHE[key]


PROFILES: dict[str, SensorProfile] = {
    "hdl64": SensorProfile(),
    "vlp16": SensorProfile(
        name="vlp16",
        n_beams=16,
        elevation_blocks=((15.0, -15.0, 16),),
        n_columns=1800,
        min_range=1.0,
        max_range=100.0,
        range_noise_std=0.03,
    ),
    "os1-64": SensorProfile(
        name="os1-64",
        n_beams=64,
        elevation_blocks=((22.5, -22.5, 64),),
        n_columns=2048,
        min_range=1.0,
        max_range=120.0,
        range_noise_std=0.015,
    ),
}


def get_profile(profile: str | SensorProfile) -> SensorProfile:
    if isinstance(profile, SensorProfile):
        return profile
    key = str(profile).lower().replace("_", "-")
    aliases = {
        "hdl-64": "hdl64",
        "hdl-64e": "hdl64",
        "vlp-16": "vlp16",
        "os1": "os1-64",
        "os164": "os1-64",
    }
    key = aliases.get(key, key)
    if key not in PROFILES:
        raise InvalidInputError(
            f"unknown sensor profile {profile!r}; choose one of {list(PROFILES)}"
        )
    return PROFILES[key]


#: Albedo per SemanticKITTI class, used by the intensity model (signs are retro-reflective).
_ALBEDO = np.full(256, 0.35, np.float32)
for _cls, _alb in {
    W.ROAD: 0.22, W.SIDEWALK: 0.32, W.TERRAIN: 0.38, W.BUILDING: 0.42, W.FENCE: 0.30,
    W.VEGETATION: 0.48, W.TRUNK: 0.30, W.POLE: 0.50, W.TRAFFIC_SIGN: 0.95, W.CAR: 0.28,
    W.OTHER_OBJECT: 0.40, 252: 0.28, 254: 0.35,
}.items():  # fmt: skip
    _ALBEDO[_cls] = _alb


#: Scales the echo so that mean intensities resemble KITTI's HDL-64E (about 0.3).
_INTENSITY_GAIN = np.float32(2.0)


def _triangle_albedo(world: W.World) -> NDArray[np.float32]:
    """Per-triangle albedo: the class albedo varied +-15% per object instance (cached)."""
    cached = world.__dict__.get("_albedo")
    if cached is None:
        inst = world.tri_instance.astype(np.uint64)
        jitter = ((inst * np.uint64(2654435761)) % np.uint64(1000)).astype(np.float32) / 1000.0
        cached = (_ALBEDO[world.tri_class] * (0.85 + 0.3 * jitter)).astype(np.float32)
        world.__dict__["_albedo"] = cached
    return cached


def render_scan(
    world: W.World,
    T_world_lidar: NDArray,
    profile: str | SensorProfile = "hdl64",
    rng: np.random.Generator | int | None = None,
    return_landmarks: bool = False,
    sweep: NDArray | None = None,
    dynamic: tuple | None = None,
):
    """Scan ``world`` from pose ``T_world_lidar``.

    Returns ``(points (N, 4) float32 [x y z intensity] in the sensor frame, labels (N,) uint32)``
    with label = (instance << 16) | class; with ``return_landmarks`` also ``(N,) int32`` indices of
    the GT landmark each point sampled (-1 for none), for checking extraction.
    ``sweep``: (n_columns, 4, 4) pose of each azimuth column (motion distortion; points stay
    in the frame of the pose they were taken from, as a real raw scan). ``dynamic``:
    (vertices, triangles, tri_class, tri_instance) of moving objects at this scan's time.
    """
    import open3d as o3d

    prof = get_profile(profile)
    T = check_transform(T_world_lidar, "T_world_lidar")
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    d_sensor = prof.ray_directions()
    R, t = T[:3, :3], T[:3, 3]
    rays = np.empty((len(d_sensor), 6), np.float32)
    dT = _columns(d_sensor)
    if sweep is None:
        rays[:, :3] = t
        # column-wise rotation: a BLAS matmul with a 3-wide inner dimension is slow (and spins
        # threads on a loaded machine); nine fused vector ops are ~50x faster here
        for k in range(3):
            rays[:, 3 + k] = R[k, 0] * dT[0] + R[k, 1] * dT[1] + R[k, 2] * dT[2]
    else:
        S = np.asarray(sweep, float)
        if S.shape != (prof.n_columns, 4, 4):
            raise InvalidInputError(f"sweep must be ({prof.n_columns}, 4, 4), got {S.shape}")
        # rays are beam-major: ray k is column k % n_columns; per-column rotations broadcast
        # over the beams (no (N, 3, 3) copy)
        Rc = S[:, :3, :3]
        rays[:, :3] = np.tile(S[:, :3, 3], (prof.n_beams, 1))
        shape = (prof.n_beams, prof.n_columns)
        d0, d1, d2 = (dT[j].reshape(shape) for j in range(3))
        for k in range(3):
            rays[:, 3 + k] = (Rc[:, k, 0] * d0 + Rc[:, k, 1] * d1 + Rc[:, k, 2] * d2).reshape(-1)
    ans = world.scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
    t_hit = ans["t_hit"].numpy()
    prim = ans["primitive_ids"].numpy()
    normals = ans["primitive_normals"].numpy()
    albedo, tri_cls, tri_inst = _triangle_albedo(world), world.tri_class, world.tri_instance
    tri_lm, tri_mat = world.tri_landmark, world.tri_material
    if dynamic is not None:
        t_hit, prim, normals, albedo, tri_cls, tri_inst, tri_lm, tri_mat = _with_dynamic(
            rays, dynamic, t_hit, prim, normals, albedo, tri_cls, tri_inst, tri_lm, tri_mat
        )
    hit = np.isfinite(t_hit) & (t_hit >= prof.min_range) & (t_hit <= prof.max_range)
    idx = np.flatnonzero(hit)
    nT = normals[idx].T
    cos_inc = np.abs(nT[0] * rays[idx, 3] + nT[1] * rays[idx, 4] + nT[2] * rays[idx, 5])
    # the echo weakens with range and with dark, oblique surfaces: beyond half the maximum
    # range, returns fade out (quadratically) unless the surface is bright and square-on
    echo = albedo[prim[idx]] * (0.3 + 0.7 * cos_inc)
    far = np.clip((t_hit[idx] - 0.5 * prof.max_range) / (0.5 * prof.max_range), 0.0, 1.0)
    p_drop = prof.dropout_prob + far**2 * (1.0 - np.minimum(echo, 1.0))
    keep = (cos_inc >= prof.grazing_cos) & (rng.random(len(idx)) >= p_drop)
    idx, echo = idx[keep], echo[keep]
    r = t_hit[idx] + rng.normal(0.0, prof.range_noise_std, len(idx)).astype(np.float32)
    tri = prim[idx]
    lm_hit = tri_lm[tri]
    glass = tri_mat[tri] == W.GLASS
    if glass.any():
        # windows: 40 % of the rays return nothing, the rest from the room behind the pane
        # (a curtain or wall 0.3-3 m inside, fixed per pane, with furniture: 10 cm spread)
        g = np.flatnonzero(glass)
        gone = rng.random(len(g)) < 0.4
        pane = (tri[g].astype(np.uint64) // np.uint64(2)) * np.uint64(2654435761)
        depth = 0.3 + 2.7 * ((pane % np.uint64(1000)).astype(np.float32) / 1000.0)
        r[g] += (depth + rng.normal(0.0, 0.1, len(g))).astype(np.float32)
        lm_hit = np.where(glass, -1, lm_hit)
        keep = np.ones(len(idx), bool)
        keep[g[gone]] = False
        idx, echo, r, tri, lm_hit = idx[keep], echo[keep], r[keep], tri[keep], lm_hit[keep]
        echo = echo * np.where(glass[keep], 0.5, 1.0).astype(np.float32)
    foliage = tri_mat[tri] == W.FOLIAGE
    if foliage.any():
        # leaves: the echo comes from a leaf at an exponential depth (mean 0.5 m) into the
        # crown, and 15 % of the rays find a gap and return nothing
        f = np.flatnonzero(foliage)
        r[f] += np.minimum(rng.exponential(0.5, len(f)), 2.0).astype(np.float32)
        keep = np.ones(len(idx), bool)
        keep[f[rng.random(len(f)) < 0.15]] = False
        idx, echo, r, tri, lm_hit = idx[keep], echo[keep], r[keep], tri[keep], lm_hit[keep]
    cls = tri_cls[tri]
    inst = tri_inst[tri]
    rough = float(getattr(world.config, "facade_roughness_m", 0.0))
    if rough > 0:
        built = np.flatnonzero(np.isin(cls, (W.BUILDING, W.FENCE)))
        r[built] += rng.normal(0.0, rough, len(built)).astype(np.float32)
    relief = float(getattr(world.config, "facade_relief_m", 0.0))
    if relief > 0:
        built = np.flatnonzero(np.isin(cls, (W.BUILDING, W.FENCE)))
        r[built] += _panel_relief(
            rays[idx[built]], t_hit[idx[built]], normals[idx[built]], inst[built],
            relief, float(world.config.facade_relief_cell_m),
        )  # fmt: skip
    inten = _INTENSITY_GAIN * echo * (1.0 - 0.4 * r / prof.max_range)
    inten = inten + rng.normal(0.0, prof.intensity_noise_std, len(idx)).astype(np.float32)
    pts = np.empty((len(idx), 4), np.float32)
    dT = dT[:, idx]
    pts[:, 0], pts[:, 1], pts[:, 2] = dT[0] * r, dT[1] * r, dT[2] * r
    pts[:, 3] = np.clip(inten, 0.0, 1.0)
    labels = (inst.astype(np.uint32) << np.uint32(16)) | cls.astype(np.uint32)
    if return_landmarks:
        return pts, labels, lm_hit
    return pts, labels


def _panel_relief(
    rays: NDArray, t_hit: NDArray, normals: NDArray, inst: NDArray, sigma: float, cell: float
) -> NDArray[np.float32]:
    """Range offsets of hits on a surface with panel-sized relief (cladding, siding, recessed
    bands): the surface is cut into ``cell``-sized panels in its own plane, each standing out
    by a depth with standard deviation ``sigma``, fixed per (object, panel) so that every scan
    sees the same wall. A depth d along the normal is d / cos(incidence) along the ray."""
    pos = rays[:, :3] + t_hit[:, None] * rays[:, 3:]
    n = np.abs(normals)
    # the panel grid lies in the surface: drop the axis the normal points along
    drop = np.argmax(n, axis=1)
    keep_a = np.where(drop == 0, 1, 0)
    keep_b = np.where(drop == 2, 1, 2)
    rows = np.arange(len(pos))
    ia = np.floor(pos[rows, keep_a] / cell).astype(np.int64)
    ib = np.floor(pos[rows, keep_b] / cell).astype(np.int64)
    h = (
        ia.astype(np.uint64) * np.uint64(73856093)
        ^ ib.astype(np.uint64) * np.uint64(19349663)
        ^ drop.astype(np.uint64) * np.uint64(83492791)
        ^ np.asarray(inst, np.uint64) * np.uint64(2654435761)
    )
    h = (h ^ (h >> np.uint64(29))) * np.uint64(0xBF58476D1CE4E5B9)
    u = ((h >> np.uint64(40)).astype(np.float64) + 0.5) / float(1 << 24)  # uniform in (0, 1)
    depth = sigma * np.sqrt(12.0) * (u - 0.5)
    cos_inc = np.abs(np.einsum("ij,ij->i", normals, rays[:, 3:]))
    return (depth / np.maximum(cos_inc, 0.2)).astype(np.float32)


def _with_dynamic(rays, dynamic, t_hit, prim, normals, albedo, tri_cls, tri_inst, tri_lm, tri_mat):
    """Merge the first hits on moving objects (their own small scene) with the static ones;
    dynamic triangles get ids after the world's, and per-triangle arrays are extended."""
    import open3d as o3d

    V, F, dcls, dinst = dynamic
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor.from_numpy(np.ascontiguousarray(V, np.float32)),
        o3d.core.Tensor.from_numpy(np.ascontiguousarray(F, np.uint32)),
    )
    ans = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
    td = ans["t_hit"].numpy()
    closer = td < t_hit
    n_static = len(tri_cls)
    t_hit = np.where(closer, td, t_hit)
    prim = np.where(closer, ans["primitive_ids"].numpy().astype(np.int64) + n_static, prim)
    normals = np.where(closer[:, None], ans["primitive_normals"].numpy(), normals)
    albedo = np.concatenate([albedo, _ALBEDO[np.asarray(dcls) & 0xFF] * 0.9])
    tri_cls = np.concatenate([tri_cls, np.asarray(dcls, tri_cls.dtype)])
    tri_inst = np.concatenate([tri_inst, np.asarray(dinst, tri_inst.dtype)])
    tri_lm = np.concatenate([tri_lm, np.full(len(dcls), -1, tri_lm.dtype)])
    tri_mat = np.concatenate([tri_mat, np.zeros(len(dcls), tri_mat.dtype)])
    return t_hit, prim, normals, albedo, tri_cls, tri_inst, tri_lm, tri_mat
