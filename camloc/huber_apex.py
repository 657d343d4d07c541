"""Which observations a Newton step of the robust cost carries past the apex of their cone.

Beyond the Huber threshold an observation's cost is a cone, ``rho = 2 f |r| - f^2`` of its
whitened residual r. The smoother's Newton Hessian (``camloc.smoother.normal_equations(newton=True)``)
is that cone's second-order model at r: a constant pull ``f u`` along ``u = r / |r|`` and no
curvature along it. The model holds while the step keeps the residual on its own side of the
apex; a step that changes it by ``J delta`` with ``|r| + u . J delta < 0`` has crossed the apex,
where the cone rises again and the model keeps falling, by ``2 f`` times the distance past it.
Where nothing else holds the unknowns that move along u (no map: a few poses and the landmarks
they alone see), the Newton step follows that pull until the odometry stops it: on the 20,000-pose
3-D world with no map, observations at 2-6 standard deviations were taken 10-140 past their apex,
five Newton steps in a row were rejected for it (docs/performance.md, 2026-12-05).

The IRLS rows of such an observation (``rho' J^T J``, ``normal_equations``' ``majorized``) put
back the cone's curvature along u at r, ``f / |r|``: along u their model is lowest exactly at the
apex. ``camloc.smoother`` solves the step again with those rows for the observations the Newton
step carried past their apex (the rest keep the Newton rows, which converge quadratically).

Pure: no I/O, no printing.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from camloc.measurement import MAX_DIM as OBS_DIM  # an observation's rows (the g2o layout's three)


def past_apex(residual: np.ndarray, jacobian: sp.csr_matrix, step: np.ndarray, first_obs_row: int,
              obs_sq: np.ndarray, huber: float) -> np.ndarray:
    """(M,) bool: the observations beyond the Huber threshold whose linearized residual the step
    takes past the apex of their cone, ``|r| + u . J delta < 0`` (``r . (r + J delta) < 0``).

    Parameters
    ----------
    residual : (rows,) whitened residuals (odometry, then ``OBS_DIM`` rows per observation, ...).
    jacobian : (rows, unknowns) their Jacobian.
    step : (unknowns,) the step.
    first_obs_row : the first observation's row.
    obs_sq : (M,) each observation's squared whitened distance.
    huber : Huber threshold on the whitened distance.
    """
    rows = slice(first_obs_row, first_obs_row + OBS_DIM * len(obs_sq))
    r = residual[rows].reshape(-1, OBS_DIM)
    change = (jacobian @ step)[rows].reshape(-1, OBS_DIM)
    beyond = obs_sq > huber * huber  # never with huber = inf (plain least squares)
    return beyond & (obs_sq + np.einsum("mi,mi->m", r, change) < 0.0)
