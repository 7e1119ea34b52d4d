"""`fit_lights(grid=...)`: the greedy placement (one light at a time, the unplaced ones left out
of the model) and the deal of the placed positions to the lights. Two point lights of different
colours, each started near the *other* one's true position (the labels swapped), 0.3 m off:
both come back exactly, each with its own colour."""

import numpy as np

import inverse
import jaxshadow as js
from benchmarks.inverse_scenes import THREE_LIGHTS_EYE as EYE
from benchmarks.inverse_scenes import floor_receivers

MATERIAL = js.Material(ka=0.2, kd=[0.6, 0.5, 0.4], ks=0.0, exponent=1.0)
WARM, COLD = np.array([4.0, 3.0, 2.0]), np.array([1.0, 1.5, 2.5])
TRUE = js.Scene([js.PointLight([-0.6, 0.2, 1.5], WARM), js.PointLight([0.7, -0.3, 1.2], COLD)], ambient=0.1)
# light 0 (warm) starts near light 1's truth and light 1 (cold) near light 0's
START = js.Scene([js.PointLight([0.9, -0.1, 1.4], WARM), js.PointLight([-0.4, 0.4, 1.3], COLD)], ambient=0.1)


def test_greedy_placement_undoes_swapped_starts():
    pts, nrm = floor_receivers(40, seed=2)
    targets = inverse.PaintedTargets(pts, nrm, js.shade(TRUE, MATERIAL, pts, nrm, EYE), EYE)
    fit = inverse.fit_lights(START, targets, MATERIAL, fit=("position", "power"), starts=2, sweeps=1, grid=16)
    for got, want in zip(fit.lights, TRUE.lights, strict=True):
        np.testing.assert_allclose(got.position, want.position, atol=1e-6)
        np.testing.assert_allclose(got.intensity, want.intensity, rtol=1e-6)
    assert fit.report.loss < 1e-20
