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


def compile_deferred_kernels(scene, settings) -> list:
    """Compile the kernels their callers call only where a run reaches them
    (``_jit.called(kernel, deferred=True)``: the beam's chain check, ``beam_chain.checked``, which
    runs only where odometry is noisy enough to branch chains of rays; the re-check's
    ``restored_pairs``), for the types their call sites pass, over ``scene``'s arrays; then any
    other deferred kernel whose call site this process typed (``_jit.compile_deferred``). What a
    compile's second process does last (``camloc.warmup.deferred_kernels``). Returns the kernels."""
    import numpy as np
    from numba import typeof

    from camloc.kernels import _jit, update
    from camloc.kernels.beam_chain import checked
    from camloc.kernels.recheck import restored_pairs

    n = 6                                           # the Euler state's size (the bundled worlds')
    x, P, pairs = np.zeros(n), np.eye(n), np.zeros((2, 2), np.int64)
    chain = (update.pair_model(scene), settings.iterations, x, P, x, P, pairs, np.int64(0), np.int64(2))
    rays = (np.zeros((1, 3)), np.zeros((1, 3, n)), P, np.eye(3)[None].copy(), np.eye(3)[None].copy(), np.ones(1))
    for kernel, arguments in ((checked, chain), (restored_pairs, rays)):
        kernel.compile(tuple(typeof(a) for a in arguments))
    return [checked, restored_pairs] + _jit.compile_deferred()
