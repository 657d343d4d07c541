"""Monte Carlo sweeps: one localization run per cell of seeds x simulate options x run options.

A spec (TOML) names ``camloc simulate``'s and ``camloc run``'s options by their command-line
names; a list gives one value per cell and the cells are the product of the lists::

    seeds = [1, 2, 3]                   # or seeds = 10 (0..9); or datasets = ["worlds/*.g2o"]
    [simulate]
    trajectory = ["grid", "smooth3d"]
    poses = 300
    [run]
    association = ["beam", "oracle"]

Each cell makes its world where it runs (``camloc.simulate`` from its seed, a planar robot's with
``robot = "planar"``, a world of tags with ``tag-sigma-deg``; or reads its file),
localizes it (``camloc.localize``) and scores it (``camloc.metrics.evaluate``): nothing large
travels to a worker and a cell's numbers do not depend on where it ran. The sweep folder holds
``spec.json`` (the normalized spec, so that a resumed sweep can say what changed), ``runs.csv`` (a
row per finished cell, sorted in cell order) and ``summary.csv`` (a row per configuration: every
parameter but the world). Both CSV files are rewritten whole through a temporary file and a
rename, at most once per ``FLUSH_SECONDS`` and when the sweep ends or is interrupted: a reader, or
a resumed sweep, never sees half a file.

Cells run in local processes (``concurrent.futures``, spawned) or on a Dask cluster
(``distributed.Client``, imported only then).
"""

from __future__ import annotations

import contextlib
import csv
import difflib
import glob
import hashlib
import importlib
import io
import itertools
import json
import math
import multiprocessing
import os
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, Optional

from camloc.errors import CamlocError, ConfigError

SPEC_FILE = "spec.json"
RUNS_FILE = "runs.csv"
SUMMARY_FILE = "summary.csv"
SPEC_KEYS = ("seeds", "datasets", "simulate", "run")
# What a cell reports, after its parameters; empty where a run failed or has no ground truth.
RESULT_COLUMNS = ("status", "error", "ate_rmse", "rotation_rmse_deg", "rpe", "precision", "recall", "nees_mean", "seconds")
METRIC_COLUMNS = RESULT_COLUMNS[2:8]
ORACLE = "oracle"
FLUSH_SECONDS = 1.0
Scalar = str | int | float | bool


# --------------------------------------------------------------------------------------------
# The spec


@dataclass(frozen=True)
class SweepSpec:
    """A parsed sweep spec; every value is a tuple of the cells' values, in the spec's order.

    Attributes
    ----------
    seeds : the simulated worlds' seeds (empty with ``datasets``).
    datasets : g2o files, as matched relative to ``base_dir`` (empty with ``seeds``).
    simulate : ``camloc simulate`` option (command-line name) -> its values.
    run : ``camloc run`` option (command-line name) -> its values.
    base_dir : the folder dataset paths are relative to (the spec file's); not part of the spec's
        identity.
    """

    seeds: tuple[int, ...] = ()
    datasets: tuple[str, ...] = ()
    simulate: tuple[tuple[str, tuple[Scalar, ...]], ...] = ()
    run: tuple[tuple[str, tuple[Scalar, ...]], ...] = ()
    base_dir: str = "."

    @property
    def world_column(self) -> str:
        """``seed`` or ``dataset``: the parameter the summary aggregates over."""
        return "dataset" if self.datasets else "seed"

    @property
    def columns(self) -> tuple[str, ...]:
        """Every parameter column of ``runs.csv``: the world, then simulate's, then run's options."""
        return (self.world_column, *(name for name, _ in self.simulate), *(name for name, _ in self.run))

    @property
    def config_columns(self) -> tuple[str, ...]:
        """The parameters that make a configuration: all but the world."""
        return self.columns[1:]

    def normalized(self) -> dict:
        """The spec as plain JSON data (scalars as one-value lists): what ``spec.json`` records."""
        worlds = {"datasets": list(self.datasets)} if self.datasets else {"seeds": list(self.seeds)}
        return {**worlds, "simulate": {k: list(v) for k, v in self.simulate}, "run": {k: list(v) for k, v in self.run}}

    @classmethod
    def from_normalized(cls, data: Mapping, *, base_dir: str = ".") -> "SweepSpec":
        """The spec ``normalized`` gave (no validation: it was validated when written)."""
        table = lambda key: tuple((k, tuple(v)) for k, v in data.get(key, {}).items())  # noqa: E731
        return cls(tuple(data.get("seeds", ())), tuple(data.get("datasets", ())), table("simulate"), table("run"), base_dir)


