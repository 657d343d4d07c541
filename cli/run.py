"""``camloc run``: localize a dataset and write the run folder."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape

from camloc.cli.common import console, err_console, handles_errors


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


@handles_errors
def run(
    dataset: Optional[Path] = typer.Argument(
        None, help="g2o dataset to localize. Default: the bundled grid-small.g2o.", show_default=False
    ),
    output: Optional[Path] = typer.Option(
        None, "--output", "-o", help="Run folder to write. Default: runs/<dataset name>.", show_default=False
    ),
    config_file: Optional[Path] = typer.Option(
        None, "--config", help="TOML file with localizer options (names as below, with underscores); "
        "options given on the command line win. Default: none.", show_default=False
    ),
    filter_kind: Optional[FilterChoice] = typer.Option(
        None, "--filter", help="State parametrization: euler (x, y, z, roll, pitch, yaw; singular at pitch "
        "+-90 deg) or se3 (error-state filter on SE(3), no singularity). Default: euler.", show_default=False
    ),
    association: Optional[AssociationChoice] = typer.Option(
        None, help="Data association: beam (a beam of association hypotheses), jcbb (joint compatibility "
        "branch and bound, seeded by best friends), best-friends (mutual best match with gates) or oracle "
        "(the file's landmark ids, gated; for comparison). Only oracle reads the file's ids. Default: beam.",
        show_default=False
    ),
    iterations: Optional[int] = typer.Option(
        None, help="Linearizations per update: 1 = EKF, more = iterated EKF. Default: 3.", show_default=False
    ),
    gate_probability: Optional[float] = typer.Option(
        None, "--gate", help="Chi-square gate probability on each pair's innovation (3 dof). Default: 0.99.",
        show_default=False
    ),
    cost: Optional[CostChoice] = typer.Option(
        None, help="Best-friends pair cost: nll (Mahalanobis + log det S), mahalanobis, euclidean. Default: nll.",
        show_default=False
    ),
    margin: Optional[float] = typer.Option(
        None, help="Lonely-best-friends margin in cost units: reject a pair whose closest rival is "
        "within it. Default: 1.0.", show_default=False
    ),
    sequential: Optional[bool] = typer.Option(
        None, "--sequential/--batch", help="Accept best-friends pairs one at a time, conditioning on "
        "each (sequential), or all at once (batch, the original method). Default: sequential.", show_default=False
    ),
    beam_width: Optional[int] = typer.Option(
        None, help="Beam: association hypotheses kept after each pose. Default: 16.", show_default=False
    ),
    beam_delta: Optional[float] = typer.Option(
        None, help="Beam: drop hypotheses this much costlier than the best (2 x log-likelihood ratio). "
        "Default: 14.", show_default=False
    ),
    branch_delta: Optional[float] = typer.Option(
        None, help="Beam: explore only an observation's options within this cost of its best. Default: 8.",
        show_default=False
    ),
    null_cost: Optional[float] = typer.Option(
        None, help="Beam: cost of leaving an observation unassigned. Default: from the data (clutter "
        "uniform over the measured volume; about 18 for the real file's camera).", show_default=False
    ),
    slip_inflation: Optional[float] = typer.Option(
        None, help="Beam: covariance factor of the odometry-slip hypothesis. Default: 25.", show_default=False
    ),
    slip_cost: Optional[float] = typer.Option(
        None, help="Beam: extra cost of the odometry-slip hypothesis. Default: 10.", show_default=False
    ),
    recheck: Optional[bool] = typer.Option(
        None, "--recheck/--no-recheck", help="After each update, judge every pair again by the posterior "
        "of the pose's other pairs and drop the ones that do not hold (not for oracle). Default: --recheck.",
        show_default=False
    ),
    recheck_margin: Optional[float] = typer.Option(
        None, help="Re-check: drop a pair when leaving its observation unassigned or pairing it with "
        "another landmark costs no more than this. Default: 0.", show_default=False
    ),
    recheck_steal_margin: Optional[float] = typer.Option(
        None, help="Re-check: drop a pair when another observation of the pose could take its landmark "
        "for no more than this extra cost (two detections fit one landmark). Default: 6.", show_default=False
    ),
    jcbb_max_nodes: Optional[int] = typer.Option(
        None, help="JCBB: most joint compatibility tests per pose; past it the best set found is kept. "
        "Default: 2000.", show_default=False
    ),
    min_depth: Optional[float] = typer.Option(
        None, help="Nearest candidate landmark depth, metres. Default: 0.", show_default=False
    ),
    max_depth: Optional[float] = typer.Option(
        None, help="Farthest candidate landmark depth, metres. Default: from the data "
        "(1.25 x the largest measured depth + 0.5).", show_default=False
    ),
    max_angle: Optional[float] = typer.Option(
        None, help="Candidates within this angle of the optical axis, degrees. Default: from the data "
        "(widest observed ray + 10).", show_default=False
    ),
    initial_sigma_xyz: Optional[float] = typer.Option(
        None, help="Standard deviation of the start position, metres. Default: 0.01.", show_default=False
    ),
    initial_sigma_deg: Optional[float] = typer.Option(
        None, help="Standard deviation of the start orientation, degrees. Default: 0.5.", show_default=False
    ),
    json_output: bool = typer.Option(False, "--json", help="Print the run summary as JSON instead of tables. Default: tables."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Print nothing but errors. Default: off."),
) -> None:
    """Localize the robot of DATASET in its landmark map and write the run folder.

    The run folder gets estimate.tum, odometry.tum, groundtruth.tum (with ground truth), associations.csv, states.npz and summary.json, written all at once or not at all.
    """
    from camloc.config import make_config, read_config_file
    from camloc.pipeline import DEFAULT_DATASET, default_output_dir, run_dataset

    overrides = {
        "filter": filter_kind.value if filter_kind else None,
        "association": association.value if association else None,
        "iterations": iterations,
        "gate_probability": gate_probability,
        "cost": cost.value if cost else None,
        "margin": margin,
        "sequential": sequential,
        "beam_width": beam_width,
        "beam_delta": beam_delta,
        "branch_delta": branch_delta,
        "null_cost": null_cost,
        "slip_inflation": slip_inflation,
        "slip_cost": slip_cost,
        "recheck": recheck,
        "recheck_margin": recheck_margin,
        "recheck_steal_margin": recheck_steal_margin,
        "jcbb_max_nodes": jcbb_max_nodes,
        "min_depth": min_depth,
        "max_depth": max_depth,
        "max_angle_deg": max_angle,
        "initial_sigma_xyz": initial_sigma_xyz,
        "initial_sigma_deg": initial_sigma_deg,
    }
    config = make_config(read_config_file(config_file) if config_file else None, overrides)
    dataset_path = dataset if dataset is not None else DEFAULT_DATASET
    output_dir = output if output is not None else default_output_dir(dataset_path)

    from camloc.cli.progress import pose_progress

    import warnings

    from camloc.g2o import G2oWarning

    with warnings.catch_warnings(), pose_progress(
        enabled=not (quiet or json_output), description=f"localizing {dataset_path.name}"
    ) as on_progress:
        # The reader's warnings are part of the summary, printed once below.
        warnings.simplefilter("ignore", G2oWarning)
        result, written = run_dataset(dataset_path, config, output_dir, on_progress=on_progress)

    if json_output:
        from camloc.results import dumps_json

        typer.echo(dumps_json(result.summary), nl=False)
    elif not quiet:
        from camloc.cli.run_render import render_run_summary

        console.print(render_run_summary(result.summary, written))
        for warning in result.summary.get("warnings", []):
            err_console.print(f"[yellow]warning:[/] {escape(warning)}", highlight=False)
