"""With the true association, the filter is consistent on every kind of world the simulator makes:
the run's NEES and NIS inside their chi-square bounds (issue 21, point 1), NEES's interval for one
run holding its 95% on a filter consistent by construction, and Bar-Shalom's Monte Carlo test.
What is left of NEES's excess (the gate, and the linearization at poses with one or two pixel
pairs) is measured in docs/filter.md, "Consistency: NEES".

Simulated data carry the exact models and the noise their information states
(``tests/test_simulate.py``), so a filter given the file's own landmark ids has nothing to blame
but itself.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

import camloc
from camloc import ekf, metrics
from camloc.filters import make_filter
from camloc.simulate import INTRINSICS, TRAJECTORIES, SimulationConfig, simulate

POSES = 200
WORLDS = list(itertools.product(TRAJECTORIES, INTRINSICS, (1, 2)))
WORLD_IDS = [f"{trajectory}-{intrinsics}-{cameras}cam" for trajectory, intrinsics, cameras in WORLDS]


def _oracle_run(trajectory: str, intrinsics: str, cameras: int, *, seed: int = 0):
    config = SimulationConfig(trajectory=trajectory, intrinsics=intrinsics, cameras=cameras, poses=POSES)
    dataset = simulate(config, seed=seed)
    result = camloc.localize(dataset, camloc.LocalizerConfig(association="oracle"), parallel=False)
    return dataset, result


@pytest.fixture(scope="module")
def oracle_runs():
    """Every kind of world, run once for the module's tests (about 6 s together)."""
    return {world_id: _oracle_run(*world) for world_id, world in zip(WORLD_IDS, WORLDS)}


def posterior_costs(dataset, result) -> np.ndarray:
    """(U,) the MAP cost ``d' P^-1 d + r' R^-1 r`` of each update's posterior (``ekf.posterior_cost``),
    rebuilt from the run: the prior predicted from the previous pose's posterior, the posterior
    the run stored, the pairs it accepted. For a linear model it is the NIS; for an iterated update
    it is the chi^2(3p) statistic that carries no linearization error of the prior's point."""
    euler = make_filter("euler")
    row_of_pose = {int(i): k for k, i in enumerate(dataset.pose_ids)}
    row_of_landmark = {int(i): j for j, i in enumerate(dataset.landmark_ids)}
    chosen = result.associations.landmark
    costs = []
    for pose_id in result.update_pose_ids:
        k = row_of_pose[int(pose_id)]
        x_prior, F, G = euler.predict(result.filter_state[k - 1], dataset.T_odometry[k - 1])
        P_prior = ekf.predict(result.filter_cov[k - 1], F, G, dataset.odom_cov[k - 1])
        obs = np.flatnonzero((dataset.obs_pose_index == k) & (chosen >= 0))
        landmarks = dataset.landmark_xyz[[row_of_landmark[int(i)] for i in chosen[obs]]]

        def measure(state, obs=obs, landmarks=landmarks):
            z_hat, H = np.empty((obs.size, 3)), np.empty((obs.size, 3, 6))
            for camera_id in np.unique(dataset.obs_camera[obs]):
                mine = dataset.obs_camera[obs] == camera_id
                c = dataset.cameras[int(camera_id)]
                z_hat[mine], H[mine] = euler.observe(state, c.T_robot_camera, (c.fx, c.fy, c.cx, c.cy), landmarks[mine])
            return z_hat.reshape(-1), H.reshape(-1, 6)

        costs.append(ekf.posterior_cost(result.filter_state[k], x_prior, P_prior, dataset.obs_z[obs].reshape(-1),
                                        dataset.obs_cov[obs], measure, euler.difference))
    return np.array(costs)


