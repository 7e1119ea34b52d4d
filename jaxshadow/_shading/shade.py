"""Public evaluation: `irradiance`, `specular`, `shade` for a whole scene and a batch of points.

Plan, then evaluate: light kinds present in the scene select code paths before tracing (a
scene without linear lights never traces the linear kernel); lights of one kind are stacked and
`vmap`ped. Input checks run in NumPy before jit when values are concrete.
"""

from __future__ import annotations

from typing import Any, no_type_check

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._core.geometry import check_points_normals, evaluate_checked, inputs_ok, pad_polygons_jax
from .._core.misc import map_chunks, safe_normalize, unit_rows
from .._kernels.linear import linear_irradiance_kernel
from .._kernels.point import directional_irradiance_kernel, point_irradiance_kernel
from .._kernels.polygon import form_factor_kernel
from .._kernels.specular import (
    DEFAULT_DEGREE,
    directional_specular_kernel,
    point_specular_kernel,
    polygon_specular_kernel,
    segment_specular_kernel,
)
from .._scene.model import Material, Scene, checked_material, checked_scene
from .._shadows.evaluators import Receivers, choose, receivers
from .._shadows.integrands import Lambert, Phong
from .._shadows.options import DEFAULT_OPTIONS, ShadowOptions


def _stack(lights: list, field: str, dt: Any) -> Array:
    return jnp.stack([getattr(light, field) for light in lights]).astype(dt)


def _emissions(lights: list, dt: Any) -> Array:
    return jnp.stack([light.emission(dt) for light in lights])


def _group(scene: Scene) -> dict[str, list]:
    """Lights by kernel (`AbstractLight.group`): polygon, point, directional, and one group per
    linear-light exponent."""
    groups: dict[str, list] = {"polygon": [], "point": [], "directional": []}
    for light in scene.lights:
        groups.setdefault(light.group, []).append(light)
    return groups


def _per_light(kernel: Any, points: Array, normals: Array, *light_args: Array) -> Array:
    """`kernel(p, n, *light)` over points (inner) and lights (outer): `(L, N)`."""
    over_points = jax.vmap(kernel, in_axes=(0, 0) + (None,) * len(light_args))
    return jax.vmap(over_points, in_axes=(None, None) + (0,) * len(light_args))(
        points, normals, *light_args
    )


def unoccluded_irradiance(scene: Scene, points: Float[Array, "N 3"], normals: Float[Array, "N 3"]) -> Float[Array, "N 3"]:
    """Irradiance `(N, 3)` (W/m^2) of a scene *without occluders* (scenes with occluders go
    through the shadow engine, `_shadows`). Traceable, no input checks. The solvers call it
    (`jaxshadow.traced`) inside their own compiled programs."""
    terms = _irradiance_terms(scene, points, normals)
    return combine_terms(terms, points.shape, points.dtype)


def _irradiance_terms(scene: Scene, points: Array, normals: Array) -> tuple[tuple[Array, Array], ...]:
    r"""Per light group `(g (L, N), emission (L, 3))` with $E = \sum_l g_l\,\text{emission}_l$,
    without occluders."""
    assert scene.occluders is None, "scenes with occluders go through the shadow engine (_shadows)"
    dt = points.dtype
    normals = unit_rows(normals)
    terms = []
    for lights in _group(scene).values():
        if not lights:
            continue
        kind = lights[0].kind
        if kind == "polygon":
            verts = pad_polygons_jax([light.vertices for light in lights]).astype(dt)
            g = jnp.pi * _per_light(form_factor_kernel, points, normals, verts)
        elif kind == "segment":
            m = lights[0].exponent
            kern = lambda p, n, a, b: linear_irradiance_kernel(p, n, a, b, m)  # noqa: B023, E731
            g = _per_light(kern, points, normals, _stack(lights, "start", dt), _stack(lights, "end", dt))
        elif kind == "point":
            g = _per_light(point_irradiance_kernel, points, normals, _stack(lights, "position", dt))
        else:  # directional
            d = _stack(lights, "direction", dt)
            g = _per_light(lambda p, n, d: directional_irradiance_kernel(n, d), points, normals, d)
        terms.append((g, _emissions(lights, dt)))
    return tuple(terms)


