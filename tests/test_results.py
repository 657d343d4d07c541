"""Run-folder I/O: TUM and CSV round trips, save_run/load_run, atomicity, clear errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from camloc import geometry, results
from camloc.errors import CamlocError, DatasetError
from camloc.results import load_run, read_tum, save_run, write_tum

ARRAY_FIELDS = (
    "pose_ids", "estimate_xyz", "estimate_quat_xyzw", "estimate_cov", "filter_state", "filter_cov",
    "odometry_xyz", "odometry_quat_xyzw", "truth_xyz", "truth_quat_xyzw", "map_landmark_ids",
    "map_landmark_xyz", "update_pose_ids", "nis", "nis_dof",
)


def _leftovers(folder: Path) -> list[str]:
    return sorted(path.name for path in folder.iterdir() if path.name.startswith("."))


# --------------------------------------------------------------------------------------------
# TUM


def test_tum_round_trip_is_exact(tmp_path, rng):
    stamps = np.arange(1000, 1020, dtype=float)
    xyz = rng.normal(0.0, 10.0, (20, 3))
    quat = geometry.euler_to_quat(rng.uniform(-3.0, 3.0, (20, 3)))
    write_tum(tmp_path / "a.tum", stamps, xyz, quat)
    stamps_read, xyz_read, quat_read = read_tum(tmp_path / "a.tum")
    np.testing.assert_array_equal(stamps_read, stamps)
    np.testing.assert_array_equal(xyz_read, xyz)  # repr: the shortest text that reads back exactly
    np.testing.assert_allclose(quat_read, quat, rtol=0, atol=1e-15)
    assert (tmp_path / "a.tum").read_text().splitlines()[1].split()[0] == "1000.0"


def test_read_tum_skips_comments_and_blank_lines_and_normalizes_quaternions(tmp_path):
    path = tmp_path / "b.tum"
    path.write_text("# a comment\n\n1 0 0 0 0 0 0 2\n  # indented comment\n2.5 1 2 3 0 0 3 4\n")
    stamps, xyz, quat = read_tum(path)
    np.testing.assert_array_equal(stamps, [1.0, 2.5])
    np.testing.assert_array_equal(xyz[1], [1.0, 2.0, 3.0])
    np.testing.assert_allclose(quat, [[0, 0, 0, 1], [0, 0, 0.6, 0.8]])


@pytest.mark.parametrize(
    "text, line, fragment",
    [
        ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n", 2, "expected 8 fields"),
        ("# header\n1 0 0 x 0 0 0 1\n", 2, "expected a number for z, found 'x'"),
        ("1 0 0 0 0 0 0 nan\n", 1, "expected a finite number for qw"),
        ("1 0 0 0 0 0 0 0\n", 1, "found all zeros"),
        ("1 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n", 2, "first on line 1"),
        ("# only a comment\n", None, "found none"),
    ],
)
def test_read_tum_reports_the_bad_line(tmp_path, text, line, fragment):
    path = tmp_path / "bad.tum"
    path.write_text(text)
    with pytest.raises(DatasetError) as caught:
        read_tum(path)
    assert caught.value.line == line
    assert fragment in str(caught.value)
    assert str(caught.value).startswith(f"{path}:{line}:" if line else f"{path}:")


def test_read_tum_of_a_missing_file(tmp_path):
    with pytest.raises(DatasetError, match="no such file"):
        read_tum(tmp_path / "missing.tum")


# --------------------------------------------------------------------------------------------
# Single-file atomic writes


def test_atomic_write_keeps_the_old_file_when_writing_fails(tmp_path):
    path = tmp_path / "out.txt"
    results.write_text_atomic(path, "old\n")
    with pytest.raises(RuntimeError):
        with results.atomic_write(path) as handle:
            handle.write("half of the new")
            raise RuntimeError("disk full")
    assert path.read_text() == "old\n"
    assert _leftovers(tmp_path) == []


def test_write_json_is_strict_and_converts_numpy(tmp_path):
    path = tmp_path / "x.json"
    results.write_json_atomic(path, {"a": np.float32(1.5), "b": np.arange(3), "c": float("nan"), "d": (np.int64(2),)})
    assert json.loads(path.read_text()) == {"a": 1.5, "b": [0, 1, 2], "c": None, "d": [2]}


def test_atomic_write_into_a_missing_directory_is_a_camloc_error(tmp_path):
    with pytest.raises(CamlocError, match="cannot write"):
        results.write_text_atomic(tmp_path / "nope" / "x.txt", "x")


# --------------------------------------------------------------------------------------------
# Run folders


def test_save_and_load_round_trip(tmp_path, synthetic_run):
    result = synthetic_run()
    save_run(tmp_path / "run", result)
    loaded = load_run(tmp_path / "run")

    assert loaded.dataset == result.dataset
    for name in ARRAY_FIELDS:
        np.testing.assert_array_equal(getattr(loaded, name), getattr(result, name), err_msg=name)
    for name in ("pose_id", "camera", "uvd", "landmark", "true_landmark", "mahalanobis"):
        np.testing.assert_array_equal(getattr(loaded.associations, name), getattr(result.associations, name),
                                      err_msg=name)
    assert loaded.pose_ids.dtype == np.int64 and loaded.associations.landmark.dtype == np.int64
    # numpy scalars became JSON numbers, inf became null.
    assert loaded.summary["config"] == {"gate_probability": 0.99, "seed": 7}
    assert loaded.summary["timing"]["poses_per_second"] is None


def test_run_folder_files(tmp_path, synthetic_run):
    result = synthetic_run()
    run_dir = save_run(tmp_path / "run", result)
    assert sorted(p.name for p in run_dir.iterdir()) == [
        "associations.csv", "estimate.tum", "groundtruth.tum", "odometry.tum", "states.npz", "summary.json"
    ]
    lines = (run_dir / "associations.csv").read_text().splitlines()
    assert lines[0] == "pose,camera,u,v,depth,landmark,true_landmark,mahalanobis"
    assert len(lines) == 1 + len(result.associations.pose_id)
    rejected = int(np.flatnonzero(result.associations.landmark == results.UNASSOCIATED)[0])
    fields = lines[1 + rejected].split(",")
    assert fields[5] == "" and fields[7] == "" and fields[6] == str(result.associations.true_landmark[rejected])
    stamps, xyz, _ = read_tum(run_dir / "groundtruth.tum")
    np.testing.assert_array_equal(stamps, result.pose_ids)
    np.testing.assert_array_equal(xyz, result.truth_xyz)
    assert json.loads((run_dir / "summary.json").read_text())["dataset"] == result.summary["dataset"]
    assert _leftovers(tmp_path) == []


def test_run_without_truth_has_no_groundtruth_file(tmp_path, synthetic_run):
    run_dir = save_run(tmp_path / "run", synthetic_run(with_truth=False))
    assert not (run_dir / "groundtruth.tum").exists()
    loaded = load_run(run_dir)
    assert loaded.truth_xyz is None and loaded.truth_quat_xyzw is None


def test_a_failing_save_leaves_no_folder(tmp_path, synthetic_run, monkeypatch):
    def broken_savez(*args, **kwargs):
        raise OSError("no space left on device")

    monkeypatch.setattr(results.np, "savez_compressed", broken_savez)
    with pytest.raises(OSError, match="no space"):
        save_run(tmp_path / "run", synthetic_run())
    assert list(tmp_path.iterdir()) == []


def test_a_failing_save_keeps_the_previous_run(tmp_path, synthetic_run, monkeypatch):
    run_dir = tmp_path / "run"
    save_run(run_dir, synthetic_run(seed=1))
    before = {p.name: p.read_bytes() for p in run_dir.iterdir()}

    def broken_dumps(obj):
        raise TypeError("cannot convert")

    monkeypatch.setattr(results, "dumps_json", broken_dumps)
    with pytest.raises(TypeError):
        save_run(run_dir, synthetic_run(seed=2))
    assert {p.name: p.read_bytes() for p in run_dir.iterdir()} == before
    assert _leftovers(tmp_path) == []


def test_saving_again_replaces_the_run_whole(tmp_path, synthetic_run):
    run_dir = tmp_path / "run"
    save_run(run_dir, synthetic_run(seed=1))
    save_run(run_dir, synthetic_run(seed=2, with_truth=False))
    assert not (run_dir / "groundtruth.tum").exists()  # nothing of the old run survives
    assert load_run(run_dir).dataset == "synthetic-circle-2"
    assert _leftovers(tmp_path) == []


def test_save_refuses_to_replace_a_folder_that_is_not_a_run(tmp_path, synthetic_run):
    precious = tmp_path / "thesis"
    precious.mkdir()
    (precious / "chapter1.tex").write_text("years of work")
    with pytest.raises(CamlocError, match="refusing to replace it"):
        save_run(precious, synthetic_run())
    assert (precious / "chapter1.tex").read_text() == "years of work"


def test_save_rejects_a_malformed_result(tmp_path, synthetic_run):
    import dataclasses

    bad = dataclasses.replace(synthetic_run(), nis=np.zeros(3))
    with pytest.raises(ValueError, match=r"nis has shape \(3,\)"):
        save_run(tmp_path / "run", bad)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------
# load_run errors


def test_load_run_of_a_missing_folder(tmp_path):
    with pytest.raises(CamlocError, match="no such directory"):
        load_run(tmp_path / "nothing")


def test_load_run_of_a_folder_missing_files(tmp_path, synthetic_run):
    run_dir = save_run(tmp_path / "run", synthetic_run())
    (run_dir / "states.npz").unlink()
    with pytest.raises(CamlocError, match="missing states.npz"):
        load_run(run_dir)


def test_load_run_of_a_corrupt_archive(tmp_path, synthetic_run):
    run_dir = save_run(tmp_path / "run", synthetic_run())
    data = (run_dir / "states.npz").read_bytes()
    (run_dir / "states.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match="states.npz: expected a numpy .npz archive"):
        load_run(run_dir)


def test_load_run_of_an_archive_missing_an_array(tmp_path, synthetic_run):
    run_dir = save_run(tmp_path / "run", synthetic_run())
    with np.load(run_dir / "states.npz") as npz:
        arrays = {name: npz[name] for name in npz.files if name != "nis"}
    np.savez(run_dir / "states.npz", **arrays)
    with pytest.raises(DatasetError, match="expected arrays nis"):
        load_run(run_dir)


def test_load_run_of_inconsistent_arrays(tmp_path, synthetic_run):
    run_dir = save_run(tmp_path / "run", synthetic_run())
    with np.load(run_dir / "states.npz") as npz:
        arrays = {name: npz[name] for name in npz.files}
    arrays["estimate_xyz"] = arrays["estimate_xyz"][:-1]
    np.savez(run_dir / "states.npz", **arrays)
    with pytest.raises(CamlocError, match=r"inconsistent run folder: estimate_xyz has shape \(39, 3\)"):
        load_run(run_dir)


def test_load_run_of_corrupt_json_names_the_line(tmp_path, synthetic_run):
    run_dir = save_run(tmp_path / "run", synthetic_run())
    (run_dir / "summary.json").write_text('{\n  "dataset": "x",\n  oops\n}\n')
    with pytest.raises(DatasetError) as caught:
        load_run(run_dir)
    assert caught.value.line == 3 and "summary.json:3: expected JSON" in str(caught.value)


@pytest.mark.parametrize(
    "edit, line, fragment",
    [
        (lambda lines: ["pose,camera,u,v"] + lines[1:], 1, "expected the header"),
        (lambda lines: lines[:3] + ["1001,0,0.1,0.2"] + lines[4:], 4, "expected 8 comma-separated fields, found 4"),
        (lambda lines: lines[:2] + ["1001,0,0.1,zero,1.0,100,100,"] + lines[3:], 3, "expected a number for v"),
        (lambda lines: lines[:2] + ["1001,0,0.1,0.2,1.0,100,,"] + lines[3:], 3, "expected a value for true_landmark"),
    ],
)
def test_load_run_of_a_bad_associations_csv_names_the_line(tmp_path, synthetic_run, edit, line, fragment):
    run_dir = save_run(tmp_path / "run", synthetic_run())
    path = run_dir / "associations.csv"
    path.write_text("\n".join(edit(path.read_text().splitlines())) + "\n")
    with pytest.raises(DatasetError) as caught:
        load_run(run_dir)
    assert caught.value.line == line
    assert fragment in str(caught.value)
