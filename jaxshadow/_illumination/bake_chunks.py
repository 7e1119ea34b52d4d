"""One bake chunk: a patch's own inputs (the lights that reach it, the occluder faces that may
meet its shadow volumes), its mesh (planar: `illumination_mesh`; curved: `_refine_curved`) and
its exact irradiance per light at the vertices, and the hash that names its file (`bake`, step 2)."""

from __future__ import annotations

import hashlib
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .._scene.model import Scene
from .bake_patches import _newell, _Patch, _unpad
from .builder import ESTIMATE_MARGIN
from .refine import CORNER_GRADE, CORNER_SIZE

BAKE_FORMAT = 3  # bumped when a chunk file's content changes meaning (part of its hash)
MIN_BATCH = 256  # smallest padded batch of `_values`
_CODE = 1 << 31  # an edge (a, b) of local vertex ids is the code a * _CODE + b
PIERCED_MIN_EDGE = 1e-3  # elements of a patch that open geometry passes through stop here (of its size)


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
                 extra: Sequence[np.ndarray] = (), exact: bool = False) -> Scene:
    """The scene of a chunk: the lights of `mask` and the occluder faces `occ_idx` of `scene`
    (welded again into meshes as `Scene` does; their convexity was checked when `scene` was
    built, so it is not checked again: that costs ~1 ms a face, per chunk). With no face kept,
    `sentinel` (a triangle below a planar patch's plane: it blocks nothing there) is its one
    occluder, so that the chunk runs on the host shadow engine like the others (the unoccluded
    kernels compile per batch shape, ~1 s each, and run slower than the engine here). `extra`:
    polygons added as they are, after the welding (`_cross_sections`). `exact`: the faces moved to
    the double on-surface rule (`exact_planes`: a curved patch's chunk)."""
    from .._core.geometry import pad_polygons_jax
    from .._core.mesh import Mesh, max_face_vertices, stack_occluders, weld_polygons

    sub = Scene(tuple(light for light, m in zip(scene.lights, mask, strict=True) if m), ambient=scene.ambient)
    if scene.occluders is None or occ_idx.size == 0:
        if sentinel is None or scene.occluders is None:
            return sub
        object.__setattr__(sub, "occluders", pad_polygons_jax([sentinel]))
        return sub
    occ = np.asarray(scene.occluders, np.float64)
    if exact:
        occ = exact_planes(occ)
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
    segments = np.zeros((0, 2, 3))
    if scene.lights:
        with warnings.catch_warnings():  # reported per patch in `BakedScene.stats["unconverged"]`
            warnings.simplefilter("ignore", RuntimeWarning)
            # nothing updates a chunk's mesh (a changed chunk is baked again): the lean mesher
            m = illumination_mesh(scene, poly, tol, scale=scale, **{"updatable": False, **options})
        v, tris = np.array(m.vertices, np.float64), np.asarray(m.triangles, np.int64)
        unrefined = int(m.stats.get("unrefined_min_edge", 0))
        stopped = int(m.stats.get("tiles_stopped_by_budget", 0))
        error = float(m.max_error_estimate)
        segments = m.discontinuity_segments()
        del m
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
            "occ_t": np.array(occ_t, np.float64), "unrefined": np.array(unrefined), "stopped": np.array(stopped),
            "error": np.array(error), "segments": segments}


# A point on an edge of its receiver face takes the limit from inside the face: extrapolated
# linearly from the values CURVED_STEP and 2 CURVED_STEP (of the patch's size) inside, towards
# the face's centroid (error O(step^2)). Closer in, a neighbouring face is seen within the
# engine's horizon band (1e-7 rad: nearly edge-on faces block nothing) and still takes the
# point for one of its own.
CURVED_STEP = 1e-6


def exact_planes(occ: np.ndarray) -> np.ndarray:
    """`occ` with every float32 coordinate moved one double ulp up (`np.nextafter`): its faces
    then take the double on-surface rule (`jaxshadow._kernels.planes.ON_SURFACE_64`, 2^-44 of
    the coordinates' magnitude) instead of the float32 one (2^-18). A curved patch's points are
    computed in float64 on its own faces, so they lie in those planes to double rounding; under
    the float32 rule a point of a face within 2^-18 S / sin(dihedral angle) of an edge (1e-5 m
    on a 22-segment sphere of 1 m) counts as lying on the neighbouring face too, which then
    blocks nothing: a band along every edge near the terminator with another value, which no
    refinement resolves. The geometry moves by one ulp (2e-16 relative)."""
    occ = np.asarray(occ, np.float64)
    f32 = occ.astype(np.float32).astype(np.float64) == occ
    return np.where(f32, np.nextafter(occ, np.inf), occ)


