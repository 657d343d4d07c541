"""A run says what its numbers do not: which filter ran, that an estimate without an update is
odometry alone, and that a map looks incomplete (``camloc.diagnostics``), in the tables, in
``summary.json`` and on stderr, also under ``--quiet``."""

from __future__ import annotations

import dataclasses
import json

import numpy as np

import pytest
from typer.testing import CliRunner

from camloc.cli.app import app
from camloc.diagnostics import (
    INFORMATION_DECADES_APART,
    MAPPED_LANDMARKS,
    ODOMETRY_ALONE,
    divergence_cause,
    estimate_name,
    filter_name,
    information_decades,
    rejection_tail,
    run_warnings,
)
from camloc.g2o import read_g2o, write_g2o
from camloc.localizer import localize
from camloc.simulate import SimulationConfig, simulate


def invoke(*args):
    return CliRunner().invoke(app, [str(arg) for arg in args])


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    path = tmp_path_factory.mktemp("diagnostics") / "world.g2o"
    write_g2o(simulate(SimulationConfig(trajectory="grid", poses=60), seed=4), path)
    return path


def _with_lines(source, target, keep):
    target.write_text("".join(line for line in source.read_text().splitlines(keepends=True) if keep(line)))
    return target


def _without_every_other_landmark(source, target):
    """The file with every second VERTEX_TRACKXYZ removed: half its map."""
    seen = iter(range(10**9))
    return _with_lines(source, target, lambda line: not line.startswith("VERTEX_TRACKXYZ") or next(seen) % 2 == 0)


# --------------------------------------------------------------------------------------------
# The pure functions


@pytest.mark.parametrize("kind", [dict(), dict(measurement="pixel", intrinsics="pixel", cameras=2),
                                  dict(measurement="disparity", trajectory="aerial"), "planar"])
def test_a_breakdown_on_the_simulators_noise_is_called_a_lost_path_not_the_file_s_information(kind):
    # Every simulated kind spans a few decades of noise (metres, radians and pixels together), so a
    # covariance that breaks down there was not broken by rounding: the message must not blame the file.
    if kind == "planar":
        from camloc.simulate_planar import PlanarSimulationConfig, simulate_planar

        dataset = simulate_planar(PlanarSimulationConfig(poses=20), seed=1)
    else:
        dataset = simulate(SimulationConfig(poses=20, **kind), seed=1)
    assert 0 < information_decades(dataset) < INFORMATION_DECADES_APART - 2
    assert "lost the robot's path" in divergence_cause(dataset)


def test_observations_claiming_a_thousandth_of_a_nanometre_are_called_information_far_apart():
    dataset = simulate(SimulationConfig(poses=20), seed=1)
    exact = dataclasses.replace(dataset, obs_cov=dataset.obs_cov * np.where(np.arange(len(dataset.obs_cov)) % 2, 1e-12, 1.0)[:, None, None])
    decades = information_decades(exact)
    assert decades == pytest.approx(information_decades(dataset) + 12, abs=1.0)
    assert f"information matrices are {decades:.0f} orders of magnitude apart" in divergence_cause(exact)


def test_the_real_file_spans_few_decades_of_noise(real_dataset_path):
    assert information_decades(read_g2o(real_dataset_path)) < INFORMATION_DECADES_APART - 2


def test_the_filter_is_named_by_its_state_and_its_iterations():
    assert filter_name({"filter": "euler", "iterations": 3}) == "iterated EKF (euler)"
    assert filter_name({"filter": "se3", "iterations": 1}) == "EKF (se3)"
    assert filter_name({}) == "filter"  # an edited summary.json: no claim
    assert estimate_name({"config": {"filter": "euler", "iterations": 2}, "counts": {"updates": 5}}) == "iterated EKF (euler)"
    assert estimate_name({"config": {"filter": "euler", "iterations": 2}, "counts": {"updates": 0}}) == ODOMETRY_ALONE


def test_no_observation_or_no_update_is_called_odometry_alone():
    (none,) = run_warnings({"observations": 0, "rejected": 0, "updates": 0})
    assert "odometry alone" in none
    found = run_warnings({"observations": 12, "rejected": 12, "updates": 0})
    assert any("all 12 observations were rejected" in w and "odometry alone" in w for w in found)
    assert run_warnings({"observations": 12, "rejected": 1, "updates": 9}) == []


