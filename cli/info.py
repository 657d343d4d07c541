"""``camloc info``: what a g2o dataset holds, as tables or as one JSON object."""

from __future__ import annotations

from pathlib import Path

from camloc.cli.common import console, dataset_argument, echo_json, json_option, print_warnings, quiet_option


def info(
    dataset: Path = dataset_argument("The g2o dataset to summarize, or the name of a bundled one (grid-small, "
                                     "smooth3d-clutter, pixel-2cam)."),
    json_output: bool = json_option("the summary"),
    quiet: bool = quiet_option(),
) -> None:
    """Summarize DATASET: records per tag (unknown ones included), cameras, trajectory length and
    extent, odometry and observation noise, observations per pose, unobserved landmarks and
    observations of landmarks missing from the map, and the reader's warnings.

    Reads the file only; writes nothing. Exit status 2 when the file cannot be read.
    """
    import warnings

    from camloc.bundled import resolve_dataset
    from camloc.dataset_summary import summarize_dataset
    from camloc.g2o import G2oWarning, read_g2o

    with warnings.catch_warnings():
        # The reader's warnings are part of the summary; printing them twice would be noise.
        warnings.simplefilter("ignore", G2oWarning)
        summary = summarize_dataset(read_g2o(resolve_dataset(dataset)))
    if echo_json(summary, enabled=json_output):
        return  # the warnings are the object's "warnings"
    if quiet:
        print_warnings(summary["warnings"], dataset)  # the table lists them; without it, stderr does
        return
    from camloc.cli.info_render import render_dataset_summary

    console.print(render_dataset_summary(summary))
