"""What every command does the same way: errors, bad options, Ctrl-C, --quiet, --help, and the
files it will not overwrite."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from camloc.cli.app import app
from camloc.g2o import write_g2o
from camloc.results import save_run
from camloc.simulate import SimulationConfig, simulate

COMMANDS = ("run", "eval", "plot", "info", "simulate", "smooth")


def invoke(*args, **kwargs):
    return CliRunner().invoke(app, [str(arg) for arg in args], **kwargs)


def assert_one_error_line(outcome, fragment: str, *, status: int = 2) -> None:
    assert outcome.exit_code == status, outcome.output
    assert outcome.stderr.startswith("error: "), outcome.stderr  # no stray blank line before it
    assert len(outcome.stderr.splitlines()) == 1, outcome.stderr
    assert fragment in outcome.stderr, outcome.stderr
    assert outcome.stdout == ""


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    folder = tmp_path_factory.mktemp("common")
    dataset = folder / "world.g2o"
    write_g2o(simulate(SimulationConfig(poses=20), seed=3), dataset)
    run_dir = folder / "run"
    assert invoke("run", dataset, "-o", run_dir, "--quiet").exit_code == 0
    return dataset, run_dir


# --------------------------------------------------------------------------------------------
# Bad options, errors and Ctrl-C


@pytest.mark.parametrize("args, fragment", [
    (["run", "--iterations", "x"], "Invalid value for '--iterations'"),
    (["run", "--warp"], "No such option: --warp"),
    (["run", "--gate"], "Option '--gate' requires an argument"),  # pointed to 'camloc --help'
    (["eval", "--delta", "0"], "Invalid value for '--delta'"),
    (["plot", "RUN", "--dpi", "10"], "Invalid value for '--dpi'"),
    (["info"], "Missing argument 'DATASET'"),
    (["simulate", "-o", "x.g2o", "--poses", "-3"], "--poses"),
    (["simulate", "-o", "x.g2o", "--intrinsics", "fisheye"], "Invalid value for '--intrinsics'"),
    (["smooth"], "Missing argument 'RUN_DIR'"),
    (["frobnicate"], "No such command 'frobnicate'"),
    (["--bogus"], "No such option: --bogus"),
])
def test_a_bad_option_is_one_short_line_and_exit_2_in_every_command(tmp_path, monkeypatch, args, fragment):
    monkeypatch.chdir(tmp_path)
    outcome = invoke(*args)
    assert_one_error_line(outcome, fragment)
    command = args[0] if args[0] in COMMANDS else ""
    assert outcome.stderr.rstrip().endswith(f"(see '{' '.join(filter(None, ['camloc', command]))} --help')")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("args, target", [
    (["run", "{dataset}", "-o", "{tmp}/r", "--quiet"], "camloc.pipeline.localize"),
    (["eval", "{run_dir}"], "camloc.metrics.evaluate"),
    (["info", "{dataset}"], "camloc.dataset_summary.summarize_dataset"),
    (["simulate", "-o", "{tmp}/s.g2o"], "camloc.simulate.simulate_labelled"),
])
@pytest.mark.parametrize("inside_numba", [False, True], ids=["plain", "inside-numba"])
def test_ctrl_c_says_interrupted_and_exits_130(tmp_path, monkeypatch, world, args, target, inside_numba):
    dataset, run_dir = world

    def interrupted(*args, **kwargs):
        if not inside_numba:
            raise KeyboardInterrupt
        # what a Ctrl-C inside a compiled kernel becomes: SystemErrors, one per level of
        # compiled calls, the KeyboardInterrupt their first cause
        try:
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as error:
                raise SystemError("<function _numba_unpickle> returned a result with an exception set") from error
        except SystemError as error:
            raise SystemError("CPUDispatcher(<function run_poses>) returned a result with an exception set") from error

    monkeypatch.setattr(target, interrupted)
    outcome = invoke(*(arg.format(dataset=dataset, run_dir=run_dir, tmp=tmp_path) for arg in args))
    assert outcome.exit_code == 130
    assert outcome.stderr == "interrupted\n"
    assert list(tmp_path.iterdir()) == []


def test_only_an_interrupt_in_the_chain_counts_as_one():
    from camloc.cli.interrupts import caused_by_interrupt

    def chained(cause, *, suppress=False):
        try:
            raise cause
        except BaseException:
            try:
                raise (SystemError("wrapped") if not suppress else ValueError("new")) from (cause if not suppress else None)
            except BaseException as error:
                return error

    assert caused_by_interrupt(KeyboardInterrupt()) and caused_by_interrupt(chained(KeyboardInterrupt()))
    assert not caused_by_interrupt(chained(ValueError("bad")))
    assert not caused_by_interrupt(chained(KeyboardInterrupt(), suppress=True))  # 'from None' cuts the chain
    assert not caused_by_interrupt(None)


def test_eval_plot_and_smooth_of_a_dataset_file_say_what_it_is(world):
    dataset, _ = world
    for command in ("eval", "plot", "smooth"):
        assert_one_error_line(invoke(command, dataset), f"{dataset}: expected a run folder written by 'camloc run', "
                                                        f"found a file (a dataset: localize it first, 'camloc run {dataset}')")


# --------------------------------------------------------------------------------------------
# Output files and folders: created the same way, never replaced without --force


def test_every_command_creates_missing_output_folders(tmp_path, world):
    dataset, run_dir = world
    assert invoke("run", dataset, "-o", tmp_path / "a" / "b" / "run", "--quiet").exit_code == 0
    assert invoke("simulate", "-o", tmp_path / "c" / "d" / "w.g2o", "--poses", "5", "--quiet").exit_code == 0
    assert invoke("plot", run_dir, "-o", tmp_path / "e" / "f" / "report.png", "--quiet").exit_code == 0
    for path in ("a/b/run/summary.json", "c/d/w.g2o", "e/f/report.png"):
        assert (tmp_path / path).is_file(), path


def test_every_command_words_a_folder_it_cannot_create_the_same_way(tmp_path, world):
    dataset, run_dir = world
    blocker = tmp_path / "a-file"
    blocker.write_text("mine")
    for args in (["run", dataset, "-o", blocker / "run"], ["simulate", "-o", blocker / "w.g2o"],
                 ["plot", run_dir, "-o", blocker / "report.png"]):
        assert_one_error_line(invoke(*args), f"cannot create the folder {blocker}: ")
    assert blocker.read_text() == "mine"


def test_simulate_and_plot_refuse_an_existing_file_without_force(tmp_path, world):
    _, run_dir = world
    precious = tmp_path / "course.g2o"
    precious.write_text("the course dataset\n")
    report = tmp_path / "report.pdf"
    report.write_text("my report")
    assert_one_error_line(invoke("simulate", "-o", precious), f"{precious}: already exists; refusing to replace it "
                                                              "without --force")
    assert_one_error_line(invoke("plot", run_dir, "-o", report), f"{report}: already exists")
    assert precious.read_text() == "the course dataset\n" and report.read_text() == "my report"
    assert invoke("simulate", "-o", precious, "--poses", "5", "--force", "--quiet").exit_code == 0
    assert precious.read_text().startswith("PARAMS_CAMERACALIB") or "VERTEX" in precious.read_text()
    assert invoke("plot", run_dir, "-o", report, "--force", "--quiet").exit_code == 0
    assert report.read_bytes()[:4] == b"%PDF"


def test_run_refuses_an_existing_run_folder_unless_forced_and_keeps_the_users_files(tmp_path, world, synthetic_run):
    dataset, _ = world
    run_dir = save_run(tmp_path / "run", synthetic_run())
    (run_dir / "notes.md").write_text("what I saw")
    (run_dir / "smoothed.tum").write_text("# the old run's\n")
    before = {p.name: p.read_bytes() for p in run_dir.iterdir()}
    assert_one_error_line(invoke("run", dataset, "-o", run_dir), f"{run_dir}: already exists; refusing to replace it "
                                                                 "without --force")
    assert {p.name: p.read_bytes() for p in run_dir.iterdir()} == before

    assert invoke("run", dataset, "-o", run_dir, "--force", "--quiet").exit_code == 0
    assert (run_dir / "notes.md").read_text() == "what I saw"
    assert not (run_dir / "smoothed.tum").exists()  # it belonged to the old run
    assert str(dataset) in (run_dir / "summary.json").read_text()

    other = tmp_path / "thesis"
    other.mkdir()
    (other / "chapter.tex").write_text("years of work")
    assert_one_error_line(invoke("run", dataset, "-o", other, "--force"), "is not a camloc run folder")
    assert [p.name for p in other.iterdir()] == ["chapter.tex"]


def test_a_file_system_refusal_is_one_line_and_leaves_the_old_run_and_nothing_else(tmp_path, world, synthetic_run, monkeypatch):
    # a run folder that cannot be moved aside (read-only parent, as a user other than root finds it)
    import os

    from camloc import results

    dataset, _ = world
    run_dir = save_run(tmp_path / "run", synthetic_run())
    before = {p.name: p.read_bytes() for p in run_dir.iterdir()}
    real_rename = os.rename

    def refusing(source, target):
        if ".old-" in str(target):
            raise PermissionError(13, "Permission denied", str(source), None, str(target))
        return real_rename(source, target)

    monkeypatch.setattr(results.os, "rename", refusing)
    assert_one_error_line(invoke("run", dataset, "-o", run_dir, "--force"), f"cannot move {run_dir} to ")
    assert {p.name: p.read_bytes() for p in run_dir.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # no .run.old-* or .run.tmp-* left


def test_running_out_of_memory_is_one_line(tmp_path, monkeypatch):
    import camloc.simulate

    def too_big(*args, **kwargs):
        raise MemoryError()

    monkeypatch.setattr(camloc.simulate, "simulate", too_big)
    assert_one_error_line(invoke("simulate", "-o", tmp_path / "w.g2o", "--landmarks", "100000000000"), "not enough memory")
    assert not any(tmp_path.iterdir())


def test_a_folder_given_for_a_file_is_refused_even_with_force(tmp_path, world):
    _, run_dir = world
    folder, named_like_a_figure = tmp_path / "figures", tmp_path / "report.pdf"
    folder.mkdir()
    named_like_a_figure.mkdir()
    for args in (["simulate", "-o", folder, "--poses", "5", "--force"], ["plot", run_dir, "-o", named_like_a_figure, "--force"]):
        assert_one_error_line(invoke(*args), "is a folder; expected the path of a file to write")
    assert not any(folder.iterdir()) and not any(named_like_a_figure.iterdir())


def test_run_prints_each_warning_on_one_line_named_by_the_dataset(tmp_path, world):
    dataset, _ = world
    odd = tmp_path / "odd.g2o"
    odd.write_text(dataset.read_text() + "VERTEX_XY 9 1.0 2.0 a record g2o knows and camloc does not read\n")
    outcome = invoke("run", odd, "-o", tmp_path / "r")
    assert outcome.exit_code == 0, outcome.output
    lines = [line for line in outcome.stderr.splitlines() if line.startswith("warning:")]
    assert lines and all(line.startswith(f"warning: {odd}: ") for line in lines), outcome.stderr
    assert any("VERTEX_XY" in line and "skipped 1 record" in line for line in lines), outcome.stderr


def test_a_device_is_not_read_as_a_config_file(tmp_path, world):
    import os

    if not os.path.exists("/dev/zero"):
        pytest.skip("no /dev/zero here")
    dataset, _ = world
    assert_one_error_line(invoke("run", dataset, "-o", tmp_path / "r", "--config", "/dev/zero"),
                          "/dev/zero: is a device, expected a TOML config file", status=2)


# --------------------------------------------------------------------------------------------
# --quiet, and run and eval agreeing


def test_quiet_prints_nothing_in_every_command(tmp_path, world):
    dataset, run_dir = world
    for args in (["run", dataset, "-o", tmp_path / "r"], ["eval", run_dir], ["plot", run_dir],
                 ["info", dataset], ["simulate", "-o", tmp_path / "s.g2o", "--poses", "5"], ["smooth", run_dir]):
        outcome = invoke(*args, "--quiet")
        assert outcome.exit_code == 0, outcome.output
        assert outcome.output == "", args
    assert {"--quiet", "-q"} <= _options_of("run") and all("--quiet" in _options_of(name) for name in COMMANDS)


def test_run_and_eval_show_the_same_precision_without_ground_truth(tmp_path, world):
    dataset, _ = world
    lines = dataset.read_text().splitlines()
    vertices = [i for i, line in enumerate(lines) if line.startswith("VERTEX_SE3:QUAT")]
    bare = tmp_path / "bare.g2o"
    bare.write_text("\n".join(line for i, line in enumerate(lines) if i not in vertices[1:]) + "\n")
    table = invoke("run", bare, "-o", tmp_path / "run", env={"COLUMNS": "200"})
    assert table.exit_code == 0, table.output
    evaluation = invoke("eval", tmp_path / "run", "--json")
    precision = f"{__import__('json').loads(evaluation.stdout)['association']['precision']:.3f}"
    row = next(line for line in table.stdout.splitlines() if re.match(r"^│\s+\d+\s+│", line))
    assert row.split("│")[6].strip() == precision


# --------------------------------------------------------------------------------------------
# --help


def _command(name: str):
    return typer.main.get_command(app).commands[name]


def _options_of(name: str) -> set[str]:
    return {opt for param in _command(name).params for opt in param.opts}


@pytest.mark.parametrize("name", COMMANDS)
def test_help_states_every_default_the_same_way_and_no_bool_value(name):
    outcome = invoke(name, "--help", env={"COLUMNS": "300"})
    assert outcome.exit_code == 0
    text = outcome.stdout
    assert "<bool>" not in text and "[default:" not in text and "{" not in text  # usage: RUN_DIR, [RUN_DIR], never {RUN_DIR}
    for param in _command(name).params:
        if isinstance(param, typer.core.TyperArgument):
            assert param.metavar in ("DATASET", "RUN_DIR"), param.name
        elif not param.required:
            assert "Default: " in param.help, f"{name} {param.opts[0]}"


def test_help_defaults_are_the_codes_defaults():
    from camloc.localizer import LocalizerConfig
    from camloc.simulate import SimulationConfig
    from camloc.smoother import SmootherConfig

    def flat(*args):
        return " ".join(invoke(*args, env={"COLUMNS": "300"}).stdout.replace("│", " ").split())

    run, simulate_help, smooth = flat("run", "--help"), flat("simulate", "--help"), flat("smooth", "--help")
    defaults = LocalizerConfig()
    assert f"kept after each pose (more, and further in cost, at a pose of a few pixel observations only: docs/beam.md). " \
           f"Default: {defaults.beam.width}." in run
    assert f"iterated EKF. Default: {defaults.iterations}." in run
    assert "Default: --recheck." in run and "Default: --sequential." in run
    assert f"(at least 2). Default: {SimulationConfig().poses}." in simulate_help
    assert f"least squares. Default: {SmootherConfig().huber!r}." in smooth


# Options a user cannot act on without knowing what a cost unit or a slip is (issue 36).
COST_OPTIONS = ("--null-cost", "--beam-delta", "--branch-delta", "--slip-inflation", "--slip-cost", "--margin",
                "--recheck-margin", "--recheck-steal-margin", "--recheck-ray-margin")


def test_every_cost_option_gives_its_unit_and_the_design_doc():
    params = {param.opts[0]: param for param in _command("run").params}
    for flag in COST_OPTIONS:
        text = params[flag].help
        assert "docs/beam.md" in text or "docs/association.md" in text, flag
        assert "cost units" in text or "factor" in text, flag
        if "cost units" in text:
            assert "log-likelihood" in text, flag  # what a cost unit is
    assert "Slip (odometry that jumped)" in params["--slip-cost"].help


ALL_COMMANDS = (*COMMANDS, "sweep")


@pytest.mark.parametrize("columns", ["80", "110"])
@pytest.mark.parametrize("name", ALL_COMMANDS)
def test_help_shows_every_panel_title_whole_and_usage_without_braces(name, columns):
    outcome = invoke(name, "--help", env={"COLUMNS": columns})
    assert outcome.exit_code == 0
    titles = {param.rich_help_panel for param in _command(name).params if getattr(param, "rich_help_panel", None)}
    heads = [line for line in outcome.stdout.splitlines() if line.startswith("╭─ ")]
    for title in titles:
        assert any(head.startswith(f"╭─ {title.replace(chr(92), '')} ─") for head in heads), (title, heads)
    usage = next(line for line in outcome.stdout.splitlines() if "Usage:" in line)
    assert "{" not in usage and "}" not in usage, usage


def test_the_commands_list_flows_each_commands_first_paragraph_at_the_terminals_width():
    """typer's rich help kept a docstring's single line breaks in the commands' list ("trajectory
    length and" / "extent" on two lines whatever the width)."""
    outcome = CliRunner().invoke(app, ["--help"], env={"COLUMNS": "400"})
    assert outcome.exit_code == 0
    rows = [line for line in outcome.stdout.splitlines() if line.startswith("│ ")]
    for name in ALL_COMMANDS:
        row = next(line for line in rows if line.split()[1] == name)
        assert row.rstrip(" │").endswith("."), row  # the whole paragraph on the command's one row
    assert any("trajectory length and extent, odometry" in row for row in rows)


