"""``camloc info``: what a g2o dataset holds, as tables or as one JSON object."""

from __future__ import annotations

from pathlib import Path

import typer

from camloc.cli.common import console, handles_errors


@handles_errors
def info(
    dataset: Path = typer.Argument(..., metavar="DATASET", help="The g2o dataset to summarize.", show_default=False),
    json_output: bool = typer.Option(
        False, "--json", help="Print the summary as one JSON object (snake_case keys) instead of tables. "
        "Default: tables.", show_default=False
    ),
) -> None:
    """Summarize DATASET: records per tag (unknown ones included), cameras, trajectory length and
    extent, odometry and observation noise, observations per pose, unobserved landmarks and
    observations of landmarks missing from the map, and the reader's warnings.

    Reads the file only; writes nothing. Exit status 2 when the file cannot be read.
    """
    import json
    import warnings

    from camloc.dataset_summary import summarize_dataset
    from camloc.g2o import G2oWarning, read_g2o

    with warnings.catch_warnings():
        # The reader's warnings are part of the summary; printing them twice would be noise.
        warnings.simplefilter("ignore", G2oWarning)
        summary = summarize_dataset(read_g2o(dataset))
    if json_output:
        typer.echo(json.dumps(summary, indent=2))
    else:
        from camloc.cli.info_render import render_dataset_summary

        console.print(render_dataset_summary(summary))
