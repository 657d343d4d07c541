"""How the smoother's Huber threshold changes its accuracy, on simulated worlds (never the real file).

For each trajectory type, noise setting and seed: simulate, run the filter (best-friends
association), then smooth the run's accepted associations with every threshold. Prints, per
setting, the mean over the seeds of the smoothed position RMSE divided by the filter's (lower is
better) and the mean smoothed position RMSE in metres, and the same overall.

    python benchmarks/smooth_huber.py [--poses 120] [--seeds 5]
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from camloc.localizer import LocalizerConfig, localize
from camloc.simulate import SimulationConfig, simulate
from camloc.smoother import SmootherConfig, smooth_run

THRESHOLDS = (1.0, 1.5, 2.0, 2.5, 3.0, 5.0, math.inf)
# Outliers keep their true landmark id, so the filter may accept them as "correct" pairs whose
# measurement is garbage; the dense map with clutter makes wrong associations likely too.
SETTINGS = {
    "clean": {},
    "clutter+outliers": {"clutter_fraction": 0.1, "outlier_fraction": 0.05},
    "dense+heavy": {"dense": True, "clutter_fraction": 0.3, "outlier_fraction": 0.1},
}


def position_rmse(xyz: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((xyz - truth) ** 2, axis=1))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=120, help="poses per world (default 120)")
    parser.add_argument("--seeds", type=int, default=5, help="seeds per setting (default 5)")
    args = parser.parse_args()

    header = f"{'trajectory':<10} {'setting':<17} {'filter [m]':>10} " + " ".join(f"{f'f={f:g}':>11}" for f in THRESHOLDS)
    print("smoothed / filter position RMSE (mean over seeds), and the mean smoothed RMSE [m]")
    print(header)
    overall = {f: [] for f in THRESHOLDS}
    for trajectory in ("grid", "smooth3d", "aerial"):
        for setting, extra in SETTINGS.items():
            ratios = {f: [] for f in THRESHOLDS}
            errors = {f: [] for f in THRESHOLDS}
            filter_errors = []
            for seed in range(1, args.seeds + 1):
                dataset = simulate(SimulationConfig(trajectory=trajectory, poses=args.poses, **extra), seed=seed)
                run = localize(dataset, LocalizerConfig())
                filter_rmse = position_rmse(run.estimate_xyz, dataset.truth_xyz)
                filter_errors.append(filter_rmse)
                for f in THRESHOLDS:
                    smoothed = smooth_run(dataset, run, SmootherConfig(huber=f))
                    rmse = position_rmse(smoothed.xyz, dataset.truth_xyz)
                    ratios[f].append(rmse / filter_rmse)
                    errors[f].append(rmse)
                    overall[f].append(rmse / filter_rmse)
            cells = " ".join(f"{np.mean(ratios[f]):>5.3f} {np.mean(errors[f]):.3f}" for f in THRESHOLDS)
            print(f"{trajectory:<10} {setting:<17} {np.mean(filter_errors):>10.4f} {cells}")
    print(f"{'all':<10} {'':<17} {'':>10} " + " ".join(f"{np.mean(overall[f]):>5.3f}      " for f in THRESHOLDS))


if __name__ == "__main__":
    main()
