"""The map figure of a run (``fig-map``): the map it was given, the map it estimated (``map.csv``)
with each landmark's 2-sigma ellipse, added landmarks marked apart, and, given the true map, how
far the given map had each landmark that was moved.

Like ``camloc.plotting`` (the run's other figures), plot functions draw into an axis they are
given; with it, the only modules that import matplotlib. A map of thousands of landmarks is drawn
as a few collections (points, ellipses, segments), never one artist per landmark.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import EllipseCollection, LineCollection
from matplotlib.figure import Figure

from camloc.map_scores import MOVED_FROM_M  # given positions this far from the truth are drawn as moved
from camloc.plotting import ESTIMATE_COLOR, MAP_COLOR, TRUTH_COLOR, dataset_name
from camloc.results import LandmarkMap, RunResult

ADDED_COLOR = "tab:orange"
SIGMA = 2.0  # the ellipses hold 86% of a 2-D Gaussian's mass
MAP_FIGURE_SIZE = (8.0, 7.0)
# Point clouds of more landmarks than this are rasterized in a vector figure (.pdf, .svg).
RASTERIZED_FROM = 2000


@dataclass(frozen=True)
class MapView:
    """What the map figure draws.

    Attributes
    ----------
    result : the run (its path, and the map it was given: ``map_landmark_ids`` / ``_xyz``, less
        the ids ``estimated`` has as added).
    estimated : the run's ``map.csv``.
    true_ids, true_xyz : (T,), (T, 3) the true map, or None.
    """

    result: RunResult
    estimated: LandmarkMap
    true_ids: np.ndarray | None = None
    true_xyz: np.ndarray | None = None

    def given(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids (G,), xyz (G, 3)) of the map the run was given."""
        keep = ~np.isin(self.result.map_landmark_ids, self.estimated.ids[self.estimated.added])
        return np.asarray(self.result.map_landmark_ids)[keep], np.asarray(self.result.map_landmark_xyz).reshape(-1, 3)[keep]


def ellipse_axes(cov_xy: np.ndarray, *, sigma: float = SIGMA) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Widths, heights (full axes, metres) and angles (degrees, of the width from +x) of the
    ``sigma`` ellipses of covariances (K, 2, 2): ``2 sigma sqrt(lambda)`` along each eigenvector."""
    eigenvalues, eigenvectors = np.linalg.eigh(cov_xy)  # ascending: the major axis is the last
    major = eigenvectors[:, :, 1]
    width = 2.0 * sigma * np.sqrt(np.maximum(eigenvalues[:, 1], 0.0))
    height = 2.0 * sigma * np.sqrt(np.maximum(eigenvalues[:, 0], 0.0))
    return width, height, np.degrees(np.arctan2(major[:, 1], major[:, 0]))


def plot_map(ax: Axes, view: MapView, *, sigma: float = SIGMA) -> Axes:
    """Top-down (x-y) view of the map, metres: the given map (grey points), the estimated one (blue
    dots, added landmarks orange triangles) with its ``sigma`` ellipses (none for a landmark held
    exactly, zero covariance), the estimated path faintly beneath; with the true map, its
    landmarks (red crosses) and a segment from each moved landmark's given position to its truth."""
    m = view.estimated
    given_ids, given_xyz = view.given()
    ax.plot(*view.result.estimate_xyz[:, :2].T, color=ESTIMATE_COLOR, alpha=0.25, linewidth=0.8, label="estimated path",
            zorder=1)
    size, rasterized = _point_size(len(m.ids) + len(given_ids)), len(m.ids) > RASTERIZED_FROM
    ax.scatter(given_xyz[:, 0], given_xyz[:, 1], s=1.4 * size, color=MAP_COLOR, linewidths=0, label=f"given map ({len(given_ids)})",
               zorder=2, rasterized=rasterized)
    if view.true_xyz is not None:
        _draw_truth(ax, view, given_ids, given_xyz, size)
    _draw_ellipses(ax, m, sigma)
    for rows, marker, color, name in ((~m.added, "o", ESTIMATE_COLOR, "estimated, mapped"), (m.added, "^", ADDED_COLOR, "added")):
        ax.scatter(m.xyz[rows, 0], m.xyz[rows, 1], s=size if marker == "o" else 2.2 * size, marker=marker, color=color,
                   linewidths=0, label=f"{name} ({int(np.count_nonzero(rows))})", zorder=5, rasterized=rasterized)
    ax.autoscale_view()
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{dataset_name(view.result)}: map, {int(np.count_nonzero(~m.added))} mapped and "
                 f"{int(np.count_nonzero(m.added))} added landmarks ({sigma:g}-sigma ellipses)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.09), ncols=2, fontsize="small", frameon=False)
    return ax


def _point_size(count: int) -> float:
    """Marker area (points^2) of a map of ``count`` landmarks: 10 up to a few hundred, smaller
    beyond (as 1/count, at least 1), so that thousands stay points rather than a carpet."""
    return float(np.clip(3000.0 / max(count, 1), 1.0, 10.0))


def _draw_ellipses(ax: Axes, m: LandmarkMap, sigma: float) -> None:
    """One collection of the landmarks' xy ellipses, each in its origin's colour (a landmark held
    exactly has none)."""
    width, height, angle = ellipse_axes(np.asarray(m.cov)[:, :2, :2], sigma=sigma)
    shown = width > 0.0
    if not shown.any():
        return
    colors = np.where(m.added[shown], ADDED_COLOR, ESTIMATE_COLOR)
    ax.add_collection(EllipseCollection(width[shown], height[shown], angle[shown], units="xy", offsets=m.xyz[shown, :2],
                                        offset_transform=ax.transData, facecolors="none", edgecolors=colors,
                                        linewidths=0.7, zorder=4))
    ax.update_datalim(np.vstack([m.xyz[shown, :2] - width[shown, None] / 2, m.xyz[shown, :2] + width[shown, None] / 2]))
    # The legend cannot draw an EllipseCollection: an empty line with a hollow marker stands for it.
    ax.plot([], [], linestyle="none", marker="o", markersize=9, markerfacecolor="none", markeredgecolor=ESTIMATE_COLOR,
            label=f"{sigma:g}-sigma ellipses ({int(shown.sum())})")


def _draw_truth(ax: Axes, view: MapView, given_ids: np.ndarray, given_xyz: np.ndarray, size: float) -> None:
    """The true landmarks, and a segment from each moved one's given position to its truth."""
    ax.scatter(view.true_xyz[:, 0], view.true_xyz[:, 1], s=1.8 * size, marker="x", color=TRUTH_COLOR, linewidths=0.8,
               label=f"true map ({len(view.true_ids)})", zorder=3, rasterized=len(view.true_ids) > RASTERIZED_FROM)
    order = np.argsort(view.true_ids)
    at = np.clip(np.searchsorted(view.true_ids[order], given_ids), 0, max(len(order) - 1, 0))
    known = (view.true_ids[order][at] == given_ids) if len(order) else np.zeros(len(given_ids), dtype=bool)
    true_of_given = view.true_xyz[order][at]
    moved = known & (np.linalg.norm(given_xyz - true_of_given, axis=1) >= MOVED_FROM_M)
    if moved.any():
        segments = np.stack([given_xyz[moved, :2], true_of_given[moved, :2]], axis=1)
        ax.add_collection(LineCollection(segments, colors=TRUTH_COLOR, linewidths=1.2, zorder=3,
                                         label=f"moved: given -> true ({int(moved.sum())})"))


def draw_map(fig: Figure, view: MapView) -> Figure:
    plot_map(fig.add_subplot(1, 1, 1), view)
    return fig
