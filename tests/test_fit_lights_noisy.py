"""Issue #40: noisy several-light fits are honest about placements the search never refined.

`inverse._rescreen.noise_contenders` (each light screened again over its candidates with the
others held at the answer, at the told noise), `inverse._rescreen.noise_rivals` (those refined
and handed to the rival check) and `inverse._uncertainty.widened` (a flagged fit's standard
errors widened over its rivals' spread).
"""

import math

import numpy as np
import pytest

from inverse import _diagnostics as diag
from inverse import _rescreen
from inverse._uncertainty import Quantity, widened

XS = np.linspace(-1.0, 1.0, 50)


def _column(row: np.ndarray) -> np.ndarray:
    """A light's unit column at centre `row`: a bump at x = row[0], dimmer with |row[1]| (so a
    centre and its mirror image in y = 0 paint alike)."""
    return np.exp(-((XS - row[0]) ** 2) / 0.1) / (1.0 + row[1] ** 2) / row[2] ** 2


def test_noise_contenders_keep_distinct_candidates_within_the_margin():
    """A candidate whose column paints like the answer's light (its mirror image) is kept, one
    beside the answer (within `away`) or beside a kept one is not, nor one that explains the
    targets far worse than the answer; the other lights stay at the answer; the best pair with
    both lights moved follows."""
    theta = np.array([0.2, 0.5, 1.0, -0.3, 0.1, 1.0])
    sizes, offsets = [3, 3], (0, 3)
    noise = 1e-3
    y = 2.0 * _column(theta[:3]) + 0.5 * _column(theta[3:])  # the answer and the mirror images paint y exactly
    rows = [np.array([[0.2, 0.5, 1.0], [0.9, 0.5, 1.0], [0.2, -0.5, 1.0], [0.2, -0.51, 1.0]]),
            np.array([[-0.3, 0.11, 1.0], [-0.3, -0.1, 1.0]])]
    cols = [np.stack([_column(r) for r in rows[j]]) for j in range(2)]
    out = _rescreen.noise_contenders(theta, [0, 1], offsets, sizes, rows, cols, y, True,
                                     lambda j, r: np.stack([_column(x) for x in r]), lambda j, r: np.asarray(r),
                                     noise ** 2, diag.rival_allowance(8), 0.05)
    # each light's mirror image alone, then both (the pair move; the two lights' own far candidates)
    want = [np.r_[0.2, -0.5, 1.0, theta[3:]], np.r_[theta[:3], -0.3, -0.1, 1.0], np.r_[0.2, -0.5, 1.0, -0.3, -0.1, 1.0]]
    np.testing.assert_array_equal(out, np.stack(want))
    # The far candidate's excess is far beyond the margin (it paints the bump elsewhere).
    f = _rescreen.nnls_rss(_column(theta[3:])[:, None], cols[0], y, True)
    assert (f[1] - f[0]) / noise ** 2 > 100 * _rescreen.SCREEN_MARGIN * diag.rival_allowance(8)


def test_noise_contenders_none_when_nothing_competes():
    """With no candidate within the margin (the noise far smaller than any candidate's misfit),
    nothing is refined."""
    theta = np.array([0.2, 0.5, 1.0])
    y = 2.0 * _column(theta)
    rows = [np.array([[0.6, 0.5, 1.0], [-0.5, 0.9, 1.3]])]
    cols = [np.stack([_column(r) for r in rows[0]])]
    out = _rescreen.noise_contenders(theta, [0], (0,), [3], rows, cols, y, True,
                                     lambda j, r: np.stack([_column(x) for x in r]), lambda j, r: np.asarray(r),
                                     1e-8, diag.rival_allowance(4), 0.05)
    assert out.shape == (0, 3)


def test_widened_by_the_rivals_spread():
    """Each centre coordinate, power and emitted power: the standard error and the interval's
    half-width grow by the largest distance to a rival along that quantity (hand-computed)."""
    se = {"light0.x": 0.01, "light0.y": 0.01, "light0.z": 0.02, "light0.power": 0.05, "light1.x": 0.03}
    q = {"light0.x": Quantity(0.0, 0.01, 0.04, True), "light0.flux": Quantity(3.0, 0.1, 0.3, True),
         "light1.x": Quantity(1.0, 0.03, 0.1, True)}
    answer = {"light0": {"centre": (0.0, 0.0, 1.0), "power": 2.0, "emitted": 10.0},
              "light1": {"centre": (1.0, 0.0, 1.0), "power": 1.0, "emitted": 4.0}}
    rivals = ((1.0, {"light0": {"centre": (0.3, 0.0, 1.1), "power": 2.5, "emitted": 12.0}, "light1": answer["light1"]},
               ("light0",)),
              (2.0, {"light0": {"centre": (-0.1, 0.05, 1.0), "power": 1.5, "emitted": 9.0},
                     "light1": answer["light1"]}, ("light0",)))
    se2, q2 = widened(se, q, answer, rivals)
    assert se2 == pytest.approx({"light0.x": 0.31, "light0.y": 0.06, "light0.z": 0.12, "light0.power": 0.55,
                                 "light1.x": 0.03})
    assert (q2["light0.x"].std_error, q2["light0.x"].interval) == pytest.approx((0.31, 0.34))
    assert (q2["light0.flux"].std_error, q2["light0.flux"].interval) == pytest.approx((0.7, 0.9))  # 20 % of 3.0
    assert q2["light1.x"] == q["light1.x"] and q2["light0.x"].determined
    assert widened(se, q, answer, ()) == (se, q)
    assert not math.isinf(se2["light0.x"])


