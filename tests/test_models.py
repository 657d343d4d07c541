"""Every Jacobian of the motion and camera models against central finite differences, at random
states including large roll and pitch."""

import numpy as np
import pytest

from camloc import geometry, measurement, models
from camloc.sensors import CameraModel, intrinsics_by_row

STEP = 1e-6


def numeric_jacobian(function, x0, size):
    columns = []
    for i in range(size):
        d = np.zeros(size)
        d[i] = STEP
        columns.append((function(x0 + d) - function(x0 - d)) / (2 * STEP))
    return np.stack(columns, axis=-1)


def random_state(rng, max_pitch_deg=75.0):
    return np.r_[rng.normal(scale=5.0, size=3), rng.uniform(-3.0, 3.0),
                 np.radians(rng.uniform(-max_pitch_deg, max_pitch_deg)), rng.uniform(-3.0, 3.0)]


def random_increment(rng):
    return geometry.pose_from_euler(np.r_[rng.normal(scale=0.7, size=3), rng.normal(scale=0.5, size=3)])


@pytest.mark.parametrize("trial", range(10))
def test_motion_state_jacobian(rng, trial):
    state, increment = random_state(rng), random_increment(rng)
    _, F, _ = models.motion(state, increment)
    numeric = numeric_jacobian(lambda s: models.motion(s, increment)[0], state, 6)
    np.testing.assert_allclose(F, numeric, atol=1e-6)


@pytest.mark.parametrize("trial", range(10))
def test_motion_noise_jacobian(rng, trial):
    state, increment = random_state(rng), random_increment(rng)
    _, _, G = models.motion(state, increment)

    def with_noise(w):
        noise = geometry.make_pose(geometry.so3_exp(w[3:6]), w[0:3])
        return models.motion(state, increment @ noise)[0]

    np.testing.assert_allclose(G, numeric_jacobian(with_noise, np.zeros(6), 6), atol=1e-6)


def test_motion_composes_poses(rng):
    state, increment = random_state(rng), random_increment(rng)
    next_state, _, _ = models.motion(state, increment)
    np.testing.assert_allclose(geometry.pose_from_euler(next_state), geometry.pose_from_euler(state) @ increment, atol=1e-12)


CAMERAS = {
    "real-file mount, normalized": (geometry.pose_from_quat(np.array([0, 0, 0.3]), np.array([0.5, -0.5, 0.5, -0.5])), (1.0, 1.0, 0.5, 0.5)),
    "tilted mount, pixels": (geometry.pose_from_euler(np.array([0.1, -0.2, 0.4, -1.2, 0.3, -1.4])), (525.0, 525.0, 319.5, 239.5)),
}


@pytest.mark.parametrize("camera", CAMERAS)
@pytest.mark.parametrize("trial", range(5))
def test_observation_jacobian(rng, camera, trial):
    T_robot_camera, intrinsics = CAMERAS[camera]
    state = random_state(rng)
    T_world_camera = geometry.pose_from_euler(state) @ T_robot_camera
    p_camera = np.column_stack([rng.uniform(-1, 1, 8), rng.uniform(-1, 1, 8), rng.uniform(0.5, 4.0, 8)])
    landmarks = geometry.transform_points(T_world_camera, p_camera)
    z_hat, H = models.observe(state, T_robot_camera, intrinsics, landmarks)
    numeric = numeric_jacobian(lambda s: models.observe(s, T_robot_camera, intrinsics, landmarks)[0], state, 6)
    scale = max(intrinsics[0], 1.0)
    np.testing.assert_allclose(H, numeric, atol=1e-6 * scale)
    np.testing.assert_allclose(z_hat[:, 2], p_camera[:, 2], atol=1e-12)


