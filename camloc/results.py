"""What a localization run produces (``RunResult``), and saving/loading it as a run folder.

A run folder holds:
- ``estimate.tum``, ``odometry.tum``, ``groundtruth.tum`` (when there is ground truth): TUM lines
  ``timestamp x y z qx qy qz qw`` with the pose id as timestamp;
- ``associations.csv``: ``pose,camera,u,v,depth,landmark,true_landmark,mahalanobis``, one row per
  observation, ``landmark`` and ``mahalanobis`` empty when the observation was rejected;
- ``states.npz``: per-pose filter state and covariance, pose covariance, NIS per update, the map
  (and its markers' and tags' headings, ``map_landmark_heading``);
- ``summary.json``: dataset, configuration, counts, timings and headline metrics;
- ``smoothed.tum`` (only after ``camloc smooth``): the smoother's poses, TUM like the others;
- ``map.csv`` (only after ``camloc smooth``): the smoother's map, a row per landmark
  (``MAP_HEADER``: position, covariance, ``mapped`` or ``added``, observations).

The TUM files are the run's trajectories: ``load_run`` reads the estimate, odometry and ground
truth from them (timestamps must be the run's pose ids), so that ``camloc eval`` and ``camloc
plot`` score and draw what is on disk, an edited or swapped trajectory included.
``states.npz`` holds the other arrays of ``RunResult`` (the associations' one home is
``associations.csv``, written with round-trip precision), plus ``dataset`` and
``format_version`` (2; version 1 also held copies of the poses, which are not read). ``save_run`` builds the folder in a hidden temporary sibling and renames it into place,
so a failure leaves nothing behind; an existing run folder is replaced only with ``force=True``,
and then keeps the files that are not camloc's (``CAMLOC_FILES``). The single-file helpers
(``write_json_atomic`` here, ``write_text_atomic`` and ``atomic_write`` of ``camloc.atomic_files``) give the same whole-or-nothing
guarantee to any other output, and ``atomic_files.write_files_atomic`` to a set of files (the figures of
``camloc plot``); ``write_smoothed`` adds ``smoothed.tum`` to an existing run folder that way,
and ``load_run`` reads it back into ``RunResult.smoothed_xyz`` / ``smoothed_quat_xyzw`` when it
is there. Every writer creates missing parent folders (``camloc.atomic_files``, the writers' home).

``load_run`` checks what it reads as it reads it, one function per file kind (``read_tum``,
``read_associations``, ``_check_states``, ``_read_summary``): types, shapes, finite values,
covariances, that the TUM files' timestamps are the run's pose ids and that the associations are
of the run's poses. A damaged folder is
then a ``DatasetError`` naming the file (and line), not a crash in the metrics or the plots.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import re
import shutil
import tempfile
import zipfile
import zlib
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from camloc import geometry
from camloc.atomic_files import make_folder, naming_the_output, refuse_existing, write_text_atomic
from camloc.errors import CamlocError, DatasetError
from camloc.g2o import INT64_RANGE, INTEGER, MAX_COORDINATE as MAX_INPUT_COORDINATE, parse_number

UNASSOCIATED = -1

ESTIMATE_TUM = "estimate.tum"
ODOMETRY_TUM = "odometry.tum"
GROUNDTRUTH_TUM = "groundtruth.tum"
ASSOCIATIONS_CSV = "associations.csv"
STATES_NPZ = "states.npz"
SUMMARY_JSON = "summary.json"
SMOOTHED_TUM = "smoothed.tum"
MAP_CSV = "map.csv"
MAP_HEADER = ("id", "x", "y", "z", "cxx", "cxy", "cxz", "cyy", "cyz", "czz", "origin", "observations")
# after MAP_HEADER where the map has tags: a tag's orientation (world) and its covariance (rad^2,
# the world rotation error e of R_true = Exp(e) R_tag), empty for a landmark that is not a tag
MAP_ORIENTATION_HEADER = ("qx", "qy", "qz", "qw", "crxx", "crxy", "crxz", "cryy", "cryz", "crzz")
ASSOCIATIONS_HEADER = ("pose", "camera", "u", "v", "depth", "landmark", "true_landmark", "mahalanobis")
TUM_FIELDS = ("timestamp", "x", "y", "z", "qx", "qy", "qz", "qw")
RUN_FORMAT_VERSION = 2
# A run's positions may leave its dataset's +-MAX_INPUT_COORDINATE (a start at 1e9 m plus the path
# from it, odometry steps of up to 1e9 m each), and a run folder camloc wrote must read back: its
# bound only keeps their squares, in the errors, far from overflowing.
MAX_RUN_COORDINATE = 1e6 * MAX_INPUT_COORDINATE
# Version 1 also stored the poses in states.npz; its folders load the same, those copies unread.
_READABLE_FORMAT_VERSIONS = (1, 2)
# What makes a folder a run folder: enough to load it back.
_REQUIRED_FILES = (STATES_NPZ, SUMMARY_JSON, ASSOCIATIONS_CSV)
# The figures 'camloc plot' draws into a run folder, fig-<name>.<format>.
FIGURE_NAMES = ("topdown", "3d", "errors", "consistency", "associations")
# fig-map, drawn beside them when the run folder has a map.csv (camloc.plotting_map)
MAP_FIGURE_NAME = "map"
FIGURE_FORMATS = ("png", "pdf", "svg")
# Every file camloc writes into a run folder; replacing a run (force=True) drops these, the
# derived ones included (a smoothed path or a figure of the old run would pass for the new one's),
# and keeps everything else.
CAMLOC_FILES = frozenset(
    (ESTIMATE_TUM, ODOMETRY_TUM, GROUNDTRUTH_TUM, ASSOCIATIONS_CSV, STATES_NPZ, SUMMARY_JSON, SMOOTHED_TUM, MAP_CSV)
    + tuple(f"fig-{name}.{suffix}" for name in (*FIGURE_NAMES, MAP_FIGURE_NAME) for suffix in FIGURE_FORMATS)
)


@dataclass(frozen=True)
class Associations:
    """One row per observation of the dataset, in the dataset's order (K rows).

    Attributes
    ----------
    pose_id : (K,) int64 id of the observing pose.
    camera : (K,) int64 camera id.
    uvd : (K, 3) measured u, v, depth.
    landmark : (K,) int64 landmark chosen by the localizer, ``UNASSOCIATED`` (-1) when rejected.
    true_landmark : (K,) int64 the file's landmark id (for scoring only).
    mahalanobis : (K,) Mahalanobis distance of the accepted innovation, NaN when rejected.
    """

    pose_id: np.ndarray
    camera: np.ndarray
    uvd: np.ndarray
    landmark: np.ndarray
    true_landmark: np.ndarray
    mahalanobis: np.ndarray


@dataclass(frozen=True)
class RunResult:
    """A localization run over N poses.

    Attributes
    ----------
    dataset : the dataset's source (path).
    pose_ids : (N,) int64.
    estimate_xyz, estimate_quat_xyzw : (N, 3), (N, 4) the filter's poses, world frame.
    estimate_cov : (N, 6, 6) covariance of the pose error ``(t_true - t_est, Log(R_true R_est^T))``
        (world-frame position and rotation vector, see ``geometry.pose_error_vector``), whatever
        the filter's own parametrization, so that NEES is comparable across filters.
    filter_state, filter_cov : (N, S), (N, D, D) the filter's own state and the covariance of its
        error: the Euler filter stores x, y, z, roll, pitch, yaw (D = S = 6); the SE(3) filter
        stores x, y, z, qx, qy, qz, qw and a 6-dimensional right-perturbation error.
    odometry_xyz, odometry_quat_xyzw : (N, 3), (N, 4) odometry alone from the same start.
    truth_xyz, truth_quat_xyzw : (N, 3), (N, 4) ground truth, or None.
    map_landmark_ids, map_landmark_xyz : (L,), (L, 3) the known map the run localized against.
    map_landmark_heading : (L,) each landmark's heading in the plane, radians: a marker's psi, a
        tag's yaw (its x axis); NaN for a point. None for a run folder written before it was kept.
    associations : one row per observation.
    update_pose_ids : (U,) int64 the pose of each filter update (one per pose with accepted pairs).
    nis : (U,) normalized innovation squared of each update; nis_dof : (U,) its degrees of freedom.
    summary : JSON-serializable dict (dataset, configuration, counts, timings, metrics, warnings).
    smoothed_xyz, smoothed_quat_xyzw : (N, 3), (N, 4) the smoother's poses (``smoothed.tum``),
        or None when the run was not smoothed.
    landmark_map : the map the run estimated (``map.csv``): a mapping run's (``camloc.slam_run``),
        or None. Its added landmarks' ids are those ``associations.landmark`` may hold beyond the map's.
    """

    dataset: str
    pose_ids: np.ndarray
    estimate_xyz: np.ndarray
    estimate_quat_xyzw: np.ndarray
    estimate_cov: np.ndarray
    filter_state: np.ndarray
    filter_cov: np.ndarray
    odometry_xyz: np.ndarray
    odometry_quat_xyzw: np.ndarray
    truth_xyz: np.ndarray | None
    truth_quat_xyzw: np.ndarray | None
    map_landmark_ids: np.ndarray
    map_landmark_xyz: np.ndarray
    associations: Associations
    update_pose_ids: np.ndarray
    nis: np.ndarray
    nis_dof: np.ndarray
    summary: dict = field(default_factory=dict)
    smoothed_xyz: np.ndarray | None = None
    smoothed_quat_xyzw: np.ndarray | None = None
    landmark_map: "LandmarkMap | None" = None
    map_landmark_heading: np.ndarray | None = None


# --------------------------------------------------------------------------------------------
# JSON


def write_json_atomic(path: str | Path, obj: Any) -> None:
    """Write ``obj`` as pretty, strict JSON (see ``to_jsonable``) whole or not at all."""
    write_text_atomic(path, dumps_json(obj))


def to_jsonable(obj: Any) -> Any:
    """A copy of ``obj`` that strict JSON accepts.

    numpy scalars and arrays become Python numbers and lists, paths become strings, tuples
    become lists, and non-finite floats (NaN, inf) become ``None`` (JSON has no NaN).

    Raises
    ------
    TypeError : for an object JSON has no form for (a bug in the caller).
    """
    if isinstance(obj, dict):
        return {str(key): to_jsonable(value) for key, value in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(value) for value in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if obj is None or isinstance(obj, (str, bool, int)):
        return obj
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot convert {type(obj).__name__} to JSON: {obj!r}")


def dumps_json(obj: Any) -> str:
    """``obj`` as pretty, strict JSON text ending with a newline."""
    return json.dumps(to_jsonable(obj), indent=2, allow_nan=False) + "\n"


# --------------------------------------------------------------------------------------------
# TUM trajectories


def tum_text(stamps: np.ndarray, xyz: np.ndarray, quat_xyzw: np.ndarray) -> str:
    """TUM text, one line ``timestamp x y z qx qy qz qw`` per pose, after a ``#`` header.

    Parameters
    ----------
    stamps : (N,) timestamps (camloc writes pose ids).
    xyz : (N, 3) positions, metres.
    quat_xyzw : (N, 4) orientations, scalar last.
    """
    rows = np.column_stack([np.asarray(stamps, dtype=float), xyz, quat_xyzw]).astype(float).tolist()
    lines = ["# " + " ".join(TUM_FIELDS)]
    # repr of a Python float is the shortest text that reads back to the same double
    lines += [" ".join(map(repr, row)) for row in rows]
    return "\n".join(lines) + "\n"


def write_tum(path: str | Path, stamps: np.ndarray, xyz: np.ndarray, quat_xyzw: np.ndarray) -> None:
    """Write a TUM trajectory file whole or not at all; see ``tum_text`` for the arguments."""
    write_text_atomic(path, tum_text(stamps, xyz, quat_xyzw))


def _read_text(path: Path) -> str:
    try:
        # utf-8-sig drops a leading byte order mark, which editors on Windows add (the g2o reader
        # accepts it too); otherwise it is UTF-8.
        return path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DatasetError(path, None, "no such file") from None
    except IsADirectoryError:
        raise DatasetError(path, None, "expected a file, found a directory") from None
    except UnicodeDecodeError as error:
        raise DatasetError(path, None, f"expected UTF-8 text, found byte 0x{error.object[error.start]:02x}") from None
    except OSError as error:
        raise DatasetError(path, None, f"cannot read: {error.strerror or error}") from None


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a TUM trajectory file (``timestamp x y z qx qy qz qw`` a line, ``#`` comments).

    Quaternions that are not unit to 1e-12 are normalized (files written by other tools are not
    always exactly unit); unit ones are kept as they are, so a file ``write_tum`` wrote reads back
    to the same numbers.

    Returns
    -------
    stamps : (N,) timestamps.
    xyz : (N, 3) positions.
    quat_xyzw : (N, 4) unit quaternions, scalar last.

    Raises
    ------
    DatasetError : ``path:line`` of the first bad line (wrong field count, a field that is not a
        finite number, a coordinate beyond ``MAX_RUN_COORDINATE`` metres, a zero quaternion, a
        repeated timestamp), or when there is no pose.
    """
    path = Path(path)
    rows: list[list[float]] = []
    line_of_stamp: dict[float, int] = {}
    for number, line in enumerate(_read_text(path).splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) != len(TUM_FIELDS):
            raise DatasetError(
                path, number, f"expected 8 fields '{' '.join(TUM_FIELDS)}', found {len(fields)}"
            )
        values = [_tum_value(path, number, name, text) for name, text in zip(TUM_FIELDS, fields)]
        if not any(values[4:8]):
            raise DatasetError(path, number, "expected a unit quaternion qx qy qz qw, found all zeros")
        if values[0] in line_of_stamp:
            raise DatasetError(
                path, number, f"expected unique timestamps, found {fields[0]} again (first on line {line_of_stamp[values[0]]})"
            )
        line_of_stamp[values[0]] = number
        rows.append(values)
    if not rows:
        raise DatasetError(path, None, f"expected TUM lines '{' '.join(TUM_FIELDS)}', found none")
    table = np.array(rows)
    quat = table[:, 4:8]
    # What camloc wrote is unit to rounding and read back bit for bit; only others are rescaled.
    with np.errstate(over="ignore"):
        off_unit = ~(np.abs(np.linalg.norm(quat, axis=1) - 1.0) <= 1e-12)
    quat[off_unit] = geometry.normalized_quaternions(quat[off_unit])
    return table[:, 0], table[:, 1:4], quat


