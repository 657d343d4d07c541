"""The localizer end to end on data with known truth: accuracy, association quality, consistency,
and that the default never reads the file's landmark ids."""

import dataclasses
import re

import numpy as np
import pytest

import camloc.beam
from camloc import geometry
from camloc.ekf import FilterDivergedError
from camloc.dataset import Dataset
from camloc.errors import ConfigError
from camloc.g2o import read_g2o
from camloc.localizer import localize
from camloc.localizer_config import BeamOptions, BestFriendsOptions, JcbbOptions, LocalizerConfig, RecheckOptions, ViewOptions
from camloc.metrics import evaluate, position_errors, run_nees
from camloc.simulate import SimulationConfig, simulate


def localize_both(dataset, config=None, **options):
    """The beam scenario on both engines: the compiled loop must pair as the numpy localizer does
    (these worlds are below the size where ``localize`` picks the compiled one itself); returns the
    compiled run."""
    options.pop("parallel", None)  # the numpy one's replay process gives the same result either way
    compiled = localize(dataset, config, engine="compiled", **options)
    reference = localize(dataset, config, engine="numpy", parallel=False, **options)
    np.testing.assert_array_equal(compiled.associations.landmark, reference.associations.landmark)
    return compiled


def beam_run(dataset, **settings):
    """The numpy localizer's beam run of ``dataset`` (what ``localize(dataset, engine="numpy",
    parallel=False)`` returns) and the beam's ``BeamStatistics``; ``settings``: ``BeamSettings``
    fields changed from the run's (library settings a ``LocalizerConfig`` does not hold)."""
    from camloc.localizer import _Localizer

    localizer = _Localizer(dataset, LocalizerConfig())
    localizer.search_beam(settings=dataclasses.replace(localizer.beam_settings(), **settings))
    for k in range(dataset.num_poses):
        localizer.step(k)
    return localizer.result(filter_seconds=0.0), localizer.beam_statistics


def rmse(xyz, dataset):
    return float(np.sqrt(np.mean(np.sum((xyz - dataset.truth_xyz) ** 2, axis=1))))


def position_rmse(result, dataset):
    return rmse(result.estimate_xyz, dataset)


def precision_recall(result, dataset):
    a = result.associations
    made = a.landmark != -1
    correct = made & (a.landmark == a.true_landmark)
    in_map = np.isin(a.true_landmark, dataset.landmark_ids)
    return correct.sum() / max(made.sum(), 1), correct.sum() / max(in_map.sum(), 1)


def test_real_dataset_meets_the_accuracy_bounds(real_dataset_path):
    dataset = read_g2o(real_dataset_path)
    result = localize(dataset)
    metrics = evaluate(result)
    assert metrics["estimate"]["ate"]["rmse"] <= 0.10
    assert metrics["estimate"]["rotation"]["rmse_deg"] <= 3.5
    assert metrics["association"]["precision"] >= 0.97
    assert metrics["association"]["recall"] >= 0.90
    assert result.associations.landmark.shape == (362,)
    assert metrics["odometry"]["ate"]["rmse"] > 1.5  # the filter improves a lot on odometry alone


SIMULATED = {
    "grid like the real file": SimulationConfig(trajectory="grid", poses=150),
    "smooth3d with clutter and outliers": SimulationConfig(trajectory="smooth3d", poses=150, clutter_fraction=0.15, outlier_fraction=0.03),
    "aerial, pixel camera, two cameras": SimulationConfig(trajectory="aerial", poses=120, intrinsics="pixel", cameras=2),
}


@pytest.mark.parametrize("name", SIMULATED)
@pytest.mark.parametrize("seed", [11, 12])
def test_simulated_accuracy_close_to_the_oracle(name, seed):
    dataset = simulate(SIMULATED[name], seed=seed)
    oracle = localize(dataset, LocalizerConfig(association="oracle"))
    result = localize(dataset)
    precision, recall = precision_recall(result, dataset)
    assert position_rmse(result, dataset) <= 1.25 * position_rmse(oracle, dataset) + 0.01
    assert position_rmse(result, dataset) <= 0.15
    assert precision >= 0.98
    assert recall >= 0.85
    odometry_rmse = rmse(result.odometry_xyz, dataset)
    assert position_rmse(result, dataset) < 0.5 * odometry_rmse


def test_clutter_is_rejected():
    dataset = simulate(SimulationConfig(trajectory="smooth3d", poses=150, clutter_fraction=0.2), seed=5)
    result = localize(dataset)
    clutter = ~np.isin(result.associations.true_landmark, dataset.landmark_ids)
    assert clutter.sum() > 50
    assert np.count_nonzero(result.associations.landmark[clutter] != -1) <= clutter.sum() / 100


@pytest.mark.parametrize("seed", [200, 203])
def test_recheck_rejects_clutter_the_beam_accepted(seed):
    """15% clutter and 3% gross outliers: judged by the posterior of the pose's other pairs, most of
    the clutter pairs the beam took are dropped, and precision reaches the association issue's 99.5%."""
    dataset = simulate(SimulationConfig(trajectory="smooth3d", poses=300, clutter_fraction=0.15, outlier_fraction=0.03), seed=seed)
    clutter = ~np.isin(dataset.obs_true_landmark, dataset.landmark_ids)
    oracle = localize(dataset, LocalizerConfig(association="oracle"))
    scores = {}
    for recheck in (False, True):
        result = localize(dataset, LocalizerConfig(recheck=RecheckOptions(enabled=recheck)))
        made = result.associations.landmark != -1
        correct = made & (result.associations.landmark == result.associations.true_landmark)
        scores[recheck] = (np.count_nonzero(made & clutter), correct.sum() / made.sum(), position_rmse(result, dataset))
    assert clutter.sum() > 150
    # A single clutter pair more or less moves these figures: one of 191 clutter observations is
    # 0.5%, so the bounds leave room for one. Since issue 36's changes to the beam (the seeded
    # search's trigger, contested landmarks) it takes one clutter pair on seed 203 by itself, which
    # the re-check keeps; the re-check still drops gross outliers' pairs.
    assert scores[True][0] <= scores[False][0] and scores[True][0] <= clutter.sum() / 90
    assert scores[True][1] >= 0.995 and scores[True][1] > scores[False][1]
    assert scores[True][2] <= 1.25 * position_rmse(oracle, dataset)


@pytest.mark.parametrize("association", ["beam", "jcbb", "best-friends"])
def test_default_association_never_reads_the_file_ids(association):
    dataset = simulate(SimulationConfig(trajectory="grid", poses=60), seed=2)
    scrambled = dataclasses.replace(dataset, obs_true_landmark=np.full_like(dataset.obs_true_landmark, -7))
    config = LocalizerConfig(association=association)
    a, b = localize(dataset, config), localize(scrambled, config)
    np.testing.assert_array_equal(a.estimate_xyz, b.estimate_xyz)
    np.testing.assert_array_equal(a.associations.landmark, b.associations.landmark)


