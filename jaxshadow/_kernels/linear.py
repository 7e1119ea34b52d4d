r"""Linear (segment) lights: diffuse irradiance in closed form (Poulin §3.2.1.1, eq. 3.10; §3.2.2).

Work in Poulin's 2-D frame: $Q$ is the foot of the receiver $p$ on the supporting line,
$h = Q - p$, $d = |h|$, $u$ the unit direction of the segment and $t$ the signed position of a
point $X(t) = Q + t u$ along the line, $r^2 = d^2 + t^2$. With $\cos\beta = d / r$ ($\beta$
measured from the plane perpendicular to the segment) and the per-length intensity
$I(\beta) = C_m \Phi \cos^m\beta$,

$$E = C_m \Phi \int \frac{d^m}{r^m} \frac{N\cdot h + t\,N\cdot u}{r^3}\,dt
    = C_m \Phi \Big[\frac{N\cdot h}{d^2} J_{m+1}
      + N\cdot u\, d^m \frac{r_A^{-(m+1)} - r_B^{-(m+1)}}{m+1}\Big],
\qquad J_k = \int_{\phi_A}^{\phi_B} \cos^k\phi\,d\phi,$$

which for $m = 0$ is eq. 3.10 ($C_0 = 1/4\pi$; Poulin projects $N$ onto the plane of the
light and the point, $N\cdot N_p \cos\phi$ being our $(N\cdot h + t\,N\cdot u)/r$) and for
$m = 1$ is the cosine-distributed tube of §3.2.2. $J_k$ follows the standard reduction
$J_k = [\cos^{k-1}\phi \sin\phi]/k + (k-1)/k\, J_{k-2}$ with $\cos\phi = d/r$, $\sin\phi = t/r$,
so any integer $m \ge 0$ is exact (closed form) up to `MAX_COSINE_EXPONENT` (above: a
build-time error); non-integer $m$ is rejected at build time.

The normalisation $C_m = 1 / (2\pi W_{m+1})$, $W_k = \int_{-\pi/2}^{\pi/2}\cos^k$, makes every
profile emit the same power $\Phi$ per unit length (DESIGN.md).

Numerics. $J_1 / d^2 = (t_B/r_B - t_A/r_A)/d^2$ is rewritten as
$(t_B - t_A)(t_B + t_A) / ((t_B r_A + t_A r_B) r_A r_B)$ when the foot of $p$ is outside the
segment, so a receiver on (or near) the supporting line is exact and smooth: that is Poulin's
"on the supporting line" special case, $\int_0^{\mathcal L} (N\cdot L)/(l+b)^2 dl$, as a limit
rather than a branch. A receiver *on* the segment gets $+\infty$ (the integral diverges) with a
zero gradient. The segment is clipped exactly to the receiver's horizon first.
For $m \ge 1$ the same $E$ is evaluated as
$$E = \frac{C_m \Phi}{d}\Big[\frac{N\cdot h}{d} J_{m+1}
      + N\cdot u\,\frac{c_A^{m+1} - c_B^{m+1}}{m+1}\Big],\qquad c = \frac{d}{r},\ s = \frac{t}{r},$$
(since $d^m r^{-(m+1)} = c^{m+1}/d$), with $J_{m+1}$ reduced in $c$ and $s$ only
($[c^{k-1}s]_A^B / k$, $J_1 = s_B - s_A$, $J_0 = \operatorname{atan2}$ of $\sin$ and $\cos$ of
$\phi_B - \phi_A$), $s_B - s_A = c_A c_B (t_B - t_A)(t_B + t_A)/(t_B r_A + t_A r_B)$ when the
foot is outside the segment and $c_A - c_B = c_A (t_B - t_A)(t_B + t_A) / (r_B (r_A + r_B))$
(no cancellation). Everything inside the bracket is a ratio of order one and the only
dimensional factor is the overall $1/d$, so neither the value nor its derivatives overflow in
float32 at small or large scene scales (the direct $r^{-(m+1)}$, about $10^{30}$ at a scale of
$10^{-6}$ for $m = 4$, overflowed in its derivative; the $m = 0$ quotient above is likewise
grouped as $\frac{t_B - t_A}{r_A}\,\frac{t_B + t_A}{r_B} / (t_B r_A + t_A r_B)$). A receiver on the supporting line ($d = 0$) gets the
limit $E = 0$ for $m \ge 1$ (no emission along the axis).
"""

from __future__ import annotations

