"""Newton steps stopped at the apex of the observations' cones (``camloc.huber_apex``,
``smoother._apex_limited_step``): which observations a step carries past their apex, and a 3-D
world with no map that the solver without it smoothed with rejected steps."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp

from camloc import geometry, smoother
from camloc.huber_apex import past_apex
from camloc.localizer import LocalizerConfig, localize
from camloc.simulate import SimulationConfig, simulate

NONE = smoother.SmootherConfig(map="none")


def test_past_apex_is_the_cone_crossing_its_apex_along_the_residual():
    """Three observations beyond the threshold f = 2 (|r| = 3) and one within it, after two
    odometry rows: a step crosses an apex where the residual's own component goes below zero."""
    r_obs = np.array([[3.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, 3.0], [1.0, 0.0, 0.0]])
    residual = np.concatenate([[0.5, -0.5], r_obs.ravel()])
    jacobian = sp.identity(14, format="csr")
    change = np.zeros((4, 3))
    change[0] = [-3.5, 0.0, 0.0]   # along -u past the apex: 3 - 3.5 < 0
    change[1] = [0.0, -2.9, 5.0]   # not past it (3 - 2.9 > 0), however far sideways
    change[2] = [1.0, 1.0, -3.0]   # exactly at the apex: not past it
    change[3] = [-5.0, 0.0, 0.0]   # within the threshold: its model is the quadratic, exact
    step = np.concatenate([[7.0, 7.0], change.ravel()])
    obs_sq = np.einsum("mi,mi->m", r_obs, r_obs)
    assert past_apex(residual, jacobian, step, 2, obs_sq, 2.0).tolist() == [True, False, False, False]
    assert not past_apex(residual, jacobian, step, 2, obs_sq, np.inf).any()  # plain least squares


@pytest.fixture(scope="module")
def no_map_world():
    """A 300-pose grid world, one depth camera, the true association. Smoothed with no map, the
    solver without the apex-limited steps took 12 iterations, two Newton steps rejected (their
    models broken by observations carried past their apex), and 8 factorizations; now 9, none
    rejected. (Seeds 0-9: 9-12 iterations before with 0-2 rejected, 8-10 after, none rejected.)"""
    dataset = simulate(SimulationConfig(trajectory="grid", poses=300), seed=1)
    return dataset, localize(dataset, LocalizerConfig(association="oracle"))


def _without_apex_limit(monkeypatch, dataset, run, config):
    with monkeypatch.context() as patch:
        patch.setattr(smoother, "_apex_limited_step", lambda *args: None)
        steps = []
        return smoother.smooth_run(dataset, run, config, on_iteration=steps.append), steps


def test_no_map_smoothing_takes_no_rejected_step_to_the_same_solution(no_map_world, monkeypatch):
    dataset, run = no_map_world
    steps = []
    ours = smoother.smooth_run(dataset, run, NONE, on_iteration=steps.append)
    before, before_steps = _without_apex_limit(monkeypatch, dataset, run, NONE)
    assert ours.converged and before.converged
    assert ours.iterations <= 9 < before.iterations
    assert all(step.accepted for step in steps) and not all(step.accepted for step in before_steps)
    # The same minimum: both solvers run to a step tolerance of 1e-11.
    tight = dataclasses.replace(NONE, step_tolerance=1e-11, max_iterations=200)
    ours = smoother.smooth_run(dataset, run, tight)
    reference, _ = _without_apex_limit(monkeypatch, dataset, run, tight)
    assert ours.converged and reference.converged
    assert ours.final_cost <= reference.final_cost * (1 + 1e-14)
    assert np.abs(ours.xyz - reference.xyz).max() < 1e-9
    R = np.swapaxes(ours.T_world_robot[:, :3, :3], 1, 2) @ reference.T_world_robot[:, :3, :3]
    assert np.abs(geometry.so3_log(R)).max() < 1e-9
    assert np.array_equal(ours.landmarks.ids, reference.landmarks.ids)
    assert np.abs(ours.landmarks.xyz - reference.landmarks.xyz).max() < 1e-9
