"""Run-folder I/O: TUM and CSV round trips, save_run/load_run, atomicity, clear errors."""

from __future__ import annotations

import dataclasses
import errno
import json
from pathlib import Path

import numpy as np
import pytest

from camloc import atomic_files, geometry, results
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
        # beyond a run's bound (results.MAX_RUN_COORDINATE): squared in the metrics, 1e200
        # overflows (numpy warnings, a singular matrix in the plots)
        ("1 0 0 0 0 0 0 1\n2 1e200 0 0 0 0 0 1\n", 2, "expected metres within +-1e+15 for x, found 1e200"),
        ("1 0 0 -2e15 0 0 0 1\n", 1, "expected metres within +-1e+15 for z"),
        ("1 1_0 0 0 0 0 0 1\n", 1, "expected a number for x, found '1_0'"),
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


def test_read_tum_accepts_a_byte_order_mark(tmp_path):
    path = tmp_path / "bom.tum"
    path.write_bytes("\ufeff1 0 0 0 0 0 0 1\n2 1 0 0 0 0 0 1\n".encode())
    stamps, xyz, _ = read_tum(path)
    np.testing.assert_array_equal(stamps, [1.0, 2.0])
    np.testing.assert_array_equal(xyz[1], [1.0, 0.0, 0.0])


def test_read_tum_normalizes_quaternions_whose_squares_overflow_or_underflow(tmp_path):
    path = tmp_path / "scaled.tum"
    path.write_text("1 0 0 0 0 0 0 1e200\n2 0 0 0 0 0 3e300 4e300\n3 0 0 0 0 0 3e-200 4e-200\n")
    _, _, quat = read_tum(path)
    np.testing.assert_allclose(quat, [[0, 0, 0, 1], [0, 0, 0.6, 0.8], [0, 0, 0.6, 0.8]], rtol=0, atol=1e-15)


def test_read_tum_of_a_missing_file(tmp_path):
    with pytest.raises(DatasetError, match="no such file"):
        read_tum(tmp_path / "missing.tum")


# --------------------------------------------------------------------------------------------
# Single-file atomic writes


def test_atomic_write_keeps_the_old_file_when_writing_fails(tmp_path):
    path = tmp_path / "out.txt"
    atomic_files.write_text_atomic(path, "old\n")
    with pytest.raises(RuntimeError):
        with atomic_files.atomic_write(path) as handle:
            handle.write("half of the new")
            raise RuntimeError("disk full")
    assert path.read_text() == "old\n"
    assert _leftovers(tmp_path) == []


def test_a_full_disk_names_the_output_and_leaves_nothing(tmp_path):
    """A full disk's OSError names no file ("No space left on device" from write or close): the
    error says which output could not be written, and no temporary is left."""
    path = tmp_path / "out.g2o"
    with pytest.raises(CamlocError, match=f"^cannot write {path}: No space left on device$"):
        with atomic_files.atomic_write(path) as handle:
            handle.write("half")
            raise OSError(errno.ENOSPC, "No space left on device")

    def full_disk(path, handle):
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(CamlocError, match=f"^cannot write {tmp_path / 'b.png'}: No space left on device$"):
        atomic_files.write_files_atomic([tmp_path / "b.png"], full_disk)
    assert list(tmp_path.iterdir()) == []


def test_write_json_is_strict_and_converts_numpy(tmp_path):
    path = tmp_path / "x.json"
    results.write_json_atomic(path, {"a": np.float32(1.5), "b": np.arange(3), "c": float("nan"), "d": (np.int64(2),)})
    assert json.loads(path.read_text()) == {"a": 1.5, "b": [0, 1, 2], "c": None, "d": [2]}


def test_write_files_atomic_writes_all_or_none(tmp_path):
    old = tmp_path / "a.png"
    old.write_bytes(b"old a")

    def write(path, handle):
        if path.name == "c.png":
            raise RuntimeError("drawing failed")
        handle.write(b"new " + path.name.encode())

    with pytest.raises(RuntimeError):
        atomic_files.write_files_atomic([tmp_path / "a.png", tmp_path / "b.png", tmp_path / "c.png"], write)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png"]  # no b.png, no temporaries
    assert old.read_bytes() == b"old a"

    atomic_files.write_files_atomic([tmp_path / "a.png", tmp_path / "b.png"], write)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.png"]
    assert old.read_bytes() == b"new a.png"
    assert oct((tmp_path / "b.png").stat().st_mode & 0o777) == oct(0o644)


