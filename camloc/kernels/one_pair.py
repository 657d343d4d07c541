"""The iterated update of one observation-landmark pair (the beam settling a branched child: about
35 a pose on a pixel-only world), in scalars: ``update.iterated_update``'s textbook form (3 rows
against n = 6 or 3 state entries) with the same arithmetic in the same order, so bit for bit the
same posterior, where the general update passes its ~20 scratch arrays through a dozen compiled
calls per linearization, each counting a reference to every array on entry and on return
(docs/performance.md, 2026-12-07 (twenty-fourth session), "The one-pair update in scalars").

The 3 x 3 innovation covariance S and its Cholesky factor L are scalars, a solve with L a
function of scalars; the gain K (n, 3) and the posterior's products are local arrays, read and
written by index only; the prediction is ``camera.observe_pairs_into`` of the one pair. The
measurement model stays the scene's: every kind of sensor and both states.
"""

from __future__ import annotations

import math

import numpy as np

from camloc.kernels._jit import inlined, jit
from camloc.kernels.camera import observe_pairs_into
from camloc.kernels.planar import wrapped_residual
from camloc.kernels.state import difference_into, retract_into, stepped_into


@inlined
def solve3(L00, L10, L11, L20, L21, L22, b0, b1, b2):
    """S^-1 b of a 3 x 3 S with lower Cholesky factor L, as ``update.cho_solve_into``: forward,
    then back substitution, each sum in its order."""
    b0 = b0 / L00
    b1 = (b1 - L10 * b0) / L11
    b2 = (b2 - L20 * b0 - L21 * b1) / L22
    b2 = b2 / L22
    b1 = (b1 - L21 * b2) / L11
    b0 = (b0 - L10 * b1 - L20 * b2) / L00
    return b0, b1, b2


@inlined
def gain3(P, H, noise, o, K):
    """The gain K = P H' S^-1 (n, 3) of one pair (Jacobian H[0] (3, n), noise noise[o] (3, 3)),
    as ``update.gain_into``: P H' written into K, then each row solved in place. Returns S's
    lower Cholesky factor (6 scalars)."""
    n = P.shape[0]
    for c in range(n):
        for r in range(3):
            s = 0.0
            for d in range(n):
                s += P[c, d] * H[0, r, d]
            K[c, r] = s
    S00, S01, S02 = entry3(H, K, noise, o, 0, 0), entry3(H, K, noise, o, 0, 1), entry3(H, K, noise, o, 0, 2)
    S11, S12, S22 = entry3(H, K, noise, o, 1, 1), entry3(H, K, noise, o, 1, 2), entry3(H, K, noise, o, 2, 2)
    if not S00 > 0.0:
        raise FloatingPointError("innovation covariance is not positive definite")
    L00 = math.sqrt(S00)
    L10, L20 = S01 / L00, S02 / L00
    s = S11 - L10 * L10
    if not s > 0.0:
        raise FloatingPointError("innovation covariance is not positive definite")
    L11 = math.sqrt(s)
    L21 = (S12 - L20 * L10) / L11
    s = S22 - L20 * L20 - L21 * L21
    if not s > 0.0:
        raise FloatingPointError("innovation covariance is not positive definite")
    L22 = math.sqrt(s)
    for c in range(n):
        K[c, 0], K[c, 1], K[c, 2] = solve3(L00, L10, L11, L20, L21, L22, K[c, 0], K[c, 1], K[c, 2])
    return L00, L10, L11, L20, L21, L22


@inlined
def entry3(H, PHt, noise, o, r, q):
    """S[r, q] = (H P H')[r, q] + R's symmetric part, as ``update.innovation_system_into``; PHt
    (n, 3) = P H'."""
    s = 0.0
    for c in range(PHt.shape[0]):
        s += H[0, r, c] * PHt[c, q]
    return s + 0.5 * (noise[o, r, q] + noise[o, q, r])


@inlined
def covariance3(P, K, H, noise, o):
    """Joseph form (I - K H) P (I - K H)' + K R K' (n, n) of one pair, as
    ``update.covariance_posterior_into``."""
    n = P.shape[0]
    work, out = np.empty((2, n, n)), np.empty((n, n))            # I - K H, (I - K H) P
    for c in range(n):
        for d in range(n):
            s = 0.0
            for r in range(3):
                s += K[c, r] * H[0, r, d]
            work[0, c, d] = (1.0 if c == d else 0.0) - s
    for c in range(n):
        for d in range(n):
            s = 0.0
            for q in range(n):
                s += work[0, c, q] * P[q, d]
            work[1, c, d] = s
    for c in range(n):
        for d in range(c, n):
            s = 0.0
            for q in range(n):
                s += work[1, c, q] * work[0, d, q]
            for a in range(3):
                k_ca = K[c, a]
                for b in range(3):
                    s += k_ca * noise[o, a, b] * K[d, b]
            out[c, d] = s
            out[d, c] = s
    return out


