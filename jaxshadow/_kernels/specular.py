r"""Phong-lobe (specular) integrals for polygon, segment, point and directional lights.

Convention (DESIGN.md, Poulin eq. 3.12 normalisation): the specular factor at a receiver $p$
with normal $N$, seen from the eye along $V$, is

$$S = \int L_i(w)\,\frac{n+1}{2\pi}\,\max(0, w \cdot R)^n\,dw,\qquad R = 2(N\cdot V)N - V,$$

over the part of the light above the tangent plane. The kernels return the geometric factor
per unit radiance (polygon), per unit power per length (segment), per unit intensity (point)
or per unit irradiance (directional); the caller multiplies by the (RGB) emission.

**One edge, one arc.** Every edge of a (horizon-clipped) polygon and every segment light is an
arc of a great circle of directions. Parametrise it by arc length $u$ measured from the point of
its great circle closest to $R$: $w(u) = \cos u\,e_1 + \sin u\,e_2$, so that
$w \cdot R = \rho \cos u$ with $\rho = \cos\alpha$ ($\alpha$: Poulin's angle from $R$ to the
great circle) and $s = R \cdot \hat m = \pm\sin\alpha$ ($\hat m$ the arc's plane normal,
oriented by the edge direction).

*Polygon (Poulin §3.3.2, eq. 3.12).* Integrating the lobe over the spherical triangle
$(R, w_i, w_{i+1})$ in polar coordinates about $R$ gives Tanaka and Takahashi's
$(\beta_B - \beta_A) - (H(\alpha, \beta_B) - H(\alpha, \beta_A))$, in the azimuth $\beta$ about
$R$. With $d\beta = s\,du / (1 - c^2)$, $c = w\cdot R$, the same edge term reads

$$\int_{u_a}^{u_b} s\,\frac{1 - \max(0, c)^{n+1}}{1 - c^2}\,du,$$

and $S = -\frac{1}{2\pi}\sum_{\text{edges}}(\cdot)$. The signed $s$ carries Poulin's orientation
sign $F(w_i, w_{i+1})$. We integrate in $u$ rather than in $\beta$: in $\beta$ the integrand
becomes a step as the lobe peak approaches an edge ($\alpha \to 0$) and $\beta_A, \beta_B$ jump,
while in $u$ it is analytic (the pole of $1/(1 - c^2)$ at $c = 1$ is cancelled by the
numerator) and bounded by $(n+1)/2$. The arc is split into the part with $|u| \le X$, where the
lobe lives, and the rest, where $\max(0, c)^{n+1}$ is negligible (Chebyshev method, $X$ the
cut-off angle) or exactly 0 (exact method, $X = \pi/2$: the cut to $w \cdot R > 0$ of §4.3.1);
the rest is an exact change of azimuth (`atan2`).

*Segment (Poulin eq. 3.11, §3.2.2).* In the plane through $p$ and the segment,
$dl / r^2 = du / d$ ($d$ the distance from $p$ to the line) and $w\cdot R = \rho\cos u$ with
$\rho = |R_{p}|$ ($R_p$: $R$ projected on that plane), so

$$S = I_0\,\frac{n+1}{2\pi}\,\frac{\rho^n}{d}\int \cos^n u\;\cos^m(u - u_\perp)\,du$$

over the part of the segment above the tangent plane with $w \cdot R > 0$ ($|u| < \pi/2$);
$m = 0$, $I_0 = 1/(4\pi)$ for the isotropic profile and $I_0 = 1/(2\pi W(m+1))$ for the
$\cos^m$ tube ($u_\perp$: the direction of the foot of the perpendicular, where $\beta = 0$).

**Methods** (static): `"chebyshev"` (Poulin fig. 3.9). Polygon edges: one even Chebyshev fit
of the edge integrand on $[-x_M, x_M]$ (`degree + 1` samples, degree `2 * degree` in $u$,
`_chebyshev.even_fit_integral`), integrated analytically (Clenshaw); the lobe beyond the
cut-off angle $x_M$ ($\cos^{n+1} x_M = $ `tol`) is dropped. Segments: a degree-`2 * degree` fit
of $\cos^n u \cos^m(u - u_\perp)$ on the part of the arc inside the cut-off (Poulin's "product
of two polynomials"), the cut-off taken relative to the largest $\cos^n$ on the arc so that a
segment in the lobe's tail keeps its relative accuracy. `"exact"`: for integer
$n$ the recurrence $\int\cos^j = [\cos^{j-1}\sin]/j + \frac{j-1}{j}\int\cos^{j-2}$ (with
$\frac{1 - c^{k}}{1 - c^2} = \frac{1 - c^{k-2}}{1 - c^2} + c^{k-2}$ for polygons, Arvo's
edge-sum structure), for non-integer $n$ (and for $\cos^m$ tubes) composite 24-point
Gauss-Legendre quadrature on panels graded geometrically about the lobe peak (and the tube
peak and $|u| = \pi/2$). For integer $n$ the value comes from the recurrence and the
derivatives (any order, forward and reverse, including $\partial/\partial n$) from the
quadrature, which agrees with it to about 1e-13. The exact method is a reference: about 150-250
times slower than the Chebyshev default (benchmarks/specular_error.py).
"""

