"""Landmarks added twice with no map (issue 38, "at most 2% of added"): where each copy comes from.

Steps the mapping localizer (``camloc.slam_run.MappingLocalizer``, ``--map none``, the default
association) over each world of ``benchmarks/mapping.py --cases none`` and, at the end, takes
each added landmark to stand for the true landmark most of its observations are of. For every
landmark added twice it prints, at the pose the copy was made (the state as that pose's update
left it): the robot's position error, and for the landmark it copies (the original) how long it
had been unseen, its own position error, and the copy's first observation against it: the
squared Mahalanobis distance (its degrees of freedom), the innovation's norm and the predicted
spread ``sqrt(trace S)``. And the last **return** before the copy (a pair with a landmark unseen
for more than ``RETURN_GAP`` poses) that was **wrong** (its observation of another true landmark
than its landmark stands for), within 30 poses. Per world: clutter observations, how many of them
were paired with a landmark, and the wrong pairs.

    nice python benchmarks/mapping_copies.py --trajectories grid --clutter 0.1 --seeds 0,1,2,3
    nice python benchmarks/mapping_copies.py --robot planar --sensors points --seeds 2
    nice python benchmarks/mapping_copies.py --robot planar --sensors points,markers,cameras --seeds 2
    nice python benchmarks/mapping_copies.py --robot planar --sensors points --seeds 0,1,2,3,4,5,6,7 --no-fusion

Each world's line also gives its position RMSE, mean NEES, the landmark fusions
(``camloc.slam_fusion``) and the wrong ones (two landmarks whose observations were mostly of
different true landmarks), and the clutter made into landmarks; ``--no-fusion`` runs without the
fusion (the run before it), ``--tags DEG`` tag worlds.

A copy whose original is far off while the robot is not is a map bent earlier (landmarks mapped
while the robot was lost, not carried back by the loop closure); one that follows a wrong return
is the return's (docs/performance.md, 2026-12-05, "Where the copies come from").
"""

from __future__ import annotations

import argparse
from collections import Counter

import numpy as np

from camloc import metrics, slam
from camloc.localizer import resolved_config
from camloc.localizer_config import LocalizerConfig
from camloc.simulate import SimulationConfig, simulate_labelled
from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar
from camloc.slam_association import RETURN_GAP
from camloc.slam_run import MappingLocalizer

WRONG_RETURN_WINDOW = 30  # poses before a copy within which a wrong return is named as its cause


def worlds(args):
    """(name, seed, no-map dataset, true map id -> position) of each world asked for."""
    for kind in ([args.sensors] if args.robot == "planar" else args.trajectories.split(",")):
        for seed in [int(s) for s in args.seeds.split(",")]:
            if args.tags:
                from camloc.simulate_tags import simulate_tags

                base = dict(trajectory=kind, poses=args.poses, clutter_fraction=args.clutter)
                full = simulate_tags(SimulationConfig(**base), seed=seed, sigma_rad=np.radians(args.tags))
                ds = simulate_tags(SimulationConfig(**base, no_map=True), seed=seed, sigma_rad=np.radians(args.tags))
            elif args.robot == "planar":
                base = dict(sensors=kind, poses=args.poses, clutter_fraction=args.clutter, cameras=SimulationConfig(measurement="depth"))
                full = simulate_planar(PlanarSimulationConfig(**base), seed=seed)
                ds = simulate_planar(PlanarSimulationConfig(**base, no_map=True), seed=seed)
            else:
                base = dict(trajectory=kind, poses=args.poses, clutter_fraction=args.clutter)
                full = simulate_labelled(SimulationConfig(**base), seed=seed).dataset
                ds = simulate_labelled(SimulationConfig(**base, no_map=True), seed=seed).dataset
            yield kind, seed, ds, dict(zip(full.landmark_ids.tolist(), full.landmark_xyz))