def test_atomic_writes_create_missing_folders_or_say_they_cannot(tmp_path):
    atomic_files.write_text_atomic(tmp_path / "new" / "deeper" / "x.txt", "x")
    assert (tmp_path / "new" / "deeper" / "x.txt").read_text() == "x"
    (tmp_path / "a-file").write_text("")
    with pytest.raises(CamlocError, match=f"cannot create the folder {tmp_path / 'a-file' / 'sub'}: "):
        atomic_files.write_text_atomic(tmp_path / "a-file" / "sub" / "x.txt", "x")


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
    assert loaded.summary["config"] == {"gate": 0.99, "seed": 7}
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


def test_a_run_beyond_the_datasets_bound_reads_back(tmp_path, synthetic_run):
    """A start at the g2o reader's bound (1e9 m) and a path from it: the run's positions pass
    1e9, and the folder camloc wrote must load (eval and smooth refused it before)."""
    result = synthetic_run()
    far = dataclasses.replace(result, estimate_xyz=result.estimate_xyz + 1.5e9, odometry_xyz=result.odometry_xyz + 1.5e9,
                              truth_xyz=result.truth_xyz + 1.5e9, map_landmark_xyz=result.map_landmark_xyz + 1.5e9)
    loaded = load_run(save_run(tmp_path / "run", far))
    np.testing.assert_array_equal(loaded.estimate_xyz, far.estimate_xyz)
    np.testing.assert_array_equal(loaded.map_landmark_xyz, far.map_landmark_xyz)


def test_run_without_truth_has_no_groundtruth_file(tmp_path, synthetic_run):
    run_dir = save_run(tmp_path / "run", synthetic_run(with_truth=False))
    assert not (run_dir / "groundtruth.tum").exists()
    loaded = load_run(run_dir)
    assert loaded.truth_xyz is None and loaded.truth_quat_xyzw is None


def test_a_failing_save_leaves_no_folder(tmp_path, synthetic_run, monkeypatch):
    def broken_savez(*args, **kwargs):
        raise OSError("no space left on device")

    monkeypatch.setattr(results.np, "savez_compressed", broken_savez)
    # a write's OSError names no file: the error names the run folder asked for
    with pytest.raises(CamlocError, match=f"cannot write {tmp_path / 'run'}: no space left on device"):
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
        save_run(run_dir, synthetic_run(seed=2), force=True)
    assert {p.name: p.read_bytes() for p in run_dir.iterdir()} == before
    assert _leftovers(tmp_path) == []


def test_saving_again_is_refused_without_force(tmp_path, synthetic_run):
    run_dir = tmp_path / "run"
    save_run(run_dir, synthetic_run(seed=1))
    before = {p.name: p.read_bytes() for p in run_dir.iterdir()}
    with pytest.raises(CamlocError, match=f"{run_dir}: already exists; refusing to replace it without --force"):
        save_run(run_dir, synthetic_run(seed=2))
    assert {p.name: p.read_bytes() for p in run_dir.iterdir()} == before


def test_saving_again_with_force_replaces_the_run_and_keeps_the_users_files(tmp_path, synthetic_run):
    run_dir = tmp_path / "run"
    save_run(run_dir, synthetic_run(seed=1))
    (run_dir / "notes.md").write_text("what I saw")
    (run_dir / "mine").mkdir()
    (run_dir / "mine" / "fig-topdown.png").write_bytes(b"my own figure")
    for stale in ("smoothed.tum", "fig-topdown.png", "fig-errors.pdf"):  # derived from the old run
        (run_dir / stale).write_bytes(b"old")
    save_run(run_dir, synthetic_run(seed=2, with_truth=False), force=True)
    assert sorted(p.name for p in run_dir.iterdir()) == [
        "associations.csv", "estimate.tum", "mine", "notes.md", "odometry.tum", "states.npz", "summary.json"
    ]
    assert (run_dir / "notes.md").read_text() == "what I saw"
    assert (run_dir / "mine" / "fig-topdown.png").read_bytes() == b"my own figure"
    assert load_run(run_dir).dataset == "synthetic-circle-2"
    assert _leftovers(tmp_path) == []


