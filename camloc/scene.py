"""What a run needs and never changes, built once from the dataset and the configuration: the
map and its grid hash, the cameras, every observation's noise (as the estimate weighs it and as
association judges it), each observation as a camera-frame point, the cost of leaving it
unassigned, the odometry, the view limits and the consistency bounds, as the arrays the compiled
kernels take (``camloc.kernels.types.SceneArrays``). How association judges each observation, and
the candidate view, are computed as for the numpy localizer (``camloc.observation_space``)."""

from __future__ import annotations

import threading

import numpy as np

from camloc import measurement, sym3
from camloc.observation_space import ObservationNoise, candidate_distance, candidate_range, detection_range, landmark_rows, observation_noise, planar_range
from camloc.sensors import sensors_of
from camloc.measurement import observation_gates
from camloc.dataset import LANDMARK_MARKER, LANDMARK_POINT2, Dataset, observations_by_pose
from camloc.kernels.types import SceneArrays, Settings
from camloc.tails import chi2_quantile

def build_scene(dataset: Dataset, config, view_range: tuple[float, float, float] | None = None,
                null_cost_offset: float = 0.0) -> SceneArrays:
    """The run's fixed arrays for ``dataset`` under ``config`` (a ``LocalizerConfig``);
    ``view_range``: its ``candidate_range``, when the caller has it (a pixel-only file's estimate
    of it builds a k-d tree of the map); ``null_cost_offset``: ``observation_noise``'s."""
    from camloc.kernels.view import build_grid, view_cone_ball  # numba: imported where the compiled loop runs

    # numba's start in a fresh process (its registries, then a first kernel: about 0.5 s) goes on in
    # a thread while the observations' arrays are computed, whose numpy loops release the GIL; in a
    # process that has loaded the kernel there is nothing to start
    numba_start = None
    if not view_cone_ball.signatures:
        numba_start = threading.Thread(target=_load_first_kernel, args=(view_cone_ball,), name="camloc-numba-start")
        numba_start.start()
    # a row of the camera tables per sensor: a camera and the kind of its measurements, the kind
    # in the intrinsics' fifth column, where the kernels' camera model reads it
    sensors, obs_camera = sensors_of(dataset)
    cameras = [sensors[i] for i in range(len(sensors))]
    camera_K = np.array([(*c.intrinsics, float(c.kind)) for c in cameras], dtype=float).reshape(-1, 5)
    noise = observation_noise(dataset, config, null_cost_offset)
    true_index = landmark_rows(dataset.landmark_ids, dataset.obs_true_landmark)
    pose_obs, pose_obs_start = observations_by_pose(dataset)
    view = np.array(candidate_range(dataset, config) if view_range is None else view_range)
    # the beam's miss term, the planar range, the candidates' distance
    view = np.concatenate([view, detection_range(dataset, float(view[2])), [planar_range(dataset), candidate_distance(config)]])
    most_pairs = int(np.diff(pose_obs_start).max(initial=0))
    if numba_start is not None:
        numba_start.join()
    # cells of half the view's ball: a query visits about 4^3 of them, where cells of the ball's
    # size hold six times the ball's volume in their 3^3
    reach = view_cone_ball(np.zeros(3), np.array([0.0, 0.0, 1.0]), view[1], view[2])[1]
    if not np.any(~measurement.is_planar(dataset.obs_kind)) and view[5] > 0.0:
        reach = view[5]  # only a planar robot's own sensors: their range is the query's ball
    grid = build_grid(dataset.landmark_xyz, 0.5 * reach)
    return SceneArrays(
        landmark_table(dataset), landmark_sensor_kind(dataset), *grid,
        np.ascontiguousarray([c.T_robot_camera[:3, :3] for c in cameras], dtype=float).reshape(-1, 3, 3),
        np.ascontiguousarray([c.T_robot_camera[:3, 3] for c in cameras], dtype=float).reshape(-1, 3),
        camera_K, obs_camera,
        np.ascontiguousarray(dataset.obs_z, dtype=float),
        np.ascontiguousarray(dataset.obs_cov, dtype=float), np.ascontiguousarray(dataset.obs_info, dtype=float),
        np.ascontiguousarray(noise.cov), np.ascontiguousarray(noise.info), noise.log_det,
        noise.point, noise.point_cov, point_cov_inverse(noise, dataset.obs_kind), noise.log_det_point_cov,
        np.ascontiguousarray(noise.null_cost, dtype=float), true_index, pose_obs, pose_obs_start,
        np.ascontiguousarray(dataset.T_odometry, dtype=float).reshape(-1, 4, 4),
        np.ascontiguousarray(dataset.odom_cov, dtype=float).reshape(-1, 6, 6),
        view, chi2_quantile(np.maximum(np.arange(measurement.MAX_DIM * (most_pairs + 1) + 1), 1), 0.001),
        observation_gates(dataset.obs_kind, 1.0 - config.gate), measurement.dof_of(dataset.obs_kind),
    )


