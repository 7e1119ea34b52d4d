"""`inverse.Outside`: a light kept outside a solid made of occluders. The truth (a point light
between two upright plates) is inside their convex hull, so the unconstrained optimum (the
truth, loss 0) is inside; the constrained fit must end outside by the margin."""

import numpy as np
import pytest

import inverse
import jaxshadow as js
from benchmarks.inverse_scenes import THREE_LIGHTS_EYE as EYE
from benchmarks.inverse_scenes import floor_receivers, quad

MATERIAL = js.Material(ka=0.2, kd=[0.6, 0.5, 0.4], ks=0.0, exponent=1.0)
# Two plates facing +-x at x = -+0.05, y in [-0.3, 0.3], z in [1.0, 1.6]: their hull is that box.
PLATES = [quad([x, 0.0, 1.3], 0.6, 0.6, (0.0, np.pi / 2, 0.0)) for x in (-0.05, 0.05)]
LO, HI = np.array([-0.05, -0.3, 1.0]), np.array([0.05, 0.3, 1.6])


def _box_depth(c):
    """How far `c` is inside the box [LO, HI] (> 0 inside, <= 0 outside): the hull, analytically."""
    return float(np.min(np.minimum(c - LO, HI - c)))


def test_light_ends_outside_the_occluders_hull():
    np.testing.assert_allclose(np.sort(np.concatenate(PLATES), axis=0)[[0, -1]], [LO, HI], atol=1e-12)
    true = js.Scene([js.PointLight([0.0, 0.05, 1.3], 3.0)], occluders=PLATES, ambient=0.1)
    pts, nrm = floor_receivers(40, seed=2)
    targets = inverse.PaintedTargets(pts, nrm, js.shade(true, MATERIAL, pts, nrm, EYE), EYE)
    assert _box_depth(np.array([0.0, 0.05, 1.3])) > 0  # the truth (the unconstrained optimum) is inside
    start = js.Scene([js.PointLight([0.5, 0.3, 1.6], 2.0)], occluders=PLATES, ambient=0.1)
    margin = 0.02
    # The constraint excludes every light that paints these targets: said out loud (#40).
    with pytest.warns(inverse.FitQualityWarning, match="constraints that cannot paint these targets"):
        fit = inverse.fit_lights(start, targets, MATERIAL, fit=("position", "power"), starts=4,
                                 constraints={0: inverse.Outside([0, 1], margin=margin)})
    c = np.asarray(fit.lights[0].position)
    assert _box_depth(c) <= -margin + 1e-9, c
    assert fit.report.loss > 1e-8  # the constraint held the light away from the exact fit
    assert "wrong_minimum" in fit.report.quality.flags


def test_outside_errors():
    scene = js.Scene([js.PointLight([0.0, 0.0, 2.0], 1.0)], occluders=PLATES, ambient=0.1)
    pts, nrm = floor_receivers(8, seed=2)
    t = inverse.PaintedTargets(pts, nrm, np.full((8, 3), 0.2), EYE)
    with pytest.raises(ValueError, match="no volume"):
        inverse.fit_lights(scene, t, MATERIAL, constraints={0: inverse.Outside([0])})
    with pytest.raises(ValueError, match="out of range"):
        inverse.fit_lights(scene, t, MATERIAL, constraints={0: inverse.Outside([0, 5])})
    with pytest.raises(ValueError, match="margin"):
        inverse.Outside([0, 1], margin=-1.0)
    with pytest.raises(ValueError, match="position is not fitted"):
        inverse.fit_lights(scene, t, MATERIAL, fit=("power",), constraints={0: inverse.Outside([0, 1])})


def test_outside_depth_and_its_gradient():
    """The hinge's depth against the box's analytic one inside, and its gradient against central
    differences (a point light's position, in scene-size units)."""
    import jax
    import jax.numpy as jnp

    from inverse._multilight import LightsProblem, outside_depth
    from inverse._parametrisation import LightParametrisation, outside_planes

    scene = js.Scene([js.PointLight([0.01, 0.05, 1.3], 1.0)], occluders=PLATES, ambient=0.1)
    A, b = outside_planes(scene, inverse.Outside([0, 1]))
    param = LightParametrisation(scene.lights[0], 0, ("position",), None, 2.0, "sigmoid")
    pts, nrm = floor_receivers(2, seed=2)
    t = inverse.PaintedTargets(pts, nrm, np.full((2, 3), 0.2), EYE)
    z = jnp.zeros((2, 3))
    prob = LightsProblem((param,), tuple(scene.lights), scene, MATERIAL, t, z, z, (0,), True, False, False, None,
                         outside=((0, jnp.asarray(A), jnp.asarray(b), 0.02),))
    theta = jnp.zeros(3)
    depth = float(outside_depth(theta, prob)[0])
    np.testing.assert_allclose(depth, 0.02 + _box_depth(np.array([0.01, 0.05, 1.3])), atol=1e-12)
    g = np.asarray(jax.grad(lambda th: outside_depth(th, prob)[0])(theta))
    h = 1e-6
    fd = [(float(outside_depth(theta.at[i].add(h), prob)[0]) - float(outside_depth(theta.at[i].add(-h), prob)[0]))
          / (2 * h) for i in range(3)]
    np.testing.assert_allclose(g, fd, atol=1e-8)
    np.testing.assert_allclose(g, [-2.0, 0.0, 0.0], atol=1e-12)  # nearest face x = 0.05: d(depth)/dx = -scale