def read_spec(path: str | Path) -> SweepSpec:
    """Read and validate a sweep spec file (see ``parse_spec``)."""
    from camloc.config import read_toml

    path = Path(path)
    return parse_spec(read_toml(path, what="sweep spec"), source=str(path), base_dir=str(path.parent))


def parse_spec(document: Mapping[str, Any], *, source: str = "spec", base_dir: str = ".") -> SweepSpec:
    """Validate a spec's TOML document and return the ``SweepSpec``.

    Every simulate cell and every run cell is checked by the library's own validation (so a bad
    value fails here, before anything runs), and so is the size of the product.

    Raises
    ------
    ConfigError : ``source: what is wrong``: an unknown key or option, a bad value, both seeds and
        datasets, a pattern that matches no file, or an empty product.
    """
    where = lambda text: ConfigError(f"{source}: {text}")  # noqa: E731
    for key in document:
        if key not in SPEC_KEYS:
            raise where(f"unknown key {key!r}{_did_you_mean(key, SPEC_KEYS)}; expected some of {', '.join(SPEC_KEYS)}")
    simulate = _option_table(document, "simulate", where)
    run = _option_table(document, "run", where)
    if "datasets" in document:
        if "seeds" in document or simulate:
            raise where("datasets sweeps existing files: it takes neither seeds nor [simulate]")
        spec = SweepSpec(datasets=_datasets(document["datasets"], base_dir, where), run=run, base_dir=base_dir)
    elif "seeds" in document:
        spec = SweepSpec(seeds=_seeds(document["seeds"], where), simulate=simulate, run=run, base_dir=base_dir)
    else:
        raise where("expected seeds = N or [list] (worlds simulated from [simulate]) or datasets = [\"*.g2o\"]")
    clash = set(name for name, _ in simulate) & set(name for name, _ in run)
    if clash:
        raise where(f"option(s) {', '.join(sorted(clash))} in both [simulate] and [run]")
    _check_cells(spec, where)
    return spec


def _option_table(document: Mapping, key: str, where) -> tuple[tuple[str, tuple[Scalar, ...]], ...]:
    table = document.get(key, {})
    if not isinstance(table, dict):
        raise where(f"{key} must be a table ([{key}]) of options, found {table!r}")
    out = []
    for name, value in table.items():
        values = tuple(value) if isinstance(value, list) else (value,)
        if not values:
            raise where(f"empty product: [{key}] {name} = [] gives no cells")
        bad = [v for v in values if not isinstance(v, (str, int, float, bool))]
        if bad:
            raise where(f"[{key}] {name}: expected a value or a list of values, found {bad[0]!r}")
        if len(set(map(format_value, values))) < len(values):
            raise where(f"[{key}] {name}: a value is listed twice in {list(values)}")
        out.append((name, values))
    return tuple(out)


def _seeds(value: Any, where) -> tuple[int, ...]:
    if isinstance(value, int) and not isinstance(value, bool):
        seeds = tuple(range(value)) if value >= 0 else None
    elif isinstance(value, list) and all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in value):
        seeds = tuple(value) if len(set(value)) == len(value) else None
    else:
        seeds = None
    if seeds is None:
        raise where(f"seeds: expected a count N (seeds 0..N-1) or a list of distinct integers >= 0, found {value!r}")
    if not seeds:
        raise where(f"empty product: seeds = {value!r} gives no worlds")
    return seeds


def _datasets(value: Any, base_dir: str, where) -> tuple[str, ...]:
    patterns = [value] if isinstance(value, str) else value
    if not isinstance(patterns, list) or not all(isinstance(p, str) for p in patterns):
        raise where(f"datasets: expected a list of file names or glob patterns, found {value!r}")
    if not patterns:
        raise where("empty product: datasets = [] gives no worlds")
    found: dict[str, None] = {}
    for pattern in patterns:
        matches = sorted(glob.glob(pattern, root_dir=base_dir, recursive=True))
        matches = [m for m in matches if Path(base_dir, m).is_file()]
        if not matches:
            raise where(f"datasets: no file matches {pattern!r} (relative to {base_dir})")
        found.update(dict.fromkeys(matches))
    return tuple(found)


