"""Planar g2o files (issue 37): VERTEX_SE2, EDGE_SE2, VERTEX_XY, EDGE_SE2_XY, and the planar
markers VERTEX_MARKER_SE2 / EDGE_SE2_MARKER, read, refused with file:line, and written back."""

from __future__ import annotations

import math

import numpy as np
import pytest

from camloc import measurement, planar
from camloc.dataset import LANDMARK_MARKER, LANDMARK_POINT2, LANDMARK_POINT3
from camloc.errors import DatasetError
from camloc.g2o import read_g2o, write_g2o
from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar

# The worked example's robot and marker (tests/test_planar.py), a point, a 3-D camera's landmark.
VALID = [
    "PARAMS_CAMERACALIB 0 0 0 0.3 0.5 -0.5 0.5 -0.5 1 1 0.5 0.5",
    "VERTEX_MARKER_SE2 5 0.9828427124746191 0.7828427124746191 0",
    "VERTEX_XY 6 2.0 1.0",
    "VERTEX_TRACKXYZ 7 2.4071067811865475 1.2071067811865475 0.3",
    "VERTEX_SE2 100 0.7 0.5 0.7853981633974483",
    "VERTEX_SE2 101 1.7 0.5 0.7853981633974483",
    "EDGE_SE2 100 101 0.7071067811865476 -0.7071067811865476 0 100 0 0 100 0 1000",
    "EDGE_SE2_MARKER 100 5 0.4 0.0 -0.7853981633974483 1000 0 0 1000 0 1000",
    "EDGE_SE2_XY 101 6 0.5657 0.1414 1000 0 1000",
    "EDGE_PROJECT_DEPTH 101 7 0 0.5 0.5 1.0 1000 0 0 1000 0 1000",
]


def write_file(tmp_path, lines, name="planar.g2o"):
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def test_planar_file_is_read_lifted(tmp_path):
    dataset = read_g2o(write_file(tmp_path, VALID))
    assert dataset.planar
    assert dataset.pose_ids.tolist() == [100, 101]
    assert dataset.truth_xyz == pytest.approx(np.array([[0.7, 0.5, 0.0], [1.7, 0.5, 0.0]]))
    assert planar.flatten(dataset.T_world_truth)[:, 2] == pytest.approx([math.pi / 4] * 2)
    assert planar.flatten(dataset.T_odometry)[0] == pytest.approx([0.7071067811865476, -0.7071067811865476, 0.0])
    assert dataset.odom_info.shape == (1, 3, 3) and dataset.odom_info[0] == pytest.approx(np.diag([100, 100, 1000]))
    # the lifted covariance: the file's (x, y, theta) block, nothing in z, roll and pitch
    assert planar.planar_block(dataset.odom_cov[0]) == pytest.approx(np.diag([0.01, 0.01, 0.001]))
    assert np.count_nonzero(dataset.odom_cov[0]) == 3
    assert dataset.landmark_ids.tolist() == [5, 6, 7]
    assert dataset.landmark_kind.tolist() == [LANDMARK_MARKER, LANDMARK_POINT2, LANDMARK_POINT3]
    assert dataset.landmark_heading[0] == 0.0 and np.isnan(dataset.landmark_heading[1:]).all()
    assert dataset.obs_kind.tolist() == [measurement.MARKER, measurement.POINT2, measurement.DEPTH]
    assert dataset.obs_camera.tolist() == [measurement.ROBOT_FRAME_SENSOR, measurement.ROBOT_FRAME_SENSOR, 0]
    assert dataset.obs_z[0] == pytest.approx([0.4, 0.0, -math.pi / 4])
    assert dataset.obs_info[1] == pytest.approx(np.diag([1000, 1000, 1]))  # a point2's inert third row


def test_planar_file_without_camera_is_read(tmp_path):
    lines = [line for line in VALID if not line.startswith(("PARAMS", "EDGE_PROJECT"))]
    dataset = read_g2o(write_file(tmp_path, lines))
    assert dataset.cameras == {} and dataset.num_observations == 2


@pytest.mark.parametrize("sensors", ["points", "markers", "cameras", "points,markers,cameras"])
def test_planar_round_trip(tmp_path, sensors):
    """Written and read back: every array equal (a heading passes through a quaternion in memory,
    so to rounding), and written again, the same text."""
    dataset = simulate_planar(PlanarSimulationConfig(sensors=sensors, poses=30, clutter_fraction=0.1), seed=3)
    write_g2o(dataset, tmp_path / "a.g2o")
    back = read_g2o(tmp_path / "a.g2o")
    assert back.planar
    for name in ("landmark_ids", "landmark_kind", "pose_ids", "obs_pose_index", "obs_camera", "obs_kind", "obs_true_landmark"):
        assert np.array_equal(getattr(back, name), getattr(dataset, name)), name
    for name in ("landmark_xyz", "landmark_heading", "truth_xyz", "truth_quat_xyzw", "odom_translation", "odom_quat_xyzw",
                 "odom_info", "odom_cov", "obs_z", "obs_info"):
        assert np.allclose(getattr(back, name), getattr(dataset, name), rtol=0, atol=1e-12, equal_nan=True), name
    write_g2o(back, tmp_path / "b.g2o")
    again = read_g2o(tmp_path / "b.g2o")
    assert np.allclose(again.truth_quat_xyzw, back.truth_quat_xyzw, rtol=0, atol=1e-15)


