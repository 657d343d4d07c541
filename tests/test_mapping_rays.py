"""Pixel-only cameras with no map (camloc.slam_anchors, camloc.slam_rays): on a world built so that
a map pays (a robot driving three laps of a circle among landmarks it sees again on each lap),
the true association's estimate is far better than odometry alone, seed after seed; the compiled
and numpy runs agree; a track's clone leaves the state once the track is done; the covariance
stays symmetric positive semidefinite."""

import numpy as np
from camloc import geometry, measurement, metrics
from camloc.dataset import Camera, Dataset
from camloc.g2o import observation_cov_from_info, odometry_cov_from_info
from camloc.localizer import localize
from camloc.localizer_config import LocalizerConfig
from camloc.slam_run import MappingLocalizer

F, CX, CY = 500.0, 320.0, 240.0


def _circling(seed: int, laps: int = 3, per_lap: int = 36, sigma_t: float = 0.01, sigma_r: float = 0.01) -> Dataset:
    """A robot driving ``laps`` laps of a circle of 1 m radius (``per_lap`` poses a lap) with two
    pixel-only cameras (one ahead, one out to the right, 1 px noise, f = 500), 36 landmarks on a
    cylinder of 3 m radius around it, odometry noise ``sigma_t`` m and ``sigma_r`` rad per step
    and axis. No map."""
    rng = np.random.default_rng(seed)
    n = laps * per_lap
    angle = 2 * np.pi * np.arange(n) / per_lap
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = np.column_stack([np.cos(angle), np.sin(angle), np.zeros(n)])
    T[:, :3, :3] = [geometry.so3_exp(np.array([0.0, 0.0, a + np.pi / 2])) for a in angle]
    around = 2 * np.pi * np.arange(36) / 36
    landmarks = np.column_stack([3 * np.cos(around), 3 * np.sin(around), rng.uniform(-0.5, 0.5, 36)])
    look = {0: np.radians([-90.0, 0.0, -90.0]), 1: np.radians([-90.0, 0.0, 180.0])}  # camera z along x, along -y
    cameras = {c: Camera(id=c, translation=np.zeros(3), quat_xyzw=geometry.euler_to_quat(rpy), fx=F, fy=F, cx=CX, cy=CY)
               for c, rpy in look.items()}
    pose_of, camera_of, z, true_id = [], [], [], []
    for k in range(n):
        for c, camera in cameras.items():
            R_c = geometry.quat_to_matrix(camera.quat_xyzw)
            p = (landmarks - T[k, :3, 3]) @ T[k, :3, :3] @ R_c
            uv = F * p[:, :2] / p[:, 2:3] + [CX, CY]
            seen = (p[:, 2] > 0.3) & (np.abs(uv[:, 0] - CX) < CX) & (np.abs(uv[:, 1] - CY) < CY)
            for i in np.flatnonzero(seen).tolist():
                pose_of.append(k)
                camera_of.append(c)
                z.append(np.concatenate([uv[i] + rng.normal(size=2), [0.0]]))
                true_id.append(1000 + i)
    increments = np.linalg.inv(T[:-1]) @ T[1:]
    noise = rng.normal(size=(n - 1, 6)) * np.repeat([sigma_t, sigma_r], 3)
    odometry = increments.copy()
    for i in range(n - 1):
        odometry[i, :3, :3] = increments[i, :3, :3] @ geometry.so3_exp(noise[i, 3:])
        odometry[i, :3, 3] = increments[i, :3, 3] + noise[i, :3]
    K = len(z)
    obs_info = np.tile(measurement.padded_information(np.array([[1.0, 0.0, 1.0]]), measurement.PIXEL), (K, 1, 1))
    odom_info = np.tile(np.diag(1.0 / np.repeat([sigma_t, sigma_r], 3) ** 2), (n - 1, 1, 1))
    truth_xyz, truth_quat = geometry.pose_to_quat(T)
    odom_t, odom_q = geometry.pose_to_quat(odometry)
    return Dataset(
        source="circling", cameras=cameras, landmark_ids=np.zeros(0, np.int64), landmark_xyz=np.zeros((0, 3)),
        pose_ids=np.arange(n), start_xyz=truth_xyz[0], start_quat_xyzw=truth_quat[0],
        truth_xyz=truth_xyz, truth_quat_xyzw=truth_quat, odom_translation=odom_t, odom_quat_xyzw=odom_q,
        odom_info=odom_info, odom_cov=odometry_cov_from_info(odom_info), obs_pose_index=np.array(pose_of, np.int64),
        obs_camera=np.array(camera_of, np.int64), obs_z=np.array(z), obs_info=obs_info, obs_cov=observation_cov_from_info(obs_info),
        obs_true_landmark=np.array(true_id, np.int64), obs_kind=np.full(K, measurement.PIXEL, np.int64),
    )


