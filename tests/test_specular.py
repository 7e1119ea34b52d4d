"""Phong-lobe integrals (jaxshadow._kernels.specular, jaxshadow._kernels.chebyshev).

The exact method is checked against independent float64 quadrature written here (scipy over
the light itself: the segment's length, the clipped polygon's plane), the Chebyshev default
against the exact method, derivatives with `check_grads`, and the singular configurations for
finiteness.
"""

import functools
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy import integrate

from benchmarks.scenes import clip_halfspace, random_convex
from jaxshadow._kernels.chebyshev import cutoff_angle, poulin_cos_power_integral
from jaxshadow._kernels.specular import (
    contour_specular_kernel,
    directional_specular,
    directional_specular_kernel,
    point_specular,
    point_specular_kernel,
    polygon_specular,
    polygon_specular_kernel,
    segment_specular,
    segment_specular_kernel,
)

EXPONENTS = [1.0, 5.0, 20.0, 100.0, 1000.0, 10000.0]
K = 6  # padded vertex count


# --------------------------------------------------------------------------------------
# Independent references (NumPy / SciPy only)
# --------------------------------------------------------------------------------------


def _mirror(p, nrm, eye):
    v = (eye - p) / np.linalg.norm(eye - p)
    nrm = nrm / np.linalg.norm(nrm)
    return nrm, 2 * (nrm @ v) * nrm - v


def reference_polygon(p, nrm, eye, verts, n):
    """S / L by nested adaptive quadrature over the clipped polygon in its own plane."""
    nrm, r = _mirror(p, nrm, eye)
    # The integrand is smooth on the part above the horizon with w . R > 0: clip to both.
    verts = np.array(clip_halfspace(np.asarray(verts, float), p, nrm))
    if len(verts) >= 3:
        verts = np.array(clip_halfspace(verts, p, r))
    if len(verts) < 3:
        return 0.0
    o = verts[0]
    e1 = verts[1] - o
    e1 /= np.linalg.norm(e1)
    nl = np.cross(verts[1] - o, verts[2] - o)
    nl /= np.linalg.norm(nl)
    e2 = np.cross(nl, e1)
    uv = np.stack([(verts - o) @ e1, (verts - o) @ e2], 1)
    # Where the mirror ray meets the light plane: the lobe's peak, a hint for the quadrature.
    t_hit = (nl @ (o - p)) / (nl @ r) if abs(nl @ r) > 1e-12 else -1.0
    peak = (p + t_hit * r - o) @ np.stack([e1, e2], 1) if t_hit > 0 else None

    def f(y, x):
        d = o + x * e1 + y * e2 - p
        r2 = d @ d
        w = d / np.sqrt(r2)
        c = max(0.0, w @ r)
        return (n + 1) / (2 * np.pi) * c**n * abs(nl @ w) / r2

    def y_range(x):
        lo, hi = np.inf, -np.inf
        m = len(uv)
        for i in range(m):
            (xa, ya), (xb, yb) = uv[i], uv[(i + 1) % m]
            if min(xa, xb) <= x <= max(xa, xb) and xa != xb:
                y = ya + (x - xa) / (xb - xa) * (yb - ya)
                lo, hi = min(lo, y), max(hi, y)
        return lo, hi

    def inner(x):
        lo, hi = y_range(x)
        if not hi > lo:
            return 0.0
        pts = [peak[1]] if peak is not None and lo < peak[1] < hi else None
        return integrate.quad(f, lo, hi, args=(x,), points=pts, epsabs=0, epsrel=1e-13, limit=400)[
            0
        ]

    xs = sorted(uv[:, 0])
    pts = list(xs[1:-1]) + ([peak[0]] if peak is not None and xs[0] < peak[0] < xs[-1] else [])
    return integrate.quad(
        inner, xs[0], xs[-1], points=pts or None, epsabs=0, epsrel=1e-12, limit=400
    )[0]


