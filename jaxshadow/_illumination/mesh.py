r"""Illumination meshes: adaptive receiver meshes with exact irradiance at their vertices.

Campbell & Fussell (§3.3, §4.4) mesh each receiver so that the illumination is represented to a
tolerance: shadow boundaries become mesh edges, regions are refined until the intensity over each
element varies less than the tolerance, extrema are found by optimisation, and T vertices are
avoided. Chrysanthou & Slater keep such a mesh per receiver and, when an object moves, redo only
the part of it the object's shadow touches. `illumination_mesh` builds that mesh for a planar
receiver polygon:

1. **Tiles.** The receiver is cut by a fixed grid into convex tiles (the leaves of a shallow
   i-tree, §4.1). Every tile is meshed from its own data only, and the tile edges are refined
   first, on their own, so neighbouring tiles share their edge vertices (no T vertices, §4.4.5)
   and a tile whose neighbourhood did not change meshes identically: what makes the incremental
   update exact (`IlluminationMesh.update`).
2. **Discontinuity lines** (`_illumination_events`): the VE and EV event segments of the
   occluders that can shadow the receiver, kept where a ray along the event is not blocked, and
   the lines leaving the foot of an occluder edge standing on the receiver (the planes through
   that edge and another edge in a plane with it), inserted as constrained edges of a
   constrained Delaunay triangulation (artem-ogre's CDT, through the `pythoncdt` package). Each
   tile's occluder list holds the faces whose shadow volume can reach it (C&F §4.3, C&S's
   per-cell occluder lists).
3. **Extrema** (`_illumination_extrema`): starts where a coarse grid sample beats its
   neighbours, batched BFGS on central differences of exact values (or on the exact gradient,
   `jax.grad`), and a golden-section search along tile edges; the extrema become vertices.
4. **Refinement.** Every element is checked at seven points (edge midpoints, centroid, and the
   midpoints between centroid and corners) against exact irradiance; the worst point of an
   element whose linear interpolation misses by more than `ESTIMATE_MARGIN * tol * scale` is
   inserted, and the tile re-triangulated, until no element fails. Tile edges are refined the
   same way in 1-D beforehand. A round's triangulation starts with the previous round's vertices
   in order, so the elements it keeps (same three vertices) keep their checked errors and the
   vertices keep their evaluated values: a round evaluates and looks up only the new vertices
   and the new elements' check points (`_illumination_refine`). A round's inner check points
   (most of the evaluations) are evaluated in groups of tiles, and a mesher that will not be
   updated (`updatable=False`) drops after each round the values it will not ask for again: the
   elements' inner check points and everything strictly inside a finished tile; it keeps a value
   per evaluated point and nothing else (where and how it was evaluated are for `update`), and
   hands the freed heap back to the system after each round.

Values come from `jaxshadow.irradiance` (the host shadow engine for concrete inputs).
"""

from __future__ import annotations

import time
import warnings
from typing import Any

import numpy as np

from .._core.geometry import check_convex_polygon
from .._scene.model import Scene
from . import events as ev
from .builder import ESTIMATE_MARGIN as ESTIMATE_MARGIN  # noqa: F401 (documented)
from .builder import _Builder
from .pslg import _Edge, _interpolate, _Tile
from .refine import CORNER_GRADE, CORNER_SIZE

# --------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------


