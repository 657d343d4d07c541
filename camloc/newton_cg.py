"""A Newton step with the exact Hessian, without forming it: conjugate gradients on Hessian-vector
products differenced from the gradient, preconditioned with a Gauss-Newton factor.

Gauss-Newton's Hessian ``J^T W J`` leaves out the residuals' second derivatives, ``sum r_i d2 r_i``.
Where a direction is determined weakly, its information can be of the order of that term: Gauss-
Newton then converges linearly, each step a fixed share of the one before (Nocedal and Wright,
"Numerical optimization", 2006, sec. 10.3). The smoother meets this on monocular worlds with no
map: a landmark seen twice at a few degrees of parallax and the poses that see it, steps shrinking
by 0.76-0.87 an iteration, 50-107 iterations to the step tolerance (docs/performance.md,
2026-12-05 (night)). The exact Hessian converges quadratically there.

The exact Hessian of the robust cost is never formed: its product with a vector v is the change
of the exact gradient along v (Nocedal and Wright, sec. 8.1, "Approximating the Hessian-vector
product")::

    H v ~ (g(x + h v) - g(x)) / h,    h = H_STEP / |v|_inf

(one linearization a product; error O(h), with H_STEP 1e-6 metres or radians on the largest
component a relative 1e-6 or so, far below what a Newton step needs). ``H delta = -g`` is solved
by conjugate gradients (sec. 5.1) in the Jacobi-scaled unknowns ``y = delta / d``, preconditioned
with the Gauss-Newton matrix's factor: where Gauss-Newton is nearly right, its factor is nearly
the inverse, and CG needs a few products. CG starts from the preconditioned right-hand side, which
is the Gauss-Newton step itself. Where a search direction meets non-positive curvature (far from
a minimum, the exact Hessian need not be positive definite) there is no Newton step: None, and
the caller keeps its Gauss-Newton step (sec. 7.1's line-search Newton-CG stops there too).

Pure: no I/O, no printing.
"""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np

# The largest component of a Hessian-vector product's difference step (metres or radians).
H_STEP = 1e-6


def newton_step(gradient_at: Callable[[np.ndarray], np.ndarray], g: np.ndarray, d: np.ndarray,
                precondition: Callable[[np.ndarray], np.ndarray], *, rtol: float = 1e-6,
                max_iterations: int = 20) -> Optional[np.ndarray]:
    """The step ``delta`` (n,) of ``H delta = -g`` with H the Hessian of the function whose
    gradient at ``x + delta`` is ``gradient_at(delta)`` (g: the gradient at x), or None (non-
    positive curvature met, or no convergence in ``max_iterations`` products).

    Parameters
    ----------
    d : (n,) the Jacobi scale: CG runs on ``D H D y = -D g``, ``delta = D y``.
    precondition : an approximation of ``(D H D)^-1`` (a Gauss-Newton factor's solve).
    rtol : the residual of the scaled system, relative to its right-hand side, at which to stop.
    """
    def hessian_times(y: np.ndarray) -> np.ndarray:
        v = d * y
        h = H_STEP / max(float(np.max(np.abs(v))), 1e-300)
        return d * (gradient_at(h * v) - g) / h

    y = conjugate_gradients(hessian_times, -d * g, precondition, rtol=rtol, max_iterations=max_iterations)
    return None if y is None else d * y


def conjugate_gradients(times: Callable[[np.ndarray], np.ndarray], b: np.ndarray,
                        precondition: Callable[[np.ndarray], np.ndarray], *, rtol: float,
                        max_iterations: int) -> Optional[np.ndarray]:
    """The solution x of ``A x = b`` by preconditioned conjugate gradients (Nocedal and Wright,
    algorithm 5.3), ``times(v)`` = A v, started from ``precondition(b)``; None where a search
    direction meets non-positive curvature (A is not positive definite there) or the residual
    does not fall to ``rtol`` of ``|b|`` in ``max_iterations`` products."""
    target = rtol * float(np.linalg.norm(b))
    x = precondition(b)
    r = b - times(x)
    z = precondition(r)
    p, rz = z.copy(), float(r @ z)
    for _ in range(max_iterations):
        if float(np.linalg.norm(r)) <= target:
            return x
        Ap = times(p)
        curvature = float(p @ Ap)
        if not curvature > 0.0:
            return None
        alpha = rz / curvature
        x += alpha * p
        r -= alpha * Ap
        z = precondition(r)
        rz, previous = float(r @ z), rz
        p = z + (rz / previous) * p
    return None
