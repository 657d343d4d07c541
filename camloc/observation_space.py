"""Each observation as association judges it, and the view it is looked for in: computed once per
run from the dataset and the configuration, the same for both engines (the numpy localizer,
``camloc.localizer``, and the compiled loop's arrays, ``camloc.scene``), so that neither reaches
into the other for them.

- ``noise_floored``: the noise association judges an observation by (a floor where the file
  claims it is near exact);
- ``clutter_null_cost``: what leaving an observation unassigned costs (clutter uniform over the
  measured volume);
- ``observation_noise``: both of those for every observation, and the observation as a
  camera-frame point with its covariance;
- ``candidate_range``: the depths and angle within which a camera's candidate landmarks lie;
- ``landmark_rows``: map rows of landmark ids;
- ``with_map_uncertainty``: the observations' noise widened by a map prior's (the beam's pass over
  a map held as a prior).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, replace

import numpy as np

from camloc import measurement, models, sym3
from camloc.constants import MAX_HALF_ANGLE_DEG
from camloc.dataset import Dataset

# Observations are turned into points in chunks: (K, 3, 3) temporaries add up on large files.
POINT_CHUNK = 32768


# Observations that claim standard deviations below EXACT_CLAIM on u, v and depth (relative to
# the focal length and to the depth) are judged by association as NOISE_FLOOR: see ``noise_floored``.
EXACT_CLAIM = 1e-5
NOISE_FLOOR = 1e-3


def noise_floored(
    uvd: np.ndarray, cov: np.ndarray, info: np.ndarray, fx: np.ndarray, fy: np.ndarray, kinds: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Observation covariances (K, 3, 3) and their inverses as association judges them: those
    that claim to be exact (standard deviations of u, v and depth all below ``EXACT_CLAIM`` x
    (fx, fy, depth)) raised to ``NOISE_FLOOR`` x (fx, fy, depth) on the diagonal, half a pixel at
    a focal length of 500 and a millimetre at a metre. Returns ``(cov, info)`` themselves when no
    observation claims to be exact: real sensors' noise is far above the claim (the real file's
    3,000 times), and is left as it is.

    A pair's prediction carries its linearization's error, second order in the prior's spread.
    Noise-free simulated data (information 1e12) judges that error thousands of standard
    deviations out: right pairs fail the gate, leaving an observation unassigned looks cheaper
    than any pair, and the association is left to chance (the beam's recall fell to 0.34 on
    such data). Only association uses the floor: the filter still weighs each pair by the
    file's own noise, and stays as exact as the data.

    uvd : (K, 3) the measurements (``camloc.measurement``'s layout: the third row is the depth, its
    inverse, or inert); cov, info : (K, 3, 3) the file's covariances and information; fx, fy :
    (K,) each observation's camera's focal lengths; kinds : (K,) the measurements' kinds (None:
    depth). The third row is judged relative to itself (depth, or inverse depth); an inert row
    (a pixel's) is never floored.
    """
    scale = np.column_stack([np.abs(fx), np.abs(fy), np.abs(uvd[:, 2])]) if uvd.size else np.zeros((0, 3))
    variance = np.diagonal(cov, axis1=1, axis2=2)
    inert = measurement.inert_rows(kinds) if kinds is not None else np.zeros(variance.shape, bool)
    scale = np.where(inert, 0.0, scale)  # the floor adds nothing there
    exact = np.all((variance < (EXACT_CLAIM * scale) ** 2) | inert, axis=1)
    if not np.any(exact):
        return cov, info
    floored = cov.copy()
    floored[exact, :, :] += np.eye(3) * np.maximum((NOISE_FLOOR * scale[exact]) ** 2 - variance[exact], 0.0)[:, None, :]
    return floored, sym3.inverse(floored)


