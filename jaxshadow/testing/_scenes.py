"""Geometry of the catalogue scenes and the parameters their derivatives are taken with respect to.

Every scene has one light (index 0), a receiver plane z = 0 with normal +z, and a square window
on it: the reference points are the centres of a 4 x 4 grid over the window, and the Mitsuba
camera images the same window. Coordinates avoid symmetric placements on purpose, so that no
reference point lies on a shadow's kink (where a derivative has no value) and no derivative
vanishes by symmetry alone.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._core.mesh import Mesh
from .._scene.model import LinearLight, Material, PolygonLight, Scene

#: Parameter names and what a unit of each is. Derivatives are d(quantity)/d(parameter) at 0.
PARAMETERS: dict[str, str] = {
    "light.tx": "translation of the light along x (m)",
    "light.ty": "translation of the light along y (m)",
    "light.tz": "translation of the light along z (m)",
    "light.rx": "rotation of the light about the x axis through its centre (rad)",
    "light.ry": "rotation of the light about the y axis through its centre (rad)",
    "light.rz": "rotation of the light about the z axis through its centre (rad)",
    "light.scale": "relative scale of the light about its centre (1: double the size)",
    "occluder.tx": "translation of every occluder along x (m)",
    "occluder.ty": "translation of every occluder along y (m)",
    "occluder.tz": "translation of every occluder along z (m)",
    "material.ka": "grey change of the ambient coefficient k_a (all channels)",
    "material.kd": "grey change of the diffuse albedo k_d (all channels)",
    "material.ks": "grey change of the specular coefficient k_s (all channels)",
    "material.exponent": "change of the Phong exponent n",
}
LIGHT_TRANSLATION = ("light.tx", "light.ty", "light.tz")
LIGHT_PARAMETERS = (*LIGHT_TRANSLATION, "light.rx", "light.ry", "light.rz", "light.scale")
OCCLUDER_PARAMETERS = ("occluder.tx", "occluder.ty", "occluder.tz")
MATERIAL_PARAMETERS = ("material.ka", "material.kd", "material.ks", "material.exponent")
GRID = 4  # reference points per window side


@dataclass(frozen=True)
class Window:
    """A square on the receiver plane z = 0: `centre` (x, y) (m), half side `half` (m), and the
    height of the camera (m) above its centre that images it (below every occluder and light
    over the window, so the camera sees the receiver only)."""

    centre: tuple[float, float]
    half: float
    camera_height: float

    def grid(self, n: int) -> np.ndarray:
        """Centres of an n x n grid of cells, row-major from the top (+y) row, left (-x) first:
        `(n * n, 3)` points on z = 0 (the pixel centres of an n x n image of the window)."""
        cx, cy = self.centre
        u = (np.arange(n) + 0.5) / n
        x = cx - self.half + 2.0 * self.half * u
        y = cy + self.half - 2.0 * self.half * u
        xx, yy = np.meshgrid(x, y)
        return np.stack([xx.ravel(), yy.ravel(), np.zeros(n * n)], axis=1)


@dataclass(frozen=True)
class Spec:
    name: str
    description: str
    scene: Scene
    material: Material
    eye: np.ndarray
    window: Window


def _rect(centre: Any, u: Any, v: Any, normal: Any) -> np.ndarray:
    """Rectangle c +- u +- v, vertex order chosen so the right-hand normal points along `normal`."""
    c, u, v = (np.asarray(a, dtype=np.float64) for a in (centre, u, v))
    verts = np.array([c - u - v, c + u - v, c + u + v, c - u + v])
    if np.dot(np.cross(u, v), np.asarray(normal, dtype=np.float64)) < 0:
        verts = verts[::-1].copy()
    return verts


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


DOWN = (0.0, 0.0, -1.0)


def _unoccluded() -> Spec:
    light = _rect([0.1, -0.05, 1.2], [0.4, 0.0, 0.0], [0.0, 0.3, 0.06], DOWN)
    return Spec(
        "unoccluded",
        "A tilted rectangular light over the receivers, nothing in between: smooth values and "
        "derivatives, no visibility term.",
        Scene([PolygonLight(light, [4.0, 3.5, 3.0])], ambient=[0.1, 0.1, 0.12]),
        Material(ka=0.2, kd=[0.6, 0.5, 0.4], ks=0.2, exponent=10.0),
        np.array([1.3, -0.4, 1.1]),
        Window((0.35, 0.12), 0.45, 0.35),
    )


def _penumbra() -> Spec:
    light = _rect([0.0, 0.0, 2.0], [0.5, 0.0, 0.0], [0.0, 0.5, 0.0], DOWN)
    xy = np.array([[-0.3, -1.0], [0.3, -1.0], [0.3, 1.0], [-0.3, 1.0]])
    occ = np.c_[xy, 1.0 + 0.05 * xy[:, 0]] @ _rot_z(0.1).T
    return Spec(
        "penumbra",
        "A 1 m square light at 2 m, a long strip occluder at 1 m: every receiver sees part of "
        "the light, so every derivative has a term from the moving shadow edge.",
        Scene([PolygonLight(light, [3.0, 2.6, 2.2])], occluders=[occ], ambient=0.05),
        Material(ka=0.3, kd=[0.5, 0.6, 0.7], ks=0.15, exponent=6.0),
        np.array([0.9, -0.5, 1.4]),
        Window((0.6, 0.07), 0.35, 0.4),
    )


def _umbra() -> Spec:
    light = _rect([0.05, 0.0, 2.0], [0.25, 0.0, 0.0], [0.0, 0.25, 0.0], DOWN)
    sq = _rect([0.0, 0.0, 0.0], [0.6, 0.0, 0.0], [0.0, 0.6, 0.0], DOWN) @ _rot_z(0.3).T
    return Spec(
        "umbra",
        "A small light and a large occluder: half the receivers are in the umbra (zero "
        "irradiance, zero derivatives), the others in the penumbra around it.",
        Scene([PolygonLight(light, [2.5, 2.5, 3.0])], occluders=[sq + [0.0, 0.0, 1.0]], ambient=0.2),
        Material(ka=0.25, kd=0.5, ks=0.1, exponent=4.0),
        np.array([1.5, 0.3, 1.2]),
        Window((0.75, 0.1), 0.45, 0.4),
    )


def _touching() -> Spec:
    light = _rect([0.05, 0.1, 1.5], [0.4, 0.0, 0.0], [0.0, 0.3, 0.0], DOWN)
    wall = np.array([[0.0, -0.7, 0.0], [0.0, 0.7, 0.0], [0.0, 0.7, 0.7], [0.0, -0.7, 0.7]]) @ _rot_z(0.05).T
    return Spec(
        "touching",
        "A wall standing on the receiver plane under the light: its shadow starts at the "
        "contact line, where the penumbra narrows to nothing.",
        Scene([PolygonLight(light, [3.0, 3.0, 3.0])], occluders=[wall], ambient=0.1),
        Material(ka=0.2, kd=0.55, ks=0.2, exponent=8.0),
        np.array([0.9, 0.6, 0.8]),
        Window((0.33, 0.05), 0.3, 0.25),
    )


def _grazing() -> Spec:
    light = _rect([-0.35, 0.05, 0.2], [0.0, 0.45, 0.0], [0.05, 0.0, 0.35], [1.0, 0.0, 0.0])
    return Spec(
        "grazing",
        "A light standing on edge beside the receivers and reaching below their horizon: "
        "its lower part is cut by each receiver's tangent plane, light arrives at grazing angles.",
        Scene([PolygonLight(light, [2.0, 2.0, 2.4])], ambient=0.05),
        Material(ka=0.1, kd=0.6, ks=0.3, exponent=5.0),
        np.array([-0.1, -0.8, 0.6]),
        Window((0.35, 0.05), 0.3, 0.25),
    )


def _highlight() -> Spec:
    light = _rect([0.0, 0.0, 1.4], [0.3, 0.0, 0.0], [0.0, 0.2, 0.0], DOWN)
    occ = _rect([0.35, 0.1, 0.8], [0.08, 0.02, 0.0], [-0.02, 0.08, 0.01], DOWN)
    return Spec(
        "highlight",
        "A shiny receiver (k_s = 0.6, n = 30) seen from the mirror direction of the light, "
        "with a small occluder shadowing part of the highlight.",
        Scene([PolygonLight(light, [5.0, 4.5, 4.0])], occluders=[occ], ambient=0.05),
        Material(ka=0.1, kd=[0.3, 0.3, 0.35], ks=0.6, exponent=30.0),
        np.array([1.2, 0.4, 1.0]),
        Window((0.55, 0.15), 0.35, 0.3),
    )


def _linear() -> Spec:
    occ = _rect([0.0, 0.0, 0.0], [0.15, 0.0, 0.02], [0.0, 0.6, 0.0], DOWN) @ _rot_z(0.6).T + [0.1, 0.2, 0.9]
    return Spec(
        "linear",
        "A linear light (cosine profile, m = 1) crossed by the shadow of an oblique strip occluder.",
        Scene(
            [LinearLight([-0.6, -0.1, 1.5], [0.6, 0.15, 1.6], [2.0, 1.8, 1.6], profile="cosine", exponent=1)],
            occluders=[occ],
            ambient=0.1,
        ),
        Material(ka=0.2, kd=0.6, ks=0.25, exponent=12.0),
        np.array([0.8, 1.2, 1.0]),
        Window((0.1, 0.35), 0.4, 0.35),
    )


def _box_mesh() -> Mesh:
    corners = np.array([[x, y, z] for x in (-0.25, 0.25) for y in (-0.2, 0.2) for z in (-0.15, 0.15)])
    verts = corners @ (_rot_z(0.4) @ _rot_x(0.2)).T + np.array([0.1, 0.0, 0.9])
    # Corner index = 4 * ix + 2 * iy + iz; faces counter-clockwise seen from outside.
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return Mesh(verts, tris)


def _mesh() -> Spec:
    light = _rect([-0.1, 0.05, 2.0], [0.45, 0.0, 0.0], [0.0, 0.35, 0.0], DOWN)
    return Spec(
        "mesh",
        "A closed box mesh (12 triangles, merged into 6 quads) as the occluder of a "
        "rectangular light.",
        Scene([PolygonLight(light, [3.0, 3.0, 3.0])], occluders=[_box_mesh()], ambient=0.1),
        Material(ka=0.2, kd=0.5, ks=0.2, exponent=6.0),
        np.array([1.0, -0.6, 1.2]),
        Window((0.3, 0.1), 0.5, 0.4),
    )


BUILDERS: dict[str, Callable[[], Spec]] = {
    "unoccluded": _unoccluded,
    "penumbra": _penumbra,
    "umbra": _umbra,
    "touching": _touching,
    "grazing": _grazing,
    "highlight": _highlight,
    "linear": _linear,
    "mesh": _mesh,
}


def parameters_of(scene: Scene) -> tuple[str, ...]:
    """The parameters a scene's derivatives are taken with respect to."""
    occ = OCCLUDER_PARAMETERS if scene.occluders is not None else ()
    return (*LIGHT_PARAMETERS, *occ, *MATERIAL_PARAMETERS)


