"""The camloc command line: thin typer commands that wire options to library calls.

This module is the console script's entry point (``main``) and imports nothing heavy, so that a
Ctrl-C while the commands are still being imported ends like one during a command.
"""

from __future__ import annotations

import os

# camloc's matrices are small (6x6 poses, a few hundred rows of a mapping run's state): BLAS
# threads cost more to wake than they save, and on a busy machine far more (the mapping tests:
# 51 s with OpenBLAS's threads on two loaded cores, 10 s with one). Set before numpy loads; a
# user's own setting wins.
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

from camloc.cli.interrupts import run_console_script  # noqa: E402 (after the environment above)


def main() -> None:
    """Console-script entry point: the ``camloc`` app, whose commands are imported inside
    ``run_console_script``, so that a Ctrl-C while they are still being imported ends like one
    during a command."""
    run_console_script(_load_app)


def _load_app():
    from camloc.cli.app import app

    return app
