"""Simulated camera-localization worlds: a trajectory, a landmark map, noisy odometry and detections.

Pure: ``simulate(config, seed=...)`` returns a ``camloc.dataset.Dataset`` and does no I/O. The
models are exactly those of docs/format.md and ``camloc.models``; ground truth is exact, odometry and
observations are noisy.

Model card
----------
Trajectory  ``grid``: the real file's style, flat ground (z = 0), each step either 1 m forward or a
            turn in place of +-90 deg (sometimes 180 deg), a random walk on a 1 m grid kept inside a
            square region centred on the start. ``smooth3d``: moves along its body x axis at
            0.3..1 m per step, smoothly varying yaw rate, roll and pitch oscillating up to
            ``max_tilt_deg`` (default 18 deg), so the height changes by a few metres. ``aerial``: a
            flying vehicle looking around, its velocity independent of its attitude, roll and pitch
            oscillating up to ``max_tilt_deg`` (default 60 deg; up to 90 to approach the Euler
            singularity).
Map         landmarks uniform in a ball of radius ``max_range`` around random poses (``grid``: a disk,
            within +-0.5 m of the floor like the real room), kept if some camera sees them from some
            pose: every landmark of the real file is observed. By default as many as give the real
            file's 3.62 visible landmarks per camera and pose (144 landmarks for its 100 poses), so
            the detection rate does not depend on how compact the path is.
Visibility  measured on the real file, where it explains all 362 detections and misses only those of
            the first pose and one landmark at 2.00 m:
            distance from the camera centre in [0.5, 2.0] m and the ray within 45 deg of the optical
            axis (``hypot(x/z, y/z) <= 1``); the normalized image is not clipped. The first pose sees
            nothing unless ``observe_first_pose``. Pixel cameras also need the measured (u, v) inside
            the image: a detector reports only pixels it has.
Odometry    ``T_k+1 = T_k dT Exp(w)`` (``camloc.models``), w = (w_t, w_theta) ~ N(0, Q) with
            Q = ``odometry_cov_from_info(info)``, the information written into the file in g2o's
            quaternion-vector parametrization (rotation-vector covariance 4x the quaternion one).
Observation ``z = project(camera_points(T_k, T_rc, l)) + n``, n ~ N(0, obs_info^-1).
Clutter     extra detections with ids absent from the map, measurement uniform in the visible volume.
Outliers    real detections whose measurement is replaced by one uniform in the visible volume; they
            KEEP the true landmark id, so scoring them as correct associations is a scorer's choice
            (``simulate_labelled`` returns the mask).
Ids         landmarks 0..L-1, poses from 1000 (or the next power of ten above L, because g2o shares
            one id space between vertices), clutter from the next power of ten above the last pose.
Randomness  one ``np.random.default_rng(seed)``, split into independent streams per stage so that,
            for one seed, changing e.g. the clutter leaves the trajectory, map and noise unchanged.
Imperfect   ``withhold_map``, ``move_map`` / ``move_distance`` and ``no_map`` edit the map written
map         after the whole world is simulated (``camloc.simulate_map``): the detections are of the
            true map whatever the file's map says, and ``Simulation.map_edits`` keeps the truth.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from dataclasses import dataclass, fields
from typing import Any, Mapping

import numpy as np
from scipy.spatial import cKDTree

from camloc import geometry, measurement, models
from camloc.dataset import Camera, Dataset
from camloc.errors import ConfigError
from camloc.g2o import observation_cov_from_info, odometry_cov_from_info, odometry_info_from_cov
from camloc.simulate_map import DEFAULT_MOVE_DISTANCE_M, MapEdits, edit_map, edits_map, map_edit_problem

TRAJECTORIES = ("grid", "smooth3d", "aerial")
INTRINSICS = ("normalized", "pixel")
RANGE_KINDS = ("distance", "depth")
DEFAULT_MAX_TILT_DEG = {"grid": 0.0, "smooth3d": 18.0, "aerial": 60.0}

# The real file: 144 landmarks around a 101-pose grid walk, 362 detections from 100 poses.
VISIBLE_PER_VIEW = 3.62
DENSE_FACTOR = 5.0
# The real file's camera: 0.3 m above the robot origin, optical axis along robot +x.
REAL_MOUNT_TRANSLATION = np.array([0.0, 0.0, 0.3])
REAL_MOUNT_QUAT_XYZW = np.array([0.5, -0.5, 0.5, -0.5])
# Extra cameras look backwards, left, right (yaw of the mount), 0.1 m out from the centre.
EXTRA_CAMERA_YAWS = (math.pi, math.pi / 2.0, -math.pi / 2.0)
EXTRA_CAMERA_OFFSET_M = 0.1
PIXEL_INTRINSICS = (525.0, 525.0, 319.5, 239.5)
PIXEL_IMAGE_SIZE = (640, 480)
# Noise defaults of the real file: odometry information 100 (translation) and 10000 (quaternion
# vector part, i.e. 0.02 rad as a rotation vector); observation information 1000 per component.
REAL_OBS_SIGMA = 1.0 / math.sqrt(1000.0)
PIXEL_SIGMA_UV = 1.0
# A zero sigma is simulated exactly but written as this floor, so the information stays finite.
SIGMA_FLOOR = 1e-6
GRID_FLOOR_BAND_M = 0.5
# Rejection samplers give up (ConfigError) rather than loop forever on a near-empty volume.
_MAX_BATCHES = 10000


@dataclass(frozen=True)
class SimulationConfig:
    """Everything that defines a simulated world, besides the seed. Units: metres, radians unless
    a name says ``_deg``.

    Attributes
    ----------
    trajectory : ``grid``, ``smooth3d`` or ``aerial`` (see the module's model card).
    poses : number of poses N (>= 2).
    landmarks : map size L; None: the real file's density, as many as give 3.62 visible landmarks
        per camera and observing pose on average (the real file: 144 for 100 poses).
    dense : a dense map over the same region, 5x the default density.
    region : side of the square region the path stays in, metres; None: ``1.3 * sqrt(poses)``
        (>= 4 m), the real file's 13 m for 100 poses.
    max_tilt_deg : roll and pitch amplitude for smooth3d / aerial; None: 18 / 60. In (0, 90];
        ignored by grid.
    cameras : number of cameras, 1..4 (ids 0..3: forward, backward, left, right).
    intrinsics : ``normalized`` (fx=fy=1, cx=cy=0.5, unclipped image) or ``pixel`` (fx=fy=525,
        cx=319.5, cy=239.5, 640x480 image).
    measurement : what the cameras measure (``camloc.measurement``): ``depth`` (u, v, depth),
        ``pixel`` (u, v only: a monocular camera) or ``disparity`` (u, v, 1/depth); one name for
        every camera, or a comma-separated list of one per camera (``depth,pixel``).
    range_kind : what ``min_range``/``max_range`` bound: ``distance`` from the camera centre
        (the real file's rule) or ``depth`` (camera z).
    min_range, max_range : visible range, metres: 0.5 and 2.0 like the real file.
    fov_half_angle_deg : visible cone around the optical axis, 45 like the real file.
    detection_probability : chance that a visible landmark is reported (the real file: 1).
    max_observations_per_pose : cap on real detections per pose (random subset); None: no cap.
    observe_first_pose : detections at the first pose (the real file has none there).
    clutter_fraction : fraction of all observations that are clutter, in [0, 1).
    outlier_fraction : fraction of real detections replaced by a random measurement, in [0, 1).
    odometry_sigma_translation : per-axis std of the increment's translation, metres (0.1).
    odometry_sigma_rotation : per-axis std of the increment's rotation vector, radians (0.02,
        i.e. information 10000 on g2o's quaternion vector part).
    odometry_sigma_scale : multiplies both odometry sigmas; 0 gives exact odometry.
    observation_sigma_uv : std of u and v; None: 1/sqrt(1000) normalized, 1 px for pixel cameras.
    observation_sigma_depth : std of depth, metres (1/sqrt(1000)); of a disparity camera's
        inverse depth, in 1/m, the same number.
    observation_sigma_scale : multiplies the observation sigmas; 0 gives exact observations.
    withhold_map : share of the landmarks left out of the file's map, in [0, 1]; their detections
        stay, with their true ids (``camloc.simulate_map``).
    move_map : share of the landmarks written ``move_distance`` metres from their true position in
        a random direction, in [0, 1 - withhold_map]; detections are of the true positions.
    move_distance : how far a moved landmark is written from its true position, metres (0.3).
    no_map : write no landmark at all (detections stay, with their true ids).
    """

    trajectory: str = "grid"
    poses: int = 100
    landmarks: int | None = None
    dense: bool = False
    region: float | None = None
    max_tilt_deg: float | None = None
    cameras: int = 1
    intrinsics: str = "normalized"
    measurement: str = "depth"
    range_kind: str = "distance"
    min_range: float = 0.5
    max_range: float = 2.0
    fov_half_angle_deg: float = 45.0
    detection_probability: float = 1.0
    max_observations_per_pose: int | None = None
    observe_first_pose: bool = False
    clutter_fraction: float = 0.0
    outlier_fraction: float = 0.0
    odometry_sigma_translation: float = 0.1
    odometry_sigma_rotation: float = 0.02
    odometry_sigma_scale: float = 1.0
    observation_sigma_uv: float | None = None
    observation_sigma_depth: float = REAL_OBS_SIGMA
    observation_sigma_scale: float = 1.0
    withhold_map: float = 0.0
    move_map: float = 0.0
    move_distance: float = DEFAULT_MOVE_DISTANCE_M
    no_map: bool = False

    def __post_init__(self) -> None:
        _require(self.trajectory in TRAJECTORIES, "trajectory", f"one of {', '.join(TRAJECTORIES)}", self.trajectory)
        _require(self.intrinsics in INTRINSICS, "intrinsics", f"one of {', '.join(INTRINSICS)}", self.intrinsics)
        _require(self.range_kind in RANGE_KINDS, "range_kind", f"one of {', '.join(RANGE_KINDS)}", self.range_kind)
        names = [name.strip() for name in str(self.measurement).split(",")]
        _require(all(name in measurement.KIND_BY_NAME for name in names), "measurement",
                 f"one of {', '.join(measurement.KIND_BY_NAME)}, or a comma-separated list of one per camera", self.measurement)
        _require(len(names) in (1, self.cameras), "measurement", f"one kind, or one per camera ({self.cameras})", self.measurement)
        _require(self.poses >= 2, "poses", "at least 2", self.poses)
        _require(self.landmarks is None or self.landmarks >= 0, "landmarks", "a count >= 0", self.landmarks)
        _require(not (self.dense and self.landmarks is not None), "dense",
                 "either dense or an explicit landmarks count", f"dense and landmarks={self.landmarks}")
        _require(self.region is None or 0 < self.region <= MAX_LENGTH_M, "region", f"in (0, {MAX_LENGTH_M:.0e}] m", self.region)
        _require(self.max_tilt_deg is None or 0 < self.max_tilt_deg <= 90, "max_tilt_deg", "in (0, 90]", self.max_tilt_deg)
        _require(1 <= self.cameras <= 4, "cameras", "1 to 4", self.cameras)
        _require(self.min_range >= 0, "min_range", ">= 0", self.min_range)
        _require(self.min_range < self.max_range <= MAX_LENGTH_M, "max_range",
                 f"more than min_range = {self.min_range} and at most {MAX_LENGTH_M:.0e} m", self.max_range)
        _require(0 < self.fov_half_angle_deg < 90, "fov_half_angle_deg", "in (0, 90)", self.fov_half_angle_deg)
        _require(0 < self.detection_probability <= 1, "detection_probability", "in (0, 1]", self.detection_probability)
        _require(self.max_observations_per_pose is None or self.max_observations_per_pose >= 0,
                 "max_observations_per_pose", "a count >= 0", self.max_observations_per_pose)
        for name in ("clutter_fraction", "outlier_fraction"):
            _require(0 <= getattr(self, name) < 1, name, "in [0, 1)", getattr(self, name))
        for name in ("odometry_sigma_translation", "odometry_sigma_rotation", "odometry_sigma_scale",
                     "observation_sigma_depth", "observation_sigma_scale"):
            _require(getattr(self, name) >= 0, name, ">= 0", getattr(self, name))
        _require(self.observation_sigma_uv is None or self.observation_sigma_uv >= 0,
                 "observation_sigma_uv", ">= 0", self.observation_sigma_uv)
        # Upper bounds keep the written file readable (camloc.g2o.MAX_COORDINATE) and the noise meaningful.
        scaled = {
            "odometry_sigma_translation": (self.odometry_sigma_translation * self.odometry_sigma_scale, MAX_LENGTH_M, "m"),
            "odometry_sigma_rotation": (self.odometry_sigma_rotation * self.odometry_sigma_scale, MAX_ROTATION_SIGMA, "rad"),
            "observation_sigma_depth": (self.observation_sigma_depth * self.observation_sigma_scale, MAX_LENGTH_M, "m"),
            "observation_sigma_uv": ((self.observation_sigma_uv or 0.0) * self.observation_sigma_scale, MAX_LENGTH_M, "image units"),
        }
        for name, (value, bound, unit) in scaled.items():
            _require(value <= bound, name, f"at most {bound:g} {unit} (times its scale)", value)
        problem = map_edit_problem(self.withhold_map, self.move_map, self.move_distance, self.no_map, MAX_LENGTH_M)
        if problem is not None:
            _require(False, *problem)

    def camera_kinds(self) -> list[int]:
        """The measurement kind of each camera (``camloc.measurement`` codes)."""
        names = [name.strip() for name in str(self.measurement).split(",")]
        names = names * self.cameras if len(names) == 1 else names
        return [measurement.KIND_BY_NAME[name].code for name in names]

    @property
    def region_side_m(self) -> float:
        return self.region if self.region is not None else max(4.0, round(1.3 * math.sqrt(self.poses)))

    @property
    def tilt_rad(self) -> float:
        tilt = self.max_tilt_deg if self.max_tilt_deg is not None else DEFAULT_MAX_TILT_DEG[self.trajectory]
        return math.radians(tilt)


# Lengths (region, range, sigmas) beyond this are refused: a 20,000-pose walk still stays well
# inside what the reader accepts (camloc.g2o.MAX_COORDINATE).
MAX_LENGTH_M = 1e6
# g2o's rotation error is the quaternion's vector part, which saturates beyond about 1 rad of noise.
MAX_ROTATION_SIGMA = 1.0


class SimulationOptionError(ConfigError):
    """A ``SimulationConfig`` field out of range; ``field`` names it, ``reason`` says why."""

    def __init__(self, field: str, reason: str):
        self.field = field
        self.reason = reason
        super().__init__(f"simulation option {field}: {reason}")


def simulation_config(options: Mapping[str, Any]) -> SimulationConfig:
    """The ``SimulationConfig`` of ``camloc simulate``'s options named as on its command line.

    Each option is its field's name with dashes (``clutter-fraction`` is ``clutter_fraction``);
    ``camloc simulate`` and ``camloc sweep``'s ``[simulate]`` table both come through here. A
    None value is an option not given: its field keeps its default.

    Raises
    ------
    SimulationOptionError : an unknown name, a value of the wrong type or out of range; ``field``
        is the option's command-line name.
    """
    values = {}
    for name, value in options.items():
        if value is None:
            continue
        field = name.replace("-", "_")
        if "_" in name or field not in _FIELD_TYPES:
            close = difflib.get_close_matches(field.replace("_", "-"), [f.replace("_", "-") for f in _FIELD_TYPES], n=1)
            raise SimulationOptionError(name, "not an option of camloc simulate" + (f" (did you mean {close[0]}?)" if close else ""))
        expected = _FIELD_TYPES[field]
        if not isinstance(value, expected) or (isinstance(value, bool) and bool not in expected):
            raise SimulationOptionError(name, f"expected {' or '.join(t.__name__ for t in expected)}, found {value!r}")
        values[field] = value
    try:
        return SimulationConfig(**values)
    except SimulationOptionError as error:
        raise SimulationOptionError(error.field.replace("_", "-"), error.reason) from None


# field -> the types its value may have (a float option takes an integer too; None is the default).
_FIELD_TYPES = {
    f.name: {"str": (str,), "int": (int,), "bool": (bool,), "float": (int, float)}[f.type.split("|")[0].strip()]
    for f in fields(SimulationConfig)
}


def _require(ok: bool, name: str, expected: str, found: object) -> None:
    if not ok:
        raise SimulationOptionError(name, f"expected {expected}, found {found!r}")


@dataclass(frozen=True)
class CameraSpec:
    """A camera and what it can see: image bounds (pixels) or None for an unclipped image."""

    camera: Camera
    image_size: tuple[int, int] | None
    kind: int = measurement.DEPTH  # what its observations measure (``camloc.measurement``)


@dataclass(frozen=True)
class Simulation:
    """A simulated dataset and the labels a file cannot carry.

    Attributes
    ----------
    dataset : the simulated data.
    is_outlier : (K,) bool, the measurement was replaced by a random one (true id kept).
    is_clutter : (K,) bool, a detection of nothing (its id is absent from the true map; a withheld
        landmark's detections are not clutter, though their ids are absent from the file's map).
    map_edits : the true map and what was withheld or moved, when the config asks for an
        imperfect map (``camloc.simulate_map``); None when the file's map is the truth.
    """

    dataset: Dataset
    is_outlier: np.ndarray
    is_clutter: np.ndarray
    map_edits: MapEdits | None = None


def simulate(config: SimulationConfig, *, seed: int) -> Dataset:
    """Simulate a world and return it as a ``Dataset``, deterministic for a seed.

    Parameters
    ----------
    config : the world's description.
    seed : seed of ``np.random.default_rng``.

    Returns
    -------
    Dataset with ground truth for every pose; ``start`` is the first true pose.
    """
    return simulate_labelled(config, seed=seed).dataset


def simulate_labelled(config: SimulationConfig, *, seed: int) -> Simulation:
    """``simulate``, also returning which observations are outliers and clutter, and the true map
    when the file's is edited (``withhold_map``, ``move_map``, ``no_map``)."""
    simulation = _simulate_whole(config, seed=seed)
    if not edits_map(config):
        return simulation
    edits = edit_map(simulation.dataset, config, seed=seed)
    return dataclasses.replace(simulation, dataset=edits.dataset, map_edits=edits)


def _simulate_whole(config: SimulationConfig, *, seed: int) -> Simulation:
    """The world with its complete, true map (``simulate_labelled`` before any map edit)."""
    rng_path, rng_map, rng_odom, rng_detect, rng_noise, rng_spurious = np.random.default_rng(seed).spawn(6)
    # The world: a true path, the cameras on the robot, a map around the path.
    T_world_robot = TRAJECTORY_GENERATORS[config.trajectory](config, rng_path)
    specs = make_cameras(config)
    landmark_xyz = place_landmarks(T_world_robot, specs, config, rng_map)
    ids = _Ids(landmark_xyz.shape[0], T_world_robot.shape[0])
    # Odometry: the true increments with noise drawn from the information written.
    odom_T, odom_info = noisy_odometry(T_world_robot, config, rng_odom)
    # Detections: visible landmarks, measured with noise, kept inside the image, capped per pose.
    obs = detect(T_world_robot, specs, landmark_xyz, config, rng_detect)
    kind_of_camera = {spec.camera.id: spec.kind for spec in specs}
    obs_kind = np.array([kind_of_camera[int(c)] for c in obs.camera], dtype=np.int64)
    obs_info = observation_info(config, obs_kind)
    obs = dataclasses.replace(obs, uvd=add_observation_noise(as_measured(obs.uvd, obs_kind), obs_info, config, rng_noise, obs_kind))
    obs = obs.select(inside_images(obs.uvd, obs.camera, specs))
    obs = obs.select(cap_per_pose(obs.pose_index, config.max_observations_per_pose, rng_detect))
    # Spurious data: outliers replace some measurements, clutter adds detections of nothing.
    obs = replace_outliers(obs, specs, config, rng_spurious)
    obs = obs.concat(make_clutter(obs.count, T_world_robot.shape[0], specs, ids.clutter_base, config, rng_spurious))
    # Order by pose and camera, randomly within: neither clutter nor ids may be guessed from order.
    obs = obs.select(np.lexsort((rng_spurious.random(obs.count), obs.camera, obs.pose_index)))

    truth_xyz, truth_quat = geometry.pose_to_quat(T_world_robot)
    odom_xyz, odom_quat = geometry.pose_to_quat(odom_T)
    obs_kind = np.array([kind_of_camera[int(c)] for c in obs.camera], dtype=np.int64)
    obs_info_all = observation_info(config, obs_kind)
    dataset = Dataset(
        source=describe(config, seed),
        cameras={spec.camera.id: spec.camera for spec in specs},
        landmark_ids=np.arange(landmark_xyz.shape[0], dtype=np.int64),
        landmark_xyz=landmark_xyz,
        pose_ids=ids.pose_base + np.arange(T_world_robot.shape[0], dtype=np.int64),
        start_xyz=truth_xyz[0].copy(),
        start_quat_xyzw=truth_quat[0].copy(),
        truth_xyz=truth_xyz,
        truth_quat_xyzw=truth_quat,
        odom_translation=odom_xyz,
        odom_quat_xyzw=odom_quat,
        odom_info=odom_info,
        odom_cov=odometry_cov_from_info(odom_info),
        obs_pose_index=obs.pose_index,
        obs_camera=obs.camera,
        obs_z=obs.uvd,
        obs_info=obs_info_all,
        obs_cov=observation_cov_from_info(obs_info_all),
        obs_true_landmark=obs.landmark,
        obs_kind=obs_kind,
        tag_counts={
            "PARAMS_CAMERACALIB": len(specs),
            "VERTEX_TRACKXYZ": landmark_xyz.shape[0],
            "VERTEX_SE3:QUAT": T_world_robot.shape[0],
            "EDGE_SE3:QUAT": T_world_robot.shape[0] - 1,
            **{measurement.KINDS[int(kind)].tag: int(np.count_nonzero(obs_kind == kind)) for kind in np.unique(obs_kind)},
        },
    )
    return Simulation(dataset=dataset, is_outlier=obs.is_outlier, is_clutter=obs.is_clutter)


@dataclass(frozen=True)
class _Observations:
    """Observations being built, K rows: pose index, camera id, landmark id (int64, (K,)),
    measurement (K, 3), and the outlier / clutter labels (K,) bool."""

    pose_index: np.ndarray
    camera: np.ndarray
    landmark: np.ndarray
    uvd: np.ndarray
    is_outlier: np.ndarray
    is_clutter: np.ndarray

    @classmethod
    def of(cls, pose_index, camera, landmark, uvd, *, clutter: bool) -> "_Observations":
        count = len(pose_index)
        return cls(np.asarray(pose_index, dtype=np.int64), np.asarray(camera, dtype=np.int64),
                   np.asarray(landmark, dtype=np.int64), np.asarray(uvd, dtype=float).reshape(count, 3),
                   np.zeros(count, dtype=bool), np.full(count, clutter))

    @property
    def count(self) -> int:
        return int(self.pose_index.shape[0])

    def select(self, rows: np.ndarray) -> "_Observations":
        """The rows given by a boolean mask or an index array."""
        return _Observations(*(getattr(self, f.name)[rows] for f in fields(self)))

    def concat(self, other: "_Observations") -> "_Observations":
        return _Observations(*(np.concatenate([getattr(self, f.name), getattr(other, f.name)]) for f in fields(self)))


def describe(config: SimulationConfig, seed: int) -> str:
    """``simulate(trajectory=grid, poses=100, ..., seed=3)``: the options that differ from the
    defaults, trajectory and poses always."""
    default = SimulationConfig()
    parts = [f"trajectory={config.trajectory}", f"poses={config.poses}"]
    for f in fields(config):
        value = getattr(config, f.name)
        if f.name not in ("trajectory", "poses") and value != getattr(default, f.name):
            parts.append(f"{f.name}={value}")
    return f"simulate({', '.join(parts)}, seed={seed})"


class _Ids:
    """Id layout: landmarks 0..L-1, then poses, then clutter, never overlapping (g2o vertices
    share one id space)."""

    def __init__(self, num_landmarks: int, num_poses: int):
        self.pose_base = _power_of_ten_above(num_landmarks, minimum=1000)
        self.clutter_base = _power_of_ten_above(self.pose_base + num_poses, minimum=10000)


def _power_of_ten_above(n: int, *, minimum: int) -> int:
    power = minimum
    while power <= n:
        power *= 10
    return power


# ----------------------------------------------------------------------------------- trajectories


def grid_trajectory(config: SimulationConfig, rng: np.random.Generator) -> np.ndarray:
    """Random walk on a 1 m grid, z = 0: each step 1 m forward or a turn in place.

    Turns happen a third of the time (the real file: 33 of 100 steps), one in ten of them 180 deg;
    a step that would leave the region becomes a turn. Returns (N, 4, 4) T_world_robot, the first
    the identity.
    """
    half = int(config.region_side_m // 2)
    cell = np.zeros(2, dtype=int)
    heading = 0  # quarter turns from +x
    cells, headings = [cell.copy()], [heading]
    for _ in range(config.poses - 1):
        ahead = cell + _HEADING_STEP[heading % 4]
        if rng.random() < 1.0 / 3.0 or np.any(np.abs(ahead) > half):
            heading += 2 if rng.random() < 0.1 else int(rng.choice([-1, 1]))
        else:
            cell = ahead
        cells.append(cell.copy())
        headings.append(heading)
    yaw = geometry.wrap_angle(np.array(headings) * (np.pi / 2.0))
    rpy = np.column_stack([np.zeros_like(yaw), np.zeros_like(yaw), yaw])
    xyz = np.column_stack([np.array(cells, dtype=float), np.zeros(len(cells))])
    return geometry.make_pose(geometry.euler_to_matrix(rpy), xyz)


_HEADING_STEP = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])


def smooth3d_trajectory(config: SimulationConfig, rng: np.random.Generator) -> np.ndarray:
    """Smooth 3D motion along the body x axis: speed 0.3..1 m per step, smoothly varying yaw rate,
    roll and pitch oscillating with amplitude ``max_tilt``; pitching makes the height vary by a
    few metres around z = 0. Returns (N, 4, 4) T_world_robot."""
    n = config.poses
    speed = 0.65 + 0.35 * np.tanh(_ar1(rng, n, sigma=1.0, correlation_steps=20.0))
    yaw_rate = _ar1(rng, n, sigma=0.12, correlation_steps=10.0)
    roll = config.tilt_rad * np.sin(_oscillation_phase(rng, n))
    pitch = config.tilt_rad * np.sin(_oscillation_phase(rng, n))
    xyz, yaw = np.zeros((n, 3)), np.zeros(n)
    for k in range(n - 1):
        R = geometry.euler_to_matrix(np.array([roll[k], pitch[k], yaw[k]]))
        xyz[k + 1] = xyz[k] + speed[k] * R[:, 0]
        xyz[k + 1, 2] -= 0.05 * xyz[k, 2]  # a weak spring to z = 0 bounds the height's drift
        yaw[k + 1] = yaw[k] + yaw_rate[k] + _steer_home(xyz[k + 1], yaw[k], config.region_side_m / 2.0)
    return geometry.pose_from_euler(np.column_stack([xyz, roll, pitch, geometry.wrap_angle(yaw)]))


def aerial_trajectory(config: SimulationConfig, rng: np.random.Generator) -> np.ndarray:
    """A flying vehicle looking around: a smooth 3D velocity (~0.5 m per step) pulled back into the
    region, independent of the attitude; yaw drifts smoothly, roll and pitch oscillate with
    amplitude ``max_tilt`` and reach it once per oscillation. Returns (N, 4, 4) T_world_robot."""
    n = config.poses
    drift = np.column_stack([_ar1(rng, n, sigma=0.4, correlation_steps=15.0) for _ in range(3)])
    yaw = np.cumsum(_ar1(rng, n, sigma=0.1, correlation_steps=10.0))
    roll = config.tilt_rad * np.sin(_oscillation_phase(rng, n))
    pitch = config.tilt_rad * np.sin(_oscillation_phase(rng, n))
    half = config.region_side_m / 2.0
    xyz = np.zeros((n, 3))
    for k in range(n - 1):
        # A spring beyond the region's edge (and beyond 1 m of height) keeps the drift bounded.
        pull = -0.3 * np.maximum(np.abs(xyz[k]) - np.array([half, half, 1.0]), 0.0) * np.sign(xyz[k])
        xyz[k + 1] = xyz[k] + drift[k] + pull
    return geometry.pose_from_euler(np.column_stack([xyz, roll, pitch, geometry.wrap_angle(yaw)]))


TRAJECTORY_GENERATORS = {"grid": grid_trajectory, "smooth3d": smooth3d_trajectory, "aerial": aerial_trajectory}


def _ar1(rng: np.random.Generator, n: int, *, sigma: float, correlation_steps: float) -> np.ndarray:
    """A stationary first-order autoregressive sequence (n,) with std ``sigma``: smooth noise."""
    a = math.exp(-1.0 / correlation_steps)
    shocks = rng.standard_normal(n) * sigma * math.sqrt(1.0 - a * a)
    out = np.empty(n)
    out[0] = rng.standard_normal() * sigma
    for k in range(1, n):
        out[k] = a * out[k - 1] + shocks[k]
    return out


def _oscillation_phase(rng: np.random.Generator, n: int) -> np.ndarray:
    """Phase (n,) of an oscillation with a random start and a rate varying in 0.05..0.15 rad per
    step, so ``sin(phase)`` sweeps -1..1 every ~60 steps without being periodic."""
    rate = 0.1 * (1.0 + 0.5 * np.tanh(_ar1(rng, n, sigma=1.0, correlation_steps=15.0)))
    return rng.uniform(0.0, 2.0 * np.pi) + np.cumsum(rate)


def _steer_home(xyz: np.ndarray, yaw: float, half_side: float) -> float:
    """Extra yaw (rad) turning a vehicle beyond ``half_side`` of the origin back towards it."""
    distance = float(np.hypot(xyz[0], xyz[1]))
    if distance <= half_side:
        return 0.0
    bearing_home = math.atan2(-xyz[1], -xyz[0])
    return float(np.clip(0.3 * geometry.wrap_angle(bearing_home - yaw), -0.3, 0.3))


# ------------------------------------------------------------------------------- cameras and map


def make_cameras(config: SimulationConfig) -> list[CameraSpec]:
    """Camera 0 is the real file's (forward); cameras 1..3 look backward, left, right."""
    if config.intrinsics == "pixel":
        (fx, fy, cx, cy), image = PIXEL_INTRINSICS, PIXEL_IMAGE_SIZE
    else:
        (fx, fy, cx, cy), image = (1.0, 1.0, 0.5, 0.5), None
    kinds = config.camera_kinds()
    specs = [CameraSpec(Camera(0, REAL_MOUNT_TRANSLATION.copy(), REAL_MOUNT_QUAT_XYZW.copy(), fx, fy, cx, cy), image, kinds[0])]
    R_forward = geometry.quat_to_matrix(REAL_MOUNT_QUAT_XYZW)
    for camera_id, yaw in enumerate(EXTRA_CAMERA_YAWS[: config.cameras - 1], start=1):
        # The mounts are quarter turns: rounding drops cos(pi/2) = 6e-17 so they are exact.
        R_robot_camera = np.round(geometry.euler_to_matrix(np.array([0.0, 0.0, yaw])) @ R_forward, 12)
        offset = np.round(EXTRA_CAMERA_OFFSET_M * np.array([math.cos(yaw), math.sin(yaw), 0.0]), 12)
        quat = geometry.matrix_to_quat(R_robot_camera) + 0.0  # + 0.0 turns -0.0 into 0.0 for the file
        camera = Camera(camera_id, REAL_MOUNT_TRANSLATION + offset + 0.0, quat, fx, fy, cx, cy)
        specs.append(CameraSpec(camera, image, kinds[camera_id]))
    return specs


def visible(p_camera: np.ndarray, spec: CameraSpec, config: SimulationConfig) -> np.ndarray:
    """(M,) bool: which camera-frame points (M, 3) the camera sees (range, cone, image)."""
    z = p_camera[:, 2]
    extent = np.linalg.norm(p_camera, axis=1) if config.range_kind == "distance" else z
    seen = (z > 0.0) & (extent >= config.min_range) & (extent <= config.max_range)
    off_axis = np.hypot(p_camera[:, 0], p_camera[:, 1])
    seen &= off_axis <= math.tan(math.radians(config.fov_half_angle_deg)) * z
    if spec.image_size is not None:
        seen &= _in_image(_project(p_camera, spec, seen), spec.image_size)
    return seen


def _project(p_camera: np.ndarray, spec: CameraSpec, valid: np.ndarray) -> np.ndarray:
    """``models.project_points`` where ``valid``, NaN elsewhere (no division by a zero depth)."""
    uvd = np.full(p_camera.shape, np.nan)
    c = spec.camera
    uvd[valid] = models.project_points(p_camera[valid], (c.fx, c.fy, c.cx, c.cy))
    return uvd


def _in_image(uvd: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    # Pixel centres are integers (cx = 319.5 for 640 columns), so the image spans -0.5..W-0.5.
    width, height = image_size
    with np.errstate(invalid="ignore"):
        return (uvd[:, 0] >= -0.5) & (uvd[:, 0] <= width - 0.5) & (uvd[:, 1] >= -0.5) & (uvd[:, 1] <= height - 0.5)


def sample_visible_points(spec: CameraSpec, count: int, config: SimulationConfig, rng: np.random.Generator) -> np.ndarray:
    """``count`` points (count, 3) uniform in the camera's visible volume, camera frame."""
    # Rejection sampling from the ball that holds the whole visible volume.
    radius = _reach(config)
    found = [np.zeros((0, 3))]
    for _ in range(_MAX_BATCHES):
        if sum(len(f) for f in found) >= count:
            return np.concatenate(found)[:count]
        p = rng.uniform(-radius, radius, size=(max(64, 16 * count), 3))
        p = p[np.linalg.norm(p, axis=1) <= radius]
        found.append(p[visible(p, spec, config)])
    raise ConfigError("simulation: the visible volume of the cameras is too small to sample; "
                      "widen the field of view or the range")


def place_landmarks(
    T_world_robot: np.ndarray, specs: list[CameraSpec], config: SimulationConfig, rng: np.random.Generator
) -> np.ndarray:
    """Map (L, 3), world frame: landmarks around the path, each seen from at least one pose.

    A candidate is a random pose's position plus an offset uniform in the ball of radius
    ``max_range`` (for ``grid``: a disk, height within +-0.5 m of the floor, as in the real room);
    it is kept if some camera at some observing pose sees it, as every landmark of the real file
    is observed at least once. Without an explicit count, landmarks are added until there are
    ``VISIBLE_PER_VIEW`` visible landmarks per camera and observing pose on average (x5 when
    ``dense``): the real file's density, whatever the trajectory's shape.
    """
    first = 0 if config.observe_first_pose else 1
    T_world_camera = [T_world_robot[first:] @ spec.camera.T_robot_camera for spec in specs]
    target_views = VISIBLE_PER_VIEW * len(specs) * (T_world_robot.shape[0] - first) * (DENSE_FACTOR if config.dense else 1.0)
    chunks: list[np.ndarray] = []
    views: list[np.ndarray] = []
    for _ in range(_MAX_BATCHES):
        if _enough(views, config.landmarks, target_views):
            break
        batch = 64 if config.landmarks is None else max(32, 2 * (config.landmarks - sum(map(len, views))))
        candidates = T_world_robot[rng.integers(0, T_world_robot.shape[0], size=batch), :3, 3]
        candidates = candidates + _ball_offsets(batch, config, rng)
        count = sum(_view_counts(candidates, T_wc, spec, config) for spec, T_wc in zip(specs, T_world_camera))
        chunks.append(candidates[count > 0])
        views.append(count[count > 0])
    else:
        raise ConfigError("simulation: cannot place landmarks that the cameras see from the path; "
                          "widen the field of view or the range")
    if not chunks:
        return np.zeros((0, 3))
    landmarks, views_all = np.concatenate(chunks), np.concatenate(views)
    keep = config.landmarks if config.landmarks is not None else int(np.searchsorted(np.cumsum(views_all), target_views)) + 1
    return landmarks[:keep]


def _enough(views: list[np.ndarray], landmarks: int | None, target_views: float) -> bool:
    if landmarks is not None:
        return sum(map(len, views)) >= landmarks
    return sum(float(v.sum()) for v in views) >= target_views


def _ball_offsets(count: int, config: SimulationConfig, rng: np.random.Generator) -> np.ndarray:
    """Offsets (count, 3) uniform in the ball of radius ``max_range`` (grid: disk x floor band)."""
    radius = _reach(config)
    offsets = np.zeros((0, 3))
    while len(offsets) < count:
        p = rng.uniform(-radius, radius, size=(2 * count, 3))
        if config.trajectory == "grid":
            p[:, 2] = rng.uniform(-GRID_FLOOR_BAND_M, GRID_FLOOR_BAND_M, size=2 * count)
            p = p[np.hypot(p[:, 0], p[:, 1]) <= radius]
        else:
            p = p[np.linalg.norm(p, axis=1) <= radius]
        offsets = np.concatenate([offsets, p])
    return offsets[:count]


def _view_counts(points: np.ndarray, T_world_camera: np.ndarray, spec: CameraSpec, config: SimulationConfig) -> np.ndarray:
    """(M,) int: from how many of its poses (P, 4, 4) the camera sees each world point (M, 3)."""
    point_index, _, _ = visible_pairs(points, T_world_camera, spec, config)
    return np.bincount(point_index, minlength=len(points))


def visible_pairs(
    points: np.ndarray, T_world_camera: np.ndarray, spec: CameraSpec, config: SimulationConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every (point, camera pose) pair in which the camera sees the point.

    Parameters
    ----------
    points : (M, 3) world frame.
    T_world_camera : (P, 4, 4) the camera's poses.

    Returns
    -------
    point_index, pose_index : (V,) int, sorted by pose then point.
    p_camera : (V, 3) the point in the camera frame.
    """
    # Only pairs closer than the reach can be visible: a k-d tree finds them without P x M work.
    near = cKDTree(points).sparse_distance_matrix(cKDTree(T_world_camera[:, :3, 3]), _reach(config), output_type="ndarray")
    order = np.lexsort((near["i"], near["j"]))
    point_index, pose_index = near["i"][order].astype(np.int64), near["j"][order].astype(np.int64)
    T = T_world_camera[pose_index]
    p_camera = np.einsum("vji,vj->vi", T[:, :3, :3], points[point_index] - T[:, :3, 3])
    seen = visible(p_camera, spec, config)
    return point_index[seen], pose_index[seen], p_camera[seen]


def _reach(config: SimulationConfig) -> float:
    """Radius (m) of the ball around the camera centre that holds its whole visible volume."""
    if config.range_kind == "depth":
        return config.max_range / math.cos(math.radians(config.fov_half_angle_deg))
    return config.max_range


# ------------------------------------------------------------------------------------ noise


def _rounded(info: np.ndarray) -> np.ndarray:
    """Information rounded to 12 significant digits, so that the defaults are written as the real
    file's exact 100, 10000 and 1000 rather than 99.99999999999997."""
    return np.vectorize(lambda x: float(f"{x:.12g}"))(info)


def noisy_odometry(
    T_world_robot: np.ndarray, config: SimulationConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Noisy increments (N-1, 4, 4) and their g2o information (N-1, 6, 6).

    The true increment is ``dT = T_k^-1 T_k+1``; the measured one ``dT Exp(w)^-1`` so that
    ``T_k+1 = T_k dT_measured Exp(w)`` exactly as in ``camloc.models``, with ``Exp(w)`` the pose
    (rotation ``so3_exp(w_theta)``, translation ``w_t``) and w ~ N(0, odometry_cov_from_info(info)).
    """
    sigmas = config.odometry_sigma_scale * np.repeat(
        [config.odometry_sigma_translation, config.odometry_sigma_rotation], 3
    )
    info = _rounded(odometry_info_from_cov(np.diag(np.maximum(sigmas, SIGMA_FLOOR) ** 2)))
    # Draw from the covariance of the information actually written; exactly zero where sigma is.
    std = np.where(sigmas > 0.0, np.sqrt(np.diag(odometry_cov_from_info(info))), 0.0)
    count = T_world_robot.shape[0] - 1
    w = rng.standard_normal((count, 6)) * std
    T_noise = geometry.make_pose(geometry.so3_exp(w[:, 3:6]), w[:, 0:3])
    dT_true = geometry.relative_se3(T_world_robot[:-1], T_world_robot[1:])
    return dT_true @ geometry.se3_inverse(T_noise), np.broadcast_to(info, (count, 6, 6)).copy()


def observation_sigmas(config: SimulationConfig) -> np.ndarray:
    """(3,) std of u, v (image units) and depth (metres; a disparity camera's inverse depth in
    1/m: the same number), the scale applied."""
    sigma_uv = config.observation_sigma_uv
    if sigma_uv is None:
        sigma_uv = PIXEL_SIGMA_UV if config.intrinsics == "pixel" else REAL_OBS_SIGMA
    return config.observation_sigma_scale * np.array([sigma_uv, sigma_uv, config.observation_sigma_depth])


def observation_info(config: SimulationConfig, kinds: np.ndarray | None = None) -> np.ndarray:
    """(3, 3) information of (u, v, depth) as written to the file (finite for zero sigmas); with
    ``kinds`` (K,), (K, 3, 3) for observations of those kinds (a pixel's inert third row: unit
    information, ``camloc.measurement``)."""
    info = _rounded(np.diag(1.0 / np.maximum(observation_sigmas(config), SIGMA_FLOOR) ** 2))
    if kinds is None:
        return info
    out = np.broadcast_to(info, (len(kinds), 3, 3)).copy()
    inert = measurement.inert_rows(kinds)[:, 2]
    out[inert, 2, :] = 0.0
    out[inert, :, 2] = 0.0
    out[inert, 2, 2] = 1.0
    return out


def as_measured(uvd: np.ndarray, kinds: np.ndarray) -> np.ndarray:
    """(u, v, depth) (K, 3) as each observation's kind measures it (K,): the depth row kept, made
    the inverse depth, or the inert 0 of a pixel."""
    z = uvd.copy()
    z[kinds == measurement.PIXEL, 2] = 0.0
    disparity = kinds == measurement.DISPARITY
    z[disparity, 2] = 1.0 / uvd[disparity, 2]
    return z


def add_observation_noise(
    z_true: np.ndarray, info: np.ndarray, config: SimulationConfig, rng: np.random.Generator,
    kinds: np.ndarray | None = None,
) -> np.ndarray:
    """Measurements (K, 3): the truth plus N(0, info^-1) noise (info (3, 3), or (K, 3, 3) per
    observation), none where a sigma is zero and none on an inert row of the kinds (K,) given
    (a pixel's third)."""
    info = np.broadcast_to(info, (len(z_true), 3, 3))
    diagonal = np.diagonal(observation_cov_from_info(info), axis1=1, axis2=2) if len(z_true) else np.zeros((0, 3))
    std = np.where(observation_sigmas(config)[None, :] > 0.0, np.sqrt(diagonal), 0.0)
    if kinds is not None:
        std[measurement.inert_rows(kinds)] = 0.0
    return z_true + rng.standard_normal(z_true.shape) * std


# ------------------------------------------------------------------------------------ detection


def detect(
    T_world_robot: np.ndarray,
    specs: list[CameraSpec],
    landmark_xyz: np.ndarray,
    config: SimulationConfig,
    rng: np.random.Generator,
) -> _Observations:
    """Every visible landmark of every camera at every observing pose, each kept with
    ``detection_probability``, with its exact measurement."""
    first = 0 if config.observe_first_pose else 1
    parts = []
    for spec in specs:
        T_world_camera = T_world_robot[first:] @ spec.camera.T_robot_camera
        landmark_index, pose_index, p_camera = visible_pairs(landmark_xyz, T_world_camera, spec, config)
        c = spec.camera
        uvd = models.project_points(p_camera, (c.fx, c.fy, c.cx, c.cy)).reshape(-1, 3)
        parts.append((pose_index + first, np.full(len(pose_index), c.id), landmark_index, uvd))
    pose_index, camera_id, landmark_index, uvd = (np.concatenate(columns) for columns in zip(*parts))
    # Landmark ids are their indices (see _Ids).
    detections = _Observations.of(pose_index, camera_id, landmark_index, uvd, clutter=False)
    return detections.select(rng.random(detections.count) < config.detection_probability)


def inside_images(uvd: np.ndarray, camera_id: np.ndarray, specs: list[CameraSpec]) -> np.ndarray:
    """(K,) bool: measured (u, v) inside the image for pixel cameras; all True when unclipped."""
    keep = np.ones(len(uvd), dtype=bool)
    for spec in specs:
        if spec.image_size is not None:
            mine = camera_id == spec.camera.id
            keep[mine] = _in_image(uvd[mine], spec.image_size)
    return keep


def cap_per_pose(pose_index: np.ndarray, cap: int | None, rng: np.random.Generator) -> np.ndarray:
    """(K,) bool keeping at most ``cap`` random detections per pose; all when ``cap`` is None."""
    keep = np.ones(len(pose_index), dtype=bool)
    if cap is None:
        return keep
    for k in np.unique(pose_index):
        mine = np.flatnonzero(pose_index == k)
        if len(mine) > cap:
            keep[rng.choice(mine, size=len(mine) - cap, replace=False)] = False
    return keep


def random_measurements(
    specs: list[CameraSpec], camera_id: np.ndarray, config: SimulationConfig, rng: np.random.Generator
) -> np.ndarray:
    """(M, 3) measurements of points uniform in the visible volume of each given camera."""
    out = np.zeros((len(camera_id), 3))
    for spec in specs:
        mine = np.flatnonzero(camera_id == spec.camera.id)
        if len(mine):
            p_camera = sample_visible_points(spec, len(mine), config, rng)
            out[mine] = as_measured(_project(p_camera, spec, np.ones(len(mine), dtype=bool)), np.full(len(mine), spec.kind))
    return out


def replace_outliers(
    obs: _Observations, specs: list[CameraSpec], config: SimulationConfig, rng: np.random.Generator
) -> _Observations:
    """Replace ``outlier_fraction`` of the measurements by random ones; the true ids stay."""
    rows = rng.choice(obs.count, size=round(config.outlier_fraction * obs.count), replace=False)
    uvd, is_outlier = obs.uvd.copy(), obs.is_outlier.copy()
    uvd[rows] = random_measurements(specs, obs.camera[rows], config, rng)
    is_outlier[rows] = True
    return dataclasses.replace(obs, uvd=uvd, is_outlier=is_outlier)


def make_clutter(
    real_count: int, num_poses: int, specs: list[CameraSpec], first_id: int, config: SimulationConfig,
    rng: np.random.Generator,
) -> _Observations:
    """Clutter, ``clutter_fraction`` of all observations once added to ``real_count`` detections:
    random observing poses and cameras, measurements uniform in the visible volume, each with its
    own id from ``first_id`` on (absent from the map)."""
    f = config.clutter_fraction
    count = round(real_count * f / (1.0 - f))
    first = 0 if config.observe_first_pose else 1
    pose_index = rng.integers(first, num_poses, size=count)
    camera_id = np.array([specs[i].camera.id for i in rng.integers(len(specs), size=count)], dtype=np.int64)
    uvd = random_measurements(specs, camera_id, config, rng)
    return _Observations.of(pose_index, camera_id, first_id + np.arange(count), uvd, clutter=True)
