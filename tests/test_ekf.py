"""The EKF steps: textbook equations on linear systems, Joseph form, the iterated update's MAP."""

import numpy as np
import pytest
from scipy.optimize import minimize

from camloc import ekf


def plain_difference(a, b):
    return a - b


def random_spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + n * np.eye(n))


def range_bearing(s):
    """A range-bearing measurement of a 2D position: strongly nonlinear for a wide prior."""
    return np.array([np.hypot(s[0], s[1]), np.arctan2(s[1], s[0])])


def range_bearing_jacobian(s):
    r2 = s[0] ** 2 + s[1] ** 2
    r = np.sqrt(r2)
    return np.array([[s[0] / r, s[1] / r], [-s[1] / r2, s[0] / r2]])


def test_linear_update_matches_information_form(rng):
    n, m = 4, 3
    x, P, R = rng.normal(size=n), random_spd(rng, n), random_spd(rng, m, 0.1)
    H, z = rng.normal(size=(m, n)), rng.normal(size=m)
    result = ekf.update(x, P, z, R, lambda s: (H @ s, H), difference=plain_difference)
    # Information form: P+ = (P^-1 + H' R^-1 H)^-1, x+ = P+ (P^-1 x + H' R^-1 z)
    info = np.linalg.inv(P) + H.T @ np.linalg.solve(R, H)
    P_post = np.linalg.inv(info)
    x_post = P_post @ (np.linalg.solve(P, x) + H.T @ np.linalg.solve(R, z))
    np.testing.assert_allclose(result.cov, P_post, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(result.state, x_post, rtol=1e-9, atol=1e-12)
    y = z - H @ x
    assert result.nis == pytest.approx(y @ np.linalg.solve(H @ P @ H.T + R, y))
    iterated = ekf.update(x, P, z, R, lambda s: (H @ s, H), difference=plain_difference, iterations=2, map_cost=True)
    assert iterated.map_cost == pytest.approx(result.nis)  # linear model: the MAP cost is the NIS


def test_iterations_change_nothing_on_a_linear_model(rng):
    x, P, R = rng.normal(size=3), random_spd(rng, 3), random_spd(rng, 2, 0.1)
    H, z = rng.normal(size=(2, 3)), rng.normal(size=2)
    one = ekf.update(x, P, z, R, lambda s: (H @ s, H), difference=plain_difference)
    five = ekf.update(x, P, z, R, lambda s: (H @ s, H), difference=plain_difference, iterations=5)
    np.testing.assert_allclose(one.state, five.state, atol=1e-12)
    np.testing.assert_allclose(one.cov, five.cov, atol=1e-12)


def test_iterated_update_reaches_the_map_estimate(rng):
    h, H_of = range_bearing, range_bearing_jacobian
    x, P, R = np.array([2.0, 0.5]), np.diag([1.0, 1.0]), np.diag([0.01, 0.001])
    z = h(np.array([1.5, 1.5]))
    result = ekf.update(x, P, z, R, lambda s: (h(s), H_of(s)), difference=plain_difference, iterations=20, map_cost=True)

    def map_cost(s):
        e, r = s - x, z - h(s)
        return e @ np.linalg.solve(P, e) + r @ np.linalg.solve(R, r)

    optimum = minimize(map_cost, result.state + 0.05, method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-14}).x
    np.testing.assert_allclose(result.state, optimum, atol=1e-5)
    plain = ekf.update(x, P, z, R, lambda s: (h(s), H_of(s)), difference=plain_difference)
    assert map_cost(result.state) < map_cost(plain.state)
    assert result.map_cost == pytest.approx(map_cost(result.state))


def test_a_start_changes_where_the_iterations_begin_not_where_they_end(rng):
    measure = lambda s: (range_bearing(s), range_bearing_jacobian(s))  # noqa: E731
    x, P, R = np.array([2.0, 0.5]), np.diag([1.0, 1.0]), np.diag([0.01, 0.001])
    z = range_bearing(np.array([1.5, 1.5]))
    settled = ekf.update(x, P, z, R, measure, difference=plain_difference, iterations=30, map_cost=True)
    started = ekf.update(x, P, z, R, measure, difference=plain_difference, iterations=30, map_cost=True,
                         start=np.array([1.4, 1.6]))
    np.testing.assert_allclose(started.state, settled.state, atol=1e-8)
    assert started.nis == settled.nis  # judged at the prior either way
    assert ekf.posterior_cost(started.state, x, P, z, R, measure, plain_difference) == pytest.approx(started.map_cost)
    # a plain EKF (one linearization, at the prior) has no iterations for a start to begin
    plain = ekf.update(x, P, z, R, measure, difference=plain_difference)
    ignored = ekf.update(x, P, z, R, measure, difference=plain_difference, start=np.array([1.4, 1.6]))
    np.testing.assert_array_equal(ignored.state, plain.state)


