"""Small numerical helpers shared by every kernel (NaN-safe forms of common operations)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float


def safe_norm(x: Float[Array, "... 3"], axis: int = -1) -> Float[Array, "..."]:
    """Euclidean norm whose gradient at `x = 0` is zero instead of NaN (double `where`)."""
    sq = jnp.sum(x * x, axis=axis)
    ok = sq > 0
    safe_sq = jnp.where(ok, sq, 1.0)
    return jnp.where(ok, jnp.sqrt(safe_sq), 0.0)


def safe_normalize(x: Float[Array, "... 3"], axis: int = -1) -> Float[Array, "... 3"]:
    """`x / |x|`, zero (with zero gradient) where `x = 0`."""
    sq = jnp.sum(x * x, axis=axis, keepdims=True)
    ok = sq > 0
    safe_sq = jnp.where(ok, sq, 1.0)
    return jnp.where(ok, x / jnp.sqrt(safe_sq), 0.0)


def safe_div(num: Array, den: Array, fallback: float | Array = 0.0) -> Array:
    """`num / den` where `den != 0`, else `fallback`, NaN-free in value and gradient."""
    ok = den != 0
    safe_den = jnp.where(ok, den, 1.0)
    return jnp.where(ok, num / safe_den, fallback)


def angle_over_sin(s2: Array, c: Array) -> Array:
    r"""$\theta / s$ for $\theta = \operatorname{atan2}(s, c)$, $s = \sqrt{s_2} \ge 0$.

    This is the factor that turns the (unnormalised) cross product of two edge vectors into
    Lambert's $\theta \hat\Gamma$ term. It is smooth in `s2` (an even function of $s$) when
    $c > 0$, so gradients stay finite when a receiver lies on the supporting line of an edge
    (outside the edge, where $\theta \to 0$). It is set to 0 in the one truly singular case,
    $s = 0,\ c \le 0$ (the receiver on the edge itself or at a vertex), which only happens for
    receivers in the emitter's plane, where the caller returns 0 anyway.
    """
    # Series of atan(x)/x in u = x^2 = s2/c^2 for tiny angles: error < u^4/9.
    small = (c > 0) & (s2 < 1e-4 * c * c)
    c_safe = jnp.where(small, c, 1.0)
    u = jnp.where(small, s2 / (c_safe * c_safe), 0.0)
    series = (1.0 - u * (1.0 / 3.0 - u * (1.0 / 5.0 - u / 7.0))) / c_safe
    generic = (~small) & (s2 > 0)
    s2_safe = jnp.where(generic, s2, 1.0)
    s = jnp.sqrt(s2_safe)
    c_gen = jnp.where(generic, c, 1.0)
    direct = jnp.arctan2(s, c_gen) / s
    return jnp.where(small, series, jnp.where(generic, direct, 0.0))
