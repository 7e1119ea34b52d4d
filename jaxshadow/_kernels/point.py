r"""Point and directional lights (hard-edged, no area): $E = I\cos\theta/r^2$ and $E = E_0 \max(0, -n\cdot\hat d)$."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._core.misc import safe_normalize


def point_irradiance_kernel(
    p: Float[Array, "3"], n: Float[Array, "3"], x: Float[Array, "3"]
) -> Float[Array, ""]:
    r"""$E/I = \max(0, \cos\theta)/r^2$ (1/m^2) from a point light at `x`; `+inf` at `p = x`."""
    w = x - p
    r2 = jnp.dot(w, w)
    ok = r2 > 0
    r2s = jnp.where(ok, r2, 1.0)
    cos_r = jnp.dot(n, w)
    value = jnp.where(cos_r > 0, cos_r, 0.0) / (r2s * jnp.sqrt(r2s))
    return jnp.where(ok, value, jnp.inf)


def directional_irradiance_kernel(
    n: Float[Array, "3"], direction: Float[Array, "3"]
) -> Float[Array, ""]:
    r"""$E/E_0 = \max(0, -n\cdot\hat d)$ for light travelling along `direction`."""
    dhat = safe_normalize(direction)  # scale-free: any non-zero length
    c = -jnp.dot(n, dhat)
    return jnp.where(c > 0, c, 0.0)
