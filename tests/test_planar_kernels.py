"""The planar robot's compiled kernels (``camloc.kernels.planar``, and the steps that pick the model by
the state's size: ``kernels.state``, ``motion.predict``, ``camera.observe_pairs``,
``view.widened_view``, ``view.landmarks_near``) against their numpy twins in ``camloc.planar`` (whose
Jacobians ``tests/test_planar.py`` checks against finite differences) and the numpy engine's
candidate query. The whole runs are tied by ``tests/test_engine_parity.py``."""

from __future__ import annotations

import numpy as np
import pytest

from camloc import geometry, planar
from camloc.constants import MAX_HALF_ANGLE_DEG, WIDENED_VIEW_SIGMAS
from camloc.dataset import LANDMARK_MARKER, LANDMARK_POINT2
from camloc.kernels import _jit, camera, motion, state, view
from camloc.kernels import planar as kernel_planar
from camloc.localizer_config import LocalizerConfig
from camloc.measurement import DEPTH, DISPARITY, MARKER, PIXEL, POINT2
from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar

camera, motion, state, view, kernel_planar = (_jit.FromPython(m) for m in (camera, motion, state, view, kernel_planar))

RTOL = 1e-10
# a camera on the robot looking ahead (z forward, x right, y down), off its centre
T_ROBOT_CAMERA = geometry.pose_from_euler(np.array([0.1, 0.05, 0.3, -np.pi / 2, 0.0, -np.pi / 2]))


def _random_planar_state(rng):
    return np.r_[rng.normal(0, 3, 2), rng.uniform(-np.pi, np.pi)]


def test_motion_and_prediction_match_the_numpy_model(rng):
    for _ in range(20):
        x, u = _random_planar_state(rng), np.r_[rng.normal(0, 0.5, 2), rng.uniform(-np.pi, np.pi)]
        T = planar.lift(u)
        x_next, F, G = kernel_planar.planar_motion(x, T)
        x_ref, F_ref, G_ref = planar.motion(x, T)
        np.testing.assert_allclose(x_next, x_ref, rtol=RTOL, atol=1e-14)
        np.testing.assert_allclose(F, F_ref, rtol=RTOL, atol=1e-14)
        np.testing.assert_array_equal(G, G_ref)
        A = rng.normal(0, 0.3, (3, 3))
        P, Q = A @ A.T + 0.01 * np.eye(3), np.diag(rng.uniform(1e-4, 1e-2, 6))
        x_predicted, P_predicted = motion.predict(x, P, T, Q)
        np.testing.assert_allclose(x_predicted, x_ref, rtol=RTOL, atol=1e-14)
        np.testing.assert_allclose(P_predicted, F_ref @ P @ F_ref.T + G_ref @ Q @ G_ref.T, rtol=RTOL, atol=1e-15)
        np.testing.assert_array_equal(P_predicted, P_predicted.T)


def test_retract_and_difference_pick_the_model_by_the_state_size(rng):
    for _ in range(20):
        x, delta = _random_planar_state(rng), rng.normal(0, 0.7, 3)
        moved = state.retract(x, delta)
        np.testing.assert_allclose(moved, planar.retract(x, delta), rtol=RTOL, atol=1e-14)
        np.testing.assert_allclose(state.difference(moved, x), planar.difference(moved, x), rtol=RTOL, atol=1e-14)
        np.testing.assert_allclose(state.difference(moved, x), np.r_[delta[:2], geometry.wrap_angle(delta[2])], atol=1e-12)
        euler = np.r_[rng.normal(0, 2, 3), rng.uniform(-1, 1, 3)]
        step = rng.normal(0, 0.3, 6)
        np.testing.assert_array_equal(state.retract(euler, step), _jit.from_python(_euler_retract())(euler, step))


def _euler_retract():
    from camloc.kernels import rotation

    return rotation.retract


def test_the_worked_marker_example():
    # issue 37: the robot at (0.7, 0.5, 45 deg) sees the marker at (0.983, 0.783, 0 deg) at (0.4, 0.0, -45 deg)
    x = np.array([0.7, 0.5, np.radians(45.0)])
    landmarks = np.array([[0.7 + 0.4 / np.sqrt(2), 0.5 + 0.4 / np.sqrt(2), 0.0, 0.0]])
    z_hat, _ = camera.observe_pairs(x, landmarks, np.zeros(1, np.int64), np.eye(3)[None].copy(), np.zeros((1, 3)),
                                    np.array([[1.0, 1.0, 0.0, 0.0, MARKER]]))
    np.testing.assert_allclose(landmarks[0, :2], [0.983, 0.783], atol=5e-4)
    np.testing.assert_allclose(z_hat[0], [0.4, 0.0, -np.pi / 4], atol=1e-12)


