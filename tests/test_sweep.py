"""``camloc sweep``: spec parsing, cells, local and Dask execution with identical rows, resume,
failures as rows, the summary, the plot, and the option mapping shared with ``camloc run``."""

from __future__ import annotations

import csv
import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from camloc.cli.app import app
from camloc.errors import CamlocError, ConfigError
from camloc.g2o import write_g2o
from camloc.simulate import SimulationConfig, simulate
from camloc.sweep import (RESULT_COLUMNS, expand, local_results, parse_spec, prepare_folder, read_spec, run_cell,
                          run_sweep, spec_changes)

# Tiny worlds: the point is the machinery, not the localizer.
SPEC = """
seeds = [3, 4]
[simulate]
trajectory = ["grid", "smooth3d"]
poses = 30
clutter-fraction = 0.1
[run]
association = ["beam", "oracle"]
"""


def invoke(*args):
    return CliRunner().invoke(app, [str(arg) for arg in args])


def rows_of(folder: Path, name: str = "runs.csv") -> list[dict]:
    with open(folder / name, newline="") as handle:
        return list(csv.DictReader(handle))


def without_seconds(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in row.items() if k not in ("seconds", "seconds_mean")} for row in rows]


@pytest.fixture
def spec_file(tmp_path) -> Path:
    path = tmp_path / "spec.toml"
    path.write_text(SPEC)
    return path


@pytest.fixture(scope="module")
def local_sweep(tmp_path_factory) -> Path:
    """The small sweep, run once through the command line with two local workers."""
    folder = tmp_path_factory.mktemp("local")
    (folder / "spec.toml").write_text(SPEC)
    result = invoke("sweep", folder / "spec.toml", "-o", folder / "out", "--workers", "2")
    assert result.exit_code == 0, result.output
    return folder / "out"


# ------------------------------------------------------------------------------------- the spec


def test_spec_expands_to_the_product_in_cell_order(spec_file):
    spec = read_spec(spec_file)
    assert spec.columns == ("seed", "trajectory", "poses", "clutter-fraction", "association")
    cells = expand(spec)
    assert len(cells) == 2 * 2 * 2
    # configurations in spec order, the worlds inside each
    assert [c.key for c in cells[:3]] == [("3", "grid", "30", "0.1", "beam"), ("4", "grid", "30", "0.1", "beam"),
                                          ("3", "grid", "30", "0.1", "oracle")]
    assert [c.index for c in cells] == list(range(8))
    assert parse_spec({"seeds": 4}).seeds == (0, 1, 2, 3)


@pytest.mark.parametrize("document, message", [
    ({"seeds": 2, "simulate": {"poses": 1}}, "[simulate] poses = 1: simulation option poses: expected at least 2"),
    ({"seeds": 2, "simulate": {"clutter_fraction": 0.1}}, "did you mean clutter-fraction?"),
    ({"seeds": 2, "simulate": {"tag-sigma-deg": 0.0}}, "tag-sigma-deg: expected a standard deviation > 0 degrees"),
    ({"seeds": 2, "simulate": {"robot": "planar", "tag-sigma-deg": 1.0}}, "tag-sigma-deg: applies only to a 3-D robot"),
    ({"seeds": 2, "run": {"association": ["beam", "telepathy"]}}, "[run] association = \"telepathy\": --association must be one of"),
    ({"seeds": 2, "run": {"gate": "wide"}}, "[run] gate = \"wide\": --gate must be a number, got 'wide'"),
    ({"seeds": 2, "run": {"association": ["beam", "oracle"], "jcbb-max-nodes": 10}},
     "[run] jcbb-max-nodes: applies only with association jcbb, which no cell selects"),
    ({"seeds": 2, "run": {"batch": True}}, "batch (write sequential = false)"),
    ({"seeds": 2, "simulte": {}}, "unknown key 'simulte' (did you mean simulate?)"),
    ({"seeds": 2, "run": {"association": []}}, "empty product: [run] association = [] gives no cells"),
    ({"seeds": [], "run": {}}, "empty product: seeds = [] gives no worlds"),
    ({"seeds": 0}, "empty product"),
    ({"seeds": [1, 1]}, "seeds: expected a count N"),
    ({"seeds": 2, "run": {"association": ["beam", "beam"]}}, "listed twice"),
    ({"seeds": 2, "datasets": ["*.g2o"]}, "datasets sweeps existing files: it takes neither seeds nor [simulate]"),
    ({"simulate": {"poses": 30}}, "expected seeds = N"),
    ({"seeds": 2, "run": {"iterations": {"a": 1}}}, "expected a value or a list of values"),
])
def test_bad_specs_are_one_clear_error(document, message):
    with pytest.raises(ConfigError) as error:
        parse_spec(document, source="s.toml")
    assert str(error.value).startswith("s.toml: ") and message in str(error.value)


