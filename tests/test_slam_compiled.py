"""The mapping localizer's compiled update (camloc.slam_compiled) against its numpy reference
(``ekf.update`` over ``camloc.slam``'s model, as ``slam_run`` calls it), on depth, pixel and
disparity cameras and a mix of them, and its Jacobian against finite differences."""

import numpy as np
import pytest

from camloc import ekf, geometry, measurement, slam
from camloc.association import mahalanobis_3x3
from camloc.constants import CONVERGED
from camloc.sensors import CameraModel
from camloc.slam_compiled import CompiledUpdate, difference_columns, observe_columns, retract

KINDS = [measurement.DEPTH, measurement.PIXEL, measurement.DISPARITY]


def _camera(kind, sensor_id=0):
    # a camera looking along the robot's x axis (its z), offset on the robot
    Rc = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rc, [0.1, -0.05 + 0.1 * sensor_id, 0.2]
    return CameraModel(T, (500.0 + 10 * sensor_id, 510.0, 320.0, 240.0), kind, sensor_id)


def _state(rng, m):
    R = geometry.so3_exp(rng.normal(size=3) * 0.5)
    t = rng.normal(size=3)
    L = t + (R @ (np.array([4.0, 0.0, 0.0]) + rng.normal(size=(m, 3)) * 0.5).T).T
    return slam.SlamMean(R, t, L)


def _noise(kind, rng, p):
    """Measurement noise (p, 3, 3) in the padded layout (a pixel's inert row: unit)."""
    R_z = np.zeros((p, 3, 3))
    for o in range(p):
        A = rng.normal(size=(3, 3)) * 0.3
        R_z[o] = A @ A.T + np.diag([2.0, 2.0, 0.01 if kind == measurement.DEPTH else 1e-4])
        if kind == measurement.PIXEL:
            R_z[o, 2, :], R_z[o, :, 2], R_z[o, 2, 2] = 0.0, 0.0, 1.0
    return R_z


def _problem(kinds, seed, spread=1.0):
    """A state of 6 landmarks with a prior spread (``spread`` times the usual), and pairs (of
    each sensor in ``kinds``) with landmarks of the state (one seen twice) and points held fixed,
    measured with noise."""
    rng = np.random.default_rng(seed)
    x = _state(rng, 6)
    A = rng.normal(size=(x.dim, x.dim)) * 0.05 * spread
    P = A @ A.T + 1e-3 * np.eye(x.dim)
    sensors = {s: _camera(kind, s) for s, kind in enumerate(kinds)}
    rows = np.array([4, -1, 1, 4, -1, 0, 2])
    sensor = np.arange(rows.size) % len(kinds)
    fixed = x.t + (x.R @ (np.array([5.0, 0.0, 0.0]) + rng.normal(size=(rows.size, 3)) * 0.7).T).T
    xyz = np.where(rows[:, None] >= 0, 0.0, fixed)  # a state landmark's position is the state's
    truth = slam.retract(x, rng.multivariate_normal(np.zeros(x.dim), P))
    z, R_z = np.zeros((rows.size, 3)), np.zeros((rows.size, 3, 3))
    for o in range(rows.size):
        s = sensors[int(sensor[o])]
        point = truth.L[rows[o]] if rows[o] >= 0 else fixed[o]
        R_z[o] = _noise(s.kind, rng, 1)[0]
        z[o] = measurement.project(slam.camera_points(truth, s, point[None, :]), s.intrinsics, s.kind)[0]
        z[o] += rng.multivariate_normal(np.zeros(3), R_z[o]) * (np.arange(3) < s.dof)
    return x, P, sensors, sensor, rows, xyz, z, R_z


def _numpy_update(x, P, sensors, sensor, rows, xyz, z, R_z, iterations, monotone=False):
    """``slam_run``'s numpy update (``MappingLocalizer._numpy_update``), on plain arrays."""
    columns, block = slam.state_columns(rows)
    in_state = rows >= 0

    def measure(s: slam.SlamMean):
        points = xyz.copy()
        points[in_state] = s.L[rows[in_state]]
        z_hat, H = np.zeros((rows.size, 3)), np.zeros((rows.size, 3, columns.size))
        for sensor_id, camera in sensors.items():
            at = sensor == sensor_id
            z_hat[at], H[at] = slam.observe_columns(s, camera, points[at], block[at], columns.size)
        return z_hat.ravel(), H.reshape(-1, columns.size)

    return ekf.update(x, P, z.ravel(), R_z, measure, retract=slam.retract, difference=slam.difference,
                      iterations=iterations, map_cost=True, R_inverse=np.linalg.inv(R_z), columns=columns,
                      monotone=monotone)


