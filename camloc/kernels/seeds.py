"""The ranking of a slip search's seed pairs: what a pose's whole explanation costs if each seed
is taken first (the numpy twin: ``camloc.association.seeded_explanation_costs``).

    cost_s + sum over the other observations i of min(null_i, min_q c_q|s)

with ``c_q|s`` pair q's cost conditioned on seed s (the Schur complement of the two pairs' joint
innovation covariance), linearized at the prior. And the other way seeds are found: how many
pairs imply nearly the same shift of the robot as each (``shift_agreement``). And the search's
loop over the seeds it tries (``seeded_explanations``), one call a search.
"""

from __future__ import annotations

import math

import numpy as np

from camloc.constants import SEED_EXPLANATIONS
from camloc.kernels._jit import FALSE, ONE, called, entry, inlined, jit
from camloc.kernels.beam import copy_hypothesis, explain_from_at, gather, new_generation, put_state
from camloc.kernels.sym3 import inverse_components, log_det as log_det_3x3, mahalanobis, quadratic_and_det, spread
from camloc.kernels.update import pair_model, updated_at


@entry
def seeded_explanation_costs(y, H, R, P, pair_obs, pair_landmark, null_cost, seeds, gate):
    """(M,) the approximate cost of explaining a pose's m observations given each seed pair
    (seeds (M,) indices of pairs) is right. Pairs: innovation y (N, 3), Jacobian H (N, 3, n),
    noise R (N, 3, 3) (each in its own coordinates), observation pair_obs (N,) in 0..m-1 and
    landmark (N,); P the prior covariance; null_cost (m,); gate (N,) on each conditioned pair's d^2 (at its observation's dof).

    No BLAS call: a matrix product here ran on BLAS's threads, which, on a machine with one other
    busy process, made the whole run twice as slow (benchmarks: ``docs/performance.md``)."""
    N, m = y.shape[0], null_cost.size
    S, log_det_R, HP, H_rows, y_rows, S_rows, S_inverse_rows = pair_spreads(y, H, R, P)
    out = np.empty(seeds.size)
    best = np.empty(m)
    bound, quadratic, det = np.empty(N), np.empty(N), np.empty(N)
    correction = np.empty(6)
    U = np.empty((6, 3))
    for k in range(seeds.size):
        s = seeds[k]
        conditioning_on(S, HP, y, s, U, correction)
        for i in range(m):
            best[i] = null_cost[i]
        # S|s <= S, so d^2 under S is a lower bound and screens the pairs (as the numpy twin does);
        # under a slip's wide prior most pass it, so every pair's conditioned cost is computed in
        # one branch-free pass and the screen only decides which of them count
        conditioned_costs(H_rows, y_rows, S_rows, S_inverse_rows, correction, U, bound, quadratic, det)
        for q in range(N):
            if bound[q] > gate[q] or pair_obs[q] == pair_obs[s] or pair_landmark[q] == pair_landmark[s]:
                continue
            if det[q] > 0.0 and quadratic[q] <= gate[q] * det[q]:  # d^2 within the gate: its logarithm only then
                cost = quadratic[q] / det[q] + math.log(det[q]) - log_det_R[q]
                if cost < best[pair_obs[q]]:
                    best[pair_obs[q]] = cost
        best[pair_obs[s]] = 0.0
        d2_seed, log_det_seed = mahalanobis(S[s], y[s])
        total = d2_seed + log_det_seed - log_det_R[s]
        for i in range(m):
            total += best[i]
        out[k] = total
    return out


