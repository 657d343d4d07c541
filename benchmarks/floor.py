"""The floor: the least a pose costs in numpy when the filter has nothing to decide.

Issue 6 asks for 5,000 poses per second (200 µs a pose) on the 20k world. This script measures
what the filter alone costs there, with the association known, so that the budget left for the
association is a measured number rather than a guess. On the first 1,000 poses of the scale
benchmark's world (``scale.py``'s ``first 1k``; ``--quick``: the first 250 of its quick world), with
the pairs a run with ``association="oracle"`` accepted:

- ``bare EKF``: the leanest sequential Euler EKF camloc's models allow: ``models.motion``,
  ``F P F' + G Q G'``, ``models.observe`` of the pose's paired landmarks, one update in
  information form (one linearization, no map cost, no checks, no records), and one k-d tree
  query of the view. Each part is timed apart.
- ``windowed``: the filter computed for a window of poses at a time (Gauss-Newton over
  linearization points, ``window_pass``): the models evaluated in one numpy call for the whole
  window, then a sequential loop of 6x6 algebra that only moves the linearization. Passes repeat
  until no state moves by more than 1e-8 (at most 30); the fixed point is the fully iterated EKF,
  which the script checks against ``camloc.localize`` with ``iterations=50``. It prints the cost of
  one pass, how many passes a window needs from a dead-reckoning start, and how many windows never
  converged (plain Gauss-Newton from the odometry's guess: the sequential filter converges
  because it linearizes each pose at a prediction that its previous pose has already corrected).

    nice python benchmarks/floor.py [--quick] [--windows 16,64] [--cache DIR]

Nothing here asserts anything about time.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench  # noqa: E402  (the benchmarks folder is not a package)
from scale import FULL, QUICK  # noqa: E402

from camloc import LocalizerConfig, geometry, load, localize, models  # noqa: E402

CONVERGED = 1e-8
MAX_PASSES = 30


def main() -> None:
    args = parse_args()
    plan = QUICK if args.quick else FULL
    poses = plan.prefixes[0]
    cache = args.cache.expanduser()
    print(f"camloc floor benchmark ({'quick' if args.quick else 'full'}); {_bench.source_note()}; {_bench.machine_load()}",
          file=sys.stderr, flush=True)
    path = _bench.first_poses(cache, _bench.simulated(cache, plan.world, seed=plan.seed), poses)
    dataset = load(path)
    reference = localize(dataset, LocalizerConfig(association="oracle", iterations=50), parallel=False)
    pairs = Pairs.accepted(dataset, reference)
    print(f"{path.name}: {dataset.num_poses} poses, {pairs.pose.size / dataset.num_poses:.1f} accepted pairs a pose")

    parts = bare_ekf(dataset, pairs)
    total = sum(parts.values())
    print(f"bare EKF: {total:.0f} µs/pose ({1e6 / total:.0f} poses/s): "
          + ", ".join(f"{name} {value:.0f}" for name, value in parts.items()))
    for window in args.windows:
        per_pose, passes, unconverged, windows, agree = windowed(dataset, pairs, window, reference.filter_state)
        print(f"windowed, {window} poses a window: {per_pose:.0f} µs/pose ({1e6 / per_pose:.0f} poses/s), "
              f"{per_pose / passes:.0f} µs a pass, {passes:.1f} passes a window on average; {unconverged} of {windows} "
              f"windows not converged in {MAX_PASSES} passes; {agree:.1%} of the poses within 1e-6 of the iterated EKF")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="the quick world's first 250 poses (default: the full world's first 1,000)")
    parser.add_argument("--windows", default="16,64", help="window lengths of the windowed filter, comma-separated (default 16,64)")
    parser.add_argument("--cache", type=Path, default=_bench.DEFAULT_CACHE,
                        help=f"folder for generated worlds (default {_bench.DEFAULT_CACHE})")
    args = parser.parse_args()
    try:
        args.windows = [int(w) for w in args.windows.split(",")]
    except ValueError:
        parser.error(f"--windows must be integers separated by commas, got {args.windows!r}")
    if any(w < 1 for w in args.windows):
        parser.error("--windows must be positive")
    return args


class Pairs:
    """The accepted (pose, observation, landmark) pairs of a run, sorted by pose, with each
    observation's camera."""

    def __init__(self, dataset, pose: np.ndarray, obs: np.ndarray, landmark: np.ndarray):
        self.pose, self.obs, self.landmark = pose, obs, landmark
        cameras = [dataset.cameras[int(c)] for c in dataset.obs_camera[obs]]
        self.T_robot_camera = np.array([c.T_robot_camera for c in cameras]).reshape(-1, 4, 4)
        self.intrinsics = np.array([(c.fx, c.fy, c.cx, c.cy) for c in cameras]).reshape(-1, 4)
        self.bounds = np.searchsorted(pose, np.arange(dataset.num_poses + 1))

    @classmethod
    def accepted(cls, dataset, run) -> "Pairs":
        index_of = {int(i): n for n, i in enumerate(dataset.landmark_ids)}
        landmark = np.array([index_of.get(int(i), -1) for i in run.associations.landmark], dtype=np.int64)
        obs = np.flatnonzero(landmark >= 0)
        obs = obs[np.argsort(dataset.obs_pose_index[obs], kind="stable")]
        return cls(dataset, dataset.obs_pose_index[obs], obs, landmark[obs])