def test_bad_spec_through_the_command_line_exits_2_without_a_traceback(tmp_path):
    spec = tmp_path / "bad.toml"
    spec.write_text("seeds = 2\n[run]\nbeam-width = 0\n")
    result = invoke("sweep", spec, "-o", tmp_path / "out")
    assert result.exit_code == 2
    assert "bad.toml: [run] beam-width = 0: --beam-width must be an integer in 1..1024" in result.output
    assert "Traceback" not in result.output and not (tmp_path / "out").exists()
    assert invoke("sweep", tmp_path / "missing.toml", "-o", tmp_path / "out").exit_code == 2


def test_spec_changes_say_what_changed():
    old = parse_spec({"seeds": 3, "simulate": {"poses": 30}, "run": {"association": "beam"}}).normalized()
    new = parse_spec({"seeds": [0, 1], "simulate": {"poses": 30}, "run": {"association": ["beam", "oracle"]}}).normalized()
    assert spec_changes(old, new) == ["seeds: [0, 1, 2] -> [0, 1]", '[run] association: ["beam"] -> ["beam", "oracle"]']
    assert spec_changes(old, old) == []


# -------------------------------------------------------------------------------------- cells


def test_a_cell_is_deterministic_and_reports_its_metrics(spec_file):
    cell = expand(read_spec(spec_file))[0]
    first, second = run_cell(cell), run_cell(cell)
    assert list(first) == [*RESULT_COLUMNS, "warnings"] and first["warnings"] == []
    assert first["status"] == "ok" and first["error"] == ""
    assert 0.0 < first["ate_rmse"] < 0.5 and 0.9 <= first["precision"] <= 1.0 and first["nees_mean"] > 0
    assert {k: v for k, v in first.items() if k != "seconds"} == {k: v for k, v in second.items() if k != "seconds"}


def test_a_sweep_simulates_tag_worlds():
    """tag-sigma-deg in [simulate]: each cell a 3-D world of tags (camloc.simulate_tags), its
    orientations observed; a tag counts once in the association's scores."""
    spec = parse_spec({"seeds": 1, "simulate": {"poses": 40, "max-observations-per-pose": 2, "tag-sigma-deg": [1.0, 2.0]}})
    from camloc.measurement import TAG_ROTATION
    from camloc.simulate_planar import simulate_world, world_config

    cells = expand(spec)
    assert np.any(simulate_world(world_config(dict(cells[0].simulate)), seed=0).obs_kind == TAG_ROTATION)
    rows = [run_cell(cell) for cell in cells]
    assert [row["status"] for row in rows] == ["ok", "ok"]
    assert all(row["precision"] >= 0.99 for row in rows)