@pytest.mark.parametrize("camera", CAMERAS)
def test_back_projection_inverts_projection_and_its_jacobian(rng, camera):
    _, intrinsics = CAMERAS[camera]
    p_camera = np.column_stack([rng.uniform(-1, 1, 8), rng.uniform(-1, 1, 8), rng.uniform(0.5, 4.0, 8)])
    uvd = models.project_points(p_camera, intrinsics)
    back, J = models.back_project(uvd, intrinsics)
    np.testing.assert_allclose(back, p_camera, atol=1e-12)
    for row in range(8):
        numeric = numeric_jacobian(lambda z: models.back_project(z[None], intrinsics)[0][0], uvd[row], 3)
        np.testing.assert_allclose(J[row], numeric, atol=1e-6)
        # the inverse of the projection's Jacobian at the same point
        np.testing.assert_allclose(J[row] @ models.projection_jacobian(p_camera[row : row + 1], intrinsics)[0], np.eye(3), atol=1e-9)


@pytest.mark.parametrize("camera", CAMERAS)
def test_measured_points_carry_the_measurement_noise_to_first_order(rng, camera):
    _, (fx, fy, cx, cy) = CAMERAS[camera]
    uvd = np.array([[cx + 0.3 * fx, cy - 0.2 * fy, 1.5]])
    sigma = np.array([fx * 1e-3, fy * 1e-3, 1e-3])
    point, point_cov = models.measured_points(uvd, np.diag(sigma**2)[None], (fx, fy, cx, cy))
    scattered = models.back_project(uvd + rng.normal(size=(200_000, 3)) * sigma, (fx, fy, cx, cy))[0]
    np.testing.assert_allclose(point[0], [0.45, -0.3, 1.5], atol=1e-12)
    variance = np.diagonal(point_cov[0])
    sampling_error = np.sqrt(np.outer(variance, variance) / scattered.shape[0])  # of each covariance entry
    assert np.all(np.abs(np.cov(scattered.T) - point_cov[0]) <= 5 * sampling_error)


def test_measured_points_keep_a_positive_depth():
    _, intrinsics = next(iter(CAMERAS.values()))
    point, point_cov = models.measured_points(np.array([[0.5, 0.5, -1.0]]), np.eye(3)[None] * 1e-3, intrinsics)
    assert point[0, 2] == models.MIN_POINT_DEPTH
    assert np.all(np.isfinite(point_cov)) and np.linalg.slogdet(point_cov[0])[0] == 1


def test_observation_matches_format_model():
    # FORMAT.md: a landmark 1 m straight ahead of the real file's camera lands at the image centre.
    T_robot_camera, intrinsics = CAMERAS["real-file mount, normalized"]
    z_hat, _ = models.observe(np.zeros(6), T_robot_camera, intrinsics, np.array([[1.0, 0.0, 0.3]]))
    np.testing.assert_allclose(z_hat[0], [0.5, 0.5, 1.0], atol=1e-12)
    # image x runs along robot -y: a landmark to the robot's right (-y) has u > cx.
    z_right, _ = models.observe(np.zeros(6), T_robot_camera, intrinsics, np.array([[1.0, -0.2, 0.3]]))
    assert z_right[0, 0] > 0.5


# --- the SE(3) error-state variant: Jacobians against perturbations through the retraction ---


def numeric_manifold_jacobian(function, T, size=6):
    """d function(T [+] delta) / d delta at 0, perturbing through ``geometry.retract_right``."""
    return numeric_jacobian(lambda delta: function(geometry.retract_right(T, delta)), np.zeros(size), size)


@pytest.mark.parametrize("trial", range(8))
def test_se3_motion_jacobians(rng, trial):
    T = geometry.pose_from_euler(random_state(rng, max_pitch_deg=89.9))
    increment = random_increment(rng)
    T_next, F, G = models.motion_se3(T, increment)
    np.testing.assert_allclose(T_next, T @ increment, atol=1e-12)
    numeric_F = numeric_manifold_jacobian(lambda Tp: geometry.difference_right(models.motion_se3(Tp, increment)[0], T_next), T)
    np.testing.assert_allclose(F, numeric_F, atol=1e-6)

    def with_noise(w):
        noisy = increment @ geometry.make_pose(geometry.so3_exp(w[3:6]), w[0:3])
        return geometry.difference_right(models.motion_se3(T, noisy)[0], T_next)

    np.testing.assert_allclose(G, numeric_jacobian(with_noise, np.zeros(6), 6), atol=1e-6)


