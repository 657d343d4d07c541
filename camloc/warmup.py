"""The first compile of camloc's kernels, in a detached background process.

After an install numba compiles the kernels once and caches them: a minute or two on a 2-core
machine (``docs/performance.md``). A run that numpy takes at most ``NUMPY_FIRST_RUN_SECONDS`` over takes
less than that in the numpy engine, which gives the same result, so ``camloc run`` does not make its
user wait: with a cold cache it localizes in numpy and starts this module's compile, at the lowest
priority, for the runs after it (``localize(on_background_compile=...)``).

One compile at a time: the process holds a lock file in the kernels' cache folder, with its pid,
and the cache counts as cold while it is there (``localize`` asks ``compiling``); the lock of a
process that has gone (killed, or lost to a reboot) is taken over. A compile that failed leaves
its error in the lock: until the lock is stale, runs compile in the foreground (where the error, if
it recurs, is reported) rather than start it again.

A compile uses both cores: the filter's kernels compile in a second process (``python -m
camloc.warmup --filter``, ``start_filter_compile``), then the few of the beam's that the first
reaches last, while the beam's compile in the first, which waits for that process before its first
call of the filter and loads from the cache what the second has compiled (89-109 s -> 56-69 s on this
project's 2-core machine). numba writes its cache files by
renaming, so the two processes can cache kernels they share; each loads what the other has
cached by the time it needs it.

    python -m camloc.warmup LOCK       # what the background process runs (LOCK is removed at the end)
    python -m camloc.warmup --filter   # the second process's share of a first compile
"""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

# A cold run localizes in numpy and compiles in the background where numpy takes at most about
# this long (``numpy_seconds``); longer, it compiles first. The compile takes 35-90 s on this
# project's 2-core machine, so a first run stays under half a minute either way where it can.
NUMPY_FIRST_RUN_SECONDS = 20.0
# What the numpy beam and filter take per observation, in seconds of this project's usual 2-core
# machine (on one three times slower a core, three times as long; so is the compile this is weighed
# against), measured on 3,000-pose worlds of two cameras and 10% clutter (8 observations a pose,
# 2026-12-03, idle): 13.2 s for 24,081 observations with depth; 267 s for 24,131 pixel-only ones,
# whose rays each gate many landmarks. A world of frequent slip searches takes up to 10x as long.
# Then scaled by the CPU the numpy engine's 2026-12-05 speedups saved on such worlds (on the slower
# machine, docs/performance.md): x 0.94 with depth (alternated runs), x 0.88 pixel-only (one run each);
# then by what batching a pose's cameras saved (2026-12-05, ninth session; alternated, two runs each):
# x 0.91 with depth (the 3,000-pose world), x 0.96 pixel-only (a 1,000-pose one).
NUMPY_SECONDS_PER_OBSERVATION = 0.47e-3
NUMPY_SECONDS_PER_PIXEL_OBSERVATION = 9.3e-3

# Set to 0 to compile in the foreground, as a run did before (the tests do; so may a container's build).
ENVIRONMENT_SWITCH = "CAMLOC_BACKGROUND_COMPILE"

LOCK_NAME = "camloc-compiling.lock"

# A lock older than this belongs to a compile that died, or failed long enough ago to try again.
STALE_SECONDS = 1800.0

STARTED, RUNNING, FAILED = "started", "running", "failed"

# The argument of ``python -m camloc.warmup`` that compiles a second process's share of a first
# compile: the filter's kernels, then the beam's that the first process reaches last.
FILTER_ONLY = "--filter"

# The argument of ``python -m camloc.warmup MAPPING_ONLY LOCK``: the mapping pass's kernels
# (``camloc.slam_compiled``), with their own lock in their own cache folder.
MAPPING_ONLY = "--mapping"

# That share takes 35-55 s on this project's 2-core machine; a process that has not ended after
# this long is stopped, and the run compiles what it still needs itself.
FILTER_COMPILE_TIMEOUT = 600.0


def numpy_seconds(num_observations: int, num_pixel_observations: int) -> float:
    """About how long the numpy engine takes over a dataset of these observations (the seconds
    of ``NUMPY_SECONDS_PER_OBSERVATION`` and ``NUMPY_SECONDS_PER_PIXEL_OBSERVATION``)."""
    ranged = num_observations - num_pixel_observations
    return ranged * NUMPY_SECONDS_PER_OBSERVATION + num_pixel_observations * NUMPY_SECONDS_PER_PIXEL_OBSERVATION


def cache_folder() -> Optional[Path]:
    """Where numba caches the kernels; None where it cannot cache them."""
    from camloc.kernels._jit import CACHE_FOLDER

    return CACHE_FOLDER


