"""The stacked, iterated EKF update in information form, and what the localizer wraps around it.

A pose's pairs are independent measurements (block-diagonal R), so the update adds their
information to the prior's, a 6x6 system whatever the number of pairs:

    Lambda = sum H_i' R_i^-1 H_i,  A = (I + P Lambda)^-1
    K y  = A P g,  g = sum H_i' R_i^-1 y_i                          (correction)
    y' S^-1 y = sum y_i' R_i^-1 y_i - g' A P g                      (NIS, Woodbury)
    P+ = A (P + P Lambda P) A'                                      (Joseph form, I - K H = A)
    ln det S - ln det R = ln det (I + P Lambda)                     (determinant lemma)

Iterations (Bell & Cathey 1993): ``x_{i+1} = x [+] K_i (z - h(x_i) + H_i (x_i [-] x))`` with K_i
at x_i; the covariance uses the last linearization. The numpy twin is ``camloc.ekf.update``.
"""

from __future__ import annotations

import numpy as np

from camloc.kernels._jit import jit
from camloc.kernels.camera import back_project, observe_pairs
from camloc.kernels.rotation import difference, retract
from camloc.kernels.small import mm, mv, solve
from camloc.kernels.sym3 import log_det as log_det_3x3

# Iterated updates stop when the correction changes by less than this (metres / radians).
CONVERGED = 1e-6


@jit
def information_gain(P, H, R_inverse):
    """(R^-1 H (p, 3, 6), Lambda (6, 6), I + P Lambda (6, 6), A P (6, 6)) of pairs with
    Jacobians H (p, 3, 6) and noise information R_inverse (p, 3, 3)."""
    p = H.shape[0]
    R_inverse_H = np.zeros((p, 3, 6))
    information = np.zeros((6, 6))
    for i in range(p):
        for a in range(3):
            for b in range(3):
                r = R_inverse[i, a, b]
                for c in range(6):
                    R_inverse_H[i, a, c] += r * H[i, b, c]
        for a in range(3):
            for c in range(6):
                h = H[i, a, c]
                for d in range(c, 6):
                    information[c, d] += h * R_inverse_H[i, a, d]
    for c in range(6):
        for d in range(c):
            information[c, d] = information[d, c]
    I_P_information = np.eye(6) + mm(P, information)
    if not np.all(np.isfinite(I_P_information)):
        raise FloatingPointError("innovation covariance is not positive definite")
    posterior = solve(I_P_information, P)
    return R_inverse_H, information, I_P_information, 0.5 * (posterior + posterior.T)


@jit
def cho_solve(L, B):
    """S^-1 B from the lower Cholesky factor L of S (m, m); B (m, k)."""
    m, k = B.shape
    X = B.copy()
    for c in range(k):
        for i in range(m):
            s = X[i, c]
            for j in range(i):
                s -= L[i, j] * X[j, c]
            X[i, c] = s / L[i, i]
        for i in range(m - 1, -1, -1):
            s = X[i, c]
            for j in range(i + 1, m):
                s -= L[j, i] * X[j, c]
            X[i, c] = s / L[i, i]
    return X


@jit
def covariance_gain(P, H, R):
    """The textbook gain for few pairs (3p <= 6 rows, where the (m, m) innovation covariance is
    no larger than the state's information and better conditioned when the noise is tiny):
    (K = P H' S^-1 (6, m), S = H P H' + R (m, m), its Cholesky factor L, H stacked (m, 6))."""
    p = H.shape[0]
    m = 3 * p
    Hs = np.ascontiguousarray(H).reshape(m, 6)
    S = mm(mm(Hs, P), Hs.T)
    for i in range(p):
        S[3 * i:3 * i + 3, 3 * i:3 * i + 3] += R[i]
    S = 0.5 * (S + S.T)
    L = np.linalg.cholesky(S)
    K = cho_solve(L, mm(Hs, P)).T.copy()
    return K, S, L, Hs


@jit
def covariance_posterior(P, K, Hs, R):
    """Joseph form (I - K H) P (I - K H)' + K R K'."""
    I_KH = np.eye(6) - mm(K, Hs)
    out = mm(mm(I_KH, P), I_KH.T)
    p = R.shape[0]
    for i in range(p):
        Ki = np.ascontiguousarray(K[:, 3 * i:3 * i + 3])
        out += mm(mm(Ki, R[i]), Ki.T)
    return 0.5 * (out + out.T)


@jit
def stacked(y):
    return np.ascontiguousarray(y).reshape(-1)