def test_a_failing_dataset_is_a_row_and_the_sweep_goes_on(tmp_path):
    worlds = tmp_path / "worlds"
    worlds.mkdir()
    write_g2o(simulate(SimulationConfig(poses=30), seed=1), worlds / "a.g2o")
    (worlds / "b.g2o").write_text("VERTEX_TRACKXYZ 0 1 2\n")
    spec = tmp_path / "files.toml"
    spec.write_text('datasets = ["worlds/*.g2o"]\n[run]\nassociation = "oracle"\n')
    result = invoke("sweep", spec, "-o", tmp_path / "out", "--workers", "1", "--json")
    assert result.exit_code == 0, result.output
    outcome = json.loads(result.stdout)
    assert (outcome["cells"], outcome["ran"], outcome["failed"]) == (2, 2, 1)
    rows = rows_of(tmp_path / "out")
    assert [r["dataset"] for r in rows] == ["worlds/a.g2o", "worlds/b.g2o"]
    assert rows[0]["status"] == "ok" and float(rows[0]["ate_rmse"]) > 0
    assert rows[1]["status"] == "failed" and "b.g2o:1:" in rows[1]["error"] and rows[1]["ate_rmse"] == ""
    assert outcome["summary"][0]["runs"] == 2 and outcome["summary"][0]["failures"] == 1
    assert "b.g2o:1:" in outcome["first_error"]
    tables = invoke("sweep", spec, "-o", tmp_path / "out", "--workers", "1")  # resumed: the warning again
    assert tables.exit_code == 0
    assert "warning: 1 of 2 runs failed" in tables.stderr and "the first: " in tables.stderr and "b.g2o:1:" in tables.stderr


def test_a_methods_options_are_for_its_own_cells_beside_the_oracle(tmp_path):
    # beam-width beside association = ["beam", "oracle"] was refused for the oracle's cells, so a
    # tuned beam could not be compared with the oracle in one sweep
    import camloc
    from camloc.localizer_config import BeamOptions, LocalizerConfig
    from camloc.metrics import evaluate

    dataset = simulate(SimulationConfig(poses=30, clutter_fraction=0.3), seed=1)
    write_g2o(dataset, tmp_path / "a.g2o")
    spec = tmp_path / "tuned.toml"
    spec.write_text('datasets = ["a.g2o"]\n[run]\nassociation = ["beam", "oracle"]\nbeam-width = 1\n')
    result = invoke("sweep", spec, "-o", tmp_path / "out", "--workers", "1", "--json")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["failed"] == 0
    rows = {row["association"]: float(row["ate_rmse"]) for row in rows_of(tmp_path / "out")}
    dataset = camloc.load(tmp_path / "a.g2o")
    for association, config in (("beam", LocalizerConfig(beam=BeamOptions(width=1))), ("oracle", LocalizerConfig(association="oracle"))):
        assert rows[association] == pytest.approx(evaluate(camloc.localize(dataset, config, parallel=False))["estimate"]["ate"]["rmse"])
    default_width = evaluate(camloc.localize(dataset, LocalizerConfig(), parallel=False))["estimate"]["ate"]["rmse"]
    assert rows["beam"] != pytest.approx(default_width)  # the width was applied (this world tells 1 from 16)


def test_a_runs_warnings_are_printed_once_each_on_one_line(tmp_path):
    # each worker printed the reader's warning as a Python warning, with a source line, per cell
    write_g2o(simulate(SimulationConfig(poses=30), seed=1), tmp_path / "a.g2o")
    odd = tmp_path / "a.g2o"
    odd.write_text(odd.read_text() + "VERTEX_XY 9 1.0 2.0\n")
    spec = tmp_path / "odd.toml"
    spec.write_text('datasets = ["a.g2o"]\n[run]\nassociation = ["beam", "oracle"]\n')
    result = invoke("sweep", spec, "-o", tmp_path / "out", "--workers", "1")
    assert result.exit_code == 0, result.output
    lines = [line for line in result.stderr.splitlines() if "VERTEX_XY" in line]
    assert len(lines) == 1 and lines[0].startswith(f"warning: {odd}: line ") and "G2oWarning" not in result.stderr
    outcome = json.loads(invoke("sweep", spec, "-o", tmp_path / "again", "--workers", "1", "--json").stdout)
    assert [w for w in outcome["warnings"] if "VERTEX_XY" in w] == [lines[0].removeprefix("warning: ")]


