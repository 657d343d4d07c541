"""The stacked, iterated EKF update in information form, and what the localizer wraps around it.

A pose's pairs are independent measurements (block-diagonal R), so the update adds their
information to the prior's, an n x n system whatever the number of pairs (n the state's size: 6
for the Euler state, 3 for the planar one; every kernel here takes it from its arrays):

    Lambda = sum H_i' R_i^-1 H_i,  A = (I + P Lambda)^-1
    K y  = A P g,  g = sum H_i' R_i^-1 y_i                          (correction)
    y' S^-1 y = sum y_i' R_i^-1 y_i - g' A P g                      (NIS, Woodbury)
    P+ = A (P + P Lambda P) A'                                      (Joseph form, I - K H = A)
    ln det S - ln det R = ln det (I + P Lambda)                     (determinant lemma)

With few pairs (3p <= n rows) the textbook form is used instead: S = H P H' + R is no larger
than the state's information and better conditioned when the noise is tiny.

Iterations (Bell & Cathey 1993): ``x_{i+1} = x [+] K_i (z - h(x_i) + H_i (x_i [-] x))`` with K_i
at x_i; the covariance uses the last linearization. The numpy twin is ``camloc.ekf.update``.

Each step writes into arrays its caller owns (the ``*_into`` kernels): an iterated update
allocates its scratch once and every linearization reuses it, where fresh temporaries per step
cost more than the 6x6 arithmetic.
"""

from __future__ import annotations

import math

import numpy as np

from camloc.constants import CONVERGED, DAMPING_RAISES, DAMPING_START, MAX_LINEARIZATIONS
from camloc.kernels._jit import FALSE, TRUE, called, entry, inlined, jit
from camloc.kernels.camera import back_project, in_front_of, observe_pairs_into, robot_frame_into
from camloc.kernels.one_pair import one_pair_update
from camloc.kernels.planar import SE2_DIM, wrapped_residual
from camloc.measurement import DEPTH
from camloc.kernels.state import difference_into, retract, retract_into, stepped_into
from camloc.kernels.small import lu_factor, lu_log_det, lu_solve, mm
from camloc.kernels.sym3 import log_det as log_det_3x3
from camloc.kernels.types import PairModel


# ---------------------------------------------------------------------------------------------
# Cholesky factors of a few pairs' innovation covariance (the LU steps are in ``small``)

@jit
def cholesky_into(S, L):
    """The lower Cholesky factor L (m, m) of a symmetric S (m, m); raises FloatingPointError
    where S is not positive definite."""
    m = S.shape[0]
    for j in range(m):
        s = S[j, j]
        for q in range(j):
            s -= L[j, q] * L[j, q]
        if not s > 0.0:
            raise FloatingPointError("innovation covariance is not positive definite")
        L[j, j] = math.sqrt(s)
        for i in range(j):
            L[i, j] = 0.0
        for i in range(j + 1, m):
            s = S[i, j]
            for q in range(j):
                s -= L[i, q] * L[j, q]
            L[i, j] = s / L[j, j]


@jit
def cho_solve_into(L, b):
    """b (m,) <- S^-1 b in place, L the lower Cholesky factor of S."""
    m = b.size
    for i in range(m):
        s = b[i]
        for j in range(i):
            s -= L[i, j] * b[j]
        b[i] = s / L[i, i]
    for i in range(m - 1, -1, -1):
        s = b[i]
        for j in range(i + 1, m):
            s -= L[j, i] * b[j]
        b[i] = s / L[i, i]


@jit
def cho_solve_rows_into(L, B):
    """Each row b of B (r, m) <- S^-1 b in place (``cho_solve_into``'s arithmetic), L the lower
    Cholesky factor of S: one call for the gain's rows, where a call and a row's view each (both
    counting references) cost more than the solve."""
    m = B.shape[1]
    for c in range(B.shape[0]):
        for i in range(m):
            s = B[c, i]
            for j in range(i):
                s -= L[i, j] * B[c, j]
            B[c, i] = s / L[i, i]
        for i in range(m - 1, -1, -1):
            s = B[c, i]
            for j in range(i + 1, m):
                s -= L[j, i] * B[c, j]
            B[c, i] = s / L[i, i]


@jit
def stacked_quadratic(L, y, scratch):
    """v' S^-1 v of the innovations y (p, 3) stacked as v (3p,), L the lower Cholesky factor of S;
    scratch (3p,)."""
    p = y.shape[0]
    for i in range(p):
        for a in range(3):
            scratch[3 * i + a] = y[i, a]
    cho_solve_into(L, scratch)
    total = 0.0
    for i in range(p):
        for a in range(3):
            total += y[i, a] * scratch[3 * i + a]
    return total


