"""Progress bars of long evaluation steps, always on stderr so that stdout stays clean for pipes.

``progress_bar(enabled)`` gives a rich ``Progress`` (or an object with the same few methods that
draws nothing), so callers never branch on whether a bar is shown.
"""

from __future__ import annotations

from typing import Any


class NullProgress:
    """The methods of ``rich.progress.Progress`` the evaluation uses, drawing nothing."""

    def __enter__(self) -> NullProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def add_task(self, *a: Any, **k: Any) -> int:
        return 0

    def advance(self, *a: Any, **k: Any) -> None:
        return None

    def update(self, *a: Any, **k: Any) -> None:
        return None


def progress_bar(enabled: bool, label: str = "{task.description}", transient: bool = True) -> Any:
    """A rich progress bar (description, bar, n/N, elapsed, ETA) on stderr, or a NullProgress."""
    if not enabled:
        return NullProgress()
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    console = Console(stderr=True)
    return Progress(
        TextColumn(label),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        console=console,
        transient=transient,
        # a transient bar in a log or pipe would only leave blank lines
        disable=transient and not console.is_terminal,
    )
