"""The simulator: determinism, the exact models at zero noise, noise statistics against the written
information (the 4x rotation rule), trajectory shapes, cameras, clutter/outliers, and the CLI."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from camloc import geometry, models, simulate as sim
from camloc.errors import ConfigError
from camloc.simulate import SimulationConfig, simulate, simulate_labelled

EXACT = dict(odometry_sigma_scale=0.0, observation_sigma_scale=0.0)


def _arrays(dataset) -> dict[str, np.ndarray]:
    return {f.name: getattr(dataset, f.name) for f in dataclasses.fields(dataset)
            if isinstance(getattr(dataset, f.name), np.ndarray)}


def _predicted(dataset) -> np.ndarray:
    """(K, 3) exact measurements of every observation's true landmark from its true pose."""
    states = geometry.pose_to_euler(dataset.T_world_truth)
    row_of = {int(i): row for row, i in enumerate(dataset.landmark_ids)}
    out = np.empty((dataset.num_observations, 3))
    for j in range(dataset.num_observations):
        camera = dataset.cameras[int(dataset.obs_camera[j])]
        landmark = dataset.landmark_xyz[row_of[int(dataset.obs_true_landmark[j])]][None]
        z_hat, _ = models.observe(states[dataset.obs_pose_index[j]], camera.T_robot_camera,
                                  (camera.fx, camera.fy, camera.cx, camera.cy), landmark)
        out[j] = z_hat[0]
    return out


def _odometry_residuals(dataset) -> np.ndarray:
    """(N-1, 6) ``(t, rotvec)`` of ``dT_measured^-1 dT_true``: the noise w of ``T_k+1 = T_k dT Exp(w)``."""
    T_true = dataset.T_world_truth
    dT_true = geometry.relative_se3(T_true[:-1], T_true[1:])
    E = geometry.se3_inverse(dataset.T_odometry) @ dT_true
    return np.concatenate([E[:, :3, 3], geometry.so3_log(E[:, :3, :3])], axis=1)


# ----------------------------------------------------------------------------------- determinism


def test_same_seed_gives_identical_arrays_and_different_seeds_differ():
    config = SimulationConfig(trajectory="smooth3d", cameras=2, clutter_fraction=0.1, outlier_fraction=0.05)
    a, b, c = (_arrays(simulate(config, seed=s)) for s in (5, 5, 6))
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert not np.allclose(a["truth_xyz"], c["truth_xyz"])
    assert not np.array_equal(a["odom_translation"], c["odom_translation"])


def test_noise_streams_are_independent_of_the_clutter_and_detection_options():
    base = simulate(SimulationConfig(trajectory="smooth3d"), seed=2)
    noisier = simulate(SimulationConfig(trajectory="smooth3d", clutter_fraction=0.2, detection_probability=0.5), seed=2)
    np.testing.assert_array_equal(base.truth_xyz, noisier.truth_xyz)
    np.testing.assert_array_equal(base.landmark_xyz, noisier.landmark_xyz)
    np.testing.assert_array_equal(base.odom_translation, noisier.odom_translation)


# ------------------------------------------------------------------------------------ exactness


@pytest.mark.parametrize("trajectory", ["grid", "smooth3d", "aerial"])
def test_zero_noise_reproduces_the_models_exactly(trajectory):
    dataset = simulate(SimulationConfig(trajectory=trajectory, cameras=3, **EXACT), seed=11)
    assert dataset.num_observations > 200
    np.testing.assert_allclose(dataset.obs_z, _predicted(dataset), rtol=0, atol=1e-12)
    T_true = dataset.T_world_truth
    np.testing.assert_allclose(dataset.T_odometry, geometry.relative_se3(T_true[:-1], T_true[1:]), atol=1e-12)
    # Exact data is still written with a finite, very large information.
    assert np.all(np.isfinite(dataset.odom_info)) and np.all(np.isfinite(dataset.obs_info))
    assert np.diag(dataset.obs_info[0]).min() == 1e12
    assert np.diag(dataset.odom_info[0])[:3].min() == 1e12


def test_default_information_is_the_real_files():
    dataset = simulate(SimulationConfig(), seed=0)
    np.testing.assert_array_equal(dataset.odom_info[0], np.diag([100.0] * 3 + [10000.0] * 3))
    np.testing.assert_array_equal(dataset.obs_info[0], np.diag([1000.0] * 3))
    camera = dataset.cameras[0]
    np.testing.assert_array_equal(camera.translation, [0.0, 0.0, 0.3])
    np.testing.assert_array_equal(camera.quat_xyzw, [0.5, -0.5, 0.5, -0.5])
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (1.0, 1.0, 0.5, 0.5)