@pytest.mark.parametrize("rejected, observations, warned", [
    (5, 362, False),     # the real file, complete map: 1.4%
    (112, 801, False),   # smooth3d-clutter.g2o: 12% clutter and outliers, 14% rejected
    (184, 362, True),    # the real file with half its map removed: 51%
    (6, 10, False),      # 60% of ten observations is not evidence
    (2300, 10000, True),  # 23% of many is
])
def test_a_map_looks_incomplete_only_when_the_rejections_are_far_above_the_reference_rate(rejected, observations, warned):
    found = run_warnings({"observations": observations, "rejected": rejected, "updates": 1})
    assert any("the map may lack landmarks" in w for w in found) == warned
    assert 0.0 <= rejection_tail(rejected, observations) <= 1.0


# --------------------------------------------------------------------------------------------
# End to end


def test_a_file_without_usable_observations_is_odometry_alone_everywhere(tmp_path, world):
    unknown = _with_lines(world, tmp_path / "unknown.g2o", lambda line: True)
    unknown.write_text(unknown.read_text().replace("EDGE_PROJECT_DEPTH", "EDGE_PROJECT_XYZ"))
    run_dir = tmp_path / "run"
    outcome = invoke("run", unknown, "-o", run_dir)
    assert outcome.exit_code == 0, outcome.output
    header = next(line for line in outcome.stdout.splitlines() if "odometry only" in line)
    assert ODOMETRY_ALONE in header and "EKF" not in header
    assert any(line.startswith(f"warning: {unknown}: no observation camloc can use") for line in outcome.stderr.splitlines())
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["estimate_name"] == ODOMETRY_ALONE
    assert any("odometry alone" in warning for warning in summary["warnings"])

    evaluation = invoke("eval", run_dir, "--json")
    report = json.loads(evaluation.stdout)
    # odometry's NEES has a verdict (the real file's is "consistent"), which is not the filter's
    assert report["nees"]["verdict"] != "undetermined" and report["consistency"]["verdict"] == "undetermined"
    assert report["estimate_name"] == ODOMETRY_ALONE
    table = invoke("eval", run_dir)
    assert "verdict: undetermined: the filter made no update" in " ".join(table.stdout.split())


def test_quiet_silences_the_table_but_not_the_warnings(tmp_path, world):
    unknown = tmp_path / "unknown.g2o"
    unknown.write_text(world.read_text().replace("EDGE_PROJECT_DEPTH", "EDGE_PROJECT_XYZ"))
    outcome = invoke("run", unknown, "-o", tmp_path / "quiet", "--quiet")
    assert outcome.exit_code == 0 and outcome.stdout == "", outcome.output
    lines = outcome.stderr.splitlines()
    assert lines and all(line.startswith(f"warning: {unknown}: ") for line in lines), outcome.stderr
    assert any("odometry alone" in line for line in lines)
    as_json = invoke("run", unknown, "-o", tmp_path / "json", "--json")  # the warnings are in the object
    assert as_json.stderr == "" and any("odometry alone" in w for w in json.loads(as_json.stdout)["warnings"])
    info = invoke("info", unknown, "--quiet")
    assert info.stdout == "" and "unknown tag 'EDGE_PROJECT_XYZ'" in info.stderr


def test_a_map_missing_half_its_landmarks_is_reported_by_the_run(tmp_path, world):
    half = _without_every_other_landmark(world, tmp_path / "half.g2o")
    outcome = invoke("run", half, "-o", tmp_path / "run", "--quiet")
    assert outcome.exit_code == 0, outcome.output
    # the run adds what the map lacks where the rejected observations agree (issue 38), and says so
    assert "the map lacks landmarks" in outcome.stderr and "map.csv" in outcome.stderr
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert any("the map lacks landmarks" in warning for warning in summary["warnings"]) and summary["map"]["added"] >= 1

    whole = invoke("run", world, "-o", tmp_path / "whole", "--quiet")
    assert whole.exit_code == 0 and whole.output == ""  # a complete map: nothing to say


