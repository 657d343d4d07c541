"""Metrics of a localization run: trajectory error, association scores and filter consistency.

Pure numpy: no I/O, no printing; every function returns plain numbers or arrays, and
``evaluate`` a JSON-serializable dict (undefined values are ``None``).

Trajectory metrics follow evo's definitions, so the numbers agree with ``evo_ape`` / ``evo_rpe``
run on the TUM files of a run folder:

- ATE, ``evo_ape -r trans_part``: ``e_i = |p_est,i - p_ref,i|`` (metres), after the alignment.
- Rotation error, ``evo_ape -r angle_deg``: geodesic angle of ``R_ref,i^T R_est,i`` (degrees).
- RPE, ``evo_rpe --delta d --delta_unit f``: ``E_ij = (ref_i^-1 ref_j)^-1 (est_i^-1 est_j)`` over the
  consecutive, non-overlapping index pairs (0, d), (d, 2d), ...; its translation norm and angle.
- Statistics: rmse, mean, median, std (population, ddof=0, as evo), min, max and sse.
- Alignment ``none`` (default), ``se3`` or ``sim3`` (Umeyama) moves the estimate onto the reference,
  ``p -> s R p + t`` and ``R_est -> R R_est``, like ``evo_ape -a`` / ``-as``.

Consistency uses the chi-square tests of Bar-Shalom, Li and Kirubarajan, "Estimation with
Applications to Tracking and Navigation" (2001), sec. 5.4: a consistent filter's NEES per pose is
chi2(6), and the average of N independent ones lies, with 95% probability, in chi2(6N) bounds / N.
Bar-Shalom averages over N Monte Carlo runs at one time step (``monte_carlo_nees``); one run's
poses are not independent (an error persists from pose to pose), so the time average of a single
run (``nees_summary``) takes the same bounds with N the run's effective number of independent
poses, ``M / tau``, tau its integrated autocorrelation time (``integrated_autocorrelation_time``,
Geyer 1992). NIS needs no such correction: a consistent filter's innovations are white.
NEES is always computed on the unaligned estimate: an alignment fitted to the truth would remove
error the covariance is meant to describe.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from camloc import geometry
from camloc.planar import PLANAR_AXES, planar_block
from camloc.diagnostics import estimate_name
from camloc.errors import CamlocError, ConfigError
from camloc.tails import chi2_quantile

if TYPE_CHECKING:
    from camloc.results import Associations, RunResult

ALIGN_METHODS = ("none", "se3", "sim3")
CONFIDENCE = 0.95
POSE_DOF = 6
PLANAR_POSE_DOF = 3  # a planar filter's (x, y, yaw)
UNASSOCIATED = -1  # the same sentinel as camloc.results.UNASSOCIATED


# --------------------------------------------------------------------------------------------
# Statistics and matching


def _number(value: float) -> float | None:
    """A Python float, or None for NaN/inf (JSON has no NaN)."""
    value = float(value)
    return value if np.isfinite(value) else None


def _ratio(numerator: float, denominator: float) -> float | None:
    return _number(numerator / denominator) if denominator > 0 else None


def error_statistics(errors: np.ndarray, *, suffix: str = "") -> dict[str, float]:
    """evo's statistics of non-negative errors (P,): rmse, mean, median, std, min, max, sse.

    ``std`` is the population standard deviation (ddof=0), as evo computes it. ``suffix`` is
    appended to every key (``"_deg"`` for angles); ``sse`` is left out of suffixed (angle) sets.
    """
    errors = np.asarray(errors, dtype=float)
    stats = {
        "rmse": np.sqrt(np.mean(errors**2)),
        "mean": np.mean(errors),
        "median": np.median(errors),
        "std": np.std(errors),
        "min": np.min(errors),
        "max": np.max(errors),
    }
    if not suffix:
        stats["sse"] = np.sum(errors**2)
    return {f"{name}{suffix}": float(value) for name, value in stats.items()}


def match_by_timestamp(
    stamps_est: np.ndarray, stamps_ref: np.ndarray, *, max_diff: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """Pair poses of two trajectories by nearest timestamp, as evo's ``associate_trajectories``.

    Each estimate stamp is paired with the nearest reference stamp when they differ by at most
    ``max_diff``; a reference stamp claimed twice keeps its closest estimate.

    Parameters
    ----------
    stamps_est : (N,) timestamps of the estimate.
    stamps_ref : (M,) timestamps of the reference.
    max_diff : largest accepted difference, in the timestamps' unit (camloc uses pose ids).

    Returns
    -------
    index_est, index_ref : (P,) int indices of the pairs, in the estimate's order.

    Raises
    ------
    CamlocError : when no pair is found.
    """
    stamps_est = np.asarray(stamps_est, dtype=float)
    stamps_ref = np.asarray(stamps_ref, dtype=float)
    if stamps_est.size == 0 or stamps_ref.size == 0:
        raise CamlocError("no matching timestamps: a trajectory has no pose")
    order = np.argsort(stamps_ref, kind="stable")
    sorted_ref = stamps_ref[order]
    right = np.clip(np.searchsorted(sorted_ref, stamps_est), 0, max(len(sorted_ref) - 1, 0))
    left = np.maximum(right - 1, 0)
    take_left = np.abs(stamps_est - sorted_ref[left]) <= np.abs(stamps_est - sorted_ref[right])
    nearest = np.where(take_left, left, right)
    diff = np.abs(stamps_est - sorted_ref[nearest])
    candidates = np.flatnonzero(diff <= max_diff)
    # Closest first, so that a reference pose claimed twice goes to its nearest estimate.
    candidates = candidates[np.argsort(diff[candidates], kind="stable")]
    _, first = np.unique(nearest[candidates], return_index=True)
    index_est = np.sort(candidates[first])
    if index_est.size == 0:
        raise CamlocError(
            f"no matching timestamps within {max_diff:g} between the estimate "
            f"({_stamp_range(stamps_est)}) and the reference ({_stamp_range(stamps_ref)})"
        )
    return index_est, order[nearest[index_est]]


def _stamp_range(stamps: np.ndarray) -> str:
    return f"{len(stamps)} poses, {stamps.min():g}..{stamps.max():g}" if len(stamps) else "no poses"


# --------------------------------------------------------------------------------------------
# Alignment


@dataclass(frozen=True)
class Alignment:
    """A similarity transform ``p -> scale * rotation @ p + translation`` (world frame).

    Attributes
    ----------
    method : ``"none"``, ``"se3"`` or ``"sim3"``.
    rotation : (3, 3).
    translation : (3,) metres.
    scale : 1.0 unless ``method == "sim3"``.
    """

    method: str
    rotation: np.ndarray
    translation: np.ndarray
    scale: float

    def apply(self, xyz: np.ndarray, quat_xyzw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Transform poses (N, 3), (N, 4): ``p -> s R p + t`` and ``R_pose -> R R_pose``."""
        aligned_xyz = self.scale * xyz @ self.rotation.T + self.translation
        aligned_R = self.rotation @ geometry.quat_to_matrix(quat_xyzw)
        return aligned_xyz, geometry.matrix_to_quat(aligned_R)

    def as_dict(self) -> dict:
        return {
            "method": self.method,
            "rotation": self.rotation.tolist(),
            "rotation_angle_deg": float(np.degrees(geometry.rotation_angle(self.rotation))),
            "translation": self.translation.tolist(),
            "scale": float(self.scale),
        }


