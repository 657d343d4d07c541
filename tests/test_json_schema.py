"""Every command's ``--json`` against ``docs/json.md``: each documented key is there (``null`` only
where the table allows it) and nothing undocumented is, with and without ground truth."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from camloc.cli.app import app
from camloc.g2o import write_g2o
from camloc.simulate import SimulationConfig, simulate

DOC = Path(__file__).resolve().parents[1] / "docs" / "json.md"
TRAJECTORY_BLOCK = "Trajectory block"


def _documented() -> dict[str, dict[str, str]]:
    """Section title -> {dotted key: type}, trajectory blocks expanded into their keys."""
    sections: dict[str, dict[str, str]] = {}
    current = None
    for line in DOC.read_text(encoding="utf-8").splitlines():
        if line.startswith("## "):
            current = sections.setdefault(line[3:].strip(), {})
        row = re.match(r"^\| `([\w.]+)` \| ([^|]+) \|", line)
        if row and current is not None:
            current[row[1]] = row[2].strip()
    block = sections.pop(TRAJECTORY_BLOCK)
    for keys in sections.values():
        for key, kind in list(keys.items()):
            if kind.startswith("trajectory block"):
                keys.update({f"{key}.{child}": child_kind for child, child_kind in block.items()})
    return sections


DOCUMENTED = _documented()


def check_against_doc(output: dict, section: str) -> None:
    keys = DOCUMENTED[section]
    for key, kind in keys.items():
        *parents, name = key.split(".")
        node = output
        for parent in parents:
            node = node[parent]
            if node is None:  # a null block: its keys are not there to check
                break
        else:
            assert name in node, f"{section}: {key} is documented but missing"
            assert node[name] is not None or "null" in kind, f"{section}: {key} is null, documented as {kind}"
    # Nothing undocumented: every object whose keys the table lists has exactly those keys.
    for parent in {""} | {key.rsplit(".", 1)[0] for key in keys if "." in key}:
        node = output
        for part in filter(None, parent.split(".")):
            node = None if node is None else node[part]
        if node is None:
            continue
        prefix = f"{parent}." if parent else ""
        listed = {key[len(prefix):] for key in keys if key.startswith(prefix) and "." not in key[len(prefix):]}
        assert set(node) == listed, f"{section}: {parent or 'top level'} has {sorted(set(node) ^ listed)} differing"


def invoke_json(*args) -> dict:
    outcome = CliRunner().invoke(app, [str(arg) for arg in args] + ["--json"])
    assert outcome.exit_code == 0, outcome.output
    return json.loads(outcome.stdout)


@pytest.fixture(scope="module")
def worlds(tmp_path_factory):
    """A small simulated file with ground truth, and the same file with only the start pose's vertex."""
    folder = tmp_path_factory.mktemp("json")
    with_truth = folder / "truth.g2o"
    write_g2o(simulate(SimulationConfig(poses=30, clutter_fraction=0.1), seed=5), with_truth)
    lines = with_truth.read_text().splitlines()
    vertices = [i for i, line in enumerate(lines) if line.startswith("VERTEX_SE3:QUAT")]
    without_truth = folder / "bare.g2o"
    without_truth.write_text("\n".join(line for i, line in enumerate(lines) if i not in vertices[1:]) + "\n")
    return folder, with_truth, without_truth


def test_the_doc_lists_every_command_that_prints_json():
    assert set(DOCUMENTED) == {"camloc run", "camloc eval", "camloc eval --est --ref", "camloc smooth",
                               "camloc info", "camloc simulate", "camloc sweep"}


def test_sweep_prints_the_documented_keys(worlds):
    folder, with_truth, _ = worlds
    spec = folder / "sweep.toml"
    spec.write_text(f'datasets = ["{with_truth.name}"]\n[run]\nassociation = ["oracle", "beam"]\n')
    outcome = invoke_json("sweep", spec, "-o", folder / "sweep", "--workers", "1")
    check_against_doc(outcome, "camloc sweep")
    assert outcome["cells"] == 2 and outcome["failed"] == 0 and outcome["first_error"] == ""
    from camloc.sweep import SUMMARY_COLUMNS

    documented = next(line for line in DOC.read_text(encoding="utf-8").splitlines() if line.startswith("| `summary` | array"))
    assert all(f"`{column}`" in documented for column in SUMMARY_COLUMNS)
    assert set(SUMMARY_COLUMNS) <= set(outcome["summary"][0])