def _tum_value(path: Path, line: int, name: str, text: str) -> float:
    """One field of a TUM line: a finite number, and for x, y, z within ``MAX_RUN_COORDINATE`` metres."""
    value = _finite_number(path, line, name, text)
    if name in ("x", "y", "z") and abs(value) > MAX_RUN_COORDINATE:
        raise DatasetError(path, line, f"expected metres within +-{MAX_RUN_COORDINATE:.0e} for {name}, found {text}")
    return value


def _finite_number(path: Path, line: int, name: str, text: str) -> float:
    """A field of a text file that must be a finite number (``g2o.parse_number``'s syntax)."""
    value = parse_number(text)
    if value is None:
        raise DatasetError(path, line, f"expected a number for {name}, found {text!r}")
    if not math.isfinite(value):
        raise DatasetError(path, line, f"expected a finite number for {name}, found {text!r}")
    return value


# --------------------------------------------------------------------------------------------
# associations.csv


def associations_text(associations: Associations) -> str:
    """The CSV text of ``associations`` (header ``ASSOCIATIONS_HEADER``, one row per observation).

    ``landmark`` and ``mahalanobis`` are empty cells for a rejected observation.
    """
    # Numbers and empty cells only, so no cell needs CSV quoting; each column becomes text at once,
    # through tolist()'s Python ints and floats, each float as its repr (as in tum_text).
    a = associations
    landmark = a.landmark.astype(np.int64).tolist()
    distance = np.asarray(a.mahalanobis, dtype=float).tolist()
    uvd = np.asarray(a.uvd, dtype=float)
    columns = [
        map(str, a.pose_id.astype(np.int64).tolist()),
        map(str, a.camera.astype(np.int64).tolist()),
        *(map(repr, uvd[:, i].tolist()) for i in range(3)),
        (str(value) if value != UNASSOCIATED else "" for value in landmark),
        map(str, a.true_landmark.astype(np.int64).tolist()),
        (repr(d) if value != UNASSOCIATED and math.isfinite(d) else "" for value, d in zip(landmark, distance)),
    ]
    lines = [",".join(ASSOCIATIONS_HEADER), *map(",".join, zip(*columns))]
    return "\n".join(lines) + "\n"


