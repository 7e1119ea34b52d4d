r"""Property-based tests (hypothesis) against references that share no code with the kernels.

What is drawn: convex polygon lights (3-6 vertices, any orientation), segment lights (profile
m in {0, 1, 4}), receivers at distances 0.05-20 light sizes with any normal, near-degenerate
placements (receiver 1e-9..1e-3 light sizes from the light's plane, near the supporting line
of a polygon edge or past a segment's end, normals grazing the light), whole scenes scaled by
1e-6..1e6 and moved by up to 1e5 light sizes, float32 and float64, and small shadow scenes
(1-3 occluders between a light and its receivers).

References (float64, evaluated at the dtype-rounded inputs, so errors measure the kernels):

- unoccluded polygon form factor: `polar_form_factor` below, an *area* integral in polar
  coordinates about the receiver's foot on the light's plane: the horizon clip is a
  Sutherland-Hodgman half-plane cut in 2-D, the radial integral of
  $h(a\cdot y - c)/(\pi r^4)$ is done in closed form, the angular one by `scipy.integrate.quad`
  between the vertex directions (the kernels use Lambert's *contour* sum);
- segment lights: `test_stability.mp_linear` (mpmath quadrature along the segment, 60 digits);
- shadows: `test_clip.reference_ff` (exact polygon booleans with shapely, then Lambert's sum in
  NumPy), against `js.irradiance` (the host shadow engine);
- gradients: `jax.test_util.check_grads` (central finite differences) at generic draws, and
  finite values and gradients at every draw.

Tolerances: float64 `1e-9 F + 1e-12 S`, float32 `1e-5 F + 1e-6 S`, with $F$ the reference and
$S = \sum_i \theta_i / 2\pi$ the contour sum's condition number (the angles the light's edges
subtend; Lambert's sum cannot be more accurate than rounding times that). Segment lights:
relative 1e-9 / 2e-5 plus $8\epsilon\kappa(E + 1/r)$, $\kappa = L / r$ (coordinates of size $L$ against
the distance $r$ from the receiver to the segment, which $E \sim 1/r$ depends on).

Profiles: CI runs a derandomized (fixed-seed, no shrinking), bounded profile: `CI_EXAMPLES`
= 30 draws for each of the 4 properties (120 cases; ~50 s on one core of the CI machine, most
of it compiling), plus the reference's own closed-form check; `-m slow` runs `LONG_EXAMPLES`
= 400 random draws per property (1600 cases). Every failure hypothesis found is an explicit
case in `test_reliability.py` (`test_found_*`).
"""

from __future__ import annotations

import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, assume, given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads
from scipy import integrate
from test_clip import reference_ff
from test_stability import mp_form_factor, mp_linear

import jaxshadow as js
from benchmarks.scenes import rotation
from jaxshadow._kernels.linear import linear_irradiance_kernel
from jaxshadow._kernels.polygon import form_factor_kernel

CI_EXAMPLES = 30
LONG_EXAMPLES = 400
F32, F64 = np.float32, np.float64


def _profile(n: int, derandomize: bool):
    # CI does not shrink (a failure prints its reproduction blob at once; shrinking can take
    # minutes); the long profile does.
    phases = (Phase.explicit, Phase.reuse, Phase.generate) if derandomize else tuple(Phase)
    return settings(
        max_examples=n,
        derandomize=derandomize,
        phases=phases,
        deadline=None,
        database=None,
        print_blob=True,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much, HealthCheck.data_too_large],
    )


CI = _profile(CI_EXAMPLES, True)
LONG = _profile(LONG_EXAMPLES, False)

# --------------------------------------------------------------------------------------
# Independent reference: polar area integral about the foot point
# --------------------------------------------------------------------------------------


def _clip_halfplane(poly, a, c):
    """Sutherland-Hodgman in 2-D: the part of a convex polygon with `a . y >= c`."""
    out = []
    k = len(poly)
    for i in range(k):
        y0, y1 = poly[i], poly[(i + 1) % k]
        d0, d1 = a @ y0 - c, a @ y1 - c
        if d0 >= 0:
            out.append(y0)
        if (d0 >= 0) != (d1 >= 0):
            out.append(y0 + d0 / (d0 - d1) * (y1 - y0))
    return out


