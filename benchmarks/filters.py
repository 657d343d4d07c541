"""Euler-angle filter against the SE(3) error-state filter, on flat ground and on aerial runs
whose pitch passes through +-90 deg (the Euler filter's singularity).

    python benchmarks/filters.py            # 5 seeds per case
    python benchmarks/filters.py --seeds 2  # quicker

Prints, per case and filter: position RMSE, rotation RMSE, mean NEES (6 dof; 6 is ideal), with
the default (beam) association and with the oracle association.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from camloc.localizer import LocalizerConfig, localize
from camloc.metrics import evaluate
from camloc.simulate import SimulationConfig, simulate

CASES = {
    "grid (flat, 150 poses)": SimulationConfig(trajectory="grid", poses=150),
    "smooth3d (150 poses)": SimulationConfig(trajectory="smooth3d", poses=150),
    "aerial, pitch through +-90 (150 poses)": SimulationConfig(trajectory="aerial", poses=150, max_tilt_deg=90),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=5, help="seeds per case (default 5)")
    args = parser.parse_args()
    print(f"{'case':40s} {'association':12s} {'filter':6s} {'pos RMSE [m]':>12s} {'rot RMSE [deg]':>14s} {'NEES mean':>9s} {'worst NEES':>10s} {'s/run':>6s}")
    for name, sim in CASES.items():
        worlds = [simulate(sim, seed=seed) for seed in range(args.seeds)]
        for association in ("beam", "oracle"):
            for kind in ("euler", "se3"):
                rows = []
                for dataset in worlds:
                    started = time.perf_counter()
                    result = localize(dataset, LocalizerConfig(filter=kind, association=association))
                    report = evaluate(result)
                    rows.append((report["estimate"]["ate"]["rmse"], report["estimate"]["rotation"]["rmse_deg"],
                                 report["nees"]["mean"], time.perf_counter() - started))
                rmse, rot, nees, seconds = np.array(rows).T
                print(f"{name:40s} {association:12s} {kind:6s} {rmse.mean():12.4f} {rot.mean():14.3f} {nees.mean():9.2f} {nees.max():10.2f} {seconds.mean():6.2f}", flush=True)


if __name__ == "__main__":
    main()
