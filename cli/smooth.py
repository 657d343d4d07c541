"""``camloc smooth``: the maximum a posteriori trajectory of a run folder, written as smoothed.tum."""

from __future__ import annotations

import contextlib
import time
from enum import Enum
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Optional

import typer

from camloc.cli.common import (
    console,
    echo_json,
    err_console,
    json_option,
    library_option,
    print_warnings,
    quiet_option,
    run_dir_argument,
)
from camloc.errors import CamlocError


class MapChoice(str, Enum):
    exact = "exact"
    prior = "prior"
    none = "none"


def smooth(
    run_dir: Path = run_dir_argument(),
    *,
    dataset: Optional[Path] = typer.Option(
        None, "--dataset", metavar="DATASET", help="The g2o file the run was made from. Default: the path "
        "recorded in the run's summary.json (as given to 'camloc run', else its absolute path).", show_default=False
    ),
    huber: Optional[float] = library_option(
        "Huber threshold on each observation's Mahalanobis distance (whitened "
        "units): farther observations pull with a constant force; 'inf' gives plain least squares.",
        "smoother.huber", "--huber"
    ),
    max_iterations: Optional[int] = library_option(
        "Most linearizations (Gauss-Newton / Levenberg-Marquardt steps) before stopping; a run that stops there "
        "is reported as not converged.", "smoother.max_iterations", "--max-iterations", min=1
    ),
    map_mode: Optional[MapChoice] = library_option(
        "How the map's landmarks are held: 'exact' (fixed at the map, as the filter used them), 'prior' "
        "(estimated with the poses, pulled toward the map with --map-sigma) or 'none' (estimated from the "
        "observations alone; the start pose fixes the frame). Landmarks the map lacks that observations are "
        "assigned to are estimated in every mode. The map after smoothing is written as map.csv.",
        "smoother.map", "--map"
    ),
    map_sigma: Optional[float] = library_option(
        "Standard deviation of the map prior per axis, metres (with --map prior; a planar marker's heading is "
        "held to the same number read as radians, as 'camloc run' holds it).", "smoother.map_sigma",
        "--map-sigma"
    ),
    json_output: bool = json_option("the report"),
    quiet: bool = quiet_option(),
) -> None:
    """Smooth a run: the most probable trajectory given all the odometry and every observation the run accepted, all poses at once (the filter only used the past).

    The first pose stays at the dataset's start pose; observations beyond the Huber threshold are down-weighted. With --map prior or none the landmarks are estimated too. A planar dataset (VERTEX_SE2 / EDGE_SE2) is smoothed in SE(2) (x, y, heading: camloc/smoother_se2.py), its landmarks as --map says (cameras' 3-D points; floor points and markers on the floor, a marker's heading estimated too, though map.csv has no column for it), any other in SE(3). Writes smoothed.tum and map.csv (the map after smoothing: a row per landmark with its covariance) into RUN_DIR (each whole or not at all); 'camloc eval' and 'camloc plot' then show the smoothed path beside the filter's and odometry. Prints position and rotation (a planar robot's: heading) RMSE of the filter and of the smoothed path when there is ground truth, iterations, final cost and time.
    """
    import warnings

    from camloc import smoother
    from camloc.cli.interrupts import outputs_being_saved
    from camloc.diagnostics import estimate_name
    from camloc.g2o import G2oWarning, read_g2o
    from camloc.results import load_run, write_map, write_smoothed

    given = {"huber": huber, "max_iterations": max_iterations, "map": map_mode.value if map_mode else None,
             "map_sigma": map_sigma}
    config = smoother.SmootherConfig(**{name: value for name, value in given.items() if value is not None})
    config.validate()
    started = time.perf_counter()
    run = load_run(run_dir, smoothed=False)  # a damaged smoothed.tum is what smoothing again mends
    dataset_path = dataset if dataset is not None else _recorded_dataset(run_dir, run.summary, run.dataset)
    with warnings.catch_warnings():
        # 'camloc run' already reported the reader's warnings about this file.
        warnings.simplefilter("ignore", G2oWarning)
        data = read_g2o(dataset_path)
    read_seconds = time.perf_counter() - started

    with _iteration_status(enabled=not (json_output or quiet)) as on_iteration:
        result = _smoothed(data, run, config, on_iteration)
    landmark_map = smoother.estimated_map(data, run, result, config)
    with outputs_being_saved():  # both files, or a Ctrl-C before them leaves neither
        written = write_smoothed(run_dir, run.pose_ids, result.xyz, result.quat_xyzw)
        map_file = write_map(run_dir, landmark_map)

    report = smoother.smoothing_report(run, result, config)
    report["dataset"] = str(dataset_path)
    report["timing"] = {"read_seconds": read_seconds, **report["timing"]}
    report["smoothed_file"] = str(written)
    report["map_file"] = str(map_file)
    report["estimate_name"] = estimate_name(run.summary)
    if echo_json(report, enabled=json_output):
        return  # "converged": false says it
    if not quiet:
        console.print(render_smoothing(report))
    if not report["converged"]:
        print_warnings(["stopped at --max-iterations before the steps became tiny"], run_dir)


