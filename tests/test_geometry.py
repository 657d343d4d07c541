"""Geometry: conventions, round trips and the Euler rate matrix against finite differences."""

import numpy as np
import pytest

from camloc import geometry


def random_rpy(rng, n, max_pitch_deg=85.0):
    return np.column_stack([
        rng.uniform(-np.pi, np.pi, n),
        rng.uniform(-np.radians(max_pitch_deg), np.radians(max_pitch_deg), n),
        rng.uniform(-np.pi, np.pi, n),
    ])


def test_euler_convention_is_z_y_x():
    roll, pitch, yaw = 0.3, -0.4, 1.2
    Rx = np.array([[1, 0, 0], [0, np.cos(roll), -np.sin(roll)], [0, np.sin(roll), np.cos(roll)]])
    Ry = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]])
    Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    np.testing.assert_allclose(geometry.euler_to_matrix(np.array([roll, pitch, yaw])), Rz @ Ry @ Rx, atol=1e-12)


def test_euler_formulas_match_scipy(rng):
    from scipy.spatial.transform import Rotation

    rpy = random_rpy(rng, 500, max_pitch_deg=89.0)
    expected = Rotation.from_euler("ZYX", rpy[:, ::-1]).as_matrix()
    np.testing.assert_allclose(geometry.euler_to_matrix(rpy), expected, atol=1e-12)
    np.testing.assert_allclose(geometry.matrix_to_euler(expected), rpy, atol=1e-7)
    np.testing.assert_allclose(geometry.euler_to_matrix(rpy[0]), expected[0], atol=1e-12)


def test_quaternion_formulas_match_scipy(rng):
    # camloc writes them out (scipy's import is a fifth of a small run); they must be scipy's to rounding
    from scipy.spatial.transform import Rotation

    quat = rng.normal(size=(2000, 4)) * rng.uniform(0.1, 10.0, size=(2000, 1))  # not unit: both normalize
    np.testing.assert_allclose(geometry.quat_to_matrix(quat), Rotation.from_quat(quat).as_matrix(), atol=1e-15)
    np.testing.assert_allclose(geometry.quat_to_matrix(quat[:3].reshape(3, 1, 4)), Rotation.from_quat(quat[:3]).as_matrix()[:, None], atol=1e-15)
    # every branch of Shepperd's method: random rotations, and half-turns about each axis and between them
    half_turns = np.pi * np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.6, 0.8, 0], [0, 0.6, -0.8], [0.48, 0.6, 0.64]])
    R = np.concatenate([Rotation.random(3000, random_state=1).as_matrix(), Rotation.from_rotvec(half_turns).as_matrix(), np.eye(3)[None]])
    expected = Rotation.from_matrix(R).as_quat()
    expected *= np.where(expected[:, 3:4] < 0.0, -1.0, 1.0)
    quat = geometry.matrix_to_quat(R)
    assert np.all(quat[:, 3] >= 0.0) and geometry.matrix_to_quat(R[0]).shape == (4,)
    on_the_half_turn = np.abs(expected[:, 3]) < 1e-12  # q and -q: both w = 0, either sign is the rotation
    np.testing.assert_allclose(quat[~on_the_half_turn], expected[~on_the_half_turn], atol=1e-15)
    np.testing.assert_allclose(np.abs(quat[on_the_half_turn]), np.abs(expected[on_the_half_turn]), atol=1e-15)
    np.testing.assert_allclose(geometry.quat_to_matrix(quat), R, atol=1e-14)


def test_euler_and_quaternion_round_trips(rng):
    rpy = random_rpy(rng, 200)
    np.testing.assert_allclose(geometry.matrix_to_euler(geometry.euler_to_matrix(rpy)), rpy, atol=1e-9)
    quat = geometry.euler_to_quat(rpy)
    assert np.all(quat[:, 3] >= 0)
    np.testing.assert_allclose(geometry.quat_to_euler(quat), rpy, atol=1e-9)


