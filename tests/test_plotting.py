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
    estimate = next(line for label, line in lines.items() if label.startswith(plotting.path_names(result)["estimate"]))
    odometry = next(line for label, line in lines.items() if label.startswith("odometry"))
    np.testing.assert_array_equal(estimate.get_xydata(), result.estimate_xyz[:, :2])
    np.testing.assert_array_equal(odometry.get_xydata(), result.odometry_xyz[:, :2])
    np.testing.assert_array_equal(lines["ground truth"].get_xydata(), result.truth_xyz[:, :2])
    assert estimate.get_color() == "tab:blue" and odometry.get_color() == "tab:green"
    rmse = np.sqrt(np.mean(metrics.position_errors(result.estimate_xyz, result.truth_xyz) ** 2))
    assert f"{rmse:.3f} m" in estimate.get_label()
    assert result.dataset in ax.get_title() and f"{plotting.path_names(result)['estimate']} {rmse:.3f} m" in ax.get_title()
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
    np.testing.assert_array_equal(lines[plotting.path_names(result)["estimate"]].get_xdata(), result.pose_ids)
    np.testing.assert_allclose(lines[plotting.path_names(result)["estimate"]].get_ydata(), metrics.position_errors(result.estimate_xyz, result.truth_xyz))
    band = ax.collections[0].get_paths()[0].vertices
    assert band[:, 1].max() == pytest.approx(plotting.position_sigma_bound(result).max())

    ax = Figure().add_subplot()
    plotting.plot_rotation_error(ax, result, paths=("odometry",))
    np.testing.assert_allclose(
        _lines_by_label(ax)["odometry"].get_ydata(),
        metrics.rotation_errors_deg(result.odometry_quat_xyzw, result.truth_quat_xyzw),
    )
    assert ax.get_ylabel() == "rotation error [deg]"


def test_nees_and_nis_plots_show_values_and_bounds(result):
    ax = Figure().add_subplot()
    plotting.plot_nees(ax, result)
    nees_line = _lines_by_label(ax)[f"{plotting.path_names(result)['estimate']} NEES"]
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
    assert len(fig.axes) == 9  # paths (2), the filter's errors (2), odometry's (2), NEES, NIS, associations
    assert fig.axes[1].name == "3d"
    assert "odometry" not in _lines_by_label(fig.axes[2]) and set(_lines_by_label(fig.axes[4])) == {"odometry"}


def test_library_core_does_not_import_matplotlib():
    code = "import sys, camloc.results, camloc.metrics, camloc.cli.app; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


# --------------------------------------------------------------------------------------------
# Figures a reader trusts at a glance (issue 21, point 5)


def test_3d_view_draws_the_truth_over_the_estimates_from_a_marked_start_to_a_marked_end(result):
    ax = Figure().add_subplot(projection="3d")
    plotting.plot_3d(ax, result)
    lines = _lines_by_label(ax)
    estimate = next(line for label, line in lines.items() if label.startswith(plotting.path_names(result)["estimate"]))
    truth = lines["ground truth"]
    # drawn in zorder (no depth sorting): a thin truth over a wider estimate that shows around it
    assert ax.computed_zorder is False
    assert truth.get_zorder() > estimate.get_zorder() > ax.collections[0].get_zorder()
    assert estimate.get_linewidth() > 2 * truth.get_linewidth()
    for name, index in (("start of the estimate", 0), ("end of the estimate", -1)):
        np.testing.assert_array_equal(np.ravel(lines[name].get_data_3d()), result.estimate_xyz[index])
        assert lines[name].get_zorder() > truth.get_zorder()
    # the limits hold the estimate and the truth
    points = np.vstack([result.estimate_xyz, result.truth_xyz])
    for axis, (low, high) in enumerate((ax.get_xlim(), ax.get_ylim(), ax.get_zlim())):
        assert low <= points[:, axis].min() and points[:, axis].max() <= high