def reference_segment(p, nrm, eye, q0, q1, n, m=None):
    """S / Phi by adaptive quadrature along the segment (zero below the horizon)."""
    nrm, r = _mirror(p, nrm, eye)
    length = np.linalg.norm(q1 - q0)
    t = (q1 - q0) / length
    if m is not None:
        wk = integrate.quad(lambda b: np.cos(b) ** (m + 1), -np.pi / 2, np.pi / 2, epsrel=1e-13)[0]

    def f(s):
        d = q0 + s * t - p
        r2 = d @ d
        w = d / np.sqrt(r2)
        if nrm @ w <= 0:
            return 0.0
        if m is None:
            profile = 1 / (4 * np.pi)
        else:
            cos_beta = np.sqrt(max(0.0, 1 - (w @ t) ** 2))
            profile = cos_beta**m / (2 * np.pi * wk)
        return profile * (n + 1) / (2 * np.pi) * max(0.0, w @ r) ** n / r2

    # Breakpoints: the horizon crossing and the lobe peak (closest approach of R).
    pts = []
    dn = nrm @ (q1 - q0)
    if dn != 0:
        s0 = -(nrm @ (q0 - p)) / dn * length
        if 0 < s0 < length:
            pts.append(s0)
    ss = np.linspace(0, length, 4001)
    pts.append(ss[int(np.argmax([f(s) for s in ss]))])
    pts = [s for s in pts if 0 < s < length]
    return integrate.quad(f, 0, length, points=pts or None, epsabs=0, epsrel=1e-13, limit=500)[0]


# --------------------------------------------------------------------------------------
# Random configurations whose mirror direction hits (or nearly hits) the light
# --------------------------------------------------------------------------------------


def _pad(verts):
    """Pad to K vertices by repeating the first one."""
    return np.concatenate([verts, np.repeat(verts[:1], K - len(verts), 0)])


def _eye_for(p, nrm, target, rng):
    w = (target - p) / np.linalg.norm(target - p)
    v = 2 * (nrm @ w) * nrm - w
    return p + rng.uniform(1.0, 3.0) * v


def random_polygons(seed, count, grow=1.0):
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < count:
        m = int(rng.integers(3, K + 1))
        rad = rng.uniform(0.3, 1.0)
        centre = np.array([0, 0, rng.uniform(1.0, 2.0)]) + 0.3 * rng.normal(size=3)
        verts = random_convex(rng, m, (rad, rad), centre, max_gap=0.9 * np.pi)
        p = 0.2 * rng.normal(size=3)
        nrm = np.array([0.0, 0.0, 1.0]) + 0.3 * rng.normal(size=3)
        nrm /= np.linalg.norm(nrm)
        if np.cross(verts[1] - verts[0], verts[2] - verts[0]) @ (p - verts[0]) < 0:
            verts = verts[::-1]
        c0 = verts.mean(0)
        target = c0 + grow * (rng.dirichlet(np.ones(m)) @ verts - c0)
        if nrm @ (target - p) <= 0.05:
            continue
        padded = np.concatenate([verts, np.repeat(verts[:1], K - m, 0)])
        out.append((p, nrm, _eye_for(p, nrm, target, rng), padded))
    return [np.array(x) for x in zip(*out, strict=True)]


def random_segments(seed, count):
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < count:
        p = 0.2 * rng.normal(size=3)
        nrm = np.array([0.0, 0.0, 1.0]) + 0.3 * rng.normal(size=3)
        nrm /= np.linalg.norm(nrm)
        centre = np.array([0, 0, rng.uniform(0.5, 2.0)]) + 0.5 * rng.normal(size=3)
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        q0, q1 = centre - rng.uniform(0.3, 1.5) * d, centre + rng.uniform(0.3, 1.5) * d
        target = q0 + rng.uniform(0.05, 0.95) * (q1 - q0)
        if nrm @ (target - p) <= 0.05:
            continue
        out.append((p, nrm, _eye_for(p, nrm, target, rng), q0, q1))
    return [np.array(x) for x in zip(*out, strict=True)]


def _seg_iso(p, nrm, eye, q0, q1, n, m, method):
    return segment_specular_kernel(p, nrm, eye, q0, q1, n, method=method)


def _seg_tube(p, nrm, eye, q0, q1, n, m, method):
    return segment_specular_kernel(p, nrm, eye, q0, q1, n, m, method=method)


@functools.cache
def _batched(kind, method):
    """One jitted, vmapped kernel per (light kind, method): compiled once per dtype."""
    if kind == "polygon":
        kern = partial(polygon_specular_kernel, method=method)
        return jax.jit(jax.vmap(kern, in_axes=(0, 0, 0, 0, None)))
    kern = partial(_seg_iso if kind == "isotropic" else _seg_tube, method=method)
    return jax.jit(jax.vmap(kern, in_axes=(0, 0, 0, 0, 0, None, None)))