def read_associations(path: str | Path) -> Associations:
    """Read an ``associations.csv`` written by ``associations_text``.

    Raises
    ------
    DatasetError : ``path:line`` of a wrong header, a wrong field count, an id that is not a 64-bit
        integer or a value that is not a finite number.
    """
    return _read_associations_with_lines(path)[0]


def _read_associations_with_lines(path: str | Path) -> tuple[Associations, list[int]]:
    """``read_associations`` and the file's line number of each row (blank lines are skipped)."""
    path = Path(path)
    lines = _read_text(path).splitlines()
    expected_header = ",".join(ASSOCIATIONS_HEADER)
    if not lines or lines[0].strip() != expected_header:
        found = lines[0].strip() if lines else "an empty file"
        raise DatasetError(path, 1, f"expected the header '{expected_header}', found '{found}'")
    fast = _read_associations_fast(lines)
    if fast is not None:
        return fast
    columns: dict[str, list] = {name: [] for name in ASSOCIATIONS_HEADER}
    row_lines: list[int] = []
    for number, fields in enumerate(csv.reader(lines[1:]), start=2):
        if not fields:
            continue
        row_lines.append(number)
        if len(fields) != len(ASSOCIATIONS_HEADER):
            raise DatasetError(path, number, f"expected {len(ASSOCIATIONS_HEADER)} comma-separated fields, found {len(fields)}")
        for name, text in zip(ASSOCIATIONS_HEADER, fields):
            columns[name].append(_parse_cell(path, number, name, text.strip()))
    landmark = [UNASSOCIATED if value is None else value for value in columns["landmark"]]
    mahalanobis = [math.nan if value is None else value for value in columns["mahalanobis"]]
    associations = Associations(
        pose_id=np.array(columns["pose"], dtype=np.int64),
        camera=np.array(columns["camera"], dtype=np.int64),
        uvd=np.array([columns["u"], columns["v"], columns["depth"]], dtype=float).T.reshape(-1, 3),
        landmark=np.array(landmark, dtype=np.int64),
        true_landmark=np.array(columns["true_landmark"], dtype=np.int64),
        mahalanobis=np.array(mahalanobis, dtype=float),
    )
    return associations, row_lines


_INT_COLUMNS = ("pose", "camera", "landmark", "true_landmark")
_OPTIONAL_COLUMNS = ("landmark", "mahalanobis")

# A file as associations_text writes it: rows of eight cells, only landmark and mahalanobis ever
# empty, in characters a number or an id is written with.
_WRITTEN_ROW = r"[^,\n]+,[^,\n]+,[^,\n]+,[^,\n]+,[^,\n]+,[^,\n]*,[^,\n]+,[^,\n]*"
_WRITTEN_BODY = re.compile(f"(?:{_WRITTEN_ROW}\n)*(?:{_WRITTEN_ROW})?")
_NOT_WRITTEN = str.maketrans("", "", "0123456789+-.eE,\n")
_ASSOCIATIONS_DTYPE = [("pose", np.int64), ("camera", np.int64), ("u", float), ("v", float), ("depth", float),
                       ("landmark", np.int64), ("true_landmark", np.int64), ("mahalanobis", float)]


def _read_associations_fast(lines: list[str]) -> tuple[Associations, list[int]] | None:
    """``_read_associations_with_lines`` for a file laid out as camloc writes it (its header
    already checked), by np.loadtxt; None for anything else (a blank line, a quote, a space, nan,
    an empty required cell, an id beyond 64 bits, a number beyond a double's range...), which the
    line-by-line reader then reads or names the line of. A 200k-row file: 1.4 -> 0.6 s."""
    body = "\n".join(lines[1:])
    if not body or body.translate(_NOT_WRITTEN) or not _WRITTEN_BODY.fullmatch(body):
        return None
    # the only empty cells left are a rejected observation's landmark (between two others) and
    # mahalanobis (last): the values the line-by-line reader gives them
    body = body.replace(",,", f",{UNASSOCIATED},").replace(",\n", ",nan\n")
    if body.endswith(","):
        body += "nan"
    try:
        table = np.loadtxt(io.StringIO(body), delimiter=",", dtype=_ASSOCIATIONS_DTYPE, comments=None, ndmin=1)
    except (ValueError, OverflowError):
        return None
    uvd = np.column_stack([table["u"], table["v"], table["depth"]])
    if not np.isfinite(uvd).all() or np.isinf(table["mahalanobis"]).any():    # beyond a double's range
        return None
    associations = Associations(
        pose_id=table["pose"].copy(), camera=table["camera"].copy(), uvd=uvd, landmark=table["landmark"].copy(),
        true_landmark=table["true_landmark"].copy(), mahalanobis=table["mahalanobis"].copy(),
    )
    return associations, list(range(2, 2 + table.shape[0]))


def _parse_cell(path: Path, line: int, name: str, text: str) -> int | float | None:
    """One cell of ``associations.csv``: a 64-bit integer id, or a finite number (empty means
    rejected, in the optional columns only; the writer never writes NaN or inf)."""
    if not text:
        if name in _OPTIONAL_COLUMNS:
            return None
        raise DatasetError(path, line, f"expected a value for {name}, found an empty cell")
    if name in _INT_COLUMNS:
        if not INTEGER.fullmatch(text):
            raise DatasetError(path, line, f"expected an integer for {name}, found {text!r}")
        if not INT64_RANGE[0] <= int(text) <= INT64_RANGE[1]:
            raise DatasetError(path, line, f"expected an integer for {name} that fits in 64 bits, found {text}")
        return int(text)
    return _finite_number(path, line, name, text)


