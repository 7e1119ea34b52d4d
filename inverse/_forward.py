"""The forward model the solvers fit.

`js.irradiance`, `js.specular` and `js.shade` (docs/design.md): $L = k_a L_a + k_d/\\pi\\,E + k_s S$
(Poulin eq. 5.14). A `specular` callable with the signature of `js.specular` can be passed to
every solver (tests, or a different lobe); `None` means `js.specular`.

`shade_culled` is the same model with per-receiver occluder culling at a fixed capacity and
*no* fallback (`jaxshadow.traced`): it also returns whether any receiver had more relevant
occluders than the capacity (then its value is not exact and the solver retries with a larger
one). The public entry points cull only with concrete lights; inside a fit the light is traced.
The solvers compile their own programs, so they call the traceable model of `jaxshadow.traced`
rather than the jitted entry points.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax.numpy as jnp
from jaxtyping import Array

import jaxshadow as js
from jaxshadow import traced

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


def shade_culled(scene: Any, material: Any, points: Array, normals: Array, eye: Array,
                 specular: SpecularFn | None, with_specular: bool, max_active: int | None,
                 n_wide: int | None = None, host: bool = False) -> tuple[Array, Array]:
    """`(shade(...), overflow)`; with `max_active` (static int) each receiver sees at most that
    many occluders per polygon light, and `overflow` (bool scalar) says some receiver had more
    (the value is then not exact). `max_active=None`: the full model and `overflow = False`; a
    custom `specular` is evaluated uncull'd. `n_wide`: only that many receivers get `max_active`
    in the irradiance, the others 1. `host` (static, with `max_active`): the culled kernel's
    combinatorics run on the host (the same values, a much smaller compiled program; see
    `jaxshadow.traced.irradiance`). Traceable in the scene (no input checks: the caller
    validated them)."""
    dt = points.dtype
    e, over = irradiance_culled(scene, points, normals, max_active, n_wide, host)
    out = (material.ka.astype(dt) * scene.ambient.astype(dt))[None, :] + (material.kd.astype(dt) / jnp.pi)[None, :] * e
    if with_specular:
        s, over_s = specular_culled(scene, points, normals, eye, material.exponent, specular, max_active, host)
        out = out + material.ks.astype(dt)[None, :] * s
        over = over | over_s
    return out, over


def irradiance_culled(scene: Any, points: Array, normals: Array, max_active: int | None,
                      n_wide: int | None = None, host: bool = False) -> tuple[Array, Array]:
    """`(js.irradiance(...), overflow)` with the culling of `shade_culled`."""
    if scene.occluders is None:
        max_active = None
    return traced.irradiance(scene, points, normals, max_active=max_active, n_wide=n_wide, host=host)


def specular_culled(scene: Any, points: Array, normals: Array, eye: Array, exponent: Array,
                    specular: SpecularFn | None, max_active: int | None,
                    host: bool = False) -> tuple[Array, Array]:
    """`(js.specular(...), overflow)` (or the custom `specular`, uncull'd)."""
    if specular is not None:
        return specular(scene, points, normals, eye, exponent), jnp.zeros((), bool)
    if scene.occluders is None:
        max_active = None
    dt = points.dtype
    eyes = jnp.broadcast_to(jnp.asarray(eye, dt), points.shape)
    return traced.specular(scene, points, normals, eyes, exponent.astype(dt), max_active=max_active, host=host)


def traced_specular(scene: Any, points: Array, normals: Array, eye: Array, exponent: Array) -> Array:
    """`js.specular` (its default method and degree) without its input checks or its own jit,
    for the solvers' compiled programs (the material fit's exponent search): a module-level
    function, so it is one static argument for `equinox.filter_jit` however often it is used."""
    return specular_culled(scene, points, normals, eye, jnp.asarray(exponent), None, None)[0]
