"""The landmarks' step lengths along a Newton step (``camloc.landmark_steps``): each one the
minimum over [0, 1] of that landmark's own linearized robust cost, against a dense search written
here; a landmark whose full step lowers its cost keeps it."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from camloc.landmark_steps import landmark_step_lengths, row_landmarks
from camloc.smoother import huber_rho

HUBER = 2.0


def _landmark_cost(alpha, a, b, obs_landmark, a_prior, b_prior, prior_landmark, j):
    """Landmark j's linearized robust cost at step length alpha, written plainly."""
    cost = 0.0
    for o in np.flatnonzero(obs_landmark == j):
        moved = a[o] + alpha * b[o]
        cost += 0.5 * float(huber_rho(np.array([moved @ moved]), HUBER)[0])
    for p in np.flatnonzero(prior_landmark == j):
        cost += 0.5 * (a_prior[p] + alpha * b_prior[p]) ** 2
    return cost


def _random_rows(rng, num_odom_rows, num_obs, num_landmarks, num_prior_rows):
    """Rows laid out as the smoother's: odometry (no landmark), observations (3 rows each, one
    landmark or none), priors (one landmark a row)."""
    obs_landmark = rng.integers(-1, num_landmarks, num_obs)
    prior_landmark = rng.integers(0, num_landmarks, num_prior_rows)
    row_landmark = np.concatenate([np.full(num_odom_rows, -1), np.repeat(obs_landmark, 3), prior_landmark])
    rows = row_landmark.size
    residual = rng.normal(scale=3.0, size=rows)
    pose_change = rng.normal(scale=0.5, size=rows)
    landmark_change = np.where(row_landmark >= 0, rng.normal(scale=4.0, size=rows), 0.0)
    return row_landmark, residual, pose_change, landmark_change, obs_landmark, prior_landmark


@pytest.mark.parametrize("trial", range(4))
def test_each_step_length_minimizes_its_landmarks_cost(rng, trial):
    num_odom_rows, num_obs, count, num_prior_rows = 9, 40, 6, 5
    row_landmark, residual, pose_change, landmark_change, obs_landmark, prior_landmark = _random_rows(
        rng, num_odom_rows, num_obs, count, num_prior_rows)
    alpha = landmark_step_lengths(residual, pose_change, landmark_change, row_landmark, num_odom_rows, num_obs, count, HUBER)
    a = (residual + pose_change)[num_odom_rows:num_odom_rows + 3 * num_obs].reshape(-1, 3)
    b = landmark_change[num_odom_rows:num_odom_rows + 3 * num_obs].reshape(-1, 3)
    prior = slice(num_odom_rows + 3 * num_obs, None)
    args = (a, b, obs_landmark, (residual + pose_change)[prior], landmark_change[prior], prior_landmark)
    grid = np.linspace(0.0, 1.0, 401)  # alpha minimizes a convex cost: no grid point lies below it
    for j in range(count):
        costs = np.array([_landmark_cost(t, *args, j) for t in grid])
        assert np.all((alpha >= 0.0) & (alpha <= 1.0))
        assert _landmark_cost(alpha[j], *args, j) <= costs.min() + 1e-6, j
        if costs[-1] <= costs.min() + 1e-12:  # the full step is the minimum: kept whole
            assert alpha[j] == 1.0


def test_a_landmark_whose_observations_are_inliers_keeps_its_newton_step(rng):
    """Within the Huber threshold the cost is the Newton model's quadratic, whose minimum along
    the landmark's Newton step (given the poses' step) is the full step."""
    J = rng.normal(size=(6, 3))
    r = rng.normal(scale=0.2, size=6)
    step = -np.linalg.solve(J.T @ J, J.T @ r)  # the landmark's Newton step, two observations
    alpha = landmark_step_lengths(r, np.zeros(6), J @ step, np.zeros(6, dtype=np.int64), 0, 2, 1, HUBER)
    for at in (r, r + J @ step):  # each observation inside the threshold at both ends, so all along
        assert np.all(np.linalg.norm(at.reshape(2, 3), axis=1) < HUBER)
    assert alpha[0] == pytest.approx(1.0, abs=1e-9)


def test_row_landmarks_reads_the_landmark_columns():
    num_pose = 6
    J = sp.csr_matrix(np.array([[1.0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0],      # odometry
                                [0, 1.0, 0, 0, 0, 0, 0, 0, 2.0, 0, 0, 0],    # landmark 0
                                [0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 3.0, 0],    # landmark 1
                                [0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 5.0]]))    # a prior on landmark 1
    assert row_landmarks(J, num_pose).tolist() == [-1, 0, 1, 1]