def polar_form_factor(p, n, verts):
    r"""$F = \frac1\pi\int \cos\theta_r\cos\theta_e / r^2\,dA$ over the light above the receiver's
    horizon, in polar coordinates $(\rho, \phi)$ about the foot of `p` on the light's plane.
    Also returns $S = \sum_i \theta_i / 2\pi$ (angles the light's edges subtend at `p`)."""
    p, n, v = (np.asarray(x, np.float64) for x in (p, n, verts))
    centre = v.mean(axis=0)
    size = np.max(np.linalg.norm(v - centre, axis=1))
    p, v = (p - centre) / size, (v - centre) / size  # F is translation and scale invariant
    n = n / np.linalg.norm(n)
    rel = v - p
    cond = sum(math.atan2(np.linalg.norm(np.cross(rel[i], rel[i - 1])), rel[i] @ rel[i - 1]) for i in range(len(v)))
    ne = np.sum(np.cross(v, np.roll(v, -1, axis=0)), axis=0)
    ne /= np.linalg.norm(ne)
    h = ne @ (p - v[0])
    if h <= 0:
        return 0.0, cond / (2 * math.pi)
    foot = p - h * ne
    e1 = v[1] - v[0]
    e1 -= (e1 @ ne) * ne
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(ne, e1)
    poly = [np.array([(x - foot) @ e1, (x - foot) @ e2]) for x in v]
    a, c = np.array([n @ e1, n @ e2]), h * (n @ ne)
    poly = _clip_halfplane(poly, a, c)
    if len(poly) < 3:
        return 0.0, cond / (2 * math.pi)
    edges = [(poly[i], poly[(i + 1) % len(poly)] - poly[i]) for i in range(len(poly))]

    def g(rho, aw):
        r2 = rho * rho + h * h
        return aw * (math.atan(rho / h) / (2 * h) - rho / (2 * r2)) + c / (2 * r2)

    def radial(phi):
        w = np.array([math.cos(phi), math.sin(phi)])
        lo, hi = 0.0, math.inf
        for y0, e in edges:  # inside: cross(e, y - y0) >= 0, linear in rho along the ray
            alpha = e[0] * (-y0[1]) - e[1] * (-y0[0])
            beta = e[0] * w[1] - e[1] * w[0]
            if beta > 0:
                lo = max(lo, -alpha / beta)
            elif beta < 0:
                hi = min(hi, -alpha / beta)
            elif alpha < 0:
                return 0.0
        if not hi > lo:
            return 0.0
        aw = a @ w
        return h / math.pi * (g(hi, aw) - g(lo, aw))

    cuts = sorted({math.atan2(y[1], y[0]) for y in poly} | {-math.pi, math.pi})
    total = 0.0
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", integrate.IntegrationWarning)
            for lo, hi in zip(cuts[:-1], cuts[1:], strict=True):
                if hi > lo:
                    total += integrate.quad(radial, lo, hi, epsabs=1e-15, epsrel=1e-13, limit=200)[0]
    except integrate.IntegrationWarning:
        # quad doubts its result (a foot point within rounding of an edge): mpmath's 60-digit
        # contour sum, the other independent reference.
        total = float(mp_form_factor(p, n, v))
    return total, cond / (2 * math.pi)


