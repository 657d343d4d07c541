"""numba's cache of the kernels, cleared where it was compiled from other sources than today's.

numba checks a compiled function against its own file only, so a kernel whose callee in another
file changed would keep the callee's old code; ``check_cache`` (called once, by ``_jit``, where
the kernels are defined) compares a digest of all the kernels' sources with the one their cache
was written for. Plain Python: numba is imported only to ask where its cache is.
"""

import hashlib
from pathlib import Path

from camloc.errors import caused_by_interrupt

# Written in the cache folder: the digest of the kernels' sources its files were compiled from.
SOURCE_STAMP = "camloc-kernels-source.sha256"

# The files of the package (beside the kernels' folder) whose values the kernels read: numba
# compiles a global as a constant, so a changed constant must clear the cache too
# (``tests/test_structure.py`` keeps this list to what the kernels import, transitively).
KERNEL_INPUTS = ("constants.py", "errors.py", "measurement.py", "miss_term.py", "sparse_poses.py", "tails.py")


def source_digest(folder: Path) -> str:
    """The SHA-256 of every ``*.py`` file of ``folder`` and of the ``KERNEL_INPUTS`` beside it
    (those that exist), by name order."""
    digest = hashlib.sha256()
    inputs = sorted(folder.glob("*.py")) + [folder.parent / name for name in KERNEL_INPUTS]
    for path in inputs:
        if path.is_file():
            digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


def clear_stale_cache(cache_folder: Path, source_folder: Path) -> bool:
    """Delete numba's cache files of ``source_folder``'s modules from ``cache_folder`` when its
    stamp names other sources than today's, then stamp it; returns whether it cleared anything.
    Silent where the folder cannot be read or written (numba then compiles without caching)."""
    digest = source_digest(source_folder)
    stamp = cache_folder / SOURCE_STAMP
    try:
        if stamp.read_text() == digest:
            return False
    except OSError:
        pass
    modules = {path.stem for path in source_folder.glob("*.py")}
    cleared = False
    try:
        for path in cache_folder.glob("*.nb[ic]"):
            if path.name.split(".", 1)[0] in modules:
                path.unlink()
                cleared = True
        cache_folder.mkdir(parents=True, exist_ok=True)
        stamp.write_text(digest)
    except OSError:
        pass
    return cleared


def _numba_cache_folder() -> Path | None:
    """Where numba caches this package's kernels (beside them, in ``NUMBA_CACHE_DIR`` or in the
    per-user cache), asked of numba's own cache locators; None where that cannot be told."""
    try:
        from numba.core.caching import CacheImpl

        for locator_class in CacheImpl._locator_classes:
            # any function of this folder's files locates the folder's cache
            locator = locator_class.from_function(source_digest, __file__)
            if locator is not None:
                return Path(locator.get_cache_path())
    except Exception as error:  # numba's locators are not public API: never break a run over them
        if caused_by_interrupt(error):  # a Ctrl-C during numba's import can surface as another error
            raise
        return None
    return None


def check_cache() -> Path | None:
    """``clear_stale_cache`` of numba's cache of this folder (called once, by ``_jit``, where the
    kernels are defined: ``types`` and this package import without numba); returns the folder."""
    folder = _numba_cache_folder()
    if folder is not None:
        clear_stale_cache(folder, Path(__file__).parent)
    return folder
