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
    print_warnings,
    quiet_option,
)


class FilterChoice(str, Enum):
    auto = "auto"
    euler = "euler"
    se3 = "se3"
    se2 = "se2"


class AssociationChoice(str, Enum):
    beam = "beam"
    jcbb = "jcbb"
    best_friends = "best-friends"
    oracle = "oracle"


class MapChoice(str, Enum):
    auto = "auto"
    exact = "exact"
    prior = "prior"
    none = "none"


class CostChoice(str, Enum):
    nll = "nll"
    mahalanobis = "mahalanobis"
    euclidean = "euclidean"


# The help's panels: each method's own options, then the options of every method but oracle and of
# all; their config file's table in brackets (camloc.options).
BEAM = escape("Beam: --association beam; [beam] in a config file")
BEST_FRIENDS = escape("Best friends (and jcbb's seed): [best-friends] in a config file")
JCBB = escape("JCBB: --association jcbb; [jcbb] in a config file")
RECHECK = escape("Re-check: every association but oracle; [recheck] in a config file")
VIEW = escape("Candidate landmarks: all associations but oracle; [view] in a config file")


# The command's arguments and options, in its signature's order (their help is ``--help``'s text).
_DATASET = dataset_argument(
    "g2o dataset to localize, or the name of a bundled one (grid-small, smooth3d-clutter, pixel-2cam). "
    "Default: the bundled grid-small.g2o.", required=False
)
_OUTPUT = typer.Option(
    None, "--output", "-o", help="Run folder to write (missing parent folders are created); an existing "
    "run folder is refused unless --force. Default: runs/<dataset name>.", show_default=False
)
_FORCE = force_option("the run folder (files in it that are not camloc's are kept)")
_CONFIG_FILE = typer.Option(
    None, "--config", help=escape("TOML file of localizer options, named as on the command line: top-level "
    "ones as they are (gate = 0.95), a group's in its table without the group's prefix ([beam] width = 8 for "
    "--beam-width 8); options given on the command line win. Default: none."), show_default=False
)
_FILTER = library_option(
    "State parametrization: euler (x, y, z, roll, pitch, yaw; singular "
    "at pitch +-90 deg), se3 (error-state filter on SE(3), no singularity), se2 (error-state filter on "
    "SE(2): x, y, heading of a planar robot, 3 dof; the only one that takes a planar file's EDGE_SE2_XY and "
    "EDGE_SE2_MARKER observations), or auto: se2 for a planar file (VERTEX_SE2 / EDGE_SE2), euler otherwise. "
    "se2 runs in the numpy engine.",
    "localizer.filter", "--filter"
)
_ASSOCIATION = library_option(
    "Data association: beam (a beam of association hypotheses), jcbb (joint "
    "compatibility branch and bound, seeded by best friends), best-friends (mutual best match with gates) "
    "or oracle (the file's landmark ids, gated; for comparison). Only oracle reads the file's ids. "
    "An option of a method that is not selected is refused.",
    "localizer.association"
)
_ITERATIONS = library_option(
    "Linearizations per update: 1 = EKF, more = iterated EKF.",
    "localizer.iterations"
)
_GATE = library_option(
    "Chi-square gate probability on each pair's innovation, with its measurement's degrees of freedom (3 for a "
    "camera with depth or disparity, 2 for a pixel-only one or a planar point, 3 for a planar marker; a tag's orientation adds 3).",
    "localizer.gate", "--gate"
)
_NULL_COST = typer.Option(
    None, help="Cost of calling an observation clutter instead of pairing it (beam and re-check), in cost units "
    "(2 x negative log-likelihood: +2 = e times less likely; docs/association.md). Default: from the "
    "data (clutter uniform over the measured volume; about 18 for the real file's camera).", show_default=False
)
_MAP = library_option(
    "How the file's map is held: exact (landmarks where the map says them; where the rejected observations "
    "agree on places the map has no landmark at, those landmarks are added), prior (mapped landmarks are "
    "estimated too, pulled toward the map with --map-sigma), none (the map's positions unused: everything is "
    "mapped). Landmarks added (EKF-SLAM) are in map.csv of the run folder (docs/mapping.md): point landmarks of "
    "3-D cameras with depth or disparity and a planar robot's points and markers; a pixel-only camera's rays "
    "are mapped under prior and none only; tags are mapped with their orientations (map.csv's orientation columns). "
    "auto: exact for a file with a map, none for one without.",
    "localizer.map", "--map"
)
_MAP_SIGMA = library_option(
    "With --map prior: the map's standard deviation per axis, metres.",
    "localizer.map_sigma", "--map-sigma"
)
_INITIAL_SIGMA_XYZ = library_option(
    "Standard deviation of the start position, metres.",
    "localizer.initial_sigma_xyz"
)
_INITIAL_SIGMA_DEG = library_option(
    "Standard deviation of the start orientation, degrees.",
    "localizer.initial_sigma_deg"
)
_BEAM_WIDTH = library_option(
    "Association hypotheses kept after each pose (more, and further in cost, at a pose of a few pixel observations "
    "only: docs/beam.md).",
    "localizer.beam.width", rich_help_panel=BEAM
)
_BEAM_DELTA = library_option(
    "Drop hypotheses this much costlier than the best, in cost units (2 x log-likelihood ratio; docs/beam.md). "
    "Lower runs faster but keeps fewer ways back: 8 halved a pixel-only world's time and lost the robot on two "
    "of four simulated aerial worlds.",
    "localizer.beam.delta", rich_help_panel=BEAM
)
_BRANCH_DELTA = library_option(
    "Explore only the options of an observation within this many cost units (2 x log-likelihood ratio) of its "
    "best (docs/beam.md). Much lower can lose the robot, and a lost run searches every pose from seeds: 2 "
    "turned a 3,000-pose pixel-only world's 3 s into over 5 minutes.",
    "localizer.beam.branch_delta", rich_help_panel=BEAM
)
_SLIP_INFLATION = library_option(
    "Slip (odometry that jumped): the factor on the predicted covariance when a pose is explained as one "
    "(docs/beam.md).",
    "localizer.beam.slip_inflation", rich_help_panel=BEAM
)
_SLIP_COST = library_option(
    "Slip (odometry that jumped): the extra cost, in cost units (2 x log-likelihood ratio), of explaining a pose "
    "as one (docs/beam.md).",
    "localizer.beam.slip_cost", rich_help_panel=BEAM
)
_COST = library_option(
    "Pair cost: nll (Mahalanobis + log det S), mahalanobis, euclidean.",
    "localizer.best_friends.cost", rich_help_panel=BEST_FRIENDS
)
_MARGIN = library_option(
    "Reject a pair whose closest rival is within this many cost units (2 x log-likelihood ratio; "
    "docs/association.md).",
    "localizer.best_friends.margin", rich_help_panel=BEST_FRIENDS
)
_SEQUENTIAL = library_option(
    "Accept pairs one at a time, conditioning on each (sequential), or all at once (batch, the original "
    "method). Best friends only.",
    "localizer.best_friends.sequential", "--sequential/--batch", rich_help_panel=BEST_FRIENDS
)
_JCBB_MAX_NODES = library_option(
    "Most joint compatibility tests per pose; past it the best set found is kept.",
    "localizer.jcbb.max_nodes", rich_help_panel=JCBB
)
_RECHECK = library_option(
    "After each update, judge every pair again by the posterior of the pose's other pairs and drop the "
    "ones that do not hold.",
    "localizer.recheck.enabled", "--recheck/--no-recheck", rich_help_panel=RECHECK
)
_RECHECK_MARGIN = library_option(
    "Drop a pair when leaving its observation unassigned or pairing it with another landmark costs no "
    "more than this, in cost units (2 x log-likelihood ratio; docs/association.md).",
    "localizer.recheck.margin", rich_help_panel=RECHECK
)
_RECHECK_STEAL_MARGIN = library_option(
    "Drop a pair when another observation of the pose could take its landmark for no more than this "
    "many extra cost units (2 x log-likelihood ratio: 6 = 20 times; docs/association.md).",
    "localizer.recheck.steal_margin", rich_help_panel=RECHECK
)
_RECHECK_RAY_MARGIN = library_option(
    "Drop a pixel observation's pair when another landmark near its ray costs no more than this many "
    "extra cost units (2 x log-likelihood ratio; docs/association.md).",
    "localizer.recheck.ray_margin", rich_help_panel=RECHECK
)
_MIN_DEPTH = typer.Option(
    None, help="Nearest candidate landmark depth, metres. Default: 0 (no lower bound).", show_default=False,
    rich_help_panel=VIEW
)
_MAX_DEPTH = typer.Option(
    None, help="Farthest candidate landmark depth, metres. Default: from the data "
    "(1.25 x the largest measured depth + 0.5; a pixel-only file: 1.1 x the cameras' reach learned from "
    "the run over its first 300 poses).", show_default=False, rich_help_panel=VIEW
)
_MAX_ANGLE = typer.Option(
    None, help="Candidates within this angle of the optical axis, degrees. Default: from the data "
    "(widest observed ray + 10).", show_default=False, rich_help_panel=VIEW
)
_MAX_DISTANCE = typer.Option(
    None, help="Farthest candidate landmark from the camera's centre, metres. Default: no bound (a pixel-only "
    "file: 1.1 x the cameras' reach learned from the run over its first 300 poses, a distance).", show_default=False,
    rich_help_panel=VIEW
)
_JSON_OUTPUT = json_option("the run summary (what summary.json holds)")
_QUIET = quiet_option()