def test_polar_reference_against_closed_forms():
    # Parallel square of side 2 at height 1 over its centre: four times Howell's B-3 corner
    # term; and, at random receivers (horizon cuts included), mpmath's 60-digit contour sum.
    sq = np.array([[-1.0, -1.0, 1.0], [-1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [1.0, -1.0, 1.0]])
    corner = 1 / math.pi * (1 / math.sqrt(2)) * math.atan(1 / math.sqrt(2))
    assert polar_form_factor(np.zeros(3), [0, 0, 1.0], sq)[0] == pytest.approx(4 * corner, rel=1e-12)
    rng = np.random.default_rng(5)
    for _ in range(4):
        p = rng.normal(size=3) * [1.0, 1.0, 0.3]
        n = _unit(rng.normal(size=3) + [0, 0, 1.0])
        ref = float(mp_form_factor(p, n, sq))
        assert ref > 0
        assert polar_form_factor(p, n, sq)[0] == pytest.approx(ref, rel=1e-11)


# --------------------------------------------------------------------------------------
# Strategies
# --------------------------------------------------------------------------------------


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


@st.composite
def directions(draw):
    z = draw(st.floats(-1.0, 1.0))
    phi = draw(st.floats(0.0, 2 * math.pi))
    r = math.sqrt(max(0.0, 1.0 - z * z))
    return np.array([r * math.cos(phi), r * math.sin(phi), z])


@st.composite
def placements(draw):
    """`(scale, offset)`: scene scale 1e-6..1e6 and a shift of up to 1e5 light sizes."""
    scale = 10.0 ** draw(st.floats(-6.0, 6.0))
    far = draw(st.booleans())
    mag = 10.0 ** draw(st.floats(-1.0, 5.0)) if far else 0.0
    return scale, mag * scale * draw(directions())


@st.composite
def polygon_lights(draw):
    """A convex k-gon of size ~1 about the origin, random orientation, counter-clockwise seen
    from the side its right-hand normal points to."""
    k = draw(st.integers(3, 6))
    gaps = np.array(draw(st.lists(st.floats(0.3, 1.0), min_size=k, max_size=k)))
    ang = np.cumsum(gaps) / np.sum(gaps) * 2 * math.pi
    stretch = draw(st.floats(0.2, 1.0))
    v = np.stack([np.cos(ang), stretch * np.sin(ang), np.zeros(k)], axis=1)
    axis, angle = draw(directions()), draw(st.floats(0.0, math.pi))
    return v @ rotation(axis, angle).T


@st.composite
def receivers(draw, verts):
    """A receiver and normal for the light `verts`: generic (0.05-20 light sizes away) or near
    a degenerate configuration (close to the light's plane, near an edge's supporting line,
    normal grazing the light)."""
    ne = _unit(np.sum(np.cross(verts, np.roll(verts, -1, axis=0)), axis=0))
    kind = draw(st.sampled_from(["generic", "near-plane", "edge-line", "grazing"]))
    if kind == "generic":
        p = draw(directions()) * 10.0 ** draw(st.floats(math.log10(0.05), math.log10(20.0)))
    elif kind == "near-plane":
        # Under (or beside) the light, 1e-9 .. 1e-3 from its plane, on the lit side.
        w = np.array(draw(st.lists(st.floats(-1.5, 1.5), min_size=2, max_size=2)))
        t = _unit(np.cross(ne, [1.0, 0.3, 0.1]))
        p = w[0] * t + w[1] * np.cross(ne, t) + 10.0 ** draw(st.floats(-9.0, -3.0)) * ne
    elif kind == "edge-line":
        i = draw(st.integers(0, len(verts) - 1))
        a, b = verts[i], verts[(i + 1) % len(verts)]
        s = draw(st.floats(1.2, 4.0)) * draw(st.sampled_from([-1.0, 1.0]))
        off = 10.0 ** draw(st.floats(-9.0, -2.0)) * _unit(np.cross(b - a, [0.2, 1.0, 0.3]))
        p = a + (0.5 + s) * (b - a) + off
    else:
        p = draw(directions()) * draw(st.floats(0.5, 5.0))
    n = draw(directions())
    if kind == "grazing":
        # Normal perpendicular to the direction of the light's centre, tipped by 1e-7..1e-2.
        to_light = _unit(-p)
        n = _unit(np.cross(to_light, n) + 10.0 ** draw(st.floats(-7.0, -2.0)) * to_light)
    return p, n, kind


def _tolerances(dt):
    return (1e-9, 1e-12) if dt == F64 else (1e-5, 1e-6)


# --------------------------------------------------------------------------------------
# Properties
# --------------------------------------------------------------------------------------


def _check_polygon(data):
    verts = data.draw(polygon_lights())
    p, n, kind = data.draw(receivers(verts))
    scale, offset = data.draw(placements())
    dt = data.draw(st.sampled_from([F32, F64]))
    pv, vv = (x * scale + offset for x in (p, verts))
    assume(np.linalg.norm(pv - vv.mean(axis=0)) > 0)
    pr, nr, vr = pv.astype(dt), n.astype(dt), vv.astype(dt)
    assume(np.all(np.linalg.norm(np.roll(vr, -1, axis=0) - vr, axis=1) > 1e-3 * scale))  # rounding kept it a polygon
    try:
        f = float(js.form_factor(pr[None], nr[None], vr)[0])
    except ValueError as err:  # float32 rounding made it non-planar at the build-time tolerance
        assume("non-planar" not in str(err))
        raise
    ref, cond = polar_form_factor(pr, nr, vr)
    rtol, floor = _tolerances(dt)
    tol = rtol * ref + floor * cond
    assert np.isfinite(f) and -tol <= f <= 1.0 + tol, (kind, dt.__name__, f, ref, cond)
    # Within the rounding of the light's coordinates of its plane, the side is undecidable
    # (the documented validity bound of `form_factor`): F is 0 or the lit-side value.
    v64, p64 = vr.astype(F64), pr.astype(F64)
    ne = _unit(np.sum(np.cross(v64, np.roll(v64, -1, axis=0)), axis=0))
    if abs(ne @ (p64 - v64[0])) <= 8 * np.finfo(dt).eps * np.max(np.abs(v64 - p64)):
        assert ref == 0.0 or min(f, abs(f - ref)) <= tol, (kind, dt.__name__, f, ref)
        return
    assert abs(f - ref) <= tol, (kind, dt.__name__, f, ref, cond)


@CI
@given(st.data())
def test_polygon_form_factor_against_polar_integration(data):
    _check_polygon(data)


@pytest.mark.slow
@LONG
@given(st.data())
def test_polygon_form_factor_against_polar_integration_long(data):
    _check_polygon(data)


@st.composite
def segment_scenes(draw):
    a = draw(directions()) * draw(st.floats(0.0, 1.0))
    b = a + draw(directions()) * draw(st.floats(0.3, 2.0))
    u = _unit(b - a)
    kind = draw(st.sampled_from(["generic", "past-end", "near-line"]))
    if kind == "generic":
        p = (a + b) / 2 + draw(directions()) * 10.0 ** draw(st.floats(math.log10(0.05), 1.0))
    else:
        perp = _unit(np.cross(u, draw(directions())) + 1e-9)
        along = 10.0 ** draw(st.floats(-7.0, -1.0)) if kind == "past-end" else draw(st.floats(-0.5, 1.5))
        end = b if kind == "past-end" else a
        p = end + along * u + 10.0 ** draw(st.floats(-7.0, -1.0)) * perp
    n = draw(directions())
    return a, b, p, n, kind


def _check_segment(data):
    a, b, p, n, kind = data.draw(segment_scenes())
    scale, offset = data.draw(placements())
    m = data.draw(st.sampled_from([0, 1, 4]))
    dt = data.draw(st.sampled_from([F32, F64]))
    ar, br, pr = ((x * scale + offset).astype(dt) for x in (a, b, p))
    nr = n.astype(dt)
    assume(np.any(ar != br))
    # Receiver exactly on the segment's line after rounding: the value is a limit (tested apart).
    w = (pr - ar).astype(F64)
    e = (br - ar).astype(F64)
    assume(np.linalg.norm(np.cross(w, e)) > 1e-12 * np.linalg.norm(w) * np.linalg.norm(e))
    got = float(js.linear_irradiance(pr[None], nr[None], ar, br, m)[0])
    ref = float(mp_linear(pr.astype(F64), nr.astype(F64) / np.linalg.norm(nr.astype(F64)), ar.astype(F64), br.astype(F64), m))
    # Condition number: coordinates of size L known to rounding eps, against the distance r
    # from the receiver to the segment that E ~ 1/r depends on (backward-stable kernels reach
    # it; the float32 row-8 configurations are held to 1e-5 in test_reliability.py).
    ends = np.stack([ar, br]).astype(F64)
    t = np.clip((pr.astype(F64) - ends[0]) @ e / (e @ e), 0.0, 1.0)
    r = np.linalg.norm(pr.astype(F64) - (ends[0] + t * e))
    kappa = np.max(np.linalg.norm(ends - pr.astype(F64), axis=1)) / r
    rtol = 1e-9 if dt == F64 else 2e-5
    assert np.isfinite(got)
    # The absolute part (E's natural size 1/r): a horizon that leaves a sliver of the segment
    # makes E tiny, and only relative to 1/r is its error small.
    tol = abs(ref) * rtol + 8 * np.finfo(dt).eps * kappa * (abs(ref) + 1.0 / r)
    assert abs(got - ref) <= tol, (kind, m, dt.__name__, got, ref, kappa)


@CI
@given(st.data())
def test_segment_light_against_mpmath(data):
    _check_segment(data)


@pytest.mark.slow
@LONG
@given(st.data())
def test_segment_light_against_mpmath_long(data):
    _check_segment(data)


# ---- gradients -------------------------------------------------------------------------

K_PAD = 6  # polygons padded to one shape (repeating the first vertex): one compilation per dtype
_grad_ff = jax.jit(jax.value_and_grad(form_factor_kernel, argnums=(0, 1, 2)))
_ff = jax.jit(form_factor_kernel)
_grad_lin = {m: jax.jit(jax.value_and_grad(lambda p, n, a, b, m=m: linear_irradiance_kernel(p, n, a, b, m), argnums=(0, 1, 2, 3)))
             for m in (0, 4)}


def _check_gradients(data):
    verts = data.draw(polygon_lights())
    verts = np.concatenate([verts, np.repeat(verts[:1], K_PAD - len(verts), axis=0)])
    p, n, kind = data.draw(receivers(verts[:3]))
    dt = data.draw(st.sampled_from([F32, F64]))
    args = tuple(jnp.asarray(x, dt) for x in (p, n, verts))
    val, grads = _grad_ff(*args)
    assert np.isfinite(float(val)) and all(np.all(np.isfinite(np.asarray(g))) for g in grads), kind
    m = data.draw(st.sampled_from([0, 4]))
    val, grads = _grad_lin[m](args[0], args[1], args[2][0], args[2][1])
    assert not np.isnan(float(val)) and all(np.all(np.isfinite(np.asarray(g))) for g in grads), kind
    if kind == "generic" and dt == F64:
        # Away from the kinks (a vertex crossing the horizon within the difference step) and
        # from the light's plane (F jumps to 0 across it).
        rel = verts - p
        heights = rel @ _unit(n) / np.linalg.norm(rel, axis=1)
        assume(np.min(np.abs(heights)) > 1e-3)
        ne = _unit(np.sum(np.cross(verts, np.roll(verts, -1, axis=0)), axis=0))
        assume(abs(ne @ rel[0]) > 1e-3)
        v = jnp.asarray(verts)
        check_grads(lambda q, nn: _ff(q, nn, v), (jnp.asarray(p), jnp.asarray(_unit(n))), order=1, modes=("fwd", "rev"), eps=1e-6)


@CI
@given(st.data())
def test_gradients_finite_and_match_finite_differences(data):
    _check_gradients(data)


@pytest.mark.slow
@LONG
@given(st.data())
def test_gradients_finite_and_match_finite_differences_long(data):
    _check_gradients(data)


# ---- shadows -------------------------------------------------------------------------


@st.composite
def shadow_scenes(draw):
    """A light at height 2 (lit side down), 1-3 convex occluders at heights 0.2-1.8 over the
    light's footprint, receivers on the floor z = 0 with normals around +z."""
    light = np.array([[-0.5, -0.5, 2.0], [-0.5, 0.5, 2.0], [0.5, 0.5, 2.0], [0.5, -0.5, 2.0]])
    occ = []
    for _ in range(draw(st.integers(1, 3))):
        v = draw(polygon_lights()) * draw(st.floats(0.1, 0.5))
        v[:, 2] *= 0.3  # mostly horizontal
        centre = np.array([draw(st.floats(-0.8, 0.8)), draw(st.floats(-0.8, 0.8)), draw(st.floats(0.2, 1.8))])
        occ.append(v + centre)
    pts = np.array([[draw(st.floats(-1.5, 1.5)), draw(st.floats(-1.5, 1.5)), 0.0] for _ in range(4)])
    nrm = np.array([_unit([draw(st.floats(-0.5, 0.5)), draw(st.floats(-0.5, 0.5)), 1.0]) for _ in range(4)])
    return light, occ, pts, nrm


def _check_shadows(data):
    light, occ, pts, nrm = data.draw(shadow_scenes())
    scale, offset = data.draw(placements())
    dt = data.draw(st.sampled_from([F32, F64]))
    light, pts = ((x * scale + offset).astype(dt) for x in (light, pts))
    occ = [(o * scale + offset).astype(dt) for o in occ]
    nrm = nrm.astype(dt)
    try:
        scene = js.Scene([js.PolygonLight(light, 1.0 / np.pi)], occluders=occ)
    except ValueError:
        assume(False)  # rounding at a large offset made an occluder non-planar
    got = np.asarray(js.irradiance(scene, pts, nrm))[:, 0]
    unocc = np.asarray(js.form_factor(pts.astype(F64), nrm.astype(F64), light.astype(F64)))
    rtol = 1e-9 if dt == F64 else 1e-5
    for i in range(len(pts)):
        ref = reference_ff(pts[i], nrm[i], light, occ)
        assert np.isfinite(got[i])
        assert abs(got[i] - ref) <= rtol * max(unocc[i], 1e-3), (i, dt.__name__, got[i], ref, unocc[i])


@CI
@given(st.data())
def test_shadows_against_shapely(data):
    _check_shadows(data)


@pytest.mark.slow
@LONG
@given(st.data())
def test_shadows_against_shapely_long(data):
    _check_shadows(data)