def _polygon_batch(method, cfg, n):
    args = [jnp.asarray(x) for x in cfg]
    return np.asarray(_batched("polygon", method)(*args, jnp.asarray(n)))


def _segment_batch(method, cfg, n, m=None):
    args = [jnp.asarray(x) for x in cfg]
    kind = "isotropic" if m is None else "tube"
    mm = jnp.asarray(0.0 if m is None else m)
    return np.asarray(_batched(kind, method)(*args, jnp.asarray(n), mm))


# --------------------------------------------------------------------------------------
# Chebyshev building blocks
# --------------------------------------------------------------------------------------


def test_cutoff_angle_solves_cos_power_equal_tol():
    for n in [1.0, 5.0, 1e4, 1e6]:
        for tol in [1 / 250, 1e-6]:
            x = float(cutoff_angle(jnp.asarray(n), tol))
            assert np.isclose(n * np.log(np.cos(x)), np.log(tol), rtol=1e-10)
    g = jax.grad(lambda n: cutoff_angle(n, 1e-6))(jnp.asarray(1e6))
    assert np.isfinite(g) and g < 0
    with pytest.raises(ValueError):
        cutoff_angle(jnp.asarray(2.0), 1.5)


_poulin = jax.jit(poulin_cos_power_integral, static_argnums=(3, 4))


def test_poulin_half_range_fit_integral():
    # Fig. 3.9 (with the printed (-1)^i factor dropped): the fitted integral converges to the
    # exact one as the degree grows; intervals straddling 0 and beyond x_M are handled.
    n = jnp.asarray(20.0)
    f = lambda a, b: integrate.quad(lambda x: np.cos(x) ** 20, a, b, epsabs=0, epsrel=1e-13)[0]
    for lo, hi in [(-0.3, 0.2), (0.1, 0.4), (-1.5, 1.5)]:
        approx = float(_poulin(jnp.asarray(lo), jnp.asarray(hi), n, 24, 1e-12))
        assert np.isclose(approx, f(lo, hi), rtol=1e-9)
    # Poulin's own setting: degree 6 at epsilon = 1/250 is good to about 1e-3.
    approx = float(_poulin(jnp.asarray(-0.3), jnp.asarray(0.2), n, 6, 1 / 250))
    assert abs(approx / f(-0.3, 0.2) - 1) < 2e-3


# --------------------------------------------------------------------------------------
# Exact method against independent quadrature (float64)
# --------------------------------------------------------------------------------------


def test_polygon_exact_matches_quadrature():
    square = np.array([[-1, 1, 2.0], [1, 1, 2], [1, -1, 2], [-1, -1, 2]])
    cases = []
    # Peak inside the light, receiver normal tilted so that the horizon cuts the light; peak
    # just outside an edge (by about 0.015 rad).
    for p, nrm, target in [
        ((0.2, 0.1, 0.0), (0.9, 0.0, 0.436), (0.5, 0.3, 2.0)),
        ((0.3, -0.2, 0.0), (0.0, 0.1, 1.0), (1.03, 0.2, 2.0)),
    ]:
        p, nrm, target = (np.array(x) for x in (p, nrm, target))
        nrm /= np.linalg.norm(nrm)
        cases.append((p, nrm, _eye_for(p, nrm, target, np.random.default_rng(0))))
    verts = _pad(square)  # padded to K = 6
    for p, nrm, eye in cases:
        for n in EXPONENTS[:5]:  # n = 1e4 only costs time here (the segments cover it)
            ref = reference_polygon(p, nrm, eye, square, n)
            got = _polygon_batch("exact", [x[None] for x in (p, nrm, eye, verts)], n)[0]
            assert ref > 1e-6
            assert abs(got - ref) <= 1e-10 * ref, (n, got, ref)


