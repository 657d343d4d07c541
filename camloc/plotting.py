"""Figures of a localization run.

Every ``plot_*`` function draws into a matplotlib axis given as its first argument and returns
it; the caller owns the figure (its size, layout, saving). The ``draw_*`` functions lay several
plots out on a figure they are given. This module and ``camloc.plotting_map`` (the map figure) are
the only ones of the library that import matplotlib, and nothing in the core imports them, so
``camloc run`` never pays for it.

Colours are fixed across figures: the filter's estimate blue, odometry green, ground truth red, smoothed purple (when
the run was smoothed, ``camloc smooth``), map grey. Errors are computed against the ground truth
without alignment (``camloc.metrics``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import PathCollection
from matplotlib.lines import Line2D
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullFormatter

from camloc import metrics
from camloc.diagnostics import estimate_name
from camloc.results import RunResult

ESTIMATE_COLOR = "tab:blue"
ODOMETRY_COLOR = "tab:green"
TRUTH_COLOR = "tab:red"
SMOOTHED_COLOR = "tab:purple"
MAP_COLOR = "0.55"
CORRECT_COLOR = "#2ca25f"
WRONG_COLOR = "#de2d26"
MISSED_COLOR = "#f5a700"  # a landmark's detection left unassociated: a loss, unlike clutter rejected
CLUTTER_REJECTED_COLOR = "0.78"
START_COLOR = "black"
SIGMA = 3.0
# The paths whose errors share a panel (centimetres), apart from odometry's (metres).
FILTER_PATHS = ("estimate", "smoothed")

_STYLE = {"linewidth": 1.4}


def dataset_name(result: RunResult) -> str:
    """The dataset's file name (or description) for titles."""
    return Path(result.dataset).name or result.dataset


def _no_truth(ax: Axes, what: str) -> Axes:
    ax.text(0.5, 0.5, f"no ground truth in this run:\n{what} cannot be computed", ha="center", va="center",
            transform=ax.transAxes, color="0.35")
    ax.set_xticks([])
    ax.set_yticks([])
    return ax


def _position_rmse(result: RunResult, xyz: np.ndarray) -> float:
    return float(np.sqrt(np.mean(metrics.position_errors(xyz, result.truth_xyz) ** 2)))


def _paths(result: RunResult) -> dict[str, np.ndarray]:
    """Positions (N, 3) of the estimated paths by key: estimate, odometry, and smoothed if any."""
    paths = {"estimate": result.estimate_xyz, "odometry": result.odometry_xyz}
    if result.smoothed_xyz is not None:
        paths["smoothed"] = result.smoothed_xyz
    return paths


def path_names(result: RunResult) -> dict[str, str]:
    """Each path's name in legends and titles: the estimate named by what made it, as the run's
    tables name it (``diagnostics.estimate_name``: ``iterated EKF (euler)``, or odometry alone
    where the filter made no update), odometry, smoothed."""
    estimate = estimate_name({**result.summary, "counts": {"updates": int(result.nis.size)}})
    return {"estimate": estimate, "odometry": "odometry", "smoothed": "smoothed"}


def _path_labels(result: RunResult) -> dict[str, str]:
    """Legend labels, with each path's position RMSE when there is ground truth."""
    if result.truth_xyz is None:
        return {key: path_names(result)[key] for key in _paths(result)}
    return {key: f"{path_names(result)[key]} (RMSE {_position_rmse(result, xyz):.3f} m)" for key, xyz in _paths(result).items()}


# Characters of a title line before the next path's figure goes on a line of its own: the report
# puts the top-down view in half the page's width, and a longer line was cut at the page's edge.
TITLE_LINE_CHARS = 64


def _trajectory_title(result: RunResult, view: str) -> str:
    title = f"{dataset_name(result)}: {view}"
    if result.truth_xyz is not None:
        parts = [f"{path_names(result)[key]} {_position_rmse(result, xyz):.3f} m" for key, xyz in _paths(result).items()]
        title += "\n" + _packed(["position RMSE:", *parts], TITLE_LINE_CHARS)
    return title


def _packed(parts: list[str], width: int) -> str:
    """``parts`` joined by ", " (the first by a space), a new line begun where the next part would
    carry a line past ``width`` characters; a part is never broken."""
    lines = [parts[0]]
    for i, part in enumerate(parts[1:]):
        joint = " " if i == 0 else ", "
        if len(lines[-1]) + len(joint) + len(part) > width:
            lines[-1] += joint.rstrip()
            lines.append(part)
        else:
            lines[-1] += joint + part
    return "\n".join(lines)


