"""Joint compatibility over one pose's pairs, for the mapping localizer (``camloc.slam_run``).

Per pose: each observation's candidates (landmarks within its own chi^2 gate, with their
innovation y, Jacobian H on the filter's error, and the covariance of a landmark held outside the
state) are searched depth first for the largest set of pairs that is **jointly** compatible
(Neira & Tardos 2001: the stacked innovation's Mahalanobis distance within the chi^2 gate of
its dimension), ties broken by the lower joint cost. Jointly means through the shared pose error:
two pairs that each fit alone but pull the pose two ways do not fit together, which is what keeps
a wrong pair of a poorly predicted pose out (the per-pose least-cost assignment took such pairs).
The search stops after ``max_nodes`` nodes and keeps the best set found.

Pure: no I/O, no printing.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from camloc.tails import chi2_quantile


@dataclass(frozen=True)
class Candidate:
    """One gated pair: observation index, landmark (table index), innovation y (3,), Jacobian
    H (3, n), the extra covariance (3, 3) of a landmark outside the state (zeros: in it or exact),
    the observation's noise R (3, 3), its degrees of freedom and its cost alone."""

    obs: int
    landmark: int
    y: np.ndarray
    H: np.ndarray
    extra: np.ndarray
    R: np.ndarray
    dof: int
    cost: float


def joint_distance(P: np.ndarray, pairs: list[Candidate]) -> float:
    """The stacked innovation's squared Mahalanobis distance ``y' S^-1 y`` with
    ``S = H P H' + blockdiag(R_i + extra_i)`` (the plain statement of what ``jcbb`` computes from
    its precomputed blocks)."""
    H = np.vstack([c.H for c in pairs])
    y = np.concatenate([c.y for c in pairs])
    S = H @ P @ H.T
    for i, c in enumerate(pairs):
        S[3 * i:3 * i + 3, 3 * i:3 * i + 3] += c.R + c.extra
    return float(y @ np.linalg.solve(S, y))


@lru_cache(maxsize=256)
def _gate(dof: int, probability: float) -> float:
    return chi2_quantile(dof, 1.0 - probability)


def jcbb(P: np.ndarray, candidates: list[list[Candidate]], probability: float, max_nodes: int = 2000) -> list[Candidate]:
    """The largest jointly compatible set of pairs (one candidate or none per observation, each
    landmark once), ties by the lower sum of the pairs' own costs. Every candidate's H P H' block
    against every other's is computed once (``H P H'`` over all of them), so that a node's joint
    test costs what its few pairs do, not the state's size."""
    order = sorted(range(len(candidates)), key=lambda i: (len(candidates[i]) == 0, len(candidates[i])))
    lists = [sorted(candidates[i], key=lambda c: c.cost) for i in order]
    flat = [c for options in lists for c in options]
    if not flat:
        return []
    slot = {id(c): n for n, c in enumerate(flat)}
    H = np.vstack([c.H for c in flat])
    cols = np.flatnonzero(np.any(H != 0.0, axis=0))  # the pose and the candidates' landmarks: not the whole state
    H = H[:, cols]
    cross = H @ P[np.ix_(cols, cols)] @ H.T  # (3C, 3C): every pair of candidates' H P H'
    for n, c in enumerate(flat):
        cross[3 * n:3 * n + 3, 3 * n:3 * n + 3] += c.R + c.extra
    y_all = np.concatenate([c.y for c in flat])
    best: list[Candidate] = []
    best_cost = np.inf
    nodes = 0

    def compatible(trial: list[Candidate]) -> bool:
        rows = np.concatenate([np.arange(3 * slot[id(c)], 3 * slot[id(c)] + 3) for c in trial])
        y = y_all[rows]
        d2 = float(y @ np.linalg.solve(cross[np.ix_(rows, rows)], y))
        return d2 <= _gate(sum(t.dof for t in trial), probability)

    def search(depth: int, chosen: list[Candidate], used: set, cost: float) -> None:
        nonlocal best, best_cost, nodes
        nodes += 1
        remaining = sum(1 for rest in lists[depth:] if rest)
        if len(chosen) + remaining < len(best) or (len(chosen) + remaining == len(best) and cost >= best_cost) or nodes > max_nodes:
            return
        if depth == len(lists):
            if len(chosen) > len(best) or (len(chosen) == len(best) and cost < best_cost):
                best, best_cost = list(chosen), cost
            return
        for c in lists[depth]:
            if c.landmark in used:
                continue
            trial = chosen + [c]
            if len(trial) > 1 and not compatible(trial):
                continue
            search(depth + 1, trial, used | {c.landmark}, cost + c.cost)
        search(depth + 1, chosen, used, cost)

    search(0, [], set(), 0.0)
    return best
