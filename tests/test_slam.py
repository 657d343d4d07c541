"""The invariant EKF-SLAM's model (camloc.slam): every Jacobian against finite differences of the
state's retraction, and the prediction's error propagation against a perturbed pair of runs (a tag's orientation row too: camloc.slam_tags)."""

import numpy as np
import pytest

from camloc import geometry, measurement, slam, slam_tags
from camloc.sensors import CameraModel

STEP = 1e-6


def _state(rng, m=2):
    R = geometry.so3_exp(rng.normal(size=3) * 0.5)
    t = rng.normal(size=3)
    # landmarks in front of the camera below (about 4 m ahead along the robot's x)
    L = t + (R @ (np.array([4.0, 0.0, 0.0]) + rng.normal(size=(m, 3)) * 0.5).T).T
    return slam.SlamMean(R, t, L)


def _camera(kind):
    # a camera looking along the robot's x axis (its z), offset on the robot
    Rc = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rc, [0.1, -0.05, 0.2]
    return CameraModel(T, (500.0, 510.0, 320.0, 240.0), kind, 0)


def _numeric(f, x, dim):
    columns = []
    for i in range(dim):
        e = np.zeros(dim)
        e[i] = STEP
        columns.append((f(slam.retract(x, e)) - f(slam.retract(x, -e))) / (2 * STEP))
    return np.stack(columns, axis=-1)


@pytest.mark.parametrize("kind", [measurement.DEPTH, measurement.PIXEL, measurement.DISPARITY])
def test_observation_jacobians_match_finite_differences(kind):
    rng = np.random.default_rng(3)
    x = _state(rng)
    sensor = _camera(kind)
    fixed = x.t + x.R @ np.array([5.0, 0.3, -0.2])
    for row, xyz_of in [(0, lambda s: s.L[0]), (1, lambda s: s.L[1]), (-1, lambda s: fixed)]:
        z, H = slam.observe(x, sensor, xyz_of(x)[None, :], np.array([row]))
        numeric = _numeric(lambda s: slam.observe(s, sensor, xyz_of(s)[None, :], np.array([row]))[0][0], x, x.dim)
        np.testing.assert_allclose(H[0], numeric, atol=1e-5 * max(1.0, np.abs(numeric).max()))
        if row >= 0:  # a landmark in the state moves with it, not with the heading
            np.testing.assert_allclose(H[0][:, 3:6], 0.0, atol=1e-9)


def test_retract_and_difference_are_inverse():
    rng = np.random.default_rng(4)
    x = _state(rng)
    delta = rng.normal(size=x.dim) * 0.3
    moved = slam.retract(x, delta)
    np.testing.assert_allclose(slam.difference(moved, x), delta, atol=1e-10)


def test_inverse_observation_and_its_error():
    """The landmark a depth measurement implies reprojects to it, and its error is the pose's
    translation error plus the measurement's noise mapped (B = [I, 0], W R W')."""
    rng = np.random.default_rng(5)
    x = _state(rng, m=0)
    sensor = _camera(measurement.DEPTH)
    z = np.array([300.0, 250.0, 4.0])
    R_z = np.diag([2.0, 3.0, 0.01])
    xyz, B, N = slam.inverse_observation(x, sensor, z, R_z)
    z_back, _ = slam.observe(x, sensor, xyz[None, :], np.array([-1]))
    np.testing.assert_allclose(z_back[0], z, atol=1e-9)
    # xi_l = l(x (+) xi) - Exp(xi_theta) l^ ... : the landmark from the perturbed pose, as an error
    def landmark_error(s):
        l_new, _, _ = slam.inverse_observation(s, sensor, z, R_z)
        with_landmark = slam.SlamMean(s.R, s.t, l_new[None, :])
        base = slam.SlamMean(x.R, x.t, xyz[None, :])
        return slam.difference(with_landmark, base)[6:9]
    numeric = _numeric(landmark_error, x, 6)
    np.testing.assert_allclose(B, numeric, atol=1e-6)
    # the noise: d l / d z through W, numerically
    W = np.stack([(slam.inverse_observation(x, sensor, z + e, R_z)[0] - slam.inverse_observation(x, sensor, z - e, R_z)[0]) / 2e-6
                  for e in np.eye(3) * 1e-6], axis=1)
    np.testing.assert_allclose(N, W @ R_z @ W.T, rtol=1e-5)