def applicable(run_options: dict[str, Scalar]) -> dict[str, Scalar]:
    """A cell's run options less those of association methods other than the cell's own: in a
    sweep over methods, each method's options are for its own cells (``[run] association = ["beam",
    "oracle"]`` with ``beam-width = 8`` runs the beam at width 8 beside the oracle)."""
    from camloc.localizer_config import LocalizerConfig, option_methods
    from camloc.options import RUN_OPTIONS

    association = run_options.get("association", LocalizerConfig().association)
    methods = option_methods()
    return {name: value for name, value in run_options.items()
            if association in methods.get(RUN_OPTIONS.get(name, ""), (association,))}


def _check_cells(spec: SweepSpec, where) -> None:
    """Build every simulate cell's and run cell's config once, so bad values fail before running;
    a method's option where no cell runs that method is refused, as ``camloc run`` refuses it."""
    from camloc.config import run_config
    from camloc.simulate_planar import world_config

    for key, table, build in (("simulate", spec.simulate, world_config), ("run", spec.run, run_config)):
        unused = {name for name, _ in table} if key == "run" else set()
        for options in _product(table):
            cell = ", ".join(f"{k} = {_toml(v)}" for k, v in options.items())
            try:
                if key == "run":
                    kept = applicable(options)
                    unused -= set(kept)
                    options = kept
                build(options)
            except ConfigError as error:
                raise where(f"[{key}] {cell}: {error}") from None
        if unused:
            from camloc.localizer_config import option_methods
            from camloc.options import RUN_OPTIONS

            name = sorted(unused)[0]
            methods = option_methods()[RUN_OPTIONS[name]]
            raise where(f"[run] {name}: applies only with association {' or '.join(methods)}, which no cell selects")


def _product(table: tuple[tuple[str, tuple[Scalar, ...]], ...]) -> list[dict[str, Scalar]]:
    names = [name for name, _ in table]
    return [dict(zip(names, values)) for values in itertools.product(*(values for _, values in table))]


def _did_you_mean(name: str, choices: Iterable[str]) -> str:
    close = difflib.get_close_matches(name, list(choices), n=1)
    return f" (did you mean {close[0]}?)" if close else ""


def _toml(value: Scalar) -> str:
    return json.dumps(value) if isinstance(value, (str, bool)) else repr(value)


def spec_changes(old: Mapping, new: Mapping) -> list[str]:
    """What differs between two normalized specs, one phrase per parameter, e.g.
    ``"[run] association: ['beam'] -> ['beam', 'oracle']"``."""
    changes = []
    for key in ("seeds", "datasets"):
        if old.get(key) != new.get(key):
            changes.append(f"{key}: {_list_text(old.get(key))} -> {_list_text(new.get(key))}")
    for table in ("simulate", "run"):
        before, after = old.get(table, {}), new.get(table, {})
        for name in list(before) + [n for n in after if n not in before]:
            if before.get(name) != after.get(name):
                changes.append(f"[{table}] {name}: {_list_text(before.get(name))} -> {_list_text(after.get(name))}")
        if not changes and list(before) != list(after):
            changes.append(f"[{table}] the order of the options: {', '.join(before)} -> {', '.join(after)}")
    return changes


def _list_text(values: Optional[list]) -> str:
    return "(none)" if values is None else "[" + ", ".join(_toml(v) for v in values) + "]"


def spec_hash(normalized: Mapping) -> str:
    """SHA-256 of the normalized spec's canonical JSON."""
    return hashlib.sha256(json.dumps(normalized, sort_keys=True).encode()).hexdigest()


# --------------------------------------------------------------------------------------------
# Cells


@dataclass(frozen=True)
class Cell:
    """One run of a sweep: small and picklable, so it travels to any worker.

    Attributes
    ----------
    index : position in the sweep's cell order (configurations in spec order, worlds inside).
    params : (column, value) for every parameter column of the spec.
    seed : the simulated world's seed, or None for a dataset file.
    path : the dataset file to read (absolute), or None for a simulated world.
    simulate, run : (command-line name, value) of the simulate and run options.
    """

    index: int
    params: tuple[tuple[str, Scalar], ...]
    seed: Optional[int]
    path: Optional[str]
    simulate: tuple[tuple[str, Scalar], ...]
    run: tuple[tuple[str, Scalar], ...]

    @property
    def key(self) -> tuple[str, ...]:
        """The parameters as ``runs.csv`` writes them: a row's identity, wherever it ran."""
        return tuple(format_value(value) for _, value in self.params)