@pytest.mark.parametrize("kind", [POINT2, MARKER])
def test_planar_measurements_match_the_numpy_model(rng, kind):
    for _ in range(10):
        x = _random_planar_state(rng)
        m = 6
        landmarks = np.c_[x[:2] + rng.normal(0, 2, (m, 2)), np.zeros(m), rng.uniform(-np.pi, np.pi, m)]
        z_hat, H = camera.observe_pairs(x, landmarks, np.zeros(m, np.int64), np.eye(3)[None].copy(), np.zeros((1, 3)),
                                        np.array([[1.0, 1.0, 0.0, 0.0, kind]]))
        z_ref, H_ref = planar.observe_planar(x, landmarks[:, :2], landmarks[:, 3], kind)
        np.testing.assert_allclose(z_hat, z_ref, rtol=RTOL, atol=1e-14)
        np.testing.assert_allclose(H, H_ref, rtol=RTOL, atol=1e-14)


@pytest.mark.parametrize("kind", [DEPTH, PIXEL, DISPARITY])
def test_a_camera_on_the_planar_robot_matches_the_numpy_model(rng, kind):
    intrinsics = (520.0, 510.0, 320.0, 240.0)
    for _ in range(10):
        x = _random_planar_state(rng)
        heading = np.array([np.cos(x[2]), np.sin(x[2])])
        ahead = x[:2] + np.outer(rng.uniform(2.0, 5.0, 5), heading) + rng.normal(0, 0.5, (5, 2))
        landmarks = np.c_[ahead, rng.uniform(-0.5, 1.0, 5)]
        z_hat, H = camera.observe_pairs(x, landmarks, np.zeros(5, np.int64), T_ROBOT_CAMERA[None, :3, :3].copy(),
                                        T_ROBOT_CAMERA[None, :3, 3].copy(), np.array([[*intrinsics, kind]]))
        z_ref, H_ref = planar.observe_camera(x, T_ROBOT_CAMERA, intrinsics, landmarks, kind)
        np.testing.assert_allclose(z_hat, z_ref, rtol=RTOL, atol=1e-9)
        np.testing.assert_allclose(H, H_ref, rtol=RTOL, atol=1e-9)


def test_a_marker_residual_is_wrapped_as_numpy_wraps_it(rng):
    psi = rng.uniform(-np.pi, np.pi, 50)
    predicted = rng.uniform(-np.pi, np.pi, 50)
    for kind in (MARKER, POINT2, DEPTH):
        got = np.array([[kernel_planar.wrapped_residual(float(kind), a, float(p - q)) for a in range(3)] for p, q in zip(psi, predicted)])
        y = np.repeat((psi - predicted)[:, None], 3, axis=1)
        np.testing.assert_allclose(got, planar.wrap_residuals(y, kind), rtol=RTOL, atol=1e-15)
    assert np.abs(np.array([kernel_planar.wrapped_residual(float(MARKER), 2, float(p - q)) for p, q in zip(psi, predicted)])).max() <= np.pi


def test_the_planar_widened_view(rng):
    for _ in range(10):
        A = rng.normal(0, 0.3, (3, 3))
        P = A @ A.T
        margin, half_angle = view.widened_view(P, 0.6)
        assert margin == pytest.approx(WIDENED_VIEW_SIGMAS * np.sqrt(np.linalg.eigvalsh(P[:2, :2])[-1]), rel=RTOL)
        assert half_angle == pytest.approx(max(0.6, min(0.6 + WIDENED_VIEW_SIGMAS * np.sqrt(P[2, 2]), np.radians(MAX_HALF_ANGLE_DEG))), rel=RTOL)


def test_a_planar_sensors_candidates_are_its_kind_within_its_range():
    from camloc.scene import build_scene

    dataset = simulate_planar(PlanarSimulationConfig(sensors="points,markers,cameras", poses=60), seed=3)
    scene = build_scene(dataset, LocalizerConfig(filter="se2"))
    radius = scene.view_limits[5]
    assert radius > 0.0
    checked = 0
    for k in range(0, 60, 7):
        x = _truth_state(dataset, k)
        for kind, wanted in ((POINT2, LANDMARK_POINT2), (MARKER, LANDMARK_MARKER)):
            got = view.landmarks_near(scene, x[0], x[1], radius, float(kind))
            near = np.hypot(*(dataset.landmark_xyz[:, :2] - x[:2]).T) <= radius
            expected = np.flatnonzero(near & (dataset.landmark_kind == wanted))
            np.testing.assert_array_equal(got, expected)
            checked += expected.size
    assert checked > 20


def _truth_state(dataset, k):
    T = geometry.pose_from_quat(dataset.truth_xyz[k], dataset.truth_quat_xyzw[k])
    return planar.flatten(T)
