"""``graffmatch``: global landmark matching and registration from the terminal.

Every command follows the same habits: results on stdout, progress (with an ETA) and errors on
stderr, errors as ONE line with a non-zero exit code (a traceback only with ``-v``), output
folders named by time with the exact configuration saved next to the results.

The app is assembled here from one module per command group (:mod:`~graffmatch.cli.scans`,
:mod:`~graffmatch.cli.data`, :mod:`~graffmatch.cli.evaluation`, :mod:`~graffmatch.cli.calibrate`,
:mod:`~graffmatch.cli.config`); each command parses, calls the library and prints.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from graffmatch.cli import calibrate, config, data, evaluation, loops, scans
from graffmatch.cli.common import __version__, out, reset_state

EPILOG_MAIN = """\
[bold]Examples[/bold]

  graffmatch demo
  graffmatch extract data/kitti00/velodyne/000000.bin -o lm/
  graffmatch register scan0.bin scan5.bin --gt gt.txt --view match.html
  graffmatch register lm/000000.npz lm/000005.npz --refine icp -o result.json
  graffmatch view runs/2026-11-21_14-03-12_register/result.json -o match.html
  graffmatch config dump > my.yaml && graffmatch --config my.yaml register a.bin b.bin
  GRAFFMATCH_MATCHER__RHO=20 graffmatch register a.npz b.npz

[bold]Exit codes[/bold]: 0 ok, 1 error (one line on stderr), 2 bad usage,
3 the command ran but its result is not valid (no registration, demo bounds missed).
"""

app = typer.Typer(
    name="graffmatch",
    help="Global LiDAR landmark matching and registration on the affine Grassmannian (GraffMatch).",
    epilog=EPILOG_MAIN,
    rich_markup_mode="rich",
    no_args_is_help=True,
    add_completion=False,
    context_settings={"help_option_names": ["-h", "--help"]},
    pretty_exceptions_show_locals=False,
)


def _version_callback(value: bool) -> None:
    if value:
        out.print(f"graffmatch {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_version_callback, is_eager=True, help="Print the version."
        ),
    ] = False,
    verbose: Annotated[
        int,
        typer.Option("--verbose", "-v", count=True, help="More output; -v also shows tracebacks."),
    ] = 0,
    quiet: Annotated[
        bool, typer.Option("--quiet", "-q", help="Only results and errors; no progress.")
    ] = False,
    runs_dir: Annotated[
        Path,
        typer.Option(
            "--runs-dir",
            help="Where commands without -o create their time-named output folders.",
            envvar="GRAFFMATCH_RUNS_DIR",
        ),
    ] = Path("runs"),
    config: Annotated[
        Path | None,
        typer.Option(
            "--config",
            "-c",
            help="YAML configuration (see 'graffmatch config dump'); env GRAFFMATCH_<SECTION>__"
            "<FIELD> overrides it.",
            envvar="GRAFFMATCH_CONFIG",
        ),
    ] = None,
) -> None:
    """Global LiDAR landmark matching and registration (GraffMatch)."""
    if verbose and quiet:
        raise typer.BadParameter("use either --verbose or --quiet")
    reset_state(-1 if quiet else verbose, config, runs_dir)


# Command order of `graffmatch --help`: the demo first, then the workflow of a user.
for _group in (config, scans, config.config_app, data, evaluation, calibrate):
    if _group is config.config_app:
        app.add_typer(config.config_app, name="config")
    else:
        app.registered_commands.extend(_group.commands.registered_commands)

loops.register(app)  # loop closure over whole drives (its module adds its own commands)

__all__ = ["__version__", "app"]


if __name__ == "__main__":  # pragma: no cover
    app()
