"""Extended Kalman filter steps: prediction, and the (iterated) update in Joseph form.

The filter is generic in its models: ``predict`` takes the motion Jacobians, ``update`` takes a
measurement function returning ``(z_hat, H)`` and, for states that are not plain vectors (wrapped
angles, a pose on SE(3)), the retraction and difference that move a state by an error.

A pose's pairs are independent measurements: their covariance is block-diagonal, and given as
blocks the stacked update of many pairs runs in information form (``InformationGain``), whose cost
grows with the number of pairs instead of its cube (a pose of 150 pairs: 11x faster).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from camloc.constants import CONVERGED, DAMPING_RAISES, DAMPING_START, MAX_LINEARIZATIONS, NEGLIGIBLE_MARGIN
from camloc.errors import CamlocError

try:  # the gufuncs np.linalg wraps, called directly where their input is known good (``cho_solve``)
    from numpy.linalg import _umath_linalg
    _umath_linalg.solve, _umath_linalg.solve1, _umath_linalg.cholesky_lo  # all three, or none of them
except (ImportError, AttributeError):  # pragma: no cover - a numpy that moved them: its public functions, slower on small matrices
    _umath_linalg = None

# x -> (z_hat (m,), H (m, n)); it may also have ``feasible(x) -> bool`` (``posterior_cost``)
MeasurementFunction = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
StateDifference = Callable[[np.ndarray, np.ndarray], np.ndarray]
Retraction = Callable[[np.ndarray, np.ndarray], np.ndarray]




def _whole(delta: np.ndarray) -> np.ndarray:
    return delta


def _add(x: np.ndarray, delta: np.ndarray) -> np.ndarray:
    return x + delta


def _subtract(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a - b


class FilterDivergedError(CamlocError):
    """The innovation covariance is not positive definite: the filter's covariance broke down."""

    def at_pose(self, pose_id: int, cause: str) -> "FilterDivergedError":
        """The same error, saying where, and its likely ``cause`` (``diagnostics.divergence_cause``)."""
        return FilterDivergedError(f"pose {pose_id}: {self} (the filter's covariance broke down; {cause})")


# What a filter step may raise when its covariances break down: numpy's own error where a
# factorization fails before a check of ours could (information matrices many orders of
# magnitude apart leave a covariance indefinite to rounding).
NUMERICAL_FAILURES = (FilterDivergedError, np.linalg.LinAlgError)


def as_divergence(error: Exception) -> FilterDivergedError:
    """A numerical failure of the filter's linear algebra (``NUMERICAL_FAILURES``) as a FilterDivergedError."""
    if isinstance(error, FilterDivergedError):
        return error
    return FilterDivergedError(f"a covariance is no longer positive definite ({error})")