class IlluminationMesh:
    """A receiver mesh whose vertices carry exact irradiance (`illumination_mesh`).

    **Attributes:**

    - `vertices`: `(V, 3)` vertex positions (m).
    - `triangles`: `(T, 3)` vertex indices, counter-clockwise seen from the receiver's lit side.
    - `irradiance`: `(V, 3)` exact RGB irradiance at the vertices (W/m^2).
    - `max_error_estimate`: the largest checked interpolation error over all elements, relative
      to `scale` (each element checked at seven points against exact values), but those within
      `CORNER_SIZE` (1e-4 of the receiver's size) of a corner of a standing object's footprint:
      there the irradiance takes a different limit along each direction of approach, no mesh
      meets `tol`, and their error is `stats["corner_error"]`; and zero-area slivers (width
      below 1e-9 of their length, where a computed crossing lands off a line by round-off).
    - `scale`: the irradiance `tol` is relative to (W/m^2): the receiver's maximum found by the
      extremum search, unless given.
    - `tol`: the requested relative tolerance.
    - `updatable`: whether `update` can follow (`illumination_mesh(..., updatable=...)`).
    - `stats`: counts and timings (lines, extrema, evaluations, tiles re-meshed by an update,
      exact values dropped by a mesher without update: `rows_released`),
      and the elements that stopped refining at the minimum edge length: `unrefined_min_edge`
      (elements whose checked error is over the threshold but whose longest edge is at most
      `min_edge`, so they are not split), `tiles_unrefined_min_edge` (the tiles holding them)
      and `unrefined_min_edge_error` (their largest error, relative to `scale`).

    Those elements count in `max_error_estimate`, which can therefore exceed `tol` while the
    interpolation error measured on a dense grid stays below it. Near the corners of standing
    objects' footprints, the kinks along the planes through the object's edge there and another
    edge in a plane with it (`_illumination_events.corner_segments`) would be such elements
    (their gradient grows as 1/r towards the corner); they are mesh edges.
    """

    def __init__(self, builders: list[_Builder], tol: float, stats: dict[str, Any]):
        self._builders = builders
        self._segments = np.concatenate([b.segments() for b in builders]) if builders else np.zeros((0, 2, 3))
        parts = []
        for b in builders:
            parts.append(b.assemble())
            if b.lean:  # (`illumination_mesh(..., updatable=False)`): the assembled arrays are the mesh
                b.release_all()
        if len(parts) == 1:
            self.vertices, self.triangles, self.irradiance = parts[0][:3]
        else:
            off = np.cumsum([0] + [p[0].shape[0] for p in parts])
            self.vertices = np.concatenate([p[0] for p in parts])
            self.triangles = np.concatenate([p[1] + o for p, o in zip(parts, off[:-1], strict=True)])
            self.irradiance = np.concatenate([p[2] for p in parts])
        self.max_error_estimate = max(p[3] for p in parts)
        del parts
        tiles = [(t, float(b.scale)) for b in builders for t in b.tiles]
        stats = {**stats, "corner_error": max(t.corner_error / sc for t, sc in tiles),
                 "unrefined_min_edge": sum(t.unrefined for t, _ in tiles),
                 "tiles_unrefined_min_edge": sum(t.unrefined > 0 for t, _ in tiles),
                 "unrefined_min_edge_error": max(t.unrefined_error / sc for t, sc in tiles)}
        self.scale = max(float(b.scale) for b in builders)
        self.tol = float(tol)
        self.stats = stats
        self.updatable = not any(b.lean for b in builders)

    def __repr__(self) -> str:
        return (f"IlluminationMesh({self.vertices.shape[0]} vertices, {self.triangles.shape[0]} triangles, "
                f"tol={self.tol:g}, max_error_estimate={self.max_error_estimate:.3g}, scale={self.scale:.4g})")

    def discontinuity_segments(self) -> np.ndarray:
        """The discontinuity segments the mesher inserted as mesh edges: `(k, 2, 3)` end points
        (m) on the receiver. They are the shadow lines (VE and EV event segments of the
        occluders, kept where the visibility test along the event is passed, each tile's share
        of them: a line crossing tiles comes in pieces) and the contact lines (the feet of
        occluders standing on the receiver and the lines leaving their corners). The mesh's
        edges run along them; the irradiance, or its derivative, jumps across them."""
        return self._segments.copy()

    def interpolate(self, points: Any) -> np.ndarray:
        """Linear interpolation of the vertex irradiance at `points (N, 3)` on a single-polygon
        receiver (projected onto its plane): `(N, 3)`, NaN outside the receiver."""
        if len(self._builders) != 1:
            raise ValueError("IlluminationMesh.interpolate: only for a single receiver polygon.")
        b = self._builders[0]
        return _interpolate(b.frame.to2d(self.vertices), self.triangles, self.irradiance,
                            b.frame.to2d(np.asarray(points, np.float64).reshape(-1, 3)))

    def update(self, scene: Any) -> IlluminationMesh:
        """The mesh of the same receiver in `scene`, where only occluders changed (moved, added or
        removed): only the tiles that the changed occluders' shadow volumes can reach, before or
        after the change, are meshed again (Chrysanthou & Slater §3); the others are kept as they
        are. In the tiles meshed again, an exact value the old mesh computed is taken over, not
        computed again, where the changed occluders cannot affect it: outside their footprints,
        and where their bounding box (before and after the change) misses the point's
        illumination region of every light (`ShadowCache.update`'s test); the engine's value
        there does not depend on them. The result equals `illumination_mesh(scene, receiver, tol,
        scale=self.scale)` with the same settings, bit for bit. `stats` says how many tiles were
        redone (`tiles_meshed`), how many old values the change can affect (`values_affected`)
        or not (`values_kept`), and how many of the latter the new mesh used (`reused`).

        Raises `ValueError` if the lights or ambient changed (re-mesh instead), or if the mesh was
        built with `updatable=False`."""
        t0 = time.perf_counter()
        if not self.updatable:
            raise ValueError("IlluminationMesh.update: this mesh was built with updatable=False; "
                             "build it with updatable=True (the default) to update it.")
        if not isinstance(scene, Scene):
            raise ValueError(f"IlluminationMesh.update: expected a jaxshadow.Scene, got {type(scene).__name__}.")
        old = self._builders[0].scene
        if not _same_lights(old, scene):
            raise ValueError("IlluminationMesh.update: the lights changed; build a new mesh with illumination_mesh.")
        out = []
        meshed = 0
        for b in self._builders:
            nb = _updated(b, scene)
            meshed += nb.stats["tiles_meshed"]
            out.append(nb)
        stats = {"seconds": time.perf_counter() - t0, "tiles_meshed": meshed,
                 "tiles": sum(len(b.tiles) for b in out), **_merged_stats(out)}
        return _budget_warning(IlluminationMesh(out, self.tol, stats), out[0].max_vertices)

    def save(self, path: Any) -> None:
        """Write the mesh as PLY (vertex colours and the float irradiance as vertex properties) or
        glTF (`.gltf`/`.glb`, vertex colours), by the file's extension (`_illumination_io`)."""
        from .io import save_mesh

        save_mesh(self, path)