def test_iterated_update_is_more_consistent_than_a_single_linearization():
    nees = {}
    for iterations in (1, 3):
        values = []
        for seed in range(3):
            dataset = simulate(SimulationConfig(trajectory="grid", poses=150), seed=seed)
            result = localize(dataset, LocalizerConfig(association="oracle", iterations=iterations))
            values.append(evaluate(result)["nees"]["mean"])
        nees[iterations] = np.mean(values)
    assert nees[3] < nees[1]
    assert nees[3] < 8.0  # 6 degrees of freedom


def test_covariances_stay_symmetric_positive_definite():
    dataset = simulate(SimulationConfig(trajectory="smooth3d", poses=100), seed=4)
    result = localize(dataset)
    assert np.array_equal(result.filter_cov, np.swapaxes(result.filter_cov, 1, 2))
    assert np.all(np.linalg.eigvalsh(result.filter_cov) > 0)
    assert np.all(np.linalg.eigvalsh(result.estimate_cov) > 0)


def test_outputs_have_one_row_per_pose_and_observation():
    dataset = simulate(SimulationConfig(trajectory="grid", poses=40), seed=1)
    result = localize(dataset)
    assert result.estimate_xyz.shape == (40, 3)
    assert result.associations.landmark.shape == (dataset.num_observations,)
    np.testing.assert_allclose(result.estimate_xyz[0], dataset.start_xyz, atol=1e-12)
    odometry = dataset.T_world_start
    for increment in dataset.T_odometry:
        odometry = odometry @ increment
    np.testing.assert_allclose(result.odometry_xyz[-1], odometry[:3, 3], atol=1e-9)
    assert result.nis.shape == result.nis_dof.shape == result.update_pose_ids.shape
    assert np.all(result.nis_dof % 3 == 0)


def test_warns_near_the_euler_singularity():
    dataset = simulate(SimulationConfig(trajectory="aerial", poses=80, max_tilt_deg=88), seed=0)
    result = localize(dataset, LocalizerConfig(association="oracle"))
    assert sum("singularity" in w for w in result.summary["warnings"]) == 1
    # both engines judge the estimate (numpy judged the prediction: a pose or more earlier)
    compiled = localize(dataset, LocalizerConfig(association="oracle"), engine="compiled")
    assert [w for w in compiled.summary["warnings"] if "singularity" in w] == [w for w in result.summary["warnings"] if "singularity" in w]


@pytest.mark.parametrize("engine", ["numpy", "compiled"])
def test_the_oracle_leaves_out_a_landmark_the_prior_puts_behind_its_camera(engine):
    """The audit of 2026-12-06's world: after a 2x-noise odometry step the prior put two true
    landmarks behind the camera (predicted disparities -5.9 and -62 against 1.8 and 1.4 measured).
    Their projections' Jacobians, grown as 1/depth^2, widened their gates' S until both passed, the
    iterated update made from them left the pose 0.86 m off with a 2 mm standard deviation, and the
    oracle ended 9.95 m off (NEES 2.8e9). Left out, the other 18 pairs of that pose hold it."""
    config = SimulationConfig(trajectory="smooth3d", poses=60, dense=True, measurement="disparity",
                              odometry_sigma_scale=2.0, observe_first_pose=True)
    dataset = simulate(config, seed=731)
    result = localize(dataset, LocalizerConfig(association="oracle"), engine=engine)
    metrics = evaluate(result)
    assert metrics["estimate"]["ate"]["rmse"] < 0.05
    assert metrics["nees"]["mean"] < 12.0 and metrics["nis"]["mean_per_dof"] < 1.5


@pytest.mark.parametrize("engine", ["numpy", "compiled"])
@pytest.mark.parametrize("seed, main_nees", [(2, 1.05e7), (6, 8.56e7)])
def test_an_update_beyond_its_chi2_bound_is_sought_again_by_damped_gauss_newton(engine, seed, main_nees):
    """Odometry three times noisier than the default (its information in the file says so) leaves
    the prior half a metre wide against landmarks one or two metres from pixel cameras. Three
    Gauss-Newton linearizations from there stop 0.1-0.8 m from the MAP estimate with the
    millimetre covariance of the pairs (seed 2), or, with three pairs, run off 18 m (seed 6): main
    at 03d6ee5 had mean NEES ``main_nees`` on these worlds. Where the MAP cost is beyond its 99.9%
    bound the update is sought again from the prior with each step halved until it lowers the
    cost, and every pose's NEES is within reason."""
    config = SimulationConfig(trajectory="smooth3d", poses=30, cameras=2, measurement="pixel", intrinsics="pixel",
                              odometry_sigma_scale=3.0)
    result = localize(simulate(config, seed=seed), LocalizerConfig(association="oracle"), engine=engine)
    metrics = evaluate(result)
    assert metrics["nees"]["mean"] < 7.0 < main_nees and metrics["nis"]["mean_per_dof"] < 1.15
    assert np.nanmax(run_nees(result)) < 25.0  # every pose (main: up to 3.1e8 and 2.2e9)
    assert metrics["estimate"]["ate"]["rmse"] < 0.02


@pytest.mark.parametrize("engine", ["numpy", "compiled"])
def test_the_damped_search_does_not_leap_to_a_pose_turned_half_round(engine):
    """One pixel camera, odometry twice as noisy as the default: at pose 124 three pairs under a
    0.4 m prior cost 2.9e6 at the prior and 16 at the truth. A line search along the Gauss-Newton
    step (halved until the cost fell) leapt to a minimum of cost 1,154 with the pose turned 159
    degrees, 31 prior sigmas away, and the oracle's run ended 7.6 m off (NEES 8.4e6); damped in
    the prior's metric (Levenberg-Marquardt) the steps reach the truth's minimum."""
    config = SimulationConfig(poses=150, measurement="pixel", odometry_sigma_scale=2.0, trajectory="grid", cameras=1,
                              intrinsics="pixel", clutter_fraction=0.1)
    result = localize(simulate(config, seed=202), LocalizerConfig(association="oracle"), engine=engine)
    metrics = evaluate(result)
    assert metrics["estimate"]["ate"]["rmse"] < 0.3 and metrics["nees"]["mean"] < 40.0  # measured 0.19 m, 25.3


@pytest.mark.parametrize("engine", ["numpy", "compiled"])
def test_the_beam_leaves_out_a_landmark_the_posterior_puts_behind_its_camera(engine):
    """The oracle's world above, with the beam: at pose 36 the prior put landmarks 208 and 572
    behind the camera. Judged there they are no option (their gate's S grows as 1/depth^2), but
    under a state conditioned on the pose's clear pairs both lay in front and the beam took them;
    the update of all the pose's pairs from the prior put them behind again (depths -0.29 and
    -0.11 m) and the run ended 24.2 m off (odometry alone 3.3 m). The re-check drops a pair whose
    landmark the posterior puts behind its camera, and the run ends as the oracle's does."""
    config = SimulationConfig(trajectory="smooth3d", poses=60, dense=True, measurement="disparity",
                              odometry_sigma_scale=2.0, observe_first_pose=True)
    dataset = simulate(config, seed=731)
    result = localize(dataset, engine=engine)
    metrics = evaluate(result)
    assert metrics["estimate"]["ate"]["rmse"] < 0.05 and metrics["association"]["precision"] > 0.99
    assert not np.isin([208, 572], result.associations.landmark[dataset.obs_pose_index == 36]).any()  # landmark ids


