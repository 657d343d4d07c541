"""Joint compatibility branch and bound (Neira & Tardos, "Data association in stochastic mapping
using the joint compatibility test", IEEE Trans. Robotics and Automation 17(6), 2001).

A set of pairs (observation i -> landmark j) is jointly compatible when its stacked innovation
passes the chi^2 test with 3k degrees of freedom:

    y = [z_i - z_hat_j]_k,   H = [H_j]_k,   S = H P H' + blockdiag(R_i),   y' S^-1 y <= chi2(3k)

Individual compatibility (each pair alone passing its 3-dof gate) ignores that all predictions
share the pose's error; joint compatibility does not, so a set of pairs that are each plausible
but together imply contradictory poses is refused.

The search (``jcbb``) walks the observations depth first, trying for each its individually
compatible landmarks and then leaving it unpaired; a branch is cut when even pairing every
remaining observation could not beat the best set found (more pairs win; among equal counts, the
lower joint NIS, among the sets the search reaches). The bound on the work is ``max_nodes`` (default 2,000 joint tests per pose):
past it the search returns the best set found so far, flagged as not exhaustive.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from camloc.association import mahalanobis_3x3
from camloc.tails import chi2_quantile


@dataclass(frozen=True)
class JcbbResult:
    """assignment : (n,) candidate index per observation, -1 unpaired; nis : joint NIS of the
    pairs; nodes : joint tests made; exhaustive : False when max_nodes cut the search short."""

    assignment: np.ndarray
    nis: float
    nodes: int
    exhaustive: bool


def joint_nis(
    pairs: list[tuple[int, int]], y_all: np.ndarray, H: np.ndarray, P: np.ndarray, R_obs: np.ndarray, orientations: dict | None = None,
) -> float:
    """``y' S^-1 y`` of the stacked innovation of ``pairs`` (observation, candidate).

    y_all : (n, m, 3) innovations of every observation against every candidate; H : (m, 3, s)
    candidate Jacobians; P : (s, s) state covariance; R_obs : (n, 3, 3). orientations : a tag
    pair's orientation rows {(i, j): (e (3,), H_rot (3, s), R_rot (3, 3))}, stacked after the
    positions (``camloc.tag_orientations``).
    """
    obs = [i for i, _ in pairs]
    cand = [j for _, j in pairs]
    rows = [orientations[pair] for pair in pairs if pair in orientations] if orientations else []
    y = np.concatenate([y_all[obs, cand].reshape(-1)] + [e for e, _, _ in rows])
    H_stack = np.concatenate([H[cand].reshape(-1, H.shape[-1])] + [H_rot for _, H_rot, _ in rows])
    S = H_stack @ P @ H_stack.T
    for k, R in enumerate([R_obs[i] for i in obs] + [R_rot for _, _, R_rot in rows]):
        S[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] += R
    return float(y @ np.linalg.solve(S, y))


def _individual_d2(i: int, columns: np.ndarray, y_all: np.ndarray, H: np.ndarray, P: np.ndarray, R_obs: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distance of observation i against each candidate in ``columns``."""
    if columns.size == 0:
        return np.zeros(0)
    S = H[columns] @ P @ np.swapaxes(H[columns], 1, 2) + R_obs[i]
    return mahalanobis_3x3(S, y_all[i, columns])[0]


def jcbb(
    y_all: np.ndarray, H: np.ndarray, P: np.ndarray, R_obs: np.ndarray, compatible: np.ndarray,
    *,
    probability: float = 0.99,
    max_nodes: int = 2000,
    seed: list[tuple[int, int]] | None = None,
    dof: np.ndarray | None = None,
    orientations: dict | None = None,
    landmark_of: np.ndarray | None = None,
) -> JcbbResult:
    """The largest jointly compatible set of pairs.

    Parameters
    ----------
    y_all : (n, m, 3) innovation of observation i against candidate j.
    H : (m, 3, s) Jacobians of the candidates' predictions; P : (s, s) state covariance.
    R_obs : (n, 3, 3) observation covariances.
    compatible : (n, m) individual compatibility (each pair's own gate, at its observation's dof).
    probability : of the joint chi^2 test.
    max_nodes : bound on the number of joint tests.
    seed : a set of pairs to test first (best friends): when it is jointly compatible and pairs
        every observation, nothing can beat it and the search is skipped.
    dof : (n,) each observation's degrees of freedom (``camloc.measurement``: its rows beyond
        them are inert); None: 3 each.
    orientations : the orientation rows of tag pairs (``joint_nis``), 3 more dof each.
    landmark_of : (m,) the landmark each candidate is, where one landmark is several candidates
        (a candidate of each sensor that may see it: a camera of depth and pixel records is two
        sensors); a landmark is paired once. None: each candidate a landmark of its own.
    """
    n = compatible.shape[0]
    dof = np.full(n, 3, dtype=np.int64) if dof is None else np.asarray(dof, dtype=np.int64)
    orientations = orientations or {}
    landmark_of = np.arange(compatible.shape[1]) if landmark_of is None else np.asarray(landmark_of)
    bounds = chi2_quantile(np.arange(1, 6 * n + 1), 1.0 - probability)  # chi^2 quantiles by total dof

    def bound(pairs: list) -> float:
        return float(bounds[sum(int(dof[i]) + 3 * ((i, j) in orientations) for i, j in pairs) - 1])

    if seed and len(seed) == n:
        nis = joint_nis(seed, y_all, H, P, R_obs, orientations)
        if nis <= bound(seed):
            return JcbbResult(_assignment(n, seed), nis, 1, True)

    order = np.argsort(compatible.sum(axis=1), kind="stable")  # fewest options first: cheap cuts
    # Within an observation, try the individually closest landmark first: the search then meets a
    # large compatible set early, and the bound cuts the rest.
    tries = [np.flatnonzero(compatible[i])[np.argsort(_individual_d2(i, np.flatnonzero(compatible[i]), y_all, H, P, R_obs))] for i in range(n)]
    best: dict = {"pairs": [], "nis": 0.0}
    nodes = 0
    exhausted = True

    def better(pairs: list, nis: float) -> bool:
        return len(pairs) > len(best["pairs"]) or (len(pairs) == len(best["pairs"]) and nis < best["nis"])

    def search(depth: int, pairs: list, used: set, nis: float) -> None:
        nonlocal nodes, exhausted
        if depth == n:
            if better(pairs, nis):
                best["pairs"], best["nis"] = list(pairs), nis
            return
        i = int(order[depth])
        for j in tries[i]:
            if int(landmark_of[j]) in used:
                continue
            if nodes >= max_nodes:
                exhausted = False
                return
            nodes += 1
            trial = pairs + [(i, int(j))]
            trial_nis = joint_nis(trial, y_all, H, P, R_obs, orientations)
            if trial_nis <= bound(trial):
                search(depth + 1, trial, used | {int(landmark_of[j])}, trial_nis)
        # leave observation i unpaired, if pairing all the rest could still beat the best set
        if len(pairs) + (n - depth - 1) > len(best["pairs"]):
            search(depth + 1, pairs, used, nis)

    search(0, [], set(), 0.0)
    return JcbbResult(_assignment(n, best["pairs"]), float(best["nis"]), nodes, exhausted)


def _assignment(n: int, pairs: list[tuple[int, int]]) -> np.ndarray:
    """(n,) the candidate of each of n observations in ``pairs``, -1 where it has none."""
    assignment = np.full(n, -1, dtype=np.int64)
    for i, j in pairs:
        assignment[i] = j
    return assignment