@pytest.mark.parametrize("with_tag", [False, True])
def test_prediction_error_propagates_with_identity(with_tag):
    """Two states an error xi apart stay xi apart (to first order) after the same increment (F = I),
    and an increment's right perturbation w moves the error by G w (``noise_coefficients``; a tag's
    orientation row too: ``xi_o -= R w_theta``, camloc.slam_tags)."""
    rng = np.random.default_rng(6)
    x = _state(rng, m=1)
    if with_tag:  # a second row, the orientation of a tag whose centre is the first
        x = slam.SlamMean(x.R, x.t, np.vstack([x.L, rng.normal(size=3)]), np.array([False, True]))
    T_inc = geometry.make_pose(geometry.so3_exp(rng.normal(size=3) * 0.2), rng.normal(size=3))
    xi = rng.normal(size=x.dim) * 1e-5
    a, _ = slam.predict(x, np.eye(x.dim), T_inc, np.eye(6))
    b, _ = slam.predict(slam.retract(x, xi), np.eye(x.dim), T_inc, np.eye(6))
    np.testing.assert_allclose(slam.difference(b, a), xi, atol=1e-9)
    w = rng.normal(size=6) * 1e-5
    c, _ = slam.predict(x, np.eye(x.dim), T_inc @ geometry.make_pose(geometry.so3_exp(w[3:6]), w[0:3]), np.eye(6))
    np.testing.assert_allclose(slam.difference(c, a), slam.noise_coefficients(a) @ w, atol=1e-9)
    # and the covariance grows by exactly G Q G'
    Q = np.diag(rng.uniform(0.1, 1.0, size=6))
    _, P = slam.predict(x, np.zeros((x.dim, x.dim)), T_inc, Q)
    G = slam.noise_coefficients(a)
    np.testing.assert_allclose(P, G @ Q @ G.T, atol=1e-12)


def test_world_covariances_round_trip():
    """A landmark entered with a world prior independent of the pose reads back that prior plus
    nothing of the pose (its world covariance), and the start's world covariance reads back."""
    rng = np.random.default_rng(7)
    x = _state(rng, m=0)
    world = np.diag([0.01, 0.02, 0.03, 1e-4, 2e-4, 3e-4])
    P = slam.initial_cov(x, world)
    J = np.zeros((6, 6))  # right perturbation -> world (dt, dtheta): blockdiag(R, R)
    J[:3, :3], J[3:, 3:] = x.R, x.R
    np.testing.assert_allclose(J @ slam.pose_right_cov(x, P) @ J.T, world, atol=1e-12)
    xyz = np.array([3.0, -2.0, 1.0])
    prior = np.diag([0.04, 0.05, 0.06])
    x2, P2 = slam.augmented(x, P, xyz, slam.world_prior_coefficients(x, xyz), prior)
    np.testing.assert_allclose(slam.landmark_world_cov(x2, P2, 0), prior, atol=1e-12)


def test_jcbb_joint_test_equals_the_plain_statement():
    """jcbb's precomputed blocks give the joint distance of the plain stacked statement, and the
    search keeps the jointly compatible set: two pairs each fine alone but pulling the pose apart
    are not taken together."""
    from camloc.slam_association import Candidate, jcbb, joint_distance

    rng = np.random.default_rng(8)
    n = 12
    A = rng.normal(size=(n, n))
    P = A @ A.T * 0.01 + np.eye(n) * 1e-3
    H = [rng.normal(size=(3, n)) for _ in range(3)]
    R = np.eye(3) * 0.01
    # pair 0 and 1 agree with a pose error e; pair 2 pulls the other way
    e = rng.normal(size=n) * 0.05
    ys = [H[0] @ e, H[1] @ e, -H[2] @ e * 8]
    pairs = [Candidate(i, 100 + i, ys[i], H[i], np.zeros((3, 3)), R, 3, 1.0) for i in range(3)]
    S = np.vstack(H) @ P @ np.vstack(H).T + np.kron(np.eye(3), R)
    y = np.concatenate(ys)
    assert joint_distance(P, pairs) == pytest.approx(float(y @ np.linalg.solve(S, y)))
    chosen = jcbb(P, [[p] for p in pairs], 0.99)
    assert len(chosen) == 2 and {c.obs for c in chosen} == {0, 1}


