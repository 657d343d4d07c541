"""Plot functions draw the run's numbers into the axis they are given (Agg, no display)."""

from __future__ import annotations

import subprocess
import sys

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest
from matplotlib.figure import Figure

from camloc import metrics, plotting


@pytest.fixture
def result(synthetic_run):
    return synthetic_run(seed=5, num_poses=30)


def _lines_by_label(ax) -> dict:
    return {line.get_label(): line for line in ax.get_lines()}


def test_topdown_draws_each_path_with_its_rmse_and_equal_axes(result):
    ax = Figure().add_subplot()
    plotting.plot_topdown(ax, result)
    lines = _lines_by_label(ax)
    estimate = next(line for label, line in lines.items() if label.startswith("EKF"))
    odometry = next(line for label, line in lines.items() if label.startswith("odometry"))
    np.testing.assert_array_equal(estimate.get_xydata(), result.estimate_xyz[:, :2])
    np.testing.assert_array_equal(odometry.get_xydata(), result.odometry_xyz[:, :2])
    np.testing.assert_array_equal(lines["ground truth"].get_xydata(), result.truth_xyz[:, :2])
    assert estimate.get_color() == "tab:blue" and odometry.get_color() == "tab:green"
    rmse = np.sqrt(np.mean(metrics.position_errors(result.estimate_xyz, result.truth_xyz) ** 2))
    assert f"{rmse:.3f} m" in estimate.get_label()
    assert result.dataset in ax.get_title() and f"EKF {rmse:.3f} m" in ax.get_title()
    assert ax.get_aspect() == 1.0
    assert ax.get_xlabel() == "x [m]" and ax.get_legend() is not None
    assert len(ax.collections[0].get_offsets()) == len(result.map_landmark_ids)


def test_sigma_bands_are_three_sqrt_trace():
    class Stub:
        estimate_cov = np.diag([0.01, 0.04, 0.04, 1e-4, 1e-4, 2e-4])[None].repeat(2, axis=0)

    np.testing.assert_allclose(plotting.position_sigma_bound(Stub()), [0.9, 0.9])
    np.testing.assert_allclose(plotting.rotation_sigma_bound_deg(Stub()), np.degrees(3 * 0.02) * np.ones(2))


def test_error_plots_draw_the_errors_over_pose_ids(result):
    ax = Figure().add_subplot()
    plotting.plot_position_error(ax, result)
    lines = _lines_by_label(ax)
    np.testing.assert_array_equal(lines["EKF"].get_xdata(), result.pose_ids)
    np.testing.assert_allclose(lines["EKF"].get_ydata(), metrics.position_errors(result.estimate_xyz, result.truth_xyz))
    band = ax.collections[0].get_paths()[0].vertices
    assert band[:, 1].max() == pytest.approx(plotting.position_sigma_bound(result).max())

    ax = Figure().add_subplot()
    plotting.plot_rotation_error(ax, result)
    np.testing.assert_allclose(
        _lines_by_label(ax)["odometry"].get_ydata(),
        metrics.rotation_errors_deg(result.odometry_quat_xyzw, result.truth_quat_xyzw),
    )
    assert ax.get_ylabel() == "rotation error [deg]"


def test_nees_and_nis_plots_show_values_and_bounds(result):
    ax = Figure().add_subplot()
    plotting.plot_nees(ax, result)
    nees_line = _lines_by_label(ax)["EKF NEES"]
    np.testing.assert_allclose(nees_line.get_ydata(), metrics.run_nees(result))
    assert ax.get_yscale() == "log"
    assert "[1.24, 14.45]" in " ".join(text.get_text() for text in ax.get_legend().get_texts())

    ax = Figure().add_subplot()
    plotting.plot_nis(ax, result)
    points = _lines_by_label(ax)["NIS / dof"]
    np.testing.assert_array_equal(points.get_xdata(), result.update_pose_ids)
    np.testing.assert_allclose(points.get_ydata(), result.nis / result.nis_dof)


