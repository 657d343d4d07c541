"""What running a sweep costs beyond its runs: the same 64 cells alone, in 1 and 2 local worker
processes, and on a two-worker local Dask cluster.

The cells: seeds 0..15 x trajectory (grid, smooth3d) x association (beam, oracle), 300 poses, the
simulator's defaults otherwise. For each way of running them: wall time, runs per minute, the mean
time a cell took inside its worker (``seconds`` of runs.csv: world, localization, metrics), and the
overhead per cell, wall x workers / cells minus the mean time of the same cell run alone in this
process (``camloc.sweep.run_cell``, one after another, no pool). On a shared 2-core machine the
overhead with 2 workers also holds the contention for the cores; the in-worker mean shows how much.
The rows of every way are checked to be identical (all but ``seconds``).

    nice python benchmarks/sweep.py [--seeds 16] [--poses 300] [--skip-dask] [--json]
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench  # noqa: E402  (the benchmarks folder is not a package)


def main() -> None:
    args = parse_args()
    from camloc.sweep import expand, parse_spec, run_cell, run_sweep

    spec = parse_spec({"seeds": args.seeds, "simulate": {"trajectory": ["grid", "smooth3d"], "poses": args.poses},
                       "run": {"association": ["beam", "oracle"]}}, source="benchmark")
    cells = expand(spec)
    say = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    say(f"camloc sweep benchmark: {len(cells)} cells of {args.poses} poses; {_bench.source_note()}; {_bench.machine_load()}")

    started = time.perf_counter()
    alone = [run_cell(cell)["seconds"] for cell in cells]
    report = [{"way": "alone (in this process, no pool)", "workers": 1, "wall_s": time.perf_counter() - started,
               "cell_mean_s": statistics.fmean(alone)}]
    say(f"  alone: {report[-1]['wall_s']:.1f} s")
    with tempfile.TemporaryDirectory(prefix="camloc-sweep-bench-") as tmp:
        ways = [("local, 1 worker", 1, {"workers": 1}), ("local, 2 workers", 2, {"workers": 2})]
        cluster = None
        if not args.skip_dask:
            cluster_started = time.perf_counter()
            cluster = _dask_cluster()
            if cluster is not None:
                say(f"  dask LocalCluster (2 workers, 1 thread each) started in {time.perf_counter() - cluster_started:.1f} s")
                ways.append(("dask LocalCluster, 2 workers", 2, {"scheduler": cluster.scheduler_address}))
        try:
            rows = {}
            for name, workers, how in ways:
                folder = Path(tmp) / name.replace(" ", "_").replace(",", "")
                started = time.perf_counter()
                run_sweep(spec, folder, **how)
                wall = time.perf_counter() - started
                rows[name] = _read_rows(folder / "runs.csv")
                seconds = [float(r["seconds"]) for r in rows[name]]
                report.append({"way": name, "workers": workers, "wall_s": wall, "cell_mean_s": statistics.fmean(seconds)})
                say(f"  {name}: {wall:.1f} s")
        finally:
            if cluster is not None:
                cluster.close()
    mean_alone = report[0]["cell_mean_s"]
    for entry in report:
        entry["runs_per_minute"] = 60.0 * len(cells) / entry["wall_s"]
        entry["overhead_per_cell_s"] = entry["wall_s"] * entry["workers"] / len(cells) - mean_alone
    strip = lambda table: [{k: v for k, v in r.items() if k != "seconds"} for r in table]  # noqa: E731
    identical = len({json.dumps(strip(table)) for table in rows.values()}) == 1
    say(f"rows identical across {', '.join(rows)}: {'yes' if identical else 'NO'}; {_bench.machine_load()}")
    if args.json:
        print(json.dumps({"cells": len(cells), "poses": args.poses, "identical_rows": identical, "ways": report}, indent=2))
        return
    print("| way | wall [s] | runs/min | cell in its worker [s] | overhead per cell [s] |")
    print("|---|---|---|---|---|")
    for entry in report:
        print(f"| {entry['way']} | {entry['wall_s']:.1f} | {entry['runs_per_minute']:.0f} | {entry['cell_mean_s']:.3f} "
              f"| {entry['overhead_per_cell_s']:+.3f} |")


def _dask_cluster():
    try:
        from distributed import LocalCluster
    except ImportError:
        print("dask.distributed is not installed (pip install -e '.[dask]'): no Dask row", file=sys.stderr)
        return None
    return LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)


def _read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=16, help="seeds per configuration (4 configurations); default 16")
    parser.add_argument("--poses", type=int, default=300, help="poses per world; default 300")
    parser.add_argument("--skip-dask", action="store_true", help="no Dask row")
    parser.add_argument("--json", action="store_true", help="JSON on stdout instead of a table")
    return parser.parse_args()


if __name__ == "__main__":
    main()
