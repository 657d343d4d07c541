"""The localizer's options by the names users write, mapped onto ``LocalizerConfig`` in one place.

``camloc run``'s flags, ``camloc sweep``'s ``[run]`` table and ``--config`` files name the
options the same way: the top-level ones by their flag (``gate = 0.95`` <-> ``--gate 0.95``), a
group's by its table and the flag without the group's prefix (``[beam] width = 8`` <->
``--beam-width 8``, ``[recheck] steal-margin`` <-> ``--recheck-steal-margin``, ``[view]
max-angle`` <-> ``--max-angle``). ``RUN_OPTIONS`` is the only table from those names to the
config's fields, so a change of ``LocalizerConfig``'s layout is adapted here alone.
"""

from __future__ import annotations

from typing import Any, Mapping

from camloc.errors import ConfigError

# command-line name (without "--") -> option path in LocalizerConfig (group.field). A flag pair
# such as --sequential/--batch is named by its first form and takes a boolean.
RUN_OPTIONS: dict[str, str] = {
    "filter": "filter",
    "association": "association",
    "iterations": "iterations",
    "gate": "gate",
    "null-cost": "null_cost",
    "map": "map",
    "map-sigma": "map_sigma",
    "initial-sigma-xyz": "initial_sigma_xyz",
    "initial-sigma-deg": "initial_sigma_deg",
    "beam-width": "beam.width",
    "beam-delta": "beam.delta",
    "branch-delta": "beam.branch_delta",
    "slip-inflation": "beam.slip_inflation",
    "slip-cost": "beam.slip_cost",
    "cost": "best_friends.cost",
    "margin": "best_friends.margin",
    "sequential": "best_friends.sequential",
    "jcbb-max-nodes": "jcbb.max_nodes",
    "recheck": "recheck.enabled",
    "recheck-margin": "recheck.margin",
    "recheck-steal-margin": "recheck.steal_margin",
    "recheck-ray-margin": "recheck.ray_margin",
    "min-depth": "view.min_depth",
    "max-depth": "view.max_depth",
    "max-angle": "view.max_angle_deg",
    "max-distance": "view.max_distance",
}

FLAG_OF_PATH = {path: flag for flag, path in RUN_OPTIONS.items()}

# The second form of a flag pair -> the name it negates (for a clearer error than "unknown").
NEGATED_FLAGS = {"batch": "sequential", "no-recheck": "recheck"}

# A config file's key for an option that has no name left once its group's prefix is taken off.
_BARE_KEYS = {"recheck.enabled": "enabled"}


def table_of(path: str) -> str:
    """The config file's table of option ``path``: ``""`` (top level), ``"beam"``, ``"best-friends"``."""
    group, _, _ = path.rpartition(".")
    return group.replace("_", "-")


def key_of(path: str) -> str:
    """The config file's key of option ``path`` in its table: its flag without the table's prefix
    (``beam.width`` -> ``width``, ``view.max_angle_deg`` -> ``max-angle``)."""
    if path in _BARE_KEYS:
        return _BARE_KEYS[path]
    return FLAG_OF_PATH[path].removeprefix(f"{table_of(path)}-") if table_of(path) else FLAG_OF_PATH[path]


def file_name(path: str) -> str:
    """Option ``path`` as a config file writes it: ``gate``, ``[beam] width``."""
    return f"[{table_of(path)}] {key_of(path)}" if table_of(path) else key_of(path)


def accepted_keys(path: str) -> tuple[str, ...]:
    """The keys a config file may name option ``path`` by in its table: its key with dashes or
    underscores, and its field's name (what ``summary.json`` records: ``max_angle_deg``)."""
    key, name = key_of(path), path.rpartition(".")[2]
    return tuple(dict.fromkeys((key, key.replace("-", "_"), name, name.replace("_", "-"))))


def localizer_overrides(options: Mapping[str, Any]) -> dict[str, Any]:
    """``LocalizerConfig`` option values (by path, ``"beam.width"``) of run options named as on
    the command line.

    Parameters
    ----------
    options : command-line name (``"gate"``, ``"beam-width"``) -> value; None means not given
        and is dropped.

    Raises
    ------
    ConfigError : a name that is not an option of ``camloc run``.
    """
    unknown = [name for name in options if name not in RUN_OPTIONS]
    if unknown:
        raise ConfigError(f"unknown run option(s) {', '.join(map(_hint, unknown))}; expected some of {', '.join(RUN_OPTIONS)}")
    return {RUN_OPTIONS[name]: value for name, value in options.items() if value is not None}


def _hint(name: str) -> str:
    if name in NEGATED_FLAGS:
        return f"{name} (write {NEGATED_FLAGS[name]} = false)"
    return name