def _view_box(result: RunResult) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) (3,) of the view: the box holding the estimate, the truth and the smoothed path
    with a margin of ``VIEW_MARGIN`` of their horizontal span, and a height of at least
    ``MIN_Z_SPAN`` of it about their middle. Odometry and the map do not set it: odometry's drift
    (hundreds of metres over 20,000 poses) would shrink the estimate to a blob; they are clipped."""
    points = np.vstack([xyz for key, xyz in _paths(result).items() if key != "odometry"]
                       + ([result.truth_xyz] if result.truth_xyz is not None else []))
    low, high = points.min(axis=0), points.max(axis=0)
    margin = VIEW_MARGIN * max(float(np.max(high[:2] - low[:2])), 1.0)
    low, high = low - margin, high + margin
    middle, height = (low[2] + high[2]) / 2, max(high[2] - low[2], MIN_Z_SPAN * float(np.max(high[:2] - low[:2])))
    low[2], high[2] = middle - height / 2, middle + height / 2
    return low, high


def _inside(xyz: np.ndarray, low: np.ndarray, high: np.ndarray, dims: int) -> np.ndarray:
    """(M,) whether each point of ``xyz`` (M, 3) lies in the view box, over its first ``dims`` axes."""
    return np.all((xyz[:, :dims] >= low[:dims]) & (xyz[:, :dims] <= high[:dims]), axis=1)


def _clipped(xyz: np.ndarray, low: np.ndarray, high: np.ndarray, dims: int) -> np.ndarray:
    """``xyz`` with the points outside the view box set to NaN: the line breaks where it leaves."""
    return np.where(_inside(xyz, low, high, dims)[:, None], xyz, np.nan)


def _odometry_label(result: RunResult, low: np.ndarray, high: np.ndarray, dims: int) -> str:
    label = _path_labels(result)["odometry"]
    inside = _inside(result.odometry_xyz, low, high, dims)
    if inside.all():
        return label
    return f"{label},\n{np.count_nonzero(~inside)} of {inside.size} poses outside the view"


def path_width(count: int) -> float:
    """Line width (points) of a path of ``count`` poses: 1.4 up to ``ROLLING_FROM`` poses, thinner
    beyond (as 1/sqrt of the count, at least 0.5) so that a dense path stays a web, not a smear."""
    return float(np.clip(1.4 * np.sqrt(ROLLING_FROM / max(count, 1)), 0.5, 1.4))


def _map_style(count: int) -> dict:
    """Scatter style of a map of ``count`` landmarks: small light points, smaller and fainter as
    they grow more numerous, so that 45,000 landmarks are a grey shade under the paths."""
    return {"s": float(np.clip(8000.0 / max(count, 1), 0.5, 9.0)), "alpha": float(np.clip(600.0 / max(count, 1) ** 0.75, 0.3, 0.9)),
            "marker": "o", "color": MAP_COLOR, "linewidths": 0, "rasterized": count > 2000}


def _draw_paths(ax: Axes, result: RunResult, xyz_of: Callable[[np.ndarray], np.ndarray], odometry_label: str) -> list:
    """The paths in their drawing order, bottom first: odometry, the EKF (widest), the smoothed
    path over it (narrower), the truth on top (narrowest): where they agree, each shows
    as a border around the next; where they part, each is its own colour. Start and end on top."""
    labels = _path_labels(result)
    width = path_width(len(result.pose_ids))
    lines = [ax.plot(*xyz_of(result.odometry_xyz), color=ODOMETRY_COLOR, label=odometry_label, linewidth=width, zorder=3)]
    lines.append(ax.plot(*xyz_of(result.estimate_xyz), color=ESTIMATE_COLOR, label=labels["estimate"],
                         linewidth=2.6 * width, zorder=4))
    if result.smoothed_xyz is not None:
        lines.append(ax.plot(*xyz_of(result.smoothed_xyz), color=SMOOTHED_COLOR, label=labels["smoothed"],
                             linewidth=1.2 * width, zorder=5))
    if result.truth_xyz is not None:
        lines.append(ax.plot(*xyz_of(result.truth_xyz), color=TRUTH_COLOR, label="ground truth",
                             linewidth=0.5 * width, zorder=6))
    for index, marker, name in ((0, "o", "start"), (-1, "s", "end")):
        ax.plot(*xyz_of(result.estimate_xyz[[index]]), marker=marker, color=START_COLOR, markersize=7,
                markeredgecolor="white", markeredgewidth=1.0, linestyle="none", label=f"{name} of the estimate", zorder=7)
    return lines


def plot_topdown(ax: Axes, result: RunResult, *, show_map: bool = True) -> Axes:
    """Top-down (x-y) view of the EKF, odometry, true (and smoothed) paths over the map, metres.

    The view holds the estimate, the truth and the smoothed path (``_view_box``); odometry is
    clipped to it (its legend entry says how many poses fall outside). The truth is drawn last, a
    thin dark red line through the estimates (``_draw_paths``); start and end are marked; the map
    is small light points, fainter as it grows (``_map_style``); the legend sits below the axes.
    """
    low, high = _view_box(result)
    if show_map and len(result.map_landmark_xyz):
        _draw_map_topdown(ax, result.map_landmark_xyz, low, high)
        draw_landmark_headings(ax, result, low, high)
    _draw_paths(ax, result, lambda xyz: xyz[:, :2].T, _odometry_label(result, low, high, 2))
    # The view box as the data limits (not fixed limits): the equal aspect widens one side to
    # fill the axis, and odometry beyond the box is clipped.
    ax.dataLim.set_points(np.array([low[:2], high[:2]]))
    ax.margins(0.0)
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(_trajectory_title(result, "top-down view"))
    ax.grid(True, alpha=0.3)
    _legend_below(ax)
    return ax


# From this many landmarks in view the top-down map is a density image, not points.
MAP_DENSITY_FROM = 5000


def _draw_map_topdown(ax: Axes, map_xyz: np.ndarray, low: np.ndarray, high: np.ndarray) -> None:
    """The map's landmarks: small light points (``_map_style``); from ``MAP_DENSITY_FROM``
    landmarks, the count of those in the view box per cell (1/150 of its width) as a grey shade,
    empty cells left white, under a grey square in the legend."""
    label = f"map ({len(map_xyz)} landmarks)"
    if len(map_xyz) < MAP_DENSITY_FROM:  # all of them: the axis clips those out of view
        ax.scatter(map_xyz[:, 0], map_xyz[:, 1], label=label, zorder=1, **_map_style(len(map_xyz)))
        return
    xy = map_xyz[_inside(map_xyz, low, high, 2), :2]
    cell = float(np.max(high[:2] - low[:2])) / 150.0
    edges = [np.arange(low[axis], high[axis] + cell, cell) for axis in (0, 1)]
    counts, _, _ = np.histogram2d(xy[:, 0], xy[:, 1], bins=edges)
    shade = np.ma.masked_equal(counts.T, 0)
    ax.imshow(shade, origin="lower", extent=(edges[0][0], edges[0][-1], edges[1][0], edges[1][-1]), cmap="Greys",
              vmin=0.0, vmax=2.5 * max(float(np.percentile(counts[counts > 0], 90)), 1.0), interpolation="nearest",
              aspect="auto", zorder=1, rasterized=True)
    ax.fill([], [], color="0.6", label=f"{label[:-1]}, density per {cell:.2g} m cell)")


# A landmark's heading is a tick this share of the view box's larger side long.
HEADING_TICK = 0.025
HEADING_COLOR = "0.3"  # dark grey: the map's, apart from the paths' colours


def draw_landmark_headings(ax: Axes, result: RunResult, low: np.ndarray, high: np.ndarray) -> None:
    """A planar run's markers and tags in the view box (``low``, ``high``): each a tick from
    its position in its heading (``RunResult.map_landmark_heading``: a marker's psi, a tag's yaw),
    ``HEADING_TICK`` of the box long, drawn as one ``LineCollection`` however many there are. A
    3-D run, or a run folder without headings, draws none."""
    heading = result.map_landmark_heading
    if heading is None or not metrics.is_planar_run(result):
        return
    rows = np.flatnonzero(np.isfinite(heading) & _inside(result.map_landmark_xyz, low, high, 2))
    if rows.size == 0:
        return
    from matplotlib.collections import LineCollection

    start = result.map_landmark_xyz[rows, :2]
    tip = start + HEADING_TICK * float(np.max(high[:2] - low[:2])) * np.column_stack([np.cos(heading[rows]), np.sin(heading[rows])])
    ax.add_collection(LineCollection(np.stack([start, tip], axis=1), colors=HEADING_COLOR, linewidths=1.2, zorder=2,
                                     label=f"headings ({rows.size} markers and tags)"), autolim=False)


def _legend_below(ax: Axes) -> None:
    """The legend under the axis (below its x label), in columns, where it hides no data."""
    legend = ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.09), ncols=2, fontsize="small", frameon=False,
                       markerscale=1.0)
    _readable_handles(legend)


def _readable_handles(legend) -> None:
    """Legend keys drawn readably whatever the data's style: the map's faint points at a visible
    size, the thin lines of a long run at least 1.5 points wide."""
    for handle in legend.legend_handles:
        if isinstance(handle, PathCollection):
            handle.set_sizes([16.0])
            handle.set_alpha(1.0)
        elif isinstance(handle, Line2D) and handle.get_linestyle() != "None":
            handle.set_linewidth(max(handle.get_linewidth(), 1.5))


# The view's height is at least this share of its horizontal span: a flat path is drawn flat, on
# the same scale as x and y, in a box that is not a sliver.
MIN_Z_SPAN = 0.2
VIEW_MARGIN = 0.04


def plot_3d(ax: Axes, result: RunResult, *, show_map: bool = True) -> Axes:
    """3D view of the same paths and map; ``ax`` must be a 3D axis (``projection="3d"``).

    x, y and z share one scale. The view is ``_view_box``'s: it holds the estimate, the truth and
    the smoothed path, at least ``MIN_Z_SPAN`` of its width tall; odometry and the map are clipped
    to it (lines break where they leave it). Artists keep their ``zorder`` (no depth sorting), in
    ``_draw_paths``'s order, truth last. The legend is to the right of the axis.
    """
    ax.computed_zorder = False
    low, high = _view_box(result)
    if show_map and len(result.map_landmark_xyz):
        xyz = result.map_landmark_xyz[_inside(result.map_landmark_xyz, low, high, 3)]
        ax.scatter(*xyz.T, depthshade=False, label=f"map ({len(result.map_landmark_xyz)} landmarks)", zorder=1,
                   **_map_style(len(xyz)))
    _draw_paths(ax, result, lambda xyz: _clipped(xyz, low, high, 3).T, _odometry_label(result, low, high, 3))
    ax.set_xlim(low[0], high[0])
    ax.set_ylim(low[1], high[1])
    ax.set_zlim(low[2], high[2])
    ax.set_box_aspect(tuple(high - low), zoom=1.0)
    ax.set_xlabel("x [m]", labelpad=8)
    ax.set_ylabel("y [m]", labelpad=8)
    ax.set_zlabel("z [m]", labelpad=4)
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(MaxNLocator(nbins=5))
    ax.zaxis.set_major_locator(MaxNLocator(nbins=3))
    ax.set_title(_trajectory_title(result, "3D view"))
    _legend_outside(ax, framealpha=0.85)
    _readable_handles(ax.get_legend())
    return ax


def _finish_time_axis(ax: Axes, result: RunResult, ylabel: str, title: str) -> None:
    step = np.sign(result.pose_ids[-1] - result.pose_ids[0]) or 1
    ax.set_xlim(result.pose_ids[0] - 0.5 * step, result.pose_ids[-1] + 0.5 * step)
    ax.set_xlabel("pose id")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    # six-digit ids at ten ticks run together in a half-page panel: fewer ticks for longer ids
    digits = len(str(int(np.max(np.abs(result.pose_ids)))))
    ax.xaxis.set_major_locator(MaxNLocator(integer=True, nbins=10 if digits <= 3 else (7 if digits == 4 else 5)))
    _legend_outside(ax)


def _legend_outside(ax: Axes, **options) -> None:
    """The legend to the right of the axis, where it hides no data point."""
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, fontsize="small", **options)


def _plain_log_scale(ax: Axes) -> None:
    """Log y axis labelled 0.5, 1, 2, 5, 10 rather than 5x10^-1 ...; minor labels only over few decades."""
    ax.set_yscale("log")
    plain = FuncFormatter(lambda value, _: f"{value:g}")
    ax.yaxis.set_major_formatter(plain)
    low, high = ax.get_ylim()
    if np.log10(high / low) <= 2.5:
        leading = FuncFormatter(lambda value, _: f"{value:g}" if f"{value:.0e}"[0] in "25" else "")
        ax.yaxis.set_minor_formatter(leading)
    else:
        ax.yaxis.set_minor_formatter(NullFormatter())


def position_sigma_bound(result: RunResult, *, sigma: float = SIGMA) -> np.ndarray:
    """(N,) ``sigma * sqrt(trace(P_position))`` in metres: the error norm's RMS scaled by sigma.

    ``E|e|^2 = trace(P)``, so ``sqrt(trace)`` is the one-number size of a 3D position error that
    the filter expects; per-axis bounds would need three panels for the same message.
    """
    return sigma * np.sqrt(np.trace(result.estimate_cov[:, 0:3, 0:3], axis1=1, axis2=2))


def rotation_sigma_bound_deg(result: RunResult, *, sigma: float = SIGMA) -> np.ndarray:
    """(N,) ``sigma * sqrt(trace(P_rotation))`` in degrees, as ``position_sigma_bound``."""
    return np.degrees(sigma * np.sqrt(np.trace(result.estimate_cov[:, 3:6, 3:6], axis1=1, axis2=2)))


def _path_errors(result: RunResult, key: str, *, rotation: bool) -> np.ndarray:
    """(N,) error of path ``key`` against the truth: position (m) or rotation angle (deg)."""
    if not rotation:
        return metrics.position_errors(_paths(result)[key], result.truth_xyz)
    quat = {"estimate": result.estimate_quat_xyzw, "odometry": result.odometry_quat_xyzw,
            "smoothed": result.smoothed_quat_xyzw}[key]
    return metrics.rotation_errors_deg(quat, result.truth_quat_xyzw)


# Line widths of the error panels: the smoothed path's over the filter's, narrower.
ERROR_WIDTHS = {"estimate": 2.2, "smoothed": 1.0}
_PATH_COLORS = {"estimate": ESTIMATE_COLOR, "odometry": ODOMETRY_COLOR, "smoothed": SMOOTHED_COLOR}


def _plot_errors(ax: Axes, result: RunResult, paths: tuple[str, ...], *, rotation: bool, sigma: float) -> Axes:
    # a planar robot's rotation is its heading
    what = ("heading error" if metrics.is_planar_run(result) else "rotation error") if rotation else "position error"
    if result.truth_xyz is None:
        return _no_truth(ax, what)
    x = result.pose_ids
    bins = pose_bins(len(x))
    lowest = []  # per-bin medians, whose smallest sets a long run's log axis
    if "estimate" in paths:
        bound = rotation_sigma_bound_deg(result, sigma=sigma) if rotation else position_sigma_bound(result, sigma=sigma)
        symbol = "rot" if rotation else "xyz"
        estimate = path_names(result)["estimate"]
        name = rf"{estimate} ${sigma:g}\sigma$ ($ {sigma:g}\sqrt{{\mathrm{{tr}}\,P_{{{symbol}}}}}$)"
        if bins is None:
            ax.fill_between(x, 0.0, bound, color=ESTIMATE_COLOR, alpha=0.15, linewidth=0, label=name)
        else:  # a band of one-pose spikes is hairlines: the highest and the median bound of each bin
            _fill_bins(ax, x, bins, np.maximum.reduceat(bound, bins[:-1]), alpha=0.13,
                       label=rf"{estimate} ${sigma:g}\sigma$ (highest)")
            lowest.append(_bin_medians(bound, bins))
            _fill_bins(ax, x, bins, lowest[-1], alpha=0.3, label=f"{name} (median)")
    drawn = [key for key in paths if key in _paths(result)]
    # As the paths' views: the filter's errors wide, the smoother's narrower over them, so that
    # where they agree the filter's shows as a border
    for order, key in enumerate(drawn):
        errors = _path_errors(result, key, rotation=rotation)
        style = {"color": _PATH_COLORS[key], "zorder": 3 + order}
        width = ERROR_WIDTHS.get(key, _STYLE["linewidth"])
        if bins is None:
            ax.plot(x, errors, label=path_names(result)[key], linewidth=width, **style)
            continue
        ax.plot(*_bin_steps(x, bins, np.maximum.reduceat(errors, bins[:-1])), linewidth=0.6, alpha=0.7, **style)
        lowest.append(_bin_medians(errors, bins))
        ax.plot(*_bin_steps(x, bins, lowest[-1]), linewidth=width, label=f"{path_names(result)[key]} (median; thin: highest)",
                **style)
    unit = "deg" if rotation else "m"
    whose = " and ".join(path_names(result)[key] for key in drawn)
    title = f"{what} of {whose}"
    if bins is None:
        ax.set_ylim(bottom=0.0)
    else:  # medians of millimetres under spikes of a metre: a log axis shows both
        positive = np.concatenate(lowest)
        positive = positive[positive > 0]
        ax.set_yscale("log")
        if positive.size:
            ax.set_ylim(bottom=0.5 * float(positive.min()))
        ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        title += f", per {bins[1] - bins[0]} poses"
    _finish_time_axis(ax, result, f"{what} [{unit}]", title)
    return ax


# Past ROLLING_FROM poses a series is drawn per bin of poses, in at most this many bins: a pose is
# then narrower than a pixel, and a one-pose spike (of an error, of the 3-sigma bound) a hairline.
MAX_BINS = 150


def pose_bins(count: int, *, start: int | None = None) -> np.ndarray | None:
    """(B + 1,) indices where the bins of a series of ``count`` poses start (the last: ``count``),
    each of the same number of consecutive poses but the last; None up to ``start`` poses (by
    default ``ROLLING_FROM``), drawn one by one."""
    if count <= (ROLLING_FROM if start is None else start):
        return None
    size = -(-count // MAX_BINS)
    return np.append(np.arange(0, count, size), count)


def _bin_medians(values: np.ndarray, bins: np.ndarray) -> np.ndarray:
    return np.array([np.median(values[a:b]) for a, b in zip(bins[:-1], bins[1:])])


def _bin_steps(x: np.ndarray, bins: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A step line at ``values`` (B,) over each bin's poses of ``x``, from the first pose's left
    edge to the last one's right edge."""
    step = np.sign(x[-1] - x[0]) if len(x) > 1 else 1
    edges = np.append(x[bins[:-1]], x[-1] + step) - 0.5 * step
    return edges, np.append(values, values[-1])