# --------------------------------------------------------------------------------------------
# Run folders

# What states.npz holds: arrays whose rows are the poses, and the others.
_POSE_ARRAYS = ("pose_ids", "estimate_cov", "filter_state", "filter_cov")
_OTHER_ARRAYS = ("map_landmark_ids", "map_landmark_xyz", "update_pose_ids", "nis", "nis_dof")
# held when the run has them (a run folder written before they were has not)
_OPTIONAL_ARRAYS = ("map_landmark_heading",)
# The trajectories' one home: TUM file -> the RunResult fields it holds (ground truth and the
# smoothed path only when there are some).
_TUM_ARRAYS = {
    ESTIMATE_TUM: ("estimate_xyz", "estimate_quat_xyzw"),
    ODOMETRY_TUM: ("odometry_xyz", "odometry_quat_xyzw"),
    GROUNDTRUTH_TUM: ("truth_xyz", "truth_quat_xyzw"),
    SMOOTHED_TUM: ("smoothed_xyz", "smoothed_quat_xyzw"),
}


def run_problems(result: RunResult) -> list[str]:
    """Shape inconsistencies of ``result`` (empty when it is a well-formed run).

    Checks every array against N poses, L landmarks, K observations and U updates, and that
    ground truth is given whole (both arrays) or not at all.
    """
    n = np.shape(result.pose_ids)[0] if np.ndim(result.pose_ids) == 1 else -1
    state_dim = np.shape(result.filter_state)[-1] if np.ndim(result.filter_state) == 2 else -1
    # The covariance is over the filter's error, which need not have the state's size (SE(3):
    # the state is stored as x, y, z + quaternion, the error has 6 dimensions).
    error_dim = np.shape(result.filter_cov)[-1] if np.ndim(result.filter_cov) == 3 else -1
    expected: dict[str, tuple] = {
        "pose_ids": (n,),
        "estimate_xyz": (n, 3),
        "estimate_quat_xyzw": (n, 4),
        "estimate_cov": (n, 6, 6),
        "filter_state": (n, state_dim),
        "filter_cov": (n, error_dim, error_dim),
        "odometry_xyz": (n, 3),
        "odometry_quat_xyzw": (n, 4),
    }
    if (result.truth_xyz is None) != (result.truth_quat_xyzw is None):
        return ["ground truth needs both truth_xyz and truth_quat_xyzw, or neither"]
    if result.truth_xyz is not None:
        expected.update(truth_xyz=(n, 3), truth_quat_xyzw=(n, 4))
    if (result.smoothed_xyz is None) != (result.smoothed_quat_xyzw is None):
        return ["a smoothed path needs both smoothed_xyz and smoothed_quat_xyzw, or neither"]
    if result.smoothed_xyz is not None:
        expected.update(smoothed_xyz=(n, 3), smoothed_quat_xyzw=(n, 4))
    num_landmarks = np.shape(result.map_landmark_ids)[0] if np.ndim(result.map_landmark_ids) == 1 else -1
    expected.update(map_landmark_ids=(num_landmarks,), map_landmark_xyz=(num_landmarks, 3))
    if result.map_landmark_heading is not None:
        expected.update(map_landmark_heading=(num_landmarks,))
    num_updates = np.shape(result.update_pose_ids)[0] if np.ndim(result.update_pose_ids) == 1 else -1
    expected.update(update_pose_ids=(num_updates,), nis=(num_updates,), nis_dof=(num_updates,))
    problems = [
        f"{name} has shape {np.shape(getattr(result, name))}, expected {shape}"
        for name, shape in expected.items()
        if np.shape(getattr(result, name)) != shape or -1 in shape
    ]
    a = result.associations
    k = np.shape(a.pose_id)[0] if np.ndim(a.pose_id) == 1 else -1
    for name, shape in dict(
        pose_id=(k,), camera=(k,), uvd=(k, 3), landmark=(k,), true_landmark=(k,), mahalanobis=(k,)
    ).items():
        if np.shape(getattr(a, name)) != shape or k < 0:
            problems.append(f"associations.{name} has shape {np.shape(getattr(a, name))}, expected {shape}")
    return problems


def is_run_folder(path: str | Path) -> bool:
    """True when ``path`` is a directory holding the files ``load_run`` needs."""
    path = Path(path)
    return path.is_dir() and all((path / name).is_file() for name in _REQUIRED_FILES)


def check_run_folder(run_dir: str | Path, *, force: bool = False) -> None:
    """Whether a run may be written to ``run_dir``: it is absent or an empty directory, or (with
    ``force``) a camloc run folder. Checked before a run starts, so that a long run is not refused
    at its end, and again by ``save_run``.

    Raises
    ------
    CamlocError : ``run_dir`` holds something else: a file, or a directory that is not a run
        folder (never replaced, even with ``force``); or a run folder and not ``force``.
    """
    run_dir = Path(run_dir)
    if not (run_dir.exists() or run_dir.is_symlink()) or _is_empty_dir(run_dir):
        return
    if not is_run_folder(run_dir):
        raise CamlocError(
            f"{run_dir}: already exists and is not a camloc run folder; refusing to replace it, "
            "choose another output folder"
        )
    refuse_existing(run_dir, force=force)


def save_run(run_dir: str | Path, result: RunResult, *, force: bool = False) -> Path:
    """Write ``result`` as a run folder (see the module docstring), whole or not at all.

    The folder is built in a hidden temporary sibling (``.NAME.tmp-*``) and renamed into place.
    An existing run folder is replaced only with ``force``: the files of the old folder that are
    not camloc's (``CAMLOC_FILES``: a user's notes) are moved into the new one, and the old one is
    moved aside once the new one is complete, then deleted. Missing parent folders are created.

    Parameters
    ----------
    run_dir : the run folder to create (or, with ``force``, replace).
    result : the run.
    force : replace an existing run folder (see ``check_run_folder``).

    Returns
    -------
    The run folder's path.

    Raises
    ------
    CamlocError : ``run_dir`` exists and may not be replaced (``check_run_folder``), or it cannot
        be written.
    ValueError : ``result`` is malformed (see ``run_problems``): a bug in its producer.
    """
    run_dir = Path(run_dir)
    problems = run_problems(result)
    if problems:
        raise ValueError("malformed RunResult: " + "; ".join(problems))
    check_run_folder(run_dir, force=force)
    make_folder(run_dir.parent)
    try:
        tmp = Path(tempfile.mkdtemp(dir=run_dir.parent, prefix=f".{run_dir.name}.tmp-"))
    except OSError as error:
        raise CamlocError(f"cannot create the folder {run_dir}: {error.strerror or error}") from None
    kept: list[str] = []
    try:
        os.chmod(tmp, 0o755)
        with naming_the_output(run_dir):
            _write_run_files(tmp, result)
        if run_dir.is_dir():
            for entry in sorted(run_dir.iterdir()):
                if entry.name not in CAMLOC_FILES:
                    os.rename(entry, tmp / entry.name)
                    kept.append(entry.name)
        _move_into_place(tmp, run_dir)
    except BaseException:
        # _move_into_place has put the old folder back; so do the user's files.
        for name in kept:
            with contextlib.suppress(OSError):
                os.rename(tmp / name, run_dir / name)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return run_dir


def _is_empty_dir(path: Path) -> bool:
    return path.is_dir() and not any(path.iterdir())