def test_a_sweep_whose_every_run_failed_exits_1(tmp_path):
    (tmp_path / "bad.g2o").write_text("VERTEX_TRACKXYZ 0 1 2\n")
    spec = tmp_path / "files.toml"
    spec.write_text('datasets = ["bad.g2o"]\n[run]\nassociation = "oracle"\n')
    result = invoke("sweep", spec, "-o", tmp_path / "out", "--workers", "1")
    assert result.exit_code == 1
    assert "warning: 1 of 1 runs failed" in result.stderr and "bad.g2o:1:" in result.stderr
    assert "Traceback" not in result.output


# ------------------------------------------------------------------------------- local sweeps


def test_local_sweep_writes_sorted_rows_and_a_summary_with_the_oracle_ratio(local_sweep):
    rows = rows_of(local_sweep)
    assert [(r["seed"], r["trajectory"], r["association"]) for r in rows] == [
        (seed, trajectory, association) for trajectory in ("grid", "smooth3d")
        for association in ("beam", "oracle") for seed in ("3", "4")]
    assert list(rows[0]) == ["seed", "trajectory", "poses", "clutter-fraction", "association", *RESULT_COLUMNS]
    assert all(r["status"] == "ok" and float(r["ate_rmse"]) < 0.5 for r in rows)
    summary = rows_of(local_sweep, "summary.csv")
    assert [(s["trajectory"], s["association"], s["runs"], s["failures"]) for s in summary] == [
        ("grid", "beam", "2", "0"), ("grid", "oracle", "2", "0"), ("smooth3d", "beam", "2", "0"), ("smooth3d", "oracle", "2", "0")]
    beam = [float(r["ate_rmse"]) for r in rows[:2]]
    oracle = [float(r["ate_rmse"]) for r in rows[2:4]]
    ratios = [b / o for b, o in zip(beam, oracle)]
    assert float(summary[0]["ate_rmse_worst"]) == max(beam)
    assert float(summary[0]["ate_rmse_median"]) == pytest.approx(sum(beam) / 2)
    assert float(summary[0]["oracle_ratio_worst"]) == pytest.approx(max(ratios))
    assert summary[1]["oracle_ratio_median"] == ""  # the oracle against itself is no figure
    assert json.loads((local_sweep / "spec.json").read_text())["spec"]["run"] == {"association": ["beam", "oracle"]}


def test_the_same_spec_again_runs_nothing_and_a_changed_spec_is_refused(local_sweep, tmp_path):
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC)
    before = (local_sweep / "runs.csv").read_text()
    again = invoke("sweep", spec, "-o", local_sweep, "--json")
    assert again.exit_code == 0, again.output
    assert (json.loads(again.stdout)["ran"], json.loads(again.stdout)["resumed"]) == (0, 8)
    assert (local_sweep / "runs.csv").read_text() == before
    spec.write_text(SPEC.replace("poses = 30", "poses = 31"))
    changed = invoke("sweep", spec, "-o", local_sweep)
    assert changed.exit_code == 2
    assert "holds a sweep of another spec ([simulate] poses: [30] -> [31])" in changed.output
    assert (local_sweep / "runs.csv").read_text() == before


def test_a_folder_with_other_files_is_not_overwritten(tmp_path, spec_file):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    result = invoke("sweep", spec_file, "-o", tmp_path / "mine")
    assert result.exit_code == 2 and "not empty and not a sweep folder" in result.output
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep me"


