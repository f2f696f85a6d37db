"""Pose graph: odometry plus verified loop edges under a robust kernel, optimised with GTSAM.

Odometry edges come from consecutive odometry poses with sigmas proportional to the step
length (``odom_sigma_t`` m and ``odom_sigma_r_deg`` per metre travelled, with floors for a
standing sensor); loop edges carry the information matrix of their registration
(:func:`graffmatch.loops.io.loop_information`) inside a Cauchy kernel, so a wrong loop that got
through verification is down-weighted instead of bending the map. Levenberg-Marquardt starts
from the odometry. Accuracy is scored with evo: ATE (translation, after SE(3) Umeyama
alignment) and RPE (translation over ``rpe_delta`` frames).

Odometry drifts systematically as well as randomly: a heading bias (gyro, extrinsics, a
LiDAR odometry that turns a little too much in every metre) accumulates over the whole drive.
Loops observe that drift only where they are, so a plain pose graph leaves the stretch
before the first revisit as it was (a drive whose loops all sit at its end keeps most of its
ATE). With ``estimate_odometry_bias`` the graph also estimates one heading rate per metre
travelled (about the sensor's z axis) for the whole drive, shared by all odometry edges, under
a zero-mean prior: where the loops measure it, the correction reaches the parts of the drive
no loop sees; without loops it is not estimated. Roll/pitch rates and a scale error are not
estimated: closing a loop hardly observes scale (a scaled closed loop is still closed), and on
the benchmark drives estimating them let loop noise tilt or stretch the whole trajectory
(docs/loops.md).

How the bias is solved. A GTSAM ``CustomFactor`` (Python) on every odometry edge is exact but
does not scale: GTSAM hands each Python call a *copy* of all the graph's values (pybind11
copies a ``const Values&`` that no Python object owns), so one linearisation costs O(n^2) and
a 4,960-pose drive took 125 s instead of 1.4 s (perf: ``CustomFactor::unwhitenedError`` ->
``Values::Values``). The default solver (``bias_solver='projection'``) therefore eliminates
the poses for a fixed bias w with GTSAM's own C++ factors, i.e. the plain graph with every
odometry measurement corrected by w, and solves the one-dimensional problem
F(w) = min_X f(X, w) + w^2 / (2 sigma_w^2) for dF/dw = 0 (variable projection): by the
envelope theorem dF/dw = sum_k e_k' W_k de_k/dw + w / sigma_w^2 at the optimal poses, so a
safeguarded secant on w converges in a few warm-started plain solves. Its stationary point is
the joint problem's; ``bias_solver='joint'`` keeps the custom factor as the reference (tested:
same bias and trajectory).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from graffmatch.errors import GraffMatchError, InvalidInputError
from graffmatch.geometry.transforms import invert

Array = NDArray[np.float64]


class PoseGraphConfig(BaseModel):
    """Noise of the odometry edges and the robust kernel of the loop edges."""

    model_config = ConfigDict(extra="forbid")

    odom_sigma_t: float = Field(0.02, gt=0, description="odometry translation sigma per metre [m/m]")
    odom_sigma_r_deg: float = Field(0.05, gt=0, description="odometry rotation sigma per metre [deg/m]")
    odom_floor_t: float = Field(0.01, gt=0, description="smallest odometry translation sigma [m]")
    odom_floor_r_deg: float = Field(0.01, gt=0, description="smallest odometry rotation sigma [deg]")
    cauchy_k: float = Field(1.0, gt=0, description="Cauchy kernel width on whitened loop residuals")
    max_iterations: int = Field(100, ge=1)
    estimate_odometry_bias: bool = Field(
        True, description="estimate one heading-rate bias of the odometry for the whole drive (with loops)"
    )
    bias_prior_deg_per_100m: float = Field(
        10.0, gt=0, description="prior sigma of the heading-rate bias (about the sensor's z) [deg / 100 m]"
    )
    bias_solver: Literal["projection", "joint"] = Field(
        "projection",
        description="projection: plain C++ graphs and a secant on the bias (scales); "
        "joint: one GTSAM graph with a Python custom factor per odometry edge (O(n^2), reference)",
    )
    bias_tolerance_deg_per_100m: float = Field(
        1e-3, gt=0, description="projection: stop when the bias moves less than this [deg / 100 m]"
    )
    bias_max_solves: int = Field(12, ge=2, description="projection: at most this many pose-graph solves")


class OdometryDriftConfig(BaseModel):
    """Simulated odometry from ground truth: a yaw bias and noise per metre, a scale error."""

    model_config = ConfigDict(extra="forbid")

    yaw_bias_deg_per_100m: float = Field(3.0, description="systematic heading drift [deg / 100 m]")
    yaw_noise_deg_per_m: float = Field(0.05, ge=0, description="random heading noise [deg / sqrt(m)]")
    scale_error: float = Field(0.002, description="relative error of travelled distance")
    translation_noise_m_per_m: float = Field(0.005, ge=0, description="random translation noise")
    seed: int = 0


def _rz(a: float) -> Array:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def drifted_odometry(poses: Array, config: OdometryDriftConfig | None = None) -> Array:
    """Odometry poses (n, 4, 4) that drift from the given ones like wheel/LiDAR odometry does."""
    cfg = config or OdometryDriftConfig()
    P = np.asarray(poses, float)
    rng = np.random.default_rng(cfg.seed)
    out = np.empty_like(P)
    out[0] = P[0]
    for i in range(1, len(P)):
        rel = invert(P[i - 1]) @ P[i]
        step = float(np.linalg.norm(rel[:3, 3]))
        err = np.eye(4)
        yaw = np.radians(cfg.yaw_bias_deg_per_100m * step / 100.0) + np.radians(
            cfg.yaw_noise_deg_per_m
        ) * np.sqrt(step) * rng.standard_normal()
        err[:3, :3] = _rz(yaw)
        noisy = rel.copy()
        noisy[:3, 3] = rel[:3, 3] * (1.0 + cfg.scale_error) + cfg.translation_noise_m_per_m * step * rng.standard_normal(3)
        out[i] = out[i - 1] @ noisy @ err
    return out


BIAS_KEY = 1 << 40  # far above any pose index


def _odometry_bias_factor(gtsam, i: int, j: int, Z: Array, step: float, noise):
    """Odometry edge i -> j whose measurement is corrected by the drive's heading rate w [rad/m]:
    Z(w) = Z * Exp(-step w e_z); error = Log(Z(w)^-1 X_i^-1 X_j), as a BetweenFactor's."""
    Z3 = gtsam.Pose3(np.asarray(Z, float))
    zero = np.zeros(3)
    # d Z(w) / d w as a right perturbation: -step e_z (the right Jacobian of Exp(theta e_z)
    # leaves e_z unchanged)
    dZ = np.zeros((6, 1))
    dZ[2, 0] = -step
    H1, H2 = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")  # reused: GTSAM fills them
    Hz, Hx = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")

    def error(this, values, H):
        Xi, Xj, w = values.atPose3(i), values.atPose3(j), float(values.atVector(BIAS_KEY)[0])
        Zb = Z3.compose(gtsam.Pose3(gtsam.Rot3.Rz(-step * w), zero))
        if H is None:  # error only (LM's trial steps): no Jacobians
            return Zb.localCoordinates(Xi.between(Xj))
        between = Xi.between(Xj, H1, H2)
        e = Zb.localCoordinates(between, Hz, Hx)
        H[0], H[1], H[2] = Hx @ H1, Hx @ H2, Hz @ dZ
        return e

    return gtsam.CustomFactor(noise, [i, j, BIAS_KEY], error)


