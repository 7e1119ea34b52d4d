"""Public evaluation: `irradiance`, `specular`, `shade` for a whole scene and a batch of points.

Plan, then evaluate: light kinds present in the scene select code paths before tracing (a
scene without linear lights never traces the linear kernel); lights of one kind are stacked and
`vmap`ped. Input checks run in NumPy before jit when values are concrete.
"""

from __future__ import annotations

import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from . import _shadows
from ._bsp import (
    capacity_for,
    culled_form_factor_kernel,
    culled_visible_edges,
    grouped_culled_form_factor,
    max_relevant,
    with_fallback,
)
from ._clip import (
    directional_visibility,
    point_visibility,
    visible_edges,
    visible_form_factor_kernel,
    visible_linear_kernel,
    visible_segments,
)
from ._geometry import (
    _check_values_eagerly,
    check_points_normals,
    evaluate_checked,
    inputs_ok,
    is_concrete,
    pad_polygons_jax,
)
from ._linear import linear_irradiance_kernel
from ._misc import map_chunks, safe_normalize, unit_rows
from ._point import directional_irradiance_kernel, point_irradiance_kernel
from ._polygon import form_factor_kernel
from ._scene import DirectionalLight, LinearLight, Material, PointLight, PolygonLight, Scene
from ._shadows import DEFAULT_OPTIONS, Lambert, Phong, ShadowOptions
from ._specular import (
    DEFAULT_DEGREE,
    contour_specular_kernel,
    directional_specular_kernel,
    point_specular_kernel,
    polygon_specular_kernel,
    segment_specular_kernel,
)


def _check_scene(scene: Any, what: str) -> Scene:
    if not isinstance(scene, Scene):
        raise ValueError(f"{what}: expected a jaxshadow.Scene, got {type(scene).__name__}.")
    return scene


def _stack(lights: list, field: str, dt: Any) -> Array:
    return jnp.stack([getattr(light, field) for light in lights]).astype(dt)


def _group(scene: Scene) -> dict[str, list]:
    """Lights by kernel: polygon, point, directional, and one group per linear-light exponent."""
    groups: dict[str, list] = {"polygon": [], "point": [], "directional": []}
    for light in scene.lights:
        if isinstance(light, PolygonLight):
            groups["polygon"].append(light)
        elif isinstance(light, PointLight):
            groups["point"].append(light)
        elif isinstance(light, DirectionalLight):
            groups["directional"].append(light)
        elif isinstance(light, LinearLight):
            groups.setdefault(f"linear-{light.exponent}", []).append(light)
    return groups


def _per_light(kernel: Any, points: Array, normals: Array, *light_args: Array) -> Array:
    """`kernel(p, n, *light)` over points (inner) and lights (outer): `(L, N)`."""
    over_points = jax.vmap(kernel, in_axes=(0, 0) + (None,) * len(light_args))
    return jax.vmap(over_points, in_axes=(None, None) + (0,) * len(light_args))(
        points, normals, *light_args
    )


# Occluder culling (`_bsp.py`) pays off from about this many occluders.
CULL_MIN_OCCLUDERS = 8


def _plan_max_active(scene: Scene, points: Array, normals: Array) -> int | None:
    """Static capacity of the per-receiver occluder list for polygon lights (`_bsp.py`), or
    None (no culling): few occluders, no polygon light, or traced inputs (count unknown)."""
    occ = scene.occluders
    polys = [light.vertices for light in scene.lights if isinstance(light, PolygonLight)]
    if occ is None or occ.shape[0] < CULL_MIN_OCCLUDERS or not polys:
        return None
    if not all(is_concrete(x) for x in (occ, points, normals, *polys)):
        return None
    with jax.ensure_compile_time_eval():  # concrete inputs closed over by a caller's jit
        verts = pad_polygons_jax(polys).astype(points.dtype)
        count = max_relevant(points, normals, verts, occ.astype(points.dtype))
    cap = capacity_for(count, occ.shape[0])
    return cap  # even at M: the culled kernel compacts the edge soup (`_bsp.edge_capacity`)


