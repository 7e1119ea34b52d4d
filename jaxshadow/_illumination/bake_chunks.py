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
from .bake_curved import _refine_curved, exact_planes
from .bake_patches import _newell, _Patch, _unpad
from .bake_values import ON_SURFACE, _edge_param, _light_points, _light_scenes, _on_point, _values

BAKE_FORMAT = 3  # bumped when a chunk file's content changes meaning (part of its hash)
PIERCED_MIN_EDGE = 1e-3  # elements of a patch that open geometry passes through stop here (of its size)


# --------------------------------------------------------------------------------------
# One chunk
# --------------------------------------------------------------------------------------



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
