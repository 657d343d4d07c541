"""Extended Kalman filter steps: prediction, and the (iterated) update in Joseph form.

The filter is generic in its models: ``predict`` takes the motion Jacobians, ``update`` takes a
measurement function returning ``(z_hat, H)`` and, for states that are not plain vectors (wrapped
angles, a pose on SE(3)), the retraction and difference that move a state by an error.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs

from camloc.errors import CamlocError

MeasurementFunction = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
StateDifference = Callable[[np.ndarray, np.ndarray], np.ndarray]
Retraction = Callable[[np.ndarray, np.ndarray], np.ndarray]


# Iterated updates stop when the correction changes by less than this (metres / radians).
CONVERGED = 1e-6


def _add(x: np.ndarray, delta: np.ndarray) -> np.ndarray:
    return x + delta


def _subtract(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a - b


class FilterDivergedError(CamlocError):
    """The innovation covariance is not positive definite: the filter's covariance broke down."""

    def at_pose(self, pose_id: int) -> "FilterDivergedError":
        """The same error, saying where, and what in a file usually causes it."""
        return FilterDivergedError(f"pose {pose_id}: {self} (the filter's covariance broke down; information "
                                   "matrices in the file many orders of magnitude apart usually cause this)")


@dataclass(frozen=True)
class UpdateResult:
    """The outcome of one (stacked) update.

    Attributes
    ----------
    state : (n,) posterior state; cov : (n, n) posterior covariance.
    innovation : (m,) ``z - h(x_prior)``; S : (m, m) its covariance at the prior.
    nis : normalized innovation squared ``y^T S^-1 y`` at the prior (m degrees of freedom).
    map_cost : the MAP cost at the posterior, ``d' P^-1 d + r' R^-1 r`` with d the correction and
        r the posterior residual (NaN unless asked for); equal to ``nis`` for a linear model, and
        the better consistency statistic (also chi^2 with m dof) when the update was iterated,
        since NIS at the prior carries the linearization error the iterations removed.
    """

    state: np.ndarray
    cov: np.ndarray
    innovation: np.ndarray
    S: np.ndarray
    nis: float
    map_cost: float


def symmetrize(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + P.T)


def block_diagonal(blocks: np.ndarray) -> np.ndarray:
    """(p, b, b) blocks -> (p b, p b) block-diagonal matrix (stacked independent measurements)."""
    p, b, _ = blocks.shape
    out = np.zeros((p, b, p, b))
    out[np.arange(p), :, np.arange(p), :] = blocks
    return out.reshape(p * b, p * b)


def predict(P: np.ndarray, F: np.ndarray, G: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Propagated covariance ``P' = F P F' + G Q G'`` (the state itself comes from the model)."""
    return symmetrize(F @ P @ F.T + G @ Q @ G.T)


def joseph_update(P: np.ndarray, K: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``P+ = (I - K H) P (I - K H)' + K R K'``: stays symmetric positive semi-definite for any K,
    unlike ``(I - K H) P``, which loses symmetry and definiteness to rounding."""
    I_KH = np.eye(P.shape[0]) - K @ H
    return symmetrize(I_KH @ P @ I_KH.T + K @ R @ K.T)


def cholesky(S: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of a symmetric positive definite matrix, through LAPACK directly:
    the filter factors thousands of tiny matrices, where scipy's wrappers cost more than the
    arithmetic."""
    L, info = dpotrf(S, lower=1, clean=1)
    if info != 0:
        raise FilterDivergedError("innovation covariance is not positive definite")
    return L


def cho_solve(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``S^-1 B`` from the lower Cholesky factor L of S."""
    X, info = dpotrs(L, B, lower=1)
    if info != 0:
        raise FilterDivergedError(f"Cholesky solve failed (LAPACK info {info})")
    return X


def kalman_gain(P: np.ndarray, H: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``S = H P H' + R`` and ``K = P H' S^-1`` through a Cholesky solve; returns (K, S, L) with
    ``L L' = S``."""
    S = symmetrize(H @ P @ H.T + R)
    L = cholesky(S)
    K = cho_solve(L, H @ P).T  # K = P H' S^-1, S and P symmetric
    return K, S, L


def update(
    x: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    R: np.ndarray,
    measure: MeasurementFunction,
    *,
    retract: Retraction = _add,
    difference: StateDifference = _subtract,
    iterations: int = 1,
    map_cost: bool = False,
    at_prior: tuple[np.ndarray, np.ndarray] | None = None,
    start: np.ndarray | None = None,
) -> UpdateResult:
    """Iterated EKF update (Gauss-Newton on the MAP cost); ``iterations=1`` is the plain EKF.

    Parameters
    ----------
    x, P : prior state and covariance (n, n) of its error.
    z : (m,) stacked measurements; R : (m, m) their covariance.
    measure : x -> (z_hat (m,), H (m, n)), H with respect to the error at x.
    retract : (x, delta) -> x moved by the error delta (n,); plain addition for vector states.
    difference : (a, b) -> the error delta with retract(b, delta) == a; plain subtraction.
    iterations : number of linearizations (>= 1).
    map_cost : compute ``UpdateResult.map_cost`` at the posterior (one more evaluation of the
        measurement function); otherwise it is NaN.
    at_prior : ``measure(x)``, when the caller already has it (saves one evaluation).
    start : where the iterations after the first linearize first, instead of the plain EKF step
        from the prior (with ``iterations >= 2``); the fixed point they seek is the same MAP
        estimate, and a start near it reaches it where the prior is too far for Gauss-Newton.

    Each iteration ``x_{i+1} = x [+] K_i (z - h(x_i) + H_i (x_i [-] x))`` with ``K_i`` at ``x_i``
    (Bell & Cathey 1993); the covariance uses the last linearization, in Joseph form.
    """
    z_hat, H = measure(x) if at_prior is None else at_prior
    y_prior = z - z_hat
    K, S, L = kalman_gain(P, H, R)
    nis = float(y_prior @ cho_solve(L, y_prior))  # NIS = y' S^-1 y
    delta = K @ y_prior
    x_i = retract(x, delta)  # x+ = x [+] K y
    if start is not None and iterations >= 2:
        x_i, delta = start, difference(start, x)
    for _ in range(iterations - 1):
        z_hat_i, H_i = measure(x_i)
        K, _, _ = kalman_gain(P, H_i, R)
        H = H_i
        step = K @ (z - z_hat_i + H_i @ difference(x_i, x))
        x_i = retract(x, step)
        if np.max(np.abs(step - delta)) < CONVERGED:
            break  # the linearization no longer moves: further iterations would repeat this one
        delta = step
    cost = posterior_cost(x_i, x, P, z, R, measure, difference) if map_cost else float("nan")
    return UpdateResult(state=x_i, cov=joseph_update(P, K, H, R), innovation=y_prior, S=S, nis=nis, map_cost=cost)


def posterior_cost(
    x_post: np.ndarray, x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray,
    measure: MeasurementFunction, difference: StateDifference = _subtract,
) -> float:
    """The MAP cost ``d' P^-1 d + r' R^-1 r`` of a posterior x_post: d its correction from the
    prior x, r its residual ``z - h(x_post)`` (see ``UpdateResult.map_cost``)."""
    correction = difference(x_post, x)
    residual = z - measure(x_post)[0]
    return float(correction @ np.linalg.solve(P, correction) + residual @ np.linalg.solve(R, residual))
