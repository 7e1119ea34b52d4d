r"""Shadow discontinuity lines on a planar receiver, for the illumination meshes (`_illumination`).

The irradiance from a polygon light over a receiver is smooth except where the visible part of
the light changes shape: where a light vertex lines up with an occluder edge (a *VE* event) or an
occluder vertex with a light edge (an *EV* event). Each event is a plane (Campbell & Fussell's
extremal planes, §3.1.2; Chrysanthou & Slater's EV critical surfaces, §1) and meets the receiver
in a straight segment: the central projection of the occluder edge from the light vertex, or of
the light edge through the occluder vertex. Across such a line the irradiance has a kink (its
gradient jumps), which linear interpolation resolves only if the line is a mesh edge.

Most candidate planes are not events anywhere on the receiver, and this module keeps only those
that can be:

- **Local support.** At an event the plane touches the occluder without cutting it: every
  vertex of the faces around the occluder's edge (or vertex) lies on one side (for a convex solid
  this is Campbell's extremal-plane condition; for a single polygon it always holds).
- **Between light and receiver.** The occluder part strictly between the receiver plane and the
  light vertex (or the part of the light edge above the occluder vertex) is projected; the
  segment is clipped to the receiver polygon.
- **Visibility along the line.** Seen from a receiver point on the line, the event is real only
  if the ray from the point through the occluder feature to the light is not blocked by another
  occluder (EEE events and events hidden behind other objects are not inserted; the refinement
  resolves whatever is left). `ray_visible` is that test, one ray per sample, nudged to the side
  of the plane the occluder does not occupy so that the occluder's own edge does not block it.

Near the foot of an occluder edge standing on the receiver one more kind of line matters
(`corner_segments`): the planes through that edge and another occluder edge in a plane with it,
where the gradient jump grows without bound towards the foot. The mesher inserts them over their
whole length (where both objects can shadow): a bounded length left, beyond it, kinks in
regions of faint light that an element's seven check points can miss.

Point lights contribute their hard-shadow boundaries (the VE lines from the point); linear lights
their two endpoints as vertices and the segment as an edge. Directional lights add no lines.
Everything here is NumPy on concrete values.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._core.geometry import strip_padding
from .._scene.model import LinearLight, PointLight, PolygonLight, Scene

SUPPORT_RTOL = 1e-9  # relative tolerance of the side tests (of the occluder's size squared)
NUDGE_RTOL = 1e-7  # visibility rays start this far (of the receiver's size) on the free side
CONTACT_GAP = 1e-6  # corner lines stop this far (of the receiver's size) from another object's foot


@dataclass(frozen=True)
class Frame:
    """An orthonormal frame of the receiver plane: `origin`, in-plane axes `u`, `w` and the
    receiver's `normal` (`u x w = normal`); 2-D coordinates are along `u` and `w` (m)."""

    origin: np.ndarray
    u: np.ndarray
    w: np.ndarray
    normal: np.ndarray

    def to3d(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, np.float64)
        return self.origin + xy[..., :1] * self.u + xy[..., 1:2] * self.w

    def to2d(self, x: np.ndarray) -> np.ndarray:
        d = np.asarray(x, np.float64) - self.origin
        return np.stack([d @ self.u, d @ self.w], axis=-1)

    def height(self, x: np.ndarray) -> np.ndarray:
        """Signed distance above the receiver plane (m)."""
        return np.asarray((np.asarray(x, np.float64) - self.origin) @ self.normal)


def receiver_frame(receiver: np.ndarray) -> Frame:
    """The frame of a planar convex receiver polygon `(k, 3)` (its normal by the right-hand rule)."""
    r = np.asarray(receiver, np.float64)
    nrm = np.sum(np.cross(r, np.roll(r, -1, axis=0)), axis=0)
    nrm = nrm / np.linalg.norm(nrm)
    u = r[1] - r[0]
    u = u - (u @ nrm) * nrm
    u = u / np.linalg.norm(u)
    return Frame(r[0].copy(), u, np.cross(nrm, u), nrm)


@dataclass
class Occluders:
    """The scene's occluder faces with the adjacency the support test needs.

    `faces (M, K, 3)` padded, `face_normal (M, 3)` (unit), `face_object (M,)`; per undirected edge
    of an object `edge (E, 2, 3)`, `edge_adj (E, A, 3)` the vertices of its faces (padded with the
    edge's first end), `edge_object (E,)`; per vertex `vert (W, 3)`, `vert_adj (W, B, 3)`,
    `vert_object (W,)`. `objects` keeps each object's part (before padding), keyed by its faces'
    bytes, for `occluder_features(reuse=...)`."""

    faces: np.ndarray
    face_normal: np.ndarray
    face_object: np.ndarray
    edge: np.ndarray
    edge_adj: np.ndarray
    edge_object: np.ndarray
    vert: np.ndarray
    vert_adj: np.ndarray
    vert_object: np.ndarray
    objects: dict[bytes, tuple] = field(default_factory=dict, repr=False)


