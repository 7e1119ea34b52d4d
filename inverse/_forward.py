"""The forward model the solvers fit.

`js.irradiance`, `js.specular` and `js.shade` (DESIGN.md): $L = k_a L_a + k_d/\\pi\\,E + k_s S$
(Poulin eq. 5.14). A `specular` callable with the signature of `js.specular` can be passed to
every solver (tests, or a different lobe); `None` means `js.specular`.

`shade_culled` is the same model with per-receiver occluder culling at a fixed capacity
(`jaxshadow._bsp`) and *no* fallback: it also returns whether any receiver had more relevant
occluders than the capacity (then its value is not exact and the solver retries with a larger
one). The public entry points cull only with concrete lights; inside a fit the light is traced.
Both call the forward model's traceable implementations (`_shade._irradiance_traced`,
`_specular_traced`) rather than its jitted entry points: the solvers compile their own
programs, and a nested jit there only adds tracing (it is transformed again by every
`jvp`/`vmap` around it).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax.numpy as jnp
from jaxtyping import Array

import jaxshadow as js
from jaxshadow._shade import _irradiance_traced, _specular_traced
from jaxshadow._specular import DEFAULT_DEGREE

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
    in the irradiance, the others 1 (`jaxshadow._bsp.grouped_culled_form_factor`). `host`
    (static, with `max_active`): the culled kernel's combinatorics run in NumPy on the host
    (`jaxshadow._clip_host`; the same values, a much smaller compiled program). Traceable in
    the scene (no input checks: the caller validated them)."""
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
    return _irradiance_traced(scene, points, normals, max_active, False, n_wide, host and n_wide is None)


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
    return _specular_traced(scene, points, normals, eyes, exponent.astype(dt), "chebyshev", DEFAULT_DEGREE,
                            max_active, False, host)


def traced_specular(scene: Any, points: Array, normals: Array, eye: Array, exponent: Array) -> Array:
    """`js.specular` (its default method and degree) without its input checks or its own jit,
    for the solvers' compiled programs (the material fit's exponent search): a module-level
    function, so it is one static argument for `equinox.filter_jit` however often it is used."""
    return specular_culled(scene, points, normals, eye, jnp.asarray(exponent), None, None)[0]