def landmark_table(dataset: Dataset) -> np.ndarray:
    """The map as the kernels read it: (L, 3) positions, and for a planar robot's map a fourth
    column, each marker's heading (0 for the others: only a marker's measurement reads it)."""
    xyz = np.ascontiguousarray(dataset.landmark_xyz, dtype=float)
    if not dataset.planar:
        return xyz
    return np.ascontiguousarray(np.column_stack([xyz, np.nan_to_num(dataset.landmark_heading, nan=0.0)]))


def landmark_sensor_kind(dataset: Dataset) -> np.ndarray:
    """(L,) int64 the planar kind that observes each landmark (``measurement.POINT2`` for a
    ``LANDMARK_POINT2``, ``MARKER`` for a ``LANDMARK_MARKER``), -1 for a camera's (a 3-D point or
    a tag): a sensor's candidates are of its kind (``kernels.view.sensor_candidates``)."""
    kinds = np.asarray(dataset.landmark_kind, dtype=np.int64)
    out = np.full(kinds.shape, -1, np.int64)
    out[kinds == LANDMARK_POINT2] = measurement.POINT2
    out[kinds == LANDMARK_MARKER] = measurement.MARKER
    return out


def _load_first_kernel(view_cone_ball) -> None:
    """Call a kernel once, with arguments of the types ``build_scene`` passes it."""
    try:
        view_cone_ball(np.zeros(3), np.array([0.0, 0.0, 1.0]), np.float64(1.0), np.float64(0.5))
    except Exception:  # noqa: BLE001 (build_scene's own call of it raises the error where it is reported)
        pass


def point_cov_inverse(noise: ObservationNoise, kinds: np.ndarray) -> np.ndarray:
    """(K, 3, 3) the inverses of the observations' point covariances; zeros where there is no
    point (a sensor that measures no range)."""
    inverse = np.zeros_like(noise.point_cov)
    ranged = measurement.judged_as_point(kinds)
    if ranged.any():
        inverse[ranged] = sym3.inverse(noise.point_cov[ranged])
    return inverse


def build_settings(config, null_cost_offset: float = 0.0) -> Settings:
    """The kernels' settings of a ``LocalizerConfig`` (its gate is each observation's, at its
    dof: the scene's ``obs_gate``); ``null_cost_offset``: ``build_scene``'s."""
    from camloc.constants import MERGE_SIGMA, PARTIAL_BUDGET, POOL_GATE_FACTOR

    return Settings(
        int(config.iterations), bool(config.recheck.enabled), float(config.recheck.margin),
        float(config.recheck.steal_margin), float(config.recheck.ray_margin), float(config.beam.slip_inflation), int(config.beam.width),
        float(config.beam.delta), float(config.beam.branch_delta), MERGE_SIGMA, float(config.beam.slip_cost),
        PARTIAL_BUDGET, POOL_GATE_FACTOR, float(null_cost_offset),
    )


