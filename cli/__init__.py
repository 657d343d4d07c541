"""The camloc command line: thin typer commands that wire options to library calls.

This module is the console script's entry point (``main``) and imports nothing heavy, so that a
Ctrl-C while the commands are still being imported ends like one during a command.
"""

from __future__ import annotations

from camloc.cli.interrupts import run_console_script


def main() -> None:
    """Console-script entry point: the ``camloc`` app, whose commands are imported inside
    ``run_console_script``, so that a Ctrl-C while they are still being imported ends like one
    during a command."""
    run_console_script(_load_app)


def _load_app():
    from camloc.cli.app import app

    return app
