r"""Mesh occluders: a triangle (or convex-polygon) mesh as one occluder object.

A mesh blocks exactly what the union of its faces blocks, but handing the faces to the shadow
kernel one by one wastes work: the edges that two faces share are cut and then dropped again, and
a closed box costs twelve occluders. `Mesh` prepares a mesh once, in NumPy, before any compiled
code runs (Campbell & Fussell §4.2.2 use the same two facts):

- **Coplanar merging.** Faces that share an edge and lie in one plane are merged into one convex
  polygon when their union is convex (a box's two triangles per side become one quad). The union
  of coplanar faces is the same point set, so blocking is unchanged.
- **Closed meshes.** A mesh in which every edge is shared by exactly two faces running it in
  opposite directions is closed; its faces are oriented outwards (flipped if its signed volume is
  negative). A segment from a receiver outside a closed mesh that passes through it enters through
  a face whose outward side faces the receiver, so back faces can be dropped (C&F: "a front face of
  the same object must block the same light").
- **Convex solids.** A closed mesh whose vertices all lie on or behind every face plane is convex:
  seen from a receiver outside it, it blocks exactly the cone through its silhouette edges (the
  edges between a front and a back face), one convex region instead of up to three front faces;
  the shadow engine (`csrc/shadowc.cc`) uses that cone when the receiver is strictly outside and the
  solid strictly on the receiver's side of the light's plane, and the faces otherwise.

The result feeds `Scene`: the merged faces become rows of `Scene.occluders` (differentiable
vertex coordinates), the topology (which faces form a closed mesh or a convex solid, the solid's
edges with their two faces) a static `OccluderTopology`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from .faces import _check_faces, _closed, _convex, _face_table, _merge, _solid_edges
from .geometry import strip_padding


class Mesh:
    """A mesh occluder (m): vertices and faces, prepared once for the shadow engine.

    **Arguments:**

    - `vertices`: `(V, 3)` vertex positions (m).
    - `faces`: `(F, 3)` triangle vertex indices, or a list of index lists (convex planar polygons),
      counter-clockwise seen from outside for closed meshes (a closed mesh with inward faces is
      flipped; an open mesh may have any orientation: it blocks light from both sides).
    - `merge`: merge coplanar neighbouring faces into convex polygons (default True).
    - `weld`: `None` (default): the vertices as given. `0.0`: vertices at exactly equal
      positions are merged first (`-0.0` equals `0.0`); `tol > 0`: positions within `tol` (m) of
      each other, transitively (`jaxshadow.ReceiverMesh.welded`'s rule, by position only). A
      mesh split at UV seams or stored as a triangle soup then becomes one surface, found closed
      (and convex) when it is, which the shadow engine culls and traces faster; faces that a
      tolerance collapses (fewer than three distinct vertices) are dropped. `read_mesh` and
      `from_mitsuba` weld their occluders by position already. The welded mesh's `vertices` are
      the first vertex of each group, in the order of their first occurrence (a mesh without
      duplicates keeps its vertices and indices unchanged).

    **Attributes:** `polygons` (list of `(k, 3)` arrays, the faces the kernels see), `loops`
    (their vertex indices), `closed`, `convex`, `n_input_faces`, `n_welded` (vertices merged
    away by `weld` or `welded`; 0 otherwise), `n_repeated` (faces dropped because they repeat an
    earlier face's loop, from any vertex and in either direction: the same point set, so the
    shadows are unchanged; double-sided geometry stores each face twice).

    Raises `ValueError` for non-finite vertices, indices out of range, faces with fewer than three
    distinct vertices or zero area, and non-planar polygon faces (checked after welding).

    Example:
        ```python
        import numpy as np
        import jaxshadow as js

        box = js.Mesh.box([0, 0, 0], [1, 1, 1])
        soup = box.vertices[np.asarray(box.loops)]          # every face its own copy of its corners
        v, f = soup.reshape(-1, 3), np.arange(soup.shape[0] * soup.shape[1]).reshape(soup.shape[:2])
        print(js.Mesh(v, f).closed)                         # False: 24 corners, no shared edge
        m = js.Mesh(v, f, weld=0.0)
        print(m.closed, m.convex, m.n_welded)               # True True 16
        ```
    """

    n_welded: int = 0  # vertices merged away by `weld` or `welded`
    n_repeated: int = 0  # faces dropped as repeats of an earlier face (same loop up to start and direction)

    def __init__(self, vertices: Any, faces: Any, *, merge: bool = True, weld: float | None = None):
        v = np.asarray(vertices, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"Mesh: vertices must have shape (V, 3), got {v.shape}.")
        if not np.all(np.isfinite(v)):
            raise ValueError("Mesh: vertices must be finite.")
        table = _face_table(faces, v.shape[0])
        if weld is not None:
            v, table, self.n_welded = _welded(v, table, weld)
        self._prepare(v, table, merge, check=True)

    @classmethod
    def _of_checked_triangles(cls, vertices: np.ndarray, faces: np.ndarray) -> Mesh:
        """A `Mesh` of float64 `vertices (V, 3)` and triangles `faces (F, 3)` whose corners
        passed `geometry.triangles_pass` (finite, distinct corners, twice `_check_faces`' area
        limit: each such triangle passes it, and a triangle is planar), without checking them
        again: `weld_polygons`' meshes of triangle soups."""
        out = cls.__new__(cls)
        out._prepare(vertices, _face_table(faces, vertices.shape[0]), True, check=False)
        return out

    def _prepare(self, v: np.ndarray, table: Any, merge: bool, check: bool) -> None:
        size = float(np.max(np.ptp(v, axis=0))) if v.size else 0.0
        if not size > 0:
            raise ValueError("Mesh: all vertices coincide.")
        self.vertices = v
        self.n_input_faces = len(table)
        table, self.n_repeated = table.distinct()
        if check:
            _check_faces(table, v, size)
        self.closed, flip, index = _closed(table, v)
        if flip:
            table, index = table.reversed(), None
        if merge:
            table = _merge(table, v, size, index)
        self._faces = table
        self.convex = self.closed and _convex(table, v, size)
        self.edges = _solid_edges(table) if self.convex else None
        if self.edges is None:
            self.convex = False

    @functools.cached_property
    def loops(self) -> list[list[int]]:
        """Each face's vertex indices (`list` of `list[int]`), in the order of `polygons`."""
        return self._faces.loops()

    @functools.cached_property
    def polygons(self) -> list[Any]:
        """The faces the kernels see: `(k, 3)` vertex positions (m) per face."""
        out: list[Any] = [None] * len(self._faces)
        for idx, arr in self._faces.groups():
            for i, p in zip(idx.tolist(), self.vertices[arr], strict=True):
                out[i] = p
        return out

    def _padded_faces(self, k: int) -> np.ndarray:
        """`(F, k, 3)` face vertices (m) of a mesh with NumPy vertices, each face padded with its
        first vertex (`k` at least the largest face's vertex count)."""
        return self.vertices[self._faces.padded_to(k)]

    def with_vertices(self, vertices: Any) -> Mesh:
        """The same mesh (faces, merging, closedness, convexity) with new vertex positions,
        which may be traced (differentiable: e.g. a rigid motion or a scaling of the original
        vertices inside `jax.grad`). The structure is not re-derived: the caller keeps merged
        faces planar and convex solids convex (rigid motions and positive scalings do).

        **Arguments:** `vertices`: `(V, 3)`, the original vertex count.

        **Returns:** a `Mesh` whose `polygons` are gathered from `vertices`.
        """
        import copy

        import jax.numpy as jnp

        if tuple(np.shape(vertices)) != self.vertices.shape:
            raise ValueError(f"Mesh.with_vertices: expected shape {self.vertices.shape}, got {tuple(np.shape(vertices))}.")
        out = copy.copy(self)
        out.vertices = vertices
        out.polygons = [jnp.take(vertices, jnp.asarray(loop), axis=0) if not isinstance(vertices, np.ndarray)
                        else vertices[loop] for loop in self.loops]
        return out

    @classmethod
    def box(cls, lo: Any, hi: Any) -> Mesh:
        """An axis-aligned box from corner `lo (3,)` to corner `hi (3,)` (m), 12 triangles."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        x0, y0, z0 = lo
        x1, y1, z1 = hi
        v = [[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
             [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]]
        f = [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
             [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]]
        return cls(v, f)

    def __repr__(self) -> str:
        kind = "convex solid" if self.convex else ("closed" if self.closed else "open")
        welded = f", {self.n_welded} welded" if self.n_welded else ""
        return (f"Mesh({self.vertices.shape[0]} vertices{welded}, {self.n_input_faces} faces -> "
                f"{len(self._faces)} polygons, {kind})")

    def welded(self, tol: float = 0.0) -> Mesh:
        """The same surface with vertices at equal positions (`tol=0`) or within `tol` (m) merged
        (`Mesh(..., weld=tol)`): a mesh split at UV seams becomes one closed surface.
        **Returns:** a new `Mesh` (of this one's faces); `n_welded` counts the vertices merged
        away, here and before. Faces a tolerance collapses are dropped."""
        out = Mesh(self.vertices, self.loops, weld=tol)
        out.n_welded += self.n_welded
        return out

    def transformed(self, matrix: Any = None, *, rotation: Any = None, translation: Any = None,
                    scale: Any = 1.0) -> Mesh:
        """The mesh moved by an affine map $x \\mapsto A x + t$ (arguments as
        `jaxshadow.ReceiverMesh.transformed`); a mirroring map reverses the faces, so a closed
        mesh stays outward-oriented. **Returns:** a new `Mesh`."""
        from .welding import affine_parts

        a, t = affine_parts(matrix, rotation=rotation, translation=translation, scale=scale)
        flip = np.linalg.det(a) < 0
        return Mesh(self.vertices @ a.T + t, [lp[::-1] if flip else lp for lp in self.loops])


def _welded(v: np.ndarray, table: Any, tol: float) -> tuple[np.ndarray, Any, int]:
    """`Mesh`'s `weld`: the welded vertices, the face table on them (faces left with fewer than
    three distinct vertices dropped, repeated consecutive corners removed) and the number merged."""
    from .welding import weld_vertices

    index, first = weld_vertices(v, tol)
    merged = len(v) - len(first)
    if merged == 0:
        return v, table, 0
    loops = [[int(i) for i in index[loop]] for loop in table.loops()]
    loops = [[a for k, a in enumerate(lp) if a != lp[k - 1]] for lp in loops]
    kept = [lp for lp in loops if len(set(lp)) >= 3]
    if not kept:
        raise ValueError(f"Mesh: welding within {tol} m collapses every face.")
    return v[first], _face_table(kept, len(first)), merged


@dataclass(frozen=True, eq=False)
class OccluderTopology:
    """Static structure of `Scene.occluders` (hashable by content, so it can be a static field).

    - `face_solid (M,)`: the convex solid a face belongs to, or -1.
    - `face_closed (M,)`: for faces of closed, outward-oriented meshes the mesh's index (a receiver
      strictly outside that mesh's bounding box does not see its back faces block), else -1.
    - `solid_faces (S, 2)`: each solid's face range `[first, last)` (contiguous).
    - `solid_edge_off (S + 1,)`, `solid_edges (E, 4)`: each solid's edges as
      `(slot_a, slot_b, f_left, f_right)`, slots `f * Ko + i` into the padded face array, the edge
      running `slot_a -> slot_b` in `f_left`'s (outward, counter-clockwise) order.
    - `face_object (M,)`: which `Scene(occluders=[...])` entry each face came from.
    - `from_mesh (M,)`: 1 for faces of a `Mesh` entry.
    """

    face_solid: np.ndarray
    face_closed: np.ndarray
    solid_faces: np.ndarray
    solid_edge_off: np.ndarray
    solid_edges: np.ndarray
    face_object: np.ndarray
    from_mesh: np.ndarray

    def _key(self) -> tuple:
        return tuple(a.tobytes() for a in (self.face_solid, self.face_closed, self.solid_faces,
                                            self.solid_edge_off, self.solid_edges, self.face_object, self.from_mesh))

    def __hash__(self) -> int:
        return hash(self._key())

    def __eq__(self, other: object) -> bool:
        return isinstance(other, OccluderTopology) and self._key() == other._key()

    @property
    def n_solids(self) -> int:
        return int(self.solid_faces.shape[0])

    @staticmethod
    def independent(m: int) -> OccluderTopology:
        """`m` unrelated polygons (no meshes)."""
        return OccluderTopology(np.full(m, -1, np.int32), np.full(m, -1, np.int32), np.zeros((0, 2), np.int32),
                                np.zeros(1, np.int32), np.zeros((0, 4), np.int32), np.arange(m, dtype=np.int32),
                                np.zeros(m, np.int32))


def _occluder_blocks(items: list[Any], ko: int) -> tuple[list[tuple[bool, Any]], OccluderTopology]:
    """The entries in order as (is a mesh, entry), and their topology (see `build_occluders`)."""
    blocks: list[tuple[bool, Any]] = []
    counts: list[int] = []
    solid: list[int] = []
    closed: list[int] = []
    solid_faces: list[tuple[int, int]] = []
    edges: list[np.ndarray] = []
    edge_off = [0]
    n_closed = 0
    f0 = 0
    for item in items:
        if isinstance(item, Mesh):
            nf = len(item._faces)
            blocks.append((True, item))
            solid.append(len(solid_faces) if item.convex else -1)
            cid = -1
            if item.closed:
                cid, n_closed = n_closed, n_closed + 1
            closed.append(cid)
            if item.convex:
                solid_faces.append((f0, f0 + nf))
                e = np.asarray(item.edges or [], dtype=np.int64).reshape(-1, 6)
                fl, fr = f0 + e[:, 0], f0 + e[:, 3]
                edges.append(np.stack([fl * ko + e[:, 1], fl * ko + e[:, 2], fl, fr], axis=1))
                edge_off.append(edge_off[-1] + len(e))
        else:
            nf = 1
            blocks.append((False, item))
            solid.append(-1)
            closed.append(-1)
        counts.append(nf)
        f0 += nf
    rep = np.asarray(counts, dtype=np.intp)
    topo = OccluderTopology(
        np.repeat(np.asarray(solid, np.int32), rep), np.repeat(np.asarray(closed, np.int32), rep),
        np.asarray(solid_faces, np.int32).reshape(-1, 2), np.asarray(edge_off, np.int32),
        (np.concatenate(edges) if edges else np.zeros((0, 4), np.int64)).astype(np.int32).reshape(-1, 4),
        np.repeat(np.arange(len(items), dtype=np.int32), rep),
        np.repeat(np.asarray([1 if m else 0 for m, _ in blocks], np.int32), rep))
    return blocks, topo


def build_occluders(items: list[Any], ko: int) -> tuple[list[Any], OccluderTopology]:
    """Polygons (in order) and their topology from `Scene(occluders=[...])` entries: plain
    `(k, 3)` polygons and `Mesh` objects (their polygons kept contiguous). `ko` is the padded
    vertex count the caller will use (slots of the solid edges refer to it). A polygon is a
    NumPy array, or a JAX array (a tracer when the scene is built under `jax.grad`)."""
    blocks, topo = _occluder_blocks(items, ko)
    polys: list[Any] = []
    for is_mesh, item in blocks:
        if is_mesh:
            polys.extend(item.polygons)
        else:
            polys.append(item)
    return polys, topo


def stack_occluders(items: list[Any], ko: int) -> tuple[Any, OccluderTopology]:
    """`build_occluders` with the polygons padded to `ko` vertices (first-vertex padding) and
    stacked: `(M, ko, 3)`. Meshes with NumPy vertices are gathered in one step each; traced
    entries go through `pad_polygons_jax`."""
    import jax.numpy as jnp

    from .geometry import is_concrete, pad_polygon, pad_polygons_jax

    blocks, topo = _occluder_blocks(items, ko)
    if not all(isinstance(item.vertices, np.ndarray) if is_mesh else (is_concrete(item) and not isinstance(item, jnp.ndarray))
               for is_mesh, item in blocks):
        polys, _ = build_occluders(items, ko)
        return pad_polygons_jax(polys, ko), topo
    parts = [item._padded_faces(ko) if is_mesh else pad_polygon(np.asarray(item), ko)[None] for is_mesh, item in blocks]
    return jnp.asarray(np.concatenate(parts)), topo


def max_face_vertices(items: list[Any]) -> int:
    k = 3
    for item in items:
        if isinstance(item, Mesh):
            k = max(k, item._faces.pad.shape[1])
        else:
            k = max(k, int(np.asarray(item).shape[0]))
    return k


def mesh_dicts(faces: np.ndarray, topology: OccluderTopology) -> list[Any]:
    """The `Scene(occluders=[...])` entries back from padded faces and their topology: `(k, 3)`
    lists for plain polygons, `{"mesh": {"vertices", "faces"}}` for meshes (vertices recovered by
    exact equality of the faces' coordinates), in entry order (the JSON scene format)."""
    out: list[Any] = []
    objs = topology.face_object
    f = 0
    m = faces.shape[0]
    while f < m:
        g = f
        while g < m and objs[g] == objs[f]:
            g += 1
        polys = [strip_padding(faces[i]) for i in range(f, g)]
        if topology.from_mesh[f]:
            verts: list[tuple] = []
            index: dict[tuple, int] = {}
            loops = []
            for poly in polys:
                loop = []
                for v in poly:
                    key = tuple(float(x) for x in v)
                    if key not in index:
                        index[key] = len(verts)
                        verts.append(key)
                    loop.append(index[key])
                loops.append(loop)
            out.append({"mesh": {"vertices": [list(v) for v in verts], "faces": loops}})
        else:
            out.extend(p.tolist() for p in polys)
        f = g
    return out


def weld_polygons(items: list[Any], stacked: np.ndarray | None = None, triangles_checked: bool = False) -> list[Any]:
    """`Scene(occluders=[...])` entries with triangle soups turned into meshes: the plain polygons
    (concrete `(k, 3)` arrays) are welded by exactly equal vertex coordinates and split into
    connected components (polygons sharing an edge); each component of two or more polygons
    becomes one `Mesh` (coplanar merging, closed and convex detection), in place of its first
    polygon. It blocks exactly what its polygons block (the same point set), and the shadow
    engine then treats it as the same `Mesh` given directly would be treated (a convex solid's
    cone, interior edges left out). `Mesh` entries, lone polygons and components a `Mesh`
    refuses (e.g. faces that reuse a vertex) are kept as they are. `stacked`: the items as one
    `(m, k, 3)` array when they are its rows (read at once instead of polygon by polygon).
    `triangles_checked`: every plain item is a triangle that passed `geometry.triangles_pass`
    (its meshes are not checked again)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from .welding import unique_rows

    idx = [i for i, x in enumerate(items) if not isinstance(x, Mesh)]
    if len(idx) < 2:
        return items
    if stacked is not None and len(idx) == len(items) == len(stacked):
        n_polys, k = stacked.shape[0], stacked.shape[1]
        sizes = np.full(n_polys, k, dtype=np.intp)
        corners = np.asarray(stacked, dtype=np.float64).reshape(-1, 3)
    else:
        polys = [np.asarray(items[i], dtype=np.float64) for i in idx]
        n_polys = len(polys)
        sizes = np.fromiter((len(q) for q in polys), dtype=np.intp, count=n_polys)
        corners = np.concatenate(polys)
    start = np.concatenate([[0], np.cumsum(sizes)])
    verts, _, inv = unique_rows(corners)
    # Undirected edges (a, b) of every polygon, and the polygons that share one.
    a = inv
    nxt = np.arange(len(inv)) + 1
    nxt[start[1:] - 1] = start[:-1]
    b = inv[nxt]
    face = np.repeat(np.arange(n_polys), sizes)
    key = np.minimum(a, b) * len(verts) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks, fs = key[order], face[order]
    same = ks[1:] == ks[:-1]
    g = coo_matrix((np.ones(int(same.sum())), (fs[:-1][same], fs[1:][same])), shape=(n_polys, n_polys))
    n_comp, label = connected_components(g, directed=False)
    if n_comp == n_polys:
        return items
    # Each component's polygons in ascending order (a stable sort by component).
    by_comp = np.argsort(label, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(np.bincount(label, minlength=n_comp))]).tolist()
    k = int(sizes[0])
    table = inv.reshape(-1, k) if bool(np.all(sizes == k)) else None  # equal vertex counts: one index table
    replace: dict[int, Any] = {}
    drop: set[int] = set()
    for c in range(n_comp):
        if bounds[c + 1] - bounds[c] < 2:
            continue
        faces = by_comp[bounds[c]:bounds[c + 1]]
        loops: Any = table[faces] if table is not None else [inv[start[f]:start[f + 1]] for f in faces.tolist()]
        if n_comp == 1:  # one component of every polygon: every welded vertex is used, in order
            mverts, mloops = verts, loops if table is not None else list(loops)
        else:
            used = np.unique(loops if table is not None else np.concatenate(loops))
            local = np.full(len(verts), -1)
            local[used] = np.arange(len(used))
            mverts, mloops = verts[used], local[loops] if table is not None else [local[loop] for loop in loops]
        try:
            mesh = (Mesh._of_checked_triangles(mverts, mloops) if triangles_checked and table is not None and k == 3
                    else Mesh(mverts, mloops))
        except ValueError:
            continue
        first = faces.tolist()
        replace[idx[first[0]]] = mesh
        drop.update(idx[f] for f in first[1:])
    return [replace.get(i, x) for i, x in enumerate(items) if i not in drop]
