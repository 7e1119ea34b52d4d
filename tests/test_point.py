"""Point and directional lights (`jaxshadow._kernels.point`): closed forms, gradients."""

import jax
import jax.numpy as jnp
import numpy as np
from jax.test_util import check_grads

import jaxshadow as js
from jaxshadow._kernels.point import directional_irradiance_kernel, point_irradiance_kernel


def test_point_and_directional_closed_forms():
    p, n = jnp.zeros(3), jnp.array([0.0, 0.0, 1.0])
    x = jnp.array([1.0, 2.0, 2.0])
    np.testing.assert_allclose(float(point_irradiance_kernel(p, n, x)), 2.0 / 27.0, rtol=1e-14)
    assert float(point_irradiance_kernel(p, n, -x)) == 0.0
    d = jnp.array([0.0, -1.0, -1.0])
    np.testing.assert_allclose(float(directional_irradiance_kernel(n, d)), 1 / np.sqrt(2), rtol=1e-14)
    assert float(directional_irradiance_kernel(n, -d)) == 0.0
    scene = js.Scene([js.PointLight(x, [1.0, 2.0, 3.0]), js.DirectionalLight(d, 2.0)])
    e = js.irradiance(scene, p[None], n[None])[0]
    np.testing.assert_allclose(np.asarray(e), 2 / 27 * np.array([1, 2, 3]) + 2 / np.sqrt(2), rtol=1e-13)


def test_point_light_gradients_at_horizon_finite():
    f = jax.grad(point_irradiance_kernel, argnums=(0, 1, 2))
    for g in f(jnp.zeros(3), jnp.array([0.0, 0, 1]), jnp.array([1.0, 0, 0])):
        assert np.all(np.isfinite(np.asarray(g)))
    check_grads(
        jax.jit(point_irradiance_kernel),
        (jnp.array([0.1, 0.2, 0.0]), jnp.array([0.0, 0.6, 0.8]), jnp.array([1.0, 2.0, 2.0])),
        order=2,
        modes=("fwd", "rev"),
    )
