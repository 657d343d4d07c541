"""A planar robot end to end through the typer app: ``simulate --robot planar`` -> ``run`` ->
``eval`` -> ``plot`` -> ``smooth``, and planar input the commands refuse in one line."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from camloc.cli.app import app


def invoke(*args):
    return CliRunner().invoke(app, [str(arg) for arg in args])


@pytest.mark.parametrize("sensors", ["points", "markers", "points,markers,cameras"])
def test_simulate_run_eval_plot_smooth(tmp_path, sensors):
    world, run_dir = tmp_path / "planar.g2o", tmp_path / "run"
    made = invoke("simulate", "--robot", "planar", "--sensors", sensors, "--poses", 60, "--clutter-fraction", 0.1,
                  "-o", world, "--json")
    assert made.exit_code == 0, made.output
    assert json.loads(made.output)["counts"]["poses"] == 60
    assert "VERTEX_SE2 " in world.read_text()

    ran = invoke("run", world, "-o", run_dir, "--json")
    assert ran.exit_code == 0, ran.output
    summary = json.loads(ran.output)
    assert summary["config"]["filter"] == "se2" and summary["timing"]["engine"] == "numpy"

    evaluated = invoke("eval", run_dir, "--json")
    assert evaluated.exit_code == 0, evaluated.output
    report = json.loads(evaluated.output)
    assert report["nees"]["dof"] == 3
    assert report["estimate"]["ate"]["rmse"] < report["odometry"]["ate"]["rmse"]
    assert report["association"]["precision"] >= 0.98
    table = invoke("eval", run_dir)
    assert "heading rmse [deg]" in table.output and "NEES, 3 dof" in table.output

    plotted = invoke("plot", run_dir)
    assert plotted.exit_code == 0, plotted.output
    assert (run_dir / "fig-topdown.png").is_file() and (run_dir / "fig-consistency.png").is_file()
    assert not (run_dir / "fig-3d.png").exists()  # a planar run has no z to draw

    smoothed = invoke("smooth", run_dir, "--json")
    assert smoothed.exit_code == 0, smoothed.output
    smooth_report = json.loads(smoothed.output)
    assert smooth_report["converged"]
    assert smooth_report["smoothed"]["ate"]["rmse"] <= 1.05 * smooth_report["estimate"]["ate"]["rmse"]
    assert (run_dir / "map.csv").is_file()
    for mode in ("prior", "none"):  # the landmarks estimated with the poses (tests/test_smoother_se2.py)
        with_map = invoke("smooth", run_dir, "--map", mode, "--json")
        assert with_map.exit_code == 0, with_map.output
        assert json.loads(with_map.output)["landmarks"]["estimated"] > 0

    info = invoke("info", world, "--json")
    assert info.exit_code == 0, info.output
    assert json.loads(info.output)["robot"] == "planar"


def test_planar_options_that_do_not_apply_are_refused(tmp_path):
    result = invoke("simulate", "--robot", "planar", "--trajectory", "aerial", "-o", tmp_path / "x.g2o")
    assert result.exit_code == 2
    assert "does not apply to --robot planar" in result.output
    result = invoke("simulate", "--robot", "planar", "--sensors", "lidar", "-o", tmp_path / "x.g2o")
    assert result.exit_code == 2 and "points, markers, cameras" in result.output
    # an empty list was read as the default (points), and a 3-D robot ignored --sensors silently
    result = invoke("simulate", "--robot", "planar", "--sensors", "", "-o", tmp_path / "x.g2o")
    assert result.exit_code == 2 and "points, markers, cameras, found ''" in result.output
    result = invoke("simulate", "--sensors", "markers", "-o", tmp_path / "x.g2o")
    assert result.exit_code == 2 and "--sensors: applies only to a planar robot" in result.output
    assert not (tmp_path / "x.g2o").exists()


def test_bad_planar_file_is_one_line(tmp_path):
    path = tmp_path / "bad.g2o"
    path.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 100 0 0 100 0\n", encoding="utf-8")
    result = invoke("run", path, "-o", tmp_path / "run")
    assert result.exit_code == 2
    assert f"{path}:3: EDGE_SE2 expects 11 fields" in result.output
    assert "Traceback" not in result.output


def test_euler_on_planar_observations_is_refused(tmp_path):
    world = tmp_path / "planar.g2o"
    assert invoke("simulate", "--robot", "planar", "--poses", 20, "-o", world).exit_code == 0
    result = invoke("run", world, "--filter", "euler", "-o", tmp_path / "run")
    assert result.exit_code == 2
    assert "use --filter se2" in result.output


def test_sweep_of_planar_worlds(tmp_path):
    study = tmp_path / "study.toml"
    study.write_text('seeds = 2\n[simulate]\nrobot = "planar"\nsensors = "markers"\nposes = 40\n'
                     '[run]\nassociation = ["beam", "oracle"]\n', encoding="utf-8")
    result = invoke("sweep", study, "-o", tmp_path / "sweep", "--json")
    assert result.exit_code == 0, result.output
    rows = (tmp_path / "sweep" / "runs.csv").read_text().splitlines()
    assert len(rows) == 1 + 4 and all(",ok," in row for row in rows[1:])
    bad = tmp_path / "bad.toml"
    bad.write_text('seeds = 1\n[simulate]\nsensors = "points"\n', encoding="utf-8")
    refused = invoke("sweep", bad, "-o", tmp_path / "sweep2")
    assert refused.exit_code == 2 and "applies only to a planar robot" in refused.output


@pytest.fixture(scope="module")
def planar_maps(tmp_path_factory):
    """Planar worlds (points, markers and a depth camera) whose maps lack half their landmarks or
    have a quarter moved 0.3 m, with their true maps, and a mapping run of each."""
    folder = tmp_path_factory.mktemp("planar-maps")
    worlds = {}
    for name, edit, mode in (("half", ("--withhold-map", 0.5), "exact"),
                             ("moved", ("--move-map", 0.25, "--move-distance", 0.3), "prior")):
        world = folder / f"{name}.g2o"
        made = invoke("simulate", "--robot", "planar", "--sensors", "points,markers,cameras", "--poses", 120,
                      "--seed", 1, *edit, "-o", world, "-q")
        assert made.exit_code == 0, made.output
        ran = invoke("run", world, "-o", folder / name, "--map", mode, "--map-sigma", 0.1, "-q")
        assert ran.exit_code == 0, ran.output
        worlds[name] = (world, folder / f"{name}.true-map.g2o", folder / name)
    return worlds


def _smooth_and_score(run_dir, true_map, *options):
    smoothed = invoke("smooth", run_dir, *options, "--json")
    assert smoothed.exit_code == 0, smoothed.output
    scored = invoke("eval", run_dir, "--true-map", true_map, "--json")
    assert scored.exit_code == 0, scored.output
    return json.loads(smoothed.output), json.loads(scored.output)["map"]


def test_smooth_estimates_the_landmarks_a_planar_run_added(planar_maps):
    _, true_map, run_dir = planar_maps["half"]
    report, scores = _smooth_and_score(run_dir, true_map, "--map", "exact")
    assert report["converged"] and report["landmarks"]["added"] > 30
    assert report["smoothed"]["ate"]["rmse"] < report["estimate"]["ate"]["rmse"]
    assert scores["added"]["count"] > 30 and scores["added"]["rmse"] < 0.1
    assert scores["mapped"]["nees"] is None  # held exact: zero covariances


def _observed_moved_error(world) -> float:
    """The median distance from the truth of the moved landmarks that map.csv says were observed."""
    import numpy as np

    from camloc.g2o import read_g2o
    from camloc.results import read_map

    path, true_map, run_dir = world
    given, truth, table = read_g2o(path), read_g2o(true_map), read_map(run_dir / "map.csv")
    true_xyz = dict(zip(truth.landmark_ids.tolist(), truth.landmark_xyz))
    moved = {i for i, xyz in zip(given.landmark_ids.tolist(), given.landmark_xyz) if np.linalg.norm(xyz - true_xyz[i]) > 1e-6}
    errors = [np.linalg.norm(xyz - true_xyz[i]) for i, xyz, seen in zip(table.ids.tolist(), table.xyz, table.observations)
              if i in moved and seen > 0]
    assert len(errors) > 10
    return float(np.median(errors))


def test_smooth_corrects_a_moved_planar_map_under_a_prior(planar_maps):
    _, true_map, run_dir = planar_maps["moved"]
    report, prior = _smooth_and_score(run_dir, true_map, "--map", "prior", "--map-sigma", 0.1)
    assert report["map"] == "prior" and report["map_sigma"] == 0.1 and report["landmarks"]["estimated"] > 50
    assert prior["moved"]["count"] > 10 and prior["moved"]["given_rmse"] == pytest.approx(0.3)
    assert _observed_moved_error(planar_maps["moved"]) < 0.1  # the unobserved ones stay where the map has them
    _, exact = _smooth_and_score(run_dir, true_map, "--map", "exact")
    assert exact["moved"]["rmse"] == pytest.approx(0.3)  # held where the map has them
    none, _ = _smooth_and_score(run_dir, true_map, "--map", "none")
    assert none["converged"] and none["landmarks"]["estimated"] >= report["landmarks"]["estimated"]


def test_smooth_of_a_planar_run_refuses_bad_input_in_one_line(planar_maps):
    world, _, run_dir = planar_maps["moved"]
    other, _, _ = planar_maps["half"]
    for args, fragment in ((("--map", "prior", "--map-sigma", 0), "map_sigma must be a finite number of metres > 0"),
                           (("--map", "floor"), "expected one of exact, prior, none"),
                           (("--map", "prior", "--dataset", other), "do not match")):
        outcome = invoke("smooth", run_dir, *args)
        assert outcome.exit_code == 2, outcome.output
        assert fragment in outcome.output and "Traceback" not in outcome.output
