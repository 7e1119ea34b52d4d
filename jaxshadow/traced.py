r"""The traceable forward model: what solvers put inside their own compiled programs.

`jaxshadow.irradiance`, `specular` and `shade` check their inputs in NumPy and are jitted; a
solver that compiles its own program (a Levenberg-Marquardt loop over many starts, with
`jax.linearize` and `vmap` around the model) wants the model without either: no checks (the
light is traced there) and no nested `jit` (it would be traced once more and transformed again
by every `jvp` / `vmap` around it). This module is that model, with keyword arguments and one
extra: **per-receiver occluder culling at a static capacity without a fallback**. With
`max_active=A` each receiver of a polygon light sees only its `A` most relevant occluders, and
the result comes with an `overflow` flag (bool scalar) that says some receiver had more, so
that the value is not exact there: the caller retries with a larger capacity (a `lax.cond`
fallback inside a `vmap` over starts would run both branches every time).

`inverse` uses only this module (and the public API) of `jaxshadow`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from jaxtyping import Array, Bool, Float

from ._clip_host import _pinned
from ._clip_host import compiled_available as _compiled_available
from ._clip_host import relevant_counts as _relevant_counts
from ._scene import Scene
from ._shade import _irradiance_traced, _specular_traced
from ._specular import DEFAULT_DEGREE

__all__ = ["DEFAULT_SPECULAR_DEGREE", "irradiance", "specular", "pin", "host_combinatorics_available",
           "relevant_occluder_counts"]

DEFAULT_SPECULAR_DEGREE = DEFAULT_DEGREE
"""The Chebyshev degree of `jaxshadow.specular`'s default method."""


def irradiance(
    scene: Scene,
    points: Float[Array, "n 3"],
    normals: Float[Array, "n 3"],
    *,
    max_active: int | None = None,
    n_wide: int | None = None,
    host: bool = False,
) -> tuple[Float[Array, "n 3"], Bool[Array, ""]]:
    r"""Irradiance $E$ (W/m², RGB) at `points`, as `jaxshadow.irradiance`, and the culling flag.

    Traceable under `jit`, `vmap`, `jvp` and `grad` in the scene's arrays (light vertices,
    radiance, ...), the points and the normals; no input checks (validate before tracing).

    **Arguments:**

    - `scene`: a `jaxshadow.Scene` (its arrays may be traced).
    - `points`, `normals`: `(N, 3)` receivers and their normals (need not be unit).
    - `max_active`: static int, the occluder capacity per receiver for polygon lights; `None`
      (default) evaluates every occluder (exact, never overflows).
    - `n_wide`: static int; with `max_active`, only the first `n_wide` receivers get
      `max_active` occluders and the others 1 (two capacities in one program). `None`: all.
    - `host`: static bool; with `max_active` (and no `n_wide`) the culled kernel's
      combinatorics (which occluders, which pieces of which edges bound the visible region)
      run on the host (compiled C where it is built, else NumPy), called back from the
      compiled program, which then holds only the geometry and its derivatives. The same
      values to rounding.

    **Returns:** `(E (N, 3), overflow)`: `overflow` (bool scalar) is True when some receiver
    had more relevant occluders (or visible-region edges) than the capacity; `E` is then not
    exact at that receiver. Always False without `max_active`.

    Example:
        ```python
        import jax, jax.numpy as jnp
        import jaxshadow as js
        from jaxshadow import traced

        quad = [[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]]
        p = jnp.array([[0.5, 0.5, 0.0]]); n = jnp.array([[0.0, 0.0, 1.0]])

        def total(height):
            light = js.PolygonLight(jnp.asarray(quad, float).at[:, 2].set(height), radiance=1.0)
            e, overflow = traced.irradiance(js.Scene([light]), p, n)
            return e.sum()

        jax.grad(total)(2.0)   # d(E)/d(light height), through the traced model
        ```
    """
    return _irradiance_traced(scene, points, normals, max_active, False, n_wide, host and n_wide is None)


# The signature of `jaxshadow.specular` (and of `_shade._specular_traced`, which this wraps),
# with the culling options: the same shape on purpose.
def specular(
    scene: Scene,
    points: Float[Array, "n 3"],
    normals: Float[Array, "n 3"],
    eyes: Float[Array, "n 3"],
    exponent: Float[Array, ""],
    *,
    method: str = "chebyshev",
    degree: int = DEFAULT_DEGREE,
    max_active: int | None = None,
    host: bool = False,
) -> tuple[Float[Array, "n 3"], Bool[Array, ""]]:
    r"""Phong specular integral $S$ (RGB) at `points`, as `jaxshadow.specular`, and the culling
    flag (`irradiance` explains the culling).

    **Arguments:**

    - `scene`, `points`, `normals`: as `irradiance`.
    - `eyes`: `(N, 3)` eye position per receiver (broadcast a single eye to `(N, 3)` first).
    - `exponent`: the Phong exponent $n$, a scalar array of the points' dtype (traceable).
    - `method`, `degree`: static, as `jaxshadow.specular` (`"chebyshev"` of degree
      `DEFAULT_SPECULAR_DEGREE`, or `"exact"`).
    - `max_active`, `host`: static, as `irradiance`.

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
    return _specular_traced(scene, points, normals, eyes, exponent, method, degree, max_active, False, host)


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
    return _pinned(x)


def host_combinatorics_available() -> bool:
    """Whether the compiled host combinatorics (the C extension `jaxshadow._clipc`) are built;
    without them `host=True` runs their NumPy reference (exact, slower).

    Example:
        ```python
        from jaxshadow import traced

        traced.host_combinatorics_available()   # True after `pip install` with a C compiler
        ```
    """
    return _compiled_available()


def relevant_occluder_counts(
    points: Any, normals: Any, emitters: Any, occluders: Any
) -> np.ndarray:
    """How many occluders can shadow each receiver from each emitter, in NumPy (nothing is
    compiled): what a capacity for `max_active` must hold.

    **Arguments:** `points`, `normals`: `(N, 3)` receivers and unit normals; `emitters`:
    `(L, K, 3)` convex polygon lights padded to `K` vertices (repeat a vertex);
    `occluders`: `(M, Ko, 3)`.

    **Returns:** `(L, N)` int counts.

    Example:
        ```python
        import numpy as np
        from jaxshadow import traced

        p, n = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
        light = np.array([[[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2.0]]])
        blocker = np.array([[[0.2, 0.2, 1], [0.6, 0.2, 1], [0.6, 0.6, 1.0]]])
        traced.relevant_occluder_counts(p, n, light, blocker)   # array([[1]])
        ```
    """
    return _relevant_counts(np.asarray(points, np.float64), np.asarray(normals, np.float64),
                           np.asarray(emitters, np.float64), np.asarray(occluders, np.float64))