def _fill_bins(ax: Axes, x: np.ndarray, bins: np.ndarray, values: np.ndarray, **style) -> None:
    edges, top = _bin_steps(x, bins, values)
    ax.fill_between(edges, 0.0, top, step="post", color=ESTIMATE_COLOR, linewidth=0, **style)


def plot_position_error(ax: Axes, result: RunResult, *, paths: tuple[str, ...] = FILTER_PATHS, sigma: float = SIGMA) -> Axes:
    """Position error norm over time of the given paths (``"estimate"``, ``"odometry"``,
    ``"smoothed"``; by default the filter's and the smoother's), metres, with the EKF's ``sigma``
    band when the estimate is drawn. Odometry drifts by metres where the filter errs by
    centimetres: give it a panel of its own."""
    return _plot_errors(ax, result, paths, rotation=False, sigma=sigma)


def plot_rotation_error(ax: Axes, result: RunResult, *, paths: tuple[str, ...] = FILTER_PATHS, sigma: float = SIGMA) -> Axes:
    """Rotation error angle over time of the given paths, degrees, as ``plot_position_error``."""
    return _plot_errors(ax, result, paths, rotation=True, sigma=sigma)


# Past this many points a series of raw NEES / NIS values is a solid band: they are drawn as faint
# dots under their rolling mean.
ROLLING_FROM = 1000


