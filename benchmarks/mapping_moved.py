"""Moved maps on worlds shaped like the real file (issue 38): the default association against the true one.

Each world is ``camloc simulate``'s default density at ``--poses`` poses (100: about the real
file's 101 poses, 3.6 observations a pose, each landmark seen a few times), of a trajectory kind,
a seed and a clutter share, with a quarter of its map moved 0.3 m (``move_map=0.25``). Both runs
hold the map as a prior (``--map prior --map-sigma 0.1``): the default association (beam) and the
true one (oracle), on the same world. One row a world: position RMSE of each and their ratio, mean
NEES of each (and the mean's upper bound), the moved landmarks' mean error after each run, and
where the default's pairs of the moved landmarks' observations went: right, to another mapped
landmark, to an added landmark, left unpaired; and the other observations' wrong pairs (of a true
landmark given another mapped one) and the clutter it paired.

    nice python benchmarks/mapping_moved.py --kinds grid,smooth3d,aerial --seeds 0-7 --clutter 0,0.05,0.1

The real file itself is measured by ``benchmarks/real_variants.py`` (never tuned on).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from camloc import metrics
from camloc.localizer import localize
from camloc.localizer_config import LocalizerConfig
from camloc.results import UNASSOCIATED
from camloc.simulate import SimulationConfig, simulate_labelled

SIGMA = 0.1


def seeds(text: str) -> list[int]:
    """``0,2,5`` or ``0-7``."""
    if "-" in text:
        first, last = text.split("-")
        return list(range(int(first), int(last) + 1))
    return [int(s) for s in text.split(",")]


def world(kind: str, seed: int, poses: int, clutter: float, measurement: str):
    """The moved-map world and its true map (id -> position), the moved landmarks' ids."""
    base = dict(trajectory=kind, poses=poses, clutter_fraction=clutter, measurement=measurement)
    full = simulate_labelled(SimulationConfig(**base), seed=seed).dataset
    ds = simulate_labelled(SimulationConfig(**base, move_map=0.25), seed=seed).dataset
    truth = dict(zip(full.landmark_ids.tolist(), full.landmark_xyz))
    moved = np.array([i for i, p in zip(ds.landmark_ids.tolist(), ds.landmark_xyz) if np.linalg.norm(p - truth[i]) > 1e-6])
    return ds, truth, moved


def run(ds, truth: dict, moved: np.ndarray, association: str) -> dict:
    started = time.process_time()
    result = localize(ds, LocalizerConfig(map="prior", map_sigma=SIGMA, association=association))
    seconds = time.process_time() - started
    nees = metrics.run_nees(result)
    m = result.landmark_map
    at = np.isin(m.ids, moved) & (m.observations > 0)
    moved_error = float(np.mean([np.linalg.norm(m.xyz[i] - truth[int(m.ids[i])]) for i in np.flatnonzero(at)])) if at.any() else float("nan")
    a = result.associations
    mapped = np.isin(a.landmark, ds.landmark_ids)
    of_moved = np.isin(a.true_landmark, moved)
    real = np.isin(a.true_landmark, ds.landmark_ids)
    return {"rmse": float(np.sqrt(np.mean(np.sum((result.estimate_xyz - ds.truth_xyz) ** 2, axis=1)))),
            "nees": float(np.nanmean(nees)), "nees_high": (metrics.nees_summary(nees)["mean_bounds"] or [0, np.inf])[1],
            "moved_error": moved_error, "seconds": seconds,
            "moved_obs": int(of_moved.sum()), "moved_right": int((of_moved & (a.landmark == a.true_landmark)).sum()),
            "moved_other": int((of_moved & mapped & (a.landmark != a.true_landmark)).sum()),
            "moved_added": int((of_moved & (a.landmark != UNASSOCIATED) & ~mapped).sum()),
            "moved_left": int((of_moved & (a.landmark == UNASSOCIATED)).sum()),
            "wrong": int((real & ~of_moved & mapped & (a.landmark != a.true_landmark)).sum()),
            "clutter": int((~real & (a.landmark != UNASSOCIATED)).sum())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kinds", default="grid,smooth3d,aerial")
    parser.add_argument("--seeds", default="0-7")
    parser.add_argument("--clutter", default="0,0.1", help="clutter shares, comma-separated (default 0,0.1)")
    parser.add_argument("--poses", type=int, default=100)
    parser.add_argument("--measurement", default="depth")
    args = parser.parse_args()
    print("world | beam RMSE | oracle RMSE | ratio | beam NEES | oracle NEES | NEES bound | moved err beam | oracle | "
          "moved obs: right/other/added/left of N | wrong | clutter paired | s")
    ratios, inside, moved_ok = [], 0, 0
    for kind in args.kinds.split(","):
        for clutter in [float(c) for c in args.clutter.split(",")]:
            for seed in seeds(args.seeds):
                ds, truth, moved = world(kind, seed, args.poses, clutter, args.measurement)
                b, o = run(ds, truth, moved, "beam"), run(ds, truth, moved, "oracle")
                ratio = b["rmse"] / o["rmse"]
                ratios.append(ratio)
                inside += b["nees"] <= b["nees_high"]
                moved_ok += b["moved_error"] <= 0.15
                flag = " *" if ratio > 1.1 else ""
                print(f"{kind}/c{clutter:g}/{seed} | {b['rmse']:.3f} | {o['rmse']:.3f} | {ratio:.2f}{flag} | {b['nees']:.2f} | {o['nees']:.2f} | "
                      f"{b['nees_high']:.2f} | {b['moved_error']:.3f} | {o['moved_error']:.3f} | "
                      f"{b['moved_right']}/{b['moved_other']}/{b['moved_added']}/{b['moved_left']} of {b['moved_obs']} | "
                      f"{b['wrong']} | {b['clutter']} | {b['seconds'] + o['seconds']:.1f}", flush=True)
    r = np.array(ratios)
    print(f"{len(r)} worlds: ratio mean {r.mean():.3f}, median {np.median(r):.3f}, max {r.max():.2f}, over 1.1: {int((r > 1.1).sum())}; "
          f"NEES inside its bound: {inside}; moved error <= 0.15 m: {moved_ok}")


if __name__ == "__main__":
    main()
