"""Pixel-only worlds with a gap (issue 35, the beam's miss term): a camera that sees nothing for a
stretch of poses, after which the robot's pose is unsure and each ray's pool wide. The beam and the
oracle on the compiled engine, per seed: position RMSE ratio, precision.

    nice python benchmarks/pixel_gap.py --trajectory aerial --cameras 1 --poses 150 --gap 60:30 --seeds 0,1,2,3,4,5,6,7,8,9
"""

from __future__ import annotations

import argparse
import dataclasses

import camloc
from camloc.metrics import evaluate
from camloc.simulate import SimulationConfig, simulate


def gapped(dataset, first: int, length: int):
    """``dataset`` without the observations of poses first .. first + length - 1."""
    keep = (dataset.obs_pose_index < first) | (dataset.obs_pose_index >= first + length)
    return dataclasses.replace(dataset, **{f.name: getattr(dataset, f.name)[keep] for f in dataclasses.fields(dataset)
                                           if f.name.startswith("obs_")})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trajectory", default="aerial")
    parser.add_argument("--cameras", type=int, default=1)
    parser.add_argument("--poses", type=int, default=150)
    parser.add_argument("--gap", default="60:30", help="FIRST:LENGTH, the poses that see nothing")
    parser.add_argument("--seeds", default="0,1,2,3,4,5,6,7,8,9")
    args = parser.parse_args()
    first, length = (int(v) for v in args.gap.split(":"))
    ratios = []
    for seed in (int(s) for s in args.seeds.split(",")):
        config = SimulationConfig(poses=args.poses, trajectory=args.trajectory, cameras=args.cameras, measurement="pixel")
        dataset = gapped(simulate(config, seed=seed), first, length)
        beam = evaluate(camloc.localize(dataset, engine="compiled", parallel=False))
        oracle = evaluate(camloc.localize(dataset, camloc.LocalizerConfig(association="oracle"), engine="compiled", parallel=False))
        ratio = beam["estimate"]["ate"]["rmse"] / oracle["estimate"]["ate"]["rmse"]
        ratios.append(ratio)
        print(f"{args.trajectory} seed {seed} ratio {ratio:7.2f} precision {beam['association']['precision']:.3f}", flush=True)
    print(f"within 1.25x: {sum(r <= 1.25 for r in ratios)} of {len(ratios)}; over 3x: {sum(r > 3.0 for r in ratios)}; "
          f"worst {max(ratios):.2f}")


if __name__ == "__main__":
    main()
