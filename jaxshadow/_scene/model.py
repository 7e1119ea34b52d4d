"""Scene model: lights, material, occluders as equinox Modules (the JSON format: `format`).

Every float field is a JAX array leaf (differentiable); flags such as a linear light's profile
are static fields. Validation runs in NumPy when a light is built from concrete values and is
skipped under `jit`/`grad`/`vmap` (the inverse solvers rebuild lights from traced arrays).
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._core.geometry import (
    check_convex_polygon,
    check_convex_polygon_cached,
    check_finite,
    check_finite_leaves,
    check_rgb,
    check_unit_direction,
    check_vector3,
    is_concrete,
    pad_polygons_jax,
    triangles_pass,
)
from .._core.mesh import (
    Mesh,
    OccluderTopology,
    max_face_vertices,
    stack_occluders,
    weld_polygons,
)
from .._kernels.linear import check_profile_exponent


def _leaf(x: Any) -> Array:
    """Keep JAX arrays (and their dtype) as they are; convert anything else."""
    return x if isinstance(x, jnp.ndarray) else jnp.asarray(x)


def _rgb_leaf(x: Any) -> Array:
    a = _leaf(x)
    if a.shape == ():
        a = jnp.broadcast_to(a, (3,))
    return a


def _all_concrete(*xs: Any) -> bool:
    return all(is_concrete(x) for x in xs)


class AbstractLight(eqx.Module):
    """What every light says about itself, so that no caller asks which class it is.

    - `kind` (class attribute): what the shadow engine computes for it and which integrand
      method integrates it: `"polygon"` (a visible region), `"segment"` (visible pieces of a
      segment), `"point"` or `"directional"` (a hard shadow ray).
    - `emission(dtype)`: `(3,)` RGB emission the integrands are per unit of (radiance, power per
      length, intensity or irradiance).
    - `geometry`: the arrays that place it (vertices; start and end; position; direction).
    - `group`: lights of one group share one stacked kernel (`group` differs from `kind` only
      for segments, one group per cosine exponent).
    """

    kind: ClassVar[str]

    @abc.abstractmethod
    def emission(self, dtype: Any) -> Any:
        """`(3,)` RGB emission as `dtype`."""

    @property
    @abc.abstractmethod
    def geometry(self) -> tuple[Any, ...]:
        """The arrays that place the light."""

    @property
    def group(self) -> str:
        return self.kind


class PolygonLight(AbstractLight):
    """A planar convex polygon of uniform radiance (Lambertian emitter).

    **Fields:**

    - `vertices`: `(k, 3)` vertices (m), counter-clockwise seen from the side it emits to
      (the right-hand-rule normal points into the lit half-space).
    - `radiance`: `(3,)` RGB radiance $L$ (W m^-2 sr^-1); a scalar is broadcast to grey.

    Irradiance at a receiver is $E = \\pi L F$, $F$ the form factor of the visible part.
    """

    vertices: Float[Array, "k 3"]
    radiance: Float[Array, "3"]

    def __init__(self, vertices: Any, radiance: Any = 1.0):
        if _all_concrete(vertices, radiance):
            check_convex_polygon(vertices, "PolygonLight")
            check_rgb(radiance, "PolygonLight.radiance")
        self.vertices = _leaf(vertices)
        self.radiance = _rgb_leaf(radiance)

    kind: ClassVar[str] = "polygon"

    def emission(self, dtype: Any) -> Any:
        return self.radiance.astype(dtype)

    @property
    def geometry(self) -> tuple[Any, ...]:
        return (self.vertices,)

    @property
    def normal(self) -> Array:
        """Unit normal of the lit side (right-hand rule of the vertex order)."""
        v = self.vertices
        nrm = jnp.sum(jnp.cross(v, jnp.roll(v, -1, axis=0)), axis=0)
        return nrm / jnp.linalg.norm(nrm)


PROFILES = ("isotropic", "cosine")


class LinearLight(AbstractLight):
    """A segment light (a thin tube) with power per unit length $\\Phi$.

    **Fields:**

    - `start`, `end`: `(3,)` endpoints (m).
    - `power`: `(3,)` RGB power per unit length $\\Phi$ (W/m).
    - `profile`: `"isotropic"` (per-length intensity $\\Phi/4\\pi$) or `"cosine"` (intensity
      $\\propto \\cos^m\\beta$, $\\beta$ from the plane perpendicular to the segment, normalised
      to emit the same $\\Phi$). Static.
    - `exponent`: the integer $1 \\le m \\le 1000$ of the cosine profile (closed form for
      every integer; non-integer $m$ and $m$ above `_linear.MAX_COSINE_EXPONENT` are
      rejected). Static.
    """

    start: Float[Array, "3"]
    end: Float[Array, "3"]
    power: Float[Array, "3"]
    profile: str = eqx.field(static=True)
    exponent: int = eqx.field(static=True)

    def __init__(
        self,
        start: Any,
        end: Any,
        power: Any = 1.0,
        profile: str = "isotropic",
        exponent: int | float = 1,
    ):
        if profile not in PROFILES:
            raise ValueError(f"LinearLight.profile must be one of {PROFILES}, got {profile!r}.")
        exponent = check_profile_exponent(exponent, "LinearLight.exponent", 1 if profile == "cosine" else 0)
        if _all_concrete(start, end, power):
            s = check_vector3(start, "LinearLight.start")
            e = check_vector3(end, "LinearLight.end")
            check_rgb(power, "LinearLight.power")
            if np.linalg.norm(e - s) <= 1e-12 * max(1.0, float(np.linalg.norm(s))):
                raise ValueError("LinearLight: zero-length segment (start == end).")
        self.start = _leaf(start)
        self.end = _leaf(end)
        self.power = _rgb_leaf(power)
        self.profile = profile
        self.exponent = int(exponent) if profile == "cosine" else 0

    kind: ClassVar[str] = "segment"

    def emission(self, dtype: Any) -> Any:
        return self.power.astype(dtype)

    @property
    def geometry(self) -> tuple[Any, ...]:
        return (self.start, self.end)

    @property
    def group(self) -> str:
        return f"linear-{self.exponent}"


class PointLight(AbstractLight):
    """An isotropic point light. `position (3,)` (m), `intensity (3,)` RGB (W/sr).

    $E = I \\max(0, \\cos\\theta) / r^2$.
    """

    position: Float[Array, "3"]
    intensity: Float[Array, "3"]

    def __init__(self, position: Any, intensity: Any = 1.0):
        if _all_concrete(position, intensity):
            check_vector3(position, "PointLight.position")
            check_rgb(intensity, "PointLight.intensity")
        self.position = _leaf(position)
        self.intensity = _rgb_leaf(intensity)

    kind: ClassVar[str] = "point"

    def emission(self, dtype: Any) -> Any:
        return self.intensity.astype(dtype)

    @property
    def geometry(self) -> tuple[Any, ...]:
        return (self.position,)


class DirectionalLight(AbstractLight):
    """A distant light. `direction (3,)`: the direction light travels (any non-zero length);
    `irradiance (3,)` RGB (W/m^2) on a surface facing it. $E = E_0 \\max(0, -n\\cdot\\hat d)$."""

    direction: Float[Array, "3"]
    irradiance: Float[Array, "3"]

    def __init__(self, direction: Any, irradiance: Any = 1.0):
        if _all_concrete(direction, irradiance):
            check_unit_direction(direction, "DirectionalLight.direction")
            check_rgb(irradiance, "DirectionalLight.irradiance")
        self.direction = _leaf(direction)
        self.irradiance = _rgb_leaf(irradiance)

    kind: ClassVar[str] = "directional"

    def emission(self, dtype: Any) -> Any:
        return self.irradiance.astype(dtype)

    @property
    def geometry(self) -> tuple[Any, ...]:
        return (self.direction,)


Light = PolygonLight | LinearLight | PointLight | DirectionalLight


class Material(eqx.Module):
    """Phong material (Poulin eq. 2.1 / 5.14): $L = k_a L_a + k_d/\\pi\\, E + k_s S$.

    `ka`, `kd`, `ks`: `(3,)` RGB coefficients (`kd` is the diffuse albedo, as Mitsuba's
    `diffuse` reflectance), each >= 0, or `(N, 3)` per receiver (a texture looked up at `N`
    points: row `i` is the material at receiver `i`); a scalar is broadcast to grey. Per-receiver
    fields share one `N`. `exponent`: Phong $n \\ge 0$ (scalar array: one lobe per material).
    """

    ka: Float[Array, "3"] | Float[Array, "N 3"]
    kd: Float[Array, "3"] | Float[Array, "N 3"]
    ks: Float[Array, "3"] | Float[Array, "N 3"]
    exponent: Float[Array, ""]

    def __init__(self, ka: Any = 0.0, kd: Any = 0.5, ks: Any = 0.0, exponent: Any = 1.0):
        if _all_concrete(ka, kd, ks, exponent):
            rows = set()
            for name, v in (("ka", ka), ("kd", kd), ("ks", ks)):
                a = np.asarray(v, dtype=np.float64)
                if a.ndim == 2 and a.shape[1] == 3 and a.shape[0] >= 1:
                    rows.add(a.shape[0])
                    check_finite(a, f"Material.{name}")
                    if np.any(a < 0):
                        i, c = np.argwhere(a < 0)[0]
                        raise ValueError(f"Material.{name}[{i}]: must be >= 0, got {float(a[i, c])} in channel {'RGB'[c]}.")
                elif a.ndim == 2:
                    raise ValueError(f"Material.{name}: expected a scalar, (3,) or (N, 3), got shape {a.shape}.")
                else:
                    check_rgb(v, f"Material.{name}")
            if len(rows) > 1:
                raise ValueError(f"Material: per-receiver fields have different numbers of rows {sorted(rows)}.")
            e = np.asarray(exponent, dtype=np.float64)
            if e.shape != ():
                raise ValueError(f"Material.exponent must be a scalar, got shape {e.shape}.")
            check_finite(e.reshape(1), "Material.exponent")
            if e < 0:
                raise ValueError(f"Material.exponent must be >= 0, got {float(e)!r}.")
        self.ka = _rgb_leaf(ka)
        self.kd = _rgb_leaf(kd)
        self.ks = _rgb_leaf(ks)
        self.exponent = _leaf(exponent)

    @property
    def receivers(self) -> int | None:
        """`N` when some coefficient is given per receiver, else `None`."""
        for k in (self.ka, self.kd, self.ks):
            if k.ndim == 2:
                return int(k.shape[0])
        return None

    def radiance(self, ambient: Any, irradiance: Any, specular: Any = None) -> Array:
        """$k_a L_a + k_d E/\\pi + k_s S$ (Poulin eq. 5.14) from `ambient` `(3,)`, `irradiance` and
        `specular` `(N, 3)` (`None`: no specular term); per-receiver coefficients apply row by
        row. **Returns:** `(N, 3)` radiance (W m^-2 sr^-1), dtype of `irradiance`."""
        e = jnp.asarray(irradiance)
        dt = e.dtype
        rows = lambda k: jnp.broadcast_to(jnp.asarray(k, dt), e.shape)  # noqa: E731
        out = rows(self.ka) * rows(ambient) + rows(self.kd) / jnp.pi * e
        if specular is not None:
            out = out + rows(self.ks) * jnp.asarray(specular, dt)
        return out


def _stack_occluders(occluders: Any) -> tuple[Array | None, OccluderTopology | None]:
    if occluders is None:
        return None, None
    if isinstance(occluders, Mesh):
        occluders = [occluders]
    if isinstance(occluders, (np.ndarray, jnp.ndarray)) and not is_concrete(occluders):
        return jnp.asarray(occluders), None  # traced (m, K, 3), already padded
    arr_in = occluders
    if isinstance(occluders, (np.ndarray, jnp.ndarray)):
        arr = np.asarray(occluders)
        if arr.ndim == 2:
            occluders = [occluders]
        elif arr.ndim != 3 or arr.shape[-1] != 3:
            raise ValueError(
                f"Scene.occluders: expected an array (m, k, 3) or a list of (k, 3) polygons, got shape {arr.shape}."
            )
        else:
            occluders = list(occluders) if isinstance(occluders, np.ndarray) else [occluders[i] for i in range(arr.shape[0])]
    # A NumPy (m, k, 3) array: every entry a concrete NumPy polygon (no per-entry type checks).
    stacked = arr_in if isinstance(arr_in, np.ndarray) and arr_in.ndim == 3 else None
    items = list(occluders)
    if len(items) == 0:
        return None, None
    if stacked is not None:
        tris_ok = stacked.shape[1] == 3 and len(items) > 1 and triangles_pass(stacked)
    else:
        plain = [x for x in items if not isinstance(x, Mesh) and is_concrete(x)]
        tris_ok = len(plain) > 1 and all(np.shape(x) == (3, 3) for x in plain) and triangles_pass(np.stack(plain))
    if not tris_ok:
        for i, poly in enumerate(items):
            if not isinstance(poly, Mesh) and is_concrete(poly):
                check_convex_polygon(poly, f"Scene.occluders[{i}]")
    if stacked is not None or all(isinstance(x, Mesh) or (is_concrete(x) and not isinstance(x, jax.Array)) for x in items):
        items = weld_polygons(items, stacked, tris_ok)  # triangle soups become meshes (NumPy inputs only)
    if not any(isinstance(x, Mesh) for x in items):
        return pad_polygons_jax(items), None
    return stack_occluders(items, max_face_vertices(items))


class Scene(eqx.Module):
    """Lights, occluders and ambient radiance.

    **Fields:**

    - `lights`: tuple of `PolygonLight | LinearLight | PointLight | DirectionalLight`.
    - `occluders`: `(m, K, 3)` convex planar polygons padded by repeating their first vertex,
      or `None`. Built from a list of `(k_i, 3)` arrays and `Mesh` objects, or an `(m, k, 3)`
      array. A `Mesh` contributes its (merged) faces, kept together; its structure (closed,
      convex) goes to `occluder_topology` and lets the shadow engine treat a closed convex mesh
      as one blocker (`jaxshadow._core.mesh`).
    - `occluder_topology`: static `OccluderTopology` of the occluders, or `None` (independent
      polygons).
    - `ambient`: `(3,)` RGB ambient radiance $L_a$ (W m^-2 sr^-1).
    """

    lights: tuple
    occluders: Array | None
    ambient: Float[Array, "3"]
    occluder_topology: OccluderTopology | None = eqx.field(static=True)

    def __init__(self, lights: Sequence[Any] = (), occluders: Any = None, ambient: Any = 0.0):
        lights = tuple(lights)
        for i, light in enumerate(lights):
            if not isinstance(light, AbstractLight):
                raise ValueError(
                    f"Scene.lights[{i}]: expected PolygonLight, LinearLight, PointLight or "
                    f"DirectionalLight, got {type(light).__name__}."
                )
        if is_concrete(ambient):
            check_rgb(ambient, "Scene.ambient")
        self.lights = lights
        self.occluders, self.occluder_topology = _stack_occluders(occluders)
        self.ambient = _rgb_leaf(ambient)


def checked_scene(scene: Any, what: str) -> Scene:
    """`scene` as the public entry points use it: a `Scene` whose values are checked again,
    since they may have changed after it was built (`eqx.tree_at`) or arrive traced under the
    caller's `jit`. Concrete values: every leaf finite and every polygon light convex and
    planar (NumPy, `ValueError`; cached per polygon). Traced values: finite, checked when the
    program runs (`eqx.error_if`; use the returned scene)."""
    if not isinstance(scene, Scene):
        raise ValueError(f"{what}: expected a jaxshadow.Scene, got {type(scene).__name__}.")
    scene = check_finite_leaves(scene, f"{what}: scene")
    for i, light in enumerate(scene.lights):
        if light.kind == "polygon" and is_concrete(light.vertices):
            check_convex_polygon_cached(light.vertices, f"{what}: scene.lights[{i}].vertices")
    return scene


def checked_material(material: Any, what: str) -> Material:
    """`material` re-checked like `checked_scene`: coefficients finite and >= 0, exponent
    finite and >= 0 (concrete: `ValueError`; traced: `eqx.error_if`)."""
    if not isinstance(material, Material):
        raise ValueError(f"{what}: expected a jaxshadow.Material, got {type(material).__name__}.")
    leaves = (material.ka, material.kd, material.ks, material.exponent)
    if _all_concrete(*leaves):
        for name in ("ka", "kd", "ks"):
            c = np.asarray(getattr(material, name), np.float64)
            # (3,) or per receiver (N, 3) (Material's per-receiver coefficients).
            for i, row in enumerate(c if c.ndim == 2 else [c]):
                check_rgb(row, f"{what}: material.{name}" + (f"[{i}]" if c.ndim == 2 else ""))
        e = np.asarray(material.exponent, np.float64).reshape(-1)
        check_finite(e, f"{what}: material.exponent")
        if np.any(e < 0):
            raise ValueError(f"{what}: material.exponent must be >= 0, got {e.tolist()}.")
        return material
    bad = jnp.zeros((), bool)
    for leaf in leaves:
        bad = bad | ~jnp.all(jnp.isfinite(leaf) & (leaf >= 0))
    return eqx.error_if(material, bad, f"{what}: a material value is negative or not finite.")
