"""Association primitives: candidate search against brute force, pair statistics, best friends."""

import warnings

import numpy as np
import pytest

from camloc import association, geometry, observation_space


def test_candidates_match_a_brute_force_scan(rng):
    landmarks = rng.uniform(-20, 20, size=(5000, 3))
    index = association.PointIndex(landmarks)
    for _ in range(10):
        T_world_camera = geometry.pose_from_euler(np.r_[rng.uniform(-10, 10, 3), rng.uniform(-1, 1, 3)])
        found = association.candidate_indices(index, landmarks, T_world_camera, min_depth=0.3, max_depth=6.0, max_angle_rad=np.radians(50))
        p = (landmarks - T_world_camera[:3, 3]) @ T_world_camera[:3, :3]
        visible = (p[:, 2] > 0.3) & (p[:, 2] < 6.0) & (np.hypot(p[:, 0], p[:, 1]) <= p[:, 2] * np.tan(np.radians(50)))
        assert set(found.tolist()) == set(np.flatnonzero(visible).tolist())
        assert visible.sum() > 0


def test_candidates_with_a_margin_hold_every_landmark_that_close_to_the_view(rng):
    landmarks = rng.uniform(-20, 20, size=(5000, 3))
    index = association.PointIndex(landmarks)
    angle, margin = np.radians(50), 0.8
    for _ in range(10):
        T_world_camera = geometry.pose_from_euler(np.r_[rng.uniform(-10, 10, 3), rng.uniform(-1, 1, 3)])
        plain = association.candidate_indices(index, landmarks, T_world_camera, min_depth=0.3, max_depth=6.0, max_angle_rad=angle)
        wide = association.candidate_indices(index, landmarks, T_world_camera, min_depth=0.3, max_depth=6.0, max_angle_rad=angle,
                                             margin=margin)
        assert set(plain.tolist()) < set(wide.tolist())
        # any camera position within the margin sees only landmarks the wide search returned
        for shift in rng.normal(size=(20, 3)):
            moved = T_world_camera.copy()
            moved[:3, 3] += margin * rng.uniform() * shift / np.linalg.norm(shift)
            seen = association.candidate_indices(index, landmarks, moved, min_depth=0.3, max_depth=6.0, max_angle_rad=angle)
            assert set(seen.tolist()) <= set(wide.tolist())


@pytest.mark.parametrize("size", [7, association.STRIP_MAX_POINTS, association.STRIP_MAX_POINTS + 1], ids=["few", "strip", "k-d tree"])
def test_a_point_index_finds_exactly_the_points_within_a_ball(rng, size):
    # a map of the numpy engine's sizes is searched by strips (no scipy import), a larger one by k-d tree
    points = rng.uniform(-10, 10, size=(size, 3)) * [1.0, 3.0, 0.1]  # widest along y: the strip's axis
    index = association.PointIndex(points)
    found_any = 0
    for centre, radius in zip(rng.uniform(-10, 10, size=(20, 3)), rng.uniform(0.5, 6.0, size=20)):
        found = index.within(centre, radius)
        expected = np.flatnonzero(np.linalg.norm(points - centre, axis=1) <= radius)
        np.testing.assert_array_equal(found, expected)
        assert found.dtype == np.int64
        found_any += found.size
    assert found_any > (0 if size < 10 else 100)
    assert index.within(np.full(3, 100.0), 1.0).shape == (0,)
    assert association.PointIndex(np.zeros((0, 3))).within(np.zeros(3), 1.0).dtype == np.int64


@pytest.mark.parametrize("size", [association.SCAN_MAX_SHIFTS, association.SCAN_MAX_SHIFTS + 40, 3 * association.SCAN_MAX_SHIFTS + 7],
                         ids=["one table", "two blocks", "four blocks"])
def test_shift_agreement_counts_every_shift_within_the_radius(rng, size):
    shifts = rng.normal(scale=0.3, size=(size, 3)) * [0.5, 2.0, 1.0]  # widest along y: the blocks' axis
    counts = association.shift_agreement(shifts, 0.2)
    distances = np.linalg.norm(shifts[:, None, :] - shifts[None, :, :], axis=-1)
    np.testing.assert_array_equal(counts, (distances <= 0.2).sum(axis=1))
    assert counts.dtype == np.int64 and counts.min() >= 1 and counts.max() > 5