def combine_terms(terms: tuple, shape: tuple, dtype: Any) -> Array:
    r"""$\sum_l g_l\,\text{emission}_l$ over the groups of `_irradiance_terms`: `(N, 3)`."""
    total = jnp.zeros(shape, dtype=dtype)
    for g, emission in terms:
        total = total + jnp.sum(g[:, :, None] * emission[:, None, :], axis=0)
    return total



# --------------------------------------------------------------------------------------
# Scenes with occluders: the shadow engine (`_shadows`), three ways
# --------------------------------------------------------------------------------------


def _shadowed(scene: Scene, integ: Any, rx: Receivers, options: ShadowOptions, what: str) -> Array:
    """`(N, 3)` for a scene with occluders through the evaluator `choose` picks; abstract
    receivers' checks and a capacity overflow become run-time errors naming `what`."""
    out, overflow = choose(options, scene, integ, rx)(scene, integ, rx)
    if rx.ok is not None:
        out = eqx.error_if(out, ~rx.ok, f"{what}: a point or normal is not finite, or a normal is zero.")
    if isinstance(overflow, jax.Array):
        out = eqx.error_if(out, overflow, f"{what}: a receiver's visible region has more than {options.capacity} "
                           "boundary edges (or candidate faces); pass shadows=jaxshadow.ShadowOptions(capacity=...) "
                           "with a larger capacity.")
    return out


# Validates its own inputs (ValueError, docs/design.md): no runtime annotation check before it.
@no_type_check
def irradiance(
    scene: Scene,
    points: Float[ArrayLike, "N 3"],
    normals: Float[ArrayLike, "N 3"],
    *,
    shadows: ShadowOptions | None = None,
) -> Float[Array, "N 3"]:
    r"""Direct irradiance $E$ (W/m^2, RGB) at receivers from every light of the scene.

    Polygon lights: $E = \pi L F$ with the exact, horizon-clipped form factor (Campbell &
    Fussell eq. 11); linear lights: Poulin eq. 3.10 and §3.2.2; point lights
    $I\cos\theta/r^2$; directional lights $E_0\max(0, -n\cdot\hat d)$.

    **Arguments:**

    - `scene`: a `Scene`.
    - `points`: `(N, 3)` receiving points (m).
    - `normals`: `(N, 3)` receiver normals (normalised here; zero vectors are an error).
    - `shadows`: `ShadowOptions` (static): which shadow engine, and the boundary capacity per
      receiver when the values are abstract (inside `jax.jit`/`jax.vmap`). Default: the
      compiled host engine when it is built.

    **Returns:** `(N, 3)` irradiance, dtype following `points`.

    **Receivers on occluders.** A receiver closer to the plane of an occluder face whose
    coordinates are float32 values (meshes from files, Mitsuba) than
    $2^{-18} S \approx 3.8\cdot 10^{-6} S$ ($S$: the largest coordinate magnitude of that face's
    vertices and the receiver; 32 float32 epsilons, in float32 and float64 alike) lies on the
    face: the face blocks nothing for it, and nor does any face coplanar with it (they are seen
    edge-on); every other face, the neighbours of a non-convex surface included, casts its true
    shadow. Faces read from files or Mitsuba have float32 vertices, planar (and points computed
    on them in their planes) only to that order, so receivers on a scene's own surfaces get the
    light their surface does not hide. Lights need only be planar to rounding: the visible part
    is the cone from the receiver over the light's own vertices.

    Example:
        ```python
        import numpy as np
        import jaxshadow as js

        light = js.PolygonLight([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]], radiance=[4.0, 3.5, 3.0])
        blocker = [[0.2, 0.2, 1.0], [0.6, 0.2, 1.0], [0.6, 0.6, 1.0]]
        scene = js.Scene([light], occluders=[blocker], ambient=0.05)
        points = np.array([[0.5, 0.5, 0.0], [2.0, 0.0, 0.0]])
        normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.3, 1.0]])
        E = js.irradiance(scene, points, normals)   # (2, 3) W/m^2, soft shadow included
        ```
    """
    scene = checked_scene(scene, "irradiance")  # values changed after build / traced: checked again
    points, normals = check_points_normals(points, normals, "irradiance", values=False)
    options = _check_options(shadows, "irradiance")
    if scene.occluders is not None:
        return _shadowed(scene, Lambert(), receivers(points, normals, None, "irradiance"), options, "irradiance")
    return evaluate_checked(lambda p, n: _irradiance_checked(scene, p, n), points, normals, "irradiance")


