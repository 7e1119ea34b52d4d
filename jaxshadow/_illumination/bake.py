r"""Bake a whole scene: every receiving surface meshed, exact irradiance per light at the vertices.

Campbell & Fussell's system ends in "a collection of smooth-shaded polygonal facets that may be
rendered from any viewing position" (abstract, §3.3, §4.4). `bake` produces that for every
receiving surface of a scene:

1. **Surfaces into patches.** The receivers' vertices are welded (within `weld` of the scene's
   size: Mitsuba's float32 transforms put a wall's corner 6e-8 away from the floor's). Faces
   whose vertex normals equal their face normal are *flat*: coplanar connected flat faces are
   merged into one convex polygon where their union is one (else each triangle stays a polygon);
   every polygon is a *planar patch*, meshed by `illumination_mesh` (discontinuity lines,
   extrema, adaptive refinement). The other faces of a surface form one *curved patch*, refined
   on its own triangles (`_refine_curved`): 1-to-4 splits where an edge midpoint's or the
   centroid's exact value misses linear interpolation by more than `tol`, bisection of the
   neighbours across a split edge (red-green closure), so the patch stays conforming.
2. **Chunks.** Each patch is one independent chunk: its mesh and its exact irradiance per light
   at the vertices. Chunks run in this process or on `dask.distributed` workers (the scene is
   scattered once per worker). A chunk sees only its own inputs (`_chunk_inputs`): the lights
   that reach its patch and the occluder faces that may meet its shadow volumes (the convex
   hulls of the patch and each such light). With a `work_dir`, each chunk's result is an
   `.npz` file named by a hash of those inputs, the patch and the settings, so a killed run
   resumes where it stopped and gives the identical result, and a re-bake after moving an
   object or changing a light computes only the chunks that change reaches.
3. **Stitching.** Patches that share an edge (the same two welded vertices) get the same
   vertices on it: every patch's points on the edge are merged (parameters within 1e-9 of the
   edge are one point, at the smallest parameter), and a triangle that lacks a point on its
   edge is split there (a fan from its opposite corner, or from its centroid when several of
   its edges gain points). New or moved vertices get their exact values. No T vertices remain
   on shared edges; vertices of equal position and normal are one output vertex.

Values on a shared edge agree where the normals agree (coplanar patches, a curved surface's
smooth normals); across a crease (floor and wall) the vertices coincide but the irradiance
differs, as it physically does.
"""

from __future__ import annotations

import hashlib
import os
import time
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .._scene.model import Scene

BAKE_FORMAT = 2  # bumped when a chunk file's content changes meaning (part of its hash)
EDGE_EPS = 1e-9  # points on a shared edge closer than this (in its parameter) are one point
MIN_BATCH = 256  # smallest padded batch of `_values`
_CODE = 1 << 31  # an edge (a, b) of local vertex ids is the code a * _CODE + b
PIERCED_MIN_EDGE = 1e-3  # elements of a patch that open geometry passes through stop here (of its size)


# --------------------------------------------------------------------------------------
# Result
# --------------------------------------------------------------------------------------


class BakedScene:
    """The illumination mesh of a whole scene (`bake`).

    **Attributes:**

    - `vertices`: `(V, 3)` positions (m).
    - `normals`: `(V, 3)` unit normals the irradiance was evaluated with.
    - `triangles`: `(T, 3)` vertex indices, counter-clockwise seen from the lit side.
    - `irradiance`: `(V, 3)` exact RGB irradiance from all baked lights (W/m^2).
    - `irradiance_per_light`: `(V, L, 3)` the same per light (re-weight lights without baking
      again: `(w[None, :, None] * irradiance_per_light).sum(1)`).
    - `surface`: `(T,)` index of the receiver surface each triangle belongs to.
    - `patch`: `(T,)` index of the patch (chunk) each triangle belongs to.
    - `surface_names`: names of the surfaces.
    - `lights`: `(L,)` indices into the scene's lights of the baked lights.
    - `scale`: the irradiance `tol` is relative to (W/m^2).
    - `tol`: the requested relative tolerance.
    - `stats`: `chunks`, `chunks_computed` (this run; the others were read from `work_dir`),
      `patches_planar`, `patches_curved`, `stitched_points` (points added on shared edges),
      `moved_points`, `seconds`; `unconverged`: one dict per patch left with elements over
      `tol` (`surface`, `patch`, `kind`, `elements` over tol, `stopped_by_budget`, `error`: the
      largest checked error over `scale`), at the minimum edge length (value jumps: hard
      shadows of point lights, geometry passing through the receiver) or stopped by
      `max_vertices` (also a `RuntimeWarning`); `pierced`: one dict per planar patch that
      occluders pass through (`surface`, `patch`, `sections`: convex pieces of the cut-out
      cross-sections of closed objects, `open`: segments where open geometry crosses it).
    """

    def __init__(self, vertices: np.ndarray, normals: np.ndarray, triangles: np.ndarray, per_light: np.ndarray,
                 surface: np.ndarray, patch: np.ndarray, surface_names: list[str], lights: np.ndarray,
                 scale: float, tol: float, stats: dict[str, Any]):
        self.vertices, self.normals, self.triangles = vertices, normals, triangles
        self.irradiance_per_light = per_light
        self.irradiance = per_light.sum(axis=1)
        self.surface, self.patch, self.surface_names = surface, patch, surface_names
        self.lights, self.scale, self.tol, self.stats = lights, float(scale), float(tol), stats

    def __repr__(self) -> str:
        return (f"BakedScene({self.vertices.shape[0]} vertices, {self.triangles.shape[0]} triangles, "
                f"{len(self.surface_names)} surfaces, {self.irradiance_per_light.shape[1]} lights, tol={self.tol:g})")

    def save(self, path: str | os.PathLike, up: Any = "z") -> None:
        """Write the bake to `path` (atomically): `.glb` (binary glTF, y-up: the scene's `up`
        axis, `"z"` for jaxshadow scenes, turned to +y; vertex colours `COLOR_0`,
        `NORMAL`, float32 irradiance as the custom attributes `_IRRADIANCE` and `_IRRADIANCE_<l>`
        per light) or `.ply` (binary: vertex colours, float64 `irradiance_r/g/b` and
        `irradiance_<l>_r/g/b` per light)."""
        write_bake(path, self, up)


# --------------------------------------------------------------------------------------
# Receivers -> surfaces -> patches
# --------------------------------------------------------------------------------------


def _weld(points: np.ndarray, tol: float) -> np.ndarray:
    """`(n,)` welded id of each point: points within `tol > 0` are one (transitively,
    `jaxshadow._core.welding.weld_vertices`); the id is the lowest index of its group. `tol <= 0`:
    every point its own."""
    from .._core.welding import weld_vertices

    if points.shape[0] == 0 or tol <= 0:
        return np.arange(points.shape[0])
    index, first = weld_vertices(points, tol)
    return first[index]


def _surfaces(scene: Scene, receivers: Any) -> list[tuple[str, np.ndarray, Any, np.ndarray | None]]:
    """`(name, vertices, triangles or polygon rows, vertex normals or None)` per surface."""
    from .._io.meshio import ReceiverMesh

    if receivers is None:
        if scene.occluders is None:
            raise ValueError("bake: the scene has no occluders and no receivers were given.")
        occ = np.asarray(scene.occluders, np.float64)
        receivers = [_unpad(o) for o in occ]
    if isinstance(receivers, (ReceiverMesh, np.ndarray)) or not isinstance(receivers, (list, tuple)):
        receivers = [receivers]
    out: list[tuple[str, np.ndarray, Any, np.ndarray | None]] = []
    for i, r in enumerate(receivers):
        if isinstance(r, ReceiverMesh):
            out.append((r.name or f"surface{i}", r.vertices, r.faces, r.vertex_normals))
            continue
        from .._core.mesh import Mesh

        if isinstance(r, Mesh):
            polys = [_unpad(np.asarray(p, np.float64)) for p in r.polygons]
        else:
            p = np.asarray(r, np.float64)
            polys = [p] if p.ndim == 2 else [_unpad(q) for q in p]
        if not polys or any(p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 3 for p in polys):
            raise ValueError(f"bake: receivers[{i}] must be a ReceiverMesh, a Mesh or polygons (k, 3).")
        verts = np.concatenate(polys)
        off = np.cumsum([0] + [p.shape[0] for p in polys])
        rows = [np.arange(off[j], off[j + 1]) for j in range(len(polys))]
        out.append((f"surface{i}", verts, rows, None))
    return out


