"""The planar smoother: the maximum a posteriori trajectory of a planar robot (SE(2)) and, unless
the map is held exact, its landmarks, over all poses at once, given the associations a run
accepted. ``camloc smooth`` runs it for planar datasets; ``camloc.smoother`` is the 6-DOF one (a
planar file's odometry has no noise in z, roll and pitch, which the 6-DOF problem cannot whiten),
and this problem is that one's with SE(2) poses: the same solver (``smoother.smooth``), the same
landmark variables (``camloc.smoother_landmarks``) and the same camera factors.

    result = smooth_planar_run(dataset, run, SmootherConfig(map="prior", map_sigma=0.1))

Model card
----------
Variables   x_k = (x, y, theta), k = 0..N-1; x_0 FIXED at the dataset's start pose (it also fixes
            the frame when no map does); 3 (N-1) unknowns. Then L landmark variables, three
            coordinates each (``SmootherConfig.map``, ``camloc.smoother_landmarks``: under ``exact``
            the ones the map lacks, under ``prior`` and ``none`` every observed one):
              a camera's 3-D point    l = (x, y, z)
              a floor point (VERTEX_XY, kind point2)   l = (x, y, 0): its z PINNED at 0 (a factor
                                      ``r = z`` of unit weight that nothing else touches, so its
                                      step and its value stay exactly 0: 2 unknowns in effect)
              a marker (VERTEX_MARKER_SE2)             l = (x, y, psi), psi its heading (radians)
Update      the right perturbation of ``camloc.planar``: t <- t + R(theta) dt, theta <- theta + dtheta;
            a landmark l <- l + dl (a marker's heading wrapped).
Odometry    one factor per edge (a, b) with measured increment u (``EDGE_SE2``):
              d = between(x_a, x_b),   r = between(u, d) = (R(u_theta)^T (d_t - u_t), wrap(d_theta - u_theta))
            (g2o's ``EdgeSE2`` error, u^-1 (x_a^-1 x_b) as (t, theta)), whitened by the edge's
            covariance (the file's information inverted). Jacobians, J the rotation by +90 deg:
              dr/d delta_a = [[-R_u^T, -R_u^T J d_t], [0, 0, -1]],  dr/d delta_b = [[R_u^T R(d_theta), 0], [0, 0, 1]]
Observation one factor per accepted observation, r = z - h(x_k, l) (an angle row wrapped):
              point2  h = p = R(theta)^T (l_xy - t)      dr/d delta = [[I, J p]],  dr/dl = [-R^T, 0]
              marker  h = (p, psi - theta)               dr/d delta = [[I, J p], [0, 0, 1]],
                                                         dr/dl = [[-R^T, 0], [0, 0, -1]]
            (a point2's third row inert), and a 3-D camera's (and a tag's orientation, under
            ``exact``) that of ``camloc.smoother.observation_factors`` at the lifted pose, its pose
            Jacobian the (x, y, yaw) columns of the SE(3) right perturbation's. Whitened by the
            file's covariance.
Map prior   under ``prior``, each observed mapped landmark: r = (l - l_map) / sigma (3,), a
            marker's heading difference wrapped and its sigma read as radians (as the online
            mapping's); a floor point's z row is its pin.
Loss, solver, covariances: ``camloc.smoother``'s (Huber on each observation's Mahalanobis
            distance; Gauss-Newton on the robust cost with Levenberg-Marquardt damping; the
            landmarks eliminated by their Schur complement, ``camloc.schur``, and the reduced
            pose system factored by the sparse Cholesky, ``camloc.cholesky``; the landmarks'
            marginal covariances by selected inversion). ``map.csv`` gets a floor point's and a
            marker's position on the floor (z = 0, no z variance; a marker's heading has no column).
Every Jacobian is checked against central finite differences in tests/test_smoother_se2.py.

Pure: no I/O, no printing.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar, Optional

import numpy as np
import scipy.sparse as sp

from camloc import planar
from camloc.dataset import LANDMARK_MARKER, LANDMARK_OF_PLANAR_SENSOR, LANDMARK_POINT2, LANDMARK_POINT3, Dataset, on_the_floor
from camloc.errors import CamlocError
from camloc.measurement import MARKER, is_planar
from camloc.observation_space import landmark_rows
from camloc.results import RunResult
from camloc.schur import LANDMARK_DOF
from camloc.smoother import (IterationCallback, Linearization, SmootherConfig, SmoothingProblem, SmoothingResult,
                             block_coo, check_run_matches, landmark_coo, observation_factors, observation_fields, smooth,
                             whitening)
from camloc.smoother_landmarks import LandmarkEstimate

DOF = planar.STATE_SIZE


@dataclass(frozen=True)
class PlanarProblem(SmoothingProblem):
    """``camloc.smoother.SmoothingProblem`` with SE(2) poses: ``T_start`` and ``T_odometry``
    lifted (``planar.lift``), ``odom_whiten`` (E, 3, 3) of the planar increment's (x, y, theta);
    a landmark's coordinates (``obs_landmark_xyz``, ``landmarks``) as the model card says, their
    kinds in ``landmarks.kind``. Poses are (N, 3) planar states wherever ``smooth`` handles them."""

    pose_dof: ClassVar[int] = DOF

    @property
    def start_state(self) -> np.ndarray:
        return planar.flatten(self.T_start)

    def lifted(self, T: np.ndarray) -> np.ndarray:
        return planar.lift(T)

    def linearize(self, T: np.ndarray, X: np.ndarray | None = None) -> Linearization:
        return linearize(self, T, X)

    def retract(self, T: np.ndarray, X: np.ndarray | None, step: np.ndarray):
        n = self.num_pose_unknowns
        moved = T.copy()
        moved[1:] = retract_poses(T[1:], step[:n].reshape(-1, DOF))
        if X is None:
            return moved, None
        X = X + step[n:].reshape(-1, LANDMARK_DOF)
        marker = self.landmarks.kind == LANDMARK_MARKER
        X[marker, 2] = planar.wrap(X[marker, 2])
        return moved, X

    def landmark_jacobians(self, T: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(R, d, 3) the observations ``rows``' Jacobians by their landmark variable, at states T."""
        return observation_residuals(self, T, self.landmarks.xyz, rows)[2]

    def prior_information(self) -> np.ndarray:
        """(L, 3, 3) each landmark variable's map prior and its pin (a floor point's z)."""
        return prior_weights(self.landmarks)[:, :, None] ** 2 * np.eye(LANDMARK_DOF)

    def reported_landmarks(self, estimate: LandmarkEstimate) -> LandmarkEstimate:
        """Floor points and markers on the floor (z = 0, no z variance): a floor point's z is
        pinned, a marker's third coordinate is its heading, which ``map.csv`` has no column for."""
        on_floor = on_the_floor(self.landmarks.kind)
        xyz, cov = estimate.xyz.copy(), estimate.cov.copy()
        xyz[on_floor, 2] = 0.0
        cov[on_floor, 2, :] = cov[on_floor, :, 2] = 0.0
        return replace(estimate, xyz=xyz, cov=cov)


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


