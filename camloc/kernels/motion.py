"""Prediction of the Euler state with an odometry increment (model card: ``camloc.models``).

    x' = f(x, dT):  t' = t + R dt,  R' = R dR
    P' = F P F' + G Q G'

with F and G the Jacobians with respect to the state and to the increment's right-perturbation
noise w = (w_t, w_theta) ~ N(0, Q), derived through ``R(rpy + d) = R Exp(E(rpy) d)``.
"""

from __future__ import annotations

import numpy as np

from camloc.kernels._jit import jit
from camloc.kernels.rotation import euler_rate, euler_rate_inverse, euler_to_matrix, hat, matrix_to_euler
from camloc.kernels.small import mm, mtm, mv


@jit
def motion(x, T_increment):
    """(x' (6,), F (6, 6), G (6, 6)) of the Euler state x composed with T_increment (4, 4)."""
    R = euler_to_matrix(x[3], x[4], x[5])
    dR = np.ascontiguousarray(T_increment[:3, :3])
    dt = np.ascontiguousarray(T_increment[:3, 3])
    R_next = mm(R, dR)
    rpy_next = matrix_to_euler(R_next)
    x_next = np.empty(6)
    x_next[0:3] = x[0:3] + mv(R, dt)
    x_next[3:6] = rpy_next
    E = euler_rate(x[3], x[4])
    E_next_inverse = euler_rate_inverse(rpy_next[0], rpy_next[1])
    F = np.eye(6)
    F[0:3, 3:6] = -mm(mm(R, hat(dt)), E)              # a body rotation E d of R moves t' by -R [dt]x E d
    F[3:6, 3:6] = mm(E_next_inverse, mtm(dR, E))      # R Exp(E d) dR = R' Exp(dR' E d)
    G = np.zeros((6, 6))
    G[0:3, 0:3] = R_next                              # t' = t + R dt + R dR w_t
    G[3:6, 3:6] = E_next_inverse                      # R' Exp(w_theta)
    return x_next, F, G


@jit
def predict(x, P, T_increment, Q):
    """(x', P'): ``x' = f(x, dT)``, ``P' = F P F' + G Q G'`` (symmetrized)."""
    x_next, F, G = motion(x, T_increment)
    P_next = mm(mm(F, P), F.T) + mm(mm(G, Q), G.T)
    return x_next, 0.5 * (P_next + P_next.T)