@pytest.mark.parametrize("profile", [None, 3.0])
def test_segment_exact_matches_quadrature(profile):
    cfg = random_segments(3, 3)
    # A segment crossing the receiver's tangent plane.
    cfg = [
        np.concatenate([c, extra[None]]) for c, extra in zip(cfg, _crossing_segment(), strict=True)
    ]
    for n in EXPONENTS:
        got = _segment_batch("exact", cfg, n, profile)
        for i in range(len(cfg[0])):
            ref = reference_segment(*(c[i] for c in cfg), n, profile)
            assert abs(got[i] - ref) <= 1e-10 * ref, (n, i, got[i], ref)


def _crossing_segment():
    p = np.zeros(3)
    nrm = np.array([0.0, 0.0, 1.0])
    q0, q1 = np.array([-1.0, 0.3, -0.4]), np.array([1.2, 0.1, 1.0])
    target = q0 + 0.7 * (q1 - q0)
    w = target / np.linalg.norm(target)
    eye = 2.0 * (2 * (nrm @ w) * nrm - w)
    return p, nrm, eye, q0, q1


# --------------------------------------------------------------------------------------
# Chebyshev default against the exact method
# --------------------------------------------------------------------------------------


def test_polygon_chebyshev_default_within_1e4():
    cfg = random_polygons(11, 48)
    for n in EXPONENTS:
        exact = _polygon_batch("exact", cfg, n)
        cheb = _polygon_batch("chebyshev", cfg, n)
        assert np.all(exact > 0)
        assert np.max(np.abs(cheb - exact) / exact) <= 1e-4, n


def test_polygon_chebyshev_near_miss_floored():
    # R aimed up to 30% outside the light: relative error floored at 1e-3 of the brightest.
    cfg = random_polygons(12, 48, grow=1.3)
    for n in EXPONENTS:
        exact = _polygon_batch("exact", cfg, n)
        cheb = _polygon_batch("chebyshev", cfg, n)
        den = np.maximum(exact, 1e-3 * exact.max())
        assert np.max(np.abs(cheb - exact) / den) <= 1e-4, n


@pytest.mark.parametrize("profile", [None, 3.0])
def test_segment_chebyshev_default_within_1e4(profile):
    cfg = random_segments(13, 48)
    for n in EXPONENTS:
        exact = _segment_batch("exact", cfg, n, profile)
        cheb = _segment_batch("chebyshev", cfg, n, profile)
        assert np.all(exact > 0)
        assert np.max(np.abs(cheb - exact) / exact) <= 1e-4, n


# --------------------------------------------------------------------------------------
# Closed forms, batching, dtypes
# --------------------------------------------------------------------------------------


def test_point_and_directional_closed_forms(dtype):
    pts = np.array([[0.0, 0, 0], [0.5, 0.2, 0]], dtype)
    nrm = np.array([[0, 0, 1.0], [0, 0.6, 0.8]], dtype)
    eye = np.array([1.0, 0.5, 2.0], dtype)
    light = np.array([-0.4, 0.1, 1.5], dtype)
    n = dtype.type(30.0)
    got = point_specular(pts, nrm, eye, light, dtype.type(2.0), n)
    got_d = directional_specular(pts, nrm, eye, np.array([0.3, -0.1, -1.0], dtype), 1.5, n)
    assert got.dtype == dtype and got_d.dtype == dtype
    for i in range(2):
        nn, r = _mirror(pts[i].astype(float), nrm[i].astype(float), eye.astype(float))
        d = light - pts[i]
        w = d / np.linalg.norm(d)
        want = 2.0 * 31 / (2 * np.pi) * max(0, w @ r) ** 30 / (d @ d)
        assert np.isclose(got[i], want, rtol=1e-5 if dtype == np.float32 else 1e-12)
        w = -np.array([0.3, -0.1, -1.0]) / np.linalg.norm([0.3, -0.1, -1.0])
        want = 1.5 * 31 / (2 * np.pi) * max(0, w @ r) ** 30
        assert np.isclose(got_d[i], want, rtol=1e-5 if dtype == np.float32 else 1e-12)
    # Below the horizon: nothing.
    below = point_specular(pts, nrm, eye, np.array([0.0, 0, -1], dtype), 1.0, n)
    assert np.all(np.asarray(below) == 0)


