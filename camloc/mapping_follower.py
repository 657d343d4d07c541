"""The mapping pass run beside the beam's run that decides its pairs, in a second process.

Where the map lacks landmarks, a run is two passes: the localizer's (the beam decides which
observations are the map's, and its filter replays them, ``camloc.loop``) and the mapping pass
(``camloc.slam_run``), which takes those pairs and adds what the map lacks. The mapping pass reads
a pose's pairs only when it reaches that pose, and the filter's replay settles them in pose order,
so the two passes can overlap: a second process steps the mapping localizer through the poses the
replay has filtered, fed their pairs as they settle, while the beam goes on with the poses after
them. The result is the same as one pass after the other (the same code on the same pairs, in the
same order; ``MappingFollower.result`` checks that the pairs it sent are the run's), and the wall
time is about the longer pass's, not their sum, on a machine of two CPUs or more.

Why a process and not a thread: the mapping pass is mostly Python, and so are the beam's steps
between its kernels (the slip search). In a thread the two took turns on the GIL and the run took
as long as before (the 20,000-pose world with a fifth withheld: 19.0 s either way, the beam's part
6 -> 11 s; docs/performance.md, 2026-12-04, "The mapping pass beside the beam"). The process is a
fresh interpreter (``replay.worker_command``, as the numpy beam's replay: not a fork beside the
compiled loop's threads), fed pickled messages on its stdin, answering on its stdout; an error in
it is raised in the caller; a process that cannot start or dies leaves the pass to the caller,
which runs it after the beam's run with a warning (``failure``).

    with MappingFollower(dataset, config, decide_compiled) as follower:
        run = _localize_exact(..., on_replay=follower.on_replay)   # the process starts with the replay
        mapped = follower.result(given, on_progress)                # None: run the pass after
"""

from __future__ import annotations

import pickle
import subprocess
import tempfile
import threading
import time
from typing import Callable, Optional

import numpy as np

from camloc.dataset import Dataset, observations_by_pose
from camloc.localizer_config import LocalizerConfig
from camloc.results import RunResult

# How often the feeding thread looks again for poses the replay has filtered, in seconds.
POLL_SECONDS = 0.005
# The mapping process reports its progress about this many times a run (few enough that its
# reports fit the pipe while nobody reads them, until the beam's run ends).
PROGRESS_REPORTS = 100


