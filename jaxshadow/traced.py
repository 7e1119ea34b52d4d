r"""The traceable forward model: what solvers put inside their own compiled programs.

`jaxshadow.irradiance`, `specular` and `shade` check their inputs in NumPy and decide on the host
how to evaluate shadows; a solver that compiles its own program (a Levenberg-Marquardt loop over
many starts, with `jax.linearize` and `vmap` around the model) wants the model without either: no
checks (the light is traced there) and no host-side dispatch. This module is that model, with
keyword arguments and one extra, the **shadow capacity**: with occluders, the shadow engine runs
inside the compiled program (XLA FFI, `jaxshadow._shadows.binding`) and holds at most `capacity`
boundary edges of each receiver's visible region (visible pieces for segment lights). The
result comes with an `overflow` flag (bool scalar) that says some receiver needed more, so that
the value is not exact there: the caller retries with a larger capacity (a `lax.cond` fallback
inside a `vmap` over starts would run both branches every time). `shadow_capacity` sizes it from
concrete values on the host.

`inverse` uses only this module (and the public API) of `jaxshadow`.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._kernels.specular import DEFAULT_DEGREE
from ._scene.model import Scene
from ._shading import shade as _shade
from ._shadows import binding as _binding
from ._shadows import evaluators as _evaluators
from ._shadows import plan as _plan
from ._shadows.integrands import Both, Lambert, Phong
from ._shadows.options import DEFAULT_OPTIONS, ShadowOptions

__all__ = ["DEFAULT_SPECULAR_DEGREE", "irradiance", "specular", "irradiance_and_specular", "pin", "shadow_capacity",
           "register_engine"]

DEFAULT_SPECULAR_DEGREE = DEFAULT_DEGREE
"""The Chebyshev degree of `jaxshadow.specular`'s default method."""


def _options(capacity: int | None, shadows: ShadowOptions | None) -> ShadowOptions:
    opts = DEFAULT_OPTIONS if shadows is None else shadows
    return opts if capacity is None else ShadowOptions(opts.engine, int(capacity))


def _shadowed(scene: Scene, integ: Any, points: Array, normals: Array, eyes: Array | None,
              opts: ShadowOptions) -> tuple[Array, Array]:
    evaluator = _evaluators.TracedEngine(opts.capacity) if opts.use_engine() else _evaluators.DeviceKernels(compiled=False)
    out, overflow = evaluator(scene, integ, _evaluators.traced_receivers(points, normals, eyes))
    return out, jnp.asarray(overflow)


def irradiance(
    scene: Scene,
    points: Float[Array, "n 3"],
    normals: Float[Array, "n 3"],
    *,
    capacity: int | None = None,
    shadows: ShadowOptions | None = None,
) -> tuple[Float[Array, "n 3"], Bool[Array, ""]]:
    r"""Irradiance $E$ (W/m², RGB) at `points`, as `jaxshadow.irradiance`, and the overflow flag.

    Traceable under `jit`, `vmap`, `jvp` and `grad` in the scene's arrays (light vertices,
    radiance, occluder vertices, ...), the points and the normals; no input checks (validate
    before tracing).

    **Arguments:**

    - `scene`: a `jaxshadow.Scene` (its arrays may be traced).
    - `points`, `normals`: `(N, 3)` receivers and their normals (need not be unit).
    - `capacity`: static int, boundary edges (visible pieces for segment lights) per receiver
      the shadow engine holds; default `shadows.capacity` (64). `shadow_capacity` sizes it.
    - `shadows`: static `ShadowOptions` (`engine="device"`: every receiver against every
      occluder, no capacity, no overflow).

    **Returns:** `(E (N, 3), overflow)`: `overflow` (bool scalar) is True when some receiver
    needed more than `capacity`; `E` is then not exact at that receiver. Always False without
    occluders.

    Example:
        ```python
        import jax, jax.numpy as jnp
        import jaxshadow as js
        from jaxshadow import traced

        quad = [[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]]
        blocker = [[0.2, 0.2, 1.0], [0.6, 0.2, 1.0], [0.6, 0.6, 1.0]]
        p = jnp.array([[0.5, 0.5, 0.0]]); n = jnp.array([[0.0, 0.0, 1.0]])

        def total(height):
            light = js.PolygonLight(jnp.asarray(quad, float).at[:, 2].set(height), radiance=1.0)
            e, overflow = traced.irradiance(js.Scene([light], occluders=[blocker]), p, n, capacity=16)
            return e.sum()

        jax.grad(total)(2.0)   # d(E)/d(light height), soft shadow included
        ```
    """
    if scene.occluders is None:
        return _shade.unoccluded_irradiance(scene, points, normals), jnp.zeros((), bool)
    return _shadowed(scene, Lambert(), points, normals, None, _options(capacity, shadows))


