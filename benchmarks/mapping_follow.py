"""The mapping pass beside the beam's run (``camloc.mapping_follower``) against one after the other.

Runs ``localize`` on a g2o file under a map mode, alternating the mapping pass beside the beam
(forced: whatever the machine's load, which ``localizer._cpu_free`` otherwise consults) and after
it (the follower disabled), and prints each run's wall and CPU time (this process's and the
mapping process's) and poses/s, the load average, then whether the two give the same run
(estimate, pairs, map) bit for bit. Wall time shows the overlap only where a second CPU is free.

    camloc simulate -o w20k.g2o --poses 20000 --landmarks 20000 --withhold-map 0.2
    python benchmarks/mapping_follow.py w20k.g2o --mode exact --rounds 2
"""

from __future__ import annotations

import argparse
import os
import resource
import time

import numpy as np

from camloc import localizer
from camloc.g2o import read_g2o
from camloc.localizer_config import LocalizerConfig
from camloc.mapping_follower import MappingFollower


def _cpu_seconds() -> float:
    """CPU time of this process and of the children it has waited for (the mapping process)."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def _after(dataset, config, hooks):
    """``localizer._follower`` that never follows: the mapping pass runs after the beam's run."""
    return MappingFollower(dataset, config, lambda: localizer._mapping_compiled(dataset, hooks), enabled=False)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("file", help="a g2o file")
    parser.add_argument("--mode", default="exact", help="the map mode (default exact)")
    parser.add_argument("--rounds", type=int, default=2, help="runs of each, alternated (default 2)")
    args = parser.parse_args()
    dataset = read_g2o(args.file)
    config = LocalizerConfig(map=args.mode)
    beside = localizer._follower
    localizer.localize(dataset, config)  # kernels loaded, caches warm
    results = {}
    print("run | wall s | poses/s wall | CPU s | poses/s CPU | beam's part s | load")
    localizer._cpu_free = lambda: True
    for _ in range(args.rounds):
        for label, follower in (("beside", beside), ("after", _after)):
            localizer._follower = follower
            wall, cpu = time.perf_counter(), _cpu_seconds()
            result = localizer.localize(dataset, config)
            wall, cpu = time.perf_counter() - wall, _cpu_seconds() - cpu
            beam = (result.summary.get("map") or {}).get("beam_seconds", 0.0)
            print(f"{label} | {wall:.1f} | {dataset.num_poses / wall:.0f} | {cpu:.1f} | {dataset.num_poses / cpu:.0f} | {beam:.1f}"
                  f" | {os.getloadavg()[0]:.2f}", flush=True)
            results[label] = result
    localizer._follower = beside
    a, b = results["beside"], results["after"]
    same_map = (a.landmark_map is None and b.landmark_map is None) or (
        a.landmark_map is not None and b.landmark_map is not None and np.array_equal(a.landmark_map.xyz, b.landmark_map.xyz))
    print(f"same run: estimate {np.array_equal(a.estimate_xyz, b.estimate_xyz)}, "
          f"pairs {np.array_equal(a.associations.landmark, b.associations.landmark)}, map {same_map}")


if __name__ == "__main__":
    main()
