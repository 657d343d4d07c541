"""``camloc plot``'s map figure (``camloc.plotting_map``): what it draws, counted, and the command's
fig-map (Agg, no display)."""

from __future__ import annotations

import dataclasses

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest
from matplotlib.collections import EllipseCollection, LineCollection, PathCollection
from matplotlib.figure import Figure
from typer.testing import CliRunner

from camloc.cli.app import app
from camloc.g2o import write_g2o
from camloc.plotting_map import MapView, ellipse_axes, plot_map
from camloc.results import LandmarkMap, load_run, save_run, write_map
from camloc.simulate import SimulationConfig, simulate


def _view(synthetic_run, *, with_truth: bool) -> MapView:
    """30 given landmarks (ids 100..129, the synthetic run's map), 5 of them moved 0.3 m; an
    estimated map of 20 of them (4 held exactly, zero covariance) and 3 added landmarks."""
    run = synthetic_run(seed=5, num_poses=20)
    ids = np.r_[run.map_landmark_ids[:20], 500, 501, 502]
    rng = np.random.default_rng(0)
    xyz = np.r_[run.map_landmark_xyz[:20], rng.uniform(-3, 3, (3, 3))]
    cov = np.broadcast_to(np.diag([0.04, 0.01, 0.02]), (23, 3, 3)).copy()
    cov[:4] = 0.0
    estimated = LandmarkMap(ids, xyz, cov, np.r_[np.zeros(20, bool), np.ones(3, bool)], np.full(23, 3))
    if not with_truth:
        return MapView(run, estimated)
    true_xyz = run.map_landmark_xyz.copy()
    true_xyz[:5] += np.array([0.3, 0.0, 0.0])  # the given map has these 5 off by 0.3 m
    return MapView(run, estimated, run.map_landmark_ids, true_xyz)


def test_ellipse_axes_are_two_sigma_along_the_eigenvectors():
    cov = np.array([[[4.0, 0.0], [0.0, 1.0]], [[1.0, 0.0], [0.0, 9.0]]])
    width, height, angle = ellipse_axes(cov, sigma=2.0)
    np.testing.assert_allclose(width, [8.0, 12.0])
    np.testing.assert_allclose(height, [4.0, 4.0])
    np.testing.assert_allclose(np.abs(angle), [0.0, 90.0], atol=1e-9)  # the major axis along x, then along y


@pytest.mark.parametrize("with_truth", [False, True])
def test_the_map_draws_given_estimated_added_ellipses_and_moved_segments(synthetic_run, with_truth):
    view = _view(synthetic_run, with_truth=with_truth)
    ax = plot_map(Figure().add_subplot(), view)
    ellipses = [c for c in ax.collections if isinstance(c, EllipseCollection)]
    points = {c.get_label(): len(c.get_offsets()) for c in ax.collections if isinstance(c, PathCollection)}
    assert len(ellipses) == 1 and len(ellipses[0].get_offsets()) == 19  # 16 mapped with a covariance, 3 added
    assert points["given map (30)"] == 30 and points["estimated, mapped (20)"] == 20 and points["added (3)"] == 3
    segments = [c for c in ax.collections if isinstance(c, LineCollection)]
    if with_truth:
        assert points["true map (30)"] == 30
        assert len(segments) == 1 and len(segments[0].get_segments()) == 5
        np.testing.assert_allclose([np.linalg.norm(s[1] - s[0]) for s in segments[0].get_segments()], 0.3)
    else:
        assert not segments and "true map (30)" not in points
    legend = [text.get_text() for text in ax.get_legend().get_texts()]
    assert "2-sigma ellipses (19)" in legend and "added (3)" in legend


def test_a_run_that_lists_its_added_landmarks_in_its_map_draws_them_once(synthetic_run):
    view = _view(synthetic_run, with_truth=False)
    run = dataclasses.replace(view.result, map_landmark_ids=np.r_[view.result.map_landmark_ids, 500, 501, 502],
                              map_landmark_xyz=np.r_[view.result.map_landmark_xyz, np.zeros((3, 3))])
    assert len(MapView(run, view.estimated).given()[0]) == 30


