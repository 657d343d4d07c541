"""``camloc eval`` and ``camloc plot`` end to end through the typer app (CliRunner)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from camloc import metrics
from camloc.bundled import bundled_dataset
from camloc.cli.app import app
from camloc.results import load_run, read_tum, save_run, write_tum

GRID_SMALL = bundled_dataset()
FIGURES = ("fig-topdown", "fig-3d", "fig-errors", "fig-consistency", "fig-associations")
MAGIC = {"png": b"\x89PNG", "pdf": b"%PDF", "svg": b"<?xml"}


def invoke(*args: str):
    return CliRunner().invoke(app, [str(arg) for arg in args])


def assert_bad_input(outcome, fragment: str) -> None:
    """Exit status 2, one error line naming the problem, no traceback."""
    assert outcome.exit_code == 2, outcome.output
    assert isinstance(outcome.exception, SystemExit)
    assert fragment in outcome.stderr
    assert "Traceback" not in outcome.output


@pytest.fixture
def run_dir(tmp_path, synthetic_run) -> Path:
    return save_run(tmp_path / "run", synthetic_run(seed=4, num_poses=30))


# --------------------------------------------------------------------------------------------
# eval


def test_eval_prints_tables_with_both_paths_and_the_verdict(run_dir):
    outcome = invoke("eval", run_dir)
    assert outcome.exit_code == 0, outcome.output
    report = metrics.evaluate(load_run(run_dir))
    for text in ("ATE rmse [m]", report["estimate_name"], "odometry", "precision", "NEES, 6 dof", "verdict:",
                 f"{report['estimate']['ate']['rmse']:.4f}", f"{report['odometry']['ate']['rmse']:.4f}",
                 f"{report['association']['precision']:.3f}", report["nees"]["verdict"],
                 f"verdict: {report['consistency']['verdict']}: "):
        assert text in outcome.stdout, text
    # the verdict line speaks for NIS too
    assert "NIS per dof" in outcome.stdout.split("verdict: ")[-1]


def test_eval_json_is_the_library_report(run_dir):
    outcome = invoke("eval", run_dir, "--json", "--align", "sim3", "--delta", "2")
    assert outcome.exit_code == 0, outcome.output
    printed = json.loads(outcome.stdout)
    expected = json.loads(json.dumps(metrics.evaluate(load_run(run_dir), align="sim3", delta=2)))
    assert printed == {**expected, "map": None}  # and the map's score, with --true-map
    assert printed["estimate"]["alignment"]["method"] == "sim3"
    assert printed["estimate"]["rpe"]["delta"] == 2
    assert printed["estimate"]["rpe"]["pairs"] == 14  # pairs (0,2), (2,4), ..., (26,28)


def test_eval_prints_the_alignment(run_dir):
    outcome = invoke("eval", run_dir, "--align", "se3")
    assert outcome.exit_code == 0, outcome.output
    assert "alignment onto the reference" in outcome.stdout and "se3" in outcome.stdout


def test_eval_without_truth_keeps_its_keys_null_and_notes_it(tmp_path, synthetic_run):
    run = save_run(tmp_path / "run", synthetic_run(with_truth=False))
    outcome = invoke("eval", run, "--json")
    assert outcome.exit_code == 0, outcome.output
    report = json.loads(outcome.stdout)
    assert report["estimate"] is None and report["odometry"] is None and report["nees"] is None
    assert "no ground truth" in report["notes"][0]
    assert "no ground truth" in invoke("eval", run).stdout


def test_eval_and_plot_score_the_trajectory_on_disk(run_dir):
    before = json.loads(invoke("eval", run_dir, "--json").stdout)
    stamps, xyz, quat = read_tum(run_dir / "estimate.tum")
    write_tum(run_dir / "estimate.tum", stamps, xyz + [10.0, 0.0, 0.0], quat)  # every x shifted by 10 m
    after = json.loads(invoke("eval", run_dir, "--json").stdout)
    assert before["estimate"]["ate"]["rmse"] < 0.2
    assert after["estimate"]["ate"]["rmse"] > 9.0
    assert after["odometry"] == before["odometry"]

    (run_dir / "estimate.tum").unlink()
    for command in ("eval", "plot"):
        assert_bad_input(invoke(command, run_dir), f"{run_dir / 'estimate.tum'}: no such file")


def test_eval_of_two_tum_files(run_dir):
    outcome = invoke("eval", "--est", run_dir / "estimate.tum", "--ref", run_dir / "groundtruth.tum", "--json")
    assert outcome.exit_code == 0, outcome.output
    report = json.loads(outcome.stdout)
    expected = metrics.evaluate(load_run(run_dir))["estimate"]
    assert report["counts"]["matched"] == 30
    assert report["estimate"]["ate"]["rmse"] == pytest.approx(expected["ate"]["rmse"], abs=1e-12)
    assert report["estimate"]["rpe"]["rotation"]["rmse_deg"] == pytest.approx(expected["rpe"]["rotation"]["rmse_deg"],
                                                                              abs=1e-9)
    assert "nees" not in report and "association" not in report
    tables = invoke("eval", "--est", run_dir / "estimate.tum", "--ref", run_dir / "groundtruth.tum", "--align", "sim3")
    assert tables.exit_code == 0 and "30 poses matched" in tables.stdout and "sim3" in tables.stdout
    # Long paths are printed whole on their own lines, never folded at the terminal width.
    assert str(run_dir / "estimate.tum") in tables.stdout and str(run_dir / "groundtruth.tum") in tables.stdout


def test_eval_bad_inputs_exit_2_with_one_line(tmp_path, run_dir):
    assert_bad_input(invoke("eval", tmp_path / "nothing"), "no such directory")
    assert_bad_input(invoke("eval", tmp_path), "missing states.npz")
    assert_bad_input(invoke("eval"), "expected RUN_DIR, or --est")
    assert_bad_input(invoke("eval", run_dir, "--est", run_dir / "estimate.tum"), "found both")
    assert_bad_input(invoke("eval", "--est", run_dir / "estimate.tum"), "together with --ref")
    assert_bad_input(invoke("eval", run_dir, "--delta", "0"), "--delta")
    assert_bad_input(invoke("eval", run_dir, "--delta", "30"), "RPE delta must be between 1 and")
    assert_bad_input(invoke("eval", run_dir, "--align", "affine"), "--align")

    bad = tmp_path / "bad.tum"
    bad.write_text("# t x y z qx qy qz qw\n1000 0 0 0 0 0 0 1\n1001 0 0 0 0 0 1\n")
    outcome = invoke("eval", "--est", bad, "--ref", run_dir / "groundtruth.tum")
    assert_bad_input(outcome, f"{bad}:3: expected 8 fields")
    assert len(outcome.stderr.strip().splitlines()) == 1

    far = tmp_path / "far.tum"
    far.write_text("5 0 0 0 0 0 0 1\n6 1 0 0 0 0 0 1\n")
    assert_bad_input(invoke("eval", "--est", far, "--ref", run_dir / "groundtruth.tum"), "no matching timestamps")


# --------------------------------------------------------------------------------------------
# plot


def test_plot_writes_each_figure_into_the_run_folder(run_dir):
    outcome = invoke("plot", run_dir)
    assert outcome.exit_code == 0, outcome.output
    for name in FIGURES:
        path = run_dir / f"{name}.png"
        assert path.stat().st_size > 10_000, name
        assert path.read_bytes()[:4] == MAGIC["png"]
        assert str(path) in outcome.stdout
    assert not [p for p in run_dir.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("suffix", ["pdf", "svg", "png"])
def test_plot_output_writes_one_report_figure(tmp_path, run_dir, suffix):
    target = tmp_path / f"report.{suffix}"
    outcome = invoke("plot", run_dir, "-o", target)
    assert outcome.exit_code == 0, outcome.output
    assert target.read_bytes()[: len(MAGIC[suffix])] == MAGIC[suffix]
    assert not list(run_dir.glob("fig-*"))


def test_plot_format_option(run_dir):
    outcome = invoke("plot", run_dir, "--format", "svg")
    assert outcome.exit_code == 0, outcome.output
    assert sorted(p.stem for p in run_dir.glob("fig-*.svg")) == sorted(FIGURES)


def test_plot_without_truth_still_draws(tmp_path, synthetic_run):
    run = save_run(tmp_path / "run", synthetic_run(with_truth=False))
    outcome = invoke("plot", run)
    assert outcome.exit_code == 0, outcome.output
    assert all((run / f"{name}.png").stat().st_size > 0 for name in FIGURES)


def test_plot_bad_inputs_exit_2(tmp_path, run_dir):
    assert_bad_input(invoke("plot", tmp_path / "nothing"), "no such directory")
    assert_bad_input(invoke("plot", run_dir, "-o", tmp_path / "report.jpg"), "expected a file name ending in .png")
    (tmp_path / "a-file").write_text("")
    assert_bad_input(invoke("plot", run_dir, "-o", tmp_path / "a-file" / "report.png"),
                     f"cannot create the folder {tmp_path / 'a-file'}")


# --------------------------------------------------------------------------------------------
# Corrupt run folders and TUM files: one error line naming the file, never a traceback


def _rewrite_line(path: Path, number: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[number - 1] = text
    path.write_text("\n".join(lines) + "\n")


def _rewrite_states(run_dir: Path, **changes) -> None:
    with np.load(run_dir / "states.npz") as npz:
        arrays = {name: npz[name] for name in npz.files}
    np.savez(run_dir / "states.npz", **{**arrays, **changes})


# name -> (how the run folder is damaged, the file and line the error must name, a fragment)
CORRUPT_FOLDERS = {
    "deep-summary": (lambda run: (run / "summary.json").write_text("[" * 100_000 + "]" * 100_000),
                     "summary.json", "expected JSON"),
    "huge-id": (lambda run: _rewrite_line(run / "associations.csv", 2, "1001,0,0.5,0.5,1,99999999999999999999999,100,1.0"),
                "associations.csv:2", "expected an integer for landmark"),
    "unknown-pose": (lambda run: _rewrite_line(run / "associations.csv", 2, "99999,0,0.5,0.5,1,100,100,1.0"),
                     "associations.csv:2", "inconsistent run folder"),
    "nan-u": (lambda run: _rewrite_line(run / "associations.csv", 2, "1001,0,nan,nan,1,100,100,1.0"),
              "associations.csv:2", "expected a finite number for u"),
    "nan-cov": (lambda run: _rewrite_states(run, estimate_cov=np.full((30, 6, 6), np.nan)),
                "states.npz", "estimate_cov: expected finite numbers"),
    "zero-quat": (lambda run: _rewrite_line(run / "groundtruth.tum", 3, "1001 0 0 0 0 0 0 0"),
                  "groundtruth.tum:3", "expected a unit quaternion"),
    "nan-estimate": (lambda run: _rewrite_line(run / "estimate.tum", 2, "1000 nan 0 0 0 0 0 1"),
                     "estimate.tum:2", "expected a finite number for x"),
    "truncated-estimate": (lambda run: _rewrite_line(run / "estimate.tum", 31, "# cut"),
                           "estimate.tum", "expected the run's 30 pose ids"),
    "deleted-odometry": (lambda run: (run / "odometry.tum").unlink(), "odometry.tum", "no such file"),
    "version": (lambda run: _rewrite_states(run, format_version=np.array("abc")),
                "states.npz", "expected format_version 1 or 2, found 'abc'"),
    "smoothed-huge-xyz": (lambda run: (run / "smoothed.tum").write_text(
        (run / "estimate.tum").read_text().replace("\n1000.0 ", "\n1000.0 1e308 1e308 0 0 0 0 1\n#", 1)),
        "smoothed.tum:2", "expected metres within +-1e+15 for x"),
}


@pytest.mark.parametrize("command", ["eval", "plot"])
@pytest.mark.parametrize("name", CORRUPT_FOLDERS)
def test_corrupt_run_folders_exit_2_naming_the_file_and_leave_no_figure(run_dir, command, name):
    damage, where, fragment = CORRUPT_FOLDERS[name]
    damage(run_dir)
    before = sorted(p.name for p in run_dir.iterdir())
    outcome = invoke(command, run_dir)
    assert_bad_input(outcome, f"{run_dir / where}")
    assert fragment in outcome.stderr
    assert len(outcome.stderr.strip().splitlines()) == 1
    assert sorted(p.name for p in run_dir.iterdir()) == before  # no figure, no temporary file


def test_plot_writes_every_figure_or_none(run_dir, monkeypatch):
    from camloc import plotting

    invoke("plot", run_dir)
    before = {p.name: p.read_bytes() for p in run_dir.iterdir()}

    def broken(fig, result):
        raise RuntimeError("a drawing bug")

    size, _ = plotting.FIGURES["consistency"]  # the fourth of five figures
    monkeypatch.setitem(plotting.FIGURES, "consistency", (size, broken))
    outcome = invoke("plot", run_dir, "--dpi", "60")
    assert isinstance(outcome.exception, RuntimeError)
    # the three figures drawn before the failure did not replace the old ones; nothing left over
    assert {p.name: p.read_bytes() for p in run_dir.iterdir()} == before


def test_plot_refuses_a_folder_where_a_figure_goes_and_replaces_no_figure(run_dir):
    invoke("plot", run_dir)
    (run_dir / "fig-errors.png").unlink()
    (run_dir / "fig-errors.png").mkdir()
    before = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()}
    outcome = invoke("plot", run_dir, "--dpi", "60")
    assert_bad_input(outcome, f"{run_dir / 'fig-errors.png'}: is a folder; expected the path of a file to write")
    assert {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()} == before


def test_eval_of_tum_files_with_huge_quaternions_a_bom_or_huge_coordinates(tmp_path, run_dir):
    reference = run_dir / "groundtruth.tum"
    lines = reference.read_text().splitlines()
    fields = lines[1].split()
    # qw of 1e200: the norm overflowed, normalizing gave a zero quaternion (a scipy traceback)
    scaled = tmp_path / "scaled.tum"
    scaled.write_text("\n".join([" ".join(fields[:4] + [repr(float(q) * 1e200) for q in fields[4:]])] + lines[2:]) + "\n")
    bom = tmp_path / "bom.tum"
    bom.write_bytes(b"\xef\xbb\xbf" + reference.read_bytes())
    for estimate in (scaled, bom):
        outcome = invoke("eval", "--est", estimate, "--ref", reference, "--json")
        assert outcome.exit_code == 0, outcome.output
        report = json.loads(outcome.stdout)
        assert report["counts"]["matched"] == 30 and report["estimate"]["ate"]["rmse"] == pytest.approx(0.0, abs=1e-12)
        assert report["estimate"]["rotation"]["rmse_deg"] == pytest.approx(0.0, abs=1e-5)

    huge = tmp_path / "huge.tum"
    huge.write_text("\n".join([" ".join(fields[:1] + ["1e200"] * 3 + fields[4:])] + lines[2:]) + "\n")
    outcome = invoke("eval", "--est", huge, "--ref", reference)
    assert_bad_input(outcome, f"{huge}:1: expected metres within +-1e+15 for x, found 1e200")
    assert "RuntimeWarning" not in outcome.output


# --------------------------------------------------------------------------------------------
# The real localizer, end to end


def test_localizer_run_evaluates_and_plots(tmp_path):
    import camloc

    dataset = camloc.load(GRID_SMALL)
    result = camloc.localize(dataset)
    run = save_run(tmp_path / "grid-small", result)

    report = json.loads(invoke("eval", run, "--json").stdout)
    # Landmarks against odometry alone: the filter must beat dead reckoning by a wide margin.
    assert report["estimate"]["ate"]["rmse"] < 0.5 * report["odometry"]["ate"]["rmse"]
    assert report["association"]["observations"] == dataset.num_observations
    assert report["association"]["precision"] > 0.9
    assert report["nees"]["poses"] == dataset.num_poses - 1
    assert report["nis"]["updates"] == len(result.nis) > 0

    outcome = invoke("plot", run)
    assert outcome.exit_code == 0, outcome.output
    for name in FIGURES:
        assert (run / f"{name}.png").stat().st_size > 10_000, name
    assert invoke("plot", run, "-o", tmp_path / "report.pdf").exit_code == 0
    assert (tmp_path / "report.pdf").read_bytes()[:4] == MAGIC["pdf"]
    np.testing.assert_array_equal(load_run(run).estimate_xyz, result.estimate_xyz)


def test_eval_and_plot_refuse_the_true_map_of_another_world(tmp_path):
    """--true-map of another world (another seed; the same seed's pixel-only world) was scored
    and drawn without a word, its ids meaning other landmarks; the world's own true map is used."""
    def simulate(name, *options):
        assert invoke("simulate", "-o", tmp_path / name, "--poses", "20", "-q", *options).exit_code == 0

    simulate("w.g2o", "--withhold-map", "0.3")
    simulate("other.g2o", "--seed", "1")
    simulate("pixel.g2o", "--measurement", "pixel")
    assert invoke("run", tmp_path / "w.g2o", "-o", tmp_path / "run", "-q").exit_code == 0
    for other, difference in (("other.g2o", "odometry reaches"), ("pixel.g2o", "observation 1")):
        for command in (["eval", tmp_path / "run"], ["plot", tmp_path / "run"]):
            outcome = invoke(*command, "--true-map", tmp_path / other, "-q")
            assert_bad_input(outcome, f"do not match: {difference}")
            assert "expected the true map of the world the run was made from" in outcome.stderr
    assert not list((tmp_path / "run").glob("fig-*"))
    scored = invoke("eval", tmp_path / "run", "--true-map", tmp_path / "w.true-map.g2o", "--json")
    assert scored.exit_code == 0, scored.output
    assert json.loads(scored.stdout)["map"]["mapped"] is not None
