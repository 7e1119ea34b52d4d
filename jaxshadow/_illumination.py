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
   occluders that can shadow the receiver, kept where a ray along the event is not blocked,
   inserted as constrained edges of a constrained Delaunay triangulation (Shewchuk's Triangle,
   through the `triangle` package). Each tile's occluder list holds the faces whose shadow volume
   can reach it (C&F §4.3, C&S's per-cell occluder lists).
3. **Extrema** (`_illumination_extrema`): starts where a coarse grid sample beats its
   neighbours, batched BFGS on the exact gradient (or central differences of exact values on
   large scenes), and a golden-section search along tile edges; the extrema become vertices.
4. **Refinement.** Every element is checked at seven points (edge midpoints, centroid, and the
   midpoints between centroid and corners) against exact irradiance; the worst point of an
   element whose linear interpolation misses by more than `ESTIMATE_MARGIN * tol * scale` is
   inserted, and the tile re-triangulated, until no element fails. Tile edges are refined the
   same way in 1-D beforehand.

Values come from `jaxshadow.irradiance` (the host shadow engine for concrete inputs).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import _illumination_events as ev
from . import _illumination_extrema as ex
from ._geometry import check_convex_polygon
from ._scene import Scene
from ._shade import irradiance

ESTIMATE_MARGIN = 0.5  # elements pass when their checked error is below this fraction of tol
DEFAULT_TILES = 16  # tiles along the receiver's longer side
SAMPLES_PER_TILE = 6  # extremum-search grid per tile side
SEGMENT_SAMPLES_PER_TILE = 16  # visibility samples per tile length along a discontinuity line
JAX_GRADIENT_MAX_FACES = 16
ON_LINE_STEP = 1e-9
GRID_SHIFT = (np.sqrt(2.0) - 1) / 10
MAX_ROUNDS = 200  # refinement rounds per tile (each halves the worst elements; a guard)
_DEBUG = False  # progress prints (development)
_INNER = np.array([[0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.5]]) + 0.5 / 3  # between centroid and corners


class _Evaluator:
    """Exact irradiance at 2-D receiver points, cached by coordinates, batched per call.

    Points on a discontinuity line (`mark`) are also evaluated `ON_LINE_STEP` (of the receiver's
    size) to either side along a fixed oblique direction: the host engine can return the
    unoccluded value at a point exactly on an umbra boundary (an EV plane; see
    `tests/test_illumination_mesh.py::test_engine_on_event_plane`), and where the value at the
    point is not between its neighbours' (with a slack far above a kink's) their mean is used
    (`repairs` counts these; the irradiance is continuous there, so the mean is within
    `ON_LINE_STEP` times the gradient of the exact value)."""

    def __init__(self, scene: Scene, frame: ev.Frame, size: float):
        self.scene, self.frame = scene, frame
        self.cache: dict[tuple[float, float], np.ndarray] = {}
        self.online: set[tuple[float, float]] = set()
        self.checked: set[tuple[float, float]] = set()
        self.step = ON_LINE_STEP * size * np.array([np.cos(0.6180339887), np.sin(0.6180339887)])
        self.evaluations = 0
        self.repairs = 0
        self.seconds = 0.0

    def mark(self, xy: np.ndarray) -> None:
        """Declare points `(n, 2)` to lie on discontinuity lines."""
        self.online.update(map(tuple, np.asarray(xy, np.float64).reshape(-1, 2).tolist()))

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        keys = list(map(tuple, xy.tolist()))
        todo = {k: None for k in keys if k not in self.cache or (k in self.online and k not in self.checked)}
        if todo:
            pts = np.array(list(todo), np.float64)
            line = np.array([k in self.online for k in todo])
            side = pts[line]
            allp = np.concatenate([pts, side + self.step, side - self.step])
            t0 = time.perf_counter()
            p3 = self.frame.to3d(allp)
            nrm = np.broadcast_to(self.frame.normal, p3.shape)
            e = np.asarray(irradiance(self.scene, p3, np.ascontiguousarray(nrm)), np.float64)
            self.seconds += time.perf_counter() - t0
            self.evaluations += allp.shape[0]
            n, m = pts.shape[0], side.shape[0]
            val = e[:n].copy()
            if m:
                ep, em = e[n:n + m], e[n + m:]
                mid = 0.5 * (ep + em)
                slack = 0.5 * np.abs(ep - em) + 1e-6 * np.maximum(np.abs(ep), np.abs(em)) + 1e-300
                bad = np.any(np.abs(val[line] - mid) > slack, axis=1)
                if np.any(bad):
                    fixed = val[line]
                    fixed[bad] = mid[bad]
                    val[line] = fixed
                    self.repairs += int(bad.sum())
            for k, v, ln in zip(todo, val, line, strict=True):
                self.cache[k] = v
                if ln:
                    self.checked.add(k)
        if not keys:
            return np.zeros((0, 3))
        return np.stack([self.cache[k] for k in keys])

    def luminance(self, xy: np.ndarray) -> np.ndarray:
        return self(xy).sum(axis=1)


@dataclass
class _Edge:
    """A tile edge from global point `ga` to `gb` (`ga < gb`): its crossings with discontinuity
    segments and, once refined, its vertex parameters `s` in [0, 1]."""

    a: np.ndarray
    b: np.ndarray
    cross: dict[int, tuple[float, np.ndarray, bool]] = field(default_factory=dict)
    s: np.ndarray | None = None

    def point(self, s: np.ndarray) -> np.ndarray:
        return self.a + np.asarray(s)[..., None] * (self.b - self.a)


@dataclass
class _Tile:
    poly: np.ndarray  # (k, 2) counter-clockwise
    gids: list[int]
    lo: np.ndarray
    hi: np.ndarray
    faces: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    pieces: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    extrema: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    piece_extrema: dict[int, list[float]] = field(default_factory=dict)
    verts: np.ndarray | None = None
    tris: np.ndarray | None = None
    values: np.ndarray | None = None
    error: float = 0.0

    def edge_keys(self) -> list[tuple[int, int, bool]]:
        g = self.gids
        return [(min(g[k], g[(k + 1) % len(g)]), max(g[k], g[(k + 1) % len(g)]), g[k] > g[(k + 1) % len(g)])
                for k in range(len(g))]


def _grid(poly: np.ndarray, tile_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Interior grid lines of the tiles. They are shifted by an irrational fraction of a tile
    off the receiver's round subdivisions: scenes built on round coordinates put shadow
    boundaries on those, and a tile edge along a discontinuity line would cross it nowhere."""
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    lines = []
    for ax in range(2):
        n = max(1, int(np.ceil((hi[ax] - lo[ax]) / tile_size - 1e-9)))
        step = (hi[ax] - lo[ax]) / n
        xs = lo[ax] + step * (np.arange(1, n) + GRID_SHIFT)
        # Keep the lines off the receiver's vertices (a vertex on a line makes a degenerate tile).
        while xs.size and np.min(np.abs(poly[:, ax][:, None] - xs[None, :])) < 1e-6 * step:
            xs = xs + 0.01 * step
        lines.append(xs)
    return lines[0], lines[1]


def _tiles(poly: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> tuple[np.ndarray, list[_Tile]]:
    """Global points (receiver vertices, grid lines' crossings with the boundary, grid crossings
    inside) and the convex tiles made of them."""
    k = poly.shape[0]
    pts: list[tuple[float, float]] = [tuple(p) for p in poly.tolist()]
    inside = lambda q: all(  # noqa: E731
        (poly[(i + 1) % k, 0] - poly[i, 0]) * (q[1] - poly[i, 1]) - (poly[(i + 1) % k, 1] - poly[i, 1]) * (q[0] - poly[i, 0]) > 0
        for i in range(k))
    for ax, lines in ((0, xs), (1, ys)):
        for c in lines:
            for i in range(k):
                a, b = poly[i], poly[(i + 1) % k]
                if (a[ax] - c) * (b[ax] - c) < 0:
                    t = (c - a[ax]) / (b[ax] - a[ax])
                    other = a[1 - ax] + t * (b[1 - ax] - a[1 - ax])
                    pts.append((c, other) if ax == 0 else (other, c))
    for x in xs:
        for y in ys:
            if inside((x, y)):
                pts.append((float(x), float(y)))
    gp = np.array(pts, np.float64)
    bx = np.concatenate([[-np.inf], xs, [np.inf]])
    by = np.concatenate([[-np.inf], ys, [np.inf]])
    tiles = []
    for i in range(bx.size - 1):
        for j in range(by.size - 1):
            sel = np.nonzero((gp[:, 0] >= bx[i]) & (gp[:, 0] <= bx[i + 1]) & (gp[:, 1] >= by[j]) & (gp[:, 1] <= by[j + 1]))[0]
            if sel.size < 3:
                continue
            c = gp[sel].mean(axis=0)
            order = sel[np.argsort(np.arctan2(gp[sel, 1] - c[1], gp[sel, 0] - c[0]))]
            q = gp[order]
            area = 0.5 * np.sum(q[:, 0] * np.roll(q[:, 1], -1) - np.roll(q[:, 0], -1) * q[:, 1])
            if area <= 1e-12 * np.prod(np.ptp(poly, axis=0)):
                continue
            tiles.append(_Tile(q, [int(g) for g in order], q.min(axis=0), q.max(axis=0)))
    return gp, tiles


def _triangulate(v: np.ndarray, s: np.ndarray, m: np.ndarray) -> tuple[dict, bool]:
    """Constrained Delaunay triangulation of a PSLG (Triangle, no Steiner points on the boundary).
    Exact duplicate vertices are merged first (Triangle's Python binding crashes on them). If
    Triangle rejects the internal segments (nearly collinear ones it cannot split consistently),
    they are dropped and their vertices kept: `(mesh, dropped)`."""
    import triangle

    uniq, first, inv = np.unique(v, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # keep the input order (deterministic, boundary first)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    v2 = uniq[order]
    s2 = rank[inv.ravel()][s]
    keep = s2[:, 0] != s2[:, 1]
    s2, m2 = s2[keep], m[keep]
    _, one = np.unique(np.sort(s2, axis=1), axis=0, return_index=True)
    one = np.sort(one)
    s2, m2 = s2[one], m2[one]
    try:
        return triangle.triangulate({"vertices": v2, "segments": s2, "segment_markers": m2[:, None]}, "pYQ"), False
    except RuntimeError:
        b = m2 == 1
        return triangle.triangulate({"vertices": v2, "segments": s2[b], "segment_markers": m2[b][:, None]}, "pYQ"), True


def _split_at(v: np.ndarray, s: np.ndarray, m: np.ndarray, idx: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Split internal segments (marker 0) at the vertices `idx` that lie on them (within `tol`,
    not at their ends): Triangle keeps a vertex that is off a segment by round-off as a separate
    point and fills the gap with zero-area triangles."""
    if idx.size == 0 or s.size == 0:
        return s, m
    inner = np.nonzero(m == 0)[0]
    if inner.size == 0:
        return s, m
    a, b = v[s[inner, 0]], v[s[inner, 1]]
    d = b - a
    ll = np.maximum(np.sum(d * d, axis=1), 1e-300)
    q = v[idx]
    t = np.einsum("skj,sj->sk", q[None, :, :] - a[:, None, :], d) / ll[:, None]  # (S, k)
    foot = a[:, None, :] + t[..., None] * d[:, None, :]
    dist = np.linalg.norm(foot - q[None], axis=2)
    on = (dist <= tol) & (t > 0) & (t < 1)
    on &= (idx[None, :] != s[inner, 0][:, None]) & (idx[None, :] != s[inner, 1][:, None])
    if not np.any(on):
        return s, m
    out_s, out_m = [row for row in s[m != 0]], list(m[m != 0])
    for r, si in enumerate(inner):
        hit = np.nonzero(on[r])[0]
        chain = [s[si, 0]] + [int(idx[h]) for h in hit[np.argsort(t[r, hit])]] + [s[si, 1]]
        for i, j in zip(chain[:-1], chain[1:], strict=True):
            out_s.append(np.array([i, j]))
            out_m.append(0)
    return np.array(out_s).reshape(-1, 2), np.array(out_m)


def _noded(lines: list[tuple[np.ndarray, np.ndarray]]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Segments split where they cross or overlap (GEOS noding through shapely), duplicates
    dropped: collinear overlapping discontinuity lines (parallel occluder and light edges make
    them) would otherwise have Triangle split nearly collinear segments against each other."""
    if len(lines) < 2:
        return lines
    import shapely

    noded = shapely.node(shapely.MultiLineString([np.stack(ln) for ln in lines]))
    out, seen = [], set()
    for g in shapely.get_parts(noded):
        c = np.asarray(shapely.get_coordinates(g))
        for a, b in zip(c[:-1], c[1:], strict=True):
            key = tuple(sorted([tuple(a.tolist()), tuple(b.tolist())]))
            if key not in seen and key[0] != key[1]:
                seen.add(key)
                out.append((a, b))
    return out


def _edge_kinds(edge_ij: np.ndarray, segs: np.ndarray, marks: np.ndarray, n: int) -> np.ndarray:
    """Per triangle edge `(T, 3, 2)` the marker of the PSLG segment it lies on, or -1."""
    code = lambda a, b: np.minimum(a, b).astype(np.int64) * n + np.maximum(a, b)  # noqa: E731
    keys = code(segs[:, 0], segs[:, 1])
    order = np.argsort(keys)
    keys, marks = keys[order], marks[order]
    q = code(edge_ij[..., 0], edge_ij[..., 1])
    pos = np.clip(np.searchsorted(keys, q), 0, max(keys.size - 1, 0))
    hit = (keys.size > 0) & (keys[pos] == q) if keys.size else np.zeros(q.shape, bool)
    return np.where(hit, marks[pos] if keys.size else -1, -1)


def _segment_crossings(seg: ev.Segments, cand: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Crossings of segments `cand` with the edge a -> b: (segment ids, edge parameter s,
    segment parameter t), strictly inside the edge."""
    p, r = seg.a[cand], seg.b[cand] - seg.a[cand]
    e = b - a
    den = r[:, 0] * e[1] - r[:, 1] * e[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = ((p[:, 0] - a[0]) * r[:, 1] - (p[:, 1] - a[1]) * r[:, 0]) / -den
        t = ((p[:, 0] - a[0]) * e[1] - (p[:, 1] - a[1]) * e[0]) / -den
    ok = (den != 0) & (s > 1e-12) & (s < 1 - 1e-12) & (t >= 0) & (t <= 1)
    return cand[ok], s[ok], t[ok]


class _Builder:
    """Everything one mesh (or one update) computes; per tile and per edge, kept for updates."""

    def __init__(self, scene: Scene, receiver: np.ndarray, tol: float, tile_size: float | None,
                 min_edge: float | None, max_vertices: int, gradient: str, scale: float | None):
        self.scene, self.tol = scene, float(tol)
        self.frame = ev.receiver_frame(receiver)
        self.poly = self.frame.to2d(receiver)
        diam = float(np.max(np.ptp(self.poly, axis=0)))
        self.diam = diam
        self.tile_size = float(tile_size) if tile_size else diam / DEFAULT_TILES
        self.min_edge = float(min_edge) if min_edge else 1e-6 * diam
        self.max_vertices = int(max_vertices)
        self.gradient = gradient
        self.scale = scale
        xs, ys = _grid(self.poly, self.tile_size)
        self.gp, self.tiles = _tiles(self.poly, xs, ys)
        self.edges: dict[tuple[int, int], _Edge] = {}
        for t in self.tiles:
            for ga, gb, _ in t.edge_keys():
                if (ga, gb) not in self.edges:
                    self.edges[(ga, gb)] = _Edge(self.gp[ga], self.gp[gb])
        self.stats: dict[str, Any] = {}
        self._load_scene(scene)

    def _load_scene(self, scene: Scene) -> None:
        self.scene = scene
        self.eval = _Evaluator(scene, self.frame, self.diam)
        bbox = np.concatenate([self.poly.min(axis=0), self.poly.max(axis=0)])
        if scene.occluders is None:
            self.occ, self.seg, self.foot = None, None, np.zeros((0, 4))
            return
        self.occ = ev.occluder_features(scene)
        self.foot = ev.face_footprints(self.occ, scene, self.frame, bbox)
        self.seg = ev.discontinuity_segments(scene, self.occ, self.frame, self.poly)
        s = self.seg
        self.seg_box = np.concatenate([np.minimum(s.a, s.b), np.maximum(s.a, s.b)], axis=1)

    # ------------------------------------------------------------------ discontinuity lines
    def _tile_faces(self, t: _Tile) -> np.ndarray:
        if self.occ is None:
            return np.zeros(0, int)
        return np.nonzero(ev.boxes_overlap(self.foot, t.lo, t.hi, margin=1e-6 * self.diam))[0]

    def _tile_segments(self, t: _Tile) -> np.ndarray:
        if self.seg is None or len(self.seg) == 0:
            return np.zeros(0, int)
        return np.nonzero(ev.boxes_overlap(self.seg_box, t.lo, t.hi, margin=1e-9 * self.diam))[0]

    def _visible(self, xy: np.ndarray, ids: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """Whether the event of segment `ids` is real at `xy`: its ray, nudged off the occluder,
        reaches the light."""
        nudge = ev.NUDGE_RTOL * self.diam
        p3 = self.frame.to3d(xy + nudge * self.seg.free[ids])
        return ev.ray_visible(p3, ev.ray_targets(self.seg, ids, p3), self.occ, faces)

    def _prepare_edges(self, keys: list[tuple[int, int]]) -> None:
        """Crossings of the discontinuity lines with edges `keys` and whether each is real."""
        for key in keys:
            e = self.edges[key]
            e.cross = {}
            if self.seg is None or len(self.seg) == 0:
                continue
            lo, hi = np.minimum(e.a, e.b), np.maximum(e.a, e.b)
            cand = np.nonzero(ev.boxes_overlap(self.seg_box, lo, hi, margin=1e-9 * self.diam))[0]
            ids, s, _ = _segment_crossings(self.seg, cand, e.a, e.b)
            if ids.size == 0:
                continue
            faces = np.nonzero(ev.boxes_overlap(self.foot, lo, hi, margin=1e-6 * self.diam))[0]
            xy = e.point(s)
            vis = self._visible(xy, ids, faces)
            e.cross = {int(i): (float(si), xy[k], bool(vis[k])) for k, (i, si) in enumerate(zip(ids, s, strict=True))}

    def _prepare_tile(self, ti: int) -> None:
        t = self.tiles[ti]
        t.pieces, t.piece_extrema = [], {}
        if self.seg is None or len(self.seg) == 0:
            return
        cand = self._tile_segments(t)
        if cand.size == 0:
            return
        seg = self.seg
        k = t.poly.shape[0]
        e = np.roll(t.poly, -1, axis=0) - t.poly

        def inside(q: np.ndarray) -> np.ndarray:
            c = e[None, :, 0] * (q[:, None, 1] - t.poly[None, :, 1]) - e[None, :, 1] * (q[:, None, 0] - t.poly[None, :, 0])
            return np.all(c > 0, axis=1)

        ends: dict[int, list[tuple[float, np.ndarray, bool | None]]] = {int(i): [] for i in cand}
        ina, inb = inside(seg.a[cand]), inside(seg.b[cand])
        for i, fa, fb in zip(cand, ina, inb, strict=True):
            if fa:
                ends[int(i)].append((0.0, seg.a[i], None))
            if fb:
                ends[int(i)].append((1.0, seg.b[i], None))
        for ga, gb, _ in t.edge_keys():
            edge = self.edges[(ga, gb)]
            for i, (_, xy, vis) in edge.cross.items():
                if i in ends:
                    d = seg.b[i] - seg.a[i]
                    tt = float(np.dot(xy - seg.a[i], d) / np.dot(d, d))
                    ends[i].append((tt, xy, vis))
        samples, owner, known = [], [], []
        runs_of: list[tuple[int, int, int]] = []
        h = self.tile_size / SEGMENT_SAMPLES_PER_TILE
        for i, lst in ends.items():
            if len(lst) != 2:
                continue
            lst.sort(key=lambda z: z[0])
            (_, p0, v0), (_, p1, v1) = lst
            n = max(2, int(np.ceil(np.linalg.norm(p1 - p0) / h)))
            frac = np.linspace(0.0, 1.0, n + 1)
            pts = p0 + frac[:, None] * (p1 - p0)
            pts[0], pts[-1] = p0, p1
            start = len(samples)
            samples.extend(pts)
            owner.extend([i] * (n + 1))
            known.extend([v0] + [None] * (n - 1) + [v1])
            runs_of.append((i, start, n + 1))
        if not samples:
            return
        xy = np.array(samples)
        ids = np.array(owner)
        need = np.array([kv is None for kv in known])
        vis = np.array([bool(kv) for kv in known])
        if np.any(need):
            vis[need] = self._visible(xy[need], ids[need], t.faces)
        for _, start, n in runs_of:
            v = vis[start:start + n]
            j = 0
            while j < n:
                if not v[j]:
                    j += 1
                    continue
                r = j
                while r + 1 < n and v[r + 1]:
                    r += 1
                if r > j:
                    t.pieces.append((xy[start + j], xy[start + r]))
                j = r + 1
        del k

    # ------------------------------------------------------------------ extrema
    def _value_and_gradient(self) -> ex.Gradient:
        m = 0 if self.scene.occluders is None else self.scene.occluders.shape[0]
        mode = self.gradient
        if mode == "auto":
            mode = "jax" if m <= JAX_GRADIENT_MAX_FACES else "differences"
        self.stats["gradient"] = mode
        if mode == "differences":
            return ex.difference_gradient(self.eval.luminance, 1e-6 * self.tile_size)
        return _jax_gradient(self.scene, self.frame, self.eval)

    def _find_extrema(self, tile_ids: list[int], edge_keys: list[tuple[int, int]]) -> float:
        """Interior extrema of each tile (-> `tile.extrema`) and along each edge (-> required
        edge parameters); returns the largest irradiance seen (any channel)."""
        g = SAMPLES_PER_TILE
        top = 0.0
        starts, owners, signs, los, his = [], [], [], [], []
        for ti in tile_ids:
            t = self.tiles[ti]
            t.extrema = np.zeros((0, 2))
            fr = (np.arange(g) + 0.5) / g
            gx, gy = np.meshgrid(t.lo[0] + fr * (t.hi[0] - t.lo[0]), t.lo[1] + fr * (t.hi[1] - t.lo[1]), indexing="ij")
            q = np.stack([gx, gy], axis=-1)
            e = np.roll(t.poly, -1, axis=0) - t.poly
            c = e[None, None, :, 0] * (q[..., None, 1] - t.poly[:, 1]) - e[None, None, :, 1] * (q[..., None, 0] - t.poly[:, 0])
            ok = np.all(c > 0, axis=-1)
            vals = np.full((g, g), np.nan)
            e3 = self.eval(q[ok])
            vals[ok] = e3.sum(axis=1)
            if e3.size:
                top = max(top, float(e3.max()))
            pad = np.pad(vals, 1, constant_values=np.nan)
            nb = np.stack([pad[1 + di:1 + di + g, 1 + dj:1 + dj + g] for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj])
            with np.errstate(invalid="ignore"):
                is_max = ok & np.all(np.isnan(nb) | (vals > nb), axis=0)
                is_min = ok & np.all(np.isnan(nb) | (vals < nb), axis=0) & (vals > 0)
            for mask, sgn in ((is_max, 1.0), (is_min, -1.0)):
                for a, b in zip(*np.nonzero(mask), strict=True):
                    starts.append(q[a, b])
                    owners.append(ti)
                    signs.append(sgn)
                    los.append(t.lo)
                    his.append(t.hi)
        vg = self._value_and_gradient()
        if starts:
            x, val, interior = ex.ascend(self.eval.luminance, vg, np.array(starts), np.array(los), np.array(his),
                                         np.array(signs), np.full(len(starts), 1e-7 * self.tile_size))
            found: dict[int, list[np.ndarray]] = {}
            for k, ti in enumerate(owners):
                t = self.tiles[ti]
                e = np.roll(t.poly, -1, axis=0) - t.poly
                d = (e[:, 0] * (x[k, 1] - t.poly[:, 1]) - e[:, 1] * (x[k, 0] - t.poly[:, 0])) / np.linalg.norm(e, axis=1)
                if interior[k] and np.all(d > 1e-6 * self.tile_size):
                    lst = found.setdefault(ti, [])
                    if all(np.linalg.norm(x[k] - y) > 1e-6 * self.tile_size for y in lst):
                        lst.append(x[k])
            for ti, lst in found.items():
                self.tiles[ti].extrema = np.array(lst)
                top = max(top, float(self.eval(np.array(lst)).max()))
        # Along tile edges and along the discontinuity lines (a maximum often sits on a kink).
        found_e, vmax = self._line_extrema(np.array([self.edges[k].a for k in edge_keys]).reshape(-1, 2),
                                           np.array([self.edges[k].b for k in edge_keys]).reshape(-1, 2), False)
        top = max(top, vmax)
        self._edge_extrema = {}
        for r, s, v in found_e:
            self._edge_extrema.setdefault(edge_keys[r], []).append(s)
            top = max(top, v)
        owners = [(ti, k) for ti in tile_ids for k in range(len(self.tiles[ti].pieces))]
        if owners:
            P0 = np.array([self.tiles[ti].pieces[k][0] for ti, k in owners])
            P1 = np.array([self.tiles[ti].pieces[k][1] for ti, k in owners])
            found_p, vmax = self._line_extrema(P0, P1, True)
            top = max(top, vmax)
            for r, s, v in found_p:
                ti, k = owners[r]
                self.tiles[ti].piece_extrema.setdefault(k, []).append(s)
                top = max(top, v)
        return top

    def _line_extrema(self, A: np.ndarray, B: np.ndarray, on_line: bool) -> tuple[list[tuple[int, float, float]], float]:
        """Local extrema of the irradiance along segments `A -> B (n, 2)`: 9 samples each, a
        golden-section search around each discrete extremum. Returns (row, parameter, max channel
        value) for the extrema strictly inside their segment, and the largest value sampled."""
        fr = np.linspace(0.0, 1.0, 9)
        if A.shape[0] == 0:
            return [], 0.0
        pts = (A[:, None, :] + fr[None, :, None] * (B - A)[:, None, :]).reshape(-1, 2)
        if on_line:
            self.eval.mark(pts)
        v = self.eval(pts).reshape(A.shape[0], 9, 3)
        out: list[tuple[int, float, float]] = []
        lum = v.sum(axis=2)
        rows, a_s, b_s, sg = [], [], [], []
        for sgn in (1.0, -1.0):
            x = sgn * lum
            hit = (x[:, 1:-1] > x[:, :-2]) & (x[:, 1:-1] > x[:, 2:]) & (lum[:, 1:-1] > 0)
            for r, j in zip(*np.nonzero(hit), strict=True):
                rows.append(r)
                a_s.append(fr[j])
                b_s.append(fr[j + 2])
                sg.append(sgn)
        if rows:
            Ar, Br = A[rows], B[rows]

            def along(tr: np.ndarray) -> np.ndarray:
                r = tr[:, 1].astype(int)
                q = Ar[r] + tr[:, :1] * (Br[r] - Ar[r])
                if on_line:
                    self.eval.mark(q)
                return self.eval.luminance(q)

            t, _ = ex.golden_section(along, np.array(a_s), np.array(b_s), np.array(sg))
            val = self.eval(Ar + t[:, None] * (Br - Ar)).max(axis=1)
            for r, ti, a0, b0, vv in zip(rows, t, a_s, b_s, val, strict=True):
                if a0 + 1e-6 < ti < b0 - 1e-6:
                    out.append((int(r), float(ti), float(vv)))
        return out, float(v.max())

    # ------------------------------------------------------------------ refinement
    def _threshold(self) -> float:
        return ESTIMATE_MARGIN * self.tol * float(self.scale)

    def _refine_edges(self, keys: list[tuple[int, int]]) -> None:
        thr = self._threshold()
        params: dict[tuple[int, int], np.ndarray] = {}
        for key in keys:
            e = self.edges[key]
            on = [s for s, _, vis in e.cross.values() if vis]
            self.eval.mark(e.point(np.array(on)))
            params[key] = np.unique(np.array([0.0, 1.0] + on + self._edge_extrema.get(key, [])))
        active = list(keys)
        while active:
            if _DEBUG:
                print("edges", len(active), sum(params[k].size for k in active))
            quarter = np.array([0.25, 0.5, 0.75])
            pts, owners = [], []
            for key in active:
                s = params[key]
                probe = s[:-1, None] + quarter[None, :] * np.diff(s)[:, None]
                pts.append(probe.ravel())
                owners.append(key)
            # Evaluate vertices and probes of all active edges in one call.
            allp = np.concatenate([self.edges[k].point(np.concatenate([params[k], p])) for k, p in zip(owners, pts, strict=True)])
            self.eval(allp)
            nxt = []
            for key, probe in zip(owners, pts, strict=True):
                e, s = self.edges[key], params[key]
                ve = self.eval(e.point(s))
                vp = self.eval(e.point(probe)).reshape(s.size - 1, 3, 3)
                w = quarter[None, :, None]
                interp = (1 - w) * ve[:-1, None, :] + w * ve[1:, None, :]
                err = np.abs(vp - interp).max(axis=2)  # (intervals, 3)
                length = np.diff(s) * np.linalg.norm(e.b - e.a)
                bad = (err.max(axis=1) > thr) & (length > self.min_edge)
                if np.any(bad):
                    worst = np.argmax(err[bad], axis=1)
                    new = probe.reshape(-1, 3)[bad][np.arange(worst.size), worst]
                    params[key] = np.unique(np.concatenate([s, new]))
                    nxt.append(key)
            active = nxt
        for key in keys:
            self.edges[key].s = params[key]

    def _tile_pslg(self, t: _Tile) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        verts: list[np.ndarray] = []
        for ga, gb, rev in t.edge_keys():
            e = self.edges[(ga, gb)]
            p = e.point(e.s)
            p[0], p[-1] = e.a, e.b
            verts.extend((p[::-1] if rev else p)[:-1])
        nb = len(verts)
        segs = [[k, (k + 1) % nb] for k in range(nb)]
        marks = [1] * nb
        index = {(float(p[0]), float(p[1])): k for k, p in enumerate(verts)}

        def vid(p: np.ndarray) -> int:
            key = (float(p[0]), float(p[1]))
            if key not in index:
                index[key] = len(verts)
                verts.append(p)
            return index[key]

        lines = []
        for k, (p0, p1) in enumerate(t.pieces):
            ts = sorted(t.piece_extrema.get(k, []))
            chain = [p0] + [p0 + tk * (p1 - p0) for tk in ts] + [p1]
            lines.extend(zip(chain[:-1], chain[1:], strict=True))
        bverts = np.array(verts)
        snap = 1e-10 * self.diam
        for q0, q1 in _noded(lines):
            ends = []
            for q in (q0, q1):
                d = np.abs(bverts - q).max(axis=1)
                j = int(np.argmin(d))
                ends.append(j if d[j] <= snap else vid(q))
            if ends[0] != ends[1]:
                segs.append(ends)
                marks.append(0)
        for p in t.extrema:
            vid(p)
        return np.array(verts), np.array(segs), np.array(marks)

    def _refine_tiles(self, tile_ids: list[int]) -> None:
        thr = self._threshold()
        state = {}
        on_tol = 1e-11 * self.diam
        for ti in tile_ids:
            v, s, m = self._tile_pslg(self.tiles[ti])
            s, m = _split_at(v, s, m, np.arange(v.shape[0]), on_tol)
            state[ti] = (v, s, m)
        active = list(tile_ids)
        rounds = 0
        tried: dict[int, set] = {}
        while active:
            rounds += 1
            if _DEBUG:
                print("round", rounds, len(active), sum(state[ti][0].shape[0] for ti in active))
            meshes = {}
            probes = []
            for ti in active:
                v, s, m = state[ti]
                out, dropped = _triangulate(v, s, m)
                self.stats["cdt_fallbacks"] = self.stats.get("cdt_fallbacks", 0) + int(dropped)
                tv, tt = out["vertices"], out["triangles"]
                meshes[ti] = out
                inner_seg = out["segments"][out["segment_markers"].ravel() == 0]
                if inner_seg.size:
                    self.eval.mark(tv[inner_seg.ravel()])
                    self.eval.mark(0.5 * (tv[inner_seg[:, 0]] + tv[inner_seg[:, 1]]))
                c = tv[tt]  # (T, 3, 2)
                mids = 0.5 * (c + np.roll(c, -1, axis=1))  # edges (0,1), (1,2), (2,0)
                inner = np.einsum("ij,tjk->tik", _INNER, c)
                probes.append(tv)
                probes.append(np.concatenate([mids, c.mean(axis=1, keepdims=True), inner], axis=1).reshape(-1, 2))
            self.eval(np.concatenate(probes))
            total = sum(meshes[ti]["vertices"].shape[0] for ti in meshes) + sum(
                self.tiles[ti].verts.shape[0] for ti in range(len(self.tiles))
                if self.tiles[ti].verts is not None and ti not in meshes)
            budget = total < self.max_vertices
            nxt = []
            for ti in active:
                out = meshes[ti]
                tv, tt = out["vertices"], out["triangles"]
                segs = out["segments"]
                smark = out["segment_markers"].ravel()
                c = tv[tt]
                ve = self.eval(tv)
                vt = ve[tt]  # (T, 3, 3)
                mids = 0.5 * (c + np.roll(c, -1, axis=1))
                inner = np.einsum("ij,tjk->tik", _INNER, c)
                pts = np.concatenate([mids, c.mean(axis=1, keepdims=True), inner], axis=1)  # (T, 7, 2)
                interp = np.concatenate([0.5 * (vt + np.roll(vt, -1, axis=1)), vt.mean(axis=1, keepdims=True),
                                         np.einsum("ij,tjk->tik", _INNER, vt)], axis=1)
                err = np.abs(self.eval(pts.reshape(-1, 2)).reshape(pts.shape[0], 7, 3) - interp).max(axis=2)
                edge_ij = np.stack([tt, np.roll(tt, -1, axis=1)], axis=-1)  # (T, 3, 2)
                kind = _edge_kinds(edge_ij, segs, smark, tv.shape[0])
                longest = np.linalg.norm(c - np.roll(c, -1, axis=1), axis=2).max(axis=1)
                sel_err = err.copy()
                sel_err[:, :3][kind == 1] = -1.0  # never insert on the tile boundary
                bad = (err.max(axis=1) > thr) & (longest > self.min_edge) & (sel_err.max(axis=1) > thr)
                t = self.tiles[ti]
                if not np.any(bad) or not budget:
                    t.verts, t.tris, t.values = tv, tt, ve
                    t.error = float(err.max()) if err.size else 0.0
                    continue
                if _DEBUG and rounds > 12:
                    k = np.argmax(err.max(axis=1))
                    print("tile", ti, "worst", c[k].tolist(), err[k].tolist(), "n bad", bad.sum(), "vals", vt[k].tolist())
                worst = np.argmax(sel_err[bad], axis=1)
                newp = pts[bad][np.arange(worst.size), worst]
                on_edge = worst < 3
                seg_split = {}
                edge_of = edge_ij[bad][np.arange(worst.size), np.minimum(worst, 2)]
                nv = tv.shape[0]
                add: dict[tuple[float, float], int] = {}
                seen = tried.setdefault(ti, set())
                for p, oe, (i, j), kd in zip(newp, on_edge, edge_of.tolist(),
                                             kind[bad][np.arange(worst.size), np.minimum(worst, 2)], strict=True):
                    key = (float(p[0]), float(p[1]))
                    if key in add or key in seen:  # inserted before and not kept by Triangle
                        if _DEBUG and key in seen and key not in add:
                            import pickle
                            with open(f"/tmp/stuck_{ti}.pkl", "wb") as fh:
                                pickle.dump((state[ti], key, tv, tt, segs, smark), fh)
                        continue
                    seen.add(key)
                    add[key] = nv + len(add)
                    if oe and kd == 0:
                        seg_split[(min(i, j), max(i, j))] = add[key]
                if not add or rounds >= MAX_ROUNDS:
                    t.verts, t.tris, t.values = tv, tt, ve
                    t.error = float(err.max())
                    continue
                new_v = np.concatenate([tv, np.array(list(add), np.float64).reshape(-1, 2)])
                new_s, new_m = [], []
                for (i, j), mk in zip(segs.tolist(), smark.tolist(), strict=True):
                    mid = seg_split.get((min(i, j), max(i, j)))
                    if mid is None:
                        new_s.append([i, j])
                        new_m.append(mk)
                    else:
                        new_s.extend([[i, mid], [mid, j]])
                        new_m.extend([mk, mk])
                new_s2, new_m2 = _split_at(new_v, np.array(new_s), np.array(new_m), np.arange(nv, new_v.shape[0]), on_tol)
                state[ti] = (new_v, new_s2, new_m2)
                nxt.append(ti)
            active = nxt
        self.stats["rounds"] = max(self.stats.get("rounds", 0), rounds)

    # ------------------------------------------------------------------ driver
    def build(self, tile_ids: list[int], edge_keys: list[tuple[int, int]]) -> None:
        """Mesh tiles `tile_ids`, after refining edges `edge_keys` (the other edges of those tiles
        keep their vertices)."""
        t0 = time.perf_counter()
        for ti in tile_ids:
            self.tiles[ti].faces = self._tile_faces(self.tiles[ti])
        around = sorted({(ga, gb) for ti in tile_ids for ga, gb, _ in self.tiles[ti].edge_keys()} | set(edge_keys))
        self._prepare_edges(around)
        for ti in tile_ids:
            self._prepare_tile(ti)
        t1 = time.perf_counter()
        top = self._find_extrema(tile_ids, edge_keys)
        if self.scale is None:
            self.scale = top if top > 0 else 1.0
        t2 = time.perf_counter()
        self._refine_edges(edge_keys)
        self._refine_tiles(tile_ids)
        t3 = time.perf_counter()
        self.stats.update(
            lines_seconds=t1 - t0, extrema_seconds=t2 - t1, refine_seconds=t3 - t2,
            evaluations=self.eval.evaluations, evaluation_seconds=self.eval.seconds,
            tiles_meshed=len(tile_ids), edges_refined=len(edge_keys),
            segments=0 if self.seg is None else len(self.seg),
            pieces=sum(len(self.tiles[ti].pieces) for ti in tile_ids),
            extrema=sum(self.tiles[ti].extrema.shape[0] + sum(map(len, self.tiles[ti].piece_extrema.values())) for ti in tile_ids)
            + sum(len(v) for v in self._edge_extrema.values()),
            repairs=self.eval.repairs,
        )

    def assemble(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        vs = [t.verts for t in self.tiles]
        off = np.cumsum([0] + [v.shape[0] for v in vs])
        allv = np.concatenate(vs)
        allval = np.concatenate([t.values for t in self.tiles])
        tris = np.concatenate([t.tris + o for t, o in zip(self.tiles, off[:-1], strict=True)])
        uniq, first, inv = np.unique(allv, axis=0, return_index=True, return_inverse=True)
        inv = inv.ravel()
        err = max(t.error for t in self.tiles) / float(self.scale)
        return self.frame.to3d(uniq), inv[tris], allval[first], err


def _jax_gradient(scene: Scene, frame: ev.Frame, evaluator: _Evaluator) -> ex.Gradient:
    """Value (host engine) and exact gradient (`jax.grad` of the traced irradiance) of the
    luminance at 2-D receiver points; one compilation per power-of-two batch size."""
    import jax
    import jax.numpy as jnp

    nrm = jnp.asarray(frame.normal)

    @jax.jit
    def grad3(p3: Any, sc: Scene) -> Any:
        return jax.grad(lambda q: jnp.sum(irradiance(sc, q, jnp.broadcast_to(nrm, q.shape))))(p3)

    def vg(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = xy.shape[0]
        size = max(8, 1 << (n - 1).bit_length())
        pad = np.concatenate([xy, np.repeat(xy[:1], size - n, axis=0)])
        g3 = np.asarray(grad3(jnp.asarray(frame.to3d(pad)), scene))[:n]
        return evaluator.luminance(xy), np.stack([g3 @ frame.u, g3 @ frame.w], axis=1)

    return vg


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
      to `scale` (each element checked at seven points against exact values).
    - `scale`: the irradiance `tol` is relative to (W/m^2): the receiver's maximum found by the
      extremum search, unless given.
    - `tol`: the requested relative tolerance.
    - `stats`: counts and timings (lines, extrema, evaluations, tiles re-meshed by an update).
    """

    def __init__(self, builders: list[_Builder], tol: float, stats: dict[str, Any]):
        self._builders = builders
        parts = [b.assemble() for b in builders]
        off = np.cumsum([0] + [p[0].shape[0] for p in parts])
        self.vertices = np.concatenate([p[0] for p in parts])
        self.triangles = np.concatenate([p[1] + o for p, o in zip(parts, off[:-1], strict=True)])
        self.irradiance = np.concatenate([p[2] for p in parts])
        self.max_error_estimate = max(p[3] for p in parts)
        self.scale = max(float(b.scale) for b in builders)
        self.tol = float(tol)
        self.stats = stats

    def __repr__(self) -> str:
        return (f"IlluminationMesh({self.vertices.shape[0]} vertices, {self.triangles.shape[0]} triangles, "
                f"tol={self.tol:g}, max_error_estimate={self.max_error_estimate:.3g}, scale={self.scale:.4g})")

    def interpolate(self, points: Any) -> np.ndarray:
        """Linear interpolation of the vertex irradiance at `points (N, 3)` on a single-polygon
        receiver (projected onto its plane): `(N, 3)`, NaN outside the receiver."""
        if len(self._builders) != 1:
            raise ValueError("IlluminationMesh.interpolate: only for a single receiver polygon.")
        b = self._builders[0]
        return _interpolate(b.frame.to2d(self.vertices), self.triangles, self.irradiance,
                            b.frame.to2d(np.asarray(points, np.float64).reshape(-1, 3)))

    def update(self, scene: Scene) -> IlluminationMesh:
        """The mesh of the same receiver in `scene`, where only occluders changed (moved, added or
        removed): only the tiles that the changed occluders' shadow volumes can reach, before or
        after the change, are meshed again (Chrysanthou & Slater §3); the others are kept as they
        are. The result equals `illumination_mesh(scene, receiver, tol, scale=self.scale)` with the
        same settings. `stats["tiles_meshed"]` says how many tiles were redone.

        Raises `ValueError` if the lights or ambient changed (re-mesh instead)."""
        t0 = time.perf_counter()
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
        return IlluminationMesh(out, self.tol, stats)

    def save(self, path: Any) -> None:
        """Write the mesh as PLY (vertex colours and the float irradiance as vertex properties) or
        glTF (`.gltf`/`.glb`, vertex colours), by the file's extension (`_illumination_io`)."""
        from ._illumination_io import save_mesh

        save_mesh(self, path)


def _interpolate(xy: np.ndarray, tris: np.ndarray, values: np.ndarray, q: np.ndarray, bins: int = 64) -> np.ndarray:
    """Piecewise-linear interpolation on a 2-D triangle mesh at points `q (N, 2)` (NaN outside):
    triangles binned by their bounding boxes on a grid, barycentric tests per bin."""
    out = np.full((q.shape[0], values.shape[1]), np.nan)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    cell = (hi - lo) / bins * (1 + 1e-12) + 1e-300
    c = xy[tris]
    tlo = np.floor((c.min(axis=1) - lo) / cell).astype(int).clip(0, bins - 1)
    thi = np.floor((c.max(axis=1) - lo) / cell).astype(int).clip(0, bins - 1)
    qb = np.floor((q - lo) / cell).astype(int)
    inside = np.all((qb >= 0) & (qb < bins), axis=1)
    members: dict[int, list[int]] = {}
    for t in range(tris.shape[0]):
        for i in range(tlo[t, 0], thi[t, 0] + 1):
            for j in range(tlo[t, 1], thi[t, 1] + 1):
                members.setdefault(i * bins + j, []).append(t)
    key = np.where(inside, qb[:, 0] * bins + qb[:, 1], -1)
    order = np.argsort(key, kind="stable")
    ks, starts = np.unique(key[order], return_index=True)
    ends = np.append(starts[1:], order.size)
    for k, a, e in zip(ks, starts, ends, strict=True):
        if k < 0 or k not in members:
            continue
        qi = order[a:e]
        ts = np.array(members[k])
        p0, p1, p2 = c[ts, 0], c[ts, 1], c[ts, 2]
        det = (p1[:, 0] - p0[:, 0]) * (p2[:, 1] - p0[:, 1]) - (p2[:, 0] - p0[:, 0]) * (p1[:, 1] - p0[:, 1])
        ok = np.abs(det) > 0
        ts, p0, p1, p2, det = ts[ok], p0[ok], p1[ok], p2[ok], det[ok]
        d = q[qi][:, None, :] - p0[None]
        l1 = (d[..., 0] * (p2[:, 1] - p0[:, 1]) - d[..., 1] * (p2[:, 0] - p0[:, 0])) / det
        l2 = ((p1[:, 0] - p0[:, 0]) * d[..., 1] - (p1[:, 1] - p0[:, 1]) * d[..., 0]) / det
        l0 = 1 - l1 - l2
        eps = 1e-12
        hit = (l0 >= -eps) & (l1 >= -eps) & (l2 >= -eps)
        any_hit = hit.any(axis=1)
        first = np.argmax(hit, axis=1)
        r = np.arange(qi.size)
        tt = tris[ts[first]]
        val = (l0[r, first, None] * values[tt[:, 0]] + l1[r, first, None] * values[tt[:, 1]]
               + l2[r, first, None] * values[tt[:, 2]])
        out[qi[any_hit]] = val[any_hit]
    return out


def _same_lights(a: Scene, b: Scene) -> bool:
    from ._scene import light_to_dict

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
    nb._load_scene(scene)
    fo, fn = _face_rows(old.scene), _face_rows(scene)
    ko = max(fo.shape[1], fn.shape[1])
    pad = lambda f: np.concatenate([f, np.repeat(f[:, :1], ko - f.shape[1], axis=1)], axis=1)  # noqa: E731
    ro = {r.tobytes() for r in pad(fo)} if fo.shape[0] else set()
    rn = {r.tobytes() for r in pad(fn)} if fn.shape[0] else set()
    gone = [i for i, r in enumerate(pad(fo)) if r.tobytes() not in rn] if fo.shape[0] else []
    new = [i for i, r in enumerate(pad(fn)) if r.tobytes() not in ro] if fn.shape[0] else []
    boxes = np.concatenate([old.foot[gone], nb.foot[new]]) if (gone or new) else np.zeros((0, 4))
    boxes = boxes[np.all(np.isfinite(boxes), axis=1)]
    margin = 1e-6 * old.diam
    tile_ids = [ti for ti, t in enumerate(nb.tiles) if boxes.size and np.any(ev.boxes_overlap(boxes, t.lo, t.hi, margin))]
    edge_keys = [k for k, e in nb.edges.items()
                 if boxes.size and np.any(ev.boxes_overlap(boxes, np.minimum(e.a, e.b), np.maximum(e.a, e.b), margin))]
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


def _merged_stats(builders: list[_Builder]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for b in builders:
        for k, v in b.stats.items():
            out[k] = out.get(k, 0) + v if isinstance(v, (int, float)) and k != "rounds" else v
    return out


GRADIENTS = ("auto", "jax", "differences")


def illumination_mesh(scene: Scene, receiver: Any, tol: float = 1e-3, *, max_vertices: int = 2_000_000,
                      tile_size: float | None = None, min_edge: float | None = None, gradient: str = "auto",
                      scale: float | None = None) -> IlluminationMesh:
    r"""An adaptive, discontinuity-aware mesh of `receiver` with exact irradiance at its vertices.

    Linear interpolation of the vertex irradiance over each triangle stays within `tol` times the
    receiver's maximum irradiance, as checked against exact values at seven points per triangle
    (with a safety factor `ESTIMATE_MARGIN`); the shadows' discontinuity lines (VE and EV events
    of the polygon and linear lights, Campbell & Fussell's extremal planes) are mesh edges and the
    illumination's local extrema (found by optimisation, §3.3) are vertices. See the module
    docstring for the method and `IlluminationMesh.update` for moving occluders.

    **Arguments:**

    - `scene`: a `Scene` (any lights; shadows exact).
    - `receiver`: a planar convex polygon `(k, 3)` (m), counter-clockwise seen from its lit side
      (the side its right-hand-rule normal points to), or a `Mesh` or list of such polygons (each
      face meshed on its own; vertices are not shared between faces).
    - `tol`: relative tolerance in (0, 1): interpolation error over the receiver's maximum.
    - `max_vertices`: stop refining once the mesh has this many vertices (then
      `max_error_estimate` may exceed `tol`).
    - `tile_size`: side of the tiles the receiver is cut into (m); default 1/16 of its extent.
    - `min_edge`: elements smaller than this are not split (m); default 1e-6 of the extent. Value
      discontinuities (hard shadows of point lights, occluders touching the receiver) cannot be
      interpolated within `tol`; they stop here and show in `max_error_estimate`.
    - `gradient`: how the extremum search differentiates: `"jax"` (`jax.grad` of the traced
      irradiance, exact; compiles the device kernel, for scenes with few occluder faces),
      `"differences"` (central differences of exact values), `"auto"` (`"jax"` up to
      `JAX_GRADIENT_MAX_FACES` occluder faces).
    - `scale`: the irradiance (W/m^2) `tol` is relative to; default the receiver's maximum.

    **Returns:** `IlluminationMesh` with `vertices (V, 3)`, `triangles (T, 3)`, `irradiance (V, 3)`,
    `max_error_estimate`, `scale`, `stats`.
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
        import triangle  # noqa: F401
    except ImportError:
        raise ImportError("illumination_mesh needs the 'triangle' package: pip install 'jaxshadow[mesh]'") from None
    from ._mesh import Mesh

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
        b.build(list(range(len(b.tiles))), list(b.edges))
        builders.append(b)
    if scale is None and len(builders) > 1:
        top = max(float(b.scale) for b in builders)
        for b in builders:  # one scale for the whole receiver: refine the faces with a lower one again
            if float(b.scale) < top:
                b.scale = top
        # (refinement is monotone: faces meshed with a smaller scale already meet the larger one)
    stats = {"seconds": time.perf_counter() - t0, "tiles": sum(len(b.tiles) for b in builders), **_merged_stats(builders)}
    return IlluminationMesh(builders, float(tol), stats)