@jit
def pair_spreads(y, H, R, P):
    """Every pair's innovation covariance S = H P H' + R (N, 3, 3), ln det R (N,) and H P
    (N, 3, 6); and every pair's Jacobian, innovation, S and S^-1 by component, each a row over the
    pairs ((18, N), (3, N), (6, N), (6, N)): the costs under one seed are then one loop the
    compiler turns into vector arithmetic (``conditioned_costs``). The loops are written for the
    largest state (6 entries, the Euler one's): a smaller state's Jacobian and H P are padded with
    zero columns, which add exact zeros to every product (its seed's correction and U are zero
    there too), so that one unrolled loop serves both models."""
    N = y.shape[0]
    S = np.empty((N, 3, 3))
    log_det_R = np.empty(N)
    HP = np.empty((N, 3, 6))
    H_rows = np.empty((18, N))
    y_rows = np.empty((3, N))
    S_rows = np.empty((6, N))
    S_inverse_rows = np.empty((6, N))
    n = P.shape[0]                      # the state's size: 6 (Euler), 3 (planar: zero columns from n on)
    for q in range(N):
        for a in range(3):
            for b in range(6):
                total = 0.0
                if b < n:
                    for k in range(n):
                        total += H[q, a, k] * P[k, b]
                HP[q, a, b] = total
        s00, s01, s02, s11, s12, s22 = spread(H, q, P)
        s00, s01, s02 = s00 + R[q, 0, 0], s01 + R[q, 0, 1], s02 + R[q, 0, 2]
        s11, s12, s22 = s11 + R[q, 1, 1], s12 + R[q, 1, 2], s22 + R[q, 2, 2]
        S[q, 0, 0], S[q, 0, 1], S[q, 0, 2] = s00, s01, s02
        S[q, 1, 0], S[q, 1, 1], S[q, 1, 2] = s01, s11, s12
        S[q, 2, 0], S[q, 2, 1], S[q, 2, 2] = s02, s12, s22
        log_det_R[q] = log_det_3x3(R[q])
        for a in range(3):
            y_rows[a, q] = y[q, a]
            for b in range(6):
                H_rows[6 * a + b, q] = H[q, a, b] if b < n else 0.0
        S_rows[0, q], S_rows[1, q], S_rows[2, q] = s00, s01, s02
        S_rows[3, q], S_rows[4, q], S_rows[5, q] = s11, s12, s22
        a00, a01, a02, a11, a12, a22 = inverse_components(s00, s01, s02, s11, s12, s22)
        S_inverse_rows[0, q], S_inverse_rows[1, q], S_inverse_rows[2, q] = a00, a01, a02
        S_inverse_rows[3, q], S_inverse_rows[4, q], S_inverse_rows[5, q] = a11, a12, a22
    return S, log_det_R, HP, H_rows, y_rows, S_rows, S_inverse_rows


@inlined
def conditioning_on(S, HP, y, s, U, correction):
    """Conditioning on seed pair s: P_s = P - U U' with U = P H_s' L_s^-T (U (6, 3)), and the
    correction K_s y_s = U L_s^-1 y_s (correction (6,)), both written in place, where S_s = L L'."""
    c00 = np.sqrt(S[s, 0, 0])                          # S_s = L L' (by hand: LAPACK's call costs more)
    c10, c20 = S[s, 1, 0] / c00, S[s, 2, 0] / c00
    c11 = np.sqrt(S[s, 1, 1] - c10 * c10)
    c21 = (S[s, 2, 1] - c20 * c10) / c11
    c22 = np.sqrt(S[s, 2, 2] - c20 * c20 - c21 * c21)
    w0 = y[s, 0] / c00                                 # L^-1 y_s and the rows of L^-1 H_s P
    w1 = (y[s, 1] - c10 * w0) / c11
    w2 = (y[s, 2] - c20 * w0 - c21 * w1) / c22
    for b in range(6):
        u0 = HP[s, 0, b] / c00
        u1 = (HP[s, 1, b] - c10 * u0) / c11
        u2 = (HP[s, 2, b] - c20 * u0 - c21 * u1) / c22
        U[b, 0], U[b, 1], U[b, 2] = u0, u1, u2
        correction[b] = u0 * w0 + u1 * w1 + u2 * w2