def test_joseph_form_keeps_covariance_symmetric_positive_definite(rng):
    P = random_spd(rng, 6, 1e3)
    H = rng.normal(size=(9, 6))
    R = np.eye(9) * 1e-6
    for _ in range(50):
        result = ekf.update(np.zeros(6), P, np.zeros(9), R, lambda s: (H @ s, H), difference=plain_difference)
        P = result.cov
    assert np.array_equal(P, P.T)
    assert np.all(np.linalg.eigvalsh(P) > 0)


def test_predict_propagates_covariance(rng):
    P, Q = random_spd(rng, 3), random_spd(rng, 2)
    F, G = rng.normal(size=(3, 3)), rng.normal(size=(3, 2))
    np.testing.assert_allclose(ekf.predict(P, F, G, Q), F @ P @ F.T + G @ Q @ G.T, atol=1e-10)


def test_non_positive_definite_innovation_is_reported():
    with pytest.raises(ekf.FilterDivergedError):
        ekf.kalman_gain(np.eye(2), np.eye(2), -2.0 * np.eye(2))


def test_cholesky_and_cho_solve_are_numpys_to_the_bit():
    # they call the LAPACK gufuncs np.linalg wraps, without its checks: the same arithmetic
    rng = np.random.default_rng(3)
    for n in (2, 3, 6):
        A = rng.normal(size=(n, n))
        S = A @ A.T + n * np.eye(n)
        L = ekf.cholesky(S)
        assert np.array_equal(L, np.linalg.cholesky(S))
        for B in (rng.normal(size=n), rng.normal(size=(n, 4))):
            assert np.array_equal(ekf.cho_solve(L, B), np.linalg.solve(L.T, np.linalg.solve(L, B)))
    for broken in (np.diag([1.0, -1.0, 1.0]), np.array([[1.0, 2.0], [2.0, 1.0]]), np.full((3, 3), np.nan)):
        with pytest.raises(ekf.FilterDivergedError, match="not positive definite"):
            ekf.cholesky(broken)


def _block_system(rng, p=6, b=3, n=6):
    blocks = np.array([random_spd(rng, b, 0.05) for _ in range(p)])
    return rng.normal(size=n), random_spd(rng, n), blocks, rng.normal(size=(p * b, n)), rng.normal(size=p * b)


