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


# The 3D box's height is at least this share of its width: a flat path's heights stay readable
# (the z label says by how much they are stretched).
MIN_BOX_HEIGHT = 0.25


def plot_3d(ax: Axes, result: RunResult, *, show_map: bool = True) -> Axes:
    """3D view of the same paths and map; ``ax`` must be a 3D axis (``projection="3d"``).

    x and y share one scale; z is stretched (and its label says so) where the scene is flatter
    than ``MIN_BOX_HEIGHT`` of its width. Artists keep their ``zorder`` (no depth sorting): the
    ground truth is a wide pale line under the estimate, visible where they part and as a halo
    where they agree; the start is a black circle on top.
    """
    ax.computed_zorder = False
    labels = _path_labels(result)
    clouds = list(_paths(result).values())
    if show_map and len(result.map_landmark_xyz):
        xyz = result.map_landmark_xyz
        # a large map is drawn faint, so that it does not bury the paths
        ax.scatter(*xyz.T, s=6 if len(xyz) < 1000 else 2, marker="s", color=MAP_COLOR, linewidths=0,
                   alpha=1.0 if len(xyz) < 1000 else 0.35, depthshade=False,
                   label=f"map ({len(xyz)} landmarks)", zorder=1)
        clouds.append(xyz)
    if result.truth_xyz is not None:
        ax.plot(*result.truth_xyz.T, color=TRUTH_COLOR, label="ground truth", linewidth=4.0, alpha=0.45,
                solid_capstyle="round", zorder=2)
        clouds.append(result.truth_xyz)
    ax.plot(*result.odometry_xyz.T, color=ODOMETRY_COLOR, label=labels["odometry"], zorder=3, **_STYLE)
    ax.plot(*result.estimate_xyz.T, color=ESTIMATE_COLOR, label=labels["estimate"], zorder=4, **_STYLE)
    if result.smoothed_xyz is not None:
        ax.plot(*result.smoothed_xyz.T, color=SMOOTHED_COLOR, label=labels["smoothed"], zorder=5, **_STYLE)
    ax.plot(*result.estimate_xyz[:1].T, marker="o", color=START_COLOR, markersize=7, linestyle="none",
            label="start", zorder=6)
    stretch = _fit_box(ax, np.vstack(clouds))
    ax.set_xlabel("x [m]", labelpad=10)
    ax.set_ylabel("y [m]", labelpad=10)
    ax.set_zlabel("z [m]" if stretch < 1.05 else f"z [m], stretched {stretch:.1f}x", labelpad=8)
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(MaxNLocator(nbins=5))
    ax.zaxis.set_major_locator(MaxNLocator(nbins=4))
    ax.set_title(_trajectory_title(result, "3D view"))
    ax.legend(loc="upper left", fontsize="small", framealpha=0.85)
    return ax


def _fit_box(ax: Axes, points: np.ndarray) -> float:
    """Limits holding ``points`` (M, 3) with a 3% margin, x and y at one scale; returns how much the
    box stretches z relative to them (1 when the scene is tall enough)."""
    low, high = points.min(axis=0), points.max(axis=0)
    span = np.maximum(high - low, 1e-6)
    margin = 0.03 * span.max()
    ax.set_xlim(low[0] - margin, high[0] + margin)
    ax.set_ylim(low[1] - margin, high[1] + margin)
    ax.set_zlim(low[2] - margin, high[2] + margin)
    width = span[:2].max() + 2 * margin
    extents = np.array([span[0], span[1], span[2]]) + 2 * margin
    height = max(extents[2], MIN_BOX_HEIGHT * width)
    ax.set_box_aspect((extents[0], extents[1], height), zoom=0.95)
    return float(height / extents[2])


def _finish_time_axis(ax: Axes, result: RunResult, ylabel: str, title: str) -> None:
    ax.set_xlim(result.pose_ids[0] - 0.5, result.pose_ids[-1] + 0.5)
    ax.set_xlabel("pose id")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
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


_PATH_COLORS = {"estimate": ESTIMATE_COLOR, "odometry": ODOMETRY_COLOR, "smoothed": SMOOTHED_COLOR}


def _plot_errors(ax: Axes, result: RunResult, paths: tuple[str, ...], *, rotation: bool, sigma: float) -> Axes:
    what = "rotation error" if rotation else "position error"
    if result.truth_xyz is None:
        return _no_truth(ax, what)
    x = result.pose_ids
    if "estimate" in paths:
        bound = rotation_sigma_bound_deg(result, sigma=sigma) if rotation else position_sigma_bound(result, sigma=sigma)
        symbol = "rot" if rotation else "xyz"
        ax.fill_between(x, 0.0, bound, color=ESTIMATE_COLOR, alpha=0.15, linewidth=0,
                        label=rf"EKF ${sigma:g}\sigma$ ($ {sigma:g}\sqrt{{\mathrm{{tr}}\,P_{{{symbol}}}}}$)")
    drawn = [key for key in paths if key in _paths(result)]
    for key in drawn:
        ax.plot(x, _path_errors(result, key, rotation=rotation), color=_PATH_COLORS[key], label=_PATH_NAMES[key], **_STYLE)
    ax.set_ylim(bottom=0.0)
    unit = "deg" if rotation else "m"
    whose = " and ".join(_PATH_NAMES[key] for key in drawn)
    _finish_time_axis(ax, result, f"{what} [{unit}]", f"{what} of {whose}")
    return ax


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
    summary = metrics.nees_summary(nees)
    lower, upper = summary["bounds"]
    x = result.pose_ids
    ax.axhspan(lower, upper, color="0.5", alpha=0.12, linewidth=0,
               label=f"per-pose 95% bounds [{lower:.2f}, {upper:.2f}]")
    ax.axhline(metrics.POSE_DOF, color="0.3", linestyle=":", linewidth=1.0, label=f"expected ({metrics.POSE_DOF})")
    _plot_series(ax, x, nees, np.ones_like(nees), "EKF NEES", joined=True)
    if summary["mean"] is not None:
        mean_lower, mean_upper = summary["mean_bounds"]
        ax.axhline(summary["mean"], color="crimson" if summary["verdict"] != "consistent" else ESTIMATE_COLOR,
                   linestyle="--", linewidth=1.2,
                   label=f"mean {summary['mean']:.2f}\n(95% interval [{mean_lower:.2f}, {mean_upper:.2f}]\n"
                         f"of {summary['effective_poses']:.0f} independent poses)")
    _plain_log_scale(ax)
    _finish_time_axis(ax, result, "NEES (6 dof)", f"pose NEES: {summary['verdict']}")
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


