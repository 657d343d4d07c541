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
    assert refused.exit_code == 2 and "applies only to robot = planar" in refused.output
