"""Which compiled function allocates the kernels' arrays: a share of the allocations by caller.

numba's runtime counts the arrays it allocates (``NUMBA_NRT_STATS=1``, ``kernel_profile.py``) but
not where. This puts a uprobe on its allocators (``NRT_MemInfo_alloc_aligned`` and
``NRT_MemInfo_alloc_safe_aligned`` of ``_nrt_python``), records ``--window`` seconds of a warm call
of ``camloc.localize`` (starting ``--after`` seconds into it) with one frame of DWARF unwinding (the
allocator's own, whose return address is the caller's), and names each caller through
``kernel_profile.py``'s perf map of the kernels' machine code. A step LLVM or numba inlined counts as
its caller's; callers outside the named kernels are ``[unknown]``. Every allocation is recorded
(an event each, not a sample), so keep the window short: the shares are of the poses it covers,
and the kernels run some 10x slower under the probe. perf may drop events; the shares are what it
kept. Scale them by the count per pose from ``kernel_profile.py`` (``NUMBA_NRT_STATS``).

    python benchmarks/alloc_sites.py WORLD.g2o [--after 3] [--window 0.3] [--top 30]

Needs root (``perf probe`` adds the uprobes, removed at the end) and ``perf`` built with DWARF
unwinding. Linux only.
"""

from __future__ import annotations

import argparse
import collections
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numba.core.runtime as nrt_package

sys.path.insert(0, str(Path(__file__).resolve().parent))
from kernel_profile import write_perf_map  # noqa: E402  (the benchmarks folder is not a package)

import camloc  # noqa: E402

ALLOCATORS = ("NRT_MemInfo_alloc_aligned", "NRT_MemInfo_alloc_safe_aligned")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("world", help="a g2o file")
    parser.add_argument("--after", type=float, default=3.0, help="seconds into the warm call before recording (default 3)")
    parser.add_argument("--window", type=float, default=0.3, help="seconds recorded (default 0.3)")
    parser.add_argument("--top", type=int, default=30, help="callers listed (default 30)")
    args = parser.parse_args()
    library = next(Path(nrt_package.__file__).parent.glob("_nrt_python*.so"))
    events = add_probes(library)
    try:
        world, config = camloc.load(args.world), camloc.LocalizerConfig()
        camloc.localize(world, config, engine="compiled")
        perf_map = Path(f"/tmp/perf-{os.getpid()}.map")
        write_perf_map(perf_map)
        try:
            text = record(events, args.after, args.window, lambda: camloc.localize(world, config, engine="compiled"))
        finally:
            perf_map.unlink(missing_ok=True)
    finally:
        subprocess.run(["perf", "probe", "-q", "-d", f"{events[0].split(':')[0]}:*"], check=False)
    counts = callers(text)
    total = sum(counts.values())
    print(f"{total} allocations recorded in a {args.window} s window; share by the compiled function that made them")
    for name, n in counts.most_common(args.top):
        print(f"{100 * n / total:6.2f}%  {name}")


def add_probes(library: Path) -> list[str]:
    """perf's event names of uprobes on numba's two array allocators in ``library``."""
    for name in ALLOCATORS:
        subprocess.run(["perf", "probe", "-q", "-x", str(library), name], check=False, capture_output=True)   # or there already
    group = "probe_" + library.name.split(".")[0]
    return [f"{group}:{name}" for name in ALLOCATORS]


def record(events: list[str], after: float, window: float, call) -> str:
    """``perf script``'s text of ``window`` seconds of ``events`` in this process, ``after``
    seconds into ``call()``."""
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "perf.data"
        command = ["perf", "record", "-q", "-m", "16M", "--call-graph", "dwarf,256", "-p", str(os.getpid()), "-o", str(data)]
        for event in events:
            command += ["-e", event]

        def recorder():
            time.sleep(after)
            subprocess.run(command + ["--", "sleep", str(window)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

        thread = threading.Thread(target=recorder)
        thread.start()
        call()
        thread.join()
        return subprocess.run(["perf", "script", "-i", str(data), "-F", "ip,sym"], capture_output=True, text=True).stdout


def callers(text: str) -> collections.Counter:
    """{caller's name: allocations} of ``perf script``'s events (the second frame of each)."""
    counts = collections.Counter()
    for block in text.split("\n\n"):
        frames = [line.split(None, 1) for line in block.strip().splitlines() if line.strip()]
        if frames:
            counts[frames[1][1] if len(frames) > 1 and len(frames[1]) > 1 else "[unknown]"] += 1
    return counts


if __name__ == "__main__":
    main()