def _write_run_files(folder: Path, result: RunResult) -> None:
    # The folder is private until renamed, so plain writes suffice inside it.
    for name, (xyz, quat) in _TUM_ARRAYS.items():
        if getattr(result, xyz) is not None:
            (folder / name).write_text(
                tum_text(result.pose_ids, getattr(result, xyz), getattr(result, quat)), encoding="utf-8"
            )
    (folder / ASSOCIATIONS_CSV).write_text(associations_text(result.associations), encoding="utf-8")
    arrays = {name: np.asarray(getattr(result, name)) for name in _POSE_ARRAYS + _OTHER_ARRAYS}
    arrays.update({name: np.asarray(getattr(result, name)) for name in _OPTIONAL_ARRAYS if getattr(result, name) is not None})
    with open(folder / STATES_NPZ, "wb") as handle:
        np.savez_compressed(
            handle, format_version=np.int64(RUN_FORMAT_VERSION), dataset=np.str_(result.dataset), **arrays
        )
    (folder / SUMMARY_JSON).write_text(dumps_json(result.summary), encoding="utf-8")
    if result.landmark_map is not None:
        (folder / MAP_CSV).write_text(map_text(result.landmark_map), encoding="utf-8")


def _move_into_place(tmp: Path, run_dir: Path) -> None:
    if not run_dir.exists():
        os.rename(tmp, run_dir)
        return
    old = Path(tempfile.mkdtemp(dir=run_dir.parent, prefix=f".{run_dir.name}.old-"))
    try:
        os.rename(run_dir, old / run_dir.name)
    except BaseException:
        shutil.rmtree(old, ignore_errors=True)
        raise
    try:
        os.rename(tmp, run_dir)
    except BaseException:
        os.rename(old / run_dir.name, run_dir)
        shutil.rmtree(old, ignore_errors=True)
        raise
    shutil.rmtree(old, ignore_errors=True)


def load_run(run_dir: str | Path, *, smoothed: bool = True) -> RunResult:
    """Read a run folder written by ``save_run`` back into a ``RunResult``; without ``smoothed``,
    leave out its ``smoothed.tum`` (the smoother replaces it, whatever it holds).

    The trajectories come from the TUM files (``estimate.tum``, ``odometry.tum``; the ground
    truth from ``groundtruth.tum`` and the smoothed path from ``smoothed.tum`` when they are
    there), the other arrays from ``states.npz``, the associations from
    ``associations.csv``, the summary from ``summary.json``. What is scored and drawn is what is
    on disk: an edited trajectory gives new numbers, a truncated, swapped or missing one an error.

    Raises
    ------
    CamlocError : ``run_dir`` is not a run folder, or a file is missing, corrupt or inconsistent
        (``DatasetError`` with the file, and the line where there is one). Every array of
        ``states.npz`` is checked for its type, shape and values (``_check_states``), and each
        TUM file line by line and for the run's pose ids as timestamps, so that what is loaded can
        be scored and drawn.
    """
    run_dir = Path(run_dir)
    if run_dir.is_file():
        raise CamlocError(
            f"{run_dir}: expected a run folder written by 'camloc run', found a file"
            + (f" (a dataset: localize it first, 'camloc run {run_dir}')" if run_dir.suffix.lower() == ".g2o" else "")
        )
    if not run_dir.is_dir():
        raise CamlocError(f"{run_dir}: expected a run folder written by 'camloc run', found no such directory")
    missing = [name for name in _REQUIRED_FILES if not (run_dir / name).is_file()]
    if missing:
        raise CamlocError(
            f"{run_dir}: expected a run folder written by 'camloc run', missing {', '.join(missing)}"
        )
    arrays = _read_states(run_dir / STATES_NPZ)
    for name, (xyz, quat) in _TUM_ARRAYS.items():
        optional = name in (GROUNDTRUTH_TUM, SMOOTHED_TUM)
        if name == SMOOTHED_TUM and not smoothed:
            continue
        if not (optional and not (run_dir / name).exists()):
            hint = "smooth the run again" if name == SMOOTHED_TUM else "run 'camloc run' again"
            arrays[xyz], arrays[quat] = read_run_tum(run_dir / name, arrays["pose_ids"], hint=hint)
    summary = _read_summary(run_dir / SUMMARY_JSON)
    if arrays.get("truth_xyz") is None and summary.get("estimate") is not None:
        # the run was scored against ground truth (summary.json): its file went missing, not the truth
        raise DatasetError(run_dir / GROUNDTRUTH_TUM, None, f"missing, but {SUMMARY_JSON} scores the run against ground truth; "
                                                          "restore it or run 'camloc run' again")
    associations, row_lines = _read_associations_with_lines(run_dir / ASSOCIATIONS_CSV)
    _check_association_poses(run_dir / ASSOCIATIONS_CSV, associations, row_lines, arrays["pose_ids"])
    _check_association_count(run_dir / ASSOCIATIONS_CSV, associations, summary)
    landmark_map = read_map(run_dir / MAP_CSV) if (run_dir / MAP_CSV).is_file() else None
    known_ids = arrays["map_landmark_ids"] if landmark_map is None else np.union1d(arrays["map_landmark_ids"], landmark_map.ids)
    _check_association_landmarks(run_dir / ASSOCIATIONS_CSV, associations, row_lines, known_ids)
    arrays.setdefault("truth_xyz", None)
    arrays.setdefault("truth_quat_xyzw", None)
    result = RunResult(dataset=arrays.pop("dataset"), associations=associations, summary=summary, landmark_map=landmark_map,
                       **arrays)
    problems = run_problems(result)
    if problems:
        raise CamlocError(f"{run_dir}: inconsistent run folder: {'; '.join(problems)}")
    return result


def write_smoothed(run_dir: str | Path, pose_ids: np.ndarray, xyz: np.ndarray, quat_xyzw: np.ndarray) -> Path:
    """Write the smoother's poses as ``smoothed.tum`` into an existing run folder, atomically.

    Only that file is (re)written, whole or not at all; the rest of the folder is untouched.

    Parameters
    ----------
    run_dir : a run folder (``is_run_folder``).
    pose_ids : (N,) the run's pose ids (the TUM timestamps).
    xyz, quat_xyzw : (N, 3), (N, 4) the smoothed poses, world frame.

    Returns
    -------
    The path of ``smoothed.tum``.

    Raises
    ------
    CamlocError : ``run_dir`` is not a run folder, or the file cannot be written.
    """
    path = _file_in_run_folder(run_dir, SMOOTHED_TUM)
    write_tum(path, pose_ids, xyz, quat_xyzw)
    return path


def _file_in_run_folder(run_dir: str | Path, name: str) -> Path:
    """The path of file ``name`` in ``run_dir``, which must be a run folder (CamlocError if not)."""
    run_dir = Path(run_dir)
    if not is_run_folder(run_dir):
        raise CamlocError(f"{run_dir}: expected a run folder written by 'camloc run' to add {name} to")
    return run_dir / name