def expand(spec: SweepSpec) -> list[Cell]:
    """Every cell of the spec, in cell order: simulate options, then run options, then the world."""
    worlds = [(seed, None, seed) for seed in spec.seeds] or [
        (None, str(Path(spec.base_dir, name).resolve()), name) for name in spec.datasets
    ]
    cells = []
    for simulate, run in itertools.product(_product(spec.simulate), _product(spec.run)):
        for seed, path, world in worlds:
            params = ((spec.world_column, world), *simulate.items(), *run.items())
            cells.append(Cell(len(cells), params, seed, path, tuple(simulate.items()), tuple(run.items())))
    return cells


def run_cell(cell: Cell) -> dict[str, Any]:
    """Make the cell's world, localize it and score it: its ``RESULT_COLUMNS`` as Python values,
    and ``warnings``, the text of the warnings its run raised (not written to ``runs.csv``).

    Any error of the run (a file that does not read, a filter that fails) becomes a row with
    status ``failed`` and the error's one-line text; only interruptions propagate. ``seconds`` is
    the cell's own wall time (world, localization, metrics) in the process that ran it.
    """
    import warnings

    started = time.perf_counter()
    noted: list[str] = []
    try:
        # the reader's warnings go back with the row (a worker's own stderr would print them as
        # Python warnings, with a source line, once per cell); run_sweep gathers them
        from camloc.g2o import G2oWarning

        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", G2oWarning)
            metrics = _localize_and_score(cell)
        noted = [str(w.message) for w in caught if issubclass(w.category, G2oWarning)]
        for w in caught:  # anything else (a library's) as it would have been shown
            if not issubclass(w.category, G2oWarning):
                warnings.showwarning(w.message, w.category, w.filename, w.lineno)
        row = {"status": "ok", "error": "", **headline_metrics(metrics)}
        if row["ate_rmse"] is not None and not math.isfinite(row["ate_rmse"]):
            row.update(status="failed", error=f"the estimate diverged (ate_rmse {row['ate_rmse']})")
    except Exception as error:  # noqa: BLE001 (a cell's failure is its row; the sweep goes on)
        message = str(error) if isinstance(error, CamlocError) else f"{type(error).__name__}: {error}"
        row = {"status": "failed", "error": " ".join(message.split()), **dict.fromkeys(METRIC_COLUMNS)}
    row["seconds"] = time.perf_counter() - started
    row["warnings"] = noted
    return row


def _localize_and_score(cell: Cell) -> dict:
    import camloc
    from camloc.metrics import evaluate
    from camloc.config import run_config
    from camloc.simulate_planar import simulate_world, world_config

    if cell.path is not None:
        dataset = camloc.load(cell.path)
    else:  # robot = "planar" in [simulate]: a planar world, tag-sigma-deg: tags (camloc.simulate_planar.world_config)
        dataset = simulate_world(world_config(dict(cell.simulate)), seed=cell.seed)
    # parallel=False: the sweep already fills the cores (and a Dask worker's daemonic process may
    # not start one); the result is the same either way.
    result = camloc.localize(dataset, run_config(applicable(dict(cell.run))), parallel=False)
    return evaluate(result)


def headline_metrics(metrics: Mapping) -> dict[str, Optional[float]]:
    """The ``METRIC_COLUMNS`` of ``camloc.metrics.evaluate``'s dict (None without ground truth)."""
    estimate = metrics.get("estimate") or {}
    association = metrics.get("association") or {}
    get = lambda table, *keys: _dig(table, keys)  # noqa: E731
    return {
        "ate_rmse": get(estimate, "ate", "rmse"),
        "rotation_rmse_deg": get(estimate, "rotation", "rmse_deg"),
        "rpe": get(estimate, "rpe", "translation", "rmse"),
        "precision": association.get("precision"),
        "recall": association.get("recall"),
        "nees_mean": get(metrics.get("nees") or {}, "mean"),
    }


def _dig(table: Mapping, keys: tuple[str, ...]) -> Optional[float]:
    for key in keys:
        if not isinstance(table, Mapping) or table.get(key) is None:
            return None
        table = table[key]
    return float(table)


# --------------------------------------------------------------------------------------------
# Rows, as runs.csv holds them


def format_value(value: Any) -> str:
    """A CSV cell: booleans as TOML writes them, floats in full precision, None empty."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    return str(value)


def format_result(result: Mapping[str, Any]) -> dict[str, str]:
    """``run_cell``'s result as the text ``runs.csv`` holds."""
    return {column: format_value(result.get(column)) for column in RESULT_COLUMNS}


