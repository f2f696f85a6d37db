"""Commands that make data: ``simulate`` a drive, ``build-dataset`` a loop-closure suite."""

from __future__ import annotations

import time
from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from graffmatch.cli.common import (
    STATE,
    cli_errors,
    in_cli_words,
    info,
    make_progress,
    out,
)
from graffmatch.errors import InvalidInputError

commands = typer.Typer()


class SensorChoice(str, Enum):
    hdl64 = "hdl64"
    vlp16 = "vlp16"
    os1_64 = "os1-64"


@commands.command(
    epilog="[bold]Examples[/bold]\n\n  graffmatch simulate sim/ --style downtown --seed 0\n\n"
    "  graffmatch simulate sim/ --style suburban --scans 40 --sensor vlp16",
)
@cli_errors
def simulate(
    output: Annotated[Path, typer.Argument(help="Output KITTI-layout folder.")],
    style: Annotated[
        str, typer.Option(help="World style: downtown, suburban or open-road.")
    ] = "downtown",
    seed: Annotated[int, typer.Option(help="Seed of the world and the trajectory.")] = 0,
    scans: Annotated[
        int | None, typer.Option(min=1, help="Number of scans, ~1 m apart (default: 200).")
    ] = None,
    sensor: Annotated[SensorChoice, typer.Option(help="LiDAR profile.")] = SensorChoice.hdl64,
    overwrite: Annotated[
        bool, typer.Option(help="Replace the files of a non-empty output folder.")
    ] = False,
    reuse: Annotated[
        bool, typer.Option(help="Keep a folder that already holds this exact simulation.")
    ] = False,
) -> None:
    """Simulate a LiDAR drive through a procedural city; writes a KITTI-layout dataset.

    velodyne/*.bin, labels/*.label (SemanticKITTI classes), poses.txt (camera-0), calib.txt
    and the ground-truth landmarks; same seed -> identical bytes.
    """
    from graffmatch.datasets.simulator import STYLES, simulate_dataset

    if style not in STYLES:
        raise InvalidInputError(f"unknown style {style!r}; choose one of {', '.join(STYLES)}")
    t0 = time.perf_counter()
    with make_progress() as progress:
        task = progress.add_task(f"simulating {style}", total=scans)

        def tick(done: int, total: int) -> None:
            progress.update(task, completed=done, total=total)

        with in_cli_words({"overwrite=True": "--overwrite", "reuse=True": "--reuse"}):
            folder = simulate_dataset(
                output,
                style=style,
                seed=seed,
                n_scans=scans,
                sensor=sensor.value,
                overwrite=overwrite,
                reuse=reuse,
                progress=tick,
            )
    n = len(list((Path(folder) / "velodyne").glob("*.bin")))
    info(
        f"simulated {n} scans ({style}, {sensor.value}, seed {seed}) in "
        f"{time.perf_counter() - t0:.1f} s -> {folder}"
    )


@commands.command(
    "build-dataset",
    epilog="[bold]Examples[/bold]\n\n  graffmatch build-dataset --list\n\n"
    "  graffmatch build-dataset sim-downtown --quick\n\n"
    "  graffmatch build-dataset balm_courtyard -o datasets/",
)
@cli_errors
def build_dataset(
    name: Annotated[
        str | None, typer.Argument(help="Suite name (see --list).", show_default=False)
    ] = None,
    output: Annotated[
        Path, typer.Option("--output", "-o", help="Root folder; the suite goes to <root>/<name>.")
    ] = Path("datasets"),
    quick: Annotated[bool, typer.Option(help="A small version (for tests and previews).")] = False,
    list_: Annotated[bool, typer.Option("--list", help="List the built-in suites.")] = False,
) -> None:
    """Build a loop-closure suite: places, revisits, landmarks, ground-truth matches, cases."""
    from graffmatch.evaluation.suites import SUITES, build_suite

    if list_ or name is None:
        for key in sorted(SUITES):
            out.print(f"{key:18s} {SUITES[key].description}")
        return
    from graffmatch.cli.settings import dump_model
    from graffmatch.evaluation.loop_closures import summary_text
    from graffmatch.evaluation.suites import suite_config

    summary = build_suite(name, output, quick=quick, progress=not STATE.quiet)
    folder = output / (f"{name}-quick" if quick else name)
    # The suite's own rules (and their extractor config) made this data, not the CLI settings.
    (folder / "config.yaml").write_text(
        dump_model(suite_config(name, quick), f"loop-closure rules of suite {name}")
    )
    info(f"built {name} -> {folder}\n{summary_text(summary)}")