def floor_factors(x: np.ndarray, coords: np.ndarray, z: np.ndarray, kinds: np.ndarray) -> tuple[np.ndarray, ...]:
    """Residuals (M, 3) ``z - h`` of point2 and marker observations (model card) from poses x
    (M, 3) of landmarks with coordinates (M, 3) (a marker's third its heading), and their
    Jacobians (M, 3, 3) with respect to the pose's right perturbation and to the landmark's
    coordinates. A point2's third row is inert (0)."""
    R = planar.rotation(x[:, 2])
    p = np.einsum("mji,mj->mi", R, coords[:, :2] - x[:, :2])  # R^T (l - t)
    marker = kinds == MARKER
    r = np.zeros_like(z, dtype=float)
    r[:, :2] = z[:, :2] - p
    r[marker, 2] = planar.wrap(z[marker, 2] - planar.wrap(coords[marker, 2] - x[marker, 2]))
    J_pose = np.zeros((len(x), 3, DOF))
    J_pose[:, 0, 0] = J_pose[:, 1, 1] = 1.0
    J_pose[:, :2, 2] = p @ planar.J.T  # a turn by dtheta moves p by -J p dtheta
    J_pose[marker, 2, 2] = 1.0
    J_landmark = np.zeros((len(x), 3, LANDMARK_DOF))
    J_landmark[:, :2, :2] = -np.swapaxes(R, 1, 2)
    J_landmark[marker, 2, 2] = -1.0
    return r, J_pose, J_landmark