def _mirror_case():
    """A point light over floor targets on a line (y = 0) with normals tilted about the y axis
    only: its mirror image in y = 0 paints every target alike (`test_fit_rivals`); 1 % noise."""
    import jaxshadow as js

    x = np.linspace(-1.0, 1.0, 16)
    pts = np.c_[x, np.zeros(16), np.zeros(16)]
    a = np.linspace(-0.6, 0.6, 16)[np.random.default_rng(0).permutation(16)]
    nrm = np.c_[np.sin(a), np.zeros(16), np.cos(a)]
    material = js.Material(ka=0.2, kd=0.6, ks=0.0, exponent=1.0)
    eye = np.array([0.0, -2.0, 2.0])
    true = js.Scene([js.PointLight([0.3, 0.15, 1.2], 3.0)], ambient=0.05)
    col = np.asarray(js.shade(true, material, pts, nrm, eye), np.float64)
    col = col * (1.0 + 0.01 * np.random.default_rng(3).normal(size=col.shape))
    start = js.Scene([js.PointLight([-0.4, 0.1, 1.5], 3.0)], ambient=0.05)
    return start, pts, nrm, col, eye, material


def test_mirror_found_by_the_rescreen_and_standard_errors_widened(monkeypatch):
    """With the final joint solve given none of the global placement's other basins
    (`ALTERNATIVES` 0), the placements of the re-screen at the told noise (`noise_rivals`)
    hold the mirror image; the fit is flagged with the rival named there, and the standard
    error of y is widened to span it (the linearised one is ~100 times smaller)."""
    import inverse
    from inverse import _fit_lights, _global_placement
    from inverse._placement_rank import centre_of_row

    monkeypatch.setattr(_global_placement, "ALTERNATIVES", 0)
    seen = []
    real = _fit_lights.noise_rivals

    def spy(*a, **k):
        out = real(*a, **k)
        seen.append(out[1])
        return out

    monkeypatch.setattr(_fit_lights, "noise_rivals", spy)
    start, pts, nrm, col, eye, material = _mirror_case()
    targets = inverse.PaintedTargets(pts, nrm, col, eye)
    fit = inverse.fit_lights(start, targets, material, fit=("position", "power"), noise=0.01 * col, warn=False)
    got = np.asarray(fit.lights[0].position, np.float64)
    mirror = got * [1.0, -1.0, 1.0]
    assert len(seen) == 1
    centres = [centre_of_row(fit.parametrisations[0], r) for r in seen[0][0]]
    assert min(np.linalg.norm(c - mirror) for c in centres) < 0.05
    q = fit.report.quality
    assert "competing_placements" in q.flags and not fit.report.trusted
    excess, poses, differ = q.rivals[0]
    assert differ == ("light0",)
    np.testing.assert_allclose(poses["light0"]["centre"], mirror, atol=0.02)
    # y's standard error spans the mirror: |y_answer - y_rival| = 2 |y| plus the linearised error
    # (about 0.01 m at 1 % noise; the widest rival sets it)
    se_y = fit.report.std_errors["light0.y"]
    assert 2.0 * abs(got[1]) < se_y < 1.0
    qy = fit.report.quantities["light0.y"]
    assert qy.std_error == pytest.approx(se_y) and qy.interval > 2.0 * abs(got[1])


def test_clean_noisy_fit_not_flagged():
    """No false alarm: a point light over targets spread on the floor (no mirror image, no
    occluder), 1 % noise, is recovered within 3 standard errors and not flagged with competing
    placements, although the re-screen ran (told noise, global placement)."""
    import inverse
    import jaxshadow as js

    rng = np.random.default_rng(5)
    pts = np.c_[rng.uniform(-1.0, 1.0, (30, 2)), np.zeros(30)]
    nrm = np.tile([0.0, 0.0, 1.0], (30, 1))
    material = js.Material(ka=0.2, kd=0.6, ks=0.0, exponent=1.0)
    eye = np.array([0.0, -2.0, 2.0])
    truth = np.array([0.3, 0.15, 1.2])
    col = np.asarray(js.shade(js.Scene([js.PointLight(truth, 3.0)], ambient=0.05), material, pts, nrm, eye))
    col = col * (1.0 + 0.01 * np.random.default_rng(6).normal(size=col.shape))
    start = js.Scene([js.PointLight([-0.4, 0.1, 1.5], 3.0)], ambient=0.05)
    fit = inverse.fit_lights(start, inverse.PaintedTargets(pts, nrm, col, eye), material, fit=("position", "power"),
                             noise=0.01 * col, warn=False)
    assert "competing_placements" not in fit.report.quality.flags and fit.report.trusted
    got = np.asarray(fit.lights[0].position, np.float64)
    se = np.array([fit.report.std_errors[f"light0.{ax}"] for ax in "xyz"])
    assert np.all(np.abs(got - truth) < 3.0 * se)