def _pad_rows(rows: list[list[np.ndarray]], fill: list[np.ndarray]) -> np.ndarray:
    width = max((len(r) for r in rows), default=1)
    out = np.zeros((len(rows), max(width, 1), 3))
    for i, r in enumerate(rows):
        out[i, : len(r)] = r
        out[i, len(r):] = fill[i]
    return out


def _object_features(faces: np.ndarray) -> tuple:
    """One object's face normals `(F, 3)`, edges (with their faces' vertices) and vertices (with
    theirs), from its faces `(F, K, 3)` (vertices matched by exact equality)."""
    loops = [strip_padding(f) for f in faces]
    normals = np.stack([np.sum(np.cross(p, np.roll(p, -1, axis=0)), axis=0) for p in loops])
    index: dict[tuple, int] = {}
    coords: list[np.ndarray] = []
    face_ids: list[list[int]] = []
    for loop in loops:
        ids = []
        for x in loop:
            key = tuple(x.tolist())
            if key not in index:
                index[key] = len(coords)
                coords.append(x)
            ids.append(index[key])
        face_ids.append(ids)
    edge_faces: dict[tuple[int, int], list[int]] = {}
    vert_faces: dict[int, list[int]] = {}
    for fi, ids in enumerate(face_ids):
        for k, a in enumerate(ids):
            b = ids[(k + 1) % len(ids)]
            edge_faces.setdefault((min(a, b), max(a, b)), []).append(fi)
            vert_faces.setdefault(a, []).append(fi)
    edges = [np.stack([coords[a], coords[b]]) for a, b in edge_faces]
    eadj = [[coords[i] for f in fs for i in face_ids[f]] for fs in edge_faces.values()]
    verts = [coords[a] for a in vert_faces]
    vadj = [[coords[i] for f in fs for i in face_ids[f]] for fs in vert_faces.values()]
    return normals, edges, eadj, verts, vadj


def occluder_features(scene: Scene, reuse: Occluders | None = None) -> Occluders:
    """Edges and vertices of each occluder object (a `Mesh` entry or a polygon) with the faces
    around them, from `scene.occluders` and its topology (vertices matched by exact equality).
    `reuse`: the features of an earlier scene, whose objects with the same faces are taken over
    (an update moves a few objects; the others' features are the same)."""
    faces = np.asarray(scene.occluders, np.float64)
    m = faces.shape[0]
    topo = scene.occluder_topology
    obj_of = np.arange(m) if topo is None else np.asarray(topo.face_object)
    old = reuse.objects if reuse is not None else {}
    objects: dict[bytes, tuple] = {}
    normals, edges, eadj, eobj, verts, vadj, vobj = [], [], [], [], [], [], []
    cut = np.concatenate([[0], np.nonzero(obj_of[1:] != obj_of[:-1])[0] + 1, [m]])
    for start, stop in zip(cut[:-1].tolist(), cut[1:].tolist(), strict=True):
        key = faces[start:stop].tobytes() + bytes(str(faces.shape[1:]), 'ascii')
        part = old.get(key) or objects.get(key) or _object_features(faces[start:stop])
        objects[key] = part
        nrm, e, ea, v, va = part
        normals.append(nrm)
        edges.extend(e)
        eadj.extend(ea)
        eobj.extend([obj_of[start]] * len(e))
        verts.extend(v)
        vadj.extend(va)
        vobj.extend([obj_of[start]] * len(v))
    normal = np.concatenate(normals)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    edge = np.stack(edges)
    vert = np.stack(verts)
    return Occluders(
        faces, normal, np.asarray(obj_of), edge, _pad_rows(eadj, list(edge[:, 0])), np.asarray(eobj),
        vert, _pad_rows(vadj, verts), np.asarray(vobj), objects,
    )


@dataclass
class LightFeatures:
    """The vertices `(kv, 3)` and edges `(ke, 2, 3)` of the lights that make lines."""

    vertices: np.ndarray
    edges: np.ndarray


def light_features(scene: Scene) -> LightFeatures:
    vs: list[np.ndarray] = []
    es: list[np.ndarray] = []
    for light in scene.lights:
        if isinstance(light, PolygonLight):
            v = np.asarray(light.vertices, np.float64)
            vs.extend(v)
            es.extend(np.stack([v, np.roll(v, -1, axis=0)], axis=1))
        elif isinstance(light, LinearLight):
            a, b = np.asarray(light.start, np.float64), np.asarray(light.end, np.float64)
            vs.extend([a, b])
            es.append(np.stack([a, b]))
        elif isinstance(light, PointLight):
            vs.append(np.asarray(light.position, np.float64))
    return LightFeatures(np.asarray(vs).reshape(-1, 3), np.asarray(es).reshape(-1, 2, 3))


