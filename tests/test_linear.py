"""Linear (segment) lights (`jaxshadow._kernels.linear`): closed forms, quadrature, gradients."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.integrate import quad

import jaxshadow as js
from jaxshadow._kernels.linear import linear_irradiance_kernel

# --------------------------------------------------------------------------------------
# Closed forms
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("L,h", [(1.0, 1.0), (5.0, 0.3), (0.2, 2.0)])
def test_element_below_the_end_of_a_parallel_segment(L, h):
    # Element at the origin, normal +z, isotropic segment from (0,0,h) to (0,L,h):
    # E/Phi = 1/(4 pi) int_0^L h / (h^2 + y^2)^{3/2} dy = L / (4 pi h sqrt(h^2 + L^2))
    # (e.g. Modest, Radiative Heat Transfer, line source; elementary integral).
    ref = L / (4 * np.pi * h * np.sqrt(h * h + L * L))
    got = js.linear_irradiance(np.zeros((1, 3)), np.array([[0.0, 0, 1]]), np.array([0, 0, h]), np.array([0, L, h]))
    np.testing.assert_allclose(float(got[0]), ref, rtol=1e-12)


@pytest.mark.parametrize("L,h", [(1.0, 1.0), (4.0, 0.5)])
def test_cosine_tube_closed_form(L, h):
    # m = 1: I = Phi cos(beta) / pi^2, cos(beta) = h / r:
    # E/Phi = 1/pi^2 int_0^L h^2 / r^4 dy = 1/(2 pi^2) [L/(h^2+L^2) + atan(L/h)/h] * ... exactly:
    # int_0^L h^2/(h^2+y^2)^2 dy = (1/2) [L/(h^2+L^2) + atan(L/h)/h]
    ref = 0.5 * (L / (h * h + L * L) + np.arctan(L / h) / h) / np.pi**2
    got = js.linear_irradiance(
        np.zeros((1, 3)), np.array([[0.0, 0, 1]]), np.array([0, 0, h]), np.array([0, L, h]), 1
    )
    np.testing.assert_allclose(float(got[0]), ref, rtol=1e-12)


@pytest.mark.parametrize("b,L", [(1.0, 2.0), (0.25, 10.0)])
def test_receiver_on_the_supporting_line(b, L):
    # Poulin §3.2.1.2 special case: (N.L) L / (b (L + b)) (times 1/(4 pi) for the isotropic
    # per-length intensity), b the distance to the closest end point.
    n = np.array([0.3, 0.2, 1.0])
    n /= np.linalg.norm(n)
    p = np.zeros(3)
    a, e = np.array([0, 0, b]), np.array([0, 0, b + L])
    ref = n[2] * L / (b * (L + b)) / (4 * np.pi)
    got = float(js.linear_irradiance(p[None], n[None], a, e)[0])
    np.testing.assert_allclose(got, ref, rtol=1e-12)
    # cosine profiles emit nothing along the axis
    assert float(js.linear_irradiance(p[None], n[None], a, e, 2)[0]) == 0.0


def test_receiver_on_the_segment_is_infinite_with_zero_gradient():
    a, b = jnp.array([-1.0, 0, 0]), jnp.array([1.0, 0, 0])
    p, n = jnp.zeros(3), jnp.array([0.0, 0, 1])
    assert float(linear_irradiance_kernel(p, n, a, b, 0)) == np.inf
    g = jax.grad(linear_irradiance_kernel, argnums=(0, 1, 2, 3))(p, n, a, b, 0)
    for x in g:
        assert np.all(np.isfinite(np.asarray(x)))


# --------------------------------------------------------------------------------------
# Independent reference: adaptive quadrature along the segment of I(beta) cos(theta) / r^2
# --------------------------------------------------------------------------------------


def reference_linear(p, n, a, b, m):
    length = np.linalg.norm(b - a)
    u = (b - a) / length
    k = m + 1
    w_k = math.sqrt(math.pi) * math.gamma((k + 1) / 2) / math.gamma(k / 2 + 1)
    c = 1.0 / (2 * math.pi * w_k)

    def f(s):
        x = a + s * (b - a)
        w = x - p
        r = np.linalg.norm(w)
        cos_beta = np.sqrt(max(0.0, 1.0 - (w @ u / r) ** 2))
        return c * cos_beta**m * max(0.0, w @ n) / r**3 * length

    # split at the horizon crossing so the kink is a breakpoint
    d0, d1 = (a - p) @ n, (b - p) @ n
    pts = [d0 / (d0 - d1)] if (d0 > 0) != (d1 > 0) else None
    return quad(f, 0, 1, points=pts, epsabs=0, epsrel=1e-13, limit=400)[0]


def random_segment_cases(seed, count):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        a, b = rng.normal(size=3), rng.normal(size=3)
        p = rng.normal(size=3) * 0.5 + np.array([0, 0, -1.5])
        n = rng.normal(size=3)
        if i % 2 == 0:
            # tilt so the tangent plane cuts the segment
            mid = 0.5 * (a + b)
            n = np.cross(mid - p, rng.normal(size=3)) + 0.1 * rng.normal(size=3)
        n /= np.linalg.norm(n)
        out.append((p, n, a, b))
    return out


SEG_CASES = random_segment_cases(3, 12)


@pytest.mark.parametrize("m", [0, 1, 2, 3, 6])
def test_against_independent_quadrature_float64(m):
    for p, n, a, b in SEG_CASES:
        ref = reference_linear(p, n, a, b, m)
        got = float(linear_irradiance_kernel(jnp.asarray(p), jnp.asarray(n), jnp.asarray(a), jnp.asarray(b), m))
        np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-15)


def test_random_segments_cross_the_horizon():
    cut = sum(bool(((a - p) @ n) * ((b - p) @ n) < 0) for p, n, a, b in SEG_CASES)
    assert cut >= 3


@pytest.mark.parametrize("m", [0, 1])
def test_float32_within_1e5_of_unoccluded_value(m):
    for p, n, a, b in SEG_CASES:
        ref = reference_linear(p, n, a, b, m)
        got = float(linear_irradiance_kernel(*(jnp.asarray(x, jnp.float32) for x in (p, n, a, b)), m))
        assert abs(got - ref) <= 1e-5 * max(abs(ref), 1e-3)


@pytest.mark.parametrize("m", [0, 1, 3, 4])
def test_check_grads_generic(m):
    p, n, a, b = SEG_CASES[1]
    f = jax.jit(lambda p, n, a, b: linear_irradiance_kernel(p, n, a, b, m))
    check_grads(f, tuple(jnp.asarray(x) for x in (p, n, a, b)), order=2, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("m", [0, 1, 2, 4, 6])
def test_float32_scale_free_values_and_gradients(m):
    # E/Phi scales as 1/s and its gradient w.r.t. p as 1/s^2: with the m >= 1 terms written in
    # d/r and t/r (one overall 1/d), float32 neither overflows (r**-(m+1) ~ 1e30 at s = 1e-6)
    # nor loses accuracy, for a foot inside and outside the segment (jit + vmap, vs float64).
    p = np.array([[0.0, 0.0, 0.0], [0.1, -0.2, 0.0]])
    n = np.array([[0.1, 0.0, 1.0], [-0.3, 0.2, 1.0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    a = np.array([[-1.0, 0.3, 1.0], [0.5, 0.3, 1.0]])
    b = np.array([[1.0, 0.5, 1.2], [1.5, 0.5, 1.6]])  # foot of p inside / outside
    f = jax.jit(jax.vmap(jax.value_and_grad(lambda *x: linear_irradiance_kernel(*x, m), argnums=(0, 1))))
    for s in (1e-6, 1.0, 1e6):
        ref_v, (ref_gp, ref_gn) = f(*(jnp.asarray(x * k, jnp.float64) for x, k in ((p, s), (n, 1), (a, s), (b, s))))
        v, (gp, gn) = f(*(jnp.asarray(x * k, jnp.float32) for x, k in ((p, s), (n, 1), (a, s), (b, s))))
        for got, ref in ((v, ref_v), (gp, ref_gp), (gn, ref_gn)):
            got, ref = np.asarray(got, np.float64), np.asarray(ref)
            assert np.all(np.isfinite(got))
            np.testing.assert_allclose(got, ref, rtol=0, atol=2e-5 * np.max(np.abs(ref)))
        np.testing.assert_allclose(np.asarray(ref_v) * s, np.asarray(f(*(jnp.asarray(x) for x in (p, n, a, b)))[0]), rtol=1e-13)


@functools.cache
def _value_and_grad(m):
    return jax.jit(jax.value_and_grad(lambda *x: linear_irradiance_kernel(*x, m), argnums=(0, 1, 2, 3)))


@pytest.mark.parametrize(
    "p,n",
    [
        ([0.0, 0.0, 0.0], [0.0, 0.0, 1.0]),  # on the supporting line
        ([0.0, 1e-9, 0.0], [0.0, 0.0, 1.0]),  # 1e-9 from it
        ([0.0, 1.0, 0.0], [0.0, 0.0, 1.0]),  # segment endpoint exactly on the horizon
        ([0.0, 1.0, 2.0], [0.0, 0.0, 1.0]),  # segment entirely in the tangent plane
        ([0.0, 1.0, 2.0], [0.0, 1.0, 0.0]),  # horizon crossing at the foot of the perpendicular
    ],
)
@pytest.mark.parametrize("m", [0, 1, 2])
def test_gradients_finite_at_singular_configurations(p, n, m):
    a, b = jnp.array([0.0, 0.0, 1.0]), jnp.array([0.0, 0.0, 3.0])
    f = _value_and_grad(m)
    for dt in (jnp.float32, jnp.float64):
        val, grads = f(*(jnp.asarray(x, dt) for x in (p, n, a, b)))
        assert np.isfinite(float(val))
        for g in grads:
            assert np.all(np.isfinite(np.asarray(g)))


def test_cosine_profile_emits_the_same_power():
    # Total power per unit length: integral of I(beta) over the sphere = Phi for every m.
    for m in (0, 1, 4):
        from jaxshadow._kernels.linear import cosine_profile_constant

        c = cosine_profile_constant(m)
        total = 2 * np.pi * quad(lambda beta, c=c, m=m: c * np.cos(beta) ** (m + 1), -np.pi / 2, np.pi / 2)[0]
        np.testing.assert_allclose(total, 1.0, rtol=1e-12)


def test_scene_sums_linear_lights_of_both_profiles():
    p, n = np.zeros((1, 3)), np.array([[0.0, 0, 1]])
    a, b = np.array([0.0, 0, 1]), np.array([0.0, 2, 1])
    scene = js.Scene(
        [js.LinearLight(a, b, [1.0, 0.5, 0.0]), js.LinearLight(a, b, 2.0, profile="cosine", exponent=1)]
    )
    e = np.asarray(js.irradiance(scene, p, n)[0])
    e0 = float(js.linear_irradiance(p, n, a, b, 0)[0])
    e1 = float(js.linear_irradiance(p, n, a, b, 1)[0])
    np.testing.assert_allclose(e, np.array([1.0, 0.5, 0.0]) * e0 + 2 * e1, rtol=1e-13)
