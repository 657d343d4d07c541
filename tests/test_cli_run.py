"""``camloc run`` end to end through the typer app: outputs, options, config files, bad input."""

import csv
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from camloc.cli.app import app
from camloc.g2o import read_g2o, write_g2o
from camloc.localizer import LocalizerConfig
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


@pytest.mark.parametrize("table", ["", "[localizer]\n"], ids=["top-level", "localizer-table"])
def test_config_file_is_applied_and_the_command_line_wins(tmp_path, small_dataset, table):
    """defaults < the file < the command line, with the command line's names in the file."""
    config = tmp_path / "options.toml"
    group = "[localizer.best-friends]" if table else "[best-friends]"
    config.write_text(f'{table}association = "best-friends"\niterations = 2\ngate = 0.95\n{group}\nmargin = 2.5\n')
    result = invoke("run", small_dataset, "-o", tmp_path / "r", "--config", config, "--iterations", "4", "--json")
    assert result.exit_code == 0, result.output
    effective = json.loads(result.stdout)["config"]
    assert (effective["association"], effective["gate"], effective["best_friends"]["margin"]) == ("best-friends", 0.95, 2.5)
    assert effective["iterations"] == 4
    assert effective["best_friends"]["cost"] == LocalizerConfig().best_friends.cost == "nll"


@pytest.mark.parametrize("args, message", [
    (["--iterations", "0"], "error: --iterations must be an integer in 1..50, got 0"),
    (["--gate", "1.5"], "error: --gate must be a probability in (0, 1), got 1.5"),
    (["--association", "psychic"], "association"),
    (["--beam-width", "0"], "error: --beam-width must be an integer in 1..1024, got 0"),
    (["--max-depth", "0.5", "--min-depth", "1"], "error: --max-depth must be above the minimum depth (1 m)"),
    # an option of a method that is not selected
    (["--jcbb-max-nodes", "10"], "error: --jcbb-max-nodes applies only with association jcbb; the selected association is beam"),
    (["--association", "jcbb", "--batch"], "error: --batch applies only with association best-friends; the selected association is jcbb"),
    (["--association", "oracle", "--beam-width", "4"], "error: --beam-width applies only with association beam; the selected association is oracle"),
])
def test_bad_options_exit_2_in_one_line_without_a_folder(tmp_path, small_dataset, args, message):
    out = tmp_path / "never"
    result = invoke("run", small_dataset, "-o", out, *args)
    assert result.exit_code == 2
    assert message in result.output and len(result.output.strip().splitlines()) == 1, result.output
    assert not out.exists()


@pytest.mark.parametrize("text, args, message", [
    ("[jcbb]\nmax-nodes = 10\n", [], "[jcbb] max-nodes applies only with association jcbb; the selected association is beam"),
    ('association = "jcbb"\n[jcbb]\nmax-nodes = 10\n', ["--association", "beam"], "[jcbb] max-nodes applies only with association jcbb"),
    ("iterations = 3\nwarp_speed = 9\n", [], "unknown option(s) warp_speed; expected some of filter, association, iterations, gate"),
    ("[beam]\nwidht = 8\n", [], "unknown option(s) [beam] widht; expected some of"),
    # camloc 0.1's flat names: refused, each with its new place
    ("beam_width = 8\ngate_probability = 0.9\nrecheck = false\n", [],
     "unknown option(s) beam_width (now [beam] width), gate_probability (now gate), recheck (now [recheck] enabled)"),
    ("[view]\nmax-angle = 95\n", [], "[view] max-angle must be in (0, 90) deg, got 95"),
])
def test_a_bad_config_file_is_one_line_naming_the_file_and_the_option(tmp_path, small_dataset, text, args, message):
    config = tmp_path / "bad.toml"
    config.write_text(text)
    result = invoke("run", small_dataset, "-o", tmp_path / "never", "--config", config, *args)
    assert result.exit_code == 2
    assert f"error: {config}: {message}" in result.output and len(result.output.strip().splitlines()) == 1, result.output
    assert "Traceback" not in result.output and not (tmp_path / "never").exists()


