"""The numerical helpers every kernel relies on: polynomial atan2 and theta / sin(theta)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxshadow._core.misc import angle_over_sin, arctan2, fusible


@pytest.mark.parametrize("dt,tol", [(np.float32, 3e-7), (np.float64, 5e-16)])
def test_arctan2_matches_numpy(dt, tol):
    rng = np.random.default_rng(0)
    y = rng.normal(size=20000) * np.exp(rng.uniform(-10, 10, 20000))
    x = rng.normal(size=20000) * np.exp(rng.uniform(-10, 10, 20000))
    y[:50], x[25:75] = 0.0, 0.0
    got = np.asarray(arctan2(jnp.asarray(y, dt), jnp.asarray(x, dt)))
    np.testing.assert_allclose(got, np.arctan2(y, x), rtol=0, atol=tol * np.pi)


def test_arctan2_jvp_is_exact():
    g = jax.grad(arctan2, argnums=(0, 1))(0.3, -0.7)
    np.testing.assert_allclose(g, (-0.7 / 0.58, -0.3 / 0.58), rtol=1e-14)
    assert all(float(x) == 0.0 for x in jax.grad(arctan2, argnums=(0, 1))(0.0, 0.0))


@pytest.mark.parametrize("s2,c", [(0.5, 0.5 ** 0.5), (1.0, 1.0), (1.0, -1.0), (1e-4, 1.0), (0.3, -0.5), (2.0, 0.1)])
def test_angle_over_sin_value_and_gradient(s2, c):
    # Includes exact 45-degree ties (s = |c|), where a min/max octant reduction would split
    # the derivative and get it wrong.
    f = lambda s2, c: np.arctan2(np.sqrt(s2), c) / np.sqrt(s2)  # noqa: E731
    np.testing.assert_allclose(float(angle_over_sin(s2, c)), f(s2, c), rtol=1e-14)
    g = jax.grad(angle_over_sin, argnums=(0, 1))(s2, c)
    h = 1e-6 * max(abs(s2), 1e-12)
    fd_s2 = (f(s2 + h, c) - f(s2 - h, c)) / (2 * h)
    hc = 1e-6 * max(abs(c), 1e-3)
    fd_c = (f(s2, c + hc) - f(s2, c - hc)) / (2 * hc)
    np.testing.assert_allclose(float(g[0]), fd_s2, rtol=1e-6)
    np.testing.assert_allclose(float(g[1]), fd_c, rtol=1e-6)


def test_angle_over_sin_singular_case_is_zero():
    assert float(angle_over_sin(0.0, -1.0)) == 0.0
    g = jax.grad(angle_over_sin, argnums=(0, 1))(0.0, -1.0)
    assert all(np.isfinite(np.asarray(x)) for x in g)


def test_map_chunks_blocks_and_joins_pytrees():
    """Several blocks (the last padded): array leaves joined in order, scalar leaves stacked
    per block; the padding never leaks into the result."""
    from jaxshadow._core.misc import map_chunks

    x = jnp.arange(2 * 10 + 7, dtype=jnp.float32)[:, None] * jnp.ones((1, 3), jnp.float32)
    calls = []

    def fn(a, b, c):
        calls.append(a.shape[0])
        return a[:, 0] * c + b[:, 1], jnp.max(a)

    out, flags = map_chunks(fn, (x, 2 * x), 10.0, chunk=10)
    assert calls == [10, 10, 10]  # one shape: one compilation
    np.testing.assert_array_equal(np.asarray(out), np.arange(27) * 12.0)
    np.testing.assert_array_equal(np.asarray(flags), [9.0, 19.0, 26.0])
    # Up to two blocks: one call on the inputs themselves.
    out2, _ = map_chunks(fn, (x[:20], x[:20]), 1.0, chunk=10)
    assert calls[-1] == 20 and out2.shape == (20,)


def test_blocked_public_path_finds_a_bad_row_in_a_late_block():
    """The input check is fused into each block's compiled call; the error still names the row."""
    import jaxshadow as js
    from jaxshadow._core.misc import CHUNK

    n = 2 * CHUNK + 3
    p = np.zeros((n, 3), np.float32)
    nrm = np.tile(np.float32([0, 0, 1]), (n, 1))
    quad = np.float32([[-1, -1, 1], [-1, 1, 1], [1, 1, 1], [1, -1, 1]])  # emits down (-z)
    f = np.asarray(js.form_factor(p, nrm, quad))
    assert f.shape == (n,) and np.all(f == f[0]) and 0 < f[0] < 1
    p[n - 2, 1] = np.nan
    with pytest.raises(ValueError, match=rf"form_factor: points\[{n - 2}\] is not finite"):
        js.form_factor(p, nrm, quad)
    p[n - 2, 1] = 0.0
    nrm[CHUNK + 1] = 0.0
    with pytest.raises(ValueError, match=rf"irradiance: normals\[{CHUNK + 1}\] is the zero vector"):
        js.irradiance(js.Scene(lights=[js.PolygonLight(quad, 1.0)]), p, nrm)


@pytest.mark.parametrize("dt, bits", [(np.float32, np.uint32), (np.float64, np.uint64)])
def test_fusible_is_the_identity_to_the_bit(dt, bits):
    """`fusible` only changes XLA's scheduling: every value (denormals, signed zeros,
    infinities, NaN, the extremes) and every tangent comes back bit for bit, under jit."""
    fi = np.finfo(dt)
    special = [0.0, -0.0, fi.smallest_subnormal, -fi.smallest_subnormal, fi.smallest_normal / 3,
               fi.smallest_normal, fi.max, -fi.max, np.inf, -np.inf, np.nan, 1.0 / 3.0, -2.5]
    rng = np.random.default_rng(1)
    span = float(np.log10(fi.max)) + 8  # normal, subnormal and underflowing magnitudes
    rand = rng.standard_normal(4096) * 10.0 ** rng.uniform(-span, np.log10(fi.max) - 1, 4096)
    x = np.concatenate([np.asarray(special, dt), rand.astype(dt)])
    f = jax.jit(fusible)
    y = np.asarray(f(jnp.asarray(x)))
    _, t = jax.jvp(f, (jnp.asarray(x),), (jnp.asarray(x[::-1].copy()),))
    assert y.dtype == dt
    np.testing.assert_array_equal(y.view(bits), x.view(bits))
    np.testing.assert_array_equal(np.asarray(t).view(bits), x[::-1].view(bits))
