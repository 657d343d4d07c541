"""Association primitives: candidate search against brute force, pair statistics, best friends."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from camloc import association, geometry


def test_candidates_match_a_brute_force_scan(rng):
    landmarks = rng.uniform(-20, 20, size=(5000, 3))
    tree = cKDTree(landmarks)
    for _ in range(10):
        T_world_camera = geometry.pose_from_euler(np.r_[rng.uniform(-10, 10, 3), rng.uniform(-1, 1, 3)])
        found = association.candidate_indices(tree, landmarks, T_world_camera, min_depth=0.3, max_depth=6.0, max_angle_rad=np.radians(50))
        p = (landmarks - T_world_camera[:3, 3]) @ T_world_camera[:3, :3]
        visible = (p[:, 2] > 0.3) & (p[:, 2] < 6.0) & (np.hypot(p[:, 0], p[:, 1]) <= p[:, 2] * np.tan(np.radians(50)))
        assert set(found.tolist()) == set(np.flatnonzero(visible).tolist())
        assert visible.sum() > 0


def test_pair_statistics_match_direct_formula(rng):
    z, z_hat = rng.normal(size=(3, 3)), rng.normal(size=(4, 3))
    R_obs = np.stack([np.diag(rng.uniform(0.1, 1, 3)) for _ in range(3)])
    A = rng.normal(size=(4, 3, 3))
    HPH = A @ np.swapaxes(A, 1, 2)
    d2, nll = association.pair_statistics(z, R_obs, z_hat, HPH)
    for i in range(3):
        for j in range(4):
            S = HPH[j] + R_obs[i]
            y = z[i] - z_hat[j]
            assert d2[i, j] == pytest.approx(y @ np.linalg.solve(S, y))
            assert nll[i, j] == pytest.approx(d2[i, j] + np.log(np.linalg.det(S)))


def test_best_friends_requires_mutual_best_gate_and_margin():
    cost = np.array([
        [1.0, 5.0, 9.0],    # obs 0 <-> cand 0: mutual, clear
        [8.0, 2.0, 2.5],    # obs 1 -> cand 1, but cand 2 is within the margin
        [9.0, 9.0, 3.0],    # obs 2 -> cand 2; cand 2's best is obs 1? no: obs 1 costs 2.5 < 3.0
    ])
    d2 = cost.copy()
    rows, cols, gap = association.best_friends(cost, d2, gate=10.0, margin=1.0)
    assert rows.tolist() == [0] and cols.tolist() == [0]
    assert gap[0] == pytest.approx(4.0)
    # without the margin obs 1 pairs with cand 1; obs 2 still is not cand 2's best friend
    rows, cols, _ = association.best_friends(cost, d2, gate=10.0, margin=0.0)
    assert list(zip(rows.tolist(), cols.tolist())) == [(0, 0), (1, 1)]
    # the gate rejects even a mutual best pair
    rows, _, _ = association.best_friends(cost, d2, gate=0.5, margin=0.0)
    assert rows.size == 0


def test_best_friends_on_empty_inputs():
    rows, cols, gap = association.best_friends(np.zeros((0, 3)), np.zeros((0, 3)), gate=1.0, margin=0.0)
    assert rows.size == cols.size == gap.size == 0
