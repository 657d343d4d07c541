"""The measurement kinds (``camloc.measurement``): depth, pixel-only and disparity cameras, in the
models, the reader and writer, the simulator, the stacked update and both engines."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from camloc import ekf, geometry, measurement, models
from camloc.errors import DatasetError
from camloc.g2o import read_g2o, write_g2o
from camloc.localizer import LocalizerConfig, _Localizer, localize
from camloc.measurement import DEPTH, DISPARITY, PIXEL
from camloc.metrics import evaluate
from camloc.simulate import SimulationConfig, simulate

KINDS = (DEPTH, PIXEL, DISPARITY)
CAMERAS = {  # the real file's camera, and a tilted one in pixels
    "real-file mount, normalized": (geometry.pose_from_quat(np.array([0, 0, 0.3]), np.array([0.5, -0.5, 0.5, -0.5])),
                                    (1.0, 1.0, 0.5, 0.5)),
    "tilted mount, pixels": (geometry.pose_from_euler(np.array([0.1, -0.2, 0.4, -1.2, 0.3, -1.4])), (525.0, 525.0, 319.5, 239.5)),
}


def numeric_jacobian(function, x0, size, step=1e-6):
    return np.stack([(function(x0 + step * e) - function(x0 - step * e)) / (2 * step) for e in np.eye(size)], axis=-1)


def numeric_manifold_jacobian(function, T):
    """d function(T [+] delta) / d delta at 0, perturbing through ``geometry.retract_right``."""
    return numeric_jacobian(lambda delta: function(geometry.retract_right(T, delta)), np.zeros(6), 6)


def random_state(rng, max_pitch_deg=75.0):
    return np.r_[rng.normal(scale=5.0, size=3), rng.uniform(-3.0, 3.0), np.radians(rng.uniform(-max_pitch_deg, max_pitch_deg)),
                 rng.uniform(-3.0, 3.0)]


def _points_in_front(rng, n=8):
    return np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(0.5, 4.0, n)])


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("camera", CAMERAS)
def test_every_kind_s_euler_jacobian_is_its_finite_difference(rng, camera, kind):
    T_robot_camera, intrinsics = CAMERAS[camera]
    state = random_state(rng)
    p_camera = _points_in_front(rng)
    landmarks = geometry.transform_points(geometry.pose_from_euler(state) @ T_robot_camera, p_camera)
    z_hat, H = models.observe(state, T_robot_camera, intrinsics, landmarks, kind)
    numeric = numeric_jacobian(lambda s: models.observe(s, T_robot_camera, intrinsics, landmarks, kind)[0], state, 6)
    np.testing.assert_allclose(H, numeric, atol=1e-6 * max(intrinsics[0], 1.0))
    third = {DEPTH: p_camera[:, 2], DISPARITY: 1.0 / p_camera[:, 2], PIXEL: np.zeros(8)}[kind]
    np.testing.assert_allclose(z_hat[:, 2], third, atol=1e-12)
    if kind == PIXEL:  # the inert row: predicted 0, no derivative
        assert not H[:, 2].any()


@pytest.mark.parametrize("kind", KINDS)
def test_every_kind_s_se3_jacobian_is_its_finite_difference(rng, kind):
    T_robot_camera, intrinsics = CAMERAS["tilted mount, pixels"]
    T = geometry.pose_from_euler(random_state(rng, max_pitch_deg=89.9))
    landmarks = geometry.transform_points(T @ T_robot_camera, _points_in_front(rng, 6))
    _, H = models.observe_se3(T, T_robot_camera, intrinsics, landmarks, kind)
    numeric = numeric_manifold_jacobian(lambda Tp: models.observe_se3(Tp, T_robot_camera, intrinsics, landmarks, kind)[0], T)
    np.testing.assert_allclose(H, numeric, atol=1e-6 * intrinsics[0])


@pytest.mark.parametrize("kind", (DEPTH, DISPARITY))
def test_a_range_measurement_back_projects_to_its_point_with_the_derivative_as_jacobian(rng, kind):
    _, intrinsics = CAMERAS["tilted mount, pixels"]
    p_camera = _points_in_front(rng)
    z = measurement.project(p_camera, intrinsics, kind)
    back, J = measurement.back_project(z, intrinsics, kind)
    np.testing.assert_allclose(back, p_camera, rtol=1e-12)
    for row in range(8):
        numeric = numeric_jacobian(lambda w: measurement.back_project(w[None], intrinsics, kind)[0][0], z[row], 3)
        np.testing.assert_allclose(J[row], numeric, rtol=1e-6, atol=1e-6)
        # the inverse of the projection's Jacobian at the same point
        np.testing.assert_allclose(J[row] @ measurement.projection_jacobian(p_camera[row:row + 1], intrinsics, kind)[0],
                                   np.eye(3), atol=1e-9)


def test_a_pixel_gives_a_ray_not_a_point():
    with pytest.raises(ValueError, match="no depth"):
        measurement.back_project(np.array([[0.5, 0.5, 0.0]]), (1.0, 1.0, 0.5, 0.5), PIXEL)


def test_the_padded_information_is_the_record_s_and_inert_beyond_it():
    info = measurement.padded_information(np.array([[4.0, 1.0, 9.0]]), PIXEL)
    np.testing.assert_array_equal(info[0], [[4.0, 1.0, 0.0], [1.0, 9.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(measurement.upper_triangle(info, PIXEL), [[4.0, 1.0, 9.0]])
    assert measurement.observation_gates(np.array([DEPTH, PIXEL]), 0.01).tolist() == pytest.approx([11.3449, 9.2103], abs=1e-4)


# --- the g2o records ---------------------------------------------------------------------------

HEADER = """PARAMS_CAMERACALIB 0 0 0 0.3 0.5 -0.5 0.5 -0.5 1 1 0.5 0.5
VERTEX_TRACKXYZ 1 2.0 0.1 0.3
VERTEX_TRACKXYZ 2 2.0 -0.4 0.5
VERTEX_SE3:QUAT 100 0 0 0 0 0 0 1
EDGE_SE3:QUAT 100 101 1 0 0 0 0 0 1 100 0 0 0 0 0 100 0 0 0 0 100 0 0 0 10000 0 0 10000 0 10000
"""


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "world.g2o"
    path.write_text(HEADER + text)
    return path


def test_pixel_and_disparity_records_are_read_in_file_order_and_written_back_identically(tmp_path):
    path = _write(tmp_path, "EDGE_PROJECT_UV 101 1 0 0.6 0.4 1000 5 2000\n"
                            "EDGE_PROJECT_DEPTH 101 2 0 0.7 0.3 1.1 1000 0 0 1000 0 1000\n"
                            "EDGE_PROJECT_DISPARITY 101 2 0 0.7 0.3 0.9 1000 0 0 1000 0 50\n")
    dataset = read_g2o(path)
    assert dataset.obs_kind.tolist() == [PIXEL, DEPTH, DISPARITY]
    np.testing.assert_array_equal(dataset.obs_z, [[0.6, 0.4, 0.0], [0.7, 0.3, 1.1], [0.7, 0.3, 0.9]])
    np.testing.assert_array_equal(dataset.obs_info[0], [[1000, 5, 0], [5, 2000, 0], [0, 0, 1]])
    assert dataset.obs_info[2, 2, 2] == 50.0
    write_g2o(dataset, tmp_path / "again.g2o")
    again = read_g2o(tmp_path / "again.g2o")
    for name in ("obs_z", "obs_info", "obs_kind", "obs_camera", "obs_true_landmark", "obs_pose_index"):
        np.testing.assert_array_equal(getattr(again, name), getattr(dataset, name))
    text = (tmp_path / "again.g2o").read_text()
    assert text.count("EDGE_PROJECT_UV 101 1 0 ") == 1 and "EDGE_PROJECT_DISPARITY 101 2 0 " in text


@pytest.mark.parametrize("line, expected", [
    ("EDGE_PROJECT_UV 101 1 0 0.6 0.4 1000 0\n", "pose landmark camera u v \\+ 3 information numbers"),
    ("EDGE_PROJECT_UV 101 1 0 0.6 0.4 1000 0 -5\n", "positive definite"),
    ("EDGE_PROJECT_DISPARITY 101 1 0 0.6 0.4 nan 1000 0 0 1000 0 1000\n", "inverse_depth"),
])
def test_a_bad_pixel_or_disparity_line_is_named_with_what_was_expected(tmp_path, line, expected):
    with pytest.raises(DatasetError, match=expected) as error:
        read_g2o(_write(tmp_path, line))
    assert f"{tmp_path / 'world.g2o'}:6:" in str(error.value)


# --- the stacked update of a two-camera rig -----------------------------------------------------


def test_a_two_camera_rig_seeing_one_landmark_updates_with_the_hand_derived_four_row_update(tmp_path):
    """Two pixel-only cameras see the same landmark: one stacked update of 4 rows (u, v of each),
    equal to the textbook EKF update written out here from the projection's derivative."""
    config = SimulationConfig(poses=3, cameras=2, measurement="pixel", landmarks=4)
    world = simulate(config, seed=3)
    state = np.array([0.2, -0.1, 0.05, 0.02, -0.03, 0.3])
    T_world_robot = geometry.pose_from_euler(state)
    landmark = T_world_robot[:3, :3] @ np.array([1.5, 0.1, 0.2]) + T_world_robot[:3, 3]  # ahead of the robot
    # camera 1 looks backward: move it to look forward too, a stereo pair with a 0.1 m baseline
    rig = {0: world.cameras[0], 1: type(world.cameras[0])(1, np.array([0.0, -0.1, 0.3]), world.cameras[0].quat_xyzw,
                                                             1.0, 1.0, 0.5, 0.5)}
    sigma = 0.01
    z_true = []
    for c in (0, 1):
        p = geometry.transform_points(geometry.se3_inverse(T_world_robot @ rig[c].T_robot_camera), landmark[None])[0]
        z_true.append([p[0] / p[2] + 0.5, p[1] / p[2] + 0.5, 0.0])
    measured = np.array(z_true) + np.array([[0.004, -0.002, 0.0], [-0.003, 0.001, 0.0]])
    info = np.broadcast_to(measurement.padded_information(np.array([[1 / sigma**2, 0.0, 1 / sigma**2]]), PIXEL), (2, 3, 3)).copy()
    dataset = type(world)(**{**world.__dict__, "cameras": rig, "landmark_ids": np.array([7]), "landmark_xyz": landmark[None],
                             "obs_pose_index": np.array([1, 1]), "obs_camera": np.array([0, 1]), "obs_z": measured,
                             "obs_info": info, "obs_cov": np.linalg.inv(info), "obs_true_landmark": np.array([7, 7]),
                             "obs_kind": np.array([PIXEL, PIXEL])})
    localizer = _Localizer(dataset, LocalizerConfig(iterations=1, association="oracle"))
    P = np.diag([0.05, 0.05, 0.05, 0.01, 0.01, 0.01]) ** 2
    result = localizer.updated(state, P, np.array([0, 1]), np.array([0, 0]))

    # by hand: h_c(x) = (x_c/z_c + 0.5, y_c/z_c + 0.5), p_c = R_c' (R' (l - t) - t_c), and the
    # Euler state's body-frame rotation d p_robot = [p_robot]x E d(rpy)
    R, t = T_world_robot[:3, :3], T_world_robot[:3, 3]
    E = geometry.euler_rate_matrix(state[3:6])
    rows_H, rows_y = [], []
    for c in (0, 1):
        R_c, t_c = rig[c].T_robot_camera[:3, :3], rig[c].T_robot_camera[:3, 3]
        p_robot = R.T @ (landmark - t)
        x, y, z = R_c.T @ (p_robot - t_c)
        d_projection = np.array([[1 / z, 0, -x / z**2], [0, 1 / z, -y / z**2]])
        d_point = R_c.T @ np.hstack([-R.T, geometry.hat(p_robot) @ E])
        rows_H.append(d_projection @ d_point)
        rows_y.append(measured[c, :2] - np.array([x / z + 0.5, y / z + 0.5]))
    H, y = np.vstack(rows_H), np.concatenate(rows_y)
    S = H @ P @ H.T + sigma**2 * np.eye(4)
    K = P @ H.T @ np.linalg.inv(S)
    np.testing.assert_allclose(result.state, state + K @ y, rtol=1e-9, atol=1e-12)
    I_KH = np.eye(6) - K @ H
    np.testing.assert_allclose(result.cov, I_KH @ P @ I_KH.T + sigma**2 * K @ K.T, rtol=1e-8, atol=1e-15)
    assert result.nis == pytest.approx(y @ np.linalg.solve(S, y), rel=1e-9)