def start(dataset) -> tuple[np.ndarray, np.ndarray]:
    config = LocalizerConfig()
    sigma = np.r_[np.full(3, config.initial_sigma_xyz), np.full(3, np.radians(config.initial_sigma_deg))]
    return geometry.pose_to_euler(dataset.T_world_start), np.diag(sigma**2)


def bare_ekf(dataset, pairs: Pairs) -> dict[str, float]:
    """µs a pose of each part of the leanest sequential EKF."""
    x, P = start(dataset)
    tree = cKDTree(dataset.landmark_xyz)
    increments, Q = dataset.T_odometry, dataset.odom_cov
    view = 1.25 * float(dataset.obs_z[:, 2].max())
    clock = time.perf_counter
    spent = dict(predict=0.0, observe=0.0, update=0.0, query=0.0)
    for k in range(dataset.num_poses):
        t0 = clock()
        if k:
            x, F, G = models.motion(x, increments[k - 1])
            P = F @ P @ F.T + G @ Q[k - 1] @ G.T
        t1 = clock()
        mine = slice(pairs.bounds[k], pairs.bounds[k + 1])
        t2 = t3 = t1
        if pairs.bounds[k + 1] > pairs.bounds[k]:
            obs = pairs.obs[mine]
            z_hat, H = models.observe(x, pairs.T_robot_camera[mine][0], tuple(pairs.intrinsics[mine][0]), dataset.landmark_xyz[pairs.landmark[mine]])
            t2 = clock()
            R_inverse_H = dataset.obs_info[obs] @ H
            information = np.einsum("mji,mjk->ik", H, R_inverse_H)
            gradient = np.einsum("mji,mj->i", R_inverse_H, dataset.obs_z[obs] - z_hat)
            posterior = np.linalg.solve(np.eye(6) + P @ information, P)
            x, P = x + posterior @ gradient, 0.5 * (posterior + posterior.T)
            t3 = clock()
        tree.query_ball_point(x[:3], view)
        t4 = clock()
        spent["predict"] += t1 - t0
        spent["observe"] += t2 - t1
        spent["update"] += t3 - t2
        spent["query"] += t4 - t3
    return {name: 1e6 * value / dataset.num_poses for name, value in spent.items()}