def _unpad(p: np.ndarray) -> np.ndarray:
    keep = np.r_[True, np.any(np.diff(p, axis=0) != 0, axis=1)]
    p = p[keep]
    if p.shape[0] > 1 and np.array_equal(p[0], p[-1]):
        p = p[:-1]
    return p


def _newell(p: np.ndarray) -> np.ndarray:
    n = np.sum(np.cross(p, np.roll(p, -1, axis=0)), axis=0)
    return n / np.linalg.norm(n)


def _convex_loop(loop: np.ndarray, normal: np.ndarray) -> bool:
    """Strictly convex, counter-clockwise about `normal`, no collinear corners."""
    d = np.roll(loop, -1, axis=0) - loop
    turn = np.cross(d, np.roll(d, -1, axis=0)) @ normal
    size = np.linalg.norm(d, axis=1)
    return bool(np.all(turn > 1e-9 * size * np.roll(size, -1)))


def _planar_groups(tris: np.ndarray, pos: np.ndarray) -> list[tuple[list[int], list[np.ndarray]]]:
    """Flat triangles (rows of welded ids) grouped into coplanar connected sets; each set is
    one convex polygon `(ids loop)` when its union is one, else one polygon per triangle.
    Returns `(triangle indices, polygon id loops)` per set."""
    n = tris.shape[0]
    nrm = np.array([_newell(pos[t]) for t in tris]) if n else np.zeros((0, 3))
    by_edge: dict[tuple[int, int], list[int]] = {}
    for i, t in enumerate(tris):
        for k in range(3):
            a, b = int(t[k]), int(t[(k + 1) % 3])
            by_edge.setdefault((min(a, b), max(a, b)), []).append(i)
    seen = np.zeros(n, bool)
    groups: list[tuple[list[int], list[np.ndarray]]] = []
    for s in range(n):
        if seen[s]:
            continue
        comp, stack = [s], [s]
        seen[s] = True
        while stack:
            i = stack.pop()
            t = tris[i]
            for k in range(3):
                a, b = int(t[k]), int(t[(k + 1) % 3])
                for j in by_edge[(min(a, b), max(a, b))]:
                    if not seen[j] and nrm[j] @ nrm[s] > 1 - 1e-9 and abs((pos[tris[j]] - pos[tris[s][0]]) @ nrm[s]).max() \
                            <= 1e-7 * (1 + np.abs(pos[tris[s]]).max()):
                        seen[j] = True
                        comp.append(j)
                        stack.append(j)
        comp.sort()
        loop = _boundary_loop(tris[comp])
        if loop is not None and len(comp) > 1 and set(loop.tolist()) == set(tris[comp].ravel().tolist()) \
                and _convex_loop(pos[loop], nrm[s]):
            groups.append((comp, [loop]))
        else:
            groups.append((comp, [tris[i] for i in comp]))
    return groups


def _boundary_loop(tris: np.ndarray) -> np.ndarray | None:
    directed = {(int(t[k]), int(t[(k + 1) % 3])) for t in tris for k in range(3)}
    nxt: dict[int, int] = {}
    for a, b in directed:
        if (b, a) not in directed:
            if a in nxt:
                return None
            nxt[a] = b
    if not nxt:
        return None
    start = min(nxt)
    loop = [start]
    while True:
        b = nxt[loop[-1]]
        if b == start:
            break
        if b in loop or b not in nxt:
            return None
        loop.append(b)
    return np.array(loop) if len(loop) == len(nxt) else None


class _Patch:
    """One chunk: a planar polygon (`ids (k,)` welded ids of its corners, counter-clockwise) or
    a curved triangle set (`tri (t, 3)` local vertex ids, `vpos`, `vnrm`, `vwid` per local
    vertex)."""

    def __init__(self, kind: str, surface: int, **data: Any):
        self.kind, self.surface = kind, surface
        self.data = {k: np.ascontiguousarray(v) for k, v in data.items()}

    def digest(self) -> bytes:
        h = hashlib.sha256(self.kind.encode())
        for k in sorted(self.data):
            v = self.data[k]
            h.update(k.encode() + str(v.dtype).encode() + str(v.shape).encode() + v.tobytes())
        return h.digest()


def _patches(surfaces: list, weld: float) -> tuple[list[_Patch], np.ndarray, list[str]]:
    """The patches of all surfaces, the welded positions `(W, 3)` and the surface names."""
    allv = np.concatenate([s[1] for s in surfaces])
    size = float(np.max(np.ptp(allv, axis=0))) if allv.shape[0] else 1.0
    wid_all = _weld(allv, weld * size)
    pos = allv[wid_all]  # every point at its group's representative
    off = np.cumsum([0] + [s[1].shape[0] for s in surfaces])
    patches: list[_Patch] = []
    names = []
    for si, (name, v, faces, vn) in enumerate(surfaces):
        names.append(name)
        wid = wid_all[off[si]:off[si + 1]]
        if vn is None:  # polygons given as rows
            for rows in faces:
                ids = _dedup_loop(wid[rows])
                if ids.shape[0] >= 3:
                    patches.append(_Patch("planar", si, ids=ids, normal=_newell(pos[ids])))
            continue
        f = np.asarray(faces)
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        fn /= np.linalg.norm(fn, axis=1)[:, None]
        flat = np.all(np.einsum("fkj,fj->fk", vn[f], fn) > 1 - 1e-6, axis=1)
        wt = wid[f]
        degenerate = (wt[:, 0] == wt[:, 1]) | (wt[:, 1] == wt[:, 2]) | (wt[:, 0] == wt[:, 2])
        flat_idx = np.nonzero(flat & ~degenerate)[0]
        for comp, polys in _planar_groups(wt[flat_idx], pos):
            # one normal per coplanar set: its vertices on inner edges are then one output vertex
            ct = pos[wt[flat_idx[comp]]]
            acc = np.cross(ct[:, 1] - ct[:, 0], ct[:, 2] - ct[:, 0]).sum(axis=0)
            normal = acc / np.linalg.norm(acc)
            for ids in polys:
                patches.append(_Patch("planar", si, ids=np.asarray(ids, np.int64), normal=normal))
        curved = np.nonzero(~flat & ~degenerate)[0]
        if curved.size:
            fc = f[curved]
            # local vertices: one per (welded position, normal)
            key = np.concatenate([wid[:, None].astype(np.float64), np.round(vn, 9)], axis=1)
            uk, inv = np.unique(key[fc.ravel()], axis=0, return_inverse=True)
            tri = inv.reshape(-1, 3).astype(np.int64)
            first = np.zeros(uk.shape[0], np.int64)
            first[inv.ravel()] = fc.ravel()
            lw = wid[first]
            patches.append(_Patch("curved", si, tri=tri, vpos=pos[lw], vnrm=vn[first], vwid=lw.astype(np.int64)))
    # planar patches carry their corners' positions; all patches the welded ids they touch
    for p in patches:
        if p.kind == "planar":
            p.data["poly"] = pos[p.data["ids"]]
    return patches, pos, names


def _dedup_loop(ids: np.ndarray) -> np.ndarray:
    keep = [int(i) for k, i in enumerate(ids) if i != ids[k - 1]] if ids.shape[0] > 1 else list(ids)
    return np.array(keep, np.int64)


# --------------------------------------------------------------------------------------
# One chunk
# --------------------------------------------------------------------------------------


def _light_scenes(scene: Scene) -> list[Scene]:
    import equinox as eqx

    return [eqx.tree_at(lambda s: s.lights, scene, (light,)) for light in scene.lights]


def _values(scenes: list[Scene], points: np.ndarray, normals: np.ndarray, chunk: int = 1 << 15) -> np.ndarray:
    """`(n, L, 3)` exact irradiance per light (W/m^2). Batches are padded to a power of two
    (at least `MIN_BATCH`): the engine compiles per batch shape, and a bake calls this with
    every count of points."""
    from .._shading.shade import irradiance

    n = points.shape[0]
    out = np.zeros((n, len(scenes), 3))
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        size = max(MIN_BATCH, 1 << (e - s - 1).bit_length())
        pad = size - (e - s)
        p = np.concatenate([points[s:e], np.repeat(points[s:s + 1], pad, axis=0)])
        q = np.concatenate([normals[s:e], np.repeat(normals[s:s + 1], pad, axis=0)])
        for li, sc in enumerate(scenes):
            out[s:e, li] = np.asarray(irradiance(sc, p, q), np.float64)[:e - s]
    return out


