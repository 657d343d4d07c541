"""The exact Newton step without the Hessian (``camloc.newton_cg``) and where the smoother uses it
(``smoother._exact_newton_step``, ``smoother._gradient``): the step against a dense Newton solve,
its refusal of negative curvature, the smoother's gradient against central differences of its
cost, and a monocular world with no map whose Gauss-Newton steps shrank linearly converging
quadratically (docs/performance.md, 2026-12-05 (night))."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from camloc import smoother
from camloc.localizer import LocalizerConfig, localize
from camloc.newton_cg import newton_step
from camloc.simulate import SimulationConfig, simulate

DATA = Path(__file__).parent / "data"


def _quartic(n: int, seed: int, *, shift: float = 0.0):
    """f(x) = 1/2 x'Ax + 1/4 sum (c_i'x)^4 - shift/2 |x|^2 + b'x: gradient and Hessian, and A (a Gauss-Newton-like part)."""
    rng = np.random.default_rng(seed)
    M = rng.normal(size=(n, n))
    A = M @ M.T + n * np.eye(n)
    C = rng.normal(size=(3, n))
    b = rng.normal(size=n)

    def gradient(x):
        return A @ x + C.T @ (C @ x) ** 3 - shift * x + b

    def hessian(x):
        return A + C.T @ np.diag(3 * (C @ x) ** 2) @ C - shift * np.eye(n)

    return gradient, hessian, A


def test_the_step_is_the_dense_newton_step_with_the_exact_hessian():
    gradient, hessian, A = _quartic(8, 0)
    x = np.random.default_rng(1).normal(size=8)
    g = gradient(x)
    d = 1.0 / np.sqrt(np.diag(A))
    As = d[:, None] * A * d[None, :]
    step = newton_step(lambda delta: gradient(x + delta), g, d, lambda v: np.linalg.solve(As, v), rtol=1e-10)
    exact = -np.linalg.solve(hessian(x), g)
    gauss_newton = -np.linalg.solve(A, g)
    assert np.linalg.norm(exact - gauss_newton) > 0.1 * np.linalg.norm(exact)  # the quartic matters here
    # to the differences' accuracy (O(h), h = 1e-6 on the largest component)
    np.testing.assert_allclose(step, exact, rtol=0, atol=1e-4 * np.linalg.norm(exact))


def test_a_hessian_that_is_not_positive_definite_gives_no_step():
    gradient, hessian, A = _quartic(6, 2, shift=1e3)
    x = np.zeros(6)
    assert np.linalg.eigvalsh(hessian(x))[0] < 0.0
    d = np.ones(6)
    assert newton_step(lambda delta: gradient(x + delta), gradient(x), d, lambda v: np.linalg.solve(A, v)) is None


@pytest.fixture(scope="module")
def crawled():
    """The 300-pose aerial world with a pixel-only camera and no map, seed 4, and the oracle run
    main's filter made of it at a536270 (tests/data/README.md): Gauss-Newton took 107 iterations."""
    dataset = simulate(SimulationConfig(trajectory="aerial", poses=300, no_map=True, measurement="pixel"), seed=4)
    saved = np.load(DATA / "aerial_pixel_no_map_seed4_run.npz")
    run = localize(dataset, LocalizerConfig(map="none", association="oracle"))
    return dataset, dataclasses.replace(
        run, associations=dataclasses.replace(run.associations, landmark=saved["landmark"]),
        estimate_xyz=saved["estimate_xyz"], estimate_quat_xyzw=saved["estimate_quat_xyzw"])


def test_the_smoothers_gradient_is_that_of_its_cost(crawled):
    dataset, run = crawled
    config = smoother.SmootherConfig(map="none")
    problem = smoother.problem_from_run(dataset, run, config)
    T = smoother.initial_poses(dataset, run)
    T[0] = problem.start_state
    problem, _ = smoother._with_initial_landmarks(problem, T)
    problem, _ = smoother._without_undetermined_landmarks(problem, T)
    X = problem.landmarks.xyz
    lin = problem.linearize(T, X)
    g = smoother._gradient(lin, config.huber)
    rng = np.random.default_rng(3)
    h = 1e-6
    for _ in range(3):
        v = rng.normal(size=problem.num_unknowns)
        v /= np.linalg.norm(v)

        def cost(t):
            moved, moved_X = problem.retract(T, X, t * v)
            return smoother.robust_cost(problem.linearize(moved, moved_X), config.huber)

        assert float(g @ v) == pytest.approx((cost(h) - cost(-h)) / (2 * h), rel=1e-5, abs=1e-6)


def test_a_monocular_world_whose_gauss_newton_steps_shrank_linearly_converges(crawled):
    # Before: 107 iterations (7 rejected), the last 50 plain Newton steps shrinking by 0.87 each,
    # a landmark seen twice 0.5 m away; unconverged at the 50-iteration limit.
    dataset, run = crawled
    log: list = []
    result = smoother.smooth_run(dataset, run, smoother.SmootherConfig(map="none"), on_iteration=log.append)
    assert result.converged
    assert result.iterations <= 35
    assert result.final_cost <= 592.476318418878 * (1 + 1e-12)  # main's after 107 iterations
    # no linear tail: Gauss-Newton's took 66 steps from 1 mm to the 1e-7 tolerance (0.87 each)
    assert sum(i.accepted and i.max_step < 1e-3 for i in log) <= 8
