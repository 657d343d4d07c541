"""The one exception family of camloc.

Every error a user can cause (a bad file, a bad option) is a ``CamlocError``; the CLI turns it into
one line on stderr and exit status 2. Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional


class CamlocError(Exception):
    """An error caused by the input or the options, with a message meant for the user."""


class DatasetError(CamlocError):
    """A dataset file that cannot be read: where (``path:line``) and why.

    Parameters
    ----------
    path : the file.
    line : 1-based line number, or None when the problem is not tied to one line.
    reason : what was expected and what was found.
    """

    def __init__(self, path: str | Path, line: int | None, reason: str):
        self.path = str(path)
        self.line = line
        self.reason = reason
        where = f"{self.path}:{line}" if line is not None else self.path
        super().__init__(f"{where}: {reason}")


class ConfigError(CamlocError):
    """An option or configuration value that is out of range or inconsistent."""


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
