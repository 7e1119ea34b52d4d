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

from dataclasses import dataclass
from typing import Any

import numpy as np

# Relative tolerances (of the mesh's size) for coplanarity and convexity.
COPLANAR_RTOL = 1e-9
MAX_MERGED_VERTICES = 8


def _newell(v: np.ndarray) -> np.ndarray:
    w = np.concatenate([v[1:], v[:1]])
    return np.array([np.sum(v[:, 1] * w[:, 2] - v[:, 2] * w[:, 1]), np.sum(v[:, 2] * w[:, 0] - v[:, 0] * w[:, 2]),
                     np.sum(v[:, 0] * w[:, 1] - v[:, 1] * w[:, 0])])


def _cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


class Mesh:
    """A mesh occluder (m): vertices and faces, prepared once for the shadow engine.

    **Arguments:**

    - `vertices`: `(V, 3)` vertex positions (m).
    - `faces`: `(F, 3)` triangle vertex indices, or a list of index lists (convex planar polygons),
      counter-clockwise seen from outside for closed meshes (a closed mesh with inward faces is
      flipped; an open mesh may have any orientation: it blocks light from both sides).
    - `merge`: merge coplanar neighbouring faces into convex polygons (default True).

    **Attributes:** `polygons` (list of `(k, 3)` arrays, the faces the kernels see), `closed`,
    `convex`, `n_input_faces`.

    Raises `ValueError` for non-finite vertices, indices out of range, faces with fewer than three
    distinct vertices or zero area, and non-planar polygon faces.
    """

    def __init__(self, vertices: Any, faces: Any, *, merge: bool = True):
        v = np.asarray(vertices, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"Mesh: vertices must have shape (V, 3), got {v.shape}.")
        if not np.all(np.isfinite(v)):
            raise ValueError("Mesh: vertices must be finite.")
        loops = _face_loops(faces, v.shape[0])
        size = float(np.max(np.ptp(v, axis=0))) if v.size else 0.0
        if not size > 0:
            raise ValueError("Mesh: all vertices coincide.")
        self.vertices = v
        self.n_input_faces = len(loops)
        for i, loop in enumerate(loops):
            pts = v[loop]
            area = np.linalg.norm(_newell(pts))
            if not area > COPLANAR_RTOL * size * size:
                raise ValueError(f"Mesh: face {i} has zero area.")
            nrm = _newell(pts) / area
            if np.max(np.abs((pts - pts[0]) @ nrm)) > 1e-6 * size:
                raise ValueError(f"Mesh: face {i} is not planar.")
        self.closed, flip = _closed(loops, v)
        if flip:
            loops = [loop[::-1] for loop in loops]
        self.loops = _merge(loops, v, size) if merge else [list(x) for x in loops]
        self.polygons = [v[loop] for loop in self.loops]
        self.convex = self.closed and _convex(self.loops, v, size)
        self.edges = _solid_edges(self.loops) if self.convex else None
        if self.edges is None:
            self.convex = False

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
        return (f"Mesh({self.vertices.shape[0]} vertices, {self.n_input_faces} faces -> "
                f"{len(self.polygons)} polygons, {kind})")


def _face_loops(faces: Any, n_vertices: int) -> list[list[int]]:
    if isinstance(faces, np.ndarray) and faces.ndim == 2:
        loops = [list(map(int, f)) for f in faces]
    else:
        loops = [list(map(int, f)) for f in faces]
    out = []
    for i, loop in enumerate(loops):
        if any(j < 0 or j >= n_vertices for j in loop):
            raise ValueError(f"Mesh: face {i} has a vertex index out of range [0, {n_vertices}).")
        dedup = [a for k, a in enumerate(loop) if a != loop[k - 1]]
        if len(set(dedup)) < 3 or len(set(dedup)) != len(dedup):
            raise ValueError(f"Mesh: face {i} needs at least three distinct vertices, got {loop}.")
        out.append(dedup)
    return out


def _directed_edges(loops: list[list[int]]):
    for fi, loop in enumerate(loops):
        for k in range(len(loop)):
            yield fi, loop[k], loop[(k + 1) % len(loop)]


def _closed(loops: list[list[int]], v: np.ndarray) -> tuple[bool, bool]:
    """(closed, flip): every edge used once in each direction; flip when the volume is negative."""
    count: dict[tuple[int, int], int] = {}
    for _, a, b in _directed_edges(loops):
        count[(a, b)] = count.get((a, b), 0) + 1
    closed = all(c == 1 and count.get((b, a), 0) == 1 for (a, b), c in count.items())
    if not closed:
        return False, False
    c = v.mean(axis=0)
    vol = sum(float(np.dot(_newell(v[loop] - c), v[loop[0]] - c)) for loop in loops)
    return True, vol < 0


