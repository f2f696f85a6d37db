"""``graffmatch loops`` and ``graffmatch benchmark-loops``: loop closure over whole drives."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from graffmatch.cli.common import STATE, cli_errors, info, make_progress, out, run_dir


class Retriever(str, Enum):
    descriptor = "descriptor"
    scan_context = "scan-context"
    radius = "radius"
    descriptor_radius = "descriptor+radius"


class LoopExecutor(str, Enum):
    local = "local"
    serial = "serial"
    dask = "dask"
    ray = "ray"


def _progress_callback(progress):
    tasks: dict[str, int] = {}

    def cb(stage: str, done: int, total: int) -> None:
        if stage not in tasks:
            tasks[stage] = progress.add_task(stage, total=total)
        progress.update(tasks[stage], completed=done, total=total)

    return cb


def _open(sequence: Path, kind: str):
    from graffmatch.datasets.registry import open_dataset

    return open_dataset(kind, sequence)


def register(app: typer.Typer) -> None:
    """Add the commands to the main app (one line in cli/main.py)."""
    app.command(
        "loops",
        epilog="[bold]Examples[/bold]\n\n  graffmatch loops data/balm_courtyard -o loops-out\n\n"
        "  graffmatch loops sim/drive --optimize --odometry drift --executor ray\n\n"
        "  graffmatch loops data/seq --retriever scan-context --top-k 10 --min-confidence 0.6",
    )(cli_errors(loops))
    app.command(
        "benchmark-loops",
        epilog="[bold]Examples[/bold]\n\n  graffmatch benchmark-loops sim/drive1 sim/drive2 -o bench-loops\n\n"
        "  graffmatch benchmark-loops data/balm_courtyard -m ours -m scan-context-icp\n\n"
        "  graffmatch benchmark-loops sim/raw1 sim/raw2 --deskew --odometry drift -o bench-loops-deskew",
    )(cli_errors(benchmark_loops))


def loops(
    sequence: Annotated[Path, typer.Argument(help="Sequence folder (KITTI layout, simulated drive, ...).")],
    output: Annotated[Path | None, typer.Option("--output", "-o", help="Results folder (rerun to resume).")] = None,
    kind: Annotated[str, typer.Option(help="Dataset kind for open_dataset (folder, kitti, kitti360, nclt).")] = "folder",
    retriever: Annotated[
        Retriever,
        typer.Option(help="Candidate retrieval (descriptor+radius: the descriptor alone unless odometry is loaded)."),
    ] = Retriever.descriptor_radius,
    top_k: Annotated[int | None, typer.Option(min=1, help="Candidates retrieved per query (quick-checked).")] = None,
    max_verified: Annotated[int | None, typer.Option(min=1, help="Verify at most this many per query.")] = None,
    quick_check: Annotated[bool, typer.Option(help="Pre-screen candidates with the BEV quick check.")] = True,
    all_loops: Annotated[bool, typer.Option(help="Verify every candidate (no stop at the first accepted).")] = False,
    exclude_seconds: Annotated[float | None, typer.Option(min=0, help="Skip scans this recent (s).")] = None,
    exclude_frames: Annotated[int | None, typer.Option(min=0, help="Also skip this many recent scans.")] = None,
    radius: Annotated[
        float | None, typer.Option(min=0, help="Radius retrievers: search radius (m; radius 10, descriptor+radius 5).")
    ] = None,
    radius_drift: Annotated[
        float | None,
        typer.Option(min=0, help="descriptor+radius: the radius grows by this fraction of the odometry path (0.02)."),
    ] = None,
    min_confidence: Annotated[float | None, typer.Option(min=0, max=1, help="Report loops from this confidence.")] = None,
    place_radius: Annotated[
        float | None, typer.Option(min=0, help="Report only loops estimated at most this far apart (m), less --place-margin.")
    ] = None,
    place_margin: Annotated[
        float | None, typer.Option(min=0, help="With --place-radius: the estimate's safety margin (m).")
    ] = None,
    place_check: Annotated[
        bool | None,
        typer.Option("--place-check/--no-place-check",
                     help="With --place-radius: re-measure loops estimated just beyond it by ICP on the two scans "
                     "(a few cm instead of decimetres; 36-111 ms a checked query). On by default. Its margin assumes "
                     "motion-compensated scans: de-skew raw scans of a moving vehicle (--deskew)."),
    ] = None,
    evidence_points_below: Annotated[
        int | None,
        typer.Option(min=0, help="Scans with fewer landmarks keep their evidence points in the database (0: none)."),
    ] = None,
    scan_cloud_below: Annotated[
        int | None,
        typer.Option(min=0, help="Scans with fewer landmarks also keep their scan cloud; pairs of two such scans "
                     "are verified again on it (raw-scan evidence; 0: none)."),
    ] = None,
    local_map_frames: Annotated[
        int | None,
        typer.Option(min=0, max=200, help="Scans with fewer than --local-map-below landmarks are matched on their local "
                     "map: their landmarks merged with those of this many previous frames, moved by the odometry "
                     "(giving it loads the odometry; 0: off). Default 5 frames below 6 landmarks whenever odometry is loaded; a frame "
                     "joins only when its points land on the map's."),
    ] = None,
    local_map_below: Annotated[
        int | None, typer.Option(min=0, help="Own landmarks below which a scan is matched on its local map.")
    ] = None,
    optimize: Annotated[bool, typer.Option(help="Pose graph with GTSAM; KITTI/TUM trajectories, ATE/RPE.")] = False,
    odometry: Annotated[
        str | None,
        typer.Option(help="Odometry for --optimize/radius: drift | gt | kiss-icp | PATH (KITTI poses). Default: drift "
                     "(simulated from the ground truth) when the drive has poses, kiss-icp (from the scans) when not."),
    ] = None,
    drift_yaw: Annotated[float, typer.Option(help="Simulated drift: heading bias (deg per 100 m).")] = 3.0,
    drift_seed: Annotated[int, typer.Option(help="Simulated drift seed.")] = 0,
    odometry_bias: Annotated[
        bool, typer.Option(help="--optimize: estimate the odometry's heading-rate bias from the loops.")
    ] = True,
    executor: Annotated[LoopExecutor, typer.Option(help="Where extraction and verification run.")] = LoopExecutor.local,
    address: Annotated[str | None, typer.Option(help="Cluster address (dask/ray).")] = None,
    workers: Annotated[int | None, typer.Option(min=1, help="Local worker processes.")] = None,
    deskew: Annotated[
        bool, typer.Option(help="De-skew raw scans with the odometry's motion first (KITTI ships them de-skewed); "
                           "--odometry kiss-icp then de-skews them inside KISS-ICP too.")
    ] = False,
    use_odometry: Annotated[
        bool,
        typer.Option(help="Load --odometry even without --optimize/--deskew: the descriptor+radius retriever then adds "
                     "the scans near the odometry estimate, and weak point-verified loops are "
                     "then accepted when a neighbouring query's loop agrees through it (sequence consistency)."),
    ] = False,
) -> None:
    """Find every loop closure of a drive: landmarks per scan, retrieval, verified matching."""
    from graffmatch.datasets.base import has_ground_truth
    from graffmatch.loops.detector import LoopDetectorConfig
    from graffmatch.loops.posegraph import OdometryDriftConfig, PoseGraphConfig
    from graffmatch.loops.sequence import optimize_run, prepare_drive, run_loops

    ds = _open(sequence, kind)
    cfg = LoopDetectorConfig()
    cfg.retrieval.method = retriever.value
    radius_field = "union_radius_m" if retriever == Retriever.descriptor_radius else "radius_m"
    for field, value in (("top_k", top_k), ("exclude_seconds", exclude_seconds), ("exclude_frames", exclude_frames),
                         (radius_field, radius), ("drift_fraction", radius_drift)):
        if value is not None:
            setattr(cfg.retrieval, field, value)
    if min_confidence is not None:
        cfg.verification.min_confidence = min_confidence
    if max_verified is not None:
        cfg.verification.max_verified = max_verified
    if place_radius is not None:
        cfg.verification.max_translation_m = place_radius
    if place_margin is not None:
        cfg.verification.place_margin_m = place_margin
    if place_check is not None:
        cfg.verification.place_check = place_check
    if evidence_points_below is not None:
        cfg.verification.evidence_points_below = evidence_points_below
    if scan_cloud_below is not None:
        cfg.verification.scan_cloud_below = scan_cloud_below
    if local_map_frames is not None:
        cfg.verification.local_map_frames = local_map_frames
    if local_map_below is not None:
        cfg.verification.local_map_below = local_map_below
    cfg.verification.quick_check = quick_check
    cfg.verification.stop_when_accepted = not all_loops
    cfg = LoopDetectorConfig.model_validate(cfg.model_dump())
    out_dir = output or run_dir(STATE.runs_dir, "loops")
    need_odometry = optimize or deskew or use_odometry or retriever == Retriever.radius or bool(local_map_frames)
    if odometry is None:  # a folder of scans alone has no ground truth to drift: odometry from the scans
        odometry = "drift" if has_ground_truth(ds) else "kiss-icp"
        if need_odometry and odometry == "kiss-icp":
            info(f"{sequence}: no ground-truth poses, so the odometry comes from the scans (KISS-ICP)")
    if not deskew and getattr(ds, "motion_compensated", None) is None:  # smear cannot be read off the scans
        info(f"{sequence}: the data does not say whether its scans are de-skewed; raw scans of a moving vehicle "
             "need --deskew (docs/loops.md, session 25)")
    ds, odo = prepare_drive(ds, odometry if need_odometry else None, deskew,
                            OdometryDriftConfig(yaw_bias_deg_per_100m=drift_yaw, seed=drift_seed))
    with make_progress() as progress:
        summary = run_loops(
            ds, out_dir, cfg, executor=executor.value, workers=workers, address=address,
            positions=None if odo is None else odo[:, :3, 3], progress=_progress_callback(progress),
            odometry=odo,
        )
    out.print(
        f"{summary['n_loops']} loops in {summary['n_queries_with_loop']} of {summary['n_scans']} scans "
        f"({summary['verify_ms_per_query']:.1f} ms verification + {summary['retrieve_ms_per_query']:.2f} ms "
        f"retrieval per query, {summary['database_bytes_per_scan']:.0f} B/scan) -> {out_dir}"
    )
    if optimize and odo is not None:
        import numpy as np

        pg = optimize_run(out_dir, odo, np.asarray(ds.timestamps), reference=None if odometry == "gt" or not has_ground_truth(ds) else np.asarray(ds.poses),
                          config=PoseGraphConfig(estimate_odometry_bias=odometry_bias))
        if "odometry_heading_bias_deg_per_100m" in pg:
            out.print(f"estimated odometry heading bias: {pg['odometry_heading_bias_deg_per_100m']:+.2f} deg / 100 m")
        if "before" in pg:
            out.print(
                f"pose graph: ATE {pg['before']['ate_rmse_m']:.2f} m -> {pg['after']['ate_rmse_m']:.2f} m, "
                f"RPE {pg['before']['rpe_rmse_m']:.3f} -> {pg['after']['rpe_rmse_m']:.3f} m"
            )
        info(f"trajectories -> {out_dir}/optimized_kitti.txt, optimized_tum.txt, trajectory.png")


def benchmark_loops(
    sequences: Annotated[list[Path], typer.Argument(help="Sequence folders with ground-truth poses.")],
    output: Annotated[Path | None, typer.Option("--output", "-o", help="Results folder.")] = None,
    methods: Annotated[list[str] | None, typer.Option("--method", "-m", help="ours | scan-context-icp | mapclosures | mapclosures-gt (| mapclosures-gt:R, R m maps)")] = None,
    workers: Annotated[int | None, typer.Option(min=1, help="Local worker processes.")] = None,
    deskew: Annotated[
        bool, typer.Option(help="De-skew raw scans with the odometry's motion first, for every method (as loops --deskew).")
    ] = False,
    odometry: Annotated[
        str, typer.Option(help="--deskew: odometry whose motion de-skews: drift | gt | kiss-icp (de-skewing the raw "
                           "scans itself) | PATH (KITTI poses).")
    ] = "drift",
    drift_yaw: Annotated[float, typer.Option(help="Simulated drift: heading bias (deg per 100 m).")] = 3.0,
    drift_seed: Annotated[int, typer.Option(help="Simulated drift seed.")] = 0,
) -> None:
    """Sequence-level loop-closure benchmark: PR over confidence, F1-max, recall at 100 % precision."""
    from graffmatch.evaluation.sequence_benchmark import run_sequence_benchmark
    from graffmatch.loops.posegraph import OdometryDriftConfig

    out_dir = output or run_dir(STATE.runs_dir, "benchmark-loops")
    with make_progress() as progress:
        table = run_sequence_benchmark(
            [Path(s) for s in sequences], out_dir, methods=list(methods) if methods else None,
            workers=workers, progress=_progress_callback(progress), deskew=deskew,
            odometry=odometry if deskew else None,
            drift=OdometryDriftConfig(yaw_bias_deg_per_100m=drift_yaw, seed=drift_seed),
        )
    out.print(table)
    info(f"results -> {out_dir}")
