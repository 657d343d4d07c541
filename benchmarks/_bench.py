"""Shared pieces of the benchmark scripts: the dataset cache, one child process per measured run,
the real dataset, and the ambiguity of a map.

Not a benchmark itself. ``scale.py`` and ``association.py`` import it; it also runs as the child
process that measures one case:

    python benchmarks/_bench.py --worker '{"path": "...", "config": {"association": "beam"}}'

which reads the dataset, localizes it, evaluates the run and prints one JSON line (times, peak
memory of that process, metrics). A fresh interpreter per case keeps one case's memory and caches
out of the next case's figures.

Only the public surface of camloc is used: the ``camloc`` command (``simulate``, ``run``),
``camloc.load``, ``camloc.localize``, ``camloc.LocalizerConfig`` and ``camloc.metrics.evaluate``,
so the scripts keep working while the localizer's internals change.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Mapping, Optional

import numpy as np

REPO = Path(__file__).resolve().parents[1]
REAL_DATASET = REPO.parent / "shared" / "datasets" / "1b-3D-Camera-Localization.g2o"
DEFAULT_CACHE = Path("~/.cache/camloc-bench").expanduser()
# Generated files depend on the simulator's code as much as on its arguments.
SIMULATOR_SOURCE = REPO / "camloc" / "simulate.py"


class BenchError(RuntimeError):
    """A benchmark step that could not be done (a command failed); the message says which."""


# ------------------------------------------------------------------------------------ datasets


def real_dataset() -> Optional[Path]:
    """The real course dataset beside the repository (``<repo>/../shared/datasets``), or None."""
    return REAL_DATASET if REAL_DATASET.is_file() else None


def camloc_command() -> list[str]:
    """How a user calls camloc: the ``camloc`` script installed beside this interpreter (a venv's
    bin, activated or not), else the one on PATH."""
    beside = Path(sys.executable).parent / ("camloc.exe" if os.name == "nt" else "camloc")
    found = str(beside) if beside.is_file() else shutil.which("camloc")
    if found is None:
        raise BenchError("the camloc command is neither beside this Python nor on PATH; install the package (pip install -e .)")
    return [found]


def run(main: Callable[[], None]) -> None:
    """Run a benchmark's main; a step that could not be done ends it with its message, not a traceback."""
    try:
        main()
    except BenchError as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None


def simulate_flags(options: Mapping[str, Any], seed: int) -> list[str]:
    """``camloc simulate`` flags for ``SimulationConfig``-named options, sorted so that the same
    world always gives the same list (the cache key). True booleans become bare flags."""
    flags: list[str] = []
    for name in sorted(options):
        value = options[name]
        flag = "--" + name.replace("_", "-")
        if value is True:
            flags.append(flag)
        elif value is not None and value is not False:
            flags += [flag, str(value)]
    return flags + ["--seed", str(int(seed))]


def simulated(cache: Path, options: Mapping[str, Any], *, seed: int, timeout: float = 1800.0) -> Path:
    """The g2o file ``camloc simulate`` writes for these options and seed, made once and cached.

    The file name holds a hash of the flags and of the simulator's source, so a changed simulator
    makes new files instead of silently reusing old ones. ``camloc simulate`` writes whole or not
    at all, so an interrupted generation leaves no half file in the cache.
    """
    flags = simulate_flags(options, seed)
    key = _digest(json.dumps(flags).encode() + SIMULATOR_SOURCE.read_bytes())
    slug = "-".join(str(options.get(name)) for name in ("trajectory", "poses", "landmarks") if options.get(name))
    path = cache / f"sim-{slug}-s{seed}-{key}.g2o"
    if path.is_file():
        return path
    cache.mkdir(parents=True, exist_ok=True)
    command = camloc_command() + ["simulate", "-o", str(path), *flags, "--json"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=timeout)
    if done.returncode != 0 and path.is_file():
        return path  # a benchmark run beside this one made it first: the same flags and simulator, the same world
    if done.returncode != 0:
        raise BenchError(f"camloc simulate {' '.join(flags)} failed: {done.stderr.strip() or done.stdout.strip()}")
    _write_atomically(path.with_suffix(".json"), json.dumps({"flags": flags, "summary": json.loads(done.stdout)}, indent=2))
    return path