def test_jcbb_of_one_observation_is_the_search_s_answer():
    """``jcbb`` answers a lone observation (candidates for one observation, the others none) by its
    cheapest candidate, with ties to the first: what ``jcbb_search`` finds."""
    from camloc.slam_association import Candidate, jcbb, jcbb_search

    rng = np.random.default_rng(9)
    n = 12
    A = rng.normal(size=(n, n))
    P = A @ A.T * 0.01 + np.eye(n) * 1e-3
    for trial in range(20):
        costs = rng.integers(0, 4, size=rng.integers(1, 6)).astype(float)  # ties among them
        options = [Candidate(7, 100 + i, rng.normal(size=3), rng.normal(size=(3, n)), np.zeros((3, 3)), np.eye(3), 3, c)
                   for i, c in enumerate(costs)]
        candidates = [[]] * (trial % 3) + [options] + [[]] * (trial % 2)
        assert [id(c) for c in jcbb(P, candidates, 0.99)] == [id(c) for c in jcbb_search(P, candidates, 0.99)]


def test_jcbb_pairs_a_landmark_once_per_sensor():
    """Two cameras seeing one landmark give it two observations a pose (a stereo rig's stacked
    update); one camera cannot see it twice. Both observations consistent with the landmark: of
    two sensors both are taken, of one sensor only one (before, one of the rig's two was left out
    at every pose: the still stereo robot's landmark took 42 of its 80 observations)."""
    from camloc.slam_association import Candidate, jcbb

    rng = np.random.default_rng(3)
    n = 9
    P = np.eye(n) * 1e-4
    H = [np.hstack([rng.normal(size=(3, 6)), np.eye(3)]) for _ in range(2)]
    R = np.eye(3) * 0.01
    y = [rng.normal(size=3) * 0.01 for _ in range(2)]
    for sensors, taken in (((0, 1), 2), ((0, 0), 1)):
        candidates = [[Candidate(o, 5, y[o], H[o], np.zeros((3, 3)), R, 3, 1.0, sensor=sensors[o])] for o in range(2)]
        chosen = jcbb(P, candidates, 0.99)
        assert len(chosen) == taken and all(c.landmark == 5 for c in chosen)


def test_column_gain_equals_the_joseph_product_form():
    """The update from H's few columns (ekf.ColumnGain: the Joseph form expanded, O(n^2 m)) gives
    the covariance of the textbook product form, exactly symmetric, the same correction, and
    the MAP cost's prior term d' P^-1 d without P^-1."""
    from camloc import ekf

    rng = np.random.default_rng(11)
    n, m = 30, 6
    A = rng.normal(size=(n, n))
    P = A @ A.T * 0.01 + np.eye(n) * 1e-3
    H = np.zeros((m, n))
    H[:, 0:6] = rng.normal(size=(m, 6))       # the pose
    H[0:3, 12:15] = rng.normal(size=(3, 3))   # and two landmarks of the state
    H[3:6, 21:24] = rng.normal(size=(3, 3))
    R = np.kron(np.eye(2), np.diag([0.02, 0.03, 0.05]))
    y = rng.normal(size=m) * 0.1
    gain = ekf.ColumnGain(P, H, R)
    K, _, _ = ekf.kalman_gain(P, H, R)
    posterior = gain.posterior_cov()
    np.testing.assert_allclose(posterior, ekf.joseph_update(P, K, H, R), atol=1e-14)
    assert np.array_equal(posterior, posterior.T)
    assert np.linalg.eigvalsh(posterior)[0] > 0
    d = gain.correction(y)
    np.testing.assert_allclose(d, K @ y, atol=1e-14)
    assert gain.correction_quadratic(y) == pytest.approx(float(d @ np.linalg.solve(P, d)), rel=1e-9)
    assert gain.nis(y) == pytest.approx(float(y @ np.linalg.solve(H @ P @ H.T + R, y)), rel=1e-12)
    columns = np.r_[0:6, 12:15, 21:24]  # H given on its columns only: the same gain
    on_columns = ekf.ColumnGain(P, H[:, columns], R, columns)
    np.testing.assert_allclose(on_columns.posterior_cov(), posterior, atol=1e-15)
    np.testing.assert_allclose(on_columns.correction(y), d, atol=1e-15)