@pytest.mark.parametrize("state_pitch_deg, warned", [(-95.0, -85.0), (95.0, 85.0), (-218.9, None), (170.0, None), (-60.0, None)])
def test_the_singularity_is_judged_by_the_rotations_pitch_not_the_states_angle(state_pitch_deg, warned):
    """An update can carry the Euler state's pitch past +-90 deg (the audit of 2026-12-06: a lost
    run's -218.9 deg, warned of as near the singularity). The same rotation is pitched 180 deg
    minus it, which is what says how near the singularity the filter is."""
    from scipy.spatial.transform import Rotation

    from camloc.filters import EulerFilter

    model = EulerFilter()
    x = np.array([0.0, 0.0, 0.0, 0.3, np.radians(state_pitch_deg), -1.2])
    pitch = Rotation.from_matrix(model.pose(x)[:3, :3]).as_euler("ZYX", degrees=True)[1]
    found = model.near_singularity(x)
    if warned is None:
        assert found is None and abs(pitch) < 80.0
    else:
        assert found == pytest.approx(warned) == pytest.approx(pitch)


def test_pose_covariance_matches_euler_covariance_by_sampling(rng):
    from camloc.filters import EulerFilter

    state = np.array([1.0, -2.0, 0.5, 0.4, -0.7, 2.0])
    A = rng.normal(size=(6, 6)) * 0.02
    cov = A @ A.T + 1e-4 * np.eye(6)
    samples = rng.multivariate_normal(state, cov, size=20000)
    errors = geometry.pose_error_vector(geometry.pose_from_euler(state)[None], geometry.pose_from_euler(samples))
    predicted = EulerFilter().pose_cov(state[None], cov[None])[0]
    np.testing.assert_allclose(np.cov(errors.T), predicted, atol=0.05 * np.abs(predicted).max())


@pytest.mark.parametrize("bad, option", [
    ({"association": "magic"}, "association"), ({"iterations": 0}, "iterations"), ({"gate": 1.5}, "gate"),
    ({"association": "best-friends", "best_friends": BestFriendsOptions(margin=-1.0)}, "best_friends.margin"),
    ({"view": ViewOptions(max_angle_deg=95.0)}, "view.max_angle_deg"), ({"beam": BeamOptions(width=0)}, "beam.width"),
    ({"beam": BeamOptions(slip_inflation=0.5)}, "beam.slip_inflation"),
    ({"view": ViewOptions(min_depth=2.0, max_depth=1.0)}, "view.max_depth"),
    # finite but past what the arithmetic survives (the k-d tree overflows, P loses definiteness)
    ({"view": ViewOptions(max_depth=1e300)}, "view.max_depth"), ({"view": ViewOptions(min_depth=1e300)}, "view.min_depth"),
    ({"initial_sigma_xyz": 1e300}, "initial_sigma_xyz"), ({"initial_sigma_deg": 1e300}, "initial_sigma_deg"),
    # a group of the wrong kind; an option of a method that is not selected
    ({"beam": {"width": 8}}, "beam"), ({"jcbb": dataclasses.replace(LocalizerConfig().jcbb, max_nodes=10)}, "jcbb.max_nodes"),
    ({"association": "jcbb", "best_friends": BestFriendsOptions(sequential=False)}, "best_friends.sequential"),
])
def test_bad_configuration_is_a_config_error_naming_the_option(bad, option):
    with pytest.raises(ConfigError) as error:
        LocalizerConfig(**bad).validate()
    assert error.value.path == option and str(error.value).startswith(f"{option} ")


def test_an_option_of_another_method_at_its_default_and_a_shared_one_are_accepted():
    jcbb = LocalizerConfig(association="jcbb", best_friends=BestFriendsOptions(cost="mahalanobis", margin=2.0))
    jcbb.validate()  # best friends' cost and margin pick the pairs that seed jcbb
    LocalizerConfig(association="oracle", recheck=RecheckOptions(enabled=False), null_cost=5.0).validate()
    LocalizerConfig(association="oracle", beam=BeamOptions(width=LocalizerConfig().beam.width)).validate()


def test_the_oracle_run_says_which_options_it_ignores():
    dataset = simulate(SimulationConfig(trajectory="grid", poses=30), seed=2)
    config = LocalizerConfig(association="oracle", recheck=RecheckOptions(margin=100.0), null_cost=0.001,
                             view=ViewOptions(max_depth=0.6))
    plain = localize(dataset, LocalizerConfig(association="oracle"))
    result = localize(dataset, config)
    np.testing.assert_array_equal(result.filter_state, plain.filter_state)  # ignored indeed
    assert ("association oracle takes the file's landmark ids and ignores null_cost, recheck.margin, view.max_depth"
            in result.summary["warnings"])
    assert not any("ignores" in w for w in plain.summary["warnings"])
    assert not any("ignores" in w for w in localize(dataset, LocalizerConfig(null_cost=5.0)).summary["warnings"])


@pytest.mark.parametrize("option, value, reason", [
    ("null_cost", float("inf"), "must be a finite number > 0"),
    ("beam", "delta=inf", "must be a finite number > 0"),
    ("beam", "slip_inflation=1e300", "must be in [1, 10000]"),
    ("beam", "width=100000000000", "must be an integer in 1..1024"),
    ("recheck", "margin=inf", "must be a finite number >= 0"),
    ("best_friends", "margin=nan", "must be a finite number >= 0"),
])
def test_infinite_and_huge_option_values_are_refused(option, value, reason):
    # infinities were recorded as null in summary.json (for null_cost: "from the data"), so the
    # recorded options did not repeat the run; a huge width or inflation ran out of memory or range
    groups = {"beam": BeamOptions, "recheck": RecheckOptions, "best_friends": BestFriendsOptions}
    if option in groups:
        name, text = value.split("=")
        config = LocalizerConfig(**{option: groups[option](**{name: float(text)})})
    else:
        config = LocalizerConfig(**{option: value})
    with pytest.raises(ConfigError, match=re.escape(reason)):
        config.validate()


@pytest.mark.parametrize("seed", [0, 1])
def test_se3_filter_matches_euler_on_flat_ground(seed):
    dataset = simulate(SimulationConfig(trajectory="grid", poses=120), seed=seed)
    euler = localize(dataset, LocalizerConfig(filter="euler"))
    se3 = localize(dataset, LocalizerConfig(filter="se3"))
    assert position_rmse(se3, dataset) <= 1.05 * position_rmse(euler, dataset)
    assert se3.filter_state.shape == (120, 7) and se3.filter_cov.shape == (120, 6, 6)


def test_se3_filter_with_a_camera_that_sees_nothing_in_a_seeded_search():
    """Two cameras, a third of the detections clutter (seed 5, 40 poses): the beam's seeded search
    (``beam_seeded``) meets a pose where one camera has no candidate; its empty options had
    Jacobians as wide as the SE(3) state's 4x4 matrix (16 columns), not its error (6), and
    concatenating them with the other camera's stopped the run with a ValueError."""
    dataset = simulate(SimulationConfig(poses=40, cameras=2, clutter_fraction=0.3), seed=5)
    se3 = localize(dataset, LocalizerConfig(filter="se3"), engine="numpy")
    euler = localize(dataset, LocalizerConfig(filter="euler"), engine="numpy")
    assert position_rmse(se3, dataset) <= 1.1 * position_rmse(euler, dataset)


