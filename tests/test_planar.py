"""The planar (SE(2)) models and filter (``camloc.planar``, ``filters.SE2Filter``): the worked
marker example, every Jacobian against central finite differences through the filter's
retraction, and the retraction, difference and residual wrapping."""

from __future__ import annotations

import math

import numpy as np
import pytest

from camloc import geometry, measurement, models, planar
from camloc.filters import SE2Filter
from camloc.measurement import DEPTH, DISPARITY, MARKER, PIXEL, POINT2

STEP = 1e-6


def numeric_jacobian(function, x: np.ndarray, size: int, retract) -> np.ndarray:
    """d function(retract(x, d)) / d d at d = 0, central differences; function returns a vector."""
    columns = []
    for i in range(size):
        d = np.zeros(size)
        d[i] = STEP
        plus, minus = function(retract(x, d)), function(retract(x, -d))
        columns.append((plus - minus) / (2 * STEP))
    return np.stack(columns, axis=-1)


def random_state(rng) -> np.ndarray:
    return np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-math.pi, math.pi)])


def test_worked_marker_example():
    """Robot at (0.7, 0.5), heading 45 deg, sees a marker at (0.4 m, 0 m, -45 deg) in its own
    frame: the marker is at (0.7 + 0.4 cos 45, 0.5 + 0.4 sin 45, 0) = (0.983, 0.783, 0 deg) in the
    world, and the observation model gives the measurement back from that pose."""
    x = np.array([0.7, 0.5, math.radians(45.0)])
    z = np.array([0.4, 0.0, math.radians(-45.0)])
    marker = planar.compose(x, z)
    assert marker == pytest.approx([0.7 + 0.4 / math.sqrt(2), 0.5 + 0.4 / math.sqrt(2), 0.0], abs=1e-12)
    assert marker[:2] == pytest.approx([0.983, 0.783], abs=5e-4)
    z_hat, _ = planar.observe_planar(x, marker[None, :2], marker[None, 2], MARKER)
    assert z_hat[0] == pytest.approx(z, abs=1e-12)
    # the textbook form of h, written out
    dx, dy, psi = marker[0] - x[0], marker[1] - x[1], x[2]
    textbook = [dx * math.cos(psi) + dy * math.sin(psi), -dx * math.sin(psi) + dy * math.cos(psi), marker[2] - psi]
    assert z_hat[0] == pytest.approx(textbook, abs=1e-12)
    # the lecture's (1.27, 1.07) is a marker 0.8 m ahead, not 0.4 m
    assert planar.compose(x, np.array([0.8, 0.0, 0.0]))[:2] == pytest.approx([1.27, 1.07], abs=6e-3)


def test_retract_and_difference_are_inverse(rng):
    for _ in range(20):
        x, delta = random_state(rng), rng.normal(scale=0.3, size=3)
        assert planar.difference(planar.retract(x, delta), x) == pytest.approx(delta, abs=1e-12)


def test_lift_and_flatten_are_inverse(rng):
    x = np.array([random_state(rng) for _ in range(10)])
    assert planar.flatten(planar.lift(x)) == pytest.approx(x, abs=1e-12)
    T = planar.lift(x)
    assert np.allclose(T[:, :3, :3], geometry.quat_to_matrix(planar.quat_of_heading(x[:, 2])))


@pytest.mark.parametrize("trial", range(5))
def test_motion_jacobians(rng, trial):
    x, u = random_state(rng), np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1)])
    T_increment = planar.lift(u)
    x_next, F, G = planar.motion(x, T_increment)
    assert x_next == pytest.approx(planar.flatten(planar.lift(x) @ T_increment), abs=1e-12)
    F_numeric = numeric_jacobian(lambda s: planar.difference(planar.motion(s, T_increment)[0], x_next), x, 3, planar.retract)
    assert F == pytest.approx(F_numeric, abs=1e-6)
    # the increment's noise: a right perturbation of the lifted increment, (translation, rotation vector)
    w_numeric = numeric_jacobian(lambda w: planar.difference(planar.motion(x, T_increment @ geometry.make_pose(
        geometry.so3_exp(w[3:6]), w[0:3]))[0], x_next), np.zeros(6), 6, lambda a, d: a + d)
    assert G[:, list(planar.PLANAR_AXES)] == pytest.approx(w_numeric[:, list(planar.PLANAR_AXES)], abs=1e-6)


