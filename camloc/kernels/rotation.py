"""Euler angles and small rotations for the compiled filter: ``R = Rz(yaw) Ry(pitch) Rx(roll)``,
the convention of ``camloc.geometry`` (whose numpy functions are these kernels' twins in the tests)."""

from __future__ import annotations

import math

import numpy as np

from camloc.kernels._jit import entry, jit


@jit
def euler_to_matrix(roll, pitch, yaw):
    """R (3, 3) = Rz(yaw) Ry(pitch) Rx(roll)."""
    R = np.empty((3, 3))
    euler_to_matrix_into(roll, pitch, yaw, R)
    return R


@jit
def euler_to_matrix_into(roll, pitch, yaw, R):
    """``euler_to_matrix`` written into R (3, 3)."""
    sr, cr = math.sin(roll), math.cos(roll)
    sp, cp = math.sin(pitch), math.cos(pitch)
    sy, cy = math.sin(yaw), math.cos(yaw)
    R[0, 0], R[0, 1], R[0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    R[1, 0], R[1, 1], R[1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    R[2, 0], R[2, 1], R[2, 2] = -sp, cp * sr, cp * cr


@jit
def matrix_to_euler(R):
    """(roll, pitch, yaw) (3,) of R (3, 3), pitch in [-pi/2, pi/2]."""
    out = np.empty(3)
    out[0] = math.atan2(R[2, 1], R[2, 2])
    out[1] = math.asin(min(1.0, max(-1.0, -R[2, 0])))
    out[2] = math.atan2(R[1, 0], R[0, 0])
    return out


@jit
def euler_rate(roll, pitch):
    """E (3, 3) with ``R(rpy + d) = R(rpy) Exp(E d)`` to first order; singular at pitch +-pi/2."""
    E = np.empty((3, 3))
    euler_rate_into(roll, pitch, E)
    return E


@jit
def euler_rate_into(roll, pitch, E):
    """``euler_rate`` written into E (3, 3)."""
    sr, cr, sp, cp = math.sin(roll), math.cos(roll), math.sin(pitch), math.cos(pitch)
    E[0, 0], E[0, 1], E[0, 2] = 1.0, 0.0, -sp
    E[1, 0], E[1, 1], E[1, 2] = 0.0, cr, sr * cp
    E[2, 0], E[2, 1], E[2, 2] = 0.0, -sr, cr * cp


@jit
def euler_rate_inverse(roll, pitch):
    """E^-1 (3, 3): the Euler step of a body rotation w is ``E^-1 w``."""
    sr, cr = math.sin(roll), math.cos(roll)
    tp, sec = math.tan(pitch), 1.0 / math.cos(pitch)
    E = np.zeros((3, 3))
    E[0, 0], E[0, 1], E[0, 2] = 1.0, sr * tp, cr * tp
    E[1, 1], E[1, 2] = cr, -sr
    E[2, 1], E[2, 2] = sr * sec, cr * sec
    return E


@jit
def wrap_angle(a):
    """a wrapped into [-pi, pi)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@jit
def retract(x, delta):
    """The Euler state x (6,) moved by the error delta (6,): ``x + delta``, roll and yaw wrapped."""
    out = np.empty(6)
    retract_into(x, delta, out)
    return out


@jit
def retract_into(x, delta, out):
    """``retract`` written into out (6,) (not x or delta)."""
    for i in range(6):
        out[i] = x[i] + delta[i]
    out[3] = wrap_angle(out[3])
    out[5] = wrap_angle(out[5])


@entry
def difference(a, b):
    """The error (6,) from b to a: ``a - b`` with the three angle differences wrapped."""
    d = np.empty(6)
    difference_into(a, b, d)
    return d


@jit
def difference_into(a, b, d):
    """``difference`` written into d (6,)."""
    for i in range(6):
        d[i] = a[i] - b[i] if i < 3 else wrap_angle(a[i] - b[i])
