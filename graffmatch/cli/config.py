"""``config dump`` / ``config check`` (the whole YAML configuration) and the ``demo``."""

from __future__ import annotations

import time
from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from graffmatch.cli.common import (
    EXIT_NOT_VALID,
    STATE,
    cli_errors,
    debug,
    err,
    info,
    out,
    status,
)

commands = typer.Typer()


class DemoMode(str, Enum):
    """Demo modes; typer rejects any other value as bad usage (exit code 2)."""

    auto = "auto"
    lidar = "lidar"
    landmarks = "landmarks"


config_app = typer.Typer(help="Show or check the whole configuration (YAML).", no_args_is_help=True)


# ----------------------------------------------------------------------------------------------
# demo
# ----------------------------------------------------------------------------------------------
@commands.command(
    epilog="[bold]Examples[/bold]\n\n  graffmatch demo\n\n  graffmatch demo --seed 3 "
    "--mode landmarks",
)
@cli_errors
def demo(
    seed: Annotated[int, typer.Option(help="Seed of the scene and the transform.")] = 0,
    mode: Annotated[
        DemoMode,
        typer.Option(
            help="'lidar': simulated street scans -> extraction -> match; 'landmarks': "
            "landmark sets directly; 'auto': lidar."
        ),
    ] = DemoMode.auto,
) -> None:
    """Run the built-in demo: match two views 180° and 14 m apart, print errors and timings.

    Exits with code 3 when the recovered transform misses the demo's bounds.
    """
    from graffmatch.demo import run_demo

    t0 = time.perf_counter()
    with status("running the demo ..."):
        report = run_demo(seed=seed, mode=mode.value, config=STATE.settings.matcher)
    debug(f"demo finished in {time.perf_counter() - t0:.2f} s")
    out.print(report)
    if not report.passed:
        err.print("[bold red]demo:[/bold red] the recovered transform misses its bounds")
        raise typer.Exit(EXIT_NOT_VALID)


# ----------------------------------------------------------------------------------------------
# config
# ----------------------------------------------------------------------------------------------
@config_app.command("dump")
@cli_errors
def config_dump(
    output: Annotated[
        Path | None, typer.Option("--output", "-o", help="Write to this file, not stdout.")
    ] = None,
) -> None:
    """Print the whole configuration (defaults + --config + environment) as commented YAML.

    Example: graffmatch config dump > my.yaml ; graffmatch --config my.yaml register a.bin b.bin
    """
    from graffmatch.cli.settings import dump_settings, missing_sections, save_settings

    for name in missing_sections():
        err.print(f"[yellow]warning[/yellow]: section {name!r} unavailable (module not importable)")
    if output is not None:
        save_settings(STATE.settings, output)
        info(f"configuration: {output}")
    else:
        # Plain print: YAML must not be wrapped or styled by rich.
        typer.echo(dump_settings(STATE.settings), nl=False)


@config_app.command("check")
@cli_errors
def config_check(
    file: Annotated[Path, typer.Argument(help="YAML configuration to validate.")],
) -> None:
    """Validate a YAML configuration file (exit code 1 with the first problems if invalid)."""
    from graffmatch.cli.settings import load_settings

    load_settings(file)
    info(f"{file}: valid")