@dataclass(frozen=True)
class UpdateResult:
    """The outcome of one (stacked) update.

    Attributes
    ----------
    state : (n,) posterior state; cov : (n, n) posterior covariance.
    innovation : (m,) ``z - h(x_prior)``; S : (m, m) its covariance at the prior, or its (p, b, b)
        diagonal blocks (an update in information form, see ``update``).
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


_IDENTITIES = {n: np.eye(n) for n in (3, 6)}
for _I in _IDENTITIES.values():
    _I.flags.writeable = False


def identity(n: int) -> np.ndarray:
    """The (n, n) identity, read-only: the filters' sizes made once, not at each of the some
    20,000 updates and solves of a 1,000-pose numpy run that need one."""
    return _IDENTITIES[n] if n in _IDENTITIES else np.eye(n)


def symmetrize(P: np.ndarray) -> np.ndarray:
    """(P + P^T) / 2 of a matrix, or of each of a batch (..., n, n)."""
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def block_diagonal(blocks: np.ndarray) -> np.ndarray:
    """(p, b, b) blocks -> (p b, p b) block-diagonal matrix (stacked independent measurements)."""
    p, b, _ = blocks.shape
    if p == 1:  # a lone pair's update, the beam's most frequent (a fifth of the fancy-indexed copy's time)
        return blocks[0].copy()
    out = np.zeros((p, b, p, b))
    out[np.arange(p), :, np.arange(p), :] = blocks
    return out.reshape(p * b, p * b)


def mixture_spread(differences: np.ndarray, costs: np.ndarray) -> np.ndarray:
    """The spread of a Gaussian mixture's means about one estimate: ``sum_i w_i d_i d_i'``, where
    d_i (m, S) is component i's mean minus the estimate and w_i its weight, ``exp(-cost_i / 2)``
    normalized (costs are twice the negative log-likelihoods, as the beam's). Added to the
    estimate's own covariance it gives the mixture's second moment about that estimate (the
    spread-of-the-means term of PDA and MHT outputs): the covariance of a pose whose
    association the data leave ambiguous, where the estimate follows one of its explanations.
    Leading axes are a batch (differences (..., m, S), costs (..., m): one mixture each, the same
    numbers to the bit as one at a time)."""
    S = differences.shape[-1]
    if differences.shape[-2] < 2:
        return np.zeros(differences.shape[:-2] + (S, S))
    w = np.exp(-(costs - costs.min(axis=-1, keepdims=True)) / 2.0)
    w = w / w.sum(axis=-1, keepdims=True)
    return symmetrize(np.swapaxes(differences * w[..., None], -1, -2) @ differences)


def leave_one_out_spread(
    P: np.ndarray, residuals: np.ndarray, H: np.ndarray, R_update: np.ndarray, R_judged: np.ndarray,
    log_det_R_judged: np.ndarray, null_cost: np.ndarray,
) -> np.ndarray:
    """What the chance that one of an update's pairs is clutter adds to its covariance.

    The update's posterior (P (n, n), residuals ``r_i = z_i - h_i(x)`` (p, 3) and Jacobians H
    (p, 3, n) at its state) took every pair as right. The alternative "pair i is clutter" is the
    posterior of the other pairs, which in the model linearized at the posterior is, with
    ``B_i = R_i - H_i P H_i'`` (positive definite: P holds pair i's information, R_i = R_update),

        covariance  P_i = P + P H_i' B_i^-1 H_i P,     mean  x_i = x - P H_i' B_i^-1 r_i

    (the Woodbury form of taking H_i' R_i^-1 H_i out of the information). Judged by that
    posterior with the noise association uses (R_judged), pair i costs ``e' S^-1 e + ln det S -
    ln det R_judged`` in the beam's units, with ``e = z_i - h_i(x_i) = R_i B_i^-1 r_i`` and
    ``S = H_i P_i H_i' + R_judged``; leaving the observation unassigned costs ``null_cost``, so the
    alternative weighs ``exp(-(null - cost) / 2)`` beside the update's 1.

    Returns the mixture's second moment about the update's mean less P,
    ``sum_i w_i (P_i - P + (x_i - x)(x_i - x)')`` (n, n): a wrong pair that the beam never doubted
    (the case its spread cannot see) widens the covariance by the odds it had, and a right one,
    whose alternative costs far more, by next to nothing. A pair whose B is not positive definite
    by rounding adds nothing.
    """
    n = P.shape[0]
    spread = np.zeros((n, n))
    if residuals.shape[0] == 0:
        return spread
    PHt = P @ H.swapaxes(1, 2)                                       # (p, n, 3)
    A = H @ PHt                                                      # (p, 3, 3) H P H'
    B = R_update - A
    usable = np.linalg.eigvalsh(B)[:, 0] > 0.0
    if not usable.any():
        return spread
    PHt, A, B = PHt[usable], A[usable], B[usable]
    w, B_inverse_r = left_out_weights(A, B, residuals[usable], R_update[usable], R_judged[usable], log_det_R_judged[usable],
                                      null_cost[usable])
    d = -(PHt @ B_inverse_r[..., None])[..., 0]                       # x_i - x
    widening = PHt @ solve(B, PHt.swapaxes(1, 2))                    # P H' B^-1 H P
    return symmetrize(np.einsum("p,pij->ij", w, widening + d[:, :, None] * d[:, None, :]))


def left_out_weights(A: np.ndarray, B: np.ndarray, residuals: np.ndarray, R_update: np.ndarray, R_judged: np.ndarray,
                     log_det_R_judged: np.ndarray, null_cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The weights (p,) of ``leave_one_out_spread``'s alternatives beside the update's (each pair
    judged under the posterior of the others against ``null_cost``) and ``B_i^-1 r_i`` (p, 3),
    from ``A_i = H_i P H_i'`` and ``B_i = R_i - A_i`` (p, 3, 3, B positive definite) of pairs with
    residuals r (p, 3)."""
    B_inverse_r = solve(B, residuals[..., None])[..., 0]             # (p, 3)
    e = (R_update @ B_inverse_r[..., None])[..., 0]                   # the residual at the others' posterior
    S = A + A @ solve(B, A) + R_judged                               # H P_i H' + R_judged
    d2 = np.einsum("pi,pi->p", e, solve(S, e[..., None])[..., 0])
    cost = d2 + np.linalg.slogdet(S)[1] - log_det_R_judged
    margin = null_cost - cost                                         # the alternative's cost over the update's
    shifted = np.concatenate([[0.0], margin])
    shifted = shifted - shifted.min()
    w = np.where(shifted <= NEGLIGIBLE_MARGIN, np.exp(-shifted / 2.0), 0.0)
    return (w / w.sum())[1:], B_inverse_r


def predict(P: np.ndarray, F: np.ndarray, G: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Propagated covariance ``P' = F P F' + G Q G'`` (the state itself comes from the model)."""
    return symmetrize(F @ P @ F.T + G @ Q @ G.T)


def joseph_update(P: np.ndarray, K: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``P+ = (I - K H) P (I - K H)' + K R K'``: stays symmetric positive semi-definite for any K,
    unlike ``(I - K H) P``, which loses symmetry and definiteness to rounding."""
    I_KH = identity(P.shape[0]) - K @ H
    return symmetrize(I_KH @ P @ I_KH.T + K @ R @ K.T)


def cholesky(S: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of a symmetric positive definite matrix (numpy's, not scipy's:
    importing scipy.linalg costs ``camloc run`` 0.15 s, a sixth of its time on a small file).
    LAPACK's gufunc called directly (``_lower_factor``, a third of ``np.linalg.cholesky``'s
    time on a 3x3 or 6x6 matrix); it fills a factor that fails with NaN."""
    if _umath_linalg is None or S.ndim != 2:  # pragma: no cover - stacks go through numpy's checks
        try:
            return np.linalg.cholesky(S)
        except np.linalg.LinAlgError:
            raise FilterDivergedError("innovation covariance is not positive definite") from None
    L = _lower_factor(S)
    if np.isnan(L[-1, -1]):
        raise FilterDivergedError("innovation covariance is not positive definite")
    return L


@np.errstate(invalid="ignore")  # a matrix that is not positive definite: a NaN factor, which the caller checks
def _lower_factor(S: np.ndarray) -> np.ndarray:
    return _umath_linalg.cholesky_lo(S, signature="d->d")


def cho_solve(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``S^-1 B`` from the lower Cholesky factor L of S: ``L' \\ (L \\ B)``. L is a factor
    ``cholesky`` returned (its diagonal positive: never singular), so the solves call LAPACK's
    gufunc directly, the same arithmetic as ``np.linalg.solve`` without its checks (on 3x3 and
    6x6 matrices a fifth of the time; the numpy beam solves some 90,000 a 3,000-pose run)."""
    if _umath_linalg is None:  # pragma: no cover
        return np.linalg.solve(L.T, np.linalg.solve(L, B))
    solve = _umath_linalg.solve1 if B.ndim == 1 else _umath_linalg.solve
    return solve(L.T, solve(L, B, signature="dd->d"), signature="dd->d")


def _singular(error_type, flag):
    raise np.linalg.LinAlgError("Singular matrix")


def solve(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``np.linalg.solve(A, B)`` of float arrays (B of one dimension a vector, else a stack of
    matrices, as numpy reads it): the same LAPACK gufunc, so the same bits, and the same
    LinAlgError on a singular matrix, without the wrapper's checks and conversions (on a 6x6
    matrix 15 us of its 27 on the EPYC; the numpy engine solves some 80,000 a 3,000-pose run)."""
    if _umath_linalg is None:  # pragma: no cover
        return np.linalg.solve(A, B)
    gufunc = _umath_linalg.solve1 if B.ndim == 1 else _umath_linalg.solve
    with np.errstate(call=_singular, invalid="call", over="ignore", divide="ignore", under="ignore"):
        return gufunc(A, B, signature="dd->d")


def kalman_gain(P: np.ndarray, H: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``S = H P H' + R`` and ``K = P H' S^-1`` through a Cholesky solve; returns (K, S, L) with
    ``L L' = S``."""
    HP = H @ P
    S = symmetrize(HP @ H.T + R)
    L = cholesky(S)
    K = cho_solve(L, HP).T  # K = P H' S^-1, S and P symmetric
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
    R_inverse: np.ndarray | None = None,
    columns: np.ndarray | None = None,
    monotone: bool = False,
    step_sigma: float = 0.0,
) -> UpdateResult:
    """Iterated EKF update (Gauss-Newton on the MAP cost); ``iterations=1`` is the plain EKF.

    Parameters
    ----------
    x, P : prior state and covariance (n, n) of its error.
    z : (m,) stacked measurements; R : (m, m) their covariance, or (p, b, b) the blocks of a
        block-diagonal one (p independent measurements of b components, m = p b). With blocks and
        more measurement rows than states, the update runs in information form
        (``InformationGain``): O(m) where factoring the (m, m) innovation covariance is O(m^3).
        The same posterior to rounding; ``UpdateResult.S`` then holds the (p, b, b) blocks.
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
    R_inverse : the (p, b, b) inverses of R's blocks, when the caller has them (the information
        matrices of a file's measurements): saves inverting the blocks.
    columns : (k,) the only columns of the state H may touch (a SLAM state: the pose and the
        landmarks observed); ``measure`` then returns H on those columns only, (m, k), and the
        update (``ColumnGain``) costs O(n k m) and its covariance O(n^2 m), never O(n^3); the
        same posterior to rounding.

    monotone : the iterate of least MAP cost (with its gain), not the last: Gauss-Newton can
        overshoot where the prior is wide and the measurement bends (no map: ``slam_run``).
    step_sigma : also stop once a step moved the state by less than this many prior standard
        deviations on every axis (``constants.RAY_STEP_SIGMA``: the beam's update of one ray).

    Each iteration ``x_{i+1} = x [+] K_i (z - h(x_i) + H_i (x_i [-] x))`` with ``K_i`` at ``x_i``
    (Bell & Cathey 1993); the covariance uses the last linearization, in Joseph form.
    """
    restrict = _whole
    if columns is not None:
        R_full, P_columns = block_diagonal(R) if R.ndim == 3 else R, P[:, columns]
        gain_at = lambda H: ColumnGain(P, H, R_full, columns, P_columns)  # noqa: E731
        restrict = lambda d: d[columns]  # noqa: E731
    else:
        gain_at = _gain_for(P, R, z.size, R_inverse)
    z_hat, H = measure(x) if at_prior is None else at_prior
    y_prior = z - z_hat
    gain = gain_at(H)
    nis = gain.nis(y_prior)  # NIS = y' S^-1 y
    S = gain.S()
    delta = gain.correction(y_prior)
    x_i = retract(x, delta)  # x+ = x [+] K y
    last = y_prior  # the innovation whose correction x_i is
    if start is not None and iterations >= 2:
        x_i, delta, last = start, difference(start, x), None
    cost_of = lambda x_k, r, g, y: _iterate_cost(x_k, r, g, y, x, P, z, R, measure, difference, R_inverse, columns)  # noqa: E731
    x_i, gain, last, kept = _iterate(x, x_i, delta, last, gain, z, measure, retract, difference, gain_at, restrict, iterations,
                                     cost_of if monotone else None, step_sigma * step_sigma * np.diagonal(P))
    cost = float("nan")
    if map_cost or monotone:
        cost = cost_of(x_i, None, gain, last)
        if monotone and cost > kept[3]:  # Gauss-Newton overshot: the cheapest iterate, with its gain
            x_i, gain, last, cost = kept
        cost = cost if map_cost else float("nan")
    return UpdateResult(state=x_i, cov=gain.posterior_cov(), innovation=y_prior, S=S, nis=nis, map_cost=cost)


def damped_gauss_newton(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray, measure: MeasurementFunction, *,
    retract: Retraction = _add, difference: StateDifference = _subtract, R_inverse: np.ndarray | None = None,
) -> np.ndarray:
    """The MAP estimate of the update of prior (x, P) with measurements z, R (as ``update``'s), by
    Levenberg-Marquardt from x, damped in the prior's metric: each step solves
    ``(P^-1 (1 + damping) + H' R^-1 H) step = H' R^-1 r - P^-1 (x_i - x)``, the damping raised
    tenfold until the step lowers the MAP cost (``posterior_cost``) and lowered tenfold after.
    Where the model bends within the prior's spread (pixels of landmarks a prior's standard
    deviation from the camera's plane) the plain iterations run off, and a line search along the
    Gauss-Newton step can leap to another minimum (a pose turned half round, 31 prior sigmas away,
    whose pixels fit: docs/filter.md); the damped steps bend toward the prior's steepest descent
    instead. That step is the Gauss-Newton step of the prior (P / (1 + damping)) centred on x_i
    moved toward x by 1 / (1 + damping) of their difference, so it is one gain's correction, as
    the compiled twin (``kernels.update.damped_start``) computes it. Stops where no damping lowers
    the cost (``DAMPING_RAISES``), where the step falls below ``CONVERGED``, or after
    ``MAX_LINEARIZATIONS`` linearizations. Returns the state; ``update(..., start=it)`` gives its
    posterior (the covariance at its linearization)."""
    cost_of = lambda state: posterior_cost(state, x, P, z, R, measure, difference, R_inverse)  # noqa: E731
    x_i, cost_i, damping = x, cost_of(x), DAMPING_START
    for _ in range(MAX_LINEARIZATIONS):
        z_hat, H = measure(x_i)
        for _ in range(DAMPING_RAISES):
            shrink = 1.0 / (1.0 + damping)
            centre = retract(x_i, shrink * difference(x, x_i))
            gain = _gain_for(shrink * P, R, z.size, R_inverse)(H)
            step = difference(retract(centre, gain.correction(z - z_hat + H @ difference(x_i, centre))), x_i)
            candidate = retract(x_i, step)
            cost = cost_of(candidate)
            if cost < cost_i:
                damping *= 0.1
                break
            damping *= 10.0
        else:
            return x_i  # no damping lowers the cost: a minimum, to the step's resolution
        x_i, cost_i = candidate, cost
        if np.abs(step).max() < CONVERGED:
            break
    return x_i


def _iterate(x, x_i, delta, last, gain, z, measure, retract, difference, gain_at, restrict, iterations, cost_of, negligible):
    """``update``'s Gauss-Newton iterations after its first step (from x_i, the correction delta
    of innovation ``last`` by ``gain``): the last iterate, its gain and innovation, and the
    cheapest iterate before it as (iterate, gain, innovation, MAP cost) where ``cost_of`` (x_k,
    its residual, its gain and innovation -> its MAP cost: ``monotone``) is given. They also stop
    where a step's change squared is below ``negligible`` (n,) on every axis (``step_sigma``)."""
    kept = (x_i, gain, last, np.inf)
    for _ in range(iterations - 1):
        z_hat_i, H_i = measure(x_i)
        if cost_of is not None:
            cost_i = cost_of(x_i, z - z_hat_i, gain, last)
            if cost_i < kept[3]:
                kept = (x_i, gain, last, cost_i)
        gain = gain_at(H_i)
        last = z - z_hat_i + H_i @ restrict(difference(x_i, x))
        step = gain.correction(last)
        x_i = retract(x, step)
        moved = step - delta
        if np.abs(moved).max() < CONVERGED or np.all(moved * moved < negligible):
            break  # the linearization no longer moves: further iterations would repeat this one
        delta = step
    return x_i, gain, last, kept


def _iterate_cost(x_i, residual, gain, last, x, P, z, R, measure, difference, R_inverse, columns) -> float:
    """``posterior_cost`` of an iterate x_i of ``update`` (its residual ``z - h(x_i)`` where known,
    else None), its prior term from the gain that made it where the gain knows it (``ColumnGain``:
    P^-1 of the correction without P^-1, n^3 saved)."""
    prior_term = gain.correction_quadratic(last) if columns is not None and last is not None else None
    return posterior_cost(x_i, x, P, z, R, measure, difference, R_inverse, prior_term=prior_term, residual=residual)


class CovarianceGain:
    """The textbook gain ``K = P H' S^-1`` through the Cholesky factor of the (m, m) innovation
    covariance S, and the Joseph-form posterior."""

    def __init__(self, P: np.ndarray, H: np.ndarray, R: np.ndarray):
        self.P, self.H, self.R = P, H, R
        self.K, self._S, self.L = kalman_gain(P, H, R)

    def correction(self, y: np.ndarray) -> np.ndarray:
        return self.K @ y

    def nis(self, y: np.ndarray) -> float:
        return float(y @ cho_solve(self.L, y))

    def S(self) -> np.ndarray:
        return self._S

    def posterior_cov(self) -> np.ndarray:
        return joseph_update(self.P, self.K, self.H, self.R)


class ColumnGain:
    """The covariance-form gain for an H whose nonzero columns are few: k of the state's n (an
    EKF-SLAM update touches the pose and the landmarks observed). With ``U = P H'`` (n, m) from
    those k columns of P, ``S = H U + R``, ``K = U S^-1``, the Joseph form expanded,

        (I - K H) P (I - K H)' + K R K' = P - K U' - U K' + K S K' = P + K M' + M K',
        M = K S / 2 - U,

    is the same matrix for any K (so rounding in K stays second order in P, as in the product
    form), symmetric by construction, and costs two (n, m) x (m, n) products: O(n^2 m) where the
    product form's (n, n) products cost O(n^3) (a state of 300 landmarks: n = 906). Its rounding
    is of P's size (a difference of terms like P), where the product form's is of the posterior's:
    an update that shrinks a variance by ~1e-12 or more would lose definiteness here first (a
    mapping run's, from a prior of centimetres to millimetres, is far from that)."""

    def __init__(self, P: np.ndarray, H: np.ndarray, R: np.ndarray, columns: np.ndarray | None = None,
                 P_columns: np.ndarray | None = None):
        """H (m, n), or (m, k) on the state's ``columns`` (k,) only; ``P_columns``: ``P[:, columns]``
        when the caller has it (an iterated update's gains share it)."""
        if R.ndim == 3:
            R = block_diagonal(R)
        self.P, self.R = P, R
        if columns is None:
            columns = np.flatnonzero(np.any(H != 0.0, axis=0))
            H = H[:, columns]
        if P_columns is None:
            P_columns = P[:, columns]
        self.U = P_columns @ H.T                                        # P H' (n, m)
        self._S = symmetrize(H @ self.U[columns] + R)
        cholesky(self._S)  # the check of definiteness (FilterDivergedError)
        self._solved: tuple = (None, None)  # (y, S^-1 y) of the last y: an update asks for it up to three times

    def _solve(self, y: np.ndarray) -> np.ndarray:
        if self._solved[0] is not y:
            self._solved = (y, np.linalg.solve(self._S, y))
        return self._solved[1]

    def correction(self, y: np.ndarray) -> np.ndarray:
        return self.U @ self._solve(y)

    def nis(self, y: np.ndarray) -> float:
        return float(y @ self._solve(y))

    def S(self) -> np.ndarray:
        return self._S

    def correction_quadratic(self, y: np.ndarray) -> float:
        """``d' P^-1 d`` of the correction ``d = K y = P H' w`` (w = S^-1 y): ``w' H P H' w =
        w' (S - R) w``, with no inverse of P."""
        w = self._solve(y)
        return float(w @ (self._S - self.R) @ w)

    def posterior_cov(self) -> np.ndarray:
        K = np.linalg.solve(self._S, self.U.T).T
        KM = K @ (0.5 * (K @ self._S) - self.U).T
        return self.P + (KM + KM.T)  # exactly symmetric where P is (a matrix plus its transpose is, to the bit)


class InformationGain:
    """The same update for a block-diagonal R, through the (n, n) information the measurements
    add, ``Lambda = H' R^-1 H``, never an (m, m) matrix. With ``A = (I + P Lambda)^-1``:

        K y = A P H' R^-1 y,    y' S^-1 y = y' R^-1 y - g' A P g  (g = H' R^-1 y, Woodbury),
        P+ = A (P + P Lambda P) A'

    the last the Joseph form ``(I - K H) P (I - K H)' + K R K'`` with ``I - K H = A``: symmetric
    positive definite by construction. No inverse of P is needed (``(P^-1 + Lambda)^-1 = A P``).
    R's blocks enter through their inverses, which the caller usually has (a file gives
    information matrices), where whitening each block's rows cost a batched solve per use.
    """

    def __init__(self, P: np.ndarray, H: np.ndarray, R_blocks: np.ndarray, R_inverse: np.ndarray):
        self.P, self.R_blocks, self.R_inverse = P, R_blocks, R_inverse
        p, b, _ = R_inverse.shape
        self.H = H
        self.R_inverse_H = (R_inverse @ H.reshape(p, b, -1)).reshape(p * b, -1)
        self.information = symmetrize(H.T @ self.R_inverse_H)              # Lambda (n, n)
        self.I_P_information = identity(P.shape[0]) + P @ self.information
        if not np.isfinite(self.I_P_information).all():
            raise FilterDivergedError("innovation covariance is not positive definite")
        self.posterior_plain = symmetrize(solve(self.I_P_information, P))  # A P = (P^-1 + Lambda)^-1

    def _gradient(self, y: np.ndarray) -> np.ndarray:
        return self.R_inverse_H.T @ y

    def correction(self, y: np.ndarray) -> np.ndarray:
        return self.posterior_plain @ self._gradient(y)

    def nis(self, y: np.ndarray) -> float:
        g = self._gradient(y)
        return float(_block_quadratic(y, self.R_inverse) - g @ self.posterior_plain @ g)

    def S(self) -> np.ndarray:
        """The (p, b, b) diagonal blocks ``H_i P H_i' + R_i`` of the innovation covariance."""
        p, b, _ = self.R_inverse.shape
        H = self.H.reshape(p, b, -1)
        return H @ self.P @ H.swapaxes(1, 2) + self.R_blocks

    def posterior_cov(self) -> np.ndarray:
        P = self.P
        spread = solve(self.I_P_information, P + P @ self.information @ P)  # A (P + P Lambda P)
        return symmetrize(solve(self.I_P_information, spread.T).T)        # ... A'

    def log_det_ratio(self) -> float:
        """``ln det S - ln det R`` (the matrix determinant lemma: det S = det R det(I + P Lambda))."""
        sign, log_det = np.linalg.slogdet(self.I_P_information)
        if sign <= 0:
            raise FilterDivergedError("innovation covariance is not positive definite")
        return float(log_det)


def _gain_for(P: np.ndarray, R: np.ndarray, m: int, R_inverse: np.ndarray | None = None):
    """H -> the gain of an update with prior covariance P and measurement covariance R (full, or
    (p, b, b) blocks, with their inverses R_inverse when known): in information form where that
    is cheaper (blocks, m > n)."""
    if R.ndim == 2:
        return lambda H: CovarianceGain(P, H, R)
    if m <= P.shape[0]:
        R_full = block_diagonal(R)
        return lambda H: CovarianceGain(P, H, R_full)
    if R_inverse is None:
        R_inverse = block_inverse(R)
    return lambda H: InformationGain(P, H, R, R_inverse)


def block_inverse(blocks: np.ndarray) -> np.ndarray:
    """Inverses (p, b, b), exactly symmetric, of (p, b, b) symmetric positive definite blocks;
    FilterDivergedError when one is not positive definite."""
    block_cholesky(blocks)  # the check of definiteness
    inverse = np.linalg.inv(blocks)
    return 0.5 * (inverse + inverse.swapaxes(1, 2))


def block_cholesky(blocks: np.ndarray) -> np.ndarray:
    """Lower Cholesky factors (p, b, b) of (p, b, b) symmetric positive definite blocks."""
    try:
        factors = np.linalg.cholesky(blocks)
    except np.linalg.LinAlgError:
        raise FilterDivergedError("innovation covariance is not positive definite") from None
    if not np.all(np.isfinite(factors)):
        raise FilterDivergedError("innovation covariance is not positive definite")
    return factors


def correction(P: np.ndarray, H: np.ndarray, R: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``K y``, the correction of one EKF update with innovation y (m,), Jacobian H (m, n) and
    measurement covariance R, (m, m) or (p, b, b) blocks (in information form where cheaper)."""
    return _gain_for(P, R, y.size)(H).correction(y)


def innovation_cost(P: np.ndarray, H: np.ndarray, R: np.ndarray, y: np.ndarray) -> float:
    """``y' S^-1 y + ln det S - ln det R`` of a stacked innovation y (m,) with Jacobian H (m, n)
    and measurement covariance R, (m, m) or (p, b, b) blocks, ``S = H P H' + R``: twice the
    negative log-likelihood of y, up to a constant, relative to the measurements' own spread.
    O(m) in information form for blocks with m > n."""
    gain = _gain_for(P, R, y.size)(H)
    if isinstance(gain, InformationGain):
        return gain.nis(y) + gain.log_det_ratio()
    log_det_R = float(np.linalg.slogdet(R)[1].sum())  # of the blocks, or of the full matrix
    return gain.nis(y) + 2.0 * float(np.log(np.diagonal(gain.L)).sum()) - log_det_R


def posterior_cost(
    x_post: np.ndarray, x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray,
    measure: MeasurementFunction, difference: StateDifference = _subtract, R_inverse: np.ndarray | None = None,
    prior_term: float | None = None, residual: np.ndarray | None = None,
) -> float:
    """The MAP cost ``d' P^-1 d + r' R^-1 r`` of a posterior x_post: d its correction from the
    prior x, r its residual ``z - h(x_post)`` (see ``UpdateResult.map_cost``); R_inverse: the
    inverses of R's blocks, when known; prior_term: ``d' P^-1 d`` and residual: r, when the caller
    has them. Infinite where ``measure`` has a ``feasible(state)`` that says x_post is not while
    the prior x is: a state that puts a landmark behind the camera that saw it has no likelihood (a
    pinhole's mirrored projection is no measurement), and Gauss-Newton under a wide prior can reach
    one whose mirrored pixels fit. A prior that is not feasible itself (its pairs judged at another
    state) leaves the search no feasible start, and the cost is the plain one (docs/filter.md,
    "Behind the camera")."""
    feasible = getattr(measure, "feasible", None)
    if feasible is not None and not feasible(x_post) and feasible(x):
        return float("inf")
    if residual is None:
        residual = z - measure(x_post)[0]
    if prior_term is None:
        moved = difference(x_post, x)
        prior_term = moved @ solve(P, moved)
    if R.ndim == 3 and R_inverse is not None:
        return float(prior_term + _block_quadratic(residual, R_inverse))
    if R.ndim == 3:  # blocks: each solves its own rows
        p, b, _ = R.shape
        return float(prior_term + residual @ solve(R, residual.reshape(p, b, 1)).reshape(-1))
    return float(prior_term + residual @ solve(R, residual))


def _block_quadratic(y: np.ndarray, inverse_blocks: np.ndarray) -> float:
    """``y' R^-1 y`` for a block-diagonal R given by its blocks' inverses (p, b, b), y (p b,)."""
    p, b, _ = inverse_blocks.shape
    y_blocks = y.reshape(p, b)
    return float(np.einsum("pi,pij,pj->", y_blocks, inverse_blocks, y_blocks))