from __future__ import annotations

import functools
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.scipy.special import gammaln
from jaxtyping import Array, ArrayLike, Float

from .._core.geometry import horizon_clip_edges, on_lit_side
from .._core.misc import safe_norm, safe_normalize
from .chebyshev import cutoff_angle, even_fit_integral, interval_fit_integral

Method = Literal["chebyshev", "exact"]

#: Default Chebyshev degree and cut-off tolerance, from benchmarks/specular_error.py (1024
#: random configurations per light kind, n in {1, 5, 20, 100, 1000, 10000}, error relative to
#: max(S_exact, 1e-3 max S)): worst error 8.2e-6 (polygon) and 4.5e-7 (segment) at 1.17x and
#: 1.34x the time of Poulin's degree 6, epsilon = 1/250 (whose worst errors are 6.9e-3 and
#: 2.5e-3). Degree 10 misses 1e-4 on polygons (2.0e-4 at n = 10^4); tol 1e-4 stalls at 8.3e-5.
DEFAULT_DEGREE = 12
#: Largest Chebyshev degree: the fit's constant matrices and the traced program grow with the
#: degree (quadratically), and degree 12 already reaches ~1e-5 (above: no gain in float64).
MAX_DEGREE = 64
DEFAULT_TOL = 1e-6

# Exact method: Gauss-Legendre nodes per panel, number of geometric panels per side of a peak,
# and the largest integer exponent handled by the recurrence (above: quadrature).
_QUAD_NODES = 24
_QUAD_LEVELS = 15
_RECURRENCE_MAX = 1e5


def _check_method(method: str, degree: int) -> None:
    if method not in ("chebyshev", "exact"):
        raise ValueError(f"method must be 'chebyshev' or 'exact', got {method!r}.")
    if isinstance(degree, bool) or not isinstance(degree, int) or not 2 <= degree <= MAX_DEGREE:
        raise ValueError(f"degree must be a Python int in [2, {MAX_DEGREE}], got {degree!r}.")


def reflected_direction(
    p: Float[Array, "3"], n: Float[Array, "3"], eye: Float[Array, "3"]
) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    r"""Unit normal $N$ and the mirror direction $R = 2(N\cdot V)N - V$ of the eye about $N$."""
    nn = safe_normalize(n)
    v = safe_normalize(eye - p)
    return nn, 2.0 * jnp.dot(nn, v) * nn - v


def _pos_pow(c: Array, e: Array) -> Array:
    """`max(0, c) ** e` for real `e > 0`, NaN-free in value and gradient (also w.r.t. `e`)."""
    ok = c > 0
    cs = jnp.where(ok, c, 1.0)
    return jnp.where(ok, jnp.exp(e * jnp.log(cs)), 0.0)


# --------------------------------------------------------------------------------------
# Arc frame and the pieces of an edge integral
# --------------------------------------------------------------------------------------


def _arc_frame(R: Array, a: Array, b: Array):
    r"""Frame of the great-circle arc `a -> b` (directions from the receiver, any length).

    Returns `ok` (False for a zero-length edge or an edge whose line passes through the
    receiver), $s = R\cdot\hat m$, $\rho = |R - s\hat m|$, the arc's limits `ua <= ub`
    (arc length from the point closest to $R$; the arc contains $u = 0$ iff that point lies on
    it), the in-plane basis `e1, e2` and $|a \times b|$.
    """
    m = jnp.cross(a, b)
    ok = jnp.sum(m * m) > 0
    one = jnp.ones((), dtype=a.dtype)
    zero = jnp.zeros((), dtype=a.dtype)
    a = jnp.where(ok, a, jnp.stack([one, zero, zero]))
    b = jnp.where(ok, b, jnp.stack([zero, one, zero]))
    m = jnp.cross(a, b)
    m_len = jnp.sqrt(jnp.sum(m * m))
    m_hat = m / m_len
    s = jnp.dot(R, m_hat)
    # In-plane direction of R as m x (R x m): orthogonal to m to working precision even when R
    # is nearly normal to the arc's plane (R - s m is then rounding noise in any direction).
    q = jnp.cross(R, m_hat)
    rho = safe_norm(q)
    has_rho = rho > 0
    e1 = jnp.where(
        has_rho,
        jnp.cross(m_hat, q) / jnp.where(has_rho, rho, 1.0),
        a / jnp.sqrt(jnp.sum(a * a)),
    )
    e2 = jnp.cross(m_hat, e1)
    ua = jnp.arctan2(jnp.dot(a, e2), jnp.dot(a, e1))
    # The arc runs from ua up by its length atan2(|a x b|, a . b) in [0, pi], taken from the
    # cross product that orients it: an angle of b computed on its own can fall a rounding
    # error below ua for an edge of round-off length (the shadow code's edge soups hold such
    # edges), which would read as an arc around the whole circle.
    ub = ua + jnp.arctan2(m_len, jnp.dot(a, b))
    # Of the representatives, the one whose midpoint lies in [-pi, pi]: u = 0 is on the arc
    # iff it should be.
    over = (ua + ub) > 2.0 * np.pi
    ua = ua - jnp.where(over, 2.0 * np.pi, 0.0)
    ub = ub - jnp.where(over, 2.0 * np.pi, 0.0)
    return ok, s, rho, ua, ub, e1, e2, m_len, a, b


