"""Pixel-only cameras with no map (issue 38): the EKF-SLAM estimate against odometry alone, world by world.

Worlds of two pixel-only cameras and no map (``camloc simulate --measurement pixel --cameras 2
--no-map``), for each trajectory, seed and intrinsics (normalized: 1.8 degrees of pixel noise, the
real file's; pixel: 1 px at f = 525); each run as ``camloc run`` runs it (``--map`` auto: none)
with each association. Prints the position RMSE of the estimate and of odometry alone, their
ratio (above 1: the estimate is further from the truth than odometry), the mean NEES (6 dof) and
the landmarks added; then, per association, how many worlds are worse than odometry. This is the
measurement behind ``diagnostics.RAYS_NO_MAP`` (docs/performance.md, 2026-12-04 (evening), and
2026-12-05 with the landmarks from cloned poses).

    nice python benchmarks/pixel_no_map.py                       # 12 worlds x beam, oracle: ~10 min
    nice python benchmarks/pixel_no_map.py --associations beam --seeds 0,1,2,3
"""

from __future__ import annotations

import argparse
import itertools

import numpy as np

from camloc import metrics
from camloc.localizer import localize
from camloc.localizer_config import LocalizerConfig
from camloc.simulate import SimulationConfig, simulate


def rmse(xyz: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((xyz - truth) ** 2, axis=1))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trajectories", default="grid,smooth3d,aerial")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--intrinsics", default="normalized,pixel")
    parser.add_argument("--poses", type=int, default=200)
    parser.add_argument("--associations", default="beam,oracle")
    args = parser.parse_args()
    worlds = list(itertools.product(args.trajectories.split(","), [int(s) for s in args.seeds.split(",")],
                                    args.intrinsics.split(",")))
    print("world | association | estimate RMSE m | odometry RMSE m | ratio | NEES | added")
    ratios: dict[str, list[float]] = {a: [] for a in args.associations.split(",")}
    for trajectory, seed, intrinsics in worlds:
        dataset = simulate(SimulationConfig(trajectory=trajectory, poses=args.poses, measurement="pixel", cameras=2,
                                            intrinsics=intrinsics, no_map=True), seed=seed)
        for association in ratios:
            result = localize(dataset, LocalizerConfig(association=association))
            estimate, odometry = rmse(result.estimate_xyz, dataset.truth_xyz), rmse(result.odometry_xyz, dataset.truth_xyz)
            ratios[association].append(estimate / odometry)
            added = (result.summary.get("map") or {}).get("added", 0)
            print(f"{trajectory} {seed} {intrinsics} | {association} | {estimate:.3f} | {odometry:.3f} | "
                  f"{estimate / odometry:.2f} | {float(np.nanmean(metrics.run_nees(result))):.1f} | {added}", flush=True)
    for association, values in ratios.items():
        r = np.array(values)
        print(f"{association}: worse than odometry on {int(np.count_nonzero(r > 1.0))} of {r.size}; ratio median "
              f"{np.median(r):.2f}, mean {r.mean():.2f}")


if __name__ == "__main__":
    main()
