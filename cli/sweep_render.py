"""Rich rendering of a sweep: a progress bar over cells and the summary table."""

from __future__ import annotations

import contextlib
from typing import Any, Callable, Iterator, Mapping, Optional

from rich import box
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from camloc.cli.common import err_console


@contextlib.contextmanager
def cell_progress(*, enabled: bool, description: str) -> Iterator[Optional[Callable[[int, int, Mapping[str, str]], None]]]:
    """Yield an ``on_row(done, total, result)`` callback driving a bar over cells on stderr, or None."""
    if not enabled:
        yield None
        return
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn("cells"),
               TextColumn("{task.fields[failed]} failed"), TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, console=err_console, transient=True, refresh_per_second=4) as progress:
        task = progress.add_task(description, total=None, failed=0)
        failed = 0

        def on_row(done: int, total: int, result: Mapping[str, str]) -> None:
            nonlocal failed
            failed += result["status"] != "ok"
            progress.update(task, completed=done, total=total, failed=failed, refresh=False)

        yield on_row


def _fmt(value: Any, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def render_summary(spec, outcome) -> Table:
    """One row per configuration: the parameters that vary, runs, failures, ate_rmse median, p90
    and worst, and the ratio to the oracle; the parameters every configuration shares are in the caption."""
    from camloc.sweep import format_value

    summary = outcome.summary
    columns = spec.config_columns
    varying = [c for c in columns if len({format_value(row[c]) for row in summary}) > 1]
    shared = [c for c in columns if c not in varying and summary]
    title = (f"camloc sweep: {escape(outcome.folder)}: {outcome.cells} cells, {outcome.ran} run now, "
             f"{outcome.resumed} resumed, {outcome.failed} failed; position RMSE \\[m] over the worlds")
    caption = ", ".join(f"{c} = {format_value(summary[0][c])}" for c in shared) or None
    table = Table(title=title, title_justify="left", caption=escape(caption) if caption else None,
                  caption_justify="left", box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True)
    # Three varying options and every number fit 80 columns, none dropped: an option's header
    # breaks at its dashes (clutter-/fraction) or folds, the ratios' headers take two lines, and the mean
    # (summary.csv has it; the worst run dominates it) gives its place to median, p90 and worst.
    for column in varying:
        header = column.replace("-", "-\n")
        width = max(len(format_value(row[column])) for row in summary)  # the header may fold, a value never
        table.add_column(escape(header), min_width=width, overflow="fold")
    with_oracle = any(row["oracle_ratio_median"] is not None for row in summary)
    numbers = ["ok", "median", "p90", "worst"] + (["/oracle\nmedian", "/oracle\nworst"] if with_oracle else [])
    for header in numbers:
        table.add_column(header, justify="right", no_wrap=True, min_width=max(map(len, header.split("\n"))))
    for row in summary:
        cells = [escape(format_value(row[c])) for c in varying]
        ok = f"{row['runs'] - row['failures']}/{row['runs']}"
        cells.append(f"[red]{ok}[/]" if row["failures"] else ok)
        cells += [_fmt(row[f"ate_rmse_{s}"], ".4f") for s in ("median", "p90", "worst")]
        if with_oracle:
            cells += [_fmt(row["oracle_ratio_median"], ".3f"), _fmt(row["oracle_ratio_worst"], ".3f")]
        table.add_row(*cells)
    return table
