"""The g2o reader and writer: every malformed-input rule, warnings, chaining, round trips, the
information -> covariance conversion, and the real dataset."""

from __future__ import annotations

import os
import warnings
from dataclasses import fields, replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import camloc
from camloc import geometry
from camloc.dataset import Camera, Dataset
from camloc.errors import CamlocError, DatasetError
from camloc.g2o import (
    G2oWarning,
    observation_cov_from_info,
    odometry_cov_from_info,
    odometry_info_from_cov,
    read_g2o,
    write_g2o,
)

INFO6 = "100 0 0 0 0 0 100 0 0 0 0 100 0 0 0 10000 0 0 10000 0 10000"
INFO3 = "1000 0 0 1000 0 1000"

# A small valid file; the tests below break one line at a time (line numbers are 1-based).
VALID = [
    "# pose chain 10 -> 11 -> 12, two landmarks, one camera",  # 1
    "PARAMS_CAMERACALIB 0 0 0 0.3 0.5 -0.5 0.5 -0.5 1 1 0.5 0.5",  # 2
    "VERTEX_TRACKXYZ 1 1.0 2.0 3.0",  # 3
    "VERTEX_TRACKXYZ 2 4.0 5.0 6.0",  # 4
    "VERTEX_SE3:QUAT 10 0 0 0 0 0 0 1",  # 5
    "VERTEX_SE3:QUAT 11 1 0 0 0 0 0 1",  # 6
    "VERTEX_SE3:QUAT 12 2 0 0 0 0 0 1",  # 7
    f"EDGE_SE3:QUAT 10 11 1.1 0 0 0 0 0 1 {INFO6}",  # 8
    f"EDGE_PROJECT_DEPTH 11 1 0 0.5 0.5 1.0 {INFO3}",  # 9
    f"EDGE_SE3:QUAT 11 12 0.9 0 0 0 0 0 1 {INFO6}",  # 10
    f"EDGE_PROJECT_DEPTH 12 2 0 0.4 0.6 2.0 {INFO3}",  # 11
    f"EDGE_PROJECT_DEPTH 12 77 0 0.1 0.2 1.5 {INFO3}",  # 12: a landmark absent from the map
]


def write_file(tmp_path, lines, name="data.g2o"):
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def with_line(number, text):
    """VALID with line ``number`` (1-based) replaced; None deletes it."""
    return with_lines({number: text})


def with_lines(changes):
    """VALID with the lines ``{number: text}`` replaced (None deletes)."""
    return [changes.get(n, line) for n, line in enumerate(VALID, start=1) if changes.get(n, line) is not None]


