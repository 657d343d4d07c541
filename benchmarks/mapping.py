"""Mapping (issue 38): the run on imperfect maps against the same world's complete map, world by world.

For each world (a trajectory, ``--poses``, a seed, optional clutter) it runs:
- ``full``: the complete map, ``--map exact`` (the default localizer): the reference;
- ``half``: half the map withheld, under ``exact`` (what camloc did before mapping) and ``prior``;
- ``moved``: a quarter of the map moved by 0.3 m, under ``exact`` and ``prior`` (sigma 0.1 m), and
  the moved landmarks' error after the run (over those the run observed);
- ``none``: no map at all;
each with the default association (beam) and the true one (oracle), and prints position RMSE (and
its ratio to ``full``), mean NEES, landmarks added, added twice and made of clutter, and the speed.

    nice python benchmarks/mapping.py --trajectories grid,smooth3d,aerial --seeds 0,1,2 --poses 300
    nice python benchmarks/mapping.py --cases moved --seeds 0,1,2,3 --measurement pixel --cameras 2

``--robot planar --sensors points|cameras|points,cameras``: planar worlds (``camloc.simulate_planar``,
the trajectory option unused; ``--measurement`` and ``--cameras`` those of its 3-D cameras) instead; ``half ignore`` is the exact map's localizer with the map's
lacking landmarks ignored (what camloc did for a planar robot before it mapped them), and every row
prints the largest |z| of the estimated trajectory (a planar run's must stay 0).

    nice python benchmarks/mapping.py --robot planar --sensors points --seeds 0,1,2 --poses 300
    nice python benchmarks/mapping.py --speed --robot planar --sensors points --poses 2000 --modes exact,prior,none

``--tags SIGMA_DEG``: 3-D worlds of tags (``camloc.simulate_tags``: every landmark a tag whose
orientation each detection measures with that noise); a moved tag is also turned 0.3 rad, and the
``moved deg`` column is the moved tags' orientation error after the run (mean angle, degrees);
``half ignore`` is the exact map's localizer alone (what camloc did with a tag file's lacking tags
before it mapped tags).

    nice python benchmarks/mapping.py --tags 1 --trajectories grid,smooth3d --seeds 0,1,2,3 --clutter 0.1

``--speed``: the speed of the mapping run instead (issue 38's target: a 20,000-pose world with a
fifth of its 20,000 landmarks withheld at 1,000 poses/s): a world of ``--poses`` poses and as many
landmarks, a fifth withheld (``--seeds``' first; or ``--file``, a g2o file), run under each of
``--modes``; prints poses/s of wall time and of the process's CPU time (the latter less
sensitive to other work on the machine), the beam's part and the landmarks added.

    nice python benchmarks/mapping.py --speed --poses 2000 --seeds 1 --modes exact,prior
    camloc simulate -o w20k.g2o --poses 20000 --landmarks 20000 --withhold-map 0.2
    nice python benchmarks/mapping.py --speed --file w20k.g2o --modes exact,prior
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

import numpy as np

from camloc import metrics
from camloc.localizer import _localize_exact, localize, resolved_config
from camloc.localizer_config import LocalizerConfig
from camloc.simulate import SimulationConfig, simulate_labelled
from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar


def stands_for(result) -> dict:
    """Each added landmark's id -> the true id most of its observations are of."""
    a, m = result.associations, result.landmark_map
    out = {}
    for landmark_id in m.ids[m.added]:
        counts = Counter(a.true_landmark[a.landmark == landmark_id].tolist())
        out[int(landmark_id)] = counts.most_common(1)[0][0] if counts else None
    return out


