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
                       "parent folders are created); an existing file is refused unless --force.",
                       show_default=False)
_FORCE = force_option("the --output file")
_ROBOT = typer.Option(RobotChoice.three_d, help=with_default(
    "3d: a robot with 3-D cameras (VERTEX_SE3:QUAT, EDGE_SE3:QUAT); planar: a robot on a floor (VERTEX_SE2, "
    "EDGE_SE2; a unicycle path, camloc/simulate_planar.py) carrying the --sensors given. With planar, "
    "--poses, --landmarks (per planar sensor), --region, --min-range/--max-range and --fov-half-angle-deg "
    "(of the planar sensors; default 0.3-3 m, 60 deg), --detection-probability (default 0.9) and "
    "--clutter-fraction apply to the planar sensors, and --cameras, --intrinsics, --measurement and the "
    "observation sigmas to the 3-D cameras; the other options are refused."), show_default=False)
_SENSORS = typer.Option("points", help=with_default(
    "With --robot planar: what the robot observes, comma-separated: points (EDGE_SE2_XY: (x, y) of VERTEX_XY "
    "landmarks in the robot frame, like a laser's detections), markers (EDGE_SE2_MARKER: the planar pose (x, y, "
    "psi) of VERTEX_MARKER_SE2 markers in the robot frame, each seen only from in front of its face), cameras "
    "(3-D cameras on the robot, EDGE_PROJECT_* of VERTEX_TRACKXYZ landmarks)."), show_default=False)
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
_SEED = typer.Option(0, min=0, help=with_default("Seed of the random generator; the same seed gives the "
                                                 "same file."), show_default=False)
_JSON_OUTPUT = json_option("the summary", instead="a line")
_QUIET = quiet_option()


def simulate(
    output: Path = _OUTPUT,
    force: bool = _FORCE,
    robot: RobotChoice = _ROBOT,
    sensors: str = _SENSORS,
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
    seed: int = _SEED,
    json_output: bool = _JSON_OUTPUT,
    quiet: bool = _QUIET,
) -> None:
    """Simulate a robot, a landmark map, noisy odometry and camera detections; write a g2o file.

    Zero sigmas are simulated exactly and written as a large finite information (1e12).
    """
    from camloc.g2o import write_g2o
    from camloc.atomic_files import refuse_existing
    from camloc.simulate import SimulationConfig, SimulationOptionError, simulate_labelled, simulation_config

    # The options are named after the config's fields: pass on each one given by its command-line
    # name, enums as their text; the others keep the config's defaults.
    options = {name.replace("_", "-"): value.value if isinstance(value, Enum) else value
               for name, value in locals().items() if name in SimulationConfig.__dataclass_fields__ and value is not None}
    try:
        if robot == RobotChoice.planar:
            from camloc.simulate_planar import world_config

            config = world_config({**options, "robot": "planar", "sensors": sensors})
        else:
            config = simulation_config(options)
    except SimulationOptionError as error:
        raise typer.BadParameter(error.reason, param_hint=f"--{error.field.replace('_', '-')}") from None
    if tag_sigma_deg is not None and robot == RobotChoice.planar:
        raise typer.BadParameter("applies only to --robot 3d", param_hint="--tag-sigma-deg")
    if tag_sigma_deg is not None and not tag_sigma_deg > 0.0:
        raise typer.BadParameter(f"expected a standard deviation > 0, found {tag_sigma_deg:g}", param_hint="--tag-sigma-deg")
    refuse_existing(output, force=force)
    if tag_sigma_deg is not None:
        simulation = _tag_simulation(config, seed, tag_sigma_deg)
    else:
        simulation = simulate_labelled(config, seed=seed) if robot != RobotChoice.planar else _planar_simulation(config, seed)
    write_g2o(simulation.dataset, output)
    summary = _summary(simulation, output, seed)
    if echo_json(summary, enabled=json_output) or quiet:
        return
    counts = summary["counts"]
    console.print(
        f"[bold]{escape(str(output))}[/]: {counts['poses']} poses, {counts['landmarks']} landmarks, "
        f"{counts['observations']} observations ({counts['clutter']} clutter, "
        f"{counts['outliers']} outliers), {counts['cameras']} camera(s) from {escape(summary['description'])}",
        highlight=False, soft_wrap=True,
    )


def _tag_simulation(config, seed: int, sigma_deg: float):
    """A 3-D world of tags (``camloc.simulate_tags``), labelled as ``simulate_labelled`` labels one."""
    import math

    import numpy as np

    from camloc.simulate import Simulation
    from camloc.simulate_tags import simulate_tags

    dataset = simulate_tags(config, seed=seed, sigma_rad=math.radians(sigma_deg))
    clutter = ~np.isin(dataset.obs_true_landmark, dataset.landmark_ids)
    return Simulation(dataset=dataset, is_outlier=np.zeros(dataset.num_observations, bool), is_clutter=clutter)


def _planar_simulation(config, seed: int):
    """A planar world as ``simulate_labelled`` gives a 3-D one (its clutter labelled by id)."""
    import numpy as np

    from camloc.simulate import Simulation
    from camloc.simulate_planar import simulate_planar

    dataset = simulate_planar(config, seed=seed)
    clutter = ~np.isin(dataset.obs_true_landmark, dataset.landmark_ids)
    return Simulation(dataset=dataset, is_outlier=np.zeros(dataset.num_observations, bool), is_clutter=clutter)


def _summary(simulation, output: Path, seed: int) -> dict:
    dataset = simulation.dataset
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
    }