@jit
def one_pair_update(x, P, z, o, landmark_xyz, j, camera, camera_R, camera_t, camera_K, noise, iterations, z_hat, H, step_sigma):
    """``update.iterated_update`` of (x, P) with one pair, observation o (measured z[o], noise
    noise[o]) of landmark j (a row of the scene's landmark_xyz) by ``camera``, z_hat (1, 3) and H
    (1, 3, n) its prediction at x; no start, no MAP cost. Returns as ``iterated_update``.
    The first linearization and the later ones share one loop, so that the gain's inlined steps
    are compiled once, not twice; the prediction is ``camera.observe_pairs_into``, already
    compiled for the general update (the two together: this kernel's own compile 5.96 -> 2.52 s,
    docs/performance.md, 2026-12-07 (twenty-fourth session))."""
    n = x.shape[0]
    kind = camera_K[camera, 4]
    K = np.empty((n, 3))
    pair_xyz, pair_camera = np.empty((1, landmark_xyz.shape[1])), np.full(1, camera)
    for a in range(landmark_xyz.shape[1]):
        pair_xyz[0, a] = landmark_xyz[j, a]
    z_hat_i, H_i = np.empty((1, 3)), np.empty((1, 3, n))
    d_position, frame = np.empty((camera_R.shape[0], 3, 3)), (np.empty((3, 3)), np.empty((3, 3)), np.empty(3))
    delta, moved, x_i, y_prior = np.empty(n), np.empty(n), np.empty(n), np.empty((1, 3))
    y0 = wrapped_residual(kind, 0, z[o, 0] - z_hat[0, 0])
    y1 = wrapped_residual(kind, 1, z[o, 1] - z_hat[0, 1])
    y2 = wrapped_residual(kind, 2, z[o, 2] - z_hat[0, 2])
    y_prior[0, 0], y_prior[0, 1], y_prior[0, 2] = y0, y1, y2
    r0, r1, r2 = y0, y1, y2
    nis = 0.0
    H_last = H                                                       # the linearization of the gain
    for step_number in range(max(iterations, 1)):                    # the first linearization always
        if step_number > 0:
            observe_pairs_into(x_i, pair_xyz, pair_camera, camera_R, camera_t, camera_K, z_hat_i, H_i, d_position, frame)
            difference_into(x_i, x, moved)
            r0 = wrapped_residual(kind, 0, z[o, 0] - z_hat_i[0, 0])    # z - h(x_i) + H_i (x_i [-] x)
            r1 = wrapped_residual(kind, 1, z[o, 1] - z_hat_i[0, 1])
            r2 = wrapped_residual(kind, 2, z[o, 2] - z_hat_i[0, 2])
            for b in range(n):
                r0 += H_i[0, 0, b] * moved[b]
            for b in range(n):
                r1 += H_i[0, 1, b] * moved[b]
            for b in range(n):
                r2 += H_i[0, 2, b] * moved[b]
            H_last = H_i
        L00, L10, L11, L20, L21, L22 = gain3(P, H_last, noise, o, K)
        if step_number == 0:
            s0, s1, s2 = solve3(L00, L10, L11, L20, L21, L22, y0, y1, y2)
            nis = 0.0 + y0 * s0 + y1 * s1 + y2 * s2                  # NIS = y' S^-1 y
            for c in range(n):
                delta[c] = 0.0 + K[c, 0] * y0 + K[c, 1] * y1 + K[c, 2] * y2
            retract_into(x, delta, x_i)                              # x+ = x [+] K y
            continue
        step = moved                                                 # read no more: the step written into it
        for c in range(n):
            step[c] = 0.0 + K[c, 0] * r0 + K[c, 1] * r1 + K[c, 2] * r2
        if stepped_into(x, step, delta, x_i, P, step_sigma):
            break                                                    # the linearization no longer moves
    return x_i, covariance3(P, K, H_last, noise, o), nis, np.nan, y_prior
