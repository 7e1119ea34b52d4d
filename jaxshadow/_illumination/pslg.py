"""2-D machinery of the illumination meshes (`_illumination`): the receiver's tiles and their
shared edges, constrained Delaunay triangulation (PythonCDT) with the clean-up it needs, and
piecewise-linear interpolation on the result (the exact-irradiance evaluator is
`_illumination_evaluator`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import events as ev

GRID_SHIFT = (np.sqrt(2.0) - 1) / 10
_RADIX = 1 << 21  # vertex indices per tile that `_Checked` can encode


class _Checked:
    """A tile's triangles `tt (T, 3)` over vertices `tv (V, 2)` with what the refinement found
    per triangle (`per`: arrays `(T, ...)`: checked errors, in a hole, at a corner), for the next
    round: `match` finds which of the next triangulation's triangles are the same (the next
    round's vertices start with these, in order) and `take` gives their rows."""

    def __init__(self, tv: np.ndarray, tt: np.ndarray, *per: np.ndarray, side: np.ndarray | None = None):
        codes = _tri_codes(tt)
        order = np.argsort(codes)
        self.tv, self.codes, self.per = tv, codes[order], [a[order] for a in per]
        self.side = side  # anything else the caller keeps beside them (not reordered)
        self._pos = np.zeros(0, np.int64)

    def match(self, tv: np.ndarray, tt: np.ndarray) -> tuple[np.ndarray, int]:
        """`(T,)` bool: which triangles of `tt` over `tv` were checked before, and the number of
        leading vertices of `tv` that are the old ones (0 when they are not)."""
        n = self.tv.shape[0]
        if tv.shape[0] < n or tv.shape[0] >= _RADIX or not np.array_equal(tv[:n], self.tv):
            return np.zeros(tt.shape[0], bool), 0
        codes = _tri_codes(tt)
        pos = np.minimum(np.searchsorted(self.codes, codes), max(self.codes.size - 1, 0))
        hit = (self.codes[pos] == codes) if self.codes.size else np.zeros(tt.shape[0], bool)
        self._pos = pos
        return hit, n

    def take(self, rows: np.ndarray) -> list[np.ndarray]:
        """The stored arrays at the triangles `rows` (a mask at most `match`'s)."""
        return [a[self._pos[rows]] for a in self.per]


def _tri_codes(tt: np.ndarray) -> np.ndarray:
    s = np.sort(tt, axis=1).astype(np.int64)
    return (s[:, 0] * _RADIX + s[:, 1]) * _RADIX + s[:, 2]


@dataclass
class _Edge:
    """A tile edge from global point `ga` to `gb` (`ga < gb`): its crossings with discontinuity
    segments and, once refined, its vertex parameters `s` in [0, 1]."""

    a: np.ndarray
    b: np.ndarray
    cross: dict[int, tuple[float, np.ndarray, bool]] = field(default_factory=dict)
    s: np.ndarray | None = None

    def point(self, s: np.ndarray | float) -> np.ndarray:
        return self.a + np.asarray(s)[..., None] * (self.b - self.a)


@dataclass
class _Tile:
    poly: np.ndarray  # (k, 2) counter-clockwise
    gids: list[int]
    lo: np.ndarray
    hi: np.ndarray
    faces: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    contact: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    contact_pieces: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    pieces: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    extrema: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    piece_extrema: dict[int, list[float]] = field(default_factory=dict)
    verts: np.ndarray | None = None
    tris: np.ndarray | None = None
    values: np.ndarray | None = None
    error: float = 0.0
    corner_error: float = 0.0
    unrefined: int = 0  # elements over the threshold at the minimum edge length
    unrefined_error: float = 0.0  # their largest checked error (W/m^2)

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


