"""The ranking of a slip search's seed pairs: what a pose's whole explanation costs if each seed
is taken first (the numpy twin: ``camloc.association.seeded_explanation_costs``).

    cost_s + sum over the other observations i of min(null_i, min_q c_q|s)

with ``c_q|s`` pair q's cost conditioned on seed s (the Schur complement of the two pairs' joint
innovation covariance), linearized at the prior.
"""

from __future__ import annotations

import math

import numpy as np

from camloc.kernels._jit import jit
from camloc.kernels.sym3 import inverse_components, log_det as log_det_3x3, mahalanobis, quadratic_and_det, spread


# Seeds are screened in chunks: the whitened innovations of every pair under a chunk of seeds are
# one matrix product (3N x 6 by 6 x chunk), a few MB at most.
SEED_CHUNK = 32


@jit
def seeded_explanation_costs(y, H, R, P, pair_obs, pair_landmark, null_cost, seeds, gate):
    """(M,) the approximate cost of explaining a pose's m observations given each seed pair
    (seeds (M,) indices of pairs) is right. Pairs: innovation y (N, 3), Jacobian H (N, 3, 6),
    noise R (N, 3, 3) (each in its own coordinates), observation pair_obs (N,) in 0..m-1 and
    landmark (N,); P the prior covariance; null_cost (m,); gate on a conditioned pair's d^2."""
    N, m = y.shape[0], null_cost.size
    S = np.empty((N, 3, 3))
    log_det_R = np.empty(N)
    HP = np.empty((N, 3, 6))
    # W_q with W_q' W_q = S_q^-1 whitens pair q: |W_q (y_q - H_q c)|^2 = d^2 under S_q
    white_y = np.empty(3 * N)
    white_H = np.empty((3 * N, 6))
    for q in range(N):
        for a in range(3):
            for b in range(6):
                total = 0.0
                for k in range(6):
                    total += H[q, a, k] * P[k, b]
                HP[q, a, b] = total
        s00, s01, s02, s11, s12, s22 = spread(H, q, P)
        s00, s01, s02 = s00 + R[q, 0, 0], s01 + R[q, 0, 1], s02 + R[q, 0, 2]
        s11, s12, s22 = s11 + R[q, 1, 1], s12 + R[q, 1, 2], s22 + R[q, 2, 2]
        S[q, 0, 0], S[q, 0, 1], S[q, 0, 2] = s00, s01, s02
        S[q, 1, 0], S[q, 1, 1], S[q, 1, 2] = s01, s11, s12
        S[q, 2, 0], S[q, 2, 1], S[q, 2, 2] = s02, s12, s22
        log_det_R[q] = log_det_3x3(R[q])
        a00, a01, a02, a11, a12, a22 = inverse_components(s00, s01, s02, s11, s12, s22)
        l00 = np.sqrt(a00)                                 # A = S^-1 = L L' (3x3 Cholesky by hand), W = L'
        l10, l20 = a01 / l00, a02 / l00
        l11 = np.sqrt(a11 - l10 * l10)
        l21 = (a12 - l20 * l10) / l11
        l22 = np.sqrt(a22 - l20 * l20 - l21 * l21)
        white_y[3 * q] = l00 * y[q, 0] + l10 * y[q, 1] + l20 * y[q, 2]
        white_y[3 * q + 1] = l11 * y[q, 1] + l21 * y[q, 2]
        white_y[3 * q + 2] = l22 * y[q, 2]
        for b in range(6):
            white_H[3 * q, b] = l00 * H[q, 0, b] + l10 * H[q, 1, b] + l20 * H[q, 2, b]
            white_H[3 * q + 1, b] = l11 * H[q, 1, b] + l21 * H[q, 2, b]
            white_H[3 * q + 2, b] = l22 * H[q, 2, b]
    out = np.empty(seeds.size)
    best = np.empty(m)
    bound = np.empty(N)
    for first in range(0, seeds.size, SEED_CHUNK):
        chunk = seeds[first:first + SEED_CHUNK]
        c = chunk.size
        corrections = np.empty((6, c))
        U = np.empty((6, 3 * c))
        for k in range(c):
            s = chunk[k]
            # conditioning on s: P_s = P - U U' with U = P H_s' L_s^-T, correction K_s y_s = U L_s^-1 y_s
            c00 = np.sqrt(S[s, 0, 0])                      # S_s = L L' (by hand: LAPACK's call costs more)
            c10, c20 = S[s, 1, 0] / c00, S[s, 2, 0] / c00
            c11 = np.sqrt(S[s, 1, 1] - c10 * c10)
            c21 = (S[s, 2, 1] - c20 * c10) / c11
            c22 = np.sqrt(S[s, 2, 2] - c20 * c20 - c21 * c21)
            w0 = y[s, 0] / c00                             # L^-1 y_s and the rows of L^-1 H_s P
            w1 = (y[s, 1] - c10 * w0) / c11
            w2 = (y[s, 2] - c20 * w0 - c21 * w1) / c22
            for b in range(6):
                u0 = HP[s, 0, b] / c00
                u1 = (HP[s, 1, b] - c10 * u0) / c11
                u2 = (HP[s, 2, b] - c20 * u0 - c21 * u1) / c22
                U[b, 3 * k], U[b, 3 * k + 1], U[b, 3 * k + 2] = u0, u1, u2
                corrections[b, k] = u0 * w0 + u1 * w1 + u2 * w2
        # every pair's whitened shift under every seed of the chunk in one matrix product, (c, 3N):
        # W_q H_q c_s, a seed's row contiguous for the screen that reads all of it (BLAS writes it
        # so from the transposed operands; transposing its product after was half the ranking)
        white_moved = corrections.T @ white_H.T
        for k in range(c):
            s = chunk[k]
            for i in range(m):
                best[i] = null_cost[i]
            # S|s <= S, so d^2 under S is a lower bound: most pairs under a seed are far out (one
            # pass without branches over the seed's row, then only the pairs within it)
            for q in range(N):
                w0 = white_y[3 * q] - white_moved[k, 3 * q]
                w1 = white_y[3 * q + 1] - white_moved[k, 3 * q + 1]
                w2 = white_y[3 * q + 2] - white_moved[k, 3 * q + 2]
                bound[q] = w0 * w0 + w1 * w1 + w2 * w2
            for q in range(N):
                if bound[q] > gate or pair_obs[q] == pair_obs[s] or pair_landmark[q] == pair_landmark[s]:
                    continue
                # the few pairs the screen lets through: their shift H_q c_s, and S|s = S_q - V V'
                # with V = H_q U_s (3, 3)
                m0 = m1 = m2 = 0.0
                v00 = v01 = v02 = v10 = v11 = v12 = v20 = v21 = v22 = 0.0
                for b in range(6):
                    h0, h1, h2, shift = H[q, 0, b], H[q, 1, b], H[q, 2, b], corrections[b, k]
                    u0, u1, u2 = U[b, 3 * k], U[b, 3 * k + 1], U[b, 3 * k + 2]
                    m0 += h0 * shift
                    m1 += h1 * shift
                    m2 += h2 * shift
                    v00, v01, v02 = v00 + h0 * u0, v01 + h0 * u1, v02 + h0 * u2
                    v10, v11, v12 = v10 + h1 * u0, v11 + h1 * u1, v12 + h1 * u2
                    v20, v21, v22 = v20 + h2 * u0, v21 + h2 * u1, v22 + h2 * u2
                a = S[q, 0, 0] - (v00 * v00 + v01 * v01 + v02 * v02)
                b = S[q, 0, 1] - (v00 * v10 + v01 * v11 + v02 * v12)
                cc = S[q, 0, 2] - (v00 * v20 + v01 * v21 + v02 * v22)
                d = S[q, 1, 1] - (v10 * v10 + v11 * v11 + v12 * v12)
                e = S[q, 1, 2] - (v10 * v20 + v11 * v21 + v12 * v22)
                f = S[q, 2, 2] - (v20 * v20 + v21 * v21 + v22 * v22)
                quadratic, det = quadratic_and_det(a, b, cc, d, e, f, y[q, 0] - m0, y[q, 1] - m1, y[q, 2] - m2)
                if det > 0.0 and quadratic <= gate * det:        # d^2 within the gate: its logarithm only then
                    cost = quadratic / det + math.log(det) - log_det_R[q]
                    if cost < best[pair_obs[q]]:
                        best[pair_obs[q]] = cost
            best[pair_obs[s]] = 0.0
            d2_seed, log_det_seed = mahalanobis(S[s], y[s])
            total = d2_seed + log_det_seed - log_det_R[s]
            for i in range(m):
                total += best[i]
            out[first + k] = total
    return out