def lock_state(folder: Optional[Path] = None) -> Optional[str]:
    """``RUNNING`` while a background compile holds the lock in ``folder`` (the kernels' cache
    folder), ``FAILED`` where its lock says it failed, None without a lock younger than
    ``STALE_SECONDS`` or where the process the lock names has gone."""
    folder = folder if folder is not None else cache_folder()
    if folder is None:
        return None
    lock = folder / LOCK_NAME
    try:
        if time.time() - lock.stat().st_mtime >= STALE_SECONDS:
            return None
        text = lock.read_text()
    except (OSError, UnicodeDecodeError):
        return None
    if text.startswith(FAILED):
        return FAILED
    pid = re.search(r"\bpid (\d+)", text)
    return None if pid and not _alive(int(pid.group(1))) else RUNNING


def _alive(pid: int) -> bool:
    """Whether process ``pid`` exists (a compile killed, or lost to a reboot, leaves its lock);
    True where that cannot be told."""
    if os.name != "posix":
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process: it exists
        return True
    return True


def compiling(folder: Optional[Path] = None) -> bool:
    """Whether a background compile is running now."""
    return lock_state(folder) == RUNNING


def start_background_compile(folder: Optional[Path] = None, mapping: bool = False) -> Optional[str]:
    """Start compiling the kernels in a detached, lowest-priority process, unless one is running
    (``mapping``: the mapping pass's, ``compile_mapping_kernels``, locked in their ``folder``).

    Returns
    -------
    ``STARTED``, ``RUNNING`` (another run started it), or None where it cannot run: switched off
    (``CAMLOC_BACKGROUND_COMPILE=0``), no cache folder (numba would not keep what it compiled), a
    recent background compile failed, the lock cannot be written or the process not started. None
    means: compile in the foreground.
    """
    if switched_off():
        return None
    folder = folder if folder is not None else cache_folder()
    if folder is None:
        return None
    state = lock_state(folder)
    if state is not None:
        return RUNNING if state == RUNNING else None
    lock = folder / LOCK_NAME
    try:
        folder.mkdir(parents=True, exist_ok=True)
        lock.unlink(missing_ok=True)  # stale
        descriptor = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:  # another run took it between the check and here
        return RUNNING
    except OSError:
        return None
    with os.fdopen(descriptor, "w") as handle:
        handle.write(f"compiling since {time.strftime('%Y-%m-%d %H:%M:%S')}\n")
    try:
        _spawn([sys.executable, "-m", "camloc.warmup"] + ([MAPPING_ONLY] if mapping else []) + [str(lock)], _environment())
    except OSError:
        lock.unlink(missing_ok=True)
        return None
    return STARTED


def switched_off() -> bool:
    """Whether ``CAMLOC_BACKGROUND_COMPILE=0`` keeps every compile to the run's own process."""
    return os.environ.get(ENVIRONMENT_SWITCH, "1").strip() == "0"


def start_filter_compile() -> Optional[subprocess.Popen]:
    """Start compiling the filter's kernels (``filter_poses`` and what it calls) in a second
    process, for a compile of the beam's kernels going on in this one; None where it cannot run
    (switched off with ``CAMLOC_BACKGROUND_COMPILE=0``, no cache folder, no process). The caller
    waits for it (``wait_for``) before it first calls the filter."""
    return _start_share(FILTER_ONLY)


def start_mapping_compile() -> Optional[subprocess.Popen]:
    """``start_filter_compile`` for the mapping pass's kernels (``compile_mapping_kernels``, no
    lock): the tests' setup compiles them beside the kernels' compile."""
    return _start_share(MAPPING_ONLY)


def _start_share(share: str) -> Optional[subprocess.Popen]:
    """``python -m camloc.warmup SHARE`` as this process's child; None where it cannot run."""
    if switched_off() or cache_folder() is None:
        return None
    try:
        return _start([sys.executable, "-m", "camloc.warmup", share], _environment())
    except OSError:
        return None


def wait_for(process: Optional[subprocess.Popen]) -> None:
    """Wait for a process of ``start_filter_compile`` (or ``start_mapping_compile``); one that has not ended after
    ``FILTER_COMPILE_TIMEOUT`` seconds is stopped. Either way the caller then calls the filter,
    which loads its kernels from the cache, or compiles what is not there."""
    if process is None:
        return
    try:
        process.wait(timeout=FILTER_COMPILE_TIMEOUT)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def _start(command: list[str], environment: dict[str, str], **options) -> subprocess.Popen:
    """Run ``command`` as this process's child, without its terminal streams (``options``: more
    of ``subprocess.Popen``'s)."""
    return subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            close_fds=True, env=environment, **options)