def test_places_the_mapping_pass_adds_none_of_are_not_said_added():
    """Odometry that jumps 1 km at pose 10 (a world of 20 poses, seed 3): the rejected
    observations after it agree on a place, but the mapping pass places no landmark there; the
    warning says so rather than "0 landmark(s) added"."""
    dataset = simulate(SimulationConfig(poses=20), seed=3)
    translation = dataset.odom_translation.copy()
    translation[9, 0] = 1e3
    result = localize(dataclasses.replace(dataset, odom_translation=translation))
    said = [warning for warning in result.summary["warnings"] if warning.startswith("the map lacks landmarks")]
    assert result.summary["map"]["added"] == 0 and len(said) == 1
    assert "the mapping pass added none of them" in said[0] and "0 landmark(s)" not in said[0]


def test_the_real_file_with_half_its_map_is_reported(tmp_path, real_dataset_path):
    half = _without_every_other_landmark(real_dataset_path, tmp_path / "half.g2o")
    outcome = invoke("run", half, "-o", tmp_path / "run", "--json")
    assert outcome.exit_code == 0, outcome.output
    summary = json.loads(outcome.stdout)
    assert any("the map lacks landmarks" in warning for warning in summary["warnings"])
    # and the run added what the map lacks (issue 38: in every mode), its pairs no longer rejected
    assert summary["map"]["mode"] == "exact" and summary["map"]["added"] >= 10
    assert summary["association"]["to_added"] > 50


@pytest.mark.parametrize("args, name", [([], "iterated EKF (euler)"), (["--iterations", "1", "--filter", "se3"], "EKF (se3)")])
def test_the_tables_name_the_filter_that_ran(tmp_path, world, args, name):
    run_dir = tmp_path / "run"
    outcome = invoke("run", world, "-o", run_dir, *args)
    assert outcome.exit_code == 0, outcome.output
    assert name in next(line for line in outcome.stdout.splitlines() if "odometry only" in line)
    evaluation = invoke("eval", run_dir)
    assert name in next(line for line in evaluation.stdout.splitlines() if "odometry" in line and "metric" in line)


def test_a_run_that_cannot_map_says_why_beside_the_incomplete_map():
    counts = {"observations": 801, "rejected": 400, "updates": 300}
    (plain,) = run_warnings(counts)
    (planar,) = run_warnings(counts, map_size=70, unmappable="this dataset's robot observes markers")
    assert planar.startswith(plain) and planar.endswith(f"only for {MAPPED_LANDMARKS}, and this dataset's robot observes markers")
    assert run_warnings(counts, mapped=True, unmappable="x") == []


def test_a_pixel_only_run_on_an_incomplete_map_says_its_lacking_landmarks_are_not_found():
    """Rays do not place their landmarks: a pixel-only file whose map looks incomplete is told so
    (its run may be lost), a file with range or a planar robot's points is not."""
    from camloc import measurement
    from camloc.diagnostics import RAYS_NOT_MAPPED, rays_only
    from camloc.simulate import SimulationConfig, simulate

    counts = {"observations": 801, "rejected": 400, "updates": 300}
    (plain,) = run_warnings(counts)
    (rays,) = run_warnings(counts, rays_only=True)
    assert rays == plain + RAYS_NOT_MAPPED and "pixel-only" in rays
    assert run_warnings({"observations": 801, "rejected": 20, "updates": 300}, rays_only=True) == []  # a complete map
    pixel = simulate(SimulationConfig(poses=20, measurement="pixel", cameras=2), seed=0)
    depth = simulate(SimulationConfig(poses=20), seed=0)
    assert rays_only(pixel.obs_kind) and not rays_only(depth.obs_kind) and not rays_only(pixel.obs_kind[:0])
    assert not rays_only(np.array([measurement.PIXEL, measurement.POINT2]))  # a planar robot's points place theirs


