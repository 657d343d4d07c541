"""The beam's width and delta at a pose (``constants.SPARSE_ROWS_PER_DIM``): wider where the
pose's observations barely over-determine the state, and back to the run's before a pose that
does not.

A pose of few observations constrains the state weakly: a wrong explanation of it (one pair
swapped for a neighbouring landmark, the pose shifted to match) costs a few units more than the
right one, and it takes several poses before the right one is clearly cheaper. Pruned to the
default beam in such an episode, the right hypothesis can be lost (issue 35's aerial1 seed 10 and
s3d1 seed 9, 2-7 observations a pose). Few observations also branch little, so a wider beam costs
little there. The extra hypotheses are carried only while the poses stay sparse: a pose of many
observations would explain every one of them (half the poses of a two-camera pixel world are
sparse: explained whole, the 20k pixel world ran 38% slower) and, with many rows, it tells the
right one from the wrong ones by itself; so before such a pose the beam is cut back to the run's
width and delta (``carried``), which is where the default beam would have been.

Scalar and self-contained: the numpy beam (``camloc.beam``) calls them per pose, the compiled one
(``camloc.kernels.beam``) compiles them: one definition for both engines.
"""

from camloc.constants import SPARSE_DELTA_EXTRA, SPARSE_DISTINCT_SIGMA, SPARSE_ROWS_PER_DIM, SPARSE_WIDTH_FACTOR


def is_sparse(rows, state_dim):
    """Whether a pose whose observations give ``rows`` measurement rows (the sum of their degrees of
    freedom) is sparse for a state of ``state_dim`` dimensions: at most ``SPARSE_ROWS_PER_DIM``
    rows per dimension."""
    return rows <= SPARSE_ROWS_PER_DIM * state_dim


def pose_beam(sparse, width, delta):
    """(width, delta) of the beam at a pose, for the run's ``width`` and ``delta``: widened at a
    ``sparse`` one (``is_sparse``), as they are otherwise."""
    if sparse:
        return width * SPARSE_WIDTH_FACTOR, delta + SPARSE_DELTA_EXTRA
    return width, delta


def carried(costs, n, sparse, width, delta):
    """How many of a beam's n hypotheses (``costs`` ascending, the best first) a pose explains: all
    at a ``sparse`` one; at another, the first at most ``width`` within ``delta`` of the best (the
    run's), the extra ones kept at a sparse pose before it dropped. A beam kept at a pose that was
    not sparse is already that, so it is carried whole."""
    if n == 0 or sparse:
        return n
    m = min(n, width)
    while m > 1 and costs[m - 1] > costs[0] + delta:
        m -= 1
    return m


def copy_sigma(cost, best, kept, width, delta, merge_sigma):
    """Within how many standard deviations (on every axis) of a hypothesis kept before it a
    candidate of ``cost`` is dropped as its copy, the beam's best costing ``best`` and ``kept``
    kept so far: ``merge_sigma`` within the run's ``width`` and ``delta``; beyond them (the extra
    ones a sparse pose keeps) ``SPARSE_DISTINCT_SIGMA``: only a hypothesis apart from every one kept,
    another place for the pose, not a variant of a kept one that leaves one of its few
    observations out (those would be explained at the next pose for nothing)."""
    if cost > best + delta or kept >= width:
        return SPARSE_DISTINCT_SIGMA
    return merge_sigma
