"""The beam's one-pair update alone, calls/s: ``updated`` as ``beam.settle`` calls it (by address,
one observation-landmark pair, no start, no MAP cost, the ray's step sigma for a pixel), on the
pairs of a simulated world's poses from a prior near the truth, in a compiled loop (docs/performance.md,
2026-12-07 (twenty-fourth session), "The one-pair update in scalars"). Prints calls/s of each
model and a checksum of the posteriors (equal between trees: the same arithmetic).

    nice python benchmarks/one_pair_update.py [--poses 60] [--repeats 200] [--rounds 3]
"""

from __future__ import annotations

import argparse
import time

import numba
import numpy as np

from camloc import geometry
from camloc.constants import RAY_STEP_SIGMA
from camloc.kernels import _jit, update
from camloc.kernels._jit import FALSE
from camloc.kernels.recheck import predict_pairs
from camloc.localizer import LocalizerConfig
from camloc.measurement import PIXEL
from camloc.scene import build_scene, build_settings
from camloc.simulate import SimulationConfig, simulate


@numba.njit(cache=False)
def settle_all(model, iterations, X, P, obs, landmarks, z_hat, H, repeats):
    """Every case's one-pair update, ``repeats`` times, as ``beam.settle`` calls it; the sum of
    the posteriors' entries."""
    total = 0.0
    for _ in range(repeats):
        for c in range(obs.size):
            step_sigma = RAY_STEP_SIGMA if model.camera_K[model.obs_camera[obs[c]], 4] == PIXEL else 0.0
            x, P_new = update.updated_at(model, iterations, X[c], P[c], obs[c:c + 1], landmarks[c:c + 1], z_hat[c:c + 1],
                                         H[c:c + 1], model.R_assoc, model.R_assoc_inverse, X[c][:0], FALSE, step_sigma)[:2]
            total += x.sum() + P_new.sum()
    return total


def cases(measurement: str, poses: int, seed: int = 1):
    """(model, iterations, X, P, obs, landmarks, z_hat, H): each true pair of a simulated world's
    poses, from a prior off the truth by a few centimetres and a degree."""
    intrinsics = "pixel" if measurement == "pixel" else "normalized"
    dataset = simulate(SimulationConfig(poses=poses, cameras=2, measurement=measurement, intrinsics=intrinsics,
                                        trajectory="smooth3d"), seed=seed)
    config = LocalizerConfig()
    scene, settings = build_scene(dataset, config), build_settings(config)
    rng = np.random.default_rng(seed)
    X, P, obs, landmarks, z_hats, Hs = [], [], [], [], [], []
    for k in range(poses):
        seen = np.flatnonzero((dataset.obs_pose_index == k) & (dataset.obs_true_landmark >= 0)).astype(np.int64)
        truth = np.r_[dataset.truth_xyz[k], geometry.matrix_to_euler(geometry.quat_to_matrix(dataset.truth_quat_xyzw[k]))]
        prior = truth + rng.normal(0.0, [0.05] * 3 + [0.01] * 3)
        cov = np.diag([0.1**2] * 3 + [0.02**2] * 3)
        z_hat, H = _jit.from_python(predict_pairs)(scene, prior, seen, scene.true_index[seen])
        for i, o in enumerate(seen):
            X.append(prior), P.append(cov), obs.append(o), landmarks.append(scene.true_index[o])
            z_hats.append(z_hat[i]), Hs.append(H[i])
    return (update.pair_model(scene), settings.iterations, np.array(X), np.array(P), np.array(obs, np.int64),
            np.array(landmarks, np.int64), np.array(z_hats), np.array(Hs))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=60)
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    for measurement in ("pixel", "depth"):
        model, iterations, *arrays = cases(measurement, args.poses)
        n = arrays[2].size
        checksum = settle_all(model, iterations, *arrays, 1)      # compiled, and the result to compare
        rates = []
        for _ in range(args.rounds):
            t0 = time.process_time()
            settle_all(model, iterations, *arrays, args.repeats)
            rates.append(n * args.repeats / (time.process_time() - t0))
        print(f"{measurement}: {n} pairs, {np.mean(rates):,.0f} calls/s CPU (rounds {', '.join(f'{r:,.0f}' for r in rates)}), "
              f"checksum {checksum!r}")


if __name__ == "__main__":
    main()
