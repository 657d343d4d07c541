"""The one place the kernels' numba options live: every kernel is ``@jit``, never a bare
``numba.njit``, so that caching and the error model are never retyped (``tests/test_kernels.py``
checks that every compiled function of this package carries them).

``cache=True`` writes the compiled code beside the source, or, where that folder is not writable
(a system-wide install), in numba's per-user cache directory (``NUMBA_CACHE_DIR`` overrides both).
"""

from __future__ import annotations

from functools import partial

import numba

from camloc.kernels import check_cache

# numba's cache of these kernels, cleared first where any kernel's source changed since it was written
CACHE_FOLDER = check_cache()

OPTIONS = dict(cache=True, nogil=True, error_model="numpy")

jit = partial(numba.njit, **OPTIONS)

# A step of a larger kernel, called only from compiled code, whose body numba copies into its
# callers: numba compiles every other function on its own, with the code of everything it calls
# optimized and generated once more, so that a deep call tree costs its depth times its size
# to compile. Inlining the middle of the tree (the beam's steps) cut the first compile 140 -> 120 s.
# A step called from several places (the beam's settle and options_of) is a plain ``jit`` again:
# inlined, its body was copied into every site (``explain_all`` 12-13 -> 8 s of its own to compile).
inlined = partial(numba.njit, inline="always", **OPTIONS)