def _odometry_steps(gtsam, P: Array, cfg: PoseGraphConfig) -> list[tuple[object, Array, float, Array]]:
    """Per odometry edge i -> i+1: (gtsam Pose3, 4x4 measurement, step length, GTSAM sigmas rot first)."""
    out = []
    for i in range(len(P) - 1):
        rel = invert(P[i]) @ P[i + 1]
        step = float(np.linalg.norm(rel[:3, 3]))
        s_t = max(cfg.odom_sigma_t * step, cfg.odom_floor_t)
        s_r = np.radians(max(cfg.odom_sigma_r_deg * step, cfg.odom_floor_r_deg))
        out.append((gtsam.Pose3(rel), rel, step, np.array([s_r] * 3 + [s_t] * 3)))
    return out


def _loop_factors(gtsam, loop_edges, n: int, cfg: PoseGraphConfig) -> list:
    perm = np.r_[3:6, 0:3]
    out = []
    for i, j, T, info in loop_edges:
        if not (0 <= i < n and 0 <= j < n):
            raise InvalidInputError(f"loop edge ({i}, {j}) outside the {n} poses")
        info_g = np.asarray(info, float)[np.ix_(perm, perm)]  # g2o (t, r) -> GTSAM (r, t)
        base = gtsam.noiseModel.Gaussian.Information(info_g)
        robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(cfg.cauchy_k), base)
        out.append(gtsam.BetweenFactorPose3(int(i), int(j), gtsam.Pose3(np.asarray(T, float)), robust))
    return out


