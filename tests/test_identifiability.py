"""`inverse._identifiability.quantity_error`: a function of the parameters is determined when its
gradient is orthogonal to the null directions (an estimable function), however many of the
parameters it involves take part in them. The references are least-squares fits of the same
data in a parametrisation without the null direction (`numpy.linalg.lstsq`)."""

import math

import numpy as np
import pytest

from inverse._identifiability import identifiability, quantity_error

X = np.linspace(-1.0, 1.0, 30)
F1, F2 = np.exp(-X ** 2), 1.0 + 0.5 * X  # two basis functions


def _data(sigma: float, seed: int) -> np.ndarray:
    return 2.0 * F1 + 0.7 * F2 + sigma * np.random.default_rng(seed).normal(size=X.size)


def test_sum_of_trading_parameters_is_determined_with_the_reduced_fits_error():
    """y = (a + 1000 b) F1 + c F2: a and b trade exactly (their columns differ by a factor 1000:
    the rule is scale-free). a + 1000 b and c are determined, a, b and a - b are not; the
    standard errors of a + 1000 b and c are those of the fit of y = s F1 + c F2, with the noise
    told and with it estimated from the residual."""
    y = _data(0.05, 0)
    J = np.stack([F1, 1000.0 * F1, F2], axis=1) / 0.05  # the weighted residual's Jacobian
    A = np.stack([F1, F2], axis=1)
    coef, rss, *_ = np.linalg.lstsq(A, y, rcond=None)
    told = np.sqrt(np.diag(0.05 ** 2 * np.linalg.inv(A.T @ A)))
    dof = X.size - 3  # the residual's degrees of freedom as the module counts them: three free parameters
    estimated = np.sqrt(np.diag(float(rss[0]) / dof * np.linalg.inv(A.T @ A)))
    for row_var, ref in ((np.ones(X.size), told), (None, estimated)):
        ident = identifiability(J, float(rss[0]) / 0.05 ** 2, X.size, row_variance=row_var)
        assert len(ident.null_space) == 1 and not ident.determined[:2].any() and ident.determined[2]
        ok, se = quantity_error(ident, np.array([1.0, 1000.0, 0.0]))
        assert ok and se == pytest.approx(ref[0], rel=1e-9)
        ok, se = quantity_error(ident, np.array([0.0, 0.0, 1.0]))
        assert ok and se == pytest.approx(ref[1], rel=1e-9)
        for g in ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1000.0 * (1 + 1e-4), 0.0]):
            assert quantity_error(ident, np.array(g)) == (False, math.inf)
    assert coef[0] == pytest.approx(2.0, abs=0.1)


def test_size_and_radiance_trade_exactly_the_flux_is_determined():
    """y = p e^{2u} F1 (a radiance p and a log size u that trade exactly: the model depends on
    the flux p e^{2u} alone): at the least-squares answer the flux is determined, with the
    standard error of the one-parameter fit y = phi F1 (sigma / |F1|); p and u are not."""
    y = 1.3 * F1 + 0.02 * np.random.default_rng(1).normal(size=X.size)
    phi = float(F1 @ y / (F1 @ F1))
    p, u = 2.0, 0.5 * math.log(phi / 2.0)  # one of the answers
    J = np.stack([math.exp(2 * u) * F1, 2 * p * math.exp(2 * u) * F1], axis=1) / 0.02
    ident = identifiability(J, 0.0, X.size, row_variance=np.ones(X.size))
    assert not ident.determined.any()
    ok, se = quantity_error(ident, np.array([math.exp(2 * u), 2 * p * math.exp(2 * u)]))
    assert ok and se == pytest.approx(0.02 / np.linalg.norm(F1), rel=1e-9)
    assert not quantity_error(ident, np.array([1.0, 0.0]))[0]


def test_zero_column_and_fixed_parameters():
    """A parameter the data do not see (a zero column) makes any quantity that involves it
    undetermined; one held fixed counts as known (no error); a quantity of nothing else is
    determined with no error."""
    J = np.stack([F1, np.zeros(X.size), F2], axis=1)
    ident = identifiability(J, 0.0, X.size, row_variance=np.ones(X.size))
    assert quantity_error(ident, np.array([1.0, 0.5, 0.0]))[0] is False
    ok, se = quantity_error(ident, np.array([1.0, 0.0, 0.0]))
    assert ok and se == pytest.approx(math.sqrt(np.linalg.inv(np.stack([F1, F2], 1).T @ np.stack([F1, F2], 1))[0, 0]),
                                      rel=1e-9)
    fixed = identifiability(J, 0.0, X.size, free=np.array([True, True, False]), row_variance=np.ones(X.size))
    ok, se = quantity_error(fixed, np.array([1.0, 0.0, 3.0]))
    assert ok and se == pytest.approx(1.0 / np.linalg.norm(F1), rel=1e-9)
    assert quantity_error(fixed, np.zeros(3)) == (True, 0.0)
