"""The test run's XLA:CPU code-generator options (`tests/conftest.py`: the legacy elemental emitter
instead of the MLIR fusion emitters, LLVM without its most expensive passes) against XLA's
defaults, which users run with: the polygon and segment light kernels, unoccluded and shadowed
(the device kernels), values and gradients, jit + vmap, float32 and float64, give the same
values to rounding when compiled either way, and finite ones."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxshadow._kernels.clip import visible_form_factor_kernel, visible_linear_kernel
from jaxshadow._kernels.linear import linear_irradiance_kernel
from jaxshadow._kernels.polygon import form_factor_kernel

# XLA's own defaults for the options that tests/conftest.py sets in XLA_FLAGS: passed as a
# compile's options, they take precedence over XLA_FLAGS.
XLA_DEFAULTS = {"xla_cpu_use_fusion_emitters": True, "xla_llvm_disable_expensive_passes": False}

LIGHT = np.array([[-0.3, -0.3, 2.0], [-0.3, 0.3, 2.0], [0.3, 0.3, 2.0], [0.3, -0.3, 2.0]])
SEGMENT = (np.array([-0.5, 0.1, 1.8]), np.array([0.6, -0.2, 1.9]))


def _receivers(dtype):
    rng = np.random.default_rng(4)
    occ = rng.uniform(-0.4, 0.4, (1, 3, 3)) + np.array([0.0, 0.0, 1.0])  # one triangle
    p = np.c_[rng.uniform(-0.6, 0.6, (6, 2)), np.zeros(6)]
    n = np.tile([0.1, -0.2, 1.0], (6, 1))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return tuple(jnp.asarray(x, dtype) for x in (p, n, occ))


# The device kernels take ~20 s (float32 and float64 together) to compile twice: slow. The
# unoccluded cases cover the same comparison in the default run.
@pytest.mark.parametrize("kind", ["polygon", "segment",
                                  pytest.param("polygon-shadowed", marks=pytest.mark.slow),
                                  pytest.param("segment-shadowed", marks=pytest.mark.slow)])
def test_run_options_give_the_default_options_values(kind, dtype):
    p, n, occ = _receivers(dtype)
    verts = jnp.asarray(LIGHT, dtype)
    a, b = (jnp.asarray(x, dtype) for x in SEGMENT)
    value = {"polygon": lambda q, m: form_factor_kernel(q, m, verts),
             "segment": lambda q, m: linear_irradiance_kernel(q, m, a, b, 3),
             "polygon-shadowed": lambda q, m: visible_form_factor_kernel(q, m, verts, occ),
             "segment-shadowed": lambda q, m: visible_linear_kernel(q, m, a, b, 3, occ)}[kind]
    f = jax.vmap(jax.value_and_grad(value, argnums=(0, 1)))
    run = jax.tree_util.tree_leaves(jax.jit(f)(p, n))
    default = jax.tree_util.tree_leaves(jax.jit(f).lower(p, n).compile(XLA_DEFAULTS)(p, n))
    if kind.endswith("shadowed"):  # some receivers in penumbra: the occluder's edges are in the values
        free = {"polygon-shadowed": lambda q, m: form_factor_kernel(q, m, verts),
                "segment-shadowed": lambda q, m: linear_irradiance_kernel(q, m, a, b, 3)}[kind]
        e, e_free = np.asarray(run[0], np.float64), np.asarray(jax.vmap(free)(p, n), np.float64)
        assert np.any((e > 1e-3 * e_free) & (e < (1 - 1e-3) * e_free))
    tol = 1e-12 if dtype == np.float64 else 2e-6
    for got, want in zip(run, default, strict=True):
        got, want = np.asarray(got), np.asarray(want)
        assert got.dtype == want.dtype == dtype and np.all(np.isfinite(got)) and np.all(np.isfinite(want))
        assert np.abs(want).max() > 0
        np.testing.assert_allclose(got, want, rtol=0, atol=tol * np.abs(want).max())