def test_observation_on_its_columns_equals_the_whole_jacobian():
    """observe_columns (H on the pose's and the seen landmarks' columns, state_columns) is the
    whole Jacobian's nonzero part: landmarks of the state seen in any order, twice, or held fixed."""
    rng = np.random.default_rng(14)
    x = _state(rng, m=5)
    sensor = _camera(measurement.DEPTH)
    rows = np.array([3, -1, 1, 3])
    xyz = np.where(rows[:, None] >= 0, x.L[np.maximum(rows, 0)], x.L[0] + 0.3)
    z_whole, H_whole = slam.observe(x, sensor, xyz, rows)
    columns, block = slam.state_columns(rows)
    np.testing.assert_array_equal(columns, np.r_[0:6, 9:12, 15:18])
    z, H = slam.observe_columns(x, sensor, xyz, block, columns.size)
    np.testing.assert_array_equal(z, z_whole)
    np.testing.assert_array_equal(H, H_whole[:, :, columns])
    np.testing.assert_array_equal(np.delete(H_whole, columns, axis=2), 0.0)


def test_so3_in_plain_floats_equals_geometry():
    """retract/difference's one-vector SO(3) forms equal geometry's batched ones, on both sides
    of the small-angle switch and near pi."""
    rng = np.random.default_rng(12)
    for angle in (1e-7, 5e-5, 2e-4, 1e-2, 1.0, 3.0):
        phi = rng.normal(size=3)
        phi *= angle / np.linalg.norm(phi)
        E, J = geometry.so3_exp_and_left_jacobian_one(phi)
        np.testing.assert_allclose(E, geometry.so3_exp(phi), atol=1e-15)
        np.testing.assert_allclose(J, slam.left_jacobian(phi), atol=1e-15)
        np.testing.assert_allclose(geometry.so3_left_jacobian_inverse_one(phi), np.linalg.inv(slam.left_jacobian(phi)), atol=1e-12)
        np.testing.assert_allclose(geometry.so3_log_one(E), geometry.so3_log(E), atol=1e-15)


def test_landmarks_entering_together_equal_one_at_a_time():
    """augmented_many (one new covariance for the landmarks entering at a pose) equals adding
    them one at a time, and marginalizing one out deletes its rows and columns."""
    rng = np.random.default_rng(13)
    x = _state(rng, m=2)
    A = rng.normal(size=(x.dim, x.dim))
    P = A @ A.T * 0.01 + np.eye(x.dim) * 1e-3
    xyz = rng.normal(size=(2, 3))
    B = np.stack([slam.world_prior_coefficients(x, p) for p in xyz])
    N = np.stack([np.diag([0.01, 0.02, 0.03]), np.diag([0.04, 0.05, 0.06])])
    x_one, P_one = slam.augmented(x, P, xyz[0], B[0], N[0])
    x_one, P_one = slam.augmented(x_one, P_one, xyz[1], B[1], N[1])
    x_both, P_both = slam.augmented_many(x, P, xyz, B, N)
    np.testing.assert_allclose(P_both, P_one, atol=1e-15)
    np.testing.assert_array_equal(x_both.L, x_one.L)
    x_less, P_less = slam.without_landmarks(x_both, P_both, np.array([False, True, False, False]))
    keep = np.r_[0:9, 12:18]
    np.testing.assert_array_equal(P_less, P_both[np.ix_(keep, keep)])
    np.testing.assert_array_equal(x_less.L, x_both.L[[0, 2, 3]])


def test_landmark_table_grows_keeping_its_rows():
    """The table's columns are views of arrays with room: appending past the room keeps every row,
    and the added ones start outside the state, unseen, not tentative."""
    from camloc.slam_landmarks import LandmarkTable

    table = LandmarkTable(np.arange(3), np.arange(9.0).reshape(3, 3), np.zeros((3, 3, 3)))
    for i in range(100):
        landmark = table.append(1000 + i)
        table.xyz[landmark] = [i, i, i]
    assert len(table) == 103 and table.num_mapped == 3
    np.testing.assert_array_equal(table.xyz[:3], np.arange(9.0).reshape(3, 3))
    np.testing.assert_array_equal(table.xyz[-1], [99.0, 99.0, 99.0])
    np.testing.assert_array_equal(table.ids[[0, 3, 102]], [0, 1000, 1099])
    assert not table.added[:3].any() and table.added[3:].all()
    assert (table.state_row[3:] == -1).all() and (table.last_seen[3:] == -1).all() and not table.tentative.any()
    table.drop(np.array([5]))
    assert 5 not in table.in_range(np.zeros(3), 1e9, None).tolist() and 6 in table.in_range(np.zeros(3), 1e9, None).tolist()


