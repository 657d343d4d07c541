"""Ctrl-C in camloc's commands: one line and exit status 130, never a traceback, wherever it
lands (``run_console_script``, ``caused_by_interrupt``), and ignored once a command's outcome is
settled (``command_settled``)."""

from __future__ import annotations

import signal
import sys
from typing import Callable, Optional

EXIT_INTERRUPTED = 130  # 128 + SIGINT, what shells report for a job stopped by Ctrl-C

# Set by ``run_console_script``: this process is the console script, whose signal handling is its own (not a
# test's CliRunner or a program that calls the app).
_console_script = False


def command_settled() -> None:
    """A command's outcome is settled (outputs written, lines printed, exit status chosen): from
    now on a Ctrl-C changes nothing, so the console script ignores it. Otherwise one that lands
    while the interpreter tears down, after it has given SIGINT back its default action, kills
    the process silently (status -2) after a complete run."""
    if _console_script:
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def caused_by_interrupt(error: Optional[BaseException]) -> bool:
    """Whether ``error`` is a ``KeyboardInterrupt`` or was raised because of one: its chain (the
    causes and contexts Python would print, ``raise ... from None`` cutting it) holds one.

    A Ctrl-C that arrives while numba's compiled code runs is not raised as itself: the kernel's
    dispatcher returns with the interrupt pending and Python raises ``SystemError: CPUDispatcher(...)
    returned a result with an exception set`` (several of them, one per level of compiled calls),
    the ``KeyboardInterrupt`` at the bottom of the chain.
    """
    seen: set[int] = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, KeyboardInterrupt):
            return True
        seen.add(id(error))
        error = error.__cause__ if error.__cause__ is not None else None if error.__suppress_context__ else error.__context__
    return False


def run_console_script(load_app: Callable[[], Callable[[], None]]) -> None:
    """Run the app ``load_app()`` returns as the console script.

    A Ctrl-C inside a command ends in ``CamlocGroup.invoke``; one that lands outside it (while
    the commands are imported by ``load_app``, or while the interpreter tidies up after the
    command) ends here, the same way: one line and exit status 130, never a traceback.
    """
    global _console_script
    _console_script = True
    try:
        app = load_app()
        app()
    except SystemExit as exit_request:
        # typer turns a Ctrl-C outside the command's own call (while it parses the arguments and
        # imports its adapters) into a silent exit status 130; say the one line there too. Our own
        # 130 (``CamlocGroup.invoke``, after its line) cuts the chain, so it is not said twice.
        if exit_request.code == EXIT_INTERRUPTED and caused_by_interrupt(exit_request.__context__):
            sys.stderr.write("interrupted\n")
        raise
    except BaseException as error:
        if not caused_by_interrupt(error):
            raise
        sys.stderr.write("interrupted\n")
        sys.exit(EXIT_INTERRUPTED)
