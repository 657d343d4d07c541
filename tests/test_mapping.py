"""The mapping localizer (``camloc run --map prior|none``, camloc.slam_run) on worlds built for each
behaviour: a landmark the map lacks is added and corrected as it is seen again, a moved landmark is
corrected under a prior and not under the exact map, clutter never becomes a landmark, and two
pixel-only cameras on a robot that does not move map a landmark consistently."""

from dataclasses import replace

import numpy as np
import pytest

from camloc import geometry, measurement
from camloc.dataset import Camera, Dataset
from camloc.g2o import observation_cov_from_info, odometry_cov_from_info
from camloc.localizer import localize
from camloc.localizer_config import LocalizerConfig
from camloc.simulate import SimulationConfig, simulate_labelled
from camloc.tails import chi2_quantile


def _world(seed=0, poses=150, **options):
    return simulate_labelled(SimulationConfig(poses=poses, **options), seed=seed)


def _most_seen(dataset, count=1):
    ids, seen = np.unique(dataset.obs_true_landmark, return_counts=True)
    mapped = np.isin(ids, dataset.landmark_ids)
    return ids[mapped][np.argsort(-seen[mapped], kind="stable")][:count]


def _position_rmse(result, dataset):
    return float(np.sqrt(np.mean(np.sum((result.estimate_xyz - dataset.truth_xyz) ** 2, axis=1))))