def _same_lights(a: Scene, b: Scene) -> bool:
    from .._scene.format import light_to_dict

    la = [light_to_dict(x) for x in a.lights]
    lb = [light_to_dict(x) for x in b.lights]
    return la == lb and np.array_equal(np.asarray(a.ambient), np.asarray(b.ambient))


def _face_rows(scene: Scene) -> np.ndarray:
    if scene.occluders is None:
        return np.zeros((0, 1, 3))
    return np.asarray(scene.occluders, np.float64)


def _updated(old: _Builder, scene: Scene) -> _Builder:
    import copy

    nb = copy.copy(old)
    nb.stats = {}
    nb.tiles = list(old.tiles)
    nb.edges = dict(old.edges)
    nb._load_scene(scene, old.occ)
    fo, fn = _face_rows(old.scene), _face_rows(scene)
    ko = max(fo.shape[1], fn.shape[1])
    pad = lambda f: np.concatenate([f, np.repeat(f[:, :1], ko - f.shape[1], axis=1)], axis=1)  # noqa: E731
    ro = {r.tobytes() for r in pad(fo)} if fo.shape[0] else set()
    rn = {r.tobytes() for r in pad(fn)} if fn.shape[0] else set()
    gone = [i for i, r in enumerate(pad(fo)) if r.tobytes() not in rn] if fo.shape[0] else []
    new = [i for i, r in enumerate(pad(fn)) if r.tobytes() not in ro] if fn.shape[0] else []
    boxes = np.concatenate([old.foot[gone], nb.foot[new]]) if (gone or new) else np.zeros((0, 4))
    # Exact values the change cannot affect are taken over from the old mesh's evaluations.
    step = float(np.linalg.norm(nb.eval.step)) * (1 + 1e-6)
    fin = boxes[np.all(np.isfinite(boxes), axis=1)]
    # Tiles within reach of a changed contact polygon's corners are re-meshed too: which of
    # their elements count as at a corner (`_Builder.at_contact_corner`), and how far the
    # failing ones may be split near it (`CORNER_GRADE`), depend on them.
    margin = max(1e-6 * old.diam, CORNER_SIZE * old.diam, old.min_edge / CORNER_GRADE)
    tile_ids = [ti for ti, t in enumerate(nb.tiles) if fin.size and np.any(ev.boxes_overlap(fin, t.lo, t.hi, margin))]
    region = np.array([np.concatenate([nb.tiles[ti].lo - margin, nb.tiles[ti].hi + margin]) for ti in tile_ids]).reshape(-1, 4)
    nb.eval.inherit(old.eval, lambda xy: ~_affected(scene, nb.frame, step, xy, [fo[gone], fn[new]], boxes,
                                                    1e-6 * old.diam), region)
    edge_keys = [k for k, e in nb.edges.items()
                 if fin.size and np.any(ev.boxes_overlap(fin, np.minimum(e.a, e.b), np.maximum(e.a, e.b), margin))]
    for ti in tile_ids:
        t = nb.tiles[ti]
        nb.tiles[ti] = _Tile(t.poly, t.gids, t.lo, t.hi)
    for ti in tile_ids:
        for ga, gb, _ in nb.tiles[ti].edge_keys():
            e = nb.edges[(ga, gb)]
            nb.edges[(ga, gb)] = _Edge(e.a, e.b, s=e.s)
    nb._edge_extrema = {}
    nb.build(tile_ids, edge_keys)
    return nb


