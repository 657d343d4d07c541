"""Where the kernels' first compile goes, by kernel: numba's compile events over the steps of a
first compile (``camloc.warmup``'s: the beam over the bundled clutter world with a slip, the
oracle, the beam's late kernels), in one process, with an empty cache.

Each kernel's own time (its compile minus the kernels compiled inside it) and its whole time: an
inlined step (``@inlined``) is compiled again inside each caller and counts as the caller's own
time, so a kernel whose own time grows has had more inlined into it. Times are the process's CPU
seconds (numba compiles in the calling thread), so that other processes' load does not inflate
them as it did wall time (an own-time sum of 174 s against 115 s of CPU at load 3.5); their sum is
the CPU time of compilation (type inference, lowering, LLVM). Then every kernel compiled for more
than one signature (each specialization compiles the kernel and all it calls again).

    NUMBA_CACHE_DIR=$(mktemp -d) CAMLOC_BACKGROUND_COMPILE=0 nice python benchmarks/compile_profile.py [--top 40]

``--modules`` adds each kernel's module's size in LLVM instructions (its code and every compiled
function it calls, linked in and generated again): a figure the machine's load does not move.

``--dataset FILE`` profiles what ``camloc run FILE`` compiles instead (with
``CAMLOC_BACKGROUND_COMPILE=0``: the compiled engine, default options, one process), the issue's
world's first compile; ``--signatures`` lists every kernel compiled with its signatures, not only
those compiled more than once.

``NUMBA_CACHE_DIR`` must name an empty folder: a kernel loaded from the cache is not compiled and
does not show. Without it, the script refuses to run where the cache is warm.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import os
import sys
import time

from numba.core import event


class _Recorder(event.Listener):
    """Start and end times of every compile event (``kind`` "") or hold of numba's LLVM lock
    (``kind`` "llvm "), in order, with its dispatcher."""

    def __init__(self, records: list, kind: str = "") -> None:
        self.records, self.kind = records, kind

    def on_start(self, ev) -> None:
        self.records.append((self.kind + "start", time.process_time(), (ev.data or {}).get("dispatcher")))

    def on_end(self, ev) -> None:
        # (the LLVM lock's events carry no data; an exception here leaves numba's lock held)
        self.records.append((self.kind + "end", time.process_time(), (ev.data or {}).get("dispatcher")))


def _name(dispatcher) -> str:
    function = getattr(dispatcher, "py_func", None)
    return f"{function.__module__}.{function.__qualname__}" if function is not None else str(dispatcher)


def own_times(records) -> tuple[collections.Counter, collections.Counter, collections.Counter, collections.Counter]:
    """Each kernel's own compile seconds, whole seconds, number of compiles and own seconds in LLVM
    (numba's LLVM lock held, outermost: optimizing and generating the kernel's module, which holds
    a copy of every compiled function it calls), from nested events."""
    stack: list[list] = []
    own, whole, count, llvm = collections.Counter(), collections.Counter(), collections.Counter(), collections.Counter()
    held: list[float] = []
    for kind, at, dispatcher in records:
        if kind == "llvm start":
            held.append(at)
            continue
        if kind == "llvm end":
            started = held.pop()
            if not held and stack:
                llvm[stack[-1][0]] += at - started
            continue
        if kind == "start":
            stack.append([_name(dispatcher), at, 0.0])
            continue
        name, started, inner = stack.pop()
        seconds = at - started
        own[name] += seconds - inner
        whole[name] += seconds
        count[name] += 1
        if stack:
            stack[-1][2] += seconds
    return own, whole, count, llvm


def first_compile() -> None:
    """The steps of ``camloc.warmup.compile_kernels`` and ``compile_filter_kernels``, in one process."""
    import numpy as np

    from camloc import warmup
    from camloc.bundled import bundled_dataset
    from camloc.g2o import read_g2o
    from camloc.localizer_config import LocalizerConfig

    dataset = read_g2o(bundled_dataset("smooth3d-clutter"))
    slipped = dataset.odom_translation.copy()
    slipped[60] += np.array([0.6, -0.5, 0.0])
    dataset = dataclasses.replace(dataset, odom_translation=slipped)
    warmup._run_compiled(dataset, LocalizerConfig(association="beam"))
    warmup._run_compiled(dataset, LocalizerConfig(association="oracle"))
    warmup.late_beam_kernels(dataset, LocalizerConfig())


def run_of(path: str) -> None:
    """What ``camloc run PATH`` compiles with ``CAMLOC_BACKGROUND_COMPILE=0``: the compiled
    engine over the file, its default options, in this one process."""
    from camloc.g2o import read_g2o
    from camloc.localizer import localize

    localize(read_g2o(path), engine="compiled")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--top", type=int, default=40, help="kernels listed (default 40)")
    parser.add_argument("--signatures", action="store_true", help="print every compiled kernel's signatures")
    parser.add_argument("--modules", action="store_true", help="print the size of each kernel's module (LLVM instructions)")
    parser.add_argument("--dataset", help="profile the first compile of `camloc run DATASET` (its default options) "
                        "instead of the background compile's steps")
    args = parser.parse_args()
    from camloc.kernels import cache_is_warm

    if cache_is_warm():
        print("the kernels' cache is warm: set NUMBA_CACHE_DIR to an empty folder", file=sys.stderr)
        return 2
    records: list = []
    event.register("numba:compile", _Recorder(records))
    event.register("numba:llvm_lock", _Recorder(records, "llvm "))
    cpu = time.process_time()
    run_of(args.dataset) if args.dataset else first_compile()
    cpu = time.process_time() - cpu
    own, whole, count, llvm = own_times(records)
    print(f"first compile, one process: {cpu:.1f} s CPU; {sum(own.values()):.1f} s compiling "
          f"{len(own)} functions, {sum(llvm.values()):.1f} s of it in LLVM (load {os.getloadavg()[0]:.2f})")
    print(f"{'own s':>7} {'LLVM s':>7} {'whole s':>8} {'times':>5}  kernel")
    for name, seconds in own.most_common(args.top):
        print(f"{seconds:7.2f} {llvm[name]:7.2f} {whole[name]:8.2f} {count[name]:5d}  {name}")
    if args.modules:
        sizes = module_sizes()
        print(f"LLVM instructions in the {len(sizes)} kernel modules: {sum(n for n, _ in sizes.values()):,}")
        for name, (n, defined) in sorted(sizes.items(), key=lambda item: -item[1][0])[:args.top]:
            print(f"{n:9,} {defined:5}  {name}")
    for name, signatures in specialized_twice(1 if args.signatures else 2).items():
        print(f"compiled for {len(signatures)} signature(s) (each with all it calls): {name}")
        for signature in signatures:
            print(f"    {str(signature)[:300]}")
    return 0


def module_sizes() -> dict:
    """Each compiled camloc kernel's final module, by name (one entry a signature): its LLVM
    instructions and the functions it defines. The module holds the kernel's code and a copy of
    every compiled function it calls, linked in, which LLVM optimized and generated again for it:
    a measure of a first compile's LLVM work that the machine's load does not move."""
    import importlib
    import pkgutil

    from numba.core.registry import CPUDispatcher

    import camloc.kernels

    sizes = {}
    for info in pkgutil.iter_modules(camloc.kernels.__path__):
        module = importlib.import_module(f"camloc.kernels.{info.name}")
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value.__module__ == module.__name__:
                for k, signature in enumerate(value.signatures):
                    lines = value.inspect_llvm(signature).splitlines()
                    n = sum(1 for line in lines if line.startswith("  ") and not line.lstrip().startswith(";"))
                    defined = sum(1 for line in lines if line.startswith("define "))
                    sizes[f"{module.__name__}.{name}" + (f" #{k + 1}" if k else "")] = (n, defined)
    return sizes


def specialized_twice(at_least: int = 2) -> dict:
    """camloc's kernels compiled for more than one signature in this process, by name: a literal
    flag or count passed at one site (numba types ``True`` or ``0`` as a type of its own), or an
    array of another layout, compiles the kernel and all it calls once more."""
    import importlib
    import pkgutil

    from numba.core.registry import CPUDispatcher

    import camloc.kernels

    found = {}
    for info in pkgutil.iter_modules(camloc.kernels.__path__):
        module = importlib.import_module(f"camloc.kernels.{info.name}")
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value.__module__ == module.__name__ and len(value.signatures) >= at_least:
                found[f"{module.__name__}.{name}"] = value.signatures
    return found


if __name__ == "__main__":
    sys.exit(main())