def runs_text(spec: SweepSpec, cells: list[Cell], results: Mapping[tuple[str, ...], Mapping[str, str]]) -> str:
    """``runs.csv``: the header, then a row per cell that has a result, in cell order."""
    rows = [(*cell.key, *(results[cell.key][c] for c in RESULT_COLUMNS)) for cell in cells if cell.key in results]
    return _csv_text((*spec.columns, *RESULT_COLUMNS), rows)


def _csv_text(header: Iterable[str], rows: Iterable[Iterable[str]]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buffer.getvalue()


def read_runs(path: str | Path, spec: SweepSpec, cells: list[Cell]) -> dict[tuple[str, ...], dict[str, str]]:
    """The results recorded in a ``runs.csv`` of this spec, by cell key.

    Raises
    ------
    CamlocError : ``path:line: ...`` for a header that is not this spec's, or a row that is no
        cell of it (the file was edited).
    """
    path = Path(path)
    expected = [*spec.columns, *RESULT_COLUMNS]
    keys = {cell.key for cell in cells}
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as error:
        raise CamlocError(f"{path}: cannot read ({error})") from None
    reader = csv.reader(lines)
    header = next(reader, [])
    if header != expected:
        raise CamlocError(f"{path}:1: expected the columns {','.join(expected)}, found {','.join(header)}")
    results = {}
    for number, row in enumerate(reader, start=2):
        key = tuple(row[: len(spec.columns)])
        if len(row) != len(expected) or key not in keys:
            raise CamlocError(f"{path}:{number}: not a row of this sweep's cells: {','.join(row)}")
        results[key] = dict(zip(RESULT_COLUMNS, row[len(spec.columns):]))
    return results


# --------------------------------------------------------------------------------------------
# The summary


SUMMARY_COLUMNS = ("runs", "failures", "ate_rmse_median", "ate_rmse_mean", "ate_rmse_p90", "ate_rmse_worst",
                   "oracle_ratio_median", "oracle_ratio_worst", "seconds_mean")


def summarize(spec: SweepSpec, cells: list[Cell], results: Mapping[tuple[str, ...], Mapping[str, str]]) -> list[dict[str, Any]]:
    """One row per configuration (every parameter but the world) that has a result, in cell order.

    Each row: the configuration's parameters (Python values), ``runs`` (rows so far), ``failures``,
    ``ate_rmse`` median, mean, 90th percentile and worst over its successful runs, and, where the
    sweep's ``association`` has ``oracle``, the ratio of each world's ``ate_rmse`` to the oracle's
    on the same world with the same other parameters (median and worst; None for the oracle
    itself). Statistics of no value are None.
    """
    configs: dict[tuple, list[Cell]] = {}
    for cell in cells:
        if cell.key in results:
            configs.setdefault(cell.key[1:], []).append(cell)
    ate = {cell.key: _number(results[cell.key]["ate_rmse"]) for group in configs.values() for cell in group
           if results[cell.key]["status"] == "ok"}
    rows = []
    for group in configs.values():
        values = [ate[c.key] for c in group if ate.get(c.key) is not None]
        ratios = _oracle_ratios(spec, group, ate)
        seconds = [_number(results[c.key]["seconds"]) for c in group]
        rows.append({
            **dict(group[0].params[1:]),
            "runs": len(group),
            "failures": sum(results[c.key]["status"] != "ok" for c in group),
            "ate_rmse_median": _stat(values, 50), "ate_rmse_mean": _mean(values),
            "ate_rmse_p90": _stat(values, 90), "ate_rmse_worst": max(values, default=None),
            "oracle_ratio_median": _stat(ratios, 50), "oracle_ratio_worst": max(ratios, default=None),
            "seconds_mean": _mean([s for s in seconds if s is not None]),
        })
    return rows


def _oracle_ratios(spec: SweepSpec, group: list[Cell], ate: Mapping[tuple, Optional[float]]) -> list[float]:
    """Each world's ate_rmse over the oracle's on the same world and other parameters."""
    if ORACLE not in dict(spec.run).get("association", ()):
        return []
    column = spec.columns.index("association")
    ratios = []
    for cell in group:
        if cell.key[column] == ORACLE:
            continue
        twin = (*cell.key[:column], ORACLE, *cell.key[column + 1:])
        if ate.get(cell.key) is not None and ate.get(twin):
            ratios.append(ate[cell.key] / ate[twin])
    return ratios


def _number(text: str) -> Optional[float]:
    return float(text) if text not in ("", None) else None


def _stat(values: list[float], percent: float) -> Optional[float]:
    import numpy as np

    return float(np.percentile(values, percent)) if values else None


def _mean(values: list[float]) -> Optional[float]:
    return sum(values) / len(values) if values else None


def summary_text(spec: SweepSpec, summary: list[Mapping[str, Any]]) -> str:
    """``summary.csv``: the configuration's parameters, then ``SUMMARY_COLUMNS``."""
    header = (*spec.config_columns, *SUMMARY_COLUMNS)
    return _csv_text(header, ([format_value(row[c]) for c in header] for row in summary))


# --------------------------------------------------------------------------------------------
# The sweep folder


def prepare_folder(out_dir: str | Path, spec: SweepSpec, cells: list[Cell]) -> dict[tuple[str, ...], dict[str, str]]:
    """Make ``out_dir`` a folder of this spec and return the results it already holds.

    A new or empty folder gets ``spec.json``; a folder of the same spec keeps its rows (resume).

    Raises
    ------
    CamlocError : the folder holds another spec (the message says what changed), or files that
        are not a sweep's, or is not a folder.
    """
    from camloc.results import write_json_atomic

    out_dir = Path(out_dir)
    spec_path = out_dir / SPEC_FILE
    normalized = spec.normalized()
    if out_dir.exists() and not out_dir.is_dir():
        raise CamlocError(f"{out_dir}: exists and is not a folder")
    if spec_path.is_file():
        recorded = _read_recorded_spec(spec_path)
        if recorded != normalized:
            changes = "; ".join(spec_changes(recorded, normalized)) or "the spec differs"
            raise CamlocError(f"{out_dir} holds a sweep of another spec ({changes}); "
                              "run the recorded spec again to resume, or write into another folder")
        runs_path = out_dir / RUNS_FILE
        return read_runs(runs_path, spec, cells) if runs_path.is_file() else {}
    if out_dir.is_dir() and any(out_dir.iterdir()):
        raise CamlocError(f"{out_dir}: not empty and not a sweep folder (no {SPEC_FILE}); choose another folder")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise CamlocError(f"cannot create {out_dir}: {error.strerror or error}") from None
    write_json_atomic(spec_path, {"spec": normalized, "sha256": spec_hash(normalized)})
    return {}


def _read_recorded_spec(path: Path) -> dict:
    try:
        return json.loads(path.read_text(encoding="utf-8"))["spec"]
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise CamlocError(f"{path}: not a sweep's spec record ({error})") from None


def load_folder(out_dir: str | Path) -> tuple[SweepSpec, list[Cell], dict[tuple[str, ...], dict[str, str]]]:
    """The spec, cells and results of a sweep folder (for ``camloc plot``)."""
    out_dir = Path(out_dir)
    spec = SweepSpec.from_normalized(_read_recorded_spec(out_dir / SPEC_FILE))
    cells = expand(spec)
    runs_path = out_dir / RUNS_FILE
    return spec, cells, read_runs(runs_path, spec, cells) if runs_path.is_file() else {}


def is_sweep_folder(path: str | Path) -> bool:
    """True when ``path`` is a folder with a sweep's ``spec.json``."""
    return (Path(path) / SPEC_FILE).is_file()


def write_tables(out_dir: str | Path, spec: SweepSpec, cells: list[Cell], results: Mapping) -> list[dict[str, Any]]:
    """Rewrite ``runs.csv`` and ``summary.csv`` together (both or neither); returns the summary."""
    from camloc.atomic_files import write_files_atomic

    summary = summarize(spec, cells, results)
    texts = {Path(out_dir) / RUNS_FILE: runs_text(spec, cells, results),
             Path(out_dir) / SUMMARY_FILE: summary_text(spec, summary)}
    write_files_atomic(list(texts), lambda path, handle: handle.write(texts[path].encode("utf-8")))
    return summary


# --------------------------------------------------------------------------------------------
# Running


@dataclass(frozen=True)
class SweepOutcome:
    """What a sweep did: ``cells`` in all, ``resumed`` rows found in the folder, ``ran`` now,
    ``failed`` rows in all, the summary, the error of the first failed row in cell order
    (empty when none failed), and the dataset reader's warnings of the runs made now, each once."""

    folder: str
    cells: int
    resumed: int
    ran: int
    failed: int
    summary: list[dict[str, Any]]
    first_error: str = ""
    warnings: list[str] = field(default_factory=list)


RowCallback = Callable[[int, int, Mapping[str, str]], None]


def run_sweep(
    spec: SweepSpec,
    out_dir: str | Path,
    *,
    workers: Optional[int] = None,
    scheduler: Optional[str] = None,
    on_row: Optional[RowCallback] = None,
) -> SweepOutcome:
    """Run every cell of ``spec`` that ``out_dir`` has no row for, writing rows as they finish.

    Parameters
    ----------
    spec : the sweep.
    out_dir : the sweep folder (made if absent; see ``prepare_folder``).
    workers : local processes (default: the usable cores); not with ``scheduler``.
    scheduler : a Dask scheduler's address (``tcp://host:port``): run the cells there.
    on_row : called as ``on_row(done, total, result)`` after each finished cell (``done`` counts
        resumed rows too).

    An interruption (KeyboardInterrupt) or error still writes every finished row before it
    propagates; running the same spec into the same folder then runs only what is missing.
    """
    if scheduler is not None and workers is not None:
        raise ConfigError("--workers is for local runs: a Dask cluster has its own workers")
    client = connect_dask(scheduler) if scheduler is not None else None  # before the folder is made
    cells = expand(spec)
    try:
        results = prepare_folder(out_dir, spec, cells)
    except BaseException:
        if client is not None:
            client.close()
        raise
    resumed = len(results)
    todo = [cell for cell in cells if cell.key not in results]
    source = dask_results(todo, client) if client is not None else local_results(todo, workers)
    last_flush = time.monotonic()
    noted: dict[str, None] = {}  # the runs' warnings, each once, in the order first met
    try:
        for cell, result in source:
            results[cell.key] = format_result(result)
            noted.update(dict.fromkeys(result.get("warnings", ())))
            if on_row is not None:
                on_row(len(results), len(cells), results[cell.key])
            if time.monotonic() - last_flush >= FLUSH_SECONDS:
                write_tables(out_dir, spec, cells, results)
                last_flush = time.monotonic()
    finally:
        source.close()  # stop the workers before the last write
        summary = write_tables(out_dir, spec, cells, results)
    failed = sum(r["status"] != "ok" for r in results.values())
    first_error = next((results[c.key]["error"] for c in cells if c.key in results and results[c.key]["status"] != "ok"), "")
    return SweepOutcome(str(out_dir), len(cells), resumed, len(results) - resumed, failed, summary, first_error, list(noted))


def default_workers() -> int:
    """The cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def warm_up() -> None:
    """Import what a cell needs, once per worker, so that no cell's ``seconds`` holds the imports."""
    for module in ("camloc.localizer", "camloc.metrics", "camloc.options", "camloc.simulate"):
        importlib.import_module(module)


def local_results(cells: list[Cell], workers: Optional[int]) -> Iterator[tuple[Cell, dict]]:
    """Run ``cells`` in ``workers`` spawned processes; yield (cell, result) as each finishes."""
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    if not cells:
        return
    workers = min(workers or default_workers(), len(cells))
    others = set(multiprocessing.active_children())  # a caller's own, never stopped here
    # spawn: a clean interpreter per worker, whatever threads this process runs (a progress bar).
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=warm_up)
    started: list = []
    try:
        # The workers are spawned by the submissions, and inherit SIGINT blocked from here: a
        # Ctrl-C (which a terminal sends to every process of the group) is the parent's alone.
        # Interrupted in their imports or inside the pool's queues, workers printed tracebacks,
        # and the pool's shutdown could then wait for ever (2 Ctrl-C in 10 hung, 2026-12-06).
        with _interrupts_held():
            futures = {pool.submit(run_cell, cell): cell for cell in cells}
            started = [child for child in multiprocessing.active_children() if child not in others]
        for future in as_completed(futures):
            try:
                result = future.result()
            except BrokenProcessPool:
                raise CamlocError("a worker process died (out of memory?); the finished rows are kept, "
                                  "run the same command again to go on") from None
            yield futures[future], result
    except BaseException:
        # Interrupted, or stopped by the caller: the running cells' rows would not be kept, so
        # their workers are stopped rather than waited for; pending cells are dropped.
        _forget_manager(pool)
        pool.shutdown(wait=False, cancel_futures=True)
        _stop(started)
        raise
    pool.shutdown(wait=True)


