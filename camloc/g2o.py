"""Reading and writing g2o camera-localization files (see docs/format.md), and the one place where a
file's information matrices become covariances.

Reading is done in bulk, one tag at a time: the lines are grouped by their tag, each group is
parsed by one ``np.loadtxt`` call into a structured array (integer ids, float values), and the
values are validated with vectorized checks. Only when a bulk step fails does a per-line pass run,
to name the first offending line. A 240,000-line file reads in about 0.6 s this way on a 2-core
machine (``benchmarks/read_speed.py``); a ``float()`` per field alone costs about as much.

Warnings (unknown tags, non-unit quaternions, partial ground truth) are collected in
``Dataset.warnings`` and also emitted with ``warnings.warn(..., G2oWarning)``.
"""

from __future__ import annotations

import math
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from camloc import geometry, measurement, planar, sym3
from camloc.atomic_files import write_text_atomic
from camloc.dataset import LANDMARK_MARKER, LANDMARK_POINT2, LANDMARK_POINT3, LANDMARK_TAG, Camera, Dataset
from camloc.errors import CamlocError, DatasetError

# g2o's EDGE_SE3:QUAT error is (translation, vector part of the error quaternion). A small rotation
# vector theta has quaternion vector part theta/2, so d(rotvec)/d(qvec) = 2 on the rotation block.
_QVEC_TO_ROTVEC = np.diag([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])


def odometry_cov_from_info(info: np.ndarray) -> np.ndarray:
    """Covariance (..., 6, 6) of (translation, rotation vector) from g2o information (..., 6, 6).

    ``cov = J info^-1 J^T`` with ``J = diag(1, 1, 1, 2, 2, 2)``: the rotation block is 4x, the
    cross blocks 2x the inverse of the file's information.
    """
    cov_g2o = np.linalg.inv(info)
    cov = _QVEC_TO_ROTVEC @ cov_g2o @ _QVEC_TO_ROTVEC
    return 0.5 * (cov + np.swapaxes(cov, -1, -2))


def odometry_info_from_cov(cov: np.ndarray) -> np.ndarray:
    """Inverse of ``odometry_cov_from_info``: g2o information (..., 6, 6) for a covariance of
    (translation, rotation vector)."""
    cov_g2o = np.linalg.inv(_QVEC_TO_ROTVEC) @ cov @ np.linalg.inv(_QVEC_TO_ROTVEC)
    info = np.linalg.inv(cov_g2o)
    return 0.5 * (info + np.swapaxes(info, -1, -2))


def observation_cov_from_info(info: np.ndarray) -> np.ndarray:
    """Covariance (..., 3, 3) of (u, v, depth) from the file's information (..., 3, 3), symmetric
    (in closed form: a LAPACK inverse per observation was a seventh of reading a large file)."""
    return sym3.inverse(info)


class G2oWarning(UserWarning):
    """Something in a g2o file that was tolerated (and is also listed in ``Dataset.warnings``)."""


# --------------------------------------------------------------------------------------------
# Record layouts
# --------------------------------------------------------------------------------------------

TAG_CAMERA = "PARAMS_CAMERACALIB"
TAG_LANDMARK = "VERTEX_TRACKXYZ"
TAG_POSE = "VERTEX_SE3:QUAT"
TAG_ODOMETRY = "EDGE_SE3:QUAT"
TAG_OBSERVATION = measurement.KINDS[measurement.DEPTH].tag              # EDGE_PROJECT_DEPTH
TAG_OBSERVATION_UV = measurement.KINDS[measurement.PIXEL].tag           # EDGE_PROJECT_UV
TAG_OBSERVATION_DISPARITY = measurement.KINDS[measurement.DISPARITY].tag  # EDGE_PROJECT_DISPARITY
OBSERVATION_TAGS = (TAG_OBSERVATION, TAG_OBSERVATION_UV, TAG_OBSERVATION_DISPARITY)
# a planar robot (g2o's 2-D types), and its landmarks and observations (docs/format.md)
TAG_POSE_SE2 = "VERTEX_SE2"
TAG_ODOMETRY_SE2 = "EDGE_SE2"
TAG_LANDMARK_XY = "VERTEX_XY"
TAG_MARKER = "VERTEX_MARKER_SE2"
TAG_OBSERVATION_XY = measurement.KINDS[measurement.POINT2].tag     # EDGE_SE2_XY
TAG_OBSERVATION_MARKER = measurement.KINDS[measurement.MARKER].tag  # EDGE_SE2_MARKER
PLANAR_ROBOT_TAGS = (TAG_POSE_SE2, TAG_ODOMETRY_SE2)
# a tag (an AprilTag): its pose, and a camera's observation of its position and orientation
TAG_TAG = "VERTEX_TAG"
TAG_OBSERVATION_TAG = "EDGE_PROJECT_TAG"
TAG_OBSERVATION_TAG_UV = "EDGE_PROJECT_TAG_UV"  # a camera without depth: the tag's pixel and orientation
# a planar robot's landmarks: a 3-D file's are skipped with a warning, as unknown tags are (no
# sensor of a 3-D robot observes them, and a 3-D file read before they were known reads the same)
PLANAR_ONLY_TAGS = (TAG_LANDMARK_XY, TAG_MARKER)

# Quaternions this close to unit length are kept bit for bit (so that write -> read is exact);
# further than _QUAT_WARN_TOL they are normalized with a warning, below _QUAT_ZERO_TOL refused.
_QUAT_EXACT_TOL = 1e-12
_QUAT_WARN_TOL = 1e-6
_QUAT_ZERO_TOL = 1e-9

# Positions and translations beyond this many metres are refused: geodetic coordinates (about 1e7 m)
# fit with room to spare, while values near the float range overflow the first time they are
# squared, deep inside the localizer.
MAX_COORDINATE = 1e9

# Variances beyond the square of that bound say a measurement carries no information at all; the
# filter's products of such numbers overflow.
MAX_VARIANCE = MAX_COORDINATE**2

# Image coordinates and intrinsics, in pixels or normalized units, are bounded alike; focal lengths
# below MIN_FOCAL_LENGTH (in magnitude) put a pixel's ray beyond the bound in front of the camera.
MAX_IMAGE = 1e9
MIN_FOCAL_LENGTH = 1e-9


def _upper_names(dim: int) -> tuple[str, ...]:
    rows, cols = np.triu_indices(dim)
    return tuple(f"info{r}{c}" for r, c in zip(rows, cols))


@dataclass(frozen=True)
class _Layout:
    """The fields of one tag after the tag itself: ``n_ids`` integer ids, then float values."""

    tag: str
    names: tuple[str, ...]
    n_ids: int
    summary: str  # the layout in words, for error messages
    lengths: tuple[str, ...] = ()  # fields in metres, bounded by MAX_COORDINATE
    image: tuple[str, ...] = ()  # fields in image units (pixels, or normalized), bounded by MAX_IMAGE

    @property
    def n_fields(self) -> int:
        return len(self.names)

    @property
    def dtype(self) -> np.dtype:
        return np.dtype([("ids", "i8", (self.n_ids,)), ("values", "f8", (self.n_fields - self.n_ids,))])


_CAMERA = _Layout(TAG_CAMERA, ("id", "tx", "ty", "tz", "qx", "qy", "qz", "qw", "fx", "fy", "cx", "cy"), 1,
                  "id tx ty tz qx qy qz qw fx fy cx cy", ("tx", "ty", "tz"), ("fx", "fy", "cx", "cy"))
