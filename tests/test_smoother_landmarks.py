"""The smoother with landmarks as variables (issue 38, point 3): the observation's Jacobian with
respect to the landmark and the map prior against finite differences, the Schur solver and the
landmarks' covariances against dense linear algebra, the first estimate of added landmarks,
undetermined landmarks, a moved map under a prior, missing landmarks given as added, the
consistency of the landmarks' covariance, map.csv, and the command line."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.sparse.linalg import splu
from typer.testing import CliRunner

from camloc import geometry, measurement, smoother
from camloc.cli.app import app
from camloc.g2o import write_g2o
from camloc.localizer import LocalizerConfig, localize
from camloc.results import MAP_CSV, MAP_HEADER, LandmarkMap, map_text, read_map, write_map
from camloc.schur import SchurSolver
from camloc.simulate import SimulationConfig, simulate
from camloc.smoother_landmarks import initial_positions

STEP = 1e-6
PRIOR = smoother.SmootherConfig(map="prior", map_sigma=0.1)
NONE = smoother.SmootherConfig(map="none")


def position_rmse(xyz: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((xyz - truth) ** 2, axis=1))))


def with_associations(run, landmark: np.ndarray):
    return dataclasses.replace(run, associations=dataclasses.replace(run.associations, landmark=landmark))


@pytest.fixture(scope="module")
def world():
    """A 40-pose simulated world (two depth cameras) and its oracle run."""
    dataset = simulate(SimulationConfig(trajectory="smooth3d", poses=40, cameras=2), seed=21)
    return dataset, localize(dataset, LocalizerConfig(association="oracle"))


# --------------------------------------------------------------------------------------------
# Jacobians


@pytest.mark.parametrize("kind", [measurement.DEPTH, measurement.PIXEL, measurement.DISPARITY])
def test_observation_jacobian_with_respect_to_the_landmark(rng, kind):
    T = geometry.make_pose(geometry.so3_exp(rng.normal(size=3)), rng.normal(size=3))
    T_robot_camera = geometry.pose_from_euler(np.array([0.1, -0.2, 0.4, -1.2, 0.3, -1.4]))
    p_camera = np.column_stack([rng.uniform(-0.8, 0.8, (6, 2)), np.ones(6)]) * rng.uniform(0.5, 3.0, (6, 1))
    landmarks = geometry.transform_points(T @ T_robot_camera, p_camera)
    args = (np.repeat(T[None], 6, axis=0), np.repeat(T_robot_camera[None], 6, axis=0),
            np.tile([525.0, 520.0, 319.5, 239.5], (6, 1)))
    z, kinds = rng.normal(size=(6, 3)), np.full(6, kind)
    r, J_pose, J_landmark, _ = smoother.observation_factors(*args, landmarks, z, kinds)
    r_old, J_old, _ = smoother.observation_residuals(*args, landmarks, z, kinds)
    np.testing.assert_array_equal(r, r_old)
    np.testing.assert_array_equal(J_pose, J_old)  # the pose's Jacobian as before
    for axis in range(3):
        d = np.zeros(3)
        d[axis] = STEP
        plus = smoother.observation_residuals(*args, landmarks + d, z, kinds)[0]
        minus = smoother.observation_residuals(*args, landmarks - d, z, kinds)[0]
        np.testing.assert_allclose(J_landmark[:, :, axis], (plus - minus) / (2 * STEP), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("config", [PRIOR, NONE], ids=["prior", "none"])
def test_sparse_jacobian_with_landmark_columns_and_the_map_prior(world, rng, config):
    dataset, run = world
    problem = smoother.problem_from_run(dataset, run, config)
    T = smoother.initial_poses(dataset, run)
    problem, _ = smoother._with_initial_landmarks(problem, T)
    X = problem.landmarks.xyz + rng.normal(scale=0.05, size=problem.landmarks.xyz.shape)
    lin = smoother.linearize(problem, T, X)
    priors = problem.num_landmarks if config.map == "prior" else 0
    rows = 6 * (problem.num_poses - 1) + 3 * len(problem.obs_pose) + 3 * priors
    assert lin.jacobian.shape == (rows, problem.num_unknowns) and len(lin.prior_sq) == priors
    dense = lin.jacobian.toarray()
    n = problem.num_pose_unknowns
    for column in list(range(0, n, 17)) + list(range(n, problem.num_unknowns, 7)):
        d = np.zeros(problem.num_unknowns)
        d[column] = STEP
        plus = smoother.linearize(problem, *smoother._retract(problem, T, X, d)).residual
        minus = smoother.linearize(problem, *smoother._retract(problem, T, X, -d)).residual
        np.testing.assert_allclose(dense[:, column], (plus - minus) / (2 * STEP), atol=2e-4, err_msg=f"column {column}")
    if priors:  # the prior: (l - l_map) / sigma, whitened, in the cost
        expected = np.sum((X - problem.landmarks.prior_xyz) ** 2, axis=1) / 0.1**2
        np.testing.assert_allclose(lin.prior_sq, expected, rtol=1e-12)
        assert smoother.robust_cost(lin, 2.0) == pytest.approx(
            0.5 * (lin.odom_sq.sum() + smoother.huber_rho(lin.obs_sq, 2.0).sum() + expected.sum()), rel=1e-12)


# --------------------------------------------------------------------------------------------
# The Schur solver and the covariances


def test_schur_solver_and_covariances_equal_dense_linear_algebra(world, rng):
    dataset, run = world
    problem = smoother.problem_from_run(dataset, run, NONE)
    T = smoother.initial_poses(dataset, run)
    problem, _ = smoother._with_initial_landmarks(problem, T)
    H, g = smoother.normal_equations(smoother.linearize(problem, T), 2.0, newton=True)
    Hs, _ = smoother._scaled(H)
    dense = Hs.toarray()
    n = problem.num_pose_unknowns
    for damping in (0.0, 1e-2):
        solver = SchurSolver(Hs, n, damping)
        b = rng.normal(size=(Hs.shape[0], 2))
        expected = np.linalg.solve(dense + damping * np.eye(len(dense)), b)
        np.testing.assert_allclose(solver.solve(b), expected, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(solver.solve(b[:, 0]), expected[:, 0], rtol=1e-8, atol=1e-10)
    inverse = np.linalg.inv(dense)
    blocks = np.array([inverse[n + 3 * k: n + 3 * k + 3, n + 3 * k: n + 3 * k + 3] for k in range(problem.num_landmarks)])
    solver = SchurSolver(Hs, n)
    np.testing.assert_allclose(solver.landmark_covariances(), blocks, rtol=1e-8, atol=1e-12)  # selected inversion
    np.testing.assert_allclose(solver.landmark_covariances(by_solves=True), blocks, rtol=1e-8, atol=1e-12)  # its fallback


def test_the_steps_of_the_schur_solver_equal_superlu_on_the_whole_system(world):
    dataset, run = world
    problem = smoother.problem_from_run(dataset, run, PRIOR)
    T = smoother.initial_poses(dataset, run)
    problem, _ = smoother._with_initial_landmarks(problem, T)
    H, g = smoother.normal_equations(smoother.linearize(problem, T), 2.0, newton=True)
    Hs, d = smoother._scaled(H)
    whole = d * splu(Hs, permc_spec="MMD_AT_PLUS_A").solve(-d * g)
    np.testing.assert_allclose(smoother._solve_step(H, g, 0.0, problem.num_pose_unknowns), whole, rtol=1e-7, atol=1e-10)


class _DenseSolver:
    """Dense linear algebra in the place of the sparse Cholesky (and the Schur complement)."""

    def __init__(self, Hs, num_pose: int, damping: float = 0.0) -> None:
        self.num_pose = num_pose
        self.H = Hs.toarray() + damping * np.eye(Hs.shape[0])

    def solve(self, b, trans="N"):
        return np.linalg.solve(self.H, b)

    def landmark_covariances(self):
        inverse, n = np.linalg.inv(self.H), self.num_pose
        return np.array([inverse[k: k + 3, k: k + 3] for k in range(n, self.H.shape[0], 3)])


@pytest.mark.parametrize("config", [smoother.SmootherConfig(), PRIOR], ids=["exact", "prior"])
def test_the_smoother_on_the_sparse_cholesky_equals_it_on_dense_solves(world, monkeypatch, config):
    dataset, run = world
    sparse = smoother.smooth_run(dataset, run, config)
    monkeypatch.setattr(smoother, "_factorization", _DenseSolver)
    monkeypatch.setattr(smoother, "SchurSolver", _DenseSolver)  # the covariances' factor, where made afresh
    dense = smoother.smooth_run(dataset, run, config)
    assert sparse.converged and dense.iterations == sparse.iterations
    np.testing.assert_allclose(sparse.T_world_robot, dense.T_world_robot, rtol=0, atol=1e-9)
    assert sparse.final_cost == pytest.approx(dense.final_cost, rel=1e-12)
    if config.map == "prior":
        np.testing.assert_allclose(sparse.landmarks.xyz, dense.landmarks.xyz, rtol=0, atol=1e-9)
        np.testing.assert_allclose(sparse.landmarks.cov, dense.landmarks.cov, rtol=1e-8, atol=1e-15)


def test_a_prior_far_tighter_than_the_data_gives_the_exact_maps_result(world):
    dataset, run = world
    exact = smoother.smooth_run(dataset, run)
    assert exact.landmarks is None  # exact and complete: no landmark variable, the smoother as it was
    tight = smoother.smooth_run(dataset, run, smoother.SmootherConfig(map="prior", map_sigma=1e-7))
    np.testing.assert_allclose(tight.T_world_robot, exact.T_world_robot, atol=1e-6)
    assert tight.landmarks is not None and np.all(tight.landmarks.cov.diagonal(axis1=1, axis2=2) <= 1e-14)


# --------------------------------------------------------------------------------------------
# Added landmarks: first estimates, undetermined ones


def test_initial_positions_back_project_or_triangulate(rng):
    T_robot_camera = geometry.pose_from_euler(np.array([0.0, 0.0, 0.3, -np.pi / 2, 0.0, -np.pi / 2]))
    poses = np.array([geometry.make_pose(np.eye(3), np.array([x, 0.0, 0.0])) for x in (0.0, 0.5, 1.0)])
    point = np.array([3.0, 0.4, 0.6])
    intrinsics = np.tile([500.0, 500.0, 320.0, 240.0], (3, 1))
    mounts = np.repeat(T_robot_camera[None], 3, axis=0)
    p_cam = np.array([geometry.transform_points(np.linalg.inv(T @ T_robot_camera), point[None])[0] for T in poses])
    z = measurement.project(p_cam, intrinsics.T, measurement.DEPTH)
    # one landmark seen with depth (index 0), the same point seen by pixels alone from three poses
    # (index 1), and by a single pixel (index 2): a ray, undetermined
    kinds = np.array([measurement.DEPTH, measurement.PIXEL, measurement.PIXEL, measurement.PIXEL, measurement.PIXEL])
    T_all = np.concatenate([poses[:1], poses, poses[:1]])
    z_all = np.concatenate([z[:1], z, z[:1]])
    z_all[1:, 2] = 0.0
    found = initial_positions(T_all, np.concatenate([mounts, mounts[:2]]), np.concatenate([intrinsics, intrinsics[:2]]),
                              z_all, kinds, np.array([0, 1, 1, 1, 2]), 3)
    np.testing.assert_allclose(found[0], point, atol=1e-9)
    np.testing.assert_allclose(found[1], point, atol=1e-9)
    assert np.all(np.isnan(found[2]))


def pixel_world(seed: int):
    """A 60-pose world of two pixel-only cameras, with its oracle run."""
    dataset = simulate(SimulationConfig(trajectory="smooth3d", poses=60, cameras=2, intrinsics="pixel",
                                        measurement="pixel"), seed=seed)
    return dataset, localize(dataset, LocalizerConfig(association="oracle"))


def test_a_landmark_seen_once_by_a_pixel_camera_is_left_out_not_guessed():
    dataset, run = pixel_world(5)
    landmark = run.associations.landmark.copy()
    seen = np.flatnonzero(landmark >= 0)
    lone = seen[0]
    landmark[lone] = 777_777  # a landmark the map lacks, seen by one pixel ray only
    result = smoother.smooth_run(dataset, with_associations(run, landmark))
    np.testing.assert_array_equal(result.undetermined_landmarks, [777_777])
    assert result.landmarks is None  # the map held exact: no other landmark variable
    assert result.observation_factors == len(seen) - 1
    table = smoother.estimated_map(dataset, with_associations(run, landmark), result, smoother.SmootherConfig())
    assert 777_777 not in table.ids.tolist()
    # where the run's own map has it (a mapping run added it), its row stays, the run's estimate
    own = LandmarkMap(np.array([777_777]), np.array([[1.0, 2.0, 0.5]]), 0.04 * np.eye(3)[None], np.array([True]),
                      np.array([1]))
    mapped_run = dataclasses.replace(with_associations(run, landmark), landmark_map=own)
    table = smoother.estimated_map(dataset, mapped_run, result, smoother.SmootherConfig())
    row = table.ids.tolist().index(777_777)
    assert table.added[row] and table.observations[row] == 1
    np.testing.assert_array_equal(table.xyz[row], own.xyz[0])
    np.testing.assert_array_equal(table.cov[row], own.cov[0])
    # with no map, landmarks seen by a single ray are left out the same way, and named
    result = smoother.smooth_run(dataset, run, NONE)
    counts = np.bincount(np.searchsorted(dataset.landmark_ids, run.associations.landmark[seen]))
    assert len(result.undetermined_landmarks) >= np.count_nonzero(counts == 1) > 0


# --------------------------------------------------------------------------------------------
# Accuracy: a moved map, missing landmarks, no map


def moved_world(seed: int):
    """A 150-pose world whose map has a quarter of its landmarks moved 0.3 m (observations of the
    true ones), its oracle run on that map, and the true map."""
    truth = simulate(SimulationConfig(trajectory="grid", poses=150), seed=seed)
    rng = np.random.default_rng(seed)
    moved = rng.random(len(truth.landmark_ids)) < 0.25
    direction = rng.normal(size=(len(moved), 3))
    direction /= np.linalg.norm(direction, axis=1)[:, None]
    xyz = truth.landmark_xyz + 0.3 * moved[:, None] * direction
    dataset = dataclasses.replace(truth, landmark_xyz=xyz)
    return dataset, localize(dataset, LocalizerConfig(association="oracle")), truth, moved


@pytest.mark.parametrize("seed", [1, 2])
def test_a_moved_map_is_corrected_under_a_prior_and_not_under_exact(seed):
    dataset, run, truth, moved = moved_world(seed)
    exact = smoother.smooth_run(dataset, run)
    prior = smoother.smooth_run(dataset, run, PRIOR)
    exact_rmse, prior_rmse = (position_rmse(r.xyz, dataset.truth_xyz) for r in (exact, prior))
    assert prior_rmse < exact_rmse, (prior_rmse, exact_rmse)
    # the moved landmarks come back: their error well under the 0.3 m they moved
    estimated = dict(zip(prior.landmarks.ids.tolist(), prior.landmarks.xyz))
    ids = [i for i in truth.landmark_ids[moved].tolist() if i in estimated]
    true_xyz = dict(zip(truth.landmark_ids.tolist(), truth.landmark_xyz))
    errors = np.array([np.linalg.norm(estimated[i] - true_xyz[i]) for i in ids])
    assert len(ids) > 10 and np.median(errors) < 0.15, np.median(errors)


def missing_world(seed: int, **simulation):
    """A world whose map lacks a fifth of its landmarks; its oracle run on that map, with the
    observations of the missing ones handed back their true ids (added landmarks)."""
    truth = simulate(SimulationConfig(trajectory="smooth3d", poses=80, **simulation), seed=seed)
    rng = np.random.default_rng(seed)
    missing = rng.random(len(truth.landmark_ids)) < 0.2
    dataset = dataclasses.replace(truth, landmark_ids=truth.landmark_ids[~missing],
                                  landmark_xyz=truth.landmark_xyz[~missing])
    run = localize(dataset, LocalizerConfig(association="oracle"))
    landmark = run.associations.landmark.copy()
    handed = np.isin(run.associations.true_landmark, truth.landmark_ids[missing])
    landmark[handed] = run.associations.true_landmark[handed]
    return dataset, with_associations(run, landmark), truth, truth.landmark_ids[missing]


@pytest.mark.parametrize("simulation", [{}, {"cameras": 2, "intrinsics": "pixel", "measurement": "pixel"}],
                         ids=["depth", "pixel"])
def test_landmarks_missing_from_the_map_are_added_near_the_truth(simulation):
    dataset, run, truth, missing = missing_world(3, **simulation)
    result = smoother.smooth_run(dataset, run)
    lm = result.landmarks
    # every missing landmark that observations were handed back is added, or named undetermined
    # (seen by a single ray: a pixel-only camera's lone observation)
    handed = np.intersect1d(missing, run.associations.landmark)
    assert lm.added.all() and sorted(lm.ids.tolist() + result.undetermined_landmarks.tolist()) == handed.tolist()
    assert len(lm.ids) >= 0.5 * len(handed)
    true_xyz = dict(zip(truth.landmark_ids.tolist(), truth.landmark_xyz))
    errors = np.array([np.linalg.norm(x - true_xyz[i]) for i, x in zip(lm.ids.tolist(), lm.xyz)])
    assert np.median(errors) < 0.1, np.median(errors)
    # using them helps the poses: better than leaving those observations out
    without = smoother.smooth_run(dataset, with_associations(run, np.where(np.isin(run.associations.landmark, missing),
                                                                           -1, run.associations.landmark)))
    assert position_rmse(result.xyz, dataset.truth_xyz) < position_rmse(without.xyz, dataset.truth_xyz)


@pytest.mark.parametrize("simulation", [{}, {"cameras": 2, "intrinsics": "pixel", "measurement": "pixel"}],
                         ids=["depth", "pixel"])
def test_the_added_landmarks_covariance_is_consistent_over_seeds(simulation):
    """NEES of the added landmarks (chi^2 with 3 dof where consistent) near 3 over six seeds.
    (Under --map none the landmarks' errors share the drift of the poses, so a few seeds are a
    few samples: docs/performance.md gives that figure.)"""
    nees = []
    for seed in range(200, 206):
        dataset, run, truth, _ = missing_world(seed, **simulation)
        result = smoother.smooth_run(dataset, run)
        true_xyz = dict(zip(truth.landmark_ids.tolist(), truth.landmark_xyz))
        error = result.landmarks.xyz - np.array([true_xyz[i] for i in result.landmarks.ids.tolist()])
        nees.extend(np.einsum("ni,ni->n", error, np.linalg.solve(result.landmarks.cov, error[:, :, None])[:, :, 0]))
    mean = float(np.mean(nees))
    assert len(nees) > 100 and 2.3 < mean < 3.7, mean


# --------------------------------------------------------------------------------------------
# map.csv


def test_estimated_map_lists_every_landmark_by_mode(world):
    dataset, run = world
    for config in (smoother.SmootherConfig(), PRIOR, NONE):
        result = smoother.smooth_run(dataset, run, config)
        table = smoother.estimated_map(dataset, run, result, config)
        assert np.all(np.diff(table.ids) > 0) and not table.added.any()
        if config.map == "none":
            assert set(table.ids.tolist()) == set(result.landmarks.ids.tolist())
        else:
            np.testing.assert_array_equal(table.ids, np.sort(dataset.landmark_ids))
        if config.map == "exact":
            np.testing.assert_array_equal(table.cov, 0.0)
        seen = run.associations.landmark[run.associations.landmark >= 0]
        assert table.observations.sum() == len(seen)
        eig = np.linalg.eigvalsh(table.cov)
        assert np.all(eig >= 0.0) and (config.map == "exact" or np.all(eig[:, 0] > 0.0))
        if config.map == "prior":
            assert np.all(eig <= 0.1**2 * (1 + 1e-9))  # the prior's variance bounds the estimate's


def test_map_csv_round_trip(tmp_path, rng):
    cov = rng.normal(size=(3, 3, 3))
    cov = cov @ np.swapaxes(cov, 1, 2)
    table = LandmarkMap(np.array([3, 7, 10_000]), rng.normal(size=(3, 3)), cov, np.array([False, False, True]),
                        np.array([4, 0, 2]))
    text = map_text(table)
    assert text.splitlines()[0] == ",".join(MAP_HEADER) and text.splitlines()[3].endswith(",added,2")
    path = tmp_path / MAP_CSV
    path.write_text(text)
    back = read_map(path)
    for name in ("ids", "xyz", "cov", "added", "observations"):
        np.testing.assert_array_equal(getattr(back, name), getattr(table, name))


# --------------------------------------------------------------------------------------------
# The command line


def invoke(*args):
    return CliRunner().invoke(app, [str(arg) for arg in args])


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cli-map")
    dataset_path = folder / "world.g2o"
    write_g2o(simulate(SimulationConfig(trajectory="grid", poses=50), seed=6), dataset_path)
    outcome = invoke("run", dataset_path, "-o", folder / "run", "--association", "oracle", "--quiet")
    assert outcome.exit_code == 0, outcome.output
    return dataset_path, folder / "run"


@pytest.mark.parametrize("mode", ["exact", "prior", "none"])
def test_cli_smooth_with_each_map_mode_writes_map_csv(cli_run, mode):
    _, run_dir = cli_run
    outcome = invoke("smooth", run_dir, "--map", mode, "--map-sigma", "0.05", "--json")
    assert outcome.exit_code == 0, outcome.output
    report = json.loads(outcome.stdout)
    assert report["map"] == mode and report["map_file"] == str(run_dir / MAP_CSV)
    assert report["map_sigma"] == (0.05 if mode == "prior" else None)
    table = read_map(run_dir / MAP_CSV)
    assert len(table.ids) > 20 and report["landmarks"]["added"] == 0
    assert report["landmarks"]["estimated"] == (0 if mode == "exact" else int(np.count_nonzero(table.observations)))
    if mode == "prior":
        assert np.all(np.linalg.eigvalsh(table.cov) <= 0.05**2 * (1 + 1e-9))
    if mode != "none":  # without a map the absolute position drifts (issue 38: 0.5 m on the real file)
        assert report["smoothed"]["ate"]["rmse"] < report["estimate"]["ate"]["rmse"]


def test_cli_smooth_prints_the_map_row_and_refuses_bad_map_options(cli_run):
    _, run_dir = cli_run
    outcome = invoke("smooth", run_dir, "--map", "prior")
    assert outcome.exit_code == 0, outcome.output
    assert "prior, sigma 0.1 m" in outcome.stdout and f"{run_dir / MAP_CSV}" in outcome.stdout
    for args, fragment in ((("--map", "fixed"), "expected one of exact, prior, none, found 'fixed'"),
                           (("--map", "prior", "--map-sigma", "0"), "map_sigma must be a finite number of metres > 0")):
        outcome = invoke("smooth", run_dir, *args)
        assert outcome.exit_code == 2, outcome.output
        assert fragment in outcome.stderr and "Traceback" not in outcome.output


def test_write_map_is_atomic_and_only_into_a_run_folder(tmp_path, cli_run):
    _, run_dir = cli_run
    from camloc.errors import CamlocError

    empty = LandmarkMap(np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, dtype=bool),
                        np.zeros(0, dtype=np.int64))
    with pytest.raises(CamlocError, match="expected a run folder"):
        write_map(tmp_path, empty)
    assert not (tmp_path / MAP_CSV).exists()
    path = write_map(run_dir, empty)
    assert read_map(path).ids.shape == (0,) and [p.name for p in run_dir.glob(".map.csv*")] == []


def test_cli_eval_scores_the_smoothed_map_against_a_true_map(tmp_path):
    truth = simulate(SimulationConfig(trajectory="grid", poses=80), seed=8)
    rng = np.random.default_rng(8)
    moved = rng.random(len(truth.landmark_ids)) < 0.25
    xyz = truth.landmark_xyz + 0.3 * moved[:, None] * np.array([0.0, 0.6, 0.8])
    write_g2o(truth, tmp_path / "truth.g2o")
    write_g2o(dataclasses.replace(truth, landmark_xyz=xyz), tmp_path / "moved.g2o")
    assert invoke("run", tmp_path / "moved.g2o", "-o", tmp_path / "run", "--association", "oracle", "-q").exit_code == 0
    assert not (tmp_path / "run" / MAP_CSV).exists()  # --map exact, nothing added: the given map, held
    outcome = invoke("eval", tmp_path / "run", "--true-map", tmp_path / "truth.g2o", "--json")
    assert outcome.exit_code == 0, outcome.output
    held = json.loads(outcome.stdout)["map"]
    assert json.loads(invoke("eval", tmp_path / "run", "--json").stdout)["map"] is None

    scores = {}
    for mode in ("exact", "prior"):
        assert invoke("smooth", tmp_path / "run", "--map", mode, "-q").exit_code == 0
        outcome = invoke("eval", tmp_path / "run", "--true-map", tmp_path / "truth.g2o", "--json")
        assert outcome.exit_code == 0, outcome.output
        scores[mode] = json.loads(outcome.stdout)["map"]
    exact, prior = scores["exact"]["mapped"], scores["prior"]["mapped"]
    given_rmse = float(np.sqrt(np.mean(np.sum((xyz - truth.landmark_xyz) ** 2, axis=1))))
    assert exact["count"] == len(truth.landmark_ids) and exact["rmse"] == pytest.approx(given_rmse)
    assert exact["nees"] is None and exact["unknown"] == 0  # held exact: zero covariances
    assert held["mapped"] == exact and held["moved"] == scores["exact"]["moved"] and held["moved"]["count"] == int(moved.sum())
    assert prior["rmse"] < 0.8 * exact["rmse"] and prior["nees"] is not None
    assert scores["prior"]["added"] == {"count": 0, "rmse": None, "max": None, "nees": None, "unknown": 0}
    tables = invoke("eval", tmp_path / "run", "--true-map", tmp_path / "truth.g2o")
    assert "map vs the true map" in tables.stdout and f"{prior['rmse']:.4f}" in tables.stdout


def test_the_conditioning_check_covers_the_landmarks(world):
    dataset, run = world
    result = smoother.smooth_run(dataset, run, NONE)
    assert np.isfinite(result.condition) and result.converged
    from camloc.errors import CamlocError

    with pytest.raises(CamlocError, match=r"do not determine every pose and landmark; worst determined: (pose|landmark) \d+"):
        smoother.smooth_run(dataset, run, dataclasses.replace(NONE, max_condition=10.0))


def test_added_landmarks_started_far_off_still_reach_the_same_solution():
    dataset, run, truth, _ = missing_world(3)
    reference = smoother.smooth_run(dataset, run)
    lm = reference.landmarks
    rng = np.random.default_rng(1)
    far = {int(i): x + rng.normal(scale=0.4, size=3) for i, x in zip(lm.ids, lm.xyz)}  # 0.7 m off on average
    iterations = []
    result = smoother.smooth_run(dataset, run, added_xyz=far, on_iteration=iterations.append)
    assert result.converged and result.final_cost == pytest.approx(reference.final_cost, rel=1e-9)
    np.testing.assert_allclose(result.landmarks.xyz, lm.xyz, atol=1e-6)
    np.testing.assert_allclose(result.T_world_robot, reference.T_world_robot, atol=1e-6)
    assert result.initial_cost > 2 * reference.initial_cost and len(iterations) == result.iterations


def test_selected_inversion_needs_no_fallback_on_a_grid_world(monkeypatch):
    # axis-aligned grid poses give normal-matrix entries that cancel exactly, which scipy's sparse
    # arithmetic drops from the pattern: the pairs of poses a landmark couples are added back
    dataset = simulate(SimulationConfig(trajectory="grid", poses=120), seed=2)
    run = localize(dataset, LocalizerConfig(association="oracle"))
    problem = smoother.problem_from_run(dataset, run, NONE)
    T = smoother.initial_poses(dataset, run)
    problem, _ = smoother._with_initial_landmarks(problem, T)
    H, _ = smoother.normal_equations(smoother.linearize(problem, T), 2.0, newton=True)
    Hs, _ = smoother._scaled(H)
    solver = SchurSolver(Hs, problem.num_pose_unknowns)
    expected = solver.landmark_covariances(by_solves=True)

    def no_fallback(self):
        raise AssertionError("fell back to solves")

    monkeypatch.setattr(SchurSolver, "_quadratic_forms_by_solves", no_fallback)
    np.testing.assert_allclose(solver.landmark_covariances(), expected, rtol=1e-8, atol=1e-14)


def test_cli_smooth_keeps_the_folder_whole_where_an_added_landmark_is_one_ray(tmp_path):
    """A mapping run added a landmark seen by a single pixel ray (the smoother cannot place it):
    after 'camloc smooth', map.csv still holds every landmark associations.csv points at, so the
    folder loads, and 'camloc eval' and a second smooth run (they refused it as inconsistent)."""
    from camloc.results import save_run

    dataset, run = pixel_world(5)
    landmark = run.associations.landmark.copy()
    lone = np.flatnonzero(landmark >= 0)[0]
    landmark[lone] = 777_777
    own = LandmarkMap(np.array([777_777]), np.array([[1.0, 2.0, 0.5]]), 0.04 * np.eye(3)[None], np.array([True]),
                      np.array([1]))
    write_g2o(dataset, tmp_path / "world.g2o")
    run_dir = save_run(tmp_path / "run", dataclasses.replace(with_associations(run, landmark), landmark_map=own))
    for mode in ("exact", "prior", "none"):
        outcome = invoke("smooth", run_dir, "--dataset", tmp_path / "world.g2o", "--map", mode, "--json")
        assert outcome.exit_code == 0, outcome.output
        assert json.loads(outcome.stdout)["landmarks"]["undetermined"] >= 1
        table = read_map(run_dir / MAP_CSV)
        assert 777_777 in table.ids.tolist()
        outcome = invoke("eval", run_dir, "--json")
        assert outcome.exit_code == 0, outcome.output
