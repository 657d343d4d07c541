"""What numba's reference counts cost, beside an allocation: a micro-benchmark of jitted loops
(docs/performance.md, 2026-12-05, "The beam's allocations and reference counts").

Per call of a jitted step, in ns: 27 ``np.empty(6)``; 22 views carved from one buffer
(``buf[a:b].reshape(...)``); a 30-array named tuple passed through two non-inlined calls, against
two arrays. numba counts a reference to every array a non-inlined function is passed (on entry and
on return, calls into its runtime) and to every view it makes, so handing scratch down costs about
what allocating it does.

    nice python benchmarks/numba_counts.py [--calls 1000000]
"""

from __future__ import annotations

import argparse
import os
import time
from collections import namedtuple

os.environ.setdefault("NUMBA_OPT", "1")   # camloc's kernels' level (``camloc.kernels._jit``)

import numba  # noqa: E402
import numpy as np  # noqa: E402

Work = namedtuple("Work", [f"a{i}" for i in range(30)])
step = numba.njit(no_cpython_wrapper=True, no_cfunc_wrapper=True, error_model="numpy")


@step
def allocate(x):
    total = 0.0
    for _ in range(27):
        a = np.empty(6)
        a[0] = x
        total += a[0]
    return total


@step
def carve(buffer, x, rows):
    total = 0.0
    for k in range(22):
        view = buffer[k * 36:k * 36 + rows * 6].reshape((rows, 6))
        view[0, 0] = x
        total += view[0, 0]
    return total


@step
def leaf_tuple(work, x, p):
    a, b = work.a0[:p], work.a1[:p]
    for k in range(p):
        a[k] += x * b[k]
    if a[0] > 1e300:                       # a raise, as the kernels have: not inlined by LLVM
        raise FloatingPointError("overflow")
    return a[0]


@step
def leaf_two(f, g, x, p):
    a, b = f[:p], g[:p]
    for k in range(p):
        a[k] += x * b[k]
    if a[0] > 1e300:
        raise FloatingPointError("overflow")
    return a[0]


@step
def middle_tuple(work, x, p):
    return leaf_tuple(work, x, p) + leaf_tuple(work, x, p) + leaf_tuple(work, x, p)


@step
def middle_two(f, g, x, p):
    return leaf_two(f, g, x, p) + leaf_two(f, g, x, p) + leaf_two(f, g, x, p)


@numba.njit
def run(mode, calls):
    z = np.zeros(36)
    work = Work(z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(),
                z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(),
                z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy())
    f, g, buffer = np.zeros(1000), np.zeros(1000), np.zeros(1000)
    total = 0.0
    for _ in range(calls):
        if mode == 0:
            total += allocate(1.0)
        elif mode == 1:
            total += carve(buffer, 1.0, 6)
        elif mode == 2:
            total += middle_tuple(work, 1e-9, 6)
        else:
            total += middle_two(f, g, 1e-9, 6)
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=1_000_000, help="calls timed per case (default 1,000,000)")
    args = parser.parse_args()
    names = ("27 np.empty(6)", "22 carved views", "a 30-array tuple, two call levels", "two arrays, two call levels")
    for mode, name in enumerate(names):
        run(mode, 10)
        start = time.perf_counter()
        run(mode, args.calls)
        print(f"{name}: {(time.perf_counter() - start) / args.calls * 1e9:.0f} ns a call")


if __name__ == "__main__":
    main()