def _edge_param(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Parameter of points `p (n, 3)` along a -> b and their distance to the segment."""
    d = b - a
    t = (p - a) @ d / (d @ d)
    foot = a + np.clip(t, 0, 1)[:, None] * d
    return t, np.linalg.norm(p - foot, axis=1)


def _on_point(pos: np.ndarray, ka: int, kb: int, t: float) -> np.ndarray:
    """The point at parameter `t` of the welded edge `ka < kb` (endpoints exactly at 0 and 1)."""
    if t == 0.0:
        return pos[ka].copy()
    if t == 1.0:
        return pos[kb].copy()
    return pos[ka] + t * (pos[kb] - pos[ka])


ON_SURFACE = 2.0**-18  # `js.irradiance`'s on-surface distance, relative to the coordinates' magnitude


def _light_points(light: Any, pts: np.ndarray, reach: float) -> np.ndarray:
    """Points whose convex hull with the receiver points `pts` holds every segment from a
    receiver point to the light (for a directional light: up to `reach` towards it)."""
    from .._scene.model import DirectionalLight, LinearLight, PointLight, PolygonLight

    if isinstance(light, PolygonLight):
        return np.asarray(light.vertices, np.float64)
    if isinstance(light, LinearLight):
        return np.stack([np.asarray(light.start, np.float64), np.asarray(light.end, np.float64)])
    if isinstance(light, PointLight):
        return np.asarray(light.position, np.float64)[None, :]
    assert isinstance(light, DirectionalLight)
    d = np.asarray(light.direction, np.float64)
    return pts - reach * d / np.linalg.norm(d)


def _dark(light: Any, poly: np.ndarray, normal: np.ndarray, size: float) -> bool:
    """The light gives exactly zero on the planar convex polygon `poly` (its corners): every
    point of the light strictly behind the polygon's plane, or (a one-sided polygon light)
    every corner strictly behind the light's emitting side."""
    from .._scene.model import DirectionalLight, PolygonLight

    eps = 1e-9 * size
    if isinstance(light, DirectionalLight):
        d = np.asarray(light.direction, np.float64)
        return bool(-(d @ normal) <= -eps * np.linalg.norm(d) / size)
    lp = _light_points(light, poly, 0.0)
    if np.all((lp - poly[0]) @ normal < -eps):
        return True
    if isinstance(light, PolygonLight):
        m = _newell(lp)
        return bool(np.all((poly - lp[0]) @ m < -eps))
    return False


def _own_faces(occ: np.ndarray, poly: np.ndarray, normal: np.ndarray, size: float) -> np.ndarray:
    """`(m,)` mask of the padded faces `occ` lying on the plane of `poly` (within `ON_SURFACE`
    of `size`) and facing the way of `normal`: the receiver's own surface."""
    on = np.all(np.abs((occ - poly[0]) @ normal) <= ON_SURFACE * size, axis=1)
    nf = np.sum(np.cross(occ, np.roll(occ, -1, axis=1)), axis=1)
    return on & (nf @ normal > 0)


def without_own_faces(scene: Scene, poly: np.ndarray, normal: np.ndarray) -> Scene:
    """`scene` without the occluder faces lying on the planar receiver `poly` and facing its way
    (`_own_faces`): by the on-surface rule they block nothing on it, but the mesher would take
    them for the foot of an object standing on it (a hole). Faces on it facing the other way
    (the bottom of a box on the floor) stay: they are such feet."""
    if scene.occluders is None:
        return scene
    occ = np.asarray(scene.occluders, np.float64)
    size = max(float(np.abs(poly).max()), float(np.abs(occ).max())) + 1.0
    own = _own_faces(occ, np.asarray(poly, np.float64), normal, size)
    if not own.any():
        return scene
    keep = [_unpad(o) for o in occ[~own]]
    return Scene(scene.lights, occluders=keep or None, ambient=scene.ambient)


def _chunk_inputs(scene: Scene, occ: np.ndarray | None, patch: _Patch) -> tuple[np.ndarray, np.ndarray]:
    """What a patch's chunk sees of the scene: `(occluder indices (k,), light mask (L,))`.

    An occluder face is kept when it may meet a shadow volume of the patch: the convex hull of
    the patch's points and a light's (`_light_points`) for each light that reaches the patch;
    one outside a face plane of every such hull (by more than 1e-9 of the scene's size) blocks
    nothing there. A planar patch also drops the faces lying on its plane and facing its way
    (its own surface: by the on-surface rule they block nothing for it, but the mesher would
    take them for the foot of an object standing on it, a hole; faces lying on it and facing
    the other way, the bottom of a box on the floor, stay: they are such feet), and the lights
    that give it exactly zero (`_dark`: their values there are zeros). A chunk is a function of
    these alone, so moving an object or changing a light changes only the chunks whose inputs
    change (`bake`'s `work_dir`)."""
    from scipy.spatial import ConvexHull, QhullError

    planar = patch.kind == "planar"
    pts = patch.data["poly"] if planar else patch.data["vpos"]
    n_lights = len(scene.lights)
    size = float(np.abs(pts).max()) + 1.0
    if occ is not None:
        size = max(size, float(np.abs(occ).max()) + 1.0)
    mask = np.ones(n_lights, bool)
    if planar:
        mask = np.array([not _dark(light, pts, patch.data["normal"], size) for light in scene.lights], bool)
    if occ is None:
        return np.zeros(0, np.int64), mask
    keep = np.zeros(occ.shape[0], bool)
    if planar:
        own = _own_faces(occ, pts, patch.data["normal"], size)
    else:
        own = np.zeros(occ.shape[0], bool)
    reach = 4.0 * size
    for li in np.nonzero(mask)[0]:
        hp = np.concatenate([pts, _light_points(scene.lights[li], pts, reach)])
        try:
            eq = ConvexHull(hp).equations  # (F, 4): n . x + c <= 0 inside
        except (QhullError, ValueError):  # flat or degenerate hull: keep every face
            keep[:] = True
            break
        out = np.zeros(occ.shape[0], bool)
        for f in eq:
            out |= np.all(occ @ f[:3] + f[3] > 1e-9 * size, axis=1)
        keep |= ~out
    return np.nonzero(keep & ~own)[0].astype(np.int64), mask


def _cross_sections(faces: np.ndarray, poly: np.ndarray, normal: np.ndarray, size: float
                    ) -> tuple[list[np.ndarray], int]:
    """Where occluders pass through a planar receiver: the regions of its plane inside them.

    `faces (m, K, 3)` (padded) that cross the plane of the convex polygon `poly` (vertices
    strictly on both sides, beyond the on-surface distance) cut it along segments; the
    segments' closed loops bound the cross-sections of closed objects. Only what overlaps the
    polygon counts (a wall crosses the plane of a cube's side far from the cube). Each region is returned as convex polygons
    lying on the plane and facing away from `normal` (as the bottom of a box standing on the
    floor does: the mesher takes faces lying on its plane for the foot of an object, a hole
    bounded by mesh edges, and by the on-surface rule they block nothing on the plane). Open
    geometry (a single wall passing through the floor) leaves segments in no loop: the value
    jumps across them, no hole to cut; their count is returned.

    **Returns:** `(polygons, open segments)`."""
    import shapely
    from shapely.ops import polygonize

    p0 = poly[0]
    eps = ON_SURFACE * size
    h = (faces - p0) @ normal  # (m, K)
    crossing = np.nonzero(np.any(h > eps, axis=1) & np.any(h < -eps, axis=1))[0]
    if crossing.size == 0:
        return [], 0
    e1 = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    lines = []
    for f in crossing:
        q = _unpad(faces[f])
        hq = (q - p0) @ normal
        pts = []
        for k in range(q.shape[0]):
            a, b, ha, hb = q[k], q[(k + 1) % q.shape[0]], hq[k], hq[(k + 1) % q.shape[0]]
            if abs(ha) <= eps:
                pts.append(a)
            if (ha > eps and hb < -eps) or (ha < -eps and hb > eps):
                if tuple(b) < tuple(a):  # the same point from both faces of a shared edge
                    a, b, ha, hb = b, a, hb, ha
                pts.append(a + (ha / (ha - hb)) * (b - a))
        uv: list[tuple[float, float]] = []
        for p in pts:
            key = (float((p - p0) @ e1), float((p - p0) @ e2))
            if key not in uv:
                uv.append(key)
        if len(uv) == 2:
            lines.append(shapely.LineString(uv))
    patch = shapely.Polygon(np.stack([(poly - p0) @ e1, (poly - p0) @ e2], axis=1))
    overlap = 1e-9 * size
    polys = [pg for pg in polygonize(lines) if pg.intersection(patch).area > overlap * overlap]
    covered = shapely.unary_union([pg.boundary for pg in polys]).buffer(overlap) if polys else None
    n_open = sum(1 for ln in lines if ln.intersection(patch).length > overlap
                 and (covered is None or not ln.within(covered)))
    out = []
    for pg in polys:
        parts = [pg] if _convex_2d(np.asarray(pg.exterior.coords)[:-1]) and not pg.interiors else \
            list(shapely.constrained_delaunay_triangles(pg).geoms)
        for part in parts:
            ring = np.array(shapely.orient_polygons(part, exterior_cw=True).exterior.coords, np.float64)[:-1]
            out.append(p0 + ring[:, :1] * e1 + ring[:, 1:] * e2)  # clockwise about normal: facing away
    return out, n_open


def _convex_2d(q: np.ndarray) -> bool:
    d = np.roll(q, -1, axis=0) - q
    c = d[:, 0] * np.roll(d, -1, axis=0)[:, 1] - d[:, 1] * np.roll(d, -1, axis=0)[:, 0]
    return bool(np.all(c > 0) or np.all(c < 0))


def _chunk_scene(scene: Scene, occ_idx: np.ndarray, mask: np.ndarray, sentinel: np.ndarray | None = None,
                 extra: Sequence[np.ndarray] = ()) -> Scene:
    """The scene of a chunk: the lights of `mask` and the occluder faces `occ_idx` of `scene`
    (welded again into meshes as `Scene` does; their convexity was checked when `scene` was
    built, so it is not checked again: that costs ~1 ms a face, per chunk). With no face kept,
    `sentinel` (a triangle below a planar patch's plane: it blocks nothing there) is its one
    occluder, so that the chunk runs on the host shadow engine like the others (the unoccluded
    kernels compile per batch shape, ~1 s each, and run slower than the engine here). `extra`:
    polygons added as they are, after the welding (`_cross_sections`)."""
    from .._core.geometry import pad_polygons_jax
    from .._core.mesh import Mesh, max_face_vertices, stack_occluders, weld_polygons

    sub = Scene(tuple(light for light, m in zip(scene.lights, mask, strict=True) if m), ambient=scene.ambient)
    if scene.occluders is None or occ_idx.size == 0:
        if sentinel is None or scene.occluders is None:
            return sub
        object.__setattr__(sub, "occluders", pad_polygons_jax([sentinel]))
        return sub
    occ = np.asarray(scene.occluders, np.float64)
    items = weld_polygons([_unpad(o) for o in occ[occ_idx]]) + list(extra)
    if any(isinstance(x, Mesh) for x in items):
        arr, topo = stack_occluders(items, max_face_vertices(items))
    else:
        arr, topo = pad_polygons_jax(items), None
    object.__setattr__(sub, "occluders", arr)
    object.__setattr__(sub, "occluder_topology", topo)
    return sub


def _off_contact(v: np.ndarray, scene: Scene, poly: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Where to evaluate the vertices `v (n, 3)` of a planar patch: those on an edge of an
    occluder face lying on its plane (the foot of an object standing on it, or the
    cross-section of one passing through it: a hole, along whose edges the irradiance jumps)
    `CONTACT_STEP` of the patch's size outside it, as `illumination_mesh` evaluates them (the
    limit on the open side); the others where they are."""
    from .builder import CONTACT_STEP

    if scene.occluders is None:
        return v
    occ = np.asarray(scene.occluders, np.float64)
    diam = float(np.max(np.ptp(poly, axis=0)))
    size = max(float(np.abs(occ).max()), float(np.abs(poly).max()))
    flat = np.all(np.abs((occ - poly[0]) @ normal) <= 1e-9 * diam, axis=1)
    if not flat.any():
        return v
    push = np.zeros_like(v)
    eps = 1e-10 * diam + 4 * np.finfo(np.float64).eps * size
    for f in occ[flat]:
        q = _unpad(f)
        c = q.mean(axis=0)
        for k in range(q.shape[0]):
            a, b = q[k], q[(k + 1) % q.shape[0]]
            d = b - a
            out = np.cross(d, normal)
            out /= np.linalg.norm(out)
            if (c - a) @ out > 0:
                out = -out
            t = np.clip((v - a) @ d / (d @ d), 0.0, 1.0)
            near = np.linalg.norm(v - (a + t[:, None] * d), axis=1) <= eps
            push[near] += out
    hit = np.any(push != 0, axis=1)
    if not hit.any():
        return v
    w = v.copy()
    w[hit] += CONTACT_STEP * diam * push[hit] / np.maximum(np.linalg.norm(push[hit], axis=1, keepdims=True), 1e-300)
    return w


def _planar_chunk(scene: Scene, mask: np.ndarray, patch: _Patch, pos: np.ndarray, tol: float, scale: float,
                  options: dict[str, Any], options_weld: float) -> dict[str, np.ndarray]:
    from .mesh import illumination_mesh

    ids, poly, normal = patch.data["ids"], patch.data["poly"], patch.data["normal"]
    unrefined, stopped, error = 0, 0, 0.0
    if scene.lights:
        with warnings.catch_warnings():  # reported per patch in `BakedScene.stats["unconverged"]`
            warnings.simplefilter("ignore", RuntimeWarning)
            m = illumination_mesh(scene, poly, tol, scale=scale, **options)
        v, tris = np.array(m.vertices, np.float64), np.asarray(m.triangles, np.int64)
        unrefined = int(m.stats.get("unrefined_min_edge", 0))
        stopped = int(m.stats.get("tiles_stopped_by_budget", 0))
        error = float(m.max_error_estimate)
        del m  # its builders (every evaluated point, kept for `update`) before the vertex values
    else:  # no light reaches it: zero everywhere, its corners suffice
        v = poly.copy()
        tris = np.array([[0, k, k + 1] for k in range(1, poly.shape[0] - 1)], np.int64)
    # welded corners may leave the polygon planar only to the weld distance
    near = 1e-9 * float(np.max(np.ptp(poly, axis=0))) + 2 * options_weld
    occ_id, occ_v, occ_t, keys = [], [], [], []
    for k in range(ids.shape[0]):
        ia, ib = int(ids[k]), int(ids[(k + 1) % ids.shape[0]])
        ka, kb = min(ia, ib), max(ia, ib)
        t, dist = _edge_param(v, pos[ka], pos[kb])
        on = np.nonzero((dist <= near) & (t >= -1e-9) & (t <= 1 + 1e-9))[0]
        tt = np.clip(t[on], 0.0, 1.0)
        tt[tt < 1e-12] = 0.0
        tt[tt > 1 - 1e-12] = 1.0
        for vi, ti in zip(on, tt, strict=True):
            v[vi] = _on_point(pos, ka, kb, float(ti))
        keys.append((ka, kb))
        occ_id += [k] * on.size
        occ_v += on.tolist()
        occ_t += tt.tolist()
    nrm = np.broadcast_to(normal, v.shape).copy()
    values = np.zeros((v.shape[0], mask.size, 3))
    if scene.lights:
        values[:, mask] = _values(_light_scenes(scene), _off_contact(v, scene, poly, normal), nrm)
    return {"vertices": v, "normals": nrm, "triangles": tris,
            "values": values, "edge_keys": np.array(keys, np.int64).reshape(-1, 2),
            "occ_edge": np.array(occ_id, np.int64), "occ_vertex": np.array(occ_v, np.int64),
            "occ_t": np.array(occ_t, np.float64), "unrefined": np.array(unrefined), "stopped": np.array(stopped), "error": np.array(error)}


def _refine_curved(scenes: list[Scene], patch: _Patch, pos: np.ndarray, tol: float, scale: float,
                   min_edge: float, max_vertices: int, max_rounds: int) -> dict[str, np.ndarray]:
    """Conforming refinement of a curved triangle set: edges whose midpoint value misses the
    mean of its ends by more than `tol * scale` (max over RGB of the light sum), and the three
    edges of triangles whose centroid misses the mean of the corners, are split; a triangle with
    two split edges gets its third split too (red: 1-to-4), one with one is bisected (green).
    Stops when no edge fails, at `max_vertices`, or after `max_rounds` rounds. The result
    reports `rounds`, `unrefined` (edges whose midpoint still misses, the short ones
    included), `stopped` (1: stopped by `max_vertices` with edges failing) and `error` (the
    largest midpoint miss over `scale`).

    Edges are int64 codes `a * _CODE + b` (`a < b`): each round's unique edges, the cache of
    evaluated midpoints and the inserted midpoints are sorted code arrays (`np.searchsorted`);
    only the few edges with both ends on the patch's boundary go through Python (their points
    are recorded for stitching)."""
    tri = patch.data["tri"].astype(np.int64)
    vwid = patch.data["vwid"]
    P = patch.data["vpos"].astype(np.float64)
    N = patch.data["vnrm"].astype(np.float64)
    E = _values(scenes, P, N)
    # the patch's boundary edges (used by one triangle), in the order the triangles list them
    ed0 = np.sort(np.stack([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]], axis=1), axis=2).reshape(-1, 2)
    _, inv0, cnt0 = np.unique(ed0[:, 0] * _CODE + ed0[:, 1], return_inverse=True, return_counts=True)
    once = cnt0[inv0.ravel()] == 1
    bnd = ed0[once & (vwid[ed0[:, 0]] != vwid[ed0[:, 1]])]
    edge_keys = np.sort(vwid[bnd], axis=1).astype(np.int64).reshape(-1, 2)
    # on[v] = {boundary edge index: parameter in the welded key's direction}, boundary vertices only
    on: dict[int, dict[int, float]] = {}
    for j, (a, b) in enumerate(bnd.tolist()):
        lo = int(vwid[a]) < int(vwid[b])
        on.setdefault(a, {})[j] = 0.0 if lo else 1.0
        on.setdefault(b, {})[j] = 1.0 if lo else 0.0
    c_code = np.zeros(0, np.int64)  # evaluated midpoints, sorted by edge code
    c_p, c_n, c_v = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, E.shape[1], 3))
    m_code, m_idx = np.zeros(0, np.int64), np.zeros(0, np.int64)  # inserted midpoints
    fresh = np.ones(tri.shape[0], bool)  # triangles whose centroid is not checked yet
    limit = tol * scale

    def unit(x: np.ndarray) -> np.ndarray:
        return x / np.linalg.norm(x, axis=-1, keepdims=True)

    def lookup(codes: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        at = np.minimum(np.searchsorted(table, codes), max(table.size - 1, 0))
        return at, (table[at] == codes) if table.size else np.zeros(codes.size, bool)

    rounds, bad = 0, np.zeros(0, bool)
    while True:
        tot = E.sum(axis=1)
        ed = np.sort(np.stack([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]], axis=1), axis=2)
        ucode, eid = np.unique((ed[..., 0] * _CODE + ed[..., 1]).ravel(), return_inverse=True)
        eid = eid.reshape(-1, 3)
        ua, ub = ucode // _CODE, ucode % _CODE
        at, found = lookup(ucode, c_code)
        if not found.all():
            na, nb = ua[~found], ub[~found]
            mp = 0.5 * (P[na] + P[nb])
            for r in np.nonzero(np.isin(na, list(on)) & np.isin(nb, list(on)))[0]:
                a, b = int(na[r]), int(nb[r])
                common = on[a].keys() & on[b].keys()
                if common:
                    j = min(common)
                    ka, kb = edge_keys[j]
                    mp[r] = _on_point(pos, int(ka), int(kb), 0.5 * (on[a][j] + on[b][j]))
            same = np.all(N[na] == N[nb], axis=1)
            mn = np.where(same[:, None], N[na], unit(N[na] + N[nb]))
            mv = _values(scenes, mp, mn)
            c_code = np.concatenate([c_code, ucode[~found]])
            order = np.argsort(c_code, kind="stable")
            c_code = c_code[order]
            c_p, c_n, c_v = (np.concatenate([c_p, mp])[order], np.concatenate([c_n, mn])[order],
                             np.concatenate([c_v, mv])[order])
            at, found = lookup(ucode, c_code)
        mval = c_v[at].sum(axis=1)
        long = np.linalg.norm(P[ua] - P[ub], axis=1) > min_edge
        emiss = np.max(np.abs(mval - 0.5 * (tot[ua] + tot[ub])), axis=1)
        bad = (emiss > limit) & long
        if fresh.any():
            ft = tri[fresh]
            same = np.all((N[ft[:, 0]] == N[ft[:, 1]]) & (N[ft[:, 0]] == N[ft[:, 2]]), axis=1)
            cn = np.where(same[:, None], N[ft[:, 0]], unit(N[ft].sum(axis=1)))
            cv = _values(scenes, P[ft].mean(axis=1), cn).sum(axis=1)
            miss = np.max(np.abs(cv - tot[ft].mean(axis=1)), axis=1) > limit
            fe = eid[fresh][miss].ravel()
            bad[fe[long[fe]]] = True
        if not bad.any() or P.shape[0] >= max_vertices or rounds >= max_rounds:
            break
        rounds += 1
        while True:  # closure: two split edges -> split the third
            two = bad[eid].sum(axis=1) == 2
            if not two.any():
                break
            bad[eid[two].ravel()] = True
        split = bad[eid]  # (t, 3): which sides of each triangle are split
        bi = np.nonzero(bad)[0]
        mat, mfound = lookup(ucode[bi], m_code)
        newe = bi[~mfound]  # midpoints numbered in sorted edge order
        base = P.shape[0]
        for k, e in enumerate(newe.tolist()):
            a, b = int(ua[e]), int(ub[e])
            if a in on and b in on:
                common = on[a].keys() & on[b].keys()
                if common:
                    on[base + k] = {j: 0.5 * (on[a][j] + on[b][j]) for j in common}
        if newe.size:
            ce = at[newe]
            P, N, E = np.concatenate([P, c_p[ce]]), np.concatenate([N, c_n[ce]]), np.concatenate([E, c_v[ce]])
            m_code = np.concatenate([m_code, ucode[newe]])
            m_idx = np.concatenate([m_idx, base + np.arange(newe.size)])
            order = np.argsort(m_code, kind="stable")
            m_code, m_idx = m_code[order], m_idx[order]
        mid = np.full(ucode.size, -1, np.int64)
        mid[bi] = m_idx[lookup(ucode[bi], m_code)[0]]
        M = mid[eid]  # (t, 3): the midpoint of each split side
        ns = split.sum(axis=1)
        out = np.full((tri.shape[0], 4, 3), -1, np.int64)
        keep = ns == 0
        out[keep, 0] = tri[keep]
        r = ns == 3
        a, b, c, ab, bc, ca = tri[r, 0], tri[r, 1], tri[r, 2], M[r, 0], M[r, 1], M[r, 2]
        out[r] = np.stack([np.c_[a, ab, ca], np.c_[ab, b, bc], np.c_[ca, bc, c], np.c_[ab, bc, ca]], axis=1)
        g = np.nonzero(ns == 1)[0]
        k = np.argmax(split[g], axis=1)
        a, b, c = tri[g, k], tri[g, (k + 1) % 3], tri[g, (k + 2) % 3]
        mm = M[g, k]
        out[g, 0], out[g, 1] = np.c_[a, mm, c], np.c_[mm, b, c]
        valid = out[:, :, 0] >= 0
        fresh = (valid & ~keep[:, None])[valid]
        tri = out[valid]
    occ_e, occ_v, occ_t = [], [], []
    for vi in sorted(on):
        for j, t in sorted(on[vi].items()):
            occ_e.append(j)
            occ_v.append(vi)
            occ_t.append(t)
    return {"vertices": P, "normals": N, "triangles": tri, "values": E,
            "edge_keys": edge_keys, "occ_edge": np.array(occ_e, np.int64),
            "occ_vertex": np.array(occ_v, np.int64), "occ_t": np.array(occ_t, np.float64),
            "rounds": np.array(rounds), "unrefined": np.array(int(np.sum(emiss > limit))),
            "stopped": np.array(int(bad.any() and P.shape[0] >= max_vertices)),
            "error": np.array(float(emiss.max(initial=0.0)) / scale)}


def _chunk(scene: Scene, patch: _Patch, pos: np.ndarray, settings: dict[str, Any],
           inputs: tuple[np.ndarray, np.ndarray], before: Callable[[int], None] | None = None,
           index: int = 0) -> dict[str, np.ndarray]:
    """One chunk's result (arrays only: what its `.npz` file holds); `inputs`: `_chunk_inputs`."""
    import jax

    if settings["x64"] and not jax.config.read("jax_enable_x64"):  # a worker process: the client's precision
        jax.config.update("jax_enable_x64", True)
    # a scene shipped to a worker holds NumPy leaves (a JAX array unpickled before the line above
    # would have lost float64)
    scene = jax.tree_util.tree_map(jax.numpy.asarray, scene)
    if before is not None:
        before(index)
    occ_idx, mask = inputs
    if patch.kind == "planar":
        poly, normal = patch.data["poly"], patch.data["normal"]
        d = float(np.max(np.ptp(poly, axis=0)))
        base = poly.mean(axis=0) - d * normal
        sentinel = np.stack([base, base + 1e-2 * (poly[1] - poly[0]), base + 1e-2 * (poly[2] - poly[1])])
        sections, n_open = [], 0
        if scene.occluders is not None and occ_idx.size and mask.any():
            occ = np.asarray(scene.occluders, np.float64)[occ_idx]
            sections, n_open = _cross_sections(occ, poly, normal, max(float(np.abs(occ).max()),
                                                                         float(np.abs(poly).max())))
        options = dict(settings["planar"])
        if n_open:  # a value jump along a line, no hole to cut: elements stop at PIERCED_MIN_EDGE
            options["min_edge"] = max(options.get("min_edge", 0.0), PIERCED_MIN_EDGE * d)
        sub = _chunk_scene(scene, occ_idx, mask, sentinel, sections)
        out = _planar_chunk(sub, mask, patch, pos, settings["tol"], settings["scale"], options, settings["weld"])
        out["pierced"] = np.array([len(sections), n_open], np.int64)
        return out
    sub = _chunk_scene(scene, occ_idx, mask)
    return _refine_curved(_light_scenes(sub), patch, pos, settings["tol"], settings["scale"],
                          settings["min_edge"], settings["max_vertices"], settings["max_rounds"])


