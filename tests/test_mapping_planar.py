"""The mapping localizer (EKF-SLAM, camloc.slam_run) on a planar robot: its 3-D model run lifted,
the robot kept exactly in the plane, points of the floor (EDGE_SE2_XY) and cameras' landmarks
mapped; a half-withheld map under --map exact adds what it lacks; --map prior end to end."""

from __future__ import annotations

import json
from collections import Counter

import numpy as np
import pytest
from typer.testing import CliRunner

from camloc.cli.app import app
from camloc.dataset import LANDMARK_MARKER, LANDMARK_POINT2
from camloc.localizer import _localize_exact, localize, resolved_config
from camloc.localizer_config import LocalizerConfig
from camloc.results import UNASSOCIATED
from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar
from camloc.slam_run import MappingLocalizer

# a quiet odometry: the map's drift stays small enough to score landmarks against the truth
QUIET = dict(odometry_sigma_xy=0.02, odometry_sigma_theta=0.005)


def _rmse(result, dataset) -> float:
    return float(np.sqrt(np.mean(np.sum((result.estimate_xyz - dataset.truth_xyz) ** 2, axis=1))))


def _landmark_errors(result, truth: dict) -> np.ndarray:
    """Each added landmark's distance to the true landmark most of its observations are of."""
    m, a = result.landmark_map, result.associations
    errors = []
    for row, landmark_id in enumerate(m.ids.tolist()):
        (true_id, _), = Counter(a.true_landmark[a.landmark == landmark_id].tolist()).most_common(1)
        errors.append(np.linalg.norm(m.xyz[row] - truth[true_id]))
    return np.array(errors)


@pytest.mark.parametrize("association", ["oracle", "beam"])
def test_a_planar_robot_without_a_map_maps_the_floor_s_points(association):
    kw = dict(sensors="points", poses=120, **QUIET)
    full = simulate_planar(PlanarSimulationConfig(**kw), seed=2)
    dataset = simulate_planar(PlanarSimulationConfig(no_map=True, **kw), seed=2)
    result = localize(dataset, LocalizerConfig(association=association))  # no map: --map auto is none
    assert result.summary["config"]["map"] == "none" and result.summary["config"]["filter"] == "se2"
    assert np.all(result.estimate_xyz[:, 2] == 0.0) and np.all(result.estimate_quat_xyzw[:, :2] == 0.0)
    assert result.filter_state.shape == (120, 3) and result.filter_cov.shape == (120, 3, 3)
    m = result.landmark_map
    assert m.added.all() and m.added.sum() >= 45 and np.all(m.xyz[:, 2] == 0.0) and np.all(m.cov[:, 2] == 0.0)
    errors = _landmark_errors(result, dict(zip(full.landmark_ids.tolist(), full.landmark_xyz)))
    assert np.median(errors) < 0.12 and errors.max() < 0.35
    odometry = float(np.sqrt(np.mean(np.sum((result.odometry_xyz - dataset.truth_xyz) ** 2, axis=1))))
    assert _rmse(result, dataset) < 0.6 * odometry


def test_a_long_planar_run_stays_in_the_plane_with_a_symmetric_psd_covariance():
    """400 poses of points and a depth camera, no map: z, roll and pitch of the pose error stay
    exactly zero in P (so the estimate never leaves the plane), the floor's points keep zero
    variance in z, and P stays exactly symmetric and positive semi-definite."""
    dataset = simulate_planar(PlanarSimulationConfig(sensors="points,cameras", poses=400, no_map=True), seed=3)
    config = resolved_config(LocalizerConfig(), dataset)
    run = MappingLocalizer(dataset, config, compiled=False)
    for k in range(dataset.num_poses):
        run.step(k)
        if k % 50 == 49 or k == dataset.num_poses - 1:
            P = run.P
            assert np.all(P[2:5] == 0.0) and np.all(P[:, 2:5] == 0.0)
            assert np.array_equal(P, P.T)
            assert np.linalg.eigvalsh(P)[0] >= -1e-9 * np.abs(P).max()
            floor = np.flatnonzero(run.table.kind[np.array(run.state_landmark, np.int64)] == LANDMARK_POINT2) if run.state_landmark else []
            for row in floor:
                assert np.all(P[6 + 3 * row + 2] == 0.0) and run.x.L[row, 2] == 0.0
            assert run.x.t[2] == 0.0 and np.all(run.x.R[2, :2] == 0.0) and np.all(run.x.R[:2, 2] == 0.0)
            assert abs(run.x.R[2, 2] - 1.0) < 1e-12  # (a rotation's rounding: 6e-14 at most over 1,000 poses)
    floor = run.table.kind == LANDMARK_POINT2
    assert np.count_nonzero(floor) > 20 and np.count_nonzero(~floor & ~run.table.dead) > 20


