"""Scale and speed: how the localizer's cost grows with the number of poses and the size of the map,
with the position error beside every time so that speed is never bought with accuracy.

Cases (full mode; ``--quick`` runs the same cases on small worlds in a minute or two):

- ``real file``: ``camloc run <repo>/../shared/datasets/1b-3D-Camera-Localization.g2o -o TMP --quiet``
  as a user calls it; wall time best of ``--repeats``, interpreter start included; read and filter
  times and the RMSE from the run's summary.json. Skipped with a note when the file is absent.
- ``world 20k``: ``camloc simulate --trajectory smooth3d --poses 20000 --landmarks 20000 --region 42
  --seed 1``, about 10 observations per pose (measured and printed).
- ``first 1k``, ``first 5k``: the first 1,000 and 5,000 poses of that world (same map, same density,
  same observations per pose: only the length changes).
- ``map 1k``, ``map 10k``, ``map 100k``: one trajectory, one set of observations, maps of three sizes.
  A compact world (``--trajectory smooth3d --poses 20000 --landmarks 1000 --region 7
  --max-tilt-deg 6``, about 10 observations per pose) whose map is padded with landmarks that no
  camera can see (farther than 3 m from every pose, at the world's density): a robot in one part of
  a large mapped site. Only the map grows, so any change of cost is the map's.

Every simulated case runs in its own interpreter, whose own peak memory is reported (see
``_bench.peak_memory_mb``): read with ``camloc.load``, localize with ``camloc.localize`` (default
``LocalizerConfig`` unless ``--association`` / ``--set`` say otherwise), score with
``camloc.metrics.evaluate``. Read and filter
times are wall-clock around those calls. µs/pose = filter time / poses, flat when the cost is
linear in poses and independent of the map; µs/obs divides by observations instead.

    nice python benchmarks/scale.py --quick
    nice python benchmarks/scale.py [--association beam] [--set beam.width=8] [--json]

Generated worlds are cached in ``--cache`` (default ~/.cache/camloc-bench), keyed by their simulate
arguments and the simulator's source; results are saved there too and ``--resume`` reuses those
measured with the same library source. Nothing here asserts anything about time.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
from pathlib import Path
from typing import Any, Optional

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench  # noqa: E402  (the benchmarks folder is not a package)

# Visible only within 2 m of the camera, and the camera sits 0.3 m from the robot origin: a
# landmark 3 m from every pose is out of every view.
OUT_OF_VIEW_M = 3.0
PAD_SEED = 20261122


@dataclasses.dataclass(frozen=True)
class Plan:
    """The worlds of one mode: the main world, its prefixes, the compact world and its map sizes."""

    world: dict
    prefixes: tuple[int, ...]
    room: dict
    map_sizes: tuple[int, ...]
    seed: int = 1


FULL = Plan(
    world=dict(trajectory="smooth3d", poses=20000, landmarks=20000, region=42),
    prefixes=(1000, 5000),
    room=dict(trajectory="smooth3d", poses=20000, landmarks=1000, region=7, max_tilt_deg=6),
    map_sizes=(1000, 10000, 100000),
)
QUICK = Plan(
    world=dict(trajectory="smooth3d", poses=1000, landmarks=2000, region=10),
    prefixes=(250, 500),
    room=dict(trajectory="smooth3d", poses=500, landmarks=1000, region=9, max_tilt_deg=6),
    map_sizes=(1000, 10000, 100000),
)


def main() -> None:
    args = parse_args()
    overrides = localizer_overrides(args)
    plan = QUICK if args.quick else FULL
    cache = args.cache.expanduser()
    say = (lambda text: print(text, file=sys.stderr, flush=True))
    say(f"camloc scale benchmark ({'quick' if args.quick else 'full'}); localizer: {describe_config(overrides)}; "
        f"{_bench.source_note()}; cache: {cache}; {_bench.machine_load()}")

    rows: list[dict] = []
    store = _bench.ResultStore(cache / "results" / "scale", enabled=args.resume)

    real = _bench.real_dataset()
    if args.skip_real:
        say("real file: skipped (--skip-real)")
    elif real is None:
        say(f"real file: skipped, {_bench.REAL_DATASET} is absent")
    else:
        row = real_file_case(real, overrides, repeats=args.repeats, timeout=args.timeout)
        rows.append(announce(say, with_oracle(row, real, overrides, store, args, say)))

    say("generating / finding the simulated worlds ...")
    world = _bench.simulated(cache, plan.world, seed=plan.seed)
    cases = [(f"first {_k(n)}", _bench.first_poses(cache, world, n)) for n in plan.prefixes if n < plan.world["poses"]]
    cases.append((f"world {_k(plan.world['poses'])}", world))
    room = _bench.simulated(cache, plan.room, seed=plan.seed)
    cases += [(f"map {_k(size)}", padded_map(cache, room, size)) for size in plan.map_sizes]

    for name, path in cases:
        row = row_of(name, measured(store, path, overrides, timeout=args.timeout, say=say), path)
        rows.append(announce(say, with_oracle(row, path, overrides, store, args, say)))

    say(f"done; {_bench.machine_load()}")
    if store.version != _bench.code_version():
        say("warning: the library's source (camloc/*.py) changed during this run: the rows mix versions")
    if args.json:
        print(json.dumps({"localizer": overrides, "plan": dataclasses.asdict(plan), "machine": _bench.machine_load(),
                          "source": _bench.source_note(), "rows": rows}, indent=2))
    else:
        print_table(rows, overrides, quick=args.quick)


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small worlds, a minute or two (default: full sizes)")
    parser.add_argument("--cache", type=Path, default=_bench.DEFAULT_CACHE,
                        help=f"folder for generated worlds and saved results (default {_bench.DEFAULT_CACHE})")
    parser.add_argument("--association", default=None, metavar="METHOD",
                        help="association method, any LocalizerConfig accepts, e.g. beam, jcbb, best-friends, oracle "
                        "(default: LocalizerConfig's default)")
    parser.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                        help="any other localizer option, named as in a config file, e.g. --set beam.width=8 --set gate=0.95 "
                        "(repeatable; default: none)")
    parser.add_argument("--repeats", type=int, default=3, help="real-file runs, the fastest is reported (default 3)")
    parser.add_argument("--timeout", type=float, default=3600.0, help="seconds allowed per case (default 3600)")
    parser.add_argument("--skip-real", action="store_true", help="leave out the real file (default: run it when present)")
    parser.add_argument("--no-oracle", action="store_true",
                        help="do not run the oracle for the reference RMSE and oracle µs/pose columns (default: run it)")
    parser.add_argument("--resume", action="store_true",
                        help="reuse results saved by an earlier run with the same library source (default: measure anew)")
    parser.add_argument("--json", action="store_true", help="print the rows as JSON instead of a table (default: table)")
    return parser.parse_args()


def localizer_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The LocalizerConfig options given on the command line (``--association`` wins over a
    ``--set association=``), checked now rather than per case."""
    association = [f"association={args.association}"] if args.association else []
    return _bench.localizer_options(args.settings + association)