# --- whole runs ---------------------------------------------------------------------------------

PIXEL_WORLDS = {
    "grid, one pixel camera": SimulationConfig(trajectory="grid", poses=300, measurement="pixel"),
    "smooth3d, two pixel cameras, 10% clutter": SimulationConfig(trajectory="smooth3d", poses=300, cameras=2,
                                                                measurement="pixel", clutter_fraction=0.1),
    "aerial, depth and pixel cameras": SimulationConfig(trajectory="aerial", poses=300, cameras=2, measurement="depth,pixel"),
    "grid, disparity, pixel intrinsics": SimulationConfig(trajectory="grid", poses=300, measurement="disparity", intrinsics="pixel"),
}


@pytest.mark.parametrize("world", PIXEL_WORLDS)
def test_the_true_association_localizes_every_kind_of_camera_consistently_in_both_engines(world):
    dataset = simulate(PIXEL_WORLDS[world], seed=11)
    numpy_run = localize(dataset, LocalizerConfig(association="oracle"), engine="numpy")
    compiled_run = localize(dataset, LocalizerConfig(association="oracle"), engine="compiled")
    np.testing.assert_allclose(compiled_run.filter_state, numpy_run.filter_state, rtol=0, atol=1e-8)
    metrics = evaluate(numpy_run)
    assert metrics["estimate"]["ate"]["rmse"] < 0.3 * metrics["odometry"]["ate"]["rmse"]
    # consistency over about 300 correlated poses: the mean NEES (6 dof) and NIS per dof near
    # their expectations, within bounds wider than one run's 95% interval (four worlds, one seed)
    assert 4.5 < metrics["nees"]["mean"] < 8.0, metrics["nees"]["verdict_line"]
    assert 0.9 < metrics["nis"]["mean_per_dof"] < 1.1, metrics["nis"]["verdict_line"]
    accepted = numpy_run.associations.landmark >= 0
    assert int(np.sum(numpy_run.nis_dof)) == int(measurement.dof_of(dataset.obs_kind[accepted]).sum())  # a pixel's 2 dof
    np.testing.assert_array_equal(compiled_run.nis_dof, numpy_run.nis_dof)