def test_explained_loss_hand_computed():
    """The loss below which a fit explains its targets within the told noise: with one standard
    deviation sigma everywhere, $\\tfrac12 w\\sigma^2(\\nu + \\sqrt{2\\nu})$, $\\nu = 3N - n$; none
    when the noise is estimated; with per-entry noise the fit's weights $\\propto 1/\\sigma^2$
    turn it into the same chi-square bound. A residual of the told noise's size lies below it,
    one of twice that size (a wrong minimum's misfit on top of the noise) far above."""
    import inverse

    rng = np.random.default_rng(2)
    n, p = 60, 8
    col = 0.5 + rng.uniform(size=(n, 3))
    t = inverse.PaintedTargets(np.c_[rng.uniform(size=(n, 2)), np.zeros(n)], np.tile([0.0, 0.0, 1.0], (n, 1)),
                               col, np.array([0.0, 0.0, 3.0]))
    nu = 3 * n - p
    assert diag.explained_loss(t.weights, t, 0.02, p) == pytest.approx(0.5 * 0.02 ** 2 * (nu + math.sqrt(2 * nu)))
    assert diag.explained_loss(t.weights, t, None, p) == 0.0
    sigma = 0.01 * col
    tw = diag.noise_weighted(t, sigma)
    w = np.asarray(tw.weights, np.float64)
    bound = diag.explained_loss(tw.weights, tw, sigma, p)
    assert bound == pytest.approx(0.5 * float(np.mean(w * sigma ** 2)) * (nu + math.sqrt(2 * nu)))
    r = sigma * rng.normal(size=col.shape) * math.sqrt(nu / (3 * n))  # chi-square nu: a right minimum's
    assert 0.5 * float(np.sum(w * r ** 2)) < bound
    assert 0.5 * float(np.sum(w * (2.0 * sigma) ** 2)) > 3.0 * bound


def _spread_case(noise: float = 0.01):
    """A point light over 30 targets spread on the floor (`test_clean_noisy_fit_not_flagged`),
    `noise` relative Gaussian noise."""
    import inverse
    import jaxshadow as js

    rng = np.random.default_rng(5)
    pts = np.c_[rng.uniform(-1.0, 1.0, (30, 2)), np.zeros(30)]
    nrm = np.tile([0.0, 0.0, 1.0], (30, 1))
    material = js.Material(ka=0.2, kd=0.6, ks=0.0, exponent=1.0)
    eye = np.array([0.0, -2.0, 2.0])
    col = np.asarray(js.shade(js.Scene([js.PointLight([0.3, 0.15, 1.2], 3.0)], ambient=0.05), material, pts, nrm,
                              eye))
    col = col * (1.0 + noise * np.random.default_rng(6).normal(size=col.shape))
    return inverse.PaintedTargets(pts, nrm, col, eye), material, col


def test_noisy_fit_stops_when_explained(monkeypatch):
    """`fit_lights`' early exit at a fit explained within the told noise (`EXPLAINED_EXIT`): the
    global placement's refined answer explains the 1 % noisy targets, so the per-light sweeps
    after it are skipped (fewer starts solved than with the exit off) and the answer is the same
    minimum. Told a noise ten times smaller than the added one, the same residual is ten
    standard deviations per entry, what a wrong minimum's misfit looks like to the rule: no early
    exit, the sweeps run as with the exit off."""
    import inverse
    import jaxshadow as js
    from inverse import _fit_lights

    targets, material, col = _spread_case()
    empty = js.Scene([], ambient=0.05)

    def fit(exit_on: bool, told: float):
        monkeypatch.setattr(_fit_lights, "EXPLAINED_EXIT", exit_on)
        return inverse.fit_lights(empty, targets, material, kinds=["point"], noise=told * col, warn=False)

    on, off = fit(True, 0.01), fit(False, 0.01)
    assert on.report.starts_solved < off.report.starts_solved
    se = np.array([on.report.std_errors[f"light0.{ax}"] for ax in "xyz"])
    a, b = (np.asarray(f.lights[0].position, np.float64) for f in (on, off))
    assert np.all(np.abs(a - b) < 0.1 * se)
    tight_on, tight_off = fit(True, 0.001), fit(False, 0.001)
    assert tight_on.report.starts_solved == tight_off.report.starts_solved
    assert tight_on.report.quality.chi2 > 10.0  # reduced chi-square: not explained at the told noise
