"""A simulated extrinsic-calibration rig: chessboards seen by two LiDARs, or by an RGB + depth camera.

Why simulate: real calibration captures come without ground truth, so the only way to *measure*
the ≤ 1° / ≤ 5 cm bound of the issue (paper: 1.1°/8 cm and 0.9°/5 cm on real rigs) is a rig whose
extrinsic we chose. Everything is deterministic from a seed.

Geometry: each board is a planar rectangle with its own frame ``board``: origin at the centre of
the chessboard pattern, x along the inner-corner columns, y along the rows, z the normal. The
pattern (``cols+1`` x ``rows+1`` squares) is surrounded by a white margin so that OpenCV's
detector sees a quiet zone, and so that the board centre is the centre of the physical board:
the PnP plane anchor (camera) and the support-point anchor (LiDAR/depth) then name the same
physical point, which the anchor-shifted Grassmannian distance relies on.

Frames: every transform is ``T_<to>_<from>``; sensor frames follow the usual conventions
(LiDAR: x forward, z up; cameras: x right, y down, z forward / optical axis).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from graffmatch.errors import InvalidInputError
from graffmatch.geometry.landmarks import LandmarkSet, LandmarkType
from graffmatch.geometry.transforms import (
    invert,
    make_transform,
    rot_x,
    rot_y,
    rot_z,
    transform_points,
)

Array = NDArray[np.float64]


# ---------------------------------------------------------------------------------------
# Boards and scene
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Chessboard:
    """A chessboard target: inner-corner grid, square size and white margin [m]."""

    cols: int = 7
    rows: int = 5
    square: float = 0.1
    margin: float = 0.08

    def __post_init__(self) -> None:
        if self.cols < 2 or self.rows < 2 or self.square <= 0 or self.margin < 0:
            raise InvalidInputError(f"invalid chessboard {self}")

    @property
    def pattern_size(self) -> tuple[float, float]:
        """(width, height) of the black/white squares only [m]."""
        return (self.cols + 1) * self.square, (self.rows + 1) * self.square

    @property
    def size(self) -> tuple[float, float]:
        """(width, height) of the physical board including the margin [m]."""
        w, h = self.pattern_size
        return w + 2 * self.margin, h + 2 * self.margin

    def inner_corners(self) -> Array:
        """(cols*rows, 3) inner corners in the board frame, OpenCV order (row-major)."""
        xs = (np.arange(self.cols) - (self.cols - 1) / 2.0) * self.square
        ys = (np.arange(self.rows) - (self.rows - 1) / 2.0) * self.square
        X, Y = np.meshgrid(xs, ys)
        return np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)

    def outline(self) -> Array:
        """(4, 3) corners of the physical board in the board frame."""
        w, h = self.size
        return np.array(
            [[-w / 2, -h / 2, 0], [w / 2, -h / 2, 0], [w / 2, h / 2, 0], [-w / 2, h / 2, 0]]
        )

    def black_squares(self) -> Array:
        """(n, 4, 3) corners of the black squares in the board frame."""
        w, h = self.pattern_size
        i, j = np.meshgrid(np.arange(self.cols + 1), np.arange(self.rows + 1))
        black = ((i + j) % 2 == 0).ravel()
        x0 = (i.ravel()[black] * self.square) - w / 2
        y0 = (j.ravel()[black] * self.square) - h / 2
        s = self.square
        quad = np.array([[0, 0], [s, 0], [s, s], [0, s]])
        xy = np.stack([x0, y0], axis=1)[:, None, :] + quad[None]
        return np.concatenate([xy, np.zeros((*xy.shape[:2], 1))], axis=2)


@dataclass
class CalibrationScene:
    """Boards (and optionally a ground plane) in a world frame."""

    board: Chessboard
    T_world_boards: Array  # (n, 4, 4)
    ground_z: float | None = None  # world z of an infinite-ish ground plane, or None
    ground_half_size: float = 15.0
    walls: Array | None = None  # (k, 4, 3) extra background quads (world), e.g. a back wall

    def __post_init__(self) -> None:
        self.T_world_boards = np.asarray(self.T_world_boards, dtype=float).reshape(-1, 4, 4)
        if self.walls is not None:
            self.walls = np.asarray(self.walls, dtype=float).reshape(-1, 4, 3)

    @property
    def n_boards(self) -> int:
        return int(self.T_world_boards.shape[0])

    def board_outlines_world(self) -> Array:
        """(n, 4, 3) physical board corners in the world frame."""
        out = self.board.outline()
        return (
            np.einsum("nij,kj->nki", self.T_world_boards[:, :3, :3], out)
            + self.T_world_boards[:, None, :3, 3]
        )

    def board_planes(self, T_frame_world: Array | None = None) -> LandmarkSet:
        """Ground-truth board planes (anchor = board centre), in ``frame`` (default world)."""
        T = np.eye(4) if T_frame_world is None else np.asarray(T_frame_world, float)
        Tb = np.einsum("ij,njk->nik", T, self.T_world_boards)
        w, h = self.board.size
        n = self.n_boards
        return LandmarkSet.from_arrays(
            np.full(n, LandmarkType.PLANE),
            Tb[:, :3, 2],
            Tb[:, :3, 3],
            {"extent": np.full(n, w * h), "box": np.tile([w, h], (n, 1))},
        )

    def raycasting_scene(self) -> tuple[o3d.t.geometry.RaycastingScene, int]:
        """Open3D ray-casting scene; returns it and the geometry id of the ground (-1: none)."""
        scene = o3d.t.geometry.RaycastingScene()
        tris = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)
        for quad in self.board_outlines_world():
            scene.add_triangles(o3d.core.Tensor(quad.astype(np.float32)), o3d.core.Tensor(tris))
        ground_id = -1
        if self.ground_z is not None:
            s = self.ground_half_size
            g = np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]], float)
            g[:, 2] = self.ground_z
            ground_id = int(
                scene.add_triangles(o3d.core.Tensor(g.astype(np.float32)), o3d.core.Tensor(tris))
            )
        for quad in [] if self.walls is None else self.walls:
            scene.add_triangles(o3d.core.Tensor(quad.astype(np.float32)), o3d.core.Tensor(tris))
        return scene, ground_id


def _cast(scene: o3d.t.geometry.RaycastingScene, origins: Array, dirs: Array) -> Array:
    rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    return ans["t_hit"].numpy().astype(np.float64)


# ---------------------------------------------------------------------------------------
# LiDAR
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LidarModel:
    """A spinning multi-beam LiDAR (uniform beam elevations)."""

    n_beams: int = 64
    v_fov_deg: tuple[float, float] = (-25.0, 15.0)
    h_res_deg: float = 0.2
    max_range: float = 60.0
    range_noise: float = 0.015  # 1-sigma range noise [m]

    def ray_directions(self) -> Array:
        """(n_beams * n_azimuth, 3) unit ray directions in the LiDAR frame."""
        el = np.radians(np.linspace(self.v_fov_deg[0], self.v_fov_deg[1], self.n_beams))
        az = np.radians(np.arange(0.0, 360.0, self.h_res_deg))
        E, A = np.meshgrid(el, az, indexing="ij")
        return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(
            -1, 3
        )


VLP64 = LidarModel()
OS1_32 = LidarModel(n_beams=32, v_fov_deg=(-22.5, 22.5), h_res_deg=0.35, range_noise=0.015)


def simulate_lidar(
    scene: CalibrationScene, T_world_lidar: Array, model: LidarModel, rng: np.random.Generator
) -> NDArray[np.float32]:
    """Ray-cast one LiDAR sweep; returns (N, 3) float32 points in the LiDAR frame [m]."""
    dirs = model.ray_directions()
    R, t = T_world_lidar[:3, :3], T_world_lidar[:3, 3]
    rc, _ = scene.raycasting_scene()
    rng_hit = _cast(rc, np.broadcast_to(t, dirs.shape), dirs @ R.T)
    ok = np.isfinite(rng_hit) & (rng_hit < model.max_range)
    r = rng_hit[ok] + rng.normal(0.0, model.range_noise, int(ok.sum()))
    return (dirs[ok] * r[:, None]).astype(np.float32)


# ---------------------------------------------------------------------------------------
# Cameras
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics (no distortion) and image size [px]."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> Array:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> PinholeCamera:
        f = (width / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
        return cls(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)

    def project(self, P_cam: Array) -> Array:
        """(N, 3) camera-frame points -> (N, 2) pixel coordinates (x right, y down)."""
        P = np.asarray(P_cam, float)
        z = P[:, 2:3]
        return np.concatenate(
            [self.fx * P[:, :1] / z + self.cx, self.fy * P[:, 1:2] / z + self.cy], axis=1
        )

    def pixel_rays(self, step: int = 1) -> Array:
        """(H*W, 3) rays with z = 1 for every ``step``-th pixel (row-major)."""
        v, u = np.mgrid[0 : self.height : step, 0 : self.width : step]
        x = (u.ravel() - self.cx) / self.fx
        y = (v.ravel() - self.cy) / self.fy
        return np.stack([x, y, np.ones_like(x)], axis=1)


def render_chessboard_image(
    scene: CalibrationScene,
    T_world_camera: Array,
    camera: PinholeCamera,
    rng: np.random.Generator,
    noise_std: float = 3.0,
    blur_sigma: float = 0.7,
    supersample: int = 2,
) -> NDArray[np.uint8]:
    """Render the boards into a BGR uint8 image (painter's algorithm, anti-aliased).

    The board quads and black squares are straight-edged under a pinhole, so projecting their
    corners and filling convex polygons is exact; supersampling gives the sub-pixel edges the
    corner refiner needs, blur and Gaussian noise make detection realistic.
    """
    s = int(supersample)
    H, W = camera.height * s, camera.width * s
    # A mildly textured grey background so that the detector sees some clutter.
    sx = np.sin(np.arange(W, dtype=np.float32) / (37.0 * s))
    cy = np.cos(np.arange(H, dtype=np.float32) / (53.0 * s))
    img = (110.0 + 25.0 * cy[:, None] * sx[None, :]).astype(np.float32)
    T_cam_world = invert(T_world_camera)
    centres = transform_points(T_cam_world, scene.T_world_boards[:, :3, 3])
    order = np.argsort(-centres[:, 2])  # far to near
    shift = 4  # fixed-point sub-pixel precision of cv2.fillConvexPoly
    board = scene.board
    outline = board.outline()
    squares = board.black_squares()
    for b in order:
        T_cam_board = T_cam_world @ scene.T_world_boards[b]
        pts = transform_points(T_cam_board, np.concatenate([outline, squares.reshape(-1, 3)]))
        if np.any(pts[:, 2] <= 0.05):
            continue
        uv = (camera.project(pts) + 0.5) * s - 0.5
        fx = np.round(uv * (1 << shift)).astype(np.int32)
        cv2.fillConvexPoly(img, fx[:4], 235.0, lineType=cv2.LINE_AA, shift=shift)
        for q in fx[4:].reshape(-1, 4, 2):
            cv2.fillConvexPoly(img, q, 25.0, lineType=cv2.LINE_AA, shift=shift)
    if s > 1:
        img = cv2.resize(img, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    img = img + rng.normal(0.0, noise_std, img.shape).astype(np.float32)
    gray = np.clip(np.round(img), 0, 255).astype(np.uint8)
    # Slightly different channel gains: an "RGB" image, detection converts to grey.
    return np.stack([gray, np.clip(gray * 0.97, 0, 255).astype(np.uint8), gray], axis=2)


def render_depth(
    scene: CalibrationScene,
    T_world_depth: Array,
    camera: PinholeCamera,
    rng: np.random.Generator,
    noise_std: float = 0.01,
    max_depth: float = 10.0,
) -> NDArray[np.float32]:
    """Ray-cast a depth image (z-depth in metres, 0 = no return), Gaussian noise on z."""
    rays = camera.pixel_rays()
    norm = np.linalg.norm(rays, axis=1)
    dirs = rays / norm[:, None]
    R, t = T_world_depth[:3, :3], T_world_depth[:3, 3]
    rc, _ = scene.raycasting_scene()
    hit = _cast(rc, np.broadcast_to(t, dirs.shape), dirs @ R.T)
    z = hit / norm  # ray length -> z-depth
    ok = np.isfinite(z) & (z < max_depth)
    depth = np.zeros(z.shape, np.float32)
    depth[ok] = z[ok] + rng.normal(0.0, noise_std, int(ok.sum()))
    return depth.reshape(camera.height, camera.width)


# ---------------------------------------------------------------------------------------
# Scenario generators
# ---------------------------------------------------------------------------------------
def _board_facing(centre: Array, viewer: Array, yaw: float, pitch: float, roll: float) -> Array:
    """T_world_board: a board at ``centre`` whose normal points to ``viewer``, then tilted."""
    z = viewer - centre
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.95 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1) @ rot_y(yaw) @ rot_x(pitch) @ rot_z(roll)
    return make_transform(R, centre)


@dataclass
class LidarLidarScenario:
    """Two LiDAR sweeps of a board scene with the true extrinsic ``T_b_a`` (A -> B)."""

    scene: CalibrationScene
    T_world_a: Array
    T_world_b: Array
    cloud_a: NDArray[np.float32]
    cloud_b: NDArray[np.float32]
    model_a: LidarModel
    model_b: LidarModel
    seed: int

    @property
    def T_b_a(self) -> Array:
        return invert(self.T_world_b) @ self.T_world_a


@dataclass
class CameraDepthScenario:
    """An RGB image and a depth image of the boards, true extrinsic ``T_depth_camera``."""

    scene: CalibrationScene
    T_world_camera: Array
    T_world_depth: Array
    image: NDArray[np.uint8]
    depth: NDArray[np.float32]
    camera: PinholeCamera
    depth_camera: PinholeCamera
    seed: int
    extras: dict = field(default_factory=dict)

    @property
    def T_depth_camera(self) -> Array:
        return invert(self.T_world_depth) @ self.T_world_camera

    @property
    def board(self) -> Chessboard:
        return self.scene.board


def _min_normal_spread(T_boards: Array) -> float:
    """Smallest singular value of the stacked normals: 0 for parallel / coplanar-normal sets."""
    N = T_boards[:, :3, 2]
    return float(np.linalg.svd(N, compute_uv=False)[-1] / np.sqrt(len(N)))


def make_lidar_lidar_scenario(
    seed: int = 0,
    n_boards: int = 8,
    board: Chessboard | None = None,
    ground: bool = True,
    model_a: LidarModel = VLP64,
    model_b: LidarModel = OS1_32,
    max_extrinsic_translation: float = 1.0,
    parallel_boards: bool = False,
) -> LidarLidarScenario:
    """Boards around two LiDARs at 2–8 m with varied tilts; B has an arbitrary yaw and tilt.

    ``parallel_boards=True`` builds the degenerate case (all normals equal) for tests.
    """
    if n_boards < 1:
        raise InvalidInputError("n_boards must be >= 1")
    rng = np.random.default_rng(seed)
    board = board or Chessboard()
    bw = max(board.size)
    T_world_a = make_transform(np.eye(3), [0.0, 0.0, 0.0])
    # B: any yaw (GraffMatch needs no initial guess), some roll/pitch, up to ~1 m away.
    R_b = (
        rot_z(rng.uniform(-np.pi, np.pi))
        @ rot_x(rng.uniform(-0.25, 0.25))
        @ rot_y(rng.uniform(-0.25, 0.25))
    )
    d = rng.normal(size=3)
    t_b = d / np.linalg.norm(d) * rng.uniform(0.3, max_extrinsic_translation)
    t_b[2] = np.clip(t_b[2], -0.3, 0.3)
    T_world_b = make_transform(R_b, t_b)
    viewer = 0.5 * (T_world_a[:3, 3] + T_world_b[:3, 3])

    for _attempt in range(200):
        boards: list[Array] = []
        azimuths: list[tuple[float, float]] = []
        tries = 0
        while len(boards) < n_boards and tries < 2000:
            tries += 1
            r = rng.uniform(2.0, 8.0)
            # Parallel boards all face -x, so they must stand in front (+x) to be seen.
            az = rng.uniform(-1.0, 1.0) if parallel_boards else rng.uniform(-np.pi, np.pi)
            half = np.arctan2(0.75 * bw, r) + np.radians(3.0)
            if any(abs(np.angle(np.exp(1j * (az - a)))) < half + h for a, h in azimuths):
                continue
            z = rng.uniform(-0.4, 1.0)
            centre = np.array([r * np.cos(az), r * np.sin(az), z])
            if parallel_boards:
                R_par = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
                Tb = make_transform(R_par, centre)
            else:
                Tb = _board_facing(
                    centre,
                    viewer,
                    rng.uniform(-0.6, 0.6),
                    rng.uniform(-0.6, 0.6),
                    rng.uniform(-np.pi, np.pi),
                )
            boards.append(Tb)
            azimuths.append((az, half))
        if len(boards) < n_boards:
            continue
        T_boards = np.stack(boards)
        if parallel_boards or _min_normal_spread(T_boards) > 0.2 or n_boards < 3:
            break
    else:
        raise InvalidInputError(f"cannot place {n_boards} non-overlapping boards around the LiDARs")
    scene = CalibrationScene(board, T_boards, ground_z=-1.7 if ground else None)
    cloud_a = simulate_lidar(scene, T_world_a, model_a, rng)
    cloud_b = simulate_lidar(scene, T_world_b, model_b, rng)
    return LidarLidarScenario(scene, T_world_a, T_world_b, cloud_a, cloud_b, model_a, model_b, seed)


def make_camera_depth_scenario(
    seed: int = 0,
    n_boards: int = 6,
    board: Chessboard | None = None,
    camera: PinholeCamera | None = None,
    depth_camera: PinholeCamera | None = None,
    depth_noise: float = 0.01,
    parallel_boards: bool = False,
    back_wall: float | None = 7.0,
    tilt_scale: float = 1.0,
    min_normal_spread: float = 0.15,
) -> CameraDepthScenario:
    """Boards 2–5 m in front of an RGB camera and a depth camera (≤ 0.25 m, ≤ 10° apart).

    ``back_wall``: distance of a wall behind the boards [m] (None: boards float in empty
    space); the depth camera sees it as clutter planes the camera has no counterpart for.
    ``tilt_scale`` scales the boards' random yaw/pitch away from facing the camera (small values
    give near-parallel boards, the hard case for matching); layouts whose normals spread less
    than ``min_normal_spread`` are re-drawn.

    Boards are rejection-sampled so that each one lies wholly inside both images and their
    image footprints do not overlap (the detector masks one board after the other).
    """
    if n_boards < 1:
        raise InvalidInputError("n_boards must be >= 1")
    rng = np.random.default_rng(seed)
    board = board or Chessboard(cols=7, rows=5, square=0.07, margin=0.05)
    camera = camera or PinholeCamera.from_fov(1280, 960, 75.0)
    depth_camera = depth_camera or PinholeCamera.from_fov(640, 480, 80.0)
    T_world_camera = np.eye(4)
    ax = rng.normal(size=3)
    ax /= np.linalg.norm(ax)
    ang = np.radians(rng.uniform(2.0, 10.0))
    K = np.array([[0, -ax[2], ax[1]], [ax[2], 0, -ax[0]], [-ax[1], ax[0], 0]])
    R_d = np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K
    t_d = rng.normal(size=3)
    t_d = t_d / np.linalg.norm(t_d) * rng.uniform(0.05, 0.25)
    T_world_depth = make_transform(R_d, t_d)
    T_depth_world = invert(T_world_depth)
    outline = board.outline()

    def footprint(Tb: Array, cam: PinholeCamera, T_cam_world: Array, pad: float) -> Array | None:
        P = transform_points(T_cam_world @ Tb, outline)
        if np.any(P[:, 2] < 0.5):
            return None
        uv = cam.project(P)
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        m = pad * np.array([cam.width, cam.height])
        if np.any(lo < m) or hi[0] > cam.width - m[0] or hi[1] > cam.height - m[1]:
            return None
        return np.concatenate([lo, hi])

    for _attempt in range(200):
        boards: list[Array] = []
        boxes: list[Array] = []
        tries = 0
        while len(boards) < n_boards and tries < 5000:
            tries += 1
            z = rng.uniform(2.0, 5.0)
            x = rng.uniform(-0.75, 0.75) * z * 0.7
            y = rng.uniform(-0.75, 0.75) * z * 0.5
            centre = np.array([x, y, z])
            if parallel_boards:
                Tb = make_transform(rot_x(np.pi), centre)
            else:
                Tb = _board_facing(
                    centre,
                    np.zeros(3),
                    tilt_scale * rng.uniform(-0.7, 0.7),
                    tilt_scale * rng.uniform(-0.6, 0.6),
                    rng.uniform(-0.4, 0.4),
                )
            box = footprint(Tb, camera, np.eye(4), 0.02)
            if box is None or footprint(Tb, depth_camera, T_depth_world, 0.01) is None:
                continue
            gap = 0.06 * camera.width
            if any(
                not (
                    box[2] + gap < o[0]
                    or o[2] + gap < box[0]
                    or box[3] + gap < o[1]
                    or o[3] + gap < box[1]
                )
                for o in boxes
            ):
                continue
            boards.append(Tb)
            boxes.append(box)
        if len(boards) < n_boards:
            continue
        T_boards = np.stack(boards)
        if parallel_boards or n_boards < 3 or _min_normal_spread(T_boards) > min_normal_spread:
            break
    else:
        raise InvalidInputError(f"cannot place {n_boards} boards inside both camera views")
    walls = None
    if back_wall is not None:
        z = float(back_wall)
        walls = np.array(
            [[[-3 * z, -3 * z, z], [3 * z, -3 * z, z], [3 * z, 3 * z, z], [-3 * z, 3 * z, z]]]
        )
    scene = CalibrationScene(board, T_boards, ground_z=None, walls=walls)
    image = render_chessboard_image(scene, T_world_camera, camera, rng)
    depth = render_depth(scene, T_world_depth, depth_camera, rng, noise_std=depth_noise)
    return CameraDepthScenario(
        scene, T_world_camera, T_world_depth, image, depth, camera, depth_camera, seed
    )
