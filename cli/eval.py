"""``camloc eval``: metrics of a run folder, or of two TUM trajectories."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer

from camloc.cli.common import console, echo_json, json_option, quiet_option, run_dir_argument, with_default
from camloc.errors import ConfigError


class AlignChoice(str, Enum):
    none = "none"
    se3 = "se3"
    sim3 = "sim3"


def evaluate_command(
    run_dir: Optional[Path] = run_dir_argument(
        "Run folder written by 'camloc run'. Omit it to compare --est with --ref.", required=False
    ),
    *,
    align: AlignChoice = typer.Option(
        AlignChoice.none, "--align", help=with_default("Align each trajectory to the ground truth before ATE/RPE: "
        "none, se3 (rotation + translation, like evo -a) or sim3 (and scale, like evo -as), by Umeyama's method. "
        "NEES always uses the unaligned estimate."), show_default=False
    ),
    delta: int = typer.Option(
        1, "--delta", min=1, help=with_default("RPE pose distance, in frames (evo_rpe --delta N --delta_unit f)."),
        show_default=False
    ),
    est: Optional[Path] = typer.Option(
        None, "--est", help="Estimated trajectory, TUM file (with --ref, instead of RUN_DIR). Default: none.",
        show_default=False
    ),
    ref: Optional[Path] = typer.Option(
        None, "--ref", help="Reference (ground-truth) trajectory, TUM file (with --est). Default: none.",
        show_default=False
    ),
    max_diff: float = typer.Option(
        0.01, "--max-diff", min=0.0, help=with_default("Largest timestamp difference when pairing --est and --ref "
        "poses (camloc writes pose ids as timestamps)."), show_default=False
    ),
    true_map: Optional[Path] = typer.Option(
        None, "--true-map", metavar="DATASET", help="A g2o file whose landmarks are the true map (for a world of "
        "'camloc simulate --withhold-map/--move-map/--no-map': the <stem>.true-map.g2o it wrote): scores the run's "
        "map.csv (without one, the map the run was given, held exactly): position RMSE and NEES of mapped, moved and added landmarks (an added one against the true "
        "landmark most of its observations are), landmarks added twice, clutter made into landmarks, landmarks "
        "never added (docs/json.md). Default: none.", show_default=False
    ),
    json_output: bool = json_option("the metrics"),
    quiet: bool = quiet_option(),
) -> None:
    """Evaluate a run: trajectory error (ATE, rotation, RPE) of the filter and of odometry alone side by side, data association scores, and filter consistency (NEES, NIS) with a verdict.

    The trajectories are read from the run folder's TUM files, so an edited one is scored as it is. With --est A.tum --ref B.tum instead of RUN_DIR, only the trajectory metrics of A against B, poses paired by timestamp. The numbers follow evo's definitions (evo_ape -r trans_part / angle_deg, evo_rpe --delta_unit f).
    """
    from camloc import metrics
    from camloc.results import load_run, read_tum

    if true_map is not None and run_dir is None:
        raise ConfigError("--true-map scores a run folder's map.csv: expected RUN_DIR")
    if run_dir is not None and (est is not None or ref is not None):
        raise ConfigError("expected either RUN_DIR or --est and --ref, found both")
    if run_dir is None:
        if est is None or ref is None:
            raise ConfigError("expected RUN_DIR, or --est A.tum together with --ref B.tum")
        report = metrics.compare_trajectories(
            *read_tum(est), *read_tum(ref), align=align.value, delta=delta, max_diff=max_diff
        )
        report = {"estimate_file": str(est), "reference_file": str(ref), **report}
    else:
        result = load_run(run_dir)
        report = metrics.evaluate(result, align=align.value, delta=delta)
        report["map"] = _map_score(run_dir, result, true_map) if true_map is not None else None

    if echo_json(report, enabled=json_output) or quiet:
        return
    from camloc.cli import eval_render

    if run_dir is None:
        console.print(eval_render.render_trajectory_comparison(report), soft_wrap=True)
    else:
        console.print(eval_render.render_run_evaluation(report))


def _map_score(run_dir: Path, result, true_map: Path) -> dict:
    """``map_scores.map_score`` of the run's map.csv against the landmarks of the g2o file ``true_map``,
    through the run's associations (each observation's true id) and the map it was given."""
    from camloc.cli.common import read_true_map
    from camloc.map_scores import map_score
    from camloc.results import run_map

    associations = result.associations
    estimated = run_map(result)  # without a map.csv, the given map held exactly
    truth = read_true_map(true_map, result)
    return map_score(estimated, given_ids=result.map_landmark_ids, given_xyz=result.map_landmark_xyz,
                     true_ids=truth.landmark_ids, true_xyz=truth.landmark_xyz,
                     obs_landmark=associations.landmark, obs_true=associations.true_landmark,
                     true_quat_xyzw=truth.landmark_quat_xyzw)
