"""How fast ``read_g2o`` reads a large file.

Builds a seeded synthetic dataset (20,000 poses, about 10 observations per pose, written with
``write_g2o`` into a temporary directory, so about 230,000 lines), then times ``read_g2o`` (best
of 3) and prints lines, seconds and lines per second. The data is random but shaped like the real
file: a wandering trajectory, a landmark map, diagonal information matrices, full-precision floats
(which are longer, so slower to parse, than the real file's 6 digits).

    python benchmarks/read_speed.py [--poses 20000] [--obs-per-pose 10] [--repeats 3]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from camloc import geometry
from camloc.dataset import Camera, Dataset
from camloc.g2o import observation_cov_from_info, odometry_cov_from_info, read_g2o, write_g2o


def make_dataset(rng: np.random.Generator, *, num_poses: int, obs_per_pose: float,
                 num_landmarks: int = 2000) -> Dataset:
    """A random dataset of the requested size (its numbers are plausible, not simulated)."""
    step_xyz = rng.normal(0.0, 0.3, (num_poses - 1, 3))
    step_quat = geometry.euler_to_quat(rng.normal(0.0, 0.05, (num_poses - 1, 3)))
    truth_xyz = np.vstack([np.zeros((1, 3)), np.cumsum(step_xyz, axis=0)])
    truth_quat = geometry.euler_to_quat(rng.normal(0.0, 1.0, (num_poses, 3)))
    counts = rng.poisson(obs_per_pose, num_poses)
    num_obs = int(counts.sum())
    odom_info = np.broadcast_to(np.diag([100.0] * 3 + [10000.0] * 3), (num_poses - 1, 6, 6)).copy()
    obs_info = np.broadcast_to(np.eye(3) * 1000.0, (num_obs, 3, 3)).copy()
    camera = Camera(id=0, translation=np.array([0.0, 0.0, 0.3]), quat_xyzw=np.array([0.5, -0.5, 0.5, -0.5]),
                    fx=1.0, fy=1.0, cx=0.5, cy=0.5)
    return Dataset(
        source="benchmarks/read_speed.py",
        cameras={0: camera},
        landmark_ids=np.arange(num_landmarks, dtype=np.int64),
        landmark_xyz=rng.uniform(-50.0, 50.0, (num_landmarks, 3)),
        pose_ids=np.arange(100_000, 100_000 + num_poses, dtype=np.int64),
        start_xyz=truth_xyz[0],
        start_quat_xyzw=truth_quat[0],
        truth_xyz=truth_xyz,
        truth_quat_xyzw=truth_quat,
        odom_translation=step_xyz,
        odom_quat_xyzw=step_quat,
        odom_info=odom_info,
        odom_cov=odometry_cov_from_info(odom_info),
        obs_pose_index=np.repeat(np.arange(num_poses, dtype=np.int64), counts),
        obs_camera=np.zeros(num_obs, dtype=np.int64),
        obs_z=rng.uniform([-0.5, 0.0, 0.3], [1.5, 1.5, 2.0], (num_obs, 3)),
        obs_info=obs_info,
        obs_cov=observation_cov_from_info(obs_info),
        obs_true_landmark=rng.integers(0, num_landmarks, num_obs),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=20_000, help="number of poses (default 20000)")
    parser.add_argument("--obs-per-pose", type=float, default=10.0, help="mean observations per pose (default 10)")
    parser.add_argument("--repeats", type=int, default=3, help="timed reads, the best is reported (default 3)")
    args = parser.parse_args()

    dataset = make_dataset(np.random.default_rng(20261122), num_poses=args.poses, obs_per_pose=args.obs_per_pose)
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "large.g2o"
        started = time.perf_counter()
        write_g2o(dataset, path)
        write_seconds = time.perf_counter() - started
        lines = path.read_bytes().count(b"\n")
        megabytes = path.stat().st_size / 1e6
        times = []
        for _ in range(args.repeats):
            started = time.perf_counter()
            read_back = read_g2o(path)
            times.append(time.perf_counter() - started)
    assert read_back.num_observations == dataset.num_observations  # the timed read did the work
    best = min(times)
    print(f"file     {lines} lines, {megabytes:.1f} MB ({dataset.num_poses} poses, "
          f"{dataset.num_observations} observations)")
    print(f"write    {write_seconds:.3f} s")
    print(f"read     {best:.3f} s best of {args.repeats} (all: {', '.join(f'{t:.3f}' for t in times)})")
    print(f"speed    {lines / best:,.0f} lines/s")


if __name__ == "__main__":
    main()