def rolling_window(count: int) -> int:
    """Points per rolling mean of a series of ``count``: about a hundredth of it, at least 25."""
    return max(25, count // 100)


def rolling_ratio(numerator: np.ndarray, denominator: np.ndarray, window: int) -> np.ndarray:
    """(n,) centred rolling ``sum(numerator) / sum(denominator)`` over ``window`` points (fewer at
    the ends): a rolling mean for a denominator of ones, NIS per dof for NIS and dof."""
    kernel = np.ones(window)
    top = np.convolve(numerator, kernel, mode="same")
    bottom = np.convolve(np.asarray(denominator, dtype=float), kernel, mode="same")
    return top / bottom


def _plot_series(ax: Axes, x: np.ndarray, values: np.ndarray, weights: np.ndarray, label: str, *, joined: bool) -> None:
    """Raw values as dots (``joined``: a thin line joins them in short series, for values of
    consecutive poses); past ``ROLLING_FROM`` points, faint dots under their rolling mean
    (weighted by ``weights``, NaN values left out)."""
    if values.size <= ROLLING_FROM:
        ax.plot(x, values, color=ESTIMATE_COLOR, marker=".", markersize=4 if joined else 5,
                linewidth=0.6 if joined else 0.0, label=label)
        return
    ax.plot(x, values, color=ESTIMATE_COLOR, marker=".", markersize=2, linestyle="none", alpha=0.3, label=label)
    used = np.isfinite(values)
    window = rolling_window(int(used.sum()))
    rolling = rolling_ratio(values[used] * weights[used], weights[used], window)
    ax.plot(x[used], rolling, color="navy", linewidth=1.6, label=f"rolling mean ({window} points)", zorder=4)


def plot_nees(ax: Axes, result: RunResult) -> Axes:
    """NEES per pose (6 dof, log scale) with its per-pose chi2 95% bounds and the mean's interval
    (of the run's effective number of independent poses, ``metrics.nees_summary``); past
    ``ROLLING_FROM`` poses, with its rolling mean.

    The given start pose is left out (``metrics.run_nees``).
    """
    if result.truth_xyz is None:
        return _no_truth(ax, "NEES")
    nees = metrics.run_nees(result)
    dof = metrics.nees_dof(result)  # 3 for a planar filter's (x, y, yaw)
    summary = metrics.nees_summary(nees, dof=dof)
    lower, upper = summary["bounds"]
    x = result.pose_ids
    ax.axhspan(lower, upper, color="0.5", alpha=0.12, linewidth=0,
               label=f"per-pose 95% bounds [{lower:.2f}, {upper:.2f}]")
    ax.axhline(dof, color="0.3", linestyle=":", linewidth=1.0, label=f"expected ({dof})")
    _plot_series(ax, x, nees, np.ones_like(nees), f"{path_names(result)['estimate']} NEES", joined=True)
    if summary["mean"] is not None:
        mean_lower, mean_upper = summary["mean_bounds"]
        ax.axhline(summary["mean"], color="crimson" if summary["verdict"] != "consistent" else ESTIMATE_COLOR,
                   linestyle="--", linewidth=1.2,
                   label=f"mean {summary['mean']:.2f}\n(95% interval [{mean_lower:.2f}, {mean_upper:.2f}]\n"
                         f"of {summary['effective_poses']:.0f} independent poses)")
    _plain_log_scale(ax)
    _finish_time_axis(ax, result, f"NEES ({dof} dof)", f"pose NEES: {summary['verdict']}")
    return ax


def plot_nis(ax: Axes, result: RunResult) -> Axes:
    """NIS per degree of freedom of each update (log scale) with its per-update chi2 95% bounds;
    past ``ROLLING_FROM`` updates, with its rolling NIS per dof."""
    x = result.update_pose_ids
    if x.size == 0:
        ax.text(0.5, 0.5, "no filter update in this run", ha="center", va="center", transform=ax.transAxes)
        return ax
    dof = result.nis_dof
    lower, upper = metrics.chi2_bounds(dof)
    summary = metrics.nis_summary(result.nis, dof)
    ax.fill_between(x, lower / dof, upper / dof, step="mid", color="0.5", alpha=0.12, linewidth=0,
                    label="per-update 95% bounds")
    ax.axhline(1.0, color="0.3", linestyle=":", linewidth=1.0, label="expected (1)")
    _plot_series(ax, x, result.nis / dof, dof.astype(float), "NIS / dof", joined=False)
    mean_lower, mean_upper = summary["mean_bounds"]
    ax.axhline(summary["mean_per_dof"], color="crimson" if summary["verdict"] != "consistent" else ESTIMATE_COLOR,
               linestyle="--", linewidth=1.2,
               label=f"mean {summary['mean_per_dof']:.2f}\n(95% interval [{mean_lower:.2f}, {mean_upper:.2f}])")
    _plain_log_scale(ax)
    _finish_time_axis(ax, result, "NIS / dof", f"innovation NIS per dof ({x.size} updates): {summary['verdict']}")
    return ax


# Above this many poses the association plot counts per bin of poses (``pose_bins``): a bar per
# pose is narrower than a pixel, and a rare outcome (a missed detection, rejected clutter) vanishes
# in a comb of thousands (each bar an artist, too: 20,000 poses' took matplotlib 50 s).
MAX_BARS = ROLLING_FROM


# Per-pose outcome of the observations, bottom to top of each stack: (mask name, colour).
ASSOCIATION_CATEGORIES = {
    "correct": CORRECT_COLOR,
    "wrong": WRONG_COLOR,
    "missed": MISSED_COLOR,
    "clutter_rejected": CLUTTER_REJECTED_COLOR,
}
NO_OBSERVATION_TEXT = "no observation was used: the estimate is odometry alone"


def plot_associations(ax: Axes, result: RunResult) -> Axes:
    """Per pose, stacked bars of correct, wrong, missed (a map landmark's detection left
    unassociated) and clutter rejected (against the file's ids). Past ``MAX_BARS`` poses, each
    outcome's count per bin of poses (``pose_bins``) as its own step line on a log axis, so that
    the rare ones stay visible beside thousands of correct pairs. Every pose with a wrong pair also
    gets a red marker: above its stack, or at the top of the axis for binned counts. A run that
    used no observation says so (its estimate is odometry alone).

    Wrong includes clutter that was accepted.
    """
    outcomes = metrics.association_outcomes(result.associations, result.map_landmark_ids)
    outcomes["clutter_rejected"] = outcomes["rejected"] & ~outcomes["in_map"]
    scores = metrics.association_scores(result.associations, result.map_landmark_ids)
    # Pose ids are in the odometry chain's order, not necessarily increasing: search them sorted.
    # (load_run has checked that every association is of one of the run's poses.)
    order = np.argsort(result.pose_ids)
    index = order[np.searchsorted(result.pose_ids, result.associations.pose_id, sorter=order)]
    counts = {name: np.bincount(index[outcomes[name]], minlength=len(result.pose_ids)) for name in ASSOCIATION_CATEGORIES}
    labels = {
        "correct": f"correct ({scores['correct']})",
        "wrong": f"wrong ({scores['wrong']}, {scores['clutter_accepted']} of them clutter)",
        "missed": f"missed ({scores['missed']}: a map landmark's, left out)",
        "clutter_rejected": f"clutter rejected ({scores['rejected'] - scores['missed']})",
    }
    precision = "-" if scores["precision"] is None else f"{scores['precision']:.3f}"
    recall = "-" if scores["recall"] is None else f"{scores['recall']:.3f}"
    title = f"data association per pose: precision {precision}, recall {recall}"
    if scores["correct"] + scores["wrong"] == 0:
        ax.text(0.5, 0.5, NO_OBSERVATION_TEXT, ha="center", va="center", transform=ax.transAxes, color="0.25",
                fontsize="large", bbox={"facecolor": "white", "edgecolor": "0.6", "alpha": 0.9}, zorder=10)
        if result.associations.pose_id.size == 0:
            ax.set_yticks([])
            ax.set_xlim(result.pose_ids.min() - 0.5, result.pose_ids.max() + 0.5)
            ax.set_xlabel("pose id")
            ax.set_title("data association: no observation in the file")
            return ax
    wrong = counts["wrong"] > 0
    bins = pose_bins(len(result.pose_ids), start=MAX_BARS)
    if bins is None:
        handles, top = _stacked_bars(ax, result.pose_ids, counts, labels)
        marks = ax.scatter(result.pose_ids[wrong], top[wrong] + 0.06 * max(float(top.max()), 1.0) + 0.3, marker="v",
                           s=30, color=WRONG_COLOR, edgecolors="black", linewidths=0.4, zorder=5,
                           label=f"pose with a wrong pair ({int(wrong.sum())})")
        ax.set_ylim(0.0, max(float(top.max()), 1.0) * 1.15 + 0.6)
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        ylabel = "observations"
    else:
        handles = _binned_counts(ax, result.pose_ids, bins, counts, labels)
        marks = ax.scatter(result.pose_ids[wrong], np.full(int(wrong.sum()), 0.96), marker="v", s=30, color=WRONG_COLOR,
                           edgecolors="black", linewidths=0.4, zorder=5, transform=ax.get_xaxis_transform(),
                           label=f"pose with a wrong pair ({int(wrong.sum())})")
        ylabel = f"observations per {bins[1] - bins[0]} poses"
        title = title.replace("per pose", f"per {bins[1] - bins[0]} poses")
    _finish_time_axis(ax, result, ylabel, title)
    _legend_outside(ax, handles=[*handles, marks])  # in stacking order, bottom first
    return ax


def _stacked_bars(ax: Axes, x: np.ndarray, counts: dict, labels: dict) -> tuple[list, np.ndarray]:
    """A bar per pose and outcome, stacked in ``ASSOCIATION_CATEGORIES``' order; returns the
    bars' containers and the stacks' tops (N,)."""
    bottom = np.zeros(len(x))
    handles = []
    for name, color in ASSOCIATION_CATEGORIES.items():
        handles.append(ax.bar(x, counts[name], bottom=bottom, width=0.85, color=color, linewidth=0, label=labels[name]))
        bottom = bottom + counts[name]
    return handles, bottom


def _binned_counts(ax: Axes, x: np.ndarray, bins: np.ndarray, counts: dict, labels: dict) -> list:
    """Each outcome's count per bin of poses as a step line (no line over a bin without one) on a
    log axis, correct over a light area of its own; returns the lines."""
    handles = []
    highest = 1.0
    for name, color in ASSOCIATION_CATEGORIES.items():
        per_bin = np.add.reduceat(counts[name], bins[:-1]).astype(float)
        highest = max(highest, float(per_bin.max()))
        edges, values = _bin_steps(x, bins, per_bin)
        if name == "correct":
            ax.fill_between(edges, 0.5, np.maximum(values, 0.5), step="post", color=color, alpha=0.25, linewidth=0)
        line_color = "0.55" if color == CLUTTER_REJECTED_COLOR else color  # the bars' light grey is too faint for a line
        handles.append(ax.step(edges, np.where(values > 0, values, np.nan), where="post", color=line_color,
                               linewidth=1.6, label=labels[name])[0])
    ax.set_yscale("log")
    ax.set_ylim(0.7, 4.0 * highest)  # room above for the wrong pairs' markers
    ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    return handles


# --------------------------------------------------------------------------------------------
# Sweeps (``camloc sweep``)

ORACLE_COLOR = "0.45"


def plot_sweep_ate(ax: Axes, groups: list[tuple[str, str | None, list[float]]], *, title: str = "") -> Axes:
    """Distribution of position RMSE per configuration: a box and every run as a point.

    The colour is the association (a legend names each, the oracle's grey included), so labels
    leave it out: the configurations that differ only in their association share one label,
    centred under their boxes, between faint separators; labels too long for their room are
    slanted. The axis is logarithmic over a decade or more (ticks at 1, 2, 5 of each decade when
    it spans few), linear within one, so that it always has numbers to read.

    Parameters
    ----------
    groups : (label, association or None, ate_rmse values in metres) per configuration, in the
        order to draw them (``camloc.sweep.ate_groups`` puts the oracle beside each method).
    """
    associations = list(dict.fromkeys(a for _, a, _ in groups if a not in (None, "oracle")))
    palette = {a: f"C{n}" for n, a in enumerate(associations)} | {"oracle": ORACLE_COLOR, None: ESTIMATE_COLOR}
    positions = np.arange(1, len(groups) + 1)
    filled = [(x, values) for x, (_, _, values) in zip(positions, groups) if values]
    if filled:
        boxes = ax.boxplot([v for _, v in filled], positions=[x for x, _ in filled], widths=0.55,
                           showfliers=False, patch_artist=True, medianprops={"color": "black"})
        for patch, (x, _) in zip(boxes["boxes"], filled):
            patch.set(facecolor=palette[groups[x - 1][1]], alpha=0.35)
    # Every run as a point, jittered sideways by a fixed pattern so the figure is reproducible.
    for x, (_, association, values) in zip(positions, groups):
        jitter = (np.arange(len(values)) % 7 - 3) * 0.05
        ax.plot(x + jitter, values, "o", markersize=3, color=palette[association], alpha=0.8)
    _label_configurations(ax, [_without_association(label) for label, _, _ in groups])
    ax.set_xlim(0.4, len(groups) + 0.6)
    if filled:
        _readable_value_axis(ax, np.concatenate([v for _, v in filled]))
    ax.set_ylabel("position RMSE [m]")
    ax.set_title(title or "position RMSE per configuration")
    ax.grid(True, axis="y", alpha=0.3, which="both")
    used = list(dict.fromkeys(a for _, a, values in groups if a is not None))
    if used:
        from matplotlib.patches import Patch

        names = {"oracle": "oracle (the file's true ids)"}
        ax.legend(handles=[Patch(facecolor=palette[a], edgecolor=palette[a], alpha=0.6, label=names.get(a, a))
                           for a in used], title="association", loc="upper left", bbox_to_anchor=(1.01, 1.0),
                  borderaxespad=0.0, fontsize="small")
    return ax


def _without_association(label: str) -> str:
    """A configuration's label without its ``association=`` line: the colour says it."""
    return "\n".join(line for line in label.split("\n") if not line.startswith("association=")) or "all runs"


def _label_configurations(ax: Axes, labels: list[str]) -> None:
    """One tick label per run of equal consecutive ``labels`` (boxes 1, 2, ...), centred under
    them, with a faint line between runs; slanted when a line of text is wider than its room."""
    blocks: list[list] = []  # [label, first box, last box]
    for x, label in enumerate(labels, start=1):
        if blocks and blocks[-1][0] == label:
            blocks[-1][2] = x
        else:
            blocks.append([label, x, x])
    ax.set_xticks([(first + last) / 2 for _, first, last in blocks], [label for label, _, _ in blocks], fontsize="small")
    for _, _, last in blocks[:-1]:
        ax.axvline(last + 0.5, color="0.8", linewidth=0.8, zorder=0)
    # room per box in inches against the widest line at the small font (about 0.075 in a character)
    room = ax.get_position().width * ax.get_figure().get_size_inches()[0] / (len(labels) + 0.2)
    widest = max(min(last - first + 1, 3) * room / max(len(line), 1)
                 for label, first, last in blocks for line in label.split("\n"))
    if widest < 0.075:
        for tick in ax.get_xticklabels():
            tick.set(rotation=30, ha="right", rotation_mode="anchor")


def _readable_value_axis(ax: Axes, values: np.ndarray) -> None:
    """A log axis over values spanning a decade or more, with labelled ticks at 1, 2 and 5 of each
    decade (1 alone past three decades), plain numbers; a linear axis within a decade, where a log
    axis has one tick label or none."""
    low, high = float(np.min(values)), float(np.max(values))
    if low <= 0 or high / low < 10.0:
        ax.yaxis.set_major_locator(MaxNLocator(nbins=6))
        return
    ax.set_yscale("log")
    subs = (1.0,) if high / low > 1e3 else (1.0, 2.0, 5.0)
    ax.yaxis.set_major_locator(LogLocator(base=10.0, subs=subs))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())