# Placeholders that let each command reach its options' parsing.
_POSITIONALS = {"run": [], "eval": ["RUN"], "plot": ["RUN"], "info": ["DATA.g2o"], "simulate": ["-o", "x.g2o"],
                "smooth": ["RUN"], "sweep": ["SPEC.toml", "-o", "out"]}


def _choice_options():
    import enum
    import typing

    for name in ALL_COMMANDS:
        command = _command(name)
        hints = typing.get_type_hints(command.callback)
        for param in command.params:
            hint = hints.get(param.name)
            kinds = [k for k in (typing.get_args(hint) or (hint,)) if isinstance(k, type) and issubclass(k, enum.Enum)]
            if kinds and param.opts[0].startswith("--"):
                yield name, param.opts[0], [choice.value for choice in kinds[0]]


CHOICE_OPTIONS = list(_choice_options())


def test_every_option_with_choices_is_found():
    assert {"--align", "--filter", "--association", "--cost", "--format", "--trajectory", "--intrinsics"} <= {
        flag for _, flag, _ in CHOICE_OPTIONS}


@pytest.mark.parametrize("name, flag, choices", CHOICE_OPTIONS, ids=[f"{n} {f}" for n, f, _ in CHOICE_OPTIONS])
def test_a_value_that_is_none_of_the_choices_is_one_line_listing_them(tmp_path, monkeypatch, name, flag, choices):
    monkeypatch.chdir(tmp_path)
    outcome = invoke(name, *_POSITIONALS[name], flag, "bogus")
    assert_one_error_line(outcome, f"Invalid value for '{flag}': expected one of {', '.join(choices)}, found 'bogus'")
    assert "Value error" not in outcome.stderr