def _camera():
    from camloc.simulate import REAL_MOUNT_QUAT_XYZW, REAL_MOUNT_TRANSLATION

    return geometry.pose_from_quat(REAL_MOUNT_TRANSLATION, REAL_MOUNT_QUAT_XYZW), (1.0, 1.0, 0.5, 0.5)


@pytest.mark.parametrize("kind", [POINT2, MARKER, DEPTH, PIXEL, DISPARITY])
@pytest.mark.parametrize("trial", range(3))
def test_observation_jacobians(rng, kind, trial):
    """H of every kind the SE(2) filter observes, against central differences through its retraction."""
    se2 = SE2Filter()
    x = random_state(rng)
    T_rc, K = _camera()
    if kind in measurement.PLANAR_KINDS:
        landmarks = np.column_stack([x[:2] + rng.uniform(-3, 3, size=(4, 2)), np.zeros(4)])
    else:  # in front of the forward camera: ahead of the robot, above and below its height
        ahead = planar.lift(x)[:3, :3] @ np.array([2.0, 0.0, 0.0])
        landmarks = np.array([x[0], x[1], 0.3]) + ahead + rng.uniform(-0.5, 0.5, size=(4, 3))
    heading = rng.uniform(-math.pi, math.pi, size=4)
    z_hat, H = se2.observe(x, T_rc, K, landmarks, kind, heading=heading)
    H_numeric = numeric_jacobian(
        lambda s: planar.wrap_residuals(se2.observe(s, T_rc, K, landmarks, kind, heading=heading)[0] - z_hat, kind).ravel(),
        x, 3, se2.retract).reshape(4, 3, 3)
    assert H == pytest.approx(H_numeric, abs=1e-5)


def test_camera_on_a_planar_robot_is_the_3d_model_at_the_lifted_pose(rng):
    x = random_state(rng)
    T_rc, K = _camera()
    landmarks = np.array([x[0], x[1], 0.3]) + planar.lift(x)[:3, :3] @ np.array([2.0, 0.0, 0.0]) + rng.uniform(-0.3, 0.3, (3, 3))
    z_hat, _ = SE2Filter().observe(x, T_rc, K, landmarks, DEPTH)
    z_3d, _ = models.observe_se3(planar.lift(x), T_rc, K, landmarks, DEPTH)
    assert z_hat == pytest.approx(z_3d, abs=1e-12)


def test_marker_residuals_are_wrapped():
    """A marker seen at psi = +179 deg and predicted at -179 deg is 2 deg off, not 358."""
    y = np.array([[0.0, 0.0, math.radians(179.0) - math.radians(-179.0)]])
    assert planar.wrap_residuals(y, np.array([MARKER]))[0, 2] == pytest.approx(math.radians(-2.0))
    same = np.array([[0.1, 0.2, 7.0]])
    assert planar.wrap_residuals(same, np.array([DEPTH])) is same  # camera kinds: untouched


def test_pose_covariance_is_the_world_frame_error(rng):
    """pose_cov maps the right perturbation's covariance to that of (world position, world yaw)
    in the lifted (N, 6, 6) layout; checked by sampling."""
    se2 = SE2Filter()
    x = random_state(rng)
    A = rng.normal(size=(3, 3))
    P = A @ A.T * 0.01 + np.eye(3) * 1e-3
    cov = se2.pose_cov(x[None], P[None])[0]
    samples = rng.multivariate_normal(np.zeros(3), P, size=100_000)
    T = planar.lift(x)
    errors = np.array([geometry.pose_error_vector(T, planar.lift(planar.retract(x, d))) for d in samples[:20_000]])
    assert planar.planar_block(cov) == pytest.approx(np.cov(errors[:, list(planar.PLANAR_AXES)].T), rel=0.05, abs=2e-5)
    assert np.all(cov[2, :] == 0.0) and np.all(cov[3:5, :] == 0.0)