def test_se3_filter_stays_consistent_through_pitch_90_where_euler_does_not():
    dataset = simulate(SimulationConfig(trajectory="aerial", poses=200, max_tilt_deg=90), seed=4)
    nees = {}
    for kind in ("euler", "se3"):
        result = localize(dataset, LocalizerConfig(filter=kind, association="oracle"))
        nees[kind] = evaluate(result)["nees"]["mean"]
        assert position_rmse(result, dataset) < 0.2
    assert nees["se3"] < 7.5           # 6 degrees of freedom
    assert nees["euler"] > 2 * nees["se3"]


def test_divergence_guard_reports_runs_of_inconsistent_updates():
    from camloc.run_records import divergence_guard

    updates = np.array([100, 101, 102, 103, 105, 106, 108, 109])
    dof = np.full(8, 9)
    statistic = np.array([5.0, 60.0, 70.0, 5.0, 80.0, 90.0, 95.0, 4.0])  # 27.9 is the 99.9% bound for 9 dof
    guard = divergence_guard(updates, statistic, dof)
    assert guard["inconsistent_poses"] == [101, 102, 105, 106, 108]
    assert guard["runs"] == [[105, 108]]


def test_a_filter_fed_wrong_pairs_reports_divergence():
    dataset = simulate(SimulationConfig(trajectory="grid", poses=120), seed=1)
    # best friends, batch, no margin: the fragile original method, on data where it breaks
    broken = localize(dataset, LocalizerConfig(
        association="best-friends", best_friends=BestFriendsOptions(sequential=False, margin=0.0), recheck=RecheckOptions(enabled=False)))
    healthy = localize(dataset, LocalizerConfig(association="oracle"))
    assert position_rmse(broken, dataset) > 0.5
    assert len(broken.summary["divergence_guard"]["runs"]) >= 1
    assert any("diverged" in w for w in broken.summary["warnings"])
    assert healthy.summary["divergence_guard"]["runs"] == []


def test_jcbb_on_the_real_style_data():
    dataset = simulate(SimulationConfig(trajectory="grid", poses=100), seed=3)
    result = localize(dataset, LocalizerConfig(association="jcbb"))
    oracle = localize(dataset, LocalizerConfig(association="oracle"))
    precision, recall = precision_recall(result, dataset)
    assert precision >= 0.98 and recall >= 0.9
    assert position_rmse(result, dataset) <= 1.5 * position_rmse(oracle, dataset)


def test_jcbb_counts_the_poses_its_bound_cut_short_in_the_run_s_warnings():
    dataset = simulate(SimulationConfig(poses=40, dense=True), seed=1)
    cut_short = {}
    for max_nodes in (5, 2000):
        result = localize(dataset, LocalizerConfig(association="jcbb", jcbb=JcbbOptions(max_nodes=max_nodes)))
        warnings = [w for w in result.summary["warnings"] if w.startswith(f"JCBB hit its bound of {max_nodes} joint tests at ")]
        cut_short[max_nodes] = int(warnings[0].split(" at ")[1].split()[0]) if warnings else 0
    observed = np.unique(dataset.obs_pose_index).size
    assert observed >= cut_short[5] > cut_short[2000]  # at most once a pose, and more with a tighter bound


def _with_a_jump(dataset: Dataset, jump: tuple[float, float, float]) -> Dataset:
    """The dataset with its odometry off by ``jump`` (metres) on edge 100, from pose 100 to 101."""
    slipped = dataset.odom_translation.copy()
    slipped[100] += np.array(jump)
    return dataclasses.replace(dataset, odom_translation=slipped)


def _dense_run_with_a_jump(jump: tuple[float, float, float], clutter_fraction: float = 0.0) -> Dataset:
    config = SimulationConfig(trajectory="smooth3d", poses=200, landmarks=1500, region=11, clutter_fraction=clutter_fraction)
    return _with_a_jump(simulate(config, seed=7), jump)


def test_beam_recovers_from_an_odometry_slip_in_a_dense_map():
    dataset = _dense_run_with_a_jump((0.6, -0.5, 0.0))  # an 8-sigma odometry error at one step
    oracle = localize(dataset, LocalizerConfig(association="oracle"))
    recovered = localize_both(dataset)
    without_recovery = localize_both(dataset, LocalizerConfig(beam=BeamOptions(slip_cost=1e9)))
    assert position_rmse(recovered, dataset) <= 1.25 * position_rmse(oracle, dataset)
    assert position_rmse(without_recovery, dataset) > 1.5 * position_rmse(recovered, dataset)
    assert recovered.summary["slip_poses"]  # the recovery did fire, and it is what made the difference


def test_beam_recovers_from_a_slip_where_a_third_of_the_detections_are_clutter():
    # Clutter leaves most of many poses' observations unassigned: the slip's search must still run
    # at the slip, where nearly all of them are, and not at every cluttered pose.
    dataset = _dense_run_with_a_jump((0.6, -0.5, 0.0), clutter_fraction=0.35)
    recovered, statistics = beam_run(dataset)
    oracle = localize(dataset, LocalizerConfig(association="oracle"), engine="numpy")
    assert position_rmse(recovered, dataset) <= 1.25 * position_rmse(oracle, dataset)
    slip_searches = statistics.slip_search_poses
    assert 101 in slip_searches, slip_searches  # odometry edge 100 leads to pose 101
    assert len(slip_searches) < dataset.num_poses / 5  # 30; at every pose leaving half unassigned: 43


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_beam_recovers_from_a_slip_where_every_pose_sees_two_landmarks(seed, monkeypatch):
    # The real file's density: poses see two or three landmarks. A slip's search at a pose of two
    # observations (both unassigned) finds the slip; from three, as before, it never ran there.
    dataset = _with_a_jump(simulate(SimulationConfig(poses=200, max_observations_per_pose=2), seed=seed), (0.8, 0.0, 0.0))
    found = localize_both(dataset)
    assert any(1101 <= pose <= 1103 for pose in found.summary["slip_poses"]), found.summary["slip_poses"]
    monkeypatch.setattr(camloc.beam, "SLIP_MIN_OBSERVATIONS", 3)  # the numpy beam as it was
    missed = localize(dataset, engine="numpy", parallel=False)
    assert missed.summary["slip_poses"] == []
    assert position_rmse(found, dataset) < 0.85 * position_rmse(missed, dataset)