import functools
import math
from typing import Any, no_type_check

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._core.geometry import (
    check_finite_leaves,
    check_points_normals,
    check_vector3,
    evaluate_checked,
    inputs_ok,
    is_concrete,
)
from .._core.misc import arctan2, fusible, safe_norm, unit_rows

#: Largest exponent of the cosine profile. The kernel's cost grows linearly with m (two
#: recurrences of about m/2 and m steps per receiver); a cos^m beam has its half-power
#: half-width at about 1.18/sqrt(m) rad (2.1 degrees at m = 1000): larger m is a laser, not a
#: tube light. Checked when a `LinearLight` is built and by `linear_irradiance`.
MAX_COSINE_EXPONENT = 1000
#: Up to this m the recurrences are unrolled (fused into one loop by XLA); above, `fori_loop`.
UNROLL_MAX_EXPONENT = 16


def check_profile_exponent(m: Any, what: str, minimum: int = 0) -> int:
    """The profile exponent as a Python int, or a `ValueError` (not an integer, below `minimum`,
    above `MAX_COSINE_EXPONENT`)."""
    ok = isinstance(m, (int, float, np.integer, np.floating)) and not isinstance(m, bool)
    if not ok or not np.isfinite(m) or float(m) != int(m) or int(m) < minimum:
        raise ValueError(
            f"{what} must be an integer >= {minimum} (closed form per integer m), got {m!r}."
        )
    if int(m) > MAX_COSINE_EXPONENT:
        raise ValueError(
            f"{what} = {m!r} is above the supported maximum {MAX_COSINE_EXPONENT} (the cost "
            "grows linearly with m, and a beam narrower than ~2 degrees is not a tube light)."
        )
    return int(m)


def cosine_profile_constant(m: int) -> float:
    r"""$C_m = 1/(2\pi W_{m+1})$ with $W_k = \sqrt\pi\,\Gamma(\tfrac{k+1}{2})/\Gamma(\tfrac{k}{2}+1)$."""
    k = m + 1
    w = math.sqrt(math.pi) * math.exp(math.lgamma((k + 1) / 2) - math.lgamma(k / 2 + 1))
    return 1.0 / (2.0 * math.pi * w)


def _dot3(x, y):
    """`x . y` for 3-vectors as an elementwise expression: after `vmap` XLA:CPU fuses it into
    the surrounding loop (a `dot` of `(N, 3)` by `(3,)` is a separate library call)."""
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def segment_frame(p, a, b):
    r"""Poulin's 2-D frame of a segment seen from `p`: `(h, u, tA, tB)` with `X(t) = p + h + t u`.

    Light-relative: `tA` and `tB` are each measured from their own endpoint, and `h` from the
    endpoint nearer to the foot of `p`. Computing `tB` as `tA + length` lost it to the rounding
    of `tA` when `p` is close to `b` (float32, `p` 1e-7 past the end: $E \sim 1/|t_B|$ came
    out 2-90x too high); `h` taken from the far endpoint likewise carried its rounding."""
    e = b - a
    length = safe_norm(e)
    u = e / jnp.where(length > 0, length, 1.0)
    wa = a - p
    wb = b - p
    ta = _dot3(wa, u)
    tb = _dot3(wb, u)
    near_a = jnp.abs(ta) <= jnp.abs(tb)
    h = jnp.where(near_a, wa - ta * u, wb - tb * u)
    return h, u, ta, tb


def horizon_clip_interval(hn, un, ta, tb):
    r"""Part of $[t_A, t_B]$ where $N\cdot(X(t) - p) = h_n + t\,u_n \ge 0$; returns `(t0, t1, nonempty)`."""
    pos = un > 0
    neg = un < 0
    safe_un = jnp.where(pos | neg, un, 1.0)
    tc = fusible(-hn / safe_un)
    t0 = jnp.where(pos, jnp.maximum(ta, tc), ta)
    t1 = jnp.where(neg, jnp.minimum(tb, tc), tb)
    nonempty = jnp.where(pos | neg, t1 > t0, hn >= 0) & (tb > ta)
    return t0, t1, nonempty


def _sin_diff_over_d2(ta, tb, d2, ra, rb):
    r"""$(t_B/r_B - t_A/r_A)/d^2 = J_1/d^2$, stable when the foot is outside the segment."""
    same_side = ta * tb > 0
    den_stable = jnp.where(same_side, tb * ra + ta * rb, 1.0)
    ra_s = jnp.where(same_side, ra, 1.0)
    rb_s = jnp.where(same_side, rb, 1.0)
    # Grouped so that no intermediate goes beyond (length)^-2 (float32 at small scales).
    stable = ((tb - ta) / ra_s) * ((tb + ta) / rb_s) / den_stable
    d2_safe = jnp.where(same_side | (d2 == 0), 1.0, d2)
    direct = (tb / rb - ta / ra) / d2_safe
    return jnp.where(same_side, stable, direct)


