"""Public evaluation: `irradiance`, `specular`, `shade` for a whole scene and a batch of points.

Plan, then evaluate: light kinds present in the scene select code paths before tracing (a
scene without linear lights never traces the linear kernel); lights of one kind are stacked and
`vmap`ped. Input checks run in NumPy before jit when values are concrete.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._geometry import pad_polygons_jax
from ._linear import linear_irradiance_kernel
from ._misc import safe_normalize
from ._point import directional_irradiance_kernel, point_irradiance_kernel
from ._polygon import form_factor_kernel
from ._scene import DirectionalLight, LinearLight, PointLight, PolygonLight, Scene


def check_points_normals(points: Any, normals: Any, what: str = "") -> tuple[Array, Array]:
    """Shape/dtype/value checks shared by every public entry point; normals are normalised."""
    pre = f"{what}: " if what else ""
    points = points if isinstance(points, jnp.ndarray) else jnp.asarray(points)
    normals = normals if isinstance(normals, jnp.ndarray) else jnp.asarray(normals)
    for name, x in (("points", points), ("normals", normals)):
        if x.ndim != 2 or x.shape[-1] != 3:
            raise ValueError(f"{pre}{name} must have shape (N, 3), got {x.shape}.")
        if not jnp.issubdtype(x.dtype, jnp.floating):
            raise ValueError(f"{pre}{name} must be a floating-point array, got dtype {x.dtype}.")
    if points.shape[0] != normals.shape[0]:
        raise ValueError(
            f"{pre}points and normals must have the same length, got {points.shape[0]} and {normals.shape[0]}."
        )
    if not isinstance(points, jax.core.Tracer):
        bad = ~np.isfinite(np.asarray(points))
        if bad.any():
            i = int(np.argwhere(bad.any(axis=1))[0, 0])
            raise ValueError(f"{pre}points[{i}] is not finite: {np.asarray(points)[i].tolist()}.")
    if not isinstance(normals, jax.core.Tracer):
        nn = np.asarray(normals)
        bad = ~np.isfinite(nn)
        if bad.any():
            i = int(np.argwhere(bad.any(axis=1))[0, 0])
            raise ValueError(f"{pre}normals[{i}] is not finite: {nn[i].tolist()}.")
        zero = ~np.any(nn != 0, axis=1)
        if zero.any():
            i = int(np.argmax(zero))
            raise ValueError(f"{pre}normals[{i}] is the zero vector; a normal needs a direction.")
    return points, safe_normalize(normals)


def _check_scene(scene: Any, what: str) -> Scene:
    if not isinstance(scene, Scene):
        raise ValueError(f"{what}: expected a jaxshadow.Scene, got {type(scene).__name__}.")
    return scene


def _require_no_occluders(scene: Scene, what: str) -> None:
    if scene.occluders is not None:
        raise NotImplementedError(
            f"{what}: scenes with occluders (soft shadows) are not supported yet; "
            "remove the occluders for the unshadowed result."
        )


def _group(scene: Scene) -> dict[str, list]:
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


@eqx.filter_jit
def _irradiance_impl(scene: Scene, points: Array, normals: Array) -> Array:
    dt = points.dtype
    total = jnp.zeros(points.shape, dtype=dt)
    groups = _group(scene)
    over_points = lambda kern, *in_axes: jax.vmap(kern, in_axes=(0, 0, *in_axes))  # noqa: E731
    if groups["polygon"]:
        verts = pad_polygons_jax([light.vertices for light in groups["polygon"]]).astype(dt)
        rad = jnp.stack([light.radiance for light in groups["polygon"]]).astype(dt)
        f = jax.vmap(over_points(form_factor_kernel, None), in_axes=(None, None, 0))(
            points, normals, verts
        )  # (L, N)
        total = total + jnp.pi * jnp.einsum("ln,lc->nc", f, rad)
    for key, lights in groups.items():
        if not key.startswith("linear-") or not lights:
            continue
        m = lights[0].exponent
        a = jnp.stack([light.start for light in lights]).astype(dt)
        b = jnp.stack([light.end for light in lights]).astype(dt)
        phi = jnp.stack([light.power for light in lights]).astype(dt)
        kern = lambda p, n, a, b: linear_irradiance_kernel(p, n, a, b, m)  # noqa: B023, E731
        g = jax.vmap(over_points(kern, None, None), in_axes=(None, None, 0, 0))(points, normals, a, b)
        total = total + jnp.einsum("ln,lc->nc", g, phi)
    if groups["point"]:
        x = jnp.stack([light.position for light in groups["point"]]).astype(dt)
        inten = jnp.stack([light.intensity for light in groups["point"]]).astype(dt)
        g = jax.vmap(over_points(point_irradiance_kernel, None), in_axes=(None, None, 0))(
            points, normals, x
        )
        total = total + jnp.einsum("ln,lc->nc", g, inten)
    if groups["directional"]:
        d = jnp.stack([light.direction for light in groups["directional"]]).astype(dt)
        e0 = jnp.stack([light.irradiance for light in groups["directional"]]).astype(dt)
        g = jax.vmap(jax.vmap(directional_irradiance_kernel, in_axes=(0, None)), in_axes=(None, 0))(
            normals, d
        )
        total = total + jnp.einsum("ln,lc->nc", g, e0)
    return total


def irradiance(
    scene: Scene, points: Float[ArrayLike, "N 3"], normals: Float[ArrayLike, "N 3"]
) -> Float[Array, "N 3"]:
    r"""Direct irradiance $E$ (W/m^2, RGB) at receivers from every light of the scene.

    Polygon lights: $E = \pi L F$ with the exact, horizon-clipped form factor (Campbell &
    Fussell eq. 11); linear lights: Poulin eq. 3.10 and §3.2.2; point lights
    $I\cos\theta/r^2$; directional lights $E_0\max(0, -n\cdot\hat d)$.

    **Arguments:**

    - `scene`: a `Scene`.
    - `points`: `(N, 3)` receiving points (m).
    - `normals`: `(N, 3)` receiver normals (normalised here; zero vectors are an error).

    **Returns:** `(N, 3)` irradiance, dtype following `points`.
    """
    scene = _check_scene(scene, "irradiance")
    points, normals = check_points_normals(points, normals, "irradiance")
    _require_no_occluders(scene, "irradiance")
    return _irradiance_impl(scene, points, normals)