def clutter_null_cost(uvd: np.ndarray, cov: np.ndarray, log_det_cov: np.ndarray, camera: np.ndarray,
                      kinds: np.ndarray | None = None) -> np.ndarray:
    """Cost (K,) of explaining each observation as clutter rather than as a landmark.

    Clutter is taken as uniform over the box a sensor's measurements span in their dof
    dimensions (an image area for a pixel, a volume of (u, v, depth) or (u, v, 1/depth)), of
    measure V, so in the units of a pair's cost ``d^2 + ln det S - ln det R`` (twice the negative
    log-likelihood, less ``ln det 2 pi R`` over the dof rows) an unassigned observation costs
    ``2 ln V - ln det(2 pi R)``. (The inert row of ``camloc.measurement``'s layout has unit
    variance: it adds nothing to ln det R.)

    Parameters
    ----------
    uvd : (K, 3) measurements; cov : (K, 3, 3) their covariances and log_det_cov (K,) ln det of
    each (``sym3.log_abs_det``); camera : (K,) camera ids; kinds : (K,) their kinds (None: depth).
    """
    cost = np.zeros(uvd.shape[0])
    kinds = np.zeros(uvd.shape[0], np.int64) if kinds is None else np.asarray(kinds, np.int64)
    for camera_id in np.unique(camera):
        for kind in np.unique(kinds[camera == camera_id]):
            mine = (camera == camera_id) & (kinds == kind)
            dof = measurement.KINDS[int(kind)].dof
            span = np.ptp(uvd[mine, :dof], axis=0)
            sigma = np.sqrt(np.median(np.diagonal(cov[mine], axis1=1, axis2=2)[:, :dof], axis=0))
            log_volume = np.log(np.maximum(span, 6.0 * sigma)).sum()  # a few sigmas at least
            cost[mine] = 2.0 * log_volume - (dof * np.log(2.0 * np.pi) + log_det_cov[mine])  # ln det(2 pi R)
    return cost


@dataclass(frozen=True)
class ObservationNoise:
    """Every observation (K of them) as association judges it: ``cov``, ``info`` (K, 3, 3) the
    file's noise raised to a floor where it claims to be near exact (``noise_floored``;
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


def observation_noise(dataset: Dataset, config, null_cost_offset: float = 0.0) -> ObservationNoise:
    """The ``ObservationNoise`` of ``dataset``'s observations under ``config`` (its ``null_cost``,
    or clutter uniform over the measured volume where that is None), the null cost lowered by
    ``null_cost_offset`` (``localizer.LACKING_NULL_OFFSET``: a map that lacks landmarks). An observation whose sensor
    measures no range (a pixel: a ray) has no point: its point and point covariance are zeros
    (a singular spread, which fits nothing; its pair is judged in its own coordinates), as is a
    disparity's (``measurement.judged_as_point``)."""
    K = dataset.num_observations
    intrinsics = observation_intrinsics(dataset)
    cov, info = noise_floored(dataset.obs_z, dataset.obs_cov, dataset.obs_info, intrinsics[:, 0], intrinsics[:, 1],
                                          dataset.obs_kind)
    point, point_cov = np.zeros((K, 3)), np.zeros((K, 3, 3))
    rows = np.flatnonzero(measurement.judged_as_point(dataset.obs_kind))
    for start in range(0, rows.size, POINT_CHUNK):  # in chunks: (K, 3, 3) temporaries add up
        part = rows[start:start + POINT_CHUNK]
        point[part], point_cov[part] = models.measured_points(dataset.obs_z[part], cov[part], intrinsics[part].T)
    log_det = sym3.log_abs_det(cov) if K else np.zeros(0)
    if config.null_cost is None:
        null_cost = clutter_null_cost(dataset.obs_z, cov, log_det, dataset.obs_camera, dataset.obs_kind)
    else:
        null_cost = np.full(K, float(config.null_cost))
    null_cost = null_cost - null_cost_offset
    ranged = measurement.judged_as_point(dataset.obs_kind)
    log_det_point_cov = np.zeros(K)
    if ranged.any():
        log_det_point_cov[ranged] = sym3.log_abs_det(point_cov[ranged])
    return ObservationNoise(cov, info, log_det, point, point_cov, log_det_point_cov, null_cost)


# A pixel's point for ``with_map_uncertainty``: at this fraction of the view's typical reach.
PIXEL_PRIOR_DEPTH = 1.0