def specular(
    scene: Scene,
    points: Float[Array, "n 3"],
    normals: Float[Array, "n 3"],
    eyes: Float[Array, "n 3"],
    exponent: Float[Array, ""],
    *,
    method: str = "chebyshev",
    degree: int = DEFAULT_DEGREE,
    capacity: int | None = None,
    shadows: ShadowOptions | None = None,
) -> tuple[Float[Array, "n 3"], Bool[Array, ""]]:
    r"""Phong specular integral $S$ (RGB) at `points`, as `jaxshadow.specular`, and the overflow
    flag (`irradiance` explains the capacity).

    **Arguments:**

    - `scene`, `points`, `normals`: as `irradiance`.
    - `eyes`: `(N, 3)` eye position per receiver (broadcast a single eye to `(N, 3)` first).
    - `exponent`: the Phong exponent $n$, a scalar array of the points' dtype (traceable).
    - `method`, `degree`: static, as `jaxshadow.specular` (`"chebyshev"` of degree
      `DEFAULT_SPECULAR_DEGREE`, or `"exact"`).
    - `capacity`, `shadows`: static, as `irradiance`.

    **Returns:** `(S (N, 3), overflow)`.

    Example:
        ```python
        import jax.numpy as jnp
        import jaxshadow as js
        from jaxshadow import traced

        light = js.PolygonLight([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]], radiance=1.0)
        p = jnp.array([[0.5, 0.5, 0.0]]); n = jnp.array([[0.0, 0.0, 1.0]])
        s, _ = traced.specular(js.Scene([light]), p, n, jnp.array([[0.5, -1.0, 2.0]]), jnp.asarray(20.0))
        ```
    """
    if scene.occluders is None:
        return _shade.unoccluded_specular(scene, points, normals, eyes, exponent, method, degree), jnp.zeros((), bool)
    return _shadowed(scene, Phong(exponent, method, int(degree)), points, normals, eyes, _options(capacity, shadows))


def irradiance_and_specular(
    scene: Scene,
    points: Float[Array, "n 3"],
    normals: Float[Array, "n 3"],
    eyes: Float[Array, "n 3"],
    exponent: Float[Array, ""],
    *,
    capacity: int | None = None,
    shadows: ShadowOptions | None = None,
) -> tuple[Float[Array, "n 3"], Float[Array, "n 3"], Bool[Array, ""]]:
    r"""`(E (N, 3), S (N, 3), overflow)`: `irradiance` and `specular` (its default method and
    degree) of the same receivers, with the shadow engine run once per light and receiver block
    for both (one visible region, decoded once, integrated twice): a compiled program that needs
    both holds one copy of the engine's wrappers instead of two. The values are those of the two
    functions (the same kernels on the same visible region); arguments as `specular`.

    Example:
        ```python
        import jax.numpy as jnp
        import jaxshadow as js
        from jaxshadow import traced

        light = js.PolygonLight([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]], radiance=1.0)
        box = js.Mesh.box([0.3, 0.3, 0.5], [0.6, 0.6, 0.8])
        p = jnp.array([[0.5, 0.5, 0.0]]); n = jnp.array([[0.0, 0.0, 1.0]])
        e, s, overflow = traced.irradiance_and_specular(js.Scene([light], occluders=[box]), p, n,
                                                        jnp.array([[0.5, -1.0, 2.0]]), jnp.asarray(20.0))
        ```
    """
    opts = _options(capacity, shadows)
    if scene.occluders is None or not opts.use_engine():
        e, o1 = irradiance(scene, points, normals, capacity=capacity, shadows=shadows)
        s, o2 = specular(scene, points, normals, eyes, exponent, capacity=capacity, shadows=shadows)
        return e, s, o1 | o2
    out, overflow = _shadowed(scene, Both(Phong(exponent)), points, normals, eyes, opts)
    return out[:, 0], out[:, 1], overflow


