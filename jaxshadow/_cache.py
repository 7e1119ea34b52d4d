r"""Incremental shadows: exact values at fixed receivers, updated when the scene is edited.

Chrysanthou & Slater (§3) keep per-receiver occluder data so that moving, adding or deleting one
object updates only what that object can affect. Here the unit is a receiver and a light: its
value depends only on the light and on the occluders that meet its illumination region, the
convex hull of the receiver and the light (for a polygon light the pyramid of Campbell &
Fussell's Theorem 2, for a segment the light triangle of Poulin §4.2, for point and directional
lights the shadow ray). `ShadowCache` keeps every receiver's contribution of every light. An
edit (`update`) compares the new scene with the old one:

- occluder faces that changed (moved, reshaped, switched on or off): only the receivers whose
  illumination region meets the changed faces' bounding box, before or after the edit, are
  re-evaluated, for every light; the others keep their values;
- a light that changed (moved, resized): that light's contributions are re-evaluated for every
  receiver (the occluder hierarchy does not depend on the light), the other lights' are kept;
- only emission changed: nothing is re-evaluated, the contributions are re-weighted.

A re-evaluated receiver runs through exactly the code of a fresh evaluation (`_shadows.plan`
and `light_values` on that receiver), so the updated values are those of a rebuild; the tests
check them bit for bit. The affected-receiver test is conservative (a bounding box against the
region's bounding planes, with a rounding margin): it may re-evaluate a receiver that did not
need it, never skip one that did. Adding or deleting an occluder without changing the array
shapes is a switch: a face collapsed to a point (every vertex equal) blocks nothing.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from . import _shadows as sh
from ._misc import unit_rows_host
from ._scene import LinearLight, PointLight, PolygonLight, Scene


def _box_outside_planes(lo: np.ndarray, hi: np.ndarray, normals: np.ndarray, offsets: np.ndarray,
                        margin: np.ndarray) -> np.ndarray:
    """Per row: the box `[lo, hi]` lies strictly on the negative side of plane `normals . x >= offsets`
    (its farthest corner along the normal is below `-margin`)."""
    # Column by column (an (N, 3) where/einsum costs ~3x as much).
    far = sum(normals[:, d] * np.where(normals[:, d] >= 0, hi[d], lo[d]) for d in range(3))
    return far - offsets < -margin


def affected(light: Any, points: np.ndarray, normals: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """`(N,)` bool: the box `[lo, hi]` may meet the receiver's illumination region of `light`.

    Cheapest test first: the bounding box of the hull of the receiver and the light (exact for
    the separating axes x, y, z); the horizon and the pyramid's side planes only for receivers
    that pass it."""
    absmax = np.maximum(np.maximum(np.abs(points[:, 0]), np.abs(points[:, 1])), np.abs(points[:, 2]))
    scale = absmax + np.max(np.abs(np.concatenate([lo, hi]))) + 1.0
    margin = 1e-9 * scale
    if isinstance(light, (PolygonLight, LinearLight, PointLight)):
        if isinstance(light, PointLight):
            verts = np.asarray(light.position, np.float64)[None, :]
        else:
            verts = np.asarray(light.vertices if isinstance(light, PolygonLight) else np.stack([light.start, light.end]),
                               np.float64)
        vlo, vhi = verts.min(axis=0), verts.max(axis=0)
        # Axis by axis on (N,) columns (no (N, 3) temporaries): min(p, vlo) <= hi + margin and
        # max(p, vhi) >= lo - margin.
        hit = np.ones(points.shape[0], bool)
        for d in range(3):
            col = points[:, d]
            hit &= np.minimum(col, vlo[d]) <= hi[d] + margin
            hit &= np.maximum(col, vhi[d]) >= lo[d] - margin
    else:
        d = np.asarray(light.direction, np.float64)
        d = d / np.linalg.norm(d)
        # The shadow ray p - t d, t >= 0, meets the box only up to the box's far side.
        reach = np.linalg.norm(np.maximum(np.abs(lo), np.abs(hi))) + np.linalg.norm(points, axis=1)[:, None] + 1.0
        far = points - reach * d
        hull_lo, hull_hi = np.minimum(points, far), np.maximum(points, far)
        hit = np.all((hull_lo <= hi[None, :] + margin[:, None]) & (hull_hi >= lo[None, :] - margin[:, None]), axis=1)
    idx = np.nonzero(hit)[0]
    q, m, mg = points[idx], normals[idx], margin[idx]
    keep = ~_box_outside_planes(lo, hi, m, np.einsum("nd,nd->n", m, q), mg)
    if isinstance(light, PolygonLight):
        v = np.asarray(light.vertices, np.float64)
        centre = v.mean(axis=0)
        for i in range(v.shape[0]):
            a, b = v[i], v[(i + 1) % v.shape[0]]
            nrm = np.cross(a - q, b - q)
            side = np.sign(np.einsum("nd,nd->n", nrm, centre - q))[:, None]
            nrm = nrm * side
            keep &= ~_box_outside_planes(lo, hi, nrm, np.einsum("nd,nd->n", nrm, q), mg * np.linalg.norm(nrm, axis=1))
    out = np.zeros(points.shape[0], bool)
    out[idx[keep]] = True
    return out


class ShadowCache:
    """Exact irradiance at fixed receivers, kept up to date as the scene is edited.

    **Arguments:**

    - `scene`: a `Scene` with occluders (meshes, polygons) and any lights.
    - `points`, `normals`: `(N, 3)` concrete receivers and normals.

    **Attributes:** `irradiance` `(N, 3)` (W/m^2, as `jaxshadow.irradiance`), `scene`,
    `last_update` (a dict: receivers re-evaluated per light, changed faces and lights, seconds).

    `update(new_scene)` returns the cache for the edited scene (same light count and kinds, same
    occluder array shape and topology: e.g. a mesh moved, reshaped or collapsed to switch it off);
    any other change raises `ValueError` (build a new cache). The updated values equal a fresh
    evaluation's exactly.
    """

    def __init__(self, scene: Scene, points: Any, normals: Any):
        if not isinstance(scene, Scene) or scene.occluders is None:
            raise ValueError("ShadowCache: needs a jaxshadow.Scene with occluders.")
        if not sh.DEFAULT_OPTIONS.use_engine():
            raise RuntimeError("ShadowCache: the shadow engine (jaxshadow._shadowc) is not built.")
        from ._geometry import check_points_normals

        p, n = check_points_normals(points, normals, "ShadowCache")
        self._p = np.ascontiguousarray(np.asarray(p))
        self._n = np.ascontiguousarray(unit_rows_host(n))
        self.scene = scene
        t = time.perf_counter()
        self._g = [self._evaluate(scene, light_i, np.arange(self._p.shape[0])) for light_i in range(len(scene.lights))]
        self._combine()
        self.last_update = {"kind": "build", "seconds": time.perf_counter() - t,
                            "receivers": [self._p.shape[0]] * len(scene.lights)}

    def _evaluate(self, scene: Scene, light_i: int, idx: np.ndarray) -> np.ndarray:
        """The contribution per unit emission of light `light_i` at receivers `idx` (fresh)."""
        if idx.size == 0:
            return np.zeros(0, self._p.dtype)
        pl = sh.plan(scene, self._p[idx], self._n[idx], codes=False, decoded=False, lights=[scene.lights[light_i]],
                     lambert=True)
        return np.asarray(sh.light_values(pl.lights[0], scene.lights[light_i], sh.Lambert(), self._p[idx],
                                          self._n[idx], self._p[idx], None, True))

    def _combine(self) -> None:
        # The same compiled sum as `jaxshadow.irradiance`'s (so the two agree bit for bit).
        gs = np.asarray(self._g, self._p.dtype).reshape(len(self._g), self._p.shape[0])
        self.irradiance = np.asarray(sh.sum_lights(gs, self.scene.lights, self._p.dtype))

    def update(self, scene: Scene) -> ShadowCache:
        """Edit the scene: re-evaluate only the receivers and lights the change can affect."""
        old = self.scene
        if not isinstance(scene, Scene) or scene.occluders is None:
            raise ValueError("ShadowCache.update: needs a jaxshadow.Scene with occluders.")
        if len(scene.lights) != len(old.lights) or any(
                type(a) is not type(b) for a, b in zip(scene.lights, old.lights, strict=True)):
            raise ValueError("ShadowCache.update: the lights must be the same kinds in the same order; build a new cache.")
        assert old.occluders is not None
        if scene.occluders.shape != old.occluders.shape or scene.occluder_topology != old.occluder_topology:
            raise ValueError("ShadowCache.update: the occluders changed shape or topology (faces merged differently, "
                             "meshes added or removed); build a new cache, or switch occluders off by collapsing them.")
        t = time.perf_counter()
        f_old, f_new = np.asarray(old.occluders, np.float64), np.asarray(scene.occluders, np.float64)
        changed = np.nonzero(np.any(f_old != f_new, axis=(1, 2)))[0]
        counts = []
        changed_lights = []
        for i, (la, lb) in enumerate(zip(old.lights, scene.lights, strict=True)):
            geom_a, geom_b = _geometry(la), _geometry(lb)
            if any(not np.array_equal(x, y) for x, y in zip(geom_a, geom_b, strict=True)) or _static(la) != _static(lb):
                idx = np.arange(self._p.shape[0])
                changed_lights.append(i)
            elif changed.size:
                lo = np.minimum(f_old[changed].min(axis=(0, 1)), f_new[changed].min(axis=(0, 1)))
                hi = np.maximum(f_old[changed].max(axis=(0, 1)), f_new[changed].max(axis=(0, 1)))
                idx = np.nonzero(affected(lb, self._p, self._n, lo, hi))[0]
            else:
                idx = np.zeros(0, np.int64)
            g = self._g[i].copy()
            g[idx] = self._evaluate(scene, i, idx)
            self._g[i] = g
            counts.append(int(idx.size))
        self.scene = scene
        self._combine()
        self.last_update = {"kind": "update", "seconds": time.perf_counter() - t, "receivers": counts,
                            "changed_faces": int(changed.size), "changed_lights": changed_lights}
        return self


def _geometry(light: Any) -> tuple:
    if isinstance(light, PolygonLight):
        return (np.asarray(light.vertices),)
    if isinstance(light, LinearLight):
        return (np.asarray(light.start), np.asarray(light.end))
    if isinstance(light, PointLight):
        return (np.asarray(light.position),)
    return (np.asarray(light.direction),)


def _static(light: Any) -> tuple:
    return (getattr(light, "profile", None), getattr(light, "exponent", None))
