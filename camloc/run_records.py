"""A run's records assembled into a ``RunResult``, and the checks every run's summary carries
(the divergence guard): shared by the localizer (``camloc.localizer``) and the mapping localizer
(``camloc.slam_run``)."""

from __future__ import annotations

from dataclasses import asdict

import numpy as np

from camloc import geometry, tags
from camloc.localizer_config import ignored_options
from camloc.results import UNASSOCIATED, Associations, RunResult
from camloc.tails import chi2_quantile


def build_result(dataset, config, filter_model, states, covs, poses, odometry_poses, chosen_landmark, mahalanobis,
                 update_pose_ids, nis, map_costs, nis_dof, *, warnings, slip_pose_ids, candidate_range, timing,
                 association_spread=None) -> RunResult:
    """The RunResult of a run's records: per pose the filter's stored state (N, S), covariance
    (N, 6, 6), pose and odometry pose (N, 4, 4); per observation the chosen landmark id
    (UNASSOCIATED for none) and Mahalanobis distance; per update its pose id, NIS, MAP cost, dof.
    ``association_spread`` (N, 6, 6): with the beam, how far its explanations of each pose spread
    about the one the filter replayed (``BeamSearch._spread_about``) plus what the chance that one
    of the replayed pairs is clutter adds (``ekf.leave_one_out_spread``); the estimate's covariance
    is the filter's plus that, the filter's own stays ``filter_cov``."""
    ds = dataset
    estimate_xyz, estimate_quat = geometry.pose_to_quat(poses)
    odometry_xyz, odometry_quat = geometry.pose_to_quat(odometry_poses)
    rows = tags.association_rows(ds.obs_kind)  # a row an observation, one a tag (its position's)
    associations = Associations(
        pose_id=ds.pose_ids[ds.obs_pose_index[rows]], camera=ds.obs_camera[rows], uvd=ds.obs_z[rows],
        landmark=chosen_landmark[rows], true_landmark=ds.obs_true_landmark[rows],
        mahalanobis=tags.row_distances(mahalanobis, ds.obs_kind, ds.obs_partner),
    )
    accepted = int(np.count_nonzero(associations.landmark != UNASSOCIATED))
    filter_seconds = timing["filter_seconds"]
    min_depth, max_depth, max_angle = candidate_range
    summary = {
        "dataset": ds.source,
        "config": asdict(config),
        "candidate_range": {"min_depth": min_depth, "max_depth": max_depth, "max_angle_deg": float(np.degrees(max_angle))},
        "counts": {
            "poses": ds.num_poses, "observations": int(rows.size), "accepted": accepted,
            "rejected": int(rows.size) - accepted, "updates": len(nis), "landmarks": int(ds.landmark_ids.size),
        },
        "timing": {
            "filter_seconds": filter_seconds,
            "poses_per_second": ds.num_poses / filter_seconds if filter_seconds > 0 else float("inf"),
            **{key: value for key, value in timing.items() if key != "filter_seconds"},
        },
        "warnings": list(ds.warnings) + list(warnings),
    }
    ignored = ignored_options(config)
    if ignored:
        summary["warnings"].append(f"association oracle takes the file's landmark ids and ignores {', '.join(ignored)}")
    if slip_pose_ids:
        summary["warnings"].append(
            f"{len(slip_pose_ids)} pose(s) were explained as odometry slips (prior covariance widened "
            f"{config.beam.slip_inflation:g}x): " + ", ".join(str(i) for i in slip_pose_ids[:10]) + (" ..." if len(slip_pose_ids) > 10 else "")
        )
    guard = divergence_guard(np.asarray(update_pose_ids, dtype=np.int64), np.asarray(map_costs), np.asarray(nis_dof))
    summary["divergence_guard"] = guard
    summary["slip_poses"] = list(slip_pose_ids)
    summary["map"] = None  # a mapping run's (camloc.slam_run) what it did with the map
    if guard["runs"]:
        summary["warnings"].append(
            f"the filter may have diverged: its updates' chi-square statistic stayed above the {100 * GUARD_PROBABILITY:g}% bound for "
            f"{GUARD_RUN_LENGTH} or more consecutive updates at poses "
            + ", ".join(f"{a}-{b}" for a, b in guard["runs"][:5])
            + (" ..." if len(guard["runs"]) > 5 else "")
        )
    return RunResult(
        dataset=ds.source, pose_ids=ds.pose_ids.copy(), estimate_xyz=estimate_xyz, estimate_quat_xyzw=estimate_quat,
        estimate_cov=filter_model.pose_cov(states, covs if association_spread is None else covs + association_spread),
        filter_state=states, filter_cov=covs,
        odometry_xyz=odometry_xyz, odometry_quat_xyzw=odometry_quat, truth_xyz=ds.truth_xyz, truth_quat_xyzw=ds.truth_quat_xyzw,
        map_landmark_ids=ds.landmark_ids, map_landmark_xyz=ds.landmark_xyz, associations=associations,
        map_landmark_heading=tags.landmark_headings(ds.landmark_heading, ds.landmark_quat_xyzw),
        update_pose_ids=np.asarray(update_pose_ids, dtype=np.int64), nis=np.asarray(nis, dtype=float),
        nis_dof=np.asarray(nis_dof, dtype=np.int64), summary=summary,
    )


def recorded_nis(nis_at_prior: float, map_cost: float, iterations: int) -> float:
    """The consistency statistic an update records: for an iterated update, the MAP cost at the
    posterior (chi^2 with 3p dof; at convergence the NIS at the last linearization), since the NIS
    at the prior's linearization carries the second-order error the iterations removed (two pixel
    cameras: NIS per dof 5.3 at the prior, 1.00 at the posterior, with the true association)."""
    if iterations > 1 and np.isfinite(map_cost):
        return float(map_cost)
    return float(nis_at_prior)


GUARD_PROBABILITY = 0.999
GUARD_RUN_LENGTH = 3


def divergence_guard(update_pose_ids: np.ndarray, statistic: np.ndarray, dof: np.ndarray) -> dict:
    """Updates whose accepted pairs are jointly inconsistent, and runs of them.

    ``statistic`` is each update's chi^2 statistic with ``dof`` degrees of freedom (3 per pair):
    the MAP cost at the posterior (``ekf.UpdateResult.map_cost``; NIS for a single linearization).
    An update is inconsistent when it is above the ``GUARD_PROBABILITY`` quantile;
    ``GUARD_RUN_LENGTH`` or more consecutive inconsistent updates (poses without observations do
    not break a run) are reported as a possible divergence, as (first pose id, last pose id) pairs.
    """
    if statistic.size == 0:
        return {"inconsistent_poses": [], "runs": []}
    bad = statistic > chi2_quantile(dof, 1.0 - GUARD_PROBABILITY)
    runs, start, length = [], None, 0
    for pose_id, is_bad in zip(update_pose_ids.tolist(), bad.tolist()):
        if is_bad:
            start, length = (pose_id if length == 0 else start), length + 1
            last = pose_id
        else:
            if length >= GUARD_RUN_LENGTH:
                runs.append([start, last])
            length = 0
    if length >= GUARD_RUN_LENGTH:
        runs.append([start, last])
    return {"inconsistent_poses": update_pose_ids[bad].tolist(), "runs": runs}


