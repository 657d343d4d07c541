"""The in-memory dataset: plain frozen dataclasses of numpy arrays, no parsing and no I/O.

Frames: ``world`` (the map), ``robot`` (the pose vertices), ``camera`` (x right, y down, z along
the optical axis). Odometry covariances are in (translation, rotation vector) of the increment's
right perturbation, already converted from g2o's quaternion-vector parametrization by
``camloc.g2o.odometry_cov_from_info``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from camloc import geometry, measurement

# What each landmark of the map is (``Dataset.landmark_kind``), by the record that gave it:
# a 3-D point (VERTEX_TRACKXYZ, seen by cameras), a point of the plane (VERTEX_XY, seen by point2
# observations) or a planar marker with a heading (VERTEX_MARKER_SE2, seen by marker observations).
LANDMARK_POINT3, LANDMARK_POINT2, LANDMARK_MARKER = 0, 1, 2
# a tag (VERTEX_TAG): a 3-D point, seen by cameras like a VERTEX_TRACKXYZ, with an orientation
LANDMARK_TAG = 3
# the landmark kind a planar robot's own sensor sees, by its measurement kind (a camera's: a 3-D point)
LANDMARK_OF_PLANAR_SENSOR = {measurement.POINT2: LANDMARK_POINT2, measurement.MARKER: LANDMARK_MARKER}


def landmark_kind_of(sensor_kind: int) -> int:
    """The kind of landmark (``Dataset.landmark_kind``) a measurement of ``sensor_kind`` sees."""
    return LANDMARK_OF_PLANAR_SENSOR.get(int(sensor_kind), LANDMARK_POINT3)


def on_the_floor(kind: np.ndarray) -> np.ndarray:
    """(L,) bool: which landmark kinds (L,) lie on the floor, without a height: floor points and
    markers (a camera's 3-D point and a tag's centre have one)."""
    return np.isin(kind, (LANDMARK_POINT2, LANDMARK_MARKER))


@dataclass(frozen=True)
class Camera:
    """A camera rigidly mounted on the robot.

    Attributes
    ----------
    id : the camera id used by observations.
    translation : (3,) camera origin in the robot frame, metres.
    quat_xyzw : (4,) unit quaternion of the camera orientation in the robot frame.
    fx, fy, cx, cy : intrinsics; ``u = fx x/z + cx``, ``v = fy y/z + cy``.
    """

    id: int
    translation: np.ndarray
    quat_xyzw: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def T_robot_camera(self) -> np.ndarray:
        """(4, 4) pose of the camera in the robot frame."""
        return geometry.pose_from_quat(self.translation, self.quat_xyzw)


@dataclass(frozen=True)
class Dataset:
    """Everything a g2o camera-localization file holds.

    N poses form a chain linked by N-1 odometry increments; K observations; L map landmarks.

    Attributes
    ----------
    source : the file the dataset came from (or a description for simulated data).
    cameras : cameras by id.
    landmark_ids : (L,) int64 ids of the known map.
    landmark_xyz : (L, 3) landmark positions in the world frame, metres.
    pose_ids : (N,) int64 pose ids in chain order.
    start_xyz, start_quat_xyzw : (3,), (4,) the known first pose, world frame.
    truth_xyz, truth_quat_xyzw : (N, 3), (N, 4) ground-truth poses, or None when the file does
        not give a vertex for every pose.
    odom_translation, odom_quat_xyzw : (N-1, 3), (N-1, 4) increment k is the pose k+1 in the
        frame of pose k.
    odom_info : (N-1, 6, 6) information exactly as in the file (g2o parametrization).
    odom_cov : (N-1, 6, 6) covariance of (translation, rotation vector).
    obs_pose_index : (K,) int64 index into ``pose_ids`` of the observing pose.
    obs_camera : (K,) int64 camera id.
    obs_z : (K, 3) the measurements, in ``camloc.measurement``'s layout: (u, v, depth), (u, v, 0)
        or (u, v, 1/depth) by ``obs_kind``.
    obs_info : (K, 3, 3) information as in the file (a pixel's inert third row: unit information,
        ``camloc.measurement``); obs_cov its inverse.
    obs_kind : (K,) int64 each observation's kind (``camloc.measurement``: DEPTH, PIXEL or
        DISPARITY), by the record that gave it.
    obs_true_landmark : (K,) int64 landmark id written in the file. Localizers must not read it;
        evaluators may, to score the association. Ids absent from the map are clutter.
    tag_counts : number of records per tag, unknown tags included.
    warnings : messages about the input that did not stop the reading.
    planar : a planar robot (g2o's 2-D records: ``VERTEX_SE2``, ``EDGE_SE2``): its poses and
        increments are stored lifted to 3-D (z = 0, a rotation about z), ``odom_info`` is the file's
        (N-1, 3, 3) information of (x, y, theta) and ``odom_cov`` the lifted (N-1, 6, 6) covariance
        of (translation, rotation vector), zero in z, roll and pitch (``planar.lifted_cov``).
    landmark_kind : (L,) int64 each landmark's kind (``LANDMARK_POINT3``, ``LANDMARK_POINT2``,
        ``LANDMARK_MARKER``); a planar landmark has z = 0.
    landmark_heading : (L,) a marker's heading in the world plane (radians), NaN for a point.
    landmark_quat_xyzw : (L, 4) a tag's orientation in the world (``LANDMARK_TAG``), NaN for others.
    obs_partner : (K,) int64 for a tag's orientation (``measurement.TAG_ROTATION``), the index of
        the observation of its position (the one before it); -1 for every other observation.
    """

    source: str
    cameras: dict[int, Camera]
    landmark_ids: np.ndarray
    landmark_xyz: np.ndarray
    pose_ids: np.ndarray
    start_xyz: np.ndarray
    start_quat_xyzw: np.ndarray
    truth_xyz: np.ndarray | None
    truth_quat_xyzw: np.ndarray | None
    odom_translation: np.ndarray
    odom_quat_xyzw: np.ndarray
    odom_info: np.ndarray
    odom_cov: np.ndarray
    obs_pose_index: np.ndarray
    obs_camera: np.ndarray
    obs_z: np.ndarray
    obs_info: np.ndarray
    obs_cov: np.ndarray
    obs_true_landmark: np.ndarray
    obs_kind: np.ndarray = None  # type: ignore[assignment]  (None: every observation is DEPTH)
    tag_counts: dict[str, int] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    planar: bool = False
    landmark_kind: np.ndarray = None  # type: ignore[assignment]  (None: every landmark a 3-D point)
    landmark_heading: np.ndarray = None  # type: ignore[assignment]  (None: no marker)
    landmark_quat_xyzw: np.ndarray = None  # type: ignore[assignment]  (None: no tag)
    obs_partner: np.ndarray = None  # type: ignore[assignment]  (None: no tag orientation)

    def __post_init__(self) -> None:
        if self.landmark_kind is None:
            object.__setattr__(self, "landmark_kind", np.zeros(len(self.landmark_ids), dtype=np.int64))
        if self.landmark_heading is None:
            object.__setattr__(self, "landmark_heading", np.full(len(self.landmark_ids), np.nan))
        if self.landmark_quat_xyzw is None:
            object.__setattr__(self, "landmark_quat_xyzw", np.full((len(self.landmark_ids), 4), np.nan))
        if self.obs_partner is None:
            object.__setattr__(self, "obs_partner", np.full(self.obs_z.shape[0], -1, dtype=np.int64))
        self._fit_defaults()

    def _fit_defaults(self) -> None:
        """A dataset replaced with another map or other observations (``dataclasses.replace``) keeps
        the per-landmark and per-observation arrays it had: where those hold only their defaults
        (3-D points, no tag orientation) they are made again at the new size; otherwise a size
        that does not fit is a ValueError."""
        L, K = len(self.landmark_ids), self.obs_z.shape[0]
        defaults = {
            "landmark_kind": (L, lambda: np.zeros(L, dtype=np.int64), lambda a: np.all(a == 0)),
            "landmark_heading": (L, lambda: np.full(L, np.nan), lambda a: np.all(np.isnan(a))),
            "landmark_quat_xyzw": (L, lambda: np.full((L, 4), np.nan), lambda a: np.all(np.isnan(a))),
            "obs_partner": (K, lambda: np.full(K, -1, dtype=np.int64), lambda a: np.all(a == -1)),
        }
        for name, (size, make, is_default) in defaults.items():
            value = getattr(self, name)
            if len(value) == size:
                continue
            if not is_default(value):
                raise ValueError(f"{name} has {len(value)} rows for {size}")
            object.__setattr__(self, name, make())
        if self.obs_kind is None:  # a dataset built by hand of depth observations only
            object.__setattr__(self, "obs_kind", np.zeros(self.obs_z.shape[0], dtype=np.int64))
        if len(self.obs_kind) != self.obs_z.shape[0]:
            raise ValueError(f"obs_kind has {len(self.obs_kind)} entries for {self.obs_z.shape[0]} observations")

    @property
    def num_poses(self) -> int:
        return int(self.pose_ids.shape[0])

    @property
    def num_observations(self) -> int:
        return int(self.obs_z.shape[0])

    @property
    def has_ground_truth(self) -> bool:
        return self.truth_xyz is not None

    @property
    def T_world_start(self) -> np.ndarray:
        """(4, 4) the known first pose."""
        return geometry.pose_from_quat(self.start_xyz, self.start_quat_xyzw)

    @property
    def T_world_truth(self) -> np.ndarray | None:
        """(N, 4, 4) ground-truth poses, or None."""
        if self.truth_xyz is None:
            return None
        return geometry.pose_from_quat(self.truth_xyz, self.truth_quat_xyzw)

    @property
    def T_odometry(self) -> np.ndarray:
        """(N-1, 4, 4) odometry increments ``T_k_k+1``."""
        return geometry.pose_from_quat(self.odom_translation, self.odom_quat_xyzw)


def observations_by_pose(dataset: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """The observations in pose order, (K,) int64 (within a pose, in the file's order), and where
    each pose's start in it, (N + 1,) int64: pose k's are ``order[bounds[k]:bounds[k + 1]]``."""
    order = np.argsort(dataset.obs_pose_index, kind="stable").astype(np.int64)
    bounds = np.searchsorted(dataset.obs_pose_index[order], np.arange(dataset.num_poses + 1)).astype(np.int64)
    return order, bounds


def first_poses(dataset: Dataset, count: int) -> Dataset:
    """``dataset`` cut to its first ``count`` poses: their odometry and observations, the whole
    map (a tag observation's partner renumbered with the observations kept)."""
    from dataclasses import replace

    count = max(1, min(int(count), dataset.num_poses))
    kept = dataset.obs_pose_index < count
    renumbered = np.cumsum(kept) - 1
    partner = np.where(dataset.obs_partner[kept] >= 0, renumbered[np.maximum(dataset.obs_partner[kept], 0)], -1)
    truth = (lambda a: None if a is None else a[:count])
    return replace(
        dataset, pose_ids=dataset.pose_ids[:count], truth_xyz=truth(dataset.truth_xyz), truth_quat_xyzw=truth(dataset.truth_quat_xyzw),
        odom_translation=dataset.odom_translation[:count - 1], odom_quat_xyzw=dataset.odom_quat_xyzw[:count - 1],
        odom_info=dataset.odom_info[:count - 1], odom_cov=dataset.odom_cov[:count - 1],
        obs_pose_index=dataset.obs_pose_index[kept], obs_camera=dataset.obs_camera[kept], obs_z=dataset.obs_z[kept],
        obs_info=dataset.obs_info[kept], obs_cov=dataset.obs_cov[kept], obs_true_landmark=dataset.obs_true_landmark[kept],
        obs_kind=dataset.obs_kind[kept], obs_partner=partner.astype(np.int64),
    )