def test_resume_after_an_interrupted_sweep_runs_only_the_missing_cells(tmp_path, spec_file, local_sweep):
    spec = read_spec(spec_file)
    out = tmp_path / "out"
    seen = []

    def interrupt_after_three(done, total, result):
        seen.append(done)
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_sweep(spec, out, workers=1, on_row=interrupt_after_three)
    kept = rows_of(out)
    assert len(kept) == 3 and seen == [1, 2, 3]  # every finished row, written on the way out
    assert len(rows_of(out, "summary.csv")) >= 1
    outcome = run_sweep(spec, out, workers=1)
    assert (outcome.resumed, outcome.ran, outcome.cells) == (3, 5, 8)
    # the resumed folder holds the rows an uninterrupted sweep gives
    assert without_seconds(rows_of(out)) == without_seconds(rows_of(local_sweep))


def test_a_sweep_stopped_midway_leaves_the_exit_no_pool_thread_to_wake(spec_file):
    """The interpreter's exit hook of ``concurrent.futures`` writes to each live pool's wake-up pipe
    outside the pool's lock; a sweep stopped midway shuts its pool down without waiting, so the
    hook raced the manager thread closing that pipe ("OSError: Bad file descriptor" after a
    Ctrl-C, CI 2026-12-06/07). Stopped, the pool's manager thread is out of the hook's table, and
    it still ends."""
    from concurrent.futures import process

    cells = expand(read_spec(spec_file))
    before = set(process._threads_wakeups)
    results = local_results(cells, 2)
    next(results)  # one finished cell: the pool and its manager thread are running
    managers = [thread for thread in process._threads_wakeups if thread not in before]
    assert len(managers) == 1
    results.close()  # as a Ctrl-C in the caller's loop does
    assert managers[0] not in process._threads_wakeups
    managers[0].join(timeout=30)
    assert not managers[0].is_alive()


def test_a_damaged_runs_file_is_named_with_its_line(tmp_path, spec_file):
    spec = read_spec(spec_file)
    cells = expand(spec)
    prepare_folder(tmp_path / "out", spec, cells)
    (tmp_path / "out" / "runs.csv").write_text("seed,poses\n")
    with pytest.raises(CamlocError, match=r"runs.csv:1: expected the columns seed,trajectory"):
        prepare_folder(tmp_path / "out", spec, cells)


def test_plot_draws_a_sweep_folder(local_sweep, tmp_path):
    figure = tmp_path / "sweep.png"
    result = invoke("plot", local_sweep, "-o", figure)
    assert result.exit_code == 0, result.output
    assert figure.stat().st_size > 10_000 and figure.read_bytes()[:4] == b"\x89PNG"


def test_plot_groups_put_the_oracle_beside_each_method(local_sweep):
    from camloc.sweep import ate_groups, load_folder

    groups = ate_groups(*load_folder(local_sweep))
    assert [(label.split("\n")[0], association) for label, association, _ in groups] == [
        ("trajectory=grid", "oracle"), ("trajectory=grid", "beam"),
        ("trajectory=smooth3d", "oracle"), ("trajectory=smooth3d", "beam")]
    assert all(len(values) == 2 for _, _, values in groups)


# ---------------------------------------------------------------------- the option mapping


def test_every_localizer_option_of_camloc_run_is_in_the_one_table():
    """camloc.options.RUN_OPTIONS is the only table from command-line names to LocalizerConfig
    (tests/test_config.py: it covers every option), and each name is an option of ``camloc run``."""
    import typer

    from camloc.options import RUN_OPTIONS, localizer_overrides

    run_command = typer.main.get_command(app).commands["run"]
    flags = {opt.lstrip("-") for param in run_command.params for opt in param.opts}
    assert set(RUN_OPTIONS) <= flags, set(RUN_OPTIONS) - flags
    assert localizer_overrides({"gate": 0.9, "max-angle": 40.0, "beam-width": None}) == {
        "gate": 0.9, "view.max_angle_deg": 40.0}


# ------------------------------------------------------------------------------------- Dask


