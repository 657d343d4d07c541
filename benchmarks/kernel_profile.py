"""Where the compiled loop's time goes, by kernel: a sampling profile (Linux ``perf``) of warm calls
of ``camloc.localize``, with the kernels' machine code named.

cProfile sees only Python; inside a kernel it sees one call. ``perf`` samples the machine code, and
this script names numba's code for it: once the kernels are loaded it writes ``/tmp/perf-<pid>.map``
(perf's map of JIT-compiled code: start, size and name of every function of every loaded kernel
library), then profiles ``--calls`` more calls of ``camloc.localize`` and groups the samples:

- each compiled function by its own name (a step LLVM inlined counts as its caller's);
- ``refcounts``: numba's reference counting of arrays (``NRT_incref``/``NRT_decref``); a kernel
  that is not inlined increfs every array it is passed on entry (the scene's 31) and decrefs them
  on return;
- ``python``, ``numpy``, ``malloc and copies`` (libc), ``libm``, ``BLAS``, ``os kernel``, ``other``.

Shares are of CPU samples, over every thread (the beam and the filter's replay run in two). Also
the arrays the kernels allocate per pose, each a malloc, a free and reference counts: counted by
numba's runtime statistics in a child process (``NUMBA_NRT_STATS=1``, whose atomic counters would
slow the profiled calls).

    nice python benchmarks/kernel_profile.py [--quick | --world FILE.g2o] [--association beam|oracle] [--calls 1] [--top 25] [--json]

Needs ``perf`` (``linux-perf``/``linux-tools``) allowed to attach to its own process
(``/proc/sys/kernel/perf_event_paranoid`` at most 2). The world is ``scale.py``'s 20k world
(``--quick``: its 1,000-pose world), cached in ``--cache``. Reads numba's private code-library
fields (``_shared_module``, ``_final_module``, ``_codegen``), which numba may rename: numba 0.68.
"""

from __future__ import annotations

import argparse
import collections
import importlib
import json
import os
import pkgutil
import re
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench  # noqa: E402  (the benchmarks folder is not a package)
from scale import FULL, QUICK  # noqa: E402

import camloc  # noqa: E402
import camloc.kernels  # noqa: E402

SAMPLE_HZ = 999
GROUPS = (  # (group, pattern on perf's shared-object name)
    ("python", r"libpython|python3"),
    ("numpy", r"_multiarray|numpy"),
    ("malloc and copies", r"libc\.so|libc-"),
    ("libm", r"libm\.so|libm-"),
    ("BLAS", r"blas|lapack"),
    ("os kernel", r"kernel"),
    ("numba runtime", r"_nrt_python|_helperlib|_dispatcher"),
)