def _azimuth_change(s: Array, rho: Array, u1: Array, u2: Array) -> Array:
    r"""Signed change of azimuth about $R$ along the arc from $u_1$ to $u_2$ (length $< \pi$).

    $\operatorname{atan2}(R\cdot(w_1\times w_2),\ w_1\cdot w_2 - (w_1\cdot R)(w_2\cdot R))$.
    """
    return jnp.arctan2(
        s * jnp.sin(u2 - u1), jnp.cos(u2 - u1) - rho * rho * jnp.cos(u1) * jnp.cos(u2)
    )


def _split_arc(ua: Array, ub: Array, x: Array):
    """`[ua, ub]` = outer piece below `-x` + inner `[lo, hi]` + outer piece above `x`.

    Empty pieces collapse onto `-x` / `x` (zero length, away from `u = 0`).
    """
    lo = jnp.clip(ua, -x, x)
    hi = jnp.clip(ub, -x, x)
    below = ua < -x
    p1 = (jnp.where(below, ua, -x), jnp.where(below, jnp.minimum(ub, -x), -x))
    above = ub > x
    p2 = (jnp.where(above, jnp.maximum(ua, x), x), jnp.where(above, ub, x))
    return lo, hi, p1, p2


def _lobe_edge_integrand(s: Array, k: Array, u: Array) -> Array:
    r"""$s\,(1 - c^k)/(1 - c^2)$ with $c = \rho\cos u \ge 0$ (needs $|u| \le \pi/2$).

    Uses $1 - c^2 = \sin^2 u + s^2\cos^2 u$ (exact for unit $R$, no cancellation) and
    `expm1`/`log1p`; the removable singularity at $c = 1$ (lobe peak on the edge) is $k/2$.
    """
    cu = jnp.cos(u)
    su = jnp.sin(u)
    delta = su * su + s * s * cu * cu
    gen = (delta > 0) & (delta < 1)
    d = jnp.where(gen, delta, 0.5)
    val = -jnp.expm1(0.5 * k * jnp.log1p(-d)) / d
    pos = delta > 0
    far = 1.0 / jnp.where(pos, delta, 1.0)  # c = 0: (1 - 0) / (1 - 0)
    return s * jnp.where(gen, val, jnp.where(pos, far, 0.5 * k))


# --------------------------------------------------------------------------------------
# Exact 1-D integrals: recurrence (integer exponents) and graded Gauss quadrature
# --------------------------------------------------------------------------------------


def _cos_power_recurrence(lo, hi, rho, j0, jmax):
    r"""$C_J$ and $\sum_{j = j_0, j_0 + 2, \ldots \le j_{max}} \rho^j C_j$, $C_j = \int_{lo}^{hi}\cos^j$.

    Forward recurrence $C_j = [\cos^{j-1}u\sin u]_{lo}^{hi}/j + \frac{j-1}{j}C_{j-2}$ (stable:
    the factor $(j-1)/j < 1$ damps errors). `j0` in {0, 1}; for `jmax < j0` the sum is 0.
    """
    cl, sl, ch, sh = jnp.cos(lo), jnp.sin(lo), jnp.cos(hi), jnp.sin(hi)
    even = j0 == 0
    c0 = jnp.where(even, hi - lo, sh - sl)
    ph = jnp.where(even, ch * sh, ch * ch * sh)  # cos^{j+1} sin at j = j0
    pl = jnp.where(even, cl * sl, cl * cl * sl)
    rp = jnp.where(even, jnp.ones_like(rho), rho)
    acc = jnp.where(j0 <= jmax, rp * c0, 0.0)

    def cond(state):
        j = state[0]
        return j + 2 <= jmax

    def body(state):
        j, c, ph, pl, rp, acc = state
        j2 = j + 2
        c = (ph - pl) / j2 + (j2 - 1) / j2 * c
        ph = ph * ch * ch
        pl = pl * cl * cl
        rp = rp * rho * rho
        return j2, c, ph, pl, rp, acc + rp * c

    state = (j0, c0, ph, pl, rp, acc)
    _, c, _, _, _, acc = lax.while_loop(cond, body, state)
    return c, acc