def linear_gaussian_nees(rng, *, runs: int, steps: int, ratio: float, warm_up: int = 50) -> np.ndarray:
    """(runs, steps) NEES of a perfectly consistent Kalman filter: a 6-D random walk (odometry-like
    steps of 0.1 m and 0.02 rad) measured whole at every step with a noise ``ratio`` times the step.

    Linear and Gaussian, so its NEES is exactly chi2(6) at every step; its error persists from
    step to step (the more, the larger ``ratio``). The gain does not depend on the data, so the
    runs advance together; ``warm_up`` steps let the covariance settle first.
    """
    q_sigma = np.array([0.1, 0.1, 0.1, 0.02, 0.02, 0.02])
    Q, R = np.diag(q_sigma**2), np.diag((ratio * q_sigma) ** 2)
    P = Q.copy()
    error = rng.standard_normal((runs, 6)) * q_sigma  # x_true - x_hat
    nees = np.empty((runs, warm_up + steps))
    for k in range(warm_up + steps):
        P = P + Q  # predict: F = I, G = I
        error = error + rng.standard_normal((runs, 6)) * q_sigma
        K = np.linalg.solve(P + R, P).T  # K = P H' S^-1, H = I
        measured = error + rng.standard_normal((runs, 6)) * ratio * q_sigma  # z - H x_hat
        error = error - measured @ K.T  # x_hat += K (z - H x_hat)
        I_K = np.eye(6) - K
        P = I_K @ P @ I_K.T + K @ R @ K.T  # Joseph form
        nees[:, k] = np.einsum("ri,ij,rj->r", error, np.linalg.inv(P), error)
    return nees[:, warm_up:]


def _rejected(summary: dict) -> bool:
    return summary["verdict"] != "consistent"


@pytest.mark.parametrize("ratio, naive_rejects_at_least", [(1.0, 0.0), (3.0, 0.15)])
def test_single_run_interval_rejects_a_consistent_filter_five_percent_of_the_time(ratio, naive_rejects_at_least):
    # 200 runs of 200 steps of a filter consistent by construction. Its per-step NEES is chi2(6),
    # but the steps of a run share their error: at ratio 3 (lag-1 autocorrelation of NEES about
    # 0.5, tau about 3) the interval of 200 independent samples rejects a quarter of the runs.
    # The interval of the run's effective number of independent poses holds its 95%; at ratio 1
    # (tau about 1.3, camloc's oracle runs are near there) both do.
    nees = linear_gaussian_nees(np.random.default_rng(21), runs=200, steps=POSES, ratio=ratio)
    assert abs(np.mean(nees) - metrics.POSE_DOF) < 0.1  # the filter is consistent
    corrected = np.mean([_rejected(metrics.nees_summary(run)) for run in nees])
    naive = np.mean([not _inside(np.mean(run), metrics.mean_chi2_bounds(metrics.POSE_DOF, run.size)) for run in nees])
    assert 0.01 <= corrected <= 0.12, (corrected, naive)
    assert naive >= naive_rejects_at_least, (corrected, naive)
    # ... and it still sees a covariance 20% too small or too large.
    assert np.mean([_rejected(metrics.nees_summary(run / 0.8)) for run in nees]) > 0.5
    assert np.mean([_rejected(metrics.nees_summary(run / 1.2)) for run in nees]) > 0.5


def _inside(mean: float, bounds: list[float]) -> bool:
    return bounds[0] <= mean <= bounds[1]


@pytest.mark.parametrize("world_id", WORLD_IDS)
def test_oracle_updates_are_consistent_at_their_posterior(oracle_runs, world_id):
    # The filter itself: its updates' chi^2 statistic, taken where the iterated update ends, is
    # inside the bounds of its degrees of freedom on every kind of world (pixel cameras too).
    dataset, result = oracle_runs[world_id]
    costs = posterior_costs(dataset, result)
    summary = metrics.nis_summary(costs, result.nis_dof)
    assert result.nis.size > 0.8 * POSES and costs.shape == result.nis.shape
    assert _inside(summary["mean_per_dof"], summary["mean_bounds"]), (summary["mean_per_dof"], summary["mean_bounds"])


@pytest.mark.parametrize("world_id", WORLD_IDS)
def test_oracle_run_reports_nis_inside_its_bounds(oracle_runs, world_id):
    # What 'camloc eval' reads: the run's own NIS.
    _, result = oracle_runs[world_id]
    summary = metrics.nis_summary(result.nis, result.nis_dof)
    assert summary["verdict"] == "consistent", summary