def first_poses(cache: Path, source: Path, poses: int) -> Path:
    """A cached copy of the g2o file ``source`` cut after its first ``poses`` poses: the same map,
    the same cameras, the first pose vertices, the odometry between them and their observations.

    A prefix of one world, not a new world: the map density and the observations per pose stay
    those of the whole file, so only the length changes. Pose ids are taken to be consecutive from
    the first ``VERTEX_SE3:QUAT`` (camloc simulate writes them so).
    """
    path = cache / f"{source.stem}-first{poses}.g2o"
    if path.is_file():
        return path
    lines = source.read_text().splitlines(keepends=True)
    first_id = next(int(line.split()[1]) for line in lines if line.startswith("VERTEX_SE3:QUAT "))
    end = first_id + poses
    # The id field that places each record on the chain: a vertex's own id, an edge's "to", an
    # observation's pose.
    id_field = {"VERTEX_SE3:QUAT": 1, "EDGE_SE3:QUAT": 2, "EDGE_PROJECT_DEPTH": 1}
    kept = []
    for line in lines:
        fields = line.split(maxsplit=3)
        field = id_field.get(fields[0]) if fields else None
        if field is None or int(fields[field]) < end:
            kept.append(line)
    _write_atomically(path, "".join(kept))
    return path


def _digest(data: bytes) -> str:
    return hashlib.sha1(data).hexdigest()[:12]