def _cosine_profile_bracket(t0, t1, d, ra, rb, m):
    r"""For $m \ge 1$ and $d > 0$: $(J_{m+1}, T)$ in the ratios $c = d/r$, $s = t/r$, with
    $d\,E/(C_m\Phi) = (N\cdot h/d)\,J_{m+1} + N\cdot u\,T$ (module docstring, "Numerics"):
    $J_{m+1}$ by the reduction formula and
    $T = (c_A^{m+1} - c_B^{m+1})/(m+1) = (c_A - c_B)\sum_{i=0}^{m} c_A^i c_B^{m-i} / (m+1)$,
    $c_A - c_B = c_A (t_B - t_A)(t_B + t_A)/(r_B (r_A + r_B))$ (no cancellation). Returns `J`
    and `T`; every quantity is dimensionless and at most 1 in magnitude (up to a factor 2)."""
    ca, cb = fusible(d / ra), fusible(d / rb)
    sa, sb = fusible(t0 / ra), fusible(t1 / rb)
    k_target = m + 1
    if k_target % 2 == 0:
        # J_0 = phi_B - phi_A; both arguments divided by r_A r_B.
        j = arctan2(ca * ((t1 - t0) / rb), ca * cb + sa * sb)  # vectorised; XLA:CPU's is a libm call
        k0 = 0
    else:
        # J_1 = s_B - s_A, by the cancellation-free form when the foot is outside the segment.
        same_side = t0 * t1 > 0
        den = jnp.where(same_side, t1 * ra + t0 * rb, 1.0)
        j = jnp.where(same_side, ca * cb * ((t1 - t0) * (t1 + t0) / den), sb - sa)
        k0 = 1
    c_diff = ca * ((t1 - t0) / rb) * ((t1 + t0) / (ra + rb))
    if m <= UNROLL_MAX_EXPONENT:
        for k in range(k0 + 2, k_target + 1, 2):
            j = (cb ** (k - 1) * sb - ca ** (k - 1) * sa) / k + (k - 1) / k * j
        c_sum = sum(ca**i * cb ** (m - i) for i in range(m + 1))
        return j, c_diff * c_sum / (m + 1)
    # Large m: the same recurrences as loops (a traced program of fixed size; unrolled, the
    # trace grew as m^2 and m = 2000 took ~1 min to compile).
    ca2, cb2 = ca * ca, cb * cb

    def reduce_j(i, state):
        j, pa, pb = state  # pa = c_A^(k-1), pb = c_B^(k-1) for k = k0 + 2 + 2 i
        k = (k0 + 2 + 2 * i).astype(j.dtype)
        return (pb * sb - pa * sa) / k + (k - 1.0) / k * j, pa * ca2, pb * cb2

    p0 = ca ** (k0 + 1), cb ** (k0 + 1)
    j, _, _ = jax.lax.fori_loop(0, (k_target - k0) // 2, reduce_j, (j, *p0))

    def horner(_, state):
        acc, pb = state  # acc = sum_{i <= l} c_A^(l - i) c_B^i, pb = c_B^l
        pb = pb * cb
        return acc * ca + pb, pb

    c_sum, _ = jax.lax.fori_loop(0, m, horner, (jnp.ones_like(ca), jnp.ones_like(cb)))
    return j, c_diff * c_sum / (m + 1)


def linear_irradiance_kernel(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    a: Float[Array, "3"],
    b: Float[Array, "3"],
    m: int = 0,
) -> Float[Array, ""]:
    r"""Irradiance per unit power $E/\Phi$ (1/m) at `p` from the segment `a -> b`, profile $\cos^m\beta$.

    `m = 0` is the isotropic tube (per-length intensity $\Phi/4\pi$), `m >= 1` the
    cosine-distributed tube with exponent m (Poulin §3.2.2). Exact horizon clipping; `+inf`
    when `p` lies on the segment itself (documented divergence, zero gradient there).

    **Arguments:** `p (3,)` receiver (m), `n (3,)` unit normal, `a, b (3,)` endpoints (m),
    `m` static non-negative integer.

    **Returns:** scalar $E/\Phi$ in 1/m (multiply by the power per length $\Phi$ in W/m).
    """
    h, u, ta, tb = segment_frame(p, a, b)
    d2 = _dot3(h, h)
    hn = _dot3(n, h)
    un = _dot3(n, u)
    on_segment = (d2 == 0) & (ta <= 0) & (tb >= 0)
    t0, t1, nonempty = horizon_clip_interval(hn, un, ta, tb)
    ok = nonempty & ~on_segment
    # Dummy, harmless values where the result is not used (double-where).
    t0 = jnp.where(ok, t0, 1.0)
    t1 = jnp.where(ok, t1, 2.0)
    d2 = jnp.where(ok, d2, 1.0)
    hn = jnp.where(ok, hn, 0.0)
    # `fusible`: each square root is read several times (jaxshadow._core.misc.fusible).
    ra = fusible(jnp.sqrt(t0 * t0 + d2))
    rb = fusible(jnp.sqrt(t1 * t1 + d2))
    if m == 0:
        value = hn * _sin_diff_over_d2(t0, t1, d2, ra, rb) + un * (1.0 / ra - 1.0 / rb)
    else:
        d2_ok = d2 > 0
        d = fusible(jnp.sqrt(jnp.where(d2_ok, d2, 1.0)))
        hn_hat = hn / d  # N . h / d, in [-1, 1]
        j, tail = _cosine_profile_bracket(t0, t1, d, ra, rb, m)
        value = jnp.where(d2_ok, (hn_hat * j + un * tail) / d, 0.0)
    value = cosine_profile_constant(m) * value
    return jnp.where(on_segment, jnp.inf, jnp.where(ok, value, 0.0))


@functools.partial(jax.jit, static_argnums=4)
def _linear_batch(points: Array, normals: Array, start: Array, end: Array, m: int) -> tuple[Array, Array]:
    """`(N,)` values and the input flag (`_geometry.inputs_ok`), one compiled call."""
    e = jax.vmap(linear_irradiance_kernel, in_axes=(0, 0, None, None, None))(
        points, unit_rows(normals), start, end, m
    )
    return e, inputs_ok(points, normals)


# Validates its own inputs (ValueError, docs/design.md): no runtime annotation check before it.
@no_type_check
def linear_irradiance(
    points: Float[ArrayLike, "N 3"],
    normals: Float[ArrayLike, "N 3"],
    start: Float[ArrayLike, "3"],
    end: Float[ArrayLike, "3"],
    m: int = 0,
) -> Float[Array, " N"]:
    r"""Irradiance per unit power $E/\Phi$ (1/m) of a segment light at a batch of receivers.

    **Arguments:**

    - `points`, `normals`: `(N, 3)` receivers (m) and their normals (normalised here).
    - `start`, `end`: `(3,)` endpoints of the segment (m); cast to the dtype of `points`.
    - `m`: profile exponent, a Python int: 0 for the isotropic tube, $1 \le m \le$
      `MAX_COSINE_EXPONENT` (1000) for the $\cos^m$ tube (Poulin §3.2.2).

    **Returns:** `(N,)`; `+inf` for a receiver on the segment itself.

    Example:
        ```python
        import numpy as np
        import jaxshadow as js

        points = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.0]])
        normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
        f = js.linear_irradiance(points, normals, [-1.0, 0.0, 1.5], [1.0, 0.0, 1.5])   # (2,)
        ```
    """
    points, normals = check_points_normals(points, normals, "linear_irradiance", values=False)
    if not isinstance(m, (int, np.integer)):
        raise ValueError(f"linear_irradiance: m must be an integer >= 0 (a Python int), got {m!r}.")
    m = check_profile_exponent(m, "linear_irradiance: m")
    ends = []
    for name, x in (("start", start), ("end", end)):
        x = x if isinstance(x, jnp.ndarray) else jnp.asarray(x)
        if x.shape != (3,):
            raise ValueError(f"linear_irradiance: {name}: expected shape (3,), got {x.shape}.")
        if is_concrete(x):
            check_vector3(np.asarray(x), f"linear_irradiance: {name}")
        ends.append(x.astype(points.dtype))
    a, b = ends
    if is_concrete(a) and is_concrete(b):
        if not np.any(np.asarray(a) != np.asarray(b)):
            raise ValueError("linear_irradiance: zero-length segment (start == end).")
    else:
        a, b = check_finite_leaves((a, b), "linear_irradiance: start, end")
        a, b = eqx.error_if((a, b), jnp.all(a == b), "linear_irradiance: zero-length segment (start == end).")
    return evaluate_checked(lambda p, n: _linear_batch(p, n, a, b, int(m)), points, normals, "linear_irradiance")
