"""Worlds whose map is imperfect: landmarks withheld from the map, landmarks moved, or no map.

A world is simulated whole (``camloc.simulate``, ``camloc.simulate_planar``, ``camloc.simulate_tags``:
every landmark in the map, every detection of a landmark's true position); ``edit_map`` then makes
the map written to the file differ from the truth, as a real map does (a partial survey, furniture
moved since, no survey at all):

- **withheld**: a random ``withhold_map`` share of the landmarks is left out of the file's map.
  Their detections stay, with their true ids: a reader sees observations of ids absent from the
  map, as it sees clutter (``camloc.g2o``), and only the true map tells the two apart.
- **moved**: a random ``move_map`` share of the landmarks (none of the withheld ones) is written
  ``move_distance`` metres from its true position, in a random direction (uniform on the sphere;
  in the floor's plane for a planar landmark). The detections are of the true positions. A moved
  **tag** is also turned, by ``move_distance`` read as radians about a random axis (uniform on the
  sphere): a tag put back by hand is rarely put back at its old orientation, and the angle is the
  distance's number as ``--map-sigma`` holds a tag's orientation to its number in radians (0.3 m and
  0.3 rad: three sigmas of a 0.1 prior each). A marker's heading is kept.
- **no map**: no landmark is written at all (``no_map``).

The edit draws from its own stream (``np.random.default_rng([seed, MAP_STREAM])``), so a world with
an edited map has exactly the path, map, odometry and detections of the same seed without one.
``MapEdits.whole`` keeps the world with its true, complete map: the evaluator's ``--true-map``.

Pure: no I/O.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from camloc import geometry
from camloc.dataset import LANDMARK_MARKER, LANDMARK_POINT2, LANDMARK_POINT3, LANDMARK_TAG, Dataset, on_the_floor
from camloc.g2o import TAG_LANDMARK, TAG_LANDMARK_XY, TAG_MARKER, TAG_TAG

# The configs' fields that edit the map (``camloc.simulate.SimulationConfig`` and
# ``camloc.simulate_planar.PlanarSimulationConfig`` both have them).
MAP_EDIT_FIELDS = ("withhold_map", "move_map", "move_distance", "no_map")
DEFAULT_MOVE_DISTANCE_M = 0.3  # issue 38's "a quarter of the map moved by 0.3 m"
# The second entropy word of the edit's generator: issue 38 (the other streams are spawned children).
MAP_STREAM = 38
# The record each kind of landmark is written as (``camloc.g2o``), to keep ``Dataset.tag_counts`` true.
_LANDMARK_TAGS = {LANDMARK_POINT3: TAG_LANDMARK, LANDMARK_POINT2: TAG_LANDMARK_XY, LANDMARK_MARKER: TAG_MARKER,
                  LANDMARK_TAG: TAG_TAG}


@dataclass(frozen=True)
class MapEdits:
    """A world whose file map differs from the truth.

    Attributes
    ----------
    dataset : the world as written: its map edited, its observations those of ``whole``.
    whole : the same world with its true, complete map.
    withheld : (W,) int64 ids of the landmarks left out of ``dataset``'s map.
    moved : (M,) int64 ids of the landmarks written away from their true position (a tag also turned).
    move_distance : how far, metres (and how far a moved tag is turned, radians).
    """

    dataset: Dataset
    whole: Dataset
    withheld: np.ndarray
    moved: np.ndarray
    move_distance: float


def map_edit_problem(withhold_map: float, move_map: float, move_distance: float, no_map: bool,
                     max_distance: float) -> tuple[str, str, Any] | None:
    """The first (field, expected, found) these settings break, None when they are valid."""
    for name, value in (("withhold_map", withhold_map), ("move_map", move_map)):
        if not 0.0 <= value <= 1.0:
            return name, "a fraction in [0, 1]", value
    if withhold_map + move_map > 1.0 + 1e-12:
        return "move_map", f"at most 1 - withhold_map = {1.0 - withhold_map:g} (a withheld landmark cannot be moved)", move_map
    if not 0.0 < move_distance <= max_distance:
        return "move_distance", f"a distance in (0, {max_distance:g}] m", move_distance
    if no_map and (withhold_map > 0.0 or move_map > 0.0):
        return "no_map", "no map, or a map with landmarks withheld or moved, not both", f"no_map with withhold_map={withhold_map}, move_map={move_map}"
    return None


def edits_map(config: Any) -> bool:
    """Whether ``config`` (a simulation config with ``MAP_EDIT_FIELDS``) asks for an imperfect map."""
    return bool(config.no_map or config.withhold_map > 0.0 or config.move_map > 0.0)


def without_map_edits(config: Any) -> Any:
    """``config`` with a perfect map (the whole world ``edit_map`` starts from)."""
    return dataclasses.replace(config, withhold_map=0.0, move_map=0.0, no_map=False)


def edit_map(whole: Dataset, config: Any, *, seed: int) -> MapEdits:
    """The world ``whole`` with its map withheld, moved or removed as ``config`` says (see the module).

    Parameters
    ----------
    whole : a simulated world with its complete, true map.
    config : its simulation config (``withhold_map``, ``move_map``, ``move_distance``, ``no_map``).
    seed : the world's seed; the edit draws from its own stream of it.
    """
    rng = np.random.default_rng([seed, MAP_STREAM])
    count = len(whole.landmark_ids)
    withheld_rows = np.arange(count) if config.no_map else _pick(rng, np.arange(count), config.withhold_map * count)
    kept = np.setdiff1d(np.arange(count), withheld_rows)
    moved_rows = _pick(rng, kept, config.move_map * count)
    xyz = whole.landmark_xyz.copy()
    planar = on_the_floor(whole.landmark_kind[moved_rows])
    xyz[moved_rows] += config.move_distance * random_directions(rng, planar)
    quat = _turned_tags(rng, whole.landmark_quat_xyzw, moved_rows, config.move_distance)
    dataset = dataclasses.replace(
        whole, source=_described(whole.source, config),
        landmark_ids=whole.landmark_ids[kept], landmark_xyz=xyz[kept], landmark_kind=whole.landmark_kind[kept],
        landmark_heading=whole.landmark_heading[kept], landmark_quat_xyzw=quat[kept],
        tag_counts=_landmark_counts(whole.tag_counts, whole.landmark_kind[kept]),
    )
    return MapEdits(dataset, whole, np.sort(whole.landmark_ids[withheld_rows]), np.sort(whole.landmark_ids[moved_rows]),
                    float(config.move_distance))


def _turned_tags(rng: np.random.Generator, quat_xyzw: np.ndarray, moved_rows: np.ndarray, angle: float) -> np.ndarray:
    """The map's orientations (L, 4) with the moved tags (of ``moved_rows``) turned by ``angle``
    radians about random axes (drawn only where a moved landmark is a tag: other worlds' edits
    stay the same draws)."""
    tags = moved_rows[np.isfinite(quat_xyzw[moved_rows, 0])]
    if tags.size == 0:
        return quat_xyzw
    axes = random_directions(rng, np.zeros(tags.size, bool))
    out = quat_xyzw.copy()
    out[tags] = geometry.matrix_to_quat(geometry.so3_exp(angle * axes) @ geometry.quat_to_matrix(quat_xyzw[tags]))
    return out


def _described(source: str, config: Any) -> str:
    """A simulated world's description (``simulate(..., seed=3)``) naming the map's edits, as
    ``camloc.simulate.describe`` names every option that differs from its default."""
    defaults = {"withhold_map": 0.0, "move_map": 0.0, "move_distance": DEFAULT_MOVE_DISTANCE_M, "no_map": False}
    edits = ", ".join(f"{name}={getattr(config, name)}" for name in MAP_EDIT_FIELDS if getattr(config, name) != defaults[name])
    if not edits or edits in source:
        return source
    return source.replace(", seed=", f", {edits}, seed=", 1) if ", seed=" in source else f"{source} ({edits})"


def _pick(rng: np.random.Generator, rows: np.ndarray, share: float) -> np.ndarray:
    """``round(share)`` of ``rows`` at random (all of them at most), sorted."""
    size = min(int(round(share)), len(rows))
    return np.sort(rng.choice(rows, size=size, replace=False)) if size else np.zeros(0, dtype=np.int64)


def random_directions(rng: np.random.Generator, planar: np.ndarray) -> np.ndarray:
    """(M, 3) unit vectors, uniform on the sphere, or on the circle of the floor (z = 0) where
    ``planar`` (M,) is True."""
    v = rng.standard_normal((len(planar), 3))
    v[planar, 2] = 0.0
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    # A draw of exactly zero has probability zero; guard the division all the same.
    return np.where(norm > 0.0, v / np.where(norm > 0.0, norm, 1.0), np.array([1.0, 0.0, 0.0]))


def _landmark_counts(tag_counts: dict[str, int], kinds: np.ndarray) -> dict[str, int]:
    """``tag_counts`` with each landmark record's count that of the kinds (K,) written."""
    counts = dict(tag_counts)
    for kind, tag in _LANDMARK_TAGS.items():
        if tag in counts:
            counts[tag] = int(np.count_nonzero(kinds == kind))
    return counts
