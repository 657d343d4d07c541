"""Figures of a localization run.

Every ``plot_*`` function draws into a matplotlib axis given as its first argument and returns
it; the caller owns the figure (its size, layout, saving). The ``draw_*`` functions lay several
plots out on a figure they are given. This is the only module of the library that imports
matplotlib, and nothing in the core imports it, so ``camloc run`` never pays for it.

Colours are fixed across figures: EKF blue, odometry green, ground truth red, smoothed purple (when
the run was smoothed, ``camloc smooth``), map grey. Errors are computed against the ground truth
without alignment (``camloc.metrics``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, MaxNLocator, NullFormatter

from camloc import metrics
from camloc.results import RunResult

ESTIMATE_COLOR = "tab:blue"
ODOMETRY_COLOR = "tab:green"
TRUTH_COLOR = "tab:red"
SMOOTHED_COLOR = "tab:purple"
MAP_COLOR = "0.55"
CORRECT_COLOR = "#2ca25f"
WRONG_COLOR = "#de2d26"
REJECTED_COLOR = "0.72"
SIGMA = 3.0

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


_PATH_NAMES = {"estimate": "EKF", "odometry": "odometry", "smoothed": "smoothed"}


def _path_labels(result: RunResult) -> dict[str, str]:
    """Legend labels, with each path's position RMSE when there is ground truth."""
    if result.truth_xyz is None:
        return {key: _PATH_NAMES[key] for key in _paths(result)}
    return {key: f"{_PATH_NAMES[key]} (RMSE {_position_rmse(result, xyz):.3f} m)" for key, xyz in _paths(result).items()}


def _trajectory_title(result: RunResult, view: str) -> str:
    title = f"{dataset_name(result)}: {view}"
    if result.truth_xyz is not None:
        title += "\nposition RMSE: " + ", ".join(
            f"{_PATH_NAMES[key]} {_position_rmse(result, xyz):.3f} m" for key, xyz in _paths(result).items()
        )
    return title


def plot_topdown(ax: Axes, result: RunResult, *, show_map: bool = True) -> Axes:
    """Top-down (x-y) view of the EKF, odometry, true (and smoothed) paths over the map, metres."""
    labels = _path_labels(result)
    if show_map and len(result.map_landmark_xyz):
        xyz = result.map_landmark_xyz
        ax.scatter(xyz[:, 0], xyz[:, 1], s=9, marker="s", color=MAP_COLOR, linewidths=0,
                   label=f"map ({len(xyz)} landmarks)", zorder=1)
    if result.truth_xyz is not None:
        ax.plot(result.truth_xyz[:, 0], result.truth_xyz[:, 1], color=TRUTH_COLOR, label="ground truth",
                zorder=2, **_STYLE)
    ax.plot(result.odometry_xyz[:, 0], result.odometry_xyz[:, 1], color=ODOMETRY_COLOR,
            label=labels["odometry"], zorder=3, **_STYLE)
    ax.plot(result.estimate_xyz[:, 0], result.estimate_xyz[:, 1], color=ESTIMATE_COLOR,
            label=labels["estimate"], zorder=4, **_STYLE)
    if result.smoothed_xyz is not None:
        ax.plot(result.smoothed_xyz[:, 0], result.smoothed_xyz[:, 1], color=SMOOTHED_COLOR,
                label=labels["smoothed"], zorder=4, **_STYLE)
    start = result.estimate_xyz[0]
    ax.plot(start[0], start[1], marker="o", color="black", markersize=6, linestyle="none", label="start", zorder=5)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(_trajectory_title(result, "top-down view"))
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small", framealpha=0.85)
    return ax