def against(loc: MappingLocalizer, o: int, landmark: int) -> tuple[float, int, float, float]:
    """Observation o against the table's ``landmark`` in the localizer's state: (squared
    Mahalanobis distance, dof, innovation norm, sqrt(trace S)); a marker's heading wrapped."""
    sensor_id = int(loc.obs_sensor[o])
    row = int(loc.table.state_row[landmark])
    xyz = loc.x.L[row] if row >= 0 else loc.table.xyz[landmark]
    z_hat, H = slam.observe(loc.x, loc.sensors[sensor_id], xyz[None], np.array([row]))
    S = H[0] @ loc.P @ H[0].T + loc.association_cov[o]
    if row < 0:
        A = -H[0][:, 0:3]
        S = S + A @ loc.table.cov[landmark] @ A.T
    dof = int(loc.obs_dof[o])
    y = loc._innovation(o, z_hat[0], sensor_id)[:dof]
    S = S[:dof, :dof]
    return float(y @ np.linalg.solve(S, y)), dof, float(np.linalg.norm(y)), float(np.sqrt(np.trace(S)))


def majority(ds, chosen: np.ndarray, landmark: int):
    """The true id most of the observations paired with ``landmark`` are of (None: none)."""
    counts = Counter(ds.obs_true_landmark[chosen == landmark].tolist())
    return counts.most_common(1)[0][0] if counts else None


def trace_world(ds, fusion: bool = True) -> tuple[dict, dict, MappingLocalizer]:
    """Run the world; each birth's diagnosis against every earlier live landmark of its true id,
    each return's (pose, observation, landmark) and each fusion's (pose, the two true ids)."""
    loc = MappingLocalizer(ds, resolved_config(LocalizerConfig(map="none"), ds))
    loc.fusing = fusion
    fused_ids = []
    fuse = loc._fuse

    def traced_fuse(k, a, b):  # the true ids each stood for, before their records join
        fused_ids.append((k, majority(ds, loc.chosen, a), majority(ds, loc.chosen, b)))
        fuse(k, a, b)

    loc._fuse = traced_fuse
    births, returns = {}, []
    for k in range(ds.num_poses):
        size, last_seen = len(loc.table), loc.table.last_seen.copy()
        loc.step(k)
        obs = loc.obs_of_pose[k]
        for o in obs[loc.chosen[obs] >= 0].tolist():
            landmark = int(loc.chosen[o])
            if landmark < size and last_seen[landmark] < k - RETURN_GAP:
                returns.append((k, o, landmark))
        for new in range(size, len(loc.table)):
            mine = obs[loc.chosen[obs] == new]
            if mine.size == 0:
                continue
            o = int(mine[0])
            true_id = int(ds.obs_true_landmark[o])
            held = set(loc.chosen[(ds.obs_true_landmark == true_id) & (loc.chosen >= 0)].tolist()) - {new}
            olds = [(a, k - int(loc.table.last_seen[a]), *against(loc, o, a)) for a in sorted(held) if not loc.table.dead[a]]
            births[new] = (k, o, float(np.linalg.norm(loc.x.t - ds.truth_xyz[k])), olds, loc.x.L.copy(), loc.table.state_row.copy())
    return births, {"returns": returns, "fusions": fused_ids}, loc