def case(dataset, truth_map, is_clutter, map_mode: str, association: str, moved_ids=(), truth_quat=None) -> dict:
    started = time.perf_counter()
    if map_mode == "ignore":  # the exact map's localizer alone: landmarks the map lacks not screened for, not added
        hooks = dict(parallel=None, engine="auto", on_compile=None, on_background_compile=None)
        config = resolved_config(LocalizerConfig(association=association), dataset)
        result = _localize_exact(dataset, config, None, **hooks)
    else:
        result = localize(dataset, LocalizerConfig(map=map_mode, association=association))
    seconds = time.perf_counter() - started
    rmse = float(np.sqrt(np.mean(np.sum((result.estimate_xyz - dataset.truth_xyz) ** 2, axis=1))))
    row = {"rmse": rmse, "nees": float(np.nanmean(metrics.run_nees(result))), "seconds": seconds, "added": 0,
           "twice": 0, "clutter_landmarks": 0, "moved_error": None, "moved_turn": None, "max_z": float(np.abs(result.estimate_xyz[:, 2]).max())}
    if result.landmark_map is not None:
        stands = stands_for(result)
        real = [v for v in stands.values() if v is not None and v in truth_map]
        row["added"] = len(stands)
        row["twice"] = sum(n - 1 for n in Counter(real).values() if n > 1)
        row["clutter_landmarks"] = sum(1 for v in stands.values() if v is None or v not in truth_map)
        if len(moved_ids):
            m = result.landmark_map
            at = np.isin(m.ids, moved_ids) & (m.observations > 0)  # the moved landmarks the run saw
            row["moved_error"] = float(np.mean([np.linalg.norm(m.xyz[i] - truth_map[int(m.ids[i])]) for i in np.flatnonzero(at)]))
            if truth_quat is not None:
                row["moved_turn"] = moved_turn_deg(m, dataset, at, truth_quat)
    return row


