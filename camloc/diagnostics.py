"""What a run's numbers do not say by themselves: which filter made the estimate, whether it made
any update at all, and whether the map looks incomplete. Pure functions of a run's summary
(``summary.json``'s ``config`` and ``counts``), computed after the run, so that every command
words them the same way.

A complete map leaves few observations unexplained: the gate and the re-check reject 1.4% of the
real course file's observations and 1.7-2.8% of the bundled clutter-free worlds'; clutter adds
its own share (``smooth3d-clutter.g2o``: 12% clutter and outliers, 14% rejected). The test of an
incomplete map is a one-sided binomial test against ``REFERENCE_REJECTED_SHARE``: if every
observation were rejected independently at that rate, seeing as many rejections as the run did
would have a probability below ``INCOMPLETE_MAP_PROBABILITY``. The rate allows clutter up to about
a sixth of the detections; heavier clutter is reported too, and the warning says so. So is a lost
run: on a complete, clutter-free map, once the estimate is off the robot's path its landmarks fail
their gates (the audit of 2026-12-06: 55% rejected, 1.66 m against the true association's 0.11 m),
and the warning names that cause beside the map's. The test
never reads the file's landmark ids (as localization never does, the oracle aside).
"""

from __future__ import annotations

from typing import Any, Mapping, Optional

import numpy as np

from camloc.tails import binomial_tail

# The share of observations a complete map and ordinary clutter leave rejected (see above).
REFERENCE_REJECTED_SHARE = 0.2
# Below this binomial tail, the rejections are more than that rate explains.
INCOMPLETE_MAP_PROBABILITY = 1e-3
# The estimate's name when the filter made no update.
ODOMETRY_ALONE = "odometry alone (no update)"


def filter_name(config: Mapping[str, Any]) -> str:
    """The filter a configuration runs, as tables name it: ``iterated EKF (euler)``, ``EKF (se3)``.

    ``config`` is ``dataclasses.asdict(LocalizerConfig)`` (``summary["config"]``); an incomplete
    one (a run folder edited by hand) gives ``filter``.
    """
    state, iterations = config.get("filter"), config.get("iterations")
    if not isinstance(state, str) or not isinstance(iterations, int):
        return "filter"
    kind = 'iterated EKF' if iterations > 1 else 'EKF'
    if config.get("map") in ("prior", "none"):  # the mapping localizer (camloc.slam_run)
        return f"{kind}-SLAM (map {config['map']})"
    return f"{kind} ({state})"


def _mapping_name(summary: Mapping[str, Any]) -> Optional[str]:
    """A mapping run's name (``iterated EKF-SLAM (map exact)``), from its summary's map block."""
    block, config = summary.get("map"), summary.get("config")
    if not isinstance(block, Mapping) or not isinstance(config, Mapping):
        return None
    return f"{'iterated EKF' if config.get('iterations', 1) > 1 else 'EKF'}-SLAM (map {block.get('mode')})"


def estimate_name(summary: Mapping[str, Any]) -> str:
    """What made a run's estimate: its filter (``filter_name``), or ``ODOMETRY_ALONE`` when the
    filter made no update (``counts.updates`` is 0), so that a table never shows odometry under
    the filter's name."""
    counts = summary.get("counts") if isinstance(summary.get("counts"), Mapping) else {}
    if counts.get("updates") == 0:
        return ODOMETRY_ALONE
    config = summary.get("config")
    mapping = _mapping_name(summary)
    if mapping is not None:
        return mapping
    return filter_name(config) if isinstance(config, Mapping) else "filter"


def rejection_tail(rejected: int, observations: int, rate: float = REFERENCE_REJECTED_SHARE) -> float:
    """``P(X >= rejected)`` for X ~ Binomial(observations, rate): how likely that many rejections
    are if each observation were rejected independently at ``rate``."""
    if rejected <= 0:
        return 1.0
    return min(1.0, float(binomial_tail(rejected - 1, observations, rate)))  # its rounding can pass 1


# Information matrices whose eigenvalues span this many decades leave a covariance indefinite to
# rounding: float64 keeps about 16 digits, and an update subtracts terms of both magnitudes. Files
# of one sensor's noise span a few decades (2026-12-06: the real course file 1.4, the simulator's kinds 1.4-3.4).
INFORMATION_DECADES_APART = 10


def information_decades(dataset) -> float:
    """How many decades the noise of a dataset spans: the eigenvalues of the covariances the filter
    reads (``odom_cov``, ``obs_cov``: the file's information inverted), odometry's and the
    observations' together, each observation's own rows only (a pixel's inert padding left out, as
    the zero rows of a planar robot's lifted odometry); 0 for a dataset with none."""
    from camloc.measurement import dof_of

    blocks = [np.linalg.eigvalsh(dataset.odom_cov).ravel()] if len(dataset.odom_cov) else []
    kinds = dataset.obs_kind
    for dof in np.unique(dof_of(kinds)) if len(kinds) else ():
        blocks.append(np.linalg.eigvalsh(dataset.obs_cov[dof_of(kinds) == dof][:, :dof, :dof]).ravel())
    values = np.concatenate(blocks) if blocks else np.zeros(0)
    values = values[values > 0]
    return float(np.log10(values.max() / values.min())) if values.size else 0.0