def test_shift_agreement_counts_the_crowd_of_right_pairs(rng):
    truth = np.array([0.4, -0.7, 0.2])
    right = truth + rng.normal(scale=0.02, size=(15, 3))
    wrong = rng.uniform(-4.0, 4.0, size=(300, 3))
    counts = association.shift_agreement(np.vstack([right, wrong]), radius=0.15)
    assert counts[:15].min() >= 14
    assert counts[15:].max() <= 5
    assert association.shift_agreement(np.zeros((0, 3)), 0.1).shape == (0,)


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


def test_assignment_margins_count_every_single_change():
    inf = np.inf
    # observation 0 chose column 0 (cost 1); its next best is column 1 (cost 4), null costs 10.
    # observation 1 chose column 1 (cost 2) but could take column 0 for 2.5 (0.5 more).
    # observation 2 is unassigned (null 10) and could take column 0 for 6 (4 less than now).
    cost = np.array([[1.0, 4.0, inf], [2.5, 2.0, inf], [6.0, inf, inf]])
    null = np.full(3, 10.0)
    row, steal = association.assignment_margins(cost, null, np.array([0, 1, -1]))
    assert row[0] == pytest.approx(3.0)             # column 1 instead
    assert steal[0] == pytest.approx(3.0 - 4.0)     # observation 2 takes column 0: 6 - 10
    assert row[1] == pytest.approx(0.5)             # column 0 instead
    assert steal[1] == pytest.approx(0.5 + (4.0 - 1.0))  # observation 0 takes column 1
    assert row[2] == inf and steal[2] == inf        # unassigned: nothing to judge


def test_assignment_margins_drop_a_pair_that_fails_its_gate():
    cost = np.array([[np.inf, 3.0]])
    row, _ = association.assignment_margins(cost, np.array([10.0]), np.array([0]))
    assert row[0] == -np.inf


def test_rival_margins_look_at_the_other_landmarks_alone():
    inf = np.inf
    # observation 0 chose column 0 (cost 1): column 2 costs 2.5, 1.5 more (leaving it unassigned,
    # cheaper still, is not a rival landmark); observation 1's only gated landmark is its own;
    # observation 2 is unassigned.
    cost = np.array([[1.0, inf, 2.5], [inf, 3.0, inf], [0.5, 0.7, inf]])
    margin = association.rival_margins(cost, np.array([0, 1, -1]))
    assert margin[0] == pytest.approx(1.5)
    assert margin[1] == inf and margin[2] == inf
    row, _ = association.assignment_margins(cost, np.array([1.2, 9.0, 9.0]), np.array([0, 1, -1]))
    assert row[0] == pytest.approx(0.2)             # the null option, which the rival margin leaves out


def test_leave_one_out_costs_match_an_update_without_the_pair(rng):
    """For a linear measurement model the formula is exact: compare with the posterior of the
    other pairs computed from scratch, for every observation and candidate."""
    n_obs, n_cand = 4, 6
    H = rng.normal(size=(n_cand, 3, 6))
    offset = rng.normal(size=(n_cand, 3))
    P0 = np.diag(rng.uniform(0.05, 0.3, 6) ** 2)
    x0 = rng.normal(scale=0.2, size=6)
    R = np.array([np.diag(rng.uniform(0.02, 0.06, 3) ** 2) for _ in range(n_obs)])
    chosen = np.array([2, 0, -1, 5])
    x_true = x0 + rng.normal(scale=0.1, size=6)
    z = np.array([H[c] @ x_true + offset[c] if c >= 0 else rng.normal(size=3) for c in chosen])
    z += rng.normal(scale=0.03, size=z.shape)

    def posterior(rows):
        information = np.linalg.inv(P0)
        vector = information @ x0
        for i in rows:
            Hc, Rinv = H[chosen[i]], np.linalg.inv(R[i])
            information = information + Hc.T @ Rinv @ Hc
            vector = vector + Hc.T @ Rinv @ (z[i] - offset[chosen[i]])
        P = np.linalg.inv(information)
        return P @ vector, P

    paired = [i for i in range(n_obs) if chosen[i] >= 0]
    x_post, _ = posterior(paired)
    z_hat = np.einsum("mij,j->mi", H, x_post) + offset
    got = association.leave_one_out_costs(z, R, z_hat, H, chosen, information=np.linalg.inv(P0), gate=np.inf)
    # a finite gate screens pairs by a bound before factoring them: it must drop exactly the
    # pairs beyond the gate and leave the others' costs unchanged
    gate = 20.0
    gated = association.leave_one_out_costs(z, R, z_hat, H, chosen, information=np.linalg.inv(P0), gate=gate)
    inside = 0
    for i in range(n_obs):
        x_i, P_i = posterior([j for j in paired if j != i])
        for j in range(n_cand):
            y = z[i] - (H[j] @ x_i + offset[j])
            S = H[j] @ P_i @ H[j].T + R[i]
            d2 = y @ np.linalg.solve(S, y)
            expected = d2 + np.linalg.slogdet(S)[1] - np.linalg.slogdet(R[i])[1]
            assert got[i, j] == pytest.approx(expected, rel=1e-8, abs=1e-8)
            if d2 <= gate:
                inside += 1
                assert gated[i, j] == pytest.approx(expected, rel=1e-8, abs=1e-8)
            else:
                assert gated[i, j] == np.inf
    assert 0 < inside < n_obs * n_cand  # the gate did separate the pairs