def _drifting(result, drift):
    """``result`` whose odometry drifts by ``drift`` (3,) metres a pose (odometry's drift over
    thousands of poses)."""
    import dataclasses

    steps = np.arange(len(result.pose_ids))[:, None] * np.asarray(drift, dtype=float)
    return dataclasses.replace(result, odometry_xyz=result.odometry_xyz + steps)


def _flat(result):
    """``result`` on flat ground, map included, like the real file."""
    import dataclasses

    flat = [1.0, 1.0, 0.0]
    return dataclasses.replace(result, truth_xyz=result.truth_xyz * flat, estimate_xyz=result.estimate_xyz * flat,
                               odometry_xyz=result.odometry_xyz * flat, map_landmark_xyz=result.map_landmark_xyz * flat)


def test_path_views_are_set_by_the_estimate_and_truth_and_clip_odometry(result):
    # odometry's drift (here 30 m a pose, up and sideways) sets neither view; it is clipped to it
    drifted = _drifting(result, [30.0, 0.0, 30.0])
    span = np.ptp(np.vstack([result.estimate_xyz, result.truth_xyz]), axis=0)
    ax = plotting.plot_topdown(Figure().add_subplot(), drifted)
    ax.apply_aspect()
    assert np.ptp(ax.get_xlim()) < 3 * span[:2].max() and np.ptp(ax.get_ylim()) < 3 * span[:2].max()
    ax3 = plotting.plot_3d(Figure().add_subplot(projection="3d"), drifted)
    limits = np.array([ax3.get_xlim(), ax3.get_ylim(), ax3.get_zlim()])
    assert np.all(np.ptp(limits, axis=1) < 1.2 * span[:2].max())
    for view in (ax, ax3):
        label = next(line.get_label() for line in view.get_lines() if line.get_label().startswith("odometry"))
        assert f"of {len(result.pose_ids)} poses outside the view" in label
    odometry = next(line for line in ax3.get_lines() if line.get_label().startswith("odometry"))
    drawn = np.column_stack(odometry.get_data_3d())
    drawn = drawn[np.isfinite(drawn).all(axis=1)]
    assert len(drawn) and np.all((drawn >= limits[:, 0]) & (drawn <= limits[:, 1]))


def test_3d_view_of_a_flat_run_is_flat_on_one_scale_and_holds_the_estimate(result):
    # the real file's shape: flat ground, odometry drifting in z; the z axis is neither set by
    # the drift nor stretched, and is at least MIN_Z_SPAN of the width tall
    flat = _drifting(_flat(result), [0.0, 0.0, -0.5])
    ax = plotting.plot_3d(Figure().add_subplot(projection="3d"), flat)
    limits = np.array([ax.get_xlim(), ax.get_ylim(), ax.get_zlim()])
    spans = np.ptp(limits, axis=1)
    assert spans[2] == pytest.approx(plotting.MIN_Z_SPAN * spans[:2].max())
    assert limits[2, 0] <= flat.estimate_xyz[:, 2].min() and flat.estimate_xyz[:, 2].max() <= limits[2, 1]
    np.testing.assert_allclose(np.array(ax.get_box_aspect()) / ax.get_box_aspect()[0], spans / spans[0])
    assert ax.get_zlabel() == "z [m]"
    # a tall scene keeps its height, on the same scale
    import dataclasses

    tall = dataclasses.replace(result, truth_xyz=result.truth_xyz * [1.0, 1.0, 30.0])
    ax = plotting.plot_3d(Figure().add_subplot(projection="3d"), tall)
    assert ax.get_zlim()[1] - ax.get_zlim()[0] >= np.ptp(tall.truth_xyz[:, 2])