def run(
    dataset: Optional[Path] = _DATASET,
    output: Optional[Path] = _OUTPUT,
    force: bool = _FORCE,
    config_file: Optional[Path] = _CONFIG_FILE,
    filter: Optional[FilterChoice] = _FILTER,  # noqa: A002 (named after --filter)
    association: Optional[AssociationChoice] = _ASSOCIATION,
    iterations: Optional[int] = _ITERATIONS,
    gate: Optional[float] = _GATE,
    null_cost: Optional[float] = _NULL_COST,
    map: Optional[MapChoice] = _MAP,  # noqa: A002 (named after --map)
    map_sigma: Optional[float] = _MAP_SIGMA,
    initial_sigma_xyz: Optional[float] = _INITIAL_SIGMA_XYZ,
    initial_sigma_deg: Optional[float] = _INITIAL_SIGMA_DEG,
    beam_width: Optional[int] = _BEAM_WIDTH,
    beam_delta: Optional[float] = _BEAM_DELTA,
    branch_delta: Optional[float] = _BRANCH_DELTA,
    slip_inflation: Optional[float] = _SLIP_INFLATION,
    slip_cost: Optional[float] = _SLIP_COST,
    cost: Optional[CostChoice] = _COST,
    margin: Optional[float] = _MARGIN,
    sequential: Optional[bool] = _SEQUENTIAL,
    jcbb_max_nodes: Optional[int] = _JCBB_MAX_NODES,
    recheck: Optional[bool] = _RECHECK,
    recheck_margin: Optional[float] = _RECHECK_MARGIN,
    recheck_steal_margin: Optional[float] = _RECHECK_STEAL_MARGIN,
    recheck_ray_margin: Optional[float] = _RECHECK_RAY_MARGIN,
    min_depth: Optional[float] = _MIN_DEPTH,
    max_depth: Optional[float] = _MAX_DEPTH,
    max_angle: Optional[float] = _MAX_ANGLE,
    max_distance: Optional[float] = _MAX_DISTANCE,
    json_output: bool = _JSON_OUTPUT,
    quiet: bool = _QUIET,
) -> None:
    """Localize the robot of DATASET in its landmark map and write the run folder.

    The run folder gets estimate.tum, odometry.tum, groundtruth.tum (with ground truth), associations.csv, states.npz and summary.json (and map.csv where landmarks were mapped), written all at once or not at all. Prints the trajectory error of the filter (named by what ran: iterated EKF (euler) by default; odometry alone when no observation could be used) and of odometry alone, the associations and the speed.

    The first run after an install compiles camloc's kernels (a minute or two, once). On a dataset numpy takes under about 20 s over (some 5,300 poses of 8 observations with depth) it does not wait: it runs in numpy, which gives the same result, while the kernels compile in the background for the runs after it (CAMLOC_BACKGROUND_COMPILE=0 compiles first).
    """
    from camloc.bundled import resolve_dataset
    from camloc.config import read_config_file, run_config
    from camloc.options import RUN_OPTIONS
    from camloc.pipeline import DEFAULT_DATASET, default_output_dir, run_dataset

    # Each localizer option's parameter is named after its command-line flag, so the options pass on
    # by those names (enums as their text); camloc.options maps them onto LocalizerConfig.
    options = {name.replace("_", "-"): value.value if isinstance(value, Enum) else value
               for name, value in locals().items() if name.replace("_", "-") in RUN_OPTIONS}
    config = run_config(options, read_config_file(config_file) if config_file else None)
    dataset_path = resolve_dataset(dataset) if dataset is not None else DEFAULT_DATASET
    output_dir = output if output is not None else default_output_dir(dataset_path)

    from camloc.cli.interrupts import outputs_being_saved
    from camloc.cli.progress import pose_progress

    import warnings

    from camloc.g2o import G2oWarning

    with warnings.catch_warnings(), pose_progress(
        enabled=not (quiet or json_output), description=f"localizing {dataset_path.name}"
    ) as on_progress:
        # The reader's warnings are part of the summary, printed once below.
        warnings.simplefilter("ignore", G2oWarning)
        result, written = run_dataset(dataset_path, config, output_dir, force=force, on_progress=on_progress,
                                      on_compile=None if quiet or json_output else _say_compiling,
                                      on_background_compile=_say_compiling_in_background if not (quiet or json_output)
                                      else lambda started: None,
                                      while_saving=outputs_being_saved)

    if echo_json(result.summary, enabled=json_output):
        return  # the warnings are the object's "warnings"
    if not quiet:
        from camloc.cli.run_render import render_run_summary

        console.print(render_run_summary(result.summary, written))
    print_warnings(result.summary.get("warnings", []), dataset_path)  # named by the dataset, as errors are


def _say_compiling() -> None:
    err_console.print("compiling camloc's kernels: once after an install, a minute or two", highlight=False)


def _say_compiling_in_background(started: bool) -> None:
    what = "compiling camloc's kernels in the background (once after an install, a minute or two)" if started else \
        "camloc's kernels are still compiling in the background"
    err_console.print(f"{what}; this run uses the numpy engine, which gives the same result", highlight=False)
