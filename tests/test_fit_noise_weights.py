"""Told noise weights the light fits and sets their standard errors (`inverse._diagnostics.fit_weights`,
`row_variance`, `inverse._identifiability`).

With noise a fixed fraction of each colour, bright targets are far noisier than dark ones; an
equal-weight fit lets their noise dominate, and standard errors from the equal-weight Jacobian
and the residual's average scale do not describe its spread (two point lights 0.5-0.8 m over a
floor, colours spanning a factor 35, 1 % noise: 78 % of 320 errors within 2 standard errors,
the RMS z-score of one coordinate 2.45). Weighted by $1/\\sigma^2$, with the errors of that
problem under the told noise, they do.
"""

import warnings

import numpy as np
import pytest

import inverse
import jaxshadow as js
from inverse import _diagnostics as diag
from inverse._identifiability import identifiability

MATERIAL = js.Material(ka=0.1, kd=[0.6, 0.5, 0.4], ks=0.0, exponent=1.0)
EYE = np.array([0.0, -3.0, 2.5])
TRUE = js.Scene([js.PointLight([-0.5, 0.3, 0.5], 2.0), js.PointLight([0.6, -0.4, 0.8], 3.0)], ambient=0.05)
NOISE = 0.01
RUNS = 40


def _floor(n=60):
    rng = np.random.default_rng(123)
    return np.c_[rng.uniform(-1.5, 1.5, (n, 2)), np.zeros(n)], np.tile([0.0, 0.0, 1.0], (n, 1))


def _z_scores(fit, n_lights):
    """Per run: each light's x, y, z and power error over its reported standard error (the truth:
    `TRUE`, whose lights are also the start, so the true powers are 1)."""
    se = fit.report.std_errors
    out = []
    for j in range(n_lights):
        err = np.asarray(fit.lights[j].position) - np.asarray(TRUE.lights[j].position)
        out += [err[c] / se[f"light{j}.{ax}"] for c, ax in enumerate("xyz")]
        out.append((fit.powers[j] - 1.0) / se[f"light{j}.power"])
    return out


def test_noisy_fit_standard_errors_match_the_spread_over_noise_draws():
    """40 draws of 1 % relative noise on the same targets, each fitted from the truth (a local
    fit: the spread is the noise's, not a search's): every parameter's RMS z-score is within
    [0.7, 1.35] (1 within the sampling error of 40 draws, about 0.11) and >= 90 % of the 320
    errors are within 2 standard errors (95 % for Gaussian errors). Equal weights with the
    residual's scale gave 78 % and RMS z-scores up to 2.45."""
    pts, nrm = _floor()
    clean = np.asarray(js.shade(TRUE, MATERIAL, pts, nrm, EYE), np.float64)
    assert clean.max() / clean.min() > 20  # the noise differs by that much between targets
    z = []
    for seed in range(RUNS):
        col = clean * (1.0 + NOISE * np.random.default_rng(seed).normal(size=clean.shape))
        targets = inverse.PaintedTargets(pts, nrm, col, EYE)
        fit = inverse.fit_lights(TRUE, targets, MATERIAL, fit=("position", "power"), placement="local", starts=1,
                                 noise=NOISE * clean, warn=False)
        assert fit.report.quality.noise == "given"
        z.append(_z_scores(fit, 2))
    z = np.asarray(z)
    rms = np.sqrt(np.mean(z ** 2, axis=0))
    assert np.all((rms > 0.7) & (rms < 1.35)), rms
    assert np.mean(np.abs(z) < 2.0) >= 0.9, np.mean(np.abs(z) < 2.0)