def read_quietly(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", G2oWarning)
        return read_g2o(path)


# --------------------------------------------------------------------------------------------
# A valid file
# --------------------------------------------------------------------------------------------


def test_valid_file_is_read_in_chain_order(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean file warns about nothing
        dataset = read_g2o(write_file(tmp_path, VALID))
    assert dataset.pose_ids.tolist() == [10, 11, 12]
    assert list(dataset.cameras) == [0]
    np.testing.assert_array_equal(dataset.cameras[0].translation, [0, 0, 0.3])
    np.testing.assert_array_equal(dataset.landmark_ids, [1, 2])
    np.testing.assert_array_equal(dataset.landmark_xyz, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(dataset.truth_xyz[:, 0], [0, 1, 2])
    np.testing.assert_array_equal(dataset.odom_translation[:, 0], [1.1, 0.9])
    np.testing.assert_array_equal(dataset.obs_pose_index, [1, 2, 2])
    np.testing.assert_array_equal(dataset.obs_true_landmark, [1, 2, 77])
    np.testing.assert_array_equal(dataset.obs_z[1], [0.4, 0.6, 2.0])
    np.testing.assert_allclose(dataset.odom_cov[0].diagonal(), [0.01] * 3 + [4e-4] * 3)
    np.testing.assert_allclose(dataset.obs_cov[2], np.eye(3) * 1e-3)
    assert dataset.tag_counts == {"PARAMS_CAMERACALIB": 1, "VERTEX_TRACKXYZ": 2, "VERTEX_SE3:QUAT": 3,
                                  "EDGE_SE3:QUAT": 2, "EDGE_PROJECT_DEPTH": 3}
    assert dataset.warnings == ()
    assert dataset.source == str(tmp_path / "data.g2o")


def test_load_is_read_g2o(tmp_path):
    assert camloc.load(write_file(tmp_path, VALID)).num_observations == 3


def test_edges_in_any_file_order_are_chained_from_the_first_vertex(tmp_path):
    # The start is the first VERTEX_SE3:QUAT of the file (10); the rest comes in any order.
    lines = VALID[:4] + [VALID[4], VALID[6], VALID[5], VALID[9], VALID[10], VALID[7], VALID[8]]
    dataset = read_g2o(write_file(tmp_path, lines))
    assert dataset.pose_ids.tolist() == [10, 11, 12]
    np.testing.assert_array_equal(dataset.odom_translation[:, 0], [1.1, 0.9])  # chain order, not file order
    np.testing.assert_array_equal(dataset.truth_xyz[:, 0], [0, 1, 2])
    np.testing.assert_array_equal(dataset.obs_pose_index, [2, 1])


def test_the_chain_starts_at_its_root_wherever_its_vertex_is_in_the_file(tmp_path):
    # Vertices listed last pose first: the edges say pose 10 is where the chain starts.
    lines = VALID[:4] + [VALID[6], VALID[5], VALID[4]] + VALID[7:]
    dataset = read_g2o(write_file(tmp_path, lines))
    assert dataset.pose_ids.tolist() == [10, 11, 12]
    np.testing.assert_array_equal(dataset.start_xyz, [0, 0, 0])
    np.testing.assert_array_equal(dataset.truth_xyz[:, 0], [0, 1, 2])
    # the whole file backwards reads to the same chain, odometry and truth
    backwards = read_g2o(write_file(tmp_path, VALID[::-1], name="backwards.g2o"))
    for name in ("pose_ids", "start_xyz", "start_quat_xyzw", "truth_xyz", "odom_translation", "odom_cov"):
        np.testing.assert_array_equal(getattr(backwards, name), getattr(dataset, name))


def test_a_chain_whose_first_pose_has_no_vertex_is_refused(tmp_path):
    with pytest.raises(DatasetError, match=r"data\.g2o:7: EDGE_SE3:QUAT from pose 10 starts the odometry chain: expected a VERTEX_SE3:QUAT for pose 10"):
        read_g2o(write_file(tmp_path, with_line(5, None)))


def test_comments_blank_lines_tabs_crlf_and_leading_blanks_are_accepted(tmp_path):
    messy = ["", "   # indented comment", "#"]
    for line in VALID:
        messy.append("  " + line.replace(" ", "\t", 2))
        messy.append("")
    path = tmp_path / "messy.g2o"
    path.write_bytes(("\r\n".join(messy)).encode())
    clean = read_g2o(write_file(tmp_path, VALID))
    dataset = read_g2o(path)
    for name in ("pose_ids", "odom_translation", "odom_info", "obs_z", "obs_info", "landmark_xyz"):
        np.testing.assert_array_equal(getattr(dataset, name), getattr(clean, name))


def test_carriage_returns_alone_end_lines_as_classic_mac_os_wrote_them(tmp_path):
    path = tmp_path / "mac.g2o"
    path.write_bytes(("\r".join(VALID) + "\r").encode())
    dataset = read_quietly(path)
    np.testing.assert_array_equal(dataset.obs_z, read_quietly(write_file(tmp_path, VALID)).obs_z)
    path.write_bytes("\r".join(with_line(4, "VERTEX_TRACKXYZ 2 4.0 5.0")).encode())
    with pytest.raises(DatasetError) as caught:
        read_quietly(path)
    assert caught.value.line == 4  # the line numbers an editor shows


def test_a_carriage_return_alone_inside_an_lf_file_ends_its_line(tmp_path):
    """A lone CR among LF line ends (a line pasted from another file) ends a line, as an editor
    and Python's universal newlines count it: before, its two records were one line of too many
    fields."""
    joined = "\n".join(VALID[:3]) + "\r" + "\n".join(VALID[3:]) + "\n"
    path = tmp_path / "mixed.g2o"
    path.write_bytes(joined.encode())
    np.testing.assert_array_equal(read_quietly(path).obs_z, read_quietly(write_file(tmp_path, VALID)).obs_z)
    bad = with_line(6, "VERTEX_TRACKXYZ 2 4.0 5.0")
    path.write_bytes(("\n".join(bad[:3]) + "\r" + "\n".join(bad[3:])).encode())
    with pytest.raises(DatasetError) as caught:
        read_quietly(path)
    assert caught.value.line == 6


def test_comments_at_line_ends_are_skipped_as_g2o_skips_them(tmp_path):
    """g2o reads a record's fields and ignores the rest of its line: a '# ...' after the fields is
    a comment (it was 'expects 4 fields, found 7'); a '#' inside a field is still damage."""
    commented = [line + ("  # surveyed 2026-03-05, Kamera ①" if not line.startswith("#") else "") for line in VALID]
    commented[2] = VALID[2] + "\t#tab then comment"
    dataset = read_g2o(write_file(tmp_path, commented))
    clean = read_g2o(write_file(tmp_path, VALID, name="clean.g2o"))
    for name in ("pose_ids", "odom_translation", "odom_info", "obs_z", "obs_info", "landmark_xyz", "landmark_ids"):
        np.testing.assert_array_equal(getattr(dataset, name), getattr(clean, name))
    with pytest.raises(DatasetError, match="field z: expected a number, found '3.0#x'"):
        read_quietly(write_file(tmp_path, with_line(3, "VERTEX_TRACKXYZ 1 1.0 2.0 3.0#x")))
    with pytest.raises(DatasetError, match="expects 4 fields after the tag"):
        read_quietly(write_file(tmp_path, with_line(3, "VERTEX_TRACKXYZ 1 1.0 # 2.0 3.0")))


def test_a_g2o_fix_record_is_skipped_with_a_warning_that_says_why(tmp_path):
    with pytest.warns(G2oWarning, match="unknown tag 'FIX' .g2o's fixed vertices: camloc holds the start pose"):
        dataset = read_g2o(write_file(tmp_path, VALID[:5] + ["FIX 10"] + VALID[5:]))
    assert dataset.num_poses == 3


def test_observations_behind_the_camera_are_kept_with_one_warning(tmp_path):
    lines = with_lines({9: f"EDGE_PROJECT_DEPTH 11 1 0 0.5 0.5 0 {INFO3}", 11: f"EDGE_PROJECT_DEPTH 12 2 0 0.4 0.6 -2.0 {INFO3}"})
    with pytest.warns(G2oWarning, match="depth <= 0"):
        dataset = read_g2o(write_file(tmp_path, lines))
    assert dataset.num_observations == 3
    (warning,) = dataset.warnings
    assert "line 9: 2 EDGE_PROJECT_DEPTH record(s)" in warning


def test_byte_order_mark_is_ignored(tmp_path):
    path = tmp_path / "bom.g2o"
    path.write_bytes(b"\xef\xbb\xbf" + ("\n".join(VALID) + "\n").encode())
    assert read_g2o(path).num_poses == 3


# --------------------------------------------------------------------------------------------
# Malformed input: DatasetError with the line and a word of the reason
# --------------------------------------------------------------------------------------------

BAD_LINES = [
    # (id, lines, expected line, words expected in the reason)
    ("camera-too-few-fields", with_line(2, "PARAMS_CAMERACALIB 0 0 0 0.3 0.5 -0.5 0.5 -0.5 1 1 0.5"), 2,
     ["PARAMS_CAMERACALIB", "expects 12 fields", "found 11"]),
    ("observation-too-many-fields", with_line(9, f"EDGE_PROJECT_DEPTH 11 1 0 0.5 0.5 1.0 {INFO3} 7"), 9,
     ["EDGE_PROJECT_DEPTH", "expects 12", "found 13"]),
    ("edge-missing-information", with_line(8, "EDGE_SE3:QUAT 10 11 1.1 0 0 0 0 0 1"), 8,
     ["EDGE_SE3:QUAT", "expects 30", "found 9"]),
    ("tag-alone", with_line(11, "EDGE_PROJECT_DEPTH"), 11, ["expects 12", "found 0"]),
    ("not-a-number", with_line(3, "VERTEX_TRACKXYZ 1 1.0 abc 3.0"), 3, ["number", "'abc'", "field y"]),
    ("python-only-number", with_line(3, "VERTEX_TRACKXYZ 1 1_0 2.0 3.0"), 3, ["number", "'1_0'"]),
    ("nan", with_line(4, "VERTEX_TRACKXYZ 2 4.0 nan 6.0"), 4, ["finite", "nan", "field y"]),
    ("inf-in-information", with_line(10, "EDGE_SE3:QUAT 11 12 0.9 0 0 0 0 0 1 "
                                         "100 0 0 0 0 0 100 0 0 0 0 100 0 0 0 inf 0 0 10000 0 10000"), 10,
     ["finite", "inf"]),
    ("coordinate-beyond-the-bound", with_line(3, "VERTEX_TRACKXYZ 1 1e300 2.0 3.0"), 3,
     ["field x", "metres within", "1e+300"]),
    ("odometry-step-beyond-the-bound", with_line(8, f"EDGE_SE3:QUAT 10 11 1.1 -2e9 0 0 0 0 1 {INFO6}"), 8,
     ["field dy", "metres within", "-2e+09"]),
    ("depth-beyond-the-bound", with_line(9, f"EDGE_PROJECT_DEPTH 11 1 0 0.5 0.5 1e200 {INFO3}"), 9,
     ["field depth", "metres within"]),
    ("zero-focal-length", with_line(2, "PARAMS_CAMERACALIB 0 0 0 0.3 0.5 -0.5 0.5 -0.5 0 1 0.5 0.5"), 2,
     ["non-zero focal lengths", "fx=0"]),
    ("tiny-focal-length", with_line(2, "PARAMS_CAMERACALIB 0 0 0 0.3 0.5 -0.5 0.5 -0.5 1 1e-300 0.5 0.5"), 2,
     ["non-zero focal lengths", "at least 1e-09", "fy=1e-300"]),
    ("principal-point-beyond-the-bound", with_line(2, "PARAMS_CAMERACALIB 0 0 0 0.3 0.5 -0.5 0.5 -0.5 1 1 1e300 0.5"), 2,
     ["field cx", "image units within"]),
    ("pixel-beyond-the-bound", with_line(11, f"EDGE_PROJECT_DEPTH 12 2 0 0.4 -3e10 2.0 {INFO3}"), 11,
     ["field v", "image units within", "-3e+10"]),
    ("zero-quaternion", with_line(6, "VERTEX_SE3:QUAT 11 1 0 0 0 0 0 0"), 6, ["unit quaternion", "norm 0"]),
    ("tiny-quaternion", with_line(8, f"EDGE_SE3:QUAT 10 11 1.1 0 0 0 0 0 1e-12 {INFO6}"), 8, ["norm 1e-12"]),
    ("odometry-information-not-positive-definite",
     with_line(8, "EDGE_SE3:QUAT 10 11 1.1 0 0 0 0 0 1 100 0 0 0 0 0 100 0 0 0 0 -100 0 0 0 10000 0 0 10000 0 10000"),
     8, ["positive definite", "-100"]),
    ("observation-information-singular", with_line(11, "EDGE_PROJECT_DEPTH 12 2 0 0.4 0.6 2.0 1000 1000 0 1000 0 1000"),
     11, ["positive definite", "EDGE_PROJECT_DEPTH"]),
    ("observation-information-too-small-to-invert", with_line(11, "EDGE_PROJECT_DEPTH 12 2 0 0.4 0.6 2.0 1e-300 0 0 1e-300 0 1e-300"),
     11, ["EDGE_PROJECT_DEPTH", "variances up to 1e+18", "1e-300"]),
    ("observation-information-denormal", with_line(9, "EDGE_PROJECT_DEPTH 11 1 0 0.5 0.5 1.0 1e-320 0 0 1e-320 0 1e-320"),
     9, ["EDGE_PROJECT_DEPTH", "variances up to"]),
    ("odometry-information-below-the-variance-bound",
     with_line(10, "EDGE_SE3:QUAT 11 12 0.9 0 0 0 0 0 1 1e-20 0 0 0 0 0 100 0 0 0 0 100 0 0 0 10000 0 0 10000 0 10000"),
     10, ["EDGE_SE3:QUAT", "variances up to", "1e-20"]),
    ("duplicate-camera", VALID[:2] + ["PARAMS_CAMERACALIB 0 0 0 0 0 0 0 1 1 1 0.5 0.5"] + VALID[2:], 3,
     ["duplicate camera id 0", "line 2"]),
    ("duplicate-landmark", with_line(4, "VERTEX_TRACKXYZ 1 4.0 5.0 6.0"), 4, ["duplicate landmark id 1", "line 3"]),
    ("duplicate-pose-vertex", with_line(7, "VERTEX_SE3:QUAT 10 2 0 0 0 0 0 1"), 7,
     ["duplicate pose vertex id 10", "line 5"]),
    ("two-edges-from-one-pose", with_line(10, f"EDGE_SE3:QUAT 10 12 0.9 0 0 0 0 0 1 {INFO6}"), 10,
     ["EDGE_SE3:QUAT 10 -> 12", "second edge from pose 10", "10 -> 11, at line 8", "loop closure", "remove such edges"]),
    # a pose graph's loop closure: an edge back to an earlier pose, from the middle or the end of the chain
    ("loop-closure-from-the-middle", VALID + [f"EDGE_SE3:QUAT 11 10 0 0 0 0 0 0 1 {INFO6}"], 13,
     ["EDGE_SE3:QUAT 11 -> 10", "second edge from pose 11", "loop closure", "remove such edges"]),
    ("loop-closure-from-the-end", VALID + [f"EDGE_SE3:QUAT 12 10 0 0 0 0 0 0 1 {INFO6}"], 13,
     ["12 -> 10", "cycle", "loop closure", "remove such edges"]),
    ("full-information-matrix", with_line(8, "EDGE_SE3:QUAT 10 11 1.1 0 0 0 0 0 1 " + " ".join(
        "100" if (i == j and i < 3) else "10000" if i == j else "0" for i in range(6) for j in range(6))), 8,
     ["expects 30", "found 45", "full 6x6 matrix", "upper triangle"]),
    ("full-information-matrix-of-an-observation", with_line(9, "EDGE_PROJECT_DEPTH 11 1 0 0.5 0.5 1.0 1000 0 0 0 1000 0 0 0 1000"),
     9, ["expects 12", "found 15", "full 3x3 matrix"]),
    ("a-megabyte-field", with_line(3, "VERTEX_TRACKXYZ 1 1.0 2.0 " + "3" * 1_000_000 + "x"), 3,
     ["field z", "expected a number", "... (1000001 characters)"]),
    ("inverse-depth-beyond-the-bound", VALID + [f"EDGE_PROJECT_DISPARITY 12 2 0 0.4 0.6 1e-300 {INFO3}"], 13,
     ["EDGE_PROJECT_DISPARITY", "inverse_depth", "within 1e+09 m", "1e-300"]),
    ("landmark-written-as-a-pose", VALID + ["VERTEX_SE3:QUAT 3 7.0 8.0 9.0 0 0 0 1"], 13,
     ["VERTEX_SE3:QUAT 3", "no EDGE_SE3:QUAT reaches", "a landmark?", "VERTEX_TRACKXYZ"]),
    ("observation-of-unknown-pose", with_line(9, f"EDGE_PROJECT_DEPTH 99 1 0 0.5 0.5 1.0 {INFO3}"), 9,
     ["pose 99", "odometry chain"]),
    ("observation-through-unknown-camera", with_line(9, f"EDGE_PROJECT_DEPTH 11 1 3 0.5 0.5 1.0 {INFO3}"), 9,
     ["camera 3", "unknown camera"]),
    ("gap-in-the-chain", with_line(10, f"EDGE_SE3:QUAT 13 14 0.9 0 0 0 0 0 1 {INFO6}"), 10,
     ["13 -> 14", "never reaches", "ends at pose 11"]),
    ("cycle", with_line(10, f"EDGE_SE3:QUAT 11 10 0.9 0 0 0 0 0 1 {INFO6}"), 10, ["cycle", "11 -> 10"]),
    ("self-loop", with_line(10, f"EDGE_SE3:QUAT 11 11 0.9 0 0 0 0 0 1 {INFO6}"), 10, ["cycle"]),
    ("vertex-off-the-chain", VALID + ["VERTEX_SE3:QUAT 50 0 0 0 0 0 0 1"], 13,
     ["VERTEX_SE3:QUAT 50", "no EDGE_SE3:QUAT reaches"]),
    ("vertices-without-edges", [VALID[i] for i in (1, 2, 4, 5)], 4, ["VERTEX_SE3:QUAT 11", "reaches"]),
    ("non-integer-id", with_line(3, "VERTEX_TRACKXYZ 1.5 1.0 2.0 3.0"), 3, ["integer id", "'1.5'"]),
    ("word-as-id", with_line(9, f"EDGE_PROJECT_DEPTH 11 one 0 0.5 0.5 1.0 {INFO3}"), 9,
     ["field landmark", "integer id", "'one'"]),
    ("exponent-id", with_line(5, "VERTEX_SE3:QUAT 1e1 0 0 0 0 0 0 1"), 5, ["integer id", "'1e1'"]),
    ("id-beyond-64-bits", with_line(3, "VERTEX_TRACKXYZ 99999999999999999999 1.0 2.0 3.0"), 3, ["64 bits"]),
    # a pose's id is its timestamp in the run's TUM files: beyond 2^53 neighbours would read back as one
    ("pose-id-beyond-exact-timestamps", with_line(7, "VERTEX_SE3:QUAT 9007199254740993 2 0 0 0 0 0 1"), 7,
     ["within +-2^53", "found 9007199254740993"]),
    # Two bad lines of different tags: the earlier one in the file is reported.
    ("earliest-of-two-bad-lines", with_lines({4: "VERTEX_TRACKXYZ 2 4.0 5.0", 11: "EDGE_PROJECT_DEPTH 1 2"}), 4,
     ["VERTEX_TRACKXYZ", "expects 4", "found 3"]),
    ("huge-value-before-a-short-line-of-the-same-tag", with_lines({3: "VERTEX_TRACKXYZ 1 1.0 2.0 5e9", 4: "VERTEX_TRACKXYZ 2"}), 3,
     ["field z", "metres within"]),
    ("nan-before-a-short-line-of-the-same-tag", with_lines(
        {9: "EDGE_PROJECT_DEPTH 11 1 0 0.5 inf 1.0 1000 0 0 1000 0 1000", 12: "EDGE_PROJECT_DEPTH 12"}), 9,
     ["finite", "field v"]),
    ("earliest-of-two-bad-lines-reversed", with_lines({2: "PARAMS_CAMERACALIB 0 x", 9: "EDGE_PROJECT_DEPTH 1"}), 2,
     ["PARAMS_CAMERACALIB", "expects 12"]),
]


@pytest.mark.parametrize("lines, line, words", [case[1:] for case in BAD_LINES], ids=[case[0] for case in BAD_LINES])
def test_malformed_line_is_reported_with_its_number(tmp_path, lines, line, words):
    path = write_file(tmp_path, lines)
    with pytest.raises(DatasetError) as caught:
        read_quietly(path)
    error = caught.value
    assert error.line == line, str(error)
    assert str(error).startswith(f"{path}:{line}: ")
    for word in words:
        assert word in error.reason, f"{word!r} not in {error.reason!r}"


@pytest.mark.parametrize("lines, words", [
    ([line for line in VALID if not line.startswith("PARAMS_CAMERACALIB")], ["PARAMS_CAMERACALIB", "found none"]),
    ([line for line in VALID if not line.startswith("VERTEX_SE3:QUAT")], ["VERTEX_SE3:QUAT", "found none"]),
    ([], ["empty"]),
    (["# only", "", "   # comments"], ["empty"]),
], ids=["no-camera", "no-pose-vertex", "empty-file", "only-comments"])
def test_missing_records_are_reported_for_the_file(tmp_path, lines, words):
    with pytest.raises(DatasetError) as caught:
        read_g2o(write_file(tmp_path, lines))
    assert caught.value.line is None
    for word in words:
        assert word in caught.value.reason


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(DatasetError, match="no such file") as caught:
        read_g2o(tmp_path / "absent.g2o")
    assert caught.value.path == str(tmp_path / "absent.g2o")
    with pytest.raises(DatasetError, match="directory"):
        read_g2o(tmp_path)


def test_binary_files_are_not_text_g2o_files(tmp_path):
    nul = tmp_path / "nul.g2o"
    nul.write_bytes(("\n".join(VALID[:3]) + "\n").encode() + b"\x00\x01\x02binary\n")
    with pytest.raises(DatasetError, match="not a text g2o file") as caught:
        read_g2o(nul)
    assert caught.value.line == 4
    latin1 = tmp_path / "latin1.g2o"
    latin1.write_bytes(("\n".join(VALID[:2]) + "\n").encode() + "# caf\xe9\n".encode("latin-1"))
    with pytest.raises(DatasetError, match="not a text g2o file") as caught:
        read_g2o(latin1)
    assert caught.value.line == 3


def test_a_negative_focal_length_is_kept_with_one_warning(tmp_path):
    path = write_file(tmp_path, with_line(2, "PARAMS_CAMERACALIB 0 0 0 0.3 0.5 -0.5 0.5 -0.5 -1 1 0.5 0.5"))
    with pytest.warns(G2oWarning, match=r"line 2: 1 PARAMS_CAMERACALIB record\(s\) with a negative focal length \(camera 0: fx=-1 fy=1\)"):
        dataset = read_g2o(path)
    assert dataset.cameras[0].fx == -1.0
    with warnings.catch_warnings():
        warnings.simplefilter("error", G2oWarning)
        read_g2o(write_file(tmp_path, VALID, "plain.g2o"))  # positive focal lengths: no warning


def test_compressed_wide_and_device_files_say_what_they_are(tmp_path):
    import gzip
    import os

    text = "\n".join(VALID) + "\n"
    cases = {"data.g2o.gz": (gzip.compress(text.encode()), "gzip-compressed; decompress it first"),
             "utf16.g2o": (text.encode("utf-16"), "UTF-16 text; save it as UTF-8")}
    for name, (data, words) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(DatasetError, match=words) as caught:
            read_g2o(tmp_path / name)
        assert caught.value.line == 1
    if os.path.exists("/dev/zero"):  # read whole, it never ends
        with pytest.raises(DatasetError, match="expected a g2o file, found a device"):
            read_g2o("/dev/zero")


# --------------------------------------------------------------------------------------------
# Warnings
# --------------------------------------------------------------------------------------------


def test_unknown_tags_are_skipped_with_one_warning_per_tag(tmp_path):
    lines = VALID[:3] + ["FIX 10", "ROBOTLASER1 1 2 3"] + VALID[3:] + ["FIX 11", "FIX 12"]
    with pytest.warns(G2oWarning) as record:
        dataset = read_g2o(write_file(tmp_path, lines))
    assert dataset.tag_counts["FIX"] == 3 and dataset.tag_counts["ROBOTLASER1"] == 1
    assert len(dataset.warnings) == 2
    fix, laser = dataset.warnings
    assert "'FIX'" in fix and "3 record" in fix and "line 4" in fix
    assert "'ROBOTLASER1'" in laser and "1 record" in laser
    assert [str(warning.message) for warning in record] == [f"{tmp_path / 'data.g2o'}: {m}" for m in dataset.warnings]
    assert dataset.num_poses == 3  # the rest is read as usual


def test_non_unit_quaternions_are_normalized_with_one_warning_per_tag(tmp_path):
    lines = with_line(6, "VERTEX_SE3:QUAT 11 1 0 0 0 0 0 2")
    lines[6] = "VERTEX_SE3:QUAT 12 2 0 0 0 0 0.5 0.5"
    lines[7] = f"EDGE_SE3:QUAT 10 11 1.1 0 0 0 0 0 1.01 {INFO6}"
    with pytest.warns(G2oWarning, match="not unit length"):
        dataset = read_g2o(write_file(tmp_path, lines))
    vertex_warning, edge_warning = dataset.warnings
    assert "2 VERTEX_SE3:QUAT quaternion(s)" in vertex_warning and "line 6" in vertex_warning
    assert "|norm - 1| = 1" in vertex_warning  # the worst one: norm 2
    assert "1 EDGE_SE3:QUAT quaternion(s)" in edge_warning and "0.01" in edge_warning
    np.testing.assert_allclose(dataset.truth_quat_xyzw[1], [0, 0, 0, 1])
    np.testing.assert_allclose(dataset.truth_quat_xyzw[2], [0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    np.testing.assert_allclose(dataset.odom_quat_xyzw[0], [0, 0, 0, 1])


def test_quaternions_near_the_float_range_are_normalized_not_zeroed(tmp_path):
    # the norm of components of 1e200 overflows to inf, and dividing by it gave a zero quaternion
    lines = with_lines({2: "PARAMS_CAMERACALIB 0 0 0 0.3 1e200 -1e200 1e200 -1e200 1 1 0.5 0.5",
                        6: "VERTEX_SE3:QUAT 11 1 0 0 0 0 1e300 1e300",
                        8: f"EDGE_SE3:QUAT 10 11 1.1 0 0 0 0 0 1e250 {INFO6}"})
    dataset = read_quietly(write_file(tmp_path, lines))
    np.testing.assert_allclose(dataset.cameras[0].quat_xyzw, [0.5, -0.5, 0.5, -0.5])
    np.testing.assert_allclose(dataset.truth_quat_xyzw[1], [0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    np.testing.assert_allclose(dataset.odom_quat_xyzw[0], [0, 0, 0, 1])


def test_information_near_the_float_range_has_a_representable_covariance(tmp_path):
    # the closed-form 3x3 inverse's determinant, 1e900, overflowed and gave a zero covariance
    dataset = read_quietly(write_file(tmp_path, with_line(9, "EDGE_PROJECT_DEPTH 11 1 0 0.5 0.5 1.0 1e300 0 0 1e300 0 1e300")))
    np.testing.assert_allclose(dataset.obs_cov[0], 1e-300 * np.eye(3))


def test_quaternions_rounded_in_the_file_are_normalized_silently(tmp_path):
    lines = with_line(6, "VERTEX_SE3:QUAT 11 1 0 0 0 0 -0.707107 0.707107")  # |q| - 1 = 3e-7
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dataset = read_g2o(write_file(tmp_path, lines))
    assert abs(np.linalg.norm(dataset.truth_quat_xyzw[1]) - 1.0) < 1e-15
    assert dataset.warnings == ()


def test_ground_truth_needs_a_vertex_for_every_pose(tmp_path):
    only_start = read_g2o(write_file(tmp_path, [line for i, line in enumerate(VALID, 1) if i not in (6, 7)]))
    assert only_start.truth_xyz is None and only_start.truth_quat_xyzw is None and only_start.warnings == ()
    np.testing.assert_array_equal(only_start.start_xyz, [0, 0, 0])
    assert only_start.pose_ids.tolist() == [10, 11, 12]

    with pytest.warns(G2oWarning, match="1 of 3 poses"):
        partial = read_g2o(write_file(tmp_path, with_line(6, None)))
    assert partial.truth_xyz is None
    assert "ground truth ignored" in partial.warnings[0]


def test_observations_of_unmapped_landmarks_are_kept(tmp_path):
    dataset = read_g2o(write_file(tmp_path, VALID))
    assert 77 not in dataset.landmark_ids and dataset.obs_true_landmark[-1] == 77


# --------------------------------------------------------------------------------------------
# Writer: round trips and atomicity
# --------------------------------------------------------------------------------------------


def random_spd(rng, n, dim, scale):
    A = rng.normal(size=(n, dim, dim))
    return scale * (A @ np.swapaxes(A, -1, -2) / dim + np.eye(dim))


def make_dataset(rng, *, num_poses=6, num_obs=15, with_truth=True, sorted_obs=True) -> Dataset:
    """A small random dataset with full-precision floats and correlated information matrices."""
    odom_info = random_spd(rng, num_poses - 1, 6, 100.0)
    obs_info = random_spd(rng, num_obs, 3, 1000.0)
    pose_index = rng.integers(0, num_poses, num_obs)
    if sorted_obs:
        pose_index = np.sort(pose_index)
    truth_xyz = rng.normal(size=(num_poses, 3))
    truth_quat = Rotation.random(num_poses, random_state=1).as_quat()
    cameras = {
        3: Camera(3, rng.normal(size=3), Rotation.random(random_state=2).as_quat(), 1.1, 0.9, 0.51, 0.49),
        5: Camera(5, rng.normal(size=3), Rotation.random(random_state=3).as_quat(), 1.0, 1.0, 0.5, 0.5),
    }
    return Dataset(
        source="test",
        cameras=cameras,
        landmark_ids=np.array([4, 8, 15, 16, 23, 42], dtype=np.int64),
        landmark_xyz=rng.normal(size=(6, 3)) * 10,
        pose_ids=np.arange(100, 100 + num_poses, dtype=np.int64),
        start_xyz=truth_xyz[0],
        start_quat_xyzw=truth_quat[0],
        truth_xyz=truth_xyz if with_truth else None,
        truth_quat_xyzw=truth_quat if with_truth else None,
        odom_translation=rng.normal(size=(num_poses - 1, 3)),
        odom_quat_xyzw=Rotation.random(num_poses - 1, random_state=4).as_quat(),
        odom_info=odom_info,
        odom_cov=odometry_cov_from_info(odom_info),
        obs_pose_index=pose_index,
        obs_camera=rng.choice([3, 5], num_obs),
        obs_z=np.column_stack([rng.uniform(-0.5, 1.5, (num_obs, 2)), rng.uniform(0.3, 2.0, num_obs)]),  # in front of the camera
        obs_info=obs_info,
        obs_cov=observation_cov_from_info(obs_info),
        obs_true_landmark=rng.choice([4, 8, 15, 16, 23, 42, 99], num_obs),
    )


ARRAY_FIELDS = [f.name for f in fields(Dataset) if f.name not in ("source", "cameras", "tag_counts", "warnings", "planar")]


def assert_same_dataset(a: Dataset, b: Dataset):
    assert a.planar == b.planar
    for name in ARRAY_FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype, name
            assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), name  # a point's heading is NaN
    assert a.cameras.keys() == b.cameras.keys()
    for camera_id, camera in a.cameras.items():
        other = b.cameras[camera_id]
        assert np.array_equal(camera.translation, other.translation)
        assert np.array_equal(camera.quat_xyzw, other.quat_xyzw)
        assert (camera.fx, camera.fy, camera.cx, camera.cy) == (other.fx, other.fy, other.cx, other.cy)


@pytest.mark.parametrize("with_truth, sorted_obs", [(True, True), (False, True), (True, False)])
def test_round_trip_is_exact(tmp_path, rng, with_truth, sorted_obs):
    original = make_dataset(rng, with_truth=with_truth, sorted_obs=sorted_obs)
    write_g2o(original, tmp_path / "a.g2o")
    first = read_g2o(tmp_path / "a.g2o")
    # What the file holds comes back bit for bit (the covariances are re-derived from the info).
    assert_same_dataset(original, replace(first, source="test"))
    write_g2o(first, tmp_path / "b.g2o")
    second = read_g2o(tmp_path / "b.g2o")
    assert_same_dataset(first, second)
    assert first.tag_counts == second.tag_counts
    assert (tmp_path / "a.g2o").read_text() == (tmp_path / "b.g2o").read_text()


def test_writer_interleaves_observations_after_the_edge_reaching_their_pose(tmp_path, rng):
    dataset = make_dataset(rng, sorted_obs=True)
    write_g2o(dataset, tmp_path / "a.g2o")
    current_pose = int(dataset.pose_ids[0])
    for line in (tmp_path / "a.g2o").read_text().splitlines():
        fields_ = line.split()
        if fields_[0] == "EDGE_SE3:QUAT":
            current_pose = int(fields_[2])
        elif fields_[0] == "EDGE_PROJECT_DEPTH":
            assert int(fields_[1]) == current_pose


def test_real_dataset_round_trip(tmp_path, real_dataset_path):
    first = read_g2o(real_dataset_path)
    write_g2o(first, tmp_path / "real.g2o")
    second = read_g2o(tmp_path / "real.g2o")
    assert_same_dataset(first, second)
    assert second.tag_counts == first.tag_counts


def test_write_is_atomic(tmp_path, rng, monkeypatch):
    dataset = make_dataset(rng)
    target = tmp_path / "out.g2o"
    target.write_text("previous content\n")

    def failing_replace(source, destination):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(CamlocError, match="cannot write"):
        write_g2o(dataset, target)
    assert target.read_text() == "previous content\n"  # untouched
    assert [p.name for p in tmp_path.iterdir()] == ["out.g2o"]  # no temporary left behind

    monkeypatch.undo()
    write_g2o(dataset, target)
    assert [p.name for p in tmp_path.iterdir()] == ["out.g2o"]
    assert read_g2o(target).num_observations == dataset.num_observations


def test_write_creates_missing_folders_or_says_it_cannot(tmp_path, rng):
    dataset = make_dataset(rng)
    write_g2o(dataset, tmp_path / "absent" / "out.g2o")
    assert read_g2o(tmp_path / "absent" / "out.g2o").num_observations == dataset.num_observations
    (tmp_path / "a-file").write_text("")
    with pytest.raises(CamlocError, match="cannot create the folder"):
        write_g2o(dataset, tmp_path / "a-file" / "out.g2o")


# --------------------------------------------------------------------------------------------
# Information -> covariance
# --------------------------------------------------------------------------------------------


def test_odometry_covariance_matches_sampled_quaternion_noise(rng):
    """Draw g2o's error (t, qvec) with the file's information, turn each draw into a rotation
    vector, and compare the sample covariance with ``odometry_cov_from_info``."""
    sigma_t, sigma_q = 0.1, 0.01
    correlation = np.eye(6)
    correlation[0, 3] = correlation[3, 0] = 0.5  # a translation-rotation cross term
    correlation[4, 5] = correlation[5, 4] = -0.3
    cov_g2o = correlation * np.outer([sigma_t] * 3 + [sigma_q] * 3, [sigma_t] * 3 + [sigma_q] * 3)
    info = np.linalg.inv(cov_g2o)

    e = rng.multivariate_normal(np.zeros(6), np.linalg.inv(info), size=200_000)
    qvec = e[:, 3:]
    quat = np.column_stack([qvec, np.sqrt(1.0 - np.sum(qvec**2, axis=1))])
    rotvec = geometry.so3_log(geometry.quat_to_matrix(quat))
    samples = np.column_stack([e[:, :3], rotvec])
    sampled = np.cov(samples, rowvar=False)

    expected = odometry_cov_from_info(info)
    scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected)))
    assert np.max(np.abs(sampled - expected) / scale) < 0.02
    np.testing.assert_allclose(np.diag(sampled), np.diag(expected), rtol=0.02)
    # The naive reading (information of the rotation vector itself) is off by 4 and would fail.
    naive = np.linalg.inv(info)
    assert np.max(np.abs(sampled - naive) / scale) > 0.5


def test_odometry_info_from_cov_inverts_the_conversion(rng):
    info = random_spd(rng, 4, 6, 50.0)
    np.testing.assert_allclose(odometry_info_from_cov(odometry_cov_from_info(info)), info, rtol=1e-10)
    np.testing.assert_allclose(observation_cov_from_info(info[:, :3, :3]) @ info[:, :3, :3],
                               np.broadcast_to(np.eye(3), (4, 3, 3)), atol=1e-12)


# --------------------------------------------------------------------------------------------
# The real dataset
# --------------------------------------------------------------------------------------------


def test_real_dataset(real_dataset_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dataset = read_g2o(real_dataset_path)
    assert dataset.num_poses == 101
    assert dataset.odom_translation.shape == (100, 3)
    assert dataset.landmark_ids.shape == (144,)
    assert dataset.num_observations == 362
    assert list(dataset.cameras) == [0]
    assert dataset.tag_counts == {"PARAMS_CAMERACALIB": 1, "VERTEX_TRACKXYZ": 144, "VERTEX_SE3:QUAT": 101,
                                  "EDGE_SE3:QUAT": 100, "EDGE_PROJECT_DEPTH": 362}
    assert dataset.pose_ids.tolist() == list(range(1000, 1101))
    camera = dataset.cameras[0]
    np.testing.assert_array_equal(camera.translation, [0, 0, 0.3])
    np.testing.assert_array_equal(camera.quat_xyzw, [0.5, -0.5, 0.5, -0.5])
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (1.0, 1.0, 0.5, 0.5)
    # Optical axis along robot +x, image x along robot -y, image y along robot -z (FORMAT.md).
    R_robot_camera = camera.T_robot_camera[:3, :3]
    np.testing.assert_allclose(R_robot_camera, [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)
    assert dataset.has_ground_truth
    np.testing.assert_allclose(dataset.odom_cov[:, range(6), range(6)],
                               np.tile([0.01] * 3 + [4e-4] * 3, (100, 1)), rtol=1e-12)
    np.testing.assert_allclose(dataset.obs_cov[:, range(3), range(3)], 1e-3, rtol=1e-12)
    assert np.isin(dataset.obs_true_landmark, dataset.landmark_ids).all()


def test_real_dataset_odometry_agrees_with_ground_truth(real_dataset_path):
    """Edges are in chain order: each increment matches the truth within its noise."""
    dataset = read_g2o(real_dataset_path)
    T_truth = dataset.T_world_truth
    T_true_increments = geometry.relative_se3(T_truth[:-1], T_truth[1:])
    error = geometry.pose_error_vector(dataset.T_odometry, T_true_increments)
    # sigma 0.1 m and 0.02 rad per axis (FORMAT.md): RMS within 30 % of that.
    assert 0.07 < np.sqrt(np.mean(error[:, :3] ** 2)) < 0.13
    assert 0.014 < np.sqrt(np.mean(error[:, 3:] ** 2)) < 0.026
