"""Point-to-polygon form factor: closed forms, an independent quadrature reference, gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.integrate import dblquad

import jaxshadow as js
from benchmarks.scenes import clip_halfspace, random_convex
from jaxshadow._kernels.polygon import form_factor_kernel


def rect(x0, x1, y0, y1, z, facing_down=True):
    """Axis-aligned rectangle at height z, counter-clockwise seen from below (emits down)."""
    v = np.array([[x0, y0, z], [x0, y1, z], [x1, y1, z], [x1, y0, z]], dtype=np.float64)
    return v if facing_down else v[::-1].copy()


# --------------------------------------------------------------------------------------
# Closed forms from the literature (Howell, "A Catalog of Radiation Heat Transfer
# Configuration Factors", 3rd ed., cases B-3 and B-4).
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("a,b,c", [(1.0, 1.0, 1.0), (2.0, 0.5, 0.7), (0.1, 3.0, 2.5)])
def test_howell_b3_parallel_rectangle_through_corner(a, b, c):
    # B-3: element parallel to an a x b rectangle at distance c, normal through a corner.
    A, B = a / c, b / c
    ref = (
        A / np.sqrt(1 + A * A) * np.arctan(B / np.sqrt(1 + A * A))
        + B / np.sqrt(1 + B * B) * np.arctan(A / np.sqrt(1 + B * B))
    ) / (2 * np.pi)
    f = js.form_factor(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), rect(0, a, 0, b, c))
    assert f.dtype == jnp.float64
    np.testing.assert_allclose(float(f[0]), ref, rtol=1e-12, atol=0)


@pytest.mark.parametrize("a,b,c", [(1.0, 1.0, 1.0), (2.0, 0.5, 0.7), (0.3, 4.0, 1.5)])
def test_howell_b4_perpendicular_rectangle(a, b, c):
    # B-4: element with normal +z at the origin; rectangle in the plane x = c, spanning
    # y in [0, a], z in [0, b], emitting toward -x. F = 1/(2 pi) [atan(a/c) - c/sqrt(c^2+b^2)
    # atan(a/sqrt(c^2+b^2))].
    s = np.sqrt(c * c + b * b)
    ref = (np.arctan(a / c) - c / s * np.arctan(a / s)) / (2 * np.pi)
    v = np.array([[c, 0, 0], [c, a, 0], [c, a, b], [c, 0, b]], dtype=np.float64)
    # counter-clockwise seen from -x: right-hand normal must point to -x.
    if np.cross(v[1] - v[0], v[2] - v[1])[0] > 0:
        v = v[::-1].copy()
    f = js.form_factor(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), v)
    np.testing.assert_allclose(float(f[0]), ref, rtol=1e-12, atol=0)


def test_perpendicular_rectangle_crossing_the_horizon_is_clipped():
    # The same rectangle extended below the receiver's tangent plane (z in [-b, b]):
    # exact horizon clipping keeps only z >= 0, so the value equals case B-4.
    a, b, c = 1.3, 0.9, 1.1
    s = np.sqrt(c * c + b * b)
    ref = (np.arctan(a / c) - c / s * np.arctan(a / s)) / (2 * np.pi)
    v = np.array([[c, 0, -b], [c, 0, b], [c, a, b], [c, a, -b]], dtype=np.float64)
    if np.cross(v[1] - v[0], v[2] - v[1])[0] > 0:
        v = v[::-1].copy()
    f = js.form_factor(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), v)
    np.testing.assert_allclose(float(f[0]), ref, rtol=1e-12, atol=0)


def test_behind_and_in_plane_receivers_get_zero():
    v = rect(-1, 1, -1, 1, 1.0)  # emits downward
    pts = np.array([[0.0, 0.0, 2.0], [3.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    nrm = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(np.asarray(js.form_factor(pts, nrm, v)), 0.0)


def test_large_emitter_close_by_approaches_one():
    f = js.form_factor(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), rect(-1e4, 1e4, -1e4, 1e4, 1e-3))
    np.testing.assert_allclose(float(f[0]), 1.0, atol=1e-6)


# --------------------------------------------------------------------------------------
# Independent float64 reference: exact NumPy clip to the horizon, fan triangulation and
# adaptive quadrature (scipy dblquad) of cos cos / (pi r^2) on each triangle.
# --------------------------------------------------------------------------------------


def reference_form_factor(p, n, verts):
    ne = np.cross(verts[1] - verts[0], verts[2] - verts[0])
    ne /= np.linalg.norm(ne)
    if np.dot(ne, p - verts[0]) <= 0:
        return 0.0
    poly = np.array(clip_halfspace(verts, p, n))
    if len(poly) < 3:
        return 0.0
    total = 0.0
    for i in range(1, len(poly) - 1):
        a, b, c = poly[0], poly[i], poly[i + 1]
        area2 = np.linalg.norm(np.cross(b - a, c - a))

        def integrand(v, u, a=a, b=b, c=c, area2=area2):
            x = a + u * (b - a) + u * v * (c - b)  # Duffy map of the unit square
            w = x - p
            r2 = w @ w
            return (w @ n) * (-(w @ ne)) / (np.pi * r2 * r2) * u * area2

        val, _ = dblquad(integrand, 0, 1, 0, 1, epsabs=1e-15, epsrel=1e-13)
        total += val
    return total


def random_configurations(seed, count):
    rng = np.random.default_rng(seed)
    cases = []
    while len(cases) < count:
        centre = rng.normal(size=3)
        verts = random_convex(rng, int(rng.integers(3, 7)), rng.uniform(0.5, 1.5, 2), centre)
        ne = np.cross(verts[1] - verts[0], verts[2] - verts[0])
        ne /= np.linalg.norm(ne)
        p = centre + ne * rng.uniform(0.2, 2.0) + rng.normal(size=3) * 0.8
        # half the receivers tilted so that their tangent plane cuts the emitter
        if len(cases) % 2 == 0:
            n = -ne + rng.normal(size=3) * 0.3
        else:
            t = rng.normal(size=3)
            t -= (t @ (centre - p)) * (centre - p) / np.dot(centre - p, centre - p)
            n = t + rng.normal(size=3) * 0.2
        n /= np.linalg.norm(n)
        cases.append((p, n, verts))
    return cases


CASES = random_configurations(0, 16)


@pytest.mark.parametrize("i", range(len(CASES)))
def test_against_independent_quadrature_float64(i):
    p, n, verts = CASES[i]
    ref = reference_form_factor(p, n, verts)
    got = float(js.form_factor(p[None], n[None], verts)[0])
    assert got >= 0
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-14)


def test_random_cases_really_cross_the_horizon():
    crossing = 0
    for p, n, verts in CASES:
        d = (verts - p) @ n
        crossing += bool(np.any(d > 0) and np.any(d < 0))
    assert crossing >= 4


def test_against_independent_quadrature_float32():
    for p, n, verts in CASES[:8]:
        ref = reference_form_factor(p, n, verts)
        unocc = reference_form_factor(p, -np.cross(verts[1] - verts[0], verts[2] - verts[0]) / np.linalg.norm(np.cross(verts[1] - verts[0], verts[2] - verts[0])), verts)
        got = js.form_factor(p[None].astype(np.float32), n[None].astype(np.float32), verts.astype(np.float32))
        assert got.dtype == jnp.float32
        scale = max(ref, unocc, 1e-3)
        assert abs(float(got[0]) - ref) <= 1e-5 * scale


# --------------------------------------------------------------------------------------
# Gradients
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("i", [0, 1])
def test_check_grads_generic(i):
    # Vertices through the kernel: check_grads perturbs them off their plane, which the
    # scene's build-time validation (rightly) rejects.
    p, n, verts = CASES[i]
    args = tuple(jnp.asarray(x) for x in (p, n, verts))
    check_grads(jax.jit(form_factor_kernel), args, order=2, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)


def test_check_grads_through_the_scene():
    # The scene path adds only linear maps (radiance, a rigid shift) on top of the kernel
    # checked to second order above.
    p, n, verts = CASES[1]

    def f(p, n, rad, shift):
        scene = js.Scene([js.PolygonLight(jnp.asarray(verts) + shift[None, :], rad)])
        return js.irradiance(scene, p[None], n[None])[0]

    args = tuple(jnp.asarray(x) for x in (p, n, [1.0, 2.0, 0.5], [0.01, -0.02, 0.03]))
    check_grads(jax.jit(f), args, order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)


SQUARE = rect(-1.0, 1.0, -1.0, 1.0, 1.0)
# Module-level so that every case reuses one compilation per dtype.
_VALUE_AND_GRAD = jax.jit(jax.value_and_grad(form_factor_kernel, argnums=(0, 1, 2)))
_JACFWD = jax.jit(jax.jacfwd(form_factor_kernel, argnums=(0, 1, 2)))


@pytest.mark.parametrize(
    "p,n",
    [
        ([3.0, 0.0, 1.0], [0.0, 0.0, 1.0]),  # point on the light's plane
        ([3.0, -1.0, 0.5], [-1.0, 0.0, 0.2]),  # on the line of an edge? (y=-1 not z=1): generic
        ([3.0, -1.0, 1.0], [-0.3, 0.1, 1.0]),  # on the supporting line of the edge y=-1, z=1
        ([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]),  # emitter cut in half by the horizon
        ([1.0, 0.0, 0.0], [1.0, 0.0, 0.0]),  # emitter edge x=1 exactly on the horizon
        ([0.0, 0.0, 0.0], [1.0, 1.0, 0.0]),  # two vertices exactly on the horizon
        ([2.0, 2.0, 0.0], [-1.0, 0.0, 1.0]),  # vertex (1, 1, 1) exactly on the horizon
        ([0.0, 0.0, 0.0], [0.0, 1.0, 1.0]),  # vertex-free generic tilt
    ],
)
def test_gradients_finite_at_singular_configurations(p, n):
    p = jnp.asarray(p, dtype=jnp.float64)
    n = jnp.asarray(n, dtype=jnp.float64)
    n = n / jnp.linalg.norm(n)
    v = jnp.asarray(SQUARE)
    for dt in (jnp.float32, jnp.float64):
        val, grads = _VALUE_AND_GRAD(
            p.astype(dt), n.astype(dt), v.astype(dt)
        )
        assert np.isfinite(float(val))
        for g in grads:
            assert np.all(np.isfinite(np.asarray(g)))
        # forward mode too
        jac = _JACFWD(p.astype(dt), n.astype(dt), v.astype(dt))
        for g in jac:
            assert np.all(np.isfinite(np.asarray(g)))


def test_value_continuous_across_the_horizon():
    # Rotating the receiver so a vertex sweeps through the tangent plane: no jump.
    p = np.array([2.0, 2.0, 0.0])
    vals = []
    for eps in (-1e-7, 0.0, 1e-7):
        n = np.array([-1.0, 0.0, 1.0 + eps])
        n /= np.linalg.norm(n)
        vals.append(float(js.form_factor(p[None], n[None], SQUARE)[0]))
    assert abs(vals[0] - vals[1]) < 1e-6 and abs(vals[2] - vals[1]) < 1e-6


def test_jit_vmap_and_dtype_follow_inputs(dtype):
    pts = np.random.default_rng(1).normal(size=(7, 3)).astype(dtype) * 0.3
    nrm = np.tile(np.array([0, 0, 1], dtype=dtype), (7, 1))
    f = js.form_factor(pts, nrm, SQUARE.astype(dtype))
    assert f.dtype == dtype and f.shape == (7,)
    g = jax.jit(jax.vmap(form_factor_kernel, in_axes=(0, 0, None)))(pts, nrm, SQUARE.astype(dtype))
    np.testing.assert_allclose(np.asarray(f), np.asarray(g), rtol=1e-6)


@pytest.mark.parametrize("k", [24, 25, 33, 64])
def test_grouped_unrolled_kernel_agrees_with_compact(k):
    """Polygons longer than 1.5 EDGE_GROUP edges are evaluated in groups by a scan (the
    crossing points of the horizon carried between groups); same values as the
    edge-vectorised kernel, with receivers whose tangent plane cuts the polygon."""
    from jaxshadow._kernels.polygon import EDGE_GROUP, _form_factor_compact, _form_factor_unrolled

    assert (k > 1.5 * EDGE_GROUP) == (k != 24)  # one unrolled case, three grouped ones
    ang = -2 * np.pi * np.arange(k) / k  # clockwise seen from above: emits downwards
    verts = np.stack([0.6 * np.cos(ang), 0.6 * np.sin(ang), np.ones(k)], axis=1)
    rng = np.random.default_rng(k)
    p = rng.uniform(-1.5, 1.5, (64, 3)) * [1, 1, 0.4]
    n = rng.normal(size=(64, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    fast = jax.jit(jax.vmap(_form_factor_unrolled, in_axes=(0, 0, None)))(p, n, verts)
    ref = jax.vmap(_form_factor_compact, in_axes=(0, 0, None))(p, n, jnp.asarray(verts))
    assert np.count_nonzero(np.asarray(ref) > 0) > 10
    np.testing.assert_allclose(np.asarray(fast), np.asarray(ref), rtol=1e-12, atol=1e-15)


def test_fast_and_compact_evaluations_agree():
    # Values come from the unrolled kernel, derivatives from the edge-vectorised one.
    from jaxshadow._kernels.polygon import _form_factor_compact, _form_factor_unrolled

    for p, n, verts in CASES:
        args = (jnp.asarray(p), jnp.asarray(n), jnp.asarray(verts))
        np.testing.assert_allclose(float(_form_factor_unrolled(*args)), float(_form_factor_compact(*args)), rtol=1e-13, atol=1e-16)
