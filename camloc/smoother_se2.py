"""The planar smoother: the maximum a posteriori trajectory of a planar robot (SE(2)) over all
poses at once, given the associations a run accepted. ``camloc smooth`` runs it for planar
datasets; ``camloc.smoother`` is the 6-DOF one (a planar file's odometry has no noise in z, roll
and pitch, which the 6-DOF problem cannot whiten).

    result = smooth_planar_run(dataset, run, SmootherConfig())

Model card
----------
Variables   x_k = (x, y, theta), k = 0..N-1; x_0 FIXED at the dataset's start pose; 3 (N-1) unknowns.
Update      the right perturbation of ``camloc.planar``: t <- t + R(theta) dt, theta <- theta + dtheta.
Odometry    one factor per edge (a, b) with measured increment u (``EDGE_SE2``):
              d = between(x_a, x_b),   r = between(u, d) = (R(u_theta)^T (d_t - u_t), wrap(d_theta - u_theta))
            (g2o's ``EdgeSE2`` error, u^-1 (x_a^-1 x_b) as (t, theta)), whitened by the edge's
            covariance (the file's information inverted). Jacobians, J the rotation by +90 deg:
              dr/d delta_a = [[-R_u^T, -R_u^T J d_t], [0, 0, -1]],  dr/d delta_b = [[R_u^T R(d_theta), 0], [0, 0, 1]]
Observation one factor per accepted observation: r = z - h(x_k) (an angle row wrapped), h and its
            Jacobian H those of the filter (``filters.SE2Filter.observe``: point2, marker (its
            heading psi a row), or a 3-D camera on the lifted pose); dr/d delta = -H. A tag's
            orientation seen by a camera is a factor of its own beside its centre's, the filter's
            error state r = e = Log(R_pred^-1 R_meas) with H through Jl^-1(e) (``tags.aligned``:
            the 1-DOF turn about z of the planar robot). Whitened by the file's covariance.
Loss        as ``camloc.smoother``: 1/2 sum |r_odo|^2 + 1/2 sum rho(|r_obs|^2), Huber rho on each
            observation's Mahalanobis distance (``SmootherConfig.huber``).
Solver      Gauss-Newton on the IRLS weights with Levenberg-Marquardt damping when a step does not
            lower the cost; sparse normal equations (a sparse Cholesky,
            ``camloc.cholesky``, as the 3-D smoother's). Converged when the largest step
            component is below ``step_tolerance``.
Every Jacobian is checked against central finite differences in tests/test_smoother_se2.py.

Pure: no I/O, no printing.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import scipy.sparse as sp

from camloc import geometry, planar, tags
from camloc.cholesky import Cholesky, NotPositiveDefinite
from camloc.dataset import Dataset
from camloc.errors import CamlocError
from camloc.filters import SE2Filter
from camloc.measurement import TAG_ROTATION
from camloc.results import UNASSOCIATED, RunResult
from camloc.sensors import sensors_of
from camloc.smoother import IterationCallback, Iteration, SmootherConfig, SmoothingResult, check_run_matches, huber_rho, huber_weight

DOF = 3
_MAX_DAMPING = 1e8


@dataclass(frozen=True)
class PlanarProblem:
    """The planar factor graph: N poses (the first fixed), N-1 odometry factors, M observations.

    Attributes
    ----------
    x_start : (3,) the fixed first pose. u : (N-1, 3) measured increments; odom_whiten (N-1, 3, 3).
    obs_pose : (M,) observing pose; obs_sensor : (M,) its sensor (``sensors.sensors_of``), with
    ``sensors`` the table; obs_landmark : (M,) map rows; obs_z (M, 3), obs_kind (M,),
    obs_whiten (M, 3, 3); landmark_quat_xyzw : (L, 4) the tags' orientations (NaN for the
    others), read for a tag's orientation (``measurement.TAG_ROTATION``).
    """

    x_start: np.ndarray
    u: np.ndarray
    odom_whiten: np.ndarray
    obs_pose: np.ndarray
    obs_sensor: np.ndarray
    sensors: dict
    landmark_xyz: np.ndarray
    landmark_heading: np.ndarray
    obs_landmark: np.ndarray
    obs_z: np.ndarray
    obs_kind: np.ndarray
    obs_whiten: np.ndarray
    landmark_quat_xyzw: np.ndarray | None = None

    @property
    def num_poses(self) -> int:
        return int(self.u.shape[0]) + 1


def odometry_residual(x_a: np.ndarray, x_b: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The odometry factors' residuals (..., 3) and their Jacobians (..., 3, 3) with respect to the
    right perturbations of x_a and x_b (..., 3) (model card); u (..., 3) the measured increments."""
    R_a = planar.rotation(x_a[..., 2])
    d_t = np.einsum("...ji,...j->...i", R_a, x_b[..., :2] - x_a[..., :2])      # R_a^T (t_b - t_a)
    d_theta = planar.wrap(x_b[..., 2] - x_a[..., 2])
    R_u = planar.rotation(u[..., 2])
    r = np.concatenate([np.einsum("...ji,...j->...i", R_u, d_t - u[..., :2]), planar.wrap(d_theta - u[..., 2])[..., None]], -1)
    A = np.zeros(r.shape + (3,))
    A[..., :2, :2] = -np.swapaxes(R_u, -1, -2)
    A[..., :2, 2] = -np.einsum("...ji,...j->...i", R_u, d_t @ planar.J.T)      # -R_u^T J d_t
    A[..., 2, 2] = -1.0
    B = np.zeros(r.shape + (3,))
    B[..., :2, :2] = np.swapaxes(R_u, -1, -2) @ planar.rotation(d_theta)
    B[..., 2, 2] = 1.0
    return r, A, B