def test_dask_local_cluster_gives_the_rows_of_the_local_sweep(tmp_path, spec_file, local_sweep):
    distributed = pytest.importorskip("distributed", reason="dask.distributed is not installed (pip install -e '.[dask]')")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        outcome = run_sweep(read_spec(spec_file), tmp_path / "dask", scheduler=cluster.scheduler_address)
    assert (outcome.ran, outcome.failed) == (8, 0)
    assert without_seconds(rows_of(tmp_path / "dask")) == without_seconds(rows_of(local_sweep))
    assert without_seconds(rows_of(tmp_path / "dask", "summary.csv")) == without_seconds(rows_of(local_sweep, "summary.csv"))


def test_scheduler_without_dask_or_unreachable_is_one_line(tmp_path, spec_file, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if it were not installed
    result = invoke("sweep", spec_file, "-o", tmp_path / "out", "--scheduler", "tcp://127.0.0.1:9")
    assert result.exit_code == 2
    assert 'error: --scheduler needs dask.distributed, which is not installed: pip install -e ".[dask]"' in result.output
    assert not (tmp_path / "out").exists()
    both = invoke("sweep", spec_file, "-o", tmp_path / "out", "--scheduler", "tcp://127.0.0.1:9", "--workers", "2")
    assert both.exit_code == 2 and "--workers is for local runs" in both.output


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_sweep_against_a_dask_scheduler_and_worker_started_as_a_user_would(tmp_path, spec_file, local_sweep):
    """``dask scheduler`` and ``dask worker`` on 127.0.0.1 as subprocesses, ``camloc sweep
    --scheduler`` against them, then both stopped."""
    distributed = pytest.importorskip("distributed", reason="dask.distributed is not installed (pip install -e '.[dask]')")
    dask_cli = Path(sys.executable).parent / "dask"
    if not dask_cli.exists():
        pytest.skip(f"no dask command beside {sys.executable}")
    address = f"tcp://127.0.0.1:{_free_port()}"
    log = open(tmp_path / "dask.log", "w")
    processes = []
    try:
        processes.append(subprocess.Popen(
            [dask_cli, "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1],
             "--no-dashboard"], stdout=log, stderr=subprocess.STDOUT))
        processes.append(subprocess.Popen(
            [dask_cli, "worker", address, "--nthreads", "1", "--nworkers", "1", "--no-dashboard",
             "--host", "127.0.0.1"], stdout=log, stderr=subprocess.STDOUT))
        deadline = time.monotonic() + 30
        client = None
        while client is None:
            try:
                client = distributed.Client(address, timeout=2)
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        client.wait_for_workers(1, timeout=30)
        client.close()
        result = invoke("sweep", spec_file, "-o", tmp_path / "out", "--scheduler", address, "--json")
        assert result.exit_code == 0, result.output + (tmp_path / "dask.log").read_text()
        assert json.loads(result.stdout)["ran"] == 8
        assert without_seconds(rows_of(tmp_path / "out")) == without_seconds(rows_of(local_sweep))
    finally:
        for process in reversed(processes):
            process.terminate()
        for process in reversed(processes):
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        log.close()


def test_the_association_benchmark_spec_parses():
    """The spec beside the association benchmark (too long to run here: 40 runs of 300 poses)."""
    spec = read_spec(Path(__file__).resolve().parents[1] / "benchmarks" / "association-real-style.toml")
    assert len(expand(spec)) == 10 * 4 and dict(spec.run)["association"][0] == "oracle"


def test_quiet_prints_nothing_and_still_writes_the_rows(tmp_path):
    worlds = tmp_path / "worlds"
    worlds.mkdir()
    write_g2o(simulate(SimulationConfig(poses=30), seed=2), worlds / "a.g2o")
    spec = tmp_path / "quiet.toml"
    spec.write_text('datasets = ["worlds/*.g2o"]\n[run]\nassociation = "oracle"\n')
    result = invoke("sweep", spec, "-o", tmp_path / "out", "--workers", "1", "--quiet")
    assert result.exit_code == 0, result.output
    assert result.output == ""
    assert [r["status"] for r in rows_of(tmp_path / "out")] == ["ok"]