def _environment() -> dict[str, str]:
    """This process's environment, with the folder this camloc was imported from first on the
    path: the process must compile these kernels, whatever ``sys.path`` a notebook set up."""
    here = str(Path(__file__).resolve().parents[1])
    paths = [here] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p and p != here]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}


def _spawn(command: list[str], environment: dict[str, str]) -> None:
    """Run ``command`` detached from this process: its own session, no terminal, outliving it."""
    detached = {"start_new_session": True} if os.name == "posix" else {
        "creationflags": subprocess.DETACHED_PROCESS | subprocess.CREATE_NEW_PROCESS_GROUP}
    _start(command, environment, **detached)


def compile_kernels() -> list[int]:
    """Compile, and so cache, every kernel a compiled run calls: run the compiled loop over a
    bundled clutter world whose odometry slips on one edge (the slip search's kernels run only
    where a pose needs them), with the beam (the filter in a second thread, and after it) and with
    the oracle. Returns the pose ids the beam explained as slips (the search ran there)."""
    import numpy as np

    from camloc.bundled import bundled_dataset
    from camloc.g2o import read_g2o
    from camloc.localizer_config import LocalizerConfig

    dataset = read_g2o(bundled_dataset("smooth3d-clutter"))
    slipped = dataset.odom_translation.copy()
    slipped[60] += np.array([0.6, -0.5, 0.0])
    dataset = dataclasses.replace(dataset, odom_translation=slipped)
    for concurrent in (True, False):
        slip_poses = _run_compiled(dataset, LocalizerConfig(association="beam"), concurrent=concurrent)
    _run_compiled(dataset, LocalizerConfig(association="oracle"))
    from camloc.kernels._jit import compile_deferred

    compile_deferred()          # what this process's callers call only where a run reaches it
    return [int(i) for i in dataset.pose_ids[slip_poses]]


def compile_mapping_kernels() -> None:
    """Compile, and so cache, the mapping pass's kernels (``camloc.slam_compiled``): a small world
    with half its map withheld, mapped under a prior (every step runs: landmarks enter, are added
    and retire), then under the exact map with its pairs given, as the beam gives them
    (``slam_compiled.fixed_spread_into``)."""
    from camloc.localizer_config import LocalizerConfig
    from camloc.observation_space import landmark_rows
    from camloc.simulate import SimulationConfig, simulate
    from camloc.slam_run import localize_mapping

    dataset = simulate(SimulationConfig(poses=80, withhold_map=0.5), seed=0)
    localize_mapping(dataset, LocalizerConfig(map="prior", filter="euler"), compiled=True)
    given = landmark_rows(dataset.landmark_ids, dataset.obs_true_landmark)
    localize_mapping(dataset, LocalizerConfig(map="exact", filter="euler"), given_pairs=given, compiled=True)


def compile_filter_kernels() -> None:
    """The second process's share of a first compile, cached for the first process to load: the
    filter's kernels (a bundled world localized with the oracle association, which runs only the
    filter), then the beam's kernels that the first process, compiling the beam, reaches last
    (``late_beam_kernels``), then those a run compiles only where it reaches them
    (``deferred_kernels``: about 2.5 s, which the first process, still compiling the beam, does
    not wait for)."""
    from camloc.bundled import bundled_dataset
    from camloc.g2o import read_g2o
    from camloc.localizer_config import LocalizerConfig

    dataset = read_g2o(bundled_dataset("smooth3d-clutter"))
    _run_compiled(dataset, LocalizerConfig(association="oracle"))
    late_beam_kernels(dataset, LocalizerConfig())
    deferred_kernels(dataset, LocalizerConfig())


def _run_compiled(dataset, config, *, concurrent: bool = False):
    """The compiled loop over ``dataset`` (``camloc.loop.run_compiled``) from its start pose, as
    ``localize(engine="compiled")`` runs it, so that it compiles the same kernels: where they are not
    yet cached, a concurrent run of the beam has the filter's compiled in a second process
    (``start_filter_compile``). Returns the indices of the poses explained as slips."""
    from camloc.filters import make_filter
    from camloc.kernels import cache_is_warm
    from camloc.loop import run_compiled

    filter_compile = start_filter_compile() if concurrent and config.association == "beam" and not cache_is_warm() else None
    outputs = run_compiled(dataset, config, initial_x=make_filter("euler").initial(dataset.T_world_start),
                           initial_P=config.initial_cov(), concurrent=concurrent,
                           filter_ready=(lambda: wait_for(filter_compile)) if filter_compile else None)
    return outputs.slipped


