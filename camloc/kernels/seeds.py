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
from camloc.kernels.small import mm, mv, sandwich
from camloc.kernels.sym3 import mahalanobis


@jit
def seeded_explanation_costs(y, H, R, P, pair_obs, pair_landmark, null_cost, seeds, gate):
    """(M,) the approximate cost of explaining a pose's m observations given each seed pair
    (seeds (M,) indices of pairs) is right. Pairs: innovation y (N, 3), Jacobian H (N, 3, 6),
    noise R (N, 3, 3) (each in its own coordinates), observation pair_obs (N,) in 0..m-1 and
    landmark (N,); P the prior covariance; null_cost (m,); gate on a conditioned pair's d^2."""
    N, m = y.shape[0], null_cost.size
    S = np.empty((N, 3, 3))
    S_inverse = np.empty((N, 3, 3))
    log_det_R = np.empty(N)
    HP = np.empty((N, 3, 6))
    for q in range(N):
        HP[q] = mm(H[q], P)
        S[q] = sandwich(H[q], P) + R[q]
        S_inverse[q] = np.linalg.inv(S[q])
        log_det_R[q] = np.linalg.slogdet(R[q])[1]
    out = np.empty(seeds.size)
    best = np.empty(m)
    y_cond = np.empty(3)
    for k in range(seeds.size):
        s = seeds[k]
        # conditioning on s: P_s = P - U U' with U = P H_s' L_s^-T, correction K_s y_s = U L_s^-1 y_s
        L = np.linalg.cholesky(S[s])
        Ut = np.linalg.solve(L, HP[s])                    # (3, 6) = U'
        w = np.linalg.solve(L, y[s])
        correction = Ut.T @ w
        for i in range(m):
            best[i] = null_cost[i]
        for q in range(N):
            if pair_obs[q] == pair_obs[s] or pair_landmark[q] == pair_landmark[s]:
                continue
            for a in range(3):
                moved = 0.0
                for b in range(6):
                    moved += H[q, a, b] * correction[b]
                y_cond[a] = y[q, a] - moved
            # S|s <= S, so d^2 under S is a lower bound: most pairs under a seed are far out
            bound = 0.0
            for a in range(3):
                for b in range(3):
                    bound += y_cond[a] * S_inverse[q, a, b] * y_cond[b]
            if bound > gate:
                continue
            V = mm(H[q], Ut.T)                            # H_q U
            S_cond = S[q] - mm(V, V.T)
            d2, log_det = mahalanobis(S_cond, y_cond)
            if d2 <= gate:
                cost = d2 + log_det - log_det_R[q]
                if cost < best[pair_obs[q]]:
                    best[pair_obs[q]] = cost
        best[pair_obs[s]] = 0.0
        d2_seed, log_det_seed = mahalanobis(S[s], y[s])
        total = d2_seed + log_det_seed - log_det_R[s]
        for i in range(m):
            total += best[i]
        out[k] = total
    return out
