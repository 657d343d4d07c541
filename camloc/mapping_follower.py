"""The mapping pass run beside the beam's run that decides its pairs, pose by pose as they settle.

Where the map lacks landmarks, a run is two passes: the localizer's (the beam decides which
observations are the map's, and its filter replays them, ``camloc.loop``) and the mapping pass
(``camloc.slam_run``), which takes those pairs and adds what the map lacks. The mapping pass reads
a pose's pairs only when it reaches that pose, and the filter's replay settles them in pose order,
so the two passes can overlap: a thread steps the mapping localizer through every pose the replay
has filtered, while the beam goes on with the poses after them. The result is the same as one
pass after the other (the same pairs, read in the same order; ``MappingFollower.result`` checks
that the pairs it took are the run's); the wall time is about the longer pass's, not their sum,
on a machine of two CPUs or more (the compiled kernels release the GIL: the beam's and the
replay's run beside the mapping pass's Python).

    with MappingFollower(dataset, config, decide_compiled) as follower:
        run = _localize_exact(..., on_replay=follower.follow)   # the thread starts with the replay
        mapped = follower.result(given, on_progress)             # None: it did not follow (run it after)
"""

from __future__ import annotations

import sys
import threading
import time
from typing import Callable, Optional

import numpy as np

from camloc.dataset import Dataset
from camloc.localizer_config import LocalizerConfig
from camloc.results import RunResult

# How often the mapping thread looks again for poses the replay has filtered, and the main thread
# for the mapping thread's progress, in seconds.
POLL_SECONDS = 0.002
REPORT_SECONDS = 0.1
# Python's thread switch interval while the mapping thread runs (its default is 5 ms). Each
# compiled call releases the GIL and takes it back: at the default, the beam's thread, whose
# Python between its kernels is many short calls (the slip search's), waited up to 5 ms for the
# mapping thread at each, and the two ran about one after the other (the 20,000-pose world with a
# fifth withheld: the beam's part 6-10 s -> 15-16 s, no wall time saved); at 0.2 ms the two
# overlap (docs/performance.md, 2026-12-04, "The mapping pass beside the beam"). Restored after.
SWITCH_INTERVAL_SECONDS = 0.0002


class MappingFollower:
    """``slam_run.localize_mapping`` in a thread of its own, following the localizer's replay
    (``camloc.loop._Filter``: its ``chosen`` landmark row of every observation and ``filtered``,
    how many poses it has filtered), which ``follow`` is given when the compiled run starts."""

    def __init__(self, dataset: Dataset, config: LocalizerConfig, decide_compiled: Callable[[], bool], enabled: bool = True):
        # whether the mapping pass's steps run compiled, decided once it is sure to run (the
        # decision may start their compile in the background: ``localizer._mapping_compiled``)
        self.dataset, self.config, self.decide_compiled = dataset, config, decide_compiled
        self.compiled = False
        # ``loop.run_compiled``'s ``on_replay``: None where the pass cannot run beside the beam's
        # (one CPU, ``parallel=False``, another association), which then never starts it
        self.on_replay = self.follow if enabled else None
        self.source = None
        self.done = 0                    # poses the mapping thread has stepped
        self.cancelled = threading.Event()
        self.thread: Optional[threading.Thread] = None
        self.switch_interval: Optional[float] = None   # Python's, while the thread runs
        self.outcome: Optional[RunResult] = None
        self.error: Optional[BaseException] = None

    @property
    def following(self) -> bool:
        return self.thread is not None

    def follow(self, replay) -> None:
        """Start the mapping thread on ``replay``'s pairs (called as the compiled run begins)."""
        self.source, self.compiled = replay, self.decide_compiled()
        self.switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(min(self.switch_interval, SWITCH_INTERVAL_SECONDS))
        # a daemon: a run stopped by an error or Ctrl-C leaves it waiting for poses that never
        # come; ``cancel`` ends it, and the interpreter does not wait for it at exit either way
        self.thread = threading.Thread(target=self._run, name="camloc-mapping", daemon=True)
        self.thread.start()

    def cancel(self) -> None:
        """Stop the mapping thread (where it still runs) and wait for it."""
        self.cancelled.set()
        if self.thread is not None:
            self.thread.join()
            self._restore_switch_interval()

    def _restore_switch_interval(self) -> None:
        if self.switch_interval is not None:
            sys.setswitchinterval(self.switch_interval)
            self.switch_interval = None

    def __enter__(self) -> "MappingFollower":
        return self

    def __exit__(self, *exc) -> bool:
        self.cancel()  # a run that ended without taking its result, by an error or Ctrl-C, or a map found complete
        return False

    def _run(self) -> None:
        from camloc.slam_run import MappingLocalizer

        try:
            localizer = MappingLocalizer(self.dataset, self.config, self.source.chosen, self.compiled)
            started = time.perf_counter()
            for k in range(self.dataset.num_poses):
                while self.source.filtered <= k:
                    if self.cancelled.is_set():
                        return
                    time.sleep(POLL_SECONDS)
                if self.cancelled.is_set():
                    return
                localizer.step(k)
                self.done = k + 1
            self.outcome = localizer.result(time.perf_counter() - started)
        except BaseException as error:  # raised again in the caller's thread, by ``result``
            self.error = error

    def result(self, given: np.ndarray, on_progress: Optional[Callable[[int, int], None]] = None) -> Optional[RunResult]:
        """The mapping pass's run, once its thread has stepped every pose (reporting its progress
        meanwhile, from the caller's thread); None where it did not follow the run whose pairs
        are ``given`` (the caller runs the pass itself). Its ``filter_seconds`` are the time it
        took after the localizer's run, so that the two add up to the wall time of both."""
        if self.thread is None:
            return None
        waited_from = time.perf_counter()
        n = self.dataset.num_poses
        while self.thread.is_alive():
            if on_progress is not None:
                on_progress(self.done, n)
            self.thread.join(REPORT_SECONDS)
        self._restore_switch_interval()
        if self.error is not None:
            raise self.error
        if self.outcome is None or not np.array_equal(given, self.source.chosen):
            return None
        if on_progress is not None:
            on_progress(n, n)
        self.outcome.summary["timing"]["filter_seconds"] = time.perf_counter() - waited_from
        return self.outcome