def test_association_bars_stack_to_the_observations_of_each_pose(result):
    ax = Figure().add_subplot()
    plotting.plot_associations(ax, result)
    heights = np.zeros(len(result.pose_ids))
    for container in ax.containers:
        heights += [bar.get_height() for bar in container]
    index = np.searchsorted(result.pose_ids, result.associations.pose_id)
    np.testing.assert_array_equal(heights, np.bincount(index, minlength=len(result.pose_ids)))
    labels = [text.get_text() for text in ax.get_legend().get_texts()]
    scores = metrics.association_scores(result.associations, result.map_landmark_ids)
    assert labels[0] == f"correct ({scores['correct']})"


def test_association_bars_follow_pose_ids_that_do_not_increase(result):
    # Pose ids are in the odometry chain's order: a chain may run 1039, 1038, ..., 1000.
    import dataclasses

    reversed_id = dict(zip(result.pose_ids, result.pose_ids[::-1]))
    chain = dataclasses.replace(
        result,
        pose_ids=result.pose_ids[::-1].copy(),
        associations=dataclasses.replace(
            result.associations, pose_id=np.array([reversed_id[i] for i in result.associations.pose_id])
        ),
    )
    ax = plotting.plot_associations(Figure().add_subplot(), chain)
    heights = np.zeros(len(chain.pose_ids))
    for container in ax.containers:
        heights += [bar.get_height() for bar in container]
    index = np.searchsorted(result.pose_ids, result.associations.pose_id)  # the same poses, in order
    np.testing.assert_array_equal(heights, np.bincount(index, minlength=len(result.pose_ids)))


def test_association_areas_of_a_long_run_stack_to_the_observations_of_each_pose(synthetic_run, monkeypatch):
    # past MAX_BARS poses: three step areas instead of a bar per pose and outcome
    result = synthetic_run(seed=5, num_poses=30)
    monkeypatch.setattr(plotting, "MAX_BARS", 10)
    ax = Figure().add_subplot()
    plotting.plot_associations(ax, result)
    assert not ax.patches and len(ax.collections) == 3
    index = np.searchsorted(result.pose_ids, result.associations.pose_id)
    expected = np.bincount(index, minlength=len(result.pose_ids))
    # the last area's outline: over each pose, its highest level segment is the stack's top
    outline = ax.collections[-1].get_paths()[0].vertices
    left, right = np.minimum(outline[:-1, 0], outline[1:, 0]), np.maximum(outline[:-1, 0], outline[1:, 0])
    level = (outline[:-1, 1] == outline[1:, 1]) & (left < right)  # either way round: the outline comes back along the top
    at_pose = np.array([outline[:-1][level & (left <= pose) & (pose <= right), 1].max() for pose in result.pose_ids])
    np.testing.assert_array_equal(at_pose, expected)
    labels = [text.get_text() for text in ax.get_legend().get_texts()]
    assert labels[0].startswith("correct (")


def test_plots_without_truth_say_so(synthetic_run):
    result = synthetic_run(with_truth=False)
    for plot in (plotting.plot_position_error, plotting.plot_rotation_error, plotting.plot_nees):
        ax = Figure().add_subplot()
        plot(ax, result)
        assert "no ground truth" in ax.texts[0].get_text()
    ax = Figure().add_subplot()
    plotting.plot_topdown(ax, result)
    assert "ground truth" not in _lines_by_label(ax)


def test_report_lays_out_every_panel(result):
    fig = plotting.draw_report(Figure(figsize=plotting.REPORT_SIZE), result)
    assert len(fig.axes) == 7
    assert fig.axes[1].name == "3d"


def test_library_core_does_not_import_matplotlib():
    code = "import sys, camloc.results, camloc.metrics, camloc.cli.app; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_the_figures_plot_draws_are_the_ones_a_forced_run_replaces():
    # results.CAMLOC_FILES names them so that 'camloc run --force' drops the old run's figures.
    from camloc import plotting, results

    assert tuple(plotting.FIGURES) == results.FIGURE_NAMES
    assert {f"fig-{name}.png" for name in plotting.FIGURES} <= results.CAMLOC_FILES
