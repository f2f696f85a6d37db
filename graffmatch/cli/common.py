"""Shared plumbing of the CLI: global state, consoles, progress bars, errors and run folders.

Results go to stdout (so that they can be piped); progress, logs and errors go to stderr.
"""

from __future__ import annotations

import functools
import json
import logging
import sys
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import dataclass, field
from datetime import datetime, timezone
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _pkg_version
from pathlib import Path
from typing import Annotated, Any, TypeVar

import numpy as np
import typer
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from graffmatch.errors import GraffMatchError

F = TypeVar("F", bound=Callable[..., Any])

#: Exit codes (documented in ``graffmatch --help`` and docs/cli.md).
EXIT_ERROR = 1
EXIT_USAGE = 2  # click's own code for bad usage
EXIT_NOT_VALID = 3  # the command ran, but its result misses its bounds / is not valid

#: Tables print at most this many rows unless -v (the JSON files hold everything).
MAX_TABLE_ROWS = 40

try:
    __version__ = _pkg_version("graffmatch")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"


@dataclass
class State:
    """What the global options set; read by every command."""

    verbosity: int = 0  # -1 quiet, 0 normal, 1 -v, 2 -vv
    config_path: Path | None = None
    runs_dir: Path = Path("runs")
    _settings: Any = field(default=None, repr=False)

    @property
    def quiet(self) -> bool:
        return self.verbosity < 0

    @property
    def settings(self):
        """Settings loaded lazily (file + environment), so ``--help`` never touches them."""
        if self._settings is None:
            from graffmatch.cli.settings import load_settings

            self._settings = load_settings(self.config_path)
        return self._settings


STATE = State()
out = Console(highlight=False, soft_wrap=True)  # results (stdout)
err = Console(stderr=True, highlight=False, soft_wrap=True)  # progress, logs, errors