# Above this many poses the association plot stacks areas instead of bars: a bar is an artist of
# its own, and 20,000 poses' three bars each took matplotlib 50 s to add and draw.
MAX_BARS = 1000


# Per-pose outcome of the observations, bottom to top of each stack: (mask name, colour).
ASSOCIATION_CATEGORIES = {
    "correct": CORRECT_COLOR,
    "wrong": WRONG_COLOR,
    "missed": MISSED_COLOR,
    "clutter_rejected": CLUTTER_REJECTED_COLOR,
}


def plot_associations(ax: Axes, result: RunResult) -> Axes:
    """Per pose, stacked bars of correct, wrong, missed (a map landmark's detection left
    unassociated) and clutter rejected (against the file's ids); past ``MAX_BARS`` poses, the same
    counts as stacked step areas, one artist each. Every pose with a wrong pair also gets a red
    marker above its stack: at thousands of poses a one-pose bar is narrower than a pixel.

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
    bottom = np.zeros(len(result.pose_ids))
    handles = []
    for name, color in ASSOCIATION_CATEGORIES.items():
        top = bottom + counts[name]
        if len(result.pose_ids) > MAX_BARS:
            handles.append(ax.fill_between(result.pose_ids, bottom, top, step="mid", color=color, linewidth=0, label=labels[name]))
        else:
            handles.append(ax.bar(result.pose_ids, counts[name], bottom=bottom, width=0.85, color=color, linewidth=0, label=labels[name]))
        bottom = top
    wrong = counts["wrong"] > 0
    marks = ax.scatter(result.pose_ids[wrong], bottom[wrong] + 0.06 * max(float(bottom.max()), 1.0) + 0.3, marker="v", s=30,
               color=WRONG_COLOR, edgecolors="black", linewidths=0.4, zorder=5,
               label=f"pose with a wrong pair ({int(wrong.sum())})")
    ax.set_ylim(0.0, max(float(bottom.max()), 1.0) * 1.15 + 0.6)
    precision = "-" if scores["precision"] is None else f"{scores['precision']:.3f}"
    recall = "-" if scores["recall"] is None else f"{scores['recall']:.3f}"
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    _finish_time_axis(ax, result, "observations", f"data association per pose: precision {precision}, recall {recall}")
    _legend_outside(ax, handles=[*handles, marks])  # in stacking order, bottom first
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
    nees = metrics.nees_summary(metrics.run_nees(result)) if result.truth_xyz is not None else None
    nis = metrics.nis_summary(result.nis, result.nis_dof)
    verdict = metrics.consistency_verdict(nees, nis)["verdict"]
    parts = ([f"NEES {nees['verdict']}"] if nees is not None else []) + [f"NIS {nis['verdict']}"]
    return f"consistency: {verdict} ({', '.join(parts)})"


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
    """Every plot on one figure: paths (top-down, 3D), the filter's errors, odometry's errors,
    NEES and NIS, associations."""
    grid = fig.add_gridspec(5, 2, height_ratios=[2.2, 1.0, 1.0, 1.0, 1.0])
    plot_topdown(fig.add_subplot(grid[0, 0]), result)
    plot_3d(fig.add_subplot(grid[0, 1], projection="3d"), result)
    for row, paths in ((1, FILTER_PATHS), (2, ("odometry",))):
        plot_position_error(fig.add_subplot(grid[row, 0]), result, paths=paths)
        plot_rotation_error(fig.add_subplot(grid[row, 1]), result, paths=paths)
    plot_nees(fig.add_subplot(grid[3, 0]), result)
    plot_nis(fig.add_subplot(grid[3, 1]), result)
    plot_associations(fig.add_subplot(grid[4, :]), result)
    fig.suptitle(f"{dataset_name(result)}: filter {consistency_title(result)}")
    return fig


# name -> (figure size in inches, layout); file names are ``fig-<name>.<format>``.
FIGURES: dict[str, tuple[tuple[float, float], Callable[[Figure, RunResult], Figure]]] = {
    "topdown": ((8.0, 7.0), draw_topdown),
    "3d": ((10.0, 6.0), draw_3d),
    "errors": ((14.0, 7.0), draw_errors),
    "consistency": ((12.0, 7.0), draw_consistency),
    "associations": ((14.0, 4.5), draw_associations),
}
REPORT_SIZE = (17.0, 23.0)
