"""NEES consistency figures of docs/filter.md ("Consistency"): the single-run interval's coverage on
a consistent linear-Gaussian filter, and the Monte Carlo study of the oracle runs.

    nice python benchmarks/consistency.py interval              # seconds
    nice python benchmarks/consistency.py montecarlo            # 12 kinds x 30 seeds per experiment, ~2 min each
    nice python benchmarks/consistency.py montecarlo --seeds 10 --experiments baseline,gate

``interval``: per noise ratio and run length, the share of runs of a consistent Kalman filter
(6-D random walk measured whole at every step, the filter of tests/test_consistency.py) whose mean
NEES the old interval (chi2(6M)/M, M independent poses) and ``metrics.nees_summary``'s (M / tau
effective poses) reject; 5% is right.

``montecarlo``: per experiment and kind of world, oracle runs of 200 poses on seeds 0..N-1:
the grand mean NEES with the standard error of the runs' means, the share of poses whose ensemble
average is inside chi2(6N)/N (``metrics.monte_carlo_nees``), the position and rotation parts (3 dof
each), the share of pairs the gate rejected, and the share of single runs ``nees_summary`` rejects.
"""

from __future__ import annotations

import argparse
import itertools
import time

import numpy as np

import camloc
from camloc import geometry, metrics
from camloc.simulate import INTRINSICS, TRAJECTORIES, SimulationConfig, simulate

POSES = 200
OPEN_GATE = 1.0 - 1e-6
EXPERIMENTS = {  # name: (SimulationConfig options, LocalizerConfig options)
    "baseline": ({}, {}),
    "gate": ({}, {"gate": OPEN_GATE}),
    "iterations-10": ({}, {"gate": OPEN_GATE, "iterations": 10}),
    "iterations-1": ({}, {"gate": OPEN_GATE, "iterations": 1}),
    "odometry-x0.3": ({"odometry_sigma_scale": 0.3}, {"gate": OPEN_GATE}),
    "odometry-x0.1": ({"odometry_sigma_scale": 0.1}, {"gate": OPEN_GATE}),
    "observation-x0.3": ({"observation_sigma_scale": 0.3}, {"gate": OPEN_GATE}),
    "observation-x0.1": ({"observation_sigma_scale": 0.1}, {"gate": OPEN_GATE}),
}


def linear_gaussian_nees(rng, *, runs: int, steps: int, ratio: float, warm_up: int = 50) -> np.ndarray:
    """(runs, steps) NEES of a consistent Kalman filter: a 6-D random walk (steps of 0.1 m and
    0.02 rad) measured whole at every step with a noise ``ratio`` times the step."""
    q_sigma = np.array([0.1, 0.1, 0.1, 0.02, 0.02, 0.02])
    Q, R = np.diag(q_sigma**2), np.diag((ratio * q_sigma) ** 2)
    P = Q.copy()
    error = rng.standard_normal((runs, 6)) * q_sigma
    nees = np.empty((runs, warm_up + steps))
    for k in range(warm_up + steps):
        P = P + Q
        error = error + rng.standard_normal((runs, 6)) * q_sigma
        K = np.linalg.solve(P + R, P).T
        error = error - (error + rng.standard_normal((runs, 6)) * ratio * q_sigma) @ K.T
        I_K = np.eye(6) - K
        P = I_K @ P @ I_K.T + K @ R @ K.T
        nees[:, k] = np.einsum("ri,ij,rj->r", error, np.linalg.inv(P), error)
    return nees[:, warm_up:]


