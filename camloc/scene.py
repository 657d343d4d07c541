"""What a run needs and never changes, built once from the dataset and the configuration: the
map and its grid hash, the cameras, every observation's noise (as the estimate weighs it and as
association judges it), each observation as a camera-frame point, the cost of leaving it
unassigned, the odometry, the view limits and the consistency bounds, as the arrays the compiled
kernels take (``camloc.kernels.types.SceneArrays``)."""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from camloc import association, measurement, models, sym3
from camloc.sensors import sensors_of
from camloc.measurement import observation_gates
from camloc.dataset import Dataset
from camloc.kernels.types import SceneArrays, Settings
from camloc.tails import chi2_quantile

# Observations are turned into points in chunks: (K, 3, 3) temporaries add up on large files.
POINT_CHUNK = 32768


def build_scene(dataset: Dataset, config, view_range: tuple[float, float, float] | None = None) -> SceneArrays:
    """The run's fixed arrays for ``dataset`` under ``config`` (a ``LocalizerConfig``);
    ``view_range``: its ``candidate_range``, when the caller has it (a pixel-only file's estimate
    of it builds a k-d tree of the map)."""
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
    noise = observation_noise(dataset, config)
    true_index = landmark_rows(dataset.landmark_ids, dataset.obs_true_landmark)
    pose_obs = np.argsort(dataset.obs_pose_index, kind="stable").astype(np.int64)
    pose_obs_start = np.searchsorted(dataset.obs_pose_index[pose_obs], np.arange(dataset.num_poses + 1)).astype(np.int64)
    view = np.array(candidate_range(dataset, config) if view_range is None else view_range)
    view = np.concatenate([view, detection_range(dataset, float(view[2]))])  # the beam's miss term
    most_pairs = int(np.diff(pose_obs_start).max(initial=0))
    if numba_start is not None:
        numba_start.join()
    # cells of half the view's ball: a query visits about 4^3 of them, where cells of the ball's
    # size hold six times the ball's volume in their 3^3
    grid = build_grid(dataset.landmark_xyz, 0.5 * view_cone_ball(np.zeros(3), np.array([0.0, 0.0, 1.0]), view[1], view[2])[1])
    return SceneArrays(
        np.ascontiguousarray(dataset.landmark_xyz, dtype=float), *grid,
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


def _load_first_kernel(view_cone_ball) -> None:
    """Call a kernel once, with arguments of the types ``build_scene`` passes it."""
    try:
        view_cone_ball(np.zeros(3), np.array([0.0, 0.0, 1.0]), np.float64(1.0), np.float64(0.5))
    except Exception:  # noqa: BLE001 (build_scene's own call of it raises the error where it is reported)
        pass


@dataclass(frozen=True)
class ObservationNoise:
    """Every observation (K of them) as association judges it: ``cov``, ``info`` (K, 3, 3) the
    file's noise raised to a floor where it claims to be near exact (``association.noise_floored``;
    the estimate keeps the file's own) and ``log_det`` (K,) ln det cov; the observation as a
    camera-frame point (K, 3) with ``point_cov`` (K, 3, 3) and its ln det (K,); and ``null_cost`` (K,),
    what leaving it unassigned costs."""

    cov: np.ndarray
    info: np.ndarray
    log_det: np.ndarray
    point: np.ndarray
    point_cov: np.ndarray
    log_det_point_cov: np.ndarray
    null_cost: np.ndarray


def landmark_rows(landmark_ids: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """(n,) int64 the row of each of ``ids`` (n,) in ``landmark_ids`` (L,), -1 where it has none."""
    order = np.argsort(landmark_ids, kind="stable")
    sorted_ids = np.asarray(landmark_ids)[order]
    at = np.minimum(np.searchsorted(sorted_ids, ids), max(sorted_ids.size - 1, 0))
    found = (sorted_ids[at] == ids) if sorted_ids.size else np.zeros(np.shape(ids), bool)
    return np.where(found, order[at] if sorted_ids.size else -1, -1).astype(np.int64)


def observation_noise(dataset: Dataset, config) -> ObservationNoise:
    """The ``ObservationNoise`` of ``dataset``'s observations under ``config`` (its ``null_cost``,
    or clutter uniform over the measured volume where that is None). An observation whose sensor
    measures no range (a pixel: a ray) has no point: its point and point covariance are zeros
    (a singular spread, which fits nothing; its pair is judged in its own coordinates), as is a
    disparity's (``measurement.judged_as_point``)."""
    camera_ids = np.array(sorted(dataset.cameras), dtype=np.int64)
    camera_K = np.array([(dataset.cameras[int(c)].fx, dataset.cameras[int(c)].fy, dataset.cameras[int(c)].cx,
                          dataset.cameras[int(c)].cy) for c in camera_ids], dtype=float).reshape(-1, 4)
    K = dataset.num_observations
    intrinsics = camera_K[np.searchsorted(camera_ids, dataset.obs_camera)] if K else camera_K[:0]
    cov, info = association.noise_floored(dataset.obs_z, dataset.obs_cov, dataset.obs_info, intrinsics[:, 0], intrinsics[:, 1],
                                          dataset.obs_kind)
    point, point_cov = np.zeros((K, 3)), np.zeros((K, 3, 3))
    rows = np.flatnonzero(measurement.judged_as_point(dataset.obs_kind))
    for start in range(0, rows.size, POINT_CHUNK):  # in chunks: (K, 3, 3) temporaries add up
        part = rows[start:start + POINT_CHUNK]
        point[part], point_cov[part] = models.measured_points(dataset.obs_z[part], cov[part], intrinsics[part].T)
    log_det = sym3.log_abs_det(cov) if K else np.zeros(0)
    if config.null_cost is None:
        null_cost = association.clutter_null_cost(dataset.obs_z, cov, log_det, dataset.obs_camera, dataset.obs_kind)
    else:
        null_cost = np.full(K, float(config.null_cost))
    ranged = measurement.judged_as_point(dataset.obs_kind)
    log_det_point_cov = np.zeros(K)
    if ranged.any():
        log_det_point_cov[ranged] = sym3.log_abs_det(point_cov[ranged])
    return ObservationNoise(cov, info, log_det, point, point_cov, log_det_point_cov, null_cost)


def point_cov_inverse(noise: ObservationNoise, kinds: np.ndarray) -> np.ndarray:
    """(K, 3, 3) the inverses of the observations' point covariances; zeros where there is no
    point (a sensor that measures no range)."""
    inverse = np.zeros_like(noise.point_cov)
    ranged = measurement.judged_as_point(kinds)
    if ranged.any():
        inverse[ranged] = sym3.inverse(noise.point_cov[ranged])
    return inverse


def build_settings(config) -> Settings:
    """The kernels' settings of a ``LocalizerConfig`` (its gate is each observation's, at its
    dof: the scene's ``obs_gate``)."""
    from camloc.kernels.beam_settings import MERGE_SIGMA, PARTIAL_BUDGET, POOL_GATE_FACTOR

    return Settings(
        int(config.iterations), bool(config.recheck.enabled), float(config.recheck.margin),
        float(config.recheck.steal_margin), float(config.beam.slip_inflation), int(config.beam.width),
        float(config.beam.delta), float(config.beam.branch_delta), MERGE_SIGMA, float(config.beam.slip_cost),
        PARTIAL_BUDGET, POOL_GATE_FACTOR,
    )


def candidate_range(dataset: Dataset, config) -> tuple[float, float, float]:
    """(min_depth, max_depth, max_angle_rad) from the config, or from the data where unset:
    depth up to 1.25 x the largest measured + 0.5 m, the widest observed ray + 10 deg (at most 89).
    A pixel measures no depth: in a file where no observation measures range, the largest depth
    is estimated from the map instead (``pixel_reach``)."""
    ranged = measurement.measures_range(dataset.obs_kind)
    measured = [measurement.depth_of(dataset.obs_z[dataset.obs_kind == kind], int(kind))
                for kind in np.unique(dataset.obs_kind[ranged])]
    depth = np.concatenate(measured) if measured else np.zeros(0)
    view = config.view
    min_depth = view.min_depth if view.min_depth is not None else 0.0
    max_depth = view.max_depth
    max_angle = float(np.radians(view.max_angle_deg)) if view.max_angle_deg is not None else _widest_ray(dataset)
    if max_depth is None:
        if depth.size:
            max_depth = 1.25 * float(depth.max()) + 0.5
        elif dataset.num_observations:
            max_depth = 1.25 * pixel_reach(dataset, max_angle) + 0.5
        else:
            max_depth = 10.0
    return min_depth, max_depth, max_angle


# The k-th nearest neighbour that measures the map's local density (``pixel_reach``).
DENSITY_NEIGHBOURS = 8


def pixel_reach(dataset: Dataset, max_angle: float, *, typical: bool = False) -> float:
    """The depth within which a camera's view cone holds, in the map's median local density, as
    many landmarks as its busiest tenth of poses report (pixel-only files: no depth says how far
    a camera sees, and a ray through a dense map meets many landmarks; a view that reaches too
    far lets far ones along the ray pass the gate). The cone of half-angle a to depth r holds
    ``rho pi tan^2(a) r^3 / 3`` landmarks. ``typical``: as many as a pose reports on average
    instead (``detection_range``)."""
    L = dataset.landmark_xyz.shape[0]
    if L <= DENSITY_NEIGHBOURS:
        return float(np.linalg.norm(np.ptp(dataset.landmark_xyz, axis=0))) if L else 10.0
    from scipy.spatial import cKDTree

    distance = cKDTree(dataset.landmark_xyz).query(dataset.landmark_xyz, DENSITY_NEIGHBOURS + 1)[0][:, -1]
    radius = float(np.median(distance))
    density = DENSITY_NEIGHBOURS / (4.0 / 3.0 * np.pi * max(radius, 1e-9) ** 3)
    per_view = np.bincount(dataset.obs_pose_index * (int(dataset.obs_camera.max()) + 1) + dataset.obs_camera)
    counts = per_view[per_view > 0]
    busy = float(counts.mean()) if typical else float(np.quantile(counts, 0.9))
    tan = np.tan(min(max_angle, np.radians(80.0)))
    return float((3.0 * busy / (density * np.pi * tan * tan)) ** (1.0 / 3.0))


# A camera surely detects a landmark it sees between these fractions of its typical reach.
DETECT_NEAR, DETECT_FAR = 0.35, 1.2


def detection_range(dataset: Dataset, max_angle: float) -> tuple[float, float]:
    """(low, high) distances from a pixel camera within which it surely detects a landmark near
    one of its rays (the beam's miss term: ``camloc.beam.BeamSearch._expected``), or (0, 0) for a
    file without pixel observations. The reach at which the view cone, in the map's median
    density, holds as many landmarks as a pose reports on average (``pixel_reach``): the cone's
    half-angle is the widest observed ray's plus 10 deg, wider than the camera's, so this falls
    short of the true range (1.2-1.6 m on simulated worlds of range 2 m); the range counted as
    sure goes to 1.2 times that (1.4-1.9 m): a landmark beyond the true range counted as surely
    seen charges the right explanation."""
    if not np.any(~measurement.measures_range(dataset.obs_kind)):
        return 0.0, 0.0
    reach = pixel_reach(dataset, max_angle, typical=True)
    return DETECT_NEAR * reach, DETECT_FAR * reach


def _widest_ray(dataset: Dataset) -> float:
    """The widest observed ray's angle to its camera's axis + 10 deg (at most 89), radians."""
    if dataset.num_observations == 0:
        return float(np.radians(60.0))
    tan = np.zeros((dataset.num_observations, 2))
    for camera_id, camera in dataset.cameras.items():
        mine = dataset.obs_camera == camera_id
        tan[mine, 0] = (dataset.obs_z[mine, 0] - camera.cx) / camera.fx
        tan[mine, 1] = (dataset.obs_z[mine, 1] - camera.cy) / camera.fy
    widest = float(np.degrees(np.arctan(np.hypot(tan[:, 0], tan[:, 1])).max()))
    return float(np.radians(min(widest + 10.0, 89.0)))