def _front(scenes: list[Scene], corners: np.ndarray, size: float) -> np.ndarray:
    """`(L, t)` whether each light lies strictly in front of the plane of each face `corners
    (t, 3, 3)` (beyond 1e-9 of `size`): then the light sees no difference between the face
    and its neighbours' planes at the face's edges (see `_refine_curved`)."""
    from .._scene.model import DirectionalLight

    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    out = np.zeros((len(scenes), corners.shape[0]), bool)
    for li, sc in enumerate(scenes):
        light = sc.lights[0]
        if isinstance(light, DirectionalLight):
            d = np.asarray(light.direction, np.float64)
            out[li] = -(n @ (d / np.linalg.norm(d))) > 1e-9
            continue
        lp = _light_points(light, corners[:, 0], 0.0)  # (k, 3)
        h = np.einsum("tkd,td->tk", lp[None, :, :] - corners[:, None, 0, :], n)
        out[li] = np.all(h > 1e-9 * size, axis=1)
    return out


def _star_pairs(tri: np.ndarray) -> np.ndarray:
    """`(p, 2)` the ordered pairs of distinct faces of `tri (t, 3)` that share a corner."""
    star: dict[int, list[int]] = {}
    for f, t in enumerate(tri.tolist()):
        for v in t:
            star.setdefault(v, []).append(f)
    pairs = {(f, g) for fs in star.values() for f in fs for g in fs if f != g}
    return np.array(sorted(pairs), np.int64).reshape(-1, 2)


def _own_occluders(scenes: list[Scene], tri: np.ndarray, P: np.ndarray, size: float) -> np.ndarray:
    """`(t,)` whether each face `tri (t, 3)` (vertex positions `P`) is also an occluder face of
    the scene (a triangle with the same corners within 1e-7 of `size`): only then does the
    surface shadow itself next to its own edges (the on-surface rule at points of them)."""
    from scipy.spatial import cKDTree

    occ = scenes[0].occluders if scenes else None
    out = np.zeros(tri.shape[0], bool)
    if occ is None or tri.shape[0] == 0:
        return out
    occ = np.asarray(occ, np.float64)
    dist, idx = cKDTree(P).query(occ.reshape(-1, 3), distance_upper_bound=1e-7 * size)
    idx = np.where(np.isfinite(dist), idx, -1).reshape(occ.shape[:2])
    faces = {tuple(sorted(t)) for t in tri.tolist()}
    hit = set()
    for row in idx.tolist():
        ids = sorted(set(row))
        if len(ids) == 3 and ids[0] >= 0:
            hit.add(tuple(ids))
    for f, t in enumerate(tri.tolist()):
        out[f] = tuple(sorted(t)) in hit and tuple(sorted(t)) in faces
    return out


def _folded(tri: np.ndarray, corners: np.ndarray, P: np.ndarray, size: float, own: np.ndarray) -> np.ndarray:
    """The vertex ids where occluder faces of the surface (`own`) meet with one rising above
    another's plane (by more than 1e-9 of `size`): a concave fold's corner. Seen from a point
    of a face at distance r from it, the faces around it hide a solid angle that does not
    shrink with r but turns with the direction of approach, so the irradiance takes a
    different limit along each direction (as at the corner of a box standing on a floor): no
    mesh of linear elements meets `tol` there."""
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    star: dict[int, list[int]] = {}
    for f, t in enumerate(tri.tolist()):
        if own[f]:
            for v in t:
                star.setdefault(v, []).append(f)
    out = []
    for v, fs in star.items():
        fs_a = np.array(fs)
        h = np.einsum("gkd,fd->fgk", P[tri[fs_a]] - P[v], n[fs_a])  # every corner against every plane
        if np.any(h > 1e-9 * size):
            out.append(v)
    return np.array(sorted(out), np.int64)


def _concave(tri: np.ndarray, corners: np.ndarray, P: np.ndarray, size: float, pairs: np.ndarray) -> np.ndarray:
    """`(t,)` whether a face sharing a corner with each face `tri (t, 3)` (corners `(t, 3, 3)`,
    vertex positions `P`) rises above its plane (by more than 1e-9 of `size`): at its edges
    and corners that face shadows the face's inside (a concave fold), but not the points on the
    edge itself (which lie on it: the on-surface rule)."""
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    out = np.zeros(tri.shape[0], bool)
    if pairs.size:
        h = np.einsum("pkd,pd->pk", P[tri[pairs[:, 1]]] - corners[pairs[:, 0], 0][:, None, :], n[pairs[:, 0]])
        out[pairs[np.any(h > 1e-9 * size, axis=1), 0]] = True
    return out


