"""The forward model the solvers fit, through public `jaxshadow` names only.

`js.irradiance`, `js.specular` and `js.shade` (DESIGN.md): $L = k_a L_a + k_d/\\pi\\,E + k_s S$
(Poulin eq. 5.14). A `specular` callable with the signature of `js.specular` can be passed to
every solver (tests, or a different lobe); `None` means `js.specular`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax.numpy as jnp
from jaxtyping import Array

import jaxshadow as js

SpecularFn = Callable[[Any, Array, Array, Array, Array], Array]


def resolve_specular(specular: SpecularFn | None, what: str) -> SpecularFn:
    """`specular`, or `js.specular` when it is None (`what` names the caller)."""
    return js.specular if specular is None else specular


def shade(scene: Any, material: Any, points: Array, normals: Array, eye: Array,
          specular: SpecularFn | None = None, with_specular: bool = True) -> Array:
    """$k_a L_a + k_d/\\pi\\,E + k_s S$ at `(N, 3)` points; `js.shade` when it exists and no
    `specular` override is given. `with_specular=False` drops the $k_s S$ term (static)."""
    if specular is None and with_specular:
        return js.shade(scene, material, points, normals, eye)
    dt = points.dtype
    e = js.irradiance(scene, points, normals)
    out = (material.ka.astype(dt) * scene.ambient.astype(dt))[None, :] + (material.kd.astype(dt) / jnp.pi)[None, :] * e
    if with_specular:
        fn = resolve_specular(specular, "shade")
        s = fn(scene, points, normals, eye, material.exponent.astype(dt))
        out = out + material.ks.astype(dt)[None, :] * s
    return out
