"""Tags (issue 37): what a tag's measured orientation buys the filter, the smoother and the
association, on simulated 3-D worlds of tags (``camloc.simulate_tags``, orientation noise 1 deg).

    python benchmarks/tags.py filter [--seeds 3] [--poses 300]
    python benchmarks/tags.py smooth [--seeds 3] [--poses 300]
    python benchmarks/tags.py nearby [--seeds 3] [--poses 150]

``filter``: 1 or 2 tags a pose, depth (``EDGE_PROJECT_TAG``) and pixel-only
(``EDGE_PROJECT_TAG_UV``) cameras, the default filter and association with each tag's orientation
against the same data without it (positions alone): heading (yaw), rotation and position RMSE and
the association's precision; the mean heading ratio per kind of world (the issue's target: at
most 0.7). ``smooth``: the same worlds' runs smoothed (``camloc smooth``) with each tag's
orientation factor and without (the same run, its tags' positions alone): smoothed heading and
rotation RMSE. ``nearby``: every tag with an unseen twin 3 cm away turned by 90 deg
(``simulate_tags.with_twin_tags``), one tag a pose or two, each association method: precision and
recall with the orientation in the pair's cost and gate, with the orientation only vetoing pairs
chosen by position (``tag_orientations.ORIENTATION_IN_ASSOCIATION = False``, as before), and with
positions alone.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from camloc import geometry, metrics, smoother, tag_orientations
from camloc.localizer import localize
from camloc.measurement import TAG_ROTATION
from camloc.localizer_config import LocalizerConfig
from camloc.simulate import SimulationConfig
from camloc.simulate_tags import simulate_tags, with_twin_tags, without_orientations

SIGMA_RAD = math.radians(1.0)


def _yaw_rmse_deg(T: np.ndarray, T_true: np.ndarray) -> float:
    """RMSE of the heading (yaw of ``geometry.pose_to_euler``) of poses T (N, 4, 4), degrees."""
    d = geometry.wrap_angle(geometry.pose_to_euler(T)[:, 5] - geometry.pose_to_euler(T_true)[:, 5])
    return math.degrees(float(np.sqrt(np.mean(d**2))))


def _rotation_rmse_deg(T: np.ndarray, T_true: np.ndarray) -> float:
    e = geometry.so3_log(np.swapaxes(T_true[:, :3, :3], 1, 2) @ T[:, :3, :3])
    return math.degrees(float(np.sqrt(np.mean(np.sum(e**2, axis=1)))))


def _estimate(result) -> np.ndarray:
    return geometry.pose_from_quat(result.estimate_xyz, result.estimate_quat_xyzw)


def _worlds(seeds: int, poses: int):
    for measurement in ("depth", "pixel"):
        for trajectory in ("grid", "smooth3d"):
            for cap in (1, 2):
                for seed in range(seeds):
                    config = SimulationConfig(trajectory=trajectory, poses=poses, max_observations_per_pose=cap, measurement=measurement)
                    yield (measurement, trajectory, cap, seed), simulate_tags(config, seed=seed, sigma_rad=SIGMA_RAD)


def _run(dataset, **options):
    return localize(dataset, LocalizerConfig(**options), parallel=False)


def filter_table(seeds: int, poses: int) -> None:
    print("| camera | trajectory | tags a pose | seed | heading RMSE with / without [deg] | rotation RMSE with / without [deg] "
          "| position RMSE with / without [m] | precision with / without |")
    print("|---|---|---|---|---|---|---|---|")
    ratios: dict = {}
    for (measurement, trajectory, cap, seed), dataset in _worlds(seeds, poses):
        runs = [_run(dataset), _run(without_orientations(dataset))]
        reports = [metrics.evaluate(run) for run in runs]
        heading = [_yaw_rmse_deg(_estimate(run), dataset.T_world_truth) for run in runs]
        ratios.setdefault((measurement, trajectory, cap), []).append(heading[0] / heading[1])
        rotation = [r["estimate"]["rotation"]["rmse_deg"] for r in reports]
        ate = [r["estimate"]["ate"]["rmse"] for r in reports]
        precision = [r["association"]["precision"] for r in reports]
        print(f"| {measurement} | {trajectory} | {cap} | {seed} | {heading[0]:.3f} / {heading[1]:.3f} | {rotation[0]:.3f} / "
              f"{rotation[1]:.3f} | {ate[0]:.4f} / {ate[1]:.4f} | {precision[0]:.4f} / {precision[1]:.4f} |", flush=True)
    for key, values in ratios.items():
        print(f"mean heading ratio (with / without), {' '.join(map(str, key))} a pose: {np.mean(values):.3f} "
              f"(worst {max(values):.3f})")


def smooth_table(seeds: int, poses: int) -> None:
    print("| camera | trajectory | tags a pose | seed | smoothed heading RMSE with / without [deg] | smoothed rotation RMSE "
          "with / without [deg] | orientation factors |")
    print("|---|---|---|---|---|---|---|")
    ratios: dict = {}
    for (measurement, trajectory, cap, seed), dataset in _worlds(seeds, poses):
        run = _run(dataset)
        heading, rotation, factors = [], [], 0
        for data in (dataset, without_orientations(dataset)):
            problem = smoother.problem_from_run(data, run)
            T = smoother.smooth(problem, smoother.initial_poses(data, run)).T_world_robot
            heading.append(_yaw_rmse_deg(T, dataset.T_world_truth))
            rotation.append(_rotation_rmse_deg(T, dataset.T_world_truth))
            factors = factors or int(np.count_nonzero(problem.obs_kind == TAG_ROTATION))
        ratios.setdefault((measurement, trajectory, cap), []).append(heading[0] / heading[1])
        print(f"| {measurement} | {trajectory} | {cap} | {seed} | {heading[0]:.3f} / {heading[1]:.3f} | {rotation[0]:.3f} / "
              f"{rotation[1]:.3f} | {factors} |", flush=True)
    for key, values in ratios.items():
        print(f"mean smoothed heading ratio, {' '.join(map(str, key))} a pose: {np.mean(values):.3f} (worst {max(values):.3f})")


def nearby_table(seeds: int, poses: int) -> None:
    print("| association | tags a pose | seed | precision / recall: orientation in association | orientation vetoing "
          "| positions alone |")
    print("|---|---|---|---|---|---|")
    for association in ("beam", "jcbb", "best-friends"):
        for cap in (1, 2):
            for seed in range(seeds):
                config = SimulationConfig(trajectory="smooth3d", poses=poses, max_observations_per_pose=cap)
                dataset = with_twin_tags(simulate_tags(config, seed=seed, sigma_rad=SIGMA_RAD), offset_m=0.03, turn_deg=90.0,
                                         seed=seed)
                cells = []
                for data, in_association in ((dataset, True), (dataset, False), (without_orientations(dataset), True)):
                    tag_orientations.ORIENTATION_IN_ASSOCIATION = in_association
                    scores = metrics.evaluate(_run(data, association=association))["association"]
                    cells.append(" / ".join("n/a" if scores[k] is None else f"{scores[k]:.3f}" for k in ("precision", "recall")))
                tag_orientations.ORIENTATION_IN_ASSOCIATION = True
                print(f"| {association} | {cap} | {seed} | {' | '.join(cells)} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("what", choices=("filter", "smooth", "nearby"))
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--poses", type=int, default=None)
    args = parser.parse_args()
    if args.what == "filter":
        filter_table(args.seeds, args.poses or 300)
    elif args.what == "smooth":
        smooth_table(args.seeds, args.poses or 300)
    else:
        nearby_table(args.seeds, args.poses or 150)


if __name__ == "__main__":
    main()
