"""How fast the smoother is on a long simulated run (20,000 poses by default).

Makes the data with the command line, exactly as a user would:

    camloc simulate --poses 20000 -o DIR/big.g2o
    camloc run DIR/big.g2o -o DIR/bigrun --association oracle --quiet

(oracle association only to get a run folder quickly; the smoother does not care how the pairs were
chosen), then, for each ``--map`` mode asked for (the map held exact: poses only; ``prior``
or ``none``: every observed landmark a variable too), times ``smooth_run`` in this process
(best of ``--repeats``, with a breakdown of one iteration) and ``camloc smooth DIR/bigrun --json
--map MODE`` end to end (start-up, reading the run folder and the g2o file, smoothing, the
landmarks' covariances, writing smoothed.tum and map.csv). Prints the figures.

    python benchmarks/smooth_speed.py [--poses 20000] [--dir DIR] [--repeats 3] [--map exact,prior]

With ``--dir`` the files are kept there and reused when present; otherwise a temporary directory
is used and removed.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench  # noqa: E402  (the benchmarks folder is not a package)


def camloc(*args: str) -> str:
    command = [sys.executable, "-m", "camloc.cli.app", *args]
    return subprocess.run(command, check=True, capture_output=True, text=True).stdout


def make_data(folder: Path, poses: int) -> tuple[Path, Path, dict]:
    dataset, run = folder / "big.g2o", folder / "bigrun"
    seconds = {}
    if not dataset.is_file():
        started = time.perf_counter()
        camloc("simulate", "--poses", str(poses), "-o", str(dataset))
        seconds["simulate"] = time.perf_counter() - started
    if not (run / "summary.json").is_file():
        started = time.perf_counter()
        camloc("run", str(dataset), "-o", str(run), "--association", "oracle", "--quiet")
        seconds["run (oracle)"] = time.perf_counter() - started
    return dataset, run, seconds


def breakdown(dataset, run, mode: str) -> dict[str, float]:
    """Seconds of each part of one iteration at the filter's poses."""
    from camloc import smoother
    from camloc.schur import SchurSolver

    config = smoother.SmootherConfig(map=mode)
    parts = {}
    started = time.perf_counter()
    problem = smoother.problem_from_run(dataset, run, config)
    T = smoother.initial_poses(dataset, run)
    problem, _ = smoother._with_initial_landmarks(problem, T)
    parts["build problem (once)"] = time.perf_counter() - started
    started = time.perf_counter()
    lin = smoother.linearize(problem, T)
    parts["residuals + sparse Jacobian"] = time.perf_counter() - started
    started = time.perf_counter()
    H, g = smoother.normal_equations(lin, 2.0, newton=True)
    parts["normal equations"] = time.perf_counter() - started
    started = time.perf_counter()
    smoother._solve_step(H, g, 0.0, problem.num_pose_unknowns if problem.num_landmarks else None)
    parts["scaled sparse solve" + (" (Schur + Cholesky)" if problem.num_landmarks else " (Cholesky)")] = time.perf_counter() - started
    Hs, _ = smoother._scaled(H)
    if problem.num_landmarks:
        solver = SchurSolver(Hs, problem.num_pose_unknowns)
        started = time.perf_counter()
        solver.landmark_covariances()
        parts["landmark covariances (once)"] = time.perf_counter() - started
    else:
        started = time.perf_counter()
        smoother.condition_estimate(Hs, smoother._factorization(Hs, Hs.shape[0]))
        parts["condition estimate (once)"] = time.perf_counter() - started
    return parts


def rmse(xyz, truth) -> float:
    return float(np.sqrt(np.mean(np.sum((xyz - truth) ** 2, axis=1))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=20_000, help="poses of the simulated run (default 20000)")
    parser.add_argument("--dir", type=Path, default=None, help="keep and reuse the data here (default: a temporary directory)")
    parser.add_argument("--repeats", type=int, default=3, help="timed smoothing runs, the best is reported (default 3)")
    parser.add_argument("--map", default="exact,prior", help="map modes to time, comma-separated (default exact,prior)")
    args = parser.parse_args()

    from camloc.g2o import read_g2o
    from camloc.results import load_run
    from camloc.smoother import SmootherConfig, smooth_run

    with tempfile.TemporaryDirectory() as temporary:
        folder = args.dir or Path(temporary)
        folder.mkdir(parents=True, exist_ok=True)
        print(f"camloc smooth speed; {_bench.source_note()}; {_bench.machine_load()}")
        dataset_path, run_dir, setup = make_data(folder, args.poses)
        dataset, run = read_g2o(dataset_path), load_run(run_dir)
        for name, seconds in setup.items():
            print(f"setup    {name}: {seconds:.1f} s")
        for mode in args.map.split(","):
            times, cpu, result = [], [], None
            for _ in range(args.repeats):
                started, started_cpu = time.perf_counter(), time.process_time()
                result = smooth_run(dataset, run, SmootherConfig(map=mode))
                times.append(time.perf_counter() - started)
                cpu.append(time.process_time() - started_cpu)
            parts = breakdown(dataset, run, mode)
            started, children = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
            report = json.loads(camloc("smooth", str(run_dir), "--json", "--map", mode))
            cli_seconds = time.perf_counter() - started
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cli_cpu = after.ru_utime + after.ru_stime - children.ru_utime - children.ru_stime

            landmarks = 0 if result.landmarks is None else len(result.landmarks.ids)
            print(f"--map {mode}")
            print(f"problem  {dataset.num_poses} poses, {landmarks} landmark variables "
                  f"({6 * (dataset.num_poses - 1) + 3 * landmarks} unknowns), "
                  f"{result.odometry_factors} odometry and {result.observation_factors} observation factors")
            print(f"solve    {min(times):.2f} s best of {args.repeats} (all: {', '.join(f'{t:.2f}' for t in times)}; "
                  f"CPU {', '.join(f'{t:.2f}' for t in cpu)} s), "
                  f"{result.iterations} iterations, converged: {result.converged}, "
                  f"{min(times) / max(result.iterations, 1):.2f} s per iteration")
            for name, seconds in parts.items():
                print(f"  {name:<36} {seconds:.3f} s")
            print(f"cli      camloc smooth --json --map {mode}: {cli_seconds:.2f} s end to end, CPU {cli_cpu:.2f} s "
                  f"(reading {report['timing']['read_seconds']:.2f} s, smoothing {report['timing']['smooth_seconds']:.2f} s)")
            print(f"machine  {_bench.machine_load()}")
            print(f"accuracy position RMSE filter {rmse(run.estimate_xyz, dataset.truth_xyz):.4f} m, smoothed "
                  f"{rmse(result.xyz, dataset.truth_xyz):.4f} m")


if __name__ == "__main__":
    main()