def _affected(scene: Scene, frame: Any, step: float, xy: np.ndarray, faces: list[np.ndarray],
              foot: np.ndarray, margin: float) -> np.ndarray:
    """`(n,)` bool: whether the value at receiver points `xy (n, 2)`, or at any point within
    `step` of them (the on-line check's neighbours), may depend on the occluder faces `faces`
    (arrays `(m, k, 3)`: the changed faces before and after the change). Points outside the
    faces' footprints `foot (f, 4)` (the regions their shadow volumes can reach, which also
    decide the tiles an update re-meshes) and outside the faces' own outlines are not affected;
    for the others the test of `ShadowCache.update` (`_cache.affected`: the bounding box of each
    group, grown by `step`, against the point's illumination region of every light)."""
    from .._shadows.cache import affected

    out = np.zeros(xy.shape[0], bool)
    groups = [f.reshape(-1, 3) for f in faces if f.shape[0]]
    if not groups or xy.shape[0] == 0:
        return out
    own = [np.concatenate([frame.to2d(g).min(axis=0), frame.to2d(g).max(axis=0)]) for g in groups]
    boxes = np.concatenate([foot.reshape(-1, 4), np.array(own)])
    boxes = boxes[np.all(np.isfinite(boxes), axis=1)]
    grow = margin + step
    if boxes.shape[0] == 0:
        return out
    # The boxes' common bounding box first (they overlap: one object's faces), then each box.
    x, y = xy[:, 0], xy[:, 1]
    idx = np.nonzero((x >= boxes[:, 0].min() - grow) & (x <= boxes[:, 2].max() + grow)
                     & (y >= boxes[:, 1].min() - grow) & (y <= boxes[:, 3].max() + grow))[0]
    x, y = x[idx], y[idx]
    near = np.zeros(idx.size, bool)
    for bx in boxes:
        near |= (x >= bx[0] - grow) & (x <= bx[2] + grow) & (y >= bx[1] - grow) & (y <= bx[3] + grow)
    idx = idx[near]
    if idx.size == 0:
        return out
    p3 = np.ascontiguousarray(frame.to3d(xy[idx]))
    nrm = np.ascontiguousarray(np.broadcast_to(frame.normal, p3.shape))
    lo = np.array([g.min(axis=0) - step for g in groups])
    hi = np.array([g.max(axis=0) + step for g in groups])
    hit = np.zeros(idx.size, bool)
    for light in scene.lights:
        hit |= affected(light, p3, nrm, lo, hi)
    out[idx] = hit
    return out