def _smoothed(data, run, config, on_iteration):
    """The smoothing of ``run`` with the landmarks as ``config.map`` says: in SE(2) for a planar
    robot (its odometry has no z, roll or pitch noise), in SE(3) otherwise."""
    from camloc import smoother

    if data.planar:
        from camloc.smoother_se2 import smooth_planar_run

        return smooth_planar_run(data, run, config, on_iteration=on_iteration)
    return smoother.smooth_run(data, run, config, on_iteration=on_iteration)


def _recorded_dataset(run_dir: Path, summary: Mapping[str, Any], fallback: str) -> Path:
    """The run's g2o file: its path as given to `camloc run`, else its absolute path then (a run
    started in another folder; summaries before 2026-12-06 lack it)."""
    recorded = summary.get("dataset") or fallback
    for path in (Path(str(recorded)), Path(str(summary.get("dataset_resolved") or recorded))):
        if path.is_file():
            return path
    raise CamlocError(f"{run_dir}: the run's dataset {recorded} is not there (moved or deleted since the run); "
                      "pass the g2o file with --dataset FILE")


@contextlib.contextmanager
def _iteration_status(*, enabled: bool) -> Iterator[Optional[Callable]]:
    """A transient status line on stderr with the iteration and cost, or None (also when stderr
    is not a terminal)."""
    if not (enabled and err_console.is_terminal):
        yield None
        return
    with err_console.status("smoothing: linearizing") as status:

        def on_iteration(iteration) -> None:
            status.update(f"smoothing: iteration {iteration.number}, cost {iteration.cost:.6g}")

        yield on_iteration


def _map_row(report: Mapping[str, Any]) -> str:
    held = {"exact": "held exact", "none": "not used"}.get(report["map"]) or f"prior, sigma {report['map_sigma']:g} m"
    landmarks = report["landmarks"]
    return f"{held}; {landmarks['estimated']} landmarks estimated ({landmarks['added']} added)"


def render_smoothing(report: Mapping[str, Any]):
    """Tables of a ``camloc.smoother.smoothing_report`` (with ``output`` and ``read_seconds``)."""
    from rich.console import Group
    from rich.markup import escape
    from rich.table import Table
    from rich.text import Text

    parts: list = [Text(f"camloc smooth: {Path(str(report['dataset'])).name} ({report['counts']['poses']} poses)",
                        style="bold")]
    if report["estimate"] is not None:
        table = Table(title="error vs ground truth (no alignment)", title_justify="left")
        name = escape(str(report.get("estimate_name") or "filter"))
        for column in ("", name, "smoothed", "smoothed / filter"):
            table.add_column(column, justify="right" if column else "left")
        for label, (block, key), spec in (("position RMSE [m]", ("ate", "rmse"), ".4f"),
                                          ("rotation RMSE [deg]", ("rotation", "rmse_deg"), ".3f")):
            before, after = report["estimate"][block][key], report["smoothed"][block][key]
            ratio = f"{after / before:.2f}x" if before else "-"
            table.add_row(escape(label), format(before, spec), format(after, spec), Text(ratio, style="bold"))
        parts.append(table)
    else:
        parts.append(Text("no ground truth in the run: errors are not computed", style="yellow"))

    table = Table(title="optimization", title_justify="left", show_header=False)
    table.add_column("what")
    table.add_column("value", justify="right")
    huber = "off (least squares)" if report["huber"] is None else f"{report['huber']:g}"
    iterations = f"{report['iterations']}" + ("" if report["converged"] else " (not converged)")
    condition = "-" if report["condition_estimate"] is None else f"{report['condition_estimate']:.3g}"
    rows = (
        ("factors", f"{report['odometry_factors']} odometry, {report['observation_factors']} observations"),
        ("Huber threshold", huber),
        ("map", _map_row(report)),
        ("down-weighted observations", str(report["downweighted_observations"])),
        ("iterations", iterations),
        ("cost, initial -> final", f"{report['initial_cost']:.6g} -> {report['final_cost']:.6g}"),
        ("condition estimate", condition),
        ("time", f"{report['timing']['smooth_seconds']:.2f} s smoothing, "
                 f"{report['timing']['read_seconds']:.2f} s reading"),
    )
    for label, value in rows:
        table.add_row(escape(label), escape(value))
    parts.append(table)
    if report["dropped_observations"]:
        parts.append(Text(f"note: {report['dropped_observations']} accepted observation(s) left out: their landmark "
        "is behind the camera at the filter's poses", style="yellow"))
    if report["landmarks"]["undetermined"]:
        parts.append(Text(f"note: {report['landmarks']['undetermined']} landmark(s) left out with their observations: "
                          "the observations do not place them (a single pixel ray, or rays with too little parallax) "
                          "and no map prior holds them", style="yellow"))
    parts.append(Text(f"wrote {report['smoothed_file']} and {report['map_file']}"))
    return Group(*parts)