def _inputs_digest(scene: Scene, inputs: tuple[np.ndarray, np.ndarray]) -> bytes:
    """What a chunk's result depends on in the scene (`_chunk_inputs`): its lights, occluder
    faces and the ambient term."""
    import jax

    occ_idx, mask = inputs
    h = hashlib.sha256(mask.tobytes())
    for li in np.nonzero(mask)[0]:
        light = scene.lights[li]
        leaves, tree = jax.tree_util.tree_flatten(light)
        h.update(str(tree).encode())
        for leaf in leaves:
            a = np.asarray(leaf)
            h.update(str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
    h.update(np.asarray(scene.ambient).tobytes())
    if scene.occluders is not None and occ_idx.size:
        occ = np.asarray(scene.occluders)
        h.update(str(occ.dtype).encode() + occ_idx.tobytes() + np.ascontiguousarray(occ[occ_idx]).tobytes())
    return h.digest()


def _chunk_name(inputs_digest: bytes, patch: _Patch, pos: np.ndarray, settings: dict[str, Any]) -> str:
    h = hashlib.sha256(inputs_digest + patch.digest())
    h.update(repr(sorted((k, v) for k, v in settings.items() if k != "planar")).encode())
    h.update(repr(sorted(settings["planar"].items())).encode() + str(BAKE_FORMAT).encode())
    if patch.kind == "planar":
        h.update(pos[patch.data["ids"]].tobytes())
    return f"chunk-{h.hexdigest()[:32]}.npz"


# --------------------------------------------------------------------------------------
# Running the chunks
# --------------------------------------------------------------------------------------


def _save_chunk(path: str, result: dict[str, np.ndarray]) -> None:
    from .._core.files import atomic_write

    with atomic_write(path, "wb") as fh:
        np.savez(fh, **result)


def _load_chunk(path: str) -> dict[str, np.ndarray]:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _run_chunks(scene: Scene, patches: list[_Patch], pos: np.ndarray, settings: dict[str, Any],
                work_dir: str | None, scheduler: Any, workers: int | None, progress: Any,
                before: Callable[[int], None] | None) -> tuple[list[dict[str, np.ndarray]], int]:
    occ = None if scene.occluders is None else np.asarray(scene.occluders, np.float64)
    inputs = [_chunk_inputs(scene, occ, p) for p in patches]
    names = [_chunk_name(_inputs_digest(scene, x), p, pos, settings) for p, x in zip(patches, inputs, strict=True)]
    results: list[dict[str, np.ndarray] | None] = [None] * len(patches)
    if work_dir is not None:
        os.makedirs(work_dir, exist_ok=True)
        for i, nm in enumerate(names):
            path = os.path.join(work_dir, nm)
            if os.path.isfile(path):
                try:
                    results[i] = _load_chunk(path)
                except (OSError, ValueError, KeyError):
                    results[i] = None  # unreadable: computed again
    todo = [i for i, r in enumerate(results) if r is None]
    if progress is not None:
        progress(len(patches) - len(todo), len(patches))

    def done(i: int, res: dict[str, np.ndarray]) -> None:
        results[i] = res
        if work_dir is not None:
            _save_chunk(os.path.join(work_dir, names[i]), res)
        if progress is not None:
            progress(1, len(patches))

    if todo and (scheduler is not None or workers is not None):
        import jax
        from distributed import Client, LocalCluster, as_completed

        cluster = None
        if scheduler is None or scheduler == "local":
            cluster = LocalCluster(n_workers=int(workers or 2), threads_per_worker=1, processes=True,
                                   dashboard_address=None)
            client = Client(cluster)
        elif isinstance(scheduler, Client):
            client = scheduler
        else:
            client = Client(scheduler)
        try:
            shipped = jax.tree_util.tree_map(np.asarray, scene)
            scene_f = client.scatter(shipped, broadcast=True, hash=False)
            pos_f = client.scatter(pos, broadcast=True, hash=False)
            futures = {client.submit(_chunk, scene_f, patches[i], pos_f, settings, inputs[i], before, i,
                                     key=f"jaxshadow-bake-{names[i][6:-4]}", pure=False): i for i in todo}
            for fut in as_completed(futures):
                done(futures[fut], fut.result())
        finally:
            if not isinstance(scheduler, Client):
                client.close()
            if cluster is not None:
                cluster.close()
    else:
        for i in todo:
            done(i, _chunk(scene, patches[i], pos, settings, inputs[i], before, i))
    return [r for r in results if r is not None], len(todo)


# --------------------------------------------------------------------------------------
# Stitching and assembly
# --------------------------------------------------------------------------------------


def _stitch(parts: list[dict[str, np.ndarray]], pos: np.ndarray, scenes: list[Scene]) -> dict[str, int]:
    """Give every shared edge the same points in all patches that have it (in place)."""
    occ: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for pi, r in enumerate(parts):
        for j, (a, b) in enumerate(r["edge_keys"].tolist()):
            occ.setdefault((a, b), []).append((pi, j))
    # per part: vertices to re-evaluate, and insertions per triangle edge
    moved: list[set[int]] = [set() for _ in parts]
    newv: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in parts]
    inserts: list[dict[tuple[int, int], list[int]]] = [{} for _ in parts]
    nstitched = 0
    for (ka, kb), sides in sorted(occ.items()):
        if len(sides) < 2:
            continue
        own = []
        for pi, j in sides:
            r = parts[pi]
            sel = r["occ_edge"] == j
            vs, ts = r["occ_vertex"][sel], r["occ_t"][sel]
            if vs.size < 2:  # the patch's mesh has no edge along it (should not happen)
                continue
            o = np.argsort(ts, kind="stable")
            own.append((pi, vs[o], ts[o]))
        if len(own) < 2:
            continue
        allt = np.unique(np.concatenate([o[2] for o in own]))
        canon = [float(allt[0])]
        for t in allt[1:]:
            if t - canon[-1] > EDGE_EPS:
                canon.append(float(t))
        ct = np.array(canon)
        for pi, vs, ts in own:
            r = parts[pi]
            idx = np.searchsorted(ct, ts + EDGE_EPS, side="right") - 1
            idx = np.clip(idx, 0, ct.size - 1)
            for v, k in zip(vs, idx, strict=True):
                p = _on_point(pos, ka, kb, float(ct[k]))
                if not np.array_equal(p, r["vertices"][v]):
                    r["vertices"][v] = p
                    moved[pi].add(int(v))
            for s in range(vs.size - 1):
                u, w = int(vs[s]), int(vs[s + 1])
                missing = [k for k in range(idx[s] + 1, idx[s + 1])]
                if not missing:
                    continue
                nu, nw = r["normals"][u], r["normals"][w]
                ids = []
                for k in missing:
                    t = float(ct[k])
                    f = (t - ts[s]) / (ts[s + 1] - ts[s])
                    n = nu if np.array_equal(nu, nw) else (1 - f) * nu + f * nw
                    n = n if np.array_equal(nu, nw) else n / np.linalg.norm(n)
                    ids.append(r["vertices"].shape[0] + len(newv[pi]))
                    newv[pi].append((_on_point(pos, ka, kb, t), n))
                inserts[pi][(u, w)] = ids
                nstitched += len(ids)
    nmoved = 0
    for pi, r in enumerate(parts):
        if not inserts[pi] and not moved[pi]:
            continue
        V, N, T = r["vertices"], r["normals"], r["triangles"]
        if newv[pi]:
            V = np.concatenate([V, np.array([p for p, _ in newv[pi]])])
            N = np.concatenate([N, np.array([n for _, n in newv[pi]])])
        out, extra_v, extra_n = [], [], []
        for t in T.tolist():
            sides = []
            for k in range(3):
                a, b = t[k], t[(k + 1) % 3]
                if (a, b) in inserts[pi]:
                    sides.append(inserts[pi][(a, b)])
                elif (b, a) in inserts[pi]:
                    sides.append(inserts[pi][(b, a)][::-1])
                else:
                    sides.append([])
            nz = [k for k in range(3) if sides[k]]
            if not nz:
                out.append(t)
            elif len(nz) == 1:
                k = nz[0]
                chain = [t[k], *sides[k], t[(k + 1) % 3]]
                c = t[(k + 2) % 3]
                out += [[chain[i], chain[i + 1], c] for i in range(len(chain) - 1)]
            else:
                loop = []
                for k in range(3):
                    loop += [t[k], *sides[k]]
                g = V.shape[0] + len(extra_v)
                extra_v.append(V[t].mean(axis=0))
                nn = N[t]
                same = np.all(nn == nn[0])
                extra_n.append(nn[0] if same else nn.sum(axis=0) / np.linalg.norm(nn.sum(axis=0)))
                out += [[g, loop[i], loop[(i + 1) % len(loop)]] for i in range(len(loop))]
        if extra_v:
            V = np.concatenate([V, np.array(extra_v)])
            N = np.concatenate([N, np.array(extra_n)])
        n_old = r["vertices"].shape[0]
        fresh = np.r_[np.array(sorted(moved[pi]), np.int64), np.arange(n_old, V.shape[0])]
        vals = np.concatenate([r["values"], np.zeros((V.shape[0] - n_old, *r["values"].shape[1:]))])
        vals[fresh] = _values(scenes, V[fresh], N[fresh])
        nmoved += len(moved[pi])
        r["vertices"], r["normals"], r["triangles"], r["values"] = V, N, np.array(out, np.int64), vals
    return {"stitched_points": nstitched, "moved_points": nmoved}