@jit
def conditioned_costs(H_rows, y_rows, S_rows, S_inverse_rows, correction, U, bound, quadratic, det):
    """Every pair's innovation shifted by one seed's correction (6,), r_q = y_q - H_q c_s, as
    its d^2 under its own S (bound (N,)) and, conditioned on the seed, (r' adj(S|s) r, det S|s)
    (quadratic, det (N,)), with S|s = S_q - V V' and V = H_q U_s (U (6, 3)). Pairs by component
    (rows (18, N), (3, N), (6, N), (6, N)), without branches: most pairs of a wide view pass the
    screen, and the loop runs as vector arithmetic."""
    # The seed's values in locals: read from arrays inside the loop, where the stores to bound,
    # quadratic and det might overwrite them for all LLVM knows, they kept the loop from being
    # vectorized in the process that compiled it (33 against 9 ns a pair; the same numbers)
    c0, c1, c2, c3, c4, c5 = correction[0], correction[1], correction[2], correction[3], correction[4], correction[5]
    u00, u01, u02 = U[0, 0], U[0, 1], U[0, 2]
    u10, u11, u12 = U[1, 0], U[1, 1], U[1, 2]
    u20, u21, u22 = U[2, 0], U[2, 1], U[2, 2]
    u30, u31, u32 = U[3, 0], U[3, 1], U[3, 2]
    u40, u41, u42 = U[4, 0], U[4, 1], U[4, 2]
    u50, u51, u52 = U[5, 0], U[5, 1], U[5, 2]
    for q in range(H_rows.shape[1]):
        # row a of H_q: its product with the correction (m_a) and with U's columns (row a of V)
        h0, h1, h2, h3, h4, h5 = H_rows[0, q], H_rows[1, q], H_rows[2, q], H_rows[3, q], H_rows[4, q], H_rows[5, q]
        m0 = h0 * c0 + h1 * c1 + h2 * c2 + h3 * c3 + h4 * c4 + h5 * c5
        v00 = h0 * u00 + h1 * u10 + h2 * u20 + h3 * u30 + h4 * u40 + h5 * u50
        v01 = h0 * u01 + h1 * u11 + h2 * u21 + h3 * u31 + h4 * u41 + h5 * u51
        v02 = h0 * u02 + h1 * u12 + h2 * u22 + h3 * u32 + h4 * u42 + h5 * u52
        h0, h1, h2, h3, h4, h5 = H_rows[6, q], H_rows[7, q], H_rows[8, q], H_rows[9, q], H_rows[10, q], H_rows[11, q]
        m1 = h0 * c0 + h1 * c1 + h2 * c2 + h3 * c3 + h4 * c4 + h5 * c5
        v10 = h0 * u00 + h1 * u10 + h2 * u20 + h3 * u30 + h4 * u40 + h5 * u50
        v11 = h0 * u01 + h1 * u11 + h2 * u21 + h3 * u31 + h4 * u41 + h5 * u51
        v12 = h0 * u02 + h1 * u12 + h2 * u22 + h3 * u32 + h4 * u42 + h5 * u52
        h0, h1, h2, h3, h4, h5 = H_rows[12, q], H_rows[13, q], H_rows[14, q], H_rows[15, q], H_rows[16, q], H_rows[17, q]
        m2 = h0 * c0 + h1 * c1 + h2 * c2 + h3 * c3 + h4 * c4 + h5 * c5
        v20 = h0 * u00 + h1 * u10 + h2 * u20 + h3 * u30 + h4 * u40 + h5 * u50
        v21 = h0 * u01 + h1 * u11 + h2 * u21 + h3 * u31 + h4 * u41 + h5 * u51
        v22 = h0 * u02 + h1 * u12 + h2 * u22 + h3 * u32 + h4 * u42 + h5 * u52
        r0, r1, r2 = y_rows[0, q] - m0, y_rows[1, q] - m1, y_rows[2, q] - m2
        bound[q] = (S_inverse_rows[0, q] * r0 * r0 + S_inverse_rows[3, q] * r1 * r1 + S_inverse_rows[5, q] * r2 * r2
                    + 2.0 * (S_inverse_rows[1, q] * r0 * r1 + S_inverse_rows[2, q] * r0 * r2 + S_inverse_rows[4, q] * r1 * r2))
        a = S_rows[0, q] - (v00 * v00 + v01 * v01 + v02 * v02)
        b = S_rows[1, q] - (v00 * v10 + v01 * v11 + v02 * v12)
        c = S_rows[2, q] - (v00 * v20 + v01 * v21 + v02 * v22)
        d = S_rows[3, q] - (v10 * v10 + v11 * v11 + v12 * v12)
        e = S_rows[4, q] - (v10 * v20 + v11 * v21 + v12 * v22)
        f = S_rows[5, q] - (v20 * v20 + v21 * v21 + v22 * v22)
        quadratic[q], det[q] = quadratic_and_det(a, b, c, d, e, f, r0, r1, r2)