def _corrected(gtsam, Z3, step: float, w: float):
    """The odometry measurement corrected by the heading rate w [rad/m]: Z Exp(-step w e_z)."""
    return Z3.compose(gtsam.Pose3(gtsam.Rot3.Rz(-step * w), np.zeros(3)))


def _plain_graph(gtsam, P0: Array, steps, loops, w: float):
    """Prior, odometry edges corrected by a fixed heading rate ``w``, loop edges: C++ factors only."""
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(P0), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    for i, (Z3, _, step, sig) in enumerate(steps):
        Zb = Z3 if w == 0.0 else _corrected(gtsam, Z3, step, w)
        graph.add(gtsam.BetweenFactorPose3(i, i + 1, Zb, gtsam.noiseModel.Diagonal.Sigmas(sig)))
    for f in loops:
        graph.add(f)
    return graph


def _lm(gtsam, graph, initial, cfg: PoseGraphConfig):
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.max_iterations)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    return opt.optimize(), int(opt.iterations())


def _bias_gradient(gtsam, values, steps, w: float, prior_var: float) -> tuple[float, float]:
    """dF/dw at the poses ``values`` (optimal for this w) and the curvature with the poses held
    (sum de'W de + 1/prior_var, an upper bound of d2F/dw2: the poses' adaptation only lowers it)."""
    g, h = w / prior_var, 1.0 / prior_var
    Hz, Hx = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    Xk = values.atPose3(0)
    for i, (Z3, _, step, sig) in enumerate(steps):
        Xn = values.atPose3(i + 1)
        e = _corrected(gtsam, Z3, step, w).localCoordinates(Xk.between(Xn), Hz, Hx)
        de = -step * Hz[:, 2]  # d Z(w)/dw = -step e_z as a right perturbation (see _odometry_bias_factor)
        wde = de / sig**2
        g += float(e @ wde)
        h += float(de @ wde)
        Xk = Xn
    return g, h


def _solve_bias_projection(gtsam, P: Array, steps, loops, initial, cfg: PoseGraphConfig):
    """(values, w, summary) minimising F(w) = min_X f(X, w) + w^2 / 2 sigma^2 (module docstring)."""
    sigma = np.radians(cfg.bias_prior_deg_per_100m) / 100.0
    tol = np.radians(cfg.bias_tolerance_deg_per_100m) / 100.0
    iters = 0
    values, it = _lm(gtsam, _plain_graph(gtsam, P[0], steps, loops, 0.0), initial, cfg)
    iters += it
    w = 0.0
    g, h = _bias_gradient(gtsam, values, steps, w, sigma**2)
    lo, hi = -np.inf, np.inf  # bracket of the root of dF/dw, from the signs seen
    w_prev = g_prev = None
    converged = False
    solves = 1
    while True:
        if g > 0:
            hi = min(hi, w)
        elif g < 0:
            lo = max(lo, w)
        else:
            converged = True
            break
        if w_prev is None or g == g_prev:
            w_new = w - g / h  # the poses held: stops short of the root (h >= d2F/dw2)
        else:
            w_new = w - g * (w - w_prev) / (g - g_prev)  # secant: dF/dw is nearly linear in w
        if not lo < w_new < hi:  # a secant step out of the bracket: bisect it
            w_new = 0.5 * (lo + hi) if np.isfinite(lo) and np.isfinite(hi) else w - g / h
        if abs(w_new - w) < tol:
            converged = True
            break
        if solves >= cfg.bias_max_solves:
            break
        values_new, it = _lm(gtsam, _plain_graph(gtsam, P[0], steps, loops, w_new), values, cfg)
        iters += it
        solves += 1
        w_prev, g_prev = w, g
        w, values = w_new, values_new
        g, h = _bias_gradient(gtsam, values, steps, w, sigma**2)
    graph = _plain_graph(gtsam, P[0], steps, loops, w)
    error = float(graph.error(values) + 0.5 * (w / sigma) ** 2)
    return values, w, {"iterations": iters, "bias_solves": solves, "bias_converged": converged, "error_after": error}


