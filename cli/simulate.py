"""``camloc simulate``: write a simulated g2o dataset (options map one to one onto
``camloc.simulate.SimulationConfig``)."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape

from camloc.cli.common import (
    console,
    echo_json,
    force_option,
    json_option,
    library_option,
    quiet_option,
    with_default,
)


class RobotChoice(str, Enum):
    three_d = "3d"
    planar = "planar"


class TrajectoryChoice(str, Enum):
    grid = "grid"
    smooth3d = "smooth3d"
    aerial = "aerial"


class IntrinsicsChoice(str, Enum):
    normalized = "normalized"
    pixel = "pixel"


class RangeKindChoice(str, Enum):
    distance = "distance"
    depth = "depth"


# The command's arguments and options, in its signature's order (their help is ``--help``'s text).
_OUTPUT = typer.Option(..., "--output", "-o", help="The g2o file to write (whole or not at all; missing "
                       "parent folders are created); an existing file is refused unless --force. With "
                       "--withhold-map, --move-map or --no-map, also <stem>.true-map.g2o beside it: the same world "
                       "with its true, complete map (for 'camloc eval --true-map' and 'camloc plot --true-map'); "
                       "both files are written or neither.",
                       show_default=False)
_FORCE = force_option("the --output file (and its .true-map.g2o)")
_ROBOT = typer.Option(RobotChoice.three_d, help=with_default(
    "3d: a robot with 3-D cameras (VERTEX_SE3:QUAT, EDGE_SE3:QUAT); planar: a robot on a floor (VERTEX_SE2, "
    "EDGE_SE2; a unicycle path, camloc/simulate_planar.py) carrying the --sensors given. With planar, "
    "--poses, --landmarks (per planar sensor), --region, --min-range/--max-range and --fov-half-angle-deg "
    "(of the planar sensors; default 0.3-3 m, 60 deg), --detection-probability (default 0.9) and "
    "--clutter-fraction apply to the planar sensors, --cameras, --intrinsics, --measurement and the "
    "observation sigmas to the 3-D cameras, --withhold-map, --move-map, --move-distance and --no-map to the whole map "
    "(planar landmarks move in the floor's plane); the other options are refused."), show_default=False)
_SENSORS = typer.Option(None, help=with_default(
    "With --robot planar (refused without it): what the robot observes, comma-separated: points (EDGE_SE2_XY: "
    "(x, y) of VERTEX_XY landmarks in the robot frame, like a laser's detections), markers (EDGE_SE2_MARKER: the "
    "planar pose (x, y, psi) of VERTEX_MARKER_SE2 markers in the robot frame, each seen only from in front of its "
    "face), cameras (3-D cameras on the robot, EDGE_PROJECT_* of VERTEX_TRACKXYZ landmarks).",
    "planar_simulation.sensors"), show_default=False)
_TAG_SIGMA_DEG = typer.Option(None, min=0.0, help=with_default(
    "With --robot 3d: every landmark a tag (VERTEX_TAG, a random orientation) and every depth or pixel detection "
    "of one also measuring its orientation in the camera, with this standard deviation per axis, degrees "
    "(EDGE_PROJECT_TAG; with --measurement pixel, a camera without depth: EDGE_PROJECT_TAG_UV; "
    "camloc/simulate_tags.py). Without it: points (VERTEX_TRACKXYZ)."), show_default=False)
_TRAJECTORY = library_option(
    "grid: 1 m steps and 90 deg turns on flat ground, like the real file; smooth3d: "
    "smooth 3D motion, roll/pitch up to --max-tilt-deg (default 18); aerial: a flying vehicle looking "
    "around, roll/pitch up to --max-tilt-deg (default 60).",
    "simulation.trajectory"
)
_POSES = library_option(
    "Number of poses (at least 2).",
    "simulation.poses"
)
_LANDMARKS = typer.Option(
    None, help="Number of map landmarks. Default: the real file's density, as many as give 3.62 "
    "visible landmarks per camera and pose (the real file: 144 for 100 poses).", show_default=False
)
_DENSE = library_option(
    "A dense map: 5x the default density over the same region.",
    "simulation.dense", "--dense"
)
_REGION = typer.Option(
    None, help="Side of the square region the path stays in, metres. Default: 1.3 x sqrt(poses), "
    "at least 4 (13 m for 100 poses, like the real file).", show_default=False
)
_MAX_TILT_DEG = typer.Option(
    None, help="Roll and pitch amplitude, degrees, in (0, 90]; 85-90 passes near the Euler "
    "singularity. Default: 18 for smooth3d, 60 for aerial; grid ignores it.", show_default=False
)
_CAMERAS = library_option(
    "Number of cameras, 1 to 4: ids 0 forward (the "
    "real mount), 1 backward, 2 left, 3 right.",
    "simulation.cameras"
)
_INTRINSICS = library_option(
    "normalized: fx=fy=1, cx=cy=0.5, image not clipped (the real file); pixel: "
    "fx=fy=525, cx=319.5, cy=239.5, only detections inside the 640x480 image.",
    "simulation.intrinsics"
)
_MEASUREMENT = library_option(
    "What the cameras measure: depth (u, v, depth: EDGE_PROJECT_DEPTH), pixel (u, v "
    "only, a monocular camera: EDGE_PROJECT_UV) or disparity (u, v, 1/depth: "
    "EDGE_PROJECT_DISPARITY); one for every camera, or one per camera, comma-separated "
    "(depth,pixel).",
    "simulation.measurement"
)
_RANGE_KIND = library_option(
    "What --min-range/--max-range bound: distance from the camera centre (the real "
    "file's rule) or depth (camera z).",
    "simulation.range_kind"
)
_MIN_RANGE = library_option(
    "Nearest visible landmark, metres.",
    "simulation.min_range"
)
_MAX_RANGE = library_option(
    "Farthest visible landmark, metres.",
    "simulation.max_range"
)
_FOV_HALF_ANGLE_DEG = library_option(
    "Visible cone around the optical axis, degrees, in (0, 90).",
    "simulation.fov_half_angle_deg"
)
_DETECTION_PROBABILITY = library_option(
    "Chance that a visible landmark is detected, in (0, 1].",
    "simulation.detection_probability"
)
_MAX_OBSERVATIONS_PER_POSE = typer.Option(
    None, help="Keep at most this many detections per pose (a random subset). Default: no cap.",
    show_default=False
)
_OBSERVE_FIRST_POSE = library_option(
    "Also detect landmarks from the first pose (the real file "
    "does not).",
    "simulation.observe_first_pose", "--observe-first-pose"
)
_CLUTTER_FRACTION = library_option(
    "Fraction of all observations that are clutter (ids absent from the map, random "
    "measurements in the visible volume), in [0, 1).",
    "simulation.clutter_fraction"
)
_OUTLIER_FRACTION = library_option(
    "Fraction of real detections whose measurement is replaced by a random one in "
    "the visible volume, in [0, 1); they keep the true landmark id.",
    "simulation.outlier_fraction"
)
_ODOMETRY_SIGMA_TRANSLATION = library_option(
    "Odometry translation std per axis, metres (the real file: information 100).",
    "simulation.odometry_sigma_translation"
)
_ODOMETRY_SIGMA_ROTATION = library_option(
    "Odometry rotation-vector std per axis, radians (the real file: information "
    "10000 on g2o's quaternion vector part).",
    "simulation.odometry_sigma_rotation"
)
_ODOMETRY_SIGMA_SCALE = library_option(
    "Multiplies both odometry sigmas; 0: exact odometry.",
    "simulation.odometry_sigma_scale"
)
_OBSERVATION_SIGMA_UV = typer.Option(
    None, help="Std of u and v, image units. Default: 1/sqrt(1000) = 0.0316 for normalized "
    "cameras (information 1000, like the real file), 1 pixel for pixel cameras.", show_default=False
)
_OBSERVATION_SIGMA_DEPTH = library_option(
    "Std of the depth, metres (the real file: information 1000, 1/sqrt(1000)).",
    "simulation.observation_sigma_depth"
)
_OBSERVATION_SIGMA_SCALE = library_option(
    "Multiplies the observation sigmas; 0: exact observations.",
    "simulation.observation_sigma_scale"
)
_WITHHOLD_MAP = library_option(
    "Share of the landmarks left out of the file's map, in [0, 1] (a map from a partial survey); their "
    "detections stay, with their true ids, so they read as ids absent from the map, as clutter does. "
    "Writes the true map too (see --output).",
    "simulation.withhold_map", metavar="FRACTION"
)
_MOVE_MAP = library_option(
    "Share of the landmarks written --move-distance metres from their true position, in a random "
    "direction, in [0, 1 - --withhold-map] (moved since the survey); the detections are of the true "
    "positions. Writes the true map too (see --output).",
    "simulation.move_map", metavar="FRACTION"
)
_MOVE_DISTANCE = library_option(
    "How far a landmark of --move-map is written from its true position, metres.",
    "simulation.move_distance", metavar="METRES"
)
_NO_MAP = library_option(
    "Write no landmark at all (no survey): the detections stay, with their true ids. Writes the true "
    "map too (see --output).",
    "simulation.no_map", "--no-map"
)
_SEED = typer.Option(0, min=0, help=with_default("Seed of the random generator; the same seed gives the "
                                                 "same file."), show_default=False)
_JSON_OUTPUT = json_option("the summary", instead="a line")
_QUIET = quiet_option()


def simulate(
    output: Path = _OUTPUT,
    force: bool = _FORCE,
    robot: RobotChoice = _ROBOT,
    sensors: Optional[str] = _SENSORS,
    tag_sigma_deg: Optional[float] = _TAG_SIGMA_DEG,
    trajectory: Optional[TrajectoryChoice] = _TRAJECTORY,
    poses: Optional[int] = _POSES,
    landmarks: Optional[int] = _LANDMARKS,
    dense: Optional[bool] = _DENSE,
    region: Optional[float] = _REGION,
    max_tilt_deg: Optional[float] = _MAX_TILT_DEG,
    cameras: Optional[int] = _CAMERAS,
    intrinsics: Optional[IntrinsicsChoice] = _INTRINSICS,
    measurement: Optional[str] = _MEASUREMENT,
    range_kind: Optional[RangeKindChoice] = _RANGE_KIND,
    min_range: Optional[float] = _MIN_RANGE,
    max_range: Optional[float] = _MAX_RANGE,
    fov_half_angle_deg: Optional[float] = _FOV_HALF_ANGLE_DEG,
    detection_probability: Optional[float] = _DETECTION_PROBABILITY,
    max_observations_per_pose: Optional[int] = _MAX_OBSERVATIONS_PER_POSE,
    observe_first_pose: Optional[bool] = _OBSERVE_FIRST_POSE,
    clutter_fraction: Optional[float] = _CLUTTER_FRACTION,
    outlier_fraction: Optional[float] = _OUTLIER_FRACTION,
    odometry_sigma_translation: Optional[float] = _ODOMETRY_SIGMA_TRANSLATION,
    odometry_sigma_rotation: Optional[float] = _ODOMETRY_SIGMA_ROTATION,
    odometry_sigma_scale: Optional[float] = _ODOMETRY_SIGMA_SCALE,
    observation_sigma_uv: Optional[float] = _OBSERVATION_SIGMA_UV,
    observation_sigma_depth: Optional[float] = _OBSERVATION_SIGMA_DEPTH,
    observation_sigma_scale: Optional[float] = _OBSERVATION_SIGMA_SCALE,
    withhold_map: Optional[float] = _WITHHOLD_MAP,
    move_map: Optional[float] = _MOVE_MAP,
    move_distance: Optional[float] = _MOVE_DISTANCE,
    no_map: Optional[bool] = _NO_MAP,
    seed: int = _SEED,
    json_output: bool = _JSON_OUTPUT,
    quiet: bool = _QUIET,
) -> None:
    """Simulate a robot, a landmark map, noisy odometry and camera detections; write a g2o file.

    Zero sigmas are simulated exactly and written as a large finite information (1e12).
    """
    from camloc.atomic_files import refuse_existing_file
    from camloc.simulate import SimulationConfig, simulate_labelled
    from camloc.simulate_map import edits_map
    from camloc.simulate_planar import TagWorldConfig

    # The options are named after the config's fields: pass on each one given by its command-line
    # name, enums as their text; the others keep the config's defaults.
    options = {name.replace("_", "-"): value.value if isinstance(value, Enum) else value
               for name, value in locals().items() if name in SimulationConfig.__dataclass_fields__ and value is not None}
    config = _config(options, robot, sensors, tag_sigma_deg)
    tags = isinstance(config, TagWorldConfig)
    true_map = true_map_path(output) if edits_map(config.world if tags else config) else None
    for path in (output, true_map):
        if path is not None:
            refuse_existing_file(path, force=force)
    if tags:
        simulation = _tag_simulation(config.world, seed, config.sigma_deg)
    else:
        simulation = simulate_labelled(config, seed=seed) if robot != RobotChoice.planar else _planar_simulation(config, seed)
    _write(simulation, output, true_map)
    summary = _summary(simulation, output, seed, true_map)
    if echo_json(summary, enabled=json_output) or quiet:
        return
    counts = summary["counts"]
    console.print(
        f"[bold]{escape(str(output))}[/]: {counts['poses']} poses, {counts['landmarks']} landmarks, "
        f"{counts['observations']} observations ({counts['clutter']} clutter, "
        f"{counts['outliers']} outliers), {counts['cameras']} camera(s) from {escape(summary['description'])}",
        highlight=False, soft_wrap=True,
    )
    if true_map is not None:
        console.print(_map_line(summary["map"], true_map), highlight=False, soft_wrap=True)


def _config(options: dict, robot: RobotChoice, sensors: Optional[str], tag_sigma_deg: Optional[float]):
    """The simulation's config of the options given (``simulate_planar.world_config``: a planar
    world's, a world of tags' or a 3-D one's), a bad one refused as a bad parameter."""
    from camloc.simulate import SimulationOptionError
    from camloc.simulate_planar import world_config

    try:
        return world_config({**options, "robot": robot.value, "sensors": sensors, "tag-sigma-deg": tag_sigma_deg})
    except SimulationOptionError as error:
        raise typer.BadParameter(error.reason, param_hint=f"--{error.field.replace('_', '-')}") from None