def umeyama(source: np.ndarray, target: np.ndarray, *, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity (or rigid) transform taking ``source`` points onto ``target``.

    S. Umeyama, "Least-squares estimation of transformation parameters between two point
    patterns", IEEE TPAMI 13(4), 1991; the equation numbers below are the paper's.

    Parameters
    ----------
    source, target : (n, 3) corresponding points (x_i and y_i in the paper).
    with_scale : estimate the scale c (Sim(3)); otherwise c = 1 (SE(3)).

    Returns
    -------
    R : (3, 3), t : (3,), c : float minimizing ``sum |y_i - (c R x_i + t)|^2``.

    Raises
    ------
    CamlocError : when the points do not span at least a plane's worth of directions
        (rank(Sigma_xy) < 2, e.g. fewer than 3 poses or all on one line).
    """
    x = np.asarray(source, dtype=float)
    y = np.asarray(target, dtype=float)
    n = x.shape[0]
    mu_x = x.mean(axis=0)  # eq. (34)
    mu_y = y.mean(axis=0)  # eq. (35)
    sigma2_x = np.sum((x - mu_x) ** 2) / n  # eq. (36)
    Sigma_xy = (y - mu_y).T @ (x - mu_x) / n  # eq. (38)
    U, D, Vt = np.linalg.svd(Sigma_xy)  # Sigma_xy = U D V^T, the SVD after eq. (38)
    if n < 3 or np.count_nonzero(D > 1e-12 * max(D[0], 1e-300)) < 2:
        raise CamlocError(
            f"alignment needs at least 3 positions that are not all on one line, found {n} "
            "that are degenerate; use --align none"
        )
    # eq. (39), in the form of eq. (43) that also holds when rank(Sigma_xy) = 2: keep det(R) = +1.
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2, 2] = -1.0
    R = U @ S @ Vt  # eq. (40)
    c = float(np.trace(np.diag(D) @ S) / sigma2_x) if with_scale else 1.0  # eq. (42)
    t = mu_y - c * R @ mu_x  # eq. (41)
    return R, t, c


def align_trajectory(xyz_est: np.ndarray, xyz_ref: np.ndarray, *, method: str = "none") -> Alignment:
    """The alignment of an estimate's positions (N, 3) onto the reference's (N, 3).

    ``method`` is one of ``ALIGN_METHODS``; ``none`` is the identity.
    """
    if method not in ALIGN_METHODS:
        raise ConfigError(f"alignment must be one of {', '.join(ALIGN_METHODS)}, found {method!r}")
    if method == "none":
        return Alignment("none", np.eye(3), np.zeros(3), 1.0)
    R, t, c = umeyama(xyz_est, xyz_ref, with_scale=method == "sim3")
    return Alignment(method, R, t, c)


# --------------------------------------------------------------------------------------------
# Trajectory errors


def position_errors(xyz_est: np.ndarray, xyz_ref: np.ndarray) -> np.ndarray:
    """Position error norms (N,) in metres of matched positions (N, 3)."""
    return np.linalg.norm(np.asarray(xyz_est) - np.asarray(xyz_ref), axis=-1)


def rotation_errors_deg(quat_est: np.ndarray, quat_ref: np.ndarray) -> np.ndarray:
    """Geodesic angle (N,) in degrees of ``R_ref^T R_est`` for matched quaternions (N, 4)."""
    R_est = geometry.quat_to_matrix(quat_est)
    R_ref = geometry.quat_to_matrix(quat_ref)
    return np.degrees(geometry.rotation_angle(np.swapaxes(R_ref, -1, -2) @ R_est))


def relative_pose_errors(
    T_est: np.ndarray, T_ref: np.ndarray, *, delta: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """evo's RPE over pose pairs ``delta`` frames apart.

    Parameters
    ----------
    T_est, T_ref : (N, 4, 4) matched poses, world frame.
    delta : frame distance of the pairs (0, delta), (delta, 2 delta), ... (no overlap, as evo
        without ``--all_pairs``).

    Returns
    -------
    translation : (P,) metres, ``|t(E_ij)|``.
    angle_deg : (P,) degrees, geodesic angle of ``R(E_ij)``.
    pairs : (P, 2) the index pairs (i, j).

    Raises
    ------
    ConfigError : when there is no pair (``delta`` >= N or delta < 1).
    """
    n = T_est.shape[0]
    if delta < 1 or delta >= n:
        raise ConfigError(f"RPE delta must be between 1 and the number of poses - 1 ({n - 1}), found {delta}")
    ids = np.arange(0, n, delta)
    i, j = ids[:-1], ids[1:]
    E = geometry.relative_se3(geometry.relative_se3(T_ref[i], T_ref[j]), geometry.relative_se3(T_est[i], T_est[j]))
    translation = np.linalg.norm(E[:, :3, 3], axis=-1)
    angle_deg = np.degrees(geometry.rotation_angle(E[:, :3, :3]))
    return translation, angle_deg, np.column_stack([i, j])


def trajectory_metrics(
    xyz_est: np.ndarray,
    quat_est: np.ndarray,
    xyz_ref: np.ndarray,
    quat_ref: np.ndarray,
    *,
    align: str = "none",
    delta: int = 1,
) -> dict:
    """ATE, rotation error and RPE of matched poses, after the chosen alignment.

    Parameters
    ----------
    xyz_est, quat_est : (N, 3), (N, 4) the estimate, world frame.
    xyz_ref, quat_ref : (N, 3), (N, 4) the reference (ground truth), matched pose by pose.
    align : ``"none"``, ``"se3"`` or ``"sim3"``.
    delta : RPE frame distance.

    Returns
    -------
    ``{"poses", "alignment": {method, rotation, translation, scale}, "ate": {rmse, mean, median,
    std, min, max, sse} (m), "rotation": {rmse_deg, ...}, "rpe": {"delta", "delta_unit", "pairs",
    "translation": {...} (m), "rotation": {..._deg}}}``.
    """
    alignment = align_trajectory(xyz_est, xyz_ref, method=align)
    xyz_a, quat_a = alignment.apply(np.asarray(xyz_est, dtype=float), np.asarray(quat_est, dtype=float))
    rpe_translation, rpe_angle, pairs = relative_pose_errors(
        geometry.pose_from_quat(xyz_a, quat_a), geometry.pose_from_quat(xyz_ref, quat_ref), delta=delta
    )
    return {
        "poses": int(len(xyz_a)),
        "alignment": alignment.as_dict(),
        "ate": error_statistics(position_errors(xyz_a, xyz_ref)),
        "rotation": error_statistics(rotation_errors_deg(quat_a, quat_ref), suffix="_deg"),
        "rpe": {
            "delta": int(delta),
            "delta_unit": "frames",
            "pairs": int(len(pairs)),
            "translation": error_statistics(rpe_translation),
            "rotation": error_statistics(rpe_angle, suffix="_deg"),
        },
    }


def compare_trajectories(
    stamps_est: np.ndarray,
    xyz_est: np.ndarray,
    quat_est: np.ndarray,
    stamps_ref: np.ndarray,
    xyz_ref: np.ndarray,
    quat_ref: np.ndarray,
    *,
    align: str = "none",
    delta: int = 1,
    max_diff: float = 0.01,
) -> dict:
    """``trajectory_metrics`` of two trajectories paired by timestamp (``match_by_timestamp``).

    Returns ``"counts"`` (``matched``, ``estimate_poses``, ``reference_poses``) and ``"estimate"``,
    the dict of ``trajectory_metrics``: the estimate's ATE is ``estimate.ate.rmse`` here as in
    ``evaluate``.
    """
    index_est, index_ref = match_by_timestamp(stamps_est, stamps_ref, max_diff=max_diff)
    metrics = trajectory_metrics(
        xyz_est[index_est], quat_est[index_est], xyz_ref[index_ref], quat_ref[index_ref], align=align, delta=delta
    )
    counts = {"matched": int(len(index_est)), "estimate_poses": int(len(stamps_est)),
              "reference_poses": int(len(stamps_ref))}
    return {"counts": counts, "estimate": metrics}


# --------------------------------------------------------------------------------------------
# Associations


def association_outcomes(associations: Associations, map_landmark_ids: np.ndarray) -> dict[str, np.ndarray]:
    """Boolean masks (K,) classifying every observation.

    ``made`` (a landmark was chosen), ``correct`` (it is the true one), ``wrong`` (another one),
    ``rejected`` (none chosen), ``in_map`` (the true landmark is in the map), ``missed`` (in the
    map but rejected), ``clutter_accepted`` (not in the map but associated anyway), ``to_added``
    (paired with a landmark the run added, an id the map lacks: neither correct nor wrong here,
    ``camloc eval --true-map`` scores those).
    """
    chosen = np.asarray(associations.landmark)
    true = np.asarray(associations.true_landmark)
    made = chosen != UNASSOCIATED
    in_map = np.isin(true, map_landmark_ids)
    to_added = made & ~np.isin(chosen, map_landmark_ids)
    return {
        "made": made,
        "correct": made & (chosen == true),
        "wrong": made & (chosen != true) & ~to_added,
        "to_added": to_added,
        "rejected": ~made,
        "in_map": in_map,
        "missed": in_map & ~made,
        "clutter_accepted": ~in_map & made & ~to_added,
    }


def association_scores(associations: Associations, map_landmark_ids: np.ndarray) -> dict:
    """Counts and scores of the data association against the file's true landmark ids.

    precision = correct / pairs with the map's landmarks (those with added ones aside:
    ``to_added``); recall = correct / observations whose true landmark is in the map; F1 their harmonic mean (None when undefined, e.g. nothing was associated).
    """
    masks = association_outcomes(associations, map_landmark_ids)
    counts = {name: int(np.count_nonzero(mask)) for name, mask in masks.items()}
    precision = _ratio(counts["correct"], counts["made"] - counts["to_added"])
    recall = _ratio(counts["correct"], counts["in_map"])
    f1 = None
    if precision is not None and recall is not None and precision + recall > 0:
        f1 = 2.0 * precision * recall / (precision + recall)
    return {
        "observations": int(len(masks["made"])),
        "made": counts["made"],
        "correct": counts["correct"],
        "wrong": counts["wrong"],
        "rejected": counts["rejected"],
        "missed": counts["missed"],
        "in_map": counts["in_map"],
        "clutter": int(len(masks["made"])) - counts["in_map"],
        "clutter_accepted": counts["clutter_accepted"],
        "to_added": counts["to_added"],
        "precision": precision,
        "recall": recall,
        "f1": f1,
    }


# --------------------------------------------------------------------------------------------
# Consistency


def chi2_bounds(dof: np.ndarray | int, *, confidence: float = CONFIDENCE) -> tuple[np.ndarray, np.ndarray]:
    """Two-sided chi-square bounds: P(lower <= X <= upper) = confidence for X ~ chi2(dof)."""
    tail = (1.0 - confidence) / 2.0
    return chi2_quantile(dof, 1.0 - tail), chi2_quantile(dof, tail)  # chi^2 quantiles at tail and 1 - tail


def mean_chi2_bounds(dof: int, count: float, *, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Bounds of the mean of ``count`` independent chi2(dof) samples: chi2(dof*count) bounds / count.

    ``count`` may be an effective sample size (not an integer): the mean of M correlated samples
    whose mean has the variance of ``count`` independent ones is approximated by the chi-square of
    that variance (Satterthwaite), which keeps the skew of a short run's mean.
    """
    lower, upper = chi2_bounds(dof * count, confidence=confidence)
    return float(lower / count), float(upper / count)