def _convex(loops: list[list[int]], v: np.ndarray, size: float) -> bool:
    for loop in loops:
        pts = v[loop]
        nrm = _newell(pts)
        nrm = nrm / np.linalg.norm(nrm)
        if np.max((v - pts[0]) @ nrm) > 1e-9 * size:
            return False
    return True


def _merge(loops: list[list[int]], v: np.ndarray, size: float) -> list[list[int]]:
    """Merge coplanar faces sharing an edge while the union stays a convex polygon (greedy, one
    pass over a queue of shared edges; a merged face's edges are queued again)."""
    loops = [list(x) for x in loops]
    normals = []
    for loop in loops:
        n = _newell(v[loop])
        normals.append(n / np.linalg.norm(n))
    alive = [True] * len(loops)
    owner: dict[tuple[int, int], int] = {}
    for fi, a, b in _directed_edges(loops):
        owner[(a, b)] = fi
    queue = [e for e in owner if (e[1], e[0]) in owner and e[0] < e[1]]
    while queue:
        a, b = queue.pop()
        fi, fj = owner.get((a, b)), owner.get((b, a))
        if fi is None or fj is None or fi == fj or not (alive[fi] and alive[fj]):
            continue
        ni, nj = normals[fi], normals[fj]
        if np.dot(ni, nj) < 1 - 1e-12 or np.max(np.abs((v[loops[fj]] - v[loops[fi][0]]) @ ni)) > COPLANAR_RTOL * size:
            continue
        m = _union(loops[fi], loops[fj], a, b, v, ni, size)
        if m is None:
            continue
        for k in range(len(loops[fj])):
            owner.pop((loops[fj][k], loops[fj][(k + 1) % len(loops[fj])]), None)
        for k in range(len(loops[fi])):
            owner.pop((loops[fi][k], loops[fi][(k + 1) % len(loops[fi])]), None)
        loops[fi] = m
        alive[fj] = False
        for k in range(len(m)):
            e = (m[k], m[(k + 1) % len(m)])
            owner[e] = fi
            if (e[1], e[0]) in owner:
                queue.append(e)
    return [lp for lp, ok in zip(loops, alive, strict=True) if ok]


def _union(la: list[int], lb: list[int], a: int, b: int, v: np.ndarray, nrm: np.ndarray, size: float) -> list[int] | None:
    """`la` (containing a -> b) and `lb` (containing b -> a) glued along that edge, if convex."""
    ia = la.index(a)
    ra = la[ia + 1:] + la[:ia + 1]  # starts after a, ends at a; la's a -> b edge is last-to-first
    # ra runs b ... a (b first). Glue lb from a to b (excluding the shared ends).
    ib = lb.index(b)
    rb = lb[ib + 1:] + lb[:ib + 1]  # starts after b, so runs a ... b
    merged = ra + rb[1:-1]
    # Drop vertices where the boundary goes straight (the merge removes the shared edge only).
    out = merged
    done = False
    while not done and len(out) > 3:
        done = True
        for k in range(len(out)):
            p0, p1, p2 = v[out[k - 1]], v[out[k]], v[out[(k + 1) % len(out)]]
            turn = np.dot(_cross3(p1 - p0, p2 - p1), nrm)
            if abs(turn) <= 1e-12 * np.linalg.norm(p1 - p0) * np.linalg.norm(p2 - p1):
                out = out[:k] + out[k + 1:]
                done = False
                break
    if len(out) > MAX_MERGED_VERTICES or len(set(out)) != len(out):
        return None
    pts = v[out]
    e = np.concatenate([pts[1:], pts[:1]]) - pts
    e2 = np.concatenate([e[1:], e[:1]])
    turn = (e[:, 1] * e2[:, 2] - e[:, 2] * e2[:, 1]) * nrm[0] + (e[:, 2] * e2[:, 0] - e[:, 0] * e2[:, 2]) * nrm[1] + (
        e[:, 0] * e2[:, 1] - e[:, 1] * e2[:, 0]) * nrm[2]
    if np.any(turn <= 0):
        return None
    return out


def _solid_edges(loops: list[list[int]]) -> list[tuple[int, int, int, int, int, int]] | None:
    """Per undirected edge of a closed polygon mesh: (f_left, k_a, k_b, f_right) with the edge
    running loop[f_left][k_a] -> loop[f_left][k_b] in f_left; None when some edge does not have
    exactly one opposite (a merge left a vertex on an edge of a neighbour)."""
    where: dict[tuple[int, int], tuple[int, int, int]] = {}
    for fi, loop in enumerate(loops):
        for k in range(len(loop)):
            where[(loop[k], loop[(k + 1) % len(loop)])] = (fi, k, (k + 1) % len(loop))
    out = []
    for (a, b), (fi, ka, kb) in where.items():
        opp = where.get((b, a))
        if opp is None:
            return None
        if a < b:
            out.append((fi, ka, kb, opp[0], a, b))
    return out


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