# The true map's file beside a world whose map is edited: ``world.g2o`` -> ``world.true-map.g2o``.
TRUE_MAP_SUFFIX = ".true-map.g2o"


def true_map_path(output: Path) -> Path:
    """Where ``camloc simulate -o output`` writes the true map of an edited world."""
    return output.with_name(f"{output.stem if output.suffix.lower() == '.g2o' else output.name}{TRUE_MAP_SUFFIX}")


def _write(simulation, output: Path, true_map: Optional[Path]) -> None:
    """The world (and the whole world with its true map) written all or none."""
    from camloc.atomic_files import write_files_atomic
    from camloc.cli.interrupts import outputs_being_saved
    from camloc.g2o import g2o_text

    texts = {output: g2o_text(simulation.dataset)}
    if true_map is not None:
        texts[true_map] = g2o_text(simulation.map_edits.whole)
    with outputs_being_saved():
        write_files_atomic(list(texts), lambda path, handle: handle.write(texts[path].encode("utf-8")))


def _map_line(report: dict, true_map: Path) -> str:
    """``map: 72 of 144 landmarks withheld, 36 moved 0.3 m; true map: PATH``."""
    parts = [f"{report['withheld']} of {report['true_landmarks']} landmarks withheld"
             + (f" ({report['withheld_observations']} observations of them)" if report["withheld"] else "")]
    if report["moved"]:
        parts.append(f"{report['moved']} moved {report['move_distance']:g} m")
    return f"map: {', '.join(parts)}; true map: {escape(str(true_map))}"