@dataclass
class Segments:
    """Candidate discontinuity segments on the receiver (2-D): `a`, `b (S, 2)`; `free (S, 2)` the
    in-plane unit normal pointing to the side the occluder does not occupy; `target (S, 3)` the
    light vertex (`through = False`) or the occluder vertex the ray passes (`through = True`, EV
    events: the ray continues to the light edge `ledge (S, 2, 3)`); `obj (S,)` the occluder object;
    `kept (S,)` the lines inserted without the visibility test (`corner_segments`)."""

    a: np.ndarray
    b: np.ndarray
    free: np.ndarray
    target: np.ndarray
    through: np.ndarray
    ledge: np.ndarray
    obj: np.ndarray
    kept: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    def __post_init__(self) -> None:
        if self.kept.shape[0] != self.a.shape[0]:
            self.kept = np.zeros(self.a.shape[0], bool)

    def __len__(self) -> int:
        return int(self.a.shape[0])

    def take(self, keep: np.ndarray) -> Segments:
        return Segments(*(getattr(self, f)[keep] for f in _SEGMENT_FIELDS))

    @staticmethod
    def concat(parts: list[Segments]) -> Segments:
        return Segments(*(np.concatenate([getattr(p, f) for p in parts]) for f in _SEGMENT_FIELDS))


_SEGMENT_FIELDS = ("a", "b", "free", "target", "through", "ledge", "obj", "kept")