def test_batched_helpers_dtype_follows_inputs(dtype):
    p, nrm, eye, verts = random_polygons(5, 4)
    q = random_segments(5, 4)
    tol = 2e-4 if dtype == np.float32 else 1e-10
    # The same light and eye for every receiver (what the helpers take).
    verts = np.repeat(verts[:1], 4, 0)
    eye = np.repeat(eye[:1], 4, 0)
    q0, q1 = np.repeat(q[3][:1], 4, 0), np.repeat(q[4][:1], 4, 0)
    cast = lambda x: jnp.asarray(x, dtype)
    for n in [5.0, 1000.0]:
        got = polygon_specular(cast(p), cast(nrm), cast(eye[0]), cast(verts[0]), cast(2.0), cast(n))
        assert got.dtype == dtype
        want = 2.0 * _polygon_batch("chebyshev", [p, nrm, eye, verts], n)
        assert np.allclose(got, want, rtol=tol, atol=tol * want.max())
        got = segment_specular(
            cast(q[0]), cast(q[1]), cast(q[2]), cast(q0[0]), cast(q1[0]), cast(3.0), cast(n)
        )
        assert got.dtype == dtype
        want = 3.0 * _segment_batch("chebyshev", [q[0], q[1], q[2], q0, q1], n)
        assert np.allclose(got, want, rtol=tol, atol=tol * want.max())


def test_polygon_covering_the_lobe_gives_one():
    # A huge square far above: the whole lobe is inside, S/L = 1 (clipped at the horizon,
    # which the lobe does not reach for large n).
    big = np.array([[-1e3, 1e3, 1.0], [1e3, 1e3, 1], [1e3, -1e3, 1], [-1e3, -1e3, 1]])
    verts = _pad(big)
    cfg = [x[None] for x in (np.zeros(3), np.array([0, 0, 1.0]), np.array([0.1, 0.2, 1.0]), verts)]
    for method in ["exact", "chebyshev"]:
        assert np.isclose(_polygon_batch(method, cfg, 1000.0)[0], 1.0, rtol=1e-6)


# --------------------------------------------------------------------------------------
# Derivatives
# --------------------------------------------------------------------------------------


def _grad_config():
    # Unpadded (K = 4): padded slots have zero gradient by design (a vertex moved off its copy
    # would open a new edge), which finite differences would not see.
    verts = jnp.array([[-1, 1, 2.0], [1, 1, 2], [1.2, -1, 2.1], [-1, -1, 2]])
    return (
        jnp.array([0.2, 0.1, 0.0]),
        jnp.array([0.1, 0.2, 1.0]),
        jnp.array([0.5, -0.3, 3.0]),
        verts,
    )


def _all_kernels(p, nrm, eye, verts, n, m):
    s_poly = polygon_specular_kernel(p, nrm, eye, verts, n)
    s_iso = segment_specular_kernel(p, nrm, eye, verts[0], verts[2], n)
    s_tube = segment_specular_kernel(p, nrm, eye, verts[1], verts[3], n, m)
    s_pt = point_specular_kernel(p, nrm, eye, verts[2], n)
    s_dir = directional_specular_kernel(p, nrm, eye, -verts[1], n)
    return s_poly + 0.7 * s_iso + 0.5 * s_tube + 0.1 * s_pt + 0.05 * s_dir


_all_kernels_jit = jax.jit(_all_kernels)


@pytest.mark.slow  # XLA compiles the second derivatives of all kernels: minutes on 2 cores
def test_check_grads_order2_all_kernels():
    p, nrm, eye, verts = _grad_config()
    args = (p, nrm, eye, verts, jnp.asarray(37.5), jnp.asarray(2.5))
    check_grads(_all_kernels_jit, args, order=2, modes=("fwd", "rev"))