@jit
def innovation_system_into(P, H, R, PHt, S):
    """P H' (n, 3p) and S = H P H' + R (3p, 3p) of pairs with Jacobians H (p, 3, n) and noise R
    (p, 3, 3), S symmetric."""
    if P.shape[0] == 6:                   # the state's size a constant: ``innovation_system_of_size``
        innovation_system_of_size(P, H, R, PHt, S, 6)
    else:
        innovation_system_of_size(P, H, R, PHt, S, SE2_DIM)


@inlined
def innovation_system_of_size(P, H, R, PHt, S, n):
    """``innovation_system_into`` of a state of n entries, n a constant at each call: its loops unrolled."""
    p = H.shape[0]
    m = 3 * p
    for c in range(n):
        for r in range(m):
            s = 0.0
            for d in range(n):
                s += P[c, d] * H[r // 3, r % 3, d]
            PHt[c, r] = s
    for r in range(m):
        i, a = r // 3, r % 3
        for q in range(r, m):
            s = 0.0
            for c in range(n):
                s += H[i, a, c] * PHt[c, q]
            if q // 3 == i:
                s += 0.5 * (R[i, a, q % 3] + R[i, q % 3, a])
            S[r, q] = s
            S[q, r] = s


@jit
def gain_into(P, H, R, PHt, S, L, K):
    """The textbook gain K = P H' S^-1 (n, 3p), with S = H P H' + R and its lower Cholesky
    factor L (3p, 3p), of pairs with Jacobians H (p, 3, n) and noise R (p, 3, 3)."""
    n = P.shape[0]                        # the state's size: 6 (Euler), 3 (planar)
    innovation_system_into(P, H, R, PHt, S)
    cholesky_into(S, L)
    for c in range(n):
        for r in range(PHt.shape[1]):
            K[c, r] = PHt[c, r]
    cho_solve_rows_into(L, K)                                       # S symmetric: row c of P H' S^-1


@jit
def covariance_posterior_into(P, K, H, R, out, I_KH, scratch):
    """Joseph form (I - K H) P (I - K H)' + K R K' into out (n, n), its upper triangle mirrored;
    H (p, 3, n) stacked as K's columns; I_KH and scratch (n, n)."""
    if P.shape[0] == 6:                   # the state's size a constant: ``covariance_posterior_of_size``
        covariance_posterior_of_size(P, K, H, R, out, I_KH, scratch, 6)
    else:
        covariance_posterior_of_size(P, K, H, R, out, I_KH, scratch, SE2_DIM)


@inlined
def covariance_posterior_of_size(P, K, H, R, out, I_KH, scratch, n):
    """``covariance_posterior_into`` of a state of n entries, n a constant at each call: its loops unrolled."""
    p = H.shape[0]
    for c in range(n):
        for d in range(n):
            s = 0.0
            for r in range(3 * p):
                s += K[c, r] * H[r // 3, r % 3, d]
            I_KH[c, d] = (1.0 if c == d else 0.0) - s
    for c in range(n):
        for d in range(n):
            s = 0.0
            for q in range(n):
                s += I_KH[c, q] * P[q, d]
            scratch[c, d] = s
    for c in range(n):
        for d in range(c, n):
            s = 0.0
            for q in range(n):
                s += scratch[c, q] * I_KH[d, q]
            for i in range(p):
                for a in range(3):
                    k_ca = K[c, 3 * i + a]
                    for b in range(3):
                        s += k_ca * R[i, a, b] * K[d, 3 * i + b]
            out[c, d] = s
            out[d, c] = s


@jit
def information_into(P, H, R_inverse, R_inverse_H, information, M, pivots, AP):
    """Of pairs with Jacobians H (p, 3, n) and noise information R_inverse (p, 3, 3): R^-1 H
    (p, 3, n), Lambda (n, n), I + P Lambda factored into (M, pivots) by ``lu_factor``, and
    A P = (I + P Lambda)^-1 P (n, n), symmetrized. Its loops count to 6, the larger state's size
    (unrolled), the smaller state's entries skipped (``gradient_into``), in the order of a loop to
    n: a dispatch by size to two inlined copies counted a reference to each of its 8 arrays
    again at each call (28 operations a call against the filing's 11, docs/performance.md,
    2026-12-07 (twenty-third session))."""
    n = P.shape[0]                        # the state's size: 6 (Euler), 3 (planar)
    p = H.shape[0]
    for c in range(6):
        for d in range(6):
            if c < n and d < n:
                information[c, d] = 0.0
    for i in range(p):
        for a in range(3):
            for c in range(6):
                if c < n:
                    R_inverse_H[i, a, c] = R_inverse[i, a, 0] * H[i, 0, c] + R_inverse[i, a, 1] * H[i, 1, c] + R_inverse[i, a, 2] * H[i, 2, c]
        for a in range(3):
            for c in range(6):
                if c < n:
                    h = H[i, a, c]
                    for d in range(c, 6):
                        if d < n:
                            information[c, d] += h * R_inverse_H[i, a, d]
    for c in range(6):
        for d in range(c):
            if c < n:
                information[c, d] = information[d, c]
    finite = True
    for c in range(6):
        for d in range(6):
            if c < n and d < n:
                s = 0.0
                for q in range(6):
                    if q < n:
                        s += P[c, q] * information[q, d]
                M[c, d] = (1.0 if c == d else 0.0) + s
                finite = finite and np.isfinite(M[c, d])
                AP[c, d] = P[c, d]
    if not finite:
        raise FloatingPointError("innovation covariance is not positive definite")
    lu_factor(M, pivots)
    lu_solve(M, pivots, AP)
    for c in range(6):
        for d in range(c):
            if c < n:
                AP[c, d] = AP[d, c] = 0.5 * (AP[c, d] + AP[d, c])


@jit
def gradient_into(R_inverse_H, y, g):
    """g = sum H_i' R_i^-1 y_i (n,) for innovations y (p, 3)."""
    n = g.shape[0]                        # the state's size: 6 (Euler), 3 (planar)
    for c in range(n):
        g[c] = 0.0
    for i in range(y.shape[0]):
        for a in range(3):
            for c in range(6):            # unrolled, the smaller state's entries skipped (``information_into``)
                if c < n:
                    g[c] += R_inverse_H[i, a, c] * y[i, a]


@jit
def block_quadratic(y, R_inverse):
    """sum y_i' R_i^-1 y_i."""
    total = 0.0
    for i in range(y.shape[0]):
        for a in range(3):
            for b in range(3):
                total += y[i, a] * R_inverse[i, a, b] * y[i, b]
    return total


@jit
def plain_step_into(AP, g, step):
    """step = A P g (n,), and g' A P g."""
    n = g.shape[0]                        # the state's size: 6 (Euler), 3 (planar)
    total = 0.0
    for c in range(n):
        s = 0.0
        for d in range(6):                # unrolled, the smaller state's entries skipped (``information_into``)
            if d < n:
                s += AP[c, d] * g[d]
        step[c] = s
        total += g[c] * s
    return total


@jit
def gain_step_into(K, y, step):
    """step = K v (n,), v the innovations y (p, 3) stacked."""
    n = step.shape[0]                        # the state's size: 6 (Euler), 3 (planar)
    for c in range(n):
        s = 0.0
        for i in range(y.shape[0]):
            for a in range(3):
                s += K[c, 3 * i + a] * y[i, a]
        step[c] = s


@jit
def posterior_covariance_into(P, information, M, pivots, out, scratch):
    """A (P + P Lambda P) A' into out (n, n), symmetric positive definite by construction; I + P
    Lambda factored into (M, pivots); scratch (n, n)."""
    if P.shape[0] == 6:                   # the state's size a constant: ``posterior_covariance_of_size``
        posterior_covariance_of_size(P, information, M, pivots, out, scratch, 6)
    else:
        posterior_covariance_of_size(P, information, M, pivots, out, scratch, SE2_DIM)


@inlined
def posterior_covariance_of_size(P, information, M, pivots, out, scratch, n):
    """``posterior_covariance_into`` of a state of n entries, n a constant at each call: its loops unrolled."""
    for c in range(n):                                              # P Lambda
        for d in range(n):
            s = 0.0
            for q in range(n):
                s += P[c, q] * information[q, d]
            scratch[c, d] = s
    for c in range(n):                                              # P + P Lambda P
        for d in range(n):
            s = 0.0
            for q in range(n):
                s += scratch[c, q] * P[q, d]
            out[c, d] = P[c, d] + s
    lu_solve(M, pivots, out)                                        # A (P + P Lambda P)
    for c in range(n):
        for d in range(c):
            out[c, d], out[d, c] = out[d, c], out[c, d]
    lu_solve(M, pivots, out)                                        # A (A (P + P Lambda P))' = (... A')'
    for c in range(n):
        for d in range(c):
            out[c, d] = out[d, c] = 0.5 * (out[c, d] + out[d, c])


@jit
def innovation_cost(P, H, R, R_inverse, y):
    """``y' S^-1 y + ln det S - ln det R`` of stacked innovations y (p, 3) with Jacobians H and
    noise R, R_inverse (p, 3, 3): twice the negative log-likelihood relative to the noise's own
    spread (the beam's units)."""
    n = P.shape[0]                        # the state's size: 6 (Euler), 3 (planar)
    p = y.shape[0]
    m = 3 * p
    if 3 * p <= n:                          # S (3p x 3p) no larger than the state's information
        PHt, S, L = np.empty((n, m)), np.empty((m, m)), np.empty((m, m))
        innovation_system_into(P, H, R, PHt, S)
        cholesky_into(S, L)
        log_det = 0.0
        for i in range(m):
            log_det += 2.0 * math.log(L[i, i])
        for i in range(p):
            log_det -= log_det_3x3(R[i])
        return stacked_quadratic(L, y, np.empty(m)) + log_det
    R_inverse_H, information = np.empty((p, 3, n)), np.empty((n, n))
    M, pivots, AP, g = np.empty((n, n)), np.empty(n, np.int64), np.empty((n, n)), np.empty(n)
    information_into(P, H, R_inverse, R_inverse_H, information, M, pivots, AP)
    sign, log_det = lu_log_det(M, pivots)
    if sign <= 0.0:
        raise FloatingPointError("innovation covariance is not positive definite")
    gradient_into(R_inverse_H, y, g)
    return block_quadratic(y, R_inverse) - plain_step_into(AP, g, np.empty(n)) + log_det


@jit
def correction(P, H, R, R_inverse, y):
    """K y of one EKF update."""
    n = P.shape[0]                        # the state's size: 6 (Euler), 3 (planar)
    p = y.shape[0]
    m = 3 * p
    step = np.empty(n)
    if 3 * p <= n:                          # S (3p x 3p) no larger than the state's information
        K = np.empty((n, m))
        gain_into(P, H, R, np.empty((n, m)), np.empty((m, m)), np.empty((m, m)), K)
        gain_step_into(K, y, step)
        return step
    R_inverse_H, information = np.empty((p, 3, n)), np.empty((n, n))
    M, pivots, AP, g = np.empty((n, n)), np.empty(n, np.int64), np.empty((n, n)), np.empty(n)
    information_into(P, H, R_inverse, R_inverse_H, information, M, pivots, AP)
    gradient_into(R_inverse_H, y, g)
    plain_step_into(AP, g, step)
    return step


@jit
def prior_quadratic(P, d, M, pivots, b):
    """d' P^-1 d for d (n,); M (n, n), pivots (n,) and b (n, 1) scratch."""
    n = P.shape[0]                        # the state's size: 6 (Euler), 3 (planar)
    for c in range(n):
        b[c, 0] = d[c]
        for q in range(n):
            M[c, q] = P[c, q]
    lu_factor(M, pivots)
    lu_solve(M, pivots, b)
    total = 0.0
    for c in range(n):
        total += d[c] * b[c, 0]
    return total


@jit
def iterated_update(x, P, z, R, R_inverse, landmark_xyz, pair_camera, camera_R, camera_t, camera_K,
                    iterations, z_hat, H, start, map_cost, step_sigma, in_front):
    """The iterated EKF update of (x, P) with p pairs: measurements z (p, 3), noise information
    R_inverse (p, 3, 3), landmarks (p, 3) seen by cameras pair_camera (p,); z_hat, H: the
    predictions at x. With a ``start`` (n,) (none: size 0) the iterations after the first
    linearize first at start (a state near the MAP estimate, where the prior is too far for
    Gauss-Newton). ``map_cost``: compute the MAP cost at x+ (one more prediction and a
    factorization of P; ``in_front``: ``map_cost_into``'s); without it, NaN (scratch updates never read it).
    ``step_sigma``: also stop once a step moved the state by less than this many prior sigmas (``ekf.update``'s).

    Returns (x+ (n,), P+ (n, n), NIS at the prior, MAP cost at x+ (or NaN), y (p, 3) the innovation
    at the prior)."""
    n = x.shape[0]                        # the state's size: 6 (Euler), 3 (planar)
    p, m = z.shape[0], 3 * z.shape[0]
    few = 3 * p <= n                                                 # S (3p x 3p) no larger than the state's information (n x n)
    # every linearization's scratch, allocated once, only its form's (docs/performance.md, 2026-12-07 (22nd))
    M, pivots = np.empty((n, n)), np.empty(n, np.int64)               # both forms: the MAP cost's scratch
    if few:
        PHt, S, L, K = np.empty((n, m)), np.empty((m, m)), np.empty((m, m)), np.empty((n, m))
    else:
        R_inverse_H, information, AP, g = np.empty((p, 3, n)), np.empty((n, n)), np.empty((n, n)), np.empty(n)
    z_hat_i, H_i, r = np.empty((p, 3)), np.empty((p, 3, n)), np.empty((p, 3))
    d_position, frame = np.empty((camera_R.shape[0], 3, 3)), (np.empty((3, 3)), np.empty((3, 3)), np.empty(3))
    delta, step, moved, x_i, y_prior = np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty((p, 3))
    for i in range(p):                                               # a marker's psi wrapped (``wrapped_residual``)
        kind = camera_K[pair_camera[i], 4]
        for a in range(3):
            y_prior[i, a] = wrapped_residual(kind, a, z[i, a] - z_hat[i, a])
    if few:
        gain_into(P, H, R, PHt, S, L, K)
        nis = stacked_quadratic(L, y_prior, step[:m])                # NIS = y' S^-1 y; step (n >= m) as scratch: written below
        gain_step_into(K, y_prior, delta)
    else:
        information_into(P, H, R_inverse, R_inverse_H, information, M, pivots, AP)
        gradient_into(R_inverse_H, y_prior, g)
        nis = block_quadratic(y_prior, R_inverse) - plain_step_into(AP, g, delta)   # K y = A P g
    retract_into(x, delta, x_i)                                      # x+ = x [+] K y
    if start.size and iterations >= 2:
        for b in range(n):
            x_i[b] = start[b]
        difference_into(start, x, delta)
    H_last = H                                                       # the linearization of the gain
    for _ in range(iterations - 1):
        observe_pairs_into(x_i, landmark_xyz, pair_camera, camera_R, camera_t, camera_K, z_hat_i, H_i, d_position, frame)
        difference_into(x_i, x, moved)
        for i in range(p):                                           # z - h(x_i) + H_i (x_i [-] x)
            for a in range(3):
                s = wrapped_residual(camera_K[pair_camera[i], 4], a, z[i, a] - z_hat_i[i, a])
                for b in range(6):                                   # unrolled, the smaller state's columns skipped
                    if b < n:
                        s += H_i[i, a, b] * moved[b]
                r[i, a] = s
        if few:
            gain_into(P, H_i, R, PHt, S, L, K)
            gain_step_into(K, r, step)
        else:
            information_into(P, H_i, R_inverse, R_inverse_H, information, M, pivots, AP)
            gradient_into(R_inverse_H, r, g)
            plain_step_into(AP, g, step)
        H_last = H_i
        if stepped_into(x, step, delta, x_i, P, step_sigma):
            break                                                    # the linearization no longer moves
    P_post = np.empty((n, n))
    if few:                                                          # M as scratch: map_cost_into writes it whole first
        covariance_posterior_into(P, K, H_last, R, P_post, M, np.empty((n, n)))
    else:                                                            # AP as scratch: read no more
        posterior_covariance_into(P, information, M, pivots, P_post, AP)
    cost = np.nan
    if map_cost:                                                     # into the iterations' buffers (H_last is read above)
        cost = map_cost_of(x_i, x, P, z, R_inverse, landmark_xyz, pair_camera, camera_R, camera_t, camera_K,
                           z_hat_i, H_i, r, d_position, frame, moved, M, pivots, in_front)
    return x_i, P_post, nis, cost, y_prior


@jit
def map_cost_into(x_post, x, P, z, R_inverse, landmark_xyz, pair_camera, camera_R, camera_t, camera_K,
                  z_hat, H, r, d_position, frame, moved, M, pivots, in_front):
    """``map_cost_of`` as the restarts call it (``damped_start``, ``restart_cost``): compiled once."""
    return map_cost_of(x_post, x, P, z, R_inverse, landmark_xyz, pair_camera, camera_R, camera_t, camera_K,
                       z_hat, H, r, d_position, frame, moved, M, pivots, in_front)


# Inlined into ``iterated_update``, its one call at every update: called, it counted a reference
# to each of its 20 arrays on entry and on return (40 operations an update; inlined, numba prunes
# most of them: 36 fewer a pose of the 300-pose depth world, docs/performance.md, 2026-12-07
# (twenty-third session))
@inlined
def map_cost_of(x_post, x, P, z, R_inverse, landmark_xyz, pair_camera, camera_R, camera_t, camera_K,
                z_hat, H, r, d_position, frame, moved, M, pivots, in_front):
    """The MAP cost at x_post of the update of prior (x, P) with the pairs of ``iterated_update``
    (its arguments of the same names): the prior's quadratic of x_post [-] x plus each pair's
    y' R^-1 y at x_post; with ``in_front`` (the estimate's update), infinite where x_post puts a
    landmark behind the camera that saw it and the prior x does not (``all_in_front``; the numpy
    twin: ``ekf.posterior_cost``, which says why). The rest is scratch: z_hat (p, 3), H (p, 3, n), r (p, 3), d_position, frame
    (``observe_pairs_into``'s), moved (n,), M (n, n), pivots (n,)."""
    n = x.shape[0]
    # predicted first: the prediction leaves x_post's frame in ``frame``, which the test reads
    # (not computed again: its rotation's sines and cosines, at every update)
    observe_pairs_into(x_post, landmark_xyz, pair_camera, camera_R, camera_t, camera_K, z_hat, H, d_position, frame)
    if in_front and not all_in_front_of_frame(frame, landmark_xyz, pair_camera, camera_R, camera_t, camera_K):
        if all_in_front(x, landmark_xyz, pair_camera, camera_R, camera_t, camera_K, frame):
            return np.inf
    for i in range(z.shape[0]):
        for a in range(3):
            r[i, a] = wrapped_residual(camera_K[pair_camera[i], 4], a, z[i, a] - z_hat[i, a])
    difference_into(x_post, x, moved)
    return prior_quadratic(P, moved, M, pivots, np.empty((n, 1))) + block_quadratic(r, R_inverse)


@jit
def all_in_front(x, landmark_xyz, pair_camera, camera_R, camera_t, camera_K, frame):
    """Whether state x puts every pair's landmark in front of the camera that saw it
    (``camera.in_front_of``); frame: ``robot_frame_into``'s scratch."""
    robot_frame_into(x, frame)
    return all_in_front_of_frame(frame, landmark_xyz, pair_camera, camera_R, camera_t, camera_K)


@jit
def all_in_front_of_frame(frame, landmark_xyz, pair_camera, camera_R, camera_t, camera_K):
    """``all_in_front`` of the state whose frame (``robot_frame_into``'s) is ``frame``."""
    R, t = frame[0], frame[2]
    for i in range(landmark_xyz.shape[0]):
        c = pair_camera[i]
        if not in_front_of(R, t, camera_R[c], camera_t[c], camera_K[c, 4], landmark_xyz, i):
            return False
    return True


@jit
def damped_start(x, P, z, R, R_inverse, landmark_xyz, pair_camera, camera_R, camera_t, camera_K):
    """The MAP estimate (n,) of the update of (x, P) with the pairs of ``iterated_update`` (its
    arguments of the same names) by Levenberg-Marquardt from x, damped in the prior's metric; the
    numpy twin is ``ekf.damped_gauss_newton``, which says why and how."""
    n, p = x.shape[0], z.shape[0]
    z_hat, H, r = np.empty((p, 3)), np.empty((p, 3, n)), np.empty((p, 3))
    cost_z_hat, cost_H, cost_r = np.empty((p, 3)), np.empty((p, 3, n)), np.empty((p, 3))   # map_cost_into's scratch
    d_position, frame = np.empty((camera_R.shape[0], 3, 3)), (np.empty((3, 3)), np.empty((3, 3)), np.empty(3))
    moved, M, pivots = np.empty(n), np.empty((n, n)), np.empty(n, np.int64)
    centre, target, d, candidate, x_i = np.empty(n), np.empty(n), np.empty(n), np.empty(n), x.copy()
    cams = (camera_R, camera_t, camera_K)
    cost_i = map_cost_into(x_i, x, P, z, R_inverse, landmark_xyz, pair_camera, *cams, cost_z_hat, cost_H, cost_r, d_position, frame,
                           moved, M, pivots, TRUE)
    damping = DAMPING_START
    for _ in range(MAX_LINEARIZATIONS):
        observe_pairs_into(x_i, landmark_xyz, pair_camera, *cams, z_hat, H, d_position, frame)
        lowered = False
        for _ in range(DAMPING_RAISES):
            shrink = 1.0 / (1.0 + damping)
            difference_into(x, x_i, moved)
            for b in range(n):
                moved[b] *= shrink
            retract_into(x_i, moved, centre)                         # x_i moved toward x by shrink
            difference_into(x_i, centre, moved)
            for i in range(p):                                       # z - h(x_i) + H_i (x_i [-] centre)
                for a in range(3):
                    s = wrapped_residual(camera_K[pair_camera[i], 4], a, z[i, a] - z_hat[i, a])
                    for b in range(n):
                        s += H[i, a, b] * moved[b]
                    r[i, a] = s
            retract_into(centre, correction(P * shrink, H, R, R_inverse, r), target)
            difference_into(target, x_i, d)                          # the damped step
            retract_into(x_i, d, candidate)
            cost = map_cost_into(candidate, x, P, z, R_inverse, landmark_xyz, pair_camera, *cams, cost_z_hat, cost_H, cost_r,
                                 d_position, frame, moved, M, pivots, TRUE)
            if cost < cost_i:
                lowered = True
                damping *= 0.1
                break
            damping *= 10.0
        if not lowered:
            break                                                    # no damping lowers the cost: a minimum
        step = 0.0
        for b in range(n):
            x_i[b] = candidate[b]
            step = max(step, abs(d[b]))
        cost_i = cost
        if step < CONVERGED:
            break
    return x_i


# by its address (``_jit.called``): linked, its module (11,000 LLVM instructions) was generated
# again in ``updated``'s, for a restart that few updates reach
damped_start_at = called(damped_start)


@inlined
def restart_cost(scene, x, P, z, R_inverse, landmark_xyz, pair_camera, x_post):
    """``map_cost_into`` with scratch of its own: the cost of an update ``updated`` compares with
    a restart's, where the update was run without it (rare: an innovation beyond its bound)."""
    n, p = x.shape[0], z.shape[0]
    z_hat, H, r = np.empty((p, 3)), np.empty((p, 3, n)), np.empty((p, 3))
    d_position, frame = np.empty((scene.camera_R.shape[0], 3, 3)), (np.empty((3, 3)), np.empty((3, 3)), np.empty(3))
    moved, M, pivots = np.empty(n), np.empty((n, n)), np.empty(n, np.int64)
    return map_cost_into(x_post, x, P, z, R_inverse, landmark_xyz, pair_camera, scene.camera_R, scene.camera_t, scene.camera_K,
                         z_hat, H, r, d_position, frame, moved, M, pivots, FALSE)


@inlined
def pair_model(scene):
    """What an update and a pair's cost read of the scene (``types.PairModel``), to pass
    ``updated`` (and the beam's ``condition``) instead of the scene: a caller that updates often
    builds it once."""
    return PairModel(scene.z, scene.obs_camera, scene.obs_dof, scene.nis_bound, scene.obs_gate, scene.landmark_xyz,
                     scene.camera_R, scene.camera_t, scene.camera_K, scene.R_assoc, scene.R_assoc_inverse, scene.log_det_R,
                     scene.point, scene.point_cov, scene.point_cov_inverse, scene.log_det_point_cov)


@inlined
def point_step(scene, x, P, obs, z_hat, H):
    """x after one EKF update with the pairs' measurements as camera-frame points, where the model
    is nearly linear in the position: where Gauss-Newton in (u, v, depth) from a wide prior
    stalls, the iterations restart from here. ``scene``: a ``types.PairModel``."""
    n = x.shape[0]                        # the state's size: 6 (Euler), 3 (planar)
    p = obs.size
    Hp = np.empty((p, 3, n))
    y = np.empty((p, 3))
    R = np.empty((p, 3, 3))
    R_inverse = np.empty((p, 3, 3))
    for i in range(p):
        o = obs[i]
        K = scene.camera_K[scene.obs_camera[o]]
        if K[4] != DEPTH:  # no point (``measurement.judged_as_point``): the pair as it is
            for a in range(3):
                y[i, a] = wrapped_residual(K[4], a, scene.z[o, a] - z_hat[i, a])
                for b in range(3):
                    R[i, a, b], R_inverse[i, a, b] = scene.R_assoc[o, a, b], scene.R_assoc_inverse[o, a, b]
                for b in range(n):
                    Hp[i, a, b] = H[i, a, b]
            continue
        p_hat, J = back_project(z_hat[i], K)
        JH = mm(J, H[i])
        for a in range(3):
            y[i, a] = scene.point[o, a] - p_hat[a]
            for b in range(3):
                R[i, a, b], R_inverse[i, a, b] = scene.point_cov[o, a, b], scene.point_cov_inverse[o, a, b]
            for b in range(n):
                Hp[i, a, b] = JH[a, b]
    return retract(x, correction(P, Hp, R, R_inverse, y))


@inlined
def pair_arrays(scene, obs, landmarks, noise, noise_inverse):
    """``iterated_update``'s pairs of observations obs (p,) and landmarks (p,) of the scene
    (``pair_model``), weighed by their rows of noise and noise_inverse: (z (p, 3), R, R_inverse
    (p, 3, 3), landmark_xyz (p, 3 or 4), pair_camera (p,))."""
    p = obs.size
    z = np.empty((p, 3))
    R = np.empty((p, 3, 3))
    R_inverse = np.empty((p, 3, 3))
    landmark_xyz = np.empty((p, scene.landmark_xyz.shape[1]))   # with a marker's heading (``SceneArrays``)
    pair_camera = np.empty(p, np.int64)
    for i in range(p):
        o = obs[i]
        for a in range(3):
            z[i, a] = scene.z[o, a]
            for b in range(3):
                R[i, a, b], R_inverse[i, a, b] = noise[o, a, b], noise_inverse[o, a, b]
        pair_camera[i] = scene.obs_camera[o]
        for a in range(landmark_xyz.shape[1]):
            landmark_xyz[i, a] = scene.landmark_xyz[landmarks[i], a]
    return z, R, R_inverse, landmark_xyz, pair_camera


@entry
def updated(scene, iterations, x, P, obs, landmarks, z_hat, H, noise, noise_inverse, start, map_cost, step_sigma):
    """The stacked (iterated) update of (x, P) with pairs (obs (p,), landmarks (p,)) whose
    predictions at x are z_hat, H, each weighed by its observation's row of ``noise`` (K, 3, 3)
    and ``noise_inverse``: the file's (``scene.R_file``) for the estimate, the floored noise
    association judges pairs by (``scene.R_assoc``) for the scratch filters that decide it.
    ``scene``: what the update reads of the scene (``pair_model``: a ``types.PairModel``).

    Where the innovation is beyond the 99.9% chi^2 bound at the prior's linearization, the
    iterations also run from ``point_step``, and from ``start`` (n,) when given (size 0: none); the
    posterior with the lower MAP cost is kept. Where that cost is beyond the same bound, the
    estimate's update (``map_cost``) also iterates from ``damped_start`` (``stacked_update.StackedUpdate.damped``: plain
    Gauss-Newton from a prior as wide as the landmarks' depth stops short of the MAP estimate, or
    runs off). ``map_cost``: return the kept posterior's MAP cost
    (the filter's statistic); without it that is NaN where no restart ran (the beam's scratch
    updates, which read only the state: a prediction and a factorization saved each).
    ``step_sigma``: ``iterated_update``'s (0 but for the beam's one-ray updates).
    Returns as ``iterated_update``."""
    cams = (scene.camera_R, scene.camera_t, scene.camera_K)
    none = start[:0]                                                 # no start: a view, not an array allocated an update
    costed = map_cost or (start.size > 0 and iterations >= 2)         # a start restarts: compared below
    if obs.size == 1 and not costed:                                 # the beam's settling of a child: in scalars, bit for bit
        o = obs[0]
        best = one_pair_update(x, P, scene.z, o, scene.landmark_xyz, landmarks[0], scene.obs_camera[o], *cams, noise, iterations,
                               z_hat, H, step_sigma)
    else:
        best = iterated_update(x, P, *pair_arrays(scene, obs, landmarks, noise, noise_inverse), *cams, iterations, z_hat, H, none,
                               costed, step_sigma, map_cost)
    dof = 0
    for o in obs:
        dof += scene.obs_dof[o]
    bound = scene.nis_bound[dof]
    if iterations < 2 or not (start.size or best[2] > bound or (map_cost and best[3] > bound)):
        return best
    z, R, R_inverse, landmark_xyz, pair_camera = pair_arrays(scene, obs, landmarks, noise, noise_inverse)   # for the restarts
    if not costed:                                                   # compared below: the cost iterated_update left out
        best = (best[0], best[1], best[2], restart_cost(scene, x, P, z, R_inverse, landmark_xyz, pair_camera, best[0]), best[4])
    starts = (start, point_step(scene, x, P, obs, z_hat, H)) if best[2] > bound else (start, none)
    for s in starts:
        if s.size:
            again = iterated_update(x, P, z, R, R_inverse, landmark_xyz, pair_camera, *cams, iterations, z_hat, H, s, TRUE,
                                    step_sigma, map_cost)
            if again[3] < best[3]:
                best = (again[0], again[1], best[2], again[3], best[4])
    if map_cost and best[3] > bound:                                 # the estimate's: not the MAP estimate, or no MAP agrees
        s = damped_start_at(x, P, z, R, R_inverse, landmark_xyz, pair_camera, *cams)
        again = iterated_update(x, P, z, R, R_inverse, landmark_xyz, pair_camera, *cams, iterations, z_hat, H, s, TRUE,
                                step_sigma, map_cost)
        if again[3] < best[3]:
            best = (again[0], again[1], best[2], again[3], best[4])
    return best


# ``updated`` as the other kernels call it (the beam's, the chain check's, the filter's): by its
# address, compiled once in its own module, where linked it was optimized and generated again in
# four more (``_jit.called``)
updated_at = called(updated)