def _irradiance_traced(
    scene: Scene,
    points: Array,
    normals: Array,
    max_active: int | None = None,
    fallback: bool = True,
    n_wide: int | None = None,
    host: bool = False,
) -> Any:
    """Irradiance `(N, 3)`. With `max_active` (static) polygon lights see only the occluders that
    `_bsp.select_occluders` keeps per receiver; a receiver with more relevant occluders than that
    falls back to the full kernel (`fallback=True`), or (`fallback=False`) the result is
    `(E, overflow)` and `E` is *not* exact where `overflow` is True: the caller must retry with a
    larger capacity (the inverse solvers do; a `lax.cond` fallback inside their `vmap` over
    starts would run both branches every time). With `n_wide` (static, `fallback=False` only)
    only that many receivers get `max_active`, the others 1 (`_bsp.grouped_culled_form_factor`).
    With `host=True` (static; with `max_active`, not with `n_wide`) the culled kernel's
    combinatorics run in NumPy on the host (`_clip_host`: a much smaller compiled program,
    for the inverse solvers' fits on the CPU).

    Traceable, no input checks (`_irradiance_impl` is this function jitted). The inverse
    solvers call it inside their own compiled programs: a nested jit there is traced once and
    then transformed again by each `jvp` / `vmap` around it, which made up more than half of
    the tracing time of a light fit's first call."""
    terms, overflow = _irradiance_terms(scene, points, normals, max_active, fallback, n_wide, host)
    total = combine_terms(terms, points.shape, points.dtype)
    return total if fallback else (total, overflow)


_irradiance_impl = eqx.filter_jit(_irradiance_traced)


def _irradiance_terms(
    scene: Scene,
    points: Array,
    normals: Array,
    max_active: int | None,
    fallback: bool,
    n_wide: int | None,
    host: bool = False,
) -> tuple[tuple[tuple[Array, Array], ...], Array]:
    r"""Per light group `(g (L, N), emission (L, 3))` with $E = \sum_l g_l\,\text{emission}_l$,
    and the culling overflow flag (`_irradiance_impl`)."""
    dt = points.dtype
    overflow = jnp.zeros((), bool)
    normals = unit_rows(normals)
    occ = None if scene.occluders is None else scene.occluders.astype(dt)
    terms = []
    for key, lights in _group(scene).items():
        if not lights:
            continue
        if key == "polygon":
            verts = pad_polygons_jax([light.vertices for light in lights]).astype(dt)
            if occ is None:
                g = _per_light(form_factor_kernel, points, normals, verts)
            else:
                kern = lambda p, n, v: visible_form_factor_kernel(p, n, v, occ)  # noqa: E731
                if max_active is None:
                    g = _per_light(kern, points, normals, verts)
                elif n_wide is not None and not fallback and max_active > 1 and n_wide < points.shape[0]:
                    f, over = jax.vmap(grouped_culled_form_factor, in_axes=(None, None, 0, None, None, None))(
                        points, normals, verts, occ, max_active, n_wide
                    )
                    g, overflow = f, overflow | jnp.any(over)
                else:
                    culled = lambda p, n, v: culled_form_factor_kernel(p, n, v, occ, max_active, False, host)  # noqa: E731
                    f, over = _per_light(culled, points, normals, verts)
                    if fallback:
                        g = with_fallback(f, over, lambda: _per_light(kern, points, normals, verts))  # noqa: B023
                    else:
                        g, overflow = f, overflow | jnp.any(over)
            g = jnp.pi * g
            emission = _stack(lights, "radiance", dt)
        elif key.startswith("linear-"):
            m = lights[0].exponent
            if occ is None:
                kern = lambda p, n, a, b: linear_irradiance_kernel(p, n, a, b, m)  # noqa: B023, E731
            else:
                kern = lambda p, n, a, b: visible_linear_kernel(p, n, a, b, m, occ)  # noqa: B023, E731
            g = _per_light(kern, points, normals, _stack(lights, "start", dt), _stack(lights, "end", dt))
            emission = _stack(lights, "power", dt)
        elif key == "point":
            x = _stack(lights, "position", dt)
            g = _per_light(point_irradiance_kernel, points, normals, x)
            if occ is not None:
                vis = _per_light(lambda p, n, x: point_visibility(p, x, occ), points, normals, x)
                g = g * vis
            emission = _stack(lights, "intensity", dt)
        else:  # directional
            d = _stack(lights, "direction", dt)
            g = _per_light(lambda p, n, d: directional_irradiance_kernel(n, d), points, normals, d)
            if occ is not None:
                vis = _per_light(lambda p, n, d: directional_visibility(p, d, occ), points, normals, d)
                g = g * vis
            emission = _stack(lights, "irradiance", dt)
        terms.append((g, emission))
    return tuple(terms), overflow


def combine_terms(terms: tuple, shape: tuple, dtype: Any) -> Array:
    r"""$\sum_l g_l\,\text{emission}_l$ over the groups of `_irradiance_terms`: `(N, 3)`."""
    total = jnp.zeros(shape, dtype=dtype)
    for g, emission in terms:
        total = total + jnp.sum(g[:, :, None] * emission[:, None, :], axis=0)
    return total



# --------------------------------------------------------------------------------------
# Scenes with occluders: the shadow engine (`_shadows`), three ways
# --------------------------------------------------------------------------------------