def optimize_pose_graph(
    odometry: Array,
    loop_edges: Sequence[tuple[int, int, Array, Array]],
    config: PoseGraphConfig | None = None,
) -> tuple[Array, dict]:
    """Optimised poses (n, 4, 4) and a summary (errors before/after, iterations).

    ``loop_edges``: (i, j, T_i_j, information 6x6 translation-first), e.g. from
    :func:`graffmatch.loops.io.loop_edges`.
    """
    try:
        import gtsam
    except ImportError as exc:
        raise GraffMatchError("--optimize needs GTSAM: pip install 'graffmatch[loops]'") from exc
    cfg = config or PoseGraphConfig()
    P = np.asarray(odometry, float)
    n = len(P)
    if P.ndim != 3 or P.shape[1:] != (4, 4) or n < 2:
        raise InvalidInputError(f"odometry must be (n >= 2, 4, 4), got {P.shape}")
    initial = gtsam.Values()
    for i in range(n):
        initial.insert(i, gtsam.Pose3(P[i]))
    steps = _odometry_steps(gtsam, P, cfg)
    loops = _loop_factors(gtsam, loop_edges, n, cfg)
    bias = cfg.estimate_odometry_bias and len(loop_edges) > 0
    plain0 = _plain_graph(gtsam, P[0], steps, loops, 0.0)
    summary: dict = {"n_poses": n, "n_loop_edges": len(loop_edges), "error_before": float(plain0.error(initial))}
    if not bias:
        result, iters = _lm(gtsam, plain0, initial, cfg)
        summary.update(error_after=float(plain0.error(result)), iterations=iters)
        w = None
    elif cfg.bias_solver == "projection":
        result, w, info = _solve_bias_projection(gtsam, P, steps, loops, initial, cfg)
        summary.update(info)
    else:  # joint: the reference, one graph with a Python custom factor per odometry edge
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(P[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        initial.insert(BIAS_KEY, np.zeros(1))
        prior = np.array([np.radians(cfg.bias_prior_deg_per_100m) / 100.0])
        graph.add(gtsam.PriorFactorVector(BIAS_KEY, np.zeros(1), gtsam.noiseModel.Diagonal.Sigmas(prior)))
        for i, (_, rel, step, sig) in enumerate(steps):
            graph.add(_odometry_bias_factor(gtsam, i, i + 1, rel, step, gtsam.noiseModel.Diagonal.Sigmas(sig)))
        for f in loops:
            graph.add(f)
        result, iters = _lm(gtsam, graph, initial, cfg)
        summary.update(error_after=float(graph.error(result)), iterations=iters)
        w = float(np.asarray(result.atVector(BIAS_KEY), float)[0])
    out = np.stack([result.atPose3(i).matrix() for i in range(n)])
    if w is not None:
        summary["odometry_heading_bias_deg_per_100m"] = float(np.degrees(w) * 100.0)
    return out, summary


def trajectory_errors(estimate: Array, reference: Array, rpe_delta: int = 10) -> dict[str, float]:
    """evo's ATE (RMSE, max; SE(3)-aligned) and RPE (RMSE over ``rpe_delta`` frames) [m]."""
    from evo.core import metrics, sync  # noqa: F401
    from evo.core.trajectory import PosePath3D

    est = PosePath3D(poses_se3=[np.asarray(T, float) for T in estimate])
    ref = PosePath3D(poses_se3=[np.asarray(T, float) for T in reference])
    est.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    out = {"ate_rmse_m": float(ape.get_statistic(metrics.StatisticsType.rmse)),
           "ate_max_m": float(ape.get_statistic(metrics.StatisticsType.max))}
    delta = max(1, min(rpe_delta, len(estimate) - 1))
    rpe = metrics.RPE(metrics.PoseRelation.translation_part, delta=delta, delta_unit=metrics.Unit.frames, all_pairs=False)
    rpe.process_data((ref, est))
    out["rpe_rmse_m"] = float(rpe.get_statistic(metrics.StatisticsType.rmse))
    out["rpe_delta_frames"] = delta
    return out


def odometry_for(dataset, source: str, drift: OdometryDriftConfig | None = None, deskew: bool = False) -> Array:
    """Odometry poses of a dataset: 'gt' (its poses), 'drift' (its poses with simulated drift),
    'kiss-icp' (KISS-ICP on the scans; with ``deskew`` the scans are raw and KISS-ICP de-skews
    them itself, see :func:`kiss_icp_odometry`) or a KITTI pose file path (LiDAR-to-world)."""
    if source == "gt":
        return np.asarray(dataset.poses, float)  # MissingPosesError, naming the file, without ground truth
    if source == "drift":
        return drifted_odometry(dataset.poses, drift)
    if source == "kiss-icp":
        return kiss_icp_odometry(dataset, deskew=deskew)
    from pathlib import Path

    from graffmatch.geometry.pose_files import read_kitti

    P = read_kitti(Path(source))
    if len(P) != len(dataset):
        raise InvalidInputError(f"{source}: {len(P)} poses for {len(dataset)} scans")
    return P


#: what :func:`kiss_icp_odometry` returns, for caches keyed by it: bump when its poses change
KISS_ICP_ODOMETRY_VERSION = 2


def kiss_end_to_mid(delta: Array) -> Array:
    """T_end_mid: the mid-sweep frame in the end-of-sweep frame, for a sweep that moves by
    ``delta`` (4x4, the sensor's motion over one sweep) at constant velocity, as KISS-ICP's
    de-skew models it: exp(-0.5 log(delta)) on SE(3).

    KISS-ICP 1.x de-skews a scan into the frame at the *end* of its sweep (its C++
    ``Preprocessor``: each point moved by exp((t - 1) log(delta)), t its time normalised to
    [0, 1]), so its poses are end-of-sweep poses. The datasets' poses (KITTI's, the
    simulator's) and :mod:`graffmatch.lidar.deskew` take a scan at mid-sweep: half a sweep
    later is 0.5 m at 10 m/s, and a heading off by half a sweep's yaw in turns.
    """
    from scipy.linalg import expm, logm

    D = np.asarray(delta, float)
    if np.allclose(D, np.eye(4), atol=1e-12):
        return np.eye(4)
    out = np.real(expm(-0.5 * np.real(logm(D))))
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def kiss_icp_odometry(dataset, deskew: bool = False) -> Array:
    """KISS-ICP (Vizzo et al. 2023) with its defaults, scan by scan; poses in scan 0's frame,
    moved into the dataset's world frame with the first pose (when it has ground truth).

    ``deskew`` (raw, motion-distorted scans): KISS-ICP de-skews each scan itself, with per-point
    times from the azimuth (:func:`graffmatch.lidar.deskew.azimuth_times`: the sweep starts
    behind the sensor, forward at mid-sweep) and its constant-velocity prediction, and every
    pose is moved from the end of the sweep, where KISS-ICP puts it, to mid-sweep, where the
    dataset's poses and our de-skew expect it (:func:`kiss_end_to_mid`). Without that shift the
    de-skewed odometry was worse than none on a suburban check (docs/loops.md, session 13).
    Without ``deskew`` the scans are registered as they are (already de-skewed data).
    """
    try:
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP
    except ImportError as exc:
        raise GraffMatchError("KISS-ICP odometry needs: pip install 'graffmatch[loops]'") from exc
    from graffmatch.lidar.deskew import azimuth_times

    cfg = KISSConfig()
    cfg.data.max_range = 100.0
    cfg.data.deskew = bool(deskew)
    if cfg.mapping.voxel_size is None:  # what KISS-ICP's own load_config does
        cfg.mapping.voxel_size = float(cfg.data.max_range / 100.0)
    odo = KissICP(cfg)
    n = len(dataset)
    poses = []
    for i in range(n):
        pts = np.asarray(dataset[i].points[:, :3], np.float64)
        delta = np.asarray(odo.last_delta, float).copy()  # the motion KISS-ICP de-skews this scan with
        odo.register_frame(pts, azimuth_times(pts) + 0.5 if deskew else np.zeros(0))
        T = np.asarray(odo.last_pose, float).copy()
        poses.append(T @ kiss_end_to_mid(delta) if deskew else T)
    from graffmatch.datasets.base import has_ground_truth

    # in the ground truth's frame when there is one (so ATE compares like with like), else scan 0's
    P0 = np.asarray(dataset.poses[0], float) if has_ground_truth(dataset) else np.eye(4)
    return np.stack([P0 @ T for T in poses])


def plot_trajectories(path, reference: Array | None, odometry: Array, optimized: Array, loops) -> None:
    """Top view: reference (if any), odometry and optimised trajectory, loop edges in red."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 7))
    if reference is not None:
        ax.plot(reference[:, 0, 3], reference[:, 1, 3], "k-", lw=1, label="ground truth")
    ax.plot(odometry[:, 0, 3], odometry[:, 1, 3], "-", color="tab:orange", lw=1, label="odometry")
    ax.plot(optimized[:, 0, 3], optimized[:, 1, 3], "-", color="tab:blue", lw=1.2, label="optimised")
    for k, lc in enumerate(loops):
        a, b = optimized[lc.query, :3, 3], optimized[lc.match, :3, 3]
        ax.plot([a[0], b[0]], [a[1], b[1]], "r-", lw=0.6, alpha=0.7, label="loop edges" if k == 0 else None)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