class MappingFollower:
    """``slam_run.localize_mapping`` in a second process, following the localizer's replay
    (``camloc.loop._Filter``: its ``chosen`` landmark row of every observation and ``filtered``,
    how many poses it has filtered), which ``follow`` is given when the compiled run starts."""

    def __init__(self, dataset: Dataset, config: LocalizerConfig, decide_compiled: Callable[[], bool], enabled: bool = True):
        # whether the mapping pass's steps run compiled, decided once it is sure to run (the
        # decision may start their compile in the background: ``localizer._mapping_compiled``)
        self.dataset, self.config, self.decide_compiled = dataset, config, decide_compiled
        # ``loop.run_compiled``'s ``on_replay``: None where the pass cannot run beside the beam's
        # (one CPU, ``parallel=False``, another association), which then never starts it
        self.on_replay = self.follow if enabled else None
        self.source = None
        self.worker: Optional[subprocess.Popen] = None
        self.feeder: Optional[threading.Thread] = None
        self.errors = None            # the process's stderr, for a failure's last line
        self.cancelled = threading.Event()
        self.sent = 0                 # poses whose pairs the process has been sent
        self.failure: Optional[str] = None   # why the process gave no result, where it did not
        self.answered = False         # the process sent its run (or its error): it is ending
        self.taken = False            # its run is the caller's

    def follow(self, replay) -> None:
        """Start the mapping process on ``replay``'s pairs (called as the compiled run begins)."""
        from camloc.replay import worker_command

        self.source = replay
        compiled = self.decide_compiled()
        self.errors = tempfile.TemporaryFile()
        try:
            self.worker = subprocess.Popen(worker_command("from camloc.mapping_follower import serve\nserve(sys.stdin.buffer, sys.stdout.buffer)"),
                                           stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self.errors)
        except OSError as error:  # no interpreter to start: the caller runs the pass after
            self.failure = f"it could not start ({error})"
            return
        self.feeder = threading.Thread(target=self._feed, args=(compiled,), name="camloc-mapping-feed", daemon=True)
        self.feeder.start()

    def _feed(self, compiled: bool) -> None:
        """Send the process the run, then each stretch of poses' pairs once the replay has filtered it."""
        dataset = self.dataset
        order, bounds = observations_by_pose(dataset)
        try:
            _send(self.worker.stdin, (dataset, self.config, compiled))
            n = dataset.num_poses
            while self.sent < n and not self.cancelled.is_set():
                filtered = self.source.filtered
                if filtered <= self.sent:
                    time.sleep(POLL_SECONDS)
                    continue
                obs = order[bounds[self.sent]:bounds[filtered]]
                _send(self.worker.stdin, (filtered, obs, self.source.chosen[obs]))
                self.sent = filtered
            if not self.cancelled.is_set():
                _send(self.worker.stdin, None)  # no more poses
                self.worker.stdin.close()
        except (BrokenPipeError, ConnectionResetError, OSError, ValueError):  # it failed: ``result`` reads why
            pass

    def cancel(self) -> None:
        """Stop the mapping process and its feeding thread (where they still run)."""
        self.cancelled.set()
        if self.worker is not None and self.worker.poll() is None:
            try:
                self.worker.wait(timeout=5.0 if self.answered else 0.0)
            except subprocess.TimeoutExpired:
                self.worker.kill()
                self.worker.wait()
        if self.feeder is not None:
            self.feeder.join()
        if self.worker is not None:
            for stream in (self.worker.stdin, self.worker.stdout):
                try:
                    stream.close()
                except (OSError, ValueError):
                    pass
        if self.errors is not None:
            self.errors.close()
            self.errors = None

    def __enter__(self) -> "MappingFollower":
        return self

    def __exit__(self, *exc) -> bool:
        self.cancel()  # a run that ended without taking its result, by an error or Ctrl-C, or a map found complete
        return False

    def result(self, given: np.ndarray, on_progress: Optional[Callable[[int, int], None]] = None) -> Optional[RunResult]:
        """The mapping pass's run, reporting its progress meanwhile; None where it did not follow
        the run whose pairs are ``given`` (the caller runs the pass itself; ``failure`` says why
        where the process failed). Its ``filter_seconds`` are the time it took after the
        localizer's run, so that the two add up to the wall time of both."""
        if self.worker is None:
            return None
        waited_from = time.perf_counter()
        n = self.dataset.num_poses
        status, payload = "lost", None
        try:
            while True:
                status, payload = pickle.load(self.worker.stdout)
                if status != "progress":
                    break
                if on_progress is not None:
                    on_progress(payload, n)
        except (EOFError, pickle.UnpicklingError, OSError, ValueError):  # it died, or was killed
            status = "lost"
        self.answered = status != "lost"
        self.feeder.join()
        if status == "error":
            raise payload
        if status == "lost":
            self.worker.wait()
            self.errors.seek(0)
            last = self.errors.read().decode(errors="replace").strip().splitlines()[-1:] or [f"exit status {self.worker.returncode}"]
            self.failure = f"it ended without a result ({last[0]})"
            return None
        if not np.array_equal(given, self.source.chosen):  # not the run it followed: the caller's pairs decide
            return None
        payload.summary["timing"]["filter_seconds"] = time.perf_counter() - waited_from
        self.taken = True
        return payload


def serve(incoming, outgoing) -> None:
    """The mapping process: build the mapping localizer from the first message (dataset, config,
    compiled), step it through each stretch of poses as its pairs arrive ((last pose + 1, the
    stretch's observations, their landmark rows)), report progress, send back the run."""
    try:
        from camloc.slam_run import MappingLocalizer

        dataset, config, compiled = pickle.load(incoming)
        given = np.full(dataset.num_observations, -1, np.int64)
        localizer = MappingLocalizer(dataset, config, given, compiled)
        started = time.perf_counter()
        stride = max(1, dataset.num_poses // PROGRESS_REPORTS)
        k = 0
        while (message := pickle.load(incoming)) is not None:
            last, obs, rows = message
            given[obs] = rows
            for k in range(k, last):
                localizer.step(k)
                if (k + 1) % stride == 0:
                    _send(outgoing, ("progress", k + 1))
            k = last
        answer = ("ok", localizer.result(time.perf_counter() - started))
    except BaseException as error:  # reported to the caller, which raises it
        from camloc.replay import error_answer

        answer = error_answer(error, "the mapping pass")
    _send(outgoing, answer)


def _send(stream, message) -> None:
    pickle.dump(message, stream, protocol=pickle.HIGHEST_PROTOCOL)
    stream.flush()