def _forget_manager(pool) -> None:
    """Take the pool's manager thread out of the table ``concurrent.futures`` wakes at the
    interpreter's exit, before the pool is shut down without waiting. That wake-up (Python 3.11's
    ``_python_exit``) writes to the thread's pipe outside the pool's lock, and raced the thread
    closing it as it ended: a Ctrl-C 1.5 s into a sweep printed "Exception ignored ... OSError: Bad
    file descriptor" with its traceback at exit (CI, 2 runs in 6, 2026-12-06/07). The pool's own
    ``shutdown`` wakes the thread under the lock it closes the pipe under; the thread is not a
    daemon, so the exit still waits for it, and it ends once the stopped workers' sentinels fire.
    (Read before ``shutdown``: ``shutdown(wait=False)`` drops the pool's reference to it.)"""
    from concurrent.futures import process

    manager = getattr(pool, "_executor_manager_thread", None)
    if manager is not None:
        getattr(process, "_threads_wakeups", {}).pop(manager, None)


@contextlib.contextmanager
def _interrupts_held() -> Iterator[None]:
    """SIGINT blocked in this thread (and in the processes and threads it starts, which inherit
    the mask), then unblocked: a Ctrl-C that came meanwhile is raised here on the way out."""
    if os.name != "posix":
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _stop(processes: list) -> None:
    """Terminate the pool's worker ``processes`` and wait for them."""
    for process in processes:
        process.terminate()
    for process in processes:
        process.join()


