"""Retraction and difference of the filter's state, whichever model it is: the model's kernel
picked by the state's size (6: the Euler state, ``camloc.kernels.rotation``; 3: the planar one,
``camloc.kernels.planar``). The algorithm's kernels call these and size their arrays by the state
(``x.shape[0]``), so that one compiled algorithm runs both models. The dispatch is inlined: an
iterated update retracts and differences at every step, where a call's own cost (counting a
reference to each array it is passed) would be as large as the arithmetic."""

from __future__ import annotations

import numpy as np

from camloc.constants import CONVERGED
from camloc.kernels._jit import entry, inlined, jit
from camloc.kernels.planar import SE2_DIM, planar_difference_into, planar_retract_into
from camloc.kernels.rotation import difference_into as euler_difference_into
from camloc.kernels.rotation import retract_into as euler_retract_into


@jit
def retract(x, delta):
    """The state x moved by the error delta (x (+) delta), of x's model."""
    out = np.empty(x.shape[0])
    retract_into(x, delta, out)
    return out


@inlined
def retract_into(x, delta, out):
    """``retract`` written into out (not x or delta)."""
    if x.shape[0] == SE2_DIM:
        planar_retract_into(x, delta, out)
    else:
        euler_retract_into(x, delta, out)


@entry
def difference(a, b):
    """The error from b to a (a (-) b), of their model."""
    d = np.empty(a.shape[0])
    difference_into(a, b, d)
    return d


@inlined
def difference_into(a, b, d):
    """``difference`` written into d."""
    if a.shape[0] == SE2_DIM:
        planar_difference_into(a, b, d)
    else:
        euler_difference_into(a, b, d)


@inlined
def stepped_into(x, step, last_step, x_i, P, step_sigma):
    """An iterated update's linearization step: x_i = x [+] step, last_step (n,) replaced by step;
    whether the linearization no longer moves (the step changed by under ``CONVERGED``, or each
    entry by under ``step_sigma`` of the prior's sigma, ``ekf._iterate``)."""
    retract_into(x, step, x_i)
    change = 0.0
    negligible = True
    for b in range(x.shape[0]):
        moved_b, last_step[b] = step[b] - last_step[b], step[b]
        change = max(change, abs(moved_b))
        negligible = negligible and moved_b * moved_b < step_sigma * step_sigma * P[b, b]
    return change < CONVERGED or negligible