def _triangulate(v: np.ndarray, s: np.ndarray, m: np.ndarray, on_tol: float = 0.0) -> tuple[dict, bool]:
    """Constrained Delaunay triangulation of a PSLG whose outer segments (marker 1) bound a convex
    region (artem-ogre's CDT through PythonCDT): the input vertices first, in order, then any
    vertices CDT adds where constrained edges cross; no other Steiner points. Exact duplicate
    vertices are merged first. Vertices within `on_tol` of a constrained edge split it (CDT's
    `min_dist_to_constraint_edge`). Returns `({"vertices": (V, 2), "triangles": (T, 3)
    counter-clockwise, "segments": (S, 2), "segment_markers": (S, 1)}, dropped)`, the segments
    being the constrained edges as split by the triangulation; `dropped` is True when CDT
    rejected the internal segments and they were left out (their vertices kept)."""
    import pythoncdt as cdt

    # Rows as complex numbers: a 1-D unique (the same rows, the same first occurrences).
    key = np.ascontiguousarray(v, np.float64).view(np.complex128).ravel()
    uniq_k, first, inv = np.unique(key, return_index=True, return_inverse=True)
    uniq = uniq_k.view(np.float64).reshape(-1, 2)
    order = np.argsort(first)  # keep the input order (deterministic, boundary first)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    v2 = np.ascontiguousarray(uniq[order], np.float64)
    s2 = rank[inv.ravel()][s]
    keep = s2[:, 0] != s2[:, 1]
    s2, m2 = s2[keep], m[keep]
    _, one = np.unique(np.sort(s2, axis=1), axis=0, return_index=True)
    one = np.sort(one)
    s2, m2 = s2[one], m2[one]

    def run(segs: np.ndarray) -> cdt.Triangulation:
        tri = cdt.Triangulation(cdt.VertexInsertionOrder.AUTO, cdt.IntersectingConstraintEdges.TRY_RESOLVE,
                                float(on_tol))
        tri.insert_vertices(v2)  # type: ignore[call-overload]  # an ndarray is a Buffer
        tri.insert_edges(np.ascontiguousarray(segs, np.uint32))  # type: ignore[call-overload]
        tri.erase_super_triangle()
        return tri

    dropped = False
    try:
        tri = run(s2)
    except (RuntimeError, ValueError):
        dropped = True
        s2, m2 = s2[m2 == 1], m2[m2 == 1]
        tri = run(s2)
    verts = tri.vertices_array().view(np.float64).reshape(-1, 2)
    tris = tri.triangles_array()["vertices"].astype(np.int64).reshape(-1, 3)
    # Each fixed edge takes the marker of the input segment it is (or, when the triangulation
    # split or merged input segments, the largest of those it is a piece of; 0 for none).
    segs = np.array([(e.v1, e.v2) for e in tri.fixed_edges_iter()], np.int64).reshape(-1, 2)
    segs = np.sort(segs, axis=1)
    n = max(int(verts.shape[0]), int(s2.max(initial=0)) + 1)
    sk = np.sort(s2, axis=1).astype(np.int64)
    in_code = sk[:, 0] * n + sk[:, 1]
    order_in = np.argsort(in_code)
    in_code, in_mark = in_code[order_in], m2[order_in].astype(np.int64)

    def marker(codes: np.ndarray) -> np.ndarray:
        pos = np.clip(np.searchsorted(in_code, codes), 0, max(in_code.size - 1, 0))
        hit = (in_code[pos] == codes) if in_code.size else np.zeros(codes.shape, bool)
        return np.where(hit, in_mark[pos] if in_code.size else 0, 0)

    marks = marker(segs[:, 0] * n + segs[:, 1])
    pieces = tri.piece_to_originals
    if pieces:
        at = {(int(a), int(b)): k for k, (a, b) in enumerate(segs.tolist())}
        for e, orig in pieces.items():
            k = at.get((min(e.v1, e.v2), max(e.v1, e.v2)))
            if k is not None:
                oc = np.array([min(o.v1, o.v2) * n + max(o.v1, o.v2) for o in orig], np.int64)
                marks[k] = int(marker(oc).max(initial=0))
    out = {"vertices": verts, "triangles": tris, "segments": segs,
           "segment_markers": marks.astype(np.int64).reshape(-1, 1)}
    return out, dropped