def _graded_quadrature(f, lo, hi, peaks):
    """`∫_lo^hi f` by Gauss-Legendre on panels graded geometrically about each `(centre, width)`
    of `peaks` and towards `u = ±pi/2`; `f` is elementwise."""
    dtype = lo.dtype
    pts = [lo, hi]
    for centre, width in peaks:
        for j in range(_QUAD_LEVELS):
            pts += [centre + width * 2.0**j, centre - width * 2.0**j]
        pts.append(centre)
    half_pi = np.pi / 2
    for j in range(1, 13):
        pts += [
            jnp.asarray(half_pi * (1 - 2.0**-j), dtype),
            jnp.asarray(-half_pi * (1 - 2.0**-j), dtype),
        ]
    pts = jnp.sort(jnp.clip(jnp.stack([jnp.asarray(q, dtype) for q in pts]), lo, hi))
    a, b = pts[:-1], pts[1:]
    x, w = np.polynomial.legendre.leggauss(_QUAD_NODES)
    mid = (a + b) / 2.0
    half = (b - a) / 2.0
    u = mid[:, None] + half[:, None] * jnp.asarray(x, dtype)[None, :]
    return jnp.sum(half[:, None] * jnp.asarray(w, dtype)[None, :] * f(u))


def _leibniz_quadrature(integrand, params, lo, hi, peaks):
    r"""$\int_{lo}^{hi} g(u; \theta)\,du$ by `_graded_quadrature`, differentiated by Leibniz's rule.

    `integrand(params, u)` is $g$, elementwise in `u`; `params` a pytree of arrays. The value is
    the graded quadrature's; the derivative is $g(hi)\,\dot{hi} - g(lo)\,\dot{lo} + \int
    \partial_\theta g\,\dot\theta$, the last integral again by this rule (so derivatives of every
    order are Leibniz's). Differentiating the quadrature rule itself would move its nodes with the
    limits, an approximation of the same order as the rule only: at a receiver whose light
    crosses its horizon the integrand is steep at a limit and the derivative was off by orders of
    magnitude while the value was right. Node placement (`peaks`) carries no derivative."""
    peaks = tuple((lax.stop_gradient(c), lax.stop_gradient(w)) for c, w in peaks)
    return _leibniz(integrand, params, lo, hi, peaks)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _leibniz(integrand, params, lo, hi, peaks):
    return _graded_quadrature(lambda u: integrand(params, u), lo, hi, peaks)


def _tangent_integrand(integrand, pair, u):
    params, dparams = pair
    return jax.jvp(lambda q: integrand(q, u), (params,), (dparams,))[1]


@_leibniz.defjvp
def _leibniz_jvp(integrand, primals, tangents):
    params, lo, hi, peaks = primals
    dparams, dlo, dhi, _ = tangents
    value = _leibniz(integrand, params, lo, hi, peaks)
    interior = _leibniz(functools.partial(_tangent_integrand, integrand), (params, dparams), lo, hi, peaks)
    return value, interior + integrand(params, hi) * dhi - integrand(params, lo) * dlo


def _is_recurrence_exponent(e: Array) -> Array:
    return (e == jnp.round(e)) & (e >= 0) & (e <= _RECURRENCE_MAX)


def _lobe_edge_exact(s, rho, k, lo, hi):
    r"""$\int_{lo}^{hi} s\,(1 - c^k)/(1 - c^2)\,du$, $[lo, hi] \subset [-\pi/2, \pi/2]$, exactly."""
    use_rec = _is_recurrence_exponent(k)
    # The recurrence gives the value only (no tangents may enter its while_loop).
    s0, rho0, k0, lo0, hi0 = (lax.stop_gradient(x) for x in (s, rho, k, lo, hi))
    kk = jnp.where(use_rec, k0, 1.0)
    j0 = jnp.where(jnp.fmod(kk, 2.0) == 0, 0.0, 1.0).astype(lo.dtype)
    # k odd: the base case I_1 = ∫ du / (1 + rho cos u), times s.
    t = s0 / (1.0 + rho0)
    base = 2.0 * (jnp.arctan(t * jnp.tan(hi0 / 2.0)) - jnp.arctan(t * jnp.tan(lo0 / 2.0)))
    _, sums = _cos_power_recurrence(lo0, hi0, rho0, j0, jnp.where(use_rec, kk - 2.0, -1.0))
    rec = jnp.where(j0 == 1, base, 0.0) + s0 * sums
    width = 0.25 / jnp.sqrt(k)
    quad = _leibniz_quadrature(
        lambda q, u: _lobe_edge_integrand(q[0], q[1], u), (s, k), lo, hi, [(jnp.zeros_like(lo), width)]
    )
    return jnp.where(use_rec, _value_of_with_derivatives_of(rec, quad), quad)