def test_euler_rate_matrix_matches_finite_differences(rng):
    for rpy in random_rpy(rng, 20, max_pitch_deg=80):
        R = geometry.euler_to_matrix(rpy)
        E = geometry.euler_rate_matrix(rpy)
        numeric = np.zeros((3, 3))
        h = 1e-6
        for i in range(3):
            d = np.zeros(3)
            d[i] = h
            plus = geometry.so3_log(R.T @ geometry.euler_to_matrix(rpy + d))
            minus = geometry.so3_log(R.T @ geometry.euler_to_matrix(rpy - d))
            numeric[:, i] = (plus - minus) / (2 * h)
        np.testing.assert_allclose(E, numeric, atol=1e-7)


def test_pose_inverse_and_relative(rng):
    T = geometry.pose_from_euler(np.column_stack([rng.normal(size=(10, 3)), random_rpy(rng, 10)]))
    np.testing.assert_allclose(geometry.se3_inverse(T) @ T, np.broadcast_to(np.eye(4), T.shape), atol=1e-12)
    T_a_b = geometry.relative_se3(T[0], T[1])
    np.testing.assert_allclose(T[0] @ T_a_b, T[1], atol=1e-12)


def test_pose_error_vector_recovers_a_known_perturbation():
    T_est = geometry.pose_from_euler(np.array([1.0, 2.0, 3.0, 0.1, 0.2, 0.3]))
    delta = np.array([0.01, -0.02, 0.03, 0.004, -0.005, 0.006])
    T_true = geometry.make_pose(geometry.so3_exp(delta[3:]) @ T_est[:3, :3], T_est[:3, 3] + delta[:3])
    np.testing.assert_allclose(geometry.pose_error_vector(T_est, T_true), delta, atol=1e-12)


@pytest.mark.parametrize("angle", [-3.5, -np.pi, 0.0, np.pi - 1e-9, 7.0])
def test_wrap_angle_stays_in_range(angle):
    wrapped = geometry.wrap_angle(angle)
    assert -np.pi <= wrapped < np.pi
    assert np.isclose(np.cos(wrapped), np.cos(angle)) and np.isclose(np.sin(wrapped), np.sin(angle))


def test_wrap_angle_of_a_float_is_numpys_to_the_bit(rng):
    angles = np.concatenate([rng.normal(scale=s, size=2000) for s in (1e-8, 1.0, 3.2, 10.0, 1e3, 1e8)]
                            + [[0.0, -0.0, np.pi, -np.pi, 2 * np.pi, -2 * np.pi, np.nextafter(np.pi, 0.0), np.nextafter(-np.pi, 0.0),
                                5e-324, 1e300, np.inf, -np.inf, np.nan]])
    with np.errstate(invalid="ignore"):
        expected = geometry.wrap_angle(angles)
    found = np.array([geometry.wrap_angle_float(a) for a in angles.tolist()])
    np.testing.assert_array_equal(found.view(np.int64)[~np.isnan(expected)], expected.view(np.int64)[~np.isnan(expected)])
    assert np.isnan(found[np.isnan(expected)]).all()


