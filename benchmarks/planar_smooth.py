"""The planar smoother with landmarks (issue 38, point 3): accuracy on imperfect maps, and speed.

``accuracy``: for each planar world (``--sensors`` sets x ``--seeds``, ``--poses`` poses, 10%
clutter on the planar sensors as ``benchmarks/mapping.py``'s) it runs camloc as a user would (the
default association, the beam) and smooths the run:

- ``full``: the complete map, ``run`` and ``smooth`` with the map exact: the reference;
- ``half``: half the map withheld, ``run --map exact`` (which adds what the map lacks) and
  ``smooth --map exact`` (the added landmarks free); ``before``: the same run smoothed with the
  added landmarks' observations left out (what the planar smoother did before: the map exact,
  added landmarks ignored);
- ``moved``: a quarter moved 0.3 m, ``run`` and ``smooth --map prior --map-sigma 0.1``;
  ``before``: smoothed with the map exact; and the moved landmarks' error (those the run saw);
- ``none``: no map, ``run --map none`` and ``smooth --map none``;

and prints position RMSE (x, y; no alignment) of the filter and of the smoothed path, their ratio,
the smoothed path's over the complete map's smoothed one, and the added landmarks' median error.
``--association oracle`` runs every case with the true association instead.

    nice python benchmarks/planar_smooth.py accuracy --sensors points,markers,cameras,points+markers+cameras --seeds 0,1,2,3

``speed``: ``camloc smooth`` end to end (``--map`` each of ``--modes``) on a planar world of
``--poses`` (20,000 by default; points, markers and a depth camera), its run made with the true
association and the complete map (``--map prior`` and ``none`` then make every observed landmark
a variable: the largest problem), and a second world, ``--withhold`` of its map withheld, whose
run (the beam, ``--map exact``) added landmarks (``--worlds`` chooses). Prints wall and CPU time.

    nice python benchmarks/planar_smooth.py speed --dir /tmp/psmooth --modes exact,prior,none
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from camloc.localizer import localize
from camloc.localizer_config import LocalizerConfig
from camloc.simulate_map import edit_map
from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar
from camloc.smoother import SmootherConfig
from camloc.smoother_se2 import smooth_planar_run

CASES = {"half": dict(withhold_map=0.5), "moved": dict(move_map=0.25, move_distance=0.3), "none": dict(no_map=True)}
RUN_MAP = {"full": "exact", "half": "exact", "moved": "prior", "none": "none"}


def rmse(xyz: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((xyz[:, :2] - truth[:, :2]) ** 2, axis=1))))


def without_added(dataset, run):
    """The run with the observations of landmarks its map lacks unassigned."""
    added = ~np.isin(run.associations.landmark, dataset.landmark_ids)
    landmark = np.where(added, -1, run.associations.landmark)
    return dataclasses.replace(run, associations=dataclasses.replace(run.associations, landmark=landmark))


def landmark_errors(result, run, whole, ids=None) -> list[float]:
    """Distances in the plane of the smoothed landmarks (``ids``: only those) from the true
    landmark each stands for (its own id, or for an added one the most common true id of its
    observations)."""
    if result.landmarks is None:
        return []
    true_xy = dict(zip(whole.landmark_ids.tolist(), whole.landmark_xyz[:, :2]))
    a = run.associations
    errors = []
    for i, xyz in zip(result.landmarks.ids.tolist(), result.landmarks.xyz):
        if ids is not None and i not in ids:
            continue
        truth = i if i in true_xy else Counter(a.true_landmark[a.landmark == i].tolist()).most_common(1)[0][0]
        if truth in true_xy:
            errors.append(float(np.linalg.norm(xyz[:2] - true_xy[truth])))
    return errors


def one_world(sensors: str, seed: int, poses: int, clutter: float, association: str = "beam") -> list[str]:
    config = PlanarSimulationConfig(sensors=sensors, poses=poses, clutter_fraction=clutter)
    whole = simulate_planar(config, seed=seed)
    truth = whole.truth_xyz
    full_run = localize(whole, LocalizerConfig(association=association))
    full = rmse(smooth_planar_run(whole, full_run).xyz, truth)
    lines = [f"{sensors:24s} {seed:2d} full   filter {rmse(full_run.estimate_xyz, truth):.4f}  smoothed {full:.4f}"]
    for name, edits in CASES.items():
        edited = edit_map(whole, dataclasses.replace(config, **edits), seed=seed)
        started = time.perf_counter()
        run = localize(edited.dataset, LocalizerConfig(map=RUN_MAP[name], map_sigma=0.1, association=association))
        run_seconds = time.perf_counter() - started
        mode = "prior" if name == "moved" else RUN_MAP[name]
        started = time.perf_counter()
        result = smooth_planar_run(edited.dataset, run, SmootherConfig(map=mode, map_sigma=0.1))
        seconds = time.perf_counter() - started
        before = {"half": lambda: smooth_planar_run(edited.dataset, without_added(edited.dataset, run)),
                  "moved": lambda: smooth_planar_run(edited.dataset, run)}.get(name)
        filt, smoothed = rmse(run.estimate_xyz, truth), rmse(result.xyz, truth)
        line = (f"{sensors:24s} {seed:2d} {name:6s} filter {filt:.4f}  smoothed {smoothed:.4f}  /filter {smoothed / filt:.2f}"
                f"  /full {smoothed / full:.2f}")
        if before is not None:
            line += f"  before {rmse(before().xyz, truth):.4f}"
        added = landmark_errors(result, run, edited.whole, set(np.setdiff1d(result.landmarks.ids, whole.landmark_ids).tolist())
                                if result.landmarks is not None else set())
        if added:
            line += f"  added {len(added)} median err {np.median(added):.3f} m"
        if name == "moved":
            moved = landmark_errors(result, run, edited.whole, set(edited.moved.tolist()))
            line += f"  moved seen {len(moved)} mean err {np.mean(moved):.3f} m"
        lines.append(line + f"  (run {run_seconds:.1f} s, smooth {seconds:.2f} s, {result.iterations} it)")
    return lines


def accuracy(args) -> None:
    for sensors in args.sensors.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            for line in one_world(sensors.replace("+", ","), seed, args.poses, args.clutter, args.association):
                print(line, flush=True)


def camloc(*args) -> str:
    command = [sys.executable, "-m", "camloc.cli.app", *map(str, args)]
    return subprocess.run(command, check=True, capture_output=True, text=True).stdout


def _children_cpu() -> float:
    """CPU seconds (user + system) of the finished child processes: less sensitive to other work
    on the machine than wall time."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def speed(args) -> None:
    folder = Path(args.dir)
    folder.mkdir(parents=True, exist_ok=True)
    worlds = [("complete", (), ("--association", "oracle")), ("withheld", ("--withhold-map", args.withhold), ("--map", "exact"))]
    for name, edit, run_options in (world for world in worlds if world[0] in args.worlds.split(",")):
        world, run_dir = folder / f"{name}.g2o", folder / f"{name}-run"
        if not world.exists():
            camloc("simulate", "--robot", "planar", "--sensors", args.sensors, "--poses", args.poses, "--seed", 1, *edit,
                   "-o", world, "-q")
        if not run_dir.exists():
            camloc("run", world, "-o", run_dir, *run_options, "-q")
        for mode in args.modes.split(","):
            started, cpu = time.perf_counter(), _children_cpu()
            report = json.loads(camloc("smooth", run_dir, "--map", mode, "--map-sigma", 0.1, "--json"))
            wall, cpu = time.perf_counter() - started, _children_cpu() - cpu
            print(f"{name} {args.poses} poses, smooth --map {mode}: {wall:.1f} s end to end ({cpu:.1f} s of CPU), "
                  f"{report['timing']['smooth_seconds']:.1f} s "
                  f"smoothing, {report['iterations']} iterations, {report['landmarks']['estimated']} landmarks estimated "
                  f"({report['landmarks']['added']} added), {report['observation_factors']} observations; position RMSE "
                  f"filter {report['estimate']['ate']['rmse']:.4f} smoothed {report['smoothed']['ate']['rmse']:.4f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=("accuracy", "speed"))
    parser.add_argument("--sensors", default="points,markers,cameras,points+markers+cameras",
                        help="accuracy: sets separated by commas, a set's sensors by '+'; speed: one set, by commas")
    parser.add_argument("--seeds", default="0,1,2,3")
    parser.add_argument("--poses", type=int, default=None, help="default 300 (accuracy), 20000 (speed)")
    parser.add_argument("--clutter", type=float, default=0.1)
    parser.add_argument("--association", default="beam", help="accuracy: the runs' association (oracle: the file's ids)")
    parser.add_argument("--dir", default="/tmp/planar-smooth")
    parser.add_argument("--modes", default="exact,prior,none")
    parser.add_argument("--withhold", type=float, default=0.2)
    parser.add_argument("--worlds", default="complete,withheld", help="speed: which worlds")
    args = parser.parse_args()
    if args.what == "accuracy":
        args.poses = args.poses or 300
        accuracy(args)
    else:
        args.poses = args.poses or 20000
        if args.sensors == parser.get_default("sensors"):
            args.sensors = "points,markers,cameras"
        speed(args)


if __name__ == "__main__":
    main()