# -- a planar robot (its pose a turn about z at z = 0; a point2 sensor in the robot frame) ------------------

def _planar_state(rng, m=2):
    theta = rng.uniform(-np.pi, np.pi)
    R = geometry.so3_exp(np.array([0.0, 0.0, theta]))
    t = np.array([*rng.normal(size=2), 0.0])
    L = np.zeros((m, 3))
    L[:, :2] = t[:2] + rng.normal(size=(m, 2)) * 2.0
    return slam.SlamMean(R, t, L)


POINT2_SENSOR = CameraModel(np.eye(4), (1.0, 1.0, 0.0, 0.0), measurement.POINT2, measurement.ROBOT_FRAME_SENSOR)


def test_point2_observation_and_jacobians_match_finite_differences():
    """A point of the floor measured in the robot frame: the first two rows of R' (l - t), the third
    inert (0, with a zero Jacobian row); its Jacobian on every column of the error (also z, roll,
    pitch, which a planar run never moves) against finite differences of ``retract``."""
    rng = np.random.default_rng(11)
    x = _planar_state(rng)
    fixed = np.array([1.5, -0.7, 0.0])
    for row, xyz_of in [(0, lambda s: s.L[0]), (1, lambda s: s.L[1]), (-1, lambda s: fixed)]:
        z, H = slam.observe(x, POINT2_SENSOR, xyz_of(x)[None, :], np.array([row]))
        np.testing.assert_allclose(z[0, :2], (x.R.T @ (xyz_of(x) - x.t))[:2], atol=1e-12)
        assert z[0, 2] == 0.0 and np.all(H[0, 2] == 0.0)
        numeric = _numeric(lambda s: slam.observe(s, POINT2_SENSOR, xyz_of(s)[None, :], np.array([row]))[0][0], x, x.dim)
        np.testing.assert_allclose(H[0], numeric, atol=1e-6)
        assert np.abs(H[0]).max() > 0.5  # not a trivially zero Jacobian
        if row >= 0:  # no heading term for a landmark of the state, and nothing in its z
            np.testing.assert_allclose(H[0][:, 3:6], 0.0, atol=1e-12)
            assert np.all(H[0][:, 6 + 3 * row + 2] == 0.0)


def test_point2_inverse_observation_pins_the_landmark_on_the_floor():
    """The landmark a point2 measurement implies is on the floor (z = 0), measures back to it, its
    error is the pose's translation error (B = [I, 0], checked numerically) plus the measurement's
    noise in x and y only: zero variance in z, which no measurement reaches."""
    rng = np.random.default_rng(12)
    x = _planar_state(rng, m=0)
    z = np.array([1.2, -0.4, 0.0])
    R_z = np.array([[0.01, 0.002, 0.0], [0.002, 0.02, 0.0], [0.0, 0.0, 1.0]])  # the inert row's unit variance
    xyz, B, N = slam.inverse_observation(x, POINT2_SENSOR, z, R_z)
    assert xyz[2] == 0.0
    np.testing.assert_allclose(slam.observe(x, POINT2_SENSOR, xyz[None, :], np.array([-1]))[0][0], z, atol=1e-12)

    def landmark_error(s):
        l_new, _, _ = slam.inverse_observation(s, POINT2_SENSOR, z, R_z)
        return slam.difference(slam.SlamMean(s.R, s.t, l_new[None, :]), slam.SlamMean(x.R, x.t, xyz[None, :]))[6:9]
    np.testing.assert_allclose(B, _numeric(landmark_error, x, 6), atol=1e-6)
    assert np.all(N[2] == 0.0) and np.all(N[:, 2] == 0.0)
    np.testing.assert_allclose(N[:2, :2], x.R[:2, :2] @ R_z[:2, :2] @ x.R[:2, :2].T, atol=1e-15)


