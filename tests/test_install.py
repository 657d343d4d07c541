"""camloc installed as users install it: ``pip install .`` (not editable) into a fresh venv, then
the command and the README's library example run from a folder that is not the source tree."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import venv
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
# What a source distribution holds; the rest (.venv, runs, caches) would only slow the copy.
SOURCE_PARTS = ("pyproject.toml", "README.md", "camloc", "cli")


@pytest.mark.slow
def test_a_non_editable_install_runs_the_bundled_dataset_from_any_folder(tmp_path):
    source = tmp_path / "source"
    for part in SOURCE_PARTS:
        origin = REPO_ROOT / part
        if origin.is_dir():
            shutil.copytree(origin, source / part, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            source.mkdir(exist_ok=True)
            shutil.copy2(origin, source / part)
    environment = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True).create(environment)
    bin_dir = environment / ("Scripts" if sys.platform == "win32" else "bin")
    install = subprocess.run([bin_dir / "python", "-m", "pip", "install", "-q", str(source)],
                             capture_output=True, text=True)
    assert install.returncode == 0, install.stderr[-2000:]
    # The source copy goes away: the installed package must hold everything it needs.
    shutil.rmtree(source)

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    # What is checked here is what the install holds; compiling the kernels a second time, in this
    # venv, would add two minutes. Without the JIT they run as the plain Python they are written in.
    plain = {**os.environ, "NUMBA_DISABLE_JIT": "1"}
    run = subprocess.run([bin_dir / "camloc", "run", "--json"], cwd=elsewhere, capture_output=True, text=True, env=plain)
    assert run.returncode == 0, run.stderr
    assert (elsewhere / "runs" / "grid-small" / "estimate.tum").is_file()
    assert '"poses": 100' in run.stdout

    example = (
        "import camloc\n"
        "dataset = camloc.load(camloc.bundled_dataset('grid-small'))\n"
        "result = camloc.localize(dataset, camloc.LocalizerConfig(iterations=3))\n"
        "from camloc.metrics import evaluate\n"
        "print(camloc.__file__, evaluate(result)['estimate']['ate']['rmse'])\n"
    )
    library = subprocess.run([bin_dir / "python", "-c", example], cwd=elsewhere, capture_output=True, text=True, env=plain)
    assert library.returncode == 0, library.stderr
    module_file, rmse = library.stdout.split()
    assert Path(module_file).is_relative_to(environment)
    assert 0.0 < float(rmse) < 0.2
