"""Rich rendering of a dataset summary (``camloc.dataset_summary.summarize_dataset``)."""

from __future__ import annotations

from typing import Any, Mapping, Sequence

from rich.console import Group
from rich.markup import escape
from rich.table import Table
from rich.text import Text


def _fmt(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def _triple(values: Sequence[float] | None, spec: str) -> str:
    return "-" if values is None else "  ".join(format(value, spec) for value in values)


def _ids(ids: Sequence[int], limit: int = 12) -> str:
    shown = ", ".join(map(str, ids[:limit]))
    return shown + (f", ... ({len(ids) - limit} more)" if len(ids) > limit else "")


def render_dataset_summary(summary: Mapping[str, Any]) -> Group:
    """Tables for the counts, the cameras and the dataset's statistics, then the warnings."""
    title = Text.assemble(("camloc info: ", "bold"), str(summary["dataset"]))
    # a planar robot may carry no camera: its table would be empty
    cameras = [_cameras_table(summary["cameras"])] if summary["cameras"] or summary.get("robot") != "planar" else []
    return Group(title, _records_table(summary), *cameras, _statistics_table(summary),
                 *_warning_lines(summary["warnings"]))


def _records_table(summary: Mapping[str, Any]) -> Table:
    table = Table(title="records", title_justify="left")
    table.add_column("tag")
    table.add_column("count", justify="right")
    unknown = set(summary["unknown_tags"])
    if unknown:
        table.add_column("")
    for tag, count in summary["tag_counts"].items():
        note = ["[yellow]unknown, skipped[/]" if tag in unknown else ""] if unknown else []
        table.add_row(escape(tag), str(count), *note)
    return table


def _cameras_table(cameras: Sequence[Mapping[str, Any]]) -> Table:
    table = Table(title="cameras (mount in the robot frame)", title_justify="left")
    for name in ("id", "translation [m]", "roll pitch yaw [deg]", "fx", "fy", "cx", "cy"):
        table.add_column(escape(name), justify="right")
    for camera in cameras:
        table.add_row(str(camera["id"]), _triple(camera["translation_m"], ".3f"),
                      _triple(camera["rotation_rpy_deg"], ".1f"),
                      *(format(camera[key], ".4g") for key in ("fx", "fy", "cx", "cy")))
    return table


def _statistics_table(summary: Mapping[str, Any]) -> Table:
    counts, trajectory = summary["counts"], summary["trajectory"]
    odometry, observation = summary["odometry_noise"], summary["observation_noise"]
    per_pose = summary["observations_per_pose"]
    never, unmapped = summary["landmarks_never_observed"], summary["unmapped_observations"]
    source = "ground truth" if trajectory["source"] == "ground_truth" else "odometry from the start"
    table = Table(title="dataset", title_justify="left", show_header=False)
    table.add_column("", style="bold")
    table.add_column("")
    rows = [
        ("robot", "planar (VERTEX_SE2, EDGE_SE2; stored at z = 0)" if summary.get("robot") == "planar" else "3-D"),
        ("poses / odometry edges", f"{counts['poses']} / {counts['odometry_edges']}"),
        ("landmarks / observations", f"{counts['landmarks']} / {counts['observations']}"),
        ("trajectory length [m]", f"{trajectory['length_m']:.2f} ({source})"),
        ("extent x y z [m]", "  ".join(f"{low:.2f}..{high:.2f}" for low, high
                                       in zip(trajectory["extent_min_m"], trajectory["extent_max_m"]))),
        ("odometry sigma translation [m]", _triple(odometry["sigma_translation_m"], ".4g")),
        ("odometry sigma rotation [deg]", _triple(odometry["sigma_rotation_deg"], ".4g")),
        # a planar kind's (point2: x y; marker: x y psi) in the u, v, depth columns
        ("observation sigma u v depth" if summary.get("robot") != "planar" else "observation sigma u/x v/y depth", "  ".join(_fmt(observation[key], ".4g")
                                                  for key in ("sigma_u", "sigma_v", "sigma_depth"))),
        ("observations by kind", ", ".join(f"{count} {name}" for name, count in summary["observation_kinds"].items() if count)
                                 or "none"),
        ("observations per pose", f"min {per_pose['min']}, median {per_pose['median']:g}, max {per_pose['max']}; "
                                  f"{per_pose['poses_without']} pose(s) with none"),
        ("landmarks never observed", f"{never['count']}" + (f": {_ids(never['ids'])}" if never["count"] else "")),
        ("observations of unmapped ids", f"{unmapped['count']}"
                                         + (f" (ids {_ids(unmapped['ids'])})" if unmapped["count"] else "")),
    ]
    for name, value in rows:
        table.add_row(escape(name), escape(value))
    return table


def _warning_lines(messages: Sequence[str]) -> list[Text]:
    return [Text.assemble(("warning: ", "yellow"), message) for message in messages]