def _split_segments(segs: np.ndarray, marks: np.ndarray, edges: np.ndarray, mids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Segments `segs (S, 2)` (markers `marks (S,)`) with the one on each of `edges (n, 2)` (as
    vertex pairs, either way round) split at vertex `mids (n,)` (the last one given for an edge),
    in order: a split segment `(i, j)` becomes `(i, mid), (mid, j)` in its place."""
    marks = np.asarray(marks).ravel()
    if edges.shape[0] == 0 or segs.shape[0] == 0:
        return segs.reshape(-1, 2).astype(np.int64), marks
    n = int(max(segs.max(), edges.max(), mids.max())) + 1
    code = lambda a, b: np.minimum(a, b).astype(np.int64) * n + np.maximum(a, b)  # noqa: E731
    ec = code(edges[:, 0], edges[:, 1])
    # The last entry per edge wins: unique over the reversed list.
    uc, last = np.unique(ec[::-1], return_index=True)
    um = mids[::-1][last]
    sc = code(segs[:, 0], segs[:, 1])
    pos = np.clip(np.searchsorted(uc, sc), 0, uc.size - 1)
    hit = uc[pos] == sc
    mid = np.where(hit, um[pos], -1)
    cnt = 1 + hit.astype(np.int64)
    at = np.cumsum(cnt) - cnt
    out = np.empty((int(cnt.sum()), 2), np.int64)
    out[at, 0] = segs[:, 0]
    out[at + cnt - 1, 1] = segs[:, 1]
    out[at[hit], 1] = mid[hit]
    out[at[hit] + 1, 0] = mid[hit]
    return out, np.repeat(marks, cnt)


def _split_at(v: np.ndarray, s: np.ndarray, m: np.ndarray, idx: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Split internal segments (markers 0 and 2) at the vertices `idx` that lie on them (within `tol`,
    not at their ends), so that a vertex off a segment by round-off becomes its end point instead of
    a separate vertex beside it (with slivers in between)."""
    if idx.size == 0 or s.size == 0:
        return s, m
    inner = np.nonzero(m != 1)[0]
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
    # Every inner segment becomes the chain start, its vertices in order along it, end; all
    # chains in one array (segment by segment), the pieces its consecutive pairs within a chain.
    r, h = np.nonzero(on)
    order = np.lexsort((t[r, h], r))
    r, h = r[order], h[order]
    hits = np.bincount(r, minlength=inner.size)
    length = hits + 2
    first = np.cumsum(length) - length  # where each chain starts
    nodes = np.empty(int(length.sum()), np.int64)
    nodes[first] = s[inner, 0]
    nodes[first + length - 1] = s[inner, 1]
    rank = np.arange(r.size) - (np.cumsum(hits) - hits)[r]  # position among its segment's hits
    nodes[first[r] + 1 + rank] = idx[h]
    last = np.zeros(nodes.size, bool)
    last[first + length - 1] = True
    pieces = np.stack([nodes[:-1][~last[:-1]], nodes[1:][~last[:-1]]], axis=1)
    outer = m == 1
    out_s = np.concatenate([s[outer].astype(np.int64), pieces]).reshape(-1, 2)
    out_m = np.concatenate([m[outer], np.repeat(m[inner], hits + 1)])
    return out_s, out_m


def _noded(lines: list[tuple[np.ndarray, np.ndarray]]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Segments split where they cross or overlap (GEOS noding through shapely), duplicates
    dropped: collinear overlapping discontinuity lines (parallel occluder and light edges make
    them) would otherwise make the triangulation split nearly collinear segments against each other."""
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


def _contact_corners(polys: list[np.ndarray]) -> np.ndarray:
    """The corners `(n, 2)` of the contact polygons `polys` where the irradiance takes a
    different limit along each direction of approach: their vertices (an object's convex
    corner: its two walls hide a direction-dependent part of the light). A point where edges of
    two polygons cross (overlapping objects) is not one: the open floor there is a wedge under
    two walls that both run on past the point, each hiding, in the limit, every direction on its
    side whatever the direction of approach, so the irradiance has one limit there (its spread
    on rays from the point shrinks with their length: `test_footprint_crossings_are_not_corners`),
    varies on the scale of the distance to the nearest true corner and refines like any other
    point."""
    if not polys:
        return np.zeros((0, 2))
    return np.concatenate(polys)