_LANDMARK = _Layout(TAG_LANDMARK, ("id", "x", "y", "z"), 1, "id x y z", ("x", "y", "z"))
_POSE = _Layout(TAG_POSE, ("id", "x", "y", "z", "qx", "qy", "qz", "qw"), 1, "id x y z qx qy qz qw", ("x", "y", "z"))
_ODOMETRY = _Layout(TAG_ODOMETRY, ("from", "to", "dx", "dy", "dz", "qx", "qy", "qz", "qw") + _upper_names(6), 2,
                    "from to dx dy dz qx qy qz qw + 21 information numbers", ("dx", "dy", "dz"))
_OBSERVATION = _Layout(TAG_OBSERVATION, ("pose", "landmark", "camera", "u", "v", "depth") + _upper_names(3), 3,
                       "pose landmark camera u v depth + 6 information numbers", ("depth",), ("u", "v"))
_OBSERVATION_UV = _Layout(TAG_OBSERVATION_UV, ("pose", "landmark", "camera", "u", "v") + _upper_names(2), 3,
                          "pose landmark camera u v + 3 information numbers", (), ("u", "v"))
_OBSERVATION_DISPARITY = _Layout(
    TAG_OBSERVATION_DISPARITY, ("pose", "landmark", "camera", "u", "v", "inverse_depth") + _upper_names(3), 3,
    "pose landmark camera u v 1/depth + 6 information numbers", (), ("u", "v", "inverse_depth"))
_POSE_SE2 = _Layout(TAG_POSE_SE2, ("id", "x", "y", "theta"), 1, "id x y theta", ("x", "y"))
_ODOMETRY_SE2 = _Layout(TAG_ODOMETRY_SE2, ("from", "to", "dx", "dy", "dtheta") + _upper_names(3), 2,
                        "from to dx dy dtheta + 6 information numbers", ("dx", "dy"))
_LANDMARK_XY = _Layout(TAG_LANDMARK_XY, ("id", "x", "y"), 1, "id x y", ("x", "y"))
_MARKER = _Layout(TAG_MARKER, ("id", "x", "y", "psi"), 1, "id x y psi", ("x", "y"))
_OBSERVATION_XY = _Layout(TAG_OBSERVATION_XY, ("pose", "landmark", "x", "y") + _upper_names(2), 2,
                          "pose landmark x y + 3 information numbers", ("x", "y"))
_OBSERVATION_MARKER = _Layout(TAG_OBSERVATION_MARKER, ("pose", "landmark", "x", "y", "psi") + _upper_names(3), 2,
                              "pose landmark x y psi + 6 information numbers", ("x", "y"))
_TAG = _Layout(TAG_TAG, ("id", "x", "y", "z", "qx", "qy", "qz", "qw"), 1, "id x y z qx qy qz qw", ("x", "y", "z"))
_OBSERVATION_TAG = _Layout(TAG_OBSERVATION_TAG, ("pose", "landmark", "camera", "u", "v", "depth", "qx", "qy", "qz", "qw")
                           + _upper_names(6), 3, "pose landmark camera u v depth qx qy qz qw + 21 information numbers",
                           ("depth",), ("u", "v"))
_OBSERVATION_TAG_UV = _Layout(TAG_OBSERVATION_TAG_UV, ("pose", "landmark", "camera", "u", "v", "qx", "qy", "qz", "qw")
                              + _upper_names(5), 3, "pose landmark camera u v qx qy qz qw + 15 information numbers",
                              (), ("u", "v"))
# a tag observation's record by the kind of its position's half
_TAG_OBSERVATION_LAYOUTS = {measurement.DEPTH: _OBSERVATION_TAG, measurement.PIXEL: _OBSERVATION_TAG_UV}
# each observation record's layout by its measurement kind (camloc.measurement)
_OBSERVATION_LAYOUTS = {measurement.DEPTH: _OBSERVATION, measurement.PIXEL: _OBSERVATION_UV,
                        measurement.DISPARITY: _OBSERVATION_DISPARITY, measurement.POINT2: _OBSERVATION_XY,
                        measurement.MARKER: _OBSERVATION_MARKER}
# the map's records, by the kind of landmark each gives (camloc.dataset)
_LANDMARK_LAYOUTS = {LANDMARK_POINT3: _LANDMARK, LANDMARK_POINT2: _LANDMARK_XY, LANDMARK_MARKER: _MARKER, LANDMARK_TAG: _TAG}
_LAYOUTS = {layout.tag: layout for layout in (_CAMERA, _LANDMARK, _POSE, _ODOMETRY, _POSE_SE2, _ODOMETRY_SE2, _LANDMARK_XY,
                                              _MARKER, _TAG, *_OBSERVATION_LAYOUTS.values(), *_TAG_OBSERVATION_LAYOUTS.values())}
KNOWN_TAGS = tuple(_LAYOUTS)


@dataclass
class _Lines:
    """The records of one tag: the text after the tag, and the 1-based line numbers."""

    rests: list[str] = field(default_factory=list)
    numbers: list[int] = field(default_factory=list)


@dataclass(frozen=True)
class _Table:
    """One tag parsed: ids (n, n_ids) int64, values (n, n_values) float64, line numbers (n,)."""

    ids: np.ndarray
    values: np.ndarray
    lines: np.ndarray


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


def read_g2o(path: str | os.PathLike) -> Dataset:
    """Read a g2o camera-localization file (format in docs/format.md) into a ``Dataset``.

    Parameters
    ----------
    path : the .g2o file.

    Returns
    -------
    The dataset, poses in the order of the odometry chain; observations and landmarks in file
    order. The chain starts at its root, the one pose that edges leave and none reach, whose
    ``VERTEX_SE3:QUAT`` is the known start pose wherever it is in the file; without such a root
    (no edges, or several chains), at the file's first ``VERTEX_SE3:QUAT``.

    Raises
    ------
    DatasetError
        For anything that makes the file unusable, with ``path:line`` and what was expected and
        found. Of several lines with bad fields (count, integer ids, numbers, NaN/inf), the
        earliest in the file is reported; checks across records (quaternions, information
        matrices, duplicate ids, the chain, observation references) come after, in that order.

    Warns
    -----
    G2oWarning
        Once per unknown tag (with its count), once per tag with non-unit quaternions (they are
        normalized), and when only some poses have a ground-truth vertex (truth is then dropped).
    """
    path = Path(path)
    groups = _group_lines(path, _read_text(path))
    messages: list[str] = _unknown_tag_warnings(groups)
    is_planar = _is_planar(path, groups)
    messages += _planar_records_skipped(groups, is_planar)
    tables = _parse_tables(path, {tag: lines for tag, lines in groups.items() if is_planar or tag not in PLANAR_ONLY_TAGS}, is_planar)
    robot = (TAG_POSE_SE2, TAG_ODOMETRY_SE2) if is_planar else (TAG_POSE, TAG_ODOMETRY)  # the tags messages name

    cameras = _build_cameras(path, tables[TAG_CAMERA], messages)
    landmarks = _build_landmarks(path, tables, messages, is_planar)
    vertex_ids, vertex_xyz, vertex_quat, odometry = _build_robot(path, tables, is_planar, messages)
    start = _start_vertex(path, vertex_ids, tables[robot[0]].lines, odometry, robot)
    pose_ids, edge_order = _follow_chain(path, int(vertex_ids[start]), odometry, robot)
    _check_vertices_on_chain(path, vertex_ids, pose_ids, tables[robot[0]].lines, robot)
    truth_xyz, truth_quat = _ground_truth(pose_ids, vertex_ids, vertex_xyz, vertex_quat, messages, robot[0])
    observations = _build_all_observations(path, tables, pose_ids, cameras, messages, is_planar)

    for message in messages:
        warnings.warn(f"{path}: {message}", G2oWarning, stacklevel=2)
    odom_info = odometry["info"][edge_order]
    return Dataset(
        source=str(path),
        cameras=cameras,
        landmark_ids=landmarks["ids"],
        landmark_xyz=landmarks["xyz"],
        pose_ids=pose_ids,
        start_xyz=vertex_xyz[start],
        start_quat_xyzw=vertex_quat[start],
        truth_xyz=truth_xyz,
        truth_quat_xyzw=truth_quat,
        odom_translation=odometry["translation"][edge_order],
        odom_quat_xyzw=odometry["quat"][edge_order],
        odom_info=odom_info,
        odom_cov=odometry["cov"][edge_order],
        obs_pose_index=observations["pose_index"],
        obs_camera=observations["camera"],
        obs_z=observations["z"],
        obs_info=observations["info"],
        obs_cov=observations["cov"],
        obs_true_landmark=observations["landmark"],
        obs_kind=observations["kind"],
        tag_counts={tag: len(lines.numbers) for tag, lines in groups.items()},
        warnings=tuple(messages),
        planar=is_planar,
        landmark_kind=landmarks["kind"],
        landmark_heading=landmarks["heading"],
        landmark_quat_xyzw=landmarks["quat"],
        obs_partner=np.where(observations["kind"] == measurement.TAG_ROTATION, np.arange(observations["kind"].size) - 1, -1),
    )


