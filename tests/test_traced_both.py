"""`jaxshadow.traced.irradiance_and_specular`: one engine run for both integrals, the values and
derivatives of `irradiance` and `specular`."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxshadow as js
from jaxshadow import ShadowOptions, traced

RNG = np.random.default_rng(3)
POINTS = jnp.asarray(np.c_[RNG.uniform(-1, 1, (24, 2)), np.zeros(24)])
NORMALS = jnp.asarray(np.tile([0.0, 0.0, 1.0], (24, 1)))
EYES = jnp.asarray(np.tile([0.3, -2.0, 2.0], (24, 1)))
OCCLUDERS = [np.array([[-0.3, -0.3, 0.8], [0.3, -0.3, 0.8], [0.3, 0.3, 0.8], [-0.3, 0.3, 0.8]]),
             np.array([[0.1, 0.2, 0.5], [0.6, 0.2, 0.5], [0.4, 0.7, 0.6]])]
LIGHTS = {
    "polygon": js.PolygonLight([[-0.5, 0.5, 2], [0.5, 0.5, 2], [0.5, -0.5, 2], [-0.5, -0.5, 2]], radiance=[1.0, 2.0, 3.0]),
    "segment": js.LinearLight([-0.4, 0.1, 1.5], [0.5, -0.2, 1.7], power=[2.0, 1.0, 1.0]),
    "point": js.PointLight([0.2, 0.1, 1.9], [3.0, 3.0, 1.0]),
}


@pytest.mark.parametrize("kind", sorted(LIGHTS))
def test_values_are_those_of_the_public_functions(kind):
    jax.config.update("jax_enable_x64", True)
    scene = js.Scene([LIGHTS[kind]], occluders=OCCLUDERS)
    e, s, over = jax.jit(lambda x: traced.irradiance_and_specular(scene, POINTS, NORMALS, EYES, x, capacity=32))(
        jnp.asarray(20.0))
    e_ref, s_ref = js.irradiance(scene, POINTS, NORMALS), js.specular(scene, POINTS, NORMALS, EYES, 20.0)
    assert not bool(over)
    np.testing.assert_allclose(np.asarray(e), np.asarray(e_ref), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.asarray(s), np.asarray(s_ref), rtol=1e-12, atol=1e-14)
    # some receivers shadowed, some lit: both integrals are exercised
    assert np.ptp(np.asarray(e_ref)[:, 0]) > 0.1 * np.max(np.asarray(e_ref)) and np.max(np.asarray(s_ref)) > 0


def test_derivatives_are_those_of_the_two_calls():
    jax.config.update("jax_enable_x64", True)
    verts0 = np.asarray(LIGHTS["polygon"].vertices)

    def loss(verts, x, both):
        scene = js.Scene([js.PolygonLight(verts, radiance=1.0)], occluders=OCCLUDERS)
        if both:
            e, s, _ = traced.irradiance_and_specular(scene, POINTS, NORMALS, EYES, x, capacity=32)
        else:
            e, _ = traced.irradiance(scene, POINTS, NORMALS, capacity=32)
            s, _ = traced.specular(scene, POINTS, NORMALS, EYES, x, capacity=32)
        return jnp.sum(e * e) + jnp.sum(jnp.sin(3 * s))

    g1 = jax.jit(jax.grad(lambda v, x: loss(v, x, True), argnums=(0, 1)))(verts0, jnp.asarray(20.0))
    g2 = jax.jit(jax.grad(lambda v, x: loss(v, x, False), argnums=(0, 1)))(verts0, jnp.asarray(20.0))
    for a, b in zip(g1, g2, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-14)
    assert np.all(np.isfinite(np.asarray(g1[0]))) and abs(float(g1[1])) > 0


def test_without_the_engine_or_occluders():
    jax.config.update("jax_enable_x64", True)
    light = LIGHTS["polygon"]
    for scene, opts in ((js.Scene([light], occluders=OCCLUDERS), ShadowOptions(engine="device")),
                        (js.Scene([light]), None)):
        # Under jit, as the module is meant to run: called eagerly, the device kernels (traced
        # into the caller's program) dispatch op by op, one small compilation per operation
        # (1 267 compilations in this test, against 17 under jit).
        e, s, over = jax.jit(lambda x, sc=scene, o=opts: traced.irradiance_and_specular(
            sc, POINTS, NORMALS, EYES, x, shadows=o))(jnp.asarray(20.0))
        np.testing.assert_allclose(np.asarray(e), np.asarray(js.irradiance(scene, POINTS, NORMALS)), rtol=1e-12,
                                   atol=1e-14)
        np.testing.assert_allclose(np.asarray(s), np.asarray(js.specular(scene, POINTS, NORMALS, EYES, 20.0)),
                                   rtol=1e-12, atol=1e-14)
        assert not bool(over)
