"""``camloc run``: localize a dataset and write the run folder."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape

from camloc.cli.common import (
    console,
    dataset_argument,
    echo_json,
    err_console,
    force_option,
    json_option,
    library_option,
    quiet_option,
)


class FilterChoice(str, Enum):
    euler = "euler"
    se3 = "se3"


class AssociationChoice(str, Enum):
    beam = "beam"
    jcbb = "jcbb"
    best_friends = "best-friends"
    oracle = "oracle"


class CostChoice(str, Enum):
    nll = "nll"
    mahalanobis = "mahalanobis"
    euclidean = "euclidean"


def run(
    dataset: Optional[Path] = dataset_argument(
        "g2o dataset to localize. Default: the bundled grid-small.g2o.", required=False
    ),
    output: Optional[Path] = typer.Option(
        None, "--output", "-o", help="Run folder to write (missing parent folders are created); an existing "
        "run folder is refused unless --force. Default: runs/<dataset name>.", show_default=False
    ),
    force: bool = force_option("the run folder (files in it that are not camloc's are kept)"),
    config_file: Optional[Path] = typer.Option(
        None, "--config", help="TOML file with localizer options (names as below, with underscores); "
        "options given on the command line win. Default: none.", show_default=False
    ),
    filter: Optional[FilterChoice] = library_option(  # noqa: A002 (named after --filter)
        "State parametrization: euler (x, y, z, roll, pitch, yaw; singular "
        "at pitch +-90 deg) or se3 (error-state filter on SE(3), no singularity).",
        "localizer.filter", "--filter"
    ),
    association: Optional[AssociationChoice] = library_option(
        "Data association: beam (a beam of association hypotheses), jcbb (joint "
        "compatibility branch and bound, seeded by best friends), best-friends (mutual best match with gates) "
        "or oracle (the file's landmark ids, gated; for comparison). Only oracle reads the file's ids.",
        "localizer.association"
    ),
    iterations: Optional[int] = library_option(
        "Linearizations per update: 1 = EKF, more = iterated EKF.",
        "localizer.iterations"
    ),
    gate: Optional[float] = library_option(
        "Chi-square gate probability on each pair's innovation (3 dof).",
        "localizer.gate_probability", "--gate"
    ),
    cost: Optional[CostChoice] = library_option(
        "Best-friends pair cost: nll (Mahalanobis + log det S), mahalanobis, euclidean.",
        "localizer.cost"
    ),
    margin: Optional[float] = library_option(
        "Lonely-best-friends margin in cost units: reject a pair whose closest rival "
        "is within it.",
        "localizer.margin"
    ),
    sequential: Optional[bool] = library_option(
        "Accept best-friends pairs one at a time, conditioning "
        "on each (sequential), or all at once (batch, the original method).",
        "localizer.sequential", "--sequential/--batch"
    ),
    beam_width: Optional[int] = library_option(
        "Beam: association hypotheses kept after each pose.",
        "localizer.beam_width"
    ),
    beam_delta: Optional[float] = library_option(
        "Beam: drop hypotheses this much costlier than the best (2 x log-likelihood "
        "ratio).",
        "localizer.beam_delta"
    ),
    branch_delta: Optional[float] = library_option(
        "Beam: explore only an observation's options within this cost of its best.",
        "localizer.branch_delta"
    ),
    null_cost: Optional[float] = typer.Option(
        None, help="Beam: cost of leaving an observation unassigned. Default: from the data (clutter "
        "uniform over the measured volume; about 18 for the real file's camera).", show_default=False
    ),
    slip_inflation: Optional[float] = library_option(
        "Beam: covariance factor of the odometry-slip hypothesis.",
        "localizer.slip_inflation"
    ),
    slip_cost: Optional[float] = library_option(
        "Beam: extra cost of the odometry-slip hypothesis.",
        "localizer.slip_cost"
    ),
    recheck: Optional[bool] = library_option(
        "After each update, judge every pair again by the "
        "posterior of the pose's other pairs and drop the ones that do not hold (not for oracle).",
        "localizer.recheck", "--recheck/--no-recheck"
    ),
    recheck_margin: Optional[float] = library_option(
        "Re-check: drop a pair when leaving its observation unassigned or pairing it "
        "with another landmark costs no more than this.",
        "localizer.recheck_margin"
    ),
    recheck_steal_margin: Optional[float] = library_option(
        "Re-check: drop a pair when another observation of the pose could take its "
        "landmark for no more than this extra cost (two detections fit one landmark).",
        "localizer.recheck_steal_margin"
    ),
    jcbb_max_nodes: Optional[int] = library_option(
        "JCBB: most joint compatibility tests per pose; past it the best set found is "
        "kept.",
        "localizer.jcbb_max_nodes"
    ),
    min_depth: Optional[float] = typer.Option(
        None, help="Nearest candidate landmark depth, metres. Default: 0 (no lower bound).", show_default=False
    ),
    max_depth: Optional[float] = typer.Option(
        None, help="Farthest candidate landmark depth, metres. Default: from the data "
        "(1.25 x the largest measured depth + 0.5).", show_default=False
    ),
    max_angle: Optional[float] = typer.Option(
        None, help="Candidates within this angle of the optical axis, degrees. Default: from the data "
        "(widest observed ray + 10).", show_default=False
    ),
    initial_sigma_xyz: Optional[float] = library_option(
        "Standard deviation of the start position, metres.",
        "localizer.initial_sigma_xyz"
    ),
    initial_sigma_deg: Optional[float] = library_option(
        "Standard deviation of the start orientation, degrees.",
        "localizer.initial_sigma_deg"
    ),
    json_output: bool = json_option("the run summary (what summary.json holds)"),
    quiet: bool = quiet_option(),
) -> None:
    """Localize the robot of DATASET in its landmark map and write the run folder.

    The run folder gets estimate.tum, odometry.tum, groundtruth.tum (with ground truth), associations.csv, states.npz and summary.json, written all at once or not at all. Prints the trajectory error of the EKF and of odometry alone, the associations and the speed.
    """
    from camloc.config import read_config_file
    from camloc.options import RUN_OPTIONS, run_config
    from camloc.pipeline import DEFAULT_DATASET, default_output_dir, run_dataset

    # Each localizer option's parameter is named after its command-line flag, so the options pass on
    # by those names (enums as their text); camloc.options maps them onto LocalizerConfig.
    options = {name.replace("_", "-"): value.value if isinstance(value, Enum) else value
               for name, value in locals().items() if name.replace("_", "-") in RUN_OPTIONS}
    config = run_config(options, read_config_file(config_file) if config_file else None)
    dataset_path = dataset if dataset is not None else DEFAULT_DATASET
    output_dir = output if output is not None else default_output_dir(dataset_path)

    from camloc.cli.progress import pose_progress

    import warnings

    from camloc.g2o import G2oWarning

    from camloc.kernels import cache_is_warm

    if not (quiet or json_output) and config.filter == "euler" and not cache_is_warm():
        err_console.print("compiling camloc's kernels: once after an install, about a minute", highlight=False)
    with warnings.catch_warnings(), pose_progress(
        enabled=not (quiet or json_output), description=f"localizing {dataset_path.name}"
    ) as on_progress:
        # The reader's warnings are part of the summary, printed once below.
        warnings.simplefilter("ignore", G2oWarning)
        result, written = run_dataset(dataset_path, config, output_dir, force=force, on_progress=on_progress)

    if echo_json(result.summary, enabled=json_output):
        return
    if not quiet:
        from camloc.cli.run_render import render_run_summary

        console.print(render_run_summary(result.summary, written))
        for warning in result.summary.get("warnings", []):
            err_console.print(f"[yellow]warning:[/] {escape(warning)}", highlight=False)