@dataclass(frozen=True)
class LandmarkMap:
    """An estimated map (K landmarks), ``map.csv``'s content.

    Attributes
    ----------
    ids : (K,) int64; xyz : (K, 3) world frame, metres.
    cov : (K, 3, 3) covariance of each position, m^2 (zero for a landmark held exactly at the map).
    added : (K,) bool: ``added`` (the map lacked it) or ``mapped``.
    observations : (K,) int64 observations the estimate used.
    orientation : (K, 3) a tag's orientation (rotation vector of R_tag, world), NaN for a landmark
        that is not a tag; None: no tag in the map (``map.csv`` then has no orientation columns).
    orientation_cov : (K, 3, 3) its covariance, rad^2, of the world rotation error e
        (``R_true = Exp(e) R_tag``; zero where held exactly), None with ``orientation``.
    """

    ids: np.ndarray
    xyz: np.ndarray
    cov: np.ndarray
    added: np.ndarray
    observations: np.ndarray
    orientation: "np.ndarray | None" = None
    orientation_cov: "np.ndarray | None" = None


def map_text(landmarks: LandmarkMap) -> str:
    """The CSV text of a map (header ``MAP_HEADER``, a row per landmark; floats as their repr)."""
    m = landmarks
    cov = np.asarray(m.cov, dtype=float)
    columns = [
        map(str, np.asarray(m.ids, dtype=np.int64).tolist()),
        *(map(repr, np.asarray(m.xyz, dtype=float)[:, i].tolist()) for i in range(3)),
        *(map(repr, cov[:, i, j].tolist()) for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))),
        ("added" if added else "mapped" for added in np.asarray(m.added, dtype=bool).tolist()),
        map(str, np.asarray(m.observations, dtype=np.int64).tolist()),
    ]
    header = MAP_HEADER
    if m.orientation is not None:  # a map of tags: their orientations in columns after the others
        header = MAP_HEADER + MAP_ORIENTATION_HEADER
        columns += _orientation_columns(np.asarray(m.orientation, dtype=float), np.asarray(m.orientation_cov, dtype=float))
    lines = [",".join(header), *map(",".join, zip(*columns))]
    return "\n".join(lines) + "\n"


def _orientation_columns(rotvec: np.ndarray, cov: np.ndarray) -> list:
    """``MAP_ORIENTATION_HEADER``'s columns: a tag's quaternion and covariance, empty cells for a
    landmark that is not a tag."""
    tag = np.isfinite(rotvec[:, 0])
    quat = np.full((rotvec.shape[0], 4), np.nan)
    if np.any(tag):
        quat[tag] = geometry.matrix_to_quat(geometry.so3_exp(rotvec[tag]))
    values = [quat[:, i] for i in range(4)] + [cov[:, i, j] for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))]
    return [[repr(float(v)) if is_tag else "" for v, is_tag in zip(column.tolist(), tag.tolist())] for column in values]


def write_map(run_dir: str | Path, landmarks: LandmarkMap) -> Path:
    """Write the smoother's map as ``map.csv`` into an existing run folder, whole or not at all.

    Raises
    ------
    CamlocError : ``run_dir`` is not a run folder, or the file cannot be written.
    """
    path = _file_in_run_folder(run_dir, MAP_CSV)
    write_text_atomic(path, map_text(landmarks))
    return path


def run_map(result: RunResult) -> LandmarkMap:
    """The map a run ended with: its ``map.csv`` (``result.landmark_map``), or, for a run that wrote
    none (``--map exact`` where no landmark was added), the map it was given, held exactly (zero
    covariance, every landmark ``mapped``), each landmark's observations counted from its pairs."""
    if result.landmark_map is not None:
        return result.landmark_map
    ids = np.asarray(result.map_landmark_ids, dtype=np.int64)
    paired, counts = np.unique(np.asarray(result.associations.landmark, dtype=np.int64), return_counts=True)
    at = np.clip(np.searchsorted(paired, ids), 0, max(paired.size - 1, 0))
    observations = np.where(paired[at] == ids, counts[at], 0) if paired.size else np.zeros(ids.size, np.int64)
    return LandmarkMap(ids, np.asarray(result.map_landmark_xyz, dtype=float).reshape(-1, 3), np.zeros((ids.size, 3, 3)),
                       np.zeros(ids.size, dtype=bool), observations.astype(np.int64))


def read_map(path: str | Path) -> LandmarkMap:
    """Read a ``map.csv`` written by ``map_text`` (with its tags' orientation columns, where it has them).

    Raises
    ------
    DatasetError : a missing or malformed file (with the line).
    """
    path = Path(path)
    lines = _read_text(path).splitlines()
    header = tuple(cell.strip() for cell in lines[0].split(",")) if lines else ()
    if header not in (MAP_HEADER, MAP_HEADER + MAP_ORIENTATION_HEADER):
        raise DatasetError(path, 1, f"expected the header {','.join(MAP_HEADER)} (then {','.join(MAP_ORIENTATION_HEADER)} "
                                    f"for a map of tags), found {lines[0] if lines else 'nothing'}")
    ids, values, added, observations, turned = [], [], [], [], []
    for number, line in enumerate(lines[1:], start=2):
        cells = [cell.strip() for cell in line.split(",")]
        if len(cells) != len(header):
            raise DatasetError(path, number, f"expected {len(header)} fields, found {len(cells)}")
        if cells[10] not in ("mapped", "added"):
            raise DatasetError(path, number, f"origin: expected mapped or added, found {cells[10]!r}")
        try:
            ids.append(int(cells[0]))
            observations.append(int(cells[11]))
            row = [float(cell) for cell in cells[1:10]]
        except ValueError:
            raise DatasetError(path, number, "expected an integer id and observations and finite numbers") from None
        if not all(math.isfinite(v) for v in row):
            raise DatasetError(path, number, "expected finite numbers")
        values.append(row)
        added.append(cells[10] == "added")
        if len(header) > len(MAP_HEADER):
            turned.append(_orientation_cells(path, number, cells[len(MAP_HEADER):]))
    v = np.array(values, dtype=float).reshape(-1, 9)
    upper = v[:, [3, 4, 5, 4, 6, 7, 5, 7, 8]].reshape(-1, 3, 3)
    landmarks = LandmarkMap(np.array(ids, dtype=np.int64), v[:, :3], upper, np.array(added, dtype=bool),
                            np.array(observations, dtype=np.int64))
    if len(header) == len(MAP_HEADER):
        return landmarks
    o = np.array(turned, dtype=float).reshape(-1, 10)
    tag = np.isfinite(o[:, 0])
    rotvec = np.full((o.shape[0], 3), np.nan)
    if np.any(tag):
        rotvec[tag] = geometry.so3_log(geometry.quat_to_matrix(o[tag, :4]))
    cov = o[:, [4, 5, 6, 5, 7, 8, 6, 8, 9]].reshape(-1, 3, 3)
    cov[~tag] = 0.0  # not a tag: no orientation, nothing uncertain about it (as the run holds it)
    return dataclasses.replace(landmarks, orientation=rotvec, orientation_cov=cov)


def _orientation_cells(path: Path, number: int, cells: list[str]) -> list[float]:
    """A row's orientation cells (``MAP_ORIENTATION_HEADER``): ten numbers, a unit quaternion
    first, or ten empty cells (not a tag: NaN)."""
    if all(cell == "" for cell in cells):
        return [math.nan] * len(cells)
    try:
        numbers = [float(cell) for cell in cells]
    except ValueError:
        raise DatasetError(path, number, "orientation: expected ten numbers or ten empty cells") from None
    if not all(math.isfinite(v) for v in numbers) or abs(math.hypot(*numbers[:4]) - 1.0) > 1e-6:
        raise DatasetError(path, number, "orientation: expected a unit quaternion and finite covariances")
    return numbers