def plot_3d(ax: Axes, result: RunResult, *, show_map: bool = True) -> Axes:
    """3D view of the same paths and map; ``ax`` must be a 3D axis (``projection="3d"``)."""
    labels = _path_labels(result)
    clouds = list(_paths(result).values())
    if show_map and len(result.map_landmark_xyz):
        xyz = result.map_landmark_xyz
        ax.scatter(xyz[:, 0], xyz[:, 1], xyz[:, 2], s=6, marker="s", color=MAP_COLOR, depthshade=False,
                   label=f"map ({len(xyz)} landmarks)")
        clouds.append(xyz)
    if result.truth_xyz is not None:
        ax.plot(*result.truth_xyz.T, color=TRUTH_COLOR, label="ground truth", **_STYLE)
        clouds.append(result.truth_xyz)
    ax.plot(*result.odometry_xyz.T, color=ODOMETRY_COLOR, label=labels["odometry"], **_STYLE)
    ax.plot(*result.estimate_xyz.T, color=ESTIMATE_COLOR, label=labels["estimate"], **_STYLE)
    if result.smoothed_xyz is not None:
        ax.plot(*result.smoothed_xyz.T, color=SMOOTHED_COLOR, label=labels["smoothed"], **_STYLE)
    # Equal scale on all axes, so that heights are not exaggerated.
    points = np.vstack(clouds)
    # zoom < 1 leaves room for the z label, which constrained layout does not reserve for 3D axes.
    ax.set_box_aspect(np.maximum(np.ptp(points, axis=0), 1e-3 * np.ptp(points, axis=0).max() + 1e-9), zoom=0.82)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.zaxis.set_major_locator(MaxNLocator(nbins=3))  # a flat box has little room for z labels
    ax.set_title(_trajectory_title(result, "3D view"))
    ax.legend(loc="upper left", fontsize="small", framealpha=0.85)
    return ax


def _finish_time_axis(ax: Axes, result: RunResult, ylabel: str, title: str) -> None:
    ax.set_xlim(result.pose_ids[0] - 0.5, result.pose_ids[-1] + 0.5)
    ax.set_xlabel("pose id")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.legend(loc="upper left", fontsize="small", framealpha=0.85)


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


def plot_position_error(ax: Axes, result: RunResult, *, sigma: float = SIGMA) -> Axes:
    """Position error norm over time, EKF, odometry (and smoothed), with the EKF's ``sigma`` band (metres)."""
    if result.truth_xyz is None:
        return _no_truth(ax, "position error")
    x = result.pose_ids
    ax.fill_between(x, 0.0, position_sigma_bound(result, sigma=sigma), color=ESTIMATE_COLOR, alpha=0.15,
                    linewidth=0, label=rf"EKF ${sigma:g}\sigma$ ($ {sigma:g}\sqrt{{\mathrm{{tr}}\,P_{{xyz}}}}$)")
    ax.plot(x, metrics.position_errors(result.odometry_xyz, result.truth_xyz), color=ODOMETRY_COLOR,
            label="odometry", **_STYLE)
    ax.plot(x, metrics.position_errors(result.estimate_xyz, result.truth_xyz), color=ESTIMATE_COLOR,
            label="EKF", **_STYLE)
    if result.smoothed_xyz is not None:
        ax.plot(x, metrics.position_errors(result.smoothed_xyz, result.truth_xyz), color=SMOOTHED_COLOR,
                label="smoothed", **_STYLE)
    ax.set_ylim(bottom=0.0)
    _finish_time_axis(ax, result, "position error [m]", "position error against ground truth")
    return ax


def plot_rotation_error(ax: Axes, result: RunResult, *, sigma: float = SIGMA) -> Axes:
    """Rotation error angle over time, EKF, odometry (and smoothed), with the EKF's ``sigma`` band (degrees)."""
    if result.truth_xyz is None:
        return _no_truth(ax, "rotation error")
    x = result.pose_ids
    ax.fill_between(x, 0.0, rotation_sigma_bound_deg(result, sigma=sigma), color=ESTIMATE_COLOR, alpha=0.15,
                    linewidth=0, label=rf"EKF ${sigma:g}\sigma$ ($ {sigma:g}\sqrt{{\mathrm{{tr}}\,P_{{rot}}}}$)")
    ax.plot(x, metrics.rotation_errors_deg(result.odometry_quat_xyzw, result.truth_quat_xyzw),
            color=ODOMETRY_COLOR, label="odometry", **_STYLE)
    ax.plot(x, metrics.rotation_errors_deg(result.estimate_quat_xyzw, result.truth_quat_xyzw),
            color=ESTIMATE_COLOR, label="EKF", **_STYLE)
    if result.smoothed_xyz is not None:
        ax.plot(x, metrics.rotation_errors_deg(result.smoothed_quat_xyzw, result.truth_quat_xyzw),
                color=SMOOTHED_COLOR, label="smoothed", **_STYLE)
    ax.set_ylim(bottom=0.0)
    _finish_time_axis(ax, result, "rotation error [deg]", "rotation error against ground truth")
    return ax