def dask_results(cells: list[Cell], client) -> Iterator[tuple[Cell, dict]]:
    """Run ``cells`` through a ``distributed.Client`` (``connect_dask``), which this closes when
    done; yield (cell, result) as each finishes."""
    futures = []
    try:
        client.run(warm_up)
        futures = client.map(run_cell, cells, pure=False)
        cell_of = dict(zip((f.key for f in futures), cells))
        from distributed import as_completed

        for future in as_completed(futures):
            try:
                result = future.result()
            except Exception as error:  # noqa: BLE001 (run_cell keeps a run's own errors: this is the cluster's)
                raise CamlocError(f"the Dask cluster could not run a cell ({type(error).__name__}: {error}); "
                                  "the finished rows are kept, run the same command again to go on") from None
            yield cell_of[future.key], result
    finally:
        if futures:
            client.cancel(futures)
        client.close()


def connect_dask(address: str, *, timeout: float = 10.0):
    """A ``distributed.Client`` of the scheduler at ``address``.

    Raises
    ------
    ConfigError : dask.distributed is not installed, or the scheduler cannot be reached.
    """
    try:
        from distributed import Client
    except ImportError:
        raise ConfigError('--scheduler needs dask.distributed, which is not installed: pip install -e ".[dask]"') from None
    try:
        return Client(address, timeout=timeout)
    except (OSError, TimeoutError, ValueError) as error:
        raise ConfigError(f"cannot reach the Dask scheduler at {address}: {error}") from None


