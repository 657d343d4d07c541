"""The beam on hard simulated worlds, world by world: odometry slips put on one edge (a jump of the
position, or of the heading), 3x odometry noise, dense maps, heavy clutter, few detections a pose.
``association.py``'s cases rarely make the beam search from seeds; these worlds do, so a change to
the slip search, the seeds or the trigger shows here first.

Each world is built on purpose: a seeded ``camloc.simulate`` world, and where a family has a
slip, its odometry edge 100 (pose 100 to 101) moved by a fixed amount. Every world is localized
with the default configuration (the compiled loop, one process, ``parallel=False``) and with the
oracle. Per world: position RMSE, the oracle's, precision (correct / accepted pairs), the poses
explained as slips, and the localize time. Per family: the mean and worst RMSE ratio to the oracle
and the pooled precision.

To compare two versions of camloc, save one run's rows and compare the other's against them:

    nice python benchmarks/hard_worlds.py --json > before.json      # at the old commit
    nice python benchmarks/hard_worlds.py --compare before.json      # at the new one

``--compare`` lists the worlds whose RMSE or precision changed. Worlds are made in memory (about a
second each); the run takes about a minute once the kernels are compiled.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench  # noqa: E402  (the benchmarks folder is not a package)

SLIP_EDGE = 100


def with_a_jump(dataset, shift=(0.0, 0.0, 0.0), yaw_deg: float = 0.0):
    """The dataset with odometry edge SLIP_EDGE off by ``shift`` metres and ``yaw_deg`` of heading."""
    translation = dataset.odom_translation.copy()
    translation[SLIP_EDGE] += np.asarray(shift)
    quat = dataset.odom_quat_xyzw.copy()
    if yaw_deg:
        quat[SLIP_EDGE] = (Rotation.from_quat(quat[SLIP_EDGE]) * Rotation.from_euler("z", yaw_deg, degrees=True)).as_quat()
    return dataclasses.replace(dataset, odom_translation=translation, odom_quat_xyzw=quat)


def families():
    """name -> (description, world(seed) -> dataset)."""
    from camloc.simulate import SimulationConfig, simulate

    def dense(seed, clutter=0.0):
        return simulate(SimulationConfig(trajectory="smooth3d", poses=200, landmarks=1500, region=11, clutter_fraction=clutter), seed=seed)

    return {
        "smooth3d-3x-clutter20": ("smooth3d, 300 poses, 3x odometry noise, 20% clutter",
                                  lambda s: simulate(SimulationConfig(trajectory="smooth3d", poses=300, odometry_sigma_scale=3.0,
                                                                      clutter_fraction=0.2), seed=500 + s)),
        "grid-3x": ("grid, 300 poses, 3x odometry noise",
                    lambda s: simulate(SimulationConfig(poses=300, odometry_sigma_scale=3.0), seed=500 + s)),
        "dense-jump": ("dense smooth3d map (1,500 in 11 m), an 8-sigma jump (0.6, -0.5, 0) m",
                       lambda s: with_a_jump(dense(s), (0.6, -0.5, 0.0))),
        "dense-jump-small": ("the same, a 4-sigma jump (0.3, -0.25, 0) m", lambda s: with_a_jump(dense(s), (0.3, -0.25, 0.0))),
        "dense-yaw": ("the same, a 15 deg jump of the heading", lambda s: with_a_jump(dense(s), yaw_deg=15.0)),
        "dense-clutter35-jump": ("the same map, 35% clutter, the 8-sigma jump",
                                 lambda s: with_a_jump(dense(s, clutter=0.35), (0.6, -0.5, 0.0))),
        "grid-2obs-jump": ("grid, at most 2 detections a pose, a jump of 0.8 m",
                           lambda s: with_a_jump(simulate(SimulationConfig(poses=200, max_observations_per_pose=2), seed=s), (0.8, 0.0, 0.0))),
        "aerial-jump": ("aerial, pixel intrinsics, 2 cameras, a jump of (0.5, 0.4, 0.1) m and 10 deg",
                        lambda s: with_a_jump(simulate(SimulationConfig(trajectory="aerial", poses=300, intrinsics="pixel", cameras=2), seed=s),
                                              (0.5, 0.4, 0.1), yaw_deg=10.0)),
        "grid-dense-clutter30-out10": ("grid, dense map, 30% clutter, 10% outliers",
                                       lambda s: simulate(SimulationConfig(poses=200, dense=True, clutter_fraction=0.3, outlier_fraction=0.1),
                                                          seed=s)),
        "smooth3d-clutter40-jump": ("smooth3d, 40% clutter, the 8-sigma jump",
                                    lambda s: with_a_jump(simulate(SimulationConfig(trajectory="smooth3d", poses=200, clutter_fraction=0.4), seed=s),
                                                          (0.6, -0.5, 0.0))),
        "smooth3d-dense-2x": ("smooth3d, 500 poses, dense map, 2x odometry noise",
                              lambda s: simulate(SimulationConfig(trajectory="smooth3d", poses=500, dense=True, odometry_sigma_scale=2.0), seed=s)),
    }


def measure(name: str, seed: int, dataset) -> dict:
    import camloc

    def run(association):
        started = time.perf_counter()
        result = camloc.localize(dataset, camloc.LocalizerConfig(association=association), engine="compiled", parallel=False)
        return result, time.perf_counter() - started

    result, seconds = run("beam")
    oracle, _ = run("oracle")
    pairs = result.associations
    made = pairs.landmark != -1
    return {
        "world": f"{name}-s{seed}", "family": name, "seed": seed,
        "rmse_m": _rmse(result, dataset), "oracle_rmse_m": _rmse(oracle, dataset),
        "accepted": int(made.sum()), "correct": int((made & (pairs.landmark == pairs.true_landmark)).sum()),
        "slips": len(result.summary.get("slip_poses", [])), "seconds": seconds,
    }


def _rmse(result, dataset) -> float:
    return float(np.sqrt(np.mean(np.sum((result.estimate_xyz - dataset.truth_xyz) ** 2, axis=1))))


def family_rows(rows: list[dict], described: dict) -> list[list[str]]:
    out = []
    for name, (description, _) in described.items():
        mine = [r for r in rows if r["family"] == name]
        if not mine:
            continue
        ratio = np.array([r["rmse_m"] / r["oracle_rmse_m"] for r in mine])
        precision = sum(r["correct"] for r in mine) / max(sum(r["accepted"] for r in mine), 1)
        out.append([name, str(len(mine)), f"{np.mean([r['rmse_m'] for r in mine]):.3f}", f"{ratio.mean():.2f}", f"{ratio.max():.2f}",
                    f"{100 * precision:.2f}%", str(sum(r["slips"] for r in mine)), f"{sum(r['seconds'] for r in mine):.1f}"])
    return out


def changed(rows: list[dict], before: list[dict]) -> list[list[str]]:
    earlier = {r["world"]: r for r in before}
    out = []
    for r in rows:
        b = earlier.get(r["world"])
        if b is None:
            continue
        precision = r["correct"] / max(r["accepted"], 1)
        precision_before = b["correct"] / max(b["accepted"], 1)
        if b["rmse_m"] != r["rmse_m"] or precision_before != precision:
            out.append([r["world"], f"{b['rmse_m']:.4f} -> {r['rmse_m']:.4f}", f"{100 * precision_before:.2f}% -> {100 * precision:.2f}%",
                        f"{b['slips']} -> {r['slips']}"])
    return out


def main() -> None:
    described = families()
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=8, help="seeds per family, 0..N-1 (default 8)")
    parser.add_argument("--families", default=",".join(described),
                        help=f"comma-separated families (default all: {','.join(described)})")
    parser.add_argument("--compare", type=Path, help="a saved --json run: list the worlds whose RMSE or precision changed (default: none)")
    parser.add_argument("--json", action="store_true", help="print the rows as JSON instead of tables (default: tables)")
    args = parser.parse_args()
    chosen = [f.strip() for f in args.families.split(",") if f.strip()]
    unknown = sorted(set(chosen) - set(described))
    if unknown:
        parser.error(f"unknown families: {', '.join(unknown)}")
    say = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    say(f"camloc hard worlds; {_bench.source_note()}; {_bench.machine_load()}")
    rows = []
    for name in chosen:
        for seed in range(args.seeds):
            row = measure(name, seed, described[name][1](seed))
            say(f"{row['world']}: RMSE {row['rmse_m']:.4f} m (oracle {row['oracle_rmse_m']:.4f}), "
                f"precision {100 * row['correct'] / max(row['accepted'], 1):.2f}%, {row['slips']} slips, {row['seconds']:.2f} s")
            rows.append(row)
    before = json.loads(args.compare.read_text())["worlds"] if args.compare else None
    if args.json:
        print(json.dumps({"source": _bench.source_note(), "worlds": rows, **({"changed": changed(rows, before)} if before else {})}, indent=1))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title="the beam on hard worlds (default configuration)")
    for column in ("family", "worlds", "RMSE mean (m)", "RMSE / oracle, mean", "worst", "precision", "slips", "seconds"):
        table.add_column(column, justify="left" if column == "family" else "right")
    for row in family_rows(rows, described):
        table.add_row(*row)
    console = Console(width=None if sys.stdout.isatty() else 160)  # a file gets whole family names
    console.print(table)
    if before is not None:
        diff = Table(title=f"worlds changed against {args.compare}")
        for column in ("world", "RMSE (m)", "precision", "slips"):
            diff.add_column(column)
        for row in changed(rows, before):
            diff.add_row(*row)
        console.print(diff)
    say(f"done; {_bench.machine_load()}")


if __name__ == "__main__":
    _bench.run(main)