@jax.jit
def _irradiance_checked(scene: Scene, points: Array, normals: Array) -> tuple[Array, Array]:
    """`(E (N, 3), inputs_ok)`, one compiled call (plain `jax.jit`: its dispatch costs a fraction
    of `eqx.filter_jit`'s). The RGB weighting runs only when the inputs are good (the caller
    raises otherwise), under a `lax.cond`: that also makes XLA write the per-light values
    `g (L, N)` to memory before weighting them. Weighted in the same loop, XLA:CPU either
    recomputes the fused kernel for each of the three channels or splits it into ~27 loops,
    ~7x slower at 10^6 points (benchmarks/README.md)."""
    terms = _irradiance_terms(scene, points, normals)
    ok = inputs_ok(points, normals)
    e = jax.lax.cond(ok, lambda t: combine_terms(t, points.shape, points.dtype),
                     lambda t: jnp.zeros(points.shape, points.dtype), terms)
    return e, ok


def _check_options(shadows: Any, what: str) -> ShadowOptions:
    if shadows is None:
        return DEFAULT_OPTIONS
    if not isinstance(shadows, ShadowOptions):
        raise ValueError(f"{what}: shadows must be a jaxshadow.ShadowOptions, got {type(shadows).__name__}.")
    return shadows


def _check_eye(eye: Any, points: Array | np.ndarray, what: str) -> Array:
    eye = eye if isinstance(eye, jnp.ndarray) else jnp.asarray(eye)
    if eye.shape != (3,) and eye.shape != points.shape:
        raise ValueError(f"{what}: eye must have shape (3,) or {points.shape}, got {eye.shape}.")
    if not isinstance(eye, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(eye))):
        raise ValueError(f"{what}: eye is not finite.")
    return jnp.broadcast_to(eye.astype(points.dtype), points.shape)


def _check_exponent(exponent: Any, dt: Any, what: str) -> Array:
    e = exponent if isinstance(exponent, jnp.ndarray) else jnp.asarray(exponent)
    if e.shape != ():
        raise ValueError(f"{what}: the Phong exponent must be a scalar, got shape {e.shape}.")
    if not isinstance(e, jax.core.Tracer):
        v = float(e)
        if not np.isfinite(v) or v < 0:
            raise ValueError(f"{what}: the Phong exponent must be finite and >= 0, got {v}.")
    return e.astype(dt)