def test_withheld_landmarks_are_added_where_they_are():
    """A fifth of the map withheld (the most seen landmarks, so each is seen many times): the
    run adds them (each once), near their true place, with ids the map lacks, and pairs their
    observations with them; the pose estimate stays within 1.3x the full map's."""
    dataset = _world(seed=2).dataset
    withheld = _most_seen(dataset, count=len(dataset.landmark_ids) // 5)
    keep = ~np.isin(dataset.landmark_ids, withheld)
    partial = replace(dataset, landmark_ids=dataset.landmark_ids[keep], landmark_xyz=dataset.landmark_xyz[keep])
    full = localize(dataset, LocalizerConfig(), engine="numpy")
    result = localize(partial, LocalizerConfig(), engine="numpy")  # --map exact: the lacking ones are added
    landmarks = result.landmark_map
    added = landmarks.added
    assert added.sum() >= 0.8 * withheld.size
    assert not np.any(np.isin(landmarks.ids[added], dataset.landmark_ids))  # new ids
    # each added landmark stands for the withheld one most of its observations are of
    a = result.associations
    stands_for = []
    for landmark_id in landmarks.ids[added]:
        true_ids, counts = np.unique(a.true_landmark[a.landmark == landmark_id], return_counts=True)
        stands_for.append(true_ids[np.argmax(counts)])
    stands_for = np.array(stands_for)
    assert np.all(np.isin(stands_for, withheld))
    assert np.unique(stands_for).size == stands_for.size  # none added twice
    true_xyz = dataset.landmark_xyz[np.searchsorted(dataset.landmark_ids, stands_for)]
    error = np.linalg.norm(landmarks.xyz[added] - true_xyz, axis=1)
    assert np.median(error) < 0.1
    assert _position_rmse(result, dataset) <= 1.3 * _position_rmse(full, dataset)
    assert result.summary["map"]["added"] == int(added.sum())


def test_a_moved_landmark_is_corrected_under_a_prior_and_not_under_the_exact_map():
    dataset = _world(seed=1).dataset
    target = _most_seen(dataset)[0]
    row = int(np.flatnonzero(dataset.landmark_ids == target)[0])
    moved_xyz = dataset.landmark_xyz.copy()
    moved_xyz[row] += [0.3, 0.0, 0.0]
    moved = replace(dataset, landmark_xyz=moved_xyz)
    prior = localize(moved, LocalizerConfig(map="prior", map_sigma=0.1, association="oracle"), engine="numpy")
    at = int(np.flatnonzero(prior.landmark_map.ids == target)[0])
    assert np.linalg.norm(prior.landmark_map.xyz[at] - dataset.landmark_xyz[row]) < 0.15  # at most half of 0.3 m
    # its covariance shrank from the prior's, and is honest about what is left
    assert np.trace(prior.landmark_map.cov[at]) < 3 * 0.1**2
    exact = localize(moved, LocalizerConfig(map="exact", association="oracle"), engine="numpy")
    assert exact.landmark_map is None  # the map held as given: nothing estimated, no map.csv
    assert np.linalg.norm(exact.map_landmark_xyz[row] - dataset.landmark_xyz[row]) == pytest.approx(0.3)


def test_clutter_never_becomes_a_landmark():
    """30% of the observations clutter, the map complete and known to 3 cm: nothing is added, and
    clutter is left out. (A looser prior widens the beam's gates by the map's spread, and pairs
    more clutter with mapped landmarks: 3.4% of it at 0.1 m here, the price of finding moved ones.)"""
    sim = _world(seed=4, clutter_fraction=0.3)
    result = localize(sim.dataset, LocalizerConfig(map="prior", map_sigma=0.03), engine="numpy")
    assert result.landmark_map.added.sum() == 0
    a = result.associations
    assert np.count_nonzero(a.landmark[sim.is_clutter] != -1) <= 0.01 * sim.is_clutter.sum()


def test_no_map_maps_everything_from_the_start():
    """With no map at all the run is EKF-SLAM from the known start: every landmark it keeps is
    added, and it does better than odometry alone."""
    dataset = _world(seed=3, poses=100).dataset
    result = localize(dataset, LocalizerConfig(map="none", association="oracle"), engine="numpy")
    odometry = float(np.sqrt(np.mean(np.sum((result.odometry_xyz - dataset.truth_xyz) ** 2, axis=1))))
    assert result.landmark_map.added.all() and result.landmark_map.added.size > 20
    assert _position_rmse(result, dataset) < 0.6 * odometry


def _static_stereo(seed: int, poses: int = 40) -> tuple[Dataset, np.ndarray]:
    """A robot standing still (odometry: no motion, tight noise) with two pixel-only cameras 0.3 m
    apart looking along its x axis, seeing one landmark 3 m ahead that no map holds, 1 px noise."""
    rng = np.random.default_rng(seed)
    landmark = np.array([3.0, 0.2, 0.1])
    look_x = geometry.euler_to_quat(np.radians([-90.0, 0.0, -90.0]))  # camera z along the robot's x
    cameras = {c: Camera(id=c, translation=np.array([0.0, y, 0.0]), quat_xyzw=look_x, fx=500.0, fy=500.0, cx=320.0, cy=240.0)
               for c, y in ((0, 0.15), (1, -0.15))}
    z, camera_of = [], []
    for k in range(poses):
        for c, camera in cameras.items():
            R_c = geometry.quat_to_matrix(camera.quat_xyzw)
            p = R_c.T @ (landmark - camera.translation)
            uv = np.array([500.0 * p[0] / p[2] + 320.0, 500.0 * p[1] / p[2] + 240.0]) + rng.normal(size=2)
            z.append([uv[0], uv[1], 0.0])
            camera_of.append(c)
    K = len(z)
    obs_info = np.tile(measurement.padded_information(np.array([[1.0, 0.0, 1.0]]), measurement.PIXEL), (K, 1, 1))
    odom_info = np.tile(np.diag([1e8] * 6), (poses - 1, 1, 1))
    identity = np.tile([0.0, 0.0, 0.0, 1.0], (poses - 1, 1))
    truth_quat = np.tile([0.0, 0.0, 0.0, 1.0], (poses, 1))
    dataset = Dataset(
        source="static-stereo", cameras=cameras, landmark_ids=np.zeros(0, np.int64), landmark_xyz=np.zeros((0, 3)),
        pose_ids=np.arange(100, 100 + poses), start_xyz=np.zeros(3), start_quat_xyzw=truth_quat[0],
        truth_xyz=np.zeros((poses, 3)), truth_quat_xyzw=truth_quat, odom_translation=np.zeros((poses - 1, 3)),
        odom_quat_xyzw=identity, odom_info=odom_info, odom_cov=odometry_cov_from_info(odom_info),
        obs_pose_index=np.repeat(np.arange(poses), 2), obs_camera=np.array(camera_of, np.int64), obs_z=np.array(z),
        obs_info=obs_info, obs_cov=observation_cov_from_info(obs_info), obs_true_landmark=np.full(K, 7, np.int64),
        obs_kind=np.full(K, measurement.PIXEL, np.int64),
    )
    return dataset, landmark


@pytest.mark.parametrize("association", ["beam", "oracle"])
def test_two_pixel_cameras_on_a_still_robot_map_a_landmark_consistently(association):
    """The classic two-camera case: the landmark's estimate converges to the truth as it is seen
    again and again, and its covariance is consistent (NEES over seeds within the 95% bounds of a
    3-dof chi-square mean)."""
    nees, spread = [], []
    for seed in range(20):
        dataset, truth = _static_stereo(seed)
        config = LocalizerConfig(map="none", association=association, initial_sigma_xyz=1e-4, initial_sigma_deg=1e-3)
        landmarks = localize(dataset, config, engine="numpy").landmark_map
        assert landmarks.ids.size == 1 and landmarks.added[0]
        error = landmarks.xyz[0] - truth
        nees.append(float(error @ np.linalg.solve(landmarks.cov[0], error)))
        spread.append(np.sqrt(np.trace(landmarks.cov[0])))
    assert np.median(spread) < 0.05  # 3 m away through a 0.3 m baseline: centimetres after 40 views
    lower, upper = chi2_quantile(3 * 20, 0.975) / 20, chi2_quantile(3 * 20, 0.025) / 20
    assert lower <= np.mean(nees) <= upper


def test_a_landmark_is_corrected_as_it_is_seen_again():
    """The same still robot: after 3 poses of views the landmark is a few centimetres wide, after
    40 a fraction of that, and closer to the truth."""
    dataset, truth = _static_stereo(0, poses=40)
    config = LocalizerConfig(map="none", association="oracle", initial_sigma_xyz=1e-4, initial_sigma_deg=1e-3)
    early = localize(replace(dataset, **_first_poses(dataset, 3)), config, engine="numpy").landmark_map
    late = localize(dataset, config, engine="numpy").landmark_map
    assert np.trace(late.cov[0]) < 0.2 * np.trace(early.cov[0])
    assert np.linalg.norm(late.xyz[0] - truth) < np.linalg.norm(early.xyz[0] - truth) + 0.01


def _first_poses(dataset: Dataset, n: int) -> dict:
    keep = dataset.obs_pose_index < n
    return dict(pose_ids=dataset.pose_ids[:n], truth_xyz=dataset.truth_xyz[:n], truth_quat_xyzw=dataset.truth_quat_xyzw[:n],
                odom_translation=dataset.odom_translation[:n - 1], odom_quat_xyzw=dataset.odom_quat_xyzw[:n - 1],
                odom_info=dataset.odom_info[:n - 1], odom_cov=dataset.odom_cov[:n - 1], obs_pose_index=dataset.obs_pose_index[keep],
                obs_camera=dataset.obs_camera[keep], obs_z=dataset.obs_z[keep], obs_info=dataset.obs_info[keep],
                obs_cov=dataset.obs_cov[keep], obs_true_landmark=dataset.obs_true_landmark[keep], obs_kind=dataset.obs_kind[keep])


# --- through the command line --------------------------------------------------------------------

def _cli(*args):
    from typer.testing import CliRunner

    from camloc.cli.app import app

    return CliRunner().invoke(app, [str(arg) for arg in args])


def test_run_map_prior_writes_the_map_and_eval_scores_it(tmp_path):
    """simulate (a fifth of the map withheld) -> run --map prior -> map.csv, eval --true-map."""
    import json

    from camloc.results import read_map

    world = tmp_path / "w.g2o"
    assert _cli("simulate", "-o", world, "--poses", "120", "--seed", "2", "--withhold-map", "0.2", "-q").exit_code == 0
    run = _cli("run", world, "--map", "prior", "--map-sigma", "0.05", "-o", tmp_path / "r", "--json")
    assert run.exit_code == 0, run.output
    summary = json.loads(run.output)
    assert summary["config"]["map"] == "prior" and summary["config"]["map_sigma"] == 0.05
    assert summary["map"]["mode"] == "prior" and summary["map"]["added"] >= 1
    landmarks = read_map(tmp_path / "r" / "map.csv")
    assert int(landmarks.added.sum()) == summary["map"]["added"]
    scored = _cli("eval", tmp_path / "r", "--true-map", tmp_path / "w.true-map.g2o", "--json")
    assert scored.exit_code == 0, scored.output
    report = json.loads(scored.output)["map"]
    assert report["added_twice"]["landmarks"] == 0 and report["clutter"]["landmarks"] == 0


def test_a_mapping_run_names_the_smooth_command_that_estimates_its_map_again(tmp_path):
    """The run's table says how to smooth it with the run's own --map and sigma; that command
    runs on the folder and writes the smoothed path and map."""
    world = tmp_path / "w.g2o"
    assert _cli("simulate", "-o", world, "--poses", "60", "--seed", "2", "--withhold-map", "0.2", "-q").exit_code == 0
    run = _cli("run", world, "--map", "prior", "--map-sigma", "0.05", "-o", tmp_path / "r")
    assert run.exit_code == 0, run.output
    said = " ".join(run.output.split())
    assert "'camloc smooth" in said and "--map prior --map-sigma 0.05' estimates poses and map again" in said
    plain = _cli("run", world, "-o", tmp_path / "e")
    assert plain.exit_code == 0 and "--map exact'" in " ".join(plain.output.split())
    smoothed = _cli("smooth", tmp_path / "r", "--map", "prior", "--map-sigma", "0.05", "-q")
    assert smoothed.exit_code == 0, smoothed.output
    assert (tmp_path / "r" / "smoothed.tum").is_file() and (tmp_path / "r" / "map.csv").is_file()


def test_a_file_without_a_map_is_mapped_from_scratch(tmp_path):
    """No landmark vertex: --map auto runs as none and adds landmarks (with the true association it
    beats odometry: test_no_map_maps_everything_from_the_start)."""
    import json

    world = tmp_path / "w.g2o"
    assert _cli("simulate", "-o", world, "--poses", "80", "--seed", "1", "--no-map", "-q").exit_code == 0
    run = _cli("run", world, "-o", tmp_path / "r", "--json")
    assert run.exit_code == 0, run.output
    summary = json.loads(run.output)
    assert summary["config"]["map"] == "none" and summary["map"]["added"] > 10
    assert summary["map"]["mapped"] == 0 and summary["counts"]["updates"] > 40


def test_map_uncertainty_widens_each_observation_by_the_landmark_spread_it_implies():
    """``with_map_uncertainty``: a depth camera's covariance grows by the spread of the projections
    of a landmark scattered with sigma per axis about the observed point (sampled), a pixel's
    two rows grow and its inert row does not."""
    from camloc.observation_space import observation_intrinsics, with_map_uncertainty

    world = _world(seed=3, poses=5, cameras=2, measurement="depth,pixel").dataset
    sigma = 0.02
    widened = with_map_uncertainty(world, sigma)
    rng = np.random.default_rng(0)
    intrinsics = observation_intrinsics(world)
    for i in np.flatnonzero(world.obs_kind == measurement.DEPTH)[:3]:
        point, _ = measurement.back_project(world.obs_z[i:i + 1], intrinsics[i], measurement.DEPTH)
        scattered = point + sigma * rng.standard_normal((20000, 3))
        spread = np.cov(measurement.project(scattered, intrinsics[i], measurement.DEPTH).T)
        added = widened.obs_cov[i] - world.obs_cov[i]
        assert np.allclose(added, spread, rtol=0.05, atol=0.05 * np.abs(spread).max())
        assert np.allclose(widened.obs_info[i] @ widened.obs_cov[i], np.eye(3), atol=1e-9)
    pixel = np.flatnonzero(world.obs_kind == measurement.PIXEL)
    assert pixel.size
    added = widened.obs_cov[pixel] - world.obs_cov[pixel]
    assert np.all(added[:, 0, 0] > 0) and np.all(added[:, 1, 1] > 0)
    assert np.all(added[:, 2, :] == 0) and np.all(added[:, :, 2] == 0)


def test_moved_landmarks_are_corrected_under_a_prior_with_the_default_association():
    """A quarter of the map moved 0.3 m (``simulate --move-map``): under ``--map prior --map-sigma
    0.1`` the beam judges pairs with the map's uncertainty (``with_map_uncertainty``), so it pairs
    most observations of the moved landmarks with them instead of leaving them out or handing them
    to neighbours, and the run brings the moved landmarks to 0.12 m of where they are on average
    (0.086 m, 91% of their observations paired right; 0.098 m and 81% with one pass of the beam,
    ``localizer.PRIOR_PASSES``; judged against the map as exact, 0.154 m and 68%)."""
    full = _world(seed=1, poses=80).dataset
    world = _world(seed=1, poses=80, move_map=0.25).dataset
    moved = np.flatnonzero(np.linalg.norm(world.landmark_xyz - full.landmark_xyz, axis=1) > 1e-6)
    moved = moved[np.isin(world.landmark_ids[moved], world.obs_true_landmark)]  # seen at all
    assert moved.size > 30
    result = localize(world, LocalizerConfig(map="prior", map_sigma=0.1), engine="numpy")
    a = result.associations
    of_moved = np.isin(a.true_landmark, world.landmark_ids[moved])
    assert np.mean(a.landmark[of_moved] == a.true_landmark[of_moved]) >= 0.75
    at = np.searchsorted(result.landmark_map.ids, world.landmark_ids[moved])
    error = np.linalg.norm(result.landmark_map.xyz[at] - full.landmark_xyz[moved], axis=1)
    assert np.mean(error) < 0.12


@pytest.mark.parametrize("ready", [True, False])
def test_a_short_file_s_slow_beam_passes_run_compiled_where_the_kernels_are_ready(monkeypatch, ready):
    """A file under ``COMPILED_MIN_POSES`` runs its first beam in numpy, but the passes numpy is
    far slower over than its estimate (judging with the map prior's uncertainty; with the null cost
    lowered where the map lacks landmarks) run compiled where the kernels are compiled (never
    compiling for it): the same pairs and estimate as numpy's."""
    import camloc.localizer as localizer

    world = _world(seed=2, poses=60, move_map=0.25).dataset
    config = LocalizerConfig(map="prior", map_sigma=0.1)
    reference = localize(world, config, engine="numpy")
    engines = []
    compiled, numpy_run = localizer._localize_compiled, localizer._localize_numpy
    monkeypatch.setattr(localizer, "_localize_compiled", lambda *a, **k: engines.append("compiled") or compiled(*a, **k))
    monkeypatch.setattr(localizer, "_localize_numpy", lambda *a, **k: engines.append("numpy") or numpy_run(*a, **k))
    monkeypatch.setattr(localizer, "_kernels_ready", lambda: ready)
    result = localize(world, config)
    assert engines and set(engines) == ({"compiled"} if ready else {"numpy"})
    assert np.array_equal(result.associations.landmark, reference.associations.landmark)
    assert np.allclose(result.estimate_xyz, reference.estimate_xyz, atol=1e-9)


def _moved_pixel_world(seed=0, poses=150):
    """A grid world seen by two pixel-only cameras, a quarter of its map moved 0.3 m: the world as
    simulated (its true map) and as given, with the rows of the moved landmarks that are seen."""
    options = dict(poses=poses, measurement="pixel", cameras=2)
    full = _world(seed=seed, **options).dataset
    world = _world(seed=seed, move_map=0.25, **options).dataset
    moved = np.flatnonzero(np.linalg.norm(world.landmark_xyz - full.landmark_xyz, axis=1) > 1e-6)
    return full, world, moved[np.isin(world.landmark_ids[moved], world.obs_true_landmark)]


def _moved_scores(result, full, world, moved):
    """(mean distance of the moved landmarks' estimates to where they are, share of their
    observations paired with them)."""
    a = result.associations
    of_moved = np.isin(a.true_landmark, world.landmark_ids[moved])
    at = np.searchsorted(result.landmark_map.ids, world.landmark_ids[moved])
    error = np.linalg.norm(result.landmark_map.xyz[at] - full.landmark_xyz[moved], axis=1)
    return float(np.mean(error)), float(np.mean(a.landmark[of_moved] == a.true_landmark[of_moved]))


def test_pixel_only_moved_landmarks_are_paired_again_against_the_first_pass_map(monkeypatch):
    """Pixels alone: a ray fits a landmark 0.3 m from its map position only partly, so the beam's
    first pass (judged against the map as given) pairs few of a moved landmark's rays (0.48 here,
    0.33 with candidates to 10 m rather than the cameras' learned reach) and the run leaves it
    0.164 m out (0.22). The second pass judges against the map the first estimated
    (``localizer.PRIOR_PASSES``): 0.76 of them paired, 0.130 m (0.50, 0.195 m). The estimate still
    holds the given map as its prior."""
    import camloc.localizer as localizer

    full, world, moved = _moved_pixel_world()
    assert moved.size > 30
    config = LocalizerConfig(map="prior", map_sigma=0.1)
    two = _moved_scores(localize(world, config, engine="compiled"), full, world, moved)
    monkeypatch.setattr(localizer, "PRIOR_PASSES", 1)
    one = _moved_scores(localize(world, config, engine="compiled"), full, world, moved)
    assert two[0] < 0.15 and two[1] > 0.65
    assert one[0] > two[0] + 0.02 and one[1] < two[1] - 0.15


def test_a_later_pass_less_consistent_than_the_first_is_not_kept(monkeypatch):
    """Under a prior a second pass is kept only where its NIS per degree of freedom is within
    ``PASS_NIS_SLACK`` of the first's: with no slack at all, none is kept and the run is the
    first pass's, pair for pair."""
    import camloc.localizer as localizer

    _, world, _ = _moved_pixel_world(poses=60)
    config = LocalizerConfig(map="prior", map_sigma=0.1)
    monkeypatch.setattr(localizer, "MOVED_LEAST", -1)  # a second pass whatever the first moved
    monkeypatch.setattr(localizer, "MOVED_SHARE", 0.0)
    monkeypatch.setattr(localizer, "PASS_NIS_SLACK", 0.0)
    refused = localize(world, config, engine="compiled")
    monkeypatch.setattr(localizer, "PRIOR_PASSES", 1)
    first = localize(world, config, engine="compiled")
    assert np.array_equal(refused.associations.landmark, first.associations.landmark)
    assert np.allclose(refused.estimate_xyz, first.estimate_xyz)


def test_a_second_pass_runs_only_where_the_first_moved_the_map():
    """Under a prior the second pass judges against the first's map; where that map is the given
    one to within its noise (no landmark moved), the second pass would pair the same and is not
    run. Moved: more than MOVED_SHARE (and MOVED_LEAST) of the observed mapped landmarks left their
    map positions by over MOVED_SIGMAS sigmas."""
    from types import SimpleNamespace

    from camloc.localizer import MOVED_LEAST, _map_moved

    rng = np.random.default_rng(3)
    given = SimpleNamespace(landmark_xyz=rng.uniform(-5.0, 5.0, (200, 3)))
    rows = np.arange(200)
    seen = np.full(200, 3)

    def estimated(xyz, observations=seen):
        return SimpleNamespace(xyz=xyz, observations=observations)

    noisy = given.landmark_xyz + rng.normal(0.0, 0.02, (200, 3))
    assert not _map_moved(given, estimated(noisy), rows, 0.1)
    moved = noisy.copy()
    moved[:20] += [0.3, 0.0, 0.0]  # a tenth of the map, 3 sigma
    assert _map_moved(given, estimated(moved), rows, 0.1)
    assert not _map_moved(given, estimated(moved), rows, 0.5)  # within 1.5 of a wider prior's sigmas
    few = noisy.copy()
    few[:MOVED_LEAST] += [0.3, 0.0, 0.0]
    assert not _map_moved(given, estimated(few), rows, 0.1)
    unseen = seen.copy()
    unseen[:20] = 0  # the moved ones never observed: their estimates are not the run's evidence
    assert not _map_moved(given, estimated(moved, unseen), rows, 0.1)
    assert not _map_moved(given, estimated(moved), np.where(rows < 20, -1, rows), 0.1)  # not kept in the map


def test_a_lacking_map_lowers_what_an_unexplained_observation_costs_by_the_offset():
    from camloc.observation_space import observation_noise

    dataset = _world(seed=1, poses=40, clutter_fraction=0.1).dataset
    for config in (LocalizerConfig(), LocalizerConfig(null_cost=9.0)):
        plain = observation_noise(dataset, config).null_cost
        lowered = observation_noise(dataset, config, 4.0).null_cost
        assert plain.size == dataset.num_observations > 0
        assert np.allclose(plain - lowered, 4.0)


@pytest.mark.parametrize("engine", ["numpy", "compiled"])
def test_where_the_map_lacks_landmarks_the_beam_decides_again_with_the_lower_null_cost(monkeypatch, engine):
    """The exact map's run finds the map lacking (its rejected observations agree on places with
    no landmark): the mapping pass takes the pairs of a beam judged with LACKING_NULL_OFFSET, in
    either engine, and a parallel run (the numpy replay in a second process) equals a sequential one."""
    from camloc import localizer
    from camloc.observation_space import landmark_rows

    world = _world(seed=2, poses=120, withhold_map=0.5).dataset
    taken = {}
    real_mapping = localizer._localize_mapping

    def spy(dataset, config, on_progress, hooks, given_run=None, follower=None):
        taken["pairs"] = None if given_run is None else given_run.associations.landmark.copy()
        return real_mapping(dataset, config, on_progress, hooks, given_run, follower)

    monkeypatch.setattr(localizer, "_localize_mapping", spy)
    result = localize(world, LocalizerConfig(), engine=engine, parallel=False)
    assert result.summary["map"]["added"] > 0  # the map was found lacking
    hooks = dict(parallel=False, engine=engine, on_compile=None, on_background_compile=None)
    config = localizer.resolved_config(LocalizerConfig(), world)
    lowered = localizer._localize_exact(world, config, None, null_cost_offset=localizer.LACKING_NULL_OFFSET, **hooks)
    plain = localizer._localize_exact(world, config, None, **hooks)
    assert np.array_equal(taken["pairs"], lowered.associations.landmark)
    assert np.sum(lowered.associations.landmark >= 0) < np.sum(plain.associations.landmark >= 0)  # fewer pairs forced
    rows = landmark_rows(world.landmark_ids, taken["pairs"])
    assert np.all((rows >= 0) == (taken["pairs"] >= 0))
    parallel = localize(world, LocalizerConfig(), engine=engine, parallel=True)
    assert np.array_equal(parallel.associations.landmark, result.associations.landmark)
    assert np.allclose(parallel.estimate_xyz, result.estimate_xyz, atol=1e-9)


def test_the_lowered_null_cost_prices_explanations_without_growing_many_more_of_them():
    """The beam judged with LACKING_NULL_OFFSET explores the null option where the default would
    (its viability judged at the null cost before the offset, ``BeamSettings.null_offset``): on a
    half-withheld world it grows well under half the children it grew with the viability judged at
    the lowered cost, and the compiled beam, judged so too, pairs as the numpy one does."""
    from camloc import localizer

    world = _world(seed=2, poses=120, withhold_map=0.5).dataset
    config = localizer.resolved_config(LocalizerConfig(), world)
    grown = {}
    for null_offset in (localizer.LACKING_NULL_OFFSET, 0.0):
        lowered = localizer._Localizer(world, config, null_cost_offset=localizer.LACKING_NULL_OFFSET)
        assert lowered.beam_settings().null_offset == localizer.LACKING_NULL_OFFSET
        lowered.search_beam(settings=replace(lowered.beam_settings(), null_offset=null_offset))
        grown[null_offset] = lowered.beam_statistics.children_created
    assert grown[localizer.LACKING_NULL_OFFSET] < 0.5 * grown[0.0]
    runs = [localizer._localize_exact(world, config, None, null_cost_offset=localizer.LACKING_NULL_OFFSET, parallel=False,
                                      engine=engine, on_compile=None, on_background_compile=None)
            for engine in ("numpy", "compiled")]
    assert np.array_equal(runs[0].associations.landmark, runs[1].associations.landmark)
    np.testing.assert_allclose(runs[0].filter_state, runs[1].filter_state, atol=1e-8)


def test_the_null_option_is_explored_as_before_its_offset():
    """A pair 6 below its lowered null cost (10 before the offset of 4): with branch_delta 8 the
    null option is not explored under the offset (both engines), and is without it."""
    from camloc.beam_expansion import PoseExpansion
    from camloc.beam_types import BeamSettings
    from camloc.kernels import _jit
    from camloc.kernels.beam import clear_choices as compiled_only
    from camloc.scene import build_settings

    clear_choices = _jit.from_python(compiled_only)  # a step without numba's Python wrapper
    costs, lowered_null = np.array([0.0]), 6.0
    for offset, explored in ((4.0, False), (0.0, True)):
        expansion = PoseExpansion.__new__(PoseExpansion)
        expansion.settings = BeamSettings(branch_delta=8.0, null_offset=offset)
        assert expansion.viable(costs, lowered_null)[1] is explored
        settings = build_settings(LocalizerConfig(), offset)
        assert settings.branch_delta == 8.0
        choice = clear_choices(settings, np.array([lowered_null]), np.array([0, 1]), np.array([7]), costs, np.array([0]))
        assert bool(choice[0] < 0) is explored  # AMBIGUOUS (negative) where the null option is explored too


@pytest.mark.slow
def test_half_a_map_withheld_no_longer_loses_the_robot_where_it_sees_few_landmarks():
    """Aerial worlds (about 3.6 observations a pose, half of them of landmarks the map lacks): with
    the default null cost the beam paired the lacking landmarks' observations with mapped
    neighbours and lost the robot on 3 of these 4 (RMSE 1.1-1.5 m, the true association's
    0.2-0.28 m). Now at most one of the four is off by more than 2x the true association's."""
    lost = 0
    for seed in range(4):
        world = _world(seed=seed, poses=300, trajectory="aerial", withhold_map=0.5).dataset
        result = localize(world, LocalizerConfig())
        oracle = localize(world, LocalizerConfig(association="oracle"))
        assert result.summary["map"]["added"] > 0
        lost += _position_rmse(result, world) > 2.0 * _position_rmse(oracle, world)
    assert lost <= 1


def test_the_screening_counts_a_moved_landmark_as_lacking_only_beyond_the_map_reach():
    """Observations of one landmark, rejected from many poses, agree on a place: a landmark the
    map lacks where no mapped landmark is near. Written 0.3 m off in the map instead, it is
    lacking for an exact map (nothing within the screening's radius) and not under a prior whose
    reach (3 sigma of 0.1 m) covers it."""
    from camloc.slam_landmarks import lacking_landmarks

    dataset = _world(seed=2).dataset
    seen = _most_seen(dataset, count=len(dataset.landmark_ids))
    xyz_of = lambda i: dataset.landmark_xyz[dataset.landmark_ids == i][0]  # noqa: E731
    nearest = [np.sort(np.linalg.norm(dataset.landmark_xyz - xyz_of(i), axis=1))[1] for i in seen[:40]]
    target = seen[int(np.argmax(np.array(nearest) > 1.0))]  # a well seen landmark with no other within 1 m
    assert np.max(nearest) > 1.0
    rejected = dataset.obs_true_landmark == target
    T, pose_cov = dataset.T_world_truth, np.tile(1e-6 * np.eye(6), (dataset.num_poses, 1, 1))
    keep = dataset.landmark_ids != target
    withheld = replace(dataset, landmark_ids=dataset.landmark_ids[keep], landmark_xyz=dataset.landmark_xyz[keep])
    assert lacking_landmarks(withheld, T, pose_cov, rejected) == 1
    assert lacking_landmarks(withheld, T, pose_cov, rejected, map_reach=0.3) == 1  # no mapped landmark near
    moved_xyz = dataset.landmark_xyz.copy()
    moved_xyz[~keep] += [0.0, 0.3, 0.0]
    moved = replace(dataset, landmark_xyz=moved_xyz)
    assert lacking_landmarks(moved, T, pose_cov, rejected) == 1
    assert lacking_landmarks(moved, T, pose_cov, rejected, map_reach=0.3) == 0
    assert lacking_landmarks(dataset, T, pose_cov, rejected) == 0  # where the map has it: missed, not lacking


@pytest.mark.parametrize("seed", [1, 2])
def test_the_screening_finds_no_place_in_the_dense_clutter_of_a_complete_map(seed):
    """Half of a 600-pose run's observations clutter: uniform over what the camera sees, it
    agrees with itself three times here and there (11-43 places before the chance test in space,
    and a complete map's run went through the mapping pass), but never more than the clutter around
    it makes likely. With a fifth of the map withheld the lacking landmarks are still found."""
    from camloc.slam_landmarks import lacking_landmarks

    for withheld in (0.0, 0.2):
        dataset = simulate_labelled(SimulationConfig(poses=600, clutter_fraction=0.5, withhold_map=withheld), seed=seed).dataset
        rejected = ~np.isin(dataset.obs_true_landmark, dataset.landmark_ids)  # clutter, and the withheld landmarks' observations
        T, pose_cov = dataset.T_world_truth, np.tile(1e-3 * np.eye(6), (dataset.num_poses, 1, 1))
        places = lacking_landmarks(dataset, T, pose_cov, rejected)
        assert (places == 0) if withheld == 0.0 else (places >= 10)


def test_first_poses_keeps_the_start_of_a_run_whole():
    from camloc.dataset import first_poses

    dataset = _world(seed=1, poses=60, clutter_fraction=0.1).dataset
    start = first_poses(dataset, 25)
    assert start.num_poses == 25 and start.odom_translation.shape[0] == 24 and start.truth_xyz.shape[0] == 25
    kept = dataset.obs_pose_index < 25
    assert start.num_observations == int(kept.sum()) > 0
    assert np.array_equal(start.obs_z, dataset.obs_z[kept]) and np.array_equal(start.obs_true_landmark, dataset.obs_true_landmark[kept])
    assert np.array_equal(start.landmark_ids, dataset.landmark_ids)
    assert first_poses(dataset, 10**6).num_poses == dataset.num_poses


@pytest.mark.parametrize("withheld", [0.3, 0.0])
def test_a_long_run_screens_its_start_and_gives_what_screening_after_gives(monkeypatch, withheld):
    """Where the start of a long run shows the map lacking, the whole run's beam judges with the
    lower null cost at once: the same result as the run screened after and run again; a complete
    map's result is the same with or without the prefix."""
    from camloc import localizer

    world = _world(seed=1, poses=700, trajectory="smooth3d", withhold_map=withheld).dataset
    monkeypatch.setattr(localizer, "LACKING_PREFIX_MIN_POSES", 10**9)
    after = localize(world, LocalizerConfig(), engine="compiled", parallel=False)
    monkeypatch.setattr(localizer, "LACKING_PREFIX_MIN_POSES", 600)
    monkeypatch.setattr(localizer, "LACKING_PREFIX_SHARE", 0.5)
    config = localizer.resolved_config(LocalizerConfig(), world)
    hooks = dict(parallel=False, engine="compiled", on_compile=None, on_background_compile=None)
    assert localizer._lacking_at_start(world, world, config, hooks) == (localizer.LACKING_NULL_OFFSET if withheld else 0.0)
    first = localize(world, LocalizerConfig(), engine="compiled", parallel=False)
    assert np.array_equal(first.associations.landmark >= 0, after.associations.landmark >= 0)
    assert np.allclose(first.estimate_xyz, after.estimate_xyz, atol=1e-9)
    assert (first.summary.get("map") or {}).get("added") == (after.summary.get("map") or {}).get("added")


def test_the_oracle_maps_what_an_exact_map_lacks_and_leaves_a_complete_map_as_it_was():
    """Half the map withheld, ``--map exact``, the true association: the oracle's run is screened
    as the beam's is, and adds the landmarks the map lacks, each once and for one withheld id (its
    observations all of it), none of clutter. Unscreened, it ignored them (no landmark added),
    a reference no mapping run is measured against. A complete map's oracle run is the exact
    map's localizer's, bit for bit (the screening finds nothing there)."""
    from camloc.localizer import _localize_exact, resolved_config

    sim = _world(seed=0, poses=300, trajectory="grid", withhold_map=0.5, clutter_fraction=0.1)
    half = sim.dataset
    result = localize(half, LocalizerConfig(association="oracle"))
    landmarks, a = result.landmark_map, result.associations
    lacking = np.unique(half.obs_true_landmark[~sim.is_clutter & ~np.isin(half.obs_true_landmark, half.landmark_ids)])
    assert result.summary["map"]["added"] >= 0.5 * lacking.size
    stands_for = []
    for landmark_id in landmarks.ids[landmarks.added]:
        true_ids = np.unique(a.true_landmark[a.landmark == landmark_id])
        assert true_ids.size == 1  # the file's ids: one landmark each
        stands_for.append(int(true_ids[0]))
    assert np.all(np.isin(stands_for, lacking)) and np.unique(stands_for).size == len(stands_for)
    assert not np.any(a.landmark[sim.is_clutter] >= 0)

    full = _world(seed=0, poses=300, trajectory="grid", clutter_fraction=0.1).dataset
    config = LocalizerConfig(association="oracle")
    hooks = dict(parallel=None, engine="auto", on_compile=None, on_background_compile=None)
    alone = _localize_exact(full, resolved_config(config, full), None, **hooks)
    screened = localize(full, config)
    assert screened.landmark_map is None
    np.testing.assert_array_equal(screened.estimate_xyz, alone.estimate_xyz)
    np.testing.assert_array_equal(screened.estimate_cov, alone.estimate_cov)
    np.testing.assert_array_equal(screened.associations.landmark, alone.associations.landmark)