def autocorrelation(series: np.ndarray) -> np.ndarray:
    """Sample autocorrelation ``rho_k`` (M,) of a series (M,) at lags 0..M-1, through the FFT.

    The biased estimator (sums divided by M, not M - k), whose sequence is positive semi-definite;
    a constant series has ``rho_0 = 1`` and zeros elsewhere.
    """
    x = np.asarray(series, dtype=float)
    x = x - x.mean()
    n = x.size
    spectrum = np.fft.rfft(x, 2 * n)  # zero-padded: a linear, not circular, correlation
    covariance = np.fft.irfft(spectrum * np.conj(spectrum), 2 * n)[:n]
    if covariance[0] <= 0.0:
        return np.eye(1, n)[0]
    return covariance / covariance[0]


def integrated_autocorrelation_time(series: np.ndarray) -> float:
    """``tau = 1 + 2 sum_k rho_k`` of a stationary series (M,): the variance of its mean is
    ``tau`` times that of M independent samples, so it holds ``M / tau`` independent samples' worth.

    Geyer's initial monotone sequence estimator (C. J. Geyer, "Practical Markov chain Monte Carlo",
    Statistical Science 7(4), 1992, sec. 3.3): the sums of adjacent pairs of autocorrelations
    ``Gamma_m = rho_2m + rho_2m+1`` are positive and decreasing for a reversible process, so the
    sum stops at the first that is not positive and each is capped by the one before. It needs no
    window to tune. At least 1: a consistent filter's NEES is never anti-correlated (the covariance
    of two poses' NEES is ``2 tr(P_i^-1 C P_j^-1 C')``, C their errors' cross-covariance, >= 0), so
    a value below 1 is sampling noise that would narrow the interval.
    """
    rho = autocorrelation(series)
    if rho.size < 4:
        return 1.0
    pairs = rho[0 : rho.size - 1 : 2] + rho[1 : rho.size : 2]  # Gamma_m, m = 0, 1, ...
    not_positive = np.flatnonzero(pairs <= 0.0)
    pairs = pairs[: not_positive[0] if not_positive.size else pairs.size]
    pairs = np.minimum.accumulate(pairs)  # initial monotone sequence
    return max(float(2.0 * pairs.sum() - 1.0), 1.0)