def test_gradients_match_finite_differences():
    # First-order reverse-mode check against central differences, reusing the functions the
    # singular-configuration tests compile (so it costs no extra compilation).
    p, nrm, eye, verts = (np.asarray(x) for x in _grad_config())
    verts = np.concatenate([verts, verts[:1], verts[:1]])  # K = 6, the compiled shape
    h = 1e-6
    for n in [1.0, 37.5]:
        args = [jnp.asarray(x[None]) for x in (p, nrm, eye, verts)]
        _, grads = _singular_polygon_value_and_grad(*args, jnp.asarray(n))
        f = lambda *a, n=n: _polygon_batch("chebyshev", [np.asarray(x) for x in a], n)[0]
        for i, x in enumerate((p, nrm, eye, verts[:4])):
            for j in np.ndindex(x.shape):
                plus = [a.copy() for a in (p, nrm, eye, verts)]
                minus = [a.copy() for a in (p, nrm, eye, verts)]
                plus[i][j] += h
                minus[i][j] -= h
                if i == 3 and j[0] == 0:  # vertex 0 and its padded copies move together
                    plus[3][4:] = plus[3][0]
                    minus[3][4:] = minus[3][0]
                    want = (f(*(a[None] for a in plus)) - f(*(a[None] for a in minus))) / (2 * h)
                    got = float(grads[3][0][j]) + float(np.sum(grads[3][0][4:, j[1]]))
                else:
                    want = (f(*(a[None] for a in plus)) - f(*(a[None] for a in minus))) / (2 * h)
                    got = float(grads[i][0][j])
                assert abs(got - want) <= 1e-6 * (1 + abs(want)), (n, i, j, got, want)
        fd_n = (
            _polygon_batch("chebyshev", [x[None] for x in (p, nrm, eye, verts)], n + h)[0]
            - _polygon_batch("chebyshev", [x[None] for x in (p, nrm, eye, verts)], n - h)[0]
        ) / (2 * h)
        assert abs(float(grads[4][0]) - fd_n) <= 1e-6 * (1 + abs(fd_n))


def test_chebyshev_derivative_in_exponent_tracks_exact():
    # d/dn of the approximation is exact for the approximation, and close to the true d/dn.
    p, nrm, eye, verts = _grad_config()
    f_cheb = jax.jit(jax.grad(lambda n: polygon_specular_kernel(p, nrm, eye, verts, n)))
    # The exact method's non-integer path (quadrature) is differentiable in forward mode.
    f_ex = jax.jit(
        jax.jacfwd(lambda n: polygon_specular_kernel(p, nrm, eye, verts, n, method="exact"))
    )
    for n in [20.0, 1e4]:
        g_cheb = f_cheb(jnp.asarray(n + 0.5))
        g_ex = f_ex(jnp.asarray(n + 0.5))
        assert np.isclose(g_cheb, g_ex, rtol=1e-3, atol=1e-9)


# --------------------------------------------------------------------------------------
# Singular configurations: finite values and gradients, continuity
# --------------------------------------------------------------------------------------


def _singular_polygon_configs():
    """(p, n, eye, verts) with the lobe peak on an edge, on a vertex, R in an edge's plane."""
    sq = np.array([[-1, 1, 2.0], [1, 1, 2], [1, -1, 2], [-1, -1, 2]])
    verts = _pad(sq)
    p = np.array([0.1, 0.2, 0.0])
    nrm = np.array([0.0, 0.0, 1.0])
    out = []
    for target in [
        np.array([1.0, 0.3, 2.0]),  # peak exactly on an edge (x = 1): R in the edge's plane
        np.array([1.0, 1.0, 2.0]),  # peak exactly on a vertex
        np.array([0.1, 0.2, 2.0]),  # peak at the foot, inside
        np.array([3.0, 0.2, 2.0]),  # peak beyond the light
        np.array([1.0, 7.0, 2.0]),  # R in the plane of p and the edge x = 1, beyond the edge
    ]:
        w = (target - p) / np.linalg.norm(target - p)
        out.append((p, nrm, p + 2.0 * (2 * (nrm @ w) * nrm - w), verts))
    # Grazing: horizon through the light, peak on the horizon line.
    nrm2 = np.array([1.0, 0.0, 0.0])
    w = np.array([0.0, 0.0, 1.0])
    out.append((p, nrm2, p + 2 * (2 * (nrm2 @ w) * nrm2 - w), verts))
    return [np.array(x) for x in zip(*out, strict=True)]


_singular_polygon_value_and_grad = jax.jit(
    jax.vmap(
        jax.value_and_grad(polygon_specular_kernel, argnums=(0, 1, 2, 3, 4)),
        in_axes=(0, 0, 0, 0, None),
    )
)


