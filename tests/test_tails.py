"""The chi-square quantiles and binomial tails camloc computes itself, against scipy.special."""

import numpy as np
import pytest
from scipy.special import bdtrc, chdtri
from scipy.stats import chi2

from camloc.tails import binomial_tail, chi2_cdf, chi2_quantile, chi2_survival

DOFS = list(range(1, 41)) + [60, 99, 150, 301, 600, 1500] + [0.5, 2.7, 223.8, 6 * 37.31]  # and not whole: effective counts
TAILS = [1e-12, 1e-6, 0.001, 0.0027, 0.01, 0.05, 0.3, 0.5, 0.51, 0.9, 0.975, 0.99, 0.999, 1.0 - 1e-9]


@pytest.mark.parametrize("dof", DOFS)
def test_chi2_quantile_is_scipy_s_chdtri(dof):
    mine = chi2_quantile(dof, np.array(TAILS))
    np.testing.assert_allclose(mine, chdtri(dof, np.array(TAILS)), rtol=1e-11)
    # survival above the median, distribution function below it, each exact where it is used
    x = chdtri(dof, np.array([0.001, 0.5, 0.999]))
    np.testing.assert_allclose([chi2_survival(v, dof) for v in x[:2]], chi2.sf(x[:2], dof), rtol=1e-10)
    np.testing.assert_allclose([chi2_cdf(v, dof) for v in x[1:]], chi2.cdf(x[1:], dof), rtol=1e-12)


def test_chi2_quantile_takes_scalars_and_broadcasts():
    assert isinstance(chi2_quantile(3, 0.01), float) and chi2_quantile(3, 0.01) == pytest.approx(11.344866730144373, rel=1e-13)
    dof = 3 * np.arange(1, 7).reshape(2, 3)
    assert chi2_quantile(dof, 0.001).shape == (2, 3)
    np.testing.assert_allclose(chi2_quantile(dof, 0.001), chdtri(dof, 0.001), rtol=1e-12)
    # the edges as scipy's: a sure tail, an impossible one, and NaN for what has no answer
    edges = [(3, 0.0), (3, 1.0), (0, 0.5), (-1, 0.5), (np.nan, 0.5), (3, np.nan), (3, 1.5), (np.inf, 0.5)]
    np.testing.assert_array_equal([chi2_quantile(d, q) for d, q in edges], [chdtri(d, q) for d, q in edges])


def test_binomial_tail_is_scipy_s_bdtrc():
    k, n, p = np.meshgrid(np.arange(-2, 62), np.arange(0, 60), [0.0, 1e-3, 0.1, 0.37, 0.5, 0.9, 1.0], indexing="ij")
    defined = k <= n  # scipy gives NaN past n, where the tail is plainly 0
    np.testing.assert_allclose(binomial_tail(k, n, p)[defined], bdtrc(k, n, p)[defined], rtol=1e-11, atol=1e-15)
    assert np.all(binomial_tail(k, n, p)[~defined] == 0.0)
    assert binomial_tail(-1, 5, 0.2) == 1.0 and binomial_tail(5, 5, 0.2) == 0.0
    assert isinstance(binomial_tail(2, 10, 0.3), float)
    edges = [(1, 5, np.nan), (1, 5, 1.5), (np.nan, 5, 0.2), (1, 5, -0.1)]
    np.testing.assert_array_equal([binomial_tail(*e) for e in edges], [bdtrc(*e) for e in edges])
