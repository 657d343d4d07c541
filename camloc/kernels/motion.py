"""Prediction of the Euler state with an odometry increment (model card: ``camloc.models``).

    x' = f(x, dT):  t' = t + R dt,  R' = R dR
    P' = F P F' + G Q G'

with F and G the Jacobians with respect to the state and to the increment's right-perturbation
noise w = (w_t, w_theta) ~ N(0, Q), derived through ``R(rpy + d) = R Exp(E(rpy) d)``.
"""

from __future__ import annotations

import numpy as np

from camloc.kernels._jit import inlined, jit
from camloc.kernels.planar import SE2_DIM, planar_motion
from camloc.kernels.rotation import euler_rate, euler_rate_inverse, euler_to_matrix, matrix_to_euler


@jit
def motion(x, T_increment):
    """(x' (6,), F (6, 6), G (6, 6)) of the Euler state x composed with T_increment (4, 4).
    Written as loops over entries: numpy's block assignments and products compile to much more
    code than this arithmetic, in every kernel that predicts."""
    R = euler_to_matrix(x[3], x[4], x[5])
    R_next = np.empty((3, 3))                         # R dR
    for a in range(3):
        for b in range(3):
            R_next[a, b] = R[a, 0] * T_increment[0, b] + R[a, 1] * T_increment[1, b] + R[a, 2] * T_increment[2, b]
    rpy_next = matrix_to_euler(R_next)
    x_next = np.empty(6)
    for a in range(3):                                # t' = t + R dt
        x_next[a] = x[a] + R[a, 0] * T_increment[0, 3] + R[a, 1] * T_increment[1, 3] + R[a, 2] * T_increment[2, 3]
        x_next[3 + a] = rpy_next[a]
    E = euler_rate(x[3], x[4])
    E_next_inverse = euler_rate_inverse(rpy_next[0], rpy_next[1])
    d0, d1, d2 = T_increment[0, 3], T_increment[1, 3], T_increment[2, 3]
    F = np.zeros((6, 6))
    G = np.zeros((6, 6))
    for a in range(3):
        F[a, a] = 1.0
        # R [dt]x, row a: a body rotation E d of R moves t' by -R [dt]x E d
        m0 = R[a, 1] * d2 - R[a, 2] * d1
        m1 = R[a, 2] * d0 - R[a, 0] * d2
        m2 = R[a, 0] * d1 - R[a, 1] * d0
        for b in range(3):
            F[a, 3 + b] = -(m0 * E[0, b] + m1 * E[1, b] + m2 * E[2, b])
            # R Exp(E d) dR = R' Exp(dR' E d): E'^-1 dR' E
            s = 0.0
            for q in range(3):
                s += E_next_inverse[a, q] * (T_increment[0, q] * E[0, b] + T_increment[1, q] * E[1, b] + T_increment[2, q] * E[2, b])
            F[3 + a, 3 + b] = s
            G[a, b] = R_next[a, b]                    # t' = t + R dt + R dR w_t
            G[3 + a, 3 + b] = E_next_inverse[a, b]    # R' Exp(w_theta)
    return x_next, F, G


@jit
def predict(x, P, T_increment, Q):
    """(x', P'): ``x' = f(x, dT)``, ``P' = F P F' + G Q G'`` (symmetric: its upper triangle
    mirrored), of x's model (its size: the Euler state's ``motion``, the planar one's
    ``planar.planar_motion``), with F (n, n) and G (n, 6) its Jacobians by the error and by the
    lifted increment's noise (Q (6, 6))."""
    if x.shape[0] == SE2_DIM:
        x_next, F, G = planar_motion(x, T_increment)
        return x_next, propagated(P, F, G, Q, SE2_DIM)
    x_next, F, G = motion(x, T_increment)
    return x_next, propagated(P, F, G, Q, 6)


@inlined
def propagated(P, F, G, Q, n):
    """``F P F' + G Q G'`` (n, n) of ``predict``, n the state's size as a constant (its loops
    unrolled, the update's dense steps: ``update.information_into``)."""
    FP, GQ = np.empty((n, n)), np.empty((n, 6))
    for a in range(n):
        for b in range(6):
            s = t = 0.0
            for q in range(6):
                t += G[a, q] * Q[q, b]
            GQ[a, b] = t
            if b < n:
                for q in range(n):
                    s += F[a, q] * P[q, b]
                FP[a, b] = s
    P_next = np.empty((n, n))
    for a in range(n):
        for b in range(a, n):
            s = 0.0
            for q in range(6):                 # term by term in the order of the 6-DOF sum: Euler's rounding unchanged
                if q < n:
                    s += FP[a, q] * F[b, q] + GQ[a, q] * G[b, q]
                else:
                    s += GQ[a, q] * G[b, q]
            P_next[a, b] = s
            P_next[b, a] = s
    return P_next