def moved_turn_deg(landmark_map, dataset, at: np.ndarray, truth_quat: dict) -> float:
    """The mean angle (degrees) between the moved tags' orientations after the run (``at``: the
    map's rows; the given map's where the run's map holds no orientation) and their truth."""
    from camloc import geometry

    ids = landmark_map.ids[at]
    if landmark_map.orientation is not None:
        R = geometry.so3_exp(landmark_map.orientation[at])
    else:
        R = geometry.quat_to_matrix(dataset.landmark_quat_xyzw[np.searchsorted(dataset.landmark_ids, ids)])
    R_true = geometry.quat_to_matrix(np.array([truth_quat[int(i)] for i in ids]).reshape(-1, 4))
    return float(np.degrees(np.mean(np.linalg.norm(geometry.so3_log(R_true @ np.swapaxes(R, 1, 2)), axis=1))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trajectories", default="grid,smooth3d,aerial")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--poses", type=int, default=300)
    parser.add_argument("--clutter", type=float, default=0.0)
    parser.add_argument("--associations", default="beam,oracle")
    parser.add_argument("--cases", default="half,moved,none", help="which imperfect maps (default half,moved,none)")
    parser.add_argument("--measurement", default="depth", help="the simulator's camera measurement (default depth)")
    parser.add_argument("--cameras", type=int, default=1, help="cameras on the robot (default 1)")
    parser.add_argument("--robot", default="3d", choices=("3d", "planar"), help="3d (default) or planar worlds")
    parser.add_argument("--sensors", default="points", help="with --robot planar: the planar simulator's sensors")
    parser.add_argument("--tags", type=float, default=0.0, help="3-D worlds of tags, their orientation noise in degrees (0: points)")
    parser.add_argument("--speed", action="store_true", help="measure the speed instead (see above)")
    parser.add_argument("--file", default=None, help="with --speed: a g2o file instead of a simulated world")
    parser.add_argument("--modes", default="exact,prior", help="with --speed: the map modes to run")
    args = parser.parse_args()
    if args.speed:
        speed(args)
        return
    cases = args.cases.split(",")
    print("world | case | association | RMSE m | / full | NEES | added | twice | clutter-made | moved err m | moved deg | max abs z | s")
    planar = args.robot == "planar"
    for trajectory in ([args.sensors] if planar else args.trajectories.split(",")):
        for seed in [int(s) for s in args.seeds.split(",")]:
            if planar:
                base = dict(sensors=args.sensors, poses=args.poses, clutter_fraction=args.clutter,
                            cameras=SimulationConfig(measurement=args.measurement, cameras=args.cameras))
                make = lambda c, seed=seed: simulate_planar(PlanarSimulationConfig(**c), seed=seed)  # noqa: E731
            else:
                base = dict(trajectory=trajectory, poses=args.poses, clutter_fraction=args.clutter,
                            measurement=args.measurement, cameras=args.cameras)
                make = lambda c, seed=seed: simulate_labelled(SimulationConfig(**c), seed=seed).dataset  # noqa: E731
                if args.tags:
                    from camloc.simulate_tags import simulate_tags

                    make = lambda c, seed=seed: simulate_tags(SimulationConfig(**c), seed=seed, sigma_rad=np.radians(args.tags))  # noqa: E731
            full = make(base)
            truth_map = dict(zip(full.landmark_ids.tolist(), full.landmark_xyz))
            truth_quat = dict(zip(full.landmark_ids.tolist(), full.landmark_quat_xyzw)) if args.tags else None
            # "ignore": what camloc did before it mapped planar robots' and tags' landmarks
            worlds = [("half", dict(base, withhold_map=0.5), ("ignore", "exact", "prior") if planar or args.tags else ("exact", "prior")),
                      ("moved", dict(base, move_map=0.25), ("exact", "prior")),
                      ("none", dict(base, no_map=True), ("none",))]
            for association in args.associations.split(","):
                reference = case(full, truth_map, None, "exact", association)
                _print(trajectory, seed, "full exact", association, reference, reference["rmse"])
                for name, config, modes in [w for w in worlds if w[0] in cases]:
                    ds = make(config)
                    moved = [int(i) for i in ds.landmark_ids if np.linalg.norm(ds.landmark_xyz[ds.landmark_ids == i][0] - truth_map[int(i)]) > 1e-6]
                    for mode in modes:
                        row = case(ds, truth_map, None, mode, association, moved if name == "moved" else (), truth_quat)
                        _print(trajectory, seed, f"{name} {mode}", association, row, reference["rmse"])


def speed(args) -> None:
    """Poses per second of the mapping run (``--speed``), wall and CPU, per map mode."""
    from camloc.simulate import simulate

    if args.file:
        from camloc.g2o import read_g2o

        dataset, name = read_g2o(args.file), args.file
    elif args.robot == "planar":  # the planar simulator's own map size
        seed = int(args.seeds.split(",")[0])
        dataset = simulate_planar(PlanarSimulationConfig(sensors=args.sensors, poses=args.poses, withhold_map=0.2), seed=seed)
        name = f"simulate_planar(sensors={args.sensors}, poses={args.poses}, withhold_map=0.2, seed={seed})"
    else:
        seed = int(args.seeds.split(",")[0])
        dataset = simulate(SimulationConfig(poses=args.poses, landmarks=args.poses, withhold_map=0.2), seed=seed)
        name = f"simulate(poses={args.poses}, landmarks={args.poses}, withhold_map=0.2, seed={seed})"
    # numba's kernels loaded (compiled, on a first run) before timing, as in a process that ran before:
    # the localizer's, and the mapping pass's (camloc.slam_compiled: a map lacking landmarks)
    localize(simulate(SimulationConfig(poses=300), seed=0), LocalizerConfig())
    localize(simulate(SimulationConfig(poses=300, withhold_map=0.2), seed=0), LocalizerConfig())
    print("world | mode | poses/s wall | poses/s CPU | seconds wall | beam s | landmarks added")
    for mode in args.modes.split(","):
        wall, cpu = time.perf_counter(), _cpu_seconds()
        result = localize(dataset, LocalizerConfig(map=mode))
        wall, cpu = time.perf_counter() - wall, _cpu_seconds() - cpu
        block = result.summary.get("map") or {}
        print(f"{name} | {mode} | {dataset.num_poses / wall:.0f} | {dataset.num_poses / cpu:.0f} | {wall:.1f} | "
              f"{block.get('beam_seconds', float('nan')):.1f} | {block.get('added', 0)}", flush=True)


def _cpu_seconds() -> float:
    """CPU time of this process and of the children it has waited for (the mapping pass's own
    process, where it runs beside the beam: ``camloc.mapping_follower``)."""
    import resource

    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def _print(trajectory, seed, name, association, row, full_rmse) -> None:
    moved = f"{row['moved_error']:.3f}" if row["moved_error"] is not None else "-"
    turn = f"{row['moved_turn']:.2f}" if row.get("moved_turn") is not None else "-"
    print(f"{trajectory}/{seed} | {name} | {association} | {row['rmse']:.3f} | {row['rmse'] / full_rmse:.2f} | {row['nees']:.2f} | "
          f"{row['added']} | {row['twice']} | {row['clutter_landmarks']} | {moved} | {turn} | {row['max_z']:.1e} | {row['seconds']:.1f}", flush=True)


if __name__ == "__main__":
    main()