@pytest.mark.parametrize("truth", [True, False], ids=["ground-truth", "no-ground-truth"])
def test_run_eval_smooth_and_info_print_the_documented_keys(worlds, truth):
    folder, with_truth, without_truth = worlds
    dataset = with_truth if truth else without_truth
    run_dir = folder / f"run-{truth}"

    run = invoke_json("run", dataset, "-o", run_dir)
    check_against_doc(run, "camloc run")
    assert json.loads((run_dir / "summary.json").read_text()) == run
    assert (run["estimate"] is None) != truth

    evaluation = invoke_json("eval", run_dir)
    check_against_doc(evaluation, "camloc eval")
    smoothing = invoke_json("smooth", run_dir)
    check_against_doc(smoothing, "camloc smooth")
    check_against_doc(invoke_json("eval", run_dir), "camloc eval")  # now with the smoothed path
    if truth:  # and the map.csv the smoother wrote, scored against the file's own map
        check_against_doc(invoke_json("eval", run_dir, "--true-map", dataset), "camloc eval")
    check_against_doc(invoke_json("info", dataset), "camloc info")

    # The same quantity under the same key, whichever command prints it.
    assert run["dataset"] == evaluation["dataset"] == smoothing["dataset"] == str(dataset)
    assert run["counts"]["poses"] == evaluation["counts"]["poses"] == smoothing["counts"]["poses"] == 30
    assert run["association"] == evaluation["association"]
    if truth:
        assert run["estimate"]["ate"]["rmse"] == pytest.approx(evaluation["estimate"]["ate"]["rmse"], rel=1e-12)
        assert smoothing["estimate"]["ate"]["rmse"] == pytest.approx(evaluation["estimate"]["ate"]["rmse"], rel=1e-12)


def test_eval_of_two_files_and_simulate_print_the_documented_keys(worlds):
    folder, with_truth, _ = worlds
    run_dir = folder / "pair"
    invoke_json("run", with_truth, "-o", run_dir)
    comparison = invoke_json("eval", "--est", run_dir / "estimate.tum", "--ref", run_dir / "groundtruth.tum")
    check_against_doc(comparison, "camloc eval --est --ref")
    simulated = invoke_json("simulate", "-o", folder / "sim.g2o", "--poses", "12")
    check_against_doc(simulated, "camloc simulate")
    assert simulated["dataset"] == str(folder / "sim.g2o") and simulated["true_map"] is None
    edited = invoke_json("simulate", "-o", folder / "edited.g2o", "--poses", "12", "--move-map", "0.5")
    check_against_doc(edited, "camloc simulate")
    assert edited["true_map"] == str(folder / "edited.true-map.g2o") and edited["map"]["move_distance"] == 0.3


def test_the_check_catches_a_missing_and_an_undocumented_key():
    output = {"dataset": "x", "description": "y", "seed": 0,
              "counts": {"poses": 1, "landmarks": 1, "observations": 1, "cameras": 1, "clutter": 0, "outliers": 0},
              "true_map": None, "map": {"true_landmarks": 1, "withheld": 0, "moved": 0, "move_distance": None,
                                        "withheld_observations": 0}}
    check_against_doc(output, "camloc simulate")
    with pytest.raises(AssertionError, match="seed is documented but missing"):
        check_against_doc({key: value for key, value in output.items() if key != "seed"}, "camloc simulate")
    with pytest.raises(AssertionError, match=r"top level has \['path'\] differing"):
        check_against_doc({**output, "path": "x"}, "camloc simulate")
    with pytest.raises(AssertionError, match="seed is null"):
        check_against_doc({**output, "seed": None}, "camloc simulate")
