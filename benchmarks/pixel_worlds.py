"""The default association on pixel-only worlds (issue 35), world by world: the beam and the oracle
on the compiled engine, position RMSE, their ratio, precision, and the kind of each wrong pair
(another map landmark: ``swap``; a clutter detection taken as a landmark: ``clutter``).

Worlds (``WORLDS``) are ``camloc simulate --measurement pixel`` with the options below, made in
memory; ``--width`` and ``--delta`` set the beam's width and delta.

    nice python benchmarks/pixel_worlds.py s3d2c10,grid1,aerial1,dense,pix2c20,s3d1,aerial2c10,mono100 --poses 500 --seeds 1,2,3,4
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import camloc
from camloc.metrics import evaluate
from camloc.simulate import simulate, simulation_config

WORLDS = {
    "s3d2c10": dict(trajectory="smooth3d", cameras=2, measurement="pixel", **{"clutter-fraction": 0.1}),
    "grid1": dict(trajectory="grid", cameras=1, measurement="pixel"),
    "aerial1": dict(trajectory="aerial", cameras=1, measurement="pixel"),
    "dense": dict(trajectory="grid", cameras=1, measurement="pixel", dense=True),
    "pix2c20": dict(trajectory="smooth3d", cameras=2, measurement="pixel", intrinsics="pixel", **{"clutter-fraction": 0.2}),
    "s3d1": dict(trajectory="smooth3d", cameras=1, measurement="pixel"),
    "aerial2c10": dict(trajectory="aerial", cameras=2, measurement="pixel", **{"clutter-fraction": 0.1}),
    "mono100": dict(trajectory="smooth3d", cameras=1, measurement="pixel", landmarks=1000, region=6.0),
    # a monocular camera as real ones come: ~92 observations a pose among 1,000 landmarks, at about
    # 1 px of noise (f = 500) and at the simulator's default for normalized intrinsics (1.8 deg)
    "monodense": dict(trajectory="smooth3d", cameras=1, measurement="pixel", landmarks=1000, region=3.0,
                      **{"max-range": 6.0, "fov-half-angle-deg": 60.0, "observation-sigma-uv": 0.002}),
    "monodense-noisy": dict(trajectory="smooth3d", cameras=1, measurement="pixel", landmarks=1000, region=3.0,
                            **{"max-range": 6.0, "fov-half-angle-deg": 60.0}),
}


def world(name: str, poses: int, seed: int):
    return simulate(simulation_config({**WORLDS[name], "poses": poses}), seed=seed)


def run(dataset, association: str, config: dict | None = None):
    started = time.perf_counter()
    result = camloc.localize(dataset, camloc.LocalizerConfig(association=association, **(config or {})), engine="compiled",
                             parallel=False)
    return result, evaluate(result), time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("worlds", help="comma-separated names of WORLDS")
    parser.add_argument("--poses", type=int, default=500)
    parser.add_argument("--seeds", default="1,2,3,4")
    parser.add_argument("--width", type=int, default=None, help="the beam's width (default: the library's)")
    parser.add_argument("--delta", type=float, default=None, help="the beam's delta (default: the library's)")
    parser.add_argument("--recheck-margin", type=float, default=None, help="the re-check's margin (default: the library's)")
    parser.add_argument("--ray-margin", type=float, default=None, help="the re-check's ray margin (default: the library's)")
    args = parser.parse_args()
    rows, recalls = [], []
    for name in args.worlds.split(","):
        for seed in [int(s) for s in args.seeds.split(",")]:
            dataset = world(name, args.poses, seed)
            config = {}
            beam_options = {key: value for key, value in (("width", args.width), ("delta", args.delta)) if value is not None}
            if beam_options:
                config["beam"] = camloc.BeamOptions(**beam_options)
            recheck_options = {key: value for key, value in (("margin", args.recheck_margin), ("ray_margin", args.ray_margin))
                               if value is not None}
            if recheck_options:
                config["recheck"] = camloc.RecheckOptions(**recheck_options)
            beam, scores, seconds = run(dataset, "beam", config)
            oracle_rmse = run(dataset, "oracle")[1]["estimate"]["ate"]["rmse"]
            rmse, precision = scores["estimate"]["ate"]["rmse"], scores["association"]["precision"]
            a = beam.associations
            wrong = (a.landmark >= 0) & (a.landmark != a.true_landmark)
            mapped = np.isin(a.true_landmark, dataset.landmark_ids)
            print(f"{name:10s} seed {seed} obs/pose {dataset.num_observations / dataset.num_poses:5.1f} beam {rmse:.4f} "
                  f"oracle {oracle_rmse:.4f} ratio {rmse / oracle_rmse:5.2f} prec {precision:.4f} recall {scores['association']['recall']:.3f} "
                  f"wrong(swap {int((wrong & mapped).sum())}, clutter {int((wrong & ~mapped).sum())}) t {seconds:6.2f}s", flush=True)
            rows.append((rmse / oracle_rmse, precision))
            recalls.append(scores["association"]["recall"])
    ratios, precisions = np.array(rows).T
    print(f"within 1.25x: {int((ratios <= 1.25).sum())} of {ratios.size}; precision >= 0.99: {int((precisions >= 0.99).sum())}; "
          f"worst ratio {ratios.max():.2f}, worst precision {precisions.min():.4f}, mean recall {np.mean(recalls):.3f}")


if __name__ == "__main__":
    main()
