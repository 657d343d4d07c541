"""Scoring a run's map against the true map (``camloc.map_scores``, ``camloc eval --true-map``), on a
hand-built run folder where every count has a known answer."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from camloc.cli.app import app
from camloc.g2o import write_g2o
from camloc.map_scores import CLUTTER, NOTHING, _Lookup, map_score, stands_for
from camloc.results import UNASSOCIATED, Associations, LandmarkMap, save_run, write_map
from camloc.simulate import SimulationConfig, simulate

TRUE_XYZ = np.array([[float(i), 0.5 * i, 0.1 * (i % 3)] for i in range(10)])  # true landmarks 0..9
GIVEN = np.arange(6)  # the file's map: 6..9 withheld
MOVED = {1: np.array([0.3, 0.0, 0.0]), 2: np.array([0.0, 0.0, 0.4])}  # given map's offsets
MAPPED_ERROR = {0: [0, 0, 0], 1: [0.1, 0, 0], 2: [0, 0, 0.2], 3: [0, 0.05, 0], 4: [0, 0, 0], 5: [0.02, 0, 0]}
# added id -> (true landmark it should stand for, its estimate's offset from that landmark)
ADDED = {100: (6, [0, 0.2, 0]), 101: (6, [0, 0, 0.1]), 102: (None, None), 103: (3, [0.05, 0, 0]), 104: (7, [0, 0, 0])}
# (true id in the file, landmark assigned): clutter has ids 5000.., absent from the true map
OBSERVATIONS = (
    [(6, 100)] * 3 + [(5003, 100)]                     # 100 stands for 6 (3 of 4)
    + [(6, 101)] * 2                                   # 101 stands for 6 too: added twice
    + [(5000, 102), (5001, 102), (5002, 102)]          # 102 made of clutter alone
    + [(3, 103)] * 2                                   # 103 a copy of mapped landmark 3
    + [(7, 104), (5004, 104)] + [(7, UNASSOCIATED)]    # 104: a tie, the true landmark wins; 7 seen twice
    + [(8, UNASSOCIATED)] * 3 + [(9, UNASSOCIATED)]    # 8 never added (seen 3 times), 9 seen once
    + [(5005, UNASSOCIATED), (5006, 0)]                # more clutter: 7 clutter observations in all
    + [(k, k) for k in range(6)] * 2                   # the mapped landmarks, seen twice each
)


def _estimated_map() -> LandmarkMap:
    ids, xyz, added = list(range(6)), [TRUE_XYZ[k] + MAPPED_ERROR[k] for k in range(6)], [False] * 6
    for landmark, (true_id, offset) in ADDED.items():
        ids.append(landmark)
        xyz.append(TRUE_XYZ[true_id] + offset if true_id is not None else np.array([20.0, 20.0, 0.0]))
        added.append(True)
    n = len(ids)
    return LandmarkMap(np.array(ids), np.array(xyz), np.broadcast_to(0.01 * np.eye(3), (n, 3, 3)).copy(),
                       np.array(added), np.full(n, 2))


def _given_xyz() -> np.ndarray:
    return np.array([TRUE_XYZ[k] + MOVED.get(k, 0.0) for k in GIVEN])


def _library_score() -> dict:
    true_ids, assigned = (np.array(column) for column in zip(*OBSERVATIONS))
    added_ids = np.array(list(ADDED))
    return map_score(_estimated_map(), given_ids=np.r_[GIVEN, added_ids], given_xyz=np.r_[_given_xyz(), np.zeros((5, 3))],
                     true_ids=np.arange(10), true_xyz=TRUE_XYZ, obs_landmark=assigned, obs_true=true_ids)


def _expected() -> dict:
    def errors(offsets):
        d = np.linalg.norm(np.array(offsets, dtype=float), axis=1)
        return {"count": len(d), "rmse": pytest.approx(math.sqrt(np.mean(d**2))), "max": pytest.approx(d.max()),
                "nees": pytest.approx(np.mean(d**2) / 0.01)}

    added = [ADDED[a][1] for a in (100, 101, 103, 104)]
    return {
        "mapped": {**errors(list(MAPPED_ERROR.values())), "unknown": 0},
        "moved": {**errors([MAPPED_ERROR[1], MAPPED_ERROR[2]]), "given_rmse": pytest.approx(math.sqrt((0.09 + 0.16) / 2))},
        "added": {**errors(added), "unknown": 1},
        "added_twice": {"landmarks": 1, "true_landmarks": 1, "share": pytest.approx(1 / 5), "mapped_copies": 1},
        "clutter": {"landmarks": 1, "observations": 3, "clutter_observations": 7, "share": pytest.approx(3 / 7)},
        "never_added": {"count": 1, "of": 3, "share": pytest.approx(1 / 3)},
        "orientation": None,  # no tag in the map
    }


def test_every_count_of_the_hand_built_map():
    assert _library_score() == _expected()


def test_an_added_landmark_stands_for_most_of_its_observations_ties_to_a_true_one():
    truth = _Lookup(np.arange(10), TRUE_XYZ)
    added = np.array([7, 50, 51, 52])  # 7 has no observation but is a true id; 50 has none and is not
    obs_landmark = np.array([51, 51, 51, 52, 52])
    category = np.array([CLUTTER, CLUTTER, 4, 9, 2])
    np.testing.assert_array_equal(stands_for(added, obs_landmark, category, truth), [7, NOTHING, CLUTTER, 2])


def test_a_map_with_nothing_added_or_moved_scores_null_shares():
    exact = LandmarkMap(np.arange(3), TRUE_XYZ[:3], np.zeros((3, 3, 3)), np.zeros(3, bool), np.zeros(3, np.int64))
    score = map_score(exact, given_ids=np.arange(3), given_xyz=TRUE_XYZ[:3], true_ids=np.arange(10), true_xyz=TRUE_XYZ,
                      obs_landmark=np.array([0, 1]), obs_true=np.array([0, 1]))
    assert score["mapped"] == {"count": 3, "rmse": 0.0, "max": 0.0, "nees": None, "unknown": 0}
    assert score["moved"] == {"count": 0, "rmse": None, "max": None, "nees": None, "given_rmse": None}
    assert score["added_twice"]["share"] is None and score["clutter"]["share"] is None
    assert score["never_added"] == {"count": 0, "of": 0, "share": None}


def hand_built_run(folder, synthetic_run):
    """A run folder whose associations and map are the hand-built ones above, and the true map's g2o."""
    run = synthetic_run(seed=2, num_poses=len(OBSERVATIONS) + 1)
    true_ids, assigned = (np.array(column, dtype=np.int64) for column in zip(*OBSERVATIONS))
    accepted = assigned != UNASSOCIATED
    associations = Associations(
        pose_id=run.pose_ids[1:], camera=np.zeros(len(assigned), np.int64), uvd=np.tile([0.5, 0.5, 1.0], (len(assigned), 1)),
        landmark=assigned, true_landmark=true_ids, mahalanobis=np.where(accepted, 1.0, np.nan))
    added_ids = np.array(list(ADDED))
    counts = {**run.summary["counts"], "observations": len(assigned)}  # summary.json counts what associations.csv holds
    run = dataclasses.replace(run, associations=associations, summary={**run.summary, "counts": counts},
                              map_landmark_ids=np.r_[GIVEN, added_ids],
                              map_landmark_xyz=np.r_[_given_xyz(), _estimated_map().xyz[6:]])
    run_dir = save_run(folder / "run", run)
    write_map(run_dir, _estimated_map())
    world = simulate(SimulationConfig(poses=5, landmarks=10), seed=0)
    write_g2o(dataclasses.replace(world, landmark_xyz=TRUE_XYZ), folder / "truth.g2o")
    return run_dir, folder / "truth.g2o"


