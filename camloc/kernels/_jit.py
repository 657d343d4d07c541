"""The one place the kernels' numba options live: every kernel is ``@jit``, never a bare
``numba.njit``, so that caching and the error model are never retyped (``tests/test_kernels.py``
checks that every compiled function of this package carries them).

``cache=True`` writes the compiled code beside the source, or, where that folder is not writable
(a system-wide install), in numba's per-user cache directory (``NUMBA_CACHE_DIR`` overrides both).
"""

from __future__ import annotations

from functools import partial

import numba

OPTIONS = dict(cache=True, nogil=True, error_model="numpy")

jit = partial(numba.njit, **OPTIONS)