def divergence_cause(dataset) -> str:
    """What most likely broke a run's covariance down, for its error (``FilterDivergedError.at_pose``):
    information matrices many orders of magnitude apart where the file's are, else an estimate that
    lost the robot's path (a landmark near a pixel camera's plane makes its Jacobian unbounded)."""
    decades = information_decades(dataset)
    if decades >= INFORMATION_DECADES_APART:
        return (f"the file's information matrices are {decades:.0f} orders of magnitude apart, which leaves a "
                "covariance indefinite to rounding")
    return ("the estimate had most likely lost the robot's path, from a wrong association or odometry much noisier "
            "than its information says; '--association oracle' tells which where the file's landmark ids are true")


# What the mapping localizer maps (``localizer.unmappable_reason`` says why a dataset is not that)
MAPPED_LANDMARKS = "point landmarks, a planar robot's markers and tags with their orientations"


# Said of a pixel-only file whose map looks incomplete (docs/mapping.md, "What it reaches"): measured
# on 300-pose worlds of two pixel-only cameras with half the map withheld, the beam lost the robot
# on 9 of 12 (over 3x the true association's error).
RAYS_NOT_MAPPED = ("; with pixel-only cameras camloc does not find the landmarks a map lacks (a ray does not "
                   "place its landmark), and the association may pair their rays with mapped landmarks along "
                   "them and lose the robot (docs/mapping.md): compare the estimate with odometry's")


# Said of a pixel-only file run with no map (``--map none``; docs/mapping.md, "What it reaches"):
# measured on 24 200-pose worlds of two pixel-only cameras (grid, smooth3d, aerial; normalized and
# pixel intrinsics; seeds 0-3), the default association's estimate was further from the truth than
# odometry alone on 18 (3 with the true association; 2026-12-05, the landmarks from cloned poses).
RAYS_NO_MAP = ("with pixel-only cameras and no map, camloc's EKF-SLAM is not reliable: on simulated worlds its "
               "estimate was further from the truth than odometry alone on 18 of 24 (docs/mapping.md); compare the "
               "estimate with odometry's")


def rays_only(obs_kind) -> bool:
    """Whether a dataset's observations (their kinds, ``Dataset.obs_kind``) are all rays: none places
    its landmark (``slam_landmarks.places_points``: a measurement with range, a planar robot's own);
    False without observations."""
    from camloc.slam_landmarks import places_points

    kinds = np.asarray(obs_kind)
    return bool(kinds.size) and not bool(np.any(places_points(kinds)))


def run_warnings(counts: Mapping[str, int], *, mapped: bool = False, map_size: Optional[int] = None,
                 unmappable: Optional[str] = None, rays_only: bool = False, map_mode: Optional[str] = None) -> list[str]:
    """The warnings a run's counts call for (``summary["counts"]``: ``observations``, ``rejected``,
    ``updates``), each one line: the estimate is odometry alone, or the map looks incomplete (not
    said of a run that ``mapped``: it added what the map lacks, its summary's ``map`` says how much).
    ``map_size``: the map's landmarks, where known (an empty map is said by the reader; what is
    said here is why nothing was mapped); ``unmappable``: why the mapping localizer cannot run the
    dataset (``localizer.unmappable_reason``), said with the incomplete map it would have mended;
    ``rays_only``: every observation is a pixel-only camera's (a ray), whose landmarks the map lacks
    are not found, and whose run on such a map may be lost: said with the incomplete map, and of a run
    that mapped with no map (``map_mode`` "none", ``RAYS_NO_MAP``)."""
    observations, rejected, updates = counts["observations"], counts["rejected"], counts["updates"]
    found = []
    if observations == 0:
        found.append("no observation camloc can use (the reader's warnings say what it skipped): the estimate "
                      "is odometry alone, not corrected by the camera")
    elif updates == 0:
        found.append(f"all {observations} observations were rejected, so the filter made no update: the estimate "
                      "is odometry alone, not corrected by the camera")
    cannot_map = (f"; camloc adds the landmarks a map lacks only for {MAPPED_LANDMARKS}, and {unmappable}"
                  if unmappable else RAYS_NOT_MAPPED if rays_only else "")
    if observations and mapped and rays_only and map_mode == "none":
        found.append(RAYS_NO_MAP)
    if observations and not mapped and map_size == 0:
        found.append(f"the file has no map, and camloc maps (EKF-SLAM) only {MAPPED_LANDMARKS}: {unmappable}"
                     if unmappable else "the file has no map: '--map none' maps what the camera sees (EKF-SLAM)")
    elif observations and not mapped and rejection_tail(rejected, observations) < INCOMPLETE_MAP_PROBABILITY:
        found.append(
            f"{rejected} of {observations} observations ({rejected / observations:.0%}) were rejected, far more than "
            f"a complete map and ordinary clutter leave (at most about {REFERENCE_REJECTED_SHARE:.0%}): the map may "
            "lack landmarks the camera sees, or the detections are heavily cluttered, or the filter lost the robot "
            "and the landmarks no longer fit where it predicts them (compare the estimate with odometry's); "
            f"'camloc info' on the dataset counts the observations of ids absent from the map{cannot_map}")
    return found
