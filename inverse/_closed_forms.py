"""Closed-form light initialisers from painted cues (Poulin §5.2).

- §5.2.1 diffuse maximum: the light lies along the normal at the brightest diffuse point
  ($\\vec L = \\vec N$); with a plane constraint (a ceiling) the ray meets the plane at the light.
- §5.2.2 highlight: the light lies along the mirror direction $\\vec L = 2(\\vec N\\cdot\\vec E)
  \\vec N - \\vec E$; a second point on the highlight boundary, where the lobe falls to a
  threshold $t$, gives the roughness $n = \\log t / \\log(\\vec N\\cdot\\vec H)$ (eq. 5.13).
- §5.2.3 shadow: a shadow point and the occluder point casting it fix a line through the light;
  two or more such lines meet at a point light (least squares when they do not meet exactly).

Plain NumPy (float64): these produce starting points for `fit_light`, not differentiable values.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np


def _unit(x: Any, name: str) -> np.ndarray:
    v = np.asarray(x, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be a finite 3-vector, got {v.tolist()}.")
    n = np.linalg.norm(v)
    if n == 0:
        raise ValueError(f"{name} is the zero vector.")
    return v / n


def _vec(x: Any, name: str) -> np.ndarray:
    v = np.asarray(x, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be a finite 3-vector, got {np.asarray(x).tolist()}.")
    return v


@dataclasses.dataclass(frozen=True)
class LightRay:
    """A ray the light lies on: `origin (3,)`, unit `direction (3,)`; `position (3,)` where it
    meets the constraint plane (None without a plane)."""

    origin: np.ndarray
    direction: np.ndarray
    position: np.ndarray | None


def intersect_plane(origin: Any, direction: Any, plane_point: Any, plane_normal: Any) -> np.ndarray:
    """Point where the ray `origin + t direction`, `t > 0`, meets a plane.

    Raises `ValueError` when the ray is parallel to the plane or points away from it
    (Poulin §5.2.1 footnote 3: "there might not be any intersection").

    Example:
        ```python
        import inverse

        inverse.intersect_plane([0, 0, 0], [0, 0, 1], [0, 0, 2.5], [0, 0, 1])   # array([0., 0., 2.5])
        ```
    """
    o = _vec(origin, "origin")
    d = _unit(direction, "direction")
    p0 = _vec(plane_point, "plane_point")
    m = _unit(plane_normal, "plane_normal")
    den = float(d @ m)
    if abs(den) < 1e-12:
        raise ValueError("the light ray is parallel to the constraint plane: no intersection.")
    t = float((p0 - o) @ m) / den
    if t <= 0:
        raise ValueError("the light ray points away from the constraint plane: no intersection.")
    return o + t * d


def _ray(origin, direction, plane) -> LightRay:
    pos = None if plane is None else intersect_plane(origin, direction, *plane)
    return LightRay(origin=np.asarray(origin, np.float64), direction=direction, position=pos)


def light_from_diffuse_maximum(point: Any, normal: Any, plane: tuple | None = None) -> LightRay:
    """Poulin §5.2.1: at a painted diffuse maximum the light direction is the normal.

    **Arguments:** `point (3,)`, `normal (3,)`; `plane = (plane_point (3,), plane_normal (3,))`
    to place the light where the normal ray meets it.

    **Returns:** `LightRay` (direction $\\vec L = \\vec N$).

    Example:
        ```python
        import inverse

        ray = inverse.light_from_diffuse_maximum([0.4, 0.2, 0.0], [0.0, 0.6, 0.8], plane=([0, 0, 2.0], [0, 0, 1.0]))
        ray.position   # where the normal ray meets the ceiling z = 2
        ```
    """
    p = _vec(point, "point")
    return _ray(p, _unit(normal, "normal"), plane)


def mirror_direction(normal: Any, to_eye: Any) -> np.ndarray:
    """$\\vec L = 2(\\vec N\\cdot\\vec E)\\vec N - \\vec E$ (unit), the light direction whose
    highlight peaks at a point (Poulin §5.2.2).

    Example:
        ```python
        import inverse

        inverse.mirror_direction([0.0, 0.0, 1.0], [0.0, -1.0, 1.0])   # array([0., 0.707, 0.707])
        ```
    """
    n = _unit(normal, "normal")
    e = _unit(to_eye, "to_eye")
    return 2.0 * float(n @ e) * n - e


def light_from_highlight(point: Any, normal: Any, eye: Any, plane: tuple | None = None) -> LightRay:
    """Poulin §5.2.2: at the painted highlight maximum $\\vec H = \\vec N$, so the light lies
    along the mirror direction of the eye.

    **Arguments:** `point (3,)`, `normal (3,)`, `eye (3,)` position; optional `plane`.

    **Returns:** `LightRay`.

    Example:
        ```python
        import inverse

        ray = inverse.light_from_highlight([0, 0, 0], [0, 0, 1], eye=[0, -2, 2], plane=([0, 0, 3.0], [0, 0, 1.0]))
        ray.position   # array([0., 3., 3.])
        ```
    """
    p = _vec(point, "point")
    e = _vec(eye, "eye") - p
    n = _unit(normal, "normal")
    if float(n @ e) <= 0:
        raise ValueError("light_from_highlight: the eye is below the surface at the highlight point.")
    return _ray(p, mirror_direction(n, e), plane)


def exponent_from_highlight(boundary_point: Any, boundary_normal: Any, eye: Any, light: Any,
                            threshold: float) -> float:
    """Poulin eq. 5.13: $n = \\log t / \\log(\\vec N\\cdot\\vec H)$ at a highlight boundary point.

    **Arguments:**

    - `boundary_point (3,)`, `boundary_normal (3,)`: where the user drags the highlight edge.
    - `eye (3,)`: eye position.
    - `light (3,)`: the light position (a point light or the light's centre).
    - `threshold`: $t \\in (0, 1)$, the lobe value $(\\vec N\\cdot\\vec H)^n$ at the boundary.

    **Returns:** the Phong exponent $n$ (the highlight's size sets the roughness).

    Example:
        ```python
        import inverse

        n = inverse.exponent_from_highlight([0.3, 0, 0], [0, 0, 1], eye=[0, -2, 2], light=[0, 2, 2], threshold=0.5)
        ```
    """
    if not 0.0 < float(threshold) < 1.0:
        raise ValueError(f"exponent_from_highlight: threshold must be in (0, 1), got {threshold!r}.")
    p = _vec(boundary_point, "boundary_point")
    n = _unit(boundary_normal, "boundary_normal")
    v = _unit(_vec(eye, "eye") - p, "eye - boundary_point")
    l_ = _unit(_vec(light, "light") - p, "light - boundary_point")
    h = _unit(v + l_, "half vector")
    nh = float(n @ h)
    if not 0.0 < nh < 1.0:
        raise ValueError(
            f"exponent_from_highlight: N.H = {nh:.6g} at the boundary point; it must be in (0, 1) "
            "(the point must be off the highlight maximum and face the half vector)."
        )
    return float(np.log(threshold) / np.log(nh))


def light_from_shadow(occluder_point: Any, shadow_point: Any, plane: tuple | None = None) -> LightRay:
    """Poulin §5.2.3: a shadow point and the occluder point casting it (a silhouette vertex;
    for an area light, a point on the umbra/penumbra boundary and the vertex it comes from) fix
    the line through the light.

    **Returns:** `LightRay` from the shadow point through the occluder point (towards the light).

    Example:
        ```python
        import inverse

        ray = inverse.light_from_shadow([0.5, 0.5, 1.0], [0.0, 0.0, 0.0], plane=([0, 0, 2.0], [0, 0, 1.0]))
        ray.position   # array([1., 1., 2.])
        ```
    """
    s = _vec(shadow_point, "shadow_point")
    o = _vec(occluder_point, "occluder_point")
    return _ray(s, _unit(o - s, "occluder_point - shadow_point"), plane)


def point_from_shadows(occluder_points: Any, shadow_points: Any) -> tuple[np.ndarray, float]:
    """Poulin §5.2.3 (fig. 5.35): the point light where two or more shadow lines meet.

    The least-squares point closest to every line (exact when they meet), by the normal
    equations $\\sum_i (I - d_i d_i^T) x = \\sum_i (I - d_i d_i^T) s_i$.

    **Arguments:** `occluder_points (M, 3)`, `shadow_points (M, 3)`, `M >= 2`, not all parallel.

    **Returns:** `(position (3,), rms distance of the position from the lines)`.

    Example:
        ```python
        import inverse

        position, rms = inverse.point_from_shadows([[0.5, 0.5, 1.0], [0.0, 0.5, 1.0]], [[0, 0, 0], [-1.0, 0, 0]])
        # position = [1, 1, 2]: the point light both shadow lines meet at; rms = 0
        ```
    """
    o = np.asarray(occluder_points, np.float64)
    s = np.asarray(shadow_points, np.float64)
    if o.ndim != 2 or o.shape != s.shape or o.shape[1] != 3 or o.shape[0] < 2:
        raise ValueError(
            f"point_from_shadows: need (M, 3) occluder and shadow points with M >= 2, got {o.shape} and {s.shape}."
        )
    d = o - s
    ln = np.linalg.norm(d, axis=1)
    if np.any(ln == 0):
        i = int(np.argmax(ln == 0))
        raise ValueError(f"point_from_shadows: pair {i} has the occluder point on the shadow point.")
    d = d / ln[:, None]
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    A = P.sum(axis=0)
    b = np.einsum("mij,mj->i", P, s)
    if np.linalg.cond(A) > 1e10:
        raise ValueError("point_from_shadows: the shadow lines are (nearly) parallel; they do not fix a point.")
    x = np.linalg.solve(A, b)
    dist = np.linalg.norm(np.einsum("mij,mj->mi", P, x[None] - s), axis=1)
    return x, float(np.sqrt(np.mean(dist**2)))
