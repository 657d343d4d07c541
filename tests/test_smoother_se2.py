"""The planar smoother (``camloc.smoother_se2``): its odometry Jacobians against finite
differences, that it lowers the error of the filter it starts from, and that it finds the MAP
GTSAM finds with its own Pose2 factors (skipped where gtsam is not installed)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from camloc import geometry, planar
from camloc.localizer import localize
from camloc.localizer_config import LocalizerConfig
from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar
from camloc.smoother import SmootherConfig
from camloc.smoother_se2 import observation_residuals, odometry_residual, planar_problem, smooth_planar, smooth_planar_run

STEP = 1e-6


def _numeric(function, x: np.ndarray) -> np.ndarray:
    columns = []
    for i in range(3):
        d = np.zeros(3)
        d[i] = STEP
        columns.append((function(planar.retract(x, d)) - function(planar.retract(x, -d))) / (2 * STEP))
    return np.stack(columns, axis=-1)


@pytest.mark.parametrize("trial", range(5))
def test_odometry_factor_jacobians(rng, trial):
    a = np.array([*rng.uniform(-3, 3, 2), rng.uniform(-math.pi, math.pi)])
    u = np.array([*rng.uniform(-1, 1, 2), rng.uniform(-1, 1)])
    b = planar.compose(planar.compose(a, u), rng.normal(scale=0.1, size=3))
    r, A, B = odometry_residual(a, b, u)
    assert A == pytest.approx(_numeric(lambda s: odometry_residual(s, b, u)[0], a), abs=1e-6)
    assert B == pytest.approx(_numeric(lambda s: odometry_residual(a, s, u)[0], b), abs=1e-6)
    assert odometry_residual(a, planar.compose(a, u), u)[0] == pytest.approx(np.zeros(3), abs=1e-12)


@pytest.fixture(scope="module")
def marker_world():
    dataset = simulate_planar(PlanarSimulationConfig(sensors="markers,points", poses=60), seed=2)
    return dataset, localize(dataset, LocalizerConfig(association="oracle"))


def test_observation_factor_jacobians(marker_world):
    dataset, run = marker_world
    problem = planar_problem(dataset, run)
    x = planar.flatten(geometry.pose_from_quat(run.estimate_xyz, run.estimate_quat_xyzw))
    _, J = observation_residuals(problem, x)
    for i in range(0, problem.obs_pose.size, 97):
        k = int(problem.obs_pose[i])

        def residual(state, i=i, k=k):
            moved = x.copy()
            moved[k] = state
            return observation_residuals(problem, moved)[0][i]

        assert J[i] == pytest.approx(_numeric(residual, x[k]), abs=1e-5)


def test_smoothing_lowers_the_filters_error(marker_world):
    dataset, run = marker_world
    result = smooth_planar_run(dataset, run, SmootherConfig())
    assert result.converged
    truth = dataset.truth_xyz[:, :2]
    filter_rmse = np.sqrt(np.mean(np.sum((run.estimate_xyz[:, :2] - truth) ** 2, axis=1)))
    smoothed_rmse = np.sqrt(np.mean(np.sum((result.xyz[:, :2] - truth) ** 2, axis=1)))
    assert smoothed_rmse < filter_rmse
    assert result.xyz[0] == pytest.approx(dataset.start_xyz)


def test_the_map_is_gtsams(marker_world):
    """The same graph in GTSAM: Pose2 variables, BetweenFactorPose2 for each odometry edge and for
    each marker observation (a marker's pose held by NonlinearEqualityPose2), Gaussian noise of the
    file's covariances, Levenberg-Marquardt. GTSAM's Pose2 error is the SE(2) logarithm where g2o's
    (and camloc's) is (t, theta): the two MAPs differ at second order in the residuals (measured:
    1e-5 m and 3e-4 deg on this world), far below the noise (5 cm, 3 deg)."""
    gtsam = pytest.importorskip("gtsam")
    full, _ = marker_world
    dataset = simulate_planar(PlanarSimulationConfig(sensors="markers", poses=60), seed=2)
    run = localize(dataset, LocalizerConfig(association="oracle"))
    problem = planar_problem(dataset, run)
    x0 = planar.flatten(geometry.pose_from_quat(run.estimate_xyz, run.estimate_quat_xyzw))
    ours = planar.flatten(smooth_planar(problem, x0, SmootherConfig(huber=math.inf)).T_world_robot)

    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    pose_key, marker_key = (lambda k: gtsam.symbol("x", k)), (lambda j: gtsam.symbol("m", j))
    graph.add(gtsam.NonlinearEqualityPose2(pose_key(0), gtsam.Pose2(*problem.x_start)))
    for k, u in enumerate(problem.u):
        noise = gtsam.noiseModel.Gaussian.Covariance(planar.planar_block(dataset.odom_cov[k]))
        graph.add(gtsam.BetweenFactorPose2(pose_key(k), pose_key(k + 1), gtsam.Pose2(*u), noise))
    for k in range(dataset.num_poses):
        values.insert(pose_key(k), gtsam.Pose2(*x0[k]))
    for i, j in enumerate(problem.obs_landmark.tolist()):
        if not values.exists(marker_key(j)):
            marker = gtsam.Pose2(dataset.landmark_xyz[j, 0], dataset.landmark_xyz[j, 1], dataset.landmark_heading[j])
            graph.add(gtsam.NonlinearEqualityPose2(marker_key(j), marker))
            values.insert(marker_key(j), marker)
        W = problem.obs_whiten[i]
        noise = gtsam.noiseModel.Gaussian.Covariance(np.linalg.solve(W.T @ W, np.eye(3)))
        graph.add(gtsam.BetweenFactorPose2(pose_key(int(problem.obs_pose[i])), marker_key(j), gtsam.Pose2(*problem.obs_z[i]), noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    solved = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    theirs = np.array([[solved.atPose2(pose_key(k)).x(), solved.atPose2(pose_key(k)).y(), solved.atPose2(pose_key(k)).theta()]
                       for k in range(dataset.num_poses)])
    assert np.abs(theirs[:, :2] - ours[:, :2]).max() < 1e-4
    assert np.degrees(np.abs(planar.wrap(theirs[:, 2] - ours[:, 2]))).max() < 5e-3


@pytest.fixture(scope="module")
def planar_tag_world():
    """A planar robot's camera seeing tags (``simulate_tags.planar_tags``), the beam's run."""
    from camloc.simulate_tags import planar_tags

    dataset = planar_tags(simulate_planar(PlanarSimulationConfig(sensors="cameras", poses=80), seed=1), seed=1,
                          sigma_rad=math.radians(1.0))
    return dataset, localize(dataset)


def test_tag_orientation_factor_jacobians(planar_tag_world):
    """A tag's orientation in the planar smoother: e = Log(R_pred^-1 R_meas) and its Jacobian
    (a turn about z through Jl^-1(e)) against central differences on SE(2)."""
    from camloc.measurement import TAG_ROTATION

    dataset, run = planar_tag_world
    problem = planar_problem(dataset, run)
    rotation = np.flatnonzero(problem.obs_kind == TAG_ROTATION)
    assert rotation.size > 0.9 * np.count_nonzero(run.associations.landmark >= 0)
    x = planar.flatten(geometry.pose_from_quat(run.estimate_xyz, run.estimate_quat_xyzw))
    _, J = observation_residuals(problem, x)
    for i in rotation[:: max(1, rotation.size // 4)]:
        k = int(problem.obs_pose[i])

        def residual(state, i=i, k=k):
            moved = x.copy()
            moved[k] = state
            return observation_residuals(problem, moved)[0][i]

        assert J[i] == pytest.approx(_numeric(residual, x[k]), abs=1e-5)
        assert np.all(J[i][:, :2] == 0.0)  # the orientation does not see the robot's position


def test_tag_orientation_lowers_the_smoothed_heading_error(planar_tag_world):
    """The same run smoothed with its tags' orientations and from their centres alone: the
    heading RMSE at least 30% lower with them (measured 38-46% on three seeds of 150 poses)."""
    from camloc.simulate_tags import without_orientations

    dataset, run = planar_tag_world
    errors = []
    for data in (dataset, without_orientations(dataset)):
        result = smooth_planar_run(data, run, SmootherConfig())
        heading = planar.flatten(geometry.pose_from_quat(result.xyz, result.quat_xyzw))[:, 2]
        errors.append(float(np.sqrt(np.mean(planar.wrap(heading - planar.flatten(dataset.T_world_truth)[:, 2]) ** 2))))
    assert errors[0] <= 0.7 * errors[1], errors
