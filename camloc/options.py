"""``camloc run``'s options by their command-line names, mapped onto ``LocalizerConfig`` in one place.

``camloc run`` and ``camloc sweep``'s ``[run]`` table both name the localizer's options as the
command line does (``gate``, ``beam-width``, ``max-angle``); this module is the only table from
those names to the config's fields, so a change of ``LocalizerConfig``'s layout is adapted here
alone.
"""

from __future__ import annotations

from typing import Any, Mapping, Optional

from camloc.errors import ConfigError

# command-line name (without "--") -> LocalizerConfig field. A flag pair such as
# --sequential/--batch is named by its first form and takes a boolean.
RUN_OPTIONS: dict[str, str] = {
    "filter": "filter",
    "association": "association",
    "iterations": "iterations",
    "gate": "gate_probability",
    "cost": "cost",
    "margin": "margin",
    "sequential": "sequential",
    "beam-width": "beam_width",
    "beam-delta": "beam_delta",
    "branch-delta": "branch_delta",
    "null-cost": "null_cost",
    "slip-inflation": "slip_inflation",
    "slip-cost": "slip_cost",
    "recheck": "recheck",
    "recheck-margin": "recheck_margin",
    "recheck-steal-margin": "recheck_steal_margin",
    "jcbb-max-nodes": "jcbb_max_nodes",
    "min-depth": "min_depth",
    "max-depth": "max_depth",
    "max-angle": "max_angle_deg",
    "initial-sigma-xyz": "initial_sigma_xyz",
    "initial-sigma-deg": "initial_sigma_deg",
}

# The second form of a flag pair -> the name it negates (for a clearer error than "unknown").
NEGATED_FLAGS = {"batch": "sequential", "no-recheck": "recheck"}


def localizer_overrides(options: Mapping[str, Any]) -> dict[str, Any]:
    """``LocalizerConfig`` field values of run options named as on the command line.

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


def run_config(options: Mapping[str, Any], file_values: Optional[Mapping[str, Any]] = None):
    """The validated ``LocalizerConfig`` of run options by command-line name, over ``file_values``
    (a ``--config`` file's values, by field name). Raises ConfigError for a bad name or value."""
    from camloc.config import make_config

    return make_config(file_values, localizer_overrides(options))


def _hint(name: str) -> str:
    if name in NEGATED_FLAGS:
        return f"{name} (write {NEGATED_FLAGS[name]} = false)"
    return name