def test_the_slip_search_runs_where_a_pose_explains_less_than_this_data_usually_lets_it():
    from camloc.beam import BeamSearch
    from camloc.beam_types import BeamSettings
    from camloc.localizer import _Localizer

    search = BeamSearch(_Localizer(simulate(SimulationConfig(poses=5), seed=0), LocalizerConfig()), BeamSettings())
    assert search.seeded.unusually_unexplained(6, 10)        # nothing learnt yet: more than half is enough
    search.seeded.unexplained = [(8, 20)] * 50                 # 40% of the observations left unassigned
    assert not search.seeded.unusually_unexplained(11, 20)   # P(X >= 11 | 20, 0.4) = 0.13: usual here
    assert search.seeded.unusually_unexplained(18, 20)       # about 1e-5
    search.seeded.unexplained = [(8, 20)] * 48 + [(3, 3)] * 2  # a slip two poses ago, three observations a pose
    assert search.seeded.unusually_unexplained(3, 3)         # alone 0.4^3 = 6%; the three poses pooled 0.03%
    search.seeded.unexplained = [(4, 4)] * 50                  # nothing explained for 50 poses: lost, not clutter
    assert search.seeded.unusually_unexplained(4, 4)         # the rate is capped at 0.6: 0.6^12 = 0.2% pooled
    search.seeded.unexplained = [(11, 20)] * 50                # 55% unexplained: heavy clutter
    assert not search.seeded.unusually_unexplained(3, 4)     # one pose of four says nothing


def test_a_seeded_explanation_crowded_out_of_a_full_beam_takes_its_last_place():
    from camloc.beam import BeamSearch
    from camloc.beam_types import BeamSettings, Hypothesis
    from camloc.localizer import _Localizer

    search = BeamSearch(_Localizer(simulate(SimulationConfig(poses=5), seed=0), LocalizerConfig()), BeamSettings(beam_width=4))
    P = 0.01 * np.eye(6)
    copies = [Hypothesis(np.r_[0.1 * i, 0.0, 0.0, 0.0, 0.0, 0.0], P, 10.0 + i, 0) for i in range(4)]  # one wrong alignment, four ways
    far = Hypothesis(np.r_[0.0, 2.0, 0.0, 0.0, 0.0, 0.0], P, 19.0, 0, slipped=True)  # the slip's explanation, 9 costlier
    kept = search.seeded.with_a_seeded_one(list(copies), [far])
    assert kept == copies[:3] + [far]  # sorted by cost, the best unchanged
    assert search.seeded.with_a_seeded_one(list(copies), [far, copies[3]]) == copies  # a seeded one is kept already
    assert search.seeded.with_a_seeded_one(copies[:3], [far]) == copies[:3]  # room was left: it was pruned on its own
    too_costly = Hypothesis(far.x, P, 10.0 + BeamSettings.beam_delta + 0.1, 0)
    assert search.seeded.with_a_seeded_one(list(copies), [too_costly]) == copies
    a_copy = Hypothesis(copies[1].x + 1e-4, P, 19.0, 0)
    assert search.seeded.with_a_seeded_one(list(copies), [a_copy]) == copies


def test_beam_recovers_where_a_wrong_alignment_s_copies_crowded_out_the_slip_s_explanation():
    # 3x odometry noise, one to five observations a pose: from pose 245 the beam locks onto a
    # wrong alignment (an odometry drift of a metre in five poses the oracle also half-follows).
    # At pose 262 the slip's search explains all three observations with a pose 0.19 m from the
    # truth, 7 costlier than leaving two unassigned under the wrong one, but sixteen copies of
    # that one filled the beam. Kept in the beam, it explains pose 263 and wins (RMSE 3.0 m
    # before, 0.50 now); the replay takes the slip's pairs without re-checking them under the
    # widened prior, which left its filter metres wide while the beam went on.
    dataset = simulate(SimulationConfig(poses=300, odometry_sigma_scale=3.0), seed=502)
    oracle = localize(dataset, LocalizerConfig(association="oracle"))
    result = localize_both(dataset, parallel=False)
    assert 1262 in result.summary["slip_poses"]
    assert position_rmse(result, dataset) <= 1.25 * position_rmse(oracle, dataset)


def test_a_seed_s_second_explanation_keeps_the_right_one_a_clutter_pairing_undercuts():
    # 3x odometry noise, 20% clutter: pose 3 has six observations, three of them clutter, under
    # a prediction 0.39 m off. Grown from the right seed pair, the cheapest explanation also pairs
    # a clutter detection (137.5); the right one leaves it unassigned and costs 2.8 more. With one
    # explanation kept per seed the right one was not in the beam; a wrong slip explanation won
    # at pose 4, its near copies filled the beam from pose 5 on, and the run was lost for good
    # (RMSE 10.9 m against the oracle's 0.18).
    dataset = simulate(SimulationConfig(trajectory="smooth3d", poses=300, odometry_sigma_scale=3.0, clutter_fraction=0.2), seed=515)
    oracle = localize(dataset, LocalizerConfig(association="oracle"))
    result = localize_both(dataset, parallel=False)
    precision, _ = precision_recall(result, dataset)
    assert position_rmse(result, dataset) <= 2.0 * position_rmse(oracle, dataset)
    assert precision >= 0.95


def test_a_slip_among_few_cluttered_observations_is_found_by_the_poses_after_it():
    # 40% clutter, six observations a pose: one pose left unexplained is no surprise, three in a
    # row are. Judged a pose at a time, the slip's search never ran here (RMSE 0.44 m).
    dataset = _with_a_jump(simulate(SimulationConfig(trajectory="smooth3d", poses=200, clutter_fraction=0.4), seed=3), (0.6, -0.5, 0.0))
    result = localize_both(dataset, parallel=False)
    assert set(result.summary["slip_poses"]) & set(dataset.pose_ids[101:104].tolist())
    assert position_rmse(result, dataset) < 0.2


def test_a_seeded_explanation_that_leaves_its_prior_far_behind_is_dropped():
    # Dense map, 30% clutter, 10% outliers: at pose 60 the slip's search (25x the covariance)
    # found a seed pair that fits a landmark 6.8 m from the right one by turning the camera, and
    # the explanation grown from it cost less than the right one, every innovation along the way
    # looking likely; the filter was lost for 25 poses. Its state was far outside its own prior.
    dataset = simulate(SimulationConfig(poses=200, dense=True, clutter_fraction=0.3, outlier_fraction=0.1), seed=1)
    oracle = localize(dataset, LocalizerConfig(association="oracle"), engine="numpy")
    result, _ = beam_run(dataset)
    precision, _ = precision_recall(result, dataset)
    assert position_rmse(result, dataset) <= 1.25 * position_rmse(oracle, dataset)
    assert precision >= 0.98
    without_the_gate, _ = beam_run(dataset, state_gate=np.inf)
    assert position_rmse(without_the_gate, dataset) > 1.0


def test_beam_explains_a_large_odometry_error_from_a_seed_pair_without_a_slip():
    # 4 sigma: one by one, the observations lock onto a shifted alignment of the dense map; grown
    # from a right seed pair under the plain prediction, they do not, and no slip is needed.
    dataset = _dense_run_with_a_jump((0.3, -0.25, 0.0))
    oracle = localize(dataset, LocalizerConfig(association="oracle"))
    without_slips = localize_both(dataset, LocalizerConfig(beam=BeamOptions(slip_cost=1e9)))
    assert position_rmse(without_slips, dataset) <= 1.25 * position_rmse(oracle, dataset)
    assert not localize_both(dataset).summary["slip_poses"]