# slow (2026-12-06): 20 s of CPU on the 2-core AMD EPYC (a 300-pose pixel world in numpy, twice for
# the learned reach); the fast tests hold what it checks: both engines alike on pixel-only worlds of
# two cameras (test_engine_parity's pixel-beam-*, test_kernels's pixel-2cam-clutter), the beam's
# precision and error against the oracle on them (test_localizer's pixel-only cameras, 500 poses)
@pytest.mark.slow
def test_a_pixel_only_file_localizes_with_the_default_association_in_both_engines(tmp_path):
    dataset = simulate(SimulationConfig(trajectory="smooth3d", poses=300, cameras=2, measurement="pixel"), seed=5)
    numpy_run = localize(dataset, LocalizerConfig(), engine="numpy")
    compiled_run = localize(dataset, LocalizerConfig(), engine="compiled")
    np.testing.assert_array_equal(compiled_run.associations.landmark, numpy_run.associations.landmark)
    estimate = evaluate(compiled_run)
    oracle = evaluate(localize(dataset, LocalizerConfig(association="oracle"), engine="compiled"))
    assert estimate["association"]["precision"] > 0.9
    assert estimate["estimate"]["ate"]["rmse"] < 2.5 * oracle["estimate"]["ate"]["rmse"]


def test_the_simulator_writes_each_camera_s_kind(tmp_path):
    world = simulate(SimulationConfig(poses=50, cameras=2, measurement="depth,pixel"), seed=2)
    kinds_by_camera = {int(c): set(world.obs_kind[world.obs_camera == c].tolist()) for c in np.unique(world.obs_camera)}
    assert kinds_by_camera == {0: {DEPTH}, 1: {PIXEL}}
    pixel = world.obs_kind == PIXEL
    assert np.all(world.obs_z[pixel, 2] == 0.0) and np.all(world.obs_info[pixel, 2, 2] == 1.0)
    assert np.all(world.obs_info[pixel, 2, :2] == 0.0)
    write_g2o(world, tmp_path / "w.g2o")
    assert read_g2o(tmp_path / "w.g2o").tag_counts["EDGE_PROJECT_UV"] == int(pixel.sum())
    with pytest.raises(Exception, match="one kind, or one per camera"):
        SimulationConfig(cameras=3, measurement="depth,pixel")
    with pytest.raises(Exception, match="one of depth, pixel, disparity"):
        SimulationConfig(measurement="lidar")