def plot_nees(ax: Axes, result: RunResult) -> Axes:
    """NEES per pose (6 dof, log scale) with its per-pose chi2 95% bounds and the mean's interval.

    The given start pose is left out (``metrics.run_nees``).
    """
    if result.truth_xyz is None:
        return _no_truth(ax, "NEES")
    nees = metrics.run_nees(result)
    summary = metrics.nees_summary(nees)
    lower, upper = summary["bounds"]
    x = result.pose_ids
    ax.axhspan(lower, upper, color="0.5", alpha=0.12, linewidth=0,
               label=f"per-pose 95% bounds [{lower:.2f}, {upper:.2f}]")
    ax.axhline(metrics.POSE_DOF, color="0.3", linestyle=":", linewidth=1.0, label=f"expected ({metrics.POSE_DOF})")
    ax.plot(x, nees, color=ESTIMATE_COLOR, marker=".", markersize=4, label="EKF NEES", **_STYLE)
    if summary["mean"] is not None:
        mean_lower, mean_upper = summary["mean_bounds"]
        ax.axhline(summary["mean"], color=ESTIMATE_COLOR, linestyle="--", linewidth=1.2,
                   label=f"mean {summary['mean']:.2f} (95% interval [{mean_lower:.2f}, {mean_upper:.2f}])")
    _plain_log_scale(ax)
    _finish_time_axis(ax, result, "NEES (6 dof)", f"pose NEES: {summary['verdict']}")
    return ax


def plot_nis(ax: Axes, result: RunResult) -> Axes:
    """NIS per degree of freedom of each update (log scale) with its per-update chi2 95% bounds."""
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
    ax.plot(x, result.nis / dof, color=ESTIMATE_COLOR, marker=".", markersize=5, linestyle="none",
            label="NIS / dof")
    mean_lower, mean_upper = summary["mean_bounds"]
    ax.axhline(summary["mean_per_dof"], color=ESTIMATE_COLOR, linestyle="--", linewidth=1.2,
               label=f"mean {summary['mean_per_dof']:.2f} (95% interval [{mean_lower:.2f}, {mean_upper:.2f}])")
    _plain_log_scale(ax)
    _finish_time_axis(ax, result, "NIS / dof", f"innovation NIS per dof ({x.size} updates): {summary['verdict']}")
    return ax


# Above this many poses the association plot stacks areas instead of bars: a bar is an artist of
# its own, and 20,000 poses' three bars each took matplotlib 50 s to add and draw.
MAX_BARS = 1000


def plot_associations(ax: Axes, result: RunResult) -> Axes:
    """Per pose, stacked bars of correct, wrong and rejected associations (against the file's ids);
    past ``MAX_BARS`` poses, the same counts as stacked step areas, one artist each.

    Wrong includes clutter that was accepted; rejected includes clutter rightly rejected.
    """
    outcomes = metrics.association_outcomes(result.associations, result.map_landmark_ids)
    scores = metrics.association_scores(result.associations, result.map_landmark_ids)
    # Pose ids are in the odometry chain's order, not necessarily increasing: search them sorted.
    # (load_run has checked that every association is of one of the run's poses.)
    order = np.argsort(result.pose_ids)
    index = order[np.searchsorted(result.pose_ids, result.associations.pose_id, sorter=order)]
    counts = {
        name: np.bincount(index[outcomes[name]], minlength=len(result.pose_ids))
        for name in ("correct", "wrong", "rejected")
    }
    labels = {
        "correct": f"correct ({scores['correct']})",
        "wrong": f"wrong ({scores['wrong']}, {scores['clutter_accepted']} of them clutter)",
        "rejected": f"rejected ({scores['rejected']}, {scores['missed']} of them in the map)",
    }
    colors = {"correct": CORRECT_COLOR, "wrong": WRONG_COLOR, "rejected": REJECTED_COLOR}
    bottom = np.zeros(len(result.pose_ids))
    for name, color in colors.items():
        top = bottom + counts[name]
        if len(result.pose_ids) > MAX_BARS:
            ax.fill_between(result.pose_ids, bottom, top, step="mid", color=color, linewidth=0, label=labels[name])
        else:
            ax.bar(result.pose_ids, counts[name], bottom=bottom, width=0.85, color=color, linewidth=0, label=labels[name])
        bottom = top
    # Head room for the legend above the tallest bar.
    ax.set_ylim(0.0, max(float(bottom.max()), 1.0) * 1.3 + 0.3)
    precision = "-" if scores["precision"] is None else f"{scores['precision']:.3f}"
    recall = "-" if scores["recall"] is None else f"{scores['recall']:.3f}"
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    _finish_time_axis(ax, result, "observations", f"data association per pose: precision {precision}, recall {recall}")
    ax.legend(loc="upper center", fontsize="small", framealpha=0.9, ncol=3)
    return ax


