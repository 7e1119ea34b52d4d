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
so any integer $m \ge 0$ is exact (closed form); non-integer $m$ is rejected at build time.

The normalisation $C_m = 1 / (2\pi W_{m+1})$, $W_k = \int_{-\pi/2}^{\pi/2}\cos^k$, makes every
profile emit the same power $\Phi$ per unit length (DESIGN.md).

Numerics. $J_1 / d^2 = (t_B/r_B - t_A/r_A)/d^2$ is rewritten as
$(t_B - t_A)(t_B + t_A) / ((t_B r_A + t_A r_B) r_A r_B)$ when the foot of $p$ is outside the
segment, so a receiver on (or near) the supporting line is exact and smooth: that is Poulin's
"on the supporting line" special case, $\int_0^{\mathcal L} (N\cdot L)/(l+b)^2 dl$, as a limit
rather than a branch. A receiver *on* the segment gets $+\infty$ (the integral diverges) with a
zero gradient. The segment is clipped exactly to the receiver's horizon first.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._geometry import check_points_normals, check_vector3, is_concrete
from ._misc import map_chunks, safe_norm, safe_normalize


def cosine_profile_constant(m: int) -> float:
    r"""$C_m = 1/(2\pi W_{m+1})$ with $W_k = \sqrt\pi\,\Gamma(\tfrac{k+1}{2})/\Gamma(\tfrac{k}{2}+1)$."""
    k = m + 1
    w = math.sqrt(math.pi) * math.exp(math.lgamma((k + 1) / 2) - math.lgamma(k / 2 + 1))
    return 1.0 / (2.0 * math.pi * w)


def segment_frame(p, a, b):
    """Poulin's 2-D frame of a segment seen from `p`: `(h, u, tA, tB)` with `X(t) = p + h + t u`."""
    e = b - a
    length = safe_norm(e)
    u = e / jnp.where(length > 0, length, 1.0)
    ta = jnp.dot(a - p, u)
    h = (a - p) - ta * u
    return h, u, ta, ta + length


def horizon_clip_interval(hn, un, ta, tb):
    r"""Part of $[t_A, t_B]$ where $N\cdot(X(t) - p) = h_n + t\,u_n \ge 0$; returns `(t0, t1, nonempty)`."""
    pos = un > 0
    neg = un < 0
    safe_un = jnp.where(pos | neg, un, 1.0)
    tc = -hn / safe_un
    t0 = jnp.where(pos, jnp.maximum(ta, tc), ta)
    t1 = jnp.where(neg, jnp.minimum(tb, tc), tb)
    nonempty = jnp.where(pos | neg, t1 > t0, hn >= 0) & (tb > ta)
    return t0, t1, nonempty


def _sin_diff_over_d2(ta, tb, d2, ra, rb):
    r"""$(t_B/r_B - t_A/r_A)/d^2 = J_1/d^2$, stable when the foot is outside the segment."""
    same_side = ta * tb > 0
    den_stable = jnp.where(same_side, (tb * ra + ta * rb) * ra * rb, 1.0)
    stable = (tb - ta) * (tb + ta) / den_stable
    d2_safe = jnp.where(same_side | (d2 == 0), 1.0, d2)
    direct = (tb / rb - ta / ra) / d2_safe
    return jnp.where(same_side, stable, direct)


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
    d2 = jnp.dot(h, h)
    hn = jnp.dot(n, h)
    un = jnp.dot(n, u)
    on_segment = (d2 == 0) & (ta <= 0) & (tb >= 0)
    t0, t1, nonempty = horizon_clip_interval(hn, un, ta, tb)
    ok = nonempty & ~on_segment
    # Dummy, harmless values where the result is not used (double-where).
    t0 = jnp.where(ok, t0, 1.0)
    t1 = jnp.where(ok, t1, 2.0)
    d2 = jnp.where(ok, d2, 1.0)
    hn = jnp.where(ok, hn, 0.0)
    ra = jnp.sqrt(t0 * t0 + d2)
    rb = jnp.sqrt(t1 * t1 + d2)
    if m == 0:
        value = hn * _sin_diff_over_d2(t0, t1, d2, ra, rb) + un * (1.0 / ra - 1.0 / rb)
    else:
        d2_ok = d2 > 0
        d2_safe = jnp.where(d2_ok, d2, 1.0)
        d = jnp.sqrt(d2_safe)
        # J_k by the reduction formula, starting from J_0 or J_1 (parity of k = m + 1).
        k_target = m + 1
        if k_target % 2 == 0:
            j = jnp.arctan2(d * (t1 - t0), d2_safe + t0 * t1)  # J_0 = phi_B - phi_A
            k0 = 0
        else:
            j = d2_safe * _sin_diff_over_d2(t0, t1, d2_safe, ra, rb)  # J_1
            k0 = 1
        for k in range(k0 + 2, k_target + 1, 2):
            boundary = d ** (k - 1) * (t1 / rb**k - t0 / ra**k)
            j = boundary / k + (k - 1) / k * j
        tail = d**m * (ra ** (-(m + 1)) - rb ** (-(m + 1))) / (m + 1)
        value = jnp.where(d2_ok, hn * j / d2_safe + un * tail, 0.0)
    value = cosine_profile_constant(m) * value
    return jnp.where(on_segment, jnp.inf, jnp.where(ok, value, 0.0))


@eqx.filter_jit
def _linear_batch(points: Array, normals: Array, start: Array, end: Array, m: int) -> Array:
    normals = safe_normalize(normals)
    return jax.vmap(linear_irradiance_kernel, in_axes=(0, 0, None, None, None))(
        points, normals, start, end, m
    )


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
    - `m`: profile exponent, a Python int: 0 for the isotropic tube, $m \ge 1$ for the
      $\cos^m$ tube (Poulin §3.2.2).

    **Returns:** `(N,)`; `+inf` for a receiver on the segment itself.
    """
    points, normals = check_points_normals(points, normals, "linear_irradiance")
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 0:
        raise ValueError(f"linear_irradiance: m must be an integer >= 0 (a Python int), got {m!r}.")
    ends = []
    for name, x in (("start", start), ("end", end)):
        x = x if isinstance(x, jnp.ndarray) else jnp.asarray(x)
        if x.shape != (3,):
            raise ValueError(f"linear_irradiance: {name}: expected shape (3,), got {x.shape}.")
        if is_concrete(x):
            check_vector3(np.asarray(x), f"linear_irradiance: {name}")
        ends.append(x.astype(points.dtype))
    a, b = ends
    if is_concrete(a) and is_concrete(b) and not np.any(np.asarray(a) != np.asarray(b)):
        raise ValueError("linear_irradiance: zero-length segment (start == end).")
    return map_chunks(lambda p, n: _linear_batch(p, n, a, b, int(m)), (points, normals))
