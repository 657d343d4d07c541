"""Planar robots (issue 37): the SE(2) filter on simulated planar worlds of every sensor kind.

    python benchmarks/planar.py targets [--seeds 5] [--poses 300]
    python benchmarks/planar.py filters [--seeds 5] [--poses 300]
    python benchmarks/planar.py speed [--poses 20000] [--sensors points] [--engine compiled] [--repeat 1]
    python benchmarks/planar.py tags [--seeds 3] [--poses 300]

``targets``: per world kind and seed, the position RMSE of the default association (beam) against
the true association's (oracle), the beam's precision and recall, and the oracle's NEES (3 dof) and
NIS verdicts; a summary line per kind. ``filters``: se2 against the 6-DOF filters (euler, se3) on
planar robots carrying 3-D cameras only (the 6-DOF filters cannot take the planar kinds), the
beam's association, position and heading RMSE. ``speed``: poses a second of the filter alone on one
large planar world of the given sensors (beam association) in the given engine (the compiled loop
warm: its kernels compiled before the timed runs; the best of ``--repeat`` runs). ``tags``: 3-D worlds of tags (``camloc.simulate_tags``,
orientation noise 1 deg) with 1 or 2 tags a pose, the default filter and association with each
tag's orientation against the same data without it (positions alone): rotation, heading (yaw) and
position RMSE.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from camloc import metrics
from camloc.localizer import localize
from camloc.localizer_config import LocalizerConfig
from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar

WORLDS = {
    "points": dict(sensors="points"),
    "points+clutter": dict(sensors="points", clutter_fraction=0.1),
    "markers": dict(sensors="markers"),
    "markers+clutter": dict(sensors="markers", clutter_fraction=0.1),
    "cameras": dict(sensors="cameras"),
    "all three": dict(sensors="points,markers,cameras", clutter_fraction=0.05),
}


def _run(dataset, **options):
    result = localize(dataset, LocalizerConfig(**options), engine="numpy", parallel=False)
    return result, metrics.evaluate(result)


def targets(seeds: int, poses: int) -> None:
    print("| world | seed | beam / oracle RMSE | precision | recall | oracle NEES (3 dof) | oracle NIS/dof | verdict |")
    print("|---|---|---|---|---|---|---|---|")
    for name, options in WORLDS.items():
        ratios, precisions, verdicts = [], [], []
        for seed in range(seeds):
            dataset = simulate_planar(PlanarSimulationConfig(poses=poses, **options), seed=seed)
            _, oracle = _run(dataset, association="oracle")
            _, beam = _run(dataset)
            ratio = beam["estimate"]["ate"]["rmse"] / oracle["estimate"]["ate"]["rmse"]
            ratios.append(ratio), precisions.append(beam["association"]["precision"])
            verdicts.append(oracle["consistency"]["verdict"])
            print(f"| {name} | {seed} | {ratio:.3f} | {beam['association']['precision']:.4f} | {beam['association']['recall']:.3f} | "
                  f"{oracle['nees']['mean']:.2f} {oracle['nees']['mean_bounds']} | {oracle['nis']['mean_per_dof']:.3f} | "
                  f"{oracle['consistency']['verdict']} |")
        print(f"| **{name}** | all | max {max(ratios):.3f} | min {min(precisions):.4f} | | | | "
              f"{sum(v == 'consistent' for v in verdicts)}/{len(verdicts)} consistent |")


def filters(seeds: int, poses: int) -> None:
    print("| seed | se2 RMSE [m] | euler RMSE [m] | se3 RMSE [m] | se2 heading [deg] | euler heading [deg] | se3 heading [deg] |")
    print("|---|---|---|---|---|---|---|")
    totals = {"se2": [], "euler": [], "se3": []}
    for seed in range(seeds):
        dataset = simulate_planar(PlanarSimulationConfig(sensors="cameras", poses=poses), seed=seed)
        row = {}
        for name in totals:
            _, report = _run(dataset, filter=name)
            row[name] = (report["estimate"]["ate"]["rmse"], report["estimate"]["rotation"]["rmse_deg"])
            totals[name].append(row[name][0])
        print(f"| {seed} | " + " | ".join(f"{row[n][0]:.4f}" for n in totals) + " | "
              + " | ".join(f"{row[n][1]:.3f}" for n in totals) + " |")
    print("| mean | " + " | ".join(f"{np.mean(v):.4f}" for v in totals.values()) + " | | | |")


def speed(poses: int, sensors: str, engine: str, repeat: int) -> None:
    dataset = simulate_planar(PlanarSimulationConfig(sensors=sensors, poses=poses), seed=0)
    if engine == "compiled":  # the kernels compiled (or loaded from the cache) before the timed runs
        localize(simulate_planar(PlanarSimulationConfig(sensors=sensors, poses=50), seed=0), LocalizerConfig(), engine=engine)
    runs = []
    for _ in range(repeat):
        started = time.perf_counter()
        result = localize(dataset, LocalizerConfig(), engine=engine, parallel=None if engine == "compiled" else False)
        runs.append((result.summary["timing"]["filter_seconds"], time.perf_counter() - started, result))
    seconds, wall, result = min(runs, key=lambda run: run[0])
    print(f"{sensors}: {poses} poses, {dataset.num_observations} observations, engine {result.summary['timing']['engine']}: "
          f"filter {seconds:.2f} s ({poses / seconds:.0f} poses/s), wall {wall:.1f} s")


def tags(seeds: int, poses: int) -> None:
    import math

    from camloc import geometry
    from camloc.simulate import SimulationConfig
    from camloc.simulate_tags import simulate_tags, without_orientations

    def yaw_rmse(result) -> float:
        yaw = [geometry.pose_to_euler(geometry.pose_from_quat(xyz, quat))[:, 5] for xyz, quat in
               ((result.estimate_xyz, result.estimate_quat_xyzw), (result.truth_xyz, result.truth_quat_xyzw))]
        return math.degrees(float(np.sqrt(np.mean(geometry.wrap_angle(yaw[0] - yaw[1]) ** 2))))

    print("| trajectory | tags a pose | seed | rotation RMSE with / without [deg] | heading (yaw) RMSE with / without [deg] "
          "| position RMSE with / without [m] | precision with |")
    print("|---|---|---|---|---|---|---|")
    for trajectory in ("grid", "smooth3d"):
        for cap in (1, 2):
            ratios = []
            for seed in range(seeds):
                config = SimulationConfig(trajectory=trajectory, poses=poses, max_observations_per_pose=cap)
                dataset = simulate_tags(config, seed=seed, sigma_rad=math.radians(1.0))
                (a, ea), (b, eb) = _run(dataset), _run(without_orientations(dataset))
                ratios.append(ea["estimate"]["rotation"]["rmse_deg"] / eb["estimate"]["rotation"]["rmse_deg"])
                print(f"| {trajectory} | {cap} | {seed} | {ea['estimate']['rotation']['rmse_deg']:.3f} / "
                      f"{eb['estimate']['rotation']['rmse_deg']:.3f} | {yaw_rmse(a):.3f} / {yaw_rmse(b):.3f} | "
                      f"{ea['estimate']['ate']['rmse']:.4f} / {eb['estimate']['ate']['rmse']:.4f} | {ea['association']['precision']:.4f} |")
            print(f"| {trajectory} | {cap} | mean ratio | {np.mean(ratios):.3f} | | | |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("what", choices=("targets", "filters", "speed", "tags"))
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--poses", type=int, default=None)
    parser.add_argument("--sensors", default="points", help="speed: the world's sensors (points, markers, cameras, comma-separated)")
    parser.add_argument("--engine", default="compiled", choices=("compiled", "numpy"), help="speed: the engine")
    parser.add_argument("--repeat", type=int, default=1, help="speed: runs, the best reported")
    args = parser.parse_args()
    if args.what == "targets":
        targets(args.seeds, args.poses or 300)
    elif args.what == "filters":
        filters(args.seeds, args.poses or 300)
    elif args.what == "tags":
        tags(args.seeds, args.poses or 300)
    else:
        speed(args.poses or 20000, args.sensors, args.engine, args.repeat)


if __name__ == "__main__":
    main()