# ---------------------------------------------------------------------------------------- noise


def test_odometry_noise_matches_the_written_information_with_the_4x_rotation_rule():
    dataset = simulate(SimulationConfig(trajectory="smooth3d", poses=4001, landmarks=0), seed=1)
    w = _odometry_residuals(dataset)
    std = w.std(axis=0)
    # info 100 -> 0.1 m; info 10000 on the quaternion vector part -> 2/sqrt(10000) = 0.02 rad.
    np.testing.assert_allclose(std[:3], 0.1, rtol=0.1)
    np.testing.assert_allclose(std[3:], 0.02, rtol=0.1)
    np.testing.assert_allclose(std, np.sqrt(np.diag(dataset.odom_cov[0])), rtol=0.1)
    assert np.all(np.abs(w.mean(axis=0)) < 4.0 * std / math.sqrt(len(w)))
    # Uncorrelated, as the diagonal information says.
    assert np.abs(np.corrcoef(w.T) - np.eye(6)).max() < 0.1


def test_odometry_sigma_scale_scales_the_noise_and_the_information():
    dataset = simulate(SimulationConfig(poses=3001, landmarks=0, odometry_sigma_scale=3.0), seed=4)
    std = _odometry_residuals(dataset).std(axis=0)
    np.testing.assert_allclose(std, [0.3] * 3 + [0.06] * 3, rtol=0.1)
    np.testing.assert_allclose(np.diag(dataset.odom_info[0]), [100 / 9] * 3 + [10000 / 9] * 3, rtol=1e-9)


def test_observation_noise_matches_the_written_information():
    dataset = simulate(SimulationConfig(trajectory="smooth3d", poses=600, dense=True), seed=3)
    residual = dataset.obs_z - _predicted(dataset)
    assert len(residual) > 3000
    std = residual.std(axis=0)
    np.testing.assert_allclose(std, 1.0 / math.sqrt(1000.0), rtol=0.1)
    assert np.all(np.abs(residual.mean(axis=0)) < 4.0 * std / math.sqrt(len(residual)))


def test_explicit_observation_sigmas():
    config = SimulationConfig(poses=600, dense=True, observation_sigma_uv=0.01, observation_sigma_depth=0.05)
    dataset = simulate(config, seed=8)
    std = (dataset.obs_z - _predicted(dataset)).std(axis=0)
    np.testing.assert_allclose(std, [0.01, 0.01, 0.05], rtol=0.1)
    np.testing.assert_allclose(np.diag(dataset.obs_info[0]), [1e4, 1e4, 400.0])


# ----------------------------------------------------------------------------------- trajectories


def test_grid_moves_one_metre_or_turns_in_place_on_flat_ground():
    config = SimulationConfig(poses=500)
    dataset = simulate(config, seed=9)
    T = dataset.T_world_truth
    assert np.all(dataset.truth_xyz[:, 2] == 0.0)
    rpy = geometry.pose_to_euler(T)[:, 3:]
    np.testing.assert_allclose(rpy[:, :2], 0.0, atol=1e-12)
    np.testing.assert_allclose(dataset.truth_xyz[0], 0.0)
    dT = geometry.relative_se3(T[:-1], T[1:])
    step = np.linalg.norm(dT[:, :3, 3], axis=1)
    turn = np.degrees(geometry.rotation_angle(dT[:, :3, :3]))
    moved = step > 0.5
    np.testing.assert_allclose(dT[moved, :3, 3], np.tile([1.0, 0.0, 0.0], (moved.sum(), 1)), atol=1e-12)
    np.testing.assert_allclose(turn[moved], 0.0, atol=1e-9)
    np.testing.assert_allclose(step[~moved], 0.0, atol=1e-12)
    assert set(np.round(turn[~moved]).astype(int)) <= {90, 180}
    assert 0.25 < np.mean(~moved) < 0.45  # the real file turns 33 times in 100 steps
    assert np.abs(dataset.truth_xyz[:, :2]).max() <= config.region_side_m / 2