def _value_of_with_derivatives_of(value: Array, smooth: Array) -> Array:
    """`value`, differentiated as `smooth` (equal to it to ~1e-13).

    The recurrence is exact but piecewise in n (its loop count) and a `while_loop`, which
    reverse mode cannot differentiate; the graded quadrature is smooth in every input.
    """
    return lax.stop_gradient(value) + (smooth - lax.stop_gradient(smooth))


# --------------------------------------------------------------------------------------
# Kernels: one receiver, one light
# --------------------------------------------------------------------------------------


def contour_specular_kernel(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    eye: Float[Array, "3"],
    starts: Float[Array, "e 3"],
    ends: Float[Array, "e 3"],
    exponent: Float[Array, ""],
    *,
    method: Method = "chebyshev",
    degree: int = DEFAULT_DEGREE,
    tol: float = DEFAULT_TOL,
) -> Float[Array, ""]:
    r"""Phong-lobe integral per unit radiance of a planar region given by its boundary.

    The edge soup must already lie above the receiver's horizon and run counter-clockwise seen
    from the receiver (the contract of `_polygon.contour_form_factor`; e.g. the output of
    `horizon_clip_edges` or of the shadow code's `visible_edges`). Zero-length edges
    (`start == end`) contribute exactly 0. Arguments and result as `polygon_specular_kernel`.
    """
    sums = contour_specular_sums(p, n, eye, starts, ends, exponent, method=method, degree=degree, tol=tol)
    return contour_specular_total(p, n, eye, sums)


def contour_specular_sums(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    eye: Float[Array, "3"],
    starts: Float[Array, "e 3"],
    ends: Float[Array, "e 3"],
    exponent: Float[Array, ""],
    *,
    method: Method = "chebyshev",
    degree: int = DEFAULT_DEGREE,
    tol: float = DEFAULT_TOL,
) -> tuple[Array, Array]:
    """The two sums over an edge soup that `contour_specular_kernel` takes: the edge terms of
    the polar sweep about the reflected direction and the edges' changes of azimuth about it (no
    gradient). Sums over parts of a soup add up to the whole soup's (`contour_specular_total`)."""
    _check_method(method, degree)
    _, R = reflected_direction(p, n, eye)
    k = exponent + 1.0
    if method == "chebyshev":
        x_cut = cutoff_angle(k, tol)
    else:
        x_cut = jnp.asarray(np.pi / 2, dtype=p.dtype)

    def edge(a, b):
        ok, s, rho, ua, ub, *_ = _arc_frame(R, a, b)
        ok = ok & jnp.any(a != b)
        lo, hi, p1, p2 = _split_arc(ua, ub, x_cut)
        outer = jnp.sum(
            _azimuth_change(s, rho, jnp.stack([p1[0], p2[0]]), jnp.stack([p1[1], p2[1]]))
        )
        if method == "chebyshev":
            inner = even_fit_integral(
                lambda u: _lobe_edge_integrand(s, k, u), x_cut, lo, hi, degree
            )
        else:
            inner = _lobe_edge_exact(s, rho, k, lo, hi)
        turn = _azimuth_change(s, rho, ua, ub)  # the whole arc's change of azimuth about R
        return jnp.where(ok, outer + inner, 0.0), jnp.where(ok, turn, 0.0)

    terms, turns = jax.vmap(edge)(starts - p[None, :], ends - p[None, :])
    return jnp.sum(terms), lax.stop_gradient(jnp.sum(turns))


def contour_specular_total(
    p: Float[Array, "3"], n: Float[Array, "3"], eye: Float[Array, "3"], sums: tuple[Array, Array]
) -> Float[Array, ""]:
    """`contour_specular_kernel` from its soup's `contour_specular_sums`."""
    terms, turns = sums
    nn, R = reflected_direction(p, n, eye)
    # The polar sweep about R counts a region winding once about the R axis as containing R. A
    # region above the horizon can contain R only when R is (R . N = N . V > 0); when the eye
    # is behind the tangent plane a winding region contains -R instead, where the lobe is 0:
    # the sweep then gives (true value - 1), so add the winding back (piecewise constant).
    winding = jnp.round(turns / (2.0 * np.pi))
    minus_r_inside = jnp.where(jnp.dot(nn, R) < 0, winding, 0.0)
    return -terms / (2.0 * np.pi) + minus_r_inside