@pytest.mark.parametrize("sensors", ["points", "cameras"])
def test_a_half_withheld_planar_map_under_exact_adds_its_landmarks_and_beats_ignoring_them(sensors):
    kw = dict(sensors=sensors, poses=300)
    dataset = simulate_planar(PlanarSimulationConfig(withhold_map=0.5, **kw), seed=1)
    mapped = localize(dataset, LocalizerConfig())
    hooks = dict(parallel=None, engine="auto", on_compile=None, on_background_compile=None)
    ignored = _localize_exact(dataset, resolved_config(LocalizerConfig(), dataset), None, **hooks)  # before: the lacking ones ignored
    assert mapped.summary["map"]["mode"] == "exact" and mapped.summary["map"]["added"] >= 40
    assert any("the map lacks landmarks" in w for w in mapped.summary["warnings"])
    assert _rmse(mapped, dataset) < 0.95 * _rmse(ignored, dataset)
    assert np.all(mapped.estimate_xyz[:, 2] == 0.0)


def test_a_complete_planar_map_runs_the_localizer_unchanged():
    """Clutter on the floor agrees with itself by chance more often than a camera's in space (this
    world's three chance points made a place before ``_beyond_chance``): a complete map with 10%
    clutter is not screened as lacking, and its run is the localizer's own."""
    dataset = simulate_planar(PlanarSimulationConfig(sensors="points", poses=300, clutter_fraction=0.1), seed=1)
    result = localize(dataset, LocalizerConfig())
    hooks = dict(parallel=None, engine="auto", on_compile=None, on_background_compile=None)
    alone = _localize_exact(dataset, resolved_config(LocalizerConfig(), dataset), None, **hooks)
    assert result.summary["map"] is None and not any("lacks" in w for w in result.summary["warnings"])
    np.testing.assert_array_equal(result.estimate_xyz, alone.estimate_xyz)
    np.testing.assert_array_equal(result.associations.landmark, alone.associations.landmark)


def _cli(*args):
    return CliRunner().invoke(app, [str(arg) for arg in args])


def test_cli_map_prior_on_a_planar_file_writes_its_map_and_eval_scores_it(tmp_path):
    """simulate --robot planar (a quarter of the map moved 0.3 m) -> run --map prior --map-sigma 0.1
    -> map.csv (floor points at z = 0), a planar trajectory, eval --true-map, plot's fig-map."""
    from camloc.results import read_map

    world = tmp_path / "p.g2o"
    made = _cli("simulate", "--robot", "planar", "--sensors", "points", "--poses", 150, "--seed", 4,
                "--move-map", 0.25, "--clutter-fraction", 0.05, "-o", world, "-q")
    assert made.exit_code == 0, made.output
    run = _cli("run", world, "--map", "prior", "--map-sigma", 0.1, "-o", tmp_path / "r", "--json")
    assert run.exit_code == 0, run.output
    summary = json.loads(run.output)
    assert summary["config"]["filter"] == "se2" and summary["map"]["mode"] == "prior" and summary["map"]["sigma"] == 0.1
    assert summary["map"]["mapped_observed"] > 30
    landmarks = read_map(tmp_path / "r" / "map.csv")
    assert np.all(landmarks.xyz[:, 2] == 0.0)
    import csv

    with open(tmp_path / "r" / "associations.csv") as f:
        paired = {int(row["landmark"]) for row in csv.DictReader(f) if row["landmark"]}
    assert len(paired) > 30 and paired <= set(landmarks.ids.tolist())  # every pair names a landmark of map.csv
    trajectory = np.loadtxt(tmp_path / "r" / "estimate.tum")
    assert np.all(trajectory[:, 3] == 0.0) and np.all(trajectory[:, 4:6] == 0.0)
    scored = _cli("eval", tmp_path / "r", "--true-map", tmp_path / "p.true-map.g2o", "--json")
    assert scored.exit_code == 0, scored.output
    report = json.loads(scored.output)
    assert report["nees"]["dof"] == 3 and report["estimate"]["ate"]["rmse"] < 0.1
    moved = report["map"]["moved"]
    assert moved["count"] > 5 and moved["rmse"] < 0.25  # moved 0.3 m, held with 0.1 m
    assert report["map"]["clutter"]["landmarks"] == 0
    plotted = _cli("plot", tmp_path / "r")
    assert plotted.exit_code == 0, plotted.output
    assert (tmp_path / "r" / "fig-map.png").is_file()