def _write_atomically(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as handle:
            handle.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def code_version() -> str:
    """A hash of the library's source (``camloc/*.py``, uncommitted edits included): results
    measured with other code are not reused."""
    sources = sorted((REPO / "camloc").glob("*.py"))
    return _digest(b"".join(p.name.encode() + p.read_bytes() for p in sources))


# ------------------------------------------------------------------------------------ results


class ResultStore:
    """Results saved per (library source, measuring code, dataset file, options), so ``--resume``
    can skip them; a changed worker (this file) measures anew like a changed library."""

    def __init__(self, folder: Path, *, enabled: bool):
        self.folder, self.enabled, self.version = folder, enabled, code_version()
        self.key_version = self.version + _digest(Path(__file__).read_bytes())

    def _path(self, dataset: Path, overrides: dict) -> Path:
        key = json.dumps([self.key_version, dataset.name, overrides], sort_keys=True).encode()
        return self.folder / f"{_digest(key)}.json"

    def get(self, dataset: Path, overrides: dict) -> Optional[dict]:
        path = self._path(dataset, overrides)
        if not (self.enabled and path.is_file()):
            return None
        return {**json.loads(path.read_text()), "saved": True}

    def put(self, dataset: Path, overrides: dict, result: dict) -> None:
        if "error" not in result:
            _write_atomically(self._path(dataset, overrides), json.dumps(result))


def localizer_options(settings: list[str], *, fixed: Optional[Mapping[str, Any]] = None,
                      forbidden: tuple[str, ...] = ()) -> dict[str, Any]:
    """Localizer options from ``KEY=VALUE`` strings (values as JSON when they parse, else strings),
    merged over ``fixed`` and validated now rather than in every child: a bad option is one line on
    stderr and exit status 2. KEY is a config file's name, dotted for a group's option:
    ``gate=0.95``, ``beam.width=8``, ``recheck.enabled=false`` (``camloc.config``)."""
    from camloc.errors import CamlocError

    options = dict(fixed or {})
    for setting in settings:
        key, sep, text = setting.partition("=")
        if not sep or key in forbidden:
            _fail(f"--set expects KEY=VALUE with KEY a localizer option other than {', '.join(forbidden) or 'none'}, "
                  f"as a config file names it (gate, beam.width); found {setting!r}")
        options[key] = parse_value(text)
    try:
        localizer_config(options)
    except CamlocError as error:
        _fail(f"localizer options {options}: {error}")
    return options


def localizer_config(options: Mapping[str, Any]):
    """The validated LocalizerConfig of options named as ``localizer_options`` takes them."""
    from camloc.config import make_config, parse_config

    return make_config(parse_config(_document(options), source="--set"))


def options_for(association: str, options: Mapping[str, Any]) -> dict[str, Any]:
    """``options`` without the ones of association methods other than ``association`` (which
    ``camloc.LocalizerConfig`` refuses)."""
    from camloc.config import parse_config
    from camloc.localizer_config import option_methods

    methods = option_methods()

    def applies(key: str, value: Any) -> bool:
        (path,) = parse_config(_document({key: value}), source="--set").values
        return association in methods.get(path, (association,))

    return {key: value for key, value in options.items() if applies(key, value)}


def _document(options: Mapping[str, Any]) -> dict[str, Any]:
    """The TOML document of dotted options: ``{"beam.width": 8}`` -> ``{"beam": {"width": 8}}``."""
    document: dict[str, Any] = {}
    for key, value in options.items():
        *tables, name = key.split(".")
        node = document
        for table in tables:
            node = node.setdefault(table, {})
        node[name] = value
    return document


def _fail(message: str) -> None:
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def parse_value(text: str) -> Any:
    """``8`` -> 8, ``0.5`` -> 0.5, ``false`` -> False, ``null`` -> None, anything else the string."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


# ------------------------------------------------------------------------------- child processes


def run_case(path: Path, config: Mapping[str, Any], *, timeout: float) -> dict:
    """Localize ``path`` with the options ``config`` (as ``localizer_options`` names them) in a fresh interpreter.

    Returns the child's JSON (see ``_worker``): times, peak memory, poses, landmarks, observations
    and metrics, plus ``wall_seconds``, the child's whole life (interpreter start, read, localize,
    evaluate); or ``{"error": ...}`` when it failed or ran out of time.
    """
    request = json.dumps({"path": str(path), "config": dict(config)})
    command = [sys.executable, str(Path(__file__).resolve()), "--worker", request]
    started = time.perf_counter()
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"timeout after {timeout:.0f} s"}
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        return {"error": f"exit {done.returncode}: {last}"}
    result = json.loads(done.stdout.strip().splitlines()[-1])
    return {**result, "wall_seconds": time.perf_counter() - started}


# A tiny launcher between the benchmark and a timed command. Linux carries a process's peak memory
# across exec (ru_maxrss is the larger of the pre-exec and post-exec peaks), and a child forked from
# this benchmark starts with the benchmark's own peak, often larger than the child's: spawned from
# an interpreter that imported nothing, the command's ru_maxrss is its own.
_LAUNCHER = """
import os, sys, time
null = [(os.POSIX_SPAWN_OPEN, fd, os.devnull, os.O_WRONLY, 0) for fd in (1, 2)]
started = time.perf_counter()
pid = os.posix_spawnp(sys.argv[1], sys.argv[1:], os.environ, file_actions=null)
_, status, usage = os.wait4(pid, 0)
print(time.perf_counter() - started, usage.ru_maxrss, os.waitstatus_to_exitcode(status))
"""


def timed_command(command: list[str], *, timeout: float) -> tuple[float, float, int]:
    """Run ``command`` (output discarded); return wall seconds (interpreter start included), its
    peak resident memory in MB, and its exit status (-9 when killed at the timeout).

    A minimal launcher spawns and reaps the command (see ``_LAUNCHER``): ``os.wait4`` gives the
    rusage of that one child, and the child does not inherit this process's peak.
    """
    launcher = subprocess.Popen([sys.executable, "-I", "-S", "-c", _LAUNCHER, *command], stdout=subprocess.PIPE,
                                text=True, start_new_session=True)
    try:
        out, _ = launcher.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(launcher.pid, signal.SIGKILL)  # the launcher's own session: the command and nothing else
        launcher.communicate()
        return float(timeout), float("nan"), -9
    if launcher.returncode != 0 or not out.strip():
        return float("nan"), float("nan"), launcher.returncode or -1
    seconds, maxrss_kib, status = out.split()
    return float(seconds), int(maxrss_kib) / 1024.0, int(status)


def peak_memory_mb() -> float:
    """This process's peak resident memory since its exec, MB (``camloc.replay.peak_memory_mb``);
    ``ru_maxrss`` where /proc is absent."""
    from camloc.replay import peak_memory_mb as own_peak

    peak = own_peak()
    if peak is not None:
        return peak
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def _worker(request: dict) -> dict:
    """The measured case, in this (child) process."""
    import camloc
    from camloc.metrics import evaluate

    started = time.perf_counter()
    dataset = camloc.load(request["path"])
    read_seconds = time.perf_counter() - started
    config = localizer_config(request["config"])
    started = time.perf_counter()
    result = camloc.localize(dataset, config)
    filter_seconds = time.perf_counter() - started
    metrics = evaluate(result)
    # with the beam's replay in a second process (camloc.replay) both hold memory at once
    peak_mb = peak_memory_mb() + (result.summary["timing"].get("replay_process_peak_mb") or 0.0)
    estimate = metrics.get("estimate") or {}
    return {
        "poses": dataset.num_poses,
        "landmarks": int(dataset.landmark_ids.size),
        "observations": dataset.num_observations,
        "association": config.association,
        "read_seconds": read_seconds,
        "filter_seconds": filter_seconds,
        "peak_mb": peak_mb,
        "rmse_m": (estimate.get("ate") or {}).get("rmse"),
        "rotation_rmse_deg": (estimate.get("rotation") or {}).get("rmse_deg"),
        "association_scores": metrics["association"],
    }


# ----------------------------------------------------------------------------------- ambiguity


def ambiguity(dataset, *, sigmas: float = 3.0) -> float:
    """Fraction of the in-map observations for which another landmark's predicted measurement,
    from the TRUE pose, lies within ``sigmas`` of the measurement (Mahalanobis distance under the
    observation covariance R alone).

    A lower bound on what a filter faces: its innovation covariance S = H P H' + R is larger than
    R, so more rivals gate. NaN when there are no in-map observations or no ground truth.
    """
    from scipy.spatial import cKDTree

    if dataset.truth_xyz is None or dataset.num_observations == 0:
        return float("nan")
    index_of_id = {int(i): n for n, i in enumerate(dataset.landmark_ids)}
    true_index = np.array([index_of_id.get(int(i), -1) for i in dataset.obs_true_landmark])
    tree = cKDTree(dataset.landmark_xyz)
    T_world_robot = dataset.T_world_truth
    ambiguous = np.zeros(dataset.num_observations, dtype=bool)
    for camera_id, camera in dataset.cameras.items():
        rows = np.flatnonzero((dataset.obs_camera == camera_id) & (true_index >= 0))
        if rows.size == 0:
            continue
        T_world_camera = T_world_robot[dataset.obs_pose_index[rows]] @ camera.T_robot_camera
        intrinsics = np.array([camera.fx, camera.fy, camera.cx, camera.cy])
        ambiguous[rows] = _has_rival(rows, T_world_camera, intrinsics, dataset, tree, true_index, sigmas)
    return float(np.count_nonzero(ambiguous) / np.count_nonzero(true_index >= 0))


def _has_rival(rows, T_world_camera, intrinsics, dataset, tree, true_index, sigmas) -> np.ndarray:
    """For each observation of ``rows`` (one camera), whether a rival landmark predicts within
    ``sigmas``. Rivals are looked up in a ball around the back-projected measurement that holds
    every point whose prediction can be that close; the exact test follows."""
    fx, fy, cx, cy = intrinsics
    uvd = dataset.obs_z[rows]
    depth = uvd[:, 2]
    p_camera = np.column_stack([(uvd[:, 0] - cx) / fx * depth, (uvd[:, 1] - cy) / fy * depth, depth])
    p_world = np.einsum("nij,nj->ni", T_world_camera[:, :3, :3], p_camera) + T_world_camera[:, :3, 3]
    # Mahalanobis distance <= sigmas bounds every component of the innovation by delta; then
    # |q_x - p_x| = |(u' - u) d' + (u - cx)(d' - d)| / fx <= delta (d + delta + |u - cx|) / fx.
    delta = sigmas * np.sqrt(np.linalg.eigvalsh(dataset.obs_cov[rows])[:, -1])
    reach = np.abs(depth) + delta
    lateral_x = delta * (reach + np.abs(uvd[:, 0] - cx)) / abs(fx)
    lateral_y = delta * (reach + np.abs(uvd[:, 1] - cy)) / abs(fy)
    radius = 1.01 * np.sqrt(delta**2 + lateral_x**2 + lateral_y**2)
    out = np.zeros(rows.size, dtype=bool)
    for n, candidates in enumerate(tree.query_ball_point(p_world, radius)):
        rivals = np.array([c for c in candidates if c != true_index[rows[n]]], dtype=np.int64)
        if rivals.size == 0:
            continue
        R, t = T_world_camera[n, :3, :3], T_world_camera[n, :3, 3]
        q = (dataset.landmark_xyz[rivals] - t) @ R  # camera frame: R' (l - t)
        q = q[q[:, 2] > 1e-6]
        if q.size == 0:
            continue
        z_hat = np.column_stack([fx * q[:, 0] / q[:, 2] + cx, fy * q[:, 1] / q[:, 2] + cy, q[:, 2]])
        y = z_hat - uvd[n]
        d2 = np.einsum("ni,ni->n", y, np.linalg.solve(dataset.obs_cov[rows[n]], y.T).T)
        out[n] = bool(np.any(d2 <= sigmas**2))
    return out


def source_note() -> str:
    """Which library was measured: the source hash, and the git commit when there is one."""
    try:
        commit = subprocess.run(["git", "-C", str(REPO), "log", "-1", "--format=%h"], capture_output=True,
                                text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--", "camloc"], capture_output=True,
                               text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.TimeoutExpired):
        commit, dirty = "", ""
    git = f", git {commit}{' + uncommitted edits' if dirty else ''}" if commit else ""
    return f"camloc source {code_version()}{git}"


# ------------------------------------------------------------------------------------ formatting


def machine_load() -> str:
    """The 1, 5 and 15 minute load averages against the core count: times measured on a busy
    machine are slower, and the reader should know."""
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.1f} / {five:.1f} / {fifteen:.1f} on {os.cpu_count()} cores"


def fmt(value: Optional[float], digits: int = 3, *, percent: bool = False) -> str:
    """A table cell: '-' for a missing value."""
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "-"
    return f"{100.0 * value:.{digits}f}%" if percent else f"{value:.{digits}f}"


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--worker":
        print(json.dumps(_worker(json.loads(sys.argv[2]))))
    else:
        sys.exit("usage: python benchmarks/_bench.py --worker '<json request>' (used by the benchmark scripts)")