def _rmse(xyz, truth):
    return float(np.sqrt(np.mean(np.sum((xyz - truth) ** 2, axis=1))))


_CONFIG = LocalizerConfig(map="none", association="oracle", initial_sigma_xyz=1e-4, initial_sigma_deg=1e-3)


def test_pixel_only_cameras_with_no_map_beat_odometry():
    """Seed after seed the estimate is well within odometry's error: the landmarks, seen again on
    each lap, hold the drift. (Before the clones, each landmark triangulated from past poses as if
    they were exact, the estimate was further from the truth than odometry on one of these seeds
    and its NEES was 51 and 89 on two; now 10-45, docs/performance.md.)"""
    ratios = []
    for seed in range(4):
        dataset = _circling(seed)
        result = localize(dataset, _CONFIG, engine="numpy")
        ratios.append(_rmse(result.estimate_xyz, dataset.truth_xyz) / _rmse(result.odometry_xyz, dataset.truth_xyz))
        assert result.summary["map"]["added"] == 36  # every landmark, once
        assert np.all(np.isfinite(metrics.run_nees(result)[1:]))
    assert max(ratios) < 0.6, ratios


def test_the_compiled_run_takes_the_same_rays_into_the_state():
    """Pixel-only, no map: the compiled steps (prediction, update) and the numpy ones give the same
    run (the rays' landmarks and clones enter through the same numpy code in both)."""
    dataset = _circling(0, laps=1)
    numpy_run = localize(dataset, _CONFIG, engine="numpy")
    compiled_run = localize(dataset, _CONFIG, engine="compiled")
    assert compiled_run.summary["timing"]["engine"] == "compiled update"
    assert np.allclose(numpy_run.estimate_xyz, compiled_run.estimate_xyz, atol=1e-8)
    assert np.allclose(numpy_run.landmark_map.xyz, compiled_run.landmark_map.xyz, atol=1e-8)


def test_a_clone_leaves_the_state_when_its_tracks_are_done():
    """Clones are only in the state while a track starts at their pose: never more than the window's,
    none left once the robot sees nothing new, and none is ever in the map."""
    dataset = _circling(1, laps=2)
    localizer = MappingLocalizer(dataset, _CONFIG, compiled=False)
    most = 0
    for k in range(dataset.num_poses):
        localizer.step(k)
        most = max(most, len(localizer.clones))
        assert set(localizer.clones) <= set(range(max(0, k - 40), k + 1))
    assert 0 < most
    assert len(localizer.clones) <= 2  # the second lap: every landmark known
    landmarks = localizer.estimated_map()
    assert np.all(landmarks.ids >= 0) and landmarks.ids.size == np.unique(dataset.obs_true_landmark).size


def test_the_state_stays_symmetric_positive_semidefinite():
    """With clones in it (three rows each, rigid: their covariance singular by construction) the
    state's covariance stays exactly symmetric and without a negative eigenvalue beyond rounding."""
    dataset = _circling(2, laps=1)
    localizer = MappingLocalizer(dataset, _CONFIG, compiled=False)
    for k in range(dataset.num_poses):
        localizer.step(k)
        P = localizer.P
        assert np.array_equal(P, P.T)
        assert np.linalg.eigvalsh(P).min() > -1e-9 * max(1.0, np.abs(P).max())