def describe_config(overrides: dict) -> str:
    import camloc

    default = camloc.LocalizerConfig().association
    return ", ".join(f"{k}={v}" for k, v in overrides.items()) if overrides else f"defaults (association={default})"


def _k(n: int) -> str:
    return f"{n // 1000}k" if n >= 1000 and n % 1000 == 0 else str(n)


# --------------------------------------------------------------------------------------- cases


def real_file_case(path: Path, overrides: dict, *, repeats: int, timeout: float) -> dict:
    """``camloc run`` on the real file as a user types it; the fastest of ``repeats`` runs."""
    with tempfile.TemporaryDirectory(prefix="camloc-bench-") as tmp:
        command = _bench.camloc_command() + ["run", str(path), "-o", str(Path(tmp) / "run"), "--quiet", "--force"]
        if overrides:
            config = Path(tmp) / "localizer.toml"
            config.write_text("".join(f"{k} = {_toml(v)}\n" for k, v in overrides.items() if v is not None))
            command += ["--config", str(config)]
        best: Optional[dict] = None
        for _ in range(repeats):
            seconds, peak_mb, status = _bench.timed_command(command, timeout=timeout)
            if status != 0:
                return {"case": "real file", "error": f"camloc run exited {status}"}
            summary = json.loads((Path(tmp) / "run" / "summary.json").read_text())
            if best is None or seconds < best["wall_seconds"]:
                best = {"wall_seconds": seconds, "peak_mb": peak_mb, "summary": summary}
    summary = best["summary"]
    counts, timing = summary["counts"], summary["timing"]
    return {
        "case": "real file",
        "poses": counts["poses"],
        "landmarks": counts["landmarks"],
        "observations": counts["observations"],
        "read_seconds": timing.get("read_seconds"),
        "filter_seconds": timing.get("filter_seconds"),
        "wall_seconds": best["wall_seconds"],
        "peak_mb": best["peak_mb"],
        "rmse_m": ((summary["estimate"] or {}).get("ate") or {}).get("rmse"),
        "precision": summary["association"]["precision"],
        "association": summary["config"]["association"],
    }


