"""Writing files whole or not at all, and the folders they go in: every output of camloc goes
through here (run folders, datasets, figures, reports).

``atomic_write`` (a temporary sibling renamed into place only on success), ``write_text_atomic``
for text, ``write_files_atomic`` for a set of files (all or none), ``make_folder`` for missing
parents and ``refuse_existing`` for a user's file that ``--force`` alone may replace.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import IO, Callable, Iterator, Sequence

from camloc.errors import CamlocError


@contextlib.contextmanager
def atomic_write(path: str | Path, *, binary: bool = False) -> Iterator[IO]:
    """Open a temporary sibling of ``path`` for writing; it replaces ``path`` only on success.

    The temporary file lives in the same directory so that ``os.replace`` is a rename on one
    file system; on any exception it is removed and ``path`` keeps its old content (or stays
    absent).

    Parameters
    ----------
    path : the file to (re)write; missing parent folders are created.
    binary : open in ``"wb"`` instead of ``"w"`` (UTF-8 text, ``"\n"`` newlines).
    """
    path = Path(path)
    tmp = _temporary_sibling(path)
    try:
        with naming_the_output(path), _open_for_writing(tmp, binary) as handle:
            yield handle
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


@contextlib.contextmanager
def naming_the_output(path: str | Path) -> Iterator[None]:
    """Turn an OSError that names no file (a full disk: ``write`` and ``close`` say only "No space
    left on device") into ``cannot write <path>: <reason>``, the output the user asked for.

    Raises
    ------
    CamlocError : ``cannot write <path>: <reason>``.
    """
    try:
        yield
    except OSError as error:
        if error.filename is not None:
            raise  # it names its file already (cli.common.describe_os_error says which)
        raise CamlocError(f"cannot write {path}: {error.strerror or error}") from None


def make_folder(folder: str | Path) -> None:
    """Create ``folder`` and its missing parents (every command's outputs go through here).

    Raises
    ------
    CamlocError : ``cannot create the folder <folder>: <reason>``.
    """
    try:
        Path(folder).mkdir(parents=True, exist_ok=True)
    except OSError as error:
        blocker = _file_in_the_way(Path(folder))
        reason = f"{blocker} is a file, not a folder" if blocker is not None else error.strerror or error
        raise CamlocError(f"cannot create the folder {folder}: {reason}") from None


def _file_in_the_way(folder: Path) -> Path | None:
    """The nearest of ``folder`` and its parents that exists and is not a folder (whose "File
    exists" or "Not a directory" alone does not say which path is in the way), or None."""
    for candidate in (folder, *folder.parents):
        if candidate.exists():
            return None if candidate.is_dir() else candidate
    return None


def refuse_existing(path: str | Path, *, force: bool) -> None:
    """Refuse to replace an existing ``path`` unless ``force``: a user's file is never overwritten
    by accident (the course dataset, a figure, a report).

    Raises
    ------
    CamlocError : ``<path>: already exists; refusing to replace it without --force``.
    """
    path = Path(path)
    if not force and (path.exists() or path.is_symlink()):
        raise CamlocError(f"{path}: already exists; refusing to replace it without --force")


def refuse_existing_file(path: str | Path, *, force: bool) -> None:
    """``refuse_existing`` for an output file: a folder in its place is refused first, with
    ``force`` or without (a file cannot replace a folder, and ``--force`` would not help).

    Raises
    ------
    CamlocError : ``<path>: is a folder; ...``, or ``refuse_existing``'s.
    """
    check_replaceable(path)
    refuse_existing(path, force=force)


def check_replaceable(path: str | Path) -> None:
    """Refuse an output file's path where a folder, a device, a pipe or a socket is: a file renamed
    onto it would replace it, with ``--force`` or without (run as root, ``-o /dev/null`` replaced
    the system's null device with a regular file).

    Raises
    ------
    CamlocError : ``<path>: is a folder; ...`` or ``<path>: is a device, a pipe or a socket; ...``.
    """
    path = Path(path)
    if path.is_dir():
        raise CamlocError(f"{path}: {FOLDER_FOR_A_FILE}")
    if path.exists() and not path.is_file():
        raise CamlocError(f"{path}: is a device, a pipe or a socket, which camloc never replaces; expected the path "
                          "of a file to write")


FOLDER_FOR_A_FILE = "is a folder; expected the path of a file to write"


def _temporary_sibling(path: Path) -> Path:
    """A new empty hidden file beside ``path``, readable like any output (mkstemp makes 0600)."""
    check_replaceable(path)  # a file cannot replace a folder or a device, even with --force
    make_folder(path.parent)
    try:
        fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as error:
        raise CamlocError(f"cannot write {path}: {error.strerror or error}") from None
    os.close(fd)
    os.chmod(tmp_name, 0o644)
    return Path(tmp_name)


def _open_for_writing(path: Path, binary: bool) -> IO:
    if binary:
        return path.open("wb")
    return path.open("w", encoding="utf-8", newline="")


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` whole or not at all (temporary file + ``os.replace``)."""
    with atomic_write(path) as handle:
        handle.write(text)


def write_files_atomic(paths: Sequence[str | Path], write: Callable[[Path, IO[bytes]], None]) -> None:
    """Write every file of ``paths``, or none of them.

    ``write(path, handle)`` fills each file's hidden temporary sibling (opened ``"wb"``); only
    when every one of them is complete are they renamed into place, one after the other. On any
    failure the temporaries are removed and every path keeps its old content (or stays absent).

    Raises
    ------
    CamlocError : a folder or a temporary file cannot be created.
    """
    staged: list[tuple[Path, Path]] = []
    try:
        for path in map(Path, paths):
            staged.append((_temporary_sibling(path), path))
            with naming_the_output(path), _open_for_writing(staged[-1][0], binary=True) as handle:
                write(path, handle)
        for tmp, path in staged:
            os.replace(tmp, path)
    except BaseException:
        for tmp, _ in staged:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        raise