def test_cli_eval_scores_the_hand_built_run_folder(tmp_path, synthetic_run, monkeypatch):
    # a hand-built run is of no world, so no true map is its world's (--true-map refuses another
    # world's: tests/test_cli_eval_plot.py); here the scores alone are tested
    monkeypatch.setattr("camloc.smoother.check_run_matches", lambda *args, **kwargs: None)
    run_dir, truth = hand_built_run(tmp_path, synthetic_run)
    outcome = CliRunner().invoke(app, ["eval", str(run_dir), "--true-map", str(truth), "--json"])
    assert outcome.exit_code == 0, outcome.output
    assert json.loads(outcome.stdout)["map"] == _expected()
    tables = CliRunner().invoke(app, ["eval", str(run_dir), "--true-map", str(truth)]).stdout
    assert "map vs the true map" in tables and "moved" in tables
    assert "position RMSE [m]" in tables and "given map's RMSE [m]" in tables
    rows = {line.split("│")[1].strip(): [cell.strip() for cell in line.split("│")[2:-1]]
            for line in tables.splitlines() if line.count("│") == 5}
    assert rows["added twice"] == ["1", "5 added", "20.0%"]
    assert rows["copies of a mapped landmark"] == ["1", "5 added", "20.0%"]
    assert rows["landmarks made of clutter"] == ["1", "5 added", "20.0%"]
    assert rows["clutter observations in them"] == ["3", "7 clutter", "42.9%"]
    assert rows["never added"] == ["1", "3 seen 2+ times", "33.3%"]