@pytest.mark.parametrize("camera", CAMERAS)
@pytest.mark.parametrize("trial", range(4))
def test_se3_observation_jacobian(rng, camera, trial):
    T_robot_camera, intrinsics = CAMERAS[camera]
    # pitch exactly at 90 deg: where the Euler parametrization breaks, the SE(3) one does not
    T = geometry.pose_from_euler(np.r_[rng.normal(size=3), rng.uniform(-3, 3), np.pi / 2, rng.uniform(-3, 3)])
    p_camera = np.column_stack([rng.uniform(-1, 1, 6), rng.uniform(-1, 1, 6), rng.uniform(0.5, 4.0, 6)])
    landmarks = geometry.transform_points(T @ T_robot_camera, p_camera)
    z_hat, H = models.observe_se3(T, T_robot_camera, intrinsics, landmarks)
    numeric = numeric_manifold_jacobian(lambda Tp: models.observe_se3(Tp, T_robot_camera, intrinsics, landmarks)[0], T)
    np.testing.assert_allclose(H, numeric, atol=1e-6 * max(intrinsics[0], 1.0))
    np.testing.assert_allclose(z_hat[:, 2], p_camera[:, 2], atol=1e-12)


def test_retract_and_difference_are_inverse(rng):
    T = geometry.pose_from_euler(random_state(rng))
    delta = rng.normal(scale=0.3, size=6)
    np.testing.assert_allclose(geometry.difference_right(geometry.retract_right(T, delta), T), delta, atol=1e-10)


@pytest.mark.parametrize("kind", [measurement.DEPTH, measurement.PIXEL, measurement.DISPARITY])
@pytest.mark.parametrize("trial", range(6))
def test_a_rig_of_cameras_observes_as_each_camera_alone(rng, kind, trial):
    """``observe_rig`` (and its SE(3) twin) of several cameras in one batch: each row bit for bit
    what ``observe`` of its camera alone gives (the numpy beam's pairs must not change with the
    batching), with camera groups of one row among them (BLAS takes another path for one row);
    in odd trials the cameras share their intrinsics (``intrinsics_by_row`` then gives scalars)."""
    mounts = [random_increment(rng) for _ in range(3)]
    cameras = [CameraModel(T, tuple(rng.uniform([300, 300, 200, 150], [600, 600, 400, 300])), kind) for T in mounts]
    if trial % 2:
        cameras = [CameraModel(c.T_robot_camera, cameras[0].intrinsics, kind) for c in cameras]
    sizes = [1, int(rng.integers(2, 9)), int(rng.integers(1, 4))]
    state = random_state(rng)
    T = geometry.pose_from_euler(state)
    landmarks = np.concatenate([
        geometry.transform_points(T @ c.T_robot_camera, np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(0.5, 6.0, n)]))
        for c, n in zip(cameras, sizes)])
    bounds = np.cumsum([0] + sizes)
    for rig, alone, x in ((models.observe_rig, models.observe, state), (models.observe_rig_se3, models.observe_se3, T)):
        z_hat, H = rig(x, mounts, intrinsics_by_row(cameras, sizes), landmarks, sizes, kind)
        each = [alone(x, c.T_robot_camera, c.intrinsics, landmarks[a:b], kind) for c, a, b in zip(cameras, bounds[:-1], bounds[1:])]
        assert np.array_equal(z_hat, np.concatenate([z for z, _ in each]))
        assert np.array_equal(H, np.concatenate([J for _, J in each]))