@pytest.mark.parametrize("kinds", [[k] for k in KINDS] + [KINDS])
@pytest.mark.parametrize("iterations", [1, 3])
def test_compiled_update_equals_the_numpy_update(kinds, iterations):
    for seed in range(3):
        x, P, sensors, sensor, rows, xyz, z, R_z = _problem(kinds, seed)
        reference = _numpy_update(x, P, sensors, sensor, rows, xyz, z, R_z, iterations)
        update = CompiledUpdate(sensors, geometry._SMALL_ANGLE, CONVERGED)
        assert update.usable
        ok, R, t, L, P_new, innovation, S, nis, cost, d2 = update(x.R, x.t, x.L, P, z, R_z, np.linalg.inv(R_z), xyz, rows, sensor,
                                                              iterations)
        assert ok
        p = rows.size
        np.testing.assert_allclose(R, reference.state.R, atol=1e-12)
        np.testing.assert_allclose(t, reference.state.t, atol=1e-12)
        np.testing.assert_allclose(L, reference.state.L, atol=1e-12)
        np.testing.assert_allclose(P_new, reference.cov, atol=1e-12)
        np.testing.assert_array_equal(P_new, P_new.T)
        np.testing.assert_allclose(innovation, reference.innovation, atol=1e-12)
        np.testing.assert_allclose(S, reference.S.reshape(p, 3, p, 3)[np.arange(p), :, np.arange(p), :], atol=1e-12)
        assert nis == pytest.approx(reference.nis, rel=1e-10)
        assert cost == pytest.approx(reference.map_cost, rel=1e-10)
        np.testing.assert_allclose(d2, mahalanobis_3x3(S, innovation.reshape(p, 3))[0], rtol=1e-12)