def test_planar_noise_and_start_stay_in_the_plane():
    """A planar robot's odometry noise (zero in z, roll, pitch) and start covariance give a P that
    is exactly zero on the error's z, roll and pitch rows, also with landmarks of any height in the
    state; the prediction with such a singular Q is exactly ``P + G Q G'``."""
    from camloc import planar

    rng = np.random.default_rng(13)
    x = _planar_state(rng, m=2)
    x.L[1, 2] = 1.3  # a camera's landmark, off the floor
    P = slam.planar_initial_cov(x, np.diag([0.01, 0.02, 0.03, 1e-3, 2e-3, 3e-3]))
    P = np.pad(P, (0, 6))
    P[6:, 6:] = np.eye(6) * 0.1
    P[8, :] = P[:, 8] = 0.0  # the floor landmark's z: pinned
    Q = planar.lifted_cov(np.diag([0.0025, 0.0016, 4e-4]))
    T_inc = planar.lift(np.array([0.3, 0.05, 0.1]))
    a, P1 = slam.predict(x, P, T_inc, Q)
    G = slam.noise_coefficients(a)
    np.testing.assert_allclose(P1, P + G @ Q @ G.T, atol=1e-15)
    assert np.all(P1[2:5] == 0.0) and np.all(P1[:, 2:5] == 0.0) and np.all(P1[8] == 0.0)
    assert P1[0, 0] > P[0, 0] and P1[5, 5] > P[5, 5]


MARKER_SENSOR = CameraModel(np.eye(4), (1.0, 1.0, 0.0, 0.0), measurement.MARKER, measurement.ROBOT_FRAME_SENSOR)


def test_marker_observation_and_jacobians_match_finite_differences():
    """A marker: its heading psi the landmark's third coordinate; z = (R' (l - t) in x and y,
    psi - theta). Its Jacobian against finite differences at a planar pose (the only kind a
    marker run has): d z_psi / d (its own third error, xi_theta_z) = (1, -1)."""
    rng = np.random.default_rng(14)
    x = _planar_state(rng)
    x.L[:, 2] = [0.7, -2.9]  # headings
    fixed = np.array([1.5, -0.7, 2.5])
    for row, xyz_of in [(0, lambda s: s.L[0]), (1, lambda s: s.L[1]), (-1, lambda s: fixed)]:
        z, H = slam.observe(x, MARKER_SENSOR, xyz_of(x)[None, :], np.array([row]))
        np.testing.assert_allclose(z[0, :2], (x.R.T @ (xyz_of(x) - x.t))[:2], atol=1e-12)
        assert z[0, 2] == pytest.approx(xyz_of(x)[2] - slam.heading(x))
        numeric = _numeric(lambda s: slam.observe(s, MARKER_SENSOR, xyz_of(s)[None, :], np.array([row]))[0][0], x, x.dim)
        planar_columns = [0, 1, 5] + ([6 + 3 * row, 7 + 3 * row, 8 + 3 * row] if row >= 0 else [])
        np.testing.assert_allclose(H[0][:, planar_columns], numeric[:, planar_columns], atol=1e-6)
        assert H[0, 2, 5] == -1.0 and (row < 0 or H[0, 2, 8 + 3 * row] == 1.0)


def test_marker_inverse_observation_and_wrapped_residuals():
    """A marker's inverse observation: on the floor, its world heading the robot's plus the
    measured one, its error the pose's translation error and xi_theta_z on the heading (B checked
    numerically); a heading residual across -pi/pi is wrapped (``wrapped_predictions``) and other
    kinds' predictions are returned bit for bit."""
    rng = np.random.default_rng(15)
    x = _planar_state(rng, m=0)
    z = np.array([1.2, -0.4, 0.3])
    R_z = np.diag([0.01, 0.02, 0.003])
    xyz, B, N = slam.inverse_observation(x, MARKER_SENSOR, z, R_z)
    assert xyz[2] == pytest.approx(slam.heading(x) + 0.3)
    np.testing.assert_allclose(slam.observe(x, MARKER_SENSOR, xyz[None, :], np.array([-1]))[0][0], z, atol=1e-12)

    def landmark_error(s):
        l_new, _, _ = slam.inverse_observation(s, MARKER_SENSOR, z, R_z)
        return slam.difference(slam.SlamMean(s.R, s.t, l_new[None, :]), slam.SlamMean(x.R, x.t, xyz[None, :]))[6:9]
    numeric = _numeric(landmark_error, x, 6)
    np.testing.assert_allclose(B[:2, [0, 1, 5]], numeric[:2, [0, 1, 5]], atol=1e-6)
    np.testing.assert_allclose(B[2, [0, 1, 5]], numeric[2, [0, 1, 5]], atol=1e-6)
    assert N[2, 2] == pytest.approx(0.003) and N[2, 0] == 0.0
    z_hat = np.array([[0.0, 0.0, np.pi - 0.1]])
    measured = np.array([[0.0, 0.0, -np.pi + 0.1]])
    np.testing.assert_allclose(measured - slam.wrapped_predictions(z_hat, measured, measurement.MARKER), [[0, 0, 0.2]], atol=1e-12)
    assert slam.wrapped_predictions(z_hat, measured, measurement.POINT2) is z_hat