def test_a_failing_forced_save_keeps_the_previous_run_and_the_users_files(tmp_path, synthetic_run, monkeypatch):
    run_dir = tmp_path / "run"
    save_run(run_dir, synthetic_run(seed=1))
    (run_dir / "notes.md").write_text("what I saw")
    before = {p.name: p.read_bytes() for p in run_dir.iterdir()}

    def broken_rename(tmp, target):
        raise OSError("device busy")

    monkeypatch.setattr(results, "_move_into_place", broken_rename)
    with pytest.raises(OSError, match="device busy"):
        save_run(run_dir, synthetic_run(seed=2), force=True)
    assert {p.name: p.read_bytes() for p in run_dir.iterdir()} == before
    assert _leftovers(tmp_path) == []


def test_save_refuses_to_replace_a_folder_that_is_not_a_run(tmp_path, synthetic_run):
    precious = tmp_path / "thesis"
    precious.mkdir()
    (precious / "chapter1.tex").write_text("years of work")
    for force in (False, True):
        with pytest.raises(CamlocError, match="is not a camloc run folder; refusing to replace it"):
            save_run(precious, synthetic_run(), force=force)
    assert [p.name for p in precious.iterdir()] == ["chapter1.tex"]
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


def test_a_run_scored_against_ground_truth_needs_its_ground_truth_file(tmp_path, synthetic_run):
    # eval said "no ground truth in the run" once groundtruth.tum was deleted, while summary.json
    # held the run's errors against it
    import dataclasses

    run = synthetic_run()
    scored = save_run(tmp_path / "scored", dataclasses.replace(run, summary={**run.summary, "estimate": {"ate": {"rmse": 0.1}}}))
    (scored / "groundtruth.tum").unlink()
    with pytest.raises(DatasetError, match="groundtruth.tum: missing, but summary.json scores the run against ground truth"):
        load_run(scored)
    plain = save_run(tmp_path / "plain", run)  # a summary without scores: the truth is optional
    (plain / "groundtruth.tum").unlink()
    assert load_run(plain).truth_xyz is None