def _value_of(x: Any) -> Any:
    """`x` as a NumPy array when its value is known (concrete, or a tracer of an eager
    `jax.grad`/`jax.jacfwd` that carries its primal), else None."""
    if not isinstance(x, jax.core.Tracer):
        return np.asarray(x)
    try:
        return np.asarray(jax.extend.core.concrete_or_error(None, x))
    except jax.errors.ConcretizationTypeError:
        return None


def _valued(tree: Any) -> Any:
    """`tree` with every array leaf replaced by its NumPy value, or None if one is abstract."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    vals = []
    for leaf in leaves:
        v = _value_of(leaf) if isinstance(leaf, (jax.Array, np.ndarray, jax.core.Tracer)) else leaf
        if v is None:
            return None
        vals.append(v)
    return jax.tree_util.tree_unflatten(treedef, vals)


def _unit_np(n: np.ndarray) -> np.ndarray:
    return np.asarray(unit_rows(jnp.asarray(n)))


@eqx.filter_jit
def _device_impl(scene: Scene, integ: Any, points: Array, normals: Array, eyes: Array | None) -> Array:
    return _shadows.device_values(scene, integ, points, unit_rows(normals), eyes)


def _shadowed(scene: Scene, integ: Any, points: Array, normals: Array, eyes: Array | None,
              options: ShadowOptions, what: str) -> Array:
    """`(N, 3)` for a scene with occluders through the shadow engine: on the host from concrete
    values (`host_values`; `planned_values` when the inputs carry derivatives), in the compiled
    program (`traced_values`, static capacity, overflow an error) when they are abstract."""
    tree = (scene, integ, points, normals, eyes)
    if not options.use_engine():
        _check_values_eagerly(points, normals, what)
        out = _device_impl(scene, integ, points, normals, eyes)
        return eqx.error_if(out, ~inputs_ok(points, normals), f"{what}: a point or normal is not finite, or a normal is zero.")
    if not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree)):
        _check_values_eagerly(points, normals, what)
        p = np.asarray(points)
        e = None if eyes is None else np.asarray(eyes)
        return jnp.asarray(_shadows.host_values(scene, integ, p, _unit_np(normals), e))
    val = _valued((scene, points, normals))
    if val is not None:
        vscene, p, n = val
        _check_values_eagerly(p, n, what)
        return _shadows.planned_values(scene, vscene, integ, points, unit_rows(normals), eyes, (p, _unit_np(n)))
    total, overflow = _shadows.traced_values(scene, integ, points, unit_rows(normals), eyes, options.capacity)
    total = eqx.error_if(total, ~inputs_ok(points, normals),
                         f"{what}: a point or normal is not finite, or a normal is zero.")
    return eqx.error_if(total, overflow, f"{what}: a receiver's visible region has more than {options.capacity} "
                        "boundary edges (or candidate faces); pass shadows=jaxshadow.ShadowOptions(capacity=...) "
                        "with a larger capacity.")


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
    scene = _check_scene(scene, "irradiance")
    points, normals = check_points_normals(points, normals, "irradiance", values=False)
    options = _check_options(shadows, "irradiance")
    if scene.occluders is not None:
        return _shadowed(scene, Lambert(), points, normals, None, options, "irradiance")
    return evaluate_checked(lambda p, n: _irradiance_checked(scene, p, n, None), points, normals, "irradiance")


@functools.partial(jax.jit, static_argnums=3)
def _irradiance_checked(scene: Scene, points: Array, normals: Array, max_active: int | None) -> tuple[Array, Array]:
    """`(E (N, 3), inputs_ok)`, one compiled call (plain `jax.jit`: its dispatch costs a fraction
    of `eqx.filter_jit`'s). The RGB weighting runs only when the inputs are good (the caller
    raises otherwise), under a `lax.cond`: that also makes XLA write the per-light values
    `g (L, N)` to memory before weighting them. Weighted in the same loop, XLA:CPU either
    recomputes the fused kernel for each of the three channels or splits it into ~27 loops,
    ~7x slower at 10^6 points (benchmarks/README.md)."""
    terms, _ = _irradiance_terms(scene, points, normals, max_active, True, None)
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


def _check_eye(eye: Any, points: Array, what: str) -> Array:
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


def _specular_traced(
    scene: Scene,
    points: Array,
    normals: Array,
    eyes: Array,
    exponent: Array,
    method: str,
    degree: int,
    max_active: int | None = None,
    fallback: bool = True,
    host: bool = False,
) -> Any:
    """Specular `(N, 3)`; `max_active`, `fallback` and `host` as in `_irradiance_traced`
    (traceable, no input checks; `_specular_impl` is this function jitted)."""
    dt = points.dtype
    overflow = jnp.zeros((), bool)
    normals = safe_normalize(normals)
    occ = None if scene.occluders is None else scene.occluders.astype(dt)
    opts = dict(method=method, degree=degree)
    total = jnp.zeros(points.shape, dtype=dt)

    def per_light(kernel: Any, *light_args: Array) -> Array:
        over_points = jax.vmap(kernel, in_axes=(0, 0, 0) + (None,) * len(light_args))
        return jax.vmap(over_points, in_axes=(None, None, None) + (0,) * len(light_args))(
            points, normals, eyes, *light_args
        )

    for key, lights in _group(scene).items():
        if not lights:
            continue
        if key == "polygon":
            verts = pad_polygons_jax([light.vertices for light in lights]).astype(dt)
            if occ is None:
                kern = lambda p, n, e, v: polygon_specular_kernel(p, n, e, v, exponent, **opts)  # noqa: E731
            else:

                def kern(p, n, e, v):
                    starts, ends = visible_edges(p, n, v, occ)
                    return contour_specular_kernel(p, n, e, starts, ends, exponent, **opts)

            if occ is None or max_active is None:
                g = per_light(kern, verts)
            else:

                def culled(p, n, e, v):
                    starts, ends, over = culled_visible_edges(p, n, v, occ, max_active, False, host)
                    val = contour_specular_kernel(p, n, e, starts, ends, exponent, **opts)
                    return val, over

                f, over = per_light(culled, verts)
                if fallback:
                    g = with_fallback(f, over, lambda: per_light(kern, verts))  # noqa: B023
                else:
                    g, overflow = f, overflow | jnp.any(over)
            emission = _stack(lights, "radiance", dt)
        elif key.startswith("linear-"):
            m = lights[0].exponent
            prof = None if lights[0].profile == "isotropic" else jnp.asarray(float(m), dt)

            def kern(p, n, e, a, b, prof=prof):
                if occ is None:
                    return segment_specular_kernel(p, n, e, a, b, exponent, prof, **opts)
                sa, sb = visible_segments(p, a, b, occ)
                piece = lambda u, v: segment_specular_kernel(p, n, e, u, v, exponent, prof, **opts)  # noqa: E731
                return jnp.sum(jax.vmap(piece)(sa, sb))

            g = per_light(kern, _stack(lights, "start", dt), _stack(lights, "end", dt))
            emission = _stack(lights, "power", dt)
        elif key == "point":
            x = _stack(lights, "position", dt)

            def kern(p, n, e, x):
                val = point_specular_kernel(p, n, e, x, exponent)
                return val if occ is None else val * point_visibility(p, x, occ)

            g = per_light(kern, x)
            emission = _stack(lights, "intensity", dt)
        else:
            d = _stack(lights, "direction", dt)

            def kern(p, n, e, d):
                val = directional_specular_kernel(p, n, e, d, exponent)
                return val if occ is None else val * directional_visibility(p, d, occ)

            g = per_light(kern, d)
            emission = _stack(lights, "irradiance", dt)
        total = total + jnp.sum(g[:, :, None] * emission[:, None, :], axis=0)  # fuses; a dot does not
    return total if fallback else (total, overflow)


_specular_impl = eqx.filter_jit(_specular_traced)


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
    scene = _check_scene(scene, "specular")
    points, normals = check_points_normals(points, normals, "specular")
    if method not in ("chebyshev", "exact"):
        raise ValueError(f"specular: method must be 'chebyshev' or 'exact', got {method!r}.")
    eyes = _check_eye(eye, points, "specular")
    e = _check_exponent(exponent, points.dtype, "specular")
    options = _check_options(shadows, "specular")
    if scene.occluders is not None:
        return _shadowed(scene, Phong(e, method, int(degree)), points, normals, eyes, options, "specular")
    return map_chunks(
        lambda p, n, v: _specular_impl(scene, p, n, v, e, method, int(degree), None),
        (points, normals, eyes),
    )


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
    scene = _check_scene(scene, "shade")
    if not isinstance(material, Material):
        raise ValueError(f"shade: expected a jaxshadow.Material, got {type(material).__name__}.")
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
        e = _shadowed(scene, Lambert(), points, normals, None, options, "shade")
        s = _shadowed(scene, Phong(n, method, int(degree)), points, normals, eyes, options, "shade")
        return material.radiance(scene.ambient, e, s)
    # The same compiled irradiance as `irradiance` (its flag checks the points and normals).
    e = evaluate_checked(lambda p, q: _irradiance_checked(scene, p, q, None), points, normals, "shade")
    s = map_chunks(
        lambda p, q, v: _specular_impl(scene, p, q, v, n, method, int(degree), None),
        (points, normals, eyes),
    )
    return material.radiance(scene.ambient, e, s)