def observation_residuals(problem: PlanarProblem, x: np.ndarray, X: np.ndarray | None,
                          rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The observation factors ``rows`` (default: all) at poses x (N, 3) and landmark variables
    X (L, 3): residuals (M, 3) (angle rows wrapped) and Jacobians (M, 3, 3) with respect to the
    pose's right perturbation and to the landmark's coordinates. A camera's landmark is its
    position: a floor point's or marker's seen by a camera (never paired so online) at z = 0,
    its third coordinate not read."""
    p = problem
    rows = np.arange(len(p.obs_pose)) if rows is None else rows
    coords = p.observed_xyz(X)[rows]
    kinds = p.obs_kind[rows]
    r, J_pose, J_landmark = np.zeros((rows.size, 3)), np.zeros((rows.size, 3, DOF)), np.zeros((rows.size, 3, LANDMARK_DOF))
    floor = is_planar(kinds)
    if np.any(floor):
        f = np.flatnonzero(floor)
        r[f], J_pose[f], J_landmark[f] = floor_factors(x[p.obs_pose[rows[f]]], coords[f], p.obs_z[rows[f]], kinds[f])
    if not np.all(floor):
        c = np.flatnonzero(~floor)
        flat = _flat_landmarks(p, rows[c])
        positions = coords[c].copy()
        positions[flat, 2] = 0.0
        rc = rows[c]
        r[c], J6, J_landmark[c], _ = observation_factors(
            planar.lift(x[p.obs_pose[rc]]), p.obs_T_robot_camera[rc], p.obs_intrinsics[rc], positions, p.obs_z[rc],
            kinds[c], None if p.obs_tag_rotation is None else p.obs_tag_rotation[rc])
        J_pose[c] = J6[:, :, list(planar.PLANAR_AXES)]
        J_landmark[c[flat], :, 2] = 0.0
    return r, J_pose, J_landmark


def _flat_landmarks(problem: PlanarProblem, rows: np.ndarray) -> np.ndarray:
    """(len(rows),) bool: the observations' landmark is a floor point's or marker's variable."""
    if problem.landmarks is None or problem.landmarks.kind is None:
        return np.zeros(rows.size, dtype=bool)
    variable = problem.obs_landmark[rows]
    return (variable >= 0) & on_the_floor(problem.landmarks.kind[np.maximum(variable, 0)])


def prior_weights(landmarks) -> np.ndarray:
    """(L, 3) the whitening of each landmark's prior and pin rows: ``1 / sigma`` on each
    coordinate under a map prior, 1 on a floor point's z (its pin), 0 where there is no row."""
    weight = np.where(landmarks.has_prior, 1.0 / landmarks.prior_sigma, 0.0)[:, None] * np.ones(LANDMARK_DOF)
    weight[landmarks.kind == LANDMARK_POINT2, 2] = 1.0
    return weight


def _prior_residuals(landmarks, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The landmarks with a prior or pin row (P,), their whitened residuals (P, 3) and weights (P, 3)."""
    weight = prior_weights(landmarks)
    held = np.flatnonzero(np.any(weight > 0.0, axis=1))
    target = np.nan_to_num(landmarks.prior_xyz[held])  # a pin's target: 0
    target[landmarks.kind[held] == LANDMARK_POINT2, 2] = 0.0
    difference = X[held] - target
    marker = landmarks.kind[held] == LANDMARK_MARKER
    difference[marker, 2] = planar.wrap(difference[marker, 2])
    return held, weight[held] * difference, weight[held]


def linearize(problem: PlanarProblem, x: np.ndarray, X: np.ndarray | None = None) -> Linearization:
    """Whitened residuals and the sparse Jacobian of every factor at poses x (N, 3) and landmark
    variables X (L, 3) (None: ``problem.landmarks.xyz``), in ``camloc.smoother``'s layout
    (odometry rows, observation rows, prior rows; pose columns, then landmark columns)."""
    p = problem
    if X is None and p.landmarks is not None:
        X = p.landmarks.xyz
    u = planar.flatten(p.T_odometry)
    r_odom, A, B = odometry_residual(x[p.odom_from], x[p.odom_to], u)
    r_obs, J_obs, J_lm = observation_residuals(p, x, X)
    r_odom = np.einsum("nij,nj->ni", p.odom_whiten, r_odom)
    r_obs = np.einsum("nij,nj->ni", p.obs_whiten, r_obs)
    odom_rows = DOF * np.arange(len(p.odom_from))
    obs_rows = odom_rows.size * DOF + 3 * np.arange(len(p.obs_pose))
    parts = [block_coo(odom_rows, p.odom_from, p.odom_whiten @ A), block_coo(odom_rows, p.odom_to, p.odom_whiten @ B),
             block_coo(obs_rows, p.obs_pose, p.obs_whiten @ J_obs)]
    residuals = [r_odom.ravel(), r_obs.ravel()]
    num_rows = DOF * len(p.odom_from) + 3 * len(p.obs_pose)
    r_prior = np.zeros((0, LANDMARK_DOF))
    if p.num_landmarks:
        variable = np.flatnonzero(p.obs_landmark >= 0)
        first_col = p.num_pose_unknowns + LANDMARK_DOF * p.obs_landmark[variable]
        parts.append(landmark_coo(obs_rows[variable], first_col, p.obs_whiten[variable] @ J_lm[variable]))
        held, r_prior, weight = _prior_residuals(p.landmarks, X)
        prior_rows = num_rows + LANDMARK_DOF * np.arange(held.size)
        parts.append(landmark_coo(prior_rows, p.num_pose_unknowns + LANDMARK_DOF * held, weight[:, :, None] * np.eye(LANDMARK_DOF)))
        residuals.append(r_prior.ravel())
        num_rows += LANDMARK_DOF * held.size
    rows, cols, values = (np.concatenate(column) for column in zip(*parts))
    return Linearization(
        residual=np.concatenate(residuals),
        jacobian=sp.csr_matrix((values, (rows, cols)), shape=(num_rows, p.num_unknowns)),
        odom_sq=np.einsum("ni,ni->n", r_odom, r_odom), obs_sq=np.einsum("ni,ni->n", r_obs, r_obs),
        prior_sq=np.einsum("ni,ni->n", r_prior, r_prior), odom_dim=DOF,
    )


def retract_poses(x: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Poses (N, 3) moved by right perturbations (N, 3): ``planar.retract`` over all at once."""
    out = np.empty_like(x)
    out[:, :2] = x[:, :2] + np.einsum("nij,nj->ni", planar.rotation(x[:, 2]), delta[:, :2])
    out[:, 2] = planar.wrap(x[:, 2] + delta[:, 2])
    return out


def smooth_planar(problem: PlanarProblem, x_initial: np.ndarray, config: Optional[SmootherConfig] = None, *,
                  on_iteration: Optional[IterationCallback] = None) -> SmoothingResult:
    """The MAP poses (and landmark variables) of ``problem`` from ``x_initial`` (N, 3) (the first
    replaced by the start), as a ``camloc.smoother.SmoothingResult`` (poses lifted to (N, 4, 4))."""
    return smooth(problem, np.asarray(x_initial, dtype=float), config, on_iteration=on_iteration)


def planar_problem(dataset: Dataset, run: RunResult, config: Optional[SmootherConfig] = None) -> PlanarProblem:
    """The planar factor graph of a planar dataset's odometry and the observations the run
    accepted (``camloc.smoother.check_run_matches`` first), with the landmark variables
    ``config.map`` says (None: ``SmootherConfig()``, the map held exact)."""
    if not dataset.planar:
        raise CamlocError(f"{dataset.source}: the planar smoother needs a planar dataset (VERTEX_SE2 / EDGE_SE2)")
    config = config or SmootherConfig()
    check_run_matches(dataset, run)
    coords = dataset.landmark_xyz.copy()
    marker = dataset.landmark_kind == LANDMARK_MARKER
    coords[marker, 2] = dataset.landmark_heading[marker]
    fields = observation_fields(dataset, run, config, coords)
    landmarks = fields["landmarks"]
    if landmarks is not None:
        fields["landmarks"] = replace(landmarks, kind=_variable_kinds(dataset, landmarks.ids, fields))
    num_poses = dataset.num_poses
    return PlanarProblem(
        pose_ids=np.asarray(dataset.pose_ids, dtype=np.int64), T_start=dataset.T_world_start,
        odom_from=np.arange(num_poses - 1, dtype=np.int64), odom_to=np.arange(1, num_poses, dtype=np.int64),
        T_odometry=dataset.T_odometry, odom_whiten=whitening(planar.planar_block(dataset.odom_cov)), **fields,
    )


def _variable_kinds(dataset: Dataset, ids: np.ndarray, fields: dict) -> np.ndarray:
    """(L,) the landmark variables' kinds: a mapped one's the map's, an added one's that of the
    observations of it (a floor point's, a marker's, else a camera's 3-D point)."""
    kind = np.full(ids.size, LANDMARK_POINT3, dtype=np.int64)
    rows = landmark_rows(dataset.landmark_ids, ids)
    mapped = rows >= 0
    kind[mapped] = dataset.landmark_kind[rows[mapped]]
    for obs_kind, landmark_kind in LANDMARK_OF_PLANAR_SENSOR.items():
        seen = np.unique(fields["obs_landmark"][fields["obs_kind"] == obs_kind])
        seen = seen[seen >= 0]
        kind[seen[~mapped[seen]]] = landmark_kind
    return kind


def smooth_planar_run(dataset: Dataset, run: RunResult, config: Optional[SmootherConfig] = None, *,
                      on_iteration: Optional[IterationCallback] = None) -> SmoothingResult:
    """``smooth_planar`` the run's accepted associations over the planar dataset, from the
    filter's estimate, with the map held as ``config.map`` says."""
    from camloc import geometry

    x0 = planar.flatten(geometry.pose_from_quat(run.estimate_xyz, run.estimate_quat_xyzw))
    return smooth_planar(planar_problem(dataset, run, config), x0, config, on_iteration=on_iteration)
