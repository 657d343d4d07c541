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

Only rays make a pose sparse (``sparse_poses``): a pixel's model has no inverse, a ray that
places its landmark nowhere along it, and a few of them barely fix the pose; a point-giving
observation (depth, disparity, a tag, a planar point or marker: a model with an inverse) places
its landmark from one pose, tells the right pairing from a neighbour's by itself, and on depth data
the wider beam only moved a run (``hard_worlds.py``'s smooth3d-clutter40-jump, 0.0970 -> 0.1000 m).
So a pose with any point-giving observation is not sparse, whatever its rows, and neither is a
pose without observations (the beam passes it unexplained and unpruned in both engines), which
leaves every run without rays as it was.

``sparse_poses`` decides every pose of a run at its start, once, for both engines (the numpy beam,
``camloc.beam``, and the compiled one, ``camloc.kernels.beam``, read its array); the scalar
functions after it are compiled into the compiled one as they are: one definition of each.
"""

import numpy as np

from camloc import measurement
from camloc.constants import SPARSE_DELTA_EXTRA, SPARSE_DISTINCT_SIGMA, SPARSE_ROWS_PER_DIM, SPARSE_WIDTH_FACTOR


def sparse_poses(kinds: np.ndarray, pose_start: np.ndarray, state_dim: int) -> np.ndarray:
    """(N,) bool: which poses are sparse for a state of ``state_dim`` dimensions, of observations
    of kind codes ``kinds`` (K,) in pose order, pose k's ``kinds[pose_start[k]:pose_start[k + 1]]``
    (``pose_start`` (N + 1,)): those of at least one observation, all of them rays
    (``measurement.is_ray``), whose measurement rows (the sum of their degrees of freedom) are at
    most ``SPARSE_ROWS_PER_DIM`` per dimension."""
    kinds = np.asarray(kinds, dtype=np.int64)
    ray = measurement.is_ray(kinds)
    # per pose, by differences of running sums (a pose without observations gives 0 and 0)
    ray_rows = np.diff(np.concatenate([[0], np.cumsum(np.where(ray, measurement.dof_of(kinds), 0))])[pose_start])
    points = np.diff(np.concatenate([[0], np.cumsum(~ray)])[pose_start])
    return (points == 0) & (ray_rows > 0) & (ray_rows <= SPARSE_ROWS_PER_DIM * state_dim)


def pose_beam(sparse, width, delta):
    """(width, delta) of the beam at a pose, for the run's ``width`` and ``delta``: widened at a
    ``sparse`` one (``sparse_poses``), as they are otherwise."""
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
