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
   neighbours across a split edge (red-green closure), so the patch stays conforming. A curved
   patch's triangle takes the values of the receiver face it lies in: inside it the exact
   irradiance with the faces as exact planes, on its edges the limit from inside it. Where the
   surface shadows itself the faceted surface's irradiance jumps across its edges near the
   terminator (the faces' planes cut the light differently): such a point is one vertex per
   face (`_refine_curved`).
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

import os
import time
import warnings
from collections.abc import Callable, Sequence
from typing import Any, no_type_check

import numpy as np

from .._scene.model import Scene
from .bake_chunks import (
    _chunk,
    _chunk_inputs,
    _chunk_name,
    _inputs_digest,
)
from .bake_patches import _Patch, _patches, _surfaces
from .bake_values import _light_points, _light_scenes, _on_point, _values

EDGE_EPS = 1e-9  # points on a shared edge closer than this (in its parameter) are one point


# --------------------------------------------------------------------------------------
# Result
# --------------------------------------------------------------------------------------


class BakedScene:
    """The illumination mesh of a whole scene (`bake`).

    **Attributes:**

    - `vertices`: `(V, 3)` positions (m).
    - `normals`: `(V, 3)` unit normals the irradiance was evaluated with.
    - `triangles`: `(T, 3)` vertex indices, counter-clockwise seen from the lit side.
    - `irradiance`: `(V, 3)` exact RGB irradiance from all baked lights (W/m^2). A vertex on the
      edge of an occluder face lying in a planar receiver (the foot of an object standing on
      it, or a cut where one passes through) carries the limit from the open side, evaluated a
      small step (`CONTACT_STEP` of the patch's size) outside the face: along such an edge the
      irradiance jumps, and `js.irradiance` at the point itself sees the face edge-on.
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
      shadows of point lights, geometry passing through the receiver), after `max_rounds` or
      stopped by `max_vertices` (each also a `RuntimeWarning`); `converged`: no such patch (the corners
      below apart: warned when their error is over `tol`); `pierced`: one dict per planar patch that
      occluders pass through (`surface`, `patch`, `sections`: convex pieces of the cut-out
      cross-sections of closed objects, `open`: segments where open geometry crosses it);
      `corners`: one dict per curved patch with corners where its own faces shadow it (concave
      folds, and vertices at the terminator: `_folded`) (`surface`, `patch`,
      `points`: their positions, `error`: the largest checked error over `scale` of the edges
      within `CORNER_SIZE` of the patch's size of them, which are not split: there the
      irradiance takes a different limit along each direction of approach, as at the corner
      of a box standing on a floor, and no mesh meets `tol`).
    """

    def __init__(self, vertices: np.ndarray, normals: np.ndarray, triangles: np.ndarray, per_light: np.ndarray,
                 surface: np.ndarray, patch: np.ndarray, surface_names: list[str], lights: np.ndarray,
                 scale: float, tol: float, stats: dict[str, Any]):
        self.vertices, self.normals, self.triangles = vertices, normals, triangles
        self.irradiance_per_light = per_light
        self.irradiance = per_light.sum(axis=1)
        self.surface, self.patch, self.surface_names = surface, patch, surface_names
        self.lights, self.scale, self.tol, self.stats = lights, float(scale), float(tol), stats
        self._segments: list[np.ndarray] = []  # per patch (`discontinuity_segments`)
        self._patch_surface: list[int] = []

    def discontinuity_segments(self, surface: int | str | None = None) -> np.ndarray:
        """The discontinuity segments the planar patches' mesher inserted as mesh edges
        (`IlluminationMesh.discontinuity_segments`: shadow lines and contact lines), `(k, 2, 3)`
        end points (m), of the surface `surface` (an index into `surface_names` or a name) or of
        all. Curved patches have none: they are refined on their own triangles, and where their
        faces' values differ at a shared edge (`stats["corners"]`, the terminator) the edge is
        one of the surface's own."""
        if isinstance(surface, str):
            if surface not in self.surface_names:
                raise ValueError(f"BakedScene.discontinuity_segments: no surface {surface!r} "
                                 f"(surfaces: {self.surface_names}).")
            surface = self.surface_names.index(surface)
        keep = [s for s, k in zip(self._segments, self._patch_surface, strict=True) if surface is None or k == surface]
        return np.concatenate(keep) if keep else np.zeros((0, 2, 3))

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
        if "side" in r:  # the added points are one vertex each
            r["side"] = np.concatenate([r["side"], np.zeros(V.shape[0] - n_old, np.int64)])
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
    # a curved patch's point on a face edge where the faces' limits differ is one vertex per face (`side`)
    side = np.concatenate([r["side"] if "side" in r else np.zeros(r["vertices"].shape[0], np.int64) for r in parts])
    key = np.ascontiguousarray(np.concatenate([V, N, side[:, None].astype(np.float64)], axis=1))
    key = key.view(np.dtype((np.void, 56))).ravel()
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


# Validates its own inputs (ValueError, docs/design.md): no runtime annotation check before it.
@no_type_check
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
    corners = [{"surface": names[p.surface], "patch": i, "points": r["corners"].tolist(), "error": float(r["corner_error"])}
               for i, (p, r) in enumerate(zip(patches, parts, strict=True)) if "corners" in r and r["corners"].size]
    stopped = [u for u in unconverged if u["stopped_by_budget"]]
    if stopped:
        warnings.warn(f"bake: {len(stopped)} patches stopped at max_vertices={max_vertices:,} with elements over tol "
                      f"({_over_tol(stopped, tol)}); see BakedScene.stats['unconverged'].", RuntimeWarning, stacklevel=2)
    short = [u for u in unconverged if not u["stopped_by_budget"]]
    if short:
        warnings.warn(f"bake: {len(short)} patches left elements over tol ({_over_tol(short, tol)}) at the minimum "
                      f"edge length (a value jump: a hard shadow, geometry through the receiver) or after "
                      f"max_rounds={max_rounds}; see BakedScene.stats['unconverged'].", RuntimeWarning, stacklevel=2)
    sharp = [c for c in corners if c["error"] > tol]
    if sharp:
        warnings.warn(f"bake: {sum(len(c['points']) for c in sharp)} corners of curved patches (surfaces "
                      f"{sorted({str(c['surface']) for c in sharp})}), where the irradiance takes a different limit "
                      f"along each direction of approach, left over tol within CORNER_SIZE of them (largest error "
                      f"{max(float(c['error']) for c in sharp):.3g} of scale, tol {tol:g}); see "
                      f"BakedScene.stats['corners'].", RuntimeWarning, stacklevel=2)
    stats = {"chunks": len(patches), "chunks_computed": computed, "converged": not unconverged,
             "unconverged": unconverged, "pierced": pierced, "corners": corners,
             "patches_planar": sum(p.kind == "planar" for p in patches),
             "patches_curved": sum(p.kind == "curved" for p in patches), **stitch,
             "seconds": time.perf_counter() - t0}
    baked = BakedScene(V, N, T, E, surface, patch, names, np.array(sel, np.int64), float(scale), float(tol), stats)
    baked._segments = [np.asarray(r.get("segments", np.zeros((0, 2, 3))), np.float64).reshape(-1, 2, 3) for r in parts]
    baked._patch_surface = [p.surface for p in patches]
    return baked


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
    from .._io.meshio import IRRADIANCE_PROPERTY, import_trimesh, y_up_rotation
    from .io import vertex_colours

    trimesh = import_trimesh()
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


def _over_tol(items: list, tol: float) -> str:
    """The largest error of `items` (dicts with 'error' and 'surface') against tol, and their surfaces."""
    return (f"largest error {max(float(u['error']) for u in items):.3g} of scale, tol {tol:g}; surfaces "
            f"{sorted({str(u['surface']) for u in items})}")
