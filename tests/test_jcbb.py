"""Joint compatibility branch and bound on hand-made cases with a known answer."""

import numpy as np
import pytest

from camloc.jcbb import jcbb, joint_nis


def shifted_world(shift):
    """Two landmarks 0.2 apart along u; the pose error is shared (P large along u) and both
    observations are displaced by the same ``shift``: the swap is individually plausible, the joint
    test tells the pairing apart."""
    z_hat = np.array([[0.0, 0.0, 1.0], [0.2, 0.0, 1.0]])
    H = np.zeros((2, 3, 6))
    H[:, 0, 0] = H[:, 1, 1] = H[:, 2, 2] = 1.0   # z = landmark prediction + state offset
    P = np.diag([0.1**2, 0.01**2, 0.01**2, 1e-6, 1e-6, 1e-6])
    R = np.stack([np.eye(3) * 0.01**2] * 2)
    z = z_hat + np.array([shift, 0.0, 0.0])
    y_all = z[:, None, :] - z_hat[None, :, :]
    return y_all, H, P, R


def individually_compatible(y_all, H, P, R, gate=11.34):
    n, m = y_all.shape[:2]
    return np.array([[joint_nis([(i, j)], y_all, H, P, R) <= gate for j in range(m)] for i in range(n)])


def test_joint_test_refuses_a_swap_that_each_pair_allows():
    y_all, H, P, R = shifted_world(0.1)
    compatible = individually_compatible(y_all, H, P, R)
    assert compatible.all()  # every pairing, the swap included, passes on its own
    assert joint_nis([(0, 1), (1, 0)], y_all, H, P, R) > joint_nis([(0, 0), (1, 1)], y_all, H, P, R) + 50
    result = jcbb(y_all, H, P, R, compatible)
    assert result.assignment.tolist() == [0, 1]
    assert result.exhaustive


def test_seed_that_pairs_everything_consistently_is_taken_without_search():
    y_all, H, P, R = shifted_world(0.05)
    result = jcbb(y_all, H, P, R, individually_compatible(y_all, H, P, R), seed=[(0, 0), (1, 1)])
    assert result.assignment.tolist() == [0, 1] and result.nodes == 1


def test_an_observation_without_a_compatible_landmark_stays_unpaired():
    y_all, H, P, R = shifted_world(0.0)
    compatible = individually_compatible(y_all, H, P, R)
    compatible[1] = False
    result = jcbb(y_all, H, P, R, compatible)
    assert result.assignment.tolist() == [0, -1]


def test_node_bound_is_reported(rng):
    n, m = 8, 8
    y_all = rng.normal(scale=0.01, size=(n, m, 3))
    H = np.tile(np.eye(3, 6), (m, 1, 1))
    P = np.eye(6) * 1e-2
    R = np.stack([np.eye(3)] * n)
    result = jcbb(y_all, H, P, R, np.ones((n, m), dtype=bool), max_nodes=50)
    assert not result.exhaustive and result.nodes == 50
    assert (result.assignment >= 0).sum() >= 1


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_result_is_jointly_compatible_and_maximal_on_random_cases(seed):
    rng = np.random.default_rng(seed)
    n, m = 4, 5
    z_hat = rng.uniform(0, 1, (m, 3))
    truth = rng.permutation(m)[:n]
    H = np.tile(np.eye(3, 6), (m, 1, 1))
    P = np.eye(6) * 1e-4
    R = np.stack([np.eye(3) * 1e-4] * n)
    z = z_hat[truth] + rng.normal(scale=0.01, size=(n, 3))
    y_all = z[:, None, :] - z_hat[None, :, :]
    compatible = individually_compatible(y_all, H, P, R)
    result = jcbb(y_all, H, P, R, compatible)
    assert result.assignment.tolist() == truth.tolist()


def test_a_landmark_that_is_a_candidate_of_two_sensors_is_paired_once():
    """One camera of depth and pixel records is two sensors, each with its own candidate column of
    a landmark both may see: two observations, one of each sensor, may each fit their column, but
    a landmark is one of them at most."""
    y_all, H, P, R = shifted_world(0.0)
    compatible = np.array([[True, False], [False, True]])  # each observation its own sensor's column
    assert jcbb(y_all, H, P, R, compatible).assignment.tolist() == [0, 1]  # two landmarks: both paired
    same = jcbb(y_all, H, P, R, compatible, landmark_of=np.array([7, 7]))
    assert sorted(same.assignment.tolist()) in ([-1, 0], [-1, 1])
    assert same.exhaustive
