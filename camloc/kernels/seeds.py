"""The ranking of a slip search's seed pairs: what a pose's whole explanation costs if each seed
is taken first (the numpy twin: ``camloc.association.seeded_explanation_costs``).

    cost_s + sum over the other observations i of min(null_i, min_q c_q|s)

with ``c_q|s`` pair q's cost conditioned on seed s (the Schur complement of the two pairs' joint
innovation covariance), linearized at the prior.
"""

from __future__ import annotations


import numpy as np

from camloc.kernels._jit import jit
from camloc.kernels.small import mm, mtv
from camloc.kernels.sym3 import inverse, log_det as log_det_3x3, mahalanobis, mahalanobis_components


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
        HP[q] = mm(H[q], P)
        S[q] = mm(HP[q], H[q].T) + R[q]
        log_det_R[q] = log_det_3x3(R[q])
        A = inverse(S[q])                                  # A = L L' (3x3 Cholesky by hand), W = L'
        l00 = np.sqrt(A[0, 0])
        l10, l20 = A[1, 0] / l00, A[2, 0] / l00
        l11 = np.sqrt(A[1, 1] - l10 * l10)
        l21 = (A[2, 1] - l20 * l10) / l11
        l22 = np.sqrt(A[2, 2] - l20 * l20 - l21 * l21)
        white_y[3 * q] = l00 * y[q, 0] + l10 * y[q, 1] + l20 * y[q, 2]
        white_y[3 * q + 1] = l11 * y[q, 1] + l21 * y[q, 2]
        white_y[3 * q + 2] = l22 * y[q, 2]
        for b in range(6):
            white_H[3 * q, b] = l00 * H[q, 0, b] + l10 * H[q, 1, b] + l20 * H[q, 2, b]
            white_H[3 * q + 1, b] = l11 * H[q, 1, b] + l21 * H[q, 2, b]
            white_H[3 * q + 2, b] = l22 * H[q, 2, b]
    out = np.empty(seeds.size)
    best = np.empty(m)
    V = np.empty((3, 3))
    for first in range(0, seeds.size, SEED_CHUNK):
        chunk = seeds[first:first + SEED_CHUNK]
        c = chunk.size
        corrections = np.empty((6, c))
        U = np.empty((6, 3 * c))
        for k in range(c):
            s = chunk[k]
            # conditioning on s: P_s = P - U U' with U = P H_s' L_s^-T, correction K_s y_s = U L_s^-1 y_s
            L = np.linalg.cholesky(S[s])
            Ut = np.linalg.solve(L, HP[s])
            U[:, 3 * k:3 * k + 3] = Ut.T
            corrections[:, k] = mtv(Ut, np.linalg.solve(L, y[s]))
        # every pair's whitened shift under every seed of the chunk in one matrix product, (c, 3N):
        # W_q H_q c_s, a seed's row contiguous for the screen that reads all of it
        white_moved = np.ascontiguousarray((white_H @ corrections).T)
        for k in range(c):
            s = chunk[k]
            for i in range(m):
                best[i] = null_cost[i]
            for q in range(N):
                if pair_obs[q] == pair_obs[s] or pair_landmark[q] == pair_landmark[s]:
                    continue
                # S|s <= S, so d^2 under S is a lower bound: most pairs under a seed are far out
                w0 = white_y[3 * q] - white_moved[k, 3 * q]
                w1 = white_y[3 * q + 1] - white_moved[k, 3 * q + 1]
                w2 = white_y[3 * q + 2] - white_moved[k, 3 * q + 2]
                if w0 * w0 + w1 * w1 + w2 * w2 > gate:
                    continue
                # the few pairs the screen lets through: their shift H_q c_s, and S|s = S_q - V V'
                # with V = H_q U_s (3, 3)
                m0 = m1 = m2 = 0.0
                V[:] = 0.0
                for b in range(6):
                    h0, h1, h2, shift = H[q, 0, b], H[q, 1, b], H[q, 2, b], corrections[b, k]
                    m0 += h0 * shift
                    m1 += h1 * shift
                    m2 += h2 * shift
                    for j in range(3):
                        u = U[b, 3 * k + j]
                        V[0, j] += h0 * u
                        V[1, j] += h1 * u
                        V[2, j] += h2 * u
                a = S[q, 0, 0] - (V[0, 0] * V[0, 0] + V[0, 1] * V[0, 1] + V[0, 2] * V[0, 2])
                b = S[q, 0, 1] - (V[0, 0] * V[1, 0] + V[0, 1] * V[1, 1] + V[0, 2] * V[1, 2])
                cc = S[q, 0, 2] - (V[0, 0] * V[2, 0] + V[0, 1] * V[2, 1] + V[0, 2] * V[2, 2])
                d = S[q, 1, 1] - (V[1, 0] * V[1, 0] + V[1, 1] * V[1, 1] + V[1, 2] * V[1, 2])
                e = S[q, 1, 2] - (V[1, 0] * V[2, 0] + V[1, 1] * V[2, 1] + V[1, 2] * V[2, 2])
                f = S[q, 2, 2] - (V[2, 0] * V[2, 0] + V[2, 1] * V[2, 1] + V[2, 2] * V[2, 2])
                d2, log_det = mahalanobis_components(a, b, cc, d, e, f, y[q, 0] - m0, y[q, 1] - m1, y[q, 2] - m2)
                if d2 <= gate:
                    cost = d2 + log_det - log_det_R[q]
                    if cost < best[pair_obs[q]]:
                        best[pair_obs[q]] = cost
            best[pair_obs[s]] = 0.0
            d2_seed, log_det_seed = mahalanobis(S[s], y[s])
            total = d2_seed + log_det_seed - log_det_R[s]
            for i in range(m):
                total += best[i]
            out[first + k] = total
    return out