def _toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    return repr(value)


def padded_map(cache: Path, room: Path, size: int) -> Path:
    """The compact world with its map padded to ``size`` landmarks that no camera can see.

    The padding is uniform over a square around the world at the world's own density (landmarks
    per cubic metre of its map's bounding box), over the same heights, keeping only points farther
    than ``OUT_OF_VIEW_M`` from every true pose. The observations, trajectory and cameras are the
    file's, untouched; the new ids follow every id of the file.
    """
    import camloc
    from scipy.spatial import cKDTree

    path = cache / f"{room.stem}-map{size}.g2o"
    if path.is_file():
        return path
    dataset = camloc.load(room)
    existing = int(dataset.landmark_ids.size)
    if size <= existing:  # nothing to add: the world itself
        return room
    low, high = dataset.landmark_xyz.min(axis=0), dataset.landmark_xyz.max(axis=0)
    extent = np.maximum(high - low, 1.0)
    density = existing / float(np.prod(extent))
    # The square side whose slab, at this density, holds the map plus the padding (plus the
    # points rejected near the path, which the loop replaces).
    side = float(np.sqrt((size / density) / extent[2]))
    centre = (low + high) / 2.0
    rng = np.random.default_rng(PAD_SEED)
    near_path = cKDTree(dataset.truth_xyz)
    padding = np.zeros((0, 3))
    while padding.shape[0] < size - existing:
        batch = centre + rng.uniform(-0.5, 0.5, (2 * (size - existing), 3)) * np.array([side, side, extent[2]])
        far = near_path.query(batch, distance_upper_bound=OUT_OF_VIEW_M)[0] > OUT_OF_VIEW_M
        padding = np.vstack([padding, batch[far]])
    padding = padding[: size - existing]
    first_id = 10 ** len(str(int(max(dataset.pose_ids.max(), dataset.landmark_ids.max(), dataset.obs_true_landmark.max()))))
    lines = [f"VERTEX_TRACKXYZ {first_id + n} {x!r} {y!r} {z!r}\n" for n, (x, y, z) in enumerate(padding.tolist())]
    _bench._write_atomically(path, room.read_text() + "".join(lines))
    return path


# ------------------------------------------------------------------------------------ results


def measured(store: _bench.ResultStore, path: Path, config: dict, *, timeout: float, say) -> dict:
    """The worker's result for ``path`` with ``config``: saved (``--resume``) or measured now."""
    result = store.get(path, config)
    if result is None:
        say(f"   localizing {path.name} ({describe_config(config)}) ...")
        result = _bench.run_case(path, config, timeout=timeout)
        store.put(path, config, result)
    return result


def with_oracle(row: dict, path: Path, overrides: dict, store: _bench.ResultStore, args: argparse.Namespace, say) -> dict:
    """The row plus the oracle's RMSE and µs/pose on the same file (the file's true ids, same
    options): the accuracy the association could reach, so that an RMSE can be judged, and what
    the filter costs with no association to decide, the floor of any method's time. Not for
    --no-oracle or when the oracle is what is being timed."""
    if args.no_oracle or overrides.get("association") == "oracle" or "error" in row:
        return row
    oracle = measured(store, path, {**_bench.options_for("oracle", overrides), "association": "oracle"}, timeout=args.timeout, say=say)
    return {**row, "oracle_rmse_m": oracle.get("rmse_m"), "oracle_us_per_pose": derived(oracle).get("us_per_pose")}