def _positive_definite(cov: np.ndarray) -> np.ndarray:
    eigenvalues = np.linalg.eigvalsh(cov)
    return eigenvalues[..., 0] > 1e-12 * np.maximum(eigenvalues[..., -1], 1e-300)


def nees_per_pose(T_est: np.ndarray, T_true: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Normalized estimation error squared of each pose, ``e^T P^-1 e`` (by a solve).

    Parameters
    ----------
    T_est, T_true : (N, 4, 4) estimated and true poses, world frame.
    cov : (N, 6, 6) covariance P of ``geometry.pose_error_vector(T_est, T_true)``
        (world position in metres, then world rotation vector in radians).

    Returns
    -------
    (N,) NEES; NaN where P is not positive definite (e.g. an exactly known first pose).
    """
    e = geometry.pose_error_vector(T_est, T_true)
    nees = np.full(e.shape[0], np.nan)
    valid = _positive_definite(cov)
    if np.any(valid):
        solved = np.linalg.solve(cov[valid], e[valid][..., None])[..., 0]  # P^-1 e
        nees[valid] = np.einsum("ni,ni->n", e[valid], solved)
    return nees


def is_planar_run(result: RunResult) -> bool:
    """Whether the run's estimate is a planar filter's (``--filter se2``): its pose covariance is
    that of (x, y, yaw) alone, and its NEES has 3 degrees of freedom (``run_nees``)."""
    return result.summary.get("config", {}).get("filter") == "se2"


def nees_dof(result: RunResult) -> int:
    """The degrees of freedom of the run's NEES: 3 for a planar filter, else ``POSE_DOF``."""
    return PLANAR_POSE_DOF if is_planar_run(result) else POSE_DOF


def planar_nees_per_pose(T_est: np.ndarray, T_true: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """``nees_per_pose`` of the planar part (x, y, yaw) of the pose error and of its covariance
    (N, 6, 6) (``planar.planar_block``): 3 degrees of freedom."""
    e = geometry.pose_error_vector(T_est, T_true)[:, list(PLANAR_AXES)]
    P = planar_block(cov)
    nees = np.full(e.shape[0], np.nan)
    valid = _positive_definite(P)
    if np.any(valid):
        nees[valid] = np.einsum("ni,ni->n", e[valid], np.linalg.solve(P[valid], e[valid][..., None])[..., 0])
    return nees


def run_nees(result: RunResult) -> np.ndarray:
    """(N,) NEES of every pose of a run with ground truth, NaN for the poses left out; of the
    (x, y, yaw) error alone (3 dof) for a planar filter's run (``is_planar_run``).

    Left out: the first pose, which the dataset gives (it is the filter's known start, so its
    error is zero whatever its covariance says), and poses whose covariance is singular.
    """
    T_est = geometry.pose_from_quat(result.estimate_xyz, result.estimate_quat_xyzw)
    T_true = geometry.pose_from_quat(result.truth_xyz, result.truth_quat_xyzw)
    if is_planar_run(result):
        nees = planar_nees_per_pose(T_est, T_true, result.estimate_cov)
    else:
        nees = nees_per_pose(T_est, T_true, result.estimate_cov)
    nees[0] = np.nan
    return nees


def _verdict(mean: float, lower: float, upper: float) -> str:
    if mean > upper:
        return "overconfident"
    if mean < lower:
        return "underconfident"
    return "consistent"


def _finding(statistic: str, verdict: str, lower: float, upper: float, sample: str) -> str:
    """``"<statistic> is inside its 95% interval [a, b] for <sample>"`` (above / below)."""
    where = {"consistent": "inside", "overconfident": "above", "underconfident": "below"}[verdict]
    return f"{statistic} is {where} its {CONFIDENCE:.0%} interval [{lower:.2f}, {upper:.2f}] for {sample}"


def nees_summary(nees: np.ndarray, *, dof: int = POSE_DOF) -> dict:
    """Mean, median and bound shares of one run's per-pose NEES (N,), NaN entries skipped.

    The interval of the mean is ``mean_chi2_bounds`` of the run's effective number of independent
    poses, ``M / tau`` (``integrated_autocorrelation_time`` of the poses used, in their order):
    consecutive poses share their error, so the M poses' mean varies ``tau`` times as much as the
    mean of M independent ones, and chi2(dof M) / M would reject a consistent filter far more often
    than 5% (docs/filter.md, "Consistency").

    Returns
    -------
    ``{"dof", "poses", "skipped_poses", "mean", "median", "bounds" (per pose), "within_bounds_share",
    "autocorrelation_time", "effective_poses", "mean_bounds" (of the mean over the poses used),
    "verdict", "verdict_line"}``; the verdict is ``overconfident`` when the mean is above its
    interval, ``underconfident`` below, else ``consistent`` (``undetermined`` without a usable pose).
    """
    nees = np.asarray(nees, dtype=float)
    used = nees[np.isfinite(nees)]
    lower, upper = chi2_bounds(dof)
    out = {
        "dof": int(dof),
        "poses": int(used.size),
        "skipped_poses": int(nees.size - used.size),
        "bounds": [float(lower), float(upper)],
        "confidence": CONFIDENCE,
    }
    if used.size == 0:
        return out | {"mean": None, "median": None, "within_bounds_share": None, "autocorrelation_time": None,
                      "effective_poses": None, "mean_bounds": None, "verdict": "undetermined",
                      "verdict_line": "undetermined: no pose has a usable covariance"}
    mean = float(np.mean(used))
    tau = integrated_autocorrelation_time(used)
    effective = used.size / tau
    mean_lower, mean_upper = mean_chi2_bounds(dof, effective)
    verdict = _verdict(mean, mean_lower, mean_upper)
    sample = f"{used.size} poses ({dof} dof, worth {effective:.0f} independent ones)"
    return out | {
        "mean": mean,
        "median": float(np.median(used)),
        "within_bounds_share": float(np.mean((used >= lower) & (used <= upper))),
        "autocorrelation_time": tau,
        "effective_poses": float(effective),
        "mean_bounds": [mean_lower, mean_upper],
        "verdict": verdict,
        "verdict_line": f"{verdict}: " + _finding(f"mean NEES {mean:.2f}", verdict, mean_lower, mean_upper, sample),
    }


def monte_carlo_nees(nees: np.ndarray, *, dof: int = POSE_DOF) -> dict:
    """Bar-Shalom's Monte Carlo NEES test (sec. 5.4.2) of N independent runs of K time steps.

    Parameters
    ----------
    nees : (N, K) per-pose NEES of each run (``run_nees``), NaN where a pose is left out.

    Returns
    -------
    ``{"runs", "dof", "average" (K,): the ensemble average over the runs at each step (NaN where
    no run has a value), "bounds" (K, 2): chi2(dof n_k) / n_k with n_k the runs with a value,
    "within_bounds_share": of the steps with a value, "mean": the grand mean, "standard_error":
    from the spread of the runs' own means (the runs are independent, the steps of a run are not),
    "run_means" (N,)}``. A consistent filter has about 95% of its steps inside and a grand mean
    within about two standard errors of ``dof``.
    """
    nees = np.atleast_2d(np.asarray(nees, dtype=float))
    finite = np.isfinite(nees)
    counts = finite.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        average = np.where(counts > 0, np.where(finite, nees, 0.0).sum(axis=0) / counts, np.nan)
    bounds = np.full((nees.shape[1], 2), np.nan)
    steps = counts > 0
    lower, upper = chi2_bounds(dof * counts[steps])
    bounds[steps] = np.column_stack([lower / counts[steps], upper / counts[steps]])
    inside = (average[steps] >= bounds[steps, 0]) & (average[steps] <= bounds[steps, 1])
    run_means = np.array([np.mean(row[np.isfinite(row)]) if np.any(np.isfinite(row)) else np.nan for row in nees])
    used = run_means[np.isfinite(run_means)]
    return {
        "runs": int(nees.shape[0]),
        "dof": int(dof),
        "average": average,
        "bounds": bounds,
        "within_bounds_share": float(np.mean(inside)) if inside.size else None,
        "mean": float(np.mean(used)) if used.size else None,
        "standard_error": float(np.std(used, ddof=1) / np.sqrt(used.size)) if used.size > 1 else None,
        "run_means": run_means,
    }


def nis_summary(nis: np.ndarray, nis_dof: np.ndarray) -> dict:
    """NIS of the filter updates, per degree of freedom.

    Parameters
    ----------
    nis : (U,) normalized innovation squared of each update.
    nis_dof : (U,) its degrees of freedom (3 per accepted observation).

    Returns
    -------
    ``{"updates", "mean_per_dof", "mean_bounds", "within_bounds_share", "verdict", "verdict_line"}``:
    ``mean_per_dof = sum(NIS) / sum(dof)`` (the dof-weighted mean of NIS/dof, exactly
    chi2(sum dof) / sum dof for a consistent filter, which gives ``mean_bounds``: a consistent
    filter's innovations are white, so unlike NEES the updates are independent samples);
    ``within_bounds_share`` is the share of updates inside their own chi2(dof) 95% bounds.
    Gating rejects large innovations, so a gated filter's NIS is biased low.
    """
    nis = np.asarray(nis, dtype=float)
    nis_dof = np.asarray(nis_dof)
    if nis.size == 0:
        return {"updates": 0, "mean_per_dof": None, "mean_bounds": None, "within_bounds_share": None,
                "verdict": "undetermined", "verdict_line": "undetermined: no filter update"}
    total_dof = int(np.sum(nis_dof))
    mean_per_dof = float(np.sum(nis) / total_dof)
    lower, upper = chi2_bounds(nis_dof)
    mean_lower, mean_upper = mean_chi2_bounds(1, total_dof)
    verdict = _verdict(mean_per_dof, mean_lower, mean_upper)
    return {
        "updates": int(nis.size),
        "mean_per_dof": mean_per_dof,
        "mean_bounds": [mean_lower, mean_upper],
        "within_bounds_share": float(np.mean((nis >= lower) & (nis <= upper))),
        "verdict": verdict,
        "verdict_line": f"{verdict}: " + _finding(f"NIS per dof {mean_per_dof:.2f}", verdict, mean_lower, mean_upper,
                                                  f"{nis.size} updates ({total_dof} dof)"),
    }


def consistency_verdict(nees: dict | None, nis: dict) -> dict:
    """One verdict on the filter from its NEES (``nees_summary``, None without ground truth) and
    its NIS (``nis_summary``): a filter is consistent only when every test it could take says so.

    Returns
    -------
    ``{"verdict", "verdict_line"}``: ``consistent`` when every determined test is, ``overconfident``
    / ``underconfident`` when the tests that are not consistent all say that, ``inconsistent`` when
    they disagree in direction, ``undetermined`` when no test could be taken. The line gives every
    test's finding, the failing ones first.
    """
    tests = [summary for summary in (nees, nis) if summary is not None and summary["verdict"] != "undetermined"]
    if not tests:
        return {"verdict": "undetermined", "verdict_line": "undetermined: neither NEES nor NIS could be computed"}
    failing = {summary["verdict"] for summary in tests} - {"consistent"}
    verdict = "consistent" if not failing else failing.pop() if len(failing) == 1 else "inconsistent"
    findings = [summary["verdict_line"].split(": ", 1)[1] for summary in sorted(tests, key=lambda t: t["verdict"] == "consistent")]
    return {"verdict": verdict, "verdict_line": f"{verdict}: " + "; ".join(findings)}


# --------------------------------------------------------------------------------------------
# Everything about one run


def evaluate(result: RunResult, *, align: str = "none", delta: int = 1) -> dict:
    """All metrics of a run, for the filter's estimate, odometry alone (and the smoother) side by side.

    Parameters
    ----------
    result : the run (``camloc.results.RunResult``).
    align : trajectory alignment before ATE/RPE, one of ``ALIGN_METHODS``; each path gets its own.
    delta : RPE frame distance.

    Returns
    -------
    A JSON-serializable dict with the same keys for every run (``docs/json.md``): ``dataset``,
    ``estimate_name`` (what made the estimate, ``diagnostics.estimate_name``: ``iterated EKF
    (euler)``, or ``odometry alone (no update)``), ``counts`` (``poses``), ``align``, ``delta``, ``notes`` (list); ``estimate`` and ``odometry``
    (each as ``trajectory_metrics``), ``improvement`` (odometry / estimate ATE and rotation RMSE)
    and ``nees`` (``nees_summary`` of ``run_nees``: the given start pose is left out), each None
    without ground truth; ``smoothed`` (``trajectory_metrics``), None unless the run was smoothed
    (``RunResult.smoothed_xyz``, from ``camloc smooth``) and has ground truth; ``association``
    (``association_scores``) ``nis`` (``nis_summary``) and
    ``consistency`` (``consistency_verdict`` of NEES and NIS: the run's one verdict;
    ``undetermined`` when the filter made no update, whatever odometry's NEES).
    """
    if align not in ALIGN_METHODS:
        raise ConfigError(f"alignment must be one of {', '.join(ALIGN_METHODS)}, found {align!r}")
    out: dict = {
        "dataset": result.dataset,
        "estimate_name": estimate_name({**result.summary, "counts": {"updates": int(result.nis.size)}}),
        "counts": {"poses": int(len(result.pose_ids))},
        "align": align,
        "delta": int(delta),
        "notes": [],
        "estimate": None,
        "odometry": None,
        "smoothed": None,
        "improvement": None,
        "nees": None,
    }
    if result.truth_xyz is not None:
        estimate = trajectory_metrics(
            result.estimate_xyz, result.estimate_quat_xyzw, result.truth_xyz, result.truth_quat_xyzw,
            align=align, delta=delta,
        )
        odometry = trajectory_metrics(
            result.odometry_xyz, result.odometry_quat_xyzw, result.truth_xyz, result.truth_quat_xyzw,
            align=align, delta=delta,
        )
        out["estimate"], out["odometry"] = estimate, odometry
        out["improvement"] = {
            "ate_rmse": _ratio(odometry["ate"]["rmse"], estimate["ate"]["rmse"]),
            "rotation_rmse": _ratio(odometry["rotation"]["rmse_deg"], estimate["rotation"]["rmse_deg"]),
        }
        out["nees"] = nees_summary(run_nees(result), dof=nees_dof(result))
        if result.smoothed_xyz is not None:
            out["smoothed"] = trajectory_metrics(
                result.smoothed_xyz, result.smoothed_quat_xyzw, result.truth_xyz, result.truth_quat_xyzw,
                align=align, delta=delta,
            )
    else:
        out["notes"].append("no ground truth in the run: trajectory errors, improvement and NEES are not computed")
    out["association"] = association_scores(result.associations, result.map_landmark_ids)
    out["nis"] = nis_summary(result.nis, result.nis_dof)
    if result.nis.size == 0:
        # Without an update the estimate is odometry alone: a consistent NEES would speak for
        # odometry's covariance, not for the filter, which was never tested.
        out["consistency"] = {"verdict": "undetermined", "verdict_line": "undetermined: the filter made no update, "
                              "so its estimate is odometry alone and the filter's consistency was not tested"}
        out["notes"].append("the filter made no update: the estimate is odometry alone")
    else:
        out["consistency"] = consistency_verdict(out.get("nees"), out["nis"])
    return out
