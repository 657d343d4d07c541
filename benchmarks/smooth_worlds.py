"""Does the smoother converge on small worlds with no map? For each trajectory, seed and camera
measurement: a 300-pose world with no map (``camloc.simulate``), its oracle run, then
``smooth_run(..., SmootherConfig(map="none"))``; prints iterations (rejected), converged, the final
cost, the undetermined landmarks and the CPU time (docs/performance.md, "The 3-D smoother's
damping and far landmarks", 2026-12-05 (late)).

    nice python benchmarks/smooth_worlds.py [--trajectories aerial,grid,smooth3d] [--seeds 0,1,2,3,4,5]
        [--measurements depth,pixel] [--poses 300] [--max-iterations 50]
"""

from __future__ import annotations

import argparse
import time

from camloc import smoother
from camloc.localizer import LocalizerConfig, localize
from camloc.simulate import SimulationConfig, simulate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trajectories", default="aerial,grid,smooth3d")
    parser.add_argument("--seeds", default="0,1,2,3,4,5")
    parser.add_argument("--measurements", default="depth,pixel")
    parser.add_argument("--poses", type=int, default=300)
    parser.add_argument("--max-iterations", type=int, default=50)
    args = parser.parse_args()
    print("world | measurement | iterations (rejected) | converged | final cost | undetermined | CPU s")
    for trajectory in args.trajectories.split(","):
        for measurement in args.measurements.split(","):
            for seed in [int(s) for s in args.seeds.split(",")]:
                dataset = simulate(SimulationConfig(trajectory=trajectory, poses=args.poses, no_map=True,
                                                    measurement=measurement), seed=seed)
                run = localize(dataset, LocalizerConfig(map="none", association="oracle"))
                log: list = []
                started = time.process_time()
                try:
                    result = smoother.smooth_run(dataset, run, smoother.SmootherConfig(
                        map="none", max_iterations=args.max_iterations), on_iteration=log.append)
                    row = (f"{result.iterations} ({sum(not i.accepted for i in log)}) | {result.converged} | "
                           f"{result.final_cost:.12f} | {len(result.undetermined_landmarks)}")
                except Exception as error:  # noqa: BLE001 (a refusal is a result here)
                    row = f"{len(log)} ({sum(not i.accepted for i in log)}) | refused: {error} | - | -"
                print(f"{trajectory} {seed} | {measurement} | {row} | {time.process_time() - started:.2f}", flush=True)


if __name__ == "__main__":
    main()