def row_of(name: str, result: dict, path: Path) -> dict:
    """A table row from a worker's result."""
    if "error" in result:
        return {"case": name, "dataset": path.name, "error": result["error"]}
    scores = result["association_scores"]
    return {
        "case": name,
        "dataset": path.name,
        "poses": result["poses"],
        "landmarks": result["landmarks"],
        "observations": result["observations"],
        "read_seconds": result["read_seconds"],
        "filter_seconds": result["filter_seconds"],
        "wall_seconds": result["wall_seconds"],
        "peak_mb": result["peak_mb"],
        "rmse_m": result["rmse_m"],
        "precision": scores["precision"],
        "association": result["association"],
        "saved": bool(result.get("saved")),
    }


def derived(row: dict) -> dict:
    """obs/pose, poses per second, µs per pose and per observation."""
    poses, observations, seconds = row.get("poses"), row.get("observations"), row.get("filter_seconds")
    if not poses or seconds is None:
        return {}
    return {
        "obs_per_pose": observations / poses,
        "poses_per_second": poses / seconds if seconds > 0 else None,
        "us_per_pose": 1e6 * seconds / poses,
        "us_per_observation": 1e6 * seconds / observations if observations else None,
    }


def announce(say, row: dict) -> dict:
    """Print one finished row at once (long runs show progress), and return it with its derived figures."""
    row = {**row, **derived(row)}
    if "error" in row:
        say(f"{row['case']}: FAILED {row['error']}")
        return row
    oracle = "" if row.get("oracle_rmse_m") is None else (
        f" (oracle {row['oracle_rmse_m']:.3f} m, {_bench.fmt(row.get('oracle_us_per_pose'), 0)} µs/pose)")
    saved = " (saved result, --resume)" if row.get("saved") else ""
    say(f"{row['case']}: {row['poses']} poses, {row['landmarks']} landmarks, {row['obs_per_pose']:.2f} obs/pose, "
        f"filter {row['filter_seconds']:.2f} s ({row['us_per_pose']:.0f} µs/pose), peak {row['peak_mb']:.0f} MB, "
        f"RMSE {_bench.fmt(row['rmse_m'])} m{oracle}{saved}")
    return row


def print_table(rows: list[dict], overrides: dict, *, quick: bool) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"camloc scale ({'quick' if quick else 'full'}), localizer: {describe_config(overrides)}",
                  caption=f"at the end: {_bench.machine_load()}")
    columns = ["case", "poses", "landmarks", "obs/pose", "read (s)", "filter (s)", "wall (s)", "poses/s", "µs/pose",
               "µs/obs", "peak MB", "RMSE (m)", "oracle RMSE", "oracle µs/pose", "precision"]
    for column in columns:
        table.add_column(column, justify="left" if column == "case" else "right")
    for row in rows:
        if "error" in row:
            table.add_row(row["case"], *["-"] * (len(columns) - 2), row["error"])
            continue
        table.add_row(
            row["case"], str(row["poses"]), str(row["landmarks"]), f"{row['obs_per_pose']:.2f}",
            _bench.fmt(row["read_seconds"], 3), _bench.fmt(row["filter_seconds"], 2), _bench.fmt(row["wall_seconds"], 2),
            _bench.fmt(row["poses_per_second"], 0), _bench.fmt(row["us_per_pose"], 0),
            _bench.fmt(row["us_per_observation"], 0), _bench.fmt(row["peak_mb"], 0), _bench.fmt(row["rmse_m"]),
            _bench.fmt(row.get("oracle_rmse_m")), _bench.fmt(row.get("oracle_us_per_pose"), 0),
            _bench.fmt(row["precision"], 2, percent=True),
        )
    console = Console(width=max(Console().width, 170))
    console.print(table)
    console.print("wall: the whole child process, interpreter start included (real file: `camloc run` as a user "
                  "types it, best of --repeats; simulated: read + localize + evaluate, no run folder written).")
    console.print("µs/pose: flat down the 'first'/'world' rows = linear in poses; flat down the 'map' rows = "
                  "independent of the map's size (same trajectory and observations, map padded out of view).")
    console.print("oracle µs/pose: the same filter given the file's true association (nothing to decide): the floor "
                  "under any association method's µs/pose on this machine.")


if __name__ == "__main__":
    _bench.run(main)