@entry
def shift_agreement(shifts, radius):
    """(N,) how many of the shifts (N, 3) lie within ``radius`` of each, itself included: the
    numpy twin's ``camloc.association.shift_agreement``, by a sweep along x (a pair further apart
    in x than the radius is further apart in space), without scipy's k-d tree."""
    n = shifts.shape[0]
    order = np.argsort(shifts[:, 0].copy(), kind="mergesort")   # the merge sort the other kernels compile (contiguous)
    counts = np.ones(n, np.int64)
    limit = radius * radius
    for a in range(n):
        i = order[a]
        for b in range(a + 1, n):
            j = order[b]
            d0 = shifts[j, 0] - shifts[i, 0]
            if d0 > radius:
                break
            d1 = shifts[j, 1] - shifts[i, 1]
            d2 = shifts[j, 2] - shifts[i, 2]
            if d0 * d0 + d1 * d1 + d2 * d2 <= limit:
                counts[i] += 1
                counts[j] += 1
    return counts


# the kernel the search calls from Python too, called by its address (``_jit.called``): linked, its
# code was optimized and generated again in this module
gather_at = called(gather)


@entry
def seeded_explanations(scene, settings, h, obs, seeds, pair_obs, pair_landmark, pair_cost, pair_z_hat, pair_H):
    """The seeded search's explanations of obs (m,) under h (a generation of one), each grown from
    one of the seed pairs ``seeds`` (indices of the pairs pair_obs (positions in obs),
    pair_landmark, pair_cost, with their prediction pair_z_hat (N, 3) and pair_H (N, 3, n) at h),
    in order: the pair's update of h, then ``explain_from`` of the other observations, its chains
    checked against h. Returns (generation, count): each seed's SEED_EXPLANATIONS cheapest, in the
    seeds' order (the caller keeps those within h's prior, ``camloc.seeds.within_prior``).

    One call a search (``camloc.seeds.from_seeds``): from Python each seed took five compiled
    calls, two of them passed the scene, whose unboxing cost more than the work
    (docs/performance.md, 2026-12-07 (twenty-third session)). The update and ``explain_from`` are
    called by their addresses (``_jit.called``), as the beam calls them: not compiled again. The
    test against the prior stays in Python: numba's ``np.linalg.solve`` took 2.7 s of a first
    compile, and another solve would not give LAPACK's bits."""
    x, P = h[0][0], h[1][0]
    m, dim = obs.size, x.shape[0]
    model = pair_model(scene)
    first = np.zeros(1, np.int64)
    # a child explains each observation at most once: m pairs at most (``explain_from``'s room)
    found = new_generation(seeds.size * SEED_EXPLANATIONS, m, dim)
    n = 0
    for k in range(seeds.size):
        seed = seeds[k]
        i = pair_obs[seed]
        seeded = gather_at(h, first, ONE + m)
        state = updated_at(model, settings.iterations, x, P, obs[i:i + 1], pair_landmark[seed:seed + 1], pair_z_hat[seed:seed + 1],
                           pair_H[seed:seed + 1], model.R_assoc, model.R_assoc_inverse, x[:0], FALSE, 0.0)
        put_state(seeded, 0, state[0], state[1])
        seeded[2][0] += pair_cost[seed]
        seeded[7][0, 0, 0], seeded[7][0, 0, 1] = obs[i], pair_landmark[seed]
        seeded[6][0] = 1
        rest = np.empty(m - 1, np.int64)        # obs without its i-th
        for j in range(m - 1):
            rest[j] = obs[j] if j < i else obs[j + 1]
        children, count = explain_from_at(scene, settings, seeded, ONE, rest, h)
        for c in range(min(count, SEED_EXPLANATIONS)):
            copy_hypothesis(children, c, found, n)
            n += 1
    return found, n