def with_map_uncertainty(dataset: Dataset, sigma: float) -> Dataset:
    """``dataset`` with each camera observation's covariance widened by what a landmark known to
    ``sigma`` metres per axis adds to it: ``R + sigma^2 J J'``, J = d z / d p_camera at the point
    the observation implies (an isotropic landmark covariance is the same in every frame, so the
    pose's rotation drops out and no estimate is needed).

    Why: under ``--map prior`` the beam decides the map's pairs on the map as given; judged
    against the map as exact, a landmark moved by a few sigma fails every gate and its
    observations are left out (the mapping localizer then finds it late, if at all). With the
    map's own uncertainty in the noise, its gates are those of a landmark known to ``sigma``.

    A pixel measures no depth: its point is taken at the typical reach of the view
    (``pixel_reach``; half of it widened the gates too far: more wrong pairs). A planar robot's point
    (point2, a point of the floor known to ``sigma`` in x and y) adds ``sigma^2`` to its x and y
    (the rotation drops out too), a marker also ``sigma^2`` to its heading (``sigma`` radians), a
    tag's orientation ``sigma^2`` per axis (a tag's orientation is held to ``sigma`` radians under
    a prior, as a marker's heading: isotropic, so the same in the tag's frame).
    """
    floor = np.flatnonzero(np.isin(dataset.obs_kind, measurement.PLANAR_KINDS))
    widened = np.flatnonzero(np.isin(dataset.obs_kind, measurement.CAMERA_KINDS))
    turned = np.flatnonzero(dataset.obs_kind == measurement.TAG_ROTATION)
    if widened.size == 0 and floor.size == 0:
        return dataset
    cov, info = dataset.obs_cov.copy(), dataset.obs_info.copy()
    cov[turned] += sigma**2 * np.eye(3)
    cov[floor, 0, 0] += sigma**2
    cov[floor, 1, 1] += sigma**2
    cov[floor, 2, 2] += np.where(dataset.obs_kind[floor] == measurement.MARKER, sigma**2, 0.0)  # a marker's heading: sigma radians
    intrinsics = observation_intrinsics(dataset)
    for kind in np.unique(dataset.obs_kind[widened]).tolist():
        rows = widened[dataset.obs_kind[widened] == kind]
        z = dataset.obs_z[rows]
        if kind == measurement.PIXEL:  # the ray's point at the typical reach, back-projected as a depth
            depth = PIXEL_PRIOR_DEPTH * pixel_reach(dataset, _widest_ray(dataset), typical=True)
            z, kind_of_z = np.column_stack([z[:, :2], np.full(rows.size, depth)]), measurement.DEPTH
        else:
            kind_of_z = kind
        points, _ = measurement.back_project(z, intrinsics[rows].T, kind_of_z)
        points[:, 2] = np.maximum(points[:, 2], measurement.MIN_POINT_DEPTH)
        J = measurement.projection_jacobian(points, intrinsics[rows].T, kind)
        cov[rows] += sigma**2 * J @ np.swapaxes(J, 1, 2)
    widened = np.union1d(np.union1d(widened, floor), turned)
    info[widened] = sym3.inverse(cov[widened])
    return replace(dataset, obs_cov=cov, obs_info=info)


def observation_intrinsics(dataset: Dataset) -> np.ndarray:
    """(K, 4) each observation's camera's fx, fy, cx, cy; (1, 1, 0, 0) for a planar kind's, which
    no camera makes (its x and y are metres in the robot frame)."""
    camera_ids = np.array(sorted(dataset.cameras), dtype=np.int64)
    camera_K = np.array([(dataset.cameras[int(c)].fx, dataset.cameras[int(c)].fy, dataset.cameras[int(c)].cx,
                          dataset.cameras[int(c)].cy) for c in camera_ids], dtype=float).reshape(-1, 4)
    intrinsics = np.tile([1.0, 1.0, 0.0, 0.0], (dataset.num_observations, 1))
    by_camera = np.isin(dataset.obs_camera, camera_ids)
    if np.any(by_camera):
        intrinsics[by_camera] = camera_K[np.searchsorted(camera_ids, dataset.obs_camera[by_camera])]
    return intrinsics


def planar_range(dataset: Dataset) -> float:
    """How far a planar robot's own sensor (the planar kinds') sees: 1.25 x the farthest measured
    landmark + 0.5 m, as ``candidate_range`` takes a camera's depth; 0 without such observations."""
    mine = measurement.is_planar(dataset.obs_kind)
    if not np.any(mine):
        return 0.0
    return 1.25 * float(np.hypot(dataset.obs_z[mine, 0], dataset.obs_z[mine, 1]).max()) + 0.5


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
        if reach_unmeasured(dataset):
            max_depth = 1.25 * pixel_reach(dataset, max_angle) + 0.5
        elif depth.size:
            max_depth = 1.25 * float(depth.max()) + 0.5
        else:
            max_depth = 10.0
    return min_depth, max_depth, max_angle


def candidate_distance(config) -> float:
    """How far from a camera's centre its candidates may lie (``ViewOptions.max_distance``),
    metres; inf where unset."""
    return float(config.view.max_distance) if config.view.max_distance is not None else float("inf")


