"""``camloc info``: the summary numbers on a dataset built here, the rich and JSON output through
the CLI, and bad input giving exit status 2 without a traceback."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from camloc import geometry
from camloc.cli.app import app
from camloc.dataset import Camera, Dataset
from camloc.dataset_summary import odometry_positions, summarize_dataset
from camloc.g2o import observation_cov_from_info, odometry_cov_from_info, write_g2o

runner = CliRunner()


def square_dataset(*, with_truth: bool) -> Dataset:
    """Five poses driving a 2 m square: forward 2 m then turn left 90 degrees, four times.

    Odometry information: 400 on translation (sigma 0.05 m), 2500 on the quaternion vector
    part (sigma 0.02, so 0.04 rad = 2.29 deg as a rotation vector). Observations: poses 0 and 2
    see landmarks 7 and 9 (and the unmapped id 50), landmark 8 is never seen.
    """
    yaw = np.radians([0.0, 90.0, 180.0, 270.0, 360.0])
    truth_xyz = np.array([[0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0], [0, 0, 0]], dtype=float)
    truth_quat = geometry.euler_to_quat(np.column_stack([np.zeros(5), np.zeros(5), yaw]))
    step_quat = geometry.euler_to_quat(np.tile([0.0, 0.0, np.pi / 2], (4, 1)))
    odom_info = np.tile(np.diag([400.0] * 3 + [2500.0] * 3), (4, 1, 1))
    obs_info = np.tile(np.diag([100.0, 400.0, 25.0]), (5, 1, 1))  # sigma 0.1, 0.05, 0.2
    camera = Camera(id=2, translation=np.array([0.1, 0.0, 0.3]),
                    quat_xyzw=geometry.euler_to_quat(np.radians([-90.0, 0.0, -90.0])), fx=500.0, fy=510.0,
                    cx=320.0, cy=240.0)
    return Dataset(
        source="square",
        cameras={2: camera},
        landmark_ids=np.array([7, 8, 9], dtype=np.int64),
        landmark_xyz=np.array([[1.0, 1.0, 0.5], [3.0, 3.0, 0.5], [-1.0, 1.0, 0.5]]),
        pose_ids=np.arange(10, 15, dtype=np.int64),
        start_xyz=truth_xyz[0],
        start_quat_xyzw=truth_quat[0],
        truth_xyz=truth_xyz if with_truth else None,
        truth_quat_xyzw=truth_quat if with_truth else None,
        odom_translation=np.tile([2.0, 0.0, 0.0], (4, 1)),
        odom_quat_xyzw=step_quat,
        odom_info=odom_info,
        odom_cov=odometry_cov_from_info(odom_info),
        obs_pose_index=np.array([0, 0, 2, 2, 2], dtype=np.int64),
        obs_camera=np.full(5, 2, dtype=np.int64),
        obs_z=np.array([[300.0, 200.0, 1.5]] * 5),
        obs_info=obs_info,
        obs_cov=observation_cov_from_info(obs_info),
        obs_true_landmark=np.array([7, 9, 7, 50, 50], dtype=np.int64),
        tag_counts={"PARAMS_CAMERACALIB": 1, "VERTEX_TRACKXYZ": 3, "VERTEX_SE3:QUAT": 5, "EDGE_SE3:QUAT": 4,
                    "EDGE_PROJECT_DEPTH": 5, "FIX": 2},
        warnings=("line 3: skipped 2 record(s) with unknown tag 'FIX'",),
    )


def test_summary_numbers():
    summary = summarize_dataset(square_dataset(with_truth=True))
    assert summary["counts"] == {"poses": 5, "odometry_edges": 4, "landmarks": 3, "observations": 5, "cameras": 1}
    assert summary["unknown_tags"] == ["FIX"]
    camera = summary["cameras"][0]
    assert camera["id"] == 2 and camera["fx"] == 500.0 and camera["cy"] == 240.0
    np.testing.assert_allclose(camera["translation_m"], [0.1, 0.0, 0.3])
    np.testing.assert_allclose(camera["rotation_rpy_deg"], [-90.0, 0.0, -90.0], atol=1e-9)
    trajectory = summary["trajectory"]
    assert trajectory["source"] == "ground_truth"
    assert trajectory["length_m"] == pytest.approx(8.0)
    np.testing.assert_allclose(trajectory["extent_min_m"], [0, 0, 0])
    np.testing.assert_allclose(trajectory["extent_max_m"], [2, 2, 0])
    np.testing.assert_allclose(trajectory["size_m"], [2, 2, 0])
    # Rotation sigma is twice the quaternion-part sigma: 0.04 rad.
    np.testing.assert_allclose(summary["odometry_noise"]["sigma_translation_m"], [0.05] * 3)
    np.testing.assert_allclose(summary["odometry_noise"]["sigma_rotation_deg"], [np.degrees(0.04)] * 3)
    assert summary["observation_noise"] == pytest.approx({"sigma_u": 0.1, "sigma_v": 0.05, "sigma_depth": 0.2})
    assert summary["observations_per_pose"] == {"min": 0, "median": 0.0, "max": 3, "poses_without": 3}
    assert summary["landmarks_never_observed"] == {"count": 1, "ids": [8]}
    assert summary["unmapped_observations"] == {"count": 2, "ids": [50]}
    assert summary["robot"] == "3d"
    assert summary["warnings"] == ["line 3: skipped 2 record(s) with unknown tag 'FIX'"]
    json.dumps(summary)  # plain types only


def test_trajectory_from_odometry_without_ground_truth():
    dataset = square_dataset(with_truth=False)
    np.testing.assert_allclose(odometry_positions(dataset), square_dataset(with_truth=True).truth_xyz, atol=1e-12)
    trajectory = summarize_dataset(dataset)["trajectory"]
    assert trajectory["source"] == "odometry"
    assert trajectory["length_m"] == pytest.approx(8.0)
    np.testing.assert_allclose(trajectory["extent_max_m"], [2, 2, 0], atol=1e-12)


def test_summary_without_edges_or_observations():
    dataset = square_dataset(with_truth=False)
    empty = Dataset(**{**dataset.__dict__, "pose_ids": dataset.pose_ids[:1], "odom_translation": np.zeros((0, 3)),
                       "odom_quat_xyzw": np.zeros((0, 4)), "odom_info": np.zeros((0, 6, 6)),
                       "odom_cov": np.zeros((0, 6, 6)), "obs_pose_index": np.zeros(0, np.int64),
                       "obs_camera": np.zeros(0, np.int64), "obs_z": np.zeros((0, 3)),
                       "obs_info": np.zeros((0, 3, 3)), "obs_cov": np.zeros((0, 3, 3)),
                       "obs_true_landmark": np.zeros(0, np.int64), "obs_kind": np.zeros(0, np.int64)})
    summary = summarize_dataset(empty)
    assert summary["odometry_noise"] == {"sigma_translation_m": None, "sigma_rotation_deg": None}
    assert summary["observation_noise"] == {"sigma_u": None, "sigma_v": None, "sigma_depth": None}
    assert summary["trajectory"]["length_m"] == 0.0
    assert summary["observations_per_pose"] == {"min": 0, "median": 0.0, "max": 0, "poses_without": 1}
    assert summary["landmarks_never_observed"]["count"] == 3


# --------------------------------------------------------------------------------------------
# The command
# --------------------------------------------------------------------------------------------


@pytest.fixture
def square_file(tmp_path):
    path = tmp_path / "square.g2o"
    write_g2o(square_dataset(with_truth=True), path)
    with path.open("a") as file:
        file.write("FIX 10\nFIX 11\n")
    return path


def test_info_table(square_file):
    result = runner.invoke(app, ["info", str(square_file)], terminal_width=120)
    assert result.exit_code == 0, result.output
    out = result.stdout
    assert "square.g2o" in out
    assert "EDGE_PROJECT_DEPTH" in out and "unknown, skipped" in out
    assert "5 / 4" in out  # poses / odometry edges
    assert "3 / 5" in out  # landmarks / observations
    assert "8.00 (ground truth)" in out
    assert "0.05  0.05  0.05" in out and "2.292  2.292  2.292" in out
    assert "0.1  0.05  0.2" in out
    assert "min 0, median 0, max 3; 3 pose(s) with none" in out
    assert "1: 8" in out  # one landmark never observed, id 8
    assert "2 (ids 50)" in out
    assert "-90.0  0.0  -90.0" in out
    assert "translation [m]" in out  # units survive rich markup
    assert "unknown tag 'FIX'" in out


def test_info_json(square_file):
    result = runner.invoke(app, ["info", str(square_file), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert list(summary) == ["dataset", "counts", "tag_counts", "unknown_tags", "cameras", "trajectory",
                             "odometry_noise", "observation_noise", "observation_kinds", "robot", "observations_per_pose",
                             "landmarks_never_observed", "unmapped_observations", "warnings"]
    assert summary["counts"] == {"poses": 5, "odometry_edges": 4, "landmarks": 3, "observations": 5, "cameras": 1}
    assert summary["tag_counts"]["FIX"] == 2
    assert summary["unmapped_observations"] == {"count": 2, "ids": [50]}
    assert summary["robot"] == "3d"
    assert len(summary["warnings"]) == 1 and "'FIX'" in summary["warnings"][0]
    assert result.stderr == ""  # the warning is in the JSON, not printed twice


@pytest.mark.parametrize("content, line, word", [
    ("PARAMS_CAMERACALIB 0 0 0 0.3 0.5 -0.5 0.5 -0.5 1 1 0.5\n", 1, "expects 12 fields"),
    ("PARAMS_CAMERACALIB 0 0 0 0.3 0.5 -0.5 0.5 -0.5 1 1 0.5 0.5\nVERTEX_SE3:QUAT 1 0 0 0 0 0 0 nan\n", 2, "finite"),
])
def test_info_bad_file_exits_2_with_path_and_line(tmp_path, content, line, word):
    path = tmp_path / "bad.g2o"
    path.write_text(content)
    result = runner.invoke(app, ["info", str(path)])
    assert result.exit_code == 2
    assert f"{path}:{line}:" in result.stderr
    assert word in result.stderr
    assert "Traceback" not in result.output
    assert len(result.stderr.strip().splitlines()) == 1


def test_info_missing_file_exits_2(tmp_path):
    result = runner.invoke(app, ["info", str(tmp_path / "absent.g2o"), "--json"])
    assert result.exit_code == 2
    assert "no such file" in result.stderr and result.stdout == ""


def test_info_help_explains_the_options():
    result = runner.invoke(app, ["info", "--help"], terminal_width=120)
    assert result.exit_code == 0
    assert "--json" in result.stdout and "instead of tables. Default: off." in " ".join(result.stdout.split())


def test_info_on_the_real_dataset(real_dataset_path):
    result = runner.invoke(app, ["info", str(real_dataset_path), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["counts"] == {"poses": 101, "odometry_edges": 100, "landmarks": 144, "observations": 362,
                                 "cameras": 1}
    np.testing.assert_allclose(summary["odometry_noise"]["sigma_translation_m"], [0.1] * 3)
    np.testing.assert_allclose(summary["odometry_noise"]["sigma_rotation_deg"], [np.degrees(0.02)] * 3)
    np.testing.assert_allclose(summary["observation_noise"]["sigma_u"], 1 / np.sqrt(1000))
    assert summary["trajectory"]["source"] == "ground_truth"
    assert summary["unmapped_observations"]["count"] == 0
    assert summary["warnings"] == []
