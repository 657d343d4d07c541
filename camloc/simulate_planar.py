"""Simulated planar worlds (``camloc simulate --robot planar``): a robot driving on a floor, noisy
planar odometry, and observations of the kinds a planar robot carries.

Pure: ``simulate_planar(config, seed=...)`` returns a planar ``camloc.dataset.Dataset`` (its poses
lifted to 3-D with z = 0, as ``camloc.g2o`` reads a planar file) and does no I/O.

Model card
----------
Path        a unicycle on the floor: 0.3..0.7 m a step along the heading, a turn rate that drifts
            (AR(1), 0.25 rad a step) and is steered back toward the centre near the edge of a square
            region (side ``region``, default 1.3 sqrt(poses), at least 4 m).
Odometry    the true planar increment (dx, dy, dtheta) composed with a right perturbation
            w ~ N(0, diag(s_xy^2, s_xy^2, s_theta^2)): ``T_k+1 = T_k dT Exp(w)`` as in
            ``camloc.planar``; the file's ``EDGE_SE2`` information is that covariance's inverse.
Sensors     ``points``: a planar sensor (a laser's or radar's detections) measuring landmark
            points of the floor in the robot frame, z = (x, y); ``markers``: a planar marker
            detector measuring a marker's pose in the robot frame, z = (x, y, psi), seen only from
            the side its face looks to (within ``MARKER_FACING_DEG`` of its heading's opposite);
            both within [min_range, max_range] and ``fov_half_angle_deg`` of the heading.
            ``cameras``: 3-D cameras on the robot (``camloc.simulate``'s, its defaults: the real
            file's mount, 2 m, 45 deg) observing 3-D points around the path (``VERTEX_TRACKXYZ``).
Maps        planar landmarks uniform over the region grown by the range, as many as give
            ``visible_per_pose`` in view on average; markers' headings uniform.
Noise       point and marker: N(0, sigma_xy^2) per axis and N(0, sigma_psi^2) on psi; cameras:
            ``camloc.simulate``'s.
Clutter     ``clutter_fraction`` of each planar sensor's observations measure nothing in the map:
            uniform in its view (and psi uniform), ids absent from the map.
Ids         landmarks 0..L-1, poses from the next power of ten above (at least 1000), clutter
            from the next above the poses.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from camloc import geometry, measurement, planar
from camloc import simulate as sim3
from camloc.dataset import LANDMARK_MARKER, LANDMARK_POINT2, LANDMARK_POINT3, Dataset
from camloc.g2o import observation_cov_from_info
from camloc.simulate_map import DEFAULT_MOVE_DISTANCE_M, edit_map, edits_map, map_edit_problem, without_map_edits

SENSORS = ("points", "markers", "cameras")
MARKER_FACING_DEG = 75.0
MAX_LANDMARKS = 200_000


@dataclass(frozen=True)
class PlanarSimulationConfig:
    """A planar world, besides the seed (metres, radians unless ``_deg``).

    Attributes
    ----------
    sensors : which of ``SENSORS`` the robot carries, comma-separated ("points,markers").
    poses : number of poses N (>= 2).
    landmarks : planar landmarks per planar sensor; None: as many as give ``visible_per_pose``.
    region : side of the square the path stays in; None: 1.3 sqrt(poses), at least 4.
    min_range, max_range, fov_half_angle_deg : a planar sensor's view.
    visible_per_pose : landmarks in a planar sensor's view on average, for the default map size.
    detection_probability : chance that a landmark in view is reported.
    clutter_fraction : share of a sensor's observations that measure nothing in the map, [0, 1).
    odometry_sigma_xy, odometry_sigma_theta : the increment's noise (metres per axis, radians).
    observation_sigma_xy, observation_sigma_psi : a planar observation's noise.
    cameras : ``camloc.simulate.SimulationConfig`` of the 3-D cameras (with ``cameras`` in
        ``sensors``); its trajectory and odometry options are not used.
    withhold_map, move_map, move_distance, no_map : an imperfect map, as in
        ``camloc.simulate.SimulationConfig`` (``camloc.simulate_map``; planar landmarks move in the floor's plane).
    """

    sensors: str = "points"
    poses: int = 100
    landmarks: int | None = None
    region: float | None = None
    min_range: float = 0.3
    max_range: float = 3.0
    fov_half_angle_deg: float = 60.0
    visible_per_pose: float = 5.0
    detection_probability: float = 0.9
    clutter_fraction: float = 0.0
    odometry_sigma_xy: float = 0.05
    odometry_sigma_theta: float = 0.02
    observation_sigma_xy: float = 0.05
    observation_sigma_psi: float = 0.05
    cameras: sim3.SimulationConfig = dataclasses.field(default_factory=sim3.SimulationConfig)
    withhold_map: float = 0.0
    move_map: float = 0.0
    move_distance: float = DEFAULT_MOVE_DISTANCE_M
    no_map: bool = False

    def __post_init__(self) -> None:
        names = self.sensor_names()
        _require(bool(names) and all(n in SENSORS for n in names), "sensors", f"a comma-separated list of {', '.join(SENSORS)}", self.sensors)
        _require(self.poses >= 2, "poses", "at least 2", self.poses)
        _require(self.landmarks is None or 0 <= self.landmarks <= MAX_LANDMARKS, "landmarks", f"a count in 0..{MAX_LANDMARKS}", self.landmarks)
        _require(self.region is None or 0 < self.region <= sim3.MAX_LENGTH_M, "region", "a positive length", self.region)
        _require(0 <= self.min_range < self.max_range <= sim3.MAX_LENGTH_M, "max-range", f"more than min-range = {self.min_range}", self.max_range)
        _require(0 < self.fov_half_angle_deg <= 180, "fov-half-angle-deg", "in (0, 180] for a planar sensor", self.fov_half_angle_deg)
        _require(0 < self.detection_probability <= 1, "detection-probability", "in (0, 1]", self.detection_probability)
        _require(0 <= self.clutter_fraction < 1, "clutter-fraction", "in [0, 1)", self.clutter_fraction)
        _require(self.visible_per_pose > 0, "visible-per-pose", "> 0", self.visible_per_pose)
        for name in ("odometry_sigma_xy", "odometry_sigma_theta", "observation_sigma_xy", "observation_sigma_psi"):
            _require(0 < getattr(self, name) <= 1.0, name.replace("_", "-"), "in (0, 1]", getattr(self, name))
        problem = map_edit_problem(self.withhold_map, self.move_map, self.move_distance, self.no_map, sim3.MAX_LENGTH_M)
        if problem is not None:
            _require(False, problem[0].replace("_", "-"), *problem[1:])

    def sensor_names(self) -> list[str]:
        return [name.strip() for name in str(self.sensors).split(",") if name.strip()]

    @property
    def region_side_m(self) -> float:
        return self.region if self.region is not None else max(4.0, round(1.3 * math.sqrt(self.poses)))


def _require(ok: bool, name: str, expected: str, found: object) -> None:
    if not ok:
        raise sim3.SimulationOptionError(name, f"expected {expected}, found {found!r}")


@dataclass(frozen=True)
class _Planar:
    """Observations being built: pose index, landmark id, kind (K,), measurement (K, 3)."""

    pose_index: np.ndarray
    landmark: np.ndarray
    kind: np.ndarray
    z: np.ndarray


def simulate_planar(config: PlanarSimulationConfig, *, seed: int) -> Dataset:
    """A planar world with ground truth for every pose, deterministic for a seed; its map edited
    as the config says once the whole world is made (``camloc.simulate_map``)."""
    if edits_map(config):
        return edit_map(simulate_planar(without_map_edits(config), seed=seed), config, seed=seed).dataset
    rng_path, rng_odom, rng_map, rng_obs, rng_cam = np.random.default_rng(seed).spawn(5)
    x_true = planar_path(config.poses, config.region_side_m, rng_path)
    T_true = planar.lift(x_true)
    names = config.sensor_names()
    maps, parts = [], []
    for kind, name in ((measurement.POINT2, "points"), (measurement.MARKER, "markers")):
        if name in names:
            xy, heading = place_planar_landmarks(x_true, config, rng_map, marker=kind == measurement.MARKER)
            maps.append((xy, heading, LANDMARK_MARKER if kind == measurement.MARKER else LANDMARK_POINT2))
    cameras, camera_obs = {}, None
    if "cameras" in names:
        cameras, landmark_xyz, camera_obs = _camera_part(T_true, config.cameras, rng_cam)
        maps.append((landmark_xyz, np.full(len(landmark_xyz), np.nan), LANDMARK_POINT3))
    landmark_xyz, heading, landmark_kind = _stack_maps(maps)
    for xy_kind in (measurement.POINT2, measurement.MARKER):
        wanted = LANDMARK_MARKER if xy_kind == measurement.MARKER else LANDMARK_POINT2
        rows = np.flatnonzero(landmark_kind == wanted)
        if rows.size:
            parts.append(detect_planar(x_true, landmark_xyz[rows, :2], heading[rows], rows, xy_kind, config, rng_obs))
    pose_base = sim3._power_of_ten_above(len(landmark_xyz), minimum=1000)
    clutter_base = sim3._power_of_ten_above(pose_base + config.poses, minimum=10000)
    parts = [add_clutter(part, x_true.shape[0], clutter_base + 100000 * i, config, rng_obs) for i, part in enumerate(parts)]
    odom_T, odom_info = noisy_planar_odometry(x_true, config, rng_odom)
    return _dataset(config, seed, x_true, odom_T, odom_info, cameras, landmark_xyz, heading, landmark_kind, parts, camera_obs, pose_base)


def planar_path(n: int, side: float, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) true planar poses (model card: Path), starting at the origin heading along x."""
    x = np.zeros((n, 3))
    rate = 0.0
    half = side / 2.0
    for k in range(1, n):
        rate = 0.8 * rate + 0.25 * rng.standard_normal()
        heading = x[k - 1, 2]
        if np.max(np.abs(x[k - 1, :2])) > 0.8 * half:  # near the edge: turn toward the centre
            toward = math.atan2(-x[k - 1, 1], -x[k - 1, 0])
            rate = 0.5 * float(planar.wrap(toward - heading))
        step = rng.uniform(0.3, 0.7)
        x[k] = planar.compose(x[k - 1], np.array([step, 0.0, float(np.clip(rate, -0.8, 0.8))]))
    return x


def place_planar_landmarks(x_true: np.ndarray, config: PlanarSimulationConfig, rng: np.random.Generator,
                           *, marker: bool) -> tuple[np.ndarray, np.ndarray]:
    """Landmarks (L, 2) uniform over the path's bounding box grown by the range, and headings (L,)
    (markers; NaN for points): as many as give ``visible_per_pose`` in view (model card)."""
    low = x_true[:, :2].min(axis=0) - config.max_range
    high = x_true[:, :2].max(axis=0) + config.max_range
    view = math.radians(config.fov_half_angle_deg) * (config.max_range**2 - config.min_range**2)
    if marker:
        view *= MARKER_FACING_DEG / 180.0  # a marker faces only some of the poses that have it in view
    count = config.landmarks
    if count is None:
        count = int(min(MAX_LANDMARKS, round(config.visible_per_pose * float(np.prod(high - low)) / view)))
    xy = rng.uniform(low, high, size=(count, 2))
    heading = rng.uniform(-math.pi, math.pi, size=count) if marker else np.full(count, np.nan)
    return xy, heading


def in_view(x: np.ndarray, landmark_xy: np.ndarray, heading: np.ndarray, config: PlanarSimulationConfig, *, marker: bool) -> np.ndarray:
    """(M,) bool: which landmarks the planar sensor at x sees (range, field of view; a marker only
    from in front of its face)."""
    p = planar.robot_points(x, landmark_xy)
    distance = np.hypot(p[:, 0], p[:, 1])
    seen = (distance >= config.min_range) & (distance <= config.max_range)
    seen &= np.abs(np.arctan2(p[:, 1], p[:, 0])) <= math.radians(config.fov_half_angle_deg)
    if marker:  # the face looks along the heading: the robot must be within the facing cone of it
        to_robot = np.arctan2(x[1] - landmark_xy[:, 1], x[0] - landmark_xy[:, 0])
        seen &= np.abs(planar.wrap(to_robot - heading)) <= math.radians(MARKER_FACING_DEG)
    return seen


def detect_planar(x_true: np.ndarray, landmark_xy: np.ndarray, heading: np.ndarray, ids: np.ndarray, kind: int,
                  config: PlanarSimulationConfig, rng: np.random.Generator) -> _Planar:
    """Noisy observations of ``kind`` of the landmarks in view at every pose but the first."""
    marker = kind == measurement.MARKER
    pose_index, landmark, z = [], [], []
    sigma = np.array([config.observation_sigma_xy, config.observation_sigma_xy, config.observation_sigma_psi if marker else 0.0])
    for k in range(1, x_true.shape[0]):
        seen = np.flatnonzero(in_view(x_true[k], landmark_xy, heading, config, marker=marker))
        seen = seen[rng.random(seen.size) < config.detection_probability]
        z_true, _ = planar.observe_planar(x_true[k], landmark_xy[seen], heading[seen], kind)
        z_k = z_true + rng.standard_normal(z_true.shape) * sigma
        if marker:
            z_k[:, 2] = planar.wrap(z_k[:, 2])
        pose_index.append(np.full(seen.size, k)), landmark.append(ids[seen]), z.append(z_k)
    return _Planar(np.concatenate(pose_index).astype(np.int64), np.concatenate(landmark).astype(np.int64),
                   np.full(sum(map(len, landmark)), kind, np.int64), np.concatenate(z).reshape(-1, 3))


def add_clutter(obs: _Planar, num_poses: int, first_id: int, config: PlanarSimulationConfig, rng: np.random.Generator) -> _Planar:
    """``obs`` and clutter, ``clutter_fraction`` of the whole: uniform in the sensor's view."""
    f = config.clutter_fraction
    count = round(obs.pose_index.size * f / (1.0 - f))
    if count == 0:
        return obs
    distance = np.sqrt(rng.uniform(config.min_range**2, config.max_range**2, count))
    bearing = rng.uniform(-1.0, 1.0, count) * math.radians(config.fov_half_angle_deg)
    z = np.zeros((count, 3))
    z[:, 0], z[:, 1] = distance * np.cos(bearing), distance * np.sin(bearing)
    if obs.kind.size and obs.kind[0] == measurement.MARKER:
        z[:, 2] = rng.uniform(-math.pi, math.pi, count)
    kind = obs.kind[0] if obs.kind.size else measurement.POINT2
    return _Planar(np.concatenate([obs.pose_index, rng.integers(1, num_poses, count)]),
                   np.concatenate([obs.landmark, first_id + np.arange(count)]),
                   np.concatenate([obs.kind, np.full(count, kind)]), np.concatenate([obs.z, z]))


def noisy_planar_odometry(x_true: np.ndarray, config: PlanarSimulationConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Measured increments (N-1, 4, 4), lifted, and their (N-1, 3, 3) information: the true
    increment u with ``compose(u_measured, w) = u`` (model card: Odometry)."""
    sigma = np.array([config.odometry_sigma_xy, config.odometry_sigma_xy, config.odometry_sigma_theta])
    increments = np.empty((x_true.shape[0] - 1, 3))
    for k in range(x_true.shape[0] - 1):
        u = planar.between(x_true[k], x_true[k + 1])
        w = rng.standard_normal(3) * sigma
        increments[k] = planar.compose(u, planar.between(w, np.zeros(3)))  # u Exp(w)^-1
    info = np.broadcast_to(np.diag(1.0 / sigma**2), (increments.shape[0], 3, 3)).copy()
    return planar.lift(increments), sim3._rounded(info)


def _camera_part(T_true: np.ndarray, cameras: sim3.SimulationConfig, rng: np.random.Generator):
    """3-D cameras on the planar robot (``camloc.simulate``'s models): cameras by id, the 3-D map
    (L, 3), and their noisy observations (``_Planar`` with camera ids in ``landmark``'s place
    kept apart: a tuple of (observations, camera ids))."""
    specs = sim3.make_cameras(cameras)
    landmark_xyz = sim3.place_landmarks(T_true, specs, cameras, rng)
    obs = sim3.detect(T_true, specs, landmark_xyz, cameras, rng)
    kind_of = {spec.camera.id: spec.kind for spec in specs}
    kinds = np.array([kind_of[int(c)] for c in obs.camera], dtype=np.int64)
    info = sim3.observation_info(cameras, kinds)
    z = sim3.add_observation_noise(sim3.as_measured(obs.uvd, kinds), info, cameras, rng, kinds)
    keep = sim3.inside_images(z, obs.camera, specs)
    part = _Planar(obs.pose_index[keep], obs.landmark[keep], kinds[keep], z[keep])
    return {spec.camera.id: spec.camera for spec in specs}, landmark_xyz, (part, obs.camera[keep])


def _stack_maps(maps: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One map of the planar sensors' landmarks and the cameras' 3-D points: xyz (L, 3) (planar at
    z = 0), headings (L,), kinds (L,)."""
    xyz = [np.column_stack([m[0][:, :2], m[0][:, 2] if m[0].shape[1] == 3 else np.zeros(len(m[0]))]) for m in maps]
    if not xyz:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64)
    return (np.concatenate(xyz), np.concatenate([m[1] for m in maps]),
            np.concatenate([np.full(len(m[0]), m[2], np.int64) for m in maps]))


def _dataset(config, seed, x_true, odom_T, odom_info, cameras, landmark_xyz, heading, landmark_kind, parts, camera_obs, pose_base) -> Dataset:
    """The planar ``Dataset`` of the simulated pieces, observations ordered by pose."""
    pose_index = [p.pose_index for p in parts]
    landmark = [p.landmark for p in parts]
    kind = [p.kind for p in parts]
    z = [p.z for p in parts]
    camera = [np.full(p.pose_index.size, measurement.ROBOT_FRAME_SENSOR, np.int64) for p in parts]
    if camera_obs is not None:
        part, camera_ids = camera_obs
        offset = int(np.count_nonzero(landmark_kind != LANDMARK_POINT3))  # the 3-D points come last in the map
        pose_index.append(part.pose_index), landmark.append(part.landmark + offset), kind.append(part.kind)
        z.append(part.z), camera.append(camera_ids)
    pose_index, landmark, kind, z, camera = (np.concatenate(c) if c else np.zeros(0, np.int64) for c in (pose_index, landmark, kind, z, camera))
    z = z.reshape(-1, 3)
    order = np.lexsort((camera, pose_index))
    info = np.zeros((order.size, 3, 3))
    for code in np.unique(kind):
        mine = kind == code
        info[mine] = _information(config, int(code), camera_obs)
    truth_xyz, truth_quat = geometry.pose_to_quat(planar.lift(x_true))
    odom_xyz, odom_quat = geometry.pose_to_quat(odom_T)
    info = info[order]
    return Dataset(
        source=f"simulate(robot=planar, sensors={config.sensors}, poses={config.poses}, seed={seed})",
        cameras=cameras, landmark_ids=np.arange(len(landmark_xyz), dtype=np.int64), landmark_xyz=landmark_xyz,
        pose_ids=pose_base + np.arange(x_true.shape[0], dtype=np.int64), start_xyz=truth_xyz[0].copy(),
        start_quat_xyzw=truth_quat[0].copy(), truth_xyz=truth_xyz, truth_quat_xyzw=truth_quat,
        odom_translation=odom_xyz, odom_quat_xyzw=odom_quat, odom_info=odom_info,
        odom_cov=planar.lifted_cov(np.linalg.inv(odom_info)),
        obs_pose_index=pose_index[order].astype(np.int64), obs_camera=camera[order].astype(np.int64), obs_z=z[order],
        obs_info=info, obs_cov=observation_cov_from_info(info), obs_true_landmark=landmark[order].astype(np.int64),
        obs_kind=kind[order].astype(np.int64), planar=True, landmark_kind=landmark_kind, landmark_heading=heading,
    )


def _information(config: PlanarSimulationConfig, kind: int, camera_obs) -> np.ndarray:
    """(3, 3) the information written for an observation of ``kind`` (a point2's inert third row:
    unit information)."""
    if kind in measurement.PLANAR_KINDS:
        sigma_third = config.observation_sigma_psi if kind == measurement.MARKER else 1.0
        return sim3._rounded(np.diag(1.0 / np.array([config.observation_sigma_xy, config.observation_sigma_xy, sigma_third]) ** 2))
    return sim3.observation_info(config.cameras, np.array([kind]))[0]


def planar_simulation_config(options: dict, cameras: sim3.SimulationConfig) -> PlanarSimulationConfig:
    """The ``PlanarSimulationConfig`` of ``camloc simulate --robot planar``'s options named as on
    its command line (None: not given), ``cameras`` the 3-D cameras' config.
    ``SimulationOptionError`` for an option a planar world does not take or out of range."""
    names = {f.name for f in dataclasses.fields(PlanarSimulationConfig)} - {"cameras"}
    values = {}
    for name, value in options.items():
        field = name.replace("-", "_")
        if value is None:
            continue
        if field not in names:
            raise sim3.SimulationOptionError(name, "does not apply to --robot planar (camloc simulate --help says which do)")
        values[field] = value
    return PlanarSimulationConfig(**values, cameras=cameras)


# the options a planar world's 3-D cameras take (``camloc.simulate.SimulationConfig``, by their
# command-line names); the planar sensors take ``PlanarSimulationConfig``'s
CAMERA_OPTIONS = ("cameras", "intrinsics", "measurement", "observation-sigma-uv", "observation-sigma-depth",
                  "observation-sigma-scale")
ROBOTS = ("3d", "planar")


def world_config(options: dict) -> sim3.SimulationConfig | PlanarSimulationConfig | TagWorldConfig:
    """The config of ``camloc simulate``'s options by command-line name (None: not given), a
    planar world's where ``robot`` is "planar" (its ``sensors`` the planar sensors), a 3-D
    world of tags' with ``tag-sigma-deg``, else ``camloc.simulate.simulation_config``'s.
    ``SimulationOptionError`` names a bad option."""
    options = {name: value for name, value in options.items() if value is not None}
    robot = options.pop("robot", "3d")
    sensors = options.pop("sensors", None)
    if robot not in ROBOTS:
        raise sim3.SimulationOptionError("robot", f"expected one of {', '.join(ROBOTS)}, found {robot!r}")
    tag_sigma_deg = options.pop("tag-sigma-deg", None)
    if robot == "3d":
        if sensors is not None:
            raise sim3.SimulationOptionError("sensors", "applies only to a planar robot (robot planar); a 3-D robot's "
                                             "sensors are its cameras")
        config = sim3.simulation_config(options)
        return config if tag_sigma_deg is None else tag_world_config(config, tag_sigma_deg)
    if tag_sigma_deg is not None:
        raise sim3.SimulationOptionError("tag-sigma-deg", "applies only to a 3-D robot (robot 3d)")
    cameras = sim3.simulation_config({name: value for name, value in options.items() if name in CAMERA_OPTIONS})
    planar_options = {name: value for name, value in options.items() if name not in CAMERA_OPTIONS}
    return planar_simulation_config({**planar_options, **({"sensors": sensors} if sensors is not None else {})}, cameras)


def simulate_world(config: sim3.SimulationConfig | PlanarSimulationConfig | TagWorldConfig, *, seed: int) -> Dataset:
    """``simulate_planar``, ``camloc.simulate_tags.simulate_tags`` or ``camloc.simulate.simulate``,
    by the config's kind."""
    if isinstance(config, PlanarSimulationConfig):
        return simulate_planar(config, seed=seed)
    if isinstance(config, TagWorldConfig):
        from camloc.simulate_tags import simulate_tags

        return simulate_tags(config.world, seed=seed, sigma_rad=math.radians(config.sigma_deg))
    return sim3.simulate(config, seed=seed)


@dataclass(frozen=True)
class TagWorldConfig:
    """A 3-D world of tags (``camloc.simulate_tags``): the world's config and the orientation's
    noise, degrees per axis (``camloc simulate --tag-sigma-deg``; ``tag-sigma-deg`` in a sweep)."""

    world: sim3.SimulationConfig
    sigma_deg: float


def tag_world_config(world: sim3.SimulationConfig, sigma_deg) -> TagWorldConfig:
    """``TagWorldConfig``; ``SimulationOptionError`` for a noise that is not a number > 0."""
    if isinstance(sigma_deg, bool) or not isinstance(sigma_deg, (int, float)) or not sigma_deg > 0.0 or not math.isfinite(sigma_deg):
        raise sim3.SimulationOptionError("tag-sigma-deg", f"expected a standard deviation > 0 degrees, found {sigma_deg!r}")
    return TagWorldConfig(world, float(sigma_deg))