def _refine_curved(scenes: list[Scene], patch: _Patch, pos: np.ndarray, tol: float, scale: float,
                   min_edge: float, max_vertices: int, max_rounds: int) -> dict[str, np.ndarray]:
    """Conforming refinement of a curved triangle set: edges whose midpoint value misses the
    mean of its ends by more than `ESTIMATE_MARGIN * tol * scale` (max over RGB of the light
    sum; the margin as `illumination_mesh`'s: the checked points bound the error elsewhere only
    roughly), and the three edges of triangles whose centroid misses the mean of the corners,
    are split; a triangle with
    two split edges gets its third split too (red: 1-to-4), one with one is bisected (green).
    Stops when no edge fails, at `max_vertices`, or after `max_rounds` rounds. The result
    reports `rounds`, `unrefined` (edges whose midpoint still misses `tol`, the short ones
    included), `stopped` (1: stopped by `max_vertices` with edges failing), `error` (the
    largest midpoint miss over `scale`) and `corner_error` (the same for the edges within
    `CORNER_SIZE` of the patch's size of a concave fold's corner, `_folded`: there the
    irradiance has a different limit along each direction, as at a standing box's footprint
    corner in `illumination_mesh`; those edges are not split and are left out of the others).

    **Values per receiver face.** Each triangle lies in one of the patch's own faces (its
    *face*) and takes that face's values: at a point inside the face, the exact irradiance there
    (the occluders with `exact_planes`); at a point on the face's edges or corners, the limit
    from inside the face (extrapolated from two points `CURVED_STEP` and twice that of the
    patch's size towards the face's centroid). The limit differs from the point's own value
    only where the surface is an occluder next to the face (`_own_occluders`; at a point of an
    edge both faces then lie on the point and block nothing) and, for a light, where that light
    is not strictly in front of the face's plane (`_front`: the terminator, where the faces'
    planes cut the light differently and the irradiance of the faceted surface jumps across its
    edges, the shadow-terminator step of a polygonal mesh) or a face sharing a corner rises
    above the face's plane (`_concave`: it shadows the face's inside up to the edge); elsewhere
    the point's own value is taken. A point where a limit was taken is one vertex per face
    (`side`: the face index + 1), any other one vertex. Points on the patch's boundary edges
    (shared with other patches) take their own value, so that both patches carry the same.

    Vertices are *value vertices* (a point and a face); the splitting decisions are made on
    *geometric* edges (pairs of points), so the two faces' triangles along an edge split
    together and the mesh stays conforming. Edges are int64 codes `a * _CODE + b` (`a < b`):
    each round's unique edges, the cache of evaluated midpoints and the inserted midpoints are
    sorted code arrays (`np.searchsorted`); only the few edges with both ends on the patch's
    boundary go through Python (their points are recorded for stitching)."""
    tri0 = patch.data["tri"].astype(np.int64)
    vwid = patch.data["vwid"]
    P0 = patch.data["vpos"].astype(np.float64)
    t0 = tri0.shape[0]
    corners = P0[tri0]
    size = float(np.max(np.ptp(P0, axis=0))) or 1.0
    step = CURVED_STEP * size
    pairs = _star_pairs(tri0)
    # where the point's own value is not the face's limit (see the docstring): push those
    push = ~_front(scenes, corners, size) | _concave(tri0, corners, P0, size, pairs)[None, :]
    own = _own_occluders(scenes, tri0, P0, size)
    own[pairs[own[pairs[:, 1]], 0]] = True  # a face next to an occluder face of the surface
    folded = P0[_folded(tri0, corners, P0, size, _own_occluders(scenes, tri0, P0, size))]
    near_fold = None
    if folded.shape[0]:
        from scipy.spatial import cKDTree

        fold_tree = cKDTree(folded)

        def near_fold(x: np.ndarray) -> np.ndarray:
            return np.isfinite(fold_tree.query(x, distance_upper_bound=CORNER_SIZE * size)[0])

        def fold_distance(x: np.ndarray) -> np.ndarray:
            return fold_tree.query(x)[0]
    front = ~(push & own[None, :])  # (L, t0): the point's own value is the face's
    cent = corners.mean(axis=1)
    # value vertices: the corners of every face, on their own (merged at the end where equal)
    tri = np.arange(3 * t0, dtype=np.int64).reshape(t0, 3)
    G = tri0.ravel().copy()  # geometric id (the patch's local vertex)
    O = np.repeat(np.arange(t0, dtype=np.int64), 3)  # face
    k3 = np.tile(np.arange(3), t0)
    R = ((1 << k3) | (1 << ((k3 + 2) % 3))).astype(np.int8)  # which of the face's edges it lies on
    P = P0[G]
    N = patch.data["vnrm"].astype(np.float64)[G]
    ng = int(G.max(initial=-1)) + 1
    # the patch's boundary edges (used by one face), in the order the faces list them
    ged = np.sort(np.stack([tri0[:, [0, 1]], tri0[:, [1, 2]], tri0[:, [2, 0]]], axis=1), axis=2).reshape(-1, 2)
    _, inv0, cnt0 = np.unique(ged[:, 0] * _CODE + ged[:, 1], return_inverse=True, return_counts=True)
    once = cnt0[inv0.ravel()] == 1
    ved = np.stack([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]], axis=1).reshape(-1, 2)
    sel = once & (vwid[ged[:, 0]] != vwid[ged[:, 1]])
    bnd = ved[sel]
    edge_keys = np.sort(vwid[G[bnd]], axis=1).astype(np.int64).reshape(-1, 2)
    # on[v] = {boundary edge index: parameter in the welded key's direction}, boundary vertices only
    on: dict[int, dict[int, float]] = {}
    for j, (a, b) in enumerate(bnd.tolist()):
        lo = int(vwid[G[a]]) < int(vwid[G[b]])
        on.setdefault(a, {})[j] = 0.0 if lo else 1.0
        on.setdefault(b, {})[j] = 1.0 if lo else 0.0

    def evaluate(pts: np.ndarray, nrm: np.ndarray, face: np.ndarray, rim: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Values of points of faces `face`; `rim`: on the face's edges, off the patch's boundary."""
        vals = _values(scenes, pts, nrm)
        split = np.zeros(pts.shape[0], bool)
        rows = np.nonzero(rim)[0]
        if rows.size:
            need = ~front[:, face[rows]]  # (L, k)
            rows, need = rows[need.any(axis=0)], need[:, need.any(axis=0)]
            if rows.size:
                d = cent[face[rows]] - pts[rows]
                d *= step / np.linalg.norm(d, axis=1, keepdims=True)
                pv = 2 * _values(scenes, pts[rows] + d, nrm[rows]) - _values(scenes, pts[rows] + 2 * d, nrm[rows])
                vals[rows] = np.where(need.T[:, :, None], pv, vals[rows])
                split[rows] = True
        return vals, split

    E, S = evaluate(P, N, O, np.array([v not in on for v in range(P.shape[0])], bool))
    c_code = np.zeros(0, np.int64)  # evaluated midpoints, sorted by value-edge code
    c_p, c_n, c_v, c_s = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, E.shape[1], 3)), np.zeros(0, bool)
    m_code, m_idx = np.zeros(0, np.int64), np.zeros(0, np.int64)  # inserted midpoints
    fresh = np.ones(tri.shape[0], bool)  # triangles whose centroid is not checked yet
    limit = ESTIMATE_MARGIN * tol * scale  # the checked points bound the error between them only roughly

    def unit(x: np.ndarray) -> np.ndarray:
        return x / np.linalg.norm(x, axis=-1, keepdims=True)

    def lookup(codes: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        at = np.minimum(np.searchsorted(table, codes), max(table.size - 1, 0))
        return at, (table[at] == codes) if table.size else np.zeros(codes.size, bool)

    rounds, bad, emiss = 0, np.zeros(0, bool), np.zeros(0)
    while True:
        tot = E.sum(axis=1)
        ed = np.sort(np.stack([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]], axis=1), axis=2)
        ucode, eid = np.unique((ed[..., 0] * _CODE + ed[..., 1]).ravel(), return_inverse=True)
        eid = eid.reshape(-1, 3)
        ua, ub = ucode // _CODE, ucode % _CODE
        ga, gb = np.minimum(G[ua], G[ub]), np.maximum(G[ua], G[ub])
        gcode, vtog = np.unique(ga * _CODE + gb, return_inverse=True)
        vtog = vtog.ravel()
        at, found = lookup(ucode, c_code)
        if not found.all():
            na, nb = ua[~found], ub[~found]
            mp = 0.5 * (P[na] + P[nb])
            onb = np.zeros(na.size, bool)
            for r in np.nonzero(np.isin(na, list(on)) & np.isin(nb, list(on)))[0]:
                a, b = int(na[r]), int(nb[r])
                common = on[a].keys() & on[b].keys()
                if common:
                    j = min(common)
                    ka, kb = edge_keys[j]
                    mp[r] = _on_point(pos, int(ka), int(kb), 0.5 * (on[a][j] + on[b][j]))
                    onb[r] = True
            same = np.all(N[na] == N[nb], axis=1)
            mn = np.where(same[:, None], N[na], unit(N[na] + N[nb]))
            mv, ms = evaluate(mp, mn, O[na], ((R[na] & R[nb]) != 0) & ~onb)
            c_code = np.concatenate([c_code, ucode[~found]])
            order = np.argsort(c_code, kind="stable")
            c_code = c_code[order]
            c_p, c_n, c_v, c_s = (np.concatenate([c_p, mp])[order], np.concatenate([c_n, mn])[order],
                                  np.concatenate([c_v, mv])[order], np.concatenate([c_s, ms])[order])
            at, found = lookup(ucode, c_code)
        mval = c_v[at].sum(axis=1)
        long = np.linalg.norm(P[ua] - P[ub], axis=1) > min_edge
        corner = np.zeros(ucode.size, bool) if near_fold is None else near_fold(P[ua]) | near_fold(P[ub])
        # a fold's corner: edges there not split below CORNER_SIZE, their error reported apart
        corner &= np.linalg.norm(P[ua] - P[ub], axis=1) <= CORNER_SIZE * size
        if near_fold is not None:  # graded towards a fold's corner: down to CORNER_GRADE of the distance
            r = np.minimum(fold_distance(P[ua]), fold_distance(P[ub]))
            long |= np.linalg.norm(P[ua] - P[ub], axis=1) > CORNER_GRADE * r
        long &= ~corner
        emiss = np.max(np.abs(mval - 0.5 * (tot[ua] + tot[ub])), axis=1)
        cmiss = emiss[corner]
        emiss = np.where(corner, 0.0, emiss)
        gbad = np.zeros(gcode.size, bool)
        gbad[vtog[(emiss > limit) & long]] = True
        if fresh.any():
            ft = tri[fresh]
            same = np.all((N[ft[:, 0]] == N[ft[:, 1]]) & (N[ft[:, 0]] == N[ft[:, 2]]), axis=1)
            cn = np.where(same[:, None], N[ft[:, 0]], unit(N[ft].sum(axis=1)))
            cv = _values(scenes, P[ft].mean(axis=1), cn).sum(axis=1)
            miss = np.max(np.abs(cv - tot[ft].mean(axis=1)), axis=1) > limit
            fe = eid[fresh][miss].ravel()
            gbad[vtog[fe[long[fe]]]] = True
        if not gbad.any() or P.shape[0] >= max_vertices or rounds >= max_rounds:
            bad = gbad[vtog]
            break
        rounds += 1
        geid = vtog[eid]
        while True:  # closure: two split edges -> split the third
            two = gbad[geid].sum(axis=1) == 2
            if not two.any():
                break
            gbad[geid[two].ravel()] = True
        bad = gbad[vtog]
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
            _, gnew = np.unique(vtog[newe], return_inverse=True)  # the faces on both sides: one point
            P, N, E = np.concatenate([P, c_p[ce]]), np.concatenate([N, c_n[ce]]), np.concatenate([E, c_v[ce]])
            S = np.concatenate([S, c_s[ce]])
            G = np.concatenate([G, ng + gnew.ravel()])
            ng += int(gnew.max()) + 1
            O = np.concatenate([O, O[ua[newe]]])
            R = np.concatenate([R, R[ua[newe]] & R[ub[newe]]])
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
    # one vertex per point, but one per face where a face's limit was taken (S)
    side = np.where(S, O + 1, 0)
    _, first, inv = np.unique(np.stack([G, side], axis=1), axis=0, return_index=True, return_inverse=True)
    inv = inv.ravel()
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    keep_v = first[order]
    remap = rank[inv]
    occ_e, occ_v, occ_t = [], [], []
    for vi in sorted(on):
        for j, t in sorted(on[vi].items()):
            occ_e.append(j)
            occ_v.append(int(remap[vi]))
            occ_t.append(t)
    return {"vertices": P[keep_v], "normals": N[keep_v], "triangles": remap[tri], "values": E[keep_v],
            "side": side[keep_v], "edge_keys": edge_keys, "occ_edge": np.array(occ_e, np.int64),
            "occ_vertex": np.array(occ_v, np.int64), "occ_t": np.array(occ_t, np.float64),
            "rounds": np.array(rounds), "unrefined": np.array(int(np.sum(emiss > tol * scale))),
            "stopped": np.array(int(bad.any() and P.shape[0] >= max_vertices)),
            "error": np.array(float(emiss.max(initial=0.0)) / scale),
            "corner_error": np.array(float(cmiss.max(initial=0.0)) / scale), "corners": folded}


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
    sub = _chunk_scene(scene, occ_idx, mask, exact=True)
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