@jit
def gradient(R_inverse_H, y):
    """g = sum H_i' R_i^-1 y_i (6,) for innovations y (p, 3)."""
    g = np.zeros(6)
    for i in range(y.shape[0]):
        for a in range(3):
            for c in range(6):
                g[c] += R_inverse_H[i, a, c] * y[i, a]
    return g


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
def normalized_innovation(y, R_inverse, R_inverse_H, posterior_plain):
    """y' S^-1 y = y' R^-1 y - g' A P g."""
    g = gradient(R_inverse_H, y)
    return block_quadratic(y, R_inverse) - g @ mv(posterior_plain, g)


@jit
def posterior_covariance(P, information, I_P_information):
    """A (P + P Lambda P) A', symmetric positive definite by construction."""
    spread = solve(I_P_information, P + mm(mm(P, information), P))
    out = solve(I_P_information, np.ascontiguousarray(spread.T)).T
    return 0.5 * (out + out.T)


@jit
def innovation_cost(P, H, R, R_inverse, y):
    """``y' S^-1 y + ln det S - ln det R`` of stacked innovations y (p, 3) with Jacobians H and
    noise R, R_inverse (p, 3, 3): twice the negative log-likelihood relative to the noise's own
    spread (the beam's units)."""
    if y.shape[0] <= 2:
        K, S, L, Hs = covariance_gain(P, H, R)
        v = stacked(y)
        log_det = 0.0
        for i in range(L.shape[0]):
            log_det += 2.0 * np.log(L[i, i])
        for i in range(R.shape[0]):
            log_det -= log_det_3x3(R[i])
        return v @ cho_solve(L, v.reshape(-1, 1)).ravel() + log_det
    R_inverse_H, _, I_P_information, posterior_plain = information_gain(P, H, R_inverse)
    sign, log_det = np.linalg.slogdet(I_P_information)
    if sign <= 0.0:
        raise FloatingPointError("innovation covariance is not positive definite")
    return normalized_innovation(y, R_inverse, R_inverse_H, posterior_plain) + log_det


@jit
def correction(P, H, R, R_inverse, y):
    """K y of one EKF update."""
    if y.shape[0] <= 2:
        return mv(covariance_gain(P, H, R)[0], stacked(y))
    R_inverse_H, _, _, posterior_plain = information_gain(P, H, R_inverse)
    return mv(posterior_plain, gradient(R_inverse_H, y))


@jit
def posterior_cost(x_post, x, P, z, R_inverse, landmark_xyz, pair_camera, camera_R, camera_t, camera_K):
    """The MAP cost ``d' P^-1 d + r' R^-1 r`` of the posterior x_post: d its correction from the
    prior x, r the residual ``z - h(x_post)``; chi^2 with 3p degrees of freedom at the MAP."""
    moved = difference(x_post, x)
    z_hat, _ = observe_pairs(x_post, landmark_xyz, pair_camera, camera_R, camera_t, camera_K)
    return moved @ solve(P, moved).ravel() + block_quadratic(z - z_hat, R_inverse)


