"""A pixel-only landmark from two rays, one from a cloned pose (camloc.slam_rays): every Jacobian
against finite differences, and the landmark's error coefficients against the invariant error's
retraction (camloc.slam), which also checks that the point carries no heading term."""

import numpy as np
import pytest

from camloc import geometry, measurement, slam, slam_rays
from camloc.sensors import CameraModel

STEP = 1e-6


def _numeric(f, x0, step=STEP):
    """Central differences of f at x0: (len(f), len(x0))."""
    columns = []
    for i in range(x0.size):
        e = np.zeros(x0.size)
        e[i] = step
        columns.append((f(x0 + e) - f(x0 - e)) / (2 * step))
    return np.column_stack(columns)


def _camera(seed=0):
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = geometry.so3_exp(rng.normal(scale=0.5, size=3))
    T[:3, 3] = rng.normal(scale=0.2, size=3)
    return CameraModel(camera_id=0, T_robot_camera=T, intrinsics=(500.0, 480.0, 320.0, 240.0), kind=measurement.PIXEL)


def _pose(rng):
    return geometry.so3_exp(rng.normal(scale=0.7, size=3)), rng.normal(size=3)


@pytest.mark.parametrize("seed", range(3))
def test_rigid_point_and_pixel_direction_jacobians_match_finite_differences(seed):
    rng = np.random.default_rng(seed)
    points = slam_rays.clone_points(*_pose(rng)) + rng.normal(scale=0.01, size=(3, 3))  # a clone moved by updates
    a = rng.normal(size=3)
    _, J = slam_rays.rigid_point(points, a)
    assert np.allclose(J, _numeric(lambda p: slam_rays.rigid_point(p.reshape(3, 3), a)[0], points.ravel()), atol=1e-7)
    sensor = _camera(seed)
    z = np.array([300.0, 200.0, 0.0]) + rng.normal(scale=50.0, size=3)
    _, Jz = slam_rays.pixel_direction(z, sensor)
    numeric = _numeric(lambda uv: slam_rays.pixel_direction(np.concatenate([uv, [0.0]]), sensor)[0], z[:2])
    assert np.allclose(Jz, numeric, atol=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_midpoint_and_ray_jacobians_match_finite_differences(seed):
    rng = np.random.default_rng(seed)
    rays = rng.normal(size=12)
    _, F, _ = slam_rays.midpoint(*rays.reshape(4, 3))
    assert np.allclose(F, _numeric(lambda v: slam_rays.midpoint(*v.reshape(4, 3))[0], rays), atol=1e-6)
    points = slam_rays.clone_points(*_pose(rng))
    sensor, z = _camera(seed), np.array([350.0, 210.0, 0.0])
    _, J, W = slam_rays.ray_points(points, sensor, z)
    assert np.allclose(J, _numeric(lambda p: slam_rays.ray_points(p.reshape(3, 3), sensor, z)[0], points.ravel()), atol=1e-7)
    numeric = _numeric(lambda uv: slam_rays.ray_points(points, sensor, np.concatenate([uv, [0.0]]))[0], z[:2])
    assert np.allclose(W, numeric, atol=1e-9)


def _two_views(seed):
    """A landmark seen from a past pose (its clone) and from the robot now, 0.5 m further."""
    rng = np.random.default_rng(seed)
    sensor = CameraModel(camera_id=0, T_robot_camera=np.eye(4), intrinsics=(500.0, 500.0, 320.0, 240.0), kind=measurement.PIXEL)
    R_past, t_past = geometry.so3_exp(rng.normal(scale=0.1, size=3)), rng.normal(scale=0.1, size=3)
    R_now, t_now = R_past @ geometry.so3_exp(rng.normal(scale=0.05, size=3)), t_past + R_past @ np.array([0.5, 0.0, 0.0])
    landmark = t_past + R_past @ np.array([0.3, -0.2, 3.0])

    def pixel(R, t):
        return measurement.project(((landmark - t) @ R)[None, :], sensor.intrinsics, measurement.PIXEL)[0]

    return sensor, (R_past, t_past), (R_now, t_now), pixel(R_past, t_past), pixel(R_now, t_now), landmark


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("two_cameras", [False, True])
def test_a_two_ray_landmark_s_error_coefficients_match_the_invariant_error(seed, two_cameras):
    """The state: the robot now and the past pose's clone (three rows of L). Moving the state by an
    error delta (``slam.retract``) moves the landmark built from it by B delta (in the invariant
    error: l = Exp(xi_theta) l^ + J xi_l), with no heading term; its pixels' noise gives N. The
    rays from one camera, or the first from a second camera offset and turned on the robot."""
    sensor, past, now, z1, z2, landmark = _two_views(seed)
    first = sensor
    if two_cameras:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = geometry.so3_exp(np.array([0.05, -0.1, 0.02])), np.array([0.1, 0.2, -0.05])
        first = CameraModel(camera_id=1, T_robot_camera=T, intrinsics=(450.0, 460.0, 300.0, 250.0), kind=measurement.PIXEL)
        p = (((landmark - past[1]) @ past[0]) - T[:3, 3]) @ T[:3, :3]
        z1 = measurement.project(p[None, :], first.intrinsics, measurement.PIXEL)[0]
    x = slam.SlamMean(now[0], now[1], slam_rays.clone_points(*past))
    R1 = R2 = np.eye(2)

    def build(state):
        return slam_rays.two_ray_landmark(state.L, first, z1, R1, slam_rays.clone_points(state.R, state.t), sensor, z2, R2)

    point, B_anchor, B_translation, N, along = build(x)
    assert np.allclose(point, landmark, atol=1e-9) and np.all(along > 0)
    B = np.zeros((3, x.dim))
    B[:, 0:3], B[:, 6:] = B_translation, B_anchor

    def error_of_landmark(delta):
        moved = slam.retract(x, delta)
        E, J = geometry.so3_exp_and_left_jacobian_one(delta[3:6])
        return np.linalg.solve(J, build(moved)[0] - E @ point)

    assert np.allclose(_numeric(error_of_landmark, np.zeros(x.dim), step=1e-6), B, atol=1e-6)

    def from_pixels(uv):
        return slam_rays.two_ray_landmark(x.L, first, np.concatenate([uv[:2], [0.0]]), R1, slam_rays.clone_points(x.R, x.t),
                                          sensor, np.concatenate([uv[2:], [0.0]]), R2)[0]

    Jz = _numeric(from_pixels, np.concatenate([z1[:2], z2[:2]]))
    assert np.allclose(N, Jz @ Jz.T, rtol=1e-5, atol=1e-12)


def test_a_clone_s_points_carry_the_robot_s_translation_error_exactly():
    """Points rigid with the robot (its position and a metre along two axes) move, under any
    error delta of the pose, by xi_t: the clone's B = [I, 0]."""
    rng = np.random.default_rng(4)
    R, t = _pose(rng)
    x = slam.SlamMean(R, t, slam_rays.clone_points(R, t))
    delta = np.concatenate([rng.normal(scale=0.3, size=6), np.zeros(9)])
    delta[6:] = np.tile(delta[0:3], 3)  # the clone's errors: the translation's
    moved = slam.retract(x, delta)
    assert np.allclose(moved.L, slam_rays.clone_points(moved.R, moved.t), atol=1e-12)


def test_parallel_rays_or_a_point_behind_fix_no_landmark():
    sensor, past, now, z1, z2, _ = _two_views(0)
    same = slam_rays.clone_points(*past)
    assert slam_rays.two_ray_landmark(same, sensor, z1, np.eye(2), same, sensor, z1, np.eye(2)) is None


def test_augmenting_on_a_few_columns_equals_augmenting_with_the_whole_width():
    """``slam.augmented_on`` (C on some columns) gives what ``slam.augmented`` gives with B as wide
    as the state, zero elsewhere."""
    rng = np.random.default_rng(5)
    x = slam.SlamMean(np.eye(3), np.zeros(3), rng.normal(size=(4, 3)))
    A = rng.normal(size=(x.dim, x.dim))
    P = A @ A.T
    columns = np.array([0, 1, 2, 9, 10, 11, 15, 16, 17])
    C, N = rng.normal(size=(3, columns.size)), np.diag([0.1, 0.2, 0.3])
    B = np.zeros((3, x.dim))
    B[:, columns] = C
    xyz = rng.normal(size=3)
    _, expected = slam.augmented(x, P, xyz, B, N)
    moved, P_new = slam.augmented_on(x, P, xyz, C, columns, N)
    assert np.allclose(P_new, expected, atol=1e-12) and np.array_equal(P_new, P_new.T)
    assert np.array_equal(moved.L[-1], xyz)