def test_a_point_of_the_floor_is_scored_on_its_x_and_y():
    """A planar robot's floor point (z pinned: zero variance in z, on the floor as its truth) has a
    singular covariance: its NEES is that of x and y, times 3/2 (3 where consistent, as a 3-D one's);
    a 3-D landmark beside it keeps its own."""
    true_xyz = np.array([[1.0, 2.0, 0.0], [3.0, 1.0, 0.5]])
    floor_cov = np.diag([0.04, 0.01, 0.0])
    estimated = LandmarkMap(np.array([0, 1]), true_xyz + [[0.2, 0.1, 0.0], [0.0, 0.0, 0.3]],
                            np.stack([floor_cov, 0.09 * np.eye(3)]), np.array([False, False]), np.array([3, 3]))
    score = map_score(estimated, given_ids=np.array([0, 1]), given_xyz=true_xyz, true_ids=np.array([0, 1]), true_xyz=true_xyz,
                      obs_landmark=np.array([0, 1]), obs_true=np.array([0, 1]))
    floor_nees = 1.5 * (0.2**2 / 0.04 + 0.1**2 / 0.01)  # 3.0
    assert score["mapped"]["nees"] == pytest.approx((floor_nees + 0.3**2 / 0.09) / 2)


def test_tags_orientation_errors_of_mapped_moved_and_added_tags():
    """A map of tags: each tag's angle to its true orientation (an added one to the tag it stands
    for), grouped as the positions are, with the NEES of the world rotation error."""
    from camloc import geometry

    true_quat = geometry.matrix_to_quat(geometry.so3_exp(np.array([[0.1, 0.2, 0.3], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])))
    truth_xyz = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    turns = np.array([[0.0, 0.0, 0.02], [0.03, 0.0, 0.0], [0.0, 0.04, 0.0]])  # R_est = Exp(-turn) R_true
    rotvec = geometry.so3_log(geometry.so3_exp(-turns) @ geometry.quat_to_matrix(true_quat))
    estimated = LandmarkMap(np.array([0, 1, 50]), truth_xyz + 0.01, np.tile(np.eye(3) * 1e-4, (3, 1, 1)), np.array([False, False, True]),
                            np.array([3, 3, 3]), orientation=rotvec, orientation_cov=np.tile(np.eye(3) * 1e-4, (3, 1, 1)))
    score = map_score(estimated, given_ids=np.array([0, 1]), given_xyz=truth_xyz[:2] + [[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]],
                      true_ids=np.arange(3), true_xyz=truth_xyz, obs_landmark=np.array([50, 50]), obs_true=np.array([2, 2]),
                      true_quat_xyzw=true_quat)["orientation"]
    assert score["mapped"]["count"] == 2 and score["moved"]["count"] == 1 and score["added"]["count"] == 1
    assert score["mapped"]["max_deg"] == pytest.approx(np.degrees(0.03))
    assert score["moved"]["rmse_deg"] == pytest.approx(np.degrees(0.03))
    assert score["added"]["rmse_deg"] == pytest.approx(np.degrees(0.04))
    assert score["added"]["nees"] == pytest.approx(0.04**2 / 1e-4)