def polygon_specular_kernel(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    eye: Float[Array, "3"],
    verts: Float[Array, "k 3"],
    exponent: Float[Array, ""],
    *,
    method: Method = "chebyshev",
    degree: int = DEFAULT_DEGREE,
    tol: float = DEFAULT_TOL,
) -> Float[Array, ""]:
    r"""Phong-lobe integral of a polygon light per unit radiance (Poulin eq. 3.12).

    $S / L = \frac{n+1}{2\pi}\int_{\Omega} \max(0, w\cdot R)^n\,dw$ over the polygon clipped
    exactly to the receiver's horizon; 0 behind the emitter. The per-edge terms are Poulin's
    $(\beta_B-\beta_A) - (H(\alpha,\beta_B) - H(\alpha,\beta_A))$ written in arc length (module
    docstring).

    **Arguments:** `p (3,)` receiver, `n (3,)` normal (normalised here), `eye (3,)` eye position,
    `verts (K, 3)` padded convex polygon (counter-clockwise seen from its lit side), `exponent`
    Phong $n \ge 1$ (array; differentiable); static `method`, `degree`, `tol` (cut-off
    tolerance $\epsilon$ of the Chebyshev method: the lobe is dropped where
    $\cos^{n+1} < \epsilon$).

    **Returns:** dimensionless $S/L \in [0, 1]$.
    """
    in_front = on_lit_side(p, verts)
    starts, ends = horizon_clip_edges(p, safe_normalize(n), verts)
    s = contour_specular_kernel(
        p, n, eye, starts, ends, exponent, method=method, degree=degree, tol=tol
    )
    return jnp.where(in_front, s, 0.0)


def _profile_norm(m: Array) -> Array:
    r"""$1 / (2\pi W(m+1))$, $W(k) = \int_{-\pi/2}^{\pi/2}\cos^k = \sqrt\pi\,\Gamma(\frac{k+1}{2})/\Gamma(\frac k2 + 1)$."""
    k = m + 1.0
    log_w = 0.5 * float(np.log(np.pi)) + gammaln((k + 1.0) / 2.0) - gammaln(k / 2.0 + 1.0)
    return jnp.exp(-log_w) / (2.0 * np.pi)