# --- a tag's orientation (camloc.slam_tags) ------------------------------------------------------


def _tag_state(rng):
    """A pose, a landmark (row 0), a tag's centre (row 1) and its orientation (row 2)."""
    R = geometry.so3_exp(rng.normal(size=3) * 0.5)
    t = rng.normal(size=3)
    L = t + (R @ (np.array([4.0, 0.0, 0.0]) + rng.normal(size=(2, 3)) * 0.5).T).T
    return slam.SlamMean(R, t, np.vstack([L, rng.normal(size=3)]), np.array([False, False, True]))


def test_retract_and_difference_are_inverse_with_an_orientation():
    rng = np.random.default_rng(1)
    x = _tag_state(rng)
    delta = rng.normal(size=x.dim) * 0.3
    np.testing.assert_allclose(slam.difference(slam.retract(x, delta), x), delta, atol=1e-10)
    # the orientation's retraction is the model's: R_tag = Exp(xi_theta) Exp(xi_o) R^_tag
    moved = slam.retract(x, delta)
    expected = geometry.so3_exp(delta[3:6]) @ geometry.so3_exp(delta[12:15]) @ geometry.so3_exp(x.L[2])
    np.testing.assert_allclose(geometry.so3_exp(moved.L[2]), expected, atol=1e-12)


@pytest.mark.parametrize("in_state", [True, False])
def test_orientation_jacobian_matches_finite_differences(in_state):
    """d z_hat / d xi of a tag's orientation measurement, in the state (on its own block, nothing
    on the pose: the invariant error's point) or held fixed (on the heading)."""
    rng = np.random.default_rng(2)
    x = _tag_state(rng)
    sensor = _camera(measurement.TAG_ROTATION)
    fixed = rng.normal(size=3)
    z = geometry.so3_log(tags_prediction(x, sensor, x.L[2]) @ geometry.so3_exp(rng.normal(size=3) * 0.05))[None]
    block = np.array([2 + 2 if in_state else -1])
    rotvec_of = (lambda s: s.L[2][None]) if in_state else (lambda s: fixed[None])
    _, H = slam_tags.observe_orientations(x, sensor, rotvec_of(x), block, x.dim, z)
    numeric = _numeric(lambda s: slam_tags.observe_orientations(s, sensor, rotvec_of(s), block, s.dim, z)[0][0], x, x.dim)
    np.testing.assert_allclose(H[0], numeric, atol=1e-6)
    if in_state:
        np.testing.assert_allclose(H[0][:, 0:6], 0.0, atol=1e-12)


def tags_prediction(x, sensor, rotvec):
    from camloc import tags

    return tags.prediction(x.R, sensor.T_robot_camera[:3, :3], geometry.so3_exp(rotvec)[None])[0][0]


def test_inverse_orientation_has_no_pose_term_and_its_noise():
    rng = np.random.default_rng(3)
    x = _tag_state(rng)
    sensor = _camera(measurement.TAG_ROTATION)
    z = rng.normal(size=3)
    R_z = np.diag([1e-3, 2e-3, 3e-3])
    rotvec, B, N = slam_tags.inverse_orientation(x, sensor, z, R_z)
    np.testing.assert_allclose(tags_prediction(x, sensor, rotvec), geometry.so3_exp(z), atol=1e-12)

    def orientation_error(s):  # the new tag's error, placed from the perturbed pose, against x's
        placed, _, _ = slam_tags.inverse_orientation(s, sensor, z, R_z)
        a = slam.SlamMean(s.R, s.t, placed[None], np.array([True]))
        b = slam.SlamMean(x.R, x.t, rotvec[None], np.array([True]))
        return slam.difference(a, b)[6:9]
    np.testing.assert_allclose(_numeric(orientation_error, slam.SlamMean(x.R, x.t, np.zeros((0, 3))), 6), B, atol=1e-6)
    # the noise: n on the right of R_meas, d xi_o / d n numerically
    base = slam.SlamMean(x.R, x.t, rotvec[None], np.array([True]))
    W = np.stack([(slam.difference(slam.SlamMean(x.R, x.t, slam_tags.inverse_orientation(
        x, sensor, geometry.so3_log(geometry.so3_exp(z) @ geometry.so3_exp(e)), R_z)[0][None], np.array([True])), base)[6:9]
        - slam.difference(slam.SlamMean(x.R, x.t, slam_tags.inverse_orientation(
            x, sensor, geometry.so3_log(geometry.so3_exp(z) @ geometry.so3_exp(-e)), R_z)[0][None], np.array([True])), base)[6:9])
        / 2e-6 for e in np.eye(3) * 1e-6], axis=1)
    np.testing.assert_allclose(N, W @ R_z @ W.T, atol=1e-10)