def unoccluded_specular(
    scene: Scene,
    points: Array,
    normals: Array,
    eyes: Array,
    exponent: Array,
    method: str,
    degree: int,
) -> Array:
    """Specular `(N, 3)` of a scene *without occluders* (traceable, no input checks;
    `_specular_impl` is this function jitted): `points`, `normals`, `eyes` `(N, 3)`, `exponent` a
    scalar array, `method` and `degree` as `specular`'s."""
    assert scene.occluders is None, "scenes with occluders go through the shadow engine (_shadows)"
    dt = points.dtype
    normals = safe_normalize(normals)
    opts = dict(method=method, degree=degree)
    total = jnp.zeros(points.shape, dtype=dt)

    def per_light(kernel: Any, *light_args: Array) -> Array:
        over_points = jax.vmap(kernel, in_axes=(0, 0, 0) + (None,) * len(light_args))
        return jax.vmap(over_points, in_axes=(None, None, None) + (0,) * len(light_args))(
            points, normals, eyes, *light_args
        )

    for lights in _group(scene).values():
        if not lights:
            continue
        kind = lights[0].kind
        if kind == "polygon":
            verts = pad_polygons_jax([light.vertices for light in lights]).astype(dt)
            g = per_light(lambda p, n, e, v: polygon_specular_kernel(p, n, e, v, exponent, **opts), verts)
        elif kind == "segment":
            prof = None if lights[0].profile == "isotropic" else jnp.asarray(float(lights[0].exponent), dt)
            kern = lambda p, n, e, a, b: segment_specular_kernel(p, n, e, a, b, exponent, prof, **opts)  # noqa: B023, E731
            g = per_light(kern, _stack(lights, "start", dt), _stack(lights, "end", dt))
        elif kind == "point":
            g = per_light(lambda p, n, e, x: point_specular_kernel(p, n, e, x, exponent), _stack(lights, "position", dt))
        else:
            d = _stack(lights, "direction", dt)
            g = per_light(lambda p, n, e, d: directional_specular_kernel(p, n, e, d, exponent), d)
        total = total + jnp.sum(g[:, :, None] * _emissions(lights, dt)[:, None, :], axis=0)  # fuses; a dot does not
    return total


_specular_impl = eqx.filter_jit(unoccluded_specular)


# Validates its own inputs (ValueError, docs/design.md): no runtime annotation check before it.
@no_type_check
def specular(
    scene: Scene,
    points: Float[ArrayLike, "N 3"],
    normals: Float[ArrayLike, "N 3"],
    eye: Float[ArrayLike, "3"] | Float[ArrayLike, "N 3"],
    exponent: Float[ArrayLike, ""],
    *,
    method: str = "chebyshev",
    degree: int = DEFAULT_DEGREE,
    shadows: ShadowOptions | None = None,
) -> Float[Array, "N 3"]:
    r"""Phong specular integral $S$ (RGB) at receivers, shadows included.

    $S = \int L_i(w)\,\frac{n+1}{2\pi}\max(0, w\cdot R)^n\,dw$ over the visible light above the
    tangent plane, $R = 2(N\cdot V)N - V$, $V$ the unit vector to the eye (Poulin eq. 3.11 for
    segments, eq. 3.12 for polygons; point and directional lights weight the lobe by
    $I/r^2$ and $E_0$). Units: W m^-2 sr^-1 times sr, i.e. the radiance a mirror-like
    $k_s = 1$ surface would reflect.

    **Arguments:**

    - `scene`: a `Scene` (occluders cast exact soft shadows).
    - `points`, `normals`: `(N, 3)` receivers and their normals.
    - `eye`: `(3,)` or `(N, 3)` eye position(s).
    - `exponent`: Phong exponent $n \ge 0$ (scalar array; differentiable).
    - `method`: `"chebyshev"` (default: Chebyshev fit of the lobe with a cut-off angle) or
      `"exact"` (recurrence for integer $n$, graded quadrature otherwise). Static.
    - `degree`: Chebyshev degree (static).
    - `shadows`: `ShadowOptions` (static), as for `irradiance`.

    **Returns:** `(N, 3)`, dtype following `points`.

    Example:
        ```python
        import numpy as np
        import jaxshadow as js

        tube = js.LinearLight([-1, 0, 1.5], [1, 0, 1.5], power=2.0)
        scene = js.Scene([tube, js.PointLight([0, 2, 2], 1.0)])
        p, n = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
        S = js.specular(scene, p, n, eye=[0.0, -2.0, 2.0], exponent=50.0)   # (1, 3): the Phong lobe's integral
        ```
    """
    scene = checked_scene(scene, "specular")  # values changed after build / traced: checked again
    points, normals = check_points_normals(points, normals, "specular")
    if method not in ("chebyshev", "exact"):
        raise ValueError(f"specular: method must be 'chebyshev' or 'exact', got {method!r}.")
    eyes = _check_eye(eye, points, "specular")
    e = _check_exponent(exponent, points.dtype, "specular")
    options = _check_options(shadows, "specular")
    if scene.occluders is not None:
        rx = receivers(points, normals, eyes, "specular")
        return _shadowed(scene, Phong(e, method, int(degree)), rx, options, "specular")
    return map_chunks(
        lambda p, n, v: _specular_impl(scene, p, n, v, e, method, int(degree)),
        (points, normals, eyes),
    )