def segment_specular_kernel(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    eye: Float[Array, "3"],
    start: Float[Array, "3"],
    end: Float[Array, "3"],
    exponent: Float[Array, ""],
    profile_exponent: Float[Array, ""] | None = None,
    *,
    method: Method = "chebyshev",
    degree: int = DEFAULT_DEGREE,
    tol: float = DEFAULT_TOL,
) -> Float[Array, ""]:
    r"""Phong-lobe integral of a segment light per unit power per length (Poulin eq. 3.11, §3.2.2).

    $S/\Phi = \int \frac{I(\beta)}{\Phi}\,\frac{n+1}{2\pi}\,\frac{\max(0, \hat w\cdot R)^n}{r^2}\,dl$
    over the part of the segment above the receiver's tangent plane (cut exactly, and cut to
    $\hat w\cdot R > 0$, Poulin §4.3.1). Isotropic profile (`profile_exponent=None`):
    $I/\Phi = 1/(4\pi)$; cosine tube: $I(\beta)/\Phi = \cos^m\beta / (2\pi W(m+1))$, $\beta$ from
    the plane perpendicular to the segment. A receiver on the segment's supporting line (outside
    it) sees all of it in one direction: $\int dl/r^2 = |1/r_a - 1/r_b|$ (Poulin's special case;
    $\beta = \pi/2$ there, so a tube with $m > 0$ gives 0).

    **Arguments:** `p, n, eye (3,)` as for `polygon_specular_kernel`; `start, end (3,)` the
    segment (m); `exponent` Phong $n \ge 1$; `profile_exponent` $m \ge 0$ or `None` (static
    choice of the profile; the value is a differentiable array).

    **Returns:** $S/\Phi$ in 1/m.
    """
    _check_method(method, degree)
    nn, R = reflected_direction(p, n, eye)
    starts, ends = horizon_clip_edges(p, nn, jnp.stack([start, end]))
    a0 = starts[0] - p
    b0 = ends[0] - p
    ok, s, rho, ua, ub, e1, e2, m_len, a, b = _arc_frame(R, a0, b0)
    # With fused multiply-adds a x a need not round to 0: a zero-length segment (the padding of
    # the shadow code's visible sub-segments) would pass `_arc_frame` with ab2 = 0.
    ok = ok & jnp.any(a0 != b0)
    half_pi = jnp.asarray(np.pi / 2, dtype=p.dtype)
    if method == "chebyshev":
        # Cut-off relative to the largest cos^n on the arc (at the arc's point closest to the
        # peak), so that an arc in the lobe's tail keeps its relative accuracy.
        u_near = jnp.minimum(jnp.abs(jnp.clip(0.0, ua, ub)), half_pi)
        x_cut = jnp.minimum(cutoff_angle(exponent, tol, u_near), half_pi)
    else:
        x_cut = half_pi
    lo, hi, _, _ = _split_arc(ua, ub, x_cut)
    ab = b - a
    ab2 = jnp.where(ok, jnp.sum(ab * ab), 1.0)
    dist = m_len / jnp.sqrt(ab2)
    lobe_n = (exponent + 1.0) / (2.0 * np.pi)
    peak_width = 0.25 / jnp.sqrt(exponent + 1.0)

    if profile_exponent is None:
        norm = 1.0 / (4.0 * np.pi)
        online_profile = norm

        def f(u):
            return _pos_pow(jnp.cos(u), exponent)

        if method == "exact":
            use_rec = _is_recurrence_exponent(exponent)
            ne = jnp.where(use_rec, lax.stop_gradient(exponent), 1.0)
            j0 = jnp.where(jnp.fmod(ne, 2.0) == 0, 0.0, 1.0).astype(lo.dtype)
            lo0, hi0 = lax.stop_gradient(lo), lax.stop_gradient(hi)
            rec, _ = _cos_power_recurrence(lo0, hi0, rho, j0, jnp.where(use_rec, ne, 1.0))
            quad = _leibniz_quadrature(lambda q, u: _pos_pow(jnp.cos(u), q), exponent, lo, hi,
                                       [(jnp.zeros_like(lo), peak_width)])
            integral = jnp.where(use_rec, _value_of_with_derivatives_of(rec, quad), quad)
    else:
        m = profile_exponent
        norm = _profile_norm(m)
        # On the supporting line beta = pi/2: cos^m(beta) = 0 for m > 0, 1 for m = 0.
        online_profile = norm * jnp.where(m == 0, 1.0, 0.0)
        foot = a - jnp.dot(a, ab) / ab2 * ab
        u_foot = jnp.arctan2(jnp.dot(foot, e2), jnp.dot(foot, e1))

        def f(u):
            return _pos_pow(jnp.cos(u), exponent) * _pos_pow(jnp.cos(u - u_foot), m)

        if method == "exact":
            peaks = [(jnp.zeros_like(lo), peak_width), (u_foot, 0.25 / jnp.sqrt(m + 1.0))]
            integral = _leibniz_quadrature(
                lambda q, u: _pos_pow(jnp.cos(u), q[0]) * _pos_pow(jnp.cos(u - q[1]), q[2]), (exponent, u_foot, m),
                lo, hi, peaks)
    if method == "chebyshev":
        # The interval may hold the peak off-centre: degree 2 D (Poulin's "product of two
        # polynomials" for the cos^m profile).
        integral = interval_fit_integral(f, lo, hi, 2 * degree)

    generic = norm * lobe_n * _pos_pow(rho, exponent) / dist * integral
    generic = jnp.where(ok, generic, 0.0)

    # Receiver on the supporting line, outside the segment (and the clipped segment not empty).
    ra2 = jnp.sum(a0 * a0)
    rb2 = jnp.sum(b0 * b0)
    on_line = (~ok) & (ra2 > 0) & (rb2 > 0) & (jnp.dot(a0, b0) > 0) & (jnp.sum((b0 - a0) ** 2) > 0)
    ra = jnp.sqrt(jnp.where(on_line, ra2, 1.0))
    rb = jnp.sqrt(jnp.where(on_line, rb2, 1.0))
    w = jnp.where(on_line, a0, R) / ra
    line = (
        online_profile * lobe_n * _pos_pow(jnp.dot(w, R), exponent) * jnp.abs(1.0 / ra - 1.0 / rb)
    )
    return jnp.where(on_line, line, generic)


def point_specular_kernel(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    eye: Float[Array, "3"],
    position: Float[Array, "3"],
    exponent: Float[Array, ""],
) -> Float[Array, ""]:
    r"""Phong lobe of a point light per unit intensity: $\frac{n+1}{2\pi}\max(0,\hat w\cdot R)^n / r^2$.

    0 below the receiver's horizon and for a light at the receiver. **Returns:** 1/m².
    """
    nn, R = reflected_direction(p, n, eye)
    d = position - p
    r2 = jnp.sum(d * d)
    ok = r2 > 0
    r2s = jnp.where(ok, r2, 1.0)
    w = d / jnp.sqrt(r2s)
    above = ok & (jnp.dot(nn, w) > 0)
    val = (exponent + 1.0) / (2.0 * np.pi) * _pos_pow(jnp.dot(w, R), exponent) / r2s
    return jnp.where(above, val, 0.0)