def test_an_update_in_information_form_matches_the_textbook_one(rng):
    # More measurement rows than states, with R block-diagonal: the update runs in information
    # form (O(m)); it must give the textbook update with the full R, to rounding.
    x, P, blocks, H, z = _block_system(rng)
    R = ekf.block_diagonal(blocks)
    for iterations in (1, 3):
        full = ekf.update(x, P, z, R, lambda s: (H @ s + 0.1 * np.sin(s).sum(), H), difference=plain_difference,
                          iterations=iterations, map_cost=True)
        fast = ekf.update(x, P, z, blocks, lambda s: (H @ s + 0.1 * np.sin(s).sum(), H), difference=plain_difference,
                          iterations=iterations, map_cost=True)
        np.testing.assert_allclose(fast.state, full.state, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(fast.cov, full.cov, rtol=1e-9, atol=1e-13)
        assert fast.nis == pytest.approx(full.nis, rel=1e-10)
        assert fast.map_cost == pytest.approx(full.map_cost, rel=1e-10)
        p = blocks.shape[0]
        np.testing.assert_allclose(fast.S, full.S.reshape(p, 3, p, 3)[np.arange(p), :, np.arange(p), :], rtol=1e-12)
        assert np.array_equal(fast.cov, fast.cov.T) and np.all(np.linalg.eigvalsh(fast.cov) > 0)


def test_the_innovation_cost_and_correction_match_the_textbook_ones(rng):
    x, P, blocks, H, y = _block_system(rng)
    S = H @ P @ H.T + ekf.block_diagonal(blocks)
    expected = y @ np.linalg.solve(S, y) + np.linalg.slogdet(S)[1] - np.linalg.slogdet(blocks)[1].sum()
    assert ekf.innovation_cost(P, H, blocks, y) == pytest.approx(expected, rel=1e-10)
    assert ekf.innovation_cost(P, H, ekf.block_diagonal(blocks), y) == pytest.approx(expected, rel=1e-10)
    np.testing.assert_allclose(ekf.correction(P, H, blocks, y), P @ H.T @ np.linalg.solve(S, y), rtol=1e-9, atol=1e-12)
    # fewer rows than states: the textbook path, from the blocks
    assert ekf.innovation_cost(P, H[:3], blocks[:1], y[:3]) == pytest.approx(
        y[:3] @ np.linalg.solve(S[:3, :3], y[:3]) + np.linalg.slogdet(S[:3, :3])[1] - np.linalg.slogdet(blocks[0])[1], rel=1e-10)


def test_the_innovation_cost_of_pairs_together_is_theirs_one_after_another(rng):
    """Of a linear model, the cost of three pairs stacked (9 rows: the information form) is the
    first's under the prior plus the other two's (6 rows: the textbook form) under the posterior
    after the first: the chain rule of the likelihood, which the re-check's restore relies on."""
    H = rng.normal(0, 1, (3, 3, 6))
    R = np.stack([np.diag(rng.uniform(0.01, 0.05, 3)) for _ in range(3)])
    P = np.diag(rng.uniform(0.01, 0.1, 6))
    y = rng.normal(0, 0.3, (3, 3))
    first = ekf.innovation_cost(P, H[0], R[:1], y[0])
    K = P @ H[0].T @ np.linalg.inv(H[0] @ P @ H[0].T + R[0])
    P_after, y_after = P - K @ H[0] @ P, y[1:] - H[1:] @ (K @ y[0])
    rest = ekf.innovation_cost(P_after, H[1:].reshape(6, 6), R[1:], y_after.reshape(-1))
    assert ekf.innovation_cost(P, H.reshape(9, 6), R, y.reshape(-1)) == pytest.approx(first + rest, rel=1e-9)


def test_given_inverses_of_the_blocks_give_the_same_update(rng):
    # the localizer passes the file's information matrices instead of having the blocks inverted
    x, P, blocks, H, z = _block_system(rng)
    measure = lambda s: (H @ s + 0.1 * np.sin(s).sum(), H)  # noqa: E731
    inverted = ekf.update(x, P, z, blocks, measure, difference=plain_difference, iterations=3, map_cost=True)
    given = ekf.update(x, P, z, blocks, measure, difference=plain_difference, iterations=3, map_cost=True,
                       R_inverse=np.linalg.inv(blocks))
    np.testing.assert_allclose(given.state, inverted.state, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(given.cov, inverted.cov, rtol=1e-9, atol=1e-13)
    assert given.nis == pytest.approx(inverted.nis, rel=1e-10)
    assert given.map_cost == pytest.approx(inverted.map_cost, rel=1e-10)


def test_a_measurement_block_that_is_not_positive_definite_is_reported(rng):
    x, P, blocks, H, z = _block_system(rng)
    blocks[2] = -blocks[2]
    with pytest.raises(ekf.FilterDivergedError, match="not positive definite"):
        ekf.update(x, P, z, blocks, lambda s: (H @ s, H), difference=plain_difference)
    with pytest.raises(ekf.FilterDivergedError, match="not positive definite"):
        ekf.update(x, P, z, np.full_like(blocks, np.inf), lambda s: (H @ s, H), difference=plain_difference)


def test_the_information_form_keeps_covariance_symmetric_positive_definite(rng):
    # the stress of the Joseph-form test: a wide prior and measurements a billion times tighter
    P = random_spd(rng, 6, 1e3)
    H = rng.normal(size=(9, 6))
    blocks = np.broadcast_to(np.eye(3) * 1e-6, (3, 3, 3)).copy()
    for _ in range(50):
        P = ekf.update(np.zeros(6), P, np.zeros(9), blocks, lambda s: (H @ s, H), difference=plain_difference).cov
    assert np.array_equal(P, P.T)
    assert np.all(np.linalg.eigvalsh(P) > 0)


def test_the_mixture_spread_is_the_weighted_second_moment_about_the_estimate(rng):
    # Two components 2 cost units apart (weights 1 : e^-1): about the first, only the second's
    # offset counts, at its weight; about their weighted mean, the spread is the mixture's
    # covariance of its means, which sampling the mixture's means by their weights reproduces.
    d = rng.normal(size=6)
    two = np.stack([np.zeros(6), d])
    w = np.exp(-1.0) / (1.0 + np.exp(-1.0))
    np.testing.assert_allclose(ekf.mixture_spread(two, np.array([10.0, 12.0])), w * np.outer(d, d), atol=1e-15)
    means = rng.normal(size=(5, 6))
    costs = rng.uniform(0.0, 6.0, 5)
    weights = np.exp(-costs / 2) / np.exp(-costs / 2).sum()
    mean = weights @ means
    sample = means[rng.choice(5, size=400_000, p=weights)] - mean
    np.testing.assert_allclose(ekf.mixture_spread(means - mean, costs), sample.T @ sample / sample.shape[0], atol=5e-3)
    assert not ekf.mixture_spread(means[:1] - mean, costs[:1]).any()  # one component: nothing to add


def _posterior(x0, P0, H, R, z):
    """The linear Gaussian posterior of prior (x0, P0) and pairs z_i = H_i x + noise R_i, in
    information form from scratch."""
    information = np.linalg.inv(P0) + sum(h.T @ np.linalg.solve(r, h) for h, r in zip(H, R))
    vector = np.linalg.solve(P0, x0) + sum(h.T @ np.linalg.solve(r, y) for h, r, y in zip(H, R, z))
    P = np.linalg.inv(information)
    return P @ vector, P


@pytest.mark.parametrize("judged_scale", [1.0, 2.5])
def test_the_leave_one_out_spread_is_the_mixture_of_the_update_and_each_pair_left_out(rng, judged_scale):
    # Issue 36, point 3: each pair's alternative "this one is clutter" is the posterior of the
    # others, computed here from scratch (no Woodbury), weighed by the pair's cost under it
    # (noise R_judged) against leaving the observation unassigned.
    n, p = 6, 4
    x0, P0 = rng.normal(size=n), random_spd(rng, n, 0.05)
    H = rng.normal(size=(p, 3, n))
    R = np.stack([random_spd(rng, 3, 0.01) for _ in range(p)])
    z = H @ x0 + rng.normal(scale=0.3, size=(p, 3))
    R_judged = judged_scale * R
    null = rng.uniform(4.0, 14.0, p)
    x, P = _posterior(x0, P0, H, R, z)
    expected, weights = np.zeros((n, n)), [1.0]
    terms = []
    for i in range(p):
        others = [j for j in range(p) if j != i]
        x_i, P_i = _posterior(x0, P0, H[others], R[others], z[others])
        S = H[i] @ P_i @ H[i].T + R_judged[i]
        e = z[i] - H[i] @ x_i
        cost = e @ np.linalg.solve(S, e) + np.linalg.slogdet(S)[1] - np.linalg.slogdet(R_judged[i])[1]
        weights.append(np.exp(-(null[i] - cost) / 2.0))
        terms.append(P_i - P + np.outer(x_i - x, x_i - x))
    weights = np.array(weights) / np.sum(weights)
    expected = sum(w * t for w, t in zip(weights[1:], terms))
    spread = ekf.leave_one_out_spread(P, z - H @ x, H, R, R_judged, np.linalg.slogdet(R_judged)[1], null)
    np.testing.assert_allclose(spread, expected, rtol=1e-8, atol=1e-12)
    assert weights[1:].max() > 1e-3                  # the alternatives weigh something here
    assert np.linalg.eigvalsh(spread).min() >= -1e-12


def test_a_right_pair_far_cheaper_than_clutter_adds_next_to_nothing(rng):
    n = 6
    x0, P0 = np.zeros(n), random_spd(rng, n, 0.05)
    H = rng.normal(size=(3, 3, n))
    R = np.stack([random_spd(rng, 3, 0.01) for _ in range(3)])
    z = H @ x0
    x, P = _posterior(x0, P0, H, R, z)
    spread = ekf.leave_one_out_spread(P, z - H @ x, H, R, R, np.linalg.slogdet(R)[1], np.full(3, 60.0))
    assert np.abs(spread).max() < 1e-9 * np.abs(P).max()
    assert not ekf.leave_one_out_spread(P, np.zeros((0, 3)), H[:0], R[:0], R[:0], np.zeros(0), np.zeros(0)).any()


def test_monotone_iterations_take_the_cheapest_iterate():
    """Gauss-Newton without a line search overshoots where the prior is wide and the measurement
    bends: here its third iterate costs 40 times the plain EKF step's MAP cost. With ``monotone``
    the update is the cheapest iterate it reached (the first), with that one's gain."""
    measure = lambda s: (range_bearing(s), range_bearing_jacobian(s))  # noqa: E731
    x, P, R = np.array([2.608, 1.894]), np.diag([2.946, 4.708]), np.diag([0.01, 0.001])
    z = np.array([1.2493, 3.0754])
    plain = ekf.update(x, P, z, R, measure, difference=plain_difference, map_cost=True)
    iterated = ekf.update(x, P, z, R, measure, difference=plain_difference, iterations=3, map_cost=True)
    guarded = ekf.update(x, P, z, R, measure, difference=plain_difference, iterations=3, map_cost=True, monotone=True)
    assert iterated.map_cost > 10 * plain.map_cost  # the overshoot this guards against
    assert guarded.map_cost == pytest.approx(plain.map_cost)
    np.testing.assert_array_equal(guarded.state, plain.state)
    np.testing.assert_array_equal(guarded.cov, plain.cov)
    assert guarded.map_cost == pytest.approx(ekf.posterior_cost(guarded.state, x, P, z, R, measure, plain_difference))


def test_monotone_iterations_change_nothing_where_the_last_iterate_is_the_cheapest(rng):
    """Where Gauss-Newton converges (each iterate lowers the cost), ``monotone`` gives the same
    update bit for bit."""
    measure = lambda s: (range_bearing(s), range_bearing_jacobian(s))  # noqa: E731
    x, P, R = np.array([2.0, 0.5]), np.diag([1.0, 1.0]), np.diag([0.01, 0.001])
    z = range_bearing(np.array([1.5, 1.5]))
    free = ekf.update(x, P, z, R, measure, difference=plain_difference, iterations=20, map_cost=True)
    guarded = ekf.update(x, P, z, R, measure, difference=plain_difference, iterations=20, map_cost=True, monotone=True)
    np.testing.assert_array_equal(guarded.state, free.state)
    np.testing.assert_array_equal(guarded.cov, free.cov)
    assert guarded.map_cost == free.map_cost


def test_damped_gauss_newton_reaches_the_map_estimate_where_plain_iterations_run_off():
    """A depth-like model, h(x) = 1/x, prior x = 1 +- 0.5, the measurement (1e-2 noise) of x = 0.3:
    the Jacobian grows 11-fold over the prior's spread, so plain Gauss-Newton overshoots past zero
    (the iterated update ends at x < 0, behind the camera, whatever its iterations). Damped until
    each step lowers the MAP cost (Levenberg-Marquardt), the iterations reach the minimum a grid
    finds."""
    def measure(x):
        return np.array([1.0 / x[0]]), np.array([[-1.0 / x[0] ** 2]])

    x, P, z, R = np.array([1.0]), np.array([[0.25]]), np.array([1.0 / 0.3]), np.array([[1e-4]])
    for iterations in (3, 10, 50):
        assert ekf.update(x, P, z, R, measure, iterations=iterations).state[0] < 0.0
    found = ekf.damped_gauss_newton(x, P, z, R, measure)
    grid = np.linspace(0.05, 2.0, 400_001)
    cost = (grid - 1.0) ** 2 / 0.25 + (z[0] - 1.0 / grid) ** 2 / 1e-4
    assert found[0] == pytest.approx(grid[cost.argmin()], abs=1e-5)
    assert ekf.posterior_cost(found, x, P, z, R, measure) == pytest.approx(cost.min(), rel=1e-4)
