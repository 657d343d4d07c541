"""Metrics against hand-computed cases, evo's conventions, and a linear Kalman filter's NEES."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.special import chdtri

from camloc import geometry, metrics
from camloc.errors import CamlocError, ConfigError
from camloc.results import Associations


def _trajectory(rng: np.random.Generator, n: int = 30) -> tuple[np.ndarray, np.ndarray]:
    xyz = np.cumsum(rng.normal(0.0, 0.5, (n, 3)), axis=0)
    quat = geometry.euler_to_quat(rng.uniform(-0.8, 0.8, (n, 3)))
    return xyz, quat


# --------------------------------------------------------------------------------------------
# Statistics, ATE, rotation error


def test_error_statistics_hand_case_uses_population_std():
    stats = metrics.error_statistics(np.array([3.0, 4.0]))
    assert stats["rmse"] == pytest.approx(np.sqrt(12.5))
    assert stats["mean"] == pytest.approx(3.5)
    assert stats["median"] == pytest.approx(3.5)
    assert stats["std"] == pytest.approx(0.5)  # ddof=1 would give 0.707
    assert (stats["min"], stats["max"], stats["sse"]) == (3.0, 4.0, 25.0)
    assert set(metrics.error_statistics(np.ones(3), suffix="_deg")) == {
        "rmse_deg", "mean_deg", "median_deg", "std_deg", "min_deg", "max_deg"
    }


def test_ate_of_a_trajectory_shifted_by_a_known_offset_is_the_offset_norm(rng):
    xyz, quat = _trajectory(rng)
    offset = np.array([0.3, -0.4, 1.2])  # norm 1.3
    result = metrics.trajectory_metrics(xyz + offset, quat, xyz, quat)
    assert result["ate"]["rmse"] == pytest.approx(1.3, abs=1e-12)
    assert result["ate"]["min"] == pytest.approx(1.3, abs=1e-12)
    assert result["ate"]["std"] == pytest.approx(0.0, abs=1e-12)
    assert result["rotation"]["max_deg"] == pytest.approx(0.0, abs=1e-6)
    # A pure translation is what se3 alignment removes.
    aligned = metrics.trajectory_metrics(xyz + offset, quat, xyz, quat, align="se3")
    assert aligned["ate"]["rmse"] == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(aligned["alignment"]["translation"], -offset, atol=1e-9)


def test_rotation_error_of_a_known_rotation_is_its_angle_on_either_side(rng):
    xyz, quat = _trajectory(rng)
    R = geometry.quat_to_matrix(quat)
    delta = geometry.so3_exp(np.radians(7.0) * np.array([0.6, 0.0, 0.8]))
    for R_est in (R @ delta, delta @ R):
        errors = metrics.rotation_errors_deg(geometry.matrix_to_quat(R_est), quat)
        np.testing.assert_allclose(errors, 7.0, atol=1e-9)
    # q and -q are the same rotation.
    assert metrics.rotation_errors_deg(-quat, quat).max() == pytest.approx(0.0, abs=1e-6)


# --------------------------------------------------------------------------------------------
# Alignment


def test_umeyama_recovers_a_known_se3_and_sim3_transform(rng):
    source = rng.normal(0.0, 2.0, (50, 3))
    R = geometry.euler_to_matrix(np.array([0.3, -0.5, 2.0]))
    t = np.array([1.0, -2.0, 0.5])
    target = source @ R.T + t
    R_hat, t_hat, c_hat = metrics.umeyama(source, target)
    np.testing.assert_allclose(R_hat, R, atol=1e-12)
    np.testing.assert_allclose(t_hat, t, atol=1e-12)
    assert c_hat == 1.0

    scaled = 2.5 * source @ R.T + t
    R_hat, t_hat, c_hat = metrics.umeyama(source, scaled, with_scale=True)
    np.testing.assert_allclose(R_hat, R, atol=1e-12)
    np.testing.assert_allclose(t_hat, t, atol=1e-12)
    assert c_hat == pytest.approx(2.5, abs=1e-12)


def test_umeyama_returns_a_rotation_when_the_best_orthogonal_fit_is_a_reflection(rng):
    source = rng.normal(0.0, 1.0, (20, 3))
    mirrored = source * np.array([1.0, 1.0, -1.0])
    R_hat, _, _ = metrics.umeyama(source, mirrored)
    assert np.linalg.det(R_hat) == pytest.approx(1.0)


def test_umeyama_refuses_collinear_points():
    line = np.outer(np.arange(10.0), [1.0, 2.0, 3.0])
    with pytest.raises(CamlocError, match="not all on one line"):
        metrics.umeyama(line, line + 1.0)


def test_sim3_alignment_is_applied_to_positions_and_orientations(rng):
    xyz, quat = _trajectory(rng)
    R = geometry.euler_to_matrix(np.array([0.1, 0.2, -1.0]))
    # est = S^-1 * truth: aligning must bring it back exactly, orientations included.
    est_xyz = (xyz - np.array([0.5, 0.0, -1.0])) @ R / 1.7
    est_quat = geometry.matrix_to_quat(R.T @ geometry.quat_to_matrix(quat))
    result = metrics.trajectory_metrics(est_xyz, est_quat, xyz, quat, align="sim3")
    assert result["alignment"]["scale"] == pytest.approx(1.7)
    assert result["ate"]["max"] == pytest.approx(0.0, abs=1e-9)
    assert result["rotation"]["max_deg"] == pytest.approx(0.0, abs=1e-5)
    unaligned = metrics.trajectory_metrics(est_xyz, est_quat, xyz, quat)
    assert unaligned["ate"]["rmse"] > 0.5


# --------------------------------------------------------------------------------------------
# RPE


def _straight_line(x: list[float], yaw_deg: list[float]) -> np.ndarray:
    rpy = np.column_stack([np.zeros(len(x)), np.zeros(len(x)), np.radians(yaw_deg)])
    xyz = np.column_stack([x, np.zeros(len(x)), np.zeros(len(x))])
    return geometry.make_pose(geometry.euler_to_matrix(rpy), xyz)


def test_rpe_hand_case_translation():
    reference = _straight_line([0.0, 1.0, 2.0, 3.0], [0, 0, 0, 0])
    estimate = _straight_line([0.0, 1.0, 2.5, 3.5], [0, 0, 0, 0])  # the second step is 0.5 m long
    translation, angle, pairs = metrics.relative_pose_errors(estimate, reference, delta=1)
    np.testing.assert_allclose(translation, [0.0, 0.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(angle, 0.0, atol=1e-9)
    np.testing.assert_array_equal(pairs, [[0, 1], [1, 2], [2, 3]])
    translation, _, pairs = metrics.relative_pose_errors(estimate, reference, delta=2)
    np.testing.assert_array_equal(pairs, [[0, 2]])  # (2, 4) does not exist: no overlap, as evo
    np.testing.assert_allclose(translation, [0.5], atol=1e-12)


def test_rpe_hand_case_rotation():
    reference = _straight_line([0.0, 1.0, 2.0, 3.0], [0, 0, 0, 0])
    estimate = _straight_line([0.0, 1.0, 2.0, 3.0], [0, 0, 10, 10])  # turns 10 deg at pose 2
    translation, angle, _ = metrics.relative_pose_errors(estimate, reference, delta=1)
    np.testing.assert_allclose(angle, [0.0, 10.0, 0.0], atol=1e-9)
    # Pair (2, 3): the estimate sees the 1 m step 10 deg off its heading, |Rz(-10) e_x - e_x|.
    np.testing.assert_allclose(translation, [0.0, 0.0, 2.0 * np.sin(np.radians(5.0))], atol=1e-12)


def test_rpe_is_invariant_to_a_rigid_motion_of_the_estimate(rng):
    xyz, quat = _trajectory(rng)
    T_ref = geometry.pose_from_quat(xyz, quat)
    T_est = geometry.pose_from_quat(xyz + rng.normal(0, 0.05, xyz.shape), quat)
    motion = geometry.pose_from_euler(np.array([1.0, 2.0, 3.0, 0.4, -0.2, 1.0]))
    before = metrics.relative_pose_errors(T_est, T_ref, delta=3)
    after = metrics.relative_pose_errors(motion @ T_est, T_ref, delta=3)
    np.testing.assert_allclose(after[0], before[0], atol=1e-12)
    np.testing.assert_allclose(after[1], before[1], atol=1e-6)


def test_rpe_delta_out_of_range_is_a_config_error():
    reference = _straight_line([0.0, 1.0, 2.0], [0, 0, 0])
    with pytest.raises(ConfigError, match="between 1 and .*found 3"):
        metrics.relative_pose_errors(reference, reference, delta=3)


# --------------------------------------------------------------------------------------------
# Timestamp matching


def test_match_by_timestamp_pairs_nearest_within_max_diff():
    est = np.array([1.0, 2.004, 3.0, 7.0, 8.0])
    ref = np.array([8.001, 3.0, 2.0, 1.0, 5.0])  # unsorted on purpose
    index_est, index_ref = metrics.match_by_timestamp(est, ref, max_diff=0.01)
    np.testing.assert_array_equal(index_est, [0, 1, 2, 4])
    np.testing.assert_array_equal(index_ref, [3, 2, 1, 0])


def test_match_by_timestamp_keeps_the_closest_when_a_reference_is_claimed_twice():
    index_est, index_ref = metrics.match_by_timestamp(np.array([0.995, 1.001]), np.array([1.0]), max_diff=0.01)
    np.testing.assert_array_equal(index_est, [1])
    np.testing.assert_array_equal(index_ref, [0])


def test_match_by_timestamp_without_any_pair_is_an_error():
    with pytest.raises(CamlocError, match="no matching timestamps within 0.01"):
        metrics.match_by_timestamp(np.array([1.0, 2.0]), np.array([1.5, 2.5]))


def test_compare_trajectories_matches_then_scores(rng):
    xyz, quat = _trajectory(rng, 12)
    stamps = np.arange(12.0)
    report = metrics.compare_trajectories(
        stamps[2:], xyz[2:] + [0.0, 0.0, 0.2], quat[2:], stamps, xyz, quat
    )
    assert report["counts"] == {"matched": 10, "estimate_poses": 10, "reference_poses": 12}
    assert report["estimate"]["ate"]["mean"] == pytest.approx(0.2)


# --------------------------------------------------------------------------------------------
# Associations


def test_association_scores_on_a_hand_table():
    # map {1, 2, 3}; 99 is clutter.      chosen, true
    table = np.array([[1, 1],   # correct
                      [2, 2],   # correct
                      [3, 1],   # wrong
                      [-1, 2],  # rejected, missed
                      [-1, 99],  # rejected clutter: right
                      [2, 99],  # clutter accepted: wrong
                      [1000, 7]])  # paired with an added landmark: neither right nor wrong here
    k = len(table)
    associations = Associations(
        pose_id=np.arange(k), camera=np.zeros(k, dtype=np.int64), uvd=np.zeros((k, 3)),
        landmark=table[:, 0], true_landmark=table[:, 1], mahalanobis=np.ones(k),
    )
    scores = metrics.association_scores(associations, np.array([1, 2, 3]))
    expected = {"observations": 7, "made": 5, "correct": 2, "wrong": 2, "rejected": 2, "missed": 1,
                "in_map": 4, "clutter": 3, "clutter_accepted": 1, "to_added": 1}
    assert {key: scores[key] for key in expected} == expected
    assert scores["precision"] == pytest.approx(0.5)
    assert scores["recall"] == pytest.approx(0.5)
    assert scores["f1"] == pytest.approx(0.5)


def test_association_scores_undefined_without_any_association():
    associations = Associations(
        pose_id=np.arange(2), camera=np.zeros(2, dtype=np.int64), uvd=np.zeros((2, 3)),
        landmark=np.array([-1, -1]), true_landmark=np.array([1, 2]), mahalanobis=np.full(2, np.nan),
    )
    scores = metrics.association_scores(associations, np.array([1, 2]))
    assert scores["precision"] is None and scores["f1"] is None
    assert scores["recall"] == 0.0


# --------------------------------------------------------------------------------------------
# Consistency


def test_chi2_bounds_of_six_dof():
    lower, upper = metrics.chi2_bounds(6)
    assert lower == pytest.approx(1.2373, abs=1e-4)
    assert upper == pytest.approx(14.4494, abs=1e-4)
    mean_lower, mean_upper = metrics.mean_chi2_bounds(6, 100)
    assert 5.3 < mean_lower < 6.0 < mean_upper < 6.75


def _poses_with_error(T_true: np.ndarray, error: np.ndarray) -> np.ndarray:
    """Estimates whose ``pose_error_vector`` against ``T_true`` is exactly ``error`` (N, 6)."""
    R_est = geometry.so3_exp(-error[:, 3:]) @ T_true[:, :3, :3]  # Log(R_true R_est^T) = e_rot
    return geometry.make_pose(R_est, T_true[:, :3, 3] - error[:, :3])  # t_true - t_est = e_t


def _linear_kalman_filter_errors(rng: np.random.Generator, runs: int, steps: int):
    """A linear KF on a 6-D random walk x' = x + w, z = H x + v; returns the errors x - x_hat, the
    covariances P (both (runs*steps, 6) / (…, 6, 6)), and the NIS of every update (3 dof)."""
    Q = np.diag([0.02, 0.02, 0.01, 0.001, 0.001, 0.002])
    H = np.hstack([np.eye(3), 0.5 * np.eye(3)])  # sees position plus half the rotation
    R = np.diag([0.01, 0.02, 0.015])
    errors, covs, nis = [], [], []
    for _ in range(runs):
        x = np.zeros(6)
        x_hat, P = np.zeros(6), np.diag([0.01] * 3 + [0.001] * 3)
        x = x_hat + rng.multivariate_normal(np.zeros(6), P)
        for _ in range(steps):
            x = x + rng.multivariate_normal(np.zeros(6), Q)
            P = P + Q  # predict: F = I
            z = H @ x + rng.multivariate_normal(np.zeros(3), R)
            nu = z - H @ x_hat  # innovation
            S = H @ P @ H.T + R  # S = HPH' + R
            K = np.linalg.solve(S, H @ P).T  # K = PH'S^-1 (S symmetric)
            x_hat = x_hat + K @ nu
            I_KH = np.eye(6) - K @ H
            P = I_KH @ P @ I_KH.T + K @ R @ K.T  # Joseph form
            errors.append(x - x_hat)
            covs.append(P)
            nis.append(nu @ np.linalg.solve(S, nu))
    return np.array(errors), np.array(covs), np.array(nis)


def test_nees_of_a_linear_kalman_filter_is_near_its_dof(rng):
    errors, covs, nis = _linear_kalman_filter_errors(rng, runs=200, steps=40)
    T_true = geometry.pose_from_euler(rng.uniform(-1.0, 1.0, (len(errors), 6)))
    nees = metrics.nees_per_pose(_poses_with_error(T_true, errors), T_true, covs)

    # The same number as e^T P^-1 e computed directly on the filter's own error.
    direct = np.einsum("ni,ni->n", errors, np.linalg.solve(covs, errors[..., None])[..., 0])
    np.testing.assert_allclose(nees, direct, rtol=1e-6)
    # 8000 samples of chi2(6), correlated in time within a run: the mean's standard deviation is
    # sqrt(12/8000) = 0.039 for independent samples, somewhat more here.
    summary = metrics.nees_summary(nees)
    assert summary["mean"] == pytest.approx(6.0, abs=0.15)
    assert summary["within_bounds_share"] == pytest.approx(0.95, abs=0.015)
    # The interval of the mean assumes independent samples: take the last step of each run.
    last_steps = metrics.nees_summary(nees.reshape(200, 40)[:, -1])
    assert last_steps["verdict"] == "consistent", last_steps["verdict_line"]

    nis_summary = metrics.nis_summary(nis, np.full(len(nis), 3))
    assert nis_summary["mean_per_dof"] == pytest.approx(1.0, abs=0.05)
    assert nis_summary["verdict"] == "consistent"

    # The same filter claiming a quarter (four times) its covariance is over- (under-) confident.
    T_est = _poses_with_error(T_true, errors)
    for scale, verdict in ((0.25, "overconfident"), (4.0, "underconfident")):
        scaled = metrics.nees_per_pose(T_est, T_true, covs * scale).reshape(200, 40)[:, -1]
        assert metrics.nees_summary(scaled)["verdict"] == verdict


def test_nees_skips_singular_covariances():
    T = geometry.pose_from_euler(np.zeros((3, 6)))
    covs = np.stack([np.zeros((6, 6)), np.eye(6), 4.0 * np.eye(6)])
    error = np.tile([0.0, 0.0, 2.0, 0.0, 0.0, 0.0], (3, 1))
    nees = metrics.nees_per_pose(_poses_with_error(T, error), T, covs)
    assert np.isnan(nees[0])
    np.testing.assert_allclose(nees[1:], [4.0, 1.0])
    summary = metrics.nees_summary(nees)
    assert (summary["poses"], summary["skipped_poses"], summary["mean"]) == (2, 1, 2.5)


# --------------------------------------------------------------------------------------------
# evaluate


def test_evaluate_reports_estimate_and_odometry_side_by_side(synthetic_run):
    result = synthetic_run(num_poses=40)
    report = metrics.evaluate(result)
    json.dumps(report, allow_nan=False)  # strict JSON

    est_rmse = np.sqrt(np.mean(np.sum((result.estimate_xyz - result.truth_xyz) ** 2, axis=1)))
    odo_rmse = np.sqrt(np.mean(np.sum((result.odometry_xyz - result.truth_xyz) ** 2, axis=1)))
    assert report["estimate"]["ate"]["rmse"] == pytest.approx(est_rmse)
    assert report["odometry"]["ate"]["rmse"] == pytest.approx(odo_rmse)
    assert report["improvement"]["ate_rmse"] == pytest.approx(odo_rmse / est_rmse)
    assert report["estimate"]["rpe"]["pairs"] == 39
    assert "rmse_deg" in report["estimate"]["rotation"]
    # The synthetic estimate's error is drawn from its covariance; its first pose is left out.
    assert report["nees"]["poses"] == 39
    assert report["nees"]["verdict"] == "consistent"
    assert report["association"]["observations"] == len(result.associations.pose_id)
    assert report["nis"]["updates"] == len(result.nis)
    assert report["notes"] == []


def test_evaluate_without_truth_keeps_the_keys_null_with_a_note(synthetic_run):
    report = metrics.evaluate(synthetic_run(with_truth=False))
    assert set(report) == set(metrics.evaluate(synthetic_run()))
    assert all(report[key] is None for key in ("estimate", "odometry", "smoothed", "improvement", "nees"))
    assert "no ground truth" in report["notes"][0]
    assert report["association"]["precision"] is not None


def test_evaluate_rejects_an_unknown_alignment(synthetic_run):
    with pytest.raises(ConfigError, match="none, se3, sim3"):
        metrics.evaluate(synthetic_run(), align="affine")


def _summaries(nees_scale: float, nis_scale: float) -> tuple[dict, dict]:
    # chi2 samples at their exact quantiles, scaled: a filter over- (scale > 1) or under-confident.
    # NEES in a shuffled order: sorted, the poses would look like one slow drift, worth a single
    # independent pose to nees_summary's autocorrelation time.
    quantiles = (np.arange(400) + 0.5) / 400
    nees = metrics.nees_summary(nees_scale * np.random.default_rng(0).permutation(chdtri(6, 1.0 - quantiles)))
    nis = metrics.nis_summary(nis_scale * chdtri(3, 1.0 - quantiles), np.full(400, 3))
    return nees, nis


def test_consistency_verdict_speaks_for_nees_and_nis():
    nees, nis = _summaries(1.0, 1.0)
    assert (nees["verdict"], nis["verdict"]) == ("consistent", "consistent")
    assert metrics.consistency_verdict(nees, nis)["verdict"] == "consistent"

    # NEES inside its bounds does not make a filter whose NIS is 5x consistent: the failing test first
    nees, nis = _summaries(1.0, 5.0)
    verdict = metrics.consistency_verdict(nees, nis)
    assert verdict["verdict"] == "overconfident"
    assert verdict["verdict_line"].startswith("overconfident: NIS per dof 5.00 is above its 95% interval")
    assert "mean NEES 6.00 is inside" in verdict["verdict_line"]

    assert metrics.consistency_verdict(*_summaries(0.5, 1.0))["verdict"] == "underconfident"
    assert metrics.consistency_verdict(*_summaries(2.0, 0.5))["verdict"] == "inconsistent"
    # without ground truth, NIS alone decides
    assert metrics.consistency_verdict(None, _summaries(1.0, 3.0)[1])["verdict"] == "overconfident"
    empty = metrics.nis_summary(np.zeros(0), np.zeros(0, dtype=int))
    assert metrics.consistency_verdict(None, empty)["verdict"] == "undetermined"


def test_evaluate_gives_one_verdict_of_nees_and_nis(synthetic_run):
    import dataclasses

    result = synthetic_run(num_poses=40)
    report = metrics.evaluate(result)
    assert report["consistency"]["verdict"] == "consistent"
    overconfident = metrics.evaluate(dataclasses.replace(result, nis=result.nis * 10.0))
    assert overconfident["nees"]["verdict"] == "consistent"
    assert overconfident["consistency"]["verdict"] == "overconfident"
    assert "NIS per dof" in overconfident["consistency"]["verdict_line"]