def load_smoothed(run_dir: str | Path, pose_ids: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """The smoothed poses ``(xyz (N, 3), quat_xyzw (N, 4))`` of a run folder, None without ``smoothed.tum``.

    Parameters
    ----------
    run_dir : the run folder.
    pose_ids : (N,) the run's pose ids; when given, the file's timestamps must be exactly these.

    Raises
    ------
    DatasetError : a malformed file, or one whose timestamps are not the run's pose ids (a
        smoothed path of another run).
    """
    path = Path(run_dir) / SMOOTHED_TUM
    if not path.exists():
        return None
    if pose_ids is None:
        return read_tum(path)[1:]
    return read_run_tum(path, pose_ids, hint="smooth the run again")


def read_run_tum(path: str | Path, pose_ids: np.ndarray, *, hint: str) -> tuple[np.ndarray, np.ndarray]:
    """The poses ``(xyz (N, 3), quat_xyzw (N, 4))`` of a run folder's TUM file, whose timestamps
    must be exactly the run's ``pose_ids`` (N,), in order.

    Raises
    ------
    DatasetError : a missing or malformed file, or one of another run or cut short (``hint`` says
        what to do).
    """
    stamps, xyz, quat = read_tum(path)
    expected = np.asarray(pose_ids, dtype=float)
    if stamps.shape != expected.shape or not np.array_equal(stamps, expected):
        raise DatasetError(
            path, None, f"expected the run's {len(expected)} pose ids ({expected[0]:g}..{expected[-1]:g}) as "
            f"timestamps, found {len(stamps)} timestamps ({stamps[0]:g}..{stamps[-1]:g}) that differ; {hint}"
        )
    return xyz, quat


# How the files that can hold pickled objects begin: a zip archive (an .npz of object arrays), a
# numpy array, a pickle of protocol 2 or later.
_PICKLING_MAGICS = (b"PK\x03\x04", b"\x93NUMPY", b"\x80")


def _starts_with(path: Path, magics: tuple[bytes, ...]) -> bool:
    with open(path, "rb") as file:
        start = file.read(max(len(magic) for magic in magics))
    return any(start.startswith(magic) for magic in magics)


def _read_states(path: Path) -> dict[str, Any]:
    try:
        with np.load(path, allow_pickle=False) as npz:
            stored = {name: npz[name] for name in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as error:
        # numpy takes any file that is neither a zip nor an .npy for a pickle, and its message
        # suggests loading it unsafely: say what the file is instead (camloc never writes a pickle)
        if "pickle" in str(error) and _starts_with(path, _PICKLING_MAGICS):
            raise DatasetError(path, None, "expected a numpy .npz archive of plain arrays, found pickled Python objects "
                                           "(not loaded; camloc never writes them)") from None
        if "pickle" in str(error):
            raise DatasetError(path, None, "expected a numpy .npz archive, found a file that is not one "
                                           "(neither a zip archive nor a numpy array); run 'camloc run' again") from None
        raise DatasetError(path, None, f"expected a numpy .npz archive, found an unreadable file ({error})") from None
    if not isinstance(stored, dict) or "format_version" not in stored:
        raise DatasetError(path, None, "expected a camloc states archive, found no format_version")
    version = stored["format_version"]
    if version.ndim != 0 or version.dtype.kind not in "iu" or int(version) not in _READABLE_FORMAT_VERSIONS:
        expected = " or ".join(map(str, _READABLE_FORMAT_VERSIONS))
        raise DatasetError(path, None, f"expected format_version {expected}, found {_describe(version)}")
    names = ("dataset",) + _POSE_ARRAYS + _OTHER_ARRAYS
    missing = [name for name in names if name not in stored]
    if missing:
        raise DatasetError(path, None, f"expected arrays {', '.join(missing)}, found none of that name")
    dataset = stored["dataset"]
    if dataset.ndim != 0 or dataset.dtype.kind != "U":
        raise DatasetError(path, None, f"dataset: expected one string (the dataset's path), found {_describe(dataset)}")
    arrays: dict[str, Any] = {name: stored[name] for name in names[1:] + tuple(n for n in _OPTIONAL_ARRAYS if n in stored)}
    arrays = _check_states(path, arrays)
    arrays["dataset"] = str(dataset)
    return arrays


def _describe(array: np.ndarray) -> str:
    """A short description of an unexpected array, for error messages."""
    if array.ndim == 0:
        text = repr(array.item())
        return text if len(text) <= 40 else text[:37] + "..."
    return f"an array of {array.dtype} of shape {array.shape}"


# What each array of states.npz holds, and its shape after the first axis (None: any size of at
# least 1, the same on both axes of a covariance):
#   ids: integers; counts: integers >= 1; numbers: finite; non-negative: finite >= 0;
#   positions: finite metres within MAX_RUN_COORDINATE; headings: radians in [-2 pi, 2 pi], or NaN (none);
#   covariances: symmetric positive semi-definite, not zero at every pose.
_STATE_ARRAYS: dict[str, tuple[str, tuple]] = {
    "pose_ids": ("ids", ()),
    "estimate_cov": ("covariances", (6, 6)),
    "filter_state": ("numbers", (None,)),
    "filter_cov": ("covariances", (None, None)),
    "map_landmark_ids": ("ids", ()),
    "map_landmark_xyz": ("positions", (3,)),
    "update_pose_ids": ("ids", ()),
    "nis": ("non-negative", ()),
    "nis_dof": ("counts", ()),
    "map_landmark_heading": ("headings", ()),
}
# The run writes symmetric covariances; this tolerance only separates rounding from damage.
_MATRIX_TOLERANCE = 1e-9
# A filter's covariance collapsed to nearly rank one (a lost run) keeps the update's rounding in
# its smallest eigenvalues, which can come out slightly negative: the audit of 2026-12-06 found
# -5.2e-10 beside a largest eigenvalue of 1.6e-3 (up to 2e-6 of the largest entry) in a run camloc
# itself wrote, and eval refused it. Relative to the largest entry, as the symmetry's tolerance; a
# damaged file is far past it.
_EIGENVALUE_TOLERANCE = 1e-5


def _check_states(path: Path, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The arrays of ``states.npz`` as int64 / float64, each checked against ``_STATE_ARRAYS``.

    Shapes are checked here one array at a time; that the arrays agree on N poses, L landmarks
    and U updates is ``run_problems``'s check, after loading.

    Raises
    ------
    DatasetError : ``states.npz: <array>: expected ..., found ...`` for the first bad array.
    """
    pose_ids, problem = _checked_state_array(arrays["pose_ids"], *_STATE_ARRAYS["pose_ids"], None)
    if problem is None:
        unique, counts = np.unique(pose_ids, return_counts=True)
        if pose_ids.size == 0:
            problem = "expected at least one pose, found none"
        elif np.any(counts > 1):
            problem = f"expected distinct ids, found {unique[counts > 1][0]} more than once"
    if problem is not None:
        raise DatasetError(path, None, f"pose_ids: {problem}")
    checked = {"pose_ids": pose_ids}
    for name, array in arrays.items():
        if name == "pose_ids":
            continue
        kind, trailing = _STATE_ARRAYS[name]
        rows_are_poses = name in _POSE_ARRAYS
        value, problem = _checked_state_array(array, kind, trailing, pose_ids if rows_are_poses else None)
        if problem is not None:
            raise DatasetError(path, None, f"{name}: {problem}")
        checked[name] = value
    update_pose_ids = checked["update_pose_ids"]
    unknown = ~np.isin(update_pose_ids, pose_ids)
    if np.any(unknown):
        raise DatasetError(
            path, None, f"update_pose_ids: expected ids of the run's poses, found {update_pose_ids[unknown][0]}, "
            "which is not in pose_ids"
        )
    return checked


def _checked_state_array(
    array: np.ndarray, kind: str, trailing: tuple, pose_ids: np.ndarray | None
) -> tuple[np.ndarray, str | None]:
    """``array`` as int64 or float64 for its kind (``_STATE_ARRAYS``), and what is wrong with it
    (None when nothing is). ``pose_ids``, when the rows are poses, name the row of a bad value."""
    integers = kind in ("ids", "counts")
    if integers and not (array.dtype.kind == "i" or (array.dtype.kind == "u" and array.dtype.itemsize < 8)):
        return array, f"expected 64-bit integers, found {array.dtype}"
    if not integers and array.dtype.kind not in "fiu":
        return array, f"expected real numbers, found {array.dtype}"
    if not _shape_matches(array.shape, trailing):
        dims = ["N"] + ["D" if size is None else str(size) for size in trailing]
        expected = "(N,)" if len(dims) == 1 else f"({', '.join(dims)})"
        return array, f"expected shape {expected}, found {array.shape}"
    value = array.astype(np.int64 if integers else np.float64)

    def where(row: int) -> str:
        return f"pose {pose_ids[row]}" if pose_ids is not None and row < len(pose_ids) else f"row {row}"

    return value, _state_value_problem(value, kind, where)


def _state_value_problem(value: np.ndarray, kind: str, where: Callable[[int], str]) -> str | None:
    """What breaks the rule of ``kind`` in ``value`` (N, ...), naming the first bad row, or None."""
    if kind == "ids":
        return None
    if kind == "counts":
        return _first_bad(value, value < 1, "expected counts of at least 1", where)
    if kind == "non-negative":
        return _first_bad(value, ~(value >= 0.0), "expected finite numbers >= 0", where)
    if kind == "positions":
        expected = f"expected finite metres within +-{MAX_RUN_COORDINATE:.0e}"
        return _first_bad(value, ~(np.abs(value) <= MAX_RUN_COORDINATE), expected, where)
    if kind == "headings":
        return _first_bad(value, ~(np.isnan(value) | (np.abs(value) <= 2.0 * np.pi)), "expected radians within +-2 pi, or NaN", where)
    problem = _first_bad(value, ~np.isfinite(value), "expected finite numbers", where)
    if problem is None and kind == "covariances":
        problem = _covariance_problem(value, where)
    return problem


def _first_bad(value: np.ndarray, bad: np.ndarray, expected: str, where: Callable[[int], str]) -> str | None:
    """``"<expected>, found <the first bad value> at <its row>"``, or None when nothing is ``bad``."""
    if not np.any(bad):
        return None
    row = int(np.argmax(bad.reshape(len(bad), -1).any(axis=1)))
    return f"{expected}, found {value[bad][0]:.6g} at {where(row)}"


def _shape_matches(shape: tuple, trailing: tuple) -> bool:
    """``shape`` is (N, *trailing), a None in ``trailing`` any size >= 1, the same for every None."""
    if len(shape) != 1 + len(trailing):
        return False
    free = {size for size, want in zip(shape[1:], trailing) if want is None}
    fixed_ok = all(size == want for size, want in zip(shape[1:], trailing) if want is not None)
    return fixed_ok and len(free) <= 1 and min(free, default=1) >= 1


def _covariance_problem(cov: np.ndarray, where: Callable[[int], str]) -> str | None:
    """What makes finite ``cov`` (N, D, D) not a covariance per pose, or None.

    A single zero (or singular) covariance is possible, a start pose known exactly, and metrics
    leave it out of NEES; zero at every pose is not a filter's output.
    """
    scale = np.max(np.abs(cov), axis=(1, 2))
    if not np.any(scale > 0.0):
        return "expected covariances, found zeros at every pose"
    unit = cov / np.where(scale > 0.0, scale, 1.0)[:, None, None]  # largest entry 1: relative tolerances
    asymmetric = np.max(np.abs(unit - np.swapaxes(unit, 1, 2)), axis=(1, 2)) > _MATRIX_TOLERANCE
    if np.any(asymmetric):
        return f"expected symmetric matrices, found an asymmetric one at {where(int(np.argmax(asymmetric)))}"
    lowest = np.linalg.eigvalsh(unit)[:, 0]
    negative = lowest < -_EIGENVALUE_TOLERANCE
    if np.any(negative):
        row = int(np.argmax(negative))
        return (f"expected positive semi-definite matrices, found eigenvalue {lowest[row] * scale[row]:.6g} "
                f"at {where(row)}")
    return None


def _check_association_poses(path: Path, associations: Associations, row_lines: list[int], pose_ids: np.ndarray) -> None:
    """Every row of ``associations.csv`` must be an observation of one of the run's poses."""
    known = np.isin(associations.pose_id, pose_ids)
    if not np.all(known):
        row = int(np.argmin(known))
        raise DatasetError(
            path, row_lines[row], f"inconsistent run folder: pose {associations.pose_id[row]} is not one of the "
            f"run's {len(pose_ids)} poses in {STATES_NPZ} ({pose_ids[0]}..{pose_ids[-1]})"
        )


def _check_association_count(path: Path, associations: Associations, summary: dict) -> None:
    """``associations.csv`` has a row per observation of the dataset: as many as ``summary.json``
    counts, where it counts them (a file cut short scores a run on what is left of it)."""
    counts = summary.get("counts")
    expected = counts.get("observations") if isinstance(counts, dict) else None
    found = len(associations.pose_id)
    if isinstance(expected, int) and not isinstance(expected, bool) and expected != found:
        raise DatasetError(path, None, f"inconsistent run folder: expected {expected} rows, one per observation "
                                       f"({SUMMARY_JSON}'s counts), found {found}; run 'camloc run' again")


def _check_association_landmarks(path: Path, associations: Associations, row_lines: list[int], map_ids: np.ndarray) -> None:
    """Every chosen landmark of ``associations.csv`` must be in the run's map, with a Mahalanobis
    distance that is not negative."""
    chosen = associations.landmark != UNASSOCIATED
    unknown = chosen & ~np.isin(associations.landmark, map_ids)
    if np.any(unknown):
        row = int(np.argmax(unknown))
        raise DatasetError(path, row_lines[row], f"inconsistent run folder: landmark {associations.landmark[row]} is not in "
                                                 f"the run's map in {STATES_NPZ} ({len(map_ids)} landmarks)")
    negative = chosen & (associations.mahalanobis < 0.0)
    if np.any(negative):
        row = int(np.argmax(negative))
        raise DatasetError(path, row_lines[row], f"expected a Mahalanobis distance >= 0, found {float(associations.mahalanobis[row])!r}")


def _read_summary(path: Path) -> dict:
    try:
        summary = json.loads(_read_text(path))
    except json.JSONDecodeError as error:
        raise DatasetError(path, error.lineno, f"expected JSON, found an error: {error.msg}") from None
    except RecursionError:
        # json's decoder recurses once per level of nesting; 'camloc run' writes four levels.
        raise DatasetError(path, None, "expected JSON, found arrays or objects nested too deep to decode") from None
    if not isinstance(summary, dict):
        raise DatasetError(path, 1, f"expected a JSON object, found {type(summary).__name__}")
    return summary
