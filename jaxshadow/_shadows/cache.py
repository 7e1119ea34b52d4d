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

from .._core.misc import unit_rows_host
from .._scene.model import Scene
from . import plan as sh
from .integrands import Lambert
from .options import DEFAULT_OPTIONS


def _box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.array([[(lo, hi)[(k >> d) & 1][d] for d in range(3)] for k in range(8)])


def separating_planes(verts: np.ndarray, lo: np.ndarray, hi: np.ndarray, scale: float) -> np.ndarray:
    """`(P, 4)` planes `(n, a)`, `n` unit, with `n . v <= a` on the light's points `verts (V, 3)`
    and `n . x >= a` on the box `[lo, hi]` (within `1e-12 scale`): Campbell & Fussell's minimum
    extremal planes (§3.1.2: through a light edge and a box corner, or a box edge and a light
    vertex), the light's plane and the box's faces, where they separate the two; each distinct
    plane once. A point `p` with `n . p < a - 1e-6 scale` for one of them has a hull with the
    light that misses the box (the hull lies in `n . x <= max(n . p, a)`); with the box at least
    `1e-4 scale` from the light the rounding of the planes cannot turn a meeting into a miss
    (`affected`). Empty when the box is not that far from the light."""
    c = _box_corners(lo, hi)
    nv = verts.shape[0]
    i0 = np.arange(nv)
    le = np.stack([i0, (i0 + 1) % nv], axis=1) if nv > 2 else np.array([[0, 1]]) if nv == 2 else np.zeros((0, 2), int)
    be = np.array([(i, i | (1 << d)) for i in range(8) for d in range(3) if not i & (1 << d)])
    parts = [np.eye(3), -np.eye(3)]
    if nv >= 3:
        parts.append(np.cross(verts[1] - verts[0], verts[2] - verts[0])[None])
    # Light edge (i, j) and box corner x: (v_j - v_i) x (x - v_i); box edge and light vertex alike.
    parts.append(np.cross((verts[le[:, 1]] - verts[le[:, 0]])[:, None], c[None] - verts[le[:, 0]][:, None]).reshape(-1, 3))
    parts.append(np.cross((c[be[:, 1]] - c[be[:, 0]])[:, None], verts[None] - c[be[:, 0]][:, None]).reshape(-1, 3))
    n = np.concatenate(parts)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9 * scale**2
    n = n[ok] / norm[ok, None]
    n = np.concatenate([n, -n])
    a, b = (verts @ n.T).max(axis=0), (c @ n.T).min(axis=0)
    if not np.any(b - a >= 1e-4 * scale):
        return np.zeros((0, 4))
    keep = b - a >= -1e-12 * scale
    planes = np.concatenate([n[keep], a[keep, None]], axis=1)
    _, first = np.unique(np.round(planes / (1e-9 * np.array([1, 1, 1, scale]))), axis=0, return_index=True)
    return planes[np.sort(first)]