def _build_robot(path: Path, tables: dict[str, _Table], is_planar: bool, messages: list[str]) -> tuple:
    """The pose vertices (ids, xyz, quaternions) and the odometry edges of a 3-D or planar robot."""
    if is_planar:
        return (*_build_planar_vertices(path, tables[TAG_POSE_SE2]), _build_planar_odometry(path, tables[TAG_ODOMETRY_SE2]))
    return (*_build_pose_vertices(path, tables[TAG_POSE], messages), _build_odometry(path, tables[TAG_ODOMETRY], messages))


def _planar_records_skipped(groups: dict[str, _Lines], is_planar: bool) -> list[str]:
    """One message per planar-only tag in a 3-D file: its records are skipped (``PLANAR_ONLY_TAGS``)."""
    if is_planar:
        return []
    return [f"line {lines.numbers[0]}: skipped {len(lines.numbers)} record(s) with tag {tag!r}, a planar robot's "
            "landmark (this file's robot is 3-D)" for tag, lines in groups.items() if tag in PLANAR_ONLY_TAGS and lines.numbers]


def _is_planar(path: Path, groups: dict[str, _Lines]) -> bool:
    """Whether the file's robot is planar (``VERTEX_SE2``/``EDGE_SE2``); a file with both kinds of
    robot record is a DatasetError at the first record of the kind that comes second."""
    planar_lines = [n for tag in PLANAR_ROBOT_TAGS for n in groups.get(tag, _Lines()).numbers]
    spatial_lines = [n for tag in (TAG_POSE, TAG_ODOMETRY) for n in groups.get(tag, _Lines()).numbers]
    if planar_lines and spatial_lines:
        line = min(planar_lines) if min(planar_lines) > min(spatial_lines) else min(spatial_lines)
        raise DatasetError(path, line, f"expected one kind of robot, planar ({TAG_POSE_SE2}, {TAG_ODOMETRY_SE2}) or 3-D "
                                       f"({TAG_POSE}, {TAG_ODOMETRY}), found both")
    return bool(planar_lines)


# Files a user may hand over for a g2o file, told apart by their first bytes.
COMPRESSED_OR_WIDE = (
    (b"\x1f\x8b", "gzip-compressed; decompress it first (gunzip)"),
    (b"PK\x03\x04", "a zip archive; extract the g2o file first"),
    (b"\xff\xfe", "UTF-16 text; save it as UTF-8"),
    (b"\xfe\xff", "UTF-16 text; save it as UTF-8"),
)


def _read_text(path: Path) -> str:
    """The file's text; a missing file, a directory or a binary file is a DatasetError."""
    if path.is_dir():
        raise DatasetError(path, None, "expected a g2o file, found a directory")
    if path.is_char_device() or path.is_block_device():  # /dev/zero would be read forever (a pipe is fine)
        raise DatasetError(path, None, "expected a g2o file, found a device")
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise DatasetError(path, None, "no such file") from None
    except OSError as error:
        raise DatasetError(path, None, f"cannot be read: {error.strerror or error}") from None
    for magic, kind in COMPRESSED_OR_WIDE:
        if data.startswith(magic):
            raise DatasetError(path, 1, f"not a text g2o file: {kind}")
    nul = data.find(b"\0")
    if nul >= 0:
        raise DatasetError(path, data.count(b"\n", 0, nul) + 1, "not a text g2o file: found a NUL byte")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        line = data.count(b"\n", 0, error.start) + 1
        raise DatasetError(path, line, f"not a text g2o file: byte 0x{data[error.start]:02x} is not UTF-8") from None


def _group_lines(path: Path, text: str) -> dict[str, _Lines]:
    """Records grouped by tag, in order of first appearance; blank and ``#`` lines dropped."""
    groups: dict[str, _Lines] = {tag: _Lines() for tag in _LAYOUTS}
    has_comments = "#" in text  # a file without any skips the search on every line
    if "\r" in text:
        # every line end a line end, as Python's universal newlines and editors count them: CRLF,
        # and a carriage return alone (classic Mac OS, or one pasted into an LF file, whose two
        # records would otherwise be read as one line of too many fields)
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    # split("\n") rather than splitlines(): the latter also breaks at \v, \f, \x1c... and would
    # make line numbers disagree with an editor's.
    for number, line in enumerate(text.split("\n"), start=1):
        # Fast path for the usual "TAG fields..." line; anything else (tabs, leading blanks,
        # comments, unknown tags) goes through split(), which accepts any whitespace.
        tag, _, rest = line.partition(" ")
        lines = groups.get(tag)
        if lines is None:
            head = line.split(None, 1)
            if not head or head[0].startswith("#"):
                continue
            tag, rest = head[0], (head[1] if len(head) == 2 else "")
            lines = groups.setdefault(tag, _Lines())
        if has_comments and "#" in rest:
            rest = _END_OF_LINE_COMMENT.sub("", rest)
        lines.rests.append(rest)
        lines.numbers.append(number)
    present = sorted((lines.numbers[0], tag) for tag, lines in groups.items() if lines.numbers)
    if not present:
        raise DatasetError(path, None, "expected g2o records, found an empty file (or only comments)")
    return {tag: groups[tag] for _, tag in present}


# A comment after a record's fields, from a field that starts with '#' (g2o reads a record's
# fields and ignores the rest of its line; "0.5#x" stays a bad number).
_END_OF_LINE_COMMENT = re.compile(r"(?:^|\s)#.*")


def _unknown_tag_warnings(groups: dict[str, _Lines]) -> list[str]:
    """One message per tag camloc does not know: such records are skipped, as g2o does."""
    return [
        f"line {lines.numbers[0]}: skipped {len(lines.numbers)} record(s) with unknown tag {tag!r}{_SKIPPED_G2O_TAGS.get(tag, '')}"
        for tag, lines in groups.items()
        if tag not in _LAYOUTS
    ]


# g2o's own records that camloc skips, and why (said with the skipped tag's warning)
_SKIPPED_G2O_TAGS = {"FIX": " (g2o's fixed vertices: camloc holds the start pose at its vertex and estimates every other pose)"}