@pytest.mark.parametrize("three_d", [False, True])
def test_path_legends_hide_no_data(result, three_d):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    size, _ = plotting.FIGURES["3d" if three_d else "topdown"]
    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d") if three_d else fig.add_subplot()
    (plotting.plot_3d if three_d else plotting.plot_topdown)(ax, result)
    fig.canvas.draw()
    legend = ax.get_legend().get_window_extent()
    assert not legend.overlaps(ax.get_window_extent())  # outside the axes, let alone the data
    assert fig.bbox.contains(legend.x0, legend.y0) and fig.bbox.contains(legend.x1, legend.y1)


@pytest.mark.parametrize("count", [200, 2_000, 4_000, 20_000])
def test_a_large_map_stays_a_light_background(result, count):
    # 7,000 landmarks drawn as 9 pt^2 squares were grey blobs: the map's ink stays under a tenth
    # of the axis whatever its count; past MAP_DENSITY_FROM it is a density image
    import dataclasses

    rng = np.random.default_rng(1)
    big = dataclasses.replace(result, map_landmark_ids=np.arange(count),
                              map_landmark_xyz=rng.uniform([-3.0, -3.0, 0.0], [3.0, 3.0, 0.2], (count, 3)))
    fig = Figure(figsize=plotting.FIGURES["topdown"][0])
    ax = plotting.plot_topdown(fig.add_subplot(), big)
    if count >= plotting.MAP_DENSITY_FROM:
        assert not ax.collections and ax.images[0].get_array().sum() == count
        return
    points = ax.collections[0]
    axis_area = np.prod(ax.get_position().size * fig.get_size_inches() * 72.0)
    assert points.get_sizes()[0] * count <= 0.1 * axis_area
    assert "map (%d landmarks" % count in points.get_label()


def test_error_figure_gives_odometry_its_own_panels(result):
    fig = plotting.draw_errors(Figure(figsize=plotting.FIGURES["errors"][0]), result)
    assert len(fig.axes) == 4
    filter_axes, odometry_axes = fig.axes[0::2], fig.axes[1::2]
    for ax in filter_axes:
        labels = set(_lines_by_label(ax))
        assert plotting.path_names(result)["estimate"] in labels and "odometry" not in labels
        assert len(ax.collections) == 1  # the 3-sigma band, with the filter's errors only
        band_top = ax.collections[0].get_paths()[0].vertices[:, 1].max()
        assert ax.get_ylim()[1] >= band_top
    for ax in odometry_axes:
        assert set(_lines_by_label(ax)) == {"odometry"} and not ax.collections
    # the filter's panel is scaled to the filter: odometry's metres would squash it
    top = plotting.position_sigma_bound(result).max()
    ekf_error = metrics.position_errors(result.estimate_xyz, result.truth_xyz).max()
    assert filter_axes[0].get_ylim()[1] <= 1.1 * max(top, ekf_error)


def test_consistency_legends_sit_beside_the_data(result):
    fig = plotting.draw_consistency(Figure(figsize=plotting.FIGURES["consistency"][0]), result)
    for ax in fig.axes:
        legend = ax.get_legend()
        assert legend is not None
        anchor = legend.get_bbox_to_anchor().transformed(ax.transAxes.inverted())
        assert anchor.x0 >= 1.0  # to the right of the axis: it hides no point
    assert "consistency:" in fig.get_suptitle() and "NIS" in fig.get_suptitle()


