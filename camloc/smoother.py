"""The smoother: the maximum a posteriori trajectory over all poses (and, unless the map is held
exact, the landmarks), using all the data at once.

The filter (``camloc.localizer``) estimates each pose from the past only. Given the associations a
run accepted, the smoother solves for every pose jointly, by Gauss-Newton / Levenberg-Marquardt
on an analytic sparse Jacobian. ``SmootherConfig.map`` says how the map is held
(``camloc.smoother_landmarks``): ``exact`` (fixed: poses only, the default), ``prior`` (mapped
landmarks estimated too, pulled toward the map) or ``none``; landmarks the map lacks that the
run assigns observations to (added ones) are estimated in every mode.

    problem = problem_from_run(dataset, run)          # checks that the two belong together
    result = smooth(problem, initial_poses(dataset, run), SmootherConfig())

Model card
----------
Variables   T_k = (R_k, t_k), k = 0..N-1, robot poses in the world frame. T_0 is FIXED at the
            dataset's start pose (it also fixes the frame when no map does); the unknowns are
            the other N-1 poses, 6 (N-1) numbers, then the L landmark variables l_j, 3 L
            (world frame, metres; none under ``exact`` with a complete map).
Update      right perturbation delta_k = (dt, dtheta), body frame, metres and radians:
            ``R_k <- R_k Exp(dtheta)``, ``t_k <- t_k + R_k dt`` (``geometry.retract_right``): the
            noise convention of ``camloc.models`` (SO(3) x R^3); a landmark ``l_j <- l_j + dl``.
Odometry    one factor per edge (a, b) with measured increment dT = T_a^-1 T_b Exp(w):
              E = dT^-1 T_a^-1 T_b,    r = (t(E), Log(R(E)))                          (6,)
            whitened by the edge's covariance ``dataset.odom_cov`` (already in (translation,
            rotation vector)): ``r_w = L^-1 r`` with ``cov = L L^T`` (Cholesky).
Observation one factor per observation the run ACCEPTED (``associations.csv`` landmark set):
              r = z - h(T_k, l),   h = project(camera_points(T_k, T_robot_camera, l))   (3,)
            whitened by ``dataset.obs_cov`` the same way. Rejected observations are not used.
            l is the map's landmark where held, else the variable.
Tag         a tag's orientation (``EDGE_PROJECT_TAG``, ``camloc.tags``), a factor of its own
            beside its position's where the map holds the tag (``map = "exact"``):
              r = Log(R_meas^T R_pred),   R_pred = R_c^T R_k^T R_tag                       (3,)
            whitened by its covariance (a rotation vector in the tag's frame); under ``prior``
            or ``none`` the tag's orientation is not estimated, and its position alone is used.
Map prior   under ``prior``, one factor per observed mapped landmark:
              r = (l_j - l_map) / sigma                                                (3,)
            isotropic, ``sigma = SmootherConfig.map_sigma`` (metres); not robustified.
Loss        ``cost = 1/2 sum_odometry |r_w|^2 + 1/2 sum_observations rho(|r_w|^2)`` (scipy's
            ``least_squares`` convention, 1/2 in front), with Huber's
            ``rho(s) = s`` for ``s <= f^2`` and ``2 f sqrt(s) - f^2`` beyond: an observation
            whose Mahalanobis distance exceeds ``f`` (``SmootherConfig.huber``) pulls with a
            constant force instead of a growing one. The loss acts on each observation's
            whitened 3-vector (its Mahalanobis distance, as g2o's robust kernels), not on each
            component, so that it does not depend on the image axes. Odometry is not robustified:
            it is the chain that holds the problem together, and a wrong association shows up
            as an observation residual, not as an odometry one.
Jacobians   with ``p = R_a^T (t_b - t_a)``, ``R_ab = R_a^T R_b``, ``Jr`` the right Jacobian of SO(3):
              dr/d(dt_a, dth_a) = [[-R_dT^T, R_dT^T [p]x], [0, -Jr^-1(r_th) R_ab^T]]
              dr/d(dt_b, dth_b) = [[R_dT^T R_ab, 0],     [0,  Jr^-1(r_th)]]
              dr_obs/d(dt, dth) = -P(p_cam) R_c^T [-I, [p_robot]x]
              dr_obs/dl = -P(p_cam) R_c^T R^T,      dr_prior/dl = I / sigma
              dr_tag/d(dt, dth) = [0, Jr^-1(r) H_R],  H_R = -R_tag^T R_k    (R_pred -> R_pred Exp(H_R dth))
            (P the projection Jacobian); all checked against central finite differences on the
            manifold in tests/test_smoother.py and tests/test_smoother_landmarks.py.
Solver      re-linearize until the largest step component is below ``step_tolerance``. The first
            step is iteratively reweighted Gauss-Newton (IRLS, weights rho'(s)): its model lies
            above the robust cost, safe far from the solution. Later steps use the Gauss-Newton
            Hessian of the robust cost itself (``normal_equations(newton=True)``), which converges
            quadratically where IRLS creeps (50 iterations were not enough on 20,000 poses, 8
            are now). That Hessian is flat along the residual of each observation beyond the
            threshold, so a landmark whose observations all lie beyond it (no map to hold it)
            has a model whose minimum can be metres past the cost's; each landmark's part of a
            step is therefore cut to the minimum of its own linearized robust cost along it,
            the poses' part kept (``camloc.landmark_steps``; 20,000 planar poses with no map:
            35 iterations, most steps rejected, before; 11 now). For the same reason the Newton
            step can carry an observation beyond the threshold past the apex of its cone, where
            the cost rises again and the model keeps falling (``camloc.huber_apex``; no map: poses
            and landmarks that only those observations hold); such a step is solved again with
            those observations' IRLS rows, whose model stops at the apex (conjugate gradients on
            the step's factor), and the cheaper of the two is taken (20,000 3-D poses with no map:
            20 iterations, five Newton steps rejected in a row, before; 10 now). A step that does
            not lower the cost is retried as IRLS, then with Levenberg-Marquardt damping, on
            Nielsen's schedule (``_damping_after_accepted``: by the gain ratio after a step taken,
            doubling factors after each rejection). Where Gauss-Newton's steps shrink only
            linearly (one over half the last: the residuals' second derivatives matter along a
            weakly determined direction, a landmark seen twice at low parallax), the exact Newton
            step is tried beside it (``camloc.newton_cg``: CG on Hessian-vector products differenced
            from the exact gradient, preconditioned with the step's factor) and the cheaper taken
            (monocular aerial worlds with no map: 24-107 iterations before, 15-40 now, the same
            minima; docs/performance.md, 2026-12-05 (night)).
            A 3-D landmark farther than a metre from its
            cameras has its step measured in inverse depth for the stopping rule (``_step_size``),
            and one whose rays part until they no longer place it (its minimum at infinity) is
            left out during the solve as at the start (``_receded``). The
            normal matrix is scaled to unit diagonal (Jacobi) and factored by a sparse Cholesky (CHOLMOD's supernodal, ``camloc.cholesky``); with
            landmark variables, each landmark's 3x3 block is eliminated first (its Schur
            complement, ``camloc.schur``) and the Cholesky factors the reduced pose system. Near
            the solution a step is solved by conjugate gradients preconditioned with the last
            factor (``_PRECONDITIONER_REUSE``). Before the first step the graph is checked for
            poses tied to nothing and the matrix's 1-norm condition number is estimated, and a
            problem that does not determine every pose (and landmark) is refused with a
            ``CamlocError`` instead of solved (one so near singular that the factorization finds
            no positive pivot is refused there, naming that unknown). A landmark variable whose
            own observations do not place it (a
            single pixel ray, rays of under ~0.006 degrees of parallax) and that no prior holds
            is left out with its observations and named (``undetermined_landmarks``), not
            refused: an online map adds such landmarks as a matter of course. A step whose
            Newton system cannot be factored (a landmark whose observations are all beyond the
            Huber threshold) is retried as IRLS, then damped; a landmark whose own block of the
            Newton Hessian is singular (its observations all beyond the threshold, their residuals
            on one line: a planar marker seen twice) keeps its observations' IRLS rows in it
            (``newton_equations``), so that the step and the covariances go through.
Planar      ``camloc.smoother_se2.PlanarProblem`` is this problem with SE(2) poses: ``smooth`` calls
            the problem's own ``linearize``, ``retract``, ``lifted``, ``landmark_information`` and
            ``reported_landmarks``; the solver, the Schur complement and the covariances are shared.
Covariance  of the landmark variables: the landmark blocks of the inverse Gauss-Newton Hessian of
            the robust cost at the solution, by the Schur complement and selected inversion of
            the reduced system's Cholesky factor (``camloc.selected_inverse``, on the factor's
            own supernodal pattern), never a dense inverse.

Pure: no I/O, no printing.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, ClassVar, Optional

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import LinearOperator, onenormest

from camloc import geometry, measurement, tags
from camloc.cholesky import NotPositiveDefinite
from camloc.dataset import Dataset, on_the_floor
from camloc.dataset_summary import odometry_positions
from camloc.errors import CamlocError, ConfigError
from camloc.huber_apex import past_apex
from camloc.landmark_steps import OBS_DIM, landmark_step_lengths, row_landmarks
from camloc.newton_cg import conjugate_gradients, newton_step
from camloc.observation_space import landmark_rows
from camloc.results import UNASSOCIATED, LandmarkMap, RunResult
from camloc.schur import LANDMARK_DOF, SchurSolver, factor, landmark_blocks
from camloc.smoother_landmarks import (MAP_MODES, LandmarkEstimate, LandmarkVariables, initial_positions,
                                       landmark_variables)

POSE_DOF = 6
# Predicted depths below this (metres) put a landmark behind the camera: no projection exists.
MIN_DEPTH = 1e-6
# Largest Levenberg-Marquardt damping (on a unit-diagonal normal matrix) before giving up on
# lowering the cost: the current poses are then a minimum to working precision.
_MAX_DAMPING = 1e8
# The damping a step that even IRLS could not make cheaper starts from, and the one below which a
# taken step's damping is dropped for plain Newton steps (``_damping_after_accepted``).
_FIRST_DAMPING = 1e-4
_MIN_DAMPING = 1e-9
# A landmark variable whose own 3x3 information block (its observations and prior, the poses
# held) has a larger condition number is left out: its rays meet at under about 0.006 degrees
# (condition ~ 1 / parallax^2), so its depth is a guess, and it would spoil the whole system's.
_MAX_LANDMARK_CONDITION = 1e8
# With landmark variables, the landmarks' covariances reuse the last Newton factor while the
# poses and landmarks have moved less than this since it was made (metres or radians, the steps'
# largest components added): its Hessian then differs from the current one by about that share
# (lever arms of a metre), far below what the Laplace approximation itself leaves out, and near
# the solution a factor costs 4 s at 20,000 poses (there the last factor is made 1.4 mm before the
# solution: the preconditioned steps finish the descent).
_FACTOR_REUSE = 5e-3
# ... and a Newton step is solved with it (conjugate gradients, ``_preconditioned_step``: to the
# same tolerance as a direct solve, so the minimum reached is the same) while they have moved less
# than this: a preconditioner a few centimetres away still converges in a few iterations, and one
# that does not falls back to a new factor (20,000 poses under a prior: 4 factorizations, not 6,
# with the convergence below).
_PRECONDITIONER_REUSE = 1e-2
# A step not IRLS's larger than this share of the last one taken: Gauss-Newton converging linearly
# (quadratic convergence shrinks them faster), where the exact Newton step is tried beside it
# (``_exact_newton_step``). At 0.5 the 3-D depth worlds of ``benchmarks/smooth_worlds.py`` never try
# it and take the same steps as before; tried at every step (0), 1-4 fewer iterations, 3-70% more CPU.
_LINEAR_RATE = 0.5


@dataclass(frozen=True)
class SmootherConfig:
    """Options of the smoother.

    Attributes
    ----------
    huber : Huber threshold ``f`` on each observation's Mahalanobis distance (whitened units,
        scipy's ``f_scale``); ``inf`` gives plain least squares. Default 2.0, chosen on simulated
        worlds (``benchmarks/smooth_huber.py``: 3 trajectory types x 3 noise settings x 5
        seeds; 2.0 and 2.5 tie best, 1.0 and inf are worse by 2%). A correct association lies
        beyond 2 with probability 0.26 (chi2, 3 dof) and is then only mildly down-weighted; a
        wrong one, 10 or more away, loses most of its pull.
    max_iterations : linearizations at most.
    step_tolerance : converged when the largest component of a step is below it (metres or
        radians; a 3-D landmark's beyond a metre from its cameras in inverse depth: radians
        across its rays, 1/m along them).
    max_condition : largest accepted 1-norm condition estimate of the Jacobi-scaled normal
        matrix; beyond it the data do not determine every pose (machine epsilon is 2.2e-16, so
        1e14 leaves about two significant digits in the worst direction).
    map : how the map's landmarks are held (``camloc.smoother_landmarks``): ``exact`` (fixed at
        the map), ``prior`` (estimated, pulled toward the map with ``map_sigma``) or ``none``
        (estimated from the observations alone). Landmarks the map lacks are estimated in all three.
    map_sigma : the map prior's standard deviation per axis, metres (``map = "prior"``).
    """

    huber: float = 2.0
    max_iterations: int = 50
    step_tolerance: float = 1e-7
    max_condition: float = 1e14
    map: str = "exact"
    map_sigma: float = 0.1

    def validate(self) -> None:
        """Raise ConfigError naming the first option out of range."""
        if not self.huber > 0.0:
            raise ConfigError(f"huber must be > 0 (or inf for plain least squares), got {self.huber}")
        if int(self.max_iterations) != self.max_iterations or self.max_iterations < 1:
            raise ConfigError(f"max_iterations must be an integer >= 1, got {self.max_iterations}")
        if not self.step_tolerance > 0.0:
            raise ConfigError(f"step_tolerance must be > 0, got {self.step_tolerance}")
        if not self.max_condition > 1.0:
            raise ConfigError(f"max_condition must be > 1, got {self.max_condition}")
        if self.map not in MAP_MODES:
            raise ConfigError(f"map must be one of {', '.join(MAP_MODES)}, got {self.map!r}")
        if not (self.map_sigma > 0.0 and math.isfinite(self.map_sigma)):
            raise ConfigError(f"map_sigma must be a finite number of metres > 0, got {self.map_sigma}")


@dataclass(frozen=True)
class SmoothingProblem:
    """The factor graph: N poses (the first fixed), E odometry factors, M observation factors.

    Attributes
    ----------
    pose_ids : (N,) int64 ids, for messages.
    T_start : (4, 4) the fixed first pose, world frame.
    odom_from, odom_to : (E,) int64 pose indices of each odometry factor.
    T_odometry : (E, 4, 4) measured increments ``T_from^-1 T_to``.
    odom_whiten : (E, 6, 6) ``L^-1`` with ``L L^T`` the covariance of (translation, rotation
        vector) of the increment.
    obs_pose : (M,) int64 index of the observing pose.
    obs_T_robot_camera : (M, 4, 4) camera mount of each observation.
    obs_intrinsics : (M, 4) fx, fy, cx, cy.
    obs_landmark_xyz : (M, 3) the associated landmark, world frame, metres, where it is held fixed
        (``obs_landmark`` < 0); the others' rows are not read.
    obs_z : (M, 3) the measurements (``camloc.measurement``'s layout: u, v, then depth, inverse
        depth or a pixel's inert 0).
    obs_whiten : (M, 3, 3) ``L^-1`` of the observation covariance.
    obs_row : (M,) int64 index of each observation in the dataset (for messages and reports).
    obs_kind : (M,) int64 each measurement's kind (``camloc.measurement``); None: depth.
    landmarks : the landmarks estimated with the poses (``camloc.smoother_landmarks``); None:
        every landmark is held at ``obs_landmark_xyz``.
    obs_landmark : (M,) int64 the variable landmark (index into ``landmarks``) of each
        observation, -1 where its landmark is held fixed; None: all are fixed.
    obs_tag_rotation : (M, 3, 3) the world orientation of each observation's tag, read where
        the observation is a tag's orientation (``measurement.TAG_ROTATION``, ``camloc.tags``); None: none is.
    """

    pose_ids: np.ndarray
    T_start: np.ndarray
    odom_from: np.ndarray
    odom_to: np.ndarray
    T_odometry: np.ndarray
    odom_whiten: np.ndarray
    obs_pose: np.ndarray
    obs_T_robot_camera: np.ndarray
    obs_intrinsics: np.ndarray
    obs_landmark_xyz: np.ndarray
    obs_z: np.ndarray
    obs_whiten: np.ndarray
    obs_row: np.ndarray
    obs_kind: np.ndarray | None = None
    landmarks: LandmarkVariables | None = None
    obs_landmark: np.ndarray | None = None
    obs_tag_rotation: np.ndarray | None = None

    @property
    def num_poses(self) -> int:
        return int(self.pose_ids.shape[0])

    @property
    def num_landmarks(self) -> int:
        """Landmark variables (0 when every landmark is held fixed)."""
        return 0 if self.landmarks is None else len(self.landmarks)

    # a pose's unknowns (its right perturbation); ``camloc.smoother_se2.PlanarProblem``'s: 3
    pose_dof: ClassVar[int] = POSE_DOF

    @property
    def num_pose_unknowns(self) -> int:
        return self.pose_dof * (self.num_poses - 1)

    @property
    def num_unknowns(self) -> int:
        """Poses' 6 (N - 1), then the landmark variables' 3 L: the columns of the Jacobian."""
        return self.num_pose_unknowns + LANDMARK_DOF * self.num_landmarks

    def observed_xyz(self, X: np.ndarray | None) -> np.ndarray:
        """(M, 3) each observation's landmark: the fixed ones from ``obs_landmark_xyz``, the
        variables from X (L, 3)."""
        if self.obs_landmark is None or X is None:
            return self.obs_landmark_xyz
        xyz = self.obs_landmark_xyz.copy()
        variable = self.obs_landmark >= 0
        xyz[variable] = X[self.obs_landmark[variable]]
        return xyz

    # The model's own operations, which ``smooth`` calls (a planar problem overrides them):
    @property
    def start_state(self) -> np.ndarray:
        """The fixed first pose in the form ``smooth``'s poses take: (4, 4)."""
        return self.T_start

    def lifted(self, T: np.ndarray) -> np.ndarray:
        """Poses (..., 4, 4) of states T: here poses already."""
        return T

    def linearize(self, T: np.ndarray, X: np.ndarray | None = None) -> "Linearization":
        return linearize(self, T, X)

    def retract(self, T: np.ndarray, X: np.ndarray | None, step: np.ndarray):
        return _retract(self, T, X, step)

    def landmark_information(self, T: np.ndarray) -> np.ndarray:
        """(L, 3, 3) each landmark variable's information from its own observations at poses T and
        its map prior (the poses held): ``sum J' J`` of the whitened landmark Jacobians."""
        rows = np.flatnonzero(self.obs_landmark >= 0)
        J = self.obs_whiten[rows] @ self.landmark_jacobians(T, rows)
        blocks = np.zeros((len(self.landmarks), LANDMARK_DOF, LANDMARK_DOF))
        np.add.at(blocks, self.obs_landmark[rows], np.swapaxes(J, 1, 2) @ J)
        return blocks + self.prior_information()

    def landmark_jacobians(self, T: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(R, d, 3) the observations ``rows``' Jacobians by their landmark variable, at poses T."""
        lm = self.landmarks
        _, _, J, _ = observation_factors(T[self.obs_pose[rows]], self.obs_T_robot_camera[rows], self.obs_intrinsics[rows],
                                         lm.xyz[self.obs_landmark[rows]], self.obs_z[rows],
                                         None if self.obs_kind is None else self.obs_kind[rows])
        return J

    def prior_information(self) -> np.ndarray:
        """(L, 3, 3) the information of each landmark variable's map prior (zero without one)."""
        lm = self.landmarks
        return np.where(lm.has_prior, 1.0 / lm.prior_sigma**2, 0.0)[:, None, None] * np.eye(LANDMARK_DOF)

    def reported_landmarks(self, estimate: LandmarkEstimate) -> LandmarkEstimate:
        """The landmark variables' estimate as ``map.csv`` takes it: positions, as they are here."""
        return estimate


@dataclass(frozen=True)
class Iteration:
    """One linearization, for progress reports: its number, the cost after it, the largest
    step component (m or rad, NaN for a rejected step), the damping and whether it was taken."""

    number: int
    cost: float
    max_step: float
    damping: float
    accepted: bool


IterationCallback = Callable[[Iteration], None]


@dataclass(frozen=True)
class SmoothingResult:
    """The smoothed trajectory and how it was found.

    Attributes
    ----------
    T_world_robot : (N, 4, 4) the MAP poses, world frame; the first is the fixed start pose.
    iterations : linearizations done (accepted and rejected steps).
    converged : the last step was below ``step_tolerance`` (or no step could lower the cost).
    initial_cost, final_cost : the robust cost (see the model card) before and after.
    condition : 1-norm condition estimate of the Jacobi-scaled normal matrix at the start.
    odometry_factors, observation_factors : factors used.
    dropped_observations : accepted observations left out because their landmark is behind the
        camera at the initial poses (no projection exists there).
    downweighted_observations : observations beyond the Huber threshold at the solution.
    seconds : wall time of the optimization (the landmarks' covariances included).
    landmarks : the landmark variables' estimate and marginal covariance; None when every
        landmark was held at the map.
    undetermined_landmarks : (U,) ids of landmark variables left out with their observations:
        their observations do not place them (a single pixel ray, too little parallax) and no
        map prior holds them.
    """

    T_world_robot: np.ndarray
    iterations: int
    converged: bool
    initial_cost: float
    final_cost: float
    condition: float
    odometry_factors: int
    observation_factors: int
    dropped_observations: int
    downweighted_observations: int
    seconds: float
    landmarks: LandmarkEstimate | None = None
    undetermined_landmarks: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def xyz(self) -> np.ndarray:
        """(N, 3) positions, world frame, metres."""
        return self.T_world_robot[:, :3, 3].copy()

    @property
    def quat_xyzw(self) -> np.ndarray:
        """(N, 4) orientations, scalar last, qw >= 0."""
        return geometry.matrix_to_quat(self.T_world_robot[:, :3, :3])


# --------------------------------------------------------------------------------------------
# Residuals and their Jacobians (unwhitened, batched)


def odometry_residuals(
    T_from: np.ndarray, T_to: np.ndarray, T_meas: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Odometry residuals ``(t(E), Log(R(E)))`` of ``E = dT^-1 T_a^-1 T_b`` and their Jacobians.

    Parameters
    ----------
    T_from, T_to : (E, 4, 4) poses a and b, world frame.
    T_meas : (E, 4, 4) the measured increments dT (b in the frame of a).

    Returns
    -------
    r : (E, 6) translation (metres) then rotation vector (radians).
    J_from, J_to : (E, 6, 6) dr / d(dt, dtheta) of the right perturbation of a and of b.
    """
    R_a, t_a = T_from[:, :3, :3], T_from[:, :3, 3]
    R_b, t_b = T_to[:, :3, :3], T_to[:, :3, 3]
    R_d_T = np.swapaxes(T_meas[:, :3, :3], 1, 2)
    R_a_T = np.swapaxes(R_a, 1, 2)
    R_ab = R_a_T @ R_b
    p = np.einsum("nij,nj->ni", R_a_T, t_b - t_a)  # b's origin in a's frame
    r_t = np.einsum("nij,nj->ni", R_d_T, p - T_meas[:, :3, 3])
    r_theta = geometry.so3_log(R_d_T @ R_ab)
    Jr_inv = geometry.so3_right_jacobian_inverse(r_theta)

    J_from = np.zeros((len(r_t), 6, 6))
    J_from[:, 0:3, 0:3] = -R_d_T
    J_from[:, 0:3, 3:6] = R_d_T @ geometry.hat(p)  # Exp(-dth) p ~= p + [p]x dth
    # R_E Exp(-R_ab^T dth): the rotation of a reaches E's right side through R_ab.
    J_from[:, 3:6, 3:6] = -Jr_inv @ np.swapaxes(R_ab, 1, 2)
    J_to = np.zeros_like(J_from)
    J_to[:, 0:3, 0:3] = R_d_T @ R_ab
    J_to[:, 3:6, 3:6] = Jr_inv
    return np.concatenate([r_t, r_theta], axis=1), J_from, J_to


def observation_residuals(
    T_pose: np.ndarray,
    T_robot_camera: np.ndarray,
    intrinsics: np.ndarray,
    landmark_xyz: np.ndarray,
    z_uvd: np.ndarray,
    kinds: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observation residuals ``z - h(T, l)`` and their Jacobians, one observation a row.

    Parameters
    ----------
    T_pose : (M, 4, 4) observing robot poses, world frame.
    T_robot_camera : (M, 4, 4) camera mounts.
    intrinsics : (M, 4) fx, fy, cx, cy.
    landmark_xyz : (M, 3) landmarks, world frame.
    z_uvd : (M, 3) measurements (``camloc.measurement``'s layout).
    kinds : (M,) their kinds; None: depth.

    Returns
    -------
    r : (M, 3) residuals (a pixel's inert third row: 0).
    J : (M, 3, 6) dr / d(dt, dtheta) of the right perturbation of the pose.
    depth : (M,) predicted depth (the model has no projection where it is not positive).
    """
    r, J_pose, _, depth = observation_factors(T_pose, T_robot_camera, intrinsics, landmark_xyz, z_uvd, kinds)
    return r, J_pose, depth


def observation_factors(
    T_pose: np.ndarray,
    T_robot_camera: np.ndarray,
    intrinsics: np.ndarray,
    landmark_xyz: np.ndarray,
    z_uvd: np.ndarray,
    kinds: np.ndarray | None = None,
    tag_rotation: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``observation_residuals`` and also the Jacobian with respect to the landmark.
    ``tag_rotation`` (M, 3, 3): the tags' world orientations, for the rows that are a tag's
    orientation (``_tag_orientations``).

    Returns
    -------
    r, J_pose, depth : as ``observation_residuals``.
    J_landmark : (M, 3, 3) dr / dl, l the landmark's world position: ``-P R_c^T R^T``.
    """
    R, t = T_pose[:, :3, :3], T_pose[:, :3, 3]
    R_c_T = np.swapaxes(T_robot_camera[:, :3, :3], 1, 2)
    # The same arithmetic as models.camera_points, one pose and camera per row.
    p_robot = np.einsum("nji,nj->ni", R, landmark_xyz - t)
    p_camera = np.einsum("nij,nj->ni", R_c_T, p_robot - T_robot_camera[:, :3, 3])
    depth = p_camera[:, 2]
    kinds = measurement.DEPTH if kinds is None else kinds
    with np.errstate(divide="ignore", invalid="ignore"):  # the measurement model, camloc.measurement's
        z_hat = measurement.project(p_camera, intrinsics.T, kinds)
        P = measurement.projection_jacobian(p_camera, intrinsics.T, kinds)
    dp_robot = np.empty((len(depth), 3, 6))
    dp_robot[:, :, 0:3] = -np.eye(3)  # R^T (l - t - R dt) = p_robot - dt
    dp_robot[:, :, 3:6] = geometry.hat(p_robot)  # Exp(-dth) p_robot ~= p_robot + [p_robot]x dth
    P_c = P @ R_c_T
    J_pose = -(P_c @ dp_robot)
    J_landmark = -(P_c @ np.swapaxes(R, 1, 2))  # p_robot = R^T (l - t)
    r = z_uvd - z_hat
    if tag_rotation is not None:
        _tag_orientations(r, J_pose, J_landmark, R, T_robot_camera, z_uvd, np.broadcast_to(kinds, depth.shape), tag_rotation)
    return r, J_pose, J_landmark, depth


def _tag_orientations(r, J_pose, J_landmark, R, T_robot_camera, z, kinds, tag_rotation) -> None:
    """The rows of ``observation_factors`` that are a tag's orientation (``TAG_ROTATION``; z its
    rotation vector), in place: ``r = Log(R_meas^T R_pred)`` with ``R_pred = R_c^T R^T R_tag``,
    ``dr/d(dt, dth) = [0, Jr^-1(r) H_R]`` (``tags.smoother_residual``), nothing for the landmark's
    position. The depth stays the tag centre's: a tag behind the camera is dropped whole."""
    rows = np.flatnonzero(kinds == measurement.TAG_ROTATION)
    if rows.size == 0:
        return
    R_pred, H_R = tags.prediction(R[rows], T_robot_camera[rows, :3, :3], tag_rotation[rows])
    r[rows], J_R = tags.smoother_residual(geometry.so3_exp(z[rows]), R_pred, H_R)
    J_pose[rows] = 0.0
    J_pose[rows, :, 3:6] = J_R
    J_landmark[rows] = 0.0


# --------------------------------------------------------------------------------------------
# The whitened, sparse system


def whitening(cov: np.ndarray) -> np.ndarray:
    """``L^-1`` (..., d, d) for covariances (..., d, d) = ``L L^T``: ``|L^-1 r|^2 = r^T cov^-1 r``.

    Raises
    ------
    CamlocError : a covariance that is not symmetric positive definite.
    """
    try:
        L = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise CamlocError("a factor's covariance is not positive definite: it cannot weigh its residual") from None
    return np.linalg.solve(L, np.broadcast_to(np.eye(cov.shape[-1]), cov.shape))


@dataclass(frozen=True)
class Linearization:
    """Whitened residuals and their sparse Jacobian at one set of poses (and landmarks).

    ``residual`` (6E + 3M + 3P,) is the odometry factors' residuals, then the observations', then
    the map priors', 6, 3 and 3 rows each; ``jacobian`` (6E + 3M + 3P, 6(N-1) + 3L) CSR, the
    poses' columns then the landmarks'; ``obs_sq`` (M,) each observation's squared Mahalanobis
    distance; ``odom_sq`` (E,) each odometry factor's; ``prior_sq`` (P,) each map prior's.
    """

    residual: np.ndarray
    jacobian: sp.csr_matrix
    odom_sq: np.ndarray
    obs_sq: np.ndarray
    prior_sq: np.ndarray = field(default_factory=lambda: np.zeros(0))
    odom_dim: int = POSE_DOF  # rows of an odometry residual (a planar robot's: 3)


def block_coo(first_row: np.ndarray, pose: np.ndarray, blocks: np.ndarray) -> tuple[np.ndarray, ...]:
    """COO triplets of dense blocks (F, d, p) at rows ``first_row + 0..d-1`` and the p columns of
    ``pose`` (index >= 1; pose 0 is fixed and has no columns, so its blocks are dropped); p the
    pose's unknowns (6, or a planar robot's 3)."""
    keep = pose > 0
    first_row, pose, blocks = first_row[keep], pose[keep], blocks[keep]
    d, dof = blocks.shape[1], blocks.shape[2]
    rows = np.broadcast_to(first_row[:, None, None] + np.arange(d)[None, :, None], blocks.shape)
    cols = np.broadcast_to(dof * (pose[:, None, None] - 1) + np.arange(dof)[None, None, :], blocks.shape)
    return rows.ravel(), cols.ravel(), blocks.ravel()


def landmark_coo(first_row: np.ndarray, first_col: np.ndarray, blocks: np.ndarray) -> tuple[np.ndarray, ...]:
    """COO triplets of dense blocks (F, d, 3) at rows ``first_row + 0..d-1``, columns ``first_col + 0..2``."""
    d = blocks.shape[1]
    rows = np.broadcast_to(first_row[:, None, None] + np.arange(d)[None, :, None], blocks.shape)
    cols = np.broadcast_to(first_col[:, None, None] + np.arange(LANDMARK_DOF)[None, None, :], blocks.shape)
    return rows.ravel(), cols.ravel(), blocks.ravel()


def linearize(problem: SmoothingProblem, T: np.ndarray, X: np.ndarray | None = None) -> Linearization:
    """Whitened residuals and the analytic sparse Jacobian of every factor at poses T (N, 4, 4)
    and landmark variables X (L, 3) (None: ``problem.landmarks.xyz``)."""
    p = problem
    if X is None and p.landmarks is not None:
        X = p.landmarks.xyz
    r_odom, J_from, J_to = odometry_residuals(T[p.odom_from], T[p.odom_to], p.T_odometry)
    r_obs, J_obs, J_lm, _ = observation_factors(T[p.obs_pose], p.obs_T_robot_camera, p.obs_intrinsics,
                                                p.observed_xyz(X), p.obs_z, p.obs_kind, p.obs_tag_rotation)
    # Whitening: r_w = L^-1 r and J_w = L^-1 J.
    r_odom = np.einsum("nij,nj->ni", p.odom_whiten, r_odom)
    r_obs = np.einsum("nij,nj->ni", p.obs_whiten, r_obs)
    J_from, J_to, J_obs = p.odom_whiten @ J_from, p.odom_whiten @ J_to, p.obs_whiten @ J_obs

    num_odom = len(p.odom_from)
    odom_rows = POSE_DOF * np.arange(num_odom)
    obs_rows = POSE_DOF * num_odom + OBS_DIM * np.arange(len(p.obs_pose))
    parts = [block_coo(odom_rows, p.odom_from, J_from), block_coo(odom_rows, p.odom_to, J_to),
             block_coo(obs_rows, p.obs_pose, J_obs)]
    residuals = [r_odom.ravel(), r_obs.ravel()]
    num_rows = POSE_DOF * num_odom + OBS_DIM * len(p.obs_pose)
    r_prior = np.zeros((0, LANDMARK_DOF))
    if p.num_landmarks:
        variable = np.flatnonzero(p.obs_landmark >= 0)
        first_col = p.num_pose_unknowns + LANDMARK_DOF * p.obs_landmark[variable]
        parts.append(landmark_coo(obs_rows[variable], first_col, p.obs_whiten[variable] @ J_lm[variable]))
        # The map prior r = (l - l_map) / sigma, J = I / sigma.
        held = np.flatnonzero(p.landmarks.has_prior)
        sigma = p.landmarks.prior_sigma[held]
        r_prior = (X[held] - p.landmarks.prior_xyz[held]) / sigma[:, None]
        prior_rows = num_rows + LANDMARK_DOF * np.arange(len(held))
        J_prior = np.eye(LANDMARK_DOF)[None] / sigma[:, None, None]
        parts.append(landmark_coo(prior_rows, p.num_pose_unknowns + LANDMARK_DOF * held, J_prior))
        residuals.append(r_prior.ravel())
        num_rows += LANDMARK_DOF * len(held)
    rows, cols, values = (np.concatenate(column) for column in zip(*parts))
    jacobian = sp.csr_matrix((values, (rows, cols)), shape=(num_rows, p.num_unknowns))
    return Linearization(
        residual=np.concatenate(residuals),
        jacobian=jacobian,
        odom_sq=np.einsum("ni,ni->n", r_odom, r_odom),
        obs_sq=np.einsum("ni,ni->n", r_obs, r_obs),
        prior_sq=np.einsum("ni,ni->n", r_prior, r_prior),
    )


def huber_rho(s: np.ndarray, f: float) -> np.ndarray:
    """Huber's rho of squared distances s (scipy's form): s within f^2, ``2 f sqrt(s) - f^2`` beyond."""
    s = np.asarray(s, dtype=float)
    beyond = s > f * f  # never true for f = inf
    rho = s.copy()
    rho[beyond] = 2.0 * f * np.sqrt(s[beyond]) - f * f
    return rho


def huber_weight(s: np.ndarray, f: float) -> np.ndarray:
    """rho'(s): 1 within the threshold, ``f / sqrt(s)`` beyond (the IRLS weight)."""
    s = np.asarray(s, dtype=float)
    beyond = s > f * f
    weight = np.ones_like(s)
    weight[beyond] = f / np.sqrt(s[beyond])
    return weight


def robust_cost(lin: Linearization, huber: float) -> float:
    """``1/2 (sum odom_sq + sum rho(obs_sq) + sum prior_sq)``; inf when a residual is not finite."""
    cost = 0.5 * (float(np.sum(lin.odom_sq)) + float(np.sum(huber_rho(lin.obs_sq, huber))) + float(np.sum(lin.prior_sq)))
    return cost if math.isfinite(cost) else math.inf


def _row_weights(lin: Linearization, huber: float) -> np.ndarray:
    return np.concatenate([np.ones(lin.odom_dim * len(lin.odom_sq)), np.repeat(huber_weight(lin.obs_sq, huber), OBS_DIM),
                           np.ones(LANDMARK_DOF * len(lin.prior_sq))])


def normal_equations(lin: Linearization, huber: float, *, newton: bool,
                     majorized: np.ndarray | None = None) -> tuple[sp.csc_matrix, np.ndarray]:
    """Normal equations ``H delta = -g`` of the robust cost at a linearization.

    ``g = J^T W r`` with ``W = rho'`` per row (the exact gradient). For H, ``newton=False`` gives
    IRLS's ``J^T W J``: a quadratic that lies above the linearized robust cost (Huber's rho is
    majorized by its tangent parabola), so its minimum always lowers the linearized cost.
    ``newton=True`` gives the Gauss-Newton Hessian of the robust cost itself (Triggs et al.,
    "Bundle adjustment - a modern synthesis", 2000, sec. 4.3): beyond the threshold rho is
    linear in the distance |r|, so an observation has no curvature along its own residual and
    contributes ``rho' J^T (I - u u^T) J`` with ``u = r / |r|``. Near the solution it converges
    quadratically where IRLS creeps (linear convergence, rate set by the share downweighted).
    ``majorized`` (M,) bool: observations whose IRLS rows are kept in the Newton Hessian
    (``newton_equations``).
    """
    weights = _row_weights(lin, huber)
    g = lin.jacobian.T @ (weights * lin.residual)
    sqrt_w = np.sqrt(weights)
    rows = sp.diags(sqrt_w)
    beyond = lin.obs_sq > huber * huber
    beyond = np.flatnonzero(beyond if majorized is None else beyond & ~majorized)
    if newton and beyond.size:
        # Project the whitened rows of each downweighted observation off its residual direction:
        # (sqrt(rho') P J)^T (sqrt(rho') P J) = rho' J^T P J since P = I - u u^T is a projector.
        first = lin.odom_dim * len(lin.odom_sq) + OBS_DIM * beyond
        u = lin.residual.reshape(-1)[first[:, None] + np.arange(OBS_DIM)] / np.sqrt(lin.obs_sq[beyond])[:, None]
        P = np.eye(OBS_DIM) - u[:, :, None] * u[:, None, :]
        P *= sqrt_w[first][:, None, None]
        index = first[:, None] + np.arange(OBS_DIM)
        plain = np.ones(len(sqrt_w), dtype=bool)
        plain[index.ravel()] = False
        r_idx = np.broadcast_to(index[:, :, None], P.shape).ravel()
        c_idx = np.broadcast_to(index[:, None, :], P.shape).ravel()
        projector = sp.coo_matrix((P.ravel(), (r_idx, c_idx)), shape=(len(sqrt_w),) * 2)
        rows = (projector + sp.diags(np.where(plain, sqrt_w, 0.0))).tocsr()
    J_w = rows @ lin.jacobian
    return (J_w.T @ J_w).tocsc(), g


def newton_equations(problem: SmoothingProblem, lin: Linearization, huber: float,
                     majorized: np.ndarray | None = None) -> tuple[sp.csc_matrix, np.ndarray]:
    """``normal_equations(newton=True)``, with the IRLS rows kept for the observations of every
    landmark variable whose own block of that Hessian is singular (condition beyond
    ``_MAX_LANDMARK_CONDITION``): all its observations beyond the Huber threshold with their
    residuals on one line (a marker seen twice, each pulling it half way: at such a minimum the
    two residuals are opposite), where the robust cost has no curvature along that line and the
    Newton step would be unbounded. The others keep the Newton rows (quadratic convergence), but
    for ``majorized`` (M,) bool (``_apex_limited_step``)."""
    H, g = normal_equations(lin, huber, newton=True)
    kept = np.zeros(len(lin.obs_sq), dtype=bool) if majorized is None else majorized.copy()
    if problem.num_landmarks:
        eig = np.linalg.eigvalsh(landmark_blocks(H, problem.num_pose_unknowns))
        flat = ~(eig[:, 0] > eig[:, 2] / _MAX_LANDMARK_CONDITION)
        kept |= (problem.obs_landmark >= 0) & flat[np.maximum(problem.obs_landmark, 0)]
    if not np.any(kept):
        return H, g
    return normal_equations(lin, huber, newton=True, majorized=kept)


# --------------------------------------------------------------------------------------------
# Is the problem determined?


def check_determined(problem: SmoothingProblem) -> None:
    """Refuse a graph in which some poses are tied neither to the start pose nor to the map.

    Poses are connected by odometry factors; every connected group that does not hold the fixed
    first pose needs observations of its own.

    Raises
    ------
    CamlocError : naming the poses of the first such group.
    """
    n = problem.num_poses
    graph = sp.coo_matrix((np.ones(len(problem.odom_from)), (problem.odom_from, problem.odom_to)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    observed = np.bincount(label[problem.obs_pose], minlength=label.max() + 1)
    for group in np.unique(label):
        if group == label[0] or observed[group] > 0:
            continue
        members = problem.pose_ids[label == group]
        listed = ", ".join(str(i) for i in members[:5]) + (", ..." if len(members) > 5 else "")
        if len(members) == 1:
            what = f"pose {members[0]} has no odometry edge to the other poses and no accepted observation"
        else:
            what = (f"{len(members)} poses ({listed}) are linked to each other but to neither the start pose "
                    "nor any landmark (no odometry edge reaches them, no accepted observation)")
        raise CamlocError(f"cannot smooth: {what}, so nothing determines where they are")


def _scaled(H: sp.csc_matrix) -> tuple[sp.csc_matrix, np.ndarray]:
    """``D H D`` with unit diagonal (``D = diag(H)^-1/2``) and the scale d."""
    diag = H.diagonal()
    d = 1.0 / np.sqrt(diag)
    D = sp.diags(d)
    return (D @ H @ D).tocsc(), d


def _factorization(Hs: sp.csc_matrix, num_pose: int, damping: float = 0.0):
    """A factor of ``Hs + damping I`` with a ``solve``: the sparse Cholesky of the whole matrix
    when every unknown is a pose, else of the reduced system left by the landmarks' Schur complement.

    Raises
    ------
    np.linalg.LinAlgError : a pose system or a landmark block that is not positive definite.
    """
    if Hs.shape[0] == num_pose:
        if damping > 0.0:
            Hs = (Hs + damping * sp.identity(Hs.shape[0], format="csc")).tocsc()
        return factor(Hs)
    return SchurSolver(Hs, num_pose, damping)


def condition_estimate(Hs: sp.csc_matrix, lu) -> tuple[float, int]:
    """1-norm condition estimate ``|Hs|_1 |Hs^-1|_1`` (Higham's estimator) and the column of
    ``Hs^-1`` with the largest norm: the worst-determined unknown."""
    inverse = LinearOperator(Hs.shape, matvec=lu.solve, rmatvec=lambda v: lu.solve(v, trans="T"), dtype=float)
    estimate, column = onenormest(inverse, compute_v=True)
    norm = float(abs(Hs).sum(axis=0).max())
    return norm * float(estimate), int(np.argmax(np.abs(column)))


def _unknown_name(problem: SmoothingProblem, column: int) -> str:
    """``pose <id>`` or ``landmark <id>``: what the normal matrix's ``column`` belongs to."""
    if column < problem.num_pose_unknowns:
        return f"pose {problem.pose_ids[column // problem.pose_dof + 1]}"
    return f"landmark {problem.landmarks.ids[(column - problem.num_pose_unknowns) // LANDMARK_DOF]}"


def _check_conditioning(problem: SmoothingProblem, H: sp.csc_matrix, config: SmootherConfig) -> float:
    return _conditioned_factor(problem, H, config)[0]


def _conditioned_factor(problem: SmoothingProblem, H: sp.csc_matrix, config: SmootherConfig):
    """The condition estimate of the scaled H and its factor (the first step's, reused), or a
    CamlocError naming the worst-determined pose or landmark."""
    unknowns = problem.num_unknowns
    diag = H.diagonal()
    empty = np.flatnonzero(~(diag > 0.0))
    if empty.size:
        raise CamlocError(f"cannot smooth: no factor constrains {_unknown_name(problem, empty[0])} "
                          "(its normal-matrix block is zero)")
    Hs, _ = _scaled(H)
    what = "pose" if not problem.num_landmarks else "pose and landmark"
    try:
        lu = _factorization(Hs, problem.num_pose_unknowns)
    except np.linalg.LinAlgError as error:
        # The sparse Cholesky names where elimination found no positive pivot (the reduced
        # system's unknowns are H's first ones); a landmark's own 3x3 block does not.
        at = f" (no positive pivot at {_unknown_name(problem, error.index)})" if isinstance(error, NotPositiveDefinite) else ""
        raise CamlocError(
            f"cannot smooth: the normal matrix ({unknowns} unknowns) is singular or nearly so{at}: the odometry and "
            f"the accepted observations do not determine every {what}"
        ) from None
    condition, worst = condition_estimate(Hs, lu)
    if not condition <= config.max_condition:
        raise CamlocError(
            f"cannot smooth: the normal matrix is rank deficient or nearly so (condition estimate {condition:.2g}, "
            f"largest accepted {config.max_condition:.2g}): the data do not determine every {what}; worst "
            f"determined: {_unknown_name(problem, worst)}"
        )
    return condition, lu


# --------------------------------------------------------------------------------------------
# Gauss-Newton / Levenberg-Marquardt


def _solve_step(H: sp.csc_matrix, g: np.ndarray, damping: float, num_pose: int | None = None, *,
                factored=None) -> np.ndarray:
    """The step (6(N-1) + 3L,) of ``(H + damping diag(H)) delta = -g``, in the Jacobi-scaled
    form; ``num_pose`` the poses' unknowns (None: all), the landmarks' eliminated first;
    ``factored`` a factor of this scaled H and damping made already (``_factorization``)."""
    Hs, d = _scaled(H)
    try:
        lu = factored or _factorization(Hs, Hs.shape[0] if num_pose is None else num_pose, damping)
    except np.linalg.LinAlgError:
        raise CamlocError("cannot smooth: the normal matrix became singular during the iterations") from None
    return d * lu.solve(-d * g)


def _retract_all(T: np.ndarray, step: np.ndarray) -> np.ndarray:
    moved = T.copy()
    moved[1:] = geometry.retract_right(T[1:], step.reshape(-1, POSE_DOF))
    return moved


def _retract(problem: SmoothingProblem, T: np.ndarray, X: np.ndarray | None, step: np.ndarray):
    """Poses moved by the step's pose part (right perturbation), landmarks by the rest (added)."""
    n = problem.num_pose_unknowns
    if X is None:
        return _retract_all(T, step), None
    return _retract_all(T, step[:n]), X + step[n:].reshape(-1, LANDMARK_DOF)


def smooth(
    problem: SmoothingProblem,
    T_initial: np.ndarray,
    config: Optional[SmootherConfig] = None,
    *,
    on_iteration: Optional[IterationCallback] = None,
) -> SmoothingResult:
    """The MAP poses (and landmark variables) of ``problem``, starting from ``T_initial``.

    Parameters
    ----------
    problem : the factor graph (``problem_from_run`` builds it from a dataset and a run).
    T_initial : (N, 4, 4) initial poses, world frame (the filter's estimate); the first is
        replaced by the fixed start pose. Landmark variables start at ``problem.landmarks.xyz``,
        or from their observations at these poses where it is NaN.
    config : options; None = ``SmootherConfig()``.
    on_iteration : called after every linearization with an ``Iteration``.

    Raises
    ------
    CamlocError : a pose group that nothing determines, or an ill-conditioned normal matrix.
    ConfigError : an option out of range.
    """
    config = config or SmootherConfig()
    config.validate()
    started = time.perf_counter()
    T = np.array(T_initial, dtype=float)
    T[0] = problem.start_state
    problem, undetermined = _with_initial_landmarks(problem, T)
    problem, dropped = _without_unprojectable(problem, T)
    problem, weak = _without_undetermined_landmarks(problem, T)
    check_determined(problem)

    X = None if problem.landmarks is None else problem.landmarks.xyz
    T, X, lin, cost, initial_cost, counts = _minimize(problem, T, X, config, on_iteration)
    while counts.get("receded") is not None:
        # A landmark receded until its rays no longer place it (its minimum at infinity): left out
        # as one undetermined from the start would be (``_receded``), the rest solved on from here.
        problem, receded = counts["receded"]
        weak, X = np.concatenate([weak, receded]), problem.landmarks.xyz if problem.num_landmarks else None
        T, X, lin, cost, _, counts = _minimize(problem, T, X, config, on_iteration, start=counts)
    landmarks = _landmark_estimate(problem, lin, X, config, counts["factor"]) if problem.num_landmarks else None
    return SmoothingResult(
        T_world_robot=problem.lifted(T),
        iterations=counts["iterations"],
        converged=counts["converged"],
        initial_cost=initial_cost,
        final_cost=cost,
        condition=counts["condition"],
        odometry_factors=int(len(problem.odom_from)),
        observation_factors=int(len(problem.obs_pose)),
        dropped_observations=dropped,
        downweighted_observations=int(np.count_nonzero(lin.obs_sq > config.huber * config.huber)),
        seconds=time.perf_counter() - started,
        landmarks=None if landmarks is None else problem.reported_landmarks(landmarks),
        undetermined_landmarks=np.concatenate([undetermined, weak]),
    )


@dataclass
class _Descent:
    """Where the Gauss-Newton / Levenberg-Marquardt loop (``_minimize``) is: the poses, landmarks,
    their linearization and cost, and how the next step is to be made."""

    T: np.ndarray
    X: np.ndarray | None
    lin: Linearization
    cost: float
    iterations: int
    condition: float
    converged: bool
    damping: float = 0.0  # Levenberg-Marquardt's, on the unit-diagonal matrix (0: none)
    growth: float = 2.0  # its factor after the next rejection
    majorize: bool = True  # the next step is IRLS's (the first is)
    receded: Optional[tuple] = None  # ``_receded``'s problem and ids where a landmark stopped the loop
    factor: Optional[tuple] = None  # the last undamped Newton matrix's factor and scale
    moved: float = math.inf  # how far T moved since that factor was made
    last_step: float = 0.0  # the largest component of the last step taken that was not IRLS's (0: none)

    @property
    def newton(self) -> bool:
        """Whether the next step is a plain Newton step (undamped, not IRLS)."""
        return self.damping == 0.0 and not self.majorize


def _minimize(problem, T, X, config, on_iteration, start: dict | None = None):
    """The Gauss-Newton / Levenberg-Marquardt loop (model card, "Solver"): the poses and
    landmarks at the end, their linearization and cost, the initial cost, and the counts (with
    ``factor``: the scaled factor and scale of the last step when it was a plain Newton step;
    ``receded``: ``_receded``'s problem and ids where a landmark stopped it). ``start``: the counts
    of the loop this one goes on from (its iterations and condition)."""
    lin = problem.linearize(T, X)
    initial_cost = robust_cost(lin, config.huber)
    iterations, condition = (0, math.nan) if start is None else (start["iterations"], start["condition"])
    at = _Descent(T, X, lin, initial_cost, iterations, condition, converged=problem.num_unknowns == 0)
    # the landmark each Jacobian row touches: its sparsity is the problem's, the same at every iteration
    rows = row_landmarks(lin.jacobian, problem.num_pose_unknowns) if problem.num_landmarks else None
    while not at.converged and at.iterations < config.max_iterations:
        if at.majorize:
            H, g = normal_equations(at.lin, config.huber, newton=False)
        else:
            H, g = newton_equations(problem, at.lin, config.huber)
        steps = _proposed_steps(problem, at, H, g, config)
        at.iterations += 1
        step, candidate = _cheapest(problem, at, steps, config.huber, rows)
        accepted, max_step = _take_or_refuse(problem, at, H, g, step, candidate, config)
        if on_iteration is not None:
            on_iteration(Iteration(at.iterations, at.cost, max_step if accepted else math.nan, at.damping, accepted))
        if at.receded is not None:
            break
    # The covariances may use that factor where T moved too little since for its Hessian to differ.
    counts = {"iterations": at.iterations, "converged": bool(at.converged), "condition": at.condition,
              "factor": at.factor if at.converged and at.moved < _FACTOR_REUSE else None, "receded": at.receded}
    return at.T, at.X, at.lin, at.cost, initial_cost, counts


def _proposed_steps(problem, at: _Descent, H: sp.csc_matrix, g: np.ndarray, config: SmootherConfig) -> list:
    """This iteration's step from the normal equations (H, g), then the alternatives tried beside
    it: the Newton step stopped at the apexes it passes (``_apex_limited_step``), or else, where
    the steps shrink only linearly, the exact Newton step (``_exact_newton_step``); none where the
    Newton system cannot be factored (``_SingularStep``: the step counts as rejected)."""
    num_pose = problem.num_pose_unknowns if problem.num_landmarks else problem.num_unknowns
    Hs, d = _scaled(H)
    try:
        step, used = None, None
        if problem.num_landmarks and at.moved < _PRECONDITIONER_REUSE and at.newton:
            step, used = _preconditioned_step(Hs, d, g, at.factor), at.factor
        if step is None:
            if at.iterations == 0:  # the first step reuses the condition check's factor
                at.condition, lu = _conditioned_factor(problem, H, config)
            else:
                lu = _step_factor(Hs, num_pose, at.damping)
            step, used = d * lu.solve(-d * g), (lu, d)
            if at.newton:
                at.factor, at.moved = used, 0.0
        limited = _apex_limited_step(problem, at.lin, step, used, config.huber, num_pose) if at.newton else None
    except _SingularStep:
        # The Newton Hessian of a landmark whose observations are all beyond the Huber
        # threshold can lose rank along their residuals: a rejected step, retried as IRLS
        # (positive definite where the observations determine the landmark), then damped.
        return []
    if limited is not None:
        return [step, limited]
    if not at.majorize and at.last_step > 0.0 and float(np.max(np.abs(step))) > _LINEAR_RATE * at.last_step:
        exact = _exact_newton_step(problem, at, g, config.huber, used)
        return [step] if exact is None else [step, exact]
    return [step]


def _cheapest(problem, at: _Descent, steps: list, huber: float, rows) -> tuple:
    """The cheapest of the proposed steps (each landmark's part cut, ``_candidate``) and where it
    leads, the first of equals; (None, None) for none. Beside the step, the apex-limited one is
    mostly the cheaper; the Newton step where it passes an apex along a valley that does go on (two
    observations of a landmark pulling it apart), where stopping there would creep as IRLS does."""
    best = (None, None)
    for step in steps:
        step, candidate = _candidate(problem, at.T, at.X, at.lin, step, huber, rows)
        if best[1] is None or candidate[3] < best[1][3]:
            best = (step, candidate)
    return best


def _take_or_refuse(problem, at: _Descent, H: sp.csc_matrix, g: np.ndarray, step, candidate,
                    config: SmootherConfig) -> tuple[bool, float]:
    """Take the step where it does not raise the cost, else choose the next one's kind (IRLS,
    then damping); updates ``at``. Returns whether it was taken and its largest component."""
    accepted = step is not None and candidate[3] <= at.cost
    max_step = float(np.max(np.abs(step))) if step is not None and step.size else 0.0
    small = step is not None and _step_size(problem, at.T, at.X, step, max_step, config.step_tolerance) < config.step_tolerance
    at.last_step = max_step if accepted and not at.majorize else 0.0
    if accepted:
        at.moved += max_step
        gain = (at.cost - candidate[3]) / _model_decrease(H, g, step)
        at.converged = small
        at.T, at.X, at.lin, at.cost = candidate
        at.damping, at.growth, at.majorize = _damping_after_accepted(at.damping, gain), 2.0, False
        at.receded = None if at.converged else _receded(problem, at.T, at.X)
    elif small and at.damping == 0.0:
        # A step below the tolerance that rounding made no cheaper: the poses are at the
        # minimum to that tolerance (20,000 poses: a factorization spent on a 2e-8 step saved).
        at.converged = True
    elif not at.majorize:
        # The Newton step overshot (factors crossing the Huber threshold change the model):
        # take the IRLS step, whose model lies above the cost, from the same poses.
        at.majorize = True
    else:
        # Even that failed (the linearization is poor, or a landmark went behind a camera):
        # damp towards gradient descent (Levenberg-Marquardt) and try again.
        at.damping, at.growth = (at.damping * at.growth, 2.0 * at.growth) if at.damping > 0.0 else (_FIRST_DAMPING, 2.0)
        at.converged = at.damping > _MAX_DAMPING
    return accepted, max_step


def _exact_newton_step(problem, at: _Descent, g: np.ndarray, huber: float, factor) -> Optional[np.ndarray]:
    """The Newton step of the robust cost with its exact Hessian (``camloc.newton_cg``: conjugate
    gradients on Hessian-vector products differenced from the exact gradient, preconditioned with
    this iteration's factor, ``factor``: the scaled factor and scale); None where there is none.

    Tried where the steps shrink linearly (one larger than ``_LINEAR_RATE`` times the last one
    taken): Gauss-Newton's linear convergence where the residuals' second derivatives matter, on
    monocular worlds with no map (docs/performance.md, 2026-12-05 (night)). It is a candidate
    beside the Gauss-Newton step (``_cheapest``), so that it never replaces a cheaper one."""
    lu, d = factor  # its scale, which need not be this iteration's: CG runs in those unknowns

    def gradient_at(delta: np.ndarray) -> np.ndarray:
        moved, moved_X = problem.retract(at.T, at.X, delta)
        return _gradient(problem.linearize(moved, moved_X), huber)

    return newton_step(gradient_at, g, d, lu.solve)


def _receded(problem, T: np.ndarray, X: np.ndarray | None):
    """``_without_undetermined_landmarks`` at poses T and landmarks X: the problem without the
    landmark variables whose observations no longer place them and their ids, or None (none).

    Why: seen by a monocular camera from two or three poses, a landmark whose rays part as the
    poses settle has its minimum at infinity: each step takes it 1.3-1.5 times farther (300-pose
    aerial worlds with no map: to 2.6e4-2.3e9 m in 50 iterations), the poses follow by less and
    less, and the loop never stops (docs/performance.md, 2026-12-05 (late)). Once its rays meet at
    under ~0.006 degrees it is what the start leaves out (``_MAX_LANDMARK_CONDITION``), and is
    left out the same way: the minimum found is that of the problem without it."""
    if not problem.num_landmarks or problem.pose_dof != POSE_DOF:
        return None
    reduced, ids = _without_undetermined_landmarks(replace(problem, landmarks=problem.landmarks.with_xyz(X)), T)
    return (reduced, ids) if ids.size else None


def _step_size(problem, T: np.ndarray, X: np.ndarray | None, step: np.ndarray, max_step: float,
               tolerance: float) -> float:
    """The step's size for the stopping rule: its largest component (``max_step``, metres or
    radians), but a 3-D landmark's part measured in inverse-depth coordinates as seen from each
    camera that observed it, where they are smaller than in metres: ``|dl_perp| / d`` (radians)
    and ``|dl_par| / d^2`` (1/m) at distance d, the larger of the two and of its cameras.

    Why: a landmark seen by a monocular camera from two poses whose rays barely meet has its
    minimum far along them (300-pose aerial worlds with no map: 231 m, and 9e6 m where the rays
    part), where the cost is flat in metres (a 0.5 m move changes it by 1e-12) and its Newton
    steps stay metres long however close the poses are to their minimum: the rule in metres never
    held (the iteration limit, docs/performance.md, 2026-12-05 (late)). In inverse depth its
    steps are what its observations see. Near landmarks (d < 1 m, where the metre is the smaller)
    keep the rule in metres."""
    n = problem.num_pose_unknowns
    if max_step < tolerance or not problem.num_landmarks or problem.pose_dof != POSE_DOF:
        return max_step
    poses = float(np.max(np.abs(step[:n]))) if n else 0.0
    if poses >= tolerance:
        return max_step
    rows = np.flatnonzero(problem.obs_landmark >= 0)
    j = problem.obs_landmark[rows]
    T_cam = T[problem.obs_pose[rows]] @ problem.obs_T_robot_camera[rows]
    ray = X[j] - T_cam[:, :3, 3]
    d = np.maximum(np.linalg.norm(ray, axis=1), 1e-300)
    dl = step[n:].reshape(-1, LANDMARK_DOF)[j]
    along = np.einsum("mi,mi->m", dl, ray) / d
    across = np.sqrt(np.maximum(np.einsum("mi,mi->m", dl, dl) - along**2, 0.0))
    seen = np.zeros(problem.num_landmarks)
    np.maximum.at(seen, j, np.maximum(across / d, np.abs(along) / d**2))
    metric = np.max(np.abs(step[n:].reshape(-1, LANDMARK_DOF)), axis=1)
    return max(poses, float(np.max(np.minimum(metric, seen))))


def _gradient(lin: Linearization, huber: float) -> np.ndarray:
    """The robust cost's exact gradient ``J^T W r`` at a linearization (``normal_equations``' g)."""
    return lin.jacobian.T @ (_row_weights(lin, huber) * lin.residual)


def _model_decrease(H: sp.csc_matrix, g: np.ndarray, step: np.ndarray) -> float:
    """How much the undamped quadratic model ``g' delta + 1/2 delta' H delta`` says the step lowers
    the cost (the denominator of the gain ratio); NaN where it says it does not."""
    decrease = -(float(g @ step) + 0.5 * float(step @ (H @ step)))
    return decrease if decrease > 0.0 else math.nan


def _damping_after_accepted(damping: float, gain: float) -> float:
    """Nielsen's update of the damping after a step is taken ("Damping parameter in Marquardt's
    method", IMM-REP-1999-05; Madsen, Nielsen and Tingleff, "Methods for non-linear least squares
    problems", 2004, sec. 3.2): scaled by ``max(1/3, 1 - (2 gain - 1)^3)`` of the gain ratio
    (actual over predicted decrease), so that it falls by 3 where the model holds and stays where
    it barely does; below ``_MIN_DAMPING`` it is dropped (plain Newton steps again). A rejected step
    multiplies it by a factor that doubles with every rejection in a row (``_minimize``).

    The schedule it replaces fell by 10 after every step taken and rose from wherever it was to
    1e-4 after a rejection: on monocular aerial worlds with no map a long curved valley (the
    trajectory's tail and a landmark, moving metres for a cost change of 0.5) then cycled
    1e-4 -> 1e-7 -> rejected -> 1e-4 to the iteration limit (docs/performance.md, 2026-12-05 (late))."""
    if not math.isfinite(gain):
        return damping
    damping *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
    return damping if damping > _MIN_DAMPING else 0.0


def _candidate(problem, T, X, lin, step, huber, rows):
    """The step (each landmark's part cut, ``_landmark_line_search``) and where it leads: the
    poses, landmarks, their linearization and robust cost."""
    if problem.num_landmarks:
        step = _landmark_line_search(problem, lin, step, huber, rows)
    moved, moved_X = problem.retract(T, X, step)
    after = problem.linearize(moved, moved_X)
    return step, (moved, moved_X, after, robust_cost(after, huber))


def _apex_limited_step(problem, lin, step, factored, huber, num_pose) -> Optional[np.ndarray]:
    """The Newton step solved again with the IRLS rows of the observations it carries past the
    apex of their cone (``camloc.huber_apex``), until it carries no more (the set only grows);
    None when it carries none. Those rows change the matrix by a term of low rank, so the step
    is solved by conjugate gradients preconditioned with the Newton step's factor (``factored``),
    else with a factor of its own."""
    first_obs_row = lin.odom_dim * len(lin.odom_sq)
    kept, limited = np.zeros(len(lin.obs_sq), dtype=bool), None
    while True:
        past = past_apex(lin.residual, lin.jacobian, step, first_obs_row, lin.obs_sq, huber) & ~kept
        if not np.any(past):
            return limited
        kept |= past
        H, g = newton_equations(problem, lin, huber, majorized=kept)
        Hs, d = _scaled(H)
        step = _preconditioned_step(Hs, d, g, factored)
        if step is None:
            try:
                factored = (_factorization(Hs, num_pose), d)
            except np.linalg.LinAlgError:
                return limited
            step = d * factored[0].solve(-d * g)
        limited = step


def _landmark_line_search(problem: SmoothingProblem, lin: Linearization, step: np.ndarray, huber: float,
                          rows: np.ndarray | None = None) -> np.ndarray:
    """The step with each landmark's part shortened to the minimum of its own linearized robust
    cost along it, the poses' part kept (``camloc.landmark_steps``): the Newton model of a
    landmark whose observations are all beyond the Huber threshold is flat along their residuals,
    and its full step can overshoot by metres and spoil the whole step. ``rows``: the Jacobian's
    ``row_landmarks`` (None: read from it)."""
    n = problem.num_pose_unknowns
    pose_part, landmark_part = step.copy(), step.copy()
    pose_part[n:], landmark_part[:n] = 0.0, 0.0
    rows = row_landmarks(lin.jacobian, n) if rows is None else rows
    alpha = landmark_step_lengths(lin.residual, lin.jacobian @ pose_part, lin.jacobian @ landmark_part,
                                  rows, lin.odom_dim * len(lin.odom_sq), len(lin.obs_sq),
                                  problem.num_landmarks, huber)
    return np.concatenate([step[:n], (step[n:].reshape(-1, LANDMARK_DOF) * alpha[:, None]).ravel()])


def _preconditioned_step(Hs: sp.csc_matrix, d: np.ndarray, g: np.ndarray, factor, *, rtol: float = 1e-8,
                         max_iterations: int = 25) -> Optional[np.ndarray]:
    """The step of ``Hs (delta / d) = -d g`` by conjugate gradients preconditioned with an
    earlier iteration's factor (of ``Hs_0``, scale ``d_0``: ``Hs^-1 ~ E Hs_0^-1 E``, ``E = d_0 / d``);
    None when the residual does not fall below ``rtol`` in ``max_iterations`` (factor afresh).

    Near the solution the Newton matrix changes little from one iteration to the next, so a few
    solves with the old factor (0.07 s each at 20,000 poses) replace a new one (4 s): an inexact
    Newton step whose gradient is exact, so the minimum it converges to is the same.
    """
    lu, d_0 = factor
    ratio = d_0 / d

    def precondition(v: np.ndarray) -> np.ndarray:
        return ratio * lu.solve(ratio * v)

    y = conjugate_gradients(lambda v: Hs @ v, -d * g, precondition, rtol=rtol, max_iterations=max_iterations)
    return None if y is None else d * y


class _SingularStep(CamlocError):
    """A step's normal matrix that could not be factored (with landmark variables: retried)."""


def _step_factor(Hs: sp.csc_matrix, num_pose: int, damping: float):
    try:
        return _factorization(Hs, num_pose, damping)
    except np.linalg.LinAlgError:
        error = _SingularStep if num_pose < Hs.shape[0] else CamlocError
        raise error("cannot smooth: the normal matrix became singular during the iterations") from None


def _landmark_estimate(problem: SmoothingProblem, lin: Linearization, X: np.ndarray, config: SmootherConfig,
                       factor=None) -> LandmarkEstimate:
    """The landmark variables at the solution with their marginal covariances: the landmark
    blocks of the inverse of the robust cost's Gauss-Newton Hessian there (its Laplace
    approximation), through the Schur complement (``SchurSolver.landmark_covariances``).
    ``factor``: the last step's (SchurSolver, scale) when it was a plain Newton step: that
    Hessian is the one at the solution to within the last step (below ``step_tolerance``), and
    refactoring it would cost a step's time again."""
    if factor is None:
        H, _ = newton_equations(problem, lin, config.huber)
        Hs, d = _scaled(H)
        try:
            factor = (SchurSolver(Hs, problem.num_pose_unknowns), d)
        except np.linalg.LinAlgError:
            raise CamlocError("cannot smooth: the normal matrix is singular at the solution") from None
    solver, d = factor
    cov = solver.landmark_covariances()
    scale = d[problem.num_pose_unknowns:].reshape(-1, LANDMARK_DOF)
    cov = cov * scale[:, :, None] * scale[:, None, :]  # H^-1 = D Hs^-1 D
    observations = np.bincount(problem.obs_landmark[problem.obs_landmark >= 0], minlength=problem.num_landmarks)
    lm = problem.landmarks
    return LandmarkEstimate(ids=lm.ids, xyz=X, cov=cov, added=lm.added, observations=observations)


def _with_initial_landmarks(problem: SmoothingProblem, T: np.ndarray) -> tuple[SmoothingProblem, np.ndarray]:
    """The problem with every landmark variable given a first position (``problem.landmarks.xyz``
    where given, else from its observations at poses T), and the ids of those that their
    observations do not place (a single pixel ray, parallel rays): left out with their
    observations, unless a map prior holds them."""
    lm = problem.landmarks
    if lm is None or not len(lm):
        return problem, np.zeros(0, dtype=np.int64)
    xyz = lm.xyz.copy()
    unknown = np.isnan(xyz).any(axis=1)
    if np.any(unknown):
        rows = np.flatnonzero(unknown[np.maximum(problem.obs_landmark, 0)] & (problem.obs_landmark >= 0))
        kinds = problem.obs_kind if problem.obs_kind is not None else np.zeros(len(problem.obs_pose), dtype=np.int64)
        found = initial_positions(problem.lifted(T[problem.obs_pose[rows]]), problem.obs_T_robot_camera[rows],
                                  problem.obs_intrinsics[rows], problem.obs_z[rows], kinds[rows],
                                  problem.obs_landmark[rows], len(lm))
        xyz[unknown] = found[unknown]
    xyz = np.where(np.isnan(xyz) & lm.has_prior[:, None], lm.prior_xyz, xyz)
    placed = ~np.isnan(xyz).any(axis=1)
    problem = replace(problem, landmarks=lm.with_xyz(xyz))
    return _select_landmarks(problem, placed), lm.ids[~placed]


def _without_undetermined_landmarks(problem: SmoothingProblem, T: np.ndarray) -> tuple[SmoothingProblem, np.ndarray]:
    """The problem without the landmark variables that their observations (and prior) do not
    determine at poses T, and their ids: those whose 3x3 information block is singular or has a
    condition number beyond ``_MAX_LANDMARK_CONDITION`` (rays with too little parallax)."""
    if not problem.num_landmarks:
        return problem, np.zeros(0, dtype=np.int64)
    eig = np.linalg.eigvalsh(problem.landmark_information(T))
    keep = eig[:, 0] > eig[:, 2] / _MAX_LANDMARK_CONDITION
    if np.all(keep):
        return problem, np.zeros(0, dtype=np.int64)
    return _select_landmarks(problem, keep), problem.landmarks.ids[~keep]


def _select_landmarks(problem: SmoothingProblem, keep: np.ndarray) -> SmoothingProblem:
    """The problem with the landmark variables where ``keep`` (L,) and the observations of the others left out."""
    if np.all(keep):
        return problem
    observed = problem.obs_landmark
    kept = (observed < 0) | keep[np.maximum(observed, 0)]
    problem = _select_observations(problem, kept)
    renumber = np.cumsum(keep) - 1
    obs_landmark = np.where(problem.obs_landmark >= 0, renumber[np.maximum(problem.obs_landmark, 0)], -1)
    landmarks = problem.landmarks.select(keep)
    return replace(problem, landmarks=landmarks if len(landmarks) else None,
                   obs_landmark=obs_landmark if len(landmarks) else None)


def _without_unprojectable(problem: SmoothingProblem, T: np.ndarray) -> tuple[SmoothingProblem, int]:
    """The problem without camera observations whose landmark is behind the camera at poses T
    (a planar robot's own kinds, in its frame, have no camera)."""
    X = None if problem.landmarks is None else problem.landmarks.xyz
    keep = np.ones(len(problem.obs_pose), dtype=bool)
    cameras = np.flatnonzero(~measurement.is_planar(problem.obs_kind)) if problem.obs_kind is not None else np.arange(keep.size)
    _, _, _, depth = observation_factors(problem.lifted(T[problem.obs_pose[cameras]]), problem.obs_T_robot_camera[cameras],
                                         problem.obs_intrinsics[cameras], problem.observed_xyz(X)[cameras],
                                         problem.obs_z[cameras], None if problem.obs_kind is None else problem.obs_kind[cameras],
                                         None if problem.obs_tag_rotation is None else problem.obs_tag_rotation[cameras])
    keep[cameras] = depth > MIN_DEPTH
    if np.all(keep):
        return problem, 0
    return _select_observations(problem, keep), int(np.count_nonzero(~keep))


def _select_observations(problem: SmoothingProblem, keep: np.ndarray) -> SmoothingProblem:
    return replace(
        problem,
        obs_pose=problem.obs_pose[keep],
        obs_T_robot_camera=problem.obs_T_robot_camera[keep],
        obs_intrinsics=problem.obs_intrinsics[keep],
        obs_landmark_xyz=problem.obs_landmark_xyz[keep],
        obs_z=problem.obs_z[keep],
        obs_kind=problem.obs_kind[keep] if problem.obs_kind is not None else None,
        obs_whiten=problem.obs_whiten[keep],
        obs_row=problem.obs_row[keep],
        obs_landmark=problem.obs_landmark[keep] if problem.obs_landmark is not None else None,
        obs_tag_rotation=problem.obs_tag_rotation[keep] if problem.obs_tag_rotation is not None else None,
    )


# --------------------------------------------------------------------------------------------
# From a dataset and a run folder


def problem_from_run(
    dataset: Dataset,
    run: RunResult,
    config: Optional[SmootherConfig] = None,
    *,
    added_xyz: Optional[dict[int, np.ndarray]] = None,
) -> SmoothingProblem:
    """The factor graph of a dataset's odometry chain and the observations a run accepted.

    Parameters
    ----------
    config : its ``map`` and ``map_sigma`` say which landmarks are variables
        (``camloc.smoother_landmarks``); None: ``SmootherConfig()`` (the map held exact).
    added_xyz : first positions (3,) by id of landmarks the map lacks that the run assigns
        observations to (added landmarks); those not given start from their observations.

    Raises
    ------
    CamlocError : the run was not made from this dataset (other poses, other observations).
    """
    config = config or SmootherConfig()
    check_run_matches(dataset, run)
    num_poses = dataset.num_poses
    return SmoothingProblem(
        pose_ids=np.asarray(dataset.pose_ids, dtype=np.int64),
        T_start=dataset.T_world_start,
        odom_from=np.arange(num_poses - 1, dtype=np.int64),
        odom_to=np.arange(1, num_poses, dtype=np.int64),
        T_odometry=dataset.T_odometry,
        odom_whiten=whitening(dataset.odom_cov),
        **observation_fields(dataset, run, config, dataset.landmark_xyz, added_xyz),
    )


def observation_fields(dataset: Dataset, run: RunResult, config: SmootherConfig, landmark_coords: np.ndarray,
                       added_xyz: Optional[dict[int, np.ndarray]] = None) -> dict:
    """The observation factors of the observations ``run`` accepted and the landmark variables
    ``config.map`` makes, as ``SmoothingProblem``'s fields by name (``obs_*``, ``landmarks``,
    ``obs_landmark``, ``obs_tag_rotation``); ``landmark_coords`` (K, 3) the map's landmarks' coordinates
    (their positions; a planar robot's marker's third its heading). A planar robot's own sensor
    (``measurement.ROBOT_FRAME_SENSOR``) is given the identity mount."""
    chosen = _chosen_landmarks(dataset, run, config)
    rows = np.flatnonzero(chosen != UNASSOCIATED)
    order = np.argsort(dataset.landmark_ids, kind="stable")
    position = np.searchsorted(dataset.landmark_ids[order], chosen[rows])
    position = np.clip(position, 0, max(len(order) - 1, 0))
    found = dataset.landmark_ids[order][position] == chosen[rows] if len(order) else np.zeros(len(rows), bool)
    # Variables: the landmarks the map lacks (added), and under a prior or no map the mapped ones too.
    variable = ~found if config.map == "exact" else np.ones(len(rows), dtype=bool)
    variable_ids = np.unique(chosen[rows][variable])
    obs_landmark = np.full(len(rows), -1, dtype=np.int64)
    obs_landmark[variable] = np.searchsorted(variable_ids, chosen[rows][variable])
    obs_xyz = np.full((len(rows), 3), np.nan)
    obs_xyz[found] = landmark_coords[order][position[found]]
    landmarks = None
    if len(variable_ids):
        landmarks = landmark_variables(variable_ids, dataset.landmark_ids, landmark_coords, config.map,
                                       config.map_sigma, added_xyz)
    cameras = dataset.obs_camera[rows]
    mounts = {cid: cam.T_robot_camera for cid, cam in dataset.cameras.items()} | {measurement.ROBOT_FRAME_SENSOR: np.eye(4)}
    intrinsics = {cid: (cam.fx, cam.fy, cam.cx, cam.cy) for cid, cam in dataset.cameras.items()}
    intrinsics[measurement.ROBOT_FRAME_SENSOR] = (1.0, 1.0, 0.0, 0.0)
    return dict(
        obs_pose=np.asarray(dataset.obs_pose_index[rows], dtype=np.int64),
        obs_T_robot_camera=np.array([mounts[int(c)] for c in cameras]).reshape(-1, 4, 4),
        obs_intrinsics=np.array([intrinsics[int(c)] for c in cameras], dtype=float).reshape(-1, 4),
        obs_landmark_xyz=obs_xyz,
        obs_z=dataset.obs_z[rows],
        obs_kind=np.asarray(dataset.obs_kind[rows], dtype=np.int64),
        obs_whiten=whitening(dataset.obs_cov[rows]),
        obs_row=rows.astype(np.int64),
        landmarks=landmarks,
        obs_landmark=obs_landmark if landmarks is not None else None,
        obs_tag_rotation=_tag_rotations(dataset, rows, order[position[found]], found),
    )


def _tag_rotations(dataset: Dataset, rows: np.ndarray, mapped: np.ndarray, found: np.ndarray) -> np.ndarray | None:
    """The world orientation (M, 3, 3) of the tag of each observation ``rows`` (M,) whose
    landmark is in the map (``found``; ``mapped`` its map rows), the identity for the others
    (their rows are not read); None where none of the rows is a tag's orientation."""
    if not np.any(dataset.obs_kind[rows] == measurement.TAG_ROTATION):
        return None
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (rows.size, 1))
    quat[found] = dataset.landmark_quat_xyzw[mapped]
    quat[~np.isfinite(quat[:, 0])] = [0.0, 0.0, 0.0, 1.0]  # a point's: no orientation
    return geometry.quat_to_matrix(quat)


def _chosen_landmarks(dataset: Dataset, run: RunResult, config: SmootherConfig) -> np.ndarray:
    """Each observation's landmark id (K,) as the run chose it (``UNASSOCIATED``: none): a tag's
    orientation its position's where the map holds the tag exact (``map = "exact"`` and the tag in
    it), so that its orientation is known; otherwise a tag's position alone (the smoother does
    not estimate a tag's orientation)."""
    chosen = tags.observation_landmarks(run.associations.landmark, dataset.obs_kind, dataset.obs_partner, orientations=True)
    rotation = np.flatnonzero(dataset.obs_kind == measurement.TAG_ROTATION)
    if config.map != "exact":
        chosen[rotation] = UNASSOCIATED
        return chosen
    mapped = landmark_rows(dataset.landmark_ids, chosen[rotation])
    known = (mapped >= 0) & np.isfinite(dataset.landmark_quat_xyzw[np.maximum(mapped, 0), 0]) if len(dataset.landmark_ids) else mapped >= 0
    chosen[rotation[~known]] = UNASSOCIATED
    return chosen


def check_run_matches(dataset: Dataset, run: RunResult, *, with_map: bool = True,
                      hint: str = "expected the dataset the run was made from (pass it with --dataset)") -> None:
    """Refuse a run folder that was not made from ``dataset``.

    The poses must be the same ids in the same order, the odometry the same, the associations one
    row per observation of the dataset, with the same observing pose, camera and measurement, and
    (``with_map``) the map the same; without it, ``dataset`` may be the world's true map
    (``camloc eval --true-map``), whose map differs from the run's by design.

    Raises
    ------
    CamlocError : naming the first difference, then ``hint``.
    """
    ours, theirs = np.asarray(run.pose_ids), np.asarray(dataset.pose_ids)
    if ours.shape != theirs.shape or not np.array_equal(ours, theirs):
        if ours.shape != theirs.shape:
            found = f"the run has {len(ours)} poses ({_id_range(ours)}), the dataset {len(theirs)} ({_id_range(theirs)})"
        else:
            k = int(np.flatnonzero(ours != theirs)[0])
            found = f"pose {k} is {ours[k]} in the run but {theirs[k]} in the dataset"
        raise CamlocError(f"run and dataset {dataset.source} do not match: {found}; {hint}")
    if with_map:
        _check_map_matches(dataset, run, hint)
    odometry = odometry_positions(dataset)
    # composed in another order by each engine: equal to a micrometre, where an edited edge moves metres
    apart = ~np.all(np.isclose(np.asarray(run.odometry_xyz), odometry, rtol=1e-6, atol=1e-6), axis=1)
    if np.any(apart):
        k = int(np.flatnonzero(apart)[0])
        raise CamlocError(f"run and dataset {dataset.source} do not match: odometry reaches {_triple(odometry[k])} at pose "
                          f"{ours[k]} in the dataset but {_triple(run.odometry_xyz[k])} in the run; {hint}")
    a = run.associations
    rows = tags.association_rows(dataset.obs_kind)  # one a tag: its position's
    if len(a.pose_id) != rows.size:
        raise CamlocError(
            f"run and dataset {dataset.source} do not match: the run has {len(a.pose_id)} observations in "
            f"associations.csv, the dataset {rows.size}; {hint}"
        )
    same = (
        (a.pose_id == dataset.pose_ids[dataset.obs_pose_index[rows]])
        & (a.camera == dataset.obs_camera[rows])
        & np.all(np.isclose(a.uvd, dataset.obs_z[rows], rtol=1e-9, atol=1e-12), axis=1)
    )
    if not np.all(same):
        k = int(np.flatnonzero(~same)[0])
        o = rows[k]
        raise CamlocError(
            f"run and dataset {dataset.source} do not match: observation {k + 1} (associations.csv line {k + 2}) is "
            f"pose {a.pose_id[k]}, camera {a.camera[k]}, uvd {_triple(a.uvd[k])} in the run but pose "
            f"{dataset.pose_ids[dataset.obs_pose_index[o]]}, camera {dataset.obs_camera[o]}, uvd "
            f"{_triple(dataset.obs_z[o])} in the dataset; {hint}"
        )


def _check_map_matches(dataset: Dataset, run: RunResult, hint: str) -> None:
    """``check_run_matches``'s refusal of a run whose map is not the dataset's: the same ids in the
    same order, each at the same place."""
    run_ids, run_xyz = np.asarray(run.map_landmark_ids), np.asarray(run.map_landmark_xyz)
    if run_ids.shape != dataset.landmark_ids.shape or not np.array_equal(run_ids, dataset.landmark_ids):
        raise CamlocError(f"run and dataset {dataset.source} do not match: the run's map has {len(run_ids)} landmarks "
                          f"({_id_range(run_ids)}), the dataset's {len(dataset.landmark_ids)} ({_id_range(dataset.landmark_ids)}); {hint}")
    moved = ~np.all(np.isclose(run_xyz, dataset.landmark_xyz, rtol=1e-9, atol=1e-9), axis=1)
    if np.any(moved):
        j = int(np.flatnonzero(moved)[0])
        raise CamlocError(f"run and dataset {dataset.source} do not match: landmark {run_ids[j]} is at {_triple(run_xyz[j])} "
                          f"in the run but {_triple(dataset.landmark_xyz[j])} in the dataset; {hint}")


def _id_range(ids: np.ndarray) -> str:
    return f"{ids[0]}..{ids[-1]}" if len(ids) else "none"


def _triple(values: np.ndarray) -> str:
    return "(" + ", ".join(f"{v:.6g}" for v in values) + ")"


def initial_poses(dataset: Dataset, run: RunResult) -> np.ndarray:
    """(N, 4, 4) the run's filter estimate, the first pose replaced by the dataset's start pose."""
    T = geometry.pose_from_quat(run.estimate_xyz, run.estimate_quat_xyzw)
    T[0] = dataset.T_world_start
    return T


def smooth_run(
    dataset: Dataset,
    run: RunResult,
    config: Optional[SmootherConfig] = None,
    *,
    added_xyz: Optional[dict[int, np.ndarray]] = None,
    on_iteration: Optional[IterationCallback] = None,
) -> SmoothingResult:
    """``smooth`` the run's accepted associations over the dataset, from the filter's estimate
    (``problem_from_run`` for ``config``'s map and ``added_xyz``)."""
    problem = problem_from_run(dataset, run, config, added_xyz=added_xyz)
    return smooth(problem, initial_poses(dataset, run), config, on_iteration=on_iteration)


def estimated_map(dataset: Dataset, run: RunResult, result: SmoothingResult, config: SmootherConfig) -> LandmarkMap:
    """The map after smoothing, a row per landmark sorted by id (``map.csv``).

    Mapped landmarks the smoother held (``exact``, or never observed under ``prior``) keep the
    map's position, with a zero covariance under ``exact`` and the prior's ``map_sigma^2 I``
    under ``prior``; under ``none`` only the landmarks it estimated are listed (the map gives no
    position). Estimated ones (mapped under ``prior`` or ``none``, and added ones in every mode)
    carry the smoother's position and marginal covariance. A landmark the smoother left
    undetermined (``undetermined_landmarks``: one ray, rays too parallel) keeps the run's own row
    of its map (``run.landmark_map``, the filter's estimate) where it has one, so that every
    landmark ``associations.csv`` points at stays in ``map.csv``; without one it is left out.
    """
    landmark = np.asarray(run.associations.landmark)
    counts = dict(zip(*np.unique(landmark[landmark != UNASSOCIATED], return_counts=True)))
    ids, xyz = [], []
    cov, added, observations = [], [], []
    if config.map != "none":
        held = dataset.landmark_ids
        if result.landmarks is not None:
            held = held[~np.isin(held, result.landmarks.ids)]
        rows = np.isin(dataset.landmark_ids, held)
        ids.append(dataset.landmark_ids[rows])
        xyz.append(dataset.landmark_xyz[rows])
        variance = 0.0 if config.map == "exact" else config.map_sigma**2
        held_cov = np.tile(variance * np.eye(3), (int(rows.sum()), 1, 1))
        on_floor = on_the_floor(dataset.landmark_kind[rows])  # no height: z = 0
        held_cov[on_floor, 2, :] = held_cov[on_floor, :, 2] = 0.0
        cov.append(held_cov)
        added.append(np.zeros(int(rows.sum()), dtype=bool))
        observations.append(np.array([counts.get(i, 0) for i in dataset.landmark_ids[rows].tolist()], dtype=np.int64))
    if result.landmarks is not None:
        lm = result.landmarks
        ids.append(lm.ids), xyz.append(lm.xyz), cov.append(lm.cov), added.append(lm.added)
        observations.append(np.asarray(lm.observations, dtype=np.int64))
    kept = _run_rows(run, result.undetermined_landmarks)
    if kept is not None:
        ids.append(kept.ids), xyz.append(kept.xyz), cov.append(kept.cov), added.append(kept.added)
        observations.append(np.asarray(kept.observations, dtype=np.int64))
    if not ids:
        return LandmarkMap(np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, dtype=bool),
                           np.zeros(0, dtype=np.int64))
    all_ids = np.concatenate(ids)
    order = np.argsort(all_ids, kind="stable")
    table = LandmarkMap(all_ids[order], np.concatenate(xyz)[order], np.concatenate(cov)[order],
                        np.concatenate(added)[order], np.concatenate(observations)[order])
    return _with_run_orientations(table, run)


def _with_run_orientations(table: LandmarkMap, run: RunResult) -> LandmarkMap:
    """``table`` with the tags' orientations of the run's own map (``run.landmark_map``: the
    filter's estimate, or the map's where it held a tag exactly), where that map has orientation
    columns: the smoother does not estimate a tag's orientation, and rewriting ``map.csv`` without
    them would lose the run's. A row the run's map lacks, or that is not a tag there: none (NaN)."""
    own = run.landmark_map
    if own is None or own.orientation is None:
        return table
    rows = landmark_rows(own.ids, table.ids)
    found = rows >= 0
    orientation = np.full((len(table.ids), 3), np.nan)
    orientation_cov = np.zeros((len(table.ids), 3, 3))
    orientation[found] = own.orientation[rows[found]]
    orientation_cov[found] = own.orientation_cov[rows[found]]
    orientation_cov[~np.isfinite(orientation[:, 0])] = 0.0
    return replace(table, orientation=orientation, orientation_cov=orientation_cov)


def _run_rows(run: RunResult, landmark_ids: np.ndarray) -> Optional[LandmarkMap]:
    """The rows of the run's own map (``run.landmark_map``) of ``landmark_ids``, or None."""
    own = run.landmark_map
    if own is None or len(landmark_ids) == 0:
        return None
    rows = np.isin(own.ids, landmark_ids)
    return LandmarkMap(own.ids[rows], own.xyz[rows], own.cov[rows], own.added[rows], own.observations[rows])


def smoothing_report(run: RunResult, result: SmoothingResult, config: SmootherConfig) -> dict:
    """A JSON-serializable summary, under the keys the other commands use for the same
    quantities (``docs/json.md``): the optimization (its time as ``timing.smooth_seconds``), and
    the filter's and the smoothed path's errors against the ground truth as ``estimate`` and
    ``smoothed`` (``metrics.trajectory_metrics``, no alignment: ``estimate.ate.rmse`` in metres,
    ``estimate.rotation.rmse_deg``, ... as in ``camloc eval``), both None without ground truth."""
    from camloc import metrics

    report: dict = {
        "dataset": run.dataset,
        "counts": {"poses": int(len(run.pose_ids))},
        "huber": config.huber if math.isfinite(config.huber) else None,
        "odometry_factors": result.odometry_factors,
        "observation_factors": result.observation_factors,
        "dropped_observations": result.dropped_observations,
        "downweighted_observations": result.downweighted_observations,
        "iterations": result.iterations,
        "converged": result.converged,
        "initial_cost": result.initial_cost,
        "final_cost": result.final_cost,
        "condition_estimate": result.condition if math.isfinite(result.condition) else None,
        "map": config.map,
        "map_sigma": config.map_sigma if config.map == "prior" else None,
        "landmarks": {
            "estimated": 0 if result.landmarks is None else len(result.landmarks.ids),
            "added": 0 if result.landmarks is None else int(np.count_nonzero(result.landmarks.added)),
            "undetermined": int(len(result.undetermined_landmarks)),
        },
        "timing": {"smooth_seconds": result.seconds},
        "estimate": None,
        "smoothed": None,
    }
    if run.truth_xyz is not None:
        for name, (xyz, quat) in {"estimate": (run.estimate_xyz, run.estimate_quat_xyzw),
                                  "smoothed": (result.xyz, result.quat_xyzw)}.items():
            report[name] = metrics.trajectory_metrics(xyz, quat, run.truth_xyz, run.truth_quat_xyzw)
    return report
