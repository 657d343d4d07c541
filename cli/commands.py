"""The list of commands. Each lives in its own module; add one line here per command."""

from __future__ import annotations

from camloc.cli.run import run
from camloc.cli.simulate import simulate

COMMANDS: list = [
    ("run", run),
    ("simulate", simulate),
]