def late_beam_kernels(dataset, config) -> list:
    """Compile the beam's kernels that a first compile of the beam reaches last, each called once
    on small arguments of the types a run passes: ``prune`` (called after ``explain_all``, whose
    tree takes most of the compile) and the slip search's ``same_state``, ``widened_view``, ``shift_agreement``,
    ``seeded_explanation_costs`` and ``seeded_explanations`` (called from Python once ``run_poses`` has compiled;
    the last with no seed, its loop not run). About
    10 s of a first compile (``docs/performance.md``). Returns the kernels."""
    import numpy as np

    from camloc.kernels import beam as kb
    from camloc.kernels import seeds as ranking
    from camloc.kernels.view import widened_view
    from camloc.scene import build_scene, build_settings

    scene = build_scene(dataset, config)
    settings = build_settings(config)
    one = kb.new_generation(1, 1, 6)
    one[1][0] = np.eye(6)
    P = one[1][0]
    kb.prune(scene, settings, one, 1, settings.beam_width, settings.beam_delta)
    # the slip search's test of a candidate against the kept (``seeds``), which the bundled world's
    # slip does not reach: a run after a background compile compiled it (as main 79d17ad did)
    kb.same_state(one[0], one[1], 0, 0, settings.merge_sigma)
    widened_view(P, scene.view_limits[2])
    ranking.shift_agreement(np.zeros((2, 3)), 1.0)
    ranking.seeded_explanation_costs(np.zeros((1, 3)), np.zeros((1, 3, 6)), np.eye(3)[None].copy(), P, np.zeros(1, np.int64),
                                     np.zeros(1, np.int64), np.ones(1), np.zeros(1, np.int64), np.ones(1))
    none = np.zeros(0, np.int64)
    ranking.seeded_explanations(scene, settings, one, np.zeros(1, np.int64), none, none, none, np.zeros(0), np.zeros((0, 3)),
                                np.zeros((0, 3, 6)))
    return [kb.prune, kb.same_state, widened_view, ranking.shift_agreement, ranking.seeded_explanation_costs, ranking.seeded_explanations]


def deferred_kernels(dataset, config) -> list:
    """Compile the kernels that their callers call by address only where a run reaches them
    (``_jit.called(kernel, deferred=True)``: ``camloc.kernels.compile_deferred_kernels``), so that
    a run after a first compile compiles nothing wherever it goes. Returns the kernels."""
    from camloc.kernels import compile_deferred_kernels
    from camloc.scene import build_scene, build_settings

    return compile_deferred_kernels(build_scene(dataset, config), build_settings(config))


def lowest_priority() -> None:
    """Lower this process to the lowest priority, against the run that started it too. A nice
    value weighs only within the process's scheduling group, and Linux's autogroups make one group
    of each session: this process has a session of its own (``_spawn``), so its nice 19 alone left
    it an equal share of the CPUs with the run's group (on 2 cores the first run of the issue's
    3,000-pose world took 56 s beside it against 32-35 s alone). So the group's nice is set too
    (``/proc/self/autogroup``), where the system has one; elsewhere the nice value is all there is.
    Only as its session's leader: the group is the whole session's, a terminal's where ``main`` is
    called in another process (a test's)."""
    try:
        os.nice(19)
    except (AttributeError, OSError):  # not on this system: the compile still runs
        pass
    if not hasattr(os, "getsid") or os.getsid(0) != os.getpid():
        return
    try:
        with open("/proc/self/autogroup", "w") as group:
            group.write("19")
    except OSError:  # no autogroups (or not allowed): the nice value above is all
        pass


def main(argv: list[str]) -> int:
    """The background process: compile at the lowest priority, then remove the lock ``argv[1]``;
    on failure, leave the error in it (no new start until it is stale). With ``--filter``, the
    second process's share of a compile going on in the process that started this one
    (``compile_filter_kernels``), without a lock; likewise ``--mapping`` alone (``compile_mapping_kernels``)."""
    if argv[1:] == [FILTER_ONLY]:
        compile_filter_kernels()
        return 0
    if argv[1:] == [MAPPING_ONLY]:          # a share of a compile its caller waits for: no lock
        compile_mapping_kernels()
        return 0
    mapping = argv[1] == MAPPING_ONLY
    lock = Path(argv[-1])
    lowest_priority()
    try:
        lock.write_text(f"compiling since {time.strftime('%Y-%m-%d %H:%M:%S')} pid {os.getpid()}\n")
    except OSError:
        pass
    try:
        compile_mapping_kernels() if mapping else compile_kernels()
    except Exception as error:  # whatever it was, the foreground compile of a later run will say it
        try:
            lock.write_text(f"{FAILED} at {time.strftime('%Y-%m-%d %H:%M:%S')}: {type(error).__name__}: {error}\n")
        except OSError:
            pass
        return 1
    lock.unlink(missing_ok=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