def test_smooth3d_has_bounded_nonzero_roll_pitch_and_a_few_metres_of_height():
    dataset = simulate(SimulationConfig(trajectory="smooth3d", poses=400), seed=5)
    rpy = np.degrees(geometry.quat_to_euler(dataset.truth_quat_xyzw))
    assert np.abs(rpy[:, :2]).max() <= 18.0 + 1e-9
    assert np.abs(rpy[:, 0]).max() > 15.0 and np.abs(rpy[:, 1]).max() > 15.0
    assert rpy[:, :2].std(axis=0).min() > 5.0
    height = np.ptp(dataset.truth_xyz[:, 2])
    assert 1.0 < height < 10.0
    step = np.linalg.norm(np.diff(dataset.truth_xyz, axis=0), axis=1)
    assert 0.25 < step.min() and step.max() < 1.1 and 0.4 < np.median(step) < 0.9  # 0.3..1 m a step
    # Smooth: the heading changes by little each step.
    T = dataset.T_world_truth
    turn = geometry.rotation_angle(geometry.relative_se3(T[:-1], T[1:])[:, :3, :3])
    assert np.degrees(turn).max() < 45.0


def test_aerial_tilts_to_about_60_degrees_and_near_the_singularity_on_request():
    dataset = simulate(SimulationConfig(trajectory="aerial", poses=300), seed=6)
    R = dataset.T_world_truth[:, :3, :3]
    tilt = np.degrees(np.arccos(np.clip(R[:, 2, 2], -1.0, 1.0)))  # body z against world z
    assert 55.0 < tilt.max()
    rpy = np.degrees(geometry.quat_to_euler(dataset.truth_quat_xyzw))
    assert np.abs(rpy[:, :2]).max() <= 60.0 + 1e-6 and np.abs(rpy[:, 1]).max() > 57.0

    steep = simulate(SimulationConfig(trajectory="aerial", poses=300, max_tilt_deg=89.0), seed=6)
    with np.errstate(all="ignore"):
        pitch = np.degrees(np.arcsin(np.clip(-steep.T_world_truth[:, 2, 0], -1, 1)))  # R[2,0] = -sin(pitch)
    assert np.abs(pitch).max() > 87.0


# ------------------------------------------------------------------------------ map and detection


def test_default_grid_sees_like_the_real_file():
    dataset = simulate(SimulationConfig(), seed=0)
    per_pose = np.bincount(dataset.obs_pose_index, minlength=dataset.num_poses)
    assert 3.4 < per_pose.mean() < 3.8  # the real file: 3.58
    assert per_pose[0] == 0 and 1 <= np.count_nonzero(per_pose == 0) <= 20
    assert 60 < dataset.landmark_ids.size < 250  # the real file: 144
    assert set(dataset.obs_true_landmark.tolist()) == set(dataset.landmark_ids.tolist())  # all seen
    u = dataset.obs_z[:, 0]
    assert -0.6 < u.min() < -0.3 and 1.3 < u.max() < 1.6  # the real file: -0.51..1.51
    landmark_height = dataset.landmark_xyz[:, 2]
    assert np.abs(landmark_height).max() <= sim.GRID_FLOOR_BAND_M


def test_visibility_rule_explains_the_real_files_detections(real_dataset_path):
    from camloc.g2o import read_g2o

    real = read_g2o(real_dataset_path)
    config = SimulationConfig()
    spec = sim.CameraSpec(real.cameras[0], None)
    observed = {(int(k), int(l)) for k, l in zip(real.obs_pose_index, real.obs_true_landmark)}
    visible = set()
    for k in range(1, real.num_poses):  # the real file observes nothing from its first pose
        _, p_camera = models.camera_points(real.T_world_truth[k], spec.camera.T_robot_camera, real.landmark_xyz)
        visible |= {(k, int(real.landmark_ids[j])) for j in np.flatnonzero(sim.visible(p_camera, spec, config))}
    assert observed <= visible
    assert len(visible - observed) <= 2  # one landmark sits at 2.0 m, on the boundary


def test_pixel_intrinsics_two_cameras_depth_range():
    config = SimulationConfig(trajectory="aerial", poses=200, intrinsics="pixel", cameras=2,
                              range_kind="depth", min_range=0.4, max_range=3.0)
    dataset = simulate(config, seed=12)
    u, v, depth = dataset.obs_z.T
    assert np.all((u >= -0.5) & (u <= 639.5) & (v >= -0.5) & (v <= 479.5))
    true_depth = _predicted(dataset)[:, 2]
    assert np.all((true_depth >= 0.4) & (true_depth <= 3.0))
    assert np.all(np.abs(depth - true_depth) < 6.0 / math.sqrt(1000.0))
    assert set(dataset.obs_camera.tolist()) == {0, 1}
    assert np.count_nonzero(dataset.obs_camera == 1) > 0.3 * dataset.num_observations
    backward_axis = dataset.cameras[1].T_robot_camera[:3, 2]  # camera z in the robot frame
    np.testing.assert_allclose(backward_axis, [-1.0, 0.0, 0.0], atol=1e-12)
    assert dataset.cameras[1].fx == 525.0 and dataset.cameras[1].cy == 239.5
    np.testing.assert_allclose(np.diag(dataset.obs_info[0]), [1.0, 1.0, 1000.0])  # 1 px default