def test_oracle_run_nees_verdict_on_every_kind_of_world(oracle_runs):
    # One run per kind of world, each judged by the interval of its effective number of
    # independent poses. A consistent filter fails a run 5% of the time, so 12 kinds are not all
    # expected to pass: at most 2 (a binomial(12, 0.05) exceeds 2 with probability 0.02). The
    # Monte Carlo study (docs/filter.md, "Consistency") measured 0-30% per kind with the default
    # gate, the excess being the gate and the linearization at poses with one or two pixel pairs;
    # these runs (seed 0) reject one, smooth3d-normalized-1cam (6.71 against [5.37, 6.67]).
    summaries = {world_id: metrics.nees_summary(metrics.run_nees(result)) for world_id, (_, result) in oracle_runs.items()}
    rejected = [summary["verdict_line"] for summary in summaries.values() if summary["verdict"] != "consistent"]
    assert len(rejected) <= 2, rejected
    assert all(summary["verdict"] != "underconfident" for summary in summaries.values())
    assert all(1.0 <= summary["autocorrelation_time"] <= 3.0 for summary in summaries.values())
    # ... and a covariance 20% too small on every pose is seen on nearly every kind.
    scaled = [metrics.nees_summary(metrics.run_nees(result) / 0.8)["verdict"] for _, result in oracle_runs.values()]
    assert scaled.count("overconfident") >= 10, scaled


MONTE_CARLO_SEEDS = 16
MONTE_CARLO_WORLDS = [("grid", "normalized", 2), ("smooth3d", "pixel", 2), ("aerial", "normalized", 2)]


def _oracle_nees(trajectory: str, intrinsics: str, cameras: int, seeds: int, **options) -> np.ndarray:
    """(seeds, POSES) per-pose NEES of oracle runs on seeds 0.. of one kind of world; ``options``
    split between ``SimulationConfig`` (``*_sigma_scale``) and ``LocalizerConfig`` (the rest)."""
    simulation = {key: options.pop(key) for key in list(options) if key.endswith("sigma_scale")}
    config = SimulationConfig(trajectory=trajectory, intrinsics=intrinsics, cameras=cameras, poses=POSES, **simulation)
    localizer = camloc.LocalizerConfig(association="oracle", **options)
    return np.array([metrics.run_nees(camloc.localize(simulate(config, seed=seed), localizer, parallel=False))
                     for seed in range(seeds)])


@pytest.mark.parametrize("world", MONTE_CARLO_WORLDS, ids=lambda world: "-".join(map(str, world)))
def test_monte_carlo_nees_of_oracle_runs_is_inside_its_bounds(world):
    # Bar-Shalom's test: at each pose, the average NEES of independent runs against chi2(6N)/N;
    # the grand mean against the standard error of the runs' means. The gate all but open
    # (1 - 1e-6): the oracle's 99% gate drops the pairs whose innovation the prior's error made
    # large, which raises NEES by 1.5% (docs/filter.md); the default gate is tested above.
    nees = _oracle_nees(*world, MONTE_CARLO_SEEDS, gate=1.0 - 1e-6)
    summary = metrics.monte_carlo_nees(nees)
    assert abs(summary["mean"] - metrics.POSE_DOF) < 3.0 * summary["standard_error"], summary["mean"]
    assert summary["within_bounds_share"] >= 0.85
    # The same runs with a covariance 10% too small fail the grand mean's test. (The per-pose test
    # of 16 runs is too wide to see 10%: it keeps 86-87% of the poses inside.)
    overconfident = metrics.monte_carlo_nees(nees / 0.9)
    assert overconfident["mean"] - metrics.POSE_DOF > 3.0 * overconfident["standard_error"]


@pytest.mark.slow
def test_monte_carlo_nees_is_consistent_on_every_kind_of_world_once_the_prior_is_tight():
    # What is left of the excess without the gate is the first-order linearization: at poses with
    # one or two pixel pairs, a wide prior against a precise bearing leaves a curved posterior
    # whose Gauss-Newton covariance is too small (aerial-pixel-1cam: 6.27 +- 0.07 over 30 runs).
    # With odometry 10x more precise the prior is tight enough for the linearization: every kind
    # of world is consistent (measured: grand means 5.88..6.13, all within 1.6 standard errors).
    for world in WORLDS:
        summary = metrics.monte_carlo_nees(_oracle_nees(*world, 20, gate=1.0 - 1e-6, odometry_sigma_scale=0.1))
        assert abs(summary["mean"] - metrics.POSE_DOF) < 3.0 * summary["standard_error"], (world, summary["mean"])
        assert summary["within_bounds_share"] >= 0.8, (world, summary["within_bounds_share"])


def test_oracle_runs_nees_pooled_over_the_worlds_is_near_its_dof(oracle_runs):
    # What holds today, tight enough to catch a covariance off by a factor (reading the odometry's
    # rotation information as a rotation angle's makes NEES about 2x): within 10% of 6 dof.
    nees = np.concatenate([metrics.run_nees(result) for _, result in oracle_runs.values()])
    summary = metrics.nees_summary(nees)
    assert summary["poses"] == len(WORLDS) * (POSES - 1)
    assert 5.4 <= summary["mean"] <= 6.6, summary["verdict_line"]


