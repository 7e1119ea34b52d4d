"""Issue #40: where to paint more targets (`LightsReport.suggestions`): for every parameter the
targets do not determine, exactly or nearly, candidates from the whole receiver region (not
collapsed onto the targets' own line), kept where they lower the predicted standard error, and
painting them does lower it."""

import numpy as np
import pytest

import inverse
import jaxshadow as js
from inverse import _diagnostics as diag

MATERIAL = js.Material(ka=0.2, kd=0.6, ks=0.0, exponent=1.0)
EYE = np.array([0.0, -2.0, 2.0])


def test_targets_on_a_line_get_suggestions_off_it():
    """Floor targets on the x axis: a point light's distance from the line and its height trade
    off with its power (a circle around the line paints them alike). The suggestions are off the
    line, distinct, and predicted to determine the parameters."""
    x = np.linspace(-1.0, 1.0, 16)
    pts = np.c_[x, np.zeros(16), np.zeros(16)]
    nrm = np.tile([0.0, 0.0, 1.0], (16, 1))
    true = js.Scene([js.PointLight([0.3, 0.5, 1.2], 3.0)], ambient=0.05)
    targets = inverse.PaintedTargets(pts, nrm, js.shade(true, MATERIAL, pts, nrm, EYE), EYE)
    start = js.Scene([js.PointLight([-0.4, 0.1, 1.5], 3.0)], ambient=0.05)
    rep = inverse.fit_lights(start, targets, MATERIAL, fit=("position", "power"), noise=1e-3, warn=False).report
    assert not rep.determined["light0.y"] and np.isinf(rep.std_errors["light0.y"])
    for nm in ("light0.y", "light0.z", "light0.power"):
        where = rep.suggestions[nm]
        assert len(where) >= 3 and np.all(np.abs(where[:, 1]) > 0.1)  # off the line
        assert len({tuple(np.round(p, 9)) for p in where}) == len(where)  # no point listed twice
        now, predicted = rep.suggestion_std_errors[nm]
        assert np.isinf(now) and np.isfinite(predicted)
    assert "predicted standard error inf ->" in str(rep)


def test_nearly_undetermined_height_gets_suggestions_that_determine_it():
    """Floor targets on a nearly exact circle (radii within 0.2 %) around a point light's foot,
    1 % noise: the height and power are nearly undetermined (standard errors above a quarter of
    the scene and above the power). Suggestions appear for them, with a predicted standard error
    far below the present one; painting the first three there brings the refitted standard
    error down as predicted (within a factor 3: the prediction is linearised at the first fit)."""
    rng = np.random.default_rng(1)
    a = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
    rad = 1.0 + 0.002 * rng.uniform(-1.0, 1.0, 24)
    pts = np.c_[0.2 + rad * np.cos(a), -0.1 + rad * np.sin(a), np.zeros(24)]
    nrm = np.tile([0.0, 0.0, 1.0], (24, 1))
    true = js.Scene([js.PointLight([0.2, -0.1, 1.5], 3.0)], ambient=0.1)
    start = js.Scene([js.PointLight([0.35, 0.05, 1.5], 2.0)], ambient=0.1)

    def fit(p, n):
        c = np.asarray(js.shade(true, MATERIAL, p, n, EYE), np.float64)
        c = c * (1.0 + 0.01 * np.random.default_rng(0).normal(size=c.shape))
        return inverse.fit_lights(start, inverse.PaintedTargets(p, n, c, EYE), MATERIAL, fit=("position", "power"),
                                  starts=1, noise=0.01 * c, warn=False).report

    rep = fit(pts, nrm)
    assert set(rep.quality.nearly_undetermined) == {"light0.z", "light0.power"}
    assert rep.std_errors["light0.z"] > diag.NEAR_POSITION_FRACTION * rep.scale
    now, predicted = rep.suggestion_std_errors["light0.z"]
    assert now == pytest.approx(rep.std_errors["light0.z"], rel=1e-6) and predicted < 0.05 * now
    assert "light0.x" not in rep.suggestions  # determined: nothing to suggest
    more = np.concatenate([pts, rep.suggestions["light0.z"][:3]])
    nrm2 = np.concatenate([nrm, rep.suggestion_normals["light0.z"][:3]])
    rep2 = fit(more, nrm2)
    assert rep2.determined["light0.z"] and rep2.trusted
    assert predicted / 3 < rep2.std_errors["light0.z"] < 3 * predicted
