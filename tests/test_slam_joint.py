"""A pose's pairs judged given one another (issue 38, no map: ``slam_association.conditional_costs``
and ``joint_pairs``; docs/performance.md, 2026-12-05, "No map: a loop closure's returns judged
together")."""

from __future__ import annotations

import numpy as np
import pytest

from camloc.slam_association import JOINT_MARGIN, Candidate, conditional_costs, joint_pairs

GATE = 0.99  # the association's gate (LocalizerConfig.gate)


def _pairs(P: np.ndarray, ys: list, R: np.ndarray, limit: float) -> list[list[Candidate]]:
    """One candidate per observation: landmark i seen through the pose's translation (H = [I, 0, ...]),
    its own cost ``y' S^-1 y + ln det S - ln det R`` with ``S = H P H' + R``."""
    n = P.shape[0]
    H = np.zeros((3, n))
    H[:, :3] = np.eye(3)
    S = H @ P @ H.T + R
    out = []
    for i, y in enumerate(ys):
        y = np.asarray(y, float)
        cost = float(y @ np.linalg.solve(S, y) + np.linalg.slogdet(S)[1] - np.linalg.slogdet(R)[1])
        out.append([Candidate(i, 10 + i, y, H, np.zeros((3, 3)), R, 3, cost, 0, limit)])
    return out


def _j(P: np.ndarray, pairs: list[Candidate]) -> float:
    """J = y' S^-1 y + ln det S - sum ln det R of the stacked pairs (the plain statement)."""
    if not pairs:
        return 0.0
    H = np.vstack([c.H for c in pairs])
    y = np.concatenate([c.y for c in pairs])
    S = H @ P @ H.T
    for i, c in enumerate(pairs):
        S[3 * i:3 * i + 3, 3 * i:3 * i + 3] += c.R + c.extra
    return float(y @ np.linalg.solve(S, y) + np.linalg.slogdet(S)[1] - sum(np.linalg.slogdet(c.R)[1] for c in pairs))


def test_conditional_costs_are_the_joint_cost_less_the_set_without_the_pair():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(12, 12))
    P = A @ A.T / 12 + 0.1 * np.eye(12)
    R = np.diag([0.02, 0.03, 0.05])
    pairs = [options[0] for options in _pairs(P, rng.normal(size=(4, 3)).tolist(), R, np.inf)]
    # each pair a Jacobian of its own on the landmark columns too, so that the pairs differ
    pairs = [Candidate(c.obs, c.landmark, c.y, c.H + np.pad(0.3 * rng.normal(size=(3, 3)), ((0, 0), (3 + 3 * i, 6 - 3 * i))),
                       c.extra, c.R, c.dof, 0.0, 0, c.limit) for i, c in enumerate(pairs[:3])]
    pairs = [Candidate(c.obs, c.landmark, c.y, c.H, c.extra, c.R, c.dof, _j(P, [c]), 0, c.limit) for c in pairs]
    got = conditional_costs(P, pairs)
    for i in range(len(pairs)):
        assert got[i] == pytest.approx(_j(P, pairs) - _j(P, pairs[:i] + pairs[i + 1:]), rel=1e-9, abs=1e-9)
    assert conditional_costs(P, pairs[:1])[0] == pairs[0].cost  # a set of one: its own cost


def test_returns_each_over_its_limit_alone_are_taken_together_where_the_pose_is_unsure():
    """Three landmarks seen again from a pose unsure by 0.6 m: each pair alone costs more than its
    limit (the pose's spread is in its ln det S), given the other two far less: all three taken.
    One of them alone, at the same limit: refused (a lone pair is judged by its own cost, as
    before)."""
    R = np.diag([1e-3, 1e-3, 1e-3])
    offset = np.array([0.4, -0.3, 0.2])  # the drift: every landmark seen shifted the same way
    ys = [offset + d for d in ([0.01, 0.0, 0.0], [0.0, -0.02, 0.01], [0.0, 0.01, -0.01])]
    unsure = np.diag([0.36] * 3 + [0.01] * 3)
    alone = [options[0].cost for options in _pairs(unsure, ys, R, np.inf)]
    limit = min(alone) - 1.0  # every pair over its limit alone
    candidates = _pairs(unsure, ys, R, limit)
    chosen = joint_pairs(unsure, candidates, GATE)
    assert len(chosen) == 3
    given = conditional_costs(unsure, chosen)
    assert np.all(given + JOINT_MARGIN < limit)
    assert np.all(given < np.array(alone) - 10.0)
    # the same limit with one observation, or two (too few to vouch for each other): refused
    assert joint_pairs(unsure, candidates[:1], GATE) == []
    assert joint_pairs(unsure, candidates[:2], GATE) == []
    # a pair within its limit alone is taken whatever the others (as before)
    candidates = _pairs(unsure, ys, R, max(alone) + 1.0)
    assert len(joint_pairs(unsure, candidates[:1], GATE)) == 1


def test_a_pair_whose_cost_given_the_others_is_over_its_limit_is_left_out():
    """Three returns that agree and one that pulls the other way: the three are taken, the fourth
    not (its cost given the three is over its limit, though jointly compatible within the gate)."""
    R = np.diag([1e-3, 1e-3, 1e-3])
    P = np.diag([0.36] * 3 + [0.01] * 3)
    ys = [[0.4, -0.3, 0.2], [0.41, -0.31, 0.2], [0.4, -0.29, 0.21], [0.4, -0.3, 0.3]]
    every = [c[0] for c in _pairs(P, ys, R, np.inf)]
    assert len(joint_pairs(P, [[c] for c in every], GATE)) == 4  # jointly compatible
    given = np.sort(conditional_costs(P, every))
    limit = float(given[2] + 0.5 * (given[3] - given[2])) + JOINT_MARGIN
    assert limit < min(c.cost for c in every)  # each over it alone
    chosen = joint_pairs(P, _pairs(P, ys, R, limit), GATE)
    assert sorted(c.obs for c in chosen) == [0, 1, 2]
    assert np.all(conditional_costs(P, chosen) + JOINT_MARGIN < limit)


def test_a_pair_given_the_others_within_its_limit_but_not_by_the_margin_is_left_out():
    """The best of the sets the search tried is the likeliest by chance too: a pair kept only
    given the others must be JOINT_MARGIN within its limit."""
    R = np.diag([1e-3, 1e-3, 1e-3])
    P = np.diag([0.36] * 3 + [0.01] * 3)
    ys = [[0.4, -0.3, 0.2], [0.41, -0.31, 0.2], [0.4, -0.29, 0.21]]
    given = conditional_costs(P, [c[0] for c in _pairs(P, ys, R, np.inf)])
    assert len(joint_pairs(P, _pairs(P, ys, R, float(given.max()) + JOINT_MARGIN + 0.1), GATE)) == 3
    assert joint_pairs(P, _pairs(P, ys, R, float(given.min()) + JOINT_MARGIN - 0.1), GATE) == []