def test_load_run_of_a_corrupt_archive(tmp_path, synthetic_run):
    run_dir = save_run(tmp_path / "run", synthetic_run())
    data = (run_dir / "states.npz").read_bytes()
    (run_dir / "states.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match="states.npz: expected a numpy .npz archive"):
        load_run(run_dir)


def test_load_run_of_an_archive_of_pickled_objects_does_not_suggest_loading_it(tmp_path, synthetic_run):
    run_dir = save_run(tmp_path / "run", synthetic_run())
    np.savez(run_dir / "states.npz", format_version=np.array([{"a": 1}], dtype=object))
    with pytest.raises(DatasetError) as caught:
        load_run(run_dir)
    assert "found pickled Python objects (not loaded" in str(caught.value) and "allow_pickle" not in str(caught.value)


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
    arrays["filter_state"] = arrays["filter_state"][:-1]
    np.savez(run_dir / "states.npz", **arrays)
    with pytest.raises(CamlocError, match=r"inconsistent run folder: filter_state has shape \(39, 6\)"):
        load_run(run_dir)


def test_load_run_of_corrupt_json_names_the_line(tmp_path, synthetic_run):
    run_dir = save_run(tmp_path / "run", synthetic_run())
    (run_dir / "summary.json").write_text('{\n  "dataset": "x",\n  oops\n}\n')
    with pytest.raises(DatasetError) as caught:
        load_run(run_dir)
    assert caught.value.line == 3 and "summary.json:3: expected JSON" in str(caught.value)


def test_load_run_of_json_nested_too_deep(tmp_path, synthetic_run):
    # json recurses per level: 100,000 levels was a RecursionError traceback.
    run_dir = save_run(tmp_path / "run", synthetic_run())
    (run_dir / "summary.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(DatasetError, match="summary.json: expected JSON, found arrays or objects nested too deep"):
        load_run(run_dir)


def test_load_run_accepts_files_with_a_byte_order_mark(tmp_path, synthetic_run):
    run_dir = save_run(tmp_path / "run", synthetic_run())
    for name in ("summary.json", "associations.csv"):
        path = run_dir / name
        path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    assert load_run(run_dir).summary["dataset"] == "synthetic-circle-7"


@pytest.mark.parametrize(
    "edit, line, fragment",
    [
        (lambda lines: ["pose,camera,u,v"] + lines[1:], 1, "expected the header"),
        (lambda lines: lines[:3] + ["1001,0,0.1,0.2"] + lines[4:], 4, "expected 8 comma-separated fields, found 4"),
        (lambda lines: lines[:2] + ["1001,0,0.1,zero,1.0,100,100,"] + lines[3:], 3, "expected a number for v"),
        (lambda lines: lines[:2] + ["1001,0,0.1,0.2,1.0,100,,"] + lines[3:], 3, "expected a value for true_landmark"),
        # an id beyond 64 bits was an OverflowError traceback
        (lambda lines: lines[:1] + ["1001,0,0.1,0.2,1.0,99999999999999999999999,100,1.0"] + lines[2:], 2,
         "expected an integer for landmark that fits in 64 bits, found 99999999999999999999999"),
        (lambda lines: lines[:1] + ["1001,0,0.1,0.2,1.0,1_00,100,1.0"] + lines[2:], 2, "expected an integer for landmark"),
        # the writer never writes NaN or inf: an empty cell is how it says "none"
        (lambda lines: lines[:1] + ["1001,0,nan,nan,nan,100,100,1.0"] + lines[2:], 2, "expected a finite number for u, found 'nan'"),
        (lambda lines: lines[:1] + ["1001,0,0.1,0.2,1.0,100,100,inf"] + lines[2:], 2, "expected a finite number for mahalanobis"),
        # an observation of a pose the run does not have: a broadcast error in the plots, and
        # silently left out by eval
        (lambda lines: lines[:1] + ["99999,0,0.5,0.5,1,100,100,1.0"] + lines[2:], 2,
         "inconsistent run folder: pose 99999 is not one of the run's 40 poses in states.npz (1000..1039)"),
        (lambda lines: lines[:3] + ["", "99999,0,0.5,0.5,1,100,100,1.0"] + lines[4:], 5, "pose 99999 is not one of"),
        # a landmark the run's map does not have, or a negative distance: scored as a wrong pair before
        (lambda lines: lines[:1] + ["1001,0,0.5,0.5,1,123456,57,1.0"] + lines[2:], 2,
         "inconsistent run folder: landmark 123456 is not in the run's map in states.npz (30 landmarks)"),
        (lambda lines: lines[:1] + ["1001,0,0.5,0.5,1,100,100,-50.5"] + lines[2:], 2,
         "expected a Mahalanobis distance >= 0, found -50.5"),
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


# --------------------------------------------------------------------------------------------
# states.npz: every array's type, shape and values


def _rewrite_states(run_dir: Path, **changes) -> None:
    with np.load(run_dir / "states.npz") as npz:
        arrays = {name: npz[name] for name in npz.files}
    arrays.update(changes)
    np.savez(run_dir / "states.npz", **arrays)


def _asymmetric(cov: np.ndarray) -> np.ndarray:
    cov = cov.copy()
    cov[5, 0, 1] += 1e-3
    return cov


# name -> (the changed arrays of states.npz, from the run; a fragment of the error), after the
# fuzzing pass's folders: each was a traceback in eval, plot or smooth, or a silent NaN.
STATES_CORRUPTIONS = {
    "version-str": (lambda run: dict(format_version=np.array("abc")), "expected format_version 1 or 2, found 'abc'"),
    "version-arr": (lambda run: dict(format_version=np.array([1, 2])),
                    "expected format_version 1 or 2, found an array of int64 of shape (2,)"),
    "version-float": (lambda run: dict(format_version=np.array(1.5)), "expected format_version 1 or 2, found 1.5"),
    "dataset-arr": (lambda run: dict(dataset=np.array(["a", "b"])), "dataset: expected one string"),
    "0d-ids": (lambda run: dict(pose_ids=np.array(5)), "pose_ids: expected shape (N,), found ()"),
    "float-ids": (lambda run: dict(pose_ids=run.pose_ids + 0.5), "pose_ids: expected 64-bit integers, found float64"),
    "dup-ids": (lambda run: dict(pose_ids=np.zeros_like(run.pose_ids)), "pose_ids: expected distinct ids, found 0 more than once"),
    "no-poses": (lambda run: {name: getattr(run, name)[:0] for name in ("pose_ids", "estimate_cov", "filter_state", "filter_cov")},
                 "pose_ids: expected at least one pose"),
    "str-map": (lambda run: dict(map_landmark_xyz=np.full((30, 3), "a")), "map_landmark_xyz: expected real numbers, found <U1"),
    "complex-cov": (lambda run: dict(estimate_cov=run.estimate_cov + 1j), "estimate_cov: expected real numbers, found complex128"),
    "map-shape": (lambda run: dict(map_landmark_xyz=run.map_landmark_xyz[:, :2]),
                  "map_landmark_xyz: expected shape (N, 3), found (30, 2)"),
    "cov-shape": (lambda run: dict(filter_cov=run.filter_cov[:, :, :5]), "filter_cov: expected shape (N, D, D), found (40, 6, 5)"),
    "nan-map": (lambda run: dict(map_landmark_xyz=np.full((30, 3), np.nan)),
                "map_landmark_xyz: expected finite metres within +-1e+15, found nan at row 0"),
    "huge-map": (lambda run: dict(map_landmark_xyz=run.map_landmark_xyz * 1e300),
                 "map_landmark_xyz: expected finite metres within +-1e+15"),
    "inf-state": (lambda run: dict(filter_state=np.where(np.arange(6) == 2, np.inf, run.filter_state)),
                  "filter_state: expected finite numbers, found inf at pose 1000"),
    "nan-cov": (lambda run: dict(estimate_cov=np.full((40, 6, 6), np.nan)),
                "estimate_cov: expected finite numbers, found nan at pose 1000"),
    "zero-cov": (lambda run: dict(estimate_cov=np.zeros((40, 6, 6))), "estimate_cov: expected covariances, found zeros at every pose"),
    "neg-cov": (lambda run: dict(estimate_cov=-run.estimate_cov),
                "estimate_cov: expected positive semi-definite matrices, found eigenvalue"),
    "asym-cov": (lambda run: dict(filter_cov=_asymmetric(run.filter_cov)),
                 "filter_cov: expected symmetric matrices, found an asymmetric one at pose 1005"),
    "neg-nis": (lambda run: dict(nis=-run.nis), "nis: expected finite numbers >= 0, found -"),
    "nan-nis": (lambda run: dict(nis=np.full_like(run.nis, np.nan)), "nis: expected finite numbers >= 0, found nan at row 0"),
    "zero-dof": (lambda run: dict(nis_dof=np.zeros_like(run.nis_dof)), "nis_dof: expected counts of at least 1, found 0 at row 0"),
    "unknown-update": (lambda run: dict(update_pose_ids=run.update_pose_ids + 5000),
                       "update_pose_ids: expected ids of the run's poses"),
}


@pytest.mark.parametrize("name", STATES_CORRUPTIONS)
def test_load_run_rejects_a_corrupt_states_archive(tmp_path, synthetic_run, name):
    run = synthetic_run()  # 40 poses
    changes, fragment = STATES_CORRUPTIONS[name]
    run_dir = save_run(tmp_path / "run", run)
    _rewrite_states(run_dir, **changes(run))
    with pytest.raises(DatasetError) as caught:
        load_run(run_dir)
    assert str(caught.value).startswith(f"{run_dir / 'states.npz'}: ")
    assert fragment in str(caught.value)


def test_load_run_accepts_what_runs_write(tmp_path, synthetic_run):
    # A start pose known exactly (zero covariance), rounding in a covariance's smallest
    # eigenvalue and a quaternion's norm, ids stored as int32: not damage.
    run = synthetic_run()
    cov = run.estimate_cov.copy()
    cov[3] -= 1e-13 * np.max(cov[3]) * np.eye(6)  # eigenvalues down by 1e-13 of the largest entry
    run_dir = save_run(tmp_path / "run", run)
    _rewrite_states(run_dir, estimate_cov=cov, pose_ids=run.pose_ids.astype(np.int32))
    loaded = load_run(run_dir)
    assert np.all(loaded.estimate_cov[0] == 0.0) and loaded.pose_ids.dtype == np.int64


def test_load_run_accepts_a_collapsed_covariance_a_lost_run_writes(tmp_path, synthetic_run):
    # The audit of 2026-12-06: a lost run's covariance collapsed to nearly rank one, eigenvalues
    # 1.6e-3 and five below 2e-9, one of them -5.2e-10 (rounding of the updates): camloc wrote it
    # and eval refused it. A covariance further below zero (1e-4 of its largest) is still damage.
    run = synthetic_run()
    axis = np.linspace(1.0, 2.0, 6) / np.linalg.norm(np.linspace(1.0, 2.0, 6))
    basis = np.linalg.qr(np.column_stack([axis, np.eye(6)[:, :5]]))[0]
    collapsed = basis @ np.diag([1.6e-3, 2e-9, 1e-9, 5e-10, 1e-10, -5.2e-10]) @ basis.T
    cov = run.estimate_cov.copy()
    cov[7] = (collapsed + collapsed.T) / 2
    run_dir = save_run(tmp_path / "run", run)
    _rewrite_states(run_dir, estimate_cov=cov)
    assert np.allclose(load_run(run_dir).estimate_cov[7], cov[7], rtol=0.0, atol=1e-18)
    cov[7] = basis @ np.diag([1.6e-3, 2e-9, 1e-9, 5e-10, 1e-10, -1.6e-7]) @ basis.T
    _rewrite_states(run_dir, estimate_cov=(cov + np.swapaxes(cov, 1, 2)) / 2)
    with pytest.raises(DatasetError, match="expected positive semi-definite matrices"):
        load_run(run_dir)


# --------------------------------------------------------------------------------------------
# The TUM files are the run's trajectories


def test_load_run_reads_the_trajectories_the_tum_files_hold(tmp_path, synthetic_run):
    run = synthetic_run()
    run_dir = save_run(tmp_path / "run", run)
    stamps, xyz, quat = read_tum(run_dir / "estimate.tum")
    write_tum(run_dir / "estimate.tum", stamps, xyz + [10.0, 0.0, 0.0], quat)  # a user's edit
    loaded = load_run(run_dir)
    np.testing.assert_array_equal(loaded.estimate_xyz, run.estimate_xyz + [10.0, 0.0, 0.0])
    np.testing.assert_array_equal(loaded.estimate_quat_xyzw, run.estimate_quat_xyzw)
    np.testing.assert_array_equal(loaded.odometry_xyz, run.odometry_xyz)

    (run_dir / "groundtruth.tum").unlink()
    assert load_run(run_dir).truth_xyz is None
    bare = save_run(tmp_path / "bare", synthetic_run(with_truth=False))
    write_tum(bare / "groundtruth.tum", run.pose_ids, run.truth_xyz, run.truth_quat_xyzw)
    np.testing.assert_array_equal(load_run(bare).truth_xyz, run.truth_xyz)


def _drop_last_pose(path: Path) -> None:
    path.write_text("".join(path.read_text().splitlines(keepends=True)[:-1]))


def _rewrite_line(path: Path, number: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[number - 1] = text
    path.write_text("\n".join(lines) + "\n")


TUM_DAMAGE = {
    "truncated": (_drop_last_pose, ": expected the run's 40 pose ids (1000..1039) as timestamps, "
                                   "found 39 timestamps (1000..1038) that differ; run 'camloc run' again"),
    "deleted": (lambda path: path.unlink(), ": no such file"),
    "nan": (lambda path: _rewrite_line(path, 3, "1001 nan 0 0 0 0 0 1"), ":3: expected a finite number for x"),
    "another-run": (lambda path: path.write_text(path.read_text().replace("\n10", "\n20")),
                    ": expected the run's 40 pose ids (1000..1039) as timestamps, found 40 timestamps (2000..2039)"),
}


@pytest.mark.parametrize("name", TUM_DAMAGE)
def test_a_damaged_trajectory_file_is_an_error_naming_it(tmp_path, synthetic_run, name):
    damage, message = TUM_DAMAGE[name]
    run_dir = save_run(tmp_path / "run", synthetic_run())
    damage(run_dir / "estimate.tum")
    with pytest.raises(DatasetError) as caught:
        load_run(run_dir)
    assert str(caught.value).startswith(f"{run_dir / 'estimate.tum'}{message}")


def test_a_format_1_folder_loads_its_trajectories_from_the_tum_files(tmp_path, synthetic_run):
    # Version 1 also kept the poses in states.npz; they are not what is read.
    run = synthetic_run()
    run_dir = save_run(tmp_path / "run", run)
    _rewrite_states(run_dir, format_version=np.array(1), estimate_xyz=np.zeros_like(run.estimate_xyz),
                    truth_xyz=run.truth_xyz)
    np.testing.assert_array_equal(load_run(run_dir).estimate_xyz, run.estimate_xyz)


def test_associations_read_back_exactly_as_written_and_as_hand_edited(tmp_path):
    """What associations_text writes reads back bit for bit (rejected rows, an accepted pair whose
    distance was not finite, -0.0, 1e-300, ids near 2^62), and a hand-edited copy of it (a blank
    line, signs, upper-case exponents, spaces around cells) reads back the same values."""
    associations = results.Associations(
        pose_id=np.array([10, 10, 11, 4611686018427387904], dtype=np.int64),
        camera=np.array([0, 1, 0, 2], dtype=np.int64),
        uvd=np.array([[320.5, -0.0, 1.25], [1e-300, 240.0, 2.0], [0.1, 0.2, 123456789.123456789], [5.0, 6.0, 7.0]]),
        landmark=np.array([7, results.UNASSOCIATED, 9, 4611686018427387905], dtype=np.int64),
        true_landmark=np.array([7, 8, -3, 4611686018427387905], dtype=np.int64),
        mahalanobis=np.array([0.5, np.nan, np.nan, 1.0 / 3.0]),
    )
    written = tmp_path / "associations.csv"
    written.write_text(results.associations_text(associations))
    edited = tmp_path / "edited.csv"
    header, *rows = written.read_text().splitlines()
    rows[0] = " +10 , 0 ,3.205E+2, -0.0,1.25,+7,7,0.5"
    edited.write_text("\n".join([header, rows[0], "", *rows[1:]]) + "\n")
    for path in (written, edited):
        read = results.read_associations(path)
        for name in ("pose_id", "camera", "uvd", "landmark", "true_landmark", "mahalanobis"):
            expected, found = getattr(associations, name), getattr(read, name)
            assert found.dtype == expected.dtype, (path.name, name)
            np.testing.assert_array_equal(found, expected, err_msg=f"{path.name}: {name}")
        assert np.signbit(read.uvd[0, 1])


def test_landmark_headings_are_kept_optional_and_checked(tmp_path, synthetic_run):
    """map_landmark_heading (a marker's or tag's heading, NaN for a point) goes through
    states.npz; a run folder written before it was kept loads without it; a heading beyond
    +-2 pi is refused, naming the array."""
    run = synthetic_run()
    L = len(run.map_landmark_ids)
    heading = np.where(np.arange(L) % 2 == 0, np.nan, 0.5)
    run_dir = save_run(tmp_path / "run", dataclasses.replace(run, map_landmark_heading=heading))
    assert np.array_equal(load_run(run_dir).map_landmark_heading, heading, equal_nan=True)
    with np.load(run_dir / "states.npz") as npz:
        arrays = {name: npz[name] for name in npz.files if name != "map_landmark_heading"}
    np.savez(run_dir / "states.npz", **arrays)
    assert load_run(run_dir).map_landmark_heading is None
    _rewrite_states(run_dir, map_landmark_heading=np.full(L, 7.0))
    with pytest.raises(DatasetError, match="map_landmark_heading: expected radians within"):
        load_run(run_dir)


def test_load_run_of_a_states_file_that_is_no_archive_says_so(tmp_path, synthetic_run):
    # numpy takes a file that is neither a zip nor an .npy for a pickle: the error must not say
    # that the file holds pickled objects
    run_dir = save_run(tmp_path / "run", synthetic_run())
    (run_dir / "states.npz").write_text("not an archive\n")
    with pytest.raises(DatasetError) as caught:
        load_run(run_dir)
    assert "found a file that is not one" in str(caught.value) and "pickled" not in str(caught.value)


def test_load_run_of_an_associations_csv_cut_short(tmp_path, synthetic_run):
    # a file cut short at a line's end reads as a well-formed shorter file: summary.json's count tells
    run = synthetic_run()
    run_dir = save_run(tmp_path / "run", run)
    lines = (run_dir / "associations.csv").read_text().splitlines(keepends=True)
    (run_dir / "associations.csv").write_text("".join(lines[:2]))
    expected = run.summary["counts"]["observations"]
    with pytest.raises(DatasetError, match=f"associations.csv: inconsistent run folder: expected {expected} rows, .* found 1"):
        load_run(run_dir)