@jit
def iterated_update(x, P, z, R, R_inverse, landmark_xyz, pair_camera, camera_R, camera_t, camera_K,
                    iterations, z_hat, H, start):
    """The iterated EKF update of (x, P) with p pairs: measurements z (p, 3), noise information
    R_inverse (p, 3, 3), landmarks (p, 3) seen by cameras pair_camera (p,); z_hat, H: the
    predictions at x. With a ``start`` (6,) (none: size 0) the iterations after the first
    linearize first at start (a state near the MAP estimate, where the prior is too far for
    Gauss-Newton).

    Returns (x+ (6,), P+ (6, 6), NIS at the prior, MAP cost at x+, y (p, 3) the innovation at the
    prior)."""
    y_prior = z - z_hat
    few = z.shape[0] <= 2                                            # S (3p x 3p) no larger than 6x6
    m = 3 * z.shape[0]
    K, L, Hs = np.zeros((6, m)), np.zeros((m, m)), np.zeros((m, 6))
    information, I_P_information = np.zeros((6, 6)), np.eye(6)
    if few:
        K, S, L, Hs = covariance_gain(P, H, R)
        v = stacked(y_prior)
        nis = v @ cho_solve(L, v.reshape(-1, 1)).ravel()               # NIS = y' S^-1 y
        delta = mv(K, v)
    else:
        R_inverse_H, information, I_P_information, posterior_plain = information_gain(P, H, R_inverse)
        nis = normalized_innovation(y_prior, R_inverse, R_inverse_H, posterior_plain)
        delta = mv(posterior_plain, gradient(R_inverse_H, y_prior))   # K y
    x_i = retract(x, delta)                                          # x+ = x [+] K y
    if start.size and iterations >= 2:
        x_i, delta = start.copy(), difference(start, x)
    for _ in range(iterations - 1):
        z_hat_i, H_i = observe_pairs(x_i, landmark_xyz, pair_camera, camera_R, camera_t, camera_K)
        moved = difference(x_i, x)
        r = z - z_hat_i
        for i in range(r.shape[0]):                                  # z - h(x_i) + H_i (x_i [-] x)
            for a in range(3):
                for b in range(6):
                    r[i, a] += H_i[i, a, b] * moved[b]
        if few:
            K, S, L, Hs = covariance_gain(P, H_i, R)
            step = mv(K, stacked(r))
        else:
            R_inverse_H, information, I_P_information, posterior_plain = information_gain(P, H_i, R_inverse)
            step = mv(posterior_plain, gradient(R_inverse_H, r))
        x_i = retract(x, step)
        change = 0.0
        for b in range(6):
            change = max(change, abs(step[b] - delta[b]))
        if change < CONVERGED:
            break                                                    # the linearization no longer moves
        delta = step
    if few:
        P_post = covariance_posterior(P, K, Hs, R)
    else:
        P_post = posterior_covariance(P, information, I_P_information)
    cost = posterior_cost(x_i, x, P, z, R_inverse, landmark_xyz, pair_camera, camera_R, camera_t, camera_K)
    return x_i, P_post, nis, cost, y_prior


@jit
def point_step(scene, x, P, obs, z_hat, H):
    """x after one EKF update with the pairs' measurements as camera-frame points, where the model
    is nearly linear in the position: where Gauss-Newton in (u, v, depth) from a wide prior
    stalls, the iterations restart from here."""
    p = obs.size
    Hp = np.empty((p, 3, 6))
    y = np.empty((p, 3))
    R = np.empty((p, 3, 3))
    R_inverse = np.empty((p, 3, 3))
    for i in range(p):
        o = obs[i]
        p_hat, J = back_project(z_hat[i], scene.camera_K[scene.obs_camera[o]])
        Hp[i] = mm(J, H[i])
        y[i] = scene.point[o] - p_hat
        R[i], R_inverse[i] = scene.point_cov[o], scene.point_cov_inverse[o]
    return retract(x, correction(P, Hp, R, R_inverse, y))


@jit
def updated(scene, iterations, x, P, obs, landmarks, z_hat, H, noise, noise_inverse, start):
    """The stacked (iterated) update of (x, P) with pairs (obs (p,), landmarks (p,)) whose
    predictions at x are z_hat, H, each weighed by its observation's row of ``noise`` (K, 3, 3)
    and ``noise_inverse``: the file's (``scene.R_file``) for the estimate, the floored noise
    association judges pairs by (``scene.R_assoc``) for the scratch filters that decide it.

    Where the innovation is beyond the 99.9% chi^2 bound at the prior's linearization, the
    iterations also run from ``point_step``, and from ``start`` (6,) when given (size 0: none); the
    posterior with the lower MAP cost is kept. Returns as ``iterated_update``."""
    p = obs.size
    z = np.empty((p, 3))
    R = np.empty((p, 3, 3))
    R_inverse = np.empty((p, 3, 3))
    landmark_xyz = np.empty((p, 3))
    pair_camera = np.empty(p, np.int64)
    for i in range(p):
        z[i] = scene.z[obs[i]]
        R[i], R_inverse[i] = noise[obs[i]], noise_inverse[obs[i]]
        landmark_xyz[i] = scene.landmark_xyz[landmarks[i]]
        pair_camera[i] = scene.obs_camera[obs[i]]
    cams = (scene.camera_R, scene.camera_t, scene.camera_K)
    none = np.empty(0)
    best = iterated_update(x, P, z, R, R_inverse, landmark_xyz, pair_camera, *cams, iterations, z_hat, H, none)
    if iterations < 2 or not (start.size or best[2] > scene.nis_bound[p]):
        return best
    starts = (start, point_step(scene, x, P, obs, z_hat, H)) if best[2] > scene.nis_bound[p] else (start, none)
    for s in starts:
        if s.size:
            again = iterated_update(x, P, z, R, R_inverse, landmark_xyz, pair_camera, *cams, iterations, z_hat, H, s)
            if again[3] < best[3]:
                best = (again[0], again[1], best[2], again[3], best[4])
    return best