def _parse_tables(path: Path, groups: dict[str, _Lines], is_planar: bool = False) -> dict[str, _Table]:
    """Every known tag parsed in bulk; of several malformed lines, the earliest is reported."""
    tables: dict[str, _Table] = {}
    errors: list[DatasetError] = []
    for tag, layout in _LAYOUTS.items():
        try:
            tables[tag] = _parse_table(path, layout, groups.get(tag, _Lines()))
        except DatasetError as error:
            errors.append(error)
    if errors:
        raise min(errors, key=lambda error: error.line if error.line is not None else 0)
    # a planar robot may observe without a camera (EDGE_SE2_XY, EDGE_SE2_MARKER)
    required = ((TAG_POSE_SE2, "the start pose"),) if is_planar else ((TAG_CAMERA, "at least one camera"), (TAG_POSE, "the start pose"))
    for tag, what in required:
        if tag not in groups:
            raise DatasetError(path, None, f"expected a {tag} record ({what}), found none")
    if not is_planar:
        for tag in (TAG_OBSERVATION_XY, TAG_OBSERVATION_MARKER):
            if tag in groups:
                raise DatasetError(path, groups[tag].numbers[0], f"{tag} is a planar robot's observation: expected "
                                                                 f"{TAG_POSE_SE2} and {TAG_ODOMETRY_SE2} poses, found {TAG_POSE}")
    return tables


def _parse_table(path: Path, layout: _Layout, lines: _Lines) -> _Table:
    """Parse all records of one tag with one ``np.loadtxt`` call, then reject non-finite values."""
    n, n_values = len(lines.rests), layout.n_fields - layout.n_ids
    if n == 0:
        return _Table(np.zeros((0, layout.n_ids), np.int64), np.zeros((0, n_values)), np.zeros(0, np.int64))
    try:
        records = np.loadtxt(lines.rests, dtype=layout.dtype, comments=None, ndmin=1)
    except ValueError:
        records = None
    if records is None or records.shape[0] != n:  # loadtxt skips empty rests: a tag alone
        _raise_first_malformed_line(path, layout, lines)
    table = _Table(records["ids"].reshape(n, layout.n_ids), records["values"].reshape(n, n_values),
                   np.asarray(lines.numbers, dtype=np.int64))
    value_names = layout.names[layout.n_ids :]
    bound = np.array([MAX_COORDINATE if name in layout.lengths else MAX_IMAGE if name in layout.image else np.inf
                      for name in value_names])
    bad = ~np.isfinite(table.values) | (np.abs(table.values) > bound)
    bad_rows, bad_cols = np.nonzero(bad)
    if bad_rows.size:
        row, col = bad_rows[0], bad_cols[0]
        raise DatasetError(path, int(table.lines[row]), _value_reason(layout, value_names[col], float(table.values[row, col])))
    return table


def _value_reason(layout: _Layout, name: str, value: float) -> str | None:
    """Why one parsed value cannot be used, or None when it can."""
    if not math.isfinite(value):
        return f"{layout.tag} field {name}: expected a finite number, found {value}"
    if name in layout.lengths and abs(value) > MAX_COORDINATE:
        return f"{layout.tag} field {name}: expected metres within +-{MAX_COORDINATE:.0e}, found {value:.6g}"
    if name in layout.image and abs(value) > MAX_IMAGE:
        return f"{layout.tag} field {name}: expected image units within +-{MAX_IMAGE:.0e}, found {value:.6g}"
    return None


# What an id looks like, and the ids that fit in int64 (the run folder's readers share both).
INTEGER = re.compile(r"[+-]?[0-9]+")
INT64_RANGE = (-(2**63), 2**63 - 1)
# A pose's id is its timestamp in the TUM files (a float): beyond 2^53 two ids could read back as one.
EXACT_TIMESTAMP_ID = 2**53


def _raise_first_malformed_line(path: Path, layout: _Layout, lines: _Lines) -> None:
    """The slow path: find the first line the bulk parser refused and say what is wrong with it."""
    for rest, number in zip(lines.rests, lines.numbers):
        reason = _malformed_reason(layout, rest.split())
        if reason is not None:
            raise DatasetError(path, number, reason)
    # The rules above mirror np.loadtxt's; should they ever disagree, let numpy name the line.
    for rest, number in zip(lines.rests, lines.numbers):
        try:
            np.loadtxt([rest], dtype=layout.dtype, comments=None)
        except ValueError as error:
            raise DatasetError(path, number, f"{layout.tag}: expected {layout.summary}, found {error}") from None
    raise DatasetError(path, lines.numbers[0], f"could not parse the {layout.tag} records")


def _malformed_reason(layout: _Layout, fields: list[str]) -> str | None:
    """Why one record's fields do not fit the layout, or None when they do."""
    if len(fields) != layout.n_fields:
        return (f"{layout.tag} expects {layout.n_fields} fields after the tag "
                f"({layout.summary}), found {len(fields)}{_full_matrix_hint(layout, len(fields))}")
    for name, token in zip(layout.names[: layout.n_ids], fields):
        if not INTEGER.fullmatch(token):
            return f"{layout.tag} field {name}: expected an integer id, found {_shown(token)}"
        if not INT64_RANGE[0] <= int(token) <= INT64_RANGE[1]:
            return f"{layout.tag} field {name}: expected an id that fits in 64 bits, found {_shown(token)}"
    for name, token in zip(layout.names[layout.n_ids:], fields[layout.n_ids:]):
        value = parse_number(token)
        if value is None:
            return f"{layout.tag} field {name}: expected a number, found {_shown(token)}"
        reason = _value_reason(layout, name, value)  # as in _parse_table, so that the earliest line wins
        if reason is not None:
            return reason
    return None


def _shown(token: str, limit: int = 40) -> str:
    """A field as an error message quotes it: whole when short, else its start and its length (a
    line of a megabyte must not become a message of a megabyte)."""
    if len(token) <= limit:
        return repr(token)
    return f"{token[:limit]!r}... ({len(token)} characters)"


def _full_matrix_hint(layout: _Layout, n_found: int) -> str:
    """Where the fields after the values are a full information matrix (d * d numbers) instead
    of its upper triangle, say so: another tool's habit, not damage."""
    information = [name for name in layout.names if name.startswith("info")]
    if not information:
        return ""
    dim = int(information[-1][-1]) + 1
    if n_found - (layout.n_fields - len(information)) != dim * dim:
        return ""
    return (f": {dim * dim} information numbers, a full {dim}x{dim} matrix? expected its upper triangle, "
            f"row by row ({len(information)} numbers)")


def parse_number(token: str) -> float | None:
    """``token`` as a float where np.loadtxt parses it as one, else None: Python's float() also
    takes 1_000 and non-ASCII digits, which no tool writes (more likely damage than data)."""
    if not token.isascii() or "_" in token:
        return None
    try:
        return float(token)
    except ValueError:
        return None


# --- validation helpers shared by the tags --------------------------------------------------


def _check_unique(path: Path, ids: np.ndarray, lines: np.ndarray, what: str) -> None:
    """Refuse the first record whose id repeats an earlier one."""
    order = np.argsort(ids, kind="stable")
    sorted_ids = ids[order]
    repeats = np.flatnonzero(sorted_ids[1:] == sorted_ids[:-1])
    if repeats.size:
        row = int(order[repeats + 1].min())
        first = int(lines[np.flatnonzero(ids == ids[row])[0]])
        raise DatasetError(path, int(lines[row]), f"duplicate {what} {ids[row]}: expected unique ids, "
                                                  f"found it already at line {first}")


