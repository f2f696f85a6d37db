"""``calibrate``: extrinsic calibration from planar boards (LiDAR-LiDAR, camera-depth)."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated, Any

import typer

from graffmatch.cli.common import (
    EXIT_NOT_VALID,
    STATE,
    ScaleOption,
    cli_errors,
    err,
    info,
    out,
    print_matrix,
    status,
    write_json,
)
from graffmatch.errors import InvalidInputError

commands = typer.Typer()


class CalibKind(str, Enum):
    lidar_lidar = "lidar-lidar"
    camera_depth = "camera-depth"
    both = "both"


@commands.command(
    epilog="[bold]Examples[/bold]\n\n  graffmatch calibrate --demo\n\n"
    "  graffmatch calibrate --demo --kind camera-depth --seed 2\n\n"
    "  graffmatch calibrate lidar_a.pcd lidar_b.pcd -o extrinsic.json\n\n"
    "  graffmatch calibrate --image rgb.png --camera-k K.txt --depth depth.png "
    "--depth-k 525,525,319.5,239.5 --board 7x5x0.07",
)
@cli_errors
def calibrate(
    cloud_a: Annotated[Path | None, typer.Argument(help="Point cloud of LiDAR A.")] = None,
    cloud_b: Annotated[Path | None, typer.Argument(help="Point cloud of LiDAR B.")] = None,
    demo_: Annotated[bool, typer.Option("--demo", help="Run the simulated rig(s).")] = False,
    kind: Annotated[CalibKind, typer.Option(help="Which demo rig.")] = CalibKind.both,
    seed: Annotated[int, typer.Option(help="Seed of the simulated rig.")] = 0,
    output: Annotated[Path | None, typer.Option("--output", "-o", help="Result JSON.")] = None,
    image: Annotated[
        Path | None, typer.Option(help="Camera-depth: RGB image of the chessboards (png/jpg).")
    ] = None,
    camera_k: Annotated[
        str | None,
        typer.Option(help="Camera intrinsics: a 3x3 text file or 'fx,fy,cx,cy' [px]."),
    ] = None,
    depth: Annotated[
        Path | None,
        typer.Option(help="Camera-depth: depth image, .npy [m] or 16-bit .png (--depth-scale)."),
    ] = None,
    depth_k: Annotated[
        str | None, typer.Option(help="Depth intrinsics: a 3x3 text file or 'fx,fy,cx,cy' [px].")
    ] = None,
    depth_scale: Annotated[
        float, typer.Option(help="Metres per unit of an integer depth image.")
    ] = 0.001,
    board: Annotated[
        str | None,
        typer.Option(
            help="Chessboard: inner corners, square and optional margin [m], "
            "COLSxROWSxSQUARE[xMARGIN], e.g. 7x5x0.07."
        ),
    ] = None,
    scale: ScaleOption = "1",
) -> None:
    """Extrinsic calibration from planar boards with GraffMatch (planes only, no initial guess).

    With two clouds: T_b_a (maps LiDAR A points into LiDAR B's frame), κ and plane residuals.
    With --demo: simulated rigs with known extrinsics; exit code 3 if a bound (1°, 5 cm) is missed.
    """
    from graffmatch import calibration

    cal = STATE.settings.calibration
    if demo_:
        kinds = ["lidar-lidar", "camera-depth"] if kind == CalibKind.both else [kind.value]
        reports = {}
        for k in kinds:
            config = cal.lidar_lidar if k == "lidar-lidar" else cal.camera_depth
            with status(f"calibrating the simulated {k} rig ..."):
                rep = calibration.run_calibration_demo(kind=k, seed=seed, config=config)
            out.print(calibration.format_demo_report(rep))
            reports[k] = rep
        if output is not None:
            write_json(output, reports)
        missed = [k for k, r in reports.items() if not r.get("within_bounds", False)]
        if missed:
            err.print(f"[bold red]calibrate:[/bold red] bounds missed for {', '.join(missed)}")
            raise typer.Exit(EXIT_NOT_VALID)
        return
    if image is not None or depth is not None:
        _calibrate_camera_depth(
            image, camera_k, depth, depth_k, depth_scale, board, cal.camera_depth, output
        )
        return
    if cloud_a is None or cloud_b is None:
        raise InvalidInputError(
            "give two point clouds (LiDAR A, LiDAR B), --image/--depth (camera-depth), or --demo"
        )
    from graffmatch.cli.inputs import read_scan

    a, _ = read_scan(cloud_a, scale=scale)
    b, _ = read_scan(cloud_b, scale=scale)
    res = calibration.calibrate_lidar_lidar(a[:, :3], b[:, :3], cal.lidar_lidar)
    _print_calibration(res, ("T_b_a", "LiDAR A -> LiDAR B"), output)


def _calibrate_camera_depth(
    image: Path | None,
    camera_k: str | None,
    depth: Path | None,
    depth_k: str | None,
    depth_scale: float,
    board: str | None,
    config: Any,
    output: Path | None,
) -> None:
    """Camera-depth calibration from files: T_depth_camera, κ and plane residuals."""
    from graffmatch import calibration
    from graffmatch.cli.inputs import parse_board, read_depth_image, read_image, read_intrinsics

    missing = [
        name
        for name, v in (
            ("--image", image),
            ("--camera-k", camera_k),
            ("--depth", depth),
            ("--depth-k", depth_k),
            ("--board", board),
        )
        if v is None
    ]
    if missing:
        raise InvalidInputError(f"camera-depth calibration also needs {', '.join(missing)}")
    res = calibration.calibrate_camera_depth(
        read_image(image),
        read_intrinsics(camera_k, "--camera-k"),
        read_depth_image(depth, depth_scale),
        read_intrinsics(depth_k, "--depth-k"),
        parse_board(board),
        config,
    )
    _print_calibration(res, ("T_depth_camera", "camera -> depth"), output)


def _print_calibration(res: Any, title: tuple[str, str], output: Path | None) -> None:
    """The result, its transform, the JSON file; exit code 3 when it is not valid."""
    out.print(repr(res))
    print_matrix(res.T_target_source, *title)
    if output is not None:
        write_json(output, res.to_dict())
        info(f"result: {output}")
    if not res.valid:
        raise typer.Exit(EXIT_NOT_VALID)