@pytest.fixture(scope="module")
def beam_runs():
    """Every kind of world with a tenth of its detections clutter, run with the default
    association (the beam), once for the module's tests (about 30 s together)."""
    runs = {}
    for world_id, (trajectory, intrinsics, cameras) in zip(WORLD_IDS, WORLDS):
        config = SimulationConfig(trajectory=trajectory, intrinsics=intrinsics, cameras=cameras, poses=POSES, clutter_fraction=0.1)
        dataset = simulate(config, seed=0)
        runs[world_id] = (dataset, camloc.localize(dataset, camloc.LocalizerConfig(), parallel=False))
    return runs


def test_the_default_association_is_consistent_on_every_kind_of_cluttered_world(beam_runs):
    # Issue 36, point 3. A wrong pair the beam takes leaves the replayed filter sure of a state
    # decimetres off: NEES in the thousands at that pose. Where the beam held other
    # explanations of the pose, the estimate's covariance carries their spread
    # (``BeamSearch._spread_about``), and every replayed pair's chance of being clutter
    # (``ekf.leave_one_out_spread``). Measured (seed 0): 1 of 12 kinds above its interval
    # (4 before either, 2 with the spread alone), none below, pooled mean 6.11 (6.43, 6.28),
    # no pose above 22 (73, 25).
    summaries = {world_id: metrics.nees_summary(metrics.run_nees(result)) for world_id, (_, result) in beam_runs.items()}
    rejected = [summary["verdict_line"] for summary in summaries.values() if summary["verdict"] != "consistent"]
    assert len(rejected) <= 3, rejected
    assert all(summary["verdict"] != "underconfident" for summary in summaries.values())
    nees = np.concatenate([metrics.run_nees(result) for _, result in beam_runs.values()])
    assert 5.4 <= np.nanmean(nees) <= 6.6
    assert np.nanmax(nees) < 100.0


def test_the_estimate_s_covariance_carries_the_spread_of_the_beam_s_explanations(beam_runs):
    # The filter's own covariance knows the one explanation it replayed; the estimate's adds how
    # far the beam's others spread about it, which is nothing where the beam held one.
    euler = make_filter("euler")
    widened = 0
    for dataset, result in beam_runs.values():
        own = euler.pose_cov(result.filter_state, result.filter_cov)
        extra = result.estimate_cov - own
        assert np.all(np.linalg.eigvalsh(extra) >= -1e-12)
        widened += int(np.count_nonzero(np.trace(extra, axis1=1, axis2=2) > 1e-12))
    assert widened > 0


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 5, 7])
def test_the_default_association_is_as_consistent_as_the_true_one_on_the_issue_s_aerial_world(seed):
    # The world issue 36 reports (aerial, 3,000 poses, two cameras of pixel intrinsics, 10%
    # clutter): mean NEES 43.8 with the beam on seed 1 against 6.11 with the true association,
    # from six poses of NEES 1,300-86,000 (a clutter detection taken for a landmark beside another
    # explanation of near equal cost; a wrong pair taken first leaving right ones unassigned).
    # Seeds 2, 5 and 7 kept one or two poses of NEES 3,000-5,700 after those fixes: a clutter
    # detection a few pixels from a landmark's prediction, its pair far cheaper than leaving it,
    # so the beam held no other explanation; the estimate now carries that pair's chance of being
    # clutter (``ekf.leave_one_out_spread``). Measured, beam / true association (mean; largest
    # pose): seed 1 5.87 / 6.11 (27), 2 5.86 / 5.98 (216), 5 6.03 / 6.11 (470), 7 5.78 / 6.06 (179).
    # (3,000 poses make the one run's interval narrow, [5.87, 6.13]: the true association's own
    # runs fall outside it on 2 of 10 seeds.)
    config = SimulationConfig(trajectory="aerial", poses=3000, cameras=2, intrinsics="pixel", clutter_fraction=0.1)
    dataset = simulate(config, seed=seed)
    nees = {association: metrics.run_nees(camloc.localize(dataset, camloc.LocalizerConfig(association=association), parallel=False))
            for association in ("beam", "oracle")}
    assert 0.9 * np.nanmean(nees["oracle"]) <= np.nanmean(nees["beam"]) <= 1.05 * np.nanmean(nees["oracle"])
    assert np.nanmax(nees["beam"]) < 1000.0
