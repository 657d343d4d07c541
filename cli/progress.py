"""A rich progress bar for long loops, refreshed a few times a second whatever the loop's rate."""

from __future__ import annotations

import contextlib
from typing import Callable, Iterator

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from camloc.cli.common import err_console


@contextlib.contextmanager
def pose_progress(*, enabled: bool, description: str) -> Iterator[Callable[[int, int], None] | None]:
    """Yield an ``on_progress(done, total)`` callback driving a transient bar on stderr, or None
    (also when stderr is not a terminal: there a bar is only noise, and the blank line it leaves
    would stand before an error)."""
    if not (enabled and err_console.is_terminal):
        yield None
        return
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn("poses"), TimeElapsedColumn())
    with Progress(*columns, console=err_console, transient=True, refresh_per_second=8) as progress:
        task = progress.add_task(description, total=None)

        def on_progress(done: int, total: int) -> None:
            # Only stores numbers: rendering happens on rich's own refresh thread at 8 Hz.
            progress.update(task, completed=done, total=total, refresh=False)

        yield on_progress