@pytest.mark.parametrize("scale", [1e-7, 1e-3, 0.5, 3.0])
def test_so3_exp_and_log_match_scipy(rng, scale):
    from scipy.spatial.transform import Rotation

    rotvec = rng.normal(size=(200, 3))
    rotvec *= scale / np.linalg.norm(rotvec, axis=1, keepdims=True) * rng.uniform(0.2, 1.0, (200, 1))
    rotvec = rotvec[np.linalg.norm(rotvec, axis=1) < np.pi]
    np.testing.assert_allclose(geometry.so3_exp(rotvec), Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(geometry.so3_log(Rotation.from_rotvec(rotvec).as_matrix()), rotvec, atol=1e-9)


def test_so3_log_near_pi():
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    for angle in (np.pi - 1e-6, np.pi - 1e-2, np.pi):
        phi = geometry.so3_log(geometry.so3_exp(angle * axis))
        assert np.linalg.norm(phi) == pytest.approx(angle, abs=1e-8)
        assert abs(abs(phi @ axis) - angle) < 1e-7


def test_euler_rate_matrix_inverse_is_the_inverse(rng):
    for _ in range(20):
        rpy = rng.uniform([-np.pi, -1.4, -np.pi], [np.pi, 1.4, np.pi])
        np.testing.assert_allclose(geometry.euler_rate_matrix_inverse(rpy) @ geometry.euler_rate_matrix(rpy), np.eye(3), atol=1e-12)


def test_single_item_fast_paths_match_the_batched_forms(rng):
    rpy = rng.uniform([-np.pi, -1.4, -np.pi], [np.pi, 1.4, np.pi], size=(5, 3))
    R = geometry.euler_to_matrix(rpy)
    for k in range(5):
        np.testing.assert_allclose(geometry.euler_to_matrix(rpy[k]), R[k], atol=1e-15)
        np.testing.assert_allclose(geometry.matrix_to_euler(R[k]), geometry.matrix_to_euler(R[k : k + 1])[0], atol=1e-14)
        np.testing.assert_allclose(geometry.euler_rate_matrix(rpy[k]), geometry.euler_rate_matrix(rpy[k : k + 1])[0], atol=1e-15)
        np.testing.assert_allclose(geometry.hat(rpy[k]), geometry.hat(rpy[k : k + 1])[0], atol=0)


def test_single_item_fast_paths_give_nan_for_non_finite_input_as_the_batched_forms_do():
    with np.errstate(invalid="ignore"):
        for rpy in (np.array([np.inf, 0.1, 0.2]), np.array([0.1, np.nan, 0.2])):
            np.testing.assert_array_equal(np.isnan(geometry.euler_to_matrix(rpy)), np.isnan(geometry.euler_to_matrix(rpy[None])[0]))
            np.testing.assert_array_equal(np.isnan(geometry.euler_rate_matrix(rpy)), np.isnan(geometry.euler_rate_matrix(rpy[None])[0]))
        R = np.full((3, 3), np.nan)
        assert np.isnan(geometry.matrix_to_euler(R)).all() and np.isnan(geometry.matrix_to_euler(R[None])).all()
        R = np.eye(3)
        R[2, 0] = 1.0 + 1e-12  # rounding past the domain of arcsin: clipped, pitch -90 deg
        np.testing.assert_allclose(geometry.matrix_to_euler(R), geometry.matrix_to_euler(R[None])[0])


@pytest.mark.parametrize("scale", [1e200, 1.0, 1e-200])
def test_normalized_quaternions_of_any_representable_length(scale):
    # the squares of components beyond 1e154 overflow and those below 1e-162 underflow
    quat = np.array([[1.0, -2.0, 2.0, 4.0], [0.0, 0.0, 0.0, 3.0]]) * scale
    np.testing.assert_allclose(geometry.normalized_quaternions(quat), [[0.2, -0.4, 0.4, 0.8], [0.0, 0.0, 0.0, 1.0]], rtol=1e-15)


def test_the_euler_filter_s_batched_differences_are_its_difference_row_by_row_to_the_bit(rng):
    # The numpy beam's pruning compares a candidate with every kept state at once
    # (beam_expansion._KeptAtOnce); its answers must be same_state's one at a time.
    from camloc.filters import make_filter

    euler = make_filter("euler")
    a = rng.normal(scale=4.0, size=6)
    b = np.vstack([rng.normal(scale=4.0, size=(200, 6)), a, a + np.array([0, 0, 0, 2 * np.pi, -np.pi, np.pi])])
    found = euler.differences(a, b)
    expected = np.array([euler.difference(a, row) for row in b])
    np.testing.assert_array_equal(found.view(np.int64), expected.view(np.int64))