def main() -> None:
    args = parse_args()
    if shutil.which("perf") is None:
        _bench._fail("perf is not installed (Debian: linux-perf; Ubuntu: linux-tools-generic)")
    plan = QUICK if args.quick else FULL
    say = (lambda text: print(text, file=sys.stderr, flush=True))
    say(f"camloc kernel profile ({'quick' if args.quick else 'full'}); {_bench.source_note()}; {_bench.machine_load()}")
    world_path = args.world or _bench.simulated(args.cache.expanduser(), plan.world, seed=plan.seed)
    world = camloc.load(world_path)
    config = camloc.LocalizerConfig(association=args.association)
    say(f"warm-up: one call on {world.num_poses} poses, association={args.association} ...")
    camloc.localize(world, config, engine="compiled")
    perf_map = Path(f"/tmp/perf-{os.getpid()}.map")
    named = write_perf_map(perf_map)
    say(f"{named} compiled functions named; profiling {args.calls} call(s) ...")
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "perf.data"
        recorder = subprocess.Popen(["perf", "record", "-F", str(SAMPLE_HZ), "-p", str(os.getpid()), "-o", str(data)],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        time.sleep(1.0)  # perf attaches
        started = time.perf_counter()
        for _ in range(args.calls):
            camloc.localize(world, config, engine="compiled")
        wall = time.perf_counter() - started
        recorder.send_signal(signal.SIGINT)
        _, err = recorder.communicate(timeout=120)
        try:
            if not data.exists():
                _bench._fail(f"perf record failed: {err.decode(errors='replace').strip()[-400:]}")
            rows = perf_rows(data)
        finally:
            perf_map.unlink(missing_ok=True)
    report = summarize(rows, wall=wall, poses=world.num_poses * args.calls, top=args.top)
    say("counting the kernels' allocations in a child process ...")
    report["arrays_allocated_per_pose"] = allocations_per_pose(world_path, args.association)
    report.update(world=world.num_poses, association=args.association, calls=args.calls)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print_report(report)


def allocations_per_pose(path: Path, association: str) -> float:
    """Arrays the kernels allocate per pose in one warm call on ``path`` (a child process)."""
    code = ("import sys, camloc\n"
            "from numba.core.runtime import rtsys\n"
            "world, config = camloc.load(sys.argv[1]), camloc.LocalizerConfig(association=sys.argv[2])\n"
            "camloc.localize(world, config, engine='compiled')\n"
            "before = rtsys.get_allocation_stats().alloc\n"
            "camloc.localize(world, config, engine='compiled')\n"
            "print((rtsys.get_allocation_stats().alloc - before) / world.num_poses)\n")
    child = subprocess.run([sys.executable, "-c", code, str(path), association], capture_output=True, text=True,
                           env={**os.environ, "NUMBA_NRT_STATS": "1"}, check=True)
    return round(float(child.stdout.split()[-1]), 1)


def kernel_libraries():
    """Every code library of a compiled kernel loaded in this process (one per signature)."""
    from numba.core.dispatcher import Dispatcher

    seen = {}
    for info in pkgutil.iter_modules(camloc.kernels.__path__):
        module = importlib.import_module(f"camloc.kernels.{info.name}")
        for value in vars(module).values():
            if isinstance(value, Dispatcher):
                for compiled in value.overloads.values():
                    seen[id(compiled.library)] = compiled.library
    return list(seen.values())


def write_perf_map(path: Path) -> int:
    """perf's map of the kernels' machine code: each defined function's address in this process
    (numba's execution engine) and its size (the library's module emitted once more as an object
    file: the same code generator, so the same sizes). Returns the number of functions named."""
    entries = {}
    for library in kernel_libraries():
        module = library._shared_module if library._shared_module is not None else library._final_module
        sizes = elf_function_sizes(library._codegen._tm.emit_object(module))
        for function in module.functions:
            if function.is_declaration or function.name not in sizes:
                continue
            address = library._codegen._engine.get_function_address(function.name)
            if address:
                entries[address] = (sizes[function.name], readable(function.name))
    with open(path, "w") as out:
        for address, (size, name) in sorted(entries.items()):
            out.write(f"{address:x} {max(size, 1):x} {name}\n")
    return len(entries)


def elf_function_sizes(obj: bytes) -> dict[str, int]:
    """{symbol: size} of an ELF64 little-endian object's function symbols (its symbol table)."""
    section_offset, = struct.unpack_from("<Q", obj, 0x28)
    entry_size, count = struct.unpack_from("<HH", obj, 0x3A)
    sections = [struct.unpack_from("<IIQQQQIIQQ", obj, section_offset + i * entry_size) for i in range(count)]
    sizes = {}
    for _, kind, _, _, offset, size, link, _, _, sym_size in sections:
        if kind != 2:    # SHT_SYMTAB
            continue
        strings = sections[link][4]
        for at in range(offset, offset + size, sym_size):
            name_at, info, _, _, _, sym_bytes = struct.unpack_from("<IBBHQQ", obj, at)
            if info & 0xF == 2:    # STT_FUNC
                end = obj.index(b"\0", strings + name_at)
                sizes[obj[strings + name_at:end].decode()] = sym_bytes
    return sizes


def readable(symbol: str) -> str:
    """``camloc.kernels.beam.options_for`` from numba's mangled name (module path and function)."""
    if not symbol.startswith("_ZN"):
        return symbol
    names, at = [], 3
    while at < len(symbol) and symbol[at].isdigit():
        digits = re.match(r"\d+", symbol[at:]).group()
        at += len(digits)
        names.append(symbol[at:at + int(digits)])
        at += int(digits)
    name = ".".join(names) if names else symbol
    name = name.replace("_3clocals_3e", "<locals>")
    return ("wrapper of " + name[len("cpython."):]) if name.startswith("cpython.") else name


def perf_rows(data: Path) -> list[tuple[float, str, str]]:
    """(share in percent, shared object, symbol) of every sample group perf reports."""
    text = subprocess.run(["perf", "report", "-i", str(data), "--stdio", "--no-children", "--sort", "dso,sym",
                           "-g", "none", "--percent-limit", "0.01"], capture_output=True, text=True, check=True).stdout
    rows = []
    for line in text.splitlines():
        match = re.match(r"\s*([\d.]+)%\s+(\S.*?)\s+\[[.k]\]\s+(.*)$", line)
        if match:
            rows.append((float(match.group(1)), match.group(2).strip(), match.group(3).strip()))
    return rows


def summarize(rows, *, wall: float, poses: int, top: int) -> dict:
    """Shares by group and by compiled function."""
    groups, functions = collections.Counter(), collections.Counter()
    for share, dso, symbol in rows:
        if dso.startswith("[JIT]") or dso.startswith("perf-"):
            if symbol.startswith("NRT_incref") or symbol.startswith("NRT_decref"):
                groups["refcounts"] += share
            elif symbol.startswith("0x"):
                groups["compiled, unnamed (no exported symbol)"] += share
            else:
                groups["compiled kernels"] += share
                functions[symbol] += share
            continue
        group = next((name for name, pattern in GROUPS if re.search(pattern, dso)), "other")
        groups[group] += share
    return {
        "wall_seconds": round(wall, 3),
        "poses_per_second": round(poses / wall, 1),
        "groups_percent": {name: round(share, 2) for name, share in groups.most_common()},
        "functions_percent": {name: round(share, 2) for name, share in functions.most_common(top)},
    }


def print_report(report: dict) -> None:
    print(f"\n{report['calls']} warm call(s), {report['world']} poses, association={report['association']}: "
          f"{report['wall_seconds']:.2f} s wall, {report['poses_per_second']:,.0f} poses/s; "
          f"{report['arrays_allocated_per_pose']:,.0f} arrays allocated by the kernels per pose")
    print("\n| where (share of CPU samples, all threads) | % |\n|---|---|")
    for name, share in report["groups_percent"].items():
        print(f"| {name} | {share:.1f} |")
    print("\n| compiled function (inlined steps count as their caller) | % |\n|---|---|")
    for name, share in report["functions_percent"].items():
        print(f"| {name} | {share:.1f} |")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="the 1,000-pose world instead of the 20k world")
    parser.add_argument("--world", type=Path, default=None,
                        help="a g2o file to profile instead of scale.py's world (default: none)")
    parser.add_argument("--association", choices=("beam", "oracle"), default="beam", help="default: beam")
    parser.add_argument("--calls", type=int, default=1, help="profiled calls after the warm-up (default: 1)")
    parser.add_argument("--top", type=int, default=25, help="compiled functions listed (default: 25)")
    parser.add_argument("--cache", type=Path, default=Path("~/.cache/camloc-bench"),
                        help="where generated worlds are kept (default: ~/.cache/camloc-bench)")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    return parser.parse_args()


if __name__ == "__main__":
    _bench.run(main)
