"""A tag's orientation in the invariant EKF-SLAM (camloc.slam_tags): every Jacobian against finite
differences of the state's retraction, the prediction's propagation, the inverse observation and
the priors' coefficients."""

import numpy as np
import pytest

from camloc import geometry, measurement, slam, slam_tags
from camloc.sensors import CameraModel

STEP = 1e-6


def _state(rng):
    """A pose, a landmark (row 0), a tag's centre (row 1) and its orientation (row 2)."""
    R = geometry.so3_exp(rng.normal(size=3) * 0.5)
    t = rng.normal(size=3)
    L = t + (R @ (np.array([4.0, 0.0, 0.0]) + rng.normal(size=(2, 3)) * 0.5).T).T
    rotvec = rng.normal(size=3)
    return slam.SlamMean(R, t, np.vstack([L, rotvec]), np.array([False, False, True]))


def _camera():
    Rc = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rc, [0.1, -0.05, 0.2]
    return CameraModel(T, (500.0, 510.0, 320.0, 240.0), measurement.TAG_ROTATION, 0)


def _numeric(f, x, dim):
    columns = []
    for i in range(dim):
        e = np.zeros(dim)
        e[i] = STEP
        columns.append((f(slam.retract(x, e)) - f(slam.retract(x, -e))) / (2 * STEP))
    return np.stack(columns, axis=-1)


def test_retract_and_difference_are_inverse_with_an_orientation():
    rng = np.random.default_rng(1)
    x = _state(rng)
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
    x = _state(rng)
    sensor = _camera()
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
    x = _state(rng)
    sensor = _camera()
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


def test_prediction_propagates_an_orientation_with_identity_and_its_noise():
    """F = I for the tag's orientation too, and the increment's right perturbation w moves its
    error by -R w_theta (``noise_coefficients``)."""
    rng = np.random.default_rng(4)
    x = _state(rng)
    T_inc = geometry.make_pose(geometry.so3_exp(rng.normal(size=3) * 0.2), rng.normal(size=3))
    xi = rng.normal(size=x.dim) * 1e-5
    a, _ = slam.predict(x, np.eye(x.dim), T_inc, np.eye(6))
    b, _ = slam.predict(slam.retract(x, xi), np.eye(x.dim), T_inc, np.eye(6))
    np.testing.assert_allclose(slam.difference(b, a), xi, atol=1e-9)
    w = rng.normal(size=6) * 1e-5
    c, _ = slam.predict(x, np.eye(x.dim), T_inc @ geometry.make_pose(geometry.so3_exp(w[3:6]), w[0:3]), np.eye(6))
    np.testing.assert_allclose(slam.difference(c, a), slam.noise_coefficients(a) @ w, atol=1e-9)


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