def test_the_sweep_table_keeps_every_column_at_80_columns(tmp_path):
    spec = tmp_path / "study.toml"
    spec.write_text('seeds = 1\n[simulate]\nposes = 8\ntrajectory = ["grid", "smooth3d"]\nclutter-fraction = [0.0, 0.15]\n'
                    '[run]\nassociation = ["beam", "oracle"]\n')
    outcome = invoke("sweep", spec, "-o", tmp_path / "out", "--workers", "1", env={"COLUMNS": "80"})
    assert outcome.exit_code == 0, outcome.output
    lines = outcome.stdout.splitlines()
    header = " ".join(lines[next(i for i, line in enumerate(lines) if "───" in line) - 2:][:2])
    for column in ("trajectory", "clutter-", "fraction", "ok", "median", "p90", "worst", "/oracle"):
        assert column in header, (column, header)
    assert header.count("/oracle") == 2 and header.count("worst") == 2
    rows = [line for line in lines if line.lstrip().startswith(("grid", "smooth3d"))]
    assert len(rows) == 8 and all(len(line.rstrip()) <= 80 for line in lines)
    assert all(line.split()[2] in ("beam", "oracle") for line in rows)  # values whole, never folded


@pytest.mark.skipif(os.name != "posix", reason="a pipe whose reader has left")
@pytest.mark.parametrize("json_output", [True, False])
def test_a_reader_that_leaves_early_ends_the_command_silently_with_status_1(world, json_output):
    """'camloc info --json | head -c 1': no 'error: Broken pipe' (what --json printed before),
    no traceback; status 1, as rich's tables end then."""
    dataset, run_dir = world
    script = Path(sys.executable).with_name("camloc")
    command = [str(script)] if script.is_file() else [sys.executable, "-c", "from camloc.cli import main; main()"]
    for args in (["info", dataset], ["eval", run_dir]):
        process = subprocess.Popen([*command, *map(str, args), *(["--json"] if json_output else [])],
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        process.stdout.close()  # the reader leaves before the command prints anything
        stderr = process.stderr.read().decode()
        process.wait(timeout=120)
        assert process.returncode == 1 and stderr == "", (args, process.returncode, stderr)


def test_an_output_file_where_a_folder_is_says_so_without_force_too(tmp_path, world):
    """Not 'already exists; refusing to replace it without --force', which --force would not mend."""
    _, run_dir = world
    folder = tmp_path / "report.pdf"
    folder.mkdir()
    for args in (["simulate", "-o", folder, "--poses", "5"], ["plot", run_dir, "-o", folder]):
        assert_one_error_line(invoke(*args), f"{folder}: is a folder; expected the path of a file to write")


def test_a_folder_that_cannot_be_made_names_the_file_in_the_way(tmp_path, world):
    dataset, _ = world
    blocker = tmp_path / "a-file"
    blocker.write_text("mine")
    assert_one_error_line(invoke("run", dataset, "-o", blocker / "deeper" / "run"),
                          f"cannot create the folder {blocker / 'deeper'}: {blocker} is a file, not a folder")


@pytest.mark.skipif(os.name != "posix", reason="a named pipe")
def test_a_device_or_pipe_given_for_an_output_file_is_never_replaced(tmp_path, world):
    """Run as root, 'camloc simulate -o /dev/null --force' replaced the system's null device with
    a regular file (found 2026-12-06, and put back); a named pipe stands in for the device here."""
    import stat

    from camloc.errors import CamlocError

    _, run_dir = world
    for name in ("w.g2o", "report.png"):
        os.mkfifo(tmp_path / name)
    for args in (["simulate", "-o", tmp_path / "w.g2o", "--poses", "5"], ["plot", run_dir, "-o", tmp_path / "report.png"]):
        for force in ([], ["--force"]):
            assert_one_error_line(invoke(*args, *force), "is a device, a pipe or a socket, which camloc never replaces")
    with pytest.raises(CamlocError, match="is a device, a pipe or a socket"):
        write_g2o(simulate(SimulationConfig(poses=5), seed=1), tmp_path / "w.g2o")
    assert all(stat.S_ISFIFO((tmp_path / name).stat().st_mode) for name in ("w.g2o", "report.png"))
    assert sorted(path.name for path in tmp_path.iterdir()) == ["report.png", "w.g2o"]  # no temporary left
