"""The compiled kernels of the filter step (numba), over plain arrays, one module per concern:

- ``rotation``: Euler angles, the rate matrix E, retraction and difference of the Euler state;
- ``motion``: prediction with its Jacobians;
- ``camera``: the camera model with its Jacobians, back-projection;
- ``sym3``, ``small``: closed-form 3x3 algebra and loop products of small matrices;
- ``view``: the grid hash of the map and the view query;
- ``update``: the stacked, iterated update in information form;
- ``recheck``: leave-one-out costs and assignment margins;
- ``beam``: the beam over association hypotheses; ``seeds``: the slip search's seed ranking;
- ``filtering``: the filter's pass over the poses with known pairs.

Every kernel is ``@jit`` (``_jit``: cached, numba's numpy error model) and has a numpy twin that
the tests compare it with (``tests/test_kernels.py``).

numba's cache checks a compiled function against its own file only: a kernel whose callee in
another file changed would keep the callee's old code (and an inlined step's). So the first
import of the kernels compares a digest of all their sources with the one their cache was written
for, and clears that cache where they differ (``check_cache``): an install rewrites every file,
but an editable checkout changes one at a time.
"""

import hashlib
import os
from pathlib import Path

# Written in the cache folder: the digest of the kernels' sources its files were compiled from.
SOURCE_STAMP = "camloc-kernels-source.sha256"


def source_digest(folder: Path) -> str:
    """The SHA-256 of every ``*.py`` file of ``folder``, by name order."""
    digest = hashlib.sha256()
    for path in sorted(folder.glob("*.py")):
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
    except Exception:  # numba's locators are not public API: never break a run over them
        return None
    return None


def check_cache() -> Path | None:
    """``clear_stale_cache`` of numba's cache of this folder (called once, by ``_jit``, where the
    kernels are defined: ``types`` and this package import without numba); returns the folder."""
    folder = _numba_cache_folder()
    if folder is not None:
        clear_stale_cache(folder, Path(__file__).parent)
    return folder


def cache_is_warm() -> bool:
    """Whether the main kernels are already compiled in numba's cache (the first run after an
    install compiles them, once: a minute or two); True where that cannot be told."""
    try:
        from camloc.kernels import beam, filtering

        for kernel in (beam.run_poses, filtering.filter_poses):
            if not os.path.exists(kernel._cache._cache_file._index_path):
                return False
    except Exception:  # numba's cache layout is not public: never claim a compile that is not one
        return True
    return True
