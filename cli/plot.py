"""``camloc plot``: draw the figures of a run folder."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer

from camloc.cli.common import console, force_option, quiet_option, run_dir_argument, with_default
from camloc.errors import ConfigError


class FigureFormat(str, Enum):
    png = "png"
    pdf = "pdf"
    svg = "svg"


def plot(
    run_dir: Path = run_dir_argument(),
    *,
    output: Optional[Path] = typer.Option(
        None, "--output", "-o", help="Write one multi-panel report figure to this file instead (.png, .pdf or "
        ".svg, by its suffix; missing parent folders are created); an existing file is refused unless --force. "
        "Default: separate figures in the run folder.", show_default=False
    ),
    force: bool = force_option("the --output file"),
    figure_format: FigureFormat = typer.Option(
        FigureFormat.png, "--format", help=with_default("File format of the separate figures in the run folder "
                                                        "(ignored with --output)."), show_default=False
    ),
    dpi: int = typer.Option(150, min=50, max=1200, help=with_default("Resolution of raster (.png) figures, dots "
                                                                     "per inch."), show_default=False),
    true_map: Optional[Path] = typer.Option(
        None, "--true-map", metavar="DATASET", help="A g2o file whose landmarks are "
        "the true map (the <stem>.true-map.g2o of 'camloc simulate --withhold-map/--move-map/--no-map'), drawn on "
        "fig-map (or the report's map panel, with --output; without a map.csv, against the map the run was given) with a segment from each moved landmark's given position to its truth. Default: none.",
        show_default=False
    ),
    show: bool = typer.Option(False, "--show", help=with_default("Also open the figures in a window (needs a "
                                                                 "display); off: files only."), show_default=False),
    quiet: bool = quiet_option(),
) -> None:
    """Draw the figures of RUN_DIR: paths top-down and in 3D, position and rotation error with the filter's 3-sigma band, NEES and NIS with chi-square bounds, and associations per pose.

    By default writes fig-topdown, fig-3d (not for a planar run, --filter se2: its z is 0), fig-errors, fig-consistency and fig-associations (.png) into the run folder, and fig-map when the run folder has a map.csv (the given map, the estimated one with 2-sigma ellipses, added landmarks marked), replacing the ones drawn before; with --output a single report figure holding every panel (the map's too, when the run folder has a map.csv). The trajectories are read from the run folder's TUM files. The figures are written all or none, each whole.

    For a sweep folder (written by 'camloc sweep'), draws fig-sweep: the distribution of position RMSE per configuration (box and points, log scale, the oracle beside each method).
    """
    from camloc.atomic_files import write_files_atomic
    from camloc.results import load_run

    _check_output(output, force)
    from camloc.sweep import is_sweep_folder

    sweep = is_sweep_folder(run_dir)
    if sweep and true_map is not None:
        raise ConfigError(f"--true-map is drawn on a run's map figure: {run_dir} is a sweep folder")
    result = _load_sweep(run_dir) if sweep else load_run(run_dir)

    import matplotlib

    if not show:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from camloc import plotting

    if sweep:
        layouts = {output or run_dir / f"fig-sweep.{figure_format.value}": (plotting.sweep_size(result[0]),
                                                                             plotting.draw_sweep)}
    elif output is not None:
        layouts = {output: _report_layout(_map_view(result, true_map))}
    else:
        layouts = {run_dir / f"fig-{name}.{figure_format.value}": layout for name, layout in plotting.figures_of(result).items()}
        layouts.update(_map_layout(run_dir, result, true_map, figure_format.value))

    def render(path: Path, handle) -> None:
        size, draw = layouts[path]
        fig = plt.figure(figsize=size, layout="constrained")
        try:
            draw(fig, result)
            fig.savefig(handle, format=path.suffix.lower().lstrip("."), dpi=dpi)
        finally:
            if not show:
                plt.close(fig)

    # Every figure or none: each is rendered to a temporary file beside its target, and they are
    # renamed into place together once all have been drawn.
    written = list(layouts)
    write_files_atomic(written, render)
    if not quiet:
        for path in written:
            console.print(f"wrote {path}", markup=False, highlight=False, soft_wrap=True)
    if show:
        plt.show()


def _check_output(output: Optional[Path], force: bool) -> None:
    """Refuse an --output that is no figure file or exists (without --force)."""
    from camloc.atomic_files import refuse_existing_file
    from camloc.results import FIGURE_FORMATS

    if output is None:
        return
    if output.suffix.lower().lstrip(".") not in FIGURE_FORMATS:
        raise ConfigError(
            f"--output {output}: expected a file name ending in .png, .pdf or .svg, found {output.suffix or 'no suffix'!r}"
        )
    refuse_existing_file(output, force=force)


def _map_view(result, true_map: Optional[Path]):
    """The run's map as the map figure draws it (``plotting_map.MapView``) when the run folder has a
    map.csv, or with --true-map (a run without map.csv held its given map exactly: that map is
    drawn against the truth); else None."""
    from camloc.results import run_map

    if result.landmark_map is None and true_map is None:
        return None
    from camloc.plotting_map import MapView

    return MapView(result, run_map(result), *_true_landmarks(true_map, result))


def _map_layout(run_dir: Path, result, true_map: Optional[Path], suffix: str) -> dict:
    """{fig-map path: (size, draw)} when the run folder has a map.csv, else {}."""
    from camloc.results import MAP_FIGURE_NAME

    view = _map_view(result, true_map)
    if view is None:
        return {}
    from camloc.plotting_map import MAP_FIGURE_SIZE, draw_map

    return {run_dir / f"fig-{MAP_FIGURE_NAME}.{suffix}": (MAP_FIGURE_SIZE, lambda fig, _: draw_map(fig, view))}


def _report_layout(view) -> tuple:
    """(size, draw) of the one-page report: every panel, the map's too when ``view`` is one."""
    from camloc import plotting

    if view is None:
        return plotting.report_size(False), plotting.draw_report
    from camloc.plotting_map import plot_map

    return plotting.report_size(True), lambda fig, result: plotting.draw_report(fig, result, lambda ax: plot_map(ax, view))


def _true_landmarks(true_map: Optional[Path], result) -> tuple:
    """(ids, xyz) of the landmarks of the g2o file ``true_map``, the true map of the run's world;
    (None, None) without one."""
    if true_map is None:
        return None, None
    from camloc.cli.common import read_true_map

    truth = read_true_map(true_map, result)
    return truth.landmark_ids, truth.landmark_xyz


def _load_sweep(folder: Path) -> tuple[list, str]:
    """(groups, title) of a sweep folder's position RMSE distributions (camloc.sweep.ate_groups)."""
    from camloc.sweep import ate_groups, load_folder

    spec, cells, results = load_folder(folder)
    return ate_groups(spec, cells, results), f"{folder.name}: position RMSE over {spec.world_column}s, {len(results)} runs"
