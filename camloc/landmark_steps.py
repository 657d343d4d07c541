"""How far each landmark goes along its Newton step: a line search per landmark on the
linearized robust cost.

The smoother's Newton Hessian of Huber's cost (``camloc.smoother.normal_equations(newton=True)``)
gives an observation beyond the threshold no curvature along its own residual: its cost there is
a cone, ``2 f |r|``, whose quadratic model is flat along ``r``. A landmark whose observations are
all beyond the threshold and that no prior holds (two observations of a point pulling it apart,
with no map) then lies in a valley that the model sees as nearly flat: the model's minimum is
metres away, past the cones' apexes, where the true cost is far higher (a 3,000-pose world: one
such landmark stepped 0.97 m, its observation from 2.8 to 37 standard deviations, and the whole
step was rejected; docs/performance.md, 2026-12-04 (late)).

Given the poses' step, the landmarks are independent of each other, and each one's cost along its
own step, ``phi_l(alpha) = sum_obs 1/2 rho(|a + alpha b|^2) + sum_prior 1/2 |a + alpha b|^2``
(``a`` the residual moved by the poses' step, ``b`` the landmark step's change, both linearized),
is convex: the step length ``alpha_l`` in [0, 1] that minimizes it is found by bisection on its
derivative. The Newton step already minimizes the Newton model along it (``phi_l'(1)`` is the
model's error there), so a landmark whose model holds keeps ``alpha_l = 1``, and the minimum the
iterations converge to is unchanged: only the path to it.

Pure: no I/O, no printing.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from camloc.measurement import MAX_DIM as OBS_DIM  # an observation's rows (the g2o layout's three)
from camloc.schur import LANDMARK_DOF

# Bisection steps on alpha in [0, 1]: 2^-40 ~ 1e-12.
_BISECTIONS = 40


def row_landmarks(jacobian: sp.csr_matrix, num_pose: int) -> np.ndarray:
    """(rows,) the landmark variable each row of the Jacobian touches (a row touches at most
    one: an observation's or a prior's), -1 where it touches none (odometry, fixed landmarks)."""
    lower = sp.coo_matrix(jacobian[:, num_pose:])
    touched = lower.data != 0.0
    landmark = np.full(jacobian.shape[0], -1, dtype=np.int64)
    landmark[lower.row[touched]] = lower.col[touched] // LANDMARK_DOF
    return landmark


def _slopes(alpha, a_obs, b_obs, obs_landmark, a_prior, b_prior, prior_landmark, huber, count):
    """(count,) each landmark's ``phi_l'(alpha_l)`` at step lengths ``alpha`` (count,)."""
    moved = a_obs + alpha[obs_landmark, None] * b_obs
    s = np.einsum("mi,mi->m", moved, moved)
    weight = np.ones_like(s)  # rho'(s): 1 within the threshold, f / sqrt(s) beyond
    beyond = s > huber * huber  # never with huber = inf (plain least squares)
    weight[beyond] = huber / np.sqrt(s[beyond])
    slope = np.bincount(obs_landmark, weights=weight * np.einsum("mi,mi->m", moved, b_obs), minlength=count)
    moved_prior = a_prior + alpha[prior_landmark] * b_prior
    return slope + np.bincount(prior_landmark, weights=moved_prior * b_prior, minlength=count)


def landmark_step_lengths(residual: np.ndarray, pose_change: np.ndarray, landmark_change: np.ndarray,
                          row_landmark: np.ndarray, first_obs_row: int, num_obs: int, count: int,
                          huber: float) -> np.ndarray:
    """(count,) each landmark's step length in [0, 1] along its Newton step: the minimum of its
    linearized robust cost given the poses' step (module docstring).

    Parameters
    ----------
    residual : (rows,) whitened residuals at the current estimate (odometry, observations, priors).
    pose_change, landmark_change : (rows,) ``J_p delta_p`` and ``J_l delta_l``, the whitened
        residuals' linear change by the step's pose part and by its landmark part.
    row_landmark : (rows,) ``row_landmarks``.
    first_obs_row, num_obs : the observations' rows, ``OBS_DIM`` each from ``first_obs_row``.
    count : landmark variables.
    huber : Huber threshold on each observation's whitened distance.
    """
    a, b = residual + pose_change, landmark_change
    obs = slice(first_obs_row, first_obs_row + OBS_DIM * num_obs)
    obs_landmark = row_landmark[obs].reshape(-1, OBS_DIM).max(axis=1)
    seen = obs_landmark >= 0
    a_obs, b_obs, obs_landmark = a[obs].reshape(-1, OBS_DIM)[seen], b[obs].reshape(-1, OBS_DIM)[seen], obs_landmark[seen]
    prior = np.flatnonzero(row_landmark >= 0)
    prior = prior[prior >= obs.stop]
    a_prior, b_prior, prior_landmark = a[prior], b[prior], row_landmark[prior]
    alpha = np.ones(count)
    # The cost rises at the full step: its minimum along the step is short of it.
    overshoot = _slopes(alpha, a_obs, b_obs, obs_landmark, a_prior, b_prior, prior_landmark, huber, count) > 0.0
    if not np.any(overshoot):
        return alpha
    o, q = overshoot[obs_landmark], overshoot[prior_landmark]  # bisect those landmarks' rows only
    rows = (a_obs[o], b_obs[o], obs_landmark[o], a_prior[q], b_prior[q], prior_landmark[q], huber, count)
    low, high = np.zeros(count), np.ones(count)
    for _ in range(_BISECTIONS):
        middle = 0.5 * (low + high)
        rising = _slopes(middle, *rows) > 0.0
        high = np.where(rising, middle, high)
        low = np.where(rising, low, middle)
    return np.where(overshoot, low, alpha)
