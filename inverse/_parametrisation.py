"""Light parametrisation: a flat parameter vector <-> a light of the scene, with constraints.

A polygon light is moved as a rigid body and stretched in its own plane: centre $c$, rotation
vector $\\omega$ (Rodrigues) applied to its initial frame, and log-scales $(s_x, s_y)$ of its
initial width and height (any convex polygon, a quad being the usual case). A segment light: its
midpoint, its direction (two rotation angles about axes perpendicular to it) and its log length.
A point light: its position. A directional light: its direction, turned like a segment's (a
rotation vector in the plane perpendicular to the given direction: unit by construction, smooth
around the start, no pole). Positions are measured in units of the scene size so every
parameter is O(1) for the solvers. The centre can be constrained to a `Plane` or a `Box`.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

import jaxshadow as js

from ._targets import PaintedTargets

FIT_GROUPS = ("position", "orientation", "size")


def _finite_3_vectors(what: str, a: Any, b: Any) -> tuple[np.ndarray, np.ndarray]:
    """`a`, `b` as float64 3-vectors; ValueError (naming `what`) unless both are finite."""
    x, y = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if x.shape != (3,) or y.shape != (3,) or not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError(f"{what} must be finite 3-vectors, got {x.tolist()}, {y.tolist()}.")
    return x, y


class Plane(eqx.Module):
    """Constrain the light centre to a plane (a ceiling): `point (3,)`, `normal (3,)`.

    Example:
        ```python
        import inverse

        ceiling = inverse.Plane([0.0, 0.0, 2.5], [0.0, 0.0, 1.0])
        # inverse.fit_light(scene, targets, material, constraints={0: ceiling})
        ```
    """

    point: Float[Array, "3"]
    normal: Float[Array, "3"]

    def __init__(self, point: Any, normal: Any):
        p, n = _finite_3_vectors("Plane: point and normal", point, normal)
        if np.linalg.norm(n) == 0:
            raise ValueError("Plane: the normal is the zero vector.")
        self.point = jnp.asarray(p)
        self.normal = jnp.asarray(n / np.linalg.norm(n))


class Box(eqx.Module):
    """Constrain the light centre to an axis-aligned box `lower (3,) <= c <= upper (3,)`.

    Example:
        ```python
        import inverse

        room = inverse.Box([-2.0, -2.0, 1.5], [2.0, 2.0, 3.0])
        # inverse.fit_light(scene, targets, material, constraints={0: room}, solver=inverse.LBFGSB())
        ```
    """

    lower: Float[Array, "3"]
    upper: Float[Array, "3"]

    def __init__(self, lower: Any, upper: Any):
        lo, hi = _finite_3_vectors("Box: lower and upper", lower, upper)
        if np.any(hi <= lo):
            raise ValueError(f"Box: need lower < upper in every axis, got {lo.tolist()} and {hi.tolist()}.")
        self.lower = jnp.asarray(lo)
        self.upper = jnp.asarray(hi)



def _rodrigues_coefficients(omega: Float[Array, "3"]) -> tuple[Array, Array]:
    """$a = \\sin t / t$, $b = (1 - \\cos t)/t^2$ with $t = |\\omega|$; smooth (and NaN-free in
    their derivatives) at $\\omega = 0$ via a double `where` onto the Taylor series."""
    t2 = jnp.sum(omega * omega)
    small = t2 < 1e-8
    t2s = jnp.where(small, 1.0, t2)
    t = jnp.sqrt(t2s)
    a = jnp.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - jnp.cos(t)) / t2s)
    return a, b


def rotation_matrix(omega: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """Rodrigues: the rotation by angle $|\\omega|$ about $\\omega$, $I + aK + bK^2$
    (`_rodrigues_coefficients`; smooth at $\\omega = 0$).

    Example:
        ```python
        import jax.numpy as jnp
        import inverse

        R = inverse.rotation_matrix(jnp.array([0.0, 0.0, jnp.pi / 2]))   # 90 degrees about z
        ```
    """
    a, b = _rodrigues_coefficients(omega)
    K = jnp.array([[0.0, -omega[2], omega[1]], [omega[2], 0.0, -omega[0]], [-omega[1], omega[0], 0.0]],
                  dtype=omega.dtype)
    return jnp.eye(3, dtype=omega.dtype) + a * K + b * (K @ K)


def _cross_rows(o: Float[Array, "3"], w: Float[Array, "K 3"]) -> Float[Array, "K 3"]:
    """$\\omega \\times w_i$ for each row, elementwise (no `jnp.cross`, no dot)."""
    wx, wy, wz = w[:, 0], w[:, 1], w[:, 2]
    return jnp.stack([o[1] * wz - o[2] * wy, o[2] * wx - o[0] * wz, o[0] * wy - o[1] * wx], axis=-1)


def rotate_rows(omega: Float[Array, "3"], w: Float[Array, "K 3"]) -> Float[Array, "K 3"]:
    """`w @ rotation_matrix(omega).T`, as $w + a\\,\\omega\\times w + b\\,\\omega\\times(\\omega\\times w)$
    in elementwise operations: inside a fit this runs under `jvp` and the batching of the
    tangents, where matrix products of 3-vectors compile to one small kernel each (the light's
    value-and-Jacobian program: 17 kernels instead of 29 fusions and 8 dots)."""
    a, b = _rodrigues_coefficients(omega)
    c1 = _cross_rows(omega, w)
    return w + a * c1 + b * _cross_rows(omega, c1)


def _frame(light: Any) -> tuple[np.ndarray, np.ndarray]:
    """Centre and orthonormal frame (columns u, v, normal) of a polygon light."""
    v = np.asarray(light.vertices, np.float64)
    c = v.mean(axis=0)
    nrm = np.sum(np.cross(v, np.roll(v, -1, axis=0)), axis=0)
    nrm /= np.linalg.norm(nrm)
    e = v[1] - v[0]
    u = e - (e @ nrm) * nrm
    u /= np.linalg.norm(u)
    return c, np.stack([u, np.cross(nrm, u), nrm], axis=1)


def _perp_basis(d: np.ndarray) -> np.ndarray:
    a = np.eye(3)[int(np.argmin(np.abs(d)))]
    u = np.cross(d, a)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(d, u)], axis=0)  # (2, 3)


class LightParametrisation(eqx.Module):
    """Flat parameter vector <-> light, for one light of a scene. Built by `fit_light`.

    `names` lists the parameters; positions are in units of `scale` (m) relative to the
    reference (or the plane origin / box), rotations in radians, sizes as log factors.
    """

    kind: str = eqx.field(static=True)
    fit: tuple = eqx.field(static=True)
    constraint: str = eqx.field(static=True)
    box_map: str = eqx.field(static=True)  # "sigmoid" (LM) or "affine" (L-BFGS-B bounds)
    light_index: int = eqx.field(static=True)
    names: tuple = eqx.field(static=True)
    template: Any
    c0: Array
    frame0: Array
    local: Array
    scale: Array
    plane_e: Array
    box_lo: Array
    box_hi: Array

    def __init__(self, light: Any, light_index: int, fit: tuple, constraint: Any, scale: float,
                 box_map: str):
        self.light_index = light_index
        self.fit = tuple(g for g in FIT_GROUPS if g in fit)
        self.box_map = box_map
        self.template = light
        self.scale = jax.device_put(scale)
        if isinstance(light, js.PolygonLight):
            self.kind = "polygon"
            c, R = _frame(light)
            self.local = jax.device_put((np.asarray(light.vertices, np.float64) - c) @ R)
            self.frame0 = jax.device_put(R)
        elif isinstance(light, js.LinearLight):
            self.kind = "linear"
            a, b = np.asarray(light.start, np.float64), np.asarray(light.end, np.float64)
            c = 0.5 * (a + b)
            d = (b - a) / np.linalg.norm(b - a)
            self.frame0 = jax.device_put(np.concatenate([_perp_basis(d), d[None]], axis=0))  # rows u, v, d
            self.local = jax.device_put(np.linalg.norm(b - a))
        elif isinstance(light, js.PointLight):
            self.kind = "point"
            c = np.asarray(light.position, np.float64)
            self.frame0 = jax.device_put(np.eye(3))
            self.local = jax.device_put(np.zeros(()))
            bad = [g for g in self.fit if g != "position"]
            if bad:
                raise ValueError(f"fit_light: a point light has only a position; cannot fit {bad}.")
        elif isinstance(light, js.DirectionalLight):
            self.kind = "directional"
            d = np.asarray(light.direction, np.float64)
            d = d / np.linalg.norm(d)
            c = np.zeros(3)
            self.frame0 = jax.device_put(np.concatenate([_perp_basis(d), d[None]], axis=0))  # rows u, v, d
            self.local = jax.device_put(np.zeros(()))
            bad = [g for g in self.fit if g != "orientation"]
            if bad:
                raise ValueError(f"fit_light: a directional light has only a direction; cannot fit {bad}.")
            if constraint is not None:
                raise ValueError(f"fit_light: light {light_index} is a DirectionalLight: it has no position to "
                                 "constrain.")
        else:
            raise ValueError(
                f"fit_light: light {light_index} is a {type(light).__name__}; only PolygonLight, "
                "LinearLight, PointLight and DirectionalLight can be placed."
            )
        # Host arrays put on the device (eager jnp.zeros/ones would compile one op each).
        self.box_lo = jax.device_put(np.zeros(3))
        self.box_hi = jax.device_put(np.ones(3))
        self.plane_e = jax.device_put(np.zeros((2, 3)))
        if constraint is None:
            self.constraint = "none"
        elif isinstance(constraint, Plane):
            self.constraint = "plane"
            m = np.asarray(constraint.normal)
            p0 = np.asarray(constraint.point)
            c = c - ((c - p0) @ m) * m  # project the reference centre onto the plane
            self.plane_e = jnp.asarray(_perp_basis(m))
        elif isinstance(constraint, Box):
            self.constraint = "box"
            self.box_lo = constraint.lower
            self.box_hi = constraint.upper
            c = np.clip(c, np.asarray(constraint.lower), np.asarray(constraint.upper))
        else:
            raise ValueError(f"fit_light: constraint must be None, Plane or Box, got {type(constraint).__name__}.")
        self.c0 = jax.device_put(np.asarray(c))
        names = []
        if "position" in self.fit:
            names += ["a", "b"] if self.constraint == "plane" else ["x", "y", "z"]
        if "orientation" in self.fit:
            names += ["rx", "ry", "rz"] if self.kind == "polygon" else ["ru", "rv"]
        if "size" in self.fit:
            names += ["log_sx", "log_sy"] if self.kind == "polygon" else ["log_length"]
        if not names:
            raise ValueError(f"fit_light: nothing to fit; fit must be a non-empty subset of {FIT_GROUPS}.")
        self.names = tuple(names)

    @property
    def size(self) -> int:
        return len(self.names)

    def _slices(self) -> dict:
        out, i = {}, 0
        for g in self.fit:
            k = {"position": 2 if self.constraint == "plane" else 3,
                 "orientation": 3 if self.kind == "polygon" else 2,
                 "size": 2 if self.kind == "polygon" else 1}[g]
            out[g] = slice(i, i + k)
            i += k
        return out

    def centre_of(self, theta: Array) -> Array:
        dt = theta.dtype
        c0, s = self.c0.astype(dt), self.scale.astype(dt)
        sl = self._slices()
        if "position" not in sl:
            return c0
        z = theta[sl["position"]]
        if self.constraint == "plane":
            return c0 + s * (z @ self.plane_e.astype(dt))
        if self.constraint == "box" and self.box_map == "sigmoid":
            lo, hi = self.box_lo.astype(dt), self.box_hi.astype(dt)
            return lo + (hi - lo) * jax.nn.sigmoid(z)
        return c0 + s * z

    def theta0(self, dtype: Any) -> Array:
        """Parameters of the reference light (all zeros except a sigmoid box position)."""
        th = np.zeros(self.size)
        sl = self._slices()
        if "position" in sl and self.constraint == "box" and self.box_map == "sigmoid":
            lo, hi = np.asarray(self.box_lo), np.asarray(self.box_hi)
            f = np.clip((np.asarray(self.c0) - lo) / (hi - lo), 1e-3, 1 - 1e-3)
            th[sl["position"]] = np.log(f / (1 - f))
        return jnp.asarray(th, dtype=dtype)

    def build(self, theta: Array) -> Any:
        """The light for parameters `theta (P,)` (traceable)."""
        dt = theta.dtype
        sl = self._slices()
        c = self.centre_of(theta)
        if self.kind == "point":
            return js.PointLight(c, self.template.intensity.astype(dt))
        if self.kind == "polygon":
            # verts = c + rotate(R0 (f * local)): the frame's columns weighted by the local
            # coordinates, as broadcasts (no matrix products; see `rotate_rows`).
            R0 = self.frame0.astype(dt)
            local = self.local.astype(dt)
            lx, ly = local[:, 0:1], local[:, 1:2]
            if "size" in sl:
                f = jnp.exp(theta[sl["size"]])
                lx, ly = lx * f[0], ly * f[1]
            w = lx * R0[:, 0][None, :] + ly * R0[:, 1][None, :] + local[:, 2:3] * R0[:, 2][None, :]
            if "orientation" in sl:
                w = rotate_rows(theta[sl["orientation"]], w)
            return js.PolygonLight(c[None, :] + w, self.template.radiance.astype(dt))
        F = self.frame0.astype(dt)
        d = F[2]
        if "orientation" in sl:
            d = rotation_matrix(theta[sl["orientation"]] @ F[:2]) @ d
        if self.kind == "directional":
            return js.DirectionalLight(d, self.template.irradiance.astype(dt))
        length = self.local.astype(dt)
        if "size" in sl:
            length = length * jnp.exp(theta[sl["size"]][0])
        half = 0.5 * length * d
        t = self.template
        return js.LinearLight(c - half, c + half, t.power.astype(dt), t.profile, t.exponent)

    def lbfgsb_bounds(self, dtype: Any) -> tuple[Array, Array]:
        lo = np.full(self.size, -np.inf)
        hi = np.full(self.size, np.inf)
        sl = self._slices()
        if "position" in sl and self.constraint == "box":
            s = float(self.scale)
            lo[sl["position"]] = (np.asarray(self.box_lo) - np.asarray(self.c0)) / s
            hi[sl["position"]] = (np.asarray(self.box_hi) - np.asarray(self.c0)) / s
        if "orientation" in sl:
            lo[sl["orientation"]], hi[sl["orientation"]] = -np.pi, np.pi
        if "size" in sl:
            lo[sl["size"]], hi[sl["size"]] = np.log(1e-3), np.log(1e3)
        big = 1e6
        return jax.device_put(np.asarray(np.clip(lo, -big, big), dtype)), jax.device_put(np.asarray(np.clip(hi, -big, big), dtype))


def with_light(scene: js.Scene, index: int, light: Any) -> js.Scene:
    """The scene with light `index` replaced."""
    return eqx.tree_at(lambda s: s.lights[index], scene, light)


def scene_size(scene: js.Scene, targets: PaintedTargets) -> float:
    """Diagonal (m) of the bounding box of targets, lights and occluders.

    Example:
        ```python
        import numpy as np
        import jaxshadow as js
        import inverse

        scene = js.Scene([js.PointLight([0.0, 0.0, 2.0], 1.0)])
        targets = inverse.PaintedTargets(np.zeros((1, 3)), [[0, 0, 1.0]], [[0.2, 0.2, 0.2]], eye=[0, -1, 1.0])
        inverse.scene_size(scene, targets)   # 2.0 m: the unit of a fit's position parameters
        ```
    """
    pts = [np.asarray(targets.points, np.float64)]
    for light in scene.lights:
        if isinstance(light, js.PolygonLight):
            pts.append(np.asarray(light.vertices, np.float64))
        elif isinstance(light, js.LinearLight):
            pts.append(np.stack([np.asarray(light.start), np.asarray(light.end)]).astype(np.float64))
        elif isinstance(light, js.PointLight):
            pts.append(np.asarray(light.position, np.float64)[None])
    if scene.occluders is not None:
        pts.append(np.asarray(scene.occluders, np.float64).reshape(-1, 3))
    p = np.concatenate(pts)
    return float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))


class Outside(eqx.Module):
    """Keep a light's centre outside a solid object made of occluders: the convex hull of the
    vertices of the scene's occluders `occluders` (indices into `scene.occluders`, at least
    four non-coplanar vertices), by at least `margin` (m). For `fit_lights(constraints={j:
    inverse.Outside([...])})`: the light's centre (a point light's position, a polygon's or a
    segment's centre; not its vertices) pays a hinge penalty in the solve for every metre it
    is inside, and the fitted centre, if still inside, is moved out through the nearest face of
    the hull (the face whose plane it is closest to): the result is outside by `margin` up to
    rounding, and the powers are solved again there.

    Example:
        ```python
        import inverse

        lamp_outside_box = inverse.Outside([0, 1, 2, 3, 4, 5], margin=0.05)   # a box of 6 quads
        # inverse.fit_lights(scene, targets, material, constraints={0: lamp_outside_box})
        ```
    """

    occluders: tuple = eqx.field(static=True)
    margin: float = eqx.field(static=True, default=0.0)

    def __init__(self, occluders: Any, margin: float = 0.0):
        idx = np.atleast_1d(np.asarray(occluders))
        if idx.ndim != 1 or idx.size == 0 or not np.issubdtype(idx.dtype, np.integer):
            raise ValueError(f"Outside: occluders must be a non-empty list of occluder indices, got {occluders!r}.")
        m = float(margin)
        if not np.isfinite(m) or m < 0:
            raise ValueError(f"Outside: margin must be finite and >= 0 (m), got {margin!r}.")
        self.occluders = tuple(int(i) for i in idx)
        self.margin = m


def outside_planes(scene: js.Scene, outside: Outside) -> tuple[np.ndarray, np.ndarray]:
    """`(normals (F, 3), offsets (F,))` of the faces of the convex hull of the occluders of
    `outside`: a point `c` is inside when `normals @ c + offsets < 0` for every face (unit
    outward normals, so `max(normals @ c + offsets)` is minus the distance to the nearest face
    plane inside). ValueError for an index out of range or a hull with no volume."""
    from scipy.spatial import ConvexHull, QhullError

    occ = [] if scene.occluders is None else list(scene.occluders)
    bad = [i for i in outside.occluders if not 0 <= i < len(occ)]
    if bad:
        raise ValueError(f"Outside: occluder index(es) {bad} out of range (the scene has {len(occ)}).")
    pts = np.concatenate([np.asarray(occ[i], np.float64).reshape(-1, 3) for i in outside.occluders])
    pts = pts[np.all(np.isfinite(pts), axis=1)]  # padded vertices, if any
    try:
        hull = ConvexHull(pts)
    except QhullError:
        raise ValueError(f"Outside: the occluders {list(outside.occluders)} span no volume (flat or too few "
                         "vertices): a light cannot be inside them.") from None
    return hull.equations[:, :3].copy(), hull.equations[:, 3].copy()