# --------------------------------------------------------------------------------------------
# Figures: layouts on a figure the caller created


def draw_topdown(fig: Figure, result: RunResult) -> Figure:
    plot_topdown(fig.add_subplot(1, 1, 1), result)
    return fig


def draw_3d(fig: Figure, result: RunResult) -> Figure:
    plot_3d(fig.add_subplot(1, 1, 1, projection="3d"), result)
    return fig


def draw_errors(fig: Figure, result: RunResult) -> Figure:
    """Position (top) and rotation (bottom) errors: the filter with its 3-sigma band on the left,
    odometry alone on the right, each on its own scale."""
    axes = fig.subplots(2, 2, sharex=True)
    for column, paths in enumerate((FILTER_PATHS, ("odometry",))):
        plot_position_error(axes[0, column], result, paths=paths)
        plot_rotation_error(axes[1, column], result, paths=paths)
        if result.truth_xyz is not None:
            axes[0, column].set_xlabel("")
    fig.suptitle(f"{dataset_name(result)}: pose errors")
    return fig


def draw_consistency(fig: Figure, result: RunResult) -> Figure:
    """NEES (top) and NIS (bottom), under the run's one verdict (``metrics.consistency_verdict``)."""
    top, bottom = fig.subplots(2, 1, sharex=True)
    plot_nees(top, result)
    plot_nis(bottom, result)
    if result.truth_xyz is not None:
        top.set_xlabel("")
    fig.suptitle(f"{dataset_name(result)}: filter {consistency_title(result)}")
    return fig