def ate_groups(spec: SweepSpec, cells: list[Cell], results: Mapping) -> list[tuple[str, Optional[str], list[float]]]:
    """``ate_rmse`` of the successful runs per configuration, for a distribution plot.

    Returns (label, association or None, values) per configuration in cell order, except that the
    oracle comes first among the configurations that differ only in their association; labels
    name the parameters that vary between configurations.
    """
    values: dict[tuple, list[float]] = {}
    params: dict[tuple, dict[str, Scalar]] = {}
    for cell in cells:
        config = cell.key[1:]
        params[config] = dict(cell.params[1:])
        result = results.get(cell.key)
        ok = result is not None and result["status"] == "ok" and result["ate_rmse"] != ""
        values.setdefault(config, []).extend([float(result["ate_rmse"])] if ok else [])
    # The context of a configuration is all of it but the association; contexts in cell order.
    context = {config: tuple(v for c, v in p.items() if c != "association") for config, p in params.items()}
    first = {}
    for config in values:
        first.setdefault(context[config], len(first))
    order = sorted(values, key=lambda c: (first[context[c]], params[c].get("association") != ORACLE))
    varying = [c for c in spec.config_columns if len({format_value(p[c]) for p in params.values()}) > 1]
    return [("\n".join(f"{c}={format_value(params[k][c])}" for c in varying) or "all runs",
             params[k].get("association"), values[k]) for k in order]