@pytest.mark.parametrize("association", ["oracle", "beam"])
def test_a_planar_robot_without_a_map_maps_its_markers_and_points(association):
    """Markers (EDGE_SE2_MARKER: a heading too) and points with no map: both mapped, each kind
    paired with its own, the markers on the floor in map.csv's terms (z = 0), near the truth."""
    kw = dict(sensors="points,markers", poses=120, **QUIET)
    full = simulate_planar(PlanarSimulationConfig(**kw), seed=2)
    dataset = simulate_planar(PlanarSimulationConfig(no_map=True, **kw), seed=2)
    result = localize(dataset, LocalizerConfig(association=association))
    assert result.summary["config"]["map"] == "none" and np.all(result.estimate_xyz[:, 2] == 0.0)
    truth = dict(zip(full.landmark_ids.tolist(), full.landmark_xyz))
    kind = dict(zip(full.landmark_ids.tolist(), full.landmark_kind.tolist()))
    a = result.associations
    markers = [lid for lid in result.landmark_map.ids.tolist()
               if Counter(a.true_landmark[a.landmark == lid].tolist()).most_common(1)[0][0] in kind
               and kind[Counter(a.true_landmark[a.landmark == lid].tolist()).most_common(1)[0][0]] == LANDMARK_MARKER]
    assert len(markers) >= 20 and np.all(result.landmark_map.xyz[:, 2] == 0.0)
    errors = _landmark_errors(result, truth)
    assert np.median(errors) < 0.12 and errors.max() < 0.4
    paired = a.landmark != UNASSOCIATED
    kinds_of = {lid: set(dataset.obs_kind[paired & (a.landmark == lid)].tolist()) for lid in result.landmark_map.ids.tolist()}
    assert all(len(k) == 1 for k in kinds_of.values())  # each landmark paired with one kind of observation
    odometry = float(np.sqrt(np.mean(np.sum((result.odometry_xyz - dataset.truth_xyz) ** 2, axis=1))))
    assert _rmse(result, dataset) < 0.6 * odometry


def test_cli_map_none_on_a_planar_file_with_markers(tmp_path):
    world = tmp_path / "m.g2o"
    assert _cli("simulate", "--robot", "planar", "--sensors", "points,markers", "--poses", 60, "--no-map", "-o", world, "-q").exit_code == 0
    run = _cli("run", world, "-o", tmp_path / "r", "--json")
    assert run.exit_code == 0, run.output
    summary = json.loads(run.output)
    assert summary["config"]["map"] == "none" and summary["map"]["added"] > 20
    scored = _cli("eval", tmp_path / "r", "--true-map", tmp_path / "m.true-map.g2o", "--json")
    assert scored.exit_code == 0, scored.output
    report = json.loads(scored.output)["map"]
    assert report["added"]["count"] > 20 and report["added"]["rmse"] < 0.5 and report["clutter"]["landmarks"] == 0