def test_leave_one_out_costs_apply_the_gate(rng):
    H = rng.normal(size=(2, 3, 6))
    z_hat = np.zeros((2, 3))
    R = np.array([np.eye(3) * 1e-4])
    z = np.array([[5.0, 0.0, 0.0]])  # far from both predictions
    cost = association.leave_one_out_costs(z, R, z_hat, H, np.array([-1]), information=np.eye(6) * 1e4, gate=11.34)
    assert np.all(np.isinf(cost))


def _linear_pose_problem(rng, n_obs=4, n_landmarks=5):
    """A linear measurement model z = H_l x + offset_l + noise with every observation gating every
    landmark: the pairs (observation, landmark) of a pose under a wide prior."""
    H_of = rng.normal(size=(n_landmarks, 3, 6))
    offset = rng.normal(size=(n_landmarks, 3))
    P = np.diag(rng.uniform(0.3, 0.6, 6) ** 2)
    x_true = rng.normal(scale=0.4, size=6)
    R_obs = np.array([np.diag(rng.uniform(0.05, 0.1, 3) ** 2) for _ in range(n_obs)])
    z = np.array([H_of[i] @ x_true + offset[i] for i in range(n_obs)]) + rng.normal(scale=0.05, size=(n_obs, 3))
    pair_obs, pair_landmark = np.divmod(np.arange(n_obs * n_landmarks), n_landmarks)
    y = z[pair_obs] - offset[pair_landmark]          # innovation at the prior mean x = 0
    return y, H_of[pair_landmark], R_obs[pair_obs], P, pair_obs, pair_landmark, R_obs


def test_seeded_explanation_costs_match_a_kalman_update_on_the_seed(rng):
    """Linear model: each seed's score equals its own pair cost plus, for every other observation,
    the cheaper of leaving it unassigned and its best gated pair after a Kalman update on the seed."""
    y, H, R, P, pair_obs, pair_landmark, R_obs = _linear_pose_problem(rng)
    null_cost = np.array([9.0, 12.0, 15.0, 30.0])
    log_det_R = np.linalg.slogdet(R_obs)[1]
    gate = 16.0
    seeds = np.array([0, 6, 7, 13, 19])
    got = association.seeded_explanation_costs(y, H, R, P, pair_obs, pair_landmark, null_cost, seeds, gate=gate)

    def pair_cost(q, x, P_q):
        r = y[q] - H[q] @ x
        S = H[q] @ P_q @ H[q].T + R[q]
        return r @ np.linalg.solve(S, r), r @ np.linalg.solve(S, r) + np.linalg.slogdet(S)[1] - log_det_R[pair_obs[q]]

    for s, score in zip(seeds, got):
        _, expected = pair_cost(s, np.zeros(6), P)
        S = H[s] @ P @ H[s].T + R[s]
        K = np.linalg.solve(S, H[s] @ P).T
        x_s, P_s = K @ y[s], (np.eye(6) - K @ H[s]) @ P
        for i in range(null_cost.size):
            if i == pair_obs[s]:
                continue
            options = [null_cost[i]]
            for q in np.flatnonzero((pair_obs == i) & (pair_landmark != pair_landmark[s])):
                d2, c = pair_cost(q, x_s, P_s)
                if d2 <= gate:
                    options.append(c)
            expected += min(options)
        assert score == pytest.approx(expected, rel=1e-9)