def windowed(dataset, pairs: Pairs, window: int, reference: np.ndarray) -> tuple[float, float, int, int, float]:
    """(µs a pose, passes a window on average, windows not converged, windows, the share of poses
    whose state is within 1e-6 of the reference) of the windowed filter."""
    n = dataset.num_poses
    x, P = start(dataset)
    increments = np.concatenate([np.eye(4)[None], dataset.T_odometry])  # row k: the increment into pose k
    Q = np.concatenate([np.zeros((1, 6, 6)), dataset.odom_cov])
    states = np.empty((n, 6))
    passes, unconverged = 0, 0
    began = time.perf_counter()
    for first in range(0, n, window):
        last = min(n, first + window)
        linearization = dead_reckoning(x, increments[first:last], from_before=first > 0)
        rows = slice(pairs.bounds[first], pairs.bounds[last])
        for count in range(1, MAX_PASSES + 1):
            moved, covs = window_pass(x, P, linearization, increments[first:last], Q[first:last], pairs, rows, first, dataset)
            change = np.abs(difference(moved, linearization)).max()
            linearization = moved
            if change < CONVERGED:
                break
        passes, unconverged = passes + count, unconverged + int(change >= CONVERGED)
        states[first:last] = linearization
        x, P = linearization[-1], covs[-1]
    seconds = time.perf_counter() - began
    windows = -(-n // window)
    agree = float(np.mean(np.abs(difference(states, reference)).max(axis=1) < 1e-6))
    return 1e6 * seconds / n, passes / windows, unconverged, windows, agree


def dead_reckoning(x: np.ndarray, increments: np.ndarray, *, from_before: bool) -> np.ndarray:
    """A window's states by odometry alone, from x: the state of the pose before the window
    (``from_before``), or of the window's first pose (the run's start)."""
    out = np.empty((increments.shape[0], 6))
    out[0] = models.motion(x, increments[0])[0] if from_before else x
    for k in range(1, out.shape[0]):
        out[k] = models.motion(out[k - 1], increments[k])[0]
    return out


def window_pass(x: np.ndarray, P: np.ndarray, linearization: np.ndarray, increments: np.ndarray, Q: np.ndarray,
                pairs: Pairs, rows: slice, first: int, dataset) -> tuple[np.ndarray, np.ndarray]:
    """One Gauss-Newton pass over a window: the models at the linearization points, all at once,
    then the filter's recursion in 6x6 algebra. (x, P): the state before the window (the start's
    own, when first == 0)."""
    w = linearization.shape[0]
    before = np.concatenate([x[None], linearization[:-1]])  # where each pose's motion is linearized
    predicted, F, G = motion_batch(before, increments)
    spread = G @ Q @ np.swapaxes(G, 1, 2)
    pose = pairs.pose[rows] - first
    obs = pairs.obs[rows]
    z_hat, H = observe_batch(linearization[pose], pairs.T_robot_camera[rows], pairs.intrinsics[rows], dataset.landmark_xyz[pairs.landmark[rows]])
    R_inverse_H = dataset.obs_info[obs] @ H
    information = np.zeros((w, 6, 6))
    np.add.at(information, pose, np.einsum("mji,mjk->mik", H, R_inverse_H))
    gradient = np.zeros((w, 6))
    np.add.at(gradient, pose, np.einsum("mji,mj->mi", R_inverse_H, dataset.obs_z[obs] - z_hat))
    observed = np.zeros(w, dtype=bool)
    observed[pose] = True
    states, covs = np.empty((w, 6)), np.empty((w, 6, 6))
    identity = np.eye(6)
    for k in range(w):
        if first or k:  # the first pose of the run has no increment into it
            x = predicted[k] + F[k] @ difference(x, before[k])
            P = F[k] @ P @ F[k].T + spread[k]
        if observed[k]:
            A = identity + P @ information[k]
            posterior = np.linalg.solve(A, P)  # (P^-1 + Lambda)^-1
            x = x + posterior @ (gradient[k] - information[k] @ difference(x, linearization[k]))
            x[3:6] = geometry.wrap_angle(x[3:6])
            joseph = np.linalg.solve(A, P + P @ information[k] @ P)
            P = np.linalg.solve(A, joseph.T).T
            P = 0.5 * (P + P.T)
        states[k], covs[k] = x, P
    return states, covs


def difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = a - b
    d[..., 3:6] = geometry.wrap_angle(d[..., 3:6])
    return d


def motion_batch(states: np.ndarray, increments: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``models.motion`` for many (state, increment) pairs in one call."""
    R = geometry.euler_to_matrix(states[:, 3:6])
    dR, dt = increments[:, :3, :3], increments[:, :3, 3]
    R_next = R @ dR
    rpy_next = geometry.matrix_to_euler(R_next)
    following = np.concatenate([states[:, :3] + np.einsum("wij,wj->wi", R, dt), rpy_next], axis=1)
    E = geometry.euler_rate_matrix(states[:, 3:6])
    E_next_inverse = np.linalg.inv(geometry.euler_rate_matrix(rpy_next))
    F = np.zeros((states.shape[0], 6, 6))
    F[:, 0:3, 0:3] = np.eye(3)
    F[:, 0:3, 3:6] = -R @ geometry.hat(dt) @ E
    F[:, 3:6, 3:6] = E_next_inverse @ np.swapaxes(dR, 1, 2) @ E
    G = np.zeros_like(F)
    G[:, 0:3, 0:3] = R_next
    G[:, 3:6, 3:6] = E_next_inverse
    return following, F, G


def observe_batch(states: np.ndarray, T_robot_camera: np.ndarray, intrinsics: np.ndarray, landmark_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``models.observe`` for many (state, camera, landmark) triples in one call."""
    R = geometry.euler_to_matrix(states[:, 3:6])
    R_c, t_c = T_robot_camera[:, :3, :3], T_robot_camera[:, :3, 3]
    p_robot = np.einsum("mji,mj->mi", R, landmark_xyz - states[:, :3])  # R^T (l - t)
    p_camera = np.einsum("mji,mj->mi", R_c, p_robot - t_c)
    z_hat = np.column_stack([intrinsics[:, 0] * p_camera[:, 0] / p_camera[:, 2] + intrinsics[:, 2],
                             intrinsics[:, 1] * p_camera[:, 1] / p_camera[:, 2] + intrinsics[:, 3], p_camera[:, 2]])
    d_robot = np.empty((states.shape[0], 3, 6))
    d_robot[:, :, 0:3] = -np.swapaxes(R, 1, 2)
    d_robot[:, :, 3:6] = geometry.hat(p_robot) @ geometry.euler_rate_matrix(states[:, 3:6])
    projection = models.projection_jacobian(p_camera, tuple(intrinsics.T))
    return z_hat, projection @ np.swapaxes(R_c, 1, 2) @ d_robot


if __name__ == "__main__":
    _bench.run(main)