def _labelled(config, seed: int, make):
    """A ``Simulation`` of a world made by another simulator than ``simulate_labelled`` (planar,
    tags; ``make(config)`` makes the world): no outliers, clutter told by the ids absent from the
    true map, the map edited as the config says once the whole world is made."""
    import numpy as np

    from camloc.simulate import Simulation
    from camloc.simulate_map import edit_map, edits_map, without_map_edits

    edits = edit_map(make(without_map_edits(config)), config, seed=seed) if edits_map(config) else None
    dataset = make(config) if edits is None else edits.dataset
    truth = dataset if edits is None else edits.whole
    clutter = ~np.isin(dataset.obs_true_landmark, truth.landmark_ids)
    return Simulation(dataset=dataset, is_outlier=np.zeros(dataset.num_observations, bool), is_clutter=clutter,
                      map_edits=edits)


def _tag_simulation(config, seed: int, sigma_deg: float):
    """A 3-D world of tags (``camloc.simulate_tags``), labelled as ``simulate_labelled`` labels one."""
    import math

    from camloc.simulate_tags import simulate_tags

    return _labelled(config, seed, lambda c: simulate_tags(c, seed=seed, sigma_rad=math.radians(sigma_deg)))


def _planar_simulation(config, seed: int):
    """A planar world as ``simulate_labelled`` gives a 3-D one (its clutter labelled by id)."""
    from camloc.simulate_planar import simulate_planar

    return _labelled(config, seed, lambda c: simulate_planar(c, seed=seed))


def _summary(simulation, output: Path, seed: int, true_map: Optional[Path]) -> dict:
    dataset = simulation.dataset
    edits = simulation.map_edits
    truth = dataset if edits is None else edits.whole
    withheld = 0 if edits is None else len(edits.withheld)
    moved = 0 if edits is None else len(edits.moved)
    return {
        "dataset": str(output),
        "description": dataset.source,
        "seed": seed,
        "counts": {
            "poses": dataset.num_poses,
            "landmarks": int(dataset.landmark_ids.shape[0]),
            "observations": dataset.num_observations,
            "cameras": len(dataset.cameras),
            "clutter": int(simulation.is_clutter.sum()),
            "outliers": int(simulation.is_outlier.sum()),
        },
        "true_map": None if true_map is None else str(true_map),
        "map": {
            "true_landmarks": int(truth.landmark_ids.shape[0]),
            "withheld": withheld,
            "moved": moved,
            "move_distance": float(edits.move_distance) if moved else None,
            "withheld_observations": 0 if edits is None else int(_count_of(dataset.obs_true_landmark, edits.withheld)),
        },
    }


def _count_of(ids, wanted) -> int:
    import numpy as np

    return int(np.count_nonzero(np.isin(ids, wanted)))