@pytest.mark.parametrize("text, words", [
    ("localizer = 3\n", ["localizer must be a table", "int 3"]),
    ("localizer = [1, 2]\n", ["localizer must be a table", "list"]),
    ("iterations = 2\n[localizer]\ngate = 0.9\n", ["both at top level (iterations) and in [localizer]"]),
    ('iterations = "three"\n', ["iterations must be an integer, got 'three'"]),
    ("beam = 8\n", ["unknown option(s) beam;"]),
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


def _toml(config: dict) -> str:
    """A recorded configuration as a config file: top-level values, then a table per group; None
    (from the data) has no TOML spelling and is left out, which is what it means."""
    def line(key, value):
        return f"{key} = {json.dumps(value)}\n" if value is not None else ""

    top = "".join(line(k, v) for k, v in config.items() if not isinstance(v, dict))
    return top + "".join(f"[{k}]\n" + "".join(line(kk, vv) for kk, vv in v.items()) for k, v in config.items() if isinstance(v, dict))


@pytest.mark.parametrize("args", [
    ["--association", "best-friends", "--batch", "--margin", "2.0", "--gate", "0.95", "--max-angle", "40", "--no-recheck"],
    ["--beam-width", "4", "--recheck-steal-margin", "3", "--null-cost", "15", "--initial-sigma-deg", "1.5"],
], ids=["best-friends", "beam"])
def test_a_runs_recorded_config_read_back_as_a_config_file_gives_the_same_run(tmp_path, small_dataset, args):
    first = invoke("run", small_dataset, "-o", tmp_path / "first", "--json", *args)
    assert first.exit_code == 0, first.output
    recorded = json.loads((tmp_path / "first" / "summary.json").read_text())["config"]
    config = tmp_path / "recorded.toml"
    config.write_text(_toml(recorded))  # every group, those of the methods not selected at their defaults
    again = invoke("run", small_dataset, "-o", tmp_path / "again", "--json", "--config", config)
    assert again.exit_code == 0, again.output
    assert json.loads(again.stdout)["config"] == recorded
    assert json.loads(again.stdout)["estimate"] == json.loads(first.stdout)["estimate"]


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
    assert f"error: {bad}: pose " in result.output and "Traceback" not in result.output  # the file, then its pose
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
    # a panel per group of options, naming its config file's table (wide: a panel's title is one line)
    help_text = CliRunner().invoke(app, ["run", "--help"], env={"COLUMNS": "300"}).output
    for panel in ("Beam: --association beam; [beam]", "JCBB: --association jcbb; [jcbb]", "[best-friends] in a config file",
                  "Re-check: every association but oracle; [recheck]", "[view] in a config file"):
        assert panel in help_text


def test_a_small_run_never_imports_scipy(tmp_path):
    # scipy's import (0.2 s, of which its array-API layer most) was a fifth of `camloc run` on a
    # small file: the run's chi-square quantiles, quaternions, Cholesky and ball queries do without
    import subprocess
    import sys

    code = ("import sys\nfrom camloc.cli.app import main\n"
            "sys.argv = ['camloc', 'run', '-o', 'out', '--quiet']\n"
            "try:\n    main()\nexcept SystemExit as done:\n    assert not done.code, done.code\n"
            "print(sorted(name for name in sys.modules if name.split('.')[0] == 'scipy')[:3])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
    assert (tmp_path / "out" / "summary.json").is_file()


def test_a_bundled_dataset_is_reached_by_its_name_from_anywhere(tmp_path, monkeypatch):
    # after 'pip install .', camloc/data/ is inside site-packages, not beside the user
    from camloc.bundled import BUNDLED_DATASETS, bundled_dataset

    monkeypatch.chdir(tmp_path)
    outcome = invoke("run", "pixel-2cam", "--json")
    assert outcome.exit_code == 0, outcome.output
    assert json.loads(outcome.stdout)["dataset"] == str(bundled_dataset("pixel-2cam"))
    assert (tmp_path / "runs" / "pixel-2cam" / "summary.json").is_file()
    for name in BUNDLED_DATASETS:
        assert invoke("info", name, "--quiet").exit_code == 0, name
    (tmp_path / "grid-small.g2o").write_text("VERTEX_TRACKXYZ 0 1 2\n")  # a file of that name wins
    assert invoke("info", "grid-small.g2o", "--quiet").exit_code == 2