def test_the_slip_is_searched_only_where_the_plain_prediction_s_seeds_leave_the_pose_unexplained():
    # An 8-sigma jump on edge 100: the slip's search (the widest prior, the costliest search)
    # runs at pose 101 and finds the slip. At the later poses where noisy odometry in the dense map
    # left most observations unassigned, the seeded search under the plain prediction explained
    # them, and the slip was not searched as well (until 2026-12-02 it was, at every such pose).
    dataset = _dense_run_with_a_jump((0.6, -0.5, 0.0))
    result, statistics = beam_run(dataset)
    assert statistics.slip_search_poses == [101]
    assert set(statistics.seeded_search_poses) > {101}
    assert result.summary["slip_poses"] == [int(dataset.pose_ids[101])]
    assert localize_both(dataset).summary["slip_poses"] == result.summary["slip_poses"]


def _dense_pixel_world_with_a_jump() -> Dataset:
    # A 0.78 m jump on edge 100 of a dense world of one pixel camera. At pose 101 the plain
    # prediction's explanation takes wrong landmarks for its rays and leaves only a third of them
    # unassigned, not the most the slip's first trigger waits for; the seeded search's explanation
    # beats it with fewer pairs: the prior's pairs cost more than leaving them unexplained, so the
    # prior is off, and the slip's search runs there. Until 2026-12-07 it did not (the numpy beam
    # never searched the slip here and stayed a metre off; the compiled run found it two poses late).
    config = SimulationConfig(trajectory="grid", cameras=1, measurement="pixel", dense=True, poses=200)
    return _with_a_jump(simulate(config, seed=1), (0.6, -0.5, 0.0))


def _rmse_after_the_jump(result, dataset: Dataset) -> float:
    # from pose 105: back on the track four poses after the jump
    return float(np.sqrt(np.mean(position_errors(result.estimate_xyz[105:], dataset.truth_xyz[105:]) ** 2)))


def test_the_compiled_beam_searches_the_slip_where_a_seed_explains_the_pose_better_with_fewer_pairs():
    dataset = _dense_pixel_world_with_a_jump()
    compiled = localize(dataset, engine="compiled")  # its run learns the reach first
    assert compiled.summary["slip_poses"][0] == int(dataset.pose_ids[101])
    oracle = localize(dataset, LocalizerConfig(association="oracle"), engine="numpy")
    # Measured 2026-12-07: 1.27x the oracle's 0.026 m after pose 105 (the numpy beam's 0.95x is
    # the slow test's below); a run that missed the slip stays about a metre off.
    assert _rmse_after_the_jump(compiled, dataset) <= 1.5 * _rmse_after_the_jump(oracle, dataset)


@pytest.mark.slow  # the numpy beam takes about 100 s over this dense pixel world
def test_the_numpy_beam_searches_the_slip_where_a_seed_explains_the_pose_better_with_fewer_pairs():
    dataset = _dense_pixel_world_with_a_jump()
    result, statistics = beam_run(dataset)
    assert statistics.slip_search_poses == [101]
    assert result.summary["slip_poses"] == [int(dataset.pose_ids[101])]
    oracle = localize(dataset, LocalizerConfig(association="oracle"), engine="numpy")
    assert _rmse_after_the_jump(result, dataset) <= 1.25 * _rmse_after_the_jump(oracle, dataset)


@pytest.mark.parametrize("association", ["beam", "oracle"])
def test_a_covariance_breakdown_names_the_pose(association, numpy_localizer):
    # Observations claiming a standard deviation of 1e-150 make a stacked innovation covariance
    # singular in floating point: a clear error naming a pose with observations, not a traceback.
    dataset = simulate(SimulationConfig(poses=30), seed=2)
    dataset = dataclasses.replace(dataset, obs_cov=np.broadcast_to(1e-300 * np.eye(3), dataset.obs_cov.shape).copy())
    with pytest.raises(FilterDivergedError, match=r"^pose (\d+): innovation covariance is not positive definite") as caught:
        localize(dataset, LocalizerConfig(association=association), parallel=False)
    pose_id = int(str(caught.value).split(":")[0].split()[1])
    assert pose_id in dataset.pose_ids[dataset.obs_pose_index]
    assert re.search(r"information matrices are \d{3} orders of magnitude apart", str(caught.value))  # 1e-300 against 1e-4


def test_observations_claiming_to_be_exact_in_four_cameras_are_localized_exactly():
    # Information 1e12 (the simulator's exact observations) beside odometry of 1e2: rounding left
    # the re-check's bound on S indefinite, and numpy's LinAlgError ended the run at the third pose.
    # Then association judged each pair's linearization error by that noise, gated right pairs out
    # and got 0.12 m where the data pins every pose (observation_space.noise_floored): now 2e-10 m.
    dataset = simulate(SimulationConfig(poses=12, cameras=4, max_range=1.5, detection_probability=0.7,
                                        observation_sigma_scale=0.0), seed=0)
    result = localize(dataset, parallel=False)
    assert position_rmse(result, dataset) < 1e-6 < 0.1 < rmse(result.odometry_xyz, dataset)
    assert evaluate(result)["association"]["precision"] == 1.0


@pytest.mark.parametrize("kind", [dict(intrinsics="pixel"), dict(trajectory="smooth3d")])
def test_association_of_noise_free_observations_matches_the_oracle(kind):
    # before observation_space.noise_floored: recall 0.15 and 0.14 m (pixel camera) and 0.64 and
    # 0.12 m (smooth3d), where the oracle gets 0.050 and 0.037 m; on 100 poses with the pixel
    # camera the beam's own filters broke down (a covariance no longer positive definite)
    dataset = simulate(SimulationConfig(poses=40, observation_sigma_scale=0.0, **kind), seed=0 if kind.get("intrinsics") else 2)
    beam = localize(dataset, parallel=False)
    oracle = localize(dataset, LocalizerConfig(association="oracle"), parallel=False)
    scores = evaluate(beam)["association"]
    assert scores["precision"] == 1.0 and scores["recall"] > 0.95
    assert position_rmse(beam, dataset) <= 1.05 * position_rmse(oracle, dataset) + 1e-6


@pytest.mark.parametrize("association", ["beam", "oracle"])
def test_a_factorization_numpy_refuses_is_reported_as_a_breakdown_at_its_pose(monkeypatch, association, numpy_localizer):
    import camloc.ekf

    dataset = simulate(SimulationConfig(poses=10), seed=2)
    calls = []

    def fails_on_the_fifth(P, F, G, Q):
        calls.append(1)
        if len(calls) == 5:
            raise np.linalg.LinAlgError("Matrix is not positive definite")
        return F @ P @ F.T + G @ Q @ G.T

    monkeypatch.setattr(camloc.ekf, "predict", fails_on_the_fifth)
    with pytest.raises(FilterDivergedError, match=r"^pose \d+: a covariance is no longer positive definite \(Matrix is not positive definite\)"):
        localize(dataset, LocalizerConfig(association=association), parallel=False)