def test_consistency_past_a_thousand_poses_draws_a_rolling_mean(synthetic_run):
    result = synthetic_run(seed=3, num_poses=plotting.ROLLING_FROM + 300)
    ax = plotting.plot_nees(Figure().add_subplot(), result)
    lines = _lines_by_label(ax)
    raw = lines[f"{plotting.path_names(result)['estimate']} NEES"]
    assert raw.get_linestyle() == "None"  # points, not a solid band of lines
    rolling = next(line for label, line in lines.items() if label.startswith("rolling mean"))
    nees = metrics.run_nees(result)
    used = np.isfinite(nees)
    window = plotting.rolling_window(int(used.sum()))
    np.testing.assert_array_equal(rolling.get_xdata(), result.pose_ids[used])
    middle = len(rolling.get_ydata()) // 2
    expected = np.mean(nees[used][middle - window // 2: middle - window // 2 + window])
    assert rolling.get_ydata()[middle] == pytest.approx(expected)

    ax = plotting.plot_nis(Figure().add_subplot(), result)
    rolling = next(line for label, line in _lines_by_label(ax).items() if label.startswith("rolling mean"))
    assert np.all(np.isfinite(rolling.get_ydata())) and len(rolling.get_ydata()) == len(result.nis)

    # a short run has no rolling mean
    short = plotting.plot_nees(Figure().add_subplot(), synthetic_run(seed=3, num_poses=50))
    assert not any(label.startswith("rolling") for label in _lines_by_label(short))


def test_rolling_ratio_weighs_by_the_denominator():
    np.testing.assert_allclose(plotting.rolling_ratio(np.array([3.0, 3.0, 12.0]), np.array([3, 3, 6]), 3),
                               [6 / 6, 18 / 12, 15 / 9])


def test_associations_tell_every_outcome_apart_and_mark_wrong_pairs(synthetic_run):
    result = synthetic_run(seed=5, num_poses=60)
    ax = plotting.plot_associations(Figure().add_subplot(), result)
    colours = [matplotlib.colors.to_hex(container.patches[0].get_facecolor()) for container in ax.containers]
    assert len(colours) == 4 and len(set(colours)) == 4  # correct, wrong, missed, clutter rejected
    labels = [text.get_text() for text in ax.get_legend().get_texts()]
    assert [label.split(" (")[0] for label in labels] == ["correct", "wrong", "missed", "clutter rejected",
                                                          "pose with a wrong pair"]
    outcomes = metrics.association_outcomes(result.associations, result.map_landmark_ids)
    index = np.searchsorted(result.pose_ids, result.associations.pose_id)
    heights = {name: np.array([bar.get_height() for bar in container])
               for name, container in zip(("correct", "wrong", "missed", "clutter"), ax.containers)}
    np.testing.assert_array_equal(heights["missed"], np.bincount(index[outcomes["missed"]], minlength=60))
    np.testing.assert_array_equal(heights["clutter"],
                                  np.bincount(index[outcomes["rejected"] & ~outcomes["in_map"]], minlength=60))
    # one marker per pose with a wrong pair, above its stack
    markers = ax.collections[-1].get_offsets()
    wrong_poses = np.unique(result.associations.pose_id[outcomes["wrong"]])
    np.testing.assert_array_equal(np.asarray(markers)[:, 0], wrong_poses)
    totals = np.bincount(index, minlength=60)
    assert np.all(np.asarray(markers)[:, 1] > totals[np.searchsorted(result.pose_ids, wrong_poses)])
    assert ax.get_ylim()[1] > np.asarray(markers)[:, 1].max()


def test_the_figures_plot_draws_are_the_ones_a_forced_run_replaces():
    # results.CAMLOC_FILES names them so that 'camloc run --force' drops the old run's figures.
    from camloc import plotting, results

    assert tuple(plotting.FIGURES) == results.FIGURE_NAMES
    assert {f"fig-{name}.png" for name in plotting.FIGURES} <= results.CAMLOC_FILES


# --------------------------------------------------------------------------------------------
# Figures that stay readable at 3,000 poses and beyond (issue 36, point 4)


@pytest.fixture
def long_run(synthetic_run):
    """3,000 poses, ids from 100,000 (six digits), smoothed: the errors of the smoother a little
    under the filter's."""
    import dataclasses

    run = synthetic_run(seed=11, num_poses=3000)
    return dataclasses.replace(run, pose_ids=run.pose_ids + 99_000,
                               associations=dataclasses.replace(run.associations, pose_id=run.associations.pose_id + 99_000),
                               update_pose_ids=run.update_pose_ids + 99_000,
                               smoothed_xyz=0.5 * (run.estimate_xyz + run.truth_xyz), smoothed_quat_xyzw=run.truth_quat_xyzw)


def _drawn(fig):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    fig.canvas.draw()
    return fig


def _overlapping_tick_labels(axis) -> int:
    extents = [label.get_window_extent() for label in axis.get_ticklabels() if label.get_visible() and label.get_text()]
    return sum(a.overlaps(b) for i, a in enumerate(extents) for b in extents[i + 1:])


@pytest.mark.parametrize("rotation", [False, True])
def test_a_long_runs_sigma_band_is_a_visible_area_and_keeps_its_highest_value(long_run, rotation):
    # 3,000 one-pose spikes of the band were sub-pixel hairlines: per bin of poses, each step of
    # the band is pixels wide, and the highest step is the highest bound
    fig = _drawn(plotting.draw_errors(Figure(figsize=plotting.FIGURES["errors"][0], layout="constrained"), long_run))
    ax = fig.axes[2 * rotation]
    bound = (plotting.rotation_sigma_bound_deg if rotation else plotting.position_sigma_bound)(long_run)
    highest, median = ax.collections[:2]
    for band in (highest, median):
        corners = ax.transData.transform(band.get_paths()[0].vertices)
        steps = np.diff(np.unique(np.round(corners[:, 0], 6)))
        assert steps.min() >= 2.0  # pixels
    assert highest.get_paths()[0].vertices[:, 1].max() == pytest.approx(bound.max())
    assert np.median(median.get_paths()[0].vertices[:, 1]) < np.median(highest.get_paths()[0].vertices[:, 1])
    assert ax.get_ylim()[0] > 0 and ax.get_yscale() == "log"  # millimetres under metre spikes
    assert _overlapping_tick_labels(ax.xaxis) == 0  # six-digit pose ids


@pytest.mark.parametrize("poses", [60, 3000])
def test_the_smoothed_errors_do_not_hide_the_filters(synthetic_run, long_run, poses):
    # the smoother's line, drawn over the filter's, is narrower: the filter's shows around it
    import dataclasses

    if poses == 3000:
        run = long_run
    else:
        run = synthetic_run(seed=5, num_poses=poses)
        run = dataclasses.replace(run, smoothed_xyz=run.truth_xyz, smoothed_quat_xyzw=run.truth_quat_xyzw)
    ax = plotting.plot_position_error(Figure().add_subplot(), run)
    names = plotting.path_names(run)
    lines = {key: next(line for line in ax.get_lines() if line.get_label().startswith(names[key]))
             for key in ("estimate", "smoothed")}
    assert lines["smoothed"].get_zorder() > lines["estimate"].get_zorder()
    assert lines["estimate"].get_linewidth() >= 2 * lines["smoothed"].get_linewidth()


def test_a_long_runs_associations_count_every_outcome_per_bin_visibly(long_run):
    # a bar per pose was a comb of sub-pixel bars where 2% missed and 10% clutter vanished: past
    # MAX_BARS poses, each outcome's count per bin is its own line on a log axis
    fig = _drawn(plotting.draw_associations(Figure(figsize=plotting.FIGURES["associations"][0], layout="constrained"),
                                            long_run))
    ax = fig.axes[0]
    assert ax.get_yscale() == "log"
    outcomes = metrics.association_outcomes(long_run.associations, long_run.map_landmark_ids)
    outcomes["clutter_rejected"] = outcomes["rejected"] & ~outcomes["in_map"]
    lines = ax.get_lines()
    assert [line.get_label().split(" (")[0] for line in lines] == ["correct", "wrong", "missed", "clutter rejected"]
    for name, line in zip(plotting.ASSOCIATION_CATEGORIES, lines):
        edges, values = line.get_xdata(), np.nan_to_num(line.get_ydata()[:-1])
        assert values.sum() == np.count_nonzero(outcomes[name])  # every observation counted once
        if values.sum():
            assert np.nanmax(line.get_ydata()) > ax.get_ylim()[0]  # in view
        widths = np.diff(ax.transData.transform(np.column_stack([edges, np.ones_like(edges)]))[:, 0])
        assert widths.min() >= 2.0  # pixels
    assert "per 20 poses" in ax.get_title() and _overlapping_tick_labels(ax.xaxis) == 0
    legend = ax.get_legend().get_window_extent()
    assert not legend.overlaps(ax.get_window_extent())


def test_associations_of_a_run_that_used_no_observation_say_why_the_panel_is_empty(result):
    import dataclasses

    none = dataclasses.replace(result, associations=dataclasses.replace(
        result.associations, **{field.name: getattr(result.associations, field.name)[:0]
                                for field in dataclasses.fields(result.associations)}))
    all_rejected = dataclasses.replace(result, associations=dataclasses.replace(
        result.associations, landmark=np.full_like(result.associations.landmark, -1)))
    for run in (none, all_rejected):
        fig = plotting.draw_associations(Figure(figsize=plotting.FIGURES["associations"][0]), run)
        texts = [text.get_text() for text in fig.axes[0].texts]
        assert "no observation was used: the estimate is odometry alone" in texts
    # a run that used some keeps its bars without the note
    ax = plotting.plot_associations(Figure().add_subplot(), result)
    assert not ax.texts


def test_the_reports_page_title_names_the_run(result):
    import dataclasses

    run = dataclasses.replace(result, summary={**result.summary, "config": {"filter": "se3", "iterations": 1, "association": "jcbb"}})
    title = plotting.draw_report(Figure(figsize=plotting.REPORT_SIZE), run).get_suptitle()
    assert title.startswith(f"{run.dataset}: EKF (se3), jcbb association, {len(run.pose_ids)} poses")
    assert "consistency:" in title.splitlines()[1]  # the verdict below it, no longer the page's title


def _sweep_groups(values_of) -> list:
    """Eight configurations as camloc.sweep.ate_groups labels them, the oracle beside each method."""
    groups = []
    for clutter in ("0.0", "0.15"):
        for trajectory in ("grid", "smooth3d"):
            for association in ("oracle", "beam"):
                label = f"clutter-fraction={clutter}\ntrajectory={trajectory}\nassociation={association}"
                groups.append((label, association, values_of(len(groups))))
    return groups


def test_sweep_labels_are_readable_and_a_legend_names_the_oracles_colour():
    groups = _sweep_groups(lambda n: list(0.05 + 0.01 * np.arange(3) + 0.002 * n))
    fig = _drawn(plotting.draw_sweep(Figure(figsize=plotting.sweep_size(groups), layout="constrained"), (groups, "study")))
    ax = fig.axes[0]
    labels = [tick.get_text() for tick in ax.get_xticklabels()]
    assert len(labels) == 4 and not any("association=" in label for label in labels)  # the colour says it
    assert _overlapping_tick_labels(ax.xaxis) == 0
    legend = ax.get_legend()
    entries = {text.get_text(): handle for text, handle in zip(legend.get_texts(), legend.legend_handles)}
    oracle = next(handle for text, handle in entries.items() if text.startswith("oracle"))
    assert matplotlib.colors.to_hex(oracle.get_facecolor()) == matplotlib.colors.to_hex(plotting.ORACLE_COLOR)
    assert "beam" in entries
    assert not legend.get_window_extent().overlaps(ax.get_window_extent())


@pytest.mark.parametrize("low, high", [(0.092, 0.097), (0.05, 0.09), (0.03, 0.5), (0.2, 9.0), (0.015, 6.0), (0.01, 40.0), (0.0015, 2.0)])
def test_the_sweeps_value_axis_always_has_numbers_to_read(low, high):
    groups = _sweep_groups(lambda n: list(np.geomspace(low, high, 8)[[n, (n + 3) % 8]]))
    fig = _drawn(plotting.draw_sweep(Figure(figsize=plotting.sweep_size(groups), layout="constrained"), (groups, "")))
    ax = fig.axes[0]
    bottom, top = ax.get_ylim()
    shown = [tick for tick in ax.yaxis.get_majorticklabels() + ax.yaxis.get_minorticklabels()
             if tick.get_text() and bottom <= tick.get_position()[1] <= top]
    assert len(shown) >= 3
    assert _overlapping_tick_labels(ax.yaxis) == 0


def test_the_figures_name_the_estimate_as_the_tables_do(synthetic_run):
    # issue 36, point 1: a table's "iterated EKF (euler)" is not a figure's "EKF", and a run whose
    # filter made no update shows odometry alone under its own name
    import dataclasses

    from camloc.diagnostics import ODOMETRY_ALONE

    result = synthetic_run(seed=3)
    result = dataclasses.replace(result, summary={**result.summary, "config": {"filter": "euler", "iterations": 3}})
    labels = [line.get_label() for line in plotting.plot_topdown(Figure().add_subplot(), result).get_lines()]
    assert any(label.startswith("iterated EKF (euler) (RMSE") for label in labels)
    assert plotting.run_title(result).split(": ", 1)[1].startswith("iterated EKF (euler), ")
    nothing = dataclasses.replace(result, nis=result.nis[:0])
    assert plotting.path_names(nothing)["estimate"] == ODOMETRY_ALONE
    nees_labels = [line.get_label() for line in plotting.plot_nees(Figure().add_subplot(), nothing).get_lines()]
    assert f"{ODOMETRY_ALONE} NEES" in nees_labels


def test_a_planar_runs_markers_are_drawn_with_their_headings(tmp_path):
    """A planar run's top-down view: a tick per marker from its position in its heading (one
    LineCollection), kept in the run folder (map_landmark_heading in states.npz); a 3-D run of
    points draws none."""
    from matplotlib.collections import LineCollection

    from camloc.localizer import localize
    from camloc.results import load_run, save_run
    from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar

    dataset = simulate_planar(PlanarSimulationConfig(sensors="markers,points", poses=40), seed=1)
    save_run(tmp_path / "run", localize(dataset))
    run = load_run(tmp_path / "run")
    assert np.allclose(run.map_landmark_heading, dataset.landmark_heading, equal_nan=True)
    ax = Figure().add_subplot()
    plotting.plot_topdown(ax, run)
    [ticks] = [c for c in ax.collections if isinstance(c, LineCollection)]
    segments = np.array(ticks.get_segments())
    assert 0 < len(segments) <= np.count_nonzero(np.isfinite(dataset.landmark_heading))
    start = np.array([np.flatnonzero(np.all(np.isclose(dataset.landmark_xyz[:, :2], s), axis=1))[0] for s in segments[:, 0]])
    direction = segments[:, 1] - segments[:, 0]
    assert np.allclose(np.arctan2(direction[:, 1], direction[:, 0]), np.angle(np.exp(1j * dataset.landmark_heading[start])))
    assert ticks.get_label().startswith(f"headings ({len(segments)} ")


def test_a_3d_run_draws_no_headings(result):
    ax = Figure().add_subplot()
    plotting.plot_topdown(ax, result)
    from matplotlib.collections import LineCollection

    assert not [c for c in ax.collections if isinstance(c, LineCollection)]


def test_path_titles_wrap_between_paths_not_inside_one():
    parts = ["position RMSE:", "iterated EKF-SLAM (map exact) 0.042 m", "odometry 1.654 m", "smoothed 0.036 m"]
    assert plotting._packed(parts, 64) == "position RMSE: iterated EKF-SLAM (map exact) 0.042 m,\nodometry 1.654 m, smoothed 0.036 m"
    assert plotting._packed(parts[:3], 80) == "position RMSE: iterated EKF-SLAM (map exact) 0.042 m, odometry 1.654 m"
    assert plotting._packed(["a:", "x" * 90, "b"], 10) == "a:\n" + "x" * 90 + ",\nb"  # a long part is never cut
