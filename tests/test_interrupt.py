"""Ctrl-C on a real ``camloc run``: whenever it lands (the imports, the compiled kernels, the
writing), one line, exit status 130, and nothing half-written."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from camloc.g2o import write_g2o
from camloc.simulate import SimulationConfig, simulate

pytestmark = pytest.mark.skipif(os.name != "posix", reason="sends SIGINT to a process group")


def _camloc_script() -> list[str]:
    script = Path(sys.executable).with_name("camloc")
    return [str(script)] if script.is_file() else [sys.executable, "-c", "from camloc.cli import main; main()"]


def _interruptible() -> None:
    """In the child: Ctrl-C's default disposition, as a terminal's foreground command has it (a
    test run started in the background of a non-interactive shell inherits SIGINT ignored, and
    its children with it: the run then finishes whatever the signal)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_anywhere_in_a_run_is_one_line_and_exit_130(tmp_path):
    dataset = tmp_path / "world.g2o"
    write_g2o(simulate(SimulationConfig(poses=6000), seed=2), dataset)
    interrupted = 0
    # as a terminal's Ctrl-C does, to the whole process group (the replay's and the kernels'
    # threads and processes included). The first delay falls in camloc's imports, after the
    # interpreter's own start: a signal during Python's site import (0.05 s did hit it with the
    # tests on two processes) ends the interpreter before any program runs.
    for delay in (0.15, 0.25, 0.4, 0.9, 1.4, 1.9, 2.4, 3.0):
        run_dir = tmp_path / f"run-{delay}"
        process = subprocess.Popen([*_camloc_script(), "run", str(dataset), "-o", str(run_dir), "--quiet"],
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True, cwd=tmp_path,
                                   preexec_fn=_interruptible)
        time.sleep(delay)
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGINT)
        stdout, stderr = process.communicate(timeout=120)
        if process.returncode == 0:  # it had finished: the whole folder, as always
            assert (run_dir / "summary.json").is_file()
            continue
        interrupted += 1
        assert process.returncode == 130, stderr.decode()
        assert stderr.decode() == "interrupted\n" and stdout == b"", stderr.decode()
        assert not run_dir.exists()
        assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []  # no temporary sibling
        shutil.rmtree(run_dir, ignore_errors=True)
    assert interrupted >= 3  # the delays hit the run, not only its end