def reach_unmeasured(dataset: Dataset) -> bool:
    """Whether nothing in ``dataset`` says how far its cameras see: no observation measures range
    and some camera's is a ray (``candidate_range`` guesses the reach from the map's density,
    ``localizer._with_learned_reach`` learns it from the run)."""
    kinds = dataset.obs_kind
    return bool(np.any(measurement.is_ray(kinds))) and not bool(np.any(measurement.measures_range(kinds)))


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
    radius = neighbour_radius(dataset.landmark_xyz)
    density = DENSITY_NEIGHBOURS / (4.0 / 3.0 * np.pi * max(radius, 1e-9) ** 3)
    by_camera = np.isin(dataset.obs_kind, measurement.CAMERA_KINDS)  # a planar robot's own sensor has no view cone, a tag's orientation no ray
    camera, pose_index = dataset.obs_camera[by_camera], dataset.obs_pose_index[by_camera]
    per_view = np.bincount(pose_index * (int(camera.max()) + 1) + camera)
    counts = per_view[per_view > 0]
    busy = float(counts.mean()) if typical else float(np.quantile(counts, 0.9))
    tan = np.tan(min(max_angle, np.radians(80.0)))
    return float((3.0 * busy / (density * np.pi * tan * tan)) ** (1.0 / 3.0))


# The last map's ``neighbour_radius``: ((its shape, its digest), the radius), read and replaced
# whole (threads of one process may localize different maps).
_LAST_RADIUS: list = [None]


def neighbour_radius(landmark_xyz: np.ndarray) -> float:
    """The median distance from a landmark to its ``DENSITY_NEIGHBOURS``-th nearest (a k-d tree's
    query of every landmark), remembered for the last map by its contents: a run asks five times
    (the view's reach, the prior's depth, the detection range), and on the 20k pixel world's 32,306
    landmarks each asking was 0.06 s, 3% of the run's CPU (docs/performance.md, 2026-12-07)."""
    xyz = np.ascontiguousarray(landmark_xyz, dtype=float)
    key = (xyz.shape, hashlib.blake2b(xyz.tobytes(), digest_size=16).digest())
    last = _LAST_RADIUS[0]
    if last is None or last[0] != key:
        from scipy.spatial import cKDTree

        distance = cKDTree(xyz).query(xyz, DENSITY_NEIGHBOURS + 1)[0][:, -1]
        last = (key, float(np.median(distance)))
        _LAST_RADIUS[0] = last
    return last[1]


# A camera surely detects a landmark it sees between these fractions of its typical reach.
DETECT_NEAR, DETECT_FAR = 0.35, 1.2


def detection_range(dataset: Dataset, max_angle: float) -> tuple[float, float]:
    """(low, high) distances from a pixel camera within which it surely detects a landmark near
    one of its rays (the beam's miss term: ``camloc.beam_expansion.PoseExpansion.expected``), or
    (0, 0) for a file without pixel observations. The reach at which the view cone, in the map's
    median density, holds as many landmarks as a pose reports on average (``pixel_reach``): the
    cone's half-angle is the widest observed ray's plus 10 deg, wider than the camera's, so this
    falls short of the true range (1.2-1.6 m on simulated worlds of range 2 m); the range counted
    as sure goes to 1.2 times that (1.4-1.9 m): a landmark beyond the true range counted as surely
    seen charges the right explanation."""
    if not np.any(measurement.is_ray(dataset.obs_kind)):
        return 0.0, 0.0  # no camera's ray (a planar robot's own sensor measures range)
    reach = pixel_reach(dataset, max_angle, typical=True)
    return DETECT_NEAR * reach, DETECT_FAR * reach


def _widest_ray(dataset: Dataset) -> float:
    """The widest observed ray's angle to its camera's axis + 10 deg (at most 89), radians."""
    if dataset.num_observations == 0:
        return float(np.radians(60.0))
    tan = np.zeros((dataset.num_observations, 2))
    if not dataset.cameras:
        return float(np.radians(60.0))
    for camera_id, camera in dataset.cameras.items():
        mine = (dataset.obs_camera == camera_id) & np.isin(dataset.obs_kind, measurement.CAMERA_KINDS)  # image coordinates
        tan[mine, 0] = (dataset.obs_z[mine, 0] - camera.cx) / camera.fx
        tan[mine, 1] = (dataset.obs_z[mine, 1] - camera.cy) / camera.fy
    widest = float(np.degrees(np.arctan(np.hypot(tan[:, 0], tan[:, 1])).max()))
    return float(np.radians(min(widest + 10.0, MAX_HALF_ANGLE_DEG)))
