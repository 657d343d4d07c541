"""Chi-square and binomial tail probabilities, and chi-square quantiles.

Written out rather than taken from ``scipy.special`` (``chdtri``, ``bdtrc``, which the tests
compare them with): importing scipy costs ``camloc run`` about 0.2 s on a small file, a fifth of
its time, and camloc needs only these.

- ``chi2_quantile(dof, tail)``: the x with ``P(X > x) = tail`` for X ~ chi^2(dof), as
  ``chdtri(dof, tail)``; dof need not be whole (the NEES interval of a run's mean uses an
  effective number of poses).
- ``binomial_tail(k, n, p)``: ``P(X > k)`` for X ~ Binomial(n, p), as ``bdtrc(k, n, p)``.

The chi-square tails are the regularized incomplete gamma functions at a = dof/2, y = x/2: below
y = a + 1 the lower one by its series, above it the upper one by its continued fraction (each
converges quickly where it is used, and neither subtracts from 1 the tail it is asked for).
"""

from __future__ import annotations

import math
from functools import lru_cache
from statistics import NormalDist

import numpy as np

# The series and the continued fraction stop when a term changes the sum by less than this.
_EPS = 1e-16
_TINY = 1e-300


def chi2_survival(x: float, dof: float) -> float:
    """``P(X > x)`` for X ~ chi^2(dof), dof > 0."""
    a, y = 0.5 * dof, 0.5 * x
    if y <= 0.0:
        return 1.0
    return 1.0 - _lower_series(a, y) if y < a + 1.0 else _upper_fraction(a, y)


def chi2_cdf(x: float, dof: float) -> float:
    """``P(X <= x)`` for X ~ chi^2(dof), dof > 0."""
    a, y = 0.5 * dof, 0.5 * x
    if y <= 0.0:
        return 0.0
    return _lower_series(a, y) if y < a + 1.0 else 1.0 - _upper_fraction(a, y)


def chi2_density(x: float, dof: float) -> float:
    """The chi^2(dof) density at x > 0."""
    k = 0.5 * dof
    return math.exp((k - 1.0) * math.log(x) - 0.5 * x - k * math.log(2.0) - math.lgamma(k))


def chi2_quantile(dof, tail):
    """The x with ``P(X > x) = tail`` for X ~ chi^2(dof): a float for scalar arguments, else an
    array of the arguments' broadcast shape. As scipy's: tail 0 gives inf, tail 1 gives 0, and a
    dof that is not positive or a tail outside [0, 1] (or NaN) gives NaN.

    Newton's method from the Wilson-Hilferty approximation, on the survival function above the
    median and on the distribution function below it (the tests hold it to scipy's ``chdtri``)."""
    dof_array, tail_array = np.broadcast_arrays(np.asarray(dof, dtype=float), np.asarray(tail, dtype=float))
    # once per distinct (dof, tail): a run asks for the bound of every update, from a few dofs
    pairs, inverse = np.unique(np.column_stack([dof_array.ravel(), tail_array.ravel()]), axis=0, return_inverse=True)
    out = np.array([_chi2_quantile(d, q) for d, q in pairs.tolist()])[inverse.ravel()]
    return float(out[0]) if dof_array.ndim == 0 else out.reshape(dof_array.shape)


def binomial_tail(k, n, p):
    """``P(X > k)`` for X ~ Binomial(n, p): a float for scalar arguments, else an array of the
    arguments' broadcast shape. ``k < 0`` gives 1 and ``k >= n`` gives 0; as scipy's, a NaN
    argument or p outside [0, 1] gives NaN."""
    k_array, n_array, p_array = np.broadcast_arrays(np.asarray(k, dtype=float), np.asarray(n, dtype=float), np.asarray(p, dtype=float))
    out = np.array([_binomial_tail(a, b, c) for a, b, c in zip(k_array.ravel().tolist(), n_array.ravel().tolist(), p_array.ravel().tolist())])
    return float(out[0]) if k_array.ndim == 0 else out.reshape(k_array.shape)


@lru_cache(maxsize=4096)  # the same few bounds are asked for at every pose (JCBB, the NIS bound)
def _chi2_quantile(dof: float, tail: float) -> float:
    if not (dof > 0.0 and 0.0 <= tail <= 1.0) or math.isinf(dof):
        return math.nan
    if tail == 0.0 or tail == 1.0:
        return math.inf if tail == 0.0 else 0.0
    z = NormalDist().inv_cdf(1.0 - tail)
    c = 2.0 / (9.0 * dof)
    x = dof * max(1.0 - c + z * math.sqrt(c), 0.1) ** 3  # Wilson-Hilferty; the floor keeps x > 0
    below_median = tail > 0.5  # there 1 - Q(x) loses digits: solve P(x) = 1 - tail instead
    for _ in range(100):
        # Newton on Q(x) - tail, or on (1 - tail) - P(x); halve a step that would leave x > 0
        if below_median:
            step = ((1.0 - tail) - chi2_cdf(x, dof)) / chi2_density(x, dof)
        else:
            step = (chi2_survival(x, dof) - tail) / chi2_density(x, dof)
        while x + step <= 0.0:
            step *= 0.5
        x += step
        if abs(step) <= 1e-15 * x:
            break
    return x


def _lower_series(a: float, y: float) -> float:
    """The regularized lower incomplete gamma P(a, y) by its series
    ``e^-y y^a / Gamma(a + 1) sum_n y^n / ((a+1)...(a+n))``, for y < a + 1 (terms fall at once)."""
    term = total = 1.0
    n = 1
    while term > _EPS * total:
        term *= y / (a + n)
        total += term
        n += 1
    return math.exp(-y + a * math.log(y) - math.lgamma(a + 1.0)) * total


def _upper_fraction(a: float, y: float) -> float:
    """The regularized upper incomplete gamma Q(a, y) by its continued fraction (modified Lentz),
    for y >= a + 1."""
    b = y + 1.0 - a
    c = 1.0 / _TINY
    d = 1.0 / b
    h = d
    for i in range(1, 10_000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = d if abs(d) > _TINY else _TINY
        c = b + an / c
        c = c if abs(c) > _TINY else _TINY
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < _EPS:
            break
    return math.exp(-y + a * math.log(y) - math.lgamma(a)) * h


def _binomial_tail(k: float, n: float, p: float) -> float:
    if math.isnan(k) or math.isnan(n) or not 0.0 <= p <= 1.0:
        return math.nan
    k, n = math.floor(k), int(n)
    if k < 0:
        return 1.0
    if k >= n:
        return 0.0
    if p <= 0.0 or p >= 1.0:
        return 0.0 if p <= 0.0 else 1.0
    log_factorial = np.concatenate([[0.0], np.cumsum(np.log(np.arange(1, n + 1)))])
    j = np.arange(k + 1, n + 1)
    log_terms = log_factorial[n] - log_factorial[j] - log_factorial[n - j] + j * math.log(p) + (n - j) * math.log1p(-p)
    return float(np.exp(log_terms).sum())

