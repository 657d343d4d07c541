"""Worlds with an imperfect map (``camloc.simulate_map``, ``camloc simulate --withhold-map / --move-map
/ --no-map``): what is withheld or moved, that nothing else changes, the true map beside the file,
and how the reader and ``camloc info`` take a map-less file and withheld landmarks."""

from __future__ import annotations

import dataclasses
import json
import warnings

import numpy as np
import pytest
from typer.testing import CliRunner

from camloc.cli.app import app
from camloc.dataset import LANDMARK_MARKER, LANDMARK_POINT2
from camloc.errors import ConfigError
from camloc.g2o import G2oWarning, read_g2o, write_g2o
from camloc.simulate import SimulationConfig, simulate_labelled
from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar

SMALL = dict(poses=60, clutter_fraction=0.1)


def invoke(*args):
    return CliRunner().invoke(app, [str(arg) for arg in args])


def _read(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", G2oWarning)
        return read_g2o(path)


def test_withheld_and_moved_landmarks_and_nothing_else_changes():
    whole = simulate_labelled(SimulationConfig(**SMALL), seed=3)
    edited = simulate_labelled(SimulationConfig(**SMALL, withhold_map=0.3, move_map=0.25, move_distance=0.4), seed=3)
    edits, L = edited.map_edits, len(whole.dataset.landmark_ids)
    assert len(edits.withheld) == round(0.3 * L) and len(edits.moved) == round(0.25 * L)
    assert not np.intersect1d(edits.withheld, edits.moved).size
    d = edited.dataset
    np.testing.assert_array_equal(d.landmark_ids, np.setdiff1d(whole.dataset.landmark_ids, edits.withheld))
    true_xyz = whole.dataset.landmark_xyz[d.landmark_ids]  # ids are row numbers in a simulated map
    distance = np.linalg.norm(d.landmark_xyz - true_xyz, axis=1)
    moved = np.isin(d.landmark_ids, edits.moved)
    np.testing.assert_allclose(distance[moved], 0.4, rtol=1e-12)
    assert np.all(distance[~moved] == 0.0)
    directions = (d.landmark_xyz - true_xyz)[moved] / 0.4
    assert np.abs(directions[:, 2]).max() > 0.3  # a 3-D world's landmarks move off the floor too
    # Same path, odometry and detections (true ids kept); the clutter labels are those of the whole world.
    for name in ("truth_xyz", "odom_translation", "obs_z", "obs_true_landmark", "obs_pose_index"):
        np.testing.assert_array_equal(getattr(d, name), getattr(whole.dataset, name), err_msg=name)
    np.testing.assert_array_equal(edited.is_clutter, whole.is_clutter)
    assert np.count_nonzero(np.isin(d.obs_true_landmark, edits.withheld)) > 0
    assert d.tag_counts["VERTEX_TRACKXYZ"] == len(d.landmark_ids)
    assert edits.whole is not None and np.array_equal(edits.whole.landmark_xyz, whole.dataset.landmark_xyz)
    assert "withhold_map=0.3, move_map=0.25, move_distance=0.4" in d.source


def test_no_map_leaves_every_detection_and_no_landmark():
    edited = simulate_labelled(SimulationConfig(poses=40, no_map=True), seed=1)
    assert edited.dataset.landmark_ids.shape == (0,) and edited.dataset.landmark_xyz.shape == (0, 3)
    assert edited.dataset.num_observations > 50 and not edited.is_clutter.any()
    assert len(edited.map_edits.withheld) == len(edited.map_edits.whole.landmark_ids)


def test_a_perfect_map_has_no_edits():
    assert simulate_labelled(SimulationConfig(poses=20), seed=0).map_edits is None


@pytest.mark.parametrize("options", [dict(withhold_map=1.2), dict(move_map=-0.1), dict(withhold_map=0.6, move_map=0.5),
                                     dict(move_distance=0.0), dict(no_map=True, move_map=0.1)])
def test_bad_map_options_raise(options):
    with pytest.raises(ConfigError, match="simulation option"):
        SimulationConfig(**options)
    with pytest.raises(ConfigError, match="simulation option"):
        PlanarSimulationConfig(**options)


def test_planar_landmarks_move_in_the_floor():
    config = PlanarSimulationConfig(sensors="points,markers", poses=40, move_map=0.5, withhold_map=0.2)
    whole = simulate_planar(dataclasses.replace(config, move_map=0.0, withhold_map=0.0), seed=2)
    edited = simulate_planar(config, seed=2)
    rows = edited.landmark_ids  # row numbers of the whole map
    offset = edited.landmark_xyz - whole.landmark_xyz[rows]
    moved = np.linalg.norm(offset, axis=1) > 0
    assert np.count_nonzero(moved) == round(0.5 * len(whole.landmark_ids))
    np.testing.assert_allclose(np.linalg.norm(offset[moved], axis=1), 0.3, rtol=1e-12)
    assert np.all(offset[:, 2] == 0.0)
    assert set(np.unique(edited.landmark_kind)) <= {LANDMARK_POINT2, LANDMARK_MARKER}
    np.testing.assert_array_equal(edited.landmark_heading, whole.landmark_heading[rows])


def test_cli_writes_the_true_map_beside_the_world_and_refuses_to_replace_it(tmp_path):
    world, truth = tmp_path / "w.g2o", tmp_path / "w.true-map.g2o"
    outcome = invoke("simulate", "-o", world, "--poses", 50, "--withhold-map", 0.5, "--move-map", 0.2, "--json")
    assert outcome.exit_code == 0, outcome.output
    summary = json.loads(outcome.stdout)
    assert summary["true_map"] == str(truth)
    read, true = _read(world), _read(truth)
    report = summary["map"]
    assert report["true_landmarks"] == len(true.landmark_ids) == len(read.landmark_ids) + report["withheld"]
    assert report["withheld"] == round(0.5 * report["true_landmarks"]) and report["move_distance"] == 0.3
    assert summary["counts"]["landmarks"] == len(read.landmark_ids)
    # The reader keeps a withheld landmark's observations, its id absent from the map, as it keeps clutter.
    withheld = np.setdiff1d(true.landmark_ids, read.landmark_ids)
    assert report["withheld_observations"] == np.count_nonzero(np.isin(read.obs_true_landmark, withheld)) > 0
    np.testing.assert_array_equal(read.obs_z, true.obs_z)
    # Both files are refused without --force, the true map alone too.
    world.unlink()
    outcome = invoke("simulate", "-o", world, "--poses", 50, "--withhold-map", 0.5)
    assert outcome.exit_code != 0 and "w.true-map.g2o: already exists" in outcome.output and not world.exists()
    assert invoke("simulate", "-o", world, "--poses", 50, "--withhold-map", 0.5, "--force", "-q").exit_code == 0
    assert invoke("simulate", "-o", tmp_path / "plain.g2o", "--poses", 20, "--json").exit_code == 0
    assert not (tmp_path / "plain.true-map.g2o").exists()


def test_a_map_less_file_reads_with_a_warning_and_info_counts_its_observations(tmp_path):
    world = tmp_path / "none.g2o"
    assert invoke("simulate", "-o", world, "--poses", 30, "--no-map", "-q").exit_code == 0
    with pytest.warns(G2oWarning, match=r"no landmark record \(VERTEX_TRACKXYZ, VERTEX_TAG\): the map is empty"):
        dataset = read_g2o(world)
    assert dataset.landmark_ids.shape == (0,) and dataset.num_observations > 0
    outcome = invoke("info", world, "--json")
    assert outcome.exit_code == 0, outcome.output
    info = json.loads(outcome.stdout)
    assert info["counts"]["landmarks"] == 0
    assert info["unmapped_observations"]["count"] == dataset.num_observations


def test_the_tag_world_is_edited_after_its_orientations_are_drawn(tmp_path):
    from camloc.simulate_tags import simulate_tags

    whole = simulate_tags(SimulationConfig(poses=30), seed=4, sigma_rad=0.02)
    edited = simulate_tags(SimulationConfig(poses=30, withhold_map=0.5), seed=4, sigma_rad=0.02)
    kept = edited.landmark_ids
    np.testing.assert_array_equal(edited.landmark_quat_xyzw, whole.landmark_quat_xyzw[kept])
    np.testing.assert_array_equal(edited.obs_z, whole.obs_z)
    write_g2o(edited, tmp_path / "t.g2o")
    assert _read(tmp_path / "t.g2o").tag_counts["VERTEX_TAG"] == len(kept)


def test_a_sweep_cell_and_a_planar_world_take_the_map_options(tmp_path):
    from camloc.simulate_planar import simulate_world, world_config

    whole = simulate_world(world_config({"poses": 20}), seed=0)
    half = simulate_world(world_config({"poses": 20, "withhold-map": 0.5}), seed=0)
    assert len(half.landmark_ids) == len(whole.landmark_ids) - round(0.5 * len(whole.landmark_ids))
    outcome = invoke("simulate", "-o", tmp_path / "p.g2o", "--robot", "planar", "--poses", 30, "--withhold-map", 0.5,
                     "--clutter-fraction", 0.1, "--json")
    assert outcome.exit_code == 0, outcome.output
    summary = json.loads(outcome.stdout)
    truth = _read(tmp_path / "p.true-map.g2o")
    clutter = ~np.isin(truth.obs_true_landmark, truth.landmark_ids)
    assert summary["counts"]["clutter"] == np.count_nonzero(clutter) > 0  # withheld landmarks are not clutter
    assert summary["map"]["withheld_observations"] > 0 and truth.planar