def test_beam_shares_a_budget_of_partial_explanations_where_every_observation_is_ambiguous():
    # 3x measurement noise in a dense map: every observation gates several landmarks and the beam
    # is full, so each hypothesis growing its own beam would keep beam_width^2 partial explanations.
    from camloc.beam_types import BeamSettings

    dataset = simulate(SimulationConfig(poses=12, dense=True, observation_sigma_scale=3.0), seed=0)
    result, statistics = beam_run(dataset)
    prunings = statistics.partial_prunings  # parents, partials grown, partials kept, each time
    budget, width = BeamSettings.partial_budget, BeamSettings.beam_width
    assert budget < width * width
    assert max(p.grown for p in prunings) > budget  # the beam was full and the parents many
    assert all(p.kept <= max(budget, p.parents) for p in prunings)
    oracle = localize(dataset, LocalizerConfig(association="oracle"), engine="numpy")
    assert position_rmse(result, dataset) <= 1.5 * position_rmse(oracle, dataset)


def _busiest_pose_of_a_dense_world():
    """(localizer, the pose's observations, their true landmarks, the true state) at the pose with
    the most observations (43 right pairs) of a 40-pose dense world."""
    from camloc.localizer import _Localizer

    dataset = simulate(SimulationConfig(poses=40, dense=True), seed=3)
    localizer = _Localizer(dataset, LocalizerConfig(association="oracle"))
    k = int(np.argmax(np.bincount(dataset.obs_pose_index, minlength=dataset.num_poses)))
    obs = localizer.obs_of_pose[k]
    landmarks = localizer.true_landmark_row[obs]
    assert (landmarks >= 0).all()  # every observation's landmark is in the map
    truth = localizer.filter.initial(geometry.pose_from_quat(dataset.truth_xyz[k], dataset.truth_quat_xyzw[k]))
    return localizer, obs, landmarks, truth


@pytest.mark.parametrize("offset", [(0.6, -0.6, 0.0), (0.3, 0.0, 0.0), (-0.6, 0.3, 0.2)])
def test_an_update_from_a_far_prior_reaches_the_pose_its_pairs_pin(monkeypatch, offset):
    # 43 right pairs pin the pose to a centimetre; from a prior 0.85 m off, Gauss-Newton in (u, v,
    # depth) stalls half a metre away, and the update starting in camera-frame points does not.
    localizer, obs, landmarks, truth = _busiest_pose_of_a_dense_world()
    prior = truth + np.r_[offset, 0.0, 0.0, 0.0]
    P = np.diag([0.3**2] * 3 + [0.05**2] * 3)
    restarted = localizer.updated(prior, P, obs, landmarks, map_cost=True)
    monkeypatch.setattr(localizer.stacked, "nis_bound", lambda dof: np.inf)  # never restart
    plain = localizer.updated(prior, P, obs, landmarks, map_cost=True)
    assert np.linalg.norm(restarted.state[:3] - truth[:3]) < 0.03
    assert restarted.map_cost <= plain.map_cost + 1e-9
    if offset == (0.6, -0.6, 0.0):
        assert np.linalg.norm(plain.state[:3] - truth[:3]) > 0.3


def test_an_update_given_a_start_keeps_the_posterior_the_map_cost_prefers(monkeypatch):
    # the replay's update at a slip pose, started from the beam's seed pair
    localizer, obs, landmarks, truth = _busiest_pose_of_a_dense_world()
    prior = truth + np.r_[0.6, -0.6, 0.0, 0.0, 0.0, 0.0]
    P = np.diag([0.3**2] * 3 + [0.05**2] * 3)
    monkeypatch.setattr(localizer.stacked, "nis_bound", lambda dof: np.inf)  # no restart of its own
    plain = localizer.updated(prior, P, obs, landmarks, map_cost=True)
    started = localizer.updated(prior, P, obs, landmarks, map_cost=True, start=truth + np.r_[0.05, 0.0, 0.0, 0.0, 0.0, 0.0])
    misled = localizer.updated(prior, P, obs, landmarks, map_cost=True, start=truth + np.r_[3.0, 3.0, 0.0, 0.0, 0.0, 0.0])
    assert np.linalg.norm(plain.state[:3] - truth[:3]) > 0.3
    assert np.linalg.norm(started.state[:3] - truth[:3]) < 0.03 and started.map_cost < plain.map_cost
    assert misled.map_cost <= plain.map_cost  # a start never leaves a posterior the MAP cost likes less
    assert started.map_cost < misled.map_cost


def test_beam_keeps_up_with_the_oracle_when_odometry_noise_rivals_the_landmark_spacing():
    # 3x odometry noise (0.3 m a step) in a 5x dense map (landmarks about 0.5 m apart): a right
    # landmark predicted decimetres off leaves the gate in pixels but not as a camera-frame point.
    dataset = simulate(SimulationConfig(poses=100, dense=True, odometry_sigma_scale=3.0), seed=8)
    oracle = localize(dataset, LocalizerConfig(association="oracle"))
    result = localize_both(dataset)
    precision, recall = precision_recall(result, dataset)
    assert position_rmse(result, dataset) <= 1.5 * position_rmse(oracle, dataset) + 0.01
    assert precision >= 0.99 and recall >= 0.85


def test_a_right_pair_implies_the_robot_s_true_shift_from_the_prediction():
    from camloc.beam import BeamSearch
    from camloc.beam_types import BeamSettings, Hypothesis
    from camloc.localizer import _Localizer

    dataset = simulate(SimulationConfig(poses=30, dense=True, observation_sigma_scale=0.0, cameras=2), seed=5)
    localizer = _Localizer(dataset, LocalizerConfig())
    search = BeamSearch(localizer, BeamSettings())
    k = int(np.argmax(np.bincount(dataset.obs_pose_index)))
    obs = localizer.obs_of_pose[k]
    landmarks = localizer.true_landmark_row[obs]
    assert (landmarks >= 0).all()  # every observation's landmark is in the map
    truth = localizer.filter.initial(geometry.pose_from_quat(dataset.truth_xyz[k], dataset.truth_quat_xyzw[k]))
    offset = np.array([0.5, -0.3, 0.2])
    predicted = Hypothesis(truth + np.r_[offset, 0.0, 0.0, 0.0], np.eye(6), 0.0, -1)
    shifts = search.seeded.implied_shifts(predicted, obs, np.arange(obs.size), landmarks)
    assert len(np.unique(dataset.obs_camera[obs])) == 2
    np.testing.assert_allclose(shifts, np.broadcast_to(-offset, shifts.shape), atol=1e-9)


def test_slip_seeds_come_from_the_crowd_of_agreeing_pairs_when_no_own_cost_ranks_them():
    # At pose 19 the prediction is 1.17 m (4 sigma) off in a dense map: under the slip's wide
    # prior 7464 pairs gate, the best right one ranks 898th by its own cost, and the 22 right
    # pairs are found as the largest crowd of pairs implying one shift of the robot.
    dataset = simulate(SimulationConfig(poses=100, dense=True, odometry_sigma_scale=3.0), seed=6)
    oracle = localize(dataset, LocalizerConfig(association="oracle"))
    result = localize(dataset)
    precision, _ = precision_recall(result, dataset)
    assert position_rmse(result, dataset) <= 1.25 * position_rmse(oracle, dataset)
    assert precision >= 0.99