def test_seeded_explanation_costs_rank_a_right_seed_first(rng):
    """The seed that is a right pair explains the others; a wrong one leaves them to the null cost."""
    y, H, R, P, pair_obs, pair_landmark, R_obs = _linear_pose_problem(rng, n_obs=5, n_landmarks=6)
    right = np.flatnonzero(pair_obs == pair_landmark)          # observation i saw landmark i
    wrong = np.flatnonzero(pair_obs != pair_landmark)
    scores = association.seeded_explanation_costs(
        y, H, R, P, pair_obs, pair_landmark, np.full(5, 20.0), np.arange(pair_obs.size), gate=11.34)
    assert scores[right].max() < scores[wrong].min()


@pytest.mark.parametrize("scales", [(1.0, 1.0, 1.0), (1e-3, 1e-3, 0.1), (2.0, 2.0, 0.05)])
def test_mahalanobis_3x3_matches_a_solve(rng, scales):
    """The closed form against LAPACK, on covariances shaped like the filter's (normalized image
    coordinates beside depth in metres, or pixels)."""
    D = np.diag(scales)
    B = rng.normal(size=(200, 3, 3))
    S = D @ (B @ np.swapaxes(B, 1, 2) + 0.1 * np.eye(3)) @ D
    y = (D @ rng.normal(size=(200, 3, 1)))[..., 0]
    d2, log_det = association.mahalanobis_3x3(S, y)
    np.testing.assert_allclose(d2, np.einsum("ni,ni->n", y, np.linalg.solve(S, y[..., None])[..., 0]), rtol=1e-9)
    np.testing.assert_allclose(log_det, np.linalg.slogdet(S)[1], rtol=1e-9, atol=1e-9)


def test_seeded_explanation_costs_do_not_depend_on_how_seeds_are_batched(rng):
    """More seeds than one chunk: each seed's score is the one it gets alone."""
    y, H, R, P, pair_obs, pair_landmark, R_obs = _linear_pose_problem(rng, n_obs=8, n_landmarks=10)
    null_cost = np.full(8, 18.0)
    seeds = np.arange(pair_obs.size)
    assert seeds.size > association.SEED_CHUNK
    together = association.seeded_explanation_costs(y, H, R, P, pair_obs, pair_landmark, null_cost, seeds, gate=11.34)
    alone = [association.seeded_explanation_costs(y, H, R, P, pair_obs, pair_landmark, null_cost, np.array([s]), gate=11.34)[0] for s in seeds]
    np.testing.assert_allclose(together, alone, rtol=1e-12)


def test_view_cone_ball_holds_the_whole_cone_and_is_smaller_than_the_apex_ball(rng):
    from camloc.geometry import euler_to_matrix

    for half_angle_deg in (10.0, 30.0, 45.0, 57.0, 80.0):
        half_angle = np.radians(half_angle_deg)
        R = euler_to_matrix(rng.uniform(-np.pi, np.pi, 3) * [1, 0.4, 1])
        apex, depth = rng.normal(size=3), 3.0
        centre, radius = association.view_cone_ball(apex, R[:, 2], depth, half_angle)
        # the cone's extreme points: its apex and its base rim, plus random points inside it
        phi = np.linspace(0.0, 2.0 * np.pi, 64)
        rim = np.c_[depth * np.tan(half_angle) * np.cos(phi), depth * np.tan(half_angle) * np.sin(phi), np.full(64, depth)]
        s = rng.uniform(0.0, 1.0, (500, 3))
        inside = np.c_[(s[:, 0] - 0.5) * 2 * s[:, 2] * depth * np.tan(half_angle) / np.sqrt(2), (s[:, 1] - 0.5) * 2 * s[:, 2] * depth * np.tan(half_angle) / np.sqrt(2), s[:, 2] * depth]
        points = apex + np.r_[np.zeros((1, 3)), rim, inside] @ R.T
        assert np.all(np.linalg.norm(points - centre, axis=1) <= radius)
        assert radius < depth / np.cos(half_angle) - 1e-6


def test_a_spread_rounding_left_without_a_positive_determinant_fits_nothing():
    S = np.array([np.eye(3), np.diag([1.0, 1.0, -1e-18]), np.zeros((3, 3))])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning from the log of a negative determinant
        d2, log_det = association.mahalanobis_3x3(S, np.full((3, 3), 0.1))
    assert d2[0] == pytest.approx(0.03) and log_det[0] == pytest.approx(0.0)
    assert np.all(np.isinf(d2[1:])) and np.all(np.isinf(log_det[1:]))


