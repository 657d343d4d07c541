"""Rich rendering of a run's summary."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from rich.console import Group
from rich.markup import escape
from rich.table import Table
from rich.text import Text


def _get(tree: Mapping[str, Any], dotted: str, default: Any = None) -> Any:
    node: Any = tree
    for key in dotted.split("."):
        if not isinstance(node, Mapping) or key not in node:
            return default
        node = node[key]
    return node


def _fmt(value: Any, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def _smooth_hint(mapped: Mapping[str, Any], written: Path | None) -> str:
    """Where landmarks were estimated, the command that estimates them again with every sighting:
    the filter placed each from the sightings before it, and on the real file's variants the batch
    estimate is 20-30% closer (docs/mapping.md, "The batch estimate on the real file")."""
    if written is None:
        return ""
    sigma = f" --map-sigma {mapped['sigma']:g}" if mapped.get("sigma") is not None else ""
    return f"; 'camloc smooth {written} --map {mapped['mode']}{sigma}' estimates poses and map again with every sighting"


def render_run_summary(summary: Mapping[str, Any], written: Path | None) -> Group:
    """The end-of-run table: trajectory error of the filter (named by what ran: ``iterated EKF
    (euler)``, or ``odometry alone (no update)`` when it made no update) and of odometry alone,
    rotation error, associations and speed (the summary holds the metrics of ``camloc eval``
    under its keys)."""
    counts = summary["counts"]
    timing = summary["timing"]
    table = Table(title=f"camloc run: {escape(Path(str(summary['dataset'])).name)}", title_justify="left")
    table.add_column("", style="bold")
    label = escape
    table.add_column(escape(str(summary.get("estimate_name", "filter"))), justify="right")
    table.add_column("odometry only", justify="right")
    if summary.get("estimate") is not None:
        table.add_row(label("position RMSE [m]"), _fmt(_get(summary, "estimate.ate.rmse"), ".4f"), _fmt(_get(summary, "odometry.ate.rmse"), ".4f"))
        table.add_row(label("position max [m]"), _fmt(_get(summary, "estimate.ate.max"), ".4f"), _fmt(_get(summary, "odometry.ate.max"), ".4f"))
        # a planar robot's rotation is its heading
        rotation = "heading RMSE [deg]" if _get(summary, "config.filter") == "se2" else "rotation RMSE [deg]"
        table.add_row(label(rotation), _fmt(_get(summary, "estimate.rotation.rmse_deg"), ".2f"), _fmt(_get(summary, "odometry.rotation.rmse_deg"), ".2f"))
        table.add_row(f"NEES mean ({_get(summary, 'nees.dof') or 6} dof)", _fmt(_get(summary, "nees.mean"), ".2f"), "")
    else:
        table.add_row("trajectory error", "no ground truth", "")
    association = Table(title="associations", title_justify="left")
    for name in ("observations", "accepted", "correct", "wrong", "rejected", "precision", "recall"):
        association.add_column(name, justify="right")
    correct = _get(summary, "association.correct")
    wrong = _get(summary, "association.wrong")
    association.add_row(
        str(counts["observations"]), str(counts["accepted"]), _fmt(correct, "d"), _fmt(wrong, "d"), str(counts["rejected"]),
        _fmt(_get(summary, "association.precision"), ".3f"), _fmt(_get(summary, "association.recall"), ".3f"),
    )
    mapped = summary.get("map")
    map_line = None
    if isinstance(mapped, Mapping):
        map_line = Text(f"map {mapped['mode']}: {mapped['mapped_observed']} of {mapped['mapped']} mapped landmarks seen, "
                        f"{mapped['added']} added (map.csv)" + _smooth_hint(mapped, written))
    reach = _get(summary, "candidate_range.learned_reach")
    if reach is not None:
        reach_line = Text(f"the pixel cameras' reach, learned from the first poses: {reach:.2f} m (candidates within "
                          f"{_get(summary, 'candidate_range.max_depth'):.2f} m; --max-depth sets it)")
        map_line = reach_line if map_line is None else Text.assemble(map_line, "\n", reach_line)
    footer = Text(
        f"{counts['poses']} poses in {timing['filter_seconds']:.2f} s ({timing['poses_per_second']:.0f} poses/s)"
        + (f"; run folder: {written}" if written else "")
    )
    return Group(table, association, *([map_line] if map_line is not None else []), footer)