def interval(runs: int) -> None:
    print(f"{'ratio':>5} {'M':>5} {'lag-1':>6} {'tau':>5} {'old':>6} {'new':>6}   (share of {runs} consistent runs rejected)")
    for ratio, steps in itertools.product((0.3, 1.0, 3.0, 10.0), (100, 200, 1000)):
        nees = linear_gaussian_nees(np.random.default_rng(7), runs=runs, steps=steps, ratio=ratio)
        summaries = [metrics.nees_summary(run) for run in nees]
        old_lower, old_upper = metrics.mean_chi2_bounds(metrics.POSE_DOF, steps)
        old = np.mean([not old_lower <= run.mean() <= old_upper for run in nees])
        new = np.mean([summary["verdict"] != "consistent" for summary in summaries])
        lag1 = np.mean([metrics.autocorrelation(run)[1] for run in nees])
        tau = np.median([summary["autocorrelation_time"] for summary in summaries])
        print(f"{ratio:5.1f} {steps:5d} {lag1:6.2f} {tau:5.2f} {old:6.1%} {new:6.1%}", flush=True)


def _parts(result) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N,) NEES of the pose (6 dof), of its position and of its rotation (3 dof each)."""
    T_est = geometry.pose_from_quat(result.estimate_xyz, result.estimate_quat_xyzw)
    T_true = geometry.pose_from_quat(result.truth_xyz, result.truth_quat_xyzw)
    error, cov = geometry.pose_error_vector(T_est, T_true), result.estimate_cov
    parts = [metrics.run_nees(result)]
    for block in (slice(0, 3), slice(3, 6)):
        part = np.full(len(error), np.nan)
        e = error[1:, block]
        part[1:] = np.einsum("ni,ni->n", e, np.linalg.solve(cov[1:, block, block], e[..., None])[..., 0])
        parts.append(part)
    return tuple(parts)


def montecarlo(experiments: list[str], seeds: int) -> None:
    for name in experiments:
        simulation, options = EXPERIMENTS[name]
        config = camloc.LocalizerConfig(association="oracle", **options)
        print(f"\n{name}: {seeds} seeds x {POSES} poses; simulate {simulation or 'defaults'}, localize {options or 'defaults'}")
        print(f"{'world':26} {'mean':>6} {'s.e.':>6} {'inside':>7} {'pos':>6} {'rot':>6} {'gated':>6} {'runs rejected':>14}")
        pooled = []
        started = time.perf_counter()
        for trajectory, intrinsics, cameras in itertools.product(TRAJECTORIES, INTRINSICS, (1, 2)):
            world = SimulationConfig(trajectory=trajectory, intrinsics=intrinsics, cameras=cameras, poses=POSES, **simulation)
            rows, gated = [], []
            for seed in range(seeds):
                result = camloc.localize(simulate(world, seed=seed), config, parallel=False)
                rows.append(_parts(result))
                gated.append(np.mean(result.associations.landmark < 0))
            full, position, rotation = (np.array(part) for part in zip(*rows))
            pooled.append(full)
            summary = metrics.monte_carlo_nees(full)
            single = np.mean([metrics.nees_summary(run)["verdict"] != "consistent" for run in full])
            print(f"{trajectory}-{intrinsics}-{cameras}cam".ljust(26) + f" {summary['mean']:6.3f} {summary['standard_error']:6.3f}"
                  f" {summary['within_bounds_share']:7.1%} {np.nanmean(position):6.3f} {np.nanmean(rotation):6.3f}"
                  f" {np.mean(gated):6.2%} {single:14.0%}", flush=True)
        summary = metrics.monte_carlo_nees(np.concatenate(pooled))
        print(f"{'all':26} {summary['mean']:6.3f} {summary['standard_error']:6.3f}   ({time.perf_counter() - started:.0f} s)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("part", choices=("interval", "montecarlo"))
    parser.add_argument("--runs", type=int, default=2000, help="interval: linear-Gaussian runs per case (2000)")
    parser.add_argument("--seeds", type=int, default=30, help="montecarlo: seeds per kind of world (30)")
    parser.add_argument("--experiments", default="baseline,gate,odometry-x0.1,observation-x0.1",
                        help=f"montecarlo: comma-separated, of {', '.join(EXPERIMENTS)}")
    args = parser.parse_args()
    if args.part == "interval":
        interval(args.runs)
    else:
        montecarlo(args.experiments.split(","), args.seeds)


if __name__ == "__main__":
    main()
