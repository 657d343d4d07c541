"""The list of commands. Each lives in its own module; add one line here per command."""

from __future__ import annotations

from camloc.cli.eval import evaluate_command
from camloc.cli.info import info
from camloc.cli.plot import plot
from camloc.cli.run import run
from camloc.cli.simulate import simulate
from camloc.cli.smooth import smooth
from camloc.cli.sweep import sweep

COMMANDS: list = [
    ("info", info),
    ("run", run),
    ("eval", evaluate_command),
    ("plot", plot),
    ("simulate", simulate),
    ("smooth", smooth),
    ("sweep", sweep),
]
