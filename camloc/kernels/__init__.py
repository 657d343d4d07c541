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
for, and clears that cache where they differ (``stale_cache.check_cache``): an install rewrites
every file, but an editable checkout changes one at a time.
"""

import os

from camloc.errors import caused_by_interrupt


def cache_is_warm() -> bool:
    """Whether the main kernels are already compiled in numba's cache (the first run after an
    install compiles them, once: a minute or two); True where that cannot be told."""
    try:
        from camloc.kernels import beam, filtering

        for kernel in (beam.run_poses, filtering.filter_poses):
            if not os.path.exists(kernel._cache._cache_file._index_path):
                return False
    except Exception as error:  # numba's cache layout is not public: never claim a compile that is not one
        if caused_by_interrupt(error):  # a Ctrl-C during numba's import can surface as another error
            raise
        return True
    return True
