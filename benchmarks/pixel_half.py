"""Pixel-only cameras with half the map withheld (issue 38): beam against the true association and
the complete map, world by world, with the association's precision on the map's pairs.

    nice python benchmarks/pixel_half.py --trajectories grid,smooth3d,aerial --seeds 0,1,2,3
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from camloc import metrics
from camloc.localizer import localize
from camloc.localizer_config import LocalizerConfig
from camloc.simulate import SimulationConfig, simulate_labelled


def run(dataset, association: str) -> tuple[float, float, float, float]:
    started = time.perf_counter()
    result = localize(dataset, LocalizerConfig(association=association))
    seconds = time.perf_counter() - started
    rmse = float(np.sqrt(np.mean(np.sum((result.estimate_xyz - dataset.truth_xyz) ** 2, axis=1))))
    nees = float(np.nanmean(metrics.run_nees(result)))
    precision = metrics.association_scores(result.associations, dataset.landmark_ids)["precision"]
    return rmse, nees, precision if precision is not None else float("nan"), seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trajectories", default="grid,smooth3d,aerial")
    parser.add_argument("--seeds", default="0,1,2,3")
    parser.add_argument("--poses", type=int, default=300)
    parser.add_argument("--cameras", type=int, default=2)
    parser.add_argument("--full", action="store_true", help="also the complete map with the beam")
    parser.add_argument("--no-oracle", action="store_true")
    args = parser.parse_args()
    print("world | full beam | half beam | prec | NEES | s | half oracle | NEES | beam/oracle | beam/full")
    for trajectory in args.trajectories.split(","):
        for seed in [int(s) for s in args.seeds.split(",")]:
            base = dict(trajectory=trajectory, poses=args.poses, measurement="pixel", cameras=args.cameras)
            full = run(simulate_labelled(SimulationConfig(**base), seed=seed).dataset, "beam") if args.full else (float("nan"),) * 4
            half = simulate_labelled(SimulationConfig(**base, withhold_map=0.5), seed=seed).dataset
            beam = run(half, "beam")
            oracle = run(half, "oracle") if not args.no_oracle else (float("nan"),) * 4
            print(f"{trajectory}/{seed} | {full[0]:.3f} | {beam[0]:.3f} | {beam[2]:.3f} | {beam[1]:.1f} | {beam[3]:.1f} | "
                  f"{oracle[0]:.3f} | {oracle[1]:.1f} | {beam[0] / oracle[0]:.2f} | {beam[0] / full[0]:.2f}", flush=True)


if __name__ == "__main__":
    main()