def test_compiled_monotone_update_equals_the_numpy_one_where_it_stops_early():
    """``monotone`` (the update of a run without a map): on wide priors, where Gauss-Newton's
    later iterates cost more than earlier ones, the compiled update keeps the iterate the numpy one keeps."""
    stopped = 0
    for seed in range(12):
        x, P, sensors, sensor, rows, xyz, z, R_z = _problem(KINDS, seed, spread=8.0)
        update = CompiledUpdate(sensors, geometry._SMALL_ANGLE, CONVERGED)
        free = update(x.R, x.t, x.L, P, z, R_z, np.linalg.inv(R_z), xyz, rows, sensor, 5)
        ok, R, t, L, P_new, innovation, S, nis, cost, d2 = update(x.R, x.t, x.L, P, z, R_z, np.linalg.inv(R_z), xyz, rows,
                                                              sensor, 5, True)
        if not (ok and free[0]):
            continue  # a step near a half turn: the numpy update's case
        reference = _numpy_update(x, P, sensors, sensor, rows, xyz, z, R_z, 5, monotone=True)
        np.testing.assert_allclose(t, reference.state.t, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(L, reference.state.L, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(P_new, reference.cov, rtol=1e-6, atol=1e-9)
        assert cost == pytest.approx(reference.map_cost, rel=1e-6)
        assert cost <= free[8] * (1 + 1e-12)  # never costlier than letting every iterate through
        stopped += cost < free[8] * (1 - 1e-9)
    assert stopped >= 1  # the wide priors do make Gauss-Newton overshoot


@pytest.mark.parametrize("kind", KINDS)
def test_compiled_jacobian_matches_finite_differences(kind):
    """observe_columns' H (on the state's columns here: every landmark's block) against central
    differences of its predictions under the compiled retraction."""
    rng = np.random.default_rng(5)
    x = _state(rng, 3)
    camera = CompiledUpdate({0: _camera(kind)}, geometry._SMALL_ANGLE, CONVERGED)
    rows = np.array([0, 2, -1])
    xyz = np.zeros((3, 3))
    xyz[2] = x.t + x.R @ np.array([5.0, 0.3, -0.2])
    block = np.where(rows >= 0, 2 + rows, -1)
    sensor = np.zeros(3, np.int64)

    def predict(R, t, L):
        return observe_columns(R, t, L, xyz, rows, block, sensor, camera.cam_R, camera.cam_t, camera.cam_K,
                               camera.cam_third, x.dim)

    _, H = predict(x.R, x.t, x.L)
    step = 1e-6
    numeric = np.zeros_like(H)
    for i in range(x.dim):
        e = np.zeros(x.dim)
        e[i] = step
        plus = predict(*retract(x.R, x.t, x.L, e, geometry._SMALL_ANGLE))[0].ravel()
        minus = predict(*retract(x.R, x.t, x.L, -e, geometry._SMALL_ANGLE))[0].ravel()
        numeric[:, i] = (plus - minus) / (2 * step)
    np.testing.assert_allclose(H, numeric, atol=1e-5 * np.abs(numeric).max())


def test_compiled_retraction_and_difference_equal_the_numpy_ones():
    rng = np.random.default_rng(9)
    x = _state(rng, 4)
    delta = rng.normal(size=x.dim) * 0.2
    R, t, L = retract(x.R, x.t, x.L, delta, geometry._SMALL_ANGLE)
    moved = slam.retract(x, delta)
    np.testing.assert_allclose(R, moved.R, atol=1e-14)
    np.testing.assert_allclose(t, moved.t, atol=1e-14)
    np.testing.assert_allclose(L, moved.L, atol=1e-14)
    landmarks = np.array([1, 3])
    d, ok = difference_columns(R, t, L, x.R, x.t, np.ascontiguousarray(x.L), landmarks, geometry._SMALL_ANGLE)
    assert ok
    whole = slam.difference(moved, x)
    np.testing.assert_allclose(d, whole[np.r_[0:6, 9:12, 15:18]], atol=1e-12)
    np.testing.assert_allclose(d, delta[np.r_[0:6, 9:12, 15:18]], atol=1e-12)


def _localizer_after(measurement_kind, poses, steps, map_mode="prior"):
    """A mapping localizer (numpy) after ``steps`` poses of a small world with half its map withheld."""
    from camloc.localizer import resolved_config
    from camloc.localizer_config import LocalizerConfig
    from camloc.simulate import SimulationConfig, simulate
    from camloc.slam_run import MappingLocalizer

    ds = simulate(SimulationConfig(poses=poses, measurement=measurement_kind, withhold_map=0.5), seed=2)
    localizer = MappingLocalizer(ds, resolved_config(LocalizerConfig(map=map_mode), ds), compiled=False)
    for k in range(steps):
        localizer.step(k)
    return localizer


@pytest.mark.parametrize("kind", ["depth", "pixel", "disparity"])
def test_compiled_candidate_costs_equal_the_numpy_ones(kind):
    """``landmark_costs`` (the candidates of a pose's observations: in view, their predictions,
    Jacobians, extra covariance and costs) compiled and in numpy, at poses of a run whose state
    holds landmarks and whose table holds others outside it."""
    from camloc.slam_run import _compiled_update

    localizer = _localizer_after(kind, 40, 25)
    compiled = _compiled_update(localizer.sensors)
    compared = 0
    for k in range(25, 40):
        localizer.step(k)
        obs = localizer.obs_of_pose[k]
        nearby = localizer.table.in_range(localizer.x.t, localizer.max_depth + 1.0, localizer.mapped_index)
        for sensor_id in np.unique(localizer.obs_sensor[obs]).tolist():
            mine = obs[localizer.obs_sensor[obs] == sensor_id]
            localizer.compiled = None
            reference = localizer.landmark_costs(sensor_id, mine, nearby)
            localizer.compiled = compiled
            result = localizer.landmark_costs(sensor_id, mine, nearby)
            localizer.compiled = None
            assert (reference is None) == (result is None)
            if reference is None:
                continue
            np.testing.assert_array_equal(result[0], reference[0])
            np.testing.assert_array_equal(result[1] >= 1e12, reference[1] >= 1e12)  # the same pairs gated
            inside = reference[1] < 1e12
            np.testing.assert_allclose(result[1][inside], reference[1][inside], rtol=1e-10, atol=1e-10)
            for a, b in zip(result[2:], reference[2:]):
                np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
            compared += int(np.count_nonzero(inside))
    assert compared > 20


@pytest.mark.parametrize("kind, map_mode", [("depth", "prior"), ("pixel", "prior"), ("disparity", "none")])
def test_a_compiled_mapping_run_equals_the_numpy_run(kind, map_mode):
    """The whole mapping pass with the compiled update and costs and in numpy: the same pairs,
    poses, covariances and map to rounding."""
    from camloc.localizer import resolved_config
    from camloc.localizer_config import LocalizerConfig
    from camloc.simulate import SimulationConfig, simulate
    from camloc.slam_run import localize_mapping

    ds = simulate(SimulationConfig(poses=60, measurement=kind, withhold_map=0.0 if map_mode == "none" else 0.5,
                                  no_map=map_mode == "none"), seed=3)
    config = resolved_config(LocalizerConfig(map=map_mode), ds)
    numpy_run, compiled_run = (localize_mapping(ds, config, compiled=c) for c in (False, True))
    _assert_same_run(compiled_run, numpy_run)


def _assert_same_run(compiled_run, numpy_run):
    """The compiled mapping pass's run and numpy's: the same pairs, poses, covariances and map to rounding."""
    assert compiled_run.summary["timing"]["engine"] == "compiled update"
    np.testing.assert_array_equal(compiled_run.associations.landmark, numpy_run.associations.landmark)
    for name in ("estimate_xyz", "estimate_cov", "filter_state", "filter_cov"):
        np.testing.assert_allclose(getattr(compiled_run, name), getattr(numpy_run, name), atol=1e-10)
    np.testing.assert_array_equal(compiled_run.landmark_map.ids, numpy_run.landmark_map.ids)
    np.testing.assert_allclose(compiled_run.landmark_map.xyz, numpy_run.landmark_map.xyz, atol=1e-10)
    np.testing.assert_allclose(compiled_run.landmark_map.cov, numpy_run.landmark_map.cov, atol=1e-10)
    assert compiled_run.summary["map"]["added"] > 0


def test_compiled_prediction_equals_the_numpy_one():
    rng = np.random.default_rng(11)
    x = _state(rng, 5)
    A = rng.normal(size=(x.dim, x.dim)) * 0.1
    P = A @ A.T
    T = geometry.make_pose(geometry.so3_exp(np.array([0.01, -0.02, 0.1])), np.array([0.3, 0.02, -0.01]))
    B = rng.normal(size=(6, 6)) * 0.05
    Q = B @ B.T + 1e-4 * np.eye(6)
    reference, P_reference = slam.predict(x, P, T, Q)
    update = CompiledUpdate({0: _camera(measurement.DEPTH)}, geometry._SMALL_ANGLE, CONVERGED)
    R, t, P_new = update.predict(x, P, T, Q)
    np.testing.assert_array_equal(R, reference.R)
    np.testing.assert_array_equal(t, reference.t)
    np.testing.assert_allclose(P_new, P_reference, rtol=1e-13, atol=1e-15)
    np.testing.assert_array_equal(P_new, P_new.T)
    assert update.predict(x, P, T, -Q) is None  # no Cholesky factor: slam.predict's own fallback takes it
    np.testing.assert_allclose(update.pose_right_cov(reference, P_reference), slam.pose_right_cov(reference, P_reference),
                               rtol=1e-13, atol=1e-16)


@pytest.mark.parametrize("kind", [measurement.DEPTH, measurement.DISPARITY])
def test_compiled_new_landmark_equals_the_inverse_observation_and_augmentation(kind):
    rng = np.random.default_rng(12)
    x = _state(rng, 3)
    A = rng.normal(size=(x.dim, x.dim)) * 0.1
    P = A @ A.T
    camera = _camera(kind)
    z = measurement.project(slam.camera_points(x, camera, (x.t + x.R @ np.array([4.0, 0.5, -0.3]))[None, :]),
                            camera.intrinsics, kind)[0]
    R_z = _noise(kind, rng, 1)[0]
    xyz_ref, B, N = slam.inverse_observation(x, camera, z, R_z)
    reference, P_reference = slam.augmented(x, P, xyz_ref, B, N)
    xyz, P_new = CompiledUpdate({0: camera}, geometry._SMALL_ANGLE, CONVERGED).augmented(x, P, camera, z, R_z)
    np.testing.assert_allclose(xyz, xyz_ref, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(P_new, P_reference, rtol=1e-13, atol=1e-15)
    np.testing.assert_array_equal(P_new, P_new.T)


def test_compiled_world_covariances_and_scan_equal_the_numpy_ones():
    rng = np.random.default_rng(13)
    x = _state(rng, 6)
    A = rng.normal(size=(x.dim, x.dim)) * 0.1
    P = A @ A.T
    update = CompiledUpdate({0: _camera(measurement.DEPTH)}, geometry._SMALL_ANGLE, CONVERGED)
    rows = np.array([4, 0, 5])
    covs = update.world_covs(x, P, rows)
    for n, row in enumerate(rows.tolist()):
        np.testing.assert_allclose(covs[n], slam.landmark_world_cov(x, P, row), rtol=1e-13, atol=1e-15)
    points = rng.normal(size=(300, 3)) * 5.0
    live = np.sort(rng.choice(300, 200, replace=False))
    centre = np.array([1.0, -1.0, 0.5])
    offset = points[live] - centre
    np.testing.assert_array_equal(update.live_within(points, live, centre, 4.0),
                                  live[np.einsum("ij,ij->i", offset, offset) <= 16.0])


def test_compiled_sure_view_equals_the_numpy_one():
    from camloc.slam_landmarks import surely_in_view

    rng = np.random.default_rng(15)
    x = _state(rng, 1)
    sensors = {0: _camera(measurement.DEPTH, 0), 1: _camera(measurement.PIXEL, 1)}
    sensors[1] = CameraModel(np.linalg.inv(sensors[1].T_robot_camera), sensors[1].intrinsics, measurement.PIXEL, 1)
    xyz = x.t + rng.normal(size=(400, 3)) * 6.0
    view = (1.0, 8.0, 0.6)
    expected = surely_in_view(x, sensors, xyz, view)
    assert 20 < np.count_nonzero(expected) < 380
    update = CompiledUpdate(sensors, geometry._SMALL_ANGLE, CONVERGED)
    np.testing.assert_array_equal(update.surely_in_view(x, xyz, view), expected)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 0.3, 2.0, np.pi - 2e-3])
def test_compiled_so3_steps_equal_geometry_s_at_every_angle(angle):
    """The compiled SO(3) exponential, log and their Jacobians are twins of geometry's one-vector
    forms: equal on both sides of the small-angle switch and near a half turn."""
    from camloc.slam_compiled import exp_and_left_jacobian, log_and_left_jacobian_inverse

    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    phi = angle * axis
    E, J = exp_and_left_jacobian(phi, geometry._SMALL_ANGLE)
    E_ref, J_ref = geometry.so3_exp_and_left_jacobian_one(phi)
    np.testing.assert_allclose(E, E_ref, atol=1e-15)
    np.testing.assert_allclose(J, J_ref, atol=1e-15)
    back, Ji, ok = log_and_left_jacobian_inverse(E_ref, geometry._SMALL_ANGLE)
    assert ok
    np.testing.assert_allclose(back, geometry.so3_log_one(E_ref), atol=1e-12)
    np.testing.assert_allclose(Ji, geometry.so3_left_jacobian_inverse_one(back), atol=1e-12)


@pytest.mark.parametrize("map_mode", ["prior", "none"])
def test_a_planar_robot_s_compiled_mapping_run_equals_the_numpy_run(map_mode):
    """A planar robot with a depth camera (its Q zero in z, roll and pitch: the compiled prediction
    falls back to numpy's): the compiled steps and numpy give the same run, in the plane; a point
    sensor has no compiled step (numpy runs)."""
    from camloc.localizer import resolved_config
    from camloc.localizer_config import LocalizerConfig
    from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar
    from camloc.slam_run import localize_mapping

    edit = dict(no_map=True) if map_mode == "none" else dict(withhold_map=0.5)
    ds = simulate_planar(PlanarSimulationConfig(sensors="cameras", poses=80, **edit), seed=3)
    config = resolved_config(LocalizerConfig(map=map_mode), ds)
    numpy_run, compiled_run = (localize_mapping(ds, config, compiled=c) for c in (False, True))
    _assert_same_run(compiled_run, numpy_run)
    assert np.all(compiled_run.estimate_xyz[:, 2] == 0.0) and compiled_run.filter_state.shape == (80, 3)
    points = simulate_planar(PlanarSimulationConfig(sensors="points", poses=20), seed=3)
    assert localize_mapping(points, resolved_config(LocalizerConfig(map="prior"), points)).summary["timing"]["engine"] == "numpy"