def _unit_quaternions(path: Path, tag: str, quat: np.ndarray, lines: np.ndarray,
                      messages: list[str]) -> np.ndarray:
    """Quaternions (n, 4) normalized where needed; a zero one is a DatasetError."""
    # the norm of components near the float range (1e155 and up) overflows: scale by the largest first
    largest = np.max(np.abs(quat), axis=1)
    with np.errstate(over="ignore"):
        norm = largest * np.linalg.norm(quat / np.where(largest > 0.0, largest, 1.0)[:, None], axis=1)
    zero = np.flatnonzero(norm < _QUAT_ZERO_TOL)
    if zero.size:
        raise DatasetError(path, int(lines[zero[0]]),
                           f"{tag}: expected a unit quaternion qx qy qz qw, found norm {norm[zero[0]]:.3g}")
    deviation = np.abs(norm - 1.0)
    far = np.flatnonzero(deviation > _QUAT_WARN_TOL)
    if far.size:
        messages.append(f"line {lines[far[0]]}: {far.size} {tag} quaternion(s) not unit length "
                        f"(largest |norm - 1| = {deviation.max():.3g}), normalized")
    fix = deviation > _QUAT_EXACT_TOL
    quat = quat.copy()
    quat[fix] = geometry.normalized_quaternions(quat[fix])
    return quat


def _info_from_upper(upper: np.ndarray, dim: int) -> np.ndarray:
    """Symmetric matrices (n, dim, dim) from their upper triangles (n, dim(dim+1)/2), row by row."""
    rows, cols = np.triu_indices(dim)
    info = np.empty((upper.shape[0], dim, dim))
    info[:, rows, cols] = upper
    info[:, cols, rows] = upper
    return info


def _check_positive_definite(path: Path, tag: str, info: np.ndarray, lines: np.ndarray) -> None:
    """Refuse the first information matrix that has no Cholesky factor."""
    row = _first_without_cholesky(info)
    if row is not None:
        eigenvalues = np.linalg.eigvalsh(info[row])
        raise DatasetError(path, int(lines[row]), f"{tag}: expected a symmetric positive definite information "
                                                  f"matrix, found smallest eigenvalue {eigenvalues[0]:.3g}")


def _first_without_cholesky(matrices: np.ndarray) -> int | None:
    """The index of the first of the (n, d, d) matrices that has no Cholesky factor, or None."""
    try:
        np.linalg.cholesky(matrices)
        return None
    except np.linalg.LinAlgError:
        pass
    for row, matrix in enumerate(matrices):  # the batch failed: find which one
        try:
            np.linalg.cholesky(matrix)
        except np.linalg.LinAlgError:
            return row
    return None


# --- one function per tag -------------------------------------------------------------------


def _covariances(path: Path, tag: str, info: np.ndarray, lines: np.ndarray, from_info) -> np.ndarray:
    """``from_info(info)``, refusing the first covariance that is not positive definite in floating
    point or whose variances exceed ``MAX_VARIANCE``: an information matrix near either end of the
    float range, which the filter's products would overflow."""
    with np.errstate(over="ignore", under="ignore", divide="ignore", invalid="ignore"):
        cov = from_info(info)
    usable = np.all(np.isfinite(cov), axis=(1, 2)) & np.all(np.diagonal(cov, axis1=1, axis2=2) <= MAX_VARIANCE, axis=1)
    bad = np.flatnonzero(~usable)
    row = int(bad[0]) if bad.size else _first_without_cholesky(cov)
    if row is not None:
        diagonal = " ".join(f"{value:.3g}" for value in np.diagonal(info[row]))
        raise DatasetError(path, int(lines[row]), f"{tag}: expected an information matrix whose inverse is positive definite "
                                                  f"with variances up to {MAX_VARIANCE:.0e}, found information diagonal {diagonal}")
    return cov


def _build_cameras(path: Path, table: _Table, messages: list[str]) -> dict[int, Camera]:
    ids = table.ids[:, 0]
    _check_unique(path, ids, table.lines, "camera id")
    flat = np.flatnonzero((np.abs(table.values[:, 7]) < MIN_FOCAL_LENGTH) | (np.abs(table.values[:, 8]) < MIN_FOCAL_LENGTH))
    if flat.size:
        row = flat[0]
        raise DatasetError(path, int(table.lines[row]), f"{TAG_CAMERA} {ids[row]}: expected non-zero focal lengths fx fy "
                                                        f"(at least {MIN_FOCAL_LENGTH:g} in magnitude), "
                                                        f"found fx={table.values[row, 7]:g} fy={table.values[row, 8]:g}")
    negative = np.flatnonzero((table.values[:, 7] < 0.0) | (table.values[:, 8] < 0.0))
    if negative.size:  # legal (an image axis flipped), but more often a sign lost in a conversion
        row = int(negative[0])
        messages.append(f"line {table.lines[row]}: {negative.size} {TAG_CAMERA} record(s) with a negative focal length "
                        f"(camera {ids[row]}: fx={table.values[row, 7]:g} fy={table.values[row, 8]:g}); kept as written, "
                        "which flips that image axis")
    quat = _unit_quaternions(path, TAG_CAMERA, table.values[:, 3:7], table.lines, messages)
    return {
        int(camera_id): Camera(id=int(camera_id), translation=values[0:3].copy(), quat_xyzw=q,
                               fx=float(values[7]), fy=float(values[8]), cx=float(values[9]), cy=float(values[10]))
        for camera_id, values, q in zip(ids, table.values, quat)
    }


def _build_landmarks(path: Path, tables: dict[str, _Table], messages: list[str], is_planar: bool = False) -> dict[str, np.ndarray]:
    """The map of every landmark record in file order: ids, xyz (planar ones at z = 0), kind and
    heading (NaN but for markers); ids unique across the records."""
    parts = []
    for kind, layout in _LANDMARK_LAYOUTS.items():
        table = tables[layout.tag]
        n = table.ids.shape[0]
        xyz = np.zeros((n, 3))
        columns = 3 if kind in (LANDMARK_POINT3, LANDMARK_TAG) else 2  # a planar landmark's z is 0
        xyz[:, :columns] = table.values[:, :columns]
        heading = table.values[:, 2].copy() if kind == LANDMARK_MARKER else np.full(n, np.nan)
        quat = _unit_quaternions(path, TAG_TAG, table.values[:, 3:7], table.lines, messages) if kind == LANDMARK_TAG else np.full((n, 4), np.nan)
        parts.append((table.ids[:, 0], xyz, np.full(n, kind, np.int64), heading, quat, table.lines))
    ids, xyz, kinds, heading, quat, lines = (np.concatenate(column) for column in zip(*parts))
    order = np.argsort(lines, kind="stable")
    ids, xyz, kinds, heading, quat, lines = ids[order], xyz[order], kinds[order], heading[order], quat[order], lines[order]
    _check_unique(path, ids, lines, "landmark id")
    if ids.size == 0:
        # A map-less file is valid (no survey: camloc simulate --no-map); its observations read as
        # observations of ids absent from the map, as clutter's and a withheld landmark's do.
        tags = (TAG_LANDMARK_XY, TAG_MARKER, TAG_LANDMARK) if is_planar else (TAG_LANDMARK, TAG_TAG)
        messages.append(f"no landmark record ({', '.join(tags)}): the map is empty")
    return {"ids": ids, "xyz": xyz, "kind": kinds, "heading": heading, "quat": quat}