def test_distance_range_bounds_the_distance_from_the_camera():
    dataset = simulate(SimulationConfig(trajectory="smooth3d", min_range=0.8, max_range=1.5, **EXACT), seed=3)
    distance = []
    for j in range(dataset.num_observations):
        camera = dataset.cameras[int(dataset.obs_camera[j])]
        u, v, depth = dataset.obs_z[j]
        ray = np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0])
        distance.append(depth * np.linalg.norm(ray))
        assert np.hypot(ray[0], ray[1]) <= 1.0 + 1e-9  # the 45 deg cone
    assert 0.8 - 1e-9 <= min(distance) and max(distance) <= 1.5 + 1e-9


def test_clutter_and_outlier_fractions():
    config = SimulationConfig(trajectory="smooth3d", poses=400, clutter_fraction=0.1, outlier_fraction=0.05)
    labelled = simulate_labelled(config, seed=7)
    dataset = labelled.dataset
    assert abs(labelled.is_clutter.mean() - 0.1) < 0.005
    real = ~labelled.is_clutter
    assert abs(labelled.is_outlier[real].mean() - 0.05) < 0.005
    assert not np.any(labelled.is_outlier & labelled.is_clutter)
    in_map = np.isin(dataset.obs_true_landmark, dataset.landmark_ids)
    np.testing.assert_array_equal(in_map, real)  # clutter ids are absent from the map, outliers keep theirs
    assert len(np.unique(dataset.obs_true_landmark[~real])) == np.count_nonzero(~real)
    assert not np.any(np.isin(dataset.obs_true_landmark, dataset.pose_ids))
    # Outliers are far from their landmark's prediction, the other detections are not.
    residual = (dataset.obs_z[real] - _predicted_rows(dataset, real)) * math.sqrt(1000.0)
    far = np.einsum("ij,ij->i", residual, residual) > 40.0  # chi2(3) > 40: p ~ 1e-8
    outlier = labelled.is_outlier[real]
    assert not np.any(far[~outlier])
    assert far[outlier].mean() > 0.9
    # Clutter lies in the visible range: depth 0.5 cos(45 deg)..2.0, u within the 45 deg cone.
    assert np.all((dataset.obs_z[~real, 2] > 0.35) & (dataset.obs_z[~real, 2] <= 2.0))
    assert np.all(np.abs(dataset.obs_z[~real, 0] - 0.5) <= 1.0)


def _predicted_rows(dataset, rows: np.ndarray) -> np.ndarray:
    keep = np.flatnonzero(rows)
    sub = dataclasses.replace(dataset, obs_pose_index=dataset.obs_pose_index[keep],
                              obs_camera=dataset.obs_camera[keep], obs_z=dataset.obs_z[keep],
                              obs_true_landmark=dataset.obs_true_landmark[keep], obs_kind=dataset.obs_kind[keep])
    return _predicted(sub)


def test_detection_probability_cap_and_dense_map():
    base = simulate(SimulationConfig(poses=300), seed=13)
    half = simulate(SimulationConfig(poses=300, detection_probability=0.5), seed=13)
    assert 0.42 < half.num_observations / base.num_observations < 0.58
    capped = simulate(SimulationConfig(poses=300, max_observations_per_pose=2), seed=13)
    assert np.bincount(capped.obs_pose_index).max() == 2
    dense = simulate(SimulationConfig(poses=300, dense=True), seed=13)
    np.testing.assert_array_equal(dense.truth_xyz, base.truth_xyz)
    assert 4.0 < dense.landmark_ids.size / base.landmark_ids.size < 6.0
    assert 4.0 < dense.num_observations / base.num_observations < 6.0
    explicit = simulate(SimulationConfig(poses=300, landmarks=50), seed=13)
    assert explicit.landmark_ids.size == 50


