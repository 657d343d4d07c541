"""The ``camloc`` typer application. Each command lives in its own module and imports the library
lazily, so ``camloc --help`` does not pay for scipy or matplotlib."""

from __future__ import annotations

import inspect

import typer

from camloc import __version__
from camloc.cli.common import CamlocCommand, CamlocGroup
from camloc.cli.interrupts import run_console_script

app = typer.Typer(
    name="camloc",
    cls=CamlocGroup,
    help="Localize a robot in a known landmark map from g2o odometry and camera observations.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"camloc {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", callback=_print_version, is_eager=True, help="Print the version and exit."
    ),
) -> None:
    """camloc: an Euler-angle EKF localizer with unknown data association."""


def _register_commands() -> None:
    from camloc.cli import commands

    for name, function in commands.COMMANDS:
        app.command(name, cls=CamlocCommand, short_help=_first_paragraph(function.__doc__ or ""))(function)


def _first_paragraph(docstring: str) -> str:
    """A docstring's first paragraph on one line: typer's rich help keeps a command's single line
    breaks in the commands' list, which broke its lines mid-sentence at any terminal width."""
    return " ".join(inspect.cleandoc(docstring).split("\n\n")[0].split())


_register_commands()


def main() -> None:
    """Entry point for ``python -m camloc.cli.app``: the app as the console script runs it
    (``camloc.cli.main``, which also ends a Ctrl-C outside a command)."""
    run_console_script(lambda: app)


if __name__ == "__main__":
    main()