def _assemble(parts: list[dict[str, np.ndarray]], patches: list[_Patch]) -> tuple[np.ndarray, ...]:
    V = np.concatenate([r["vertices"] for r in parts])
    N = np.concatenate([r["normals"] for r in parts])
    E = np.concatenate([r["values"] for r in parts])
    off = np.cumsum([0] + [r["vertices"].shape[0] for r in parts])
    T = np.concatenate([r["triangles"] + o for r, o in zip(parts, off[:-1], strict=True)])
    patch = np.concatenate([np.full(r["triangles"].shape[0], i, np.int64) for i, r in enumerate(parts)])
    surface = np.array([p.surface for p in patches], np.int64)[patch]
    key = np.ascontiguousarray(np.concatenate([V, N], axis=1)).view(np.dtype((np.void, 48))).ravel()
    _, first, inv = np.unique(key, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")  # keep the first-seen order
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    keep = first[order]
    T = rank[inv.ravel()][T]
    # two vertices of a patch snapped onto one point of a shared edge (the mesher's near-duplicates,
    # 1e-13 apart) are one vertex now: the slivers between them go
    ok = (T[:, 0] != T[:, 1]) & (T[:, 1] != T[:, 2]) & (T[:, 0] != T[:, 2])
    return V[keep], N[keep], T[ok], E[keep], surface[ok], patch[ok]


# --------------------------------------------------------------------------------------
# Public entry point
# --------------------------------------------------------------------------------------


SCALE_GRID = 8  # a planar patch's scale samples: points of a barycentric grid of this order per fan triangle


def _default_scale(scenes: list[Scene], patches: list[_Patch], pos: np.ndarray) -> float:
    """The largest exact total irradiance (W/m^2) at sample points of the patches: a planar
    patch's barycentric grid of order `SCALE_GRID` on each triangle of its fan (corners and
    edges included) and the feet of the perpendiculars from the lights' points when they fall
    inside it; a curved patch's vertices and triangle centroids."""
    i, j = np.meshgrid(np.arange(SCALE_GRID + 1), np.arange(SCALE_GRID + 1), indexing="ij")
    keep = i + j <= SCALE_GRID
    bary = np.stack([i[keep], j[keep], SCALE_GRID - i[keep] - j[keep]], axis=1) / SCALE_GRID  # (G, 3)
    pts, nrm = [], []
    for p in patches:
        if p.kind == "planar":
            poly, normal = p.data["poly"], p.data["normal"]
            fan = np.stack([np.broadcast_to(poly[0], poly[1:-1].shape), poly[1:-1], poly[2:]], axis=1)  # (k-2, 3, 3)
            q = np.einsum("gk,tkd->tgd", bary, fan).reshape(-1, 3)
            feet = []
            for sc in scenes:
                for lp in _light_points(sc.lights[0], poly, 0.0):
                    f = lp - ((lp - poly[0]) @ normal) * normal
                    d = np.roll(poly, -1, axis=0) - poly
                    if np.all(np.cross(d, f - poly) @ normal >= 0):  # inside (counter-clockwise about normal)
                        feet.append(f)
            if feet:
                q = np.concatenate([q, np.array(feet)])
            pts.append(q)
            nrm.append(np.broadcast_to(normal, q.shape))
        else:
            vp, vn, tri = p.data["vpos"], p.data["vnrm"], p.data["tri"]
            c = vn[tri].sum(axis=1)
            pts += [vp, vp[tri].mean(axis=1)]
            nrm += [vn, c / np.linalg.norm(c, axis=1)[:, None]]
    v = _values(scenes, np.concatenate(pts), np.ascontiguousarray(np.concatenate(nrm))).sum(axis=1)
    return float(v.max())


def bake(scene: Scene, receivers: Any = None, tol: float = 1e-3, *, lights: Sequence[int] | None = None,
         scale: float | None = None, work_dir: str | os.PathLike | None = None, scheduler: Any = None,
         workers: int | None = None, weld: float = 1e-6, tile_size: float | None = None,
         max_vertices: int = 2_000_000, min_edge: float | None = None, max_rounds: int = 12,
         progress: Callable[[int, int], None] | None = None,
         _before_chunk: Callable[[int], None] | None = None) -> BakedScene:
    r"""Bake every receiving surface of `scene`: an illumination mesh with exact irradiance per
    light at its vertices, conforming across shared edges (see the module `jaxshadow._illumination.bake`).

    **Arguments:**

    - `scene`: a `Scene` (its occluders cast the shadows).
    - `receivers`: the surfaces to bake: a list of `ReceiverMesh` (`from_mitsuba`'s second
      value, `read_mesh`), `Mesh`, or planar convex polygons `(k, 3)` (m, counter-clockwise
      seen from the lit side), mixed freely; default the scene's occluder polygons.
    - `tol`: relative tolerance in (0, 1): interpolation error over `scale`. Planar patches
      meet it as `illumination_mesh` does (seven checked points per element); curved patches
      at every edge midpoint and centroid.
    - `lights`: indices of the lights to bake (default all); values are kept per light.
    - `scale`: the irradiance (W/m^2) `tol` is relative to; default the largest exact value at
      sample points of the patches (`_default_scale`: a grid on each planar patch and the feet
      of the lights' points; a curved patch's vertices and centroids): the scene's maximum, or
      less (then stricter).
    - `work_dir`: a directory for the per-chunk `.npz` files; chunks already there (same
      inputs, patch and settings) are read, not computed: a killed run resumes, and a re-bake
      after an edit (an object moved, a light changed) computes only the chunks whose inputs
      changed (a chunk's inputs: the lights that reach its patch and the occluder faces that
      may meet its shadow volumes). The result is identical to a fresh bake's at the same
      `scale` (pass the first bake's `scale`: the default follows the scene's maximum, and a
      new maximum changes every chunk's threshold). Default: none (nothing written).
    - `scheduler`: `None` (in this process, unless `workers`), `"local"`, a Dask scheduler
      address (`"tcp://host:8786"`) or a `distributed.Client`.
    - `workers`: with no `scheduler`, the number of worker processes of a Dask `LocalCluster`.
    - `weld`: receiver vertices closer than `weld` times the scene's size are one vertex.
    - `tile_size`, `max_vertices`: passed to `illumination_mesh` for the planar patches;
      `max_vertices` also bounds a curved patch.
    - `min_edge`: elements shorter than this (m) are not split; default 1e-4 of the receivers'
      extent on curved patches, `illumination_mesh`'s default on planar ones. Value
      discontinuities (hard shadows of point lights, objects passing through a curved
      receiver) refine down to it. Closed objects passing through a planar receiver are cut
      out of it (their cross-section is a hole, as the foot of an object standing on it);
      open geometry crossing a planar receiver (a single wall through the floor) makes a value
      jump along a line: that patch's elements stop at `PIERCED_MIN_EDGE` (1e-3) of its size.
      Both are reported in `stats["pierced"]`, elements left over tol in `stats["unconverged"]`.
    - `max_rounds`: refinement rounds of a curved patch (each halves the split edges).
    - `progress`: `None` or `callable(n, total)`: `n` more of the `total` chunks are done
      (first call: the chunks read from `work_dir`, possibly 0; then 1 per chunk computed).

    **Returns:** a `BakedScene`: `vertices (V, 3)`, `normals (V, 3)`, `triangles (T, 3)`,
    `irradiance (V, 3)`, `irradiance_per_light (V, L, 3)`, `surface (T,)`, `patch (T,)`.

    Example:
        ```python
        import numpy as np
        import jaxshadow as js

        light = js.PolygonLight([[-0.3, -0.3, 2], [-0.3, 0.3, 2], [0.3, 0.3, 2], [0.3, -0.3, 2]], radiance=10.0)
        block = [[-0.2, -0.2, 1], [0.2, -0.2, 1], [0.2, 0.2, 1], [-0.2, 0.2, 1]]
        scene = js.Scene([light], occluders=[block])
        floor = [np.array([[-1, -1, 0], [0, -1, 0], [0, 1, 0], [-1, 1, 0.0]]),
                 np.array([[0, -1, 0], [1, -1, 0], [1, 1, 0], [0, 1, 0.0]])]
        baked = js.bake(scene, floor, 2e-2, tile_size=1.0)
        print(baked.vertices.shape, baked.irradiance_per_light.shape)
        ```
    """
    import jax

    t0 = time.perf_counter()
    if not isinstance(scene, Scene):
        raise ValueError(f"bake: expected a jaxshadow.Scene, got {type(scene).__name__}.")
    if not isinstance(tol, (int, float, np.floating)) or not 0 < float(tol) < 1:
        raise ValueError(f"bake: tol must be a number in (0, 1), got {tol!r}.")
    if workers is not None and int(workers) < 1:
        raise ValueError(f"bake: workers must be >= 1, got {workers!r}.")
    n_lights = len(scene.lights)
    sel = list(range(n_lights)) if lights is None else [int(i) for i in lights]
    if not sel or any(not 0 <= i < n_lights for i in sel) or len(set(sel)) != len(sel):
        raise ValueError(f"bake: lights must be distinct indices in [0, {n_lights}), got {lights!r}.")
    import equinox as eqx

    scene = eqx.tree_at(lambda s: s.lights, scene, tuple(scene.lights[i] for i in sel))
    surfaces = _surfaces(scene, receivers)
    patches, pos, names = _patches(surfaces, float(weld))
    if not patches:
        raise ValueError("bake: the receivers have no faces.")
    scenes = _light_scenes(scene)
    if scale is None:
        scale = _default_scale(scenes, patches, pos)
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"bake: scale must be a positive number (the scene is unlit at its sample points?), got {scale!r}.")
    extent = float(np.max(np.ptp(pos, axis=0)))
    planar: dict[str, Any] = {"max_vertices": int(max_vertices)}
    if tile_size is not None:
        planar["tile_size"] = float(tile_size)
    if min_edge is not None:
        planar["min_edge"] = float(min_edge)
    settings = {"tol": float(tol), "scale": float(scale), "x64": bool(jax.config.read("jax_enable_x64")),
                "weld": float(weld) * extent,
                "min_edge": float(min_edge) if min_edge is not None else 1e-4 * extent,
                "max_vertices": int(max_vertices), "max_rounds": int(max_rounds), "planar": planar}
    parts, computed = _run_chunks(scene, patches, pos, settings, None if work_dir is None else os.fspath(work_dir),
                                  scheduler, workers, progress, _before_chunk)
    parts = [{k: np.array(v) for k, v in r.items()} for r in parts]  # writable copies
    stitch = _stitch(parts, pos, scenes)
    V, N, T, E, surface, patch = _assemble(parts, patches)
    unconverged: list[dict[str, Any]] = [{"surface": names[p.surface], "patch": i, "kind": p.kind, "elements": int(r["unrefined"]),
                    "stopped_by_budget": bool(r["stopped"]), "error": float(r["error"])}
                   for i, (p, r) in enumerate(zip(patches, parts, strict=True)) if int(r["unrefined"]) or int(r["stopped"])]
    pierced = [{"surface": names[p.surface], "patch": i, "sections": int(r["pierced"][0]), "open": int(r["pierced"][1])}
               for i, (p, r) in enumerate(zip(patches, parts, strict=True)) if "pierced" in r and r["pierced"].any()]
    stopped = [u for u in unconverged if u["stopped_by_budget"]]
    if stopped:
        warnings.warn(f"bake: {len(stopped)} patches stopped at max_vertices={max_vertices:,} with elements over tol "
                      f"(largest error {max(float(u['error']) for u in stopped):.3g} of scale, tol {tol:g}; surfaces "
                      f"{sorted({str(u['surface']) for u in stopped})}); see BakedScene.stats['unconverged'].",
                      RuntimeWarning, stacklevel=2)
    stats = {"chunks": len(patches), "chunks_computed": computed, "unconverged": unconverged, "pierced": pierced,
             "patches_planar": sum(p.kind == "planar" for p in patches),
             "patches_curved": sum(p.kind == "curved" for p in patches), **stitch,
             "seconds": time.perf_counter() - t0}
    return BakedScene(V, N, T, E, surface, patch, names, np.array(sel, np.int64), float(scale), float(tol), stats)