@pytest.mark.parametrize("max_angle_deg", [None, 89.5])
def test_a_view_widened_by_the_covariance_holds_the_plain_view(max_angle_deg):
    from camloc.localizer import _Localizer

    dataset = simulate(SimulationConfig(poses=20, dense=True), seed=1)
    localizer = _Localizer(dataset, LocalizerConfig(view=ViewOptions(max_angle_deg=max_angle_deg)))
    for P in (np.diag([0.2**2] * 3 + [0.05**2] * 3), np.diag([1e-12] * 3 + [0.05**2] * 3)):  # the second: orientation only
        _assert_widened_holds_plain(localizer, dataset, P, strictly=P[0, 0] > 1e-6)


def _assert_widened_holds_plain(localizer, dataset, P, *, strictly):
    for k in range(0, 20, 4):
        x = localizer.filter.initial(geometry.pose_from_quat(dataset.truth_xyz[k], dataset.truth_quat_xyzw[k]))
        plain, widened = set(localizer.visible(x, 0).tolist()), set(localizer.visible(x, 0, P).tolist())
        assert plain <= widened and (len(widened) > len(plain) or not strictly)


@pytest.mark.parametrize("inflation", [1.0, 25.0])
def test_the_pair_bound_never_drops_a_pair_within_the_pool_gate(inflation):
    # The beam computes d^2 only for the pairs |y|^2 / trace(S) does not already put beyond the
    # pool's gate; every pair within it, in either coordinates, must be among them.
    from camloc.beam import BeamSearch
    from camloc.beam_types import BeamSettings
    from camloc.constants import POOL_GATE_FACTOR
    from camloc.localizer import _Localizer

    dataset = simulate(SimulationConfig(poses=40, dense=True, odometry_sigma_scale=3.0), seed=4)
    localizer = _Localizer(dataset, LocalizerConfig())
    search = BeamSearch(localizer, BeamSettings())
    limit = POOL_GATE_FACTOR * float(localizer.obs_gate[0])  # the pool of a depth observation, as _options makes it
    checked = dropped = 0
    for k in range(0, dataset.num_poses, 3):
        x = localizer.filter.initial(geometry.pose_from_quat(dataset.truth_xyz[k], dataset.truth_quat_xyzw[k]))
        x[:3] += 0.2  # a prediction off by decimetres, as with this odometry
        P = inflation * np.diag([0.04, 0.04, 0.04, 1e-3, 1e-3, 1e-3])
        o = localizer.obs_of_pose[k]
        candidates = localizer.visible(x, 0, P)
        if o.size == 0 or candidates.size == 0:
            continue
        z_hat, H = localizer.observe(x, 0, candidates)
        spread = search.gating.spread(P, [0], [candidates.size], z_hat, H)
        rows, columns = search.gating.plausible_pairs(o, z_hat, spread, limit)
        j, g = (a.ravel() for a in np.meshgrid(np.arange(o.size), np.arange(candidates.size), indexing="ij"))
        d2, _, _ = search.gating.in_best_coordinates(o[j], z_hat[g], spread[0][g], spread[2][g], spread[3][g])
        within = set(zip(j[d2 <= limit].tolist(), g[d2 <= limit].tolist()))
        assert within <= set(zip(rows.tolist(), columns.tolist()))
        checked, dropped = checked + len(within), dropped + j.size - rows.size
    assert checked > 50
    if inflation == 1.0:
        assert dropped > checked  # and it does save work


def test_a_child_s_state_is_computed_once_and_only_when_read():
    from camloc.beam_types import Hypothesis

    calls = []
    child = Hypothesis(None, None, 1.5, 0, ((3, 7),), pending=lambda: calls.append(1) or (np.ones(6), 2.0 * np.eye(6)))
    assert child.cost == 1.5 and child.pairs == ((3, 7),) and not calls
    assert np.array_equal(child.x, np.ones(6)) and np.array_equal(child.P, 2.0 * np.eye(6))
    assert np.array_equal(child.x, np.ones(6)) and len(calls) == 1
    # where every observation is ambiguous, many children are pruned before anything reads them
    dataset = simulate(SimulationConfig(poses=12, dense=True, observation_sigma_scale=3.0), seed=0)
    _, statistics = beam_run(dataset)
    assert 0 < statistics.children_settled < 0.9 * statistics.children_created  # 13,737 of 17,441 here


# ------------------------------------------------------------------------------ pixel-only cameras


def _precision_and_ratio(dataset):
    """(precision, beam RMSE / oracle RMSE) of the default association on ``dataset`` (compiled)."""
    beam = evaluate(localize(dataset, engine="compiled"))
    oracle = evaluate(localize(dataset, LocalizerConfig(association="oracle"), engine="compiled"))
    return beam["association"]["precision"], beam["estimate"]["ate"]["rmse"] / oracle["estimate"]["ate"]["rmse"]


@pytest.mark.parametrize("kind, seed, precision, ratio", [
    (dict(trajectory="smooth3d", cameras=2, clutter_fraction=0.1), 3, 0.978, 1.35),
    (dict(trajectory="grid"), 4, 0.978, 1.15),
    (dict(trajectory="aerial"), 4, 0.99, 1.15),
], ids=["smooth3d-2cam-clutter", "grid", "aerial"])
def test_the_beam_holds_on_the_rays_of_pixel_only_cameras(kind, seed, precision, ratio):
    """Pixel-only worlds of 500 poses: precision and RMSE ratio to the oracle (with the beam's miss
    term charged by the chance a landmark is on the ray, 2026-12-05: 0.991 / 1.31, 0.986 / 1.05,
    0.997 / 1.04; with its flat charge before, 0.981 / 1.28, 0.981 / 1.08, 0.992 / 1.07; at fb2f66a,
    before the term, 0.969 / 1.34, 0.969 / 1.06, 0.981 / 1.06)."""
    dataset = simulate(SimulationConfig(poses=500, measurement="pixel", **kind), seed=seed)
    got_precision, got_ratio = _precision_and_ratio(dataset)
    assert got_precision >= precision and got_ratio <= ratio



def test_auto_gives_a_short_pixel_only_file_to_the_compiled_loop():
    """Under COMPILED_MIN_POSES poses "auto" runs numpy (it starts sooner), except where numpy would
    take COMPILED_MIN_NUMPY_SECONDS over the file: a pixel-only observation's ray gates many
    landmarks (a 200-pose file of two such cameras: 17.7 s in numpy, about 1 s compiled)."""
    from camloc.localizer import COMPILED_MIN_NUMPY_SECONDS, COMPILED_MIN_POSES
    from camloc.warmup import numpy_seconds

    pixel = simulate(SimulationConfig(poses=150, measurement="pixel", cameras=2), seed=1)
    depth = simulate(SimulationConfig(poses=150, cameras=2), seed=1)
    assert pixel.num_poses < COMPILED_MIN_POSES
    assert numpy_seconds(pixel.num_observations, pixel.num_observations) >= COMPILED_MIN_NUMPY_SECONDS
    assert localize(pixel).summary["timing"]["engine"] == "compiled"
    assert localize(depth).summary["timing"]["engine"] == "numpy"