def directional_specular_kernel(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    eye: Float[Array, "3"],
    direction: Float[Array, "3"],
    exponent: Float[Array, ""],
) -> Float[Array, ""]:
    r"""Phong lobe of a directional light per unit irradiance: $\frac{n+1}{2\pi}\max(0,-\hat d\cdot R)^n$.

    `direction` is the direction the light travels; 0 when $-\hat d$ is below the horizon.
    """
    nn, R = reflected_direction(p, n, eye)
    w = -safe_normalize(direction)
    above = jnp.dot(nn, w) > 0
    val = (exponent + 1.0) / (2.0 * np.pi) * _pos_pow(jnp.dot(w, R), exponent)
    return jnp.where(above, val, 0.0)


# --------------------------------------------------------------------------------------
# Simple batched helpers (tests, benchmarks); the scene-level API lives in _shade.py
# --------------------------------------------------------------------------------------


def _eyes(eye: Array, points: Array) -> Array:
    eye = jnp.asarray(eye)
    if eye.ndim == 1:
        return jnp.broadcast_to(eye, points.shape)
    if eye.shape != points.shape:
        raise ValueError(f"eye must have shape (3,) or {points.shape}, got {eye.shape}.")
    return eye


@eqx.filter_jit
def polygon_specular(
    points: Float[ArrayLike, "N 3"],
    normals: Float[ArrayLike, "N 3"],
    eye: Float[ArrayLike, "3"] | Float[ArrayLike, "N 3"],
    vertices: Float[ArrayLike, "k 3"],
    radiance: Float[ArrayLike, ""],
    exponent: Float[ArrayLike, ""],
    *,
    method: Method = "chebyshev",
    degree: int = DEFAULT_DEGREE,
    tol: float = DEFAULT_TOL,
) -> Float[Array, " N"]:
    """Specular integral $S$ of one polygon light of scalar radiance at `N` receivers."""
    points = jnp.asarray(points)
    kern = lambda p, n, e: polygon_specular_kernel(
        p, n, e, vertices, exponent, method=method, degree=degree, tol=tol
    )
    return radiance * jax.vmap(kern)(points, jnp.asarray(normals), _eyes(eye, points))


# The batch signature of `polygon_specular`, for a segment light (the same shape on purpose).
@eqx.filter_jit
def segment_specular(
    points: Float[ArrayLike, "N 3"],
    normals: Float[ArrayLike, "N 3"],
    eye: Float[ArrayLike, "3"] | Float[ArrayLike, "N 3"],
    start: Float[ArrayLike, "3"],
    end: Float[ArrayLike, "3"],
    power: Float[ArrayLike, ""],
    exponent: Float[ArrayLike, ""],
    profile_exponent: Float[ArrayLike, ""] | None = None,
    *,
    method: Method = "chebyshev",
    degree: int = DEFAULT_DEGREE,
    tol: float = DEFAULT_TOL,
) -> Float[Array, " N"]:
    """Specular integral $S$ of one segment light (power per length `power`) at `N` receivers;
    `profile_exponent=None` for the isotropic profile, else the cosine tube exponent $m$."""
    points = jnp.asarray(points)
    kern = lambda p, n, e: segment_specular_kernel(
        p, n, e, start, end, exponent, profile_exponent, method=method, degree=degree, tol=tol
    )
    return power * jax.vmap(kern)(points, jnp.asarray(normals), _eyes(eye, points))


@eqx.filter_jit
def point_specular(
    points: Float[ArrayLike, "N 3"],
    normals: Float[ArrayLike, "N 3"],
    eye: Float[ArrayLike, "3"] | Float[ArrayLike, "N 3"],
    position: Float[ArrayLike, "3"],
    intensity: Float[ArrayLike, ""],
    exponent: Float[ArrayLike, ""],
) -> Float[Array, " N"]:
    """Specular term $S$ of one point light of scalar intensity at `N` receivers."""
    points = jnp.asarray(points)
    kern = lambda p, n, e: point_specular_kernel(p, n, e, position, exponent)
    return intensity * jax.vmap(kern)(points, jnp.asarray(normals), _eyes(eye, points))


@eqx.filter_jit
def directional_specular(
    points: Float[ArrayLike, "N 3"],
    normals: Float[ArrayLike, "N 3"],
    eye: Float[ArrayLike, "3"] | Float[ArrayLike, "N 3"],
    direction: Float[ArrayLike, "3"],
    irradiance: Float[ArrayLike, ""],
    exponent: Float[ArrayLike, ""],
) -> Float[Array, " N"]:
    """Specular term $S$ of one directional light of scalar irradiance at `N` receivers."""
    points = jnp.asarray(points)
    kern = lambda p, n, e: directional_specular_kernel(p, n, e, direction, exponent)
    return irradiance * jax.vmap(kern)(points, jnp.asarray(normals), _eyes(eye, points))