@pytest.mark.parametrize("n", [1.0, 1e4])
def test_singular_polygon_finite(dtype, n):
    cfg = [jnp.asarray(x, dtype) for x in _singular_polygon_configs()]
    val_grad = _singular_polygon_value_and_grad
    vals, grads = val_grad(*cfg, jnp.asarray(n, dtype))
    assert vals.dtype == dtype
    assert np.all(np.isfinite(vals)) and np.all(vals >= -1e-6) and np.all(vals <= 1 + 1e-6)
    for g in grads:
        assert np.all(np.isfinite(g))
    # Continuity: moving the eye a little changes the value a little.
    eye2 = cfg[2] + jnp.asarray([[1e-4, -1e-4, 0.0]], dtype)
    vals2, _ = val_grad(cfg[0], cfg[1], eye2, cfg[3], jnp.asarray(n, dtype))
    lim = 0.05 if n > 100 else 2e-3
    assert np.all(np.abs(vals2 - vals) <= lim * np.maximum(vals, 1e-3))


def test_singular_polygon_exact_matches_chebyshev():
    cfg = _singular_polygon_configs()
    for n in [1.0, 100.0, 1e4]:
        ex = _polygon_batch("exact", cfg, n)
        ch = _polygon_batch("chebyshev", cfg, n)
        assert np.all(np.abs(ch - ex) <= 1e-4 * np.maximum(ex, 1e-3 * ex.max())), (n, ch, ex)


def _singular_segment_configs():
    p = np.array([0.0, 0.0, 0.0])
    nrm = np.array([0.0, 0.0, 1.0])
    out = []
    # Crossing the tangent plane, peak on the kept part / exactly at the horizon point.
    q0, q1 = np.array([-1.0, 0.3, -0.5]), np.array([1.0, 0.3, 1.5])
    for target in [q0 + 0.8 * (q1 - q0), q0 + 0.25 * (q1 - q0), q1]:
        w = target / np.linalg.norm(target)
        out.append((p, nrm, 2 * (2 * (nrm @ w) * nrm - w), q0, q1))
    # Receiver on the segment's supporting line (outside it).
    q0, q1 = np.array([0.0, 1.0, 1.0]), np.array([0.0, 2.0, 2.0])
    w = np.array([0.0, 1.0, 1.0]) / np.sqrt(2)
    out.append((p, nrm, 2 * (2 * (nrm @ w) * nrm - w), q0, q1))
    # R perpendicular to the plane of receiver and segment (R = (0, 1, 1) / sqrt 2).
    q0, q1 = np.array([-1.0, -1.0, 1.0]), np.array([1.0, -1.0, 1.0])
    out.append((p, nrm, np.array([0.0, -1.0, 1.0]), q0, q1))
    return [np.array(x) for x in zip(*out, strict=True)]


def _iso_plus_tube(p, nrm, eye, q0, q1, n):
    tube = segment_specular_kernel(p, nrm, eye, q0, q1, n, jnp.asarray(2.0, p.dtype))
    return segment_specular_kernel(p, nrm, eye, q0, q1, n) + tube


_singular_segment_value_and_grad = jax.jit(
    jax.vmap(
        jax.value_and_grad(_iso_plus_tube, argnums=(0, 1, 2, 3, 4, 5)),
        in_axes=(0, 0, 0, 0, 0, None),
    )
)


@pytest.mark.parametrize("n", [1.0, 1e4])
def test_singular_segment_finite(dtype, n):
    cfg = [jnp.asarray(x, dtype) for x in _singular_segment_configs()]
    val_grad = _singular_segment_value_and_grad
    vals, grads = val_grad(*cfg, jnp.asarray(n, dtype))
    assert vals.dtype == dtype
    assert np.all(np.isfinite(vals)) and np.all(vals >= 0)
    for g in grads:
        assert np.all(np.isfinite(g))