def observation_residuals(problem: PlanarProblem, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (M, 3) ``z - h(x_k)`` (angles wrapped) and their Jacobians (M, 3, 3) ``-H``,
    computed a pose and a sensor at a time (the filter's models take one pose)."""
    filter_model = SE2Filter()
    m = problem.obs_pose.size
    r, J = np.zeros((m, 3)), np.zeros((m, 3, 3))
    order = np.lexsort((problem.obs_sensor, problem.obs_pose))
    key = problem.obs_pose[order] * (len(problem.sensors) + 1) + problem.obs_sensor[order]
    bounds = np.flatnonzero(np.diff(key)) + 1
    for rows in np.split(order, bounds) if m else []:
        sensor = problem.sensors[int(problem.obs_sensor[rows[0]])]
        landmarks = problem.obs_landmark[rows]
        z_hat, H = filter_model.observe(x[problem.obs_pose[rows[0]]], sensor.T_robot_camera, sensor.intrinsics,
                                        problem.landmark_xyz[landmarks], sensor.kind, heading=problem.landmark_heading[landmarks],
                                        tag_quat=None if problem.landmark_quat_xyzw is None else problem.landmark_quat_xyzw[landmarks])
        if sensor.kind == TAG_ROTATION:  # z - z_hat the error state e = Log(R_pred^-1 R_meas), H through Jl^-1(e)
            z_hat, H = tags.aligned(problem.obs_z[rows], geometry.so3_exp(z_hat), H)
        r[rows] = planar.wrap_residuals(problem.obs_z[rows] - z_hat, problem.obs_kind[rows])
        J[rows] = -H
    return r, J


@dataclass(frozen=True)
class _Linearization:
    odom_r: np.ndarray   # (E, 3) whitened
    odom_A: np.ndarray   # (E, 3, 3) whitened, w.r.t. pose a
    odom_B: np.ndarray   # (E, 3, 3) w.r.t. pose b
    obs_r: np.ndarray    # (M, 3) whitened
    obs_J: np.ndarray    # (M, 3, 3)

    @property
    def obs_sq(self) -> np.ndarray:
        return np.einsum("mi,mi->m", self.obs_r, self.obs_r)


def linearize(problem: PlanarProblem, x: np.ndarray) -> _Linearization:
    """Every factor's whitened residual and Jacobians at the poses x (N, 3)."""
    r, A, B = odometry_residual(x[:-1], x[1:], problem.u)
    W = problem.odom_whiten
    obs_r, obs_J = observation_residuals(problem, x)
    Wo = problem.obs_whiten
    return _Linearization(np.einsum("eij,ej->ei", W, r), W @ A, W @ B, np.einsum("mij,mj->mi", Wo, obs_r), Wo @ obs_J)


def robust_cost(lin: _Linearization, huber: float) -> float:
    return 0.5 * float(np.sum(lin.odom_r**2)) + 0.5 * float(np.sum(huber_rho(lin.obs_sq, huber)))


def normal_equations(problem: PlanarProblem, lin: _Linearization, huber: float) -> tuple[sp.csc_matrix, np.ndarray]:
    """The IRLS Gauss-Newton system ``H step = -g`` over the free poses 1..N-1, (3(N-1),):
    every factor's 3x3 blocks ``J_i' w J_j`` summed into a sparse matrix at once."""
    n = problem.num_poses
    k = np.arange(problem.u.shape[0])
    weight = huber_weight(lin.obs_sq, huber)
    WJ = weight[:, None, None] * lin.obs_J
    At, Bt = np.swapaxes(lin.odom_A, 1, 2), np.swapaxes(lin.odom_B, 1, 2)
    Jt = np.swapaxes(lin.obs_J, 1, 2)
    # (block row, block column, 3x3 block) of every term
    rows = np.concatenate([k, k + 1, k, k + 1, problem.obs_pose])
    cols = np.concatenate([k, k + 1, k + 1, k, problem.obs_pose])
    blocks = np.concatenate([At @ lin.odom_A, Bt @ lin.odom_B, At @ lin.odom_B, Bt @ lin.odom_A, Jt @ WJ])
    r_index = (DOF * rows[:, None, None] + np.arange(DOF)[None, :, None]) + np.zeros((1, 1, DOF), np.int64)
    c_index = (DOF * cols[:, None, None] + np.arange(DOF)[None, None, :]) + np.zeros((1, DOF, 1), np.int64)
    H = sp.coo_matrix((blocks.ravel(), (r_index.ravel(), c_index.ravel())), shape=(DOF * n, DOF * n)).tocsc()
    g = np.zeros((n, DOF))
    np.add.at(g, k, np.einsum("eji,ej->ei", lin.odom_A, lin.odom_r))
    np.add.at(g, k + 1, np.einsum("eji,ej->ei", lin.odom_B, lin.odom_r))
    np.add.at(g, problem.obs_pose, np.einsum("mji,mj->mi", WJ, lin.obs_r))
    return H[DOF:, DOF:], g.ravel()[DOF:]  # the first pose is fixed


def _step(H: sp.csc_matrix, g: np.ndarray, damping: float) -> np.ndarray:
    d = H.diagonal()
    scale = 1.0 / np.sqrt(np.maximum(d, 1e-300))  # Jacobi scaling, as camloc.smoother
    Hs = sp.diags(scale) @ H @ sp.diags(scale) + damping * sp.identity(H.shape[0], format="csc")
    try:
        return -scale * Cholesky(Hs).solve(scale * g)
    except NotPositiveDefinite as error:  # a singular system: a pose nothing determines
        raise CamlocError(f"the planar smoothing problem does not determine every pose ({error})") from None


def _retract_all(x: np.ndarray, step: np.ndarray) -> np.ndarray:
    out = x.copy()
    for k, delta in enumerate(step.reshape(-1, DOF), start=1):
        out[k] = planar.retract(x[k], delta)
    return out


def smooth_planar(problem: PlanarProblem, x_initial: np.ndarray, config: Optional[SmootherConfig] = None, *,
                  on_iteration: Optional[IterationCallback] = None) -> SmoothingResult:
    """The MAP poses of ``problem`` from ``x_initial`` (N, 3) (the first replaced by the start),
    as a ``camloc.smoother.SmoothingResult`` (poses lifted to (N, 4, 4))."""
    config = config or SmootherConfig()
    config.validate()
    started = time.perf_counter()
    x = np.array(x_initial, dtype=float)
    x[0] = problem.x_start
    lin = linearize(problem, x)
    cost = initial_cost = robust_cost(lin, config.huber)
    damping, iterations, converged = 0.0, 0, problem.num_poses < 2
    while not converged and iterations < config.max_iterations:
        H, g = normal_equations(problem, lin, config.huber)
        step = _step(H, g, damping)
        candidate = _retract_all(x, step)
        candidate_lin = linearize(problem, candidate)
        candidate_cost = robust_cost(candidate_lin, config.huber)
        iterations += 1
        accepted = candidate_cost <= cost
        max_step = float(np.max(np.abs(step))) if step.size else 0.0
        if accepted:
            x, lin, cost = candidate, candidate_lin, candidate_cost
            damping = damping / 10.0 if damping > 1e-9 else 0.0
            converged = max_step < config.step_tolerance
        else:  # the linearization is poor here: damp towards gradient descent (Levenberg-Marquardt)
            damping = max(10.0 * damping, 1e-4)
            converged = damping > _MAX_DAMPING
        if on_iteration is not None:
            on_iteration(Iteration(iterations, cost, max_step if accepted else math.nan, damping, accepted))
    return SmoothingResult(
        T_world_robot=planar.lift(x), iterations=iterations, converged=bool(converged), initial_cost=initial_cost,
        final_cost=cost, condition=math.nan, odometry_factors=int(problem.u.shape[0]),
        observation_factors=int(problem.obs_pose.size), dropped_observations=0,
        downweighted_observations=int(np.count_nonzero(lin.obs_sq > config.huber * config.huber)),
        seconds=time.perf_counter() - started,
    )


def planar_problem(dataset: Dataset, run: RunResult) -> PlanarProblem:
    """The planar factor graph of a planar dataset's odometry and the observations the run
    accepted (``camloc.smoother.check_run_matches`` first)."""
    if not dataset.planar:
        raise CamlocError(f"{dataset.source}: the planar smoother needs a planar dataset (VERTEX_SE2 / EDGE_SE2)")
    check_run_matches(dataset, run)
    chosen = tags.observation_landmarks(run.associations.landmark, dataset.obs_kind, dataset.obs_partner, orientations=True)
    rows = np.flatnonzero(chosen != UNASSOCIATED)
    order = np.argsort(dataset.landmark_ids, kind="stable")
    landmark = order[np.searchsorted(dataset.landmark_ids[order], chosen[rows])] if rows.size else np.zeros(0, np.int64)
    # a tag's orientation is a factor beside its centre's where its landmark has one (a tag)
    keep = (dataset.obs_kind[rows] != TAG_ROTATION) | np.isfinite(dataset.landmark_quat_xyzw[landmark, 0])
    rows, landmark = rows[keep], landmark[keep]
    sensors, obs_sensor = sensors_of(dataset)
    odom_cov = planar.planar_block(dataset.odom_cov)
    return PlanarProblem(
        x_start=planar.flatten(dataset.T_world_start), u=planar.flatten(dataset.T_odometry).reshape(-1, 3),
        odom_whiten=_whitening(odom_cov), obs_pose=dataset.obs_pose_index[rows].astype(np.int64),
        obs_sensor=obs_sensor[rows], sensors=sensors, landmark_xyz=dataset.landmark_xyz,
        landmark_heading=dataset.landmark_heading, obs_landmark=landmark.astype(np.int64), obs_z=dataset.obs_z[rows],
        obs_kind=dataset.obs_kind[rows], obs_whiten=_whitening(dataset.obs_cov[rows]), landmark_quat_xyzw=dataset.landmark_quat_xyzw,
    )


def _whitening(cov: np.ndarray) -> np.ndarray:
    """(..., d, d) ``L^-1`` with ``L L^T = cov`` (Cholesky; a solve, not an inverse of cov)."""
    if cov.shape[0] == 0:
        return np.zeros_like(cov)
    L = np.linalg.cholesky(cov)
    return np.linalg.solve(L, np.broadcast_to(np.eye(cov.shape[-1]), cov.shape))


def smooth_planar_run(dataset: Dataset, run: RunResult, config: Optional[SmootherConfig] = None, *,
                      on_iteration: Optional[IterationCallback] = None) -> SmoothingResult:
    """``smooth_planar`` the run's accepted associations over the planar dataset, from the
    filter's estimate."""
    from camloc import geometry

    x0 = planar.flatten(geometry.pose_from_quat(run.estimate_xyz, run.estimate_quat_xyzw))
    return smooth_planar(planar_problem(dataset, run), x0, config, on_iteration=on_iteration)
