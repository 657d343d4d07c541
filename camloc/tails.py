"""Chi-square and binomial tail probabilities for whole-number degrees of freedom and counts.

Written out rather than taken from ``scipy.special`` (``chdtri``, ``bdtrc``, which the tests
compare them with): importing scipy costs ``camloc run`` about 0.2 s on a small file, a fifth of
its time, and the localizer needs only these two tails.

- ``chi2_quantile(dof, tail)``: the x with ``P(X > x) = tail`` for X ~ chi^2(dof), as
  ``chdtri(dof, tail)``.
- ``binomial_tail(k, n, p)``: ``P(X > k)`` for X ~ Binomial(n, p), as ``bdtrc(k, n, p)``.

For whole dof the chi-square survival function is a finite sum (Abramowitz & Stegun 26.4.4-5):
``Q(x) = e^(-x/2) sum_{j<m} (x/2)^j / j!`` for dof = 2m, and
``Q(x) = erfc(sqrt(x/2)) + e^(-x/2) sum_{j<m} (x/2)^(j+1/2) / Gamma(j+3/2)`` for dof = 2m + 1.
Each term is summed from its logarithm, so that no power or factorial overflows at hundreds of
degrees of freedom.
"""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np


def chi2_survival(x: float, dof: int) -> float:
    """``P(X > x)`` for X ~ chi^2(dof), dof a whole number >= 1."""
    if x <= 0.0:
        return 1.0
    half = 0.5 * x
    j = np.arange(dof // 2)
    if dof % 2 == 0:  # terms (x/2)^j / j!
        log_terms = -half + j * math.log(half) - np.cumsum(np.log(np.maximum(j, 1)))
        return float(np.exp(log_terms).sum())
    # terms (x/2)^(j+1/2) / Gamma(j+3/2), with Gamma(j+3/2) = Gamma(3/2) prod_{i=1..j} (i+1/2)
    log_gamma = _LOG_GAMMA_3_2 + np.cumsum(np.log(np.where(j > 0, j + 0.5, 1.0)))
    log_terms = -half + (j + 0.5) * math.log(half) - log_gamma
    return math.erfc(math.sqrt(half)) + float(np.exp(log_terms).sum())


def chi2_cdf(x: float, dof: int) -> float:
    """``P(X <= x)`` for X ~ chi^2(dof), by the series of the regularized lower incomplete gamma
    function, ``e^(-y) y^a / Gamma(a+1) sum_n y^n / ((a+1)...(a+n))`` with a = dof/2, y = x/2: exact
    to rounding where ``chi2_survival`` would subtract from 1, and quick below the median, where
    its terms fall at once (the only place ``chi2_quantile`` calls it)."""
    if x <= 0.0:
        return 0.0
    a, y = 0.5 * dof, 0.5 * x
    term = total = 1.0
    n = 1
    while term > 1e-17 * total:
        term *= y / (a + n)
        total += term
        n += 1
    return math.exp(-y + a * math.log(y) - math.lgamma(a + 1.0)) * total


def chi2_density(x: float, dof: int) -> float:
    """The chi^2(dof) density at x > 0."""
    k = 0.5 * dof
    return math.exp((k - 1.0) * math.log(x) - 0.5 * x - k * math.log(2.0) - math.lgamma(k))


def chi2_quantile(dof, tail):
    """The x with ``P(X > x) = tail`` for X ~ chi^2(dof): a float for scalar arguments, else an
    array of the arguments' broadcast shape. dof whole numbers >= 1, tail in (0, 1).

    Newton's method from the Wilson-Hilferty approximation, on the survival function above the
    median and on the distribution function below it (the tests hold it to scipy's ``chdtri``)."""
    dof_array, tail_array = np.broadcast_arrays(np.asarray(dof), np.asarray(tail, dtype=float))
    out = np.array([_chi2_quantile(int(d), float(q)) for d, q in zip(dof_array.ravel(), tail_array.ravel())])
    return float(out[0]) if dof_array.ndim == 0 else out.reshape(dof_array.shape)


def binomial_tail(k, n, p):
    """``P(X > k)`` for X ~ Binomial(n, p): a float for scalar arguments, else an array of the
    arguments' broadcast shape. ``k < 0`` gives 1 and ``k >= n`` gives 0."""
    k_array, n_array, p_array = np.broadcast_arrays(np.asarray(k), np.asarray(n), np.asarray(p, dtype=float))
    out = np.array([_binomial_tail(int(a), int(b), float(c)) for a, b, c in zip(k_array.ravel(), n_array.ravel(), p_array.ravel())])
    return float(out[0]) if k_array.ndim == 0 else out.reshape(k_array.shape)


def _chi2_quantile(dof: int, tail: float) -> float:
    if not (dof >= 1 and 0.0 < tail < 1.0):
        raise ValueError(f"chi2_quantile needs dof >= 1 and 0 < tail < 1, got dof {dof}, tail {tail}")
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


def _binomial_tail(k: int, n: int, p: float) -> float:
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


_LOG_GAMMA_3_2 = math.lgamma(1.5)