def _back_facing_configs(count=8, seed=3):
    """Eyes behind the receiver's tangent plane (N . V < 0): R points below the horizon."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        nrm = np.array([0, 0, 1.0]) + 0.8 * rng.normal(size=3)
        nrm[2] = abs(nrm[2]) + 0.2
        nrm /= np.linalg.norm(nrm)
        p = np.r_[0.3 * rng.normal(size=2), 0.0]
        v = rng.normal(size=3)
        v -= (v @ nrm) * nrm
        v = v / np.linalg.norm(v) - rng.uniform(0.02, 1.0) * nrm
        out.append((p, nrm, p + 2 * v / np.linalg.norm(v)))
    # -R exactly at the middle of the light: the lobe misses it entirely (S = 0).
    d = np.array([0.2, 0.1, 2.0]) / np.linalg.norm([0.2, 0.1, 2.0])
    nz = np.array([0.0, 0.0, 1.0])
    r = -d
    out.append((np.zeros(3), nz, 2 * (2 * (nz @ r) * nz - r)))
    return out


@pytest.mark.parametrize("method", ["exact", "chebyshev"])
def test_polygon_eye_behind_the_tangent_plane(method):
    """Regression: with the eye behind the tangent plane, -R can lie inside the light seen from
    p; the polar sweep about R counted it as a winding and returned S - 1 (S = -1 where the
    lobe misses the light). Checked against the independent quadrature; S >= 0 up to round-off."""
    square = np.array([[-1, 1, 2.0], [1, 1, 2], [1, -1, 2], [-1, -1, 2]])
    cfgs = _back_facing_configs()
    n_minus_r_inside = 0
    for p, nrm, eye in cfgs:
        nn, r = _mirror(p, nrm, eye)
        assert nn @ (eye - p) < 0
        hit = p - r * (2.0 - p[2]) / -r[2] if -r[2] > 0 else None  # -R meets the light's plane z = 2
        n_minus_r_inside += int(hit is not None and np.all(np.abs(hit[:2]) < 1))
        for n in (1.0, 4.0):
            ref = reference_polygon(p, nrm, eye, square, n)
            got = _polygon_batch(method, [x[None] for x in (p, nrm, eye, _pad(square))], n)[0]
            tol = 1e-12 if method == "exact" else 1e-4 * max(ref, 1e-3)
            assert abs(got - ref) <= tol and got > -1e-12, (p, nrm, eye, n, got, ref)
    assert n_minus_r_inside >= 2  # the configurations do exercise the case


@pytest.mark.parametrize("method", ["exact", "chebyshev"])
def test_zero_length_segment_has_zero_finite_gradient(dtype, method):
    """The shadow code pads a linear light's visible sub-segments with zero-length ones; with
    fused multiply-adds `a x a` need not round to 0, so the kernel must not trust the cross
    product alone (this gave NaN derivatives of `js.specular` for a shadowed linear light)."""
    p = jnp.asarray([0.1, 0.2, 0.0], dtype)
    nrm = jnp.asarray([0.0, 0.0, 1.0], dtype)
    eye = jnp.asarray([0.4, -1.8, 1.6], dtype)
    a = jnp.asarray([-0.6, -0.1, 1.2], dtype)
    f = lambda p, u: segment_specular_kernel(p, nrm, eye, u, u, jnp.asarray(12.0, dtype), None, method=method)  # noqa: E731
    assert float(f(p, a)) == 0.0
    for g in jax.grad(f, argnums=(0, 1))(p, a):
        assert np.all(np.asarray(g) == 0.0)


@pytest.mark.parametrize("method", ["exact", "chebyshev"])
def test_edges_of_round_off_length_contribute_nothing(method):
    """Edge soups of the shadow code hold edges of round-off length at shared vertices (this one,
    1 ulp long, is from the boundary of a cube mesh's shadow). Their direction is noise: the
    arc's end must not be computed on its own, or it can land a rounding error before its start
    and read as an arc around the whole circle (this edge alone gave -0.46)."""
    h = lambda *xs: jnp.asarray([float.fromhex(x) for x in xs])  # noqa: E731
    p = h("0x1.b88ce9d5b5311p-2", "-0x1.ebf6dd7c47501p-4", "0x0.0p+0")
    eye = h("0x1.999999999999ap-2", "-0x1.ccccccccccccdp+0", "0x1.999999999999ap+0")
    a = h("0x1.fc5e2367a673cp-3", "-0x1.c2290e061baaep-3", "0x1.bbae44ab3bdd6p+0")
    b = h("0x1.fc5e2367a673dp-3", "-0x1.c2290e061baaep-3", "0x1.bbae44ab3bdd5p+0")
    nrm = jnp.asarray([0.0, 0.0, 1.0])
    for s, e in ((a, b), (b, a)):
        val = contour_specular_kernel(p, nrm, eye, s[None, :], e[None, :], jnp.asarray(12.0), method=method)
        assert abs(float(val)) < 1e-12