def _accept_any_true_map(monkeypatch) -> None:
    """A synthetic run is of no world, so no true map is its world's (--true-map refuses another
    world's: tests/test_cli_eval_plot.py); here the drawing alone is tested."""
    monkeypatch.setattr("camloc.smoother.check_run_matches", lambda *args, **kwargs: None)


def test_cli_plot_writes_fig_map_with_a_map_csv_only(tmp_path, synthetic_run, monkeypatch):
    from camloc import plotting

    monkeypatch.setattr(plotting, "figures_of", lambda result: {})  # the run's other figures: tests/test_cli_eval_plot.py
    _accept_any_true_map(monkeypatch)
    view = _view(synthetic_run, with_truth=True)
    run_dir = save_run(tmp_path / "run", view.result)
    world = simulate(SimulationConfig(poses=5, landmarks=30), seed=0)
    write_g2o(dataclasses.replace(world, landmark_ids=view.true_ids, landmark_xyz=view.true_xyz), tmp_path / "truth.g2o")
    invoke = CliRunner().invoke
    from camloc.cli.plot import _map_layout, _map_view

    assert _map_layout(run_dir, view.result, None, "png") == {}  # no map.csv, no fig-map
    run = load_run(run_dir)
    held = _map_view(run, tmp_path / "truth.g2o").estimated  # but with the truth: the given map, held
    paired = run.associations.landmark
    assert held.observations.tolist() == [int(np.count_nonzero(paired == i)) for i in held.ids.tolist()]
    assert np.array_equal(held.ids, view.result.map_landmark_ids) and not held.added.any() and not held.cov.any()
    write_map(run_dir, view.estimated)
    outcome = invoke(app, ["plot", str(run_dir), "--true-map", str(tmp_path / "truth.g2o"), "--dpi", "50"])
    assert outcome.exit_code == 0, outcome.output
    assert (run_dir / "fig-map.png").read_bytes().startswith(b"\x89PNG") and "fig-map.png" in outcome.stdout
    assert sorted(path.name for path in run_dir.glob("fig-*")) == ["fig-map.png"]

def test_cli_report_holds_the_map_panel_with_a_map_csv(tmp_path, synthetic_run, monkeypatch):
    from camloc import plotting
    from camloc.cli.plot import _map_view, _report_layout

    _accept_any_true_map(monkeypatch)

    view = _view(synthetic_run, with_truth=True)
    run_dir = save_run(tmp_path / "run", view.result)
    assert _report_layout(_map_view(load_run(run_dir), None))[0] == plotting.REPORT_SIZE  # no map.csv: no map row
    write_map(run_dir, view.estimated)
    world = simulate(SimulationConfig(poses=5, landmarks=30), seed=0)
    write_g2o(dataclasses.replace(world, landmark_ids=view.true_ids, landmark_xyz=view.true_xyz), tmp_path / "truth.g2o")
    run = load_run(run_dir)  # as the command reads it: its map.csv as its map
    assert np.array_equal(run.landmark_map.ids, view.estimated.ids)
    size, draw = _report_layout(_map_view(run, tmp_path / "truth.g2o"))
    fig = draw(Figure(figsize=size), view.result)
    assert size[1] > plotting.REPORT_SIZE[1] and len(fig.axes) == 10  # the nine panels and the map below them
    assert fig.axes[-1].get_title().endswith("(2-sigma ellipses)") and "true map" in fig.axes[-1].get_legend_handles_labels()[1][2]
    outcome = CliRunner().invoke(app, ["plot", str(run_dir), "--true-map", str(tmp_path / "truth.g2o"), "-o",
                                       str(tmp_path / "r.png"), "--dpi", "50"])
    assert outcome.exit_code == 0, outcome.output
    assert (tmp_path / "r.png").read_bytes().startswith(b"\x89PNG") and not (run_dir / "fig-map.png").exists()
