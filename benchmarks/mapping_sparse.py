"""No map on sparse worlds (issue 38): few observations a pose, landmarks seen again after gaps.

The real file's character with no map (about 1-2 observations a pose, each landmark seen a
handful of times, often after long gaps) made in simulation, so that the default association's
rules can be tuned there and not on the real file. For each kind and seed it runs ``--map none``
with the default association (and, with ``--oracle``, the true one) and prints: position RMSE
(and after an SE(3) alignment), mean NEES, landmarks added, added twice (share of added),
landmarks made of clutter, and the pairs: made, right (the landmark stands for the observation's
true id), and how many observations of true landmarks there were.

    nice python benchmarks/mapping_sparse.py --kinds grid,smooth3d,aerial,planar --seeds 0,1,2,3
    nice python benchmarks/mapping_sparse.py --kinds grid --detection 1.0   # the default density

``--detection``: the chance that a landmark in view is reported (default 0.4: about 1.4
observations a pose on the 3-D worlds, 2 on the planar ones); ``--dense``: the simulator's dense
maps (5x the landmarks), where merging two landmarks is riskiest.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

import numpy as np

from camloc import metrics
from camloc.localizer import localize
from camloc.localizer_config import LocalizerConfig
from camloc.simulate import SimulationConfig, simulate_labelled
from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar


def world(kind: str, seed: int, poses: int, detection: float, clutter: float, dense: bool):
    """The no-map world of ``kind`` (grid, smooth3d, aerial: a depth camera; planar: floor points)
    and its true map (id -> position)."""
    if kind == "planar":
        config = PlanarSimulationConfig(poses=poses, detection_probability=detection, clutter_fraction=clutter,
                                        visible_per_pose=5.0 * (5 if dense else 1))
        full = simulate_planar(config, seed=seed)
        ds = simulate_planar(PlanarSimulationConfig(**{**config.__dict__, "no_map": True}), seed=seed)
    else:
        config = SimulationConfig(trajectory=kind, poses=poses, detection_probability=detection,
                                  clutter_fraction=clutter, dense=dense)
        full = simulate_labelled(config, seed=seed).dataset
        ds = simulate_labelled(SimulationConfig(**{**config.__dict__, "no_map": True}), seed=seed).dataset
    return ds, dict(zip(full.landmark_ids.tolist(), full.landmark_xyz))


def scores(ds, truth_map: dict, association: str) -> dict:
    started = time.process_time()
    result = localize(ds, LocalizerConfig(map="none", association=association))
    seconds = time.process_time() - started
    err = result.estimate_xyz - ds.truth_xyz
    aligned = metrics.align_trajectory(result.estimate_xyz, ds.truth_xyz, method="se3")
    a, m = result.associations, result.landmark_map
    stands = {}
    for landmark_id in m.ids[m.added]:
        counts = Counter(a.true_landmark[a.landmark == landmark_id].tolist())
        stands[int(landmark_id)] = counts.most_common(1)[0][0] if counts else None
    real = [v for v in stands.values() if v is not None and v in truth_map]
    paired = a.landmark >= 0
    right = paired & np.array([stands.get(int(lm)) == int(t) for lm, t in zip(a.landmark, a.true_landmark)])
    return {"rmse": float(np.sqrt(np.mean(np.sum(err**2, axis=1)))),
            "rmse_se3": float(np.sqrt(np.mean(np.sum((result.estimate_xyz @ aligned.rotation.T + aligned.translation - ds.truth_xyz) ** 2, axis=1)))),
            "nees": float(np.nanmean(metrics.run_nees(result))), "added": len(stands),
            "twice": sum(n - 1 for n in Counter(real).values() if n > 1),
            "clutter": sum(1 for v in stands.values() if v is None or v not in truth_map),
            "pairs": int(paired.sum()), "right": int(right.sum()),
            "real_obs": int(np.isin(a.true_landmark, list(truth_map)).sum()), "seconds": seconds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kinds", default="grid,smooth3d,aerial,planar")
    parser.add_argument("--seeds", default="0,1,2,3")
    parser.add_argument("--poses", type=int, default=300)
    parser.add_argument("--detection", type=float, default=0.4)
    parser.add_argument("--clutter", type=float, default=0.0)
    parser.add_argument("--dense", action="store_true")
    parser.add_argument("--oracle", action="store_true", help="also the true association")
    args = parser.parse_args()
    print("kind/seed | association | RMSE m | SE3 m | NEES | added | twice | twice % | clutter-made | pairs | right | real obs | CPU s")
    totals: dict = {}
    for kind in args.kinds.split(","):
        for seed in [int(s) for s in args.seeds.split(",")]:
            ds, truth_map = world(kind, seed, args.poses, args.detection, args.clutter, args.dense)
            for association in ["beam"] + (["oracle"] if args.oracle else []):
                row = scores(ds, truth_map, association)
                total = totals.setdefault((kind, association), Counter())
                total.update({k: v for k, v in row.items()})
                total["n"] += 1
                print(f"{kind}/{seed} | {association} | {row['rmse']:.3f} | {row['rmse_se3']:.3f} | {row['nees']:.1f} | {row['added']} | "
                      f"{row['twice']} | {100 * row['twice'] / max(row['added'], 1):.1f} | {row['clutter']} | {row['pairs']} | "
                      f"{row['right']} | {row['real_obs']} | {row['seconds']:.1f}", flush=True)
    print("kind | association | mean RMSE | mean SE3 | mean NEES | added | twice | twice % | clutter-made | pairs | right | real obs")
    for (kind, association), t in totals.items():
        n = t["n"]
        print(f"{kind} | {association} | {t['rmse'] / n:.3f} | {t['rmse_se3'] / n:.3f} | {t['nees'] / n:.1f} | {t['added']} | {t['twice']} | "
              f"{100 * t['twice'] / max(t['added'], 1):.1f} | {t['clutter']} | {t['pairs']} | {t['right']} | {t['real_obs']}")


if __name__ == "__main__":
    main()