def _light_points(light: Any) -> Any:
    if isinstance(light, PolygonLight):
        return light.vertices
    return jnp.stack([light.start, light.end])


def _rotation(ax: Any, ay: Any, az: Any) -> Any:
    """R = Rz Ry Rx (smooth at 0; each factor is the rotation about one axis)."""
    cx, sx, cy, sy, cz, sz = jnp.cos(ax), jnp.sin(ax), jnp.cos(ay), jnp.sin(ay), jnp.cos(az), jnp.sin(az)
    one, zero = jnp.ones_like(ax), jnp.zeros_like(ax)
    rx = jnp.array([[one, zero, zero], [zero, cx, -sx], [zero, sx, cx]])
    ry = jnp.array([[cy, zero, sy], [zero, one, zero], [-sy, zero, cy]])
    rz = jnp.array([[cz, -sz, zero], [sz, cz, zero], [zero, zero, one]])
    return rz @ ry @ rx


def apply_parameters(scene: Scene, material: Material, names: tuple[str, ...], theta: Any) -> tuple[Scene, Material]:
    """The scene and material moved by `theta` (one value per name in `names`; 0 = unchanged).

    The light moves as a rigid body about its centre (the mean of its vertices, or the
    midpoint of a segment): $v' = v + t + ((1 + s) R - I)(v - c)$, exactly $v$ at $\\theta = 0$.
    Works for concrete and traced `theta` (the scene keeps its static occluder topology).
    """
    theta = jnp.asarray(theta)
    if theta.shape != (len(names),):
        raise ValueError(f"apply_parameters: theta must have shape ({len(names)},), got {theta.shape}.")
    unknown = [n for n in names if n not in PARAMETERS]
    if unknown:
        raise ValueError(f"apply_parameters: unknown parameter(s) {unknown}; known: {list(PARAMETERS)}.")
    dt = theta.dtype
    zero = jnp.zeros((), dt)
    val = {n: theta[i] for i, n in enumerate(names)}
    get = lambda n: val.get(n, zero)  # noqa: E731
    light = scene.lights[0]
    pts = _light_points(light).astype(dt)
    c = jnp.mean(pts, axis=0)
    t = jnp.stack([get("light.tx"), get("light.ty"), get("light.tz")])
    m = (1.0 + get("light.scale")) * _rotation(get("light.rx"), get("light.ry"), get("light.rz")) - jnp.eye(3, dtype=dt)
    new = pts + t[None, :] + (pts - c[None, :]) @ m.T
    if isinstance(light, PolygonLight):
        scene = eqx.tree_at(lambda s: s.lights[0].vertices, scene, new)
    else:
        scene = eqx.tree_at(lambda s: (s.lights[0].start, s.lights[0].end), scene, (new[0], new[1]))
    if scene.occluders is not None:
        o = jnp.stack([get("occluder.tx"), get("occluder.ty"), get("occluder.tz")])
        scene = eqx.tree_at(lambda s: s.occluders, scene, scene.occluders.astype(dt) + o[None, None, :])
    grey = lambda k, n: k.astype(dt) + get(n)  # noqa: E731
    material = eqx.tree_at(
        lambda mt: (mt.ka, mt.kd, mt.ks, mt.exponent),
        material,
        (
            grey(material.ka, "material.ka"),
            grey(material.kd, "material.kd"),
            grey(material.ks, "material.ks"),
            material.exponent.astype(dt) + get("material.exponent"),
        ),
    )
    return scene, material