# --------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------

BAKE_FORMATS = (".glb", ".ply")


def write_bake(path: str | os.PathLike, baked: BakedScene, up: Any = "z") -> None:
    """Write a `BakedScene` as `.glb` or `.ply` (see `BakedScene.save`), atomically; `.glb`
    y-up (the scene's `up` axis turned to +y, `jaxshadow.write_gltf`'s rotation). Vertices are
    written as they are: copies of a point on two surfaces (a crease) keep their own normals
    and values, so no welding."""
    from .._core.files import atomic_write, atomic_write_path
    from .._io.meshio import IRRADIANCE_PROPERTY, _trimesh, y_up_rotation
    from .io import vertex_colours

    trimesh = _trimesh()
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in BAKE_FORMATS:
        raise ValueError(f"bake: unknown output format {ext!r} (expected one of {', '.join(BAKE_FORMATS)}).")
    rot = np.eye(3) if ext == ".ply" else y_up_rotation(up)  # PLY in the scene's own axes
    tm = trimesh.Trimesh(baked.vertices @ rot.T, baked.triangles, vertex_normals=baked.normals @ rot.T,
                         vertex_colors=vertex_colours(baked.irradiance, baked.scale), process=False)
    per = baked.irradiance_per_light
    if ext == ".ply":
        for c, ch in enumerate("rgb"):
            tm.vertex_attributes[f"{IRRADIANCE_PROPERTY}_{ch}"] = np.ascontiguousarray(baked.irradiance[:, c])
        for li in range(per.shape[1]):
            for c, ch in enumerate("rgb"):
                tm.vertex_attributes[f"{IRRADIANCE_PROPERTY}_{li}_{ch}"] = np.ascontiguousarray(per[:, li, c])
        data = tm.export(file_type="ply", encoding="binary", include_attributes=True)
        with atomic_write(path, "wb") as fh:
            fh.write(data)
        return
    tm.vertex_attributes["_IRRADIANCE"] = np.ascontiguousarray(baked.irradiance, np.float32)
    for li in range(per.shape[1]):
        tm.vertex_attributes[f"_IRRADIANCE_{li}"] = np.ascontiguousarray(per[:, li], np.float32)
    atomic_write_path(path, lambda tmp: tm.export(tmp, file_type="glb", include_normals=True))