def build_occluders(items: list[Any], ko: int) -> tuple[list[Any], OccluderTopology]:
    """Polygons (in order) and their topology from `Scene(occluders=[...])` entries: plain
    `(k, 3)` polygons and `Mesh` objects (their polygons kept contiguous). `ko` is the padded
    vertex count the caller will use (slots of the solid edges refer to it). A polygon is a
    NumPy array, or a JAX array (a tracer when the scene is built under `jax.grad`)."""
    polys: list[Any] = []
    face_solid: list[int] = []
    face_closed: list[int] = []
    face_object: list[int] = []
    from_mesh: list[int] = []
    solid_faces: list[tuple[int, int]] = []
    edges: list[tuple[int, int, int, int]] = []
    edge_off = [0]
    n_closed = 0
    for obj_i, item in enumerate(items):
        if isinstance(item, Mesh):
            f0 = len(polys)
            sid = len(solid_faces) if item.convex else -1
            cid = -1
            if item.closed:
                cid, n_closed = n_closed, n_closed + 1
            for poly in item.polygons:
                polys.append(poly)
                face_solid.append(sid)
                face_closed.append(cid)
                face_object.append(obj_i)
                from_mesh.append(1)
            if item.convex:
                solid_faces.append((f0, len(polys)))
                for fl, ka, kb, fr, _, _ in item.edges or []:
                    edges.append(((f0 + fl) * ko + ka, (f0 + fl) * ko + kb, f0 + fl, f0 + fr))
                edge_off.append(len(edges))
        else:
            polys.append(item)
            face_solid.append(-1)
            face_closed.append(-1)
            face_object.append(obj_i)
            from_mesh.append(0)
    topo = OccluderTopology(
        np.asarray(face_solid, np.int32), np.asarray(face_closed, np.int32),
        np.asarray(solid_faces, np.int32).reshape(-1, 2), np.asarray(edge_off, np.int32),
        np.asarray(edges, np.int32).reshape(-1, 4), np.asarray(face_object, np.int32),
        np.asarray(from_mesh, np.int32))
    return polys, topo


def max_face_vertices(items: list[Any]) -> int:
    k = 3
    for item in items:
        if isinstance(item, Mesh):
            k = max([k] + [len(loop) for loop in item.loops])
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
        polys = [_strip_padding(faces[i]) for i in range(f, g)]
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


def _strip_padding(poly: np.ndarray) -> np.ndarray:
    k = poly.shape[0]
    while k > 3 and np.array_equal(poly[k - 1], poly[0]):
        k -= 1
    return poly[:k]


def weld_polygons(items: list[Any]) -> list[Any]:
    """`Scene(occluders=[...])` entries with triangle soups turned into meshes: the plain polygons
    (concrete `(k, 3)` arrays) are welded by exactly equal vertex coordinates and split into
    connected components (polygons sharing an edge); each component of two or more polygons
    becomes one `Mesh` (coplanar merging, closed and convex detection), in place of its first
    polygon. It blocks exactly what its polygons block (the same point set), and the shadow
    engine then treats it as the same `Mesh` given directly would be treated (a convex solid's
    cone, interior edges left out). `Mesh` entries, lone polygons and components a `Mesh`
    refuses (e.g. faces that reuse a vertex) are kept as they are."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    idx = [i for i, x in enumerate(items) if not isinstance(x, Mesh)]
    if len(idx) < 2:
        return items
    polys = [np.asarray(items[i], dtype=np.float64) for i in idx]
    sizes = np.array([len(q) for q in polys])
    start = np.concatenate([[0], np.cumsum(sizes)])
    verts, inv = np.unique(np.concatenate(polys), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    # Undirected edges (a, b) of every polygon, and the polygons that share one.
    a = inv
    nxt = np.arange(len(inv)) + 1
    nxt[start[1:] - 1] = start[:-1]
    b = inv[nxt]
    face = np.repeat(np.arange(len(polys)), sizes)
    key = np.minimum(a, b) * len(verts) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks, fs = key[order], face[order]
    same = ks[1:] == ks[:-1]
    g = coo_matrix((np.ones(int(same.sum())), (fs[:-1][same], fs[1:][same])), shape=(len(polys), len(polys)))
    n_comp, label = connected_components(g, directed=False)
    if n_comp == len(polys):
        return items
    members: dict[int, list[int]] = {}
    for f, c in enumerate(label):
        members.setdefault(int(c), []).append(f)
    replace: dict[int, Any] = {}
    drop: set[int] = set()
    for faces in members.values():
        if len(faces) < 2:
            continue
        loops = [inv[start[f]:start[f + 1]] for f in faces]
        used = np.unique(np.concatenate(loops))
        local = np.full(len(verts), -1)
        local[used] = np.arange(len(used))
        try:
            mesh = Mesh(verts[used], [local[loop] for loop in loops])
        except ValueError:
            continue
        replace[idx[faces[0]]] = mesh
        drop.update(idx[f] for f in faces[1:])
    return [replace.get(i, x) for i, x in enumerate(items) if i not in drop]