def _merged_stats(builders: list[_Builder]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for b in builders:
        for k, v in b.stats.items():
            out[k] = out.get(k, 0) + v if isinstance(v, (int, float)) and k != "rounds" else v
    return out


GRADIENTS = ("differences", "jax")


def illumination_mesh(scene: Any, receiver: Any, tol: float = 1e-3, *, max_vertices: int = 2_000_000,
                      tile_size: float | None = None, min_edge: float | None = None, gradient: str = "differences",
                      scale: float | None = None, progress: Any = None, updatable: bool = True) -> IlluminationMesh:
    r"""An adaptive, discontinuity-aware mesh of `receiver` with exact irradiance at its vertices.

    Linear interpolation of the vertex irradiance over each triangle stays within `tol` times the
    receiver's maximum irradiance, as checked against exact values at seven points per triangle
    (with a safety factor `ESTIMATE_MARGIN`); the shadows' discontinuity lines (VE and EV events
    of the polygon and linear lights, Campbell & Fussell's extremal planes, and the lines leaving
    a standing occluder's foot) are mesh edges and the
    illumination's local extrema (found by optimisation, §3.3) are vertices. See the module
    docstring for the method and `IlluminationMesh.update` for moving occluders.

    **Arguments:**

    - `scene`: a `Scene` (any lights; shadows exact).
    - `receiver`: a planar convex polygon `(k, 3)` (m), counter-clockwise seen from its lit side
      (the side its right-hand-rule normal points to), or a `Mesh` or list of such polygons (each
      face meshed on its own; vertices are not shared between faces).
    - `tol`: relative tolerance in (0, 1): interpolation error over the receiver's maximum.
    - `max_vertices`: stop refining once the mesh has this many vertices (per receiver polygon);
      if elements over `tol` are left then, a `RuntimeWarning` says so and
      `stats["tiles_stopped_by_budget"]` counts the tiles (`max_error_estimate` exceeds `tol`).
    - `tile_size`: side of the tiles the receiver is cut into (m); default 1/16 of its extent.
      Every refinement round triangulates each tile that still refines anew, and `update`
      meshes again the tiles a moved occluder's shadow reaches: on receivers crowded with
      shadows (many standing objects) smaller tiles are faster for both (the box benchmark
      uses 1/32).
    - `min_edge`: elements smaller than this are not split (m); default 1e-6 of the extent (but
      within `min_edge / CORNER_GRADE` of a footprint corner, down to `CORNER_GRADE` = 1e-3 of
      their distance to it: the irradiance varies there with the direction from it). Value
      discontinuities (hard shadows of point lights, occluders touching the receiver) cannot be
      interpolated within `tol`; they stop here and show in `max_error_estimate`.
    - `gradient`: how the extremum search differentiates: `"differences"` (default: central
      differences of exact values, step 1e-6 of a tile) or `"jax"` (`jax.grad` of the traced
      irradiance; exact, but it compiles the device kernel for every batch size, which costs far
      more than the search on all but the smallest scenes).
    - `scale`: the irradiance (W/m^2) `tol` is relative to; default the receiver's maximum.
    - `progress`: `None` or a callable, called after each refinement round with a dict: `round`,
      `tiles_active` (tiles still refining), `tile_vertices` (vertices of all tiles, those on
      shared tile edges counted once per tile), `failing_elements` (elements split this round),
      `seconds` (since refinement began); for a receiver of several polygons, per polygon.
    - `updatable`: keep what `IlluminationMesh.update` needs (every exact value computed, the
      tiles' meshes). With False the mesher drops the values it no longer needs as tiles
      finish (the points strictly inside finished tiles, the elements' check points), keeps
      nothing per evaluated point but its value, and the mesh keeps only its arrays: far less memory on large meshes (the box benchmark's floor
      at tol 1e-4), the same vertices, triangles and values bit for bit; `update` then raises.

    **Returns:** `IlluminationMesh` with `vertices (V, 3)`, `triangles (T, 3)`, `irradiance (V, 3)`,
    `max_error_estimate`, `scale`, `stats`.

    Example:
        ```python
        import os, tempfile
        import numpy as np
        import jaxshadow as js

        light = js.PolygonLight([[-0.3, -0.3, 2], [-0.3, 0.3, 2], [0.3, 0.3, 2], [0.3, -0.3, 2]], radiance=10.0)
        scene = js.Scene([light], occluders=[[[-0.4, -0.2, 1], [0.2, -0.2, 1], [0.2, 0.3, 1], [-0.4, 0.3, 1]]])
        floor = np.array([[-1.5, -1.5, 0], [1.5, -1.5, 0], [1.5, 1.5, 0], [-1.5, 1.5, 0]])
        mesh = js.illumination_mesh(scene, floor, 2e-2, tile_size=1.0)
        print(mesh.vertices.shape, mesh.triangles.shape, mesh.max_error_estimate)
        mesh.save(os.path.join(tempfile.mkdtemp(), "floor.ply"))  # vertex colours, exact irradiance per vertex
        ```
    """
    t0 = time.perf_counter()
    if not isinstance(scene, Scene):
        raise ValueError(f"illumination_mesh: expected a jaxshadow.Scene, got {type(scene).__name__}.")
    if not isinstance(tol, (int, float, np.floating)) or not 0 < float(tol) < 1:
        raise ValueError(f"illumination_mesh: tol must be a number in (0, 1), got {tol!r}.")
    if gradient not in GRADIENTS:
        raise ValueError(f"illumination_mesh: gradient must be one of {GRADIENTS}, got {gradient!r}.")
    if int(max_vertices) < 3:
        raise ValueError(f"illumination_mesh: max_vertices must be >= 3, got {max_vertices!r}.")
    for name, val in (("tile_size", tile_size), ("min_edge", min_edge), ("scale", scale)):
        if val is not None and not (np.isfinite(val) and val > 0):
            raise ValueError(f"illumination_mesh: {name} must be a positive number, got {val!r}.")
    try:
        import pythoncdt  # noqa: F401
    except ImportError:
        raise ImportError("illumination_mesh needs the 'pythoncdt' package: pip install 'jaxshadow[mesh]'") from None
    from .._core.mesh import Mesh

    if isinstance(receiver, Mesh):
        polys = list(receiver.polygons)
    elif isinstance(receiver, (list, tuple)) and receiver and np.asarray(receiver[0]).ndim == 2:
        polys = [np.asarray(p) for p in receiver]
    else:
        polys = [receiver]
    polys = [check_convex_polygon(p, f"illumination_mesh: receiver{'' if len(polys) == 1 else f'[{i}]'}")
             for i, p in enumerate(polys)]
    builders = []
    for p in polys:
        b = _Builder(scene, p, float(tol), tile_size, min_edge, max_vertices, gradient, scale)
        b.progress = progress
        b.lean = not updatable
        if b.lean:
            b.eval.make_lean()
        b.build(list(range(len(b.tiles))), list(b.edges))
        if b.lean:  # (the values are in the tiles now)
            b.release_evaluator()
        builders.append(b)
    if scale is None and len(builders) > 1:
        top = max(float(b.scale) for b in builders)
        for b in builders:  # one scale for the whole receiver: refine the faces with a lower one again
            if float(b.scale) < top:
                b.scale = top
        # (refinement is monotone: faces meshed with a smaller scale already meet the larger one)
    stats = {"seconds": time.perf_counter() - t0, "tiles": sum(len(b.tiles) for b in builders), **_merged_stats(builders)}
    return _budget_warning(IlluminationMesh(builders, float(tol), stats), max_vertices)


def _budget_warning(mesh: IlluminationMesh, max_vertices: int) -> IlluminationMesh:
    """Warn when refinement stopped at the vertex budget with elements still over `tol`."""
    if mesh.stats.get("tiles_stopped_by_budget", 0):
        warnings.warn(f"illumination_mesh: refinement stopped at max_vertices={max_vertices:,} with elements "
                      f"over tol in {mesh.stats['tiles_stopped_by_budget']} tiles (max_error_estimate "
                      f"{mesh.max_error_estimate:.3g}, tol {mesh.tol:g}); raise max_vertices or tol.",
                      RuntimeWarning, stacklevel=3)
    return mesh