def test_the_solver_and_filter_agree_on_a_pixel_stack():
    """The information-form update of padded pixel blocks equals the plain 2-row update."""
    rng = np.random.default_rng(4)
    P = np.diag(rng.uniform(0.01, 0.1, 6))
    H2 = rng.normal(size=(5, 2, 6))
    R2 = np.broadcast_to(np.diag([0.02, 0.03]), (5, 2, 2))
    y2 = rng.normal(scale=0.1, size=(5, 2))
    H3 = np.zeros((5, 3, 6)); H3[:, :2] = H2
    R3 = np.zeros((5, 3, 3)); R3[:, :2, :2] = R2; R3[:, 2, 2] = 1.0
    y3 = np.zeros((5, 3)); y3[:, :2] = y2
    padded = ekf._gain_for(P, R3, 15)(H3.reshape(15, 6))
    plain = ekf.CovarianceGain(P, H2.reshape(10, 6), ekf.block_diagonal(R2))
    np.testing.assert_allclose(padded.correction(y3.reshape(-1)), plain.correction(y2.reshape(-1)), rtol=1e-10)
    np.testing.assert_allclose(padded.posterior_cov(), plain.posterior_cov(), rtol=1e-10)
    assert padded.nis(y3.reshape(-1)) == pytest.approx(plain.nis(y2.reshape(-1)), rel=1e-10)
    assert padded.log_det_ratio() == pytest.approx(ekf.innovation_cost(P, H2.reshape(10, 6), R2, y2.reshape(-1))
                                                   - plain.nis(y2.reshape(-1)), rel=1e-9)


@pytest.mark.parametrize("kind", KINDS)
def test_one_point_projected_in_floats_is_the_array_forms_to_the_bit(rng, kind):
    """``project_one`` (the numpy beam's lone pair) gives ``project`` and ``projection_jacobian``
    of the same point bit for bit: the numpy engine's pairs must not move with it."""
    intrinsics = (525.0, 520.0, 319.5, 239.5)
    for point in rng.normal(size=(200, 3)) * [2.0, 2.0, 3.0]:
        found = measurement.project_one(point, intrinsics, kind)
        z_hat = measurement.project(point[None], intrinsics, kind)
        J = measurement.projection_jacobian(point[None], intrinsics, kind)
        np.testing.assert_array_equal(found[0].view(np.int64), z_hat.view(np.int64))
        np.testing.assert_array_equal(found[1].view(np.int64), J.view(np.int64))
    assert measurement.project_one(np.array([1.0, 2.0, 0.0]), intrinsics, kind) is None