def report(kind, seed, ds, truth: dict, fusion: bool = True) -> tuple:
    births, extra, loc = trace_world(ds, fusion)
    chosen = loc.chosen
    stands = {n: Counter(ds.obs_true_landmark[chosen == n].tolist()).most_common(1)[0][0] for n in set(chosen[chosen >= 0].tolist())}
    live = [n for n in stands if loc.table.added[n] and not loc.table.dead[n] and not loc.table.tentative[n]]
    by_true: dict = {}
    for n in sorted(live, key=lambda n: loc.table.born[n]):
        if stands[n] in truth:
            by_true.setdefault(stands[n], []).append(n)
    copies = [(t, ns[0], c) for t, ns in by_true.items() for c in ns[1:]]
    clutter = ~np.isin(ds.obs_true_landmark, list(truth))
    wrong = np.array([o for o in np.flatnonzero(chosen >= 0) if ds.obs_true_landmark[o] != stands[int(chosen[o])]], np.int64)
    wrong_returns = [(k, o) for k, o, lm in extra["returns"] if ds.obs_true_landmark[o] != stands.get(lm)]
    clutter_made = sum(1 for n in live if stands[n] not in truth)
    fusions = extra["fusions"]
    wrong_fusions = sum(1 for _, a, b in fusions if a != b)
    rmse = float(np.sqrt(np.mean(np.sum((loc.poses[:, :3, 3] - ds.truth_xyz) ** 2, axis=1))))
    nees = float(np.nanmean(metrics.run_nees(loc.result(0.0))))
    print(f"{kind}/{seed}: RMSE {rmse:.3f} m, NEES {nees:.1f}; fusions {len(fusions)}, wrong {wrong_fusions}"
          f"{[(k, a, b) for k, a, b in fusions if a != b]}; clutter made {clutter_made}")
    right = int(np.count_nonzero(chosen >= 0)) - wrong.size
    print(f"{kind}/{seed}: paired {int(np.count_nonzero(chosen >= 0))} of {chosen.size} observations, right {right} (by the true ids)")
    print(f"{kind}/{seed}: added {len(live)}, twice {len(copies)}; clutter observations {int(clutter.sum())}, paired "
          f"{int(np.count_nonzero(clutter & (chosen >= 0)))}; wrong pairs {wrong.size} (of clutter {int(clutter[wrong].sum())}); "
          f"wrong returns at poses {[k for k, _ in wrong_returns]}")
    after_wrong = 0
    for true_id, original, copy in sorted(copies, key=lambda c: births.get(c[2], (0,))[0]):
        if copy not in births:
            continue
        k, o, pose_error, olds, L, rows = births[copy]
        line = f"  copy of {true_id} at pose {k}: robot off {pose_error:.2f} m"
        for a, gap, d2, dof, y_norm, spread in olds:
            xyz = L[rows[a]] if rows[a] >= 0 else loc.table.xyz[a]
            line += (f" | original{'' if a == original else ' (another)'} unseen {gap}, off {np.linalg.norm(xyz - truth[true_id]):.2f} m, "
                     f"d2 {d2:.0f} ({dof} dof), |y| {y_norm:.2f}, spread {spread:.2f}")
        before = [kk for kk, _ in wrong_returns if k - WRONG_RETURN_WINDOW <= kk <= k]
        after_wrong += bool(before)
        print(line + (f" | after a wrong return at pose {before[-1]}" if before else " | no wrong return before it"))
    return len(live), len(copies), after_wrong, rmse, nees, len(fusions), wrong_fusions, clutter_made, int(clutter.sum()), right, wrong.size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trajectories", default="grid,smooth3d,aerial")
    parser.add_argument("--seeds", default="0,1,2,3")
    parser.add_argument("--poses", type=int, default=300)
    parser.add_argument("--clutter", type=float, default=0.0)
    parser.add_argument("--robot", default="3d", choices=("3d", "planar"))
    parser.add_argument("--sensors", default="points", help="with --robot planar: the planar simulator's sensors")
    parser.add_argument("--tags", type=float, default=0.0, help="3-D worlds of tags, their orientation noise in degrees (0: points)")
    parser.add_argument("--no-fusion", action="store_true", help="without landmark fusion (camloc.slam_fusion): the run before it")
    args = parser.parse_args()
    rows = [report(kind, seed, ds, truth, not args.no_fusion) for kind, seed, ds, truth in worlds(args)]
    added, twice, after_wrong, rmse, nees, fusions, wrong, clutter_made, clutter, right, wrong_pairs = (np.array(c) for c in zip(*rows))
    print(f"all: added {added.sum()}, twice {twice.sum()} ({100.0 * twice.sum() / max(added.sum(), 1):.1f}%), {after_wrong.sum()} of them within "
          f"{WRONG_RETURN_WINDOW} poses after a wrong return; RMSE mean {rmse.mean():.3f} m ({rmse.min():.2f}-{rmse.max():.2f}), "
          f"NEES mean {nees.mean():.1f} ({nees.min():.1f}-{nees.max():.1f}); fusions {fusions.sum()}, wrong {wrong.sum()}; "
          f"clutter made {clutter_made.sum()} of {clutter.sum()} clutter observations; pairs right {right.sum()}, wrong {wrong_pairs.sum()} (by the true ids)")


if __name__ == "__main__":
    main()
