"""The first compile in the background (camloc.warmup): a cold run of a few thousand poses at most
goes to numpy and leaves the kernels compiling in a detached process, once; otherwise, or where
that process cannot run, the kernels compile in the foreground as before."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

import camloc
import camloc.kernels
import camloc.localizer
from camloc import warmup
from camloc.localizer import COMPILED_MIN_POSES
from camloc.simulate import SimulationConfig, simulate


@pytest.fixture(scope="module")
def medium_world():
    """Enough poses for "auto" to choose the compiled loop, few enough for the background compile."""
    dataset = simulate(SimulationConfig(poses=COMPILED_MIN_POSES), seed=5)
    assert COMPILED_MIN_POSES <= dataset.num_poses
    assert warmup.numpy_seconds(dataset.num_observations, 0) <= warmup.NUMPY_FIRST_RUN_SECONDS
    return dataset


@pytest.fixture
def cold_cache(tmp_path, monkeypatch):
    """A cache that looks cold, a lock folder of the test's own, the switch on, and a process
    launcher that records its command instead of starting it."""
    monkeypatch.setenv(warmup.ENVIRONMENT_SWITCH, "1")
    monkeypatch.setattr(warmup, "cache_folder", lambda: tmp_path)
    monkeypatch.setattr(camloc.kernels, "cache_is_warm", lambda: False)
    spawned = []
    monkeypatch.setattr(warmup, "_spawn", lambda command, environment: spawned.append(command))
    monkeypatch.setattr(warmup, "_start", lambda command, environment: FakeProcess(command))
    return tmp_path, spawned


class FakeProcess:
    """What ``warmup._start`` returns, recording its command and each wait (into ``events``)."""

    def __init__(self, command, events=None, hangs=False):
        self.command, self.events, self.hangs, self.killed = command, events if events is not None else [], hangs, False

    def wait(self, timeout=None):
        import subprocess

        self.events.append(("wait", timeout))
        if self.hangs and not self.killed:
            raise subprocess.TimeoutExpired(self.command, timeout)
        return 0

    def kill(self):
        self.killed = True


def _localize(dataset, **kwargs):
    told = {"foreground": 0, "background": []}
    result = camloc.localize(dataset, on_compile=lambda: told.__setitem__("foreground", told["foreground"] + 1),
                             on_background_compile=told["background"].append, **kwargs)
    return result, told


def test_a_cold_run_goes_to_numpy_and_starts_one_background_compile(medium_world, cold_cache):
    folder, spawned = cold_cache
    first, told = _localize(medium_world)
    assert first.summary["timing"]["engine"] == "numpy"
    assert first.summary["timing"]["background_compile"] is True
    assert told == {"foreground": 0, "background": [True]}
    lock = folder / warmup.LOCK_NAME
    assert spawned == [[sys.executable, "-m", "camloc.warmup", str(lock)]]
    # the process imports this camloc, whatever the path it is started with
    assert warmup._environment()["PYTHONPATH"].split(os.pathsep)[0] == str(Path(camloc.__file__).resolve().parents[1])
    assert lock.read_text().startswith("compiling since")
    assert warmup.compiling(folder)
    # a second run while it compiles: numpy again, and no second compile
    second, told = _localize(medium_world)
    assert second.summary["timing"]["engine"] == "numpy"
    assert told == {"foreground": 0, "background": [False]}
    assert len(spawned) == 1
    assert (second.associations.landmark == first.associations.landmark).all()


def test_a_run_compiles_in_the_foreground_where_the_background_cannot_serve(medium_world, cold_cache, monkeypatch):
    folder, spawned = cold_cache
    # a forced engine is honoured
    forced, told = _localize(medium_world, engine="compiled")
    assert (forced.summary["timing"]["engine"], told) == ("compiled", {"foreground": 1, "background": []})
    assert forced.summary["timing"]["background_compile"] is False
    # a dataset the numpy engine would take longer over than the compile
    monkeypatch.setattr(warmup, "NUMPY_FIRST_RUN_SECONDS", 0.5 * warmup.numpy_seconds(medium_world.num_observations, 0))
    large, told = _localize(medium_world)
    assert (large.summary["timing"]["engine"], told) == ("compiled", {"foreground": 1, "background": []})
    assert spawned == []


@pytest.mark.parametrize("reason", ["switched off", "failed recently", "cannot start"])
def test_where_the_background_compile_cannot_run_the_kernels_compile_first(reason, cold_cache, monkeypatch):
    folder, spawned = cold_cache
    if reason == "switched off":
        monkeypatch.setenv(warmup.ENVIRONMENT_SWITCH, "0")
    elif reason == "failed recently":
        (folder / warmup.LOCK_NAME).write_text("failed at 2026-12-02 12:00:00: RuntimeError: out of memory\n")
        assert warmup.lock_state(folder) == warmup.FAILED and not warmup.compiling(folder)
    else:
        def refuse(command, environment):
            raise OSError("no such file")
        monkeypatch.setattr(warmup, "_spawn", refuse)
    assert warmup.start_background_compile(folder) is None
    if reason == "cannot start":
        assert not (folder / warmup.LOCK_NAME).exists()      # no lock left to hold off the next run
    assert spawned == []


def test_a_stale_lock_is_taken_over(cold_cache):
    import time

    folder, spawned = cold_cache
    lock = folder / warmup.LOCK_NAME
    lock.write_text("compiling since 2026-12-01 08:00:00\n")
    old = time.time() - warmup.STALE_SECONDS - 1
    os.utime(lock, (old, old))
    assert warmup.lock_state(folder) is None
    assert warmup.start_background_compile(folder) == warmup.STARTED
    assert len(spawned) == 1 and warmup.compiling(folder)


def test_the_lock_of_a_compile_that_was_killed_is_taken_over(cold_cache):
    import subprocess

    folder, spawned = cold_cache
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True, check=True)
    (folder / warmup.LOCK_NAME).write_text(f"compiling since 2026-12-02 12:00:00 pid {gone.stdout.strip()}\n")
    if os.name == "posix":
        assert warmup.lock_state(folder) is None
        assert warmup.start_background_compile(folder) == warmup.STARTED and len(spawned) == 1
    (folder / warmup.LOCK_NAME).write_text(f"compiling since 2026-12-02 12:00:00 pid {os.getpid()}\n")
    assert warmup.compiling(folder)                         # a process that is there holds it


@pytest.mark.parametrize("fails", [False, True])
def test_the_background_process_removes_its_lock_or_leaves_its_error_there(fails, tmp_path, monkeypatch):
    lock = tmp_path / warmup.LOCK_NAME
    lock.write_text("compiling since now\n")

    def compile_kernels():
        assert f"pid {os.getpid()}" in lock.read_text()     # the lock names the compiling process
        assert warmup.compiling(tmp_path)
        if fails:
            raise RuntimeError("LLVM ran out of memory")
    monkeypatch.setattr(warmup, "compile_kernels", compile_kernels)
    assert warmup.main(["camloc.warmup", str(lock)]) == (1 if fails else 0)
    if fails:
        assert "RuntimeError: LLVM ran out of memory" in lock.read_text()
        assert warmup.lock_state(tmp_path) == warmup.FAILED
    else:
        assert not lock.exists() and warmup.lock_state(tmp_path) is None


def test_the_background_compile_runs_every_kernel_a_run_calls():
    # the slip search's kernels are called only where a pose needs it: the warm-up world must slip
    slips = warmup.compile_kernels()
    assert slips, "the warm-up world's beam never ran its slip search"
    assert camloc.kernels.cache_is_warm()


def test_camloc_run_says_that_it_compiles_in_the_background(tmp_path, cold_cache, medium_world):
    from typer.testing import CliRunner

    from camloc.cli.app import app
    from camloc.g2o import write_g2o

    path = tmp_path / "medium.g2o"
    write_g2o(medium_world, path)
    outcome = CliRunner().invoke(app, ["run", str(path), "-o", str(tmp_path / "run")])
    assert outcome.exit_code == 0, outcome.output
    assert "compiling camloc's kernels in the background" in " ".join(outcome.output.split())
    assert "this run uses the numpy engine" in " ".join(outcome.output.split())
    outcome = CliRunner().invoke(app, ["run", str(path), "-o", str(tmp_path / "again"), "--json"])
    assert outcome.exit_code == 0, outcome.output
    import json

    summary = json.loads(outcome.output)
    assert summary["timing"]["engine"] == "numpy" and summary["timing"]["background_compile"] is True


def test_the_readme_and_the_help_state_the_limit_the_code_uses():
    from typer.testing import CliRunner

    from camloc.cli.app import app

    limit = f"under about {warmup.NUMPY_FIRST_RUN_SECONDS:.0f} s"
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    assert limit in " ".join(readme.split())
    help_text = " ".join(CliRunner().invoke(app, ["run", "--help"]).output.split())
    assert limit in help_text and warmup.ENVIRONMENT_SWITCH in help_text


@pytest.mark.parametrize("parallel", [True, None])
def test_a_first_compile_of_the_beam_compiles_the_filter_in_a_second_process_and_waits_for_it(
        parallel, medium_world, cold_cache, monkeypatch):
    import camloc.loop

    events = []
    monkeypatch.setattr(warmup, "_start", lambda command, environment: FakeProcess(command, events))
    monkeypatch.setattr(camloc.localizer, "_cpus", lambda: 2)
    real_filter = camloc.loop.filter_poses

    def filter_poses(*args):
        events.append("filter")
        return real_filter(*args)
    monkeypatch.setattr(camloc.loop, "filter_poses", filter_poses)
    result = camloc.localize(medium_world, engine="compiled", parallel=parallel)
    # one wait, before the filter's first stretch, without a time limit short of a compile's
    assert events[0] == ("wait", warmup.FILTER_COMPILE_TIMEOUT) and events.count(events[0]) == 1
    assert events.count("filter") >= 1
    assert events[1:] == ["filter"] * (len(events) - 1)
    monkeypatch.setenv(warmup.ENVIRONMENT_SWITCH, "0")          # no second process: the same result
    events.clear()
    alone = camloc.localize(medium_world, engine="compiled", parallel=parallel)
    assert ("wait", warmup.FILTER_COMPILE_TIMEOUT) not in events
    assert (alone.associations.landmark == result.associations.landmark).all()
    assert np.array_equal(alone.filter_state, result.filter_state)


def test_the_filter_compiles_alone_where_a_second_process_would_not_help(medium_world, cold_cache, monkeypatch):
    started = []
    monkeypatch.setattr(warmup, "_start", lambda command, environment: started.append(command) or FakeProcess(command))
    monkeypatch.setattr(camloc.localizer, "_cpus", lambda: 2)
    camloc.localize(medium_world, camloc.LocalizerConfig(association="oracle"), engine="compiled")  # only the filter compiles
    monkeypatch.setattr(camloc.kernels, "cache_is_warm", lambda: True)
    camloc.localize(medium_world, engine="compiled")                                                 # nothing compiles
    monkeypatch.setattr(camloc.kernels, "cache_is_warm", lambda: False)
    monkeypatch.setattr(camloc.localizer, "_cpus", lambda: 1)
    camloc.localize(medium_world, engine="compiled")                                                 # one core
    monkeypatch.setattr(camloc.localizer, "_cpus", lambda: 2)
    camloc.localize(medium_world, engine="compiled", parallel=False)                                # asked for one
    assert started == []
    camloc.localize(medium_world, engine="compiled")
    assert started == [[sys.executable, "-m", "camloc.warmup", warmup.FILTER_ONLY]]


@pytest.mark.parametrize("reason", ["switched off", "no cache folder", "cannot start"])
def test_where_the_second_process_cannot_run_the_filter_compiles_in_the_run(reason, cold_cache, monkeypatch):
    if reason == "switched off":
        monkeypatch.setenv(warmup.ENVIRONMENT_SWITCH, "0")
    elif reason == "no cache folder":
        monkeypatch.setattr(warmup, "cache_folder", lambda: None)
    else:
        def refuse(command, environment):
            raise OSError("no such file")
        monkeypatch.setattr(warmup, "_start", refuse)
    assert warmup.start_filter_compile() is None
    assert warmup.start_mapping_compile() is None
    warmup.wait_for(None)                                    # nothing to wait for


def test_a_filter_compile_that_hangs_is_stopped():
    events = []
    hung = FakeProcess(["python"], events, hangs=True)
    warmup.wait_for(hung)
    assert hung.killed and events == [("wait", warmup.FILTER_COMPILE_TIMEOUT), ("wait", None)]


def test_the_filter_compile_process_compiles_the_filter_without_a_lock(tmp_path, monkeypatch):
    compiled = []
    monkeypatch.setattr(warmup, "compile_filter_kernels", lambda: compiled.append(True))
    monkeypatch.setattr(warmup, "cache_folder", lambda: tmp_path)
    assert warmup.main(["camloc.warmup", warmup.FILTER_ONLY]) == 0
    assert compiled == [True] and list(tmp_path.iterdir()) == []


def test_the_filter_compile_command_runs():
    import subprocess

    # as the run starts it: this camloc, the bundled world with the oracle (from the cache where the
    # suite has compiled the filter already)
    done = subprocess.run([sys.executable, "-m", "camloc.warmup", warmup.FILTER_ONLY], env=warmup._environment(),
                          capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr


def test_the_late_kernels_are_compiled_for_the_arguments_a_run_passes():
    import subprocess

    # in a fresh process: the kernels' signatures after the second process's share, and after a run
    # that calls every one of them (the slip search included) from the beam and from Python
    code = (
        "import camloc\n"
        "from camloc import warmup\n"
        "from camloc.bundled import bundled_dataset\n"
        "from camloc.g2o import read_g2o\n"
        "kernels = warmup.late_beam_kernels(read_g2o(bundled_dataset('smooth3d-clutter')), camloc.LocalizerConfig())\n"
        "before = [sorted(map(str, k.signatures)) for k in kernels]\n"
        "assert warmup.compile_kernels(), 'no slip search ran'\n"
        "after = [sorted(map(str, k.signatures)) for k in kernels]\n"
        "print(before == after, [len(s) for s in after])\n"
    )
    done = subprocess.run([sys.executable, "-c", code], env=warmup._environment(), capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split()[0] == "True", done.stdout
    assert done.stdout.split(None, 1)[1].strip() == "[1, 1, 1, 1, 1, 1]"


def test_a_first_run_goes_to_numpy_where_numpy_is_quick_and_compiles_first_where_it_is_not():
    # Issue 35: a first run of 3,000 poses of two cameras with depth (24,000 observations) waited
    # for the compile; numpy takes it in about 13 s. The same poses of pixel-only observations take
    # numpy 267 s, longer than the compile.
    assert warmup.numpy_seconds(24_000, 0) <= warmup.NUMPY_FIRST_RUN_SECONDS
    assert warmup.numpy_seconds(24_000, 24_000) > warmup.NUMPY_FIRST_RUN_SECONDS
    assert warmup.numpy_seconds(24_000, 0) < warmup.numpy_seconds(24_000, 1_000) < warmup.numpy_seconds(24_000, 24_000)


@pytest.fixture
def cold_mapping_cache(tmp_path, monkeypatch, cold_cache):
    """The mapping pass's kernels (camloc.slam_compiled) looking cold, their lock folder the test's."""
    import camloc.slam_compiled

    folder = tmp_path / "mapping"
    monkeypatch.setattr(camloc.slam_compiled, "cache_is_warm", lambda: False)
    monkeypatch.setattr(camloc.slam_compiled, "cache_folder", lambda: folder)
    return folder, cold_cache[1]


def test_a_cold_mapping_pass_runs_in_numpy_and_compiles_its_kernels_in_the_background(cold_mapping_cache):
    folder, spawned = cold_mapping_cache
    dataset = simulate(SimulationConfig(poses=COMPILED_MIN_POSES, withhold_map=0.5), seed=5)
    told = []
    hooks = dict(engine="auto", on_background_compile=told.append)
    assert not camloc.localizer._mapping_compiled(dataset, hooks)
    assert told == [True] and spawned[-1][-2:] == [warmup.MAPPING_ONLY, str(folder / warmup.LOCK_NAME)]
    assert not camloc.localizer._mapping_compiled(dataset, hooks)  # one compile at a time
    assert told == [True, False] and len(spawned) == 1
    # a library call without the hook, and engine "compiled", compile in the foreground; numpy and short runs never
    assert camloc.localizer._mapping_compiled(dataset, dict(engine="auto", on_background_compile=None))
    assert camloc.localizer._mapping_compiled(dataset, dict(engine="compiled", on_background_compile=told.append))
    assert not camloc.localizer._mapping_compiled(dataset, dict(engine="numpy", on_background_compile=None))
    short = simulate(SimulationConfig(poses=COMPILED_MIN_POSES - 100, withhold_map=0.5), seed=5)
    assert not camloc.localizer._mapping_compiled(short, dict(engine="auto", on_background_compile=None))


def test_the_mapping_background_process_compiles_the_mapping_kernels(tmp_path, monkeypatch):
    lock = tmp_path / warmup.LOCK_NAME
    lock.write_text("compiling since now\n")
    called = []
    monkeypatch.setattr(warmup, "compile_mapping_kernels", lambda: called.append("mapping"))
    monkeypatch.setattr(warmup, "compile_kernels", lambda: called.append("localizer"))
    assert warmup.main(["camloc.warmup", warmup.MAPPING_ONLY, str(lock)]) == 0
    assert called == ["mapping"] and not lock.exists()


def test_the_mapping_share_compiles_the_mapping_kernels_without_a_lock(tmp_path, monkeypatch):
    # ``start_mapping_compile``'s process (the tests' setup): no lock argument, none written
    monkeypatch.chdir(tmp_path)
    called = []
    monkeypatch.setattr(warmup, "compile_mapping_kernels", lambda: called.append("mapping"))
    monkeypatch.setattr(warmup, "compile_kernels", lambda: called.append("localizer"))
    assert warmup.main(["camloc.warmup", warmup.MAPPING_ONLY]) == 0
    assert called == ["mapping"] and list(tmp_path.iterdir()) == []


@pytest.mark.skipif(not Path("/proc/self/autogroup").exists() or not hasattr(os, "setsid"),
                    reason="no Linux autogroups here: the nice value is all there is")
def test_the_background_compile_yields_to_the_run_across_sessions():
    """The background compile runs in a session of its own, and Linux weighs a nice value only
    within a session's autogroup: its group must be lowered too, or it takes half of a 2-core
    machine from the run that started it (a process of its own, so this test's stays as it is)."""
    import subprocess

    def nice_and_group(code: str) -> list[str]:
        # a process in the root group (a container's first session, never setsid) reads an empty file
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
        return out.split()[:1] + (out.split()[1:] or ["root"])[-1:]

    code = ("import os; os.setsid(); from camloc.warmup import lowest_priority; lowest_priority(); "
            "print(os.nice(0), open('/proc/self/autogroup').read())")
    assert nice_and_group(code) == ["19", "19"]
    # called in a process of somebody else's session (a test's, a notebook's): their group is left alone
    code = code.replace("os.setsid(); ", "")
    before = (open("/proc/self/autogroup").read().split() or ["root"])[-1]
    out = nice_and_group(code)
    assert out == ["19", before]
