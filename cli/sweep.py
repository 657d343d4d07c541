"""``camloc sweep``: run a Monte Carlo study (seeds x simulate options x run options) locally or on
a Dask cluster, into a resumable folder."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape

from camloc.cli.interrupts import EXIT_INTERRUPTED, caused_by_interrupt
from camloc.cli.common import console, err_console, json_option, print_warnings, quiet_option

EXIT_ALL_FAILED = 1  # no run gave a result: a script must not take the empty study for one


def sweep(
    spec_file: Path = typer.Argument(..., metavar="SPEC_FILE", help="The sweep spec (TOML): seeds or datasets, \\[simulate] and \\[run] "
                                     "options by their command-line names; a list is one value per cell.",
                                     show_default=False),
    output: Path = typer.Option(..., "--output", "-o", help="The sweep folder: spec.json, runs.csv and summary.csv. "
                                "Running the same spec into it again runs only the cells that have no row.",
                                show_default=False),
    workers: Optional[int] = typer.Option(
        None, "--workers", min=1, help="Local worker processes. Default: the number of usable cores.", show_default=False
    ),
    scheduler: Optional[str] = typer.Option(
        None, "--scheduler", help="Run the cells on the Dask cluster of this scheduler (tcp://HOST:PORT) instead "
        "of local processes; needs the dask extra (pip install -e \".\\[dask]\"). Default: local.", show_default=False
    ),
    json_output: bool = json_option("the outcome and summary", instead="a table"),
    quiet: bool = quiet_option(),
) -> None:
    """Run every cell of SPEC_FILE (one localization run per seed and option combination) and write runs.csv (a row per run) and summary.csv (a row per configuration: median, mean, p90 and worst position RMSE, ratio to the oracle).

    A failed run is a row with its error and the sweep goes on; Ctrl-C keeps every finished row. The same spec gives the same numbers locally and on Dask.
    """
    from camloc.cli.sweep_render import cell_progress, render_summary
    from camloc.results import dumps_json
    from camloc.sweep import read_spec, run_sweep

    spec = read_spec(spec_file)
    try:
        with cell_progress(enabled=not (json_output or quiet), description=f"sweeping {spec_file.name}") as on_row:
            outcome = run_sweep(spec, output, workers=workers, scheduler=scheduler, on_row=on_row)
    except BaseException as error:
        if not caused_by_interrupt(error):
            raise
        err_console.print(f"[yellow]interrupted:[/] the finished rows are in {escape(str(output))}; run the same "
                          "command again to go on", highlight=False, soft_wrap=True)
        raise typer.Exit(EXIT_INTERRUPTED) from None
    if json_output:
        typer.echo(dumps_json(vars(outcome)), nl=False)
    elif not quiet:
        console.print(render_summary(spec, outcome))
    if not json_output:  # the object holds them: its warnings, failed and first_error
        print_warnings(outcome.warnings)
    if outcome.failed and not json_output:
        print_warnings([f"{outcome.failed} of {outcome.cells} runs failed (each row of runs.csv says why); "
                        f"the first: {outcome.first_error}"])
    if outcome.failed == outcome.cells:
        raise typer.Exit(EXIT_ALL_FAILED)