def _plane_filter(points: np.ndarray, planes: np.ndarray, s_all: float) -> np.ndarray:
    """Indices of `points` on the box's side of every separating plane (`separating_planes`),
    most rejecting planes first (greedily, on a sample of the receivers)."""
    cand = np.arange(points.shape[0])
    if planes.shape[0] == 0:
        return cand
    sample = points[:: max(1, points.shape[0] // 256)]
    inside = sample @ planes[:, :3].T >= planes[:, 3] - 1e-6 * s_all
    order: list[int] = []
    left = np.ones(sample.shape[0], bool)
    for _ in range(planes.shape[0]):
        passing = np.count_nonzero(inside & left[:, None], axis=0).astype(np.float64)
        passing[order] = np.inf
        order.append(int(np.argmin(passing)))
        left &= inside[:, order[-1]]
    px, py, pz = points[:, 0], points[:, 1], points[:, 2]
    for k in order:
        # Column by column: a (N, 3) @ (3,) product costs ~20x as much.
        h = px * planes[k, 0] + py * planes[k, 1] + pz * planes[k, 2]
        keep = h >= planes[k, 3] - 1e-6 * s_all
        cand, px, py, pz = cand[keep], px[keep], py[keep], pz[keep]
        if cand.size == 0:
            break
    return cand


def affected(light: Any, points: np.ndarray, normals: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """`(N,)` bool: one of the boxes `[lo, hi]` (each `(3,)`, or `(G, 3)` for `G` boxes) may meet
    the receiver's illumination region of `light`.

    Cheapest tests first: per box, the planes that separate the whole light from it
    (`separating_planes`, the box's occlusion volume; one dot product per receiver and plane,
    on the receivers that are left), then the bounding box of the hull of the receiver and the
    light (exact for the separating axes x, y, z); the horizon and the pyramid's side planes only
    for receivers that pass both, the side planes computed once for all boxes. Column by column
    throughout: NumPy's `(N, 3)` products and `np.cross` cost far more than three columns."""
    lo_all, hi_all = np.atleast_2d(np.asarray(lo, np.float64)), np.atleast_2d(np.asarray(hi, np.float64))
    n_pts = points.shape[0]
    out = np.zeros(n_pts, bool)
    if n_pts == 0:
        return out
    # |p|_inf per receiver, column by column (an axis-1 reduction over three columns is slow).
    pmax = np.maximum(np.maximum(np.abs(points[:, 0]), np.abs(points[:, 1])), np.abs(points[:, 2]))
    picked = []  # per box: (receivers passing the cheap tests, the box's margin scale)
    for lo_g, hi_g in zip(lo_all, hi_all, strict=True):
        box_max = float(np.max(np.abs(np.concatenate([lo_g, hi_g]))))
        if light.kind != "directional":
            # The light's points: a polygon's vertices, a segment's ends, a point light's position.
            verts = np.concatenate([np.asarray(x, np.float64).reshape(-1, 3) for x in light.geometry])
            vlo, vhi = verts.min(axis=0), verts.max(axis=0)
            s_all = float(max(np.max(pmax), box_max, np.max(np.abs(verts)))) + 1.0
            cand = _plane_filter(points, separating_planes(verts, lo_g, hi_g, s_all), s_all)
            # The bounding box of the hull, axis by axis: min(p, vlo) <= hi + margin and
            # max(p, vhi) >= lo - margin (margin 1e-9 (|p|_inf + |box|_inf + 1) per receiver).
            mg = 1e-9 * (pmax[cand] + box_max + 1.0)
            ok = np.ones(cand.size, bool)
            for d in range(3):
                q = points[cand, d]
                ok &= (np.minimum(q, vlo[d]) <= hi_g[d] + mg) & (np.maximum(q, vhi[d]) >= lo_g[d] - mg)
            idx = cand[ok]
        else:
            d = np.asarray(light.geometry[0], np.float64)
            d = d / np.linalg.norm(d)
            # The shadow ray p - t d, t >= 0, meets the box only up to the box's far side.
            reach = np.linalg.norm(np.maximum(np.abs(lo_g), np.abs(hi_g))) + np.linalg.norm(points, axis=1)[:, None] + 1.0
            far = points - reach * d
            hull_lo, hull_hi = np.minimum(points, far), np.maximum(points, far)
            mg = (1e-9 * (pmax + box_max + 1.0))[:, None]
            idx = np.nonzero(np.all((hull_lo <= hi_g[None, :] + mg) & (hull_hi >= lo_g[None, :] - mg), axis=1))[0]
        picked.append((idx, box_max))
    union = np.unique(np.concatenate([idx for idx, _ in picked]))
    if union.size == 0:
        return out
    qx, qy, qz = points[union, 0], points[union, 1], points[union, 2]
    mx, my, mz = normals[union, 0], normals[union, 1], normals[union, 2]
    planes = [(mx, my, mz, mx * qx + my * qy + mz * qz, np.ones(union.size))]  # the horizon
    if light.kind == "polygon":
        v = np.asarray(light.vertices, np.float64)
        centre = v.mean(axis=0)
        for i in range(v.shape[0]):
            a, b = v[i], v[(i + 1) % v.shape[0]]
            ax, ay, az, bx, by, bz = a[0] - qx, a[1] - qy, a[2] - qz, b[0] - qx, b[1] - qy, b[2] - qz
            nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            side = np.sign(nx * (centre[0] - qx) + ny * (centre[1] - qy) + nz * (centre[2] - qz))
            nx, ny, nz = nx * side, ny * side, nz * side
            planes.append((nx, ny, nz, nx * qx + ny * qy + nz * qz, np.sqrt(nx * nx + ny * ny + nz * nz)))
    pos = np.full(n_pts, -1)
    pos[union] = np.arange(union.size)
    for (idx, box_max), lo_g, hi_g in zip(picked, lo_all, hi_all, strict=True):
        whole = idx.size == union.size  # (then idx is union: both sorted)
        r = slice(None) if whole else pos[idx]
        mg = 1e-9 * (pmax[idx] + box_max + 1.0)
        keep = np.ones(idx.size, bool)
        for nx, ny, nz, off, scale in planes:
            # Outside when the box's farthest corner along the normal is below the plane.
            cx, cy, cz = nx[r], ny[r], nz[r]
            far = (cx * np.where(cx >= 0, hi_g[0], lo_g[0]) + cy * np.where(cy >= 0, hi_g[1], lo_g[1])
                   + cz * np.where(cz >= 0, hi_g[2], lo_g[2]))
            keep &= ~(far - off[r] < -mg * scale[r])
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
        if not DEFAULT_OPTIONS.use_engine():
            raise RuntimeError("ShadowCache: the shadow engine (jaxshadow._shadows._shadowc) is not built.")
        from .._core.geometry import check_points_normals

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
        pl = sh.plan(scene, self._p[idx], self._n[idx], produce=Lambert.host_plan, lights=[scene.lights[light_i]])
        # The faces: segment lights clip their candidate faces (the other kinds do not read them).
        faces = np.asarray(scene.occluders, self._p.dtype)
        return np.asarray(sh.light_values(pl.lights[0], scene.lights[light_i], Lambert(), self._p[idx],
                                          self._n[idx], None, faces))

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
    return tuple(np.asarray(x) for x in light.geometry)


def _static(light: Any) -> tuple:
    return (getattr(light, "profile", None), getattr(light, "exponent", None))