def test_ids_sources_and_tag_counts():
    dataset = simulate(SimulationConfig(poses=300, landmarks=1200, clutter_fraction=0.1), seed=1)
    assert dataset.pose_ids[0] == 10000  # above the 1200 landmark ids; clutter from 100000
    ids = [dataset.landmark_ids, dataset.pose_ids, np.setdiff1d(dataset.obs_true_landmark, dataset.landmark_ids)]
    all_ids = np.concatenate(ids)
    assert np.unique(all_ids).size == all_ids.size
    np.testing.assert_array_equal(np.diff(dataset.pose_ids), 1)
    assert dataset.source == "simulate(trajectory=grid, poses=300, landmarks=1200, clutter_fraction=0.1, seed=1)"
    assert dataset.tag_counts == {
        "PARAMS_CAMERACALIB": 1, "VERTEX_TRACKXYZ": dataset.landmark_ids.size, "VERTEX_SE3:QUAT": 300,
        "EDGE_SE3:QUAT": 299, "EDGE_PROJECT_DEPTH": dataset.num_observations,
    }
    np.testing.assert_array_equal(dataset.start_xyz, dataset.truth_xyz[0])
    assert np.all(np.diff(dataset.obs_pose_index) >= 0)


@pytest.mark.parametrize("options", [
    dict(poses=1), dict(clutter_fraction=1.0), dict(outlier_fraction=-0.1), dict(min_range=2.0, max_range=2.0),
    dict(cameras=5), dict(trajectory="spiral"), dict(landmarks=-1), dict(max_tilt_deg=91.0),
    dict(odometry_sigma_scale=-1.0), dict(dense=True, landmarks=10), dict(detection_probability=0.0),
    dict(region=1e300), dict(max_range=1e300), dict(odometry_sigma_translation=1e300),
    dict(odometry_sigma_rotation=0.5, odometry_sigma_scale=4.0), dict(observation_sigma_uv=1e300),
])
def test_bad_options_raise_a_config_error(options):
    with pytest.raises(ConfigError, match="simulation option"):
        SimulationConfig(**options)


# ------------------------------------------------------------------------------------------- CLI

BUNDLED = {  # camloc/data/README.md gives the same commands
    "grid-small.g2o": (SimulationConfig(), 3),
    "smooth3d-clutter.g2o": (SimulationConfig(trajectory="smooth3d", poses=200, clutter_fraction=0.1,
                                              outlier_fraction=0.02), 1),
    "pixel-2cam.g2o": (SimulationConfig(trajectory="aerial", poses=200, intrinsics="pixel", cameras=2), 2),
}


@pytest.mark.parametrize("name", sorted(BUNDLED))
def test_bundled_datasets_are_what_their_commands_generate(name):
    from camloc.g2o import read_g2o

    from camloc.bundled import bundled_dataset

    path = bundled_dataset(name)
    config, seed = BUNDLED[name]
    expected = simulate(config, seed=seed)
    read = read_g2o(path)
    for field_name, array in _arrays(expected).items():
        np.testing.assert_allclose(getattr(read, field_name), array, rtol=1e-12, atol=1e-12, err_msg=field_name)
    assert path.stat().st_size < 300_000


def test_cli_writes_a_file_that_reads_back_to_the_simulated_dataset(tmp_path):
    from typer.testing import CliRunner

    from camloc.cli.app import app
    from camloc.g2o import read_g2o

    path = tmp_path / "sim.g2o"
    result = CliRunner().invoke(app, ["simulate", "-o", str(path), "--trajectory", "smooth3d", "--poses", "60",
                                      "--cameras", "2", "--clutter-fraction", "0.1", "--seed", "4", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    expected = simulate_labelled(SimulationConfig(trajectory="smooth3d", poses=60, cameras=2, clutter_fraction=0.1),
                                 seed=4)
    assert summary["counts"]["observations"] == expected.dataset.num_observations
    assert summary["counts"]["clutter"] == int(expected.is_clutter.sum()) > 0
    read = read_g2o(path)
    for name, array in _arrays(expected.dataset).items():
        np.testing.assert_array_equal(getattr(read, name), array, err_msg=name)
    assert read.tag_counts == expected.dataset.tag_counts


@pytest.mark.parametrize("arguments", [
    ["--poses", "-3"], ["--clutter-fraction", "1"], ["--min-range", "2", "--max-range", "1"],
    ["--intrinsics", "fisheye"], ["--seed", "-1"], ["--max-range", "1e300"],
])
def test_cli_refuses_bad_options_with_exit_status_2(tmp_path, arguments):
    from typer.testing import CliRunner

    from camloc.cli.app import app

    path = tmp_path / "sim.g2o"
    result = CliRunner().invoke(app, ["simulate", "-o", str(path), *arguments])
    assert result.exit_code == 2
    assert "Traceback" not in result.output
    assert not path.exists()
