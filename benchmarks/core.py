"""The compiled core's own figures, which ``scale.py`` (one fresh process per case) does not show:

- ``warm``: poses per second once the kernels are loaded: ``--calls`` calls of ``camloc.localize``
  on the 20k world in one process, beam and oracle; the first call of each pays numba's start and
  the loading of the cached machine code, the later ones do not. Wall time of the call and the
  loop's own ``summary["timing"]["filter_seconds"]`` (scene, association, filter).
- ``calls``: Python-level calls per pose (cProfile's count over one warm call on the first 1,000
  poses): what is left of the interpreter in the loop.
- ``compile``: the first run after an install: ``camloc run`` on the first 1,000 poses in a child
  process with an empty ``NUMBA_CACHE_DIR``, its wall time and peak memory (one to two minutes;
  ``--skip-compile`` leaves it out), three times: compiling first in one process
  (``CAMLOC_BACKGROUND_COMPILE=0``); compiling first with the filter's kernels in a second process,
  as a run of more than 2,000 poses does (``camloc.localize(engine="compiled")`` in the child; its
  peak is the first process's); and as a user meets it, in numpy while the kernels compile in the
  background (``camloc.warmup``): that run's wall, when the background compile ended, and the
  wall and engine of the run after it.

    nice python benchmarks/core.py [--quick] [--calls 3] [--skip-compile] [--json]

The worlds are ``scale.py``'s (``--quick``: its 1,000-pose world), cached in ``--cache``. Nothing
here asserts anything about time.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench  # noqa: E402  (the benchmarks folder is not a package)
from scale import FULL, QUICK  # noqa: E402

import camloc  # noqa: E402
from camloc import LocalizerConfig  # noqa: E402

METHODS = ("beam", "oracle")


def main() -> None:
    args = parse_args()
    plan = QUICK if args.quick else FULL
    cache = args.cache.expanduser()
    say = (lambda text: print(text, file=sys.stderr, flush=True))
    say(f"camloc core benchmark ({'quick' if args.quick else 'full'}); {_bench.source_note()}; {_bench.machine_load()}")
    world_path = _bench.simulated(cache, plan.world, seed=plan.seed)
    first_path = world_path if plan.world["poses"] <= 1000 else _bench.first_poses(cache, world_path, 1000)
    report: dict = {"world": world_path.name, "poses": None, "warm": {}, "calls_per_pose": {}, "compile": None,
                    "compile_two_processes": None, "compile_in_background": None}

    world = camloc.load(world_path)
    report["poses"] = world.num_poses
    for method in METHODS:
        say(f"warm: {args.calls} calls of camloc.localize on {world.num_poses} poses, association={method} ...")
        report["warm"][method] = warm_calls(world, method, args.calls)

    first = camloc.load(first_path)
    for method in METHODS:
        report["calls_per_pose"][method] = calls_per_pose(first, method)

    if args.skip_compile:
        say("compile: skipped (--skip-compile)")
    else:
        say(f"compile: camloc run {first_path.name} with an empty NUMBA_CACHE_DIR, compiling first (one to two minutes) ...")
        report["compile"] = first_compile(first_path, timeout=args.timeout)
        say("compile: the same, the filter's kernels compiling in a second process (about a minute) ...")
        report["compile_two_processes"] = first_compile(first_path, timeout=args.timeout, second_process=True)
        say("compile: the same, compiling in the background (one to two minutes) ...")
        report["compile_in_background"] = first_run_in_background(first_path, timeout=args.timeout)

    say(f"done; {_bench.machine_load()}")
    if args.json:
        print(json.dumps(report | {"source": _bench.source_note(), "machine": _bench.machine_load()}, indent=2))
    else:
        print_report(report)


def warm_calls(dataset, method: str, calls: int) -> list[dict]:
    """Each call's wall time and the loop's own time, in seconds."""
    config = LocalizerConfig(association=method)
    rows = []
    for _ in range(calls):
        started = time.perf_counter()
        result = camloc.localize(dataset, config)
        rows.append({"wall": time.perf_counter() - started, "filter": result.summary["timing"]["filter_seconds"],
                     "engine": result.summary["timing"]["engine"]})
    return rows


def calls_per_pose(dataset, method: str) -> float:
    """Python-level function calls per pose in one warm call (cProfile's count)."""
    config = LocalizerConfig(association=method)
    camloc.localize(dataset, config)
    profile = cProfile.Profile()
    profile.enable()
    camloc.localize(dataset, config)
    profile.disable()
    return pstats.Stats(profile).total_calls / dataset.num_poses


def first_compile(path: Path, *, timeout: float, second_process: bool = False) -> dict:
    """Wall time and peak memory of ``camloc run`` compiling every kernel it needs from nothing
    (spawned through ``_bench.timed_command``, so that the peak is the child's own); with
    ``second_process``, of ``camloc.localize(engine="compiled")``, which compiles first whatever the
    dataset's size, with the filter's kernels compiling in a second process (not in the peak)."""
    with tempfile.TemporaryDirectory(prefix="camloc-core-") as scratch, _environment(
            NUMBA_CACHE_DIR=str(Path(scratch) / "numba"), CAMLOC_BACKGROUND_COMPILE="1" if second_process else "0"):
        command = _bench.camloc_command() + ["run", str(path), "-o", str(Path(scratch) / "run"), "--quiet"]
        if second_process:
            command = [sys.executable, "-c", "import sys, camloc; camloc.localize(camloc.load(sys.argv[1]), engine='compiled')",
                       str(path)]
        seconds, peak_mb, status = _bench.timed_command(command, timeout=timeout)
    if status != 0:
        raise _bench.BenchError(f"camloc run exited {status} while compiling")
    return {"seconds": seconds, "peak_mb": peak_mb}


def first_run_in_background(path: Path, *, timeout: float) -> dict:
    """``camloc run`` from an empty cache as a user meets it: its wall time (numpy, the kernels
    compiling in a background process), seconds from its start until that process ended, and the
    wall time and engine of the run after it."""
    from camloc.warmup import LOCK_NAME

    with tempfile.TemporaryDirectory(prefix="camloc-core-") as scratch, _environment(
            NUMBA_CACHE_DIR=str(Path(scratch) / "numba"), CAMLOC_BACKGROUND_COMPILE="1"):
        run = _bench.camloc_command() + ["run", str(path), "-o", str(Path(scratch) / "run"), "--force", "--quiet"]
        started = time.perf_counter()
        first, _, status = _bench.timed_command(run, timeout=timeout)
        if status != 0:
            raise _bench.BenchError(f"camloc run exited {status} on an empty cache")
        while any(Path(scratch, "numba").rglob(LOCK_NAME)):
            if time.perf_counter() - started > timeout:
                raise _bench.BenchError("the background compile did not end within the timeout")
            if any("failed" in lock.read_text() for lock in Path(scratch, "numba").rglob(LOCK_NAME)):
                raise _bench.BenchError("the background compile failed")
            time.sleep(1.0)
        compiled_after = time.perf_counter() - started
        second, _, status = _bench.timed_command(run, timeout=timeout)
        summary = json.loads((Path(scratch) / "run" / "summary.json").read_text())
    if status != 0:
        raise _bench.BenchError(f"camloc run exited {status} after the background compile")
    return {"first_seconds": first, "compiled_after_seconds": compiled_after, "second_seconds": second,
            "second_engine": summary["timing"]["engine"]}


class _environment:
    """Environment variables set for the children started inside the block (this process's numba
    has read its own cache folder already)."""

    def __init__(self, **values: str):
        self.values, self.saved = values, {}

    def __enter__(self):
        self.saved = {name: os.environ.get(name) for name in self.values}
        os.environ.update(self.values)

    def __exit__(self, *exc):
        for name, value in self.saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def print_report(report: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    n = report["poses"]
    table = Table(title=f"camloc core: warm process, {report['world']} ({n} poses)")
    for column in ("association", "call", "wall (s)", "loop (s)", "poses/s (loop)", "µs/pose (loop)", "engine"):
        table.add_column(column, justify="right" if column not in ("association", "engine") else "left")
    for m, (method, rows) in enumerate(report["warm"].items()):
        for i, row in enumerate(rows):
            # the process's first call starts numba and loads the cached kernels the later ones reuse
            table.add_row(method, str(i + 1) + (" (first)" if m == i == 0 else ""), f"{row['wall']:.2f}", f"{row['filter']:.2f}",
                          f"{n / row['filter']:,.0f}", f"{1e6 * row['filter'] / n:.0f}", row["engine"])
    console = Console()
    console.print(table)
    for method, rows in report["warm"].items():
        later = [row["filter"] for row in rows[1:]] or [rows[0]["filter"]]
        console.print(f"{method}: warm loop median {statistics.median(later):.2f} s = {n / statistics.median(later):,.0f} poses/s; "
                      f"Python-level calls per pose {report['calls_per_pose'][method]:.1f}")
    if report["compile"] is not None:
        console.print(f"first run, compiling first: {report['compile']['seconds']:.1f} s, peak {report['compile']['peak_mb']:.0f} MB")
        two = report["compile_two_processes"]
        console.print(f"first run, compiling first with the filter in a second process: {two['seconds']:.1f} s, "
                      f"peak {two['peak_mb']:.0f} MB (the first process)")
        background = report["compile_in_background"]
        console.print(f"first run, compiling in the background: {background['first_seconds']:.1f} s in numpy; the compile ended "
                      f"{background['compiled_after_seconds']:.0f} s after its start; the next run {background['second_seconds']:.1f} s "
                      f"({background['second_engine']})")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="scale.py's 1,000-pose world instead of its 20k one (default: full)")
    parser.add_argument("--cache", type=Path, default=_bench.DEFAULT_CACHE,
                        help=f"generated worlds are kept here (default {_bench.DEFAULT_CACHE})")
    parser.add_argument("--calls", type=int, default=3, help="camloc.localize calls per association in one process (default 3)")
    parser.add_argument("--skip-compile", action="store_true", help="leave out the first compile (default: measure it)")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds allowed for the first compile (default 1800)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON instead of a table (default: table)")
    return parser.parse_args()


if __name__ == "__main__":
    _bench.run(main)