def test_fit_light_standard_errors_match_the_spread_over_noise_draws():
    """The same for `fit_light` (one point light's position, the other held): RMS z-score per
    coordinate within [0.7, 1.35] over 40 draws."""
    pts, nrm = _floor()
    clean = np.asarray(js.shade(TRUE, MATERIAL, pts, nrm, EYE), np.float64)
    z = []
    for seed in range(RUNS):
        col = clean * (1.0 + NOISE * np.random.default_rng(500 + seed).normal(size=clean.shape))
        targets = inverse.PaintedTargets(pts, nrm, col, EYE)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", inverse.FitQualityWarning)
            fit = inverse.fit_light(TRUE, targets, MATERIAL, 0, fit=("position",), starts=1,
                                    solver=inverse.LM(refine=None), noise=NOISE * clean)
        err = np.asarray(fit.light.position) - np.asarray(TRUE.lights[0].position)
        z.append([err[c] / fit.report.std_errors[ax] for c, ax in enumerate("xyz")])
    rms = np.sqrt(np.mean(np.asarray(z) ** 2, axis=0))
    assert np.all((rms > 0.7) & (rms < 1.35)), rms


def test_fit_weights_are_inverse_variances_times_the_given_weights():
    pts, nrm = _floor(4)
    col = np.full((4, 3), 0.5)
    w = np.array([1.0, 2.0, 0.0, 4.0])
    targets = inverse.PaintedTargets(pts, nrm, col, EYE, weights=w)
    sigma = np.array([[0.1], [0.2], [0.3], [0.4]]) * np.array([1.0, 1.0, 2.0])
    fw = diag.fit_weights(targets, sigma)
    expected = w[:, None] / sigma ** 2
    expected *= np.sum(np.broadcast_to(w[:, None], (4, 3))) / expected.sum()  # the weights' sum kept
    np.testing.assert_allclose(fw, expected, rtol=1e-12)
    assert np.all(fw[2] == 0)
    # the same noise everywhere, the noise estimated or the weights as inverse variances: as given
    assert diag.fit_weights(targets, 0.05) is None
    assert diag.fit_weights(targets, None) is None and diag.fit_weights(targets, "weights") is None
    with pytest.raises(ValueError, match="noise"):
        diag.fit_weights(targets, -1.0)
    v = diag.row_variance(fw, targets, sigma).reshape(4, 3)
    np.testing.assert_allclose(v[[0, 1, 3]], (fw * sigma ** 2)[[0, 1, 3]], rtol=1e-12)
    assert np.all(v[2] == 0) and diag.row_variance(fw, targets, None) is None


def test_told_noise_standard_errors_of_a_linear_fit_match_monte_carlo():
    """A linear model $y = X b$ with heteroscedastic noise, fitted with equal weights (rows not
    scaled by the noise): the told-noise standard errors (the sandwich) against the spread of
    20 000 simulated least-squares estimates; the residual-scaled ones miss it. Weighted by
    $1/\\sigma^2$ they are $\\sqrt{\\operatorname{diag}(X^\\top W X)^{-1}}$."""
    rng = np.random.default_rng(0)
    X = np.c_[np.ones(50), np.linspace(0.0, 1.0, 50), np.linspace(0.0, 1.0, 50) ** 3]
    sigma = 0.01 + 0.5 * np.linspace(0.0, 1.0, 50) ** 4  # the noise grows where the leverage is
    ident = identifiability(X, float(np.sum(sigma ** 2)), 50, row_variance=sigma ** 2)
    draws = rng.normal(size=(20000, 50)) * sigma
    b = np.linalg.lstsq(X, draws.T, rcond=None)[0]  # the estimates' errors (truth 0)
    np.testing.assert_allclose(ident.std_errors, b.std(axis=1), rtol=0.03)
    plain = identifiability(X, float(np.sum(sigma ** 2)), 50)  # the average variance: too small here
    assert plain.std_errors[2] < 0.8 * b[2].std()
    sw = 1.0 / sigma
    weighted = identifiability(X * sw[:, None], 47.0, 50, row_variance=np.ones(50))
    np.testing.assert_allclose(weighted.std_errors, np.sqrt(np.diag(np.linalg.inv(X.T @ (X * sw[:, None] ** 2)))),
                               rtol=1e-9)
