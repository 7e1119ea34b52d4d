"""The material fit's specular through the shadow engine (`inverse._forward.EngineSpecular`)."""

import jax.numpy as jnp
import numpy as np
import pytest

import inverse
import jaxshadow as js
from inverse._forward import EngineSpecular, material_specular, traced_specular
from inverse._material import SPEC_CHUNK, _Basis, _spec_eval


def _scene():
    light = js.PolygonLight([[-0.5, 0.5, 2], [0.5, 0.5, 2], [0.5, -0.5, 2], [-0.5, -0.5, 2]], radiance=[3.0, 2.0, 1.0])
    box = [np.array([[-0.3, -0.3, 0.8], [0.3, -0.3, 0.8], [0.3, 0.3, 0.8], [-0.3, 0.3, 0.8]]),
           np.array([[0.1, 0.2, 0.5], [0.6, 0.2, 0.5], [0.4, 0.7, 0.6]])]
    scene = js.Scene([light], occluders=box, ambient=0.1)
    rng = np.random.default_rng(5)
    points = np.c_[rng.uniform(-1, 1, (30, 2)), np.zeros(30)]
    normals = np.tile([0.0, 0.0, 1.0], (30, 1))
    return scene, points, normals, np.array([0.3, -2.0, 2.0])


def test_engine_specular_is_js_specular_and_flags_a_short_capacity():
    scene, points, normals, eye = _scene()
    fn = material_specular(scene, points, normals)
    assert isinstance(fn, EngineSpecular) and fn.capacity % 8 == 0
    p, n = jnp.asarray(points), jnp.asarray(normals)
    want = np.asarray(js.specular(scene, points, normals, np.broadcast_to(eye, points.shape), 25.0))
    np.testing.assert_allclose(np.asarray(fn(scene, p, n, jnp.asarray(eye), jnp.asarray(25.0))), want, rtol=1e-12, atol=1e-15)
    shadowed = np.asarray(js.irradiance(scene, points, normals))[:, 0]
    assert np.ptp(shadowed) > 0.1 * shadowed.max() and want.max() > 0  # penumbrae and a highlight
    assert not bool(fn.with_overflow(scene, p, n, jnp.asarray(eye), jnp.asarray(25.0))[1])
    assert bool(EngineSpecular(1).with_overflow(scene, p, n, jnp.asarray(eye), jnp.asarray(25.0))[1])
    t = inverse.PaintedTargets(points, normals, np.ones((30, 3)), eye)
    assert bool(_spec_eval(EngineSpecular(1), scene, t, jnp.full((SPEC_CHUNK,), 25.0))[2])
    with pytest.raises(RuntimeError, match="capacity"):
        _Basis(scene, t, EngineSpecular(1)).spec(25.0)
    assert material_specular(js.Scene(list(scene.lights)), points, normals) is traced_specular


def test_fit_material_with_occluders_recovers_the_painting_material():
    scene, points, normals, eye = _scene()
    true = js.Material(ka=[0.3, 0.2, 0.1], kd=[0.5, 0.6, 0.4], ks=[0.3, 0.2, 0.25], exponent=18.0)
    colours = np.asarray(js.shade(scene, true, points, normals, eye))
    r = inverse.fit_material(scene, inverse.PaintedTargets(points, normals, colours, eye))
    for f in ("ka", "kd", "ks"):
        np.testing.assert_allclose(np.asarray(getattr(r.material, f)), np.asarray(getattr(true, f)), atol=1e-6)
    assert abs(float(r.material.exponent) - 18.0) < 1e-3 * 18.0
