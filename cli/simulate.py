"""``camloc simulate``: write a simulated g2o dataset (options map one to one onto
``camloc.simulate.SimulationConfig``)."""

from __future__ import annotations

import json
from enum import Enum
from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape

from camloc.cli.common import console, handles_errors


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


@handles_errors
def simulate(
    output: Path = typer.Option(..., "--output", "-o", help="The g2o file to write (written whole or not at all)."),
    trajectory: TrajectoryChoice = typer.Option(
        TrajectoryChoice.grid, help="grid: 1 m steps and 90 deg turns on flat ground, like the real file; "
        "smooth3d: smooth 3D motion, roll/pitch up to --max-tilt-deg (default 18); aerial: a flying "
        "vehicle looking around, roll/pitch up to --max-tilt-deg (default 60)."
    ),
    poses: int = typer.Option(100, help="Number of poses (at least 2)."),
    landmarks: Optional[int] = typer.Option(
        None, help="Number of map landmarks. Default: the real file's density, as many as give 3.62 "
        "visible landmarks per camera and pose (the real file: 144 for 100 poses).", show_default=False
    ),
    dense: bool = typer.Option(False, "--dense", help="A dense map: 5x the default density over the same region. Default: off."),
    region: Optional[float] = typer.Option(
        None, help="Side of the square region the path stays in, metres. Default: 1.3 x sqrt(poses), "
        "at least 4 (13 m for 100 poses, like the real file).", show_default=False
    ),
    max_tilt_deg: Optional[float] = typer.Option(
        None, help="Roll and pitch amplitude, degrees, in (0, 90]; 85-90 passes near the Euler "
        "singularity. Default: 18 for smooth3d, 60 for aerial; grid ignores it.", show_default=False
    ),
    cameras: int = typer.Option(1, help="Number of cameras, 1 to 4: ids 0 forward (the real mount), 1 "
                                "backward, 2 left, 3 right."),
    intrinsics: IntrinsicsChoice = typer.Option(
        IntrinsicsChoice.normalized, help="normalized: fx=fy=1, cx=cy=0.5, image not clipped (the real "
        "file); pixel: fx=fy=525, cx=319.5, cy=239.5, only detections inside the 640x480 image."
    ),
    range_kind: RangeKindChoice = typer.Option(
        RangeKindChoice.distance, help="What --min-range/--max-range bound: distance from the camera "
        "centre (the real file's rule) or depth (camera z)."
    ),
    min_range: float = typer.Option(0.5, help="Nearest visible landmark, metres."),
    max_range: float = typer.Option(2.0, help="Farthest visible landmark, metres."),
    fov_half_angle_deg: float = typer.Option(45.0, help="Visible cone around the optical axis, degrees, in (0, 90)."),
    detection_probability: float = typer.Option(1.0, help="Chance that a visible landmark is detected, in (0, 1]."),
    max_observations_per_pose: Optional[int] = typer.Option(
        None, help="Keep at most this many detections per pose (a random subset). Default: no cap.",
        show_default=False
    ),
    observe_first_pose: bool = typer.Option(
        False, "--observe-first-pose", help="Also detect landmarks from the first pose (the real file does not). Default: off."
    ),
    clutter_fraction: float = typer.Option(
        0.0, help="Fraction of all observations that are clutter (ids absent from the map, random "
        "measurements in the visible volume), in [0, 1)."
    ),
    outlier_fraction: float = typer.Option(
        0.0, help="Fraction of real detections whose measurement is replaced by a random one in the "
        "visible volume, in [0, 1); they keep the true landmark id."
    ),
    odometry_sigma_translation: float = typer.Option(
        0.1, help="Odometry translation std per axis, metres (information 100, like the real file)."
    ),
    odometry_sigma_rotation: float = typer.Option(
        0.02, help="Odometry rotation-vector std per axis, radians (information 10000 on g2o's "
        "quaternion vector part, like the real file)."
    ),
    odometry_sigma_scale: float = typer.Option(1.0, help="Multiplies both odometry sigmas; 0: exact odometry."),
    observation_sigma_uv: Optional[float] = typer.Option(
        None, help="Std of u and v, image units. Default: 1/sqrt(1000) = 0.0316 for normalized "
        "cameras (information 1000, like the real file), 1 pixel for pixel cameras.", show_default=False
    ),
    observation_sigma_depth: float = typer.Option(
        0.03162277660168379, help="Std of the depth, metres: 1/sqrt(1000), information 1000 like the real file."
    ),
    observation_sigma_scale: float = typer.Option(1.0, help="Multiplies the observation sigmas; 0: exact observations."),
    seed: int = typer.Option(0, min=0, help="Seed of the random generator; the same seed gives the same file."),
    json_output: bool = typer.Option(False, "--json", help="Print the summary as JSON instead of a line. Default: off."),
) -> None:
    """Simulate a robot, a landmark map, noisy odometry and camera detections; write a g2o file.

    Zero sigmas are simulated exactly and written as a large finite information (1e12).
    """
    from camloc.g2o import write_g2o
    from camloc.simulate import SimulationConfig, SimulationOptionError, simulate_labelled, simulation_config

    # The options are named after the config's fields: pass each one on by its command-line name,
    # enums as their text.
    options = {name.replace("_", "-"): value.value if isinstance(value, Enum) else value
               for name, value in locals().items() if name in SimulationConfig.__dataclass_fields__}
    try:
        config = simulation_config(options)
    except SimulationOptionError as error:
        raise typer.BadParameter(error.reason, param_hint=f"--{error.field}") from None
    simulation = simulate_labelled(config, seed=seed)
    write_g2o(simulation.dataset, output)
    summary = _summary(simulation, output, seed)
    if json_output:
        console.print_json(json.dumps(summary))
    else:
        console.print(
            f"[bold]{escape(str(output))}[/]: {summary['poses']} poses, {summary['landmarks']} landmarks, "
            f"{summary['observations']} observations ({summary['clutter']} clutter, "
            f"{summary['outliers']} outliers), {summary['cameras']} camera(s) from {summary['source']}",
            highlight=False, soft_wrap=True,
        )


def _summary(simulation, output: Path, seed: int) -> dict:
    dataset = simulation.dataset
    return {
        "path": str(output),
        "source": dataset.source,
        "seed": seed,
        "poses": dataset.num_poses,
        "landmarks": int(dataset.landmark_ids.shape[0]),
        "observations": dataset.num_observations,
        "clutter": int(simulation.is_clutter.sum()),
        "outliers": int(simulation.is_outlier.sum()),
        "cameras": len(dataset.cameras),
    }