def test_noise_floor_leaves_real_sensors_noise_as_it_is(rng):
    uvd = np.column_stack([rng.uniform(0, 640, 50), rng.uniform(0, 480, 50), rng.uniform(0.5, 4.0, 50)])
    cov = np.broadcast_to(np.diag([0.05**2, 0.05**2, 1e-4**2]), (50, 3, 3)).copy()  # 0.05 px, 0.1 mm: precise, not exact
    info = np.linalg.inv(cov)
    floored_cov, floored_info = observation_space.noise_floored(uvd, cov, info, np.full(50, 525.0), np.full(50, 525.0))
    assert floored_cov is cov and floored_info is info


def test_noise_floor_raises_observations_that_claim_to_be_exact(rng):
    # information 1e12, the simulator's noise-free data, beside one ordinary observation
    uvd = np.column_stack([rng.uniform(0, 640, 4), rng.uniform(0, 480, 4), [0.5, 1.0, 2.0, 3.0]])
    cov = np.broadcast_to(np.eye(3) * 1e-12, (4, 3, 3)).copy()
    cov[3] = np.diag([1.0, 1.0, 1e-3])
    fx, fy = np.full(4, 500.0), np.full(4, 400.0)
    floored_cov, floored_info = observation_space.noise_floored(uvd, cov, np.linalg.inv(cov), fx, fy)
    expected = (observation_space.NOISE_FLOOR * np.column_stack([fx, fy, uvd[:, 2]])) ** 2
    np.testing.assert_allclose(np.diagonal(floored_cov[:3], axis1=1, axis2=2), expected[:3], rtol=1e-12)  # raised to the floor
    np.testing.assert_array_equal(floored_cov[3], cov[3])
    np.testing.assert_allclose(floored_info @ floored_cov, np.broadcast_to(np.eye(3), (4, 3, 3)), atol=1e-9)


@pytest.mark.parametrize("association, sequential", [("oracle", True), ("best-friends", True), ("best-friends", False), ("jcbb", True)])
def test_every_per_pose_method_pairs_rightly_from_the_true_state(association, sequential):
    # each method by its name in the localizer's table, called through the one signature
    # associate(scene, x, P, obs) on every pose of a world without clutter, from the true state
    from camloc.localizer import PER_POSE_ASSOCIATORS, _Localizer
    from camloc.localizer_config import BestFriendsOptions, LocalizerConfig
    from camloc.simulate import SimulationConfig, simulate

    dataset = simulate(SimulationConfig(poses=30, cameras=2), seed=4)
    config = LocalizerConfig(association=association, best_friends=BestFriendsOptions(sequential=sequential))
    localizer = _Localizer(dataset, config)
    associate, scene = PER_POSE_ASSOCIATORS[association](config), localizer.scene
    P = np.diag([0.05**2] * 3 + [0.01**2] * 3)
    right = paired = 0
    for k in range(1, dataset.num_poses):  # the first pose has no observations
        x = localizer.filter.initial(geometry.pose_from_quat(dataset.truth_xyz[k], dataset.truth_quat_xyzw[k]))
        obs, landmarks = associate(scene, x, P, localizer.obs_of_pose[k])
        assert obs.dtype == landmarks.dtype == np.int64 and obs.shape == landmarks.shape
        assert set(obs.tolist()) <= set(localizer.obs_of_pose[k].tolist())
        right, paired = right + int(np.sum(scene.true_landmark_row[obs] == landmarks)), paired + obs.size
    assert paired > 200
    assert right == paired >= 0.99 * dataset.num_observations


def _linear_pairs(rng, d):
    H = rng.normal(0, 1, (d, 3, 6))
    R = np.stack([np.diag(rng.uniform(0.01, 0.05, 3)) for _ in range(d)])
    return H, R


def test_restored_pairs_takes_back_what_fits_and_leaves_what_does_not(rng):
    """Pairs whose residuals one error of the state explains together are taken back against
    their null costs; one off by far more stays out; over RESTORE_LIMIT pairs none is weighed."""
    H, R = _linear_pairs(rng, 3)
    P = np.diag(np.full(6, 0.05))
    error = rng.normal(0, 0.2, 6)                     # the state the pairs' posterior left off
    y = np.einsum("dij,j->di", H, error)
    y[2] += 5.0                                       # clutter: no state explains it
    null = np.full(3, 12.0)
    np.testing.assert_array_equal(association.restored_pairs(y, H, P, R, null), [True, True, False])
    many = association.RESTORE_LIMIT + 1
    H, R = _linear_pairs(rng, many)
    assert not association.restored_pairs(np.zeros((many, 3)), H, P, R, np.full(many, 12.0)).any()