def _supports(m: np.ndarray, origin: np.ndarray, adj: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """(supporting, side): the planes through `origin (n, 3)` with normals `m (n, 3)` leave all
    `adj (n, A, 3)` on one side; `side` is +1 or -1, where they lie."""
    s = np.einsum("nak,nk->na", adj - origin[:, None, :], m)
    tol = SUPPORT_RTOL * size * size * np.linalg.norm(m, axis=1, keepdims=True)
    pos = np.all(s >= -tol, axis=1)
    neg = np.all(s <= tol, axis=1)
    side = np.where(np.sum(np.where(np.abs(s) > tol, s, 0.0), axis=1) >= 0, 1.0, -1.0)
    return (pos | neg) & (np.linalg.norm(m, axis=1) > 0), side


def _clip_to_polygon(a: np.ndarray, b: np.ndarray, poly: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Liang-Barsky clip of 2-D segments `a -> b (n, 2)` to a convex counter-clockwise polygon:
    `(a', b', nonempty)`."""
    t0 = np.zeros(a.shape[0])
    t1 = np.ones(a.shape[0])
    d = b - a
    for k in range(poly.shape[0]):
        p, q = poly[k], poly[(k + 1) % poly.shape[0]]
        e = q - p
        # inside: cross(e, x - p) >= 0
        f0 = e[0] * (a[:, 1] - p[1]) - e[1] * (a[:, 0] - p[0])
        df = e[0] * d[:, 1] - e[1] * d[:, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -f0 / df
        enter = df > 0
        leave = df < 0
        t0 = np.where(enter, np.maximum(t0, t), t0)
        t1 = np.where(leave, np.minimum(t1, t), t1)
        t1 = np.where((df == 0) & (f0 < 0), -1.0, t1)
    ok = t1 > t0
    return a + t0[:, None] * d, a + t1[:, None] * d, ok


def _cut_by_polygons(a: np.ndarray, b: np.ndarray, polys: list[np.ndarray], boxes: np.ndarray,
                     grow: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pieces of 2-D segments `a -> b (n, 2)` outside the convex counter-clockwise polygons
    `polys` (bounding boxes `boxes (m, 4)`) grown by `grow` (each edge moved out by it), but
    for the polygons a segment starts in (its own object's foot): `(a', b', line (k,))`, the
    piece's segment index."""
    n = a.shape[0]
    d = b - a
    lo, hi = np.minimum(a, b) - grow, np.maximum(a, b) + grow
    if boxes.shape[0] and n:
        li, pj = np.nonzero((boxes[None, :, 0] <= hi[:, None, 0]) & (boxes[None, :, 2] >= lo[:, None, 0])
                            & (boxes[None, :, 1] <= hi[:, None, 1]) & (boxes[None, :, 3] >= lo[:, None, 1]))
    else:
        li = pj = np.zeros(0, int)
    if li.size:
        k = max(q.shape[0] for q in polys)
        pad = np.stack([np.concatenate([q, np.repeat(q[-1:], k - q.shape[0], axis=0)]) for q in polys])  # (m, k, 2)
        q = pad[pj]
        e = np.roll(q, -1, axis=1) - q  # (P, k, 2); a repeated vertex gives a null edge: no constraint
        f0 = (e[..., 0] * (a[li, None, 1] - q[..., 1]) - e[..., 1] * (a[li, None, 0] - q[..., 0])
              + grow * np.linalg.norm(e, axis=2))
        df = e[..., 0] * d[li, None, 1] - e[..., 1] * d[li, None, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -f0 / df
        t0 = np.max(np.where(df > 0, t, -np.inf), axis=1)
        t1 = np.min(np.where(df < 0, t, np.inf), axis=1)
        # Missed, started in (its own foot), or entered past the end: no cut.
        cut = ~np.any((df == 0) & (f0 < 0), axis=1) & (t1 > t0) & (t0 > 0.0) & (t0 < 1.0)
        li, t0, t1 = li[cut], t0[cut], t1[cut]
    cuts: dict[int, list[tuple[float, float]]] = {}
    for i, x0, x1 in zip(li.tolist(), t0.tolist() if li.size else [], t1.tolist() if li.size else [], strict=True):
        cuts.setdefault(i, []).append((x0, x1))
    keep = np.ones(n, bool)
    out_a, out_b, out_i = [], [], []
    for i, lst in cuts.items():
        keep[i] = False
        start = 0.0
        for x0, x1 in sorted(lst):
            if x0 > start:
                out_a.append(a[i] + start * d[i])
                out_b.append(a[i] + x0 * d[i])
                out_i.append(i)
            start = max(start, x1)
        if start < 1.0:
            out_a.append(a[i] + start * d[i])
            out_b.append(b[i].copy())
            out_i.append(i)
    whole = np.nonzero(keep)[0]
    pa = np.array(out_a).reshape(-1, 2)
    pb = np.array(out_b).reshape(-1, 2)
    idx = np.concatenate([whole, np.array(out_i, dtype=int)])
    order = np.argsort(idx, kind="stable")  # the segments' order, a segment's pieces along it
    return np.concatenate([a[whole], pa])[order], np.concatenate([b[whole], pb])[order], idx[order]


def _project_from(v: np.ndarray, x: np.ndarray, frame: Frame) -> np.ndarray:
    """Central projection of `x` from `v` onto the receiver plane (needs h(v) > h(x))."""
    hv, hx = frame.height(v), frame.height(x)
    return frame.to2d(v + (x - v) * (hv / (hv - hx))[..., None])


def _slab(h0: np.ndarray, h1: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Parameter range of a segment with end heights h0, h1 where lo < h < hi."""
    dh = h1 - h0
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (lo - h0) / dh
        tb = (hi - h0) / dh
    t0 = np.where(dh > 0, ta, np.where(dh < 0, tb, 0.0))
    t1 = np.where(dh > 0, tb, np.where(dh < 0, ta, 1.0))
    inside_const = (h0 > lo) & (h0 < hi)
    t0 = np.where(dh == 0, np.where(inside_const, 0.0, 2.0), np.clip(t0, 0.0, 1.0))
    t1 = np.where(dh == 0, np.where(inside_const, 1.0, -1.0), np.clip(t1, 0.0, 1.0))
    return t0, t1


def discontinuity_segments(scene: Scene, occ: Occluders, frame: Frame, poly: np.ndarray) -> Segments:
    """The candidate VE and EV segments of `scene` on the receiver polygon `poly (k, 2)` (frame
    coordinates), after the support and between-ness tests (not yet the visibility test)."""
    lf = light_features(scene)
    size = float(np.max(np.ptp(occ.faces.reshape(-1, 3), axis=0))) or 1.0
    parts: list[tuple] = []
    # VE: light vertex v, occluder edge (x0, x1).
    for v in lf.vertices:
        hv = float(frame.height(v))
        if hv <= 0:
            continue
        x0, x1 = occ.edge[:, 0], occ.edge[:, 1]
        m = np.cross(x0 - v, x1 - v)
        sup, side = _supports(m, np.broadcast_to(v, x0.shape), occ.edge_adj, size)
        h0, h1 = frame.height(x0), frame.height(x1)
        t0, t1 = _slab(h0, h1, np.full_like(h0, 1e-9 * hv), np.full_like(h0, hv * (1 - 1e-7)))
        ok = sup & (t1 > t0)
        y0 = x0 + t0[:, None] * (x1 - x0)
        y1 = x0 + t1[:, None] * (x1 - x0)
        ok &= np.isfinite(t0) & np.isfinite(t1)
        idx = np.nonzero(ok)[0]
        if idx.size:
            a = _project_from(v, y0[idx], frame)
            b = _project_from(v, y1[idx], frame)
            parts.append((a, b, m[idx], side[idx], np.broadcast_to(v, (idx.size, 3)), False,
                          np.broadcast_to(np.stack([v, v]), (idx.size, 2, 3)), occ.edge_object[idx]))
    # EV: light edge (v0, v1), occluder vertex w.
    for v0, v1 in lf.edges:
        w = occ.vert
        m = np.cross(v0 - w, v1 - w)
        sup, side = _supports(m, w, occ.vert_adj, size)
        hw = frame.height(w)
        h0, h1 = np.full_like(hw, frame.height(v0)), np.full_like(hw, frame.height(v1))
        t0, t1 = _slab(h0, h1, hw + 1e-7 * np.maximum(hw, 1e-300), np.full_like(hw, np.inf))
        ok = sup & (hw > 0) & (t1 > t0)
        idx = np.nonzero(ok)[0]
        if idx.size:
            ya = v0 + t0[idx, None] * (v1 - v0)
            yb = v0 + t1[idx, None] * (v1 - v0)
            a = _project_from(ya, w[idx], frame)
            b = _project_from(yb, w[idx], frame)
            parts.append((a, b, m[idx], side[idx], w[idx], True,
                          np.broadcast_to(np.stack([v0, v1]), (idx.size, 2, 3)), occ.vert_object[idx]))
    if not parts:
        z2, z3 = np.zeros((0, 2)), np.zeros((0, 3))
        return Segments(z2, z2, z2, z3, np.zeros(0, bool), np.zeros((0, 2, 3)), np.zeros(0, int))
    a = np.concatenate([p[0] for p in parts])
    b = np.concatenate([p[1] for p in parts])
    m = np.concatenate([p[2] for p in parts])
    side = np.concatenate([p[3] for p in parts])
    target = np.concatenate([p[4] for p in parts])
    through = np.concatenate([np.full(p[0].shape[0], p[5]) for p in parts])
    ledge = np.concatenate([p[6] for p in parts])
    obj = np.concatenate([p[7] for p in parts])
    a, b, ok = _clip_to_polygon(a, b, poly)
    length = np.linalg.norm(b - a, axis=1)
    diam = float(np.max(np.ptp(poly, axis=0)))
    ok &= length > 1e-9 * diam
    # In-plane normal of the line, pointing away from the occluder's side of the event plane.
    d = (b - a) / np.maximum(length, 1e-300)[:, None]
    nu = np.stack([-d[:, 1], d[:, 0]], axis=1)
    m2 = np.stack([m @ frame.u, m @ frame.w], axis=1)
    s = np.sum(nu * m2, axis=1)
    free = np.where((np.sign(s) * side)[:, None] > 0, -nu, nu)
    seg = Segments(a, b, free, target, through, ledge, obj)
    return seg.take(ok)


def corner_segments(scene: Scene, occ: Occluders, frame: Frame, poly: np.ndarray, foot: np.ndarray,
                    length: float, memo: dict[bytes, list[tuple[np.ndarray, np.ndarray, int]]] | None = None,
                    contact: tuple[list[np.ndarray], np.ndarray] | None = None) -> Segments:
    """The discontinuity lines that leave the foot `c` of an occluder edge `E` standing on the
    receiver: the traces of the planes through `E` and another occluder edge `E'` in a plane
    with it (a face of the same object, or a parallel edge of another object: two boxes'
    vertical edges), on the side of `c` away from `E'`, from `c` over `length` (m), clipped to
    the receiver polygon `poly` and to the receiver region both objects can shadow (`foot`, per
    face; what an update re-meshes when either moves). Seen from a receiver point crossing such
    a plane, the blocked part of the light is bounded by the image of `E` on one side and of
    `E'` on the other, so the irradiance has a kink on the trace. For a face of the object, its
    plane bounds the face's occlusion volume (Campbell & Fussell §3.1.2, "the plane of the
    blocker"): crossing it, the face turns from back- to front-facing and its image, a sliver as
    wide as the distance to the plane, adds to the object's. For two objects it is an EEE event
    (two occluder edges and a light edge lined up; a quadric in general, beyond C&F's single
    blocker) whose two occluder edges are coplanar, so that the quadric is their plane. Its
    gradient jump grows as 1/r at distance r from `c` (the image of `E` moves on the light as
    1/r), which is what no element of at least `min_edge` resolves near a standing object's
    corner; away from it the jump is finite, but where the light is faint an element's checks
    can miss it (the mesher passes the receiver's size as `length`). Kept are the pairs where
    the plane supports both edges' objects (both are silhouette edges; on either side: the
    blocked part is bounded by the outer image, or the gap between the images opens) and, seen
    from `c` within the plane, the light's chord overlaps the directions of `E'` (the light
    lies behind `E'`). No visibility test (`kept`): a line
    where the swap is hidden is a harmless extra mesh edge. But the pieces within `CONTACT_GAP`
    (of the receiver's size) of another object's foot (`contact`: `contact_polygons`) are cut
    out: the floor there is a hole, and a line along or into its edge would make slivers whose
    vertices fall into the hole by round-off."""
    empty = Segments(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, bool),
                     np.zeros((0, 2, 3)), np.zeros(0, int), np.zeros(0, bool))
    lights = [np.asarray(lt.vertices, np.float64) for lt in scene.lights if isinstance(lt, PolygonLight)]
    lights += [np.stack([np.asarray(lt.start, np.float64), np.asarray(lt.end, np.float64)])
               for lt in scene.lights if isinstance(lt, LinearLight)]
    if not lights or occ.edge.shape[0] < 2:
        return empty
    size = float(np.max(np.ptp(occ.faces.reshape(-1, 3), axis=0))) or 1.0
    diam = float(np.max(np.ptp(poly, axis=0)))
    on = 1e-9 * diam  # the contact tolerance (`contact_polygons`)
    h = frame.height(occ.edge)  # (E, 2)
    low = np.abs(h) <= on
    rising = np.nonzero(low.any(axis=1) & (h.max(axis=1) > on))[0]
    above = np.nonzero(h.max(axis=1) > on)[0]
    nrm = frame.normal
    objs = np.unique(occ.edge_object)
    obj_box = np.full((int(objs.max()) + 1, 4), np.nan)
    for o in objs:
        f = foot[occ.face_object == o]
        obj_box[o] = np.concatenate([f[:, :2].min(axis=0), f[:, 2:].max(axis=0)])
    edge_box = obj_box[occ.edge_object]
    A: list[np.ndarray] = []
    B: list[np.ndarray] = []
    OBJ: list[int] = []
    def lines_of_edge(i: int, c: np.ndarray, e: np.ndarray, c2: np.ndarray, cand: np.ndarray) -> None:
        """The lines leaving the foot `c` of rising edge `i` (direction `e`), paired with the
        candidate edges `cand`: appended to `A`, `B`, `OBJ`."""
        w1, w2 = occ.edge[cand, 0] - c, occ.edge[cand, 1] - c
        det = np.einsum("k,nk->n", e, np.cross(w1, w2))
        scale = np.linalg.norm(e) * np.linalg.norm(w1, axis=1) * np.linalg.norm(w2, axis=1)
        far1 = np.linalg.norm(np.cross(e, w1), axis=1) >= np.linalg.norm(np.cross(e, w2), axis=1)
        w = np.where(far1[:, None], w1, w2)
        n = np.cross(e, w)
        nn = np.linalg.norm(n, axis=1)
        ok = (np.abs(det) <= SUPPORT_RTOL * np.maximum(scale, 1e-300)) & (nn > SUPPORT_RTOL * size * np.linalg.norm(e))
        cand, w, n, nn = cand[ok], w[ok], n[ok], nn[ok]
        if cand.size == 0:
            return
        sup_e, _ = _supports(n, np.broadcast_to(c, n.shape), np.broadcast_to(occ.edge_adj[i], (cand.size,) + occ.edge_adj.shape[1:]), size)
        sup_f, _ = _supports(n, np.broadcast_to(c, n.shape), occ.edge_adj[cand], size)
        ok = sup_e & sup_f
        # The trace on the receiver, away from E'; within the plane, `hdir` points to E', `up` up.
        d = np.cross(n, nrm)
        dl = np.linalg.norm(d, axis=1)
        ok &= dl > SUPPORT_RTOL
        d = d / np.maximum(dl, 1e-300)[:, None]
        toward = np.einsum("nk,nk->n", d, w)
        ok &= np.abs(toward) > SUPPORT_RTOL * size
        d = np.where((toward > 0)[:, None], -d, d)
        hdir = -d
        up = np.cross(n / nn[:, None], d)
        up = np.where((up @ nrm < 0)[:, None], -up, up)
        # Directions from c within the plane, as angles from `hdir`: E''s, then the light's chord.
        ends = occ.edge[cand] - c  # (n, 2, 3)
        a12 = np.arctan2(np.einsum("nek,nk->ne", ends, up), np.einsum("nek,nk->ne", ends, hdir))
        lo_e, hi_e = a12.min(axis=1), a12.max(axis=1)
        seen = np.zeros(cand.size, bool)
        nu = n / nn[:, None]
        for lv in lights:
            s = (lv - c) @ nu.T  # (k, n)
            nxt = np.roll(lv, -1, axis=0) if lv.shape[0] > 2 else lv[::-1]
            sn = np.roll(s, -1, axis=0) if lv.shape[0] > 2 else s[::-1]
            cross = (s * sn <= 0) & (s != sn)
            t = np.where(cross, s / np.where(cross, s - sn, 1.0), 0.0)
            pts = lv[:, None, :] + t[..., None] * (nxt - lv)[:, None, :] - c  # (k, n, 3)
            ang = np.arctan2(np.einsum("knj,nj->kn", pts, up), np.einsum("knj,nj->kn", pts, hdir))
            lo_l = np.where(cross, ang, np.inf).min(axis=0)
            hi_l = np.where(cross, ang, -np.inf).max(axis=0)
            seen |= (lo_l <= hi_e) & (hi_l >= lo_e)
        ok &= seen
        for j in np.nonzero(ok)[0]:
            b2 = c2 + length * np.array([d[j] @ frame.u, d[j] @ frame.w])
            # Where both objects can shadow (outside, one of them does not change the light).
            b1, b2_ = edge_box[i], edge_box[cand[j]]
            bx = np.concatenate([np.maximum(b1[:2], b2_[:2]), np.minimum(b1[2:], b2_[2:])])
            if not (np.all(np.isfinite(bx)) and np.all(bx[:2] < bx[2:])):
                continue
            A.append(c2)
            B.append(b2)
            OBJ.append(int(occ.edge_object[cand[j]]))
            box = np.array([[bx[0], bx[1]], [bx[2], bx[1]], [bx[2], bx[3]], [bx[0], bx[3]]])
            a_, b_, k_ = _clip_to_polygon(np.array([c2]), np.array([b2]), box)
            A[-1], B[-1] = (a_[0], b_[0]) if k_[0] else (c2, c2)
    # `memo` (kept by the mesher across updates): an edge's lines, by everything they depend on.
    common = b"".join(np.asarray(x, np.float64).tobytes() for x in [*lights, frame.normal, frame.u, frame.w,
                                                                       [size, length, SUPPORT_RTOL]])
    for i in rising:
        k = 0 if low[i, 0] else 1
        c, top = occ.edge[i, k], occ.edge[i, 1 - k]
        e = top - c
        c2 = frame.to2d(c)
        # Only objects that can shadow the receiver within `length` of c, where E's can too.
        cand = above[(above != i) & boxes_overlap(edge_box[above], c2, c2, length)
                     & boxes_overlap(edge_box[above], edge_box[i, :2], edge_box[i, 2:])]
        mkey = b""
        if memo is not None:
            mkey = hashlib.blake2b(b"".join([
                common, np.array([k], np.int64).tobytes(), c2.tobytes(), occ.edge[i].tobytes(), occ.edge_adj[i].tobytes(),
                edge_box[i].tobytes(), occ.edge[cand].tobytes(), occ.edge_adj[cand].tobytes(), edge_box[cand].tobytes(),
                occ.edge_object[cand].astype(np.int64).tobytes()]), digest_size=32).digest()
            if mkey in memo:
                for a_, b_, o_ in memo[mkey]:
                    A.append(a_)
                    B.append(b_)
                    OBJ.append(o_)
                continue
            start = len(A)
        lines_of_edge(int(i), c, e, c2, cand)
        if memo is not None:
            memo[mkey] = list(zip(A[start:], B[start:], OBJ[start:], strict=True))
    if not A:
        return empty
    a, b = np.array(A), np.array(B)
    a, b, ok = _clip_to_polygon(a, b, poly)
    ok &= np.linalg.norm(b - a, axis=1) > 1e-9 * diam
    a, b, obj = a[ok], b[ok], np.array(OBJ, dtype=int)[ok]
    # One line per corner and direction (a face's edges, or aligned edges of several objects,
    # give the same plane), the longest.
    dd = (b - a) / np.linalg.norm(b - a, axis=1)[:, None]
    key = np.concatenate([np.round(a / (1e-12 * diam)), np.round(np.arctan2(dd[:, 1], dd[:, 0]) / 1e-9)[:, None]], axis=1)
    order = np.lexsort((-np.linalg.norm(b - a, axis=1), *key.T[::-1]))
    first = np.ones(order.size, bool)
    first[1:] = np.any(key[order[1:]] != key[order[:-1]], axis=1)
    keep = np.sort(order[first])
    a, b, obj, dd = a[keep], b[keep], obj[keep], dd[keep]
    if contact is not None and contact[0]:
        a, b, src = _cut_by_polygons(a, b, contact[0], contact[1], CONTACT_GAP * diam)
        ok = np.linalg.norm(b - a, axis=1) > 1e-9 * diam
        a, b, obj, dd = a[ok], b[ok], obj[src[ok]], dd[src[ok]]
    m = a.shape[0]
    return Segments(a, b, np.stack([-dd[:, 1], dd[:, 0]], axis=1), np.zeros((m, 3)), np.zeros(m, bool),
                    np.zeros((m, 2, 3)), obj, np.ones(m, bool))


def ray_targets(seg: Segments, idx: np.ndarray, pts3: np.ndarray) -> np.ndarray:
    """The light point each sample's event ray ends at: the light vertex (VE), or where the line
    from the sample through the occluder vertex meets the light edge's line (EV)."""
    tgt = seg.target[idx].copy()
    thr = seg.through[idx]
    if np.any(thr):
        p = pts3[thr]
        w = seg.target[idx][thr]
        e0, e1 = seg.ledge[idx][thr, 0], seg.ledge[idx][thr, 1]
        d1, d2 = e1 - e0, w - p
        c = np.cross(d1, d2)
        t = np.einsum("nk,nk->n", np.cross(p - e0, d2), c) / np.maximum(np.einsum("nk,nk->n", c, c), 1e-300)
        tgt[thr] = e0 + t[:, None] * d1
    return tgt


def ray_visible(p: np.ndarray, q: np.ndarray, occ: Occluders, faces: np.ndarray) -> np.ndarray:
    """`(n,)` bool: the open segment from `p (n, 3)` to `q (n, 3)` misses the occluder faces
    `faces (c,)` (indices into `occ`); one vectorised test per (ray, face)."""
    vis = np.ones(p.shape[0], bool)
    if faces.size == 0 or p.shape[0] == 0:
        return vis
    f = occ.faces[faces]  # (c, K, 3)
    nf = occ.face_normal[faces]
    step = max(1, int(4_000_000 // max(1, faces.size * f.shape[1])))
    for s in range(0, p.shape[0], step):
        pp, qq = p[s:s + step], q[s:s + step]
        d = qq - pp
        num = np.einsum("ck,ck->c", f[:, 0], nf)[None, :] - pp @ nf.T  # (n, c)
        den = d @ nf.T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / den
        hit = (t > 1e-12) & (t < 1 - 1e-12) & (den != 0)
        t = np.where(hit, t, 0.0)  # a ray in a face's plane (den 0: t inf or NaN) misses it
        x = pp[:, None, :] + t[:, :, None] * d[:, None, :]  # (n, c, 3)
        e = np.roll(f, -1, axis=1) - f  # (c, K, 3)
        rel = x[:, :, None, :] - f[None]  # (n, c, K, 3)
        inside = np.all(np.einsum("nckj,ckj->nck", np.cross(e[None], rel), nf[:, None, :]) >= 0, axis=2)
        vis[s:s + step] = ~np.any(hit & inside, axis=1)
    return vis


def face_footprints(occ: Occluders, scene: Scene, frame: Frame, bbox: np.ndarray) -> np.ndarray:
    """Per face the 2-D bounding box `(M, 4)` = (xmin, ymin, xmax, ymax) of the receiver region its
    shadow volume can reach (the central projections of its part above the receiver from every
    light vertex; the whole receiver `bbox` when the face reaches the height of a light vertex,
    or for directional and unrecognised lights)."""
    lf = light_features(scene)
    m = occ.faces.shape[0]
    full = np.broadcast_to(bbox, (m, 4)).copy()
    other = any(not isinstance(lt, (PolygonLight, LinearLight, PointLight)) for lt in scene.lights)
    if other or lf.vertices.shape[0] == 0:
        return full
    h = frame.height(occ.faces)  # (M, K)
    below = np.all(h <= 0, axis=1)
    out = np.empty((m, 4))
    out[:, :2] = np.inf
    out[:, 2:] = -np.inf
    hv = frame.height(lf.vertices)
    unbounded = np.zeros(m, bool)
    for v, hvv in zip(lf.vertices, hv, strict=True):
        if hvv <= 0:
            continue
        unbounded |= np.any(h >= hvv * (1 - 1e-9), axis=1) & ~below
        # A face crossing the receiver plane meets it between its vertices' orthographic
        # images: those (and the projections of the vertices above) bound its shadow.
        hx = np.clip(h, 0.0, hvv * (1 - 1e-9))
        x = occ.faces + (hx - h)[..., None] * frame.normal
        xy = np.concatenate([frame.to2d(v + (x - v) * (hvv / (hvv - hx))[..., None]), frame.to2d(occ.faces)], axis=1)
        out[:, :2] = np.minimum(out[:, :2], xy.min(axis=1))
        out[:, 2:] = np.maximum(out[:, 2:], xy.max(axis=1))
    out = np.where(unbounded[:, None], full, out)
    out[below] = np.array([np.inf, np.inf, -np.inf, -np.inf])
    return out


def boxes_overlap(boxes: np.ndarray, lo: Any, hi: Any, margin: float = 0.0) -> np.ndarray:
    """Which `boxes (n, 4)` meet the axis-aligned box [lo, hi] (2-D) grown by `margin`."""
    return ((boxes[:, 0] <= hi[0] + margin) & (boxes[:, 2] >= lo[0] - margin)
            & (boxes[:, 1] <= hi[1] + margin) & (boxes[:, 3] >= lo[1] - margin))


def contact_polygons(scene: Scene, frame: Frame, tol: float) -> tuple[list[np.ndarray], np.ndarray]:
    """The occluder faces lying on the receiver plane (within `tol`), as counter-clockwise 2-D
    polygons, and their bounding boxes `(n, 4)`: an object standing on the receiver covers them,
    and along their edges the irradiance jumps (a value discontinuity no interpolation meets), so
    they are holes of the mesh, bounded by mesh edges."""
    if scene.occluders is None:
        return [], np.zeros((0, 4))
    faces = np.asarray(scene.occluders, np.float64)
    flat = np.all(np.abs(frame.height(faces)) <= tol, axis=1)
    out = []
    for f in faces[flat]:
        q = frame.to2d(strip_padding(f))
        area = 0.5 * np.sum(q[:, 0] * np.roll(q[:, 1], -1) - np.roll(q[:, 0], -1) * q[:, 1])
        if area != 0:
            out.append(q if area > 0 else q[::-1].copy())
    box = np.array([np.concatenate([q.min(axis=0), q.max(axis=0)]) for q in out]).reshape(-1, 4)
    return out, box