def test_orientation_prior_and_world_covariance_round_trip():
    """A tag's orientation entered with a world prior independent of the pose reads back that
    prior (``orientation_world_cov``), and its coefficients are the first order of its error."""
    rng = np.random.default_rng(5)
    x = slam.SlamMean(geometry.so3_exp(rng.normal(size=3)), rng.normal(size=3), np.zeros((0, 3)))
    P = slam.initial_cov(x, np.diag([0.01, 0.02, 0.03, 1e-3, 2e-3, 3e-3]))
    prior = np.diag([0.01, 0.02, 0.03])
    rotvec = rng.normal(size=3)
    x2, P2 = slam.augmented_many(x, P, rotvec[None], slam_tags.prior_coefficients()[None], prior[None], np.array([True]))
    np.testing.assert_allclose(slam_tags.orientation_world_cov(P2, 0), prior, atol=1e-12)
    assert x2.orientation.tolist() == [True]

    # the prior's coefficients: the pose's heading moved by xi_theta, the tag held in the world
    d = np.zeros(6)
    d[3:6] = rng.normal(size=3) * 1e-6
    xi_o = slam_tags.turn_between(rotvec[None], rotvec[None], geometry.so3_exp(d[3:6]))[0]  # Exp(xi_theta) Exp(xi_o) R = R
    np.testing.assert_allclose(xi_o, slam_tags.prior_coefficients() @ d, atol=1e-12)
    # the world error's coefficients (e = xi_theta + xi_o), by finite differences of the retraction
    e_of = lambda s: geometry.so3_log(geometry.so3_exp(s.L[0]) @ geometry.so3_exp(rotvec).T)  # noqa: E731
    A = _numeric(e_of, x2, x2.dim)
    expected = np.zeros((3, x2.dim))
    expected[:, 3:6], expected[:, 6:9] = np.eye(3), np.eye(3)
    np.testing.assert_allclose(A, expected, atol=1e-6)


def test_unambiguous_leaves_out_a_pair_another_set_explains_as_well():
    """Two landmarks that fit one observation as well (one jointly compatible set as large each):
    neither is taken; a lone fit is kept."""
    from camloc.slam_association import AMBIGUITY_MARGIN, Candidate, jcbb, unambiguous

    n = 12
    P = np.eye(n) * 0.01
    H = np.zeros((3, n))
    H[:, 0:3] = -np.eye(3)
    R = np.eye(3) * 0.01
    y = np.array([0.02, 0.0, 0.0])
    a, b = Candidate(0, 100, y, H, np.zeros((3, 3)), R, 3, 1.0), Candidate(0, 101, -y, H, np.zeros((3, 3)), R, 3, 1.2)
    lone = Candidate(1, 102, y, H, np.zeros((3, 3)), R, 3, 1.0)
    candidates = [[a, b], [lone]]
    chosen = jcbb(P, candidates, 0.99)
    assert len(chosen) == 2
    kept = unambiguous(P, candidates, chosen, 0.99, AMBIGUITY_MARGIN, np.zeros(2, np.int64))
    assert [c.landmark for c in kept] == [102]
    # the second landmark far costlier: the first is not ambiguous
    b_far = Candidate(0, 101, -y, H, np.zeros((3, 3)), R, 3, 1.0 + AMBIGUITY_MARGIN + 1.0)
    candidates = [[a, b_far], [lone]]
    kept = unambiguous(P, candidates, jcbb(P, candidates, 0.99), 0.99, AMBIGUITY_MARGIN, np.zeros(2, np.int64))
    assert sorted(c.landmark for c in kept) == [100, 102]