def consistency_title(result: RunResult) -> str:
    """``"consistency: <verdict> (NEES <v>, NIS <v>)"``, the verdict of NEES and NIS together."""
    nees = metrics.nees_summary(metrics.run_nees(result), dof=metrics.nees_dof(result)) if result.truth_xyz is not None else None
    nis = metrics.nis_summary(result.nis, result.nis_dof)
    verdict = metrics.consistency_verdict(nees, nis)["verdict"]
    parts = ([f"NEES {nees['verdict']}"] if nees is not None else []) + [f"NIS {nis['verdict']}"]
    return f"consistency: {verdict} ({', '.join(parts)})"


def draw_associations(fig: Figure, result: RunResult) -> Figure:
    ax = plot_associations(fig.add_subplot(1, 1, 1), result)
    ax.set_title(f"{dataset_name(result)}: {ax.get_title()}")
    return fig


def sweep_size(groups: list) -> tuple[float, float]:
    """Figure size (inches) of ``draw_sweep``: 1.1 inch a configuration, room for the legend."""
    return (max(8.0, 1.1 * len(groups) + 4.0), 6.0)


def draw_sweep(fig: Figure, sweep: tuple[list, str]) -> Figure:
    """A sweep's position RMSE per configuration; ``sweep`` is (groups, title) as
    ``plot_sweep_ate`` takes them."""
    groups, title = sweep
    plot_sweep_ate(fig.add_subplot(1, 1, 1), groups, title=title)
    return fig


