"""Ctrl-C in camloc's commands: one line and exit status 130, never a traceback, wherever it
lands (``run_console_script``; ``camloc.errors.caused_by_interrupt``), and ignored once a command's outcome is
settled (``command_settled``)."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from typing import Callable, Iterator, Optional

from camloc.errors import caused_by_interrupt  # noqa: F401 (the commands import it from here too)

EXIT_INTERRUPTED = 130  # 128 + SIGINT, what shells report for a job stopped by Ctrl-C

# A Ctrl-C that lands while numba loads a kernel from its cache waits, at most this long, for the
# load to end: raised inside one of LLVM's callbacks into Python (the object cache's), the
# KeyboardInterrupt is swallowed there and the process crashes (a segmentation fault, seen about
# once in 300 interrupts at the moment a run loads its kernels). A load takes milliseconds; a
# compile from the sources holds numba's lock for longer, and is interrupted once this has passed.
KERNEL_LOAD_GRACE_SECONDS = 2.0
# How often a deferred Ctrl-C looks again whether the load has ended.
_DEFERRED_RECHECK_SECONDS = 0.02
_deferred_since: Optional[float] = None

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


@contextlib.contextmanager
def outputs_being_saved() -> Iterator[None]:
    """The console script saves a command's outputs (``pipeline.run_dataset``'s ``while_saving``,
    ``simulate``'s world, ``smooth``'s two files) with Ctrl-C ignored, and a save that ends settles
    the command (``command_settled``): a Ctrl-C
    there lets the outputs be written whole and the command say it finished. Before, one that
    landed just after the run folder's rename said "interrupted" over a whole folder (CI,
    2026-12-07). A save takes 1-2 s for 20,000 poses (29 MB). A save that fails restores the
    handler and raises its own error."""
    if not _console_script or threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    except BaseException:
        signal.signal(signal.SIGINT, previous)
        raise
    command_settled()


def run_console_script(load_app: Callable[[], Callable[[], None]]) -> None:
    """Run the app ``load_app()`` returns as the console script.

    A Ctrl-C inside a command ends in ``CamlocGroup.invoke``; one that lands outside it (while
    the commands are imported by ``load_app``, or while the interpreter tidies up after the
    command) ends here, the same way: one line and exit status 130, never a traceback.
    """
    global _console_script
    _console_script = True
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not where Ctrl-C is ignored (a background job)
        signal.signal(signal.SIGINT, _interrupt_outside_kernel_loads)
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


def _interrupt_outside_kernel_loads(signum: int, frame) -> None:
    """The console script's SIGINT handler: Python's own (``KeyboardInterrupt``), except while this
    thread holds numba's compiler lock, where it waits for the lock's release (up to
    ``KERNEL_LOAD_GRACE_SECONDS``) by sending itself the signal again."""
    global _deferred_since
    now = time.monotonic()
    if _holds_numba_compiler_lock():
        if _deferred_since is None:
            _deferred_since = now
        if now - _deferred_since < KERNEL_LOAD_GRACE_SECONDS:
            timer = threading.Timer(_DEFERRED_RECHECK_SECONDS, os.kill, (os.getpid(), signal.SIGINT))
            timer.daemon = True
            timer.start()
            return
    _deferred_since = None
    raise KeyboardInterrupt


def _holds_numba_compiler_lock() -> bool:
    """Whether this thread is inside numba's compiler (loading a kernel from its cache, or
    compiling one); False where numba is not imported (the handler never imports it)."""
    compiler_lock = sys.modules.get("numba.core.compiler_lock")
    if compiler_lock is None:
        return False
    try:
        return bool(compiler_lock.global_compiler_lock.is_locked())
    except Exception:  # numba's lock is not public API: a Ctrl-C must never fail here
        return False
