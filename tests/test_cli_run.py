"""``camloc run`` end to end through the typer app: outputs, options, config files, bad input."""

import csv
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from camloc.cli.app import app
from camloc.g2o import read_g2o, write_g2o
from camloc.simulate import SimulationConfig, simulate


def invoke(*args):
    return CliRunner().invoke(app, [str(arg) for arg in args])


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "small.g2o"
    write_g2o(simulate(SimulationConfig(trajectory="grid", poses=50, clutter_fraction=0.1), seed=8), path)
    return path


def test_run_writes_the_run_folder_and_a_table(tmp_path, small_dataset):
    out = tmp_path / "run"
    result = invoke("run", small_dataset, "-o", out)
    assert result.exit_code == 0, result.output
    for name in ("estimate.tum", "odometry.tum", "groundtruth.tum", "associations.csv", "states.npz", "summary.json"):
        assert (out / name).is_file(), name
    assert "position RMSE [m]" in result.output and "poses/s" in result.output
    dataset = read_g2o(small_dataset)
    with open(out / "associations.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == dataset.num_observations
    assert list(rows[0]) == ["pose", "camera", "u", "v", "depth", "landmark", "true_landmark", "mahalanobis"]
    assert all((row["landmark"] == "") == (row["mahalanobis"] == "") for row in rows)
    estimate = np.loadtxt(out / "estimate.tum")
    assert estimate.shape == (50, 8)
    np.testing.assert_array_equal(estimate[:, 0], dataset.pose_ids)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["config"]["association"] == "beam"
    assert summary["estimate"]["ate"]["rmse"] < 0.2


def test_run_json_and_quiet(tmp_path, small_dataset):
    result = invoke("run", small_dataset, "-o", tmp_path / "a", "--json", "--association", "oracle")
    assert result.exit_code == 0
    summary = json.loads(result.stdout)
    assert summary["config"]["association"] == "oracle"
    assert summary["counts"]["poses"] == 50
    quiet = invoke("run", small_dataset, "-o", tmp_path / "b", "--quiet")
    assert quiet.exit_code == 0 and quiet.output == ""


def test_config_file_is_applied_and_the_command_line_wins(tmp_path, small_dataset):
    config = tmp_path / "options.toml"
    config.write_text('[localizer]\nassociation = "best-friends"\niterations = 2\nmargin = 2.5\n')
    result = invoke("run", small_dataset, "-o", tmp_path / "r", "--config", config, "--iterations", "4", "--json")
    assert result.exit_code == 0, result.output
    effective = json.loads(result.stdout)["config"]
    assert effective["association"] == "best-friends"
    assert effective["margin"] == 2.5
    assert effective["iterations"] == 4


@pytest.mark.parametrize("args, message", [
    (["--iterations", "0"], "iterations"),
    (["--gate", "1.5"], "gate_probability"),
    (["--association", "psychic"], "association"),
])
def test_bad_options_exit_2_without_a_folder(tmp_path, small_dataset, args, message):
    out = tmp_path / "never"
    result = invoke("run", small_dataset, "-o", out, *args)
    assert result.exit_code == 2
    assert message in result.output
    assert not out.exists()


def test_bad_config_file_is_one_line(tmp_path, small_dataset):
    config = tmp_path / "bad.toml"
    config.write_text("iterations = 3\nwarp_speed = 9\n")
    result = invoke("run", small_dataset, "-o", tmp_path / "r", "--config", config)
    assert result.exit_code == 2
    assert "warp_speed" in result.output and "Traceback" not in result.output


@pytest.mark.parametrize("text, words", [
    ("localizer = 3\n", ["localizer must be a table", "int 3"]),
    ("localizer = [1, 2]\n", ["localizer must be a table", "list"]),
    ("iterations = 2\n[localizer]\ngate_probability = 0.9\n", ["both at top level (iterations) and in [localizer]"]),
    ('iterations = "three"\n', ["option iterations must be of type int", "'three'"]),
])
def test_a_config_file_of_the_wrong_shape_is_named_in_one_line(tmp_path, small_dataset, text, words):
    config = tmp_path / "options[1].toml"  # brackets, which the terminal's markup must not eat
    config.write_text(text)
    out = tmp_path / "never"
    result = invoke("run", small_dataset, "-o", out, "--config", config)
    assert result.exit_code == 2
    assert f"{config}: " in result.output and "Traceback" not in result.output
    for word in words:
        assert word in result.output
    assert not out.exists()


def test_a_file_whose_information_the_filter_cannot_use_is_one_line_naming_a_pose(tmp_path):
    # information 1e300 on one observation: a covariance of 1e-300 the reader represents, and
    # the filter's products underflow; the beam once raised a bare ValueError here
    source = tmp_path / "source.g2o"
    write_g2o(simulate(SimulationConfig(poses=10), seed=0), source)
    lines = source.read_text().splitlines()
    index = next(i for i, line in enumerate(lines) if line.startswith("EDGE_PROJECT_DEPTH"))
    fields = lines[index].split()
    lines[index] = " ".join(fields[:7] + ["1e300", "0", "0", "1e300", "0", "1e300"])
    bad = tmp_path / "bad.g2o"
    bad.write_text("\n".join(lines) + "\n")
    result = invoke("run", bad, "-o", tmp_path / "never")
    assert result.exit_code == 2
    assert "error: pose " in result.output and "Traceback" not in result.output
    assert not (tmp_path / "never").exists()


def test_malformed_dataset_is_one_line_with_path_and_line(tmp_path, small_dataset):
    lines = small_dataset.read_text().splitlines()
    index = next(i for i, line in enumerate(lines) if line.startswith("EDGE_SE3:QUAT"))
    lines[index] = lines[index].rsplit(" ", 1)[0]
    bad = tmp_path / "bad.g2o"
    bad.write_text("\n".join(lines) + "\n")
    out = tmp_path / "never"
    result = invoke("run", bad, "-o", out)
    assert result.exit_code == 2
    assert f"bad.g2o:{index + 1}:" in result.output
    assert "Traceback" not in result.output
    assert not out.exists()


def test_missing_dataset(tmp_path):
    result = invoke("run", tmp_path / "nope.g2o", "-o", tmp_path / "r")
    assert result.exit_code == 2 and "nope.g2o" in result.output


def test_default_dataset_is_the_bundled_one(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = invoke("run", "--quiet")
    assert result.exit_code == 0, result.output
    assert (tmp_path / "runs" / "grid-small" / "estimate.tum").is_file()


def test_version_and_help():
    assert invoke("--version").output.startswith("camloc ")
    help_text = invoke("run", "--help").output
    for option in ("--association", "--iterations", "--gate", "--beam-width", "--config", "--json"):
        assert option in help_text
    assert "Default" in help_text