def draw_report(fig: Figure, result: RunResult, map_panel: Callable[[Axes], object] | None = None) -> Figure:
    """Every plot on one figure: paths (top-down, 3D), the filter's errors, odometry's errors,
    NEES and NIS, associations; and, given ``map_panel`` (it draws a run's map on an axes:
    ``plotting_map.plot_map``), the map in a last row."""
    ratios = [2.2, 1.0, 1.0, 1.0, 1.0] + ([MAP_ROW_RATIO] if map_panel is not None else [])
    grid = fig.add_gridspec(len(ratios), 2, height_ratios=ratios)
    if metrics.is_planar_run(result):  # no z to show: the plan takes the row
        plot_topdown(fig.add_subplot(grid[0, :]), result)
    else:
        plot_topdown(fig.add_subplot(grid[0, 0]), result)
        plot_3d(fig.add_subplot(grid[0, 1], projection="3d"), result)
    for row, paths in ((1, FILTER_PATHS), (2, ("odometry",))):
        plot_position_error(fig.add_subplot(grid[row, 0]), result, paths=paths)
        plot_rotation_error(fig.add_subplot(grid[row, 1]), result, paths=paths)
    plot_nees(fig.add_subplot(grid[3, 0]), result)
    plot_nis(fig.add_subplot(grid[3, 1]), result)
    plot_associations(fig.add_subplot(grid[4, :]), result)
    if map_panel is not None:
        map_panel(fig.add_subplot(grid[5, :]))
    fig.suptitle(f"{run_title(result)}\n{consistency_title(result)}", fontsize="x-large")
    return fig


