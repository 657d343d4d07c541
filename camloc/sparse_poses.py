"""The beam's width and delta at a pose (``constants.SPARSE_ROWS_PER_DIM``): wider where the
pose's observations barely over-determine the state.

A pose of few observations constrains the state weakly: a wrong explanation of it (one pair
swapped for a neighbouring landmark, the pose shifted to match) costs a few units more than the
right one, and it takes several poses before the right one is clearly cheaper. Pruned to the
default beam in such an episode, the right hypothesis can be lost (issue 35's aerial1 seed 10 and
s3d1 seed 9, 2-7 observations a pose). Few observations also branch little, so a wider beam costs
little there; at a pose of many observations the beam stays as it is (a wider one everywhere lets
more whole-view aliases of a dense map survive).

Scalar and self-contained: the numpy beam (``camloc.beam``) calls it per pose, the compiled one
(``camloc.kernels.beam``) compiles it: one definition for both engines.
"""

from camloc.constants import SPARSE_DELTA_EXTRA, SPARSE_ROWS_PER_DIM, SPARSE_WIDTH_FACTOR


def pose_beam(rows, state_dim, width, delta):
    """(width, delta) of the beam at a pose whose observations give ``rows`` measurement rows (the
    sum of their degrees of freedom), for a state of ``state_dim`` dimensions and the run's
    ``width`` and ``delta``: widened at a sparse pose (at most ``SPARSE_ROWS_PER_DIM`` rows per
    dimension of the state), as they are otherwise."""
    if rows <= SPARSE_ROWS_PER_DIM * state_dim:
        return width * SPARSE_WIDTH_FACTOR, delta + SPARSE_DELTA_EXTRA
    return width, delta
