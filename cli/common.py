"""Shared pieces of the command line: consoles and the one place errors become exit status 2."""

from __future__ import annotations

import functools
from typing import Callable, TypeVar

import typer
from rich.console import Console
from rich.markup import escape

from camloc.errors import CamlocError

console = Console()
err_console = Console(stderr=True)

F = TypeVar("F", bound=Callable)

EXIT_BAD_INPUT = 2


def handles_errors(command: F) -> F:
    """Turn a ``CamlocError`` raised by a command into one red line on stderr and exit status 2."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except CamlocError as error:
            err_console.print(f"[bold red]error:[/] {escape(str(error))}", markup=True, highlight=False, soft_wrap=True)
            raise typer.Exit(EXIT_BAD_INPUT) from None

    return wrapper  # type: ignore[return-value]