def run_title(result: RunResult) -> str:
    """``"<dataset>: <estimate>, <association> association, <N> poses[, smoothed]"``: which run a
    page shows (the estimate as ``path_names`` names it, the association as the run's
    configuration does)."""
    config = result.summary.get("config", {})
    parts = [path_names(result)["estimate"]]
    if "association" in config:
        parts.append(f"{config['association']} association")
    parts.append(f"{len(result.pose_ids)} poses")
    if result.smoothed_xyz is not None:
        parts.append("smoothed")
    return f"{dataset_name(result)}: {', '.join(parts)}"


# name -> (figure size in inches, layout); file names are ``fig-<name>.<format>``.
FIGURES: dict[str, tuple[tuple[float, float], Callable[[Figure, RunResult], Figure]]] = {
    "topdown": ((8.0, 7.0), draw_topdown),
    "3d": ((10.0, 6.0), draw_3d),
    "errors": ((14.0, 7.0), draw_errors),
    "consistency": ((12.0, 7.0), draw_consistency),
    "associations": ((14.0, 4.5), draw_associations),
}
REPORT_SIZE = (17.0, 23.0)
# The map's row of the report: as tall as the paths' row and a little more, for its legend below it.
MAP_ROW_RATIO = 2.6


def report_size(with_map: bool) -> tuple[float, float]:
    """Figure size (inches) of ``draw_report``, taller by the map's row when it has one."""
    width, height = REPORT_SIZE
    return (width, height + (8.0 if with_map else 0.0))


def figures_of(result: RunResult) -> dict[str, tuple[tuple[float, float], Callable[[Figure, RunResult], Figure]]]:
    """The figures ``camloc plot`` draws of a run: ``FIGURES``, less the 3D view for a planar
    filter's run (its z is 0 throughout)."""
    if metrics.is_planar_run(result):
        return {name: layout for name, layout in FIGURES.items() if name != "3d"}
    return dict(FIGURES)