def pin(x: Float[Array, "k ..."]) -> Float[Array, "k ..."]:
    """`x` as the result of a product by the identity: the same values, exactly, but XLA does not
    fuse a dot's operands into its consumers, so whatever computed `x` (a light's pose from a
    solver's parameters, and its tangents) is computed once, not again inside every fused loop
    over receivers and edges that reads it.

    **Arguments:** `x`: an array with at least one axis. **Returns:** `x` (same shape, dtype).

    Example:
        ```python
        import jax.numpy as jnp
        from jaxshadow import traced

        v = traced.pin(jnp.ones((4, 3)))   # == jnp.ones((4, 3))
        ```
    """
    return jnp.dot(jnp.eye(x.shape[0], dtype=x.dtype), x, precision=jax.lax.Precision.HIGHEST)


def shadow_capacity(scene: Scene, points: Any, normals: Any, lights: Any = None) -> int:
    """The most boundary edges (polygon lights) or visible pieces (segment lights) any receiver
    needs, for the lights of `scene` (or `lights`) at concrete receivers: what `capacity` must
    hold for `irradiance` / `specular` not to overflow there. Runs the shadow engine on the host,
    nothing is compiled; 0 without occluders or without the engine.

    **Arguments:** `scene`: a `Scene` with concrete arrays; `points`, `normals`: `(N, 3)`
    concrete receivers; `lights`: optional list of lights to use instead of the scene's (e.g. a
    light at several candidate poses).

    **Returns:** a non-negative int.

    Example:
        ```python
        import numpy as np
        import jaxshadow as js
        from jaxshadow import traced

        light = js.PolygonLight([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]], radiance=1.0)
        scene = js.Scene([light], occluders=[[[0.2, 0.2, 1], [0.6, 0.2, 1], [0.6, 0.6, 1.0]]])
        traced.shadow_capacity(scene, np.array([[0.5, 0.4, 0.0]]), np.array([[0.0, 0.0, 1.0]]))   # 7
        ```
    """
    if scene.occluders is None or not DEFAULT_OPTIONS.use_engine():
        return 0
    p = np.ascontiguousarray(np.asarray(points, np.float64))
    n = np.asarray(normals, np.float64)
    n = np.ascontiguousarray(n / np.linalg.norm(n, axis=1, keepdims=True))
    todo = [x for x in (scene.lights if lights is None else lights) if x.kind in ("polygon", "segment")]
    if not todo or p.shape[0] == 0:
        return 0
    return max(int(lp.counts.max(initial=0)) for lp in _plan.plan(scene, p, n, produce="classes", lights=todo).lights)


def register_engine() -> bool:
    """Register the shadow engine's XLA FFI handlers with JAX, once per process; nothing is
    traced or compiled. Tracing a program that holds the engine registers them too; a program
    that was not traced in this process (deserialised by `jax.export`) needs this before it
    runs. Returns whether the handlers are usable (False: the engine is not built, was built
    without jaxlib's FFI headers or for another jaxlib; programs then hold the device kernels).

    Example:
        ```python
        from jaxshadow import traced

        traced.register_engine()   # True where the engine is built with its XLA FFI handlers
        ```
    """
    return _binding.ffi_available()