def reset_state(
    verbosity: int = 0, config_path: Path | None = None, runs_dir: Path | None = None
) -> None:
    STATE.verbosity = verbosity
    STATE.config_path = config_path
    STATE.runs_dir = Path("runs") if runs_dir is None else Path(runs_dir)
    STATE._settings = None
    level = {-1: logging.ERROR, 0: logging.WARNING, 1: logging.INFO}.get(verbosity, logging.DEBUG)
    logging.getLogger("graffmatch").setLevel(level)
    warnings.showwarning = _show_warning
    if verbosity < 0:
        warnings.filterwarnings("ignore", category=RuntimeWarning, module="graffmatch")


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Library warnings as one yellow line (where they came from only with -v)."""
    where = f" ({filename}:{lineno})" if STATE.verbosity > 0 else ""
    err.print(f"[yellow]warning[/yellow]: {message}{where}", markup=True, highlight=False)


def info(message: str) -> None:
    """A line of normal output; suppressed by ``-q``."""
    if not STATE.quiet:
        out.print(message)


def debug(message: str) -> None:
    if STATE.verbosity > 0:
        err.print(f"[dim]{message}[/dim]")


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or exc.__class__.__name__
    if isinstance(exc, FileNotFoundError) and exc.filename:
        text = f"{exc.filename}: file not found"
    elif isinstance(exc, IsADirectoryError) and exc.filename:
        text = f"{exc.filename}: is a directory"
    elif isinstance(exc, PermissionError) and exc.filename:
        text = f"{exc.filename}: permission denied"
    return text


def cli_errors(fn: F) -> F:
    """Show library/OS/value errors as ONE line on stderr with exit code 1 (traceback with -v).

    The CLI catches these at the top of every command (not in ``__main__``) so that typer's
    test runner and the installed entry point behave the same way.
    """

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except (typer.Exit, typer.Abort, KeyboardInterrupt):
            raise
        except (GraffMatchError, OSError, ValueError, ImportError) as exc:
            if STATE.verbosity > 0:
                raise
            kind = "" if isinstance(exc, GraffMatchError) else f" ({exc.__class__.__name__})"
            err.print(f"[bold red]error[/bold red]{kind}: {_one_line(exc)}", markup=True)
            raise typer.Exit(EXIT_ERROR) from None

    return wrapper  # type: ignore[return-value]


def make_progress(transient: bool = True) -> Progress:
    """A rich progress bar with an ETA on stderr; disabled by ``-q`` or a non-terminal."""
    return Progress(
        SpinnerColumn(),
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TaskProgressColumn(),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        console=err,
        transient=transient,
        # No bars in logs / pipes (they would only leave blank lines); -q turns them off too.
        disable=STATE.quiet or not err.is_terminal,
    )


@contextmanager
def stage(progress: Progress, task_id: Any, description: str) -> Iterator[None]:
    """Name the current step of a multi-step task and advance it when the step ends."""
    progress.update(task_id, description=description)
    t0 = time.perf_counter()
    yield
    progress.advance(task_id)
    debug(f"{description}: {1e3 * (time.perf_counter() - t0):.1f} ms")


def timestamp() -> str:
    return datetime.now().strftime("%Y-%m-%d_%H-%M-%S")


def run_dir(root: Path | str, command: str) -> Path:
    """A new output folder named by time: ``<root>/2026-11-21_14-03-12_<command>/``."""
    root = Path(root)
    base = root / f"{timestamp()}_{command}"
    path = base
    k = 2
    while path.exists():
        path = Path(f"{base}-{k}")
        k += 1
    path.mkdir(parents=True)
    return path


def write_config_next_to(folder: Path) -> Path:
    """Save the exact configuration used next to the results (kiss-icp's habit)."""
    from graffmatch.cli.settings import save_settings

    return save_settings(STATE.settings, folder / "config.yaml")


def exit_with(code: int) -> None:
    if code:
        raise typer.Exit(code)


def python_version() -> str:
    return ".".join(str(v) for v in sys.version_info[:3])


def status(message: str) -> AbstractContextManager[Any]:
    """A spinner on stderr while a step runs; nothing under -q (rich would still draw)."""
    return nullcontext() if STATE.quiet else err.status(message, spinner="dots")


def fmt_ms(seconds: float) -> str:
    return f"{1e3 * seconds:.1f} ms"


def now() -> str:
    """UTC time stamp of a result file."""
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def jsonable(x: Any) -> Any:
    """Arrays, numpy scalars and paths as JSON values; non-finite floats as null."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, np.generic):
        return jsonable(x.item())
    if isinstance(x, float) and not np.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x


def write_json(path: Path, data: Any) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(jsonable(data), indent=2) + "\n")
    return path


def write_config_beside(result_path: Path) -> Path:
    """The configuration next to one result file: ``<stem>.config.yaml``."""
    from graffmatch.cli.settings import save_settings

    return save_settings(STATE.settings, result_path.with_name(result_path.stem + ".config.yaml"))


def print_matrix(T: Any, title: str, note: str = "") -> None:
    """A 4x4 transform on stdout, one row a line, under a bold title (and a note)."""
    out.print(f"[bold]{title}[/bold]" + (f" ({note})" if note else ""))
    for r in np.asarray(T, dtype=float):
        out.print("  " + " ".join(f"{v:+10.5f}" for v in r))


def parse_scale(value: str) -> float | str:
    """``--scale``: a factor to metres or a unit name; a bad one is a usage error (exit 2)."""
    from graffmatch.lidar.io import resolve_scale

    try:
        scale: float | str = float(value)
    except ValueError:
        scale = value
    try:
        resolve_scale(scale)
    except GraffMatchError as exc:
        raise typer.BadParameter(str(exc)) from None
    return scale


#: The ``--scale`` option of every command that reads scans.
ScaleOption = Annotated[
    str,
    typer.Option(
        "--scale",
        callback=parse_scale,
        help="Metres per unit of the scan files: a factor (0.01) or a unit (m, dm, cm, mm, km); "
        "for clouds stored in centimetres or millimetres.",
    ),
]


@contextmanager
def in_cli_words(words: dict[str, str]) -> Iterator[None]:
    """Re-raise library errors with their Python spelling replaced by the CLI's (e.g.
    ``overwrite=True`` -> ``--overwrite``): a user of the command never wrote Python."""
    try:
        yield
    except GraffMatchError as exc:
        text = str(exc)
        for python, cli in words.items():
            text = text.replace(python, cli)
        if text == str(exc):
            raise
        raise type(exc)(text) from exc
