"""The beam and the filter that replays its association, side by side in two processes.

With the beam, a run is two sequential passes: the beam decides every pose's association
(``camloc.beam``), then the filter replays those pairs (``_Localizer.step``: stacked update,
re-check). A pose's pairs are final as soon as every hypothesis in the beam descends from the same
one there, usually within a pose or two, so the replay need not wait for the end: here it runs in a
second process and filters each batch of decided poses while the beam works on the next. The
result is the same as the sequential run's, computed by the same code; the run takes about as long
as the beam alone (a second CPU does the replay).

The second process is a fresh interpreter running this module's ``_replay`` (``python -c``), fed
pickled batches on its stdin and answering on its stdout: not a fork (safe beside BLAS threads, on
every platform) and not ``multiprocessing``'s spawn, which would run the caller's own script again
in the child. It builds its own ``_Localizer`` from the dataset and config, so it holds the same
models, map index and initial state, and returns the replay's state at the end; an error in it is
raised in the caller. If the process cannot start or dies (no Python at ``sys.executable``, killed),
the replay runs in the calling process after the beam, with a warning.
"""

from __future__ import annotations

import pickle
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from camloc.errors import CamlocError

# What ``_Localizer.step`` changes, copied back from the replay process.
REPLAYED_ATTRIBUTES = (
    "x", "P", "T_odometry", "states", "covs", "poses", "odometry_poses", "chosen_landmark",
    "mahalanobis", "update_pose_ids", "nis", "map_costs", "nis_dof", "warned_singularity", "pair_spread",
)


def search_and_replay(localizer, on_pose: Optional[Callable[[int], None]] = None) -> None:
    """Run the beam on ``localizer`` (a ``camloc.localizer._Localizer``) here and its replay in a
    second process; on return the localizer holds both results, as after ``search_beam`` and
    ``step`` for every pose."""
    with tempfile.TemporaryFile() as errors:
        worker = subprocess.Popen(
            worker_command("from camloc.localizer import _Localizer\nfrom camloc.replay import _replay\n"
                           "_replay(sys.stdin.buffer, sys.stdout.buffer, _Localizer)"),
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=errors,
        )
        replay_gone = False

        def send(message) -> None:
            nonlocal replay_gone
            if replay_gone:
                return
            try:
                pickle.dump(message, worker.stdin, protocol=pickle.HIGHEST_PROTOCOL)
                worker.stdin.flush()
            except (BrokenPipeError, ConnectionResetError, OSError):  # it failed: its report is read below
                replay_gone = True

        try:
            send((localizer.dataset, localizer.config, localizer.null_cost_offset))
            localizer.search_beam(on_pose, on_decided=lambda first, chosen, slipped: send((first, chosen, slipped)))
            send(None)  # no more poses
            try:
                worker.stdin.close()
            except OSError:
                pass
            try:
                status, payload = pickle.load(worker.stdout)
            except (EOFError, pickle.UnpicklingError):  # it could not start or was killed
                worker.wait(timeout=10.0)
                errors.seek(0)
                detail = errors.read().decode(errors="replace").strip().splitlines()[-1:] or ["no message"]
                status, payload = "lost", detail[0]
        finally:
            if worker.poll() is None:
                try:
                    worker.wait(timeout=10.0)
                except subprocess.TimeoutExpired:
                    worker.kill()
                    worker.wait()
            worker.stdout.close()
    if status == "error":
        raise payload
    if status == "lost":
        # the beam's decisions are all here: replay them in this process, as a one-process run does
        for k in range(localizer.dataset.num_poses):
            localizer.step(k)
        localizer.warnings.append(f"the replay process ended without a result ({payload}); the filter ran in this process instead")
        return
    for name in REPLAYED_ATTRIBUTES:
        setattr(localizer, name, payload[name])
    localizer.replayed_in_parallel = True
    localizer.replay_peak_mb = payload["peak_mb"]
    localizer.warnings.extend(payload["warnings"])  # after the beam's own, as in the sequential run


# A worker imports this very camloc package, from its folder, however the caller found it (an
# install, an editable install, a path added by hand), without putting that folder's parent in
# front of the standard library on sys.path.
_WORKER_HEADER = """
import importlib.util, sys
spec = importlib.util.spec_from_file_location("camloc", {package!r} + "/__init__.py", submodule_search_locations=[{package!r}])
module = importlib.util.module_from_spec(spec)
sys.modules["camloc"] = module
spec.loader.exec_module(module)
"""


def worker_command(code: str) -> list[str]:
    """The command of a fresh interpreter that imports this camloc package, then runs ``code``
    (``sys`` imported): the replay's process here, the mapping pass's (``camloc.mapping_follower``)."""
    return [sys.executable, "-c", _WORKER_HEADER.format(package=str(Path(__file__).resolve().parent)) + code + "\n"]


def _replay(incoming, outgoing, make_localizer) -> None:
    """The second process: filter each batch of decided poses as it arrives, with the localizer
    ``make_localizer(dataset, config, null_cost_offset)`` builds (``camloc.localizer._Localizer``, named by the
    worker's script: this module imports nothing of the localizer that imports it); send back the
    state."""
    try:
        dataset, config, null_cost_offset = pickle.load(incoming)
        localizer = make_localizer(dataset, config, null_cost_offset)
        n = dataset.num_poses
        localizer.beam_pairs = [np.zeros((0, 2), np.int64)] * n
        localizer.beam_slipped = np.zeros(n, dtype=bool)
        while (message := pickle.load(incoming)) is not None:
            first, chosen, slipped = message
            for offset, pairs in enumerate(chosen):
                k = first + offset
                localizer.beam_pairs[k] = pairs
                localizer.beam_slipped[k] = slipped[offset]
                localizer.step(k)
        payload = {name: getattr(localizer, name) for name in REPLAYED_ATTRIBUTES}
        payload["warnings"] = localizer.warnings
        payload["peak_mb"] = peak_memory_mb()
        answer = ("ok", payload)
    except BaseException as error:  # reported to the caller, which raises it
        answer = error_answer(error, "the filter's replay")
    pickle.dump(answer, outgoing, protocol=pickle.HIGHEST_PROTOCOL)
    outgoing.flush()


def error_answer(error: BaseException, what: str) -> tuple:
    """A worker's answer reporting ``error``: the error itself where it pickles (the caller raises
    it as it would its own), else a CamlocError saying that ``what`` failed and how."""
    try:
        pickle.dumps(error)
    except Exception:
        return ("error", CamlocError(f"{what} failed: {type(error).__name__}: {error}"))
    return ("error", error)


def peak_memory_mb() -> Optional[float]:
    """This process's peak resident memory since its exec, MB: ``VmHWM`` of /proc/self/status,
    which belongs to the current address space only (``ru_maxrss`` would include the parent's peak
    carried across exec); None where /proc is absent. The replay reports its own, since the two
    processes' peaks add up."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None