def test_a_pixel_only_run_with_no_map_is_told_its_estimate_may_be_worse_than_odometry(tmp_path):
    """Pixel-only cameras with no map (EKF-SLAM of rays): the run says its estimate is not reliable;
    a depth camera's run with no map, or a pixel-only run on its map, does not."""
    import json

    from typer.testing import CliRunner

    from camloc.cli.app import app
    from camloc.diagnostics import RAYS_NO_MAP

    counts = {"observations": 801, "rejected": 400, "updates": 300}
    assert run_warnings(counts, mapped=True, rays_only=True, map_mode="none") == [RAYS_NO_MAP]
    assert run_warnings(counts, mapped=True, rays_only=False, map_mode="none") == []
    assert run_warnings(counts, mapped=True, rays_only=True, map_mode="prior") == []
    runner = CliRunner()
    for measurement_kind, said in (("pixel", True), ("depth", False)):
        world = tmp_path / f"{measurement_kind}.g2o"
        made = runner.invoke(app, ["simulate", "-o", str(world), "--poses", "40", "--cameras", "2", "--measurement",
                                   measurement_kind, "--no-map", "-q"])
        assert made.exit_code == 0, made.output
        run = runner.invoke(app, ["run", str(world), "-o", str(tmp_path / measurement_kind), "-q"])
        assert run.exit_code == 0, run.output
        summary = json.loads((tmp_path / measurement_kind / "summary.json").read_text())
        assert summary["map"]["mode"] == "none"
        assert (RAYS_NO_MAP in summary["warnings"]) == said
        assert (f"warning: {world}: {RAYS_NO_MAP}" in run.stderr) == said


def test_an_empty_map_is_not_called_incomplete_but_says_what_maps_it():
    counts = {"observations": 295, "rejected": 295, "updates": 0}
    odometry, no_map = run_warnings(counts, map_size=0, unmappable="this dataset's robot observes markers")
    assert "odometry alone" in odometry and "the map may lack" not in no_map
    assert no_map == f"the file has no map, and camloc maps (EKF-SLAM) only {MAPPED_LANDMARKS}: this dataset's robot observes markers"
    assert "'--map none'" in run_warnings(counts, map_size=0)[1]


def test_a_tag_file_without_a_map_is_mapped_and_not_warned_about(tmp_path):
    """Tags are mapped with their orientations (tests/test_mapping_tags.py): a tag file without a
    map runs --map none by default, adds its tags, and says nothing of an unmapped dataset."""
    import json

    from typer.testing import CliRunner

    from camloc.cli.app import app

    dataset = tmp_path / "nomap.g2o"
    made = CliRunner().invoke(app, ["simulate", "-o", str(dataset), "--tag-sigma-deg", "1", "--no-map", "--poses", "30", "-q"])
    assert made.exit_code == 0, made.output
    result = CliRunner().invoke(app, ["run", str(dataset), "-o", str(tmp_path / "run"), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["map"]["mode"] == "none" and summary["map"]["added"] >= 1
    assert not any("camloc maps (EKF-SLAM) only" in w or "the map may lack" in w for w in summary["warnings"])


def test_a_lost_run_on_a_complete_clutter_free_map_is_not_blamed_on_the_map_alone(tmp_path):
    """The audit of 2026-12-06's world: a complete map and no clutter, two detections a pose, a pixel
    camera beside a depth one and 3x odometry noise. The beam loses the robot (1.66 m against the
    true association's 0.11 m), and the landmarks it then rejects read as an incomplete map's; the
    warning named only the map and clutter, neither of which this world has."""
    path = tmp_path / "lost.g2o"
    made = invoke("simulate", "-o", path, "-q", "--poses", 80, "--seed", 748, "--trajectory", "smooth3d", "--cameras", 2,
                  "--measurement", "depth,pixel", "--intrinsics", "pixel", "--max-observations-per-pose", 2,
                  "--odometry-sigma-scale", 3.0, "--observe-first-pose", "--fov-half-angle-deg", 25.0)
    assert made.exit_code == 0, made.output
    run_dir = tmp_path / "run"
    outcome = invoke("run", path, "-o", run_dir, "-q")
    assert outcome.exit_code == 0, outcome.output
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["association"]["clutter"] == 0  # every detection is of a map landmark
    assert summary["association"]["precision"] < 0.6 and summary["estimate"]["ate"]["rmse"] > 1.0  # lost
    (warning,) = [w for w in summary["warnings"] if "were rejected" in w]
    assert "the map may lack landmarks" in warning and "the filter lost the robot" in warning
    assert "compare the estimate with odometry's" in warning
