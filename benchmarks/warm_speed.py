"""Warm speed of ``camloc.localize`` on one g2o file: one warm-up call, then ``--calls`` timed calls
in the same process, each as poses/s of wall and of the process's CPU (user + sys, both threads).
CPU is the figure to compare on a shared machine; alternate two trees (``PYTHONPATH=TREE``) run
after run, as docs/performance.md does.

    nice python benchmarks/warm_speed.py WORLD.g2o [--label NAME] [--calls 2] [--association beam]
"""

from __future__ import annotations

import argparse
import resource
import time

import camloc


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("world", help="a g2o file")
    parser.add_argument("--label", default="", help="printed before the figures (default: none)")
    parser.add_argument("--calls", type=int, default=2, help="timed calls after the warm-up (default 2)")
    parser.add_argument("--association", default="beam", help="beam or oracle (default beam)")
    args = parser.parse_args()
    world = camloc.load(args.world)
    config = camloc.LocalizerConfig(association=args.association)
    camloc.localize(world, config, engine="compiled")
    figures = []
    for _ in range(args.calls):
        before, start = resource.getrusage(resource.RUSAGE_SELF), time.time()
        camloc.localize(world, config, engine="compiled")
        after, wall = resource.getrusage(resource.RUSAGE_SELF), time.time() - start
        cpu = after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime
        figures.append(f"{world.num_poses / wall:,.0f}/{world.num_poses / cpu:,.0f}")
    print(f"{args.label} poses/s wall/CPU: {' '.join(figures)}", flush=True)


if __name__ == "__main__":
    main()