def _replace(line_start: str, new: str) -> list[str]:
    return [new if line.startswith(line_start) else line for line in VALID]


@pytest.mark.parametrize(
    ("lines", "line", "expected"),
    [
        (_replace("EDGE_SE2 ", "EDGE_SE2 100 101 1 0 0 100 0 0 100 0"), 7, "EDGE_SE2 expects 11 fields"),
        (_replace("VERTEX_SE2 101", "VERTEX_SE2 101 1.7 half 0.7"), 6, "VERTEX_SE2 field y: expected a number, found 'half'"),
        (_replace("VERTEX_XY", "VERTEX_XY six 2.0 1.0"), 3, "VERTEX_XY field id: expected an integer id"),
        (_replace("VERTEX_MARKER_SE2", "VERTEX_MARKER_SE2 5 1 1 nan"), 2, "VERTEX_MARKER_SE2 field psi: expected a finite number"),
        (_replace("EDGE_SE2_XY", "EDGE_SE2_XY 101 6 0.5 0.1 1000 0 -1"), 9, "EDGE_SE2_XY: expected a symmetric positive definite"),
        (_replace("EDGE_SE2_MARKER", "EDGE_SE2_MARKER 100 5 0.4 0 0 1000 0 0 1000 0"), 8, "EDGE_SE2_MARKER expects 11 fields"),
        (_replace("EDGE_SE2_MARKER", "EDGE_SE2_MARKER 999 5 0.4 0 0 1000 0 0 1000 0 1000"), 8, "from pose 999: expected a pose"),
        (_replace("EDGE_SE2 ", "EDGE_SE2 100 101 1 0 0 100 0 0 100 0 -5"), 7, "EDGE_SE2: expected a symmetric positive definite"),
        (VALID + ["VERTEX_SE3:QUAT 102 0 0 0 0 0 0 1"], 11, "expected one kind of robot"),
        (_replace("VERTEX_XY", "VERTEX_XY 5 2.0 1.0"), 3, "duplicate landmark id 5"),
    ],
)
def test_bad_planar_lines_name_file_and_line(tmp_path, lines, line, expected):
    path = write_file(tmp_path, lines)
    with pytest.raises(DatasetError) as error:
        read_g2o(path)
    assert error.value.line == line, str(error.value)
    assert expected in error.value.reason
    assert str(error.value).startswith(f"{path}:{line}: ")


def test_planar_observation_in_a_3d_file_is_refused(tmp_path):
    lines = [
        "PARAMS_CAMERACALIB 0 0 0 0.3 0.5 -0.5 0.5 -0.5 1 1 0.5 0.5",
        "VERTEX_SE3:QUAT 1000 0 0 0 0 0 0 1",
        "EDGE_SE2_XY 1000 6 0.5 0.1 1000 0 1000",
    ]
    with pytest.raises(DatasetError, match=r":3: EDGE_SE2_XY is a planar robot's observation"):
        read_g2o(write_file(tmp_path, lines))


def test_planar_file_without_start_pose_is_refused(tmp_path):
    lines = [line for line in VALID if not line.startswith("VERTEX_SE2")]
    with pytest.raises(DatasetError, match=r"planar.g2o: expected a VERTEX_SE2 record \(the start pose\), found none"):
        read_g2o(write_file(tmp_path, lines))
    lines = [line for line in VALID if not line.startswith("VERTEX_SE2 100")]
    with pytest.raises(DatasetError, match=r":6: EDGE_SE2 from pose 100 starts the odometry chain: expected a VERTEX_SE2 for pose 100"):
        read_g2o(write_file(tmp_path, lines))


def test_planar_landmarks_in_a_3d_file_are_skipped_with_a_warning(tmp_path):
    lines = [
        "PARAMS_CAMERACALIB 0 0 0 0.3 0.5 -0.5 0.5 -0.5 1 1 0.5 0.5",
        "VERTEX_TRACKXYZ 0 2.0 0.0 0.3",
        "VERTEX_XY 9 1.0 2.0",
        "VERTEX_MARKER_SE2 10 1.0 2.0 0.5",
        "VERTEX_SE3:QUAT 1000 0 0 0 0 0 0 1",
    ]
    with pytest.warns(UserWarning) as caught:
        dataset = read_g2o(write_file(tmp_path, lines))
    assert sorted(tag for tag in ("VERTEX_XY", "VERTEX_MARKER_SE2") for w in caught if f"'{tag}'" in str(w.message)) == [
        "VERTEX_MARKER_SE2", "VERTEX_XY"]
    assert not dataset.planar and dataset.landmark_ids.tolist() == [0]
    assert [w for w in dataset.warnings if "skipped 1 record(s) with tag 'VERTEX_XY'" in w and w.startswith("line 3:")]
    assert [w for w in dataset.warnings if "'VERTEX_MARKER_SE2'" in w]