# --------------------------------------------------------------------------------------------
# Sweeps (``camloc sweep``)

ORACLE_COLOR = "0.45"


def plot_sweep_ate(ax: Axes, groups: list[tuple[str, str | None, list[float]]], *, title: str = "") -> Axes:
    """Distribution of position RMSE per configuration: a box and every run as a point, log scale.

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
    ax.set_xticks(positions, [label for label, _, _ in groups], fontsize="small")
    ax.set_xlim(0.4, len(groups) + 0.6)
    if filled:
        _plain_log_scale(ax)
        low, high = ax.get_ylim()
        if high / low < 10.0:  # within a decade every tick needs its number
            ax.yaxis.set_minor_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    ax.set_ylabel("position RMSE [m]")
    ax.set_title(title or "position RMSE per configuration")
    ax.grid(True, axis="y", alpha=0.3, which="both")
    return ax


# --------------------------------------------------------------------------------------------
# Figures: layouts on a figure the caller created


def draw_topdown(fig: Figure, result: RunResult) -> Figure:
    plot_topdown(fig.add_subplot(1, 1, 1), result)
    return fig


def draw_3d(fig: Figure, result: RunResult) -> Figure:
    plot_3d(fig.add_subplot(1, 1, 1, projection="3d"), result)
    return fig


def draw_errors(fig: Figure, result: RunResult) -> Figure:
    top, bottom = fig.subplots(2, 1, sharex=True)
    plot_position_error(top, result)
    plot_rotation_error(bottom, result)
    if result.truth_xyz is not None:
        top.set_xlabel("")
    fig.suptitle(f"{dataset_name(result)}: pose errors")
    return fig


def draw_consistency(fig: Figure, result: RunResult) -> Figure:
    top, bottom = fig.subplots(2, 1, sharex=True)
    plot_nees(top, result)
    plot_nis(bottom, result)
    if result.truth_xyz is not None:
        top.set_xlabel("")
    fig.suptitle(f"{dataset_name(result)}: filter consistency")
    return fig


def draw_associations(fig: Figure, result: RunResult) -> Figure:
    ax = plot_associations(fig.add_subplot(1, 1, 1), result)
    ax.set_title(f"{dataset_name(result)}: {ax.get_title()}")
    return fig


def draw_sweep(fig: Figure, sweep: tuple[list, str]) -> Figure:
    """A sweep's position RMSE per configuration; ``sweep`` is (groups, title) as
    ``plot_sweep_ate`` takes them."""
    groups, title = sweep
    plot_sweep_ate(fig.add_subplot(1, 1, 1), groups, title=title)
    return fig


def draw_report(fig: Figure, result: RunResult) -> Figure:
    """Every plot on one figure: paths (top-down, 3D), errors, NEES and NIS, associations."""
    grid = fig.add_gridspec(4, 2, height_ratios=[2.2, 1.0, 1.0, 1.0])
    plot_topdown(fig.add_subplot(grid[0, 0]), result)
    plot_3d(fig.add_subplot(grid[0, 1], projection="3d"), result)
    plot_position_error(fig.add_subplot(grid[1, 0]), result)
    plot_rotation_error(fig.add_subplot(grid[1, 1]), result)
    plot_nees(fig.add_subplot(grid[2, 0]), result)
    plot_nis(fig.add_subplot(grid[2, 1]), result)
    plot_associations(fig.add_subplot(grid[3, :]), result)
    return fig


# name -> (figure size in inches, layout); file names are ``fig-<name>.<format>``.
FIGURES: dict[str, tuple[tuple[float, float], Callable[[Figure, RunResult], Figure]]] = {
    "topdown": ((8.0, 7.0), draw_topdown),
    "3d": ((8.0, 7.0), draw_3d),
    "errors": ((10.0, 7.0), draw_errors),
    "consistency": ((10.0, 7.0), draw_consistency),
    "associations": ((12.0, 4.0), draw_associations),
}
REPORT_SIZE = (15.0, 19.0)
