"""The forward model the solvers fit.

`js.irradiance`, `js.specular` and `js.shade` (docs/design.md): $L = k_a L_a + k_d/\\pi\\,E + k_s S$
(Poulin eq. 5.14). A `specular` callable with the signature of `js.specular` can be passed to
every solver (tests, or a different lobe); `None` means `js.specular`.

`shade_culled` is the same model inside a solver's compiled program, where the light is traced:
the shadow engine at a fixed capacity and *no* fallback (`jaxshadow.traced`); it also returns
whether any receiver needed more than the capacity (then its value is not exact and the solver
retries with a larger one). The solvers compile their own programs, so they call the traceable
model of `jaxshadow.traced` rather than the jitted entry points.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, TypeVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

import jaxshadow as js
from jaxshadow import ShadowOptions, traced

SpecularFn = Callable[[Any, Array, Array, Array, Array], Array]

# The most boundary edges per receiver a solve retries with (`at_capacity`) before it gives up.
MAX_CAPACITY = 4096

_P = TypeVar("_P")
_T = TypeVar("_T")


def at_capacity(run: Callable[[_P], tuple[_T, Any]], problem: _P, who: str, stage: str,
                hint: str = "") -> tuple[_T, _P, int]:
    """`run(problem) -> (out, overflowed)`, run again with twice the problem's shadow capacity
    (`problem.capacity`, a static field) while some receiver overflowed it, so that `out` is
    exact: the one retry of every solver, screening and placement program. `MAX_CAPACITY` edges
    at most: beyond, a `RuntimeError` names `who` (the entry point), the `stage` and `hint`.
    A problem with no capacity (every receiver against every occluder) runs once.
    Returns `(out, problem used, retries)`."""
    retries = 0
    while True:
        out, over = run(problem)
        cap = getattr(problem, "capacity")  # noqa: B009  (both problem types have it)
        if cap is None or not bool(over):
            return out, problem, retries
        if cap >= MAX_CAPACITY:
            raise RuntimeError(f"{who}: some receiver's visible region needs more than {MAX_CAPACITY} boundary "
                               f"edges during the {stage}{hint}.")
        problem = dataclasses.replace(problem, capacity=min(2 * cap, MAX_CAPACITY))  # type: ignore[type-var]
        retries += 1


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
                 specular: SpecularFn | None, with_specular: bool, capacity: int | None) -> tuple[Array, Array]:
    """`(shade(...), overflow)` inside a solver's compiled program (`jaxshadow.traced`): with
    occluders and `capacity` (static int) the shadow engine holds that many boundary edges per
    receiver and `overflow` (bool scalar) says some receiver needed more (its value is then not
    exact: the solver retries with a larger capacity). `capacity=None`: every receiver against
    every occluder (`ShadowOptions(engine="device")`), exact, `overflow = False`. A custom
    `specular` is evaluated as given. Traceable in the scene (no input checks: the caller
    validated them)."""
    dt = points.dtype
    e, over = irradiance_culled(scene, points, normals, capacity)
    out = (material.ka.astype(dt) * scene.ambient.astype(dt))[None, :] + (material.kd.astype(dt) / jnp.pi)[None, :] * e
    if with_specular:
        s, over_s = specular_culled(scene, points, normals, eye, material.exponent, specular, capacity)
        out = out + material.ks.astype(dt)[None, :] * s
        over = over | over_s
    return out, over


_EVERY_OCCLUDER = ShadowOptions(engine="device")


def irradiance_culled(scene: Any, points: Array, normals: Array, capacity: int | None) -> tuple[Array, Array]:
    """`(js.irradiance(...), overflow)` with the capacity of `shade_culled`."""
    if capacity is None:
        return traced.irradiance(scene, points, normals, shadows=_EVERY_OCCLUDER)
    return traced.irradiance(scene, points, normals, capacity=capacity)


def specular_culled(scene: Any, points: Array, normals: Array, eye: Array, exponent: Array,
                    specular: SpecularFn | None, capacity: int | None) -> tuple[Array, Array]:
    """`(js.specular(...), overflow)` (or the custom `specular`, without a flag)."""
    if specular is not None:
        return specular(scene, points, normals, eye, exponent), jnp.zeros((), bool)
    dt = points.dtype
    eyes = jnp.broadcast_to(jnp.asarray(eye, dt), points.shape)
    if capacity is None:
        return traced.specular(scene, points, normals, eyes, exponent.astype(dt), shadows=_EVERY_OCCLUDER)
    return traced.specular(scene, points, normals, eyes, exponent.astype(dt), capacity=capacity)


def irradiance_specular_culled(scene: Any, points: Array, normals: Array, eye: Array, exponent: Array,
                               specular: SpecularFn | None, capacity: int | None) -> tuple[Array, Array, Array]:
    """`(E, S, overflow)` of `irradiance_culled` and `specular_culled` together: without a
    custom `specular`, one run of the shadow engine serves both (`traced.irradiance_and_specular`:
    a program holding both has one copy of the engine)."""
    if specular is not None:
        e, over = irradiance_culled(scene, points, normals, capacity)
        s, o = specular_culled(scene, points, normals, eye, exponent, specular, capacity)
        return e, s, over | o
    dt = points.dtype
    eyes = jnp.broadcast_to(jnp.asarray(eye, dt), points.shape)
    opts = _EVERY_OCCLUDER if capacity is None else None
    return traced.irradiance_and_specular(scene, points, normals, eyes, exponent.astype(dt), capacity=capacity,
                                          shadows=opts)


class EngineSpecular(eqx.Module):
    """`js.specular` (its default method and degree) with the shadow engine inside the compiled
    program, at most `capacity` boundary edges per receiver (`jaxshadow.traced`): the material
    fit's exponent search, for receivers whose need was counted on the host
    (`material_specular`); `with_overflow` also says whether a receiver needed more (its
    value is then not exact: the caller raises), so the program holds no host callback and
    stays in the persistent compilation cache. Half the program of `traced_specular`'s
    every-occluder clipping: the engine finds each receiver's visible region, JAX decodes and
    integrates it. A module with a static capacity: one program per capacity, keyed by value
    (`fit_jit`, `_exported`)."""

    capacity: int = eqx.field(static=True)

    def with_overflow(self, scene: Any, points: Array, normals: Array, eye: Array,
                      exponent: Array) -> tuple[Array, Array]:
        """`(S (N, 3), overflow)`."""
        return specular_culled(scene, points, normals, eye, jnp.asarray(exponent), None, self.capacity)

    def __call__(self, scene: Any, points: Array, normals: Array, eye: Array, exponent: Array) -> Array:
        return self.with_overflow(scene, points, normals, eye, exponent)[0]


def material_specular(scene: Any, points: Any, normals: Any) -> SpecularFn:
    """The specular function of the material fit for a concrete `scene` and receivers:
    `EngineSpecular` at the capacity the receivers need (`traced.shadow_capacity`, rounded up to
    a multiple of 8 so that nearby scenes share the program), or `traced_specular` (no
    occluders, or no engine)."""
    cap = traced.shadow_capacity(scene, np.asarray(points), np.asarray(normals))
    return EngineSpecular(8 * -(-cap // 8)) if cap > 0 else traced_specular


def traced_specular(scene: Any, points: Array, normals: Array, eye: Array, exponent: Array) -> Array:
    """`js.specular` (its default method and degree) without its input checks or its own jit,
    for the solvers' compiled programs (the material fit's exponent search): a module-level
    function, so it is one static argument for `equinox.filter_jit` however often it is used."""
    return specular_culled(scene, points, normals, eye, jnp.asarray(exponent), None, None)[0]