# Validates its own inputs (ValueError, docs/design.md): no runtime annotation check before it.
@no_type_check
def shade(
    scene: Scene,
    material: Material,
    points: Float[ArrayLike, "N 3"],
    normals: Float[ArrayLike, "N 3"],
    eye: Float[ArrayLike, "3"] | Float[ArrayLike, "N 3"],
    *,
    method: str = "chebyshev",
    degree: int = DEFAULT_DEGREE,
    shadows: ShadowOptions | None = None,
) -> Float[Array, "N 3"]:
    r"""Outgoing radiance $L = k_a L_a + \frac{k_d}{\pi} E + k_s S$ per RGB channel (Poulin eq. 5.14).

    `E` from `irradiance`, `S` from `specular` with the material's exponent; shadows included.

    **Arguments:** `scene`, `material` (`Material`), `points`, `normals` `(N, 3)`, `eye` `(3,)`
    or `(N, 3)`; `method`, `degree`, `shadows` as for `specular`.

    **Returns:** `(N, 3)` radiance (W m^-2 sr^-1).

    Example:
        ```python
        import jax
        import jax.numpy as jnp
        import jaxshadow as js

        scene = js.Scene([js.PointLight([0, 0, 2.0], 5.0)], ambient=0.1)
        p, n = jnp.array([[0.3, 0.1, 0.0]]), jnp.array([[0.0, 0.0, 1.0]])

        def radiance(kd):   # k_a L_a + k_d / pi E + k_s S, differentiable in the material
            return js.shade(scene, js.Material(ka=0.2, kd=kd, ks=0.3, exponent=20.0), p, n, [0, -1, 1.0]).sum()

        jax.grad(radiance)(0.6)
        ```
    """
    scene = checked_scene(scene, "shade")  # values changed after build / traced: checked again
    material = checked_material(material, "shade")
    points, normals = check_points_normals(points, normals, "shade", values=False)
    if method not in ("chebyshev", "exact"):
        raise ValueError(f"shade: method must be 'chebyshev' or 'exact', got {method!r}.")
    eyes = _check_eye(eye, points, "shade")
    dt = points.dtype
    n = _check_exponent(material.exponent, dt, "shade")
    options = _check_options(shadows, "shade")
    rows = material.receivers
    if rows is not None and rows != points.shape[0]:
        raise ValueError(f"shade: the material has coefficients for {rows} receivers, got {points.shape[0]} points.")
    if scene.occluders is not None:
        rx = receivers(points, normals, eyes, "shade")  # once for both terms
        e = _shadowed(scene, Lambert(), rx, options, "shade")
        s = _shadowed(scene, Phong(n, method, int(degree)), rx, options, "shade")
        return material.radiance(scene.ambient, e, s)
    # The same compiled irradiance as `irradiance` (its flag checks the points and normals).
    e = evaluate_checked(lambda p, q: _irradiance_checked(scene, p, q), points, normals, "shade")
    s = map_chunks(
        lambda p, q, v: _specular_impl(scene, p, q, v, n, method, int(degree)),
        (points, normals, eyes),
    )
    return material.radiance(scene.ambient, e, s)