def _build_pose_vertices(path: Path, table: _Table,
                         messages: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ids = table.ids[:, 0].copy()
    _check_unique(path, ids, table.lines, "pose vertex id")
    beyond = np.flatnonzero(np.abs(ids) > EXACT_TIMESTAMP_ID)
    if beyond.size:
        row = int(beyond[0])
        raise DatasetError(path, int(table.lines[row]), f"{TAG_POSE} id: expected a pose id within +-2^53 "
                           f"({EXACT_TIMESTAMP_ID}), which the trajectory files' timestamps hold exactly, found {ids[row]}")
    quat = _unit_quaternions(path, TAG_POSE, table.values[:, 3:7], table.lines, messages)
    return ids, table.values[:, 0:3].copy(), quat


def _build_planar_vertices(path: Path, table: _Table) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``VERTEX_SE2`` records as lifted poses: ids, xyz (z = 0) and quaternions about z."""
    ids = table.ids[:, 0].copy()
    _check_unique(path, ids, table.lines, "pose vertex id")
    xyz = np.column_stack([table.values[:, :2], np.zeros(ids.size)])
    return ids, xyz, planar.quat_of_heading(table.values[:, 2])


def _build_planar_odometry(path: Path, table: _Table) -> dict[str, np.ndarray]:
    """``EDGE_SE2`` records as lifted increments, with the file's (x, y, theta) information
    (g2o's SE2 error is the increment's (dx, dy, dtheta) itself: no reparametrization) and its
    inverse lifted to (translation, rotation vector) (``planar.lifted_cov``)."""
    _check_one_edge_from_each_pose(path, TAG_ODOMETRY_SE2, table)
    info = _info_from_upper(table.values[:, 3:9], 3)
    _check_positive_definite(path, TAG_ODOMETRY_SE2, info, table.lines)
    cov = _covariances(path, TAG_ODOMETRY_SE2, info, table.lines, lambda i: 0.5 * (np.linalg.inv(i) + np.swapaxes(np.linalg.inv(i), -1, -2)))
    n = table.ids.shape[0]
    return {
        "from": table.ids[:, 0], "to": table.ids[:, 1], "lines": table.lines,
        "translation": np.column_stack([table.values[:, :2], np.zeros(n)]),
        "quat": planar.quat_of_heading(table.values[:, 2]),
        "info": info, "cov": planar.lifted_cov(cov),
    }


def _build_odometry(path: Path, table: _Table, messages: list[str]) -> dict[str, np.ndarray]:
    """Edges in file order: from, to, translation, quat, info (g2o parametrization), lines."""
    _check_one_edge_from_each_pose(path, TAG_ODOMETRY, table)
    info = _info_from_upper(table.values[:, 7:28], 6)
    _check_positive_definite(path, TAG_ODOMETRY, info, table.lines)
    return {
        "from": table.ids[:, 0], "to": table.ids[:, 1], "lines": table.lines,
        "translation": table.values[:, 0:3].copy(),
        "quat": _unit_quaternions(path, TAG_ODOMETRY, table.values[:, 3:7], table.lines, messages),
        "info": info,
        "cov": _covariances(path, TAG_ODOMETRY, info, table.lines, odometry_cov_from_info),
    }


def _build_all_observations(path: Path, tables: dict[str, _Table], pose_ids: np.ndarray,
                            cameras: dict[int, Camera], messages: list[str], is_planar: bool = False) -> dict[str, np.ndarray]:
    """The observations of every kind (``_OBSERVATION_LAYOUTS``) in file order. A planar kind's
    (no camera) sensor is ``measurement.ROBOT_FRAME_SENSOR``."""
    parts = [_build_observations(path, tables[layout.tag], layout, kind, pose_ids, cameras, messages)
             for kind, layout in _OBSERVATION_LAYOUTS.items()]
    parts += [_build_tag_observations(path, tables[layout.tag], kind, pose_ids, cameras, messages)
              for kind, layout in _TAG_OBSERVATION_LAYOUTS.items()]
    order = np.argsort(np.concatenate([part.pop("line") for part in parts]), kind="stable")
    return {name: np.concatenate([part[name] for part in parts])[order] for name in parts[0]}


def _build_observations(path: Path, table: _Table, layout: _Layout, kind: int, pose_ids: np.ndarray,
                        cameras: dict[int, Camera], messages: list[str]) -> dict[str, np.ndarray]:
    """Observations of one record kind in file order, their pose as an index into the chain
    ``pose_ids``, their measurement and information in ``camloc.measurement``'s padded layout."""
    tag = layout.tag
    dof = measurement.KINDS[kind].dof
    if measurement.KINDS[kind].measures_range:
        behind = np.flatnonzero(table.values[:, 2] <= 0.0)
        if behind.size:  # kept, as clutter is: no landmark in front of the camera fits them
            what = "depth" if kind == measurement.DEPTH else "inverse depth"
            messages.append(f"line {table.lines[behind[0]]}: {behind.size} {tag} record(s) with {what} <= 0, "
                            "where only landmarks in front of the camera (depth > 0) can be seen; no landmark will fit them")
    if kind == measurement.DISPARITY:
        _check_inverse_depths(path, table)
    pose, landmark = table.ids[:, 0], table.ids[:, 1].copy()
    camera = table.ids[:, 2].copy() if layout.n_ids == 3 else np.full(pose.size, measurement.ROBOT_FRAME_SENSOR, np.int64)
    sorter = np.argsort(pose_ids)
    slot = np.minimum(np.searchsorted(pose_ids, pose, sorter=sorter), pose_ids.size - 1)
    pose_index = sorter[slot]
    unknown = np.flatnonzero(pose_ids[pose_index] != pose)
    if unknown.size:
        row = unknown[0]
        raise DatasetError(path, int(table.lines[row]),
                           f"{tag} from pose {pose[row]}: expected a pose of the odometry chain, "
                           f"found an id that no pose vertex or odometry edge defines")
    camera_ids = np.array(sorted(cameras), dtype=np.int64)
    unknown = np.flatnonzero(~np.isin(camera, camera_ids) & (layout.n_ids == 3))
    if unknown.size:
        row = unknown[0]
        raise DatasetError(path, int(table.lines[row]),
                           f"{tag} through camera {camera[row]}: expected a {TAG_CAMERA} id "
                           f"({', '.join(map(str, camera_ids))}), found an unknown camera")
    info = measurement.padded_information(table.values[:, dof:], kind)
    _check_positive_definite(path, tag, info, table.lines)
    z = np.zeros((table.values.shape[0], measurement.MAX_DIM))
    z[:, :dof] = table.values[:, :dof]
    return {"pose_index": pose_index.astype(np.int64), "camera": camera, "landmark": landmark,
            "z": z, "info": info, "cov": _covariances(path, tag, info, table.lines, observation_cov_from_info),
            "kind": np.full(table.values.shape[0], kind, dtype=np.int64), "line": table.lines}


def _check_inverse_depths(path: Path, table: _Table) -> None:
    """Refuse the first inverse depth whose depth is beyond ``MAX_COORDINATE`` (as a depth field
    beyond it is): the filter squares it (1e-300 overflowed in the mapping pass). Zero and
    negative ones are kept, with the warning of ``_build_observations``."""
    far = np.flatnonzero((table.values[:, 2] > 0.0) & (table.values[:, 2] < 1.0 / MAX_COORDINATE))
    if far.size:
        row = int(far[0])
        raise DatasetError(path, int(table.lines[row]), f"{TAG_OBSERVATION_DISPARITY} field inverse_depth: expected 1/depth "
                           f"of a depth within {MAX_COORDINATE:.0e} m (at least {1.0 / MAX_COORDINATE:.0e}; 0 or less is "
                           f"kept, with a warning), found {table.values[row, 2]:.6g}")


def _build_tag_observations(path: Path, table: _Table, kind: int, pose_ids: np.ndarray, cameras: dict[int, Camera],
                            messages: list[str]) -> dict[str, np.ndarray]:
    """``EDGE_PROJECT_TAG`` (``kind`` depth) or ``EDGE_PROJECT_TAG_UV`` (pixel) records as two
    observations each, consecutive and on the record's line: an observation of the tag's position
    of that kind ((u, v, depth) or (u, v)) and its orientation's (``measurement.TAG_ROTATION``: z
    the rotation vector of the measured orientation), each with its block of the information,
    which must have no position x orientation correlation."""
    layout, dof = _TAG_OBSERVATION_LAYOUTS[kind], measurement.KINDS[kind].dof
    tag, dim = layout.tag, dof + 3
    info = _info_from_upper(table.values[:, dof + 4:], dim)
    _check_positive_definite(path, tag, info, table.lines)
    coupled = np.flatnonzero(np.any(info[:, :dof, dof:] != 0.0, axis=(1, 2)))
    if coupled.size:
        what = "(u, v, depth)" if kind == measurement.DEPTH else "(u, v)"
        raise DatasetError(path, int(table.lines[coupled[0]]), f"{tag}: expected no information between {what} and the "
                           f"orientation (the block of rows 0-{dof - 1}, columns {dof}-{dim - 1} zero), found some")
    position_layout = _OBSERVATION_LAYOUTS[kind]
    position = _Table(table.ids, np.hstack([table.values[:, :dof], info[(slice(None), *np.triu_indices(dof))]]), table.lines)
    layout = _Layout(tag, position_layout.names, 3, position_layout.summary, position_layout.lengths, position_layout.image)
    part = _build_observations(path, position, layout, kind, pose_ids, cameras, messages)
    quat = _unit_quaternions(path, tag, table.values[:, dof:dof + 4], table.lines, messages)
    rotation_info = info[:, dof:, dof:]
    rotation = {**part, "z": geometry.so3_log(geometry.quat_to_matrix(quat)).reshape(-1, 3), "info": rotation_info,
                "cov": _covariances(path, tag, rotation_info, table.lines, observation_cov_from_info),
                "kind": np.full(table.values.shape[0], measurement.TAG_ROTATION, dtype=np.int64)}
    # interleaved: each position, then its orientation (``Dataset.obs_partner``)
    return {name: np.stack([part[name], rotation[name]], axis=1).reshape((-1,) + part[name].shape[1:]) for name in part}


# --- the pose chain -------------------------------------------------------------------------


# What an odometry edge that leaves the chain usually is, and what to do about it.
_LOOP_CLOSURE_HINT = ("an edge between poses that are not consecutive (a loop closure of a pose graph) is not "
                      "odometry: camloc reads one chain of odometry edges, so remove such edges")


def _check_one_edge_from_each_pose(path: Path, tag: str, table: _Table) -> None:
    """Refuse the first edge that leaves a pose another edge already leaves (a fork in the chain,
    most often a loop closure), naming both edges."""
    starts = table.ids[:, 0]
    order = np.argsort(starts, kind="stable")
    repeats = np.flatnonzero(starts[order][1:] == starts[order][:-1])
    if repeats.size:
        row = int(order[repeats + 1].min())
        first = int(np.flatnonzero(starts == starts[row])[0])
        raise DatasetError(path, int(table.lines[row]),
                           f"{tag} {starts[row]} -> {table.ids[row, 1]}: expected one edge from each pose (a chain), "
                           f"found a second edge from pose {starts[row]} (the first, {starts[row]} -> {table.ids[first, 1]}, "
                           f"at line {table.lines[first]}); {_LOOP_CLOSURE_HINT}")


def _start_vertex(path: Path, vertex_ids: np.ndarray, lines: np.ndarray, odometry: dict[str, np.ndarray],
                  robot: tuple[str, str] = (TAG_POSE, TAG_ODOMETRY)) -> int:
    """Row of the start pose's vertex: the chain's root (``read_g2o``), else the first vertex.

    Files written by other tools need not list the first pose first; the edges say which it is."""
    roots = set(odometry["from"].tolist()) - set(odometry["to"].tolist())
    if len(roots) != 1:
        return 0  # no edges, a cycle or several chains: _follow_chain names the problem, if any
    root = roots.pop()
    rows = np.flatnonzero(vertex_ids == root)
    if rows.size == 0:
        edge_line = int(odometry["lines"][np.flatnonzero(odometry["from"] == root)[0]])
        raise DatasetError(path, edge_line,
                           f"{robot[1]} from pose {root} starts the odometry chain: expected a {robot[0]} for "
                           f"pose {root} (the known start pose), found vertices of other poses only")
    return int(rows[0])


def _follow_chain(path: Path, first_pose: int, odometry: dict[str, np.ndarray],
                  robot: tuple[str, str] = (TAG_POSE, TAG_ODOMETRY)) -> tuple[np.ndarray, np.ndarray]:
    """Follow the odometry edges from first_pose (``_start_vertex``).

    Returns the pose ids in chain order (N,) and the edge rows in chain order (N-1,). Forks are
    refused earlier (duplicate ``from``); here an edge closing a cycle, or an edge the chain never
    reaches (a gap or a second chain), is a DatasetError naming its line.
    """
    edge_from = odometry["from"].tolist()
    edge_to = odometry["to"].tolist()
    lines = odometry["lines"]
    edge_of = {pose: row for row, pose in enumerate(edge_from)}
    chain, order, seen = [first_pose], [], {first_pose}
    while chain[-1] in edge_of:
        row = edge_of.pop(chain[-1])
        if edge_to[row] in seen:
            raise DatasetError(path, int(lines[row]),
                               f"{robot[1]} {edge_from[row]} -> {edge_to[row]}: expected the chain to go on "
                               f"to a new pose, found a cycle (pose {edge_to[row]} is already on it); {_LOOP_CLOSURE_HINT}")
        seen.add(edge_to[row])
        chain.append(edge_to[row])
        order.append(row)
    if edge_of:
        row = min(edge_of.values())
        raise DatasetError(path, int(lines[row]),
                           f"{robot[1]} {edge_from[row]} -> {edge_to[row]}: expected every edge on the one "
                           f"chain from the first {robot[0]} {first_pose}, found an edge it never reaches "
                           f"(the chain ends at pose {chain[-1]})")
    return np.array(chain, dtype=np.int64), np.array(order, dtype=np.int64)


# A pose vertex off the chain is often a landmark written as another tool writes one.
_LANDMARK_HINT = {TAG_POSE: f" (a landmark? a point is a {TAG_LANDMARK} id x y z, a landmark with an orientation a {TAG_TAG})",
                  TAG_POSE_SE2: f" (a landmark? a point is a {TAG_LANDMARK_XY} id x y, a marker a {TAG_MARKER} id x y psi)"}


def _check_vertices_on_chain(path: Path, vertex_ids: np.ndarray, pose_ids: np.ndarray, lines: np.ndarray,
                             robot: tuple[str, str] = (TAG_POSE, TAG_ODOMETRY)) -> None:
    """A pose vertex no edge reaches cannot be localized: refuse it rather than drop it silently."""
    off = np.flatnonzero(~np.isin(vertex_ids, pose_ids))
    if off.size:
        row = off[0]
        raise DatasetError(path, int(lines[row]),
                           f"{robot[0]} {vertex_ids[row]}: expected a pose of the odometry chain from "
                           f"{pose_ids[0]}, found a vertex no {robot[1]} reaches{_LANDMARK_HINT[robot[0]]}")


def _ground_truth(pose_ids: np.ndarray, vertex_ids: np.ndarray, vertex_xyz: np.ndarray, vertex_quat: np.ndarray,
                  messages: list[str], pose_tag: str = TAG_POSE) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Truth (N, 3), (N, 4) in chain order when every chain pose has a vertex, else None, None.

    A single vertex is the start pose only, even for a one-pose chain.
    """
    if vertex_ids.size == 1:
        return None, None
    if vertex_ids.size < pose_ids.size:
        messages.append(f"ground truth ignored: {pose_ids.size - vertex_ids.size} of {pose_ids.size} poses "
                        f"have no {pose_tag}")
        return None, None
    row_of = {pose: row for row, pose in enumerate(vertex_ids.tolist())}
    rows = np.array([row_of[pose] for pose in pose_ids.tolist()], dtype=np.int64)
    return vertex_xyz[rows], vertex_quat[rows]


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def write_g2o(dataset: Dataset, path: str | os.PathLike) -> None:
    """Write a dataset as a g2o file that ``read_g2o`` reads back to identical arrays.

    Cameras, landmarks, the pose vertices (every ground-truth pose when there is ground truth,
    else only the start), then each odometry edge followed by the observations of the pose it
    reaches (as in the real dataset) when the observations are sorted by pose, else all edges
    then all observations in dataset order. Floats are written with ``repr``, the shortest text
    that reads back to the same double. The file is written whole or not at all (a temporary file
    in the same directory, then ``os.replace``); missing parent folders are created.

    Parameters
    ----------
    dataset : the dataset to write; its ``odom_info`` and ``obs_info`` are written, the
        covariances are derived from them on reading.
    path : the destination .g2o file.
    """
    path = Path(path)
    try:
        write_text_atomic(path, g2o_text(dataset))
    except OSError as error:
        raise CamlocError(f"cannot write {path}: {error.strerror or error}") from None


def g2o_text(dataset: Dataset) -> str:
    """The text ``write_g2o`` writes, for a caller that writes several files all or none
    (``camloc.atomic_files.write_files_atomic``)."""
    return "".join(_format_dataset(dataset))


def _records(tag: str, ids: np.ndarray, values: np.ndarray) -> list[str]:
    """Lines ``tag ids... values...``: ids (n, k) as integers, values (n, m) with repr, the
    shortest text that reads back to the same double."""
    if len(values) == 0:
        return []
    ids = np.asarray(ids, dtype=np.int64).reshape(len(values), -1).tolist()
    return [f"{tag} {' '.join(map(str, row_ids))} {' '.join(map(repr, row))}\n"
            for row_ids, row in zip(ids, np.asarray(values, dtype=float).tolist())]


def _format_dataset(dataset: Dataset) -> list[str]:
    """The lines of the file, in the order described in ``write_g2o``."""
    lines = ["# camloc g2o: cameras, map, pose vertices, odometry and observations (see docs/format.md)\n"]
    cameras = list(dataset.cameras.values())
    lines += _records(TAG_CAMERA, [camera.id for camera in cameras], np.array(
        [[*camera.translation, *camera.quat_xyzw, camera.fx, camera.fy, camera.cx, camera.cy] for camera in cameras]))
    lines += _landmark_records(dataset)
    lines += _pose_records(dataset)
    edges = _odometry_records(dataset)
    observations = _observation_records(dataset)
    if np.all(np.diff(dataset.obs_pose_index) >= 0):
        # Interleave: the observations of pose k come right after the edge that reaches it.
        bounds = np.searchsorted(dataset.obs_pose_index, np.arange(dataset.num_poses + 1)).tolist()
        lines += observations[bounds[0]:bounds[1]]
        for k, edge in enumerate(edges):
            lines.append(edge)
            lines += observations[bounds[k + 1]:bounds[k + 2]]
    else:
        lines += edges + observations
    return lines


def _landmark_records(dataset: Dataset) -> list[str]:
    """The map's records in dataset order, each by its landmark's kind (``_LANDMARK_LAYOUTS``)."""
    values = {LANDMARK_POINT3: dataset.landmark_xyz, LANDMARK_POINT2: dataset.landmark_xyz[:, :2],
              LANDMARK_MARKER: np.column_stack([dataset.landmark_xyz[:, :2], dataset.landmark_heading]),
              LANDMARK_TAG: np.hstack([dataset.landmark_xyz, dataset.landmark_quat_xyzw])}
    lines: list[str] = [""] * len(dataset.landmark_ids)
    for kind, layout in _LANDMARK_LAYOUTS.items():
        rows = np.flatnonzero(dataset.landmark_kind == kind)
        for row, line in zip(rows.tolist(), _records(layout.tag, dataset.landmark_ids[rows], values[kind][rows])):
            lines[row] = line
    return lines


def _pose_records(dataset: Dataset) -> list[str]:
    """Every ground-truth pose's vertex when there is ground truth, else only the start's."""
    if dataset.truth_xyz is not None:
        ids, xyz, quat = dataset.pose_ids, dataset.truth_xyz, dataset.truth_quat_xyzw
    else:
        ids, xyz, quat = dataset.pose_ids[:1], dataset.start_xyz[None], dataset.start_quat_xyzw[None]
    if dataset.planar:
        return _records(TAG_POSE_SE2, ids, planar.flatten(geometry.pose_from_quat(xyz, quat)))
    return _records(TAG_POSE, ids, np.hstack([xyz, quat]))


def _odometry_records(dataset: Dataset) -> list[str]:
    """One edge per increment, with the file's information (upper triangle, row by row)."""
    ends = np.stack([dataset.pose_ids[:-1], dataset.pose_ids[1:]], axis=1)
    if dataset.planar:
        increments = planar.flatten(dataset.T_odometry).reshape(-1, 3)
        upper = dataset.odom_info[(slice(None), *np.triu_indices(3))]
        return _records(TAG_ODOMETRY_SE2, ends, np.hstack([increments, upper]))
    odom_upper = dataset.odom_info[(slice(None), *np.triu_indices(6))]  # (N-1, 21), row by row
    return _records(TAG_ODOMETRY, ends, np.hstack([dataset.odom_translation, dataset.odom_quat_xyzw, odom_upper]))


def _observation_records(dataset: Dataset) -> list[str]:
    """One line per observation, in dataset order, each with its kind's tag and layout."""
    ids = np.stack([dataset.pose_ids[dataset.obs_pose_index], dataset.obs_true_landmark, dataset.obs_camera], axis=1)
    lines: list[str] = [""] * dataset.num_observations
    for kind, layout in _OBSERVATION_LAYOUTS.items():
        rows = np.flatnonzero(dataset.obs_kind == kind)
        dof = measurement.KINDS[kind].dof
        values = np.hstack([dataset.obs_z[rows, :dof], measurement.upper_triangle(dataset.obs_info[rows], kind)])
        for row, line in zip(rows.tolist(), _records(layout.tag, ids[rows, :layout.n_ids], values)):
            lines[row] = line
    # a tag's position and orientation: one EDGE_PROJECT_TAG (_UV) on the position's line, none on the orientation's
    for kind, layout in _TAG_OBSERVATION_LAYOUTS.items():
        rotation = np.flatnonzero(dataset.obs_kind == measurement.TAG_ROTATION)
        rotation = rotation[dataset.obs_kind[dataset.obs_partner[rotation]] == kind]
        position, dof = dataset.obs_partner[rotation], measurement.KINDS[kind].dof
        info = np.zeros((rotation.size, dof + 3, dof + 3))
        info[:, :dof, :dof], info[:, dof:, dof:] = dataset.obs_info[position, :dof, :dof], dataset.obs_info[rotation]
        quat = geometry.matrix_to_quat(geometry.so3_exp(dataset.obs_z[rotation])).reshape(-1, 4)
        values = np.hstack([dataset.obs_z[position, :dof], quat, info[(slice(None), *np.triu_indices(dof + 3))]])
        for row, partner, line in zip(position.tolist(), rotation.tolist(), _records(layout.tag, ids[position], values)):
            lines[row], lines[partner] = line, ""
    return lines
