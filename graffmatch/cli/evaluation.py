"""Commands of the evaluation: ``benchmark`` (the paper's experiments) and ``report``."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from graffmatch.cli.common import (
    STATE,
    cli_errors,
    info,
    make_progress,
    run_dir,
    status,
)
from graffmatch.errors import MalformedFileError

commands = typer.Typer()


class ExecutorChoice(str, Enum):
    local = "local"
    serial = "serial"
    dask = "dask"
    ray = "ray"


@commands.command(
    epilog="[bold]Examples[/bold]\n\n  graffmatch benchmark --quick\n\n"
    "  graffmatch benchmark sim-downtown balm_courtyard -o bench-out\n\n"
    "  graffmatch benchmark --executor dask --address tcp://10.0.0.2:8786",
)
@cli_errors
def benchmark(
    suites: Annotated[
        list[str] | None, typer.Argument(help="Suite names (default: the default suites).")
    ] = None,
    output: Annotated[
        Path | None,
        typer.Option("--output", "-o", help="Results folder; default runs/<time>_benchmark/."),
    ] = None,
    quick: Annotated[bool, typer.Option(help="The small (≤ 5 min) version.")] = False,
    executor: Annotated[
        ExecutorChoice, typer.Option(help="Where pairs run.")
    ] = ExecutorChoice.local,
    address: Annotated[
        str | None, typer.Option(help="Cluster scheduler address (dask/ray).")
    ] = None,
    workers: Annotated[int | None, typer.Option(min=1, help="Local worker processes.")] = None,
    methods: Annotated[
        list[str] | None, typer.Option("--method", "-m", help="Only these methods (repeatable).")
    ] = None,
    data_dir: Annotated[
        Path | None, typer.Option(help="Cache of built suites (share it between runs).")
    ] = None,
) -> None:
    """Run the paper's experiments (every method on every pair) in parallel; resumable.

    Writes <out>/results (one record per pair and method), <out>/report and the config. Rerun
    with the same -o to continue a killed run; 'graffmatch report <out>' rebuilds the report.
    """
    from graffmatch.evaluation.benchmark import is_benchmark_complete, run_benchmark

    args = {
        "suites": list(suites or []) or None,
        "quick": quick,
        "methods": list(methods) if methods else None,
        "data_dir": data_dir,
    }
    if output is not None and is_benchmark_complete(output, **args):
        info(f"{output} is complete; nothing to do (another -o runs it again)")
        return
    out_dir = output or run_dir(STATE.runs_dir, "benchmark")
    # run_benchmark writes the exact study configuration itself (results/config.json).
    res = run_benchmark(
        out_dir=out_dir,
        executor=executor.value,
        address=address,
        workers=workers,
        progress=not STATE.quiet,
        **args,
    )
    info(f"results -> {res}")


@commands.command(
    epilog="[bold]Example[/bold]\n\n  graffmatch report runs/2026-11-21_14-03-12_benchmark "
    "-o report/",
)
@cli_errors
def report(
    results: Annotated[
        Path,
        typer.Argument(help="Folder written by 'graffmatch benchmark' (or its results/)."),
    ],
    output: Annotated[
        Path | None,
        typer.Option("--output", "-o", help="Report folder; default <benchmark>/report."),
    ] = None,
    views: Annotated[
        int,
        typer.Option(
            min=0,
            help="Interactive 3D views (and PNGs) of this many sample pairs per suite and case, "
            "linked from summary.md; 0 for none.",
        ),
    ] = 1,
) -> None:
    """Turn benchmark results into tables, figures, sample 3D views and a markdown summary."""
    from graffmatch.evaluation.report import make_report
    from graffmatch.viz.report_views import benchmark_folder_of, write_report_views

    if not results.is_dir():
        raise MalformedFileError(f"{results}: results folder not found")
    bench = benchmark_folder_of(results)
    if bench is not None and (results / "results").is_dir():
        # a 'graffmatch benchmark' output folder: its records live in results/
        output = output or results / "report"
        results = results / "results"
    with status("writing the report ..."):
        folder = Path(make_report(results, output))
    if views and bench is not None:
        with make_progress() as progress:
            task = progress.add_task("sample views", total=None)
            entries = write_report_views(
                bench,
                folder,
                per_case=views,
                matcher_config=STATE.settings.matcher,
                max_points=min(STATE.settings.view.max_points, 20_000),
                on_pair=lambda name: progress.update(task, description=f"view {name}"),
            )
        info(f"{len(entries)} sample view(s) -> {folder / 'views'}")
    info(f"report -> {folder}")
