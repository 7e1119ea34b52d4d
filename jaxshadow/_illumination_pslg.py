"""2-D machinery of the illumination meshes (`_illumination`): the receiver's tiles and their
shared edges, the exact-irradiance evaluator, constrained Delaunay triangulation (PythonCDT)
with the clean-up it needs, and piecewise-linear interpolation on the result."""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import _illumination_events as ev
from ._scene import DirectionalLight, LinearLight, PointLight, PolygonLight, Scene
from ._shade import irradiance

ON_LINE_STEP = 1e-9
GRID_SHIFT = (np.sqrt(2.0) - 1) / 10
MIN_BATCH = 256  # smallest batch handed to the engine


class _Evaluator:
    """Exact irradiance at 2-D receiver points, cached by coordinates, batched per call.

    Points on a discontinuity line (`mark`) are also evaluated `ON_LINE_STEP` (of the receiver's
    size) to either side along a fixed oblique direction: the host engine can return the
    unoccluded value at a point exactly on an umbra boundary (an EV plane; see
    `tests/test_illumination_mesh.py::test_engine_on_event_plane`), and where the value at the
    point is not between its neighbours' (with a slack far above a kink's) their mean is used
    (`repairs` counts these; the irradiance is continuous there, so the mean is within
    `ON_LINE_STEP` times the gradient of the exact value).

    The cache maps a point's coordinates, as the Python complex `x + iy` (exact, hashed without
    building tuples), to a row of one growing value array; each row also records where it was
    evaluated and whether with the on-line check, so that an update (`inherit`) can take over the
    rows of the previous scene whose value the change cannot affect: a point asked for again
    with the same evaluation takes the old row instead of calling the engine (`reused`).

    A point needs evaluating when it is not cached, or when it was marked on a line after its
    value was computed without the on-line check (or moved: then it leaves the cache); the
    latter are kept in `pending`, so that finding them (`stale`) looks at those few keys rather
    than at every point. Batches are padded to a power of two with rows whose normal faces away
    from every light (the engine gives them 0 without clipping), not with copies of real points."""

    def __init__(self, scene: Scene, frame: ev.Frame, size: float):
        self.scene, self.frame = scene, frame
        self.cache: dict[complex, int] = {}
        self.values = np.zeros((1024, 3))
        self.targets = np.zeros(1024, np.complex128)  # per row: the point evaluated (`move`)
        self.lined = np.zeros(1024, bool)  # per row: evaluated with the on-line check
        self.succ: dict[int, int] = {}  # row -> the row of the point's next evaluation (`follow`)
        self._succ_sorted: tuple[np.ndarray, np.ndarray] | None = None
        self._rows = 0
        self.prior: dict[complex, int] | None = None  # an earlier scene's rows (`inherit`)
        self.prior_ok = np.zeros(0, bool)
        self.first_row = 0
        self.reused = 0
        self.kept = self.affected = 0  # earlier values taken over / that the change can affect (`inherit`)
        self.online: set[complex] = set()
        self.moved: dict[complex, complex] = {}  # points evaluated elsewhere (`move`)
        self.checked: set[complex] = set()
        self.pending: set[complex] = set()  # cached keys to evaluate again: `online` and not `checked`
        self.dropped: dict[complex, int] = {}  # keys evaluated (their row), then moved, not evaluated since
        self.away = _away_normal(scene, frame)
        self.step = ON_LINE_STEP * size * np.array([np.cos(0.6180339887), np.sin(0.6180339887)])
        self.evaluations = 0
        self.repairs = 0
        self.seconds = 0.0

    @staticmethod
    def _keys(xy: np.ndarray) -> list[complex]:
        xy = np.ascontiguousarray(np.asarray(xy, np.float64).reshape(-1, 2))
        return xy.view(np.complex128).ravel().tolist()  # type: ignore[no-any-return]

    def mark(self, xy: np.ndarray) -> None:
        """Declare points `(n, 2)` to lie on discontinuity lines."""
        keys = set(self._keys(xy))
        self.online |= keys
        keys -= self.checked
        if keys:  # cached without the check: pending (the others get it when first evaluated)
            cache = self.cache
            self.pending.update(k for k in keys if k in cache)

    def move(self, xy: np.ndarray, to: np.ndarray) -> None:
        """Evaluate points `xy (n, 2)` at `to (n, 2)` instead (a point on the edge of a hole takes
        the value just outside it)."""
        for a, b in zip(self._keys(xy), self._keys(to), strict=True):
            if a not in self.moved:
                self.moved[a] = b
                r = self.cache.pop(a, None)
                if r is not None:
                    self.dropped[a] = r

    def _lookup(self, keys: list[complex]) -> tuple[np.ndarray, np.ndarray]:
        """Per key its cached row (-1 when none) and whether it needs evaluating."""
        n = len(keys)
        rows = np.fromiter(map(self.cache.get, keys, itertools.repeat(-1, n)), np.int64, n)
        need = rows < 0
        if self.pending:
            need |= np.isin(np.array(keys, np.complex128), np.fromiter(self.pending, np.complex128, len(self.pending)))
        return rows, need

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        """Exact irradiance `(n, 3)` at points `xy (n, 2)`."""
        rows = self.row_of(xy)  # (first: it may grow the arrays)
        return self.values[rows]

    def _settle(self, keys: list[complex], rows: np.ndarray) -> None:
        """Keys `keys` now have rows `rows`: the rows they had before (pending or moved keys:
        the log, not every key, is searched) lead to the new ones (`follow`), and they leave
        the log."""
        if not self.pending and not self.dropped:
            return
        index = dict(zip(keys, range(len(keys)), strict=True))
        cache, dropped = self.cache, self.dropped
        for k in [k for k in self.pending if k in index] + [k for k in dropped if k in index]:
            old = cache.get(k, dropped.get(k, -1))
            new = int(rows[index[k]])
            if old >= 0 and old != new:
                self.succ[old] = new
                self._succ_sorted = None
            dropped.pop(k, None)

    def follow(self, rows: np.ndarray) -> np.ndarray:
        """The rows now holding the points whose values were at `rows` (a point evaluated again,
        moved or checked on a line, has a new row)."""
        rows = np.asarray(rows, np.int64)
        if not self.succ:
            return rows
        if self._succ_sorted is None:
            k = np.fromiter(self.succ.keys(), np.int64, len(self.succ))
            v = np.fromiter(self.succ.values(), np.int64, len(self.succ))
            o = np.argsort(k)
            self._succ_sorted = (k[o], v[o])
        ks, vs = self._succ_sorted
        while rows.size:
            pos = np.minimum(np.searchsorted(ks, rows), ks.size - 1)
            hit = ks[pos] == rows
            if not np.any(hit):
                break
            rows = np.where(hit, vs[pos], rows)
        return rows

    def row_of(self, xy: np.ndarray) -> np.ndarray:
        """The value rows `(n,)` of points `xy (n, 2)`, evaluated first where needed."""
        keys = self._keys(xy)
        cache, online, checked = self.cache, self.online, self.checked
        rows, need = self._lookup(keys)
        todo = list(dict.fromkeys(itertools.compress(keys, need))) if need.any() else []
        if todo and self.prior is not None:
            todo = self._take_prior(todo)
        if todo:
            tgt = list(map(self.moved.get, todo, todo))
            pts = np.array(tgt, np.complex128).view(np.float64).reshape(-1, 2)
            line = np.fromiter(map(online.__contains__, todo), bool, len(todo))
            side = pts[line]
            allp = np.concatenate([pts, side + self.step, side - self.step])
            t0 = time.perf_counter()
            # Padded to a power of two: the engine compiles per batch shape.
            n_all = allp.shape[0]
            size = max(MIN_BATCH, 1 << (n_all - 1).bit_length())
            p3 = self.frame.to3d(np.concatenate([allp, np.repeat(allp[:1], size - n_all, axis=0)]))
            nrm = np.empty_like(p3)
            nrm[:n_all] = self.frame.normal
            nrm[n_all:] = self.frame.normal if self.away is None else self.away
            e = np.asarray(irradiance(self.scene, p3, nrm), np.float64)[:n_all]
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
            start = self._rows  # rows are never reused (a key dropped by `move` leaves its row behind)
            self._grow(start + n)
            self.values[start:start + n] = val
            self.targets[start:start + n] = tgt
            self.lined[start:start + n] = line
            self._settle(todo, np.arange(start, start + n))
            cache.update(zip(todo, range(start, start + n), strict=True))
            self._rows = start + n
            lined = list(itertools.compress(todo, line))
            checked.update(lined)
            self.pending.difference_update(lined)
        if need.any():
            rows[need] = np.fromiter(map(cache.__getitem__, itertools.compress(keys, need)), np.int64, int(need.sum()))
        return rows

    def stale(self, xy: np.ndarray) -> np.ndarray:
        """`(n,)` bool: whether points `xy (n, 2)`, all evaluated before, would be evaluated again
        by the next call: those marked on a line since, or moved since (the log of both, not a
        look-up of every point)."""
        log = self.pending | self.dropped.keys()
        if not log:
            return np.zeros(xy.shape[0], bool)
        keys = np.ascontiguousarray(np.asarray(xy, np.float64).reshape(-1, 2)).view(np.complex128).ravel()
        return np.isin(keys, np.fromiter(log, np.complex128, len(log)))

    def _grow(self, rows: int, spare: float = 1.0) -> None:
        """Room for `rows` rows, and `spare` times as many again when the arrays must grow."""
        if rows <= self.values.shape[0]:
            return
        size = max(int(rows * (1 + spare)), 1024)
        for name in ("values", "targets", "lined"):
            a = getattr(self, name)
            b = np.zeros((size,) + a.shape[1:], a.dtype)
            b[:self._rows] = a[:self._rows]
            setattr(self, name, b)

    def _take_prior(self, todo: list[complex]) -> list[complex]:
        """Point the keys `todo` whose evaluation (the same point, with the on-line check or
        without) is a kept row of the earlier scene at that row; return the others."""
        prior = self.prior
        assert prior is not None
        if self.prior_ok.size == 0:
            return todo
        n = len(todo)
        r = np.fromiter(map(prior.get, todo, itertools.repeat(-1, n)), np.int64, n)
        hit = r >= 0
        if not np.any(hit):
            return todo
        online, moved = self.online, self.moved
        cand = list(itertools.compress(todo, hit))  # keys with an earlier row: the same evaluation?
        m, rr = len(cand), r[hit]
        tgt = np.fromiter(map(moved.get, cand, cand), np.complex128, m) if moved else np.array(cand, np.complex128)
        line = np.fromiter(map(online.__contains__, cand), bool, m)
        same = self.prior_ok[rr] & (self.targets[rr] == tgt) & (self.lined[rr] == line)
        if not np.any(same):
            return todo
        take = hit.copy()
        take[hit] = same
        keys = list(itertools.compress(cand, same))
        self._settle(keys, rr[same])
        self.cache.update(zip(keys, rr[same].tolist(), strict=True))
        lined = list(itertools.compress(keys, line[same]))
        self.checked.update(lined)
        self.pending.difference_update(lined)
        self.reused += len(keys)
        return list(itertools.compress(todo, ~take))

    def rows(self) -> tuple[dict[complex, int], np.ndarray]:
        """Every key evaluated so far or taken over (`inherit`), with its row, and which rows hold
        a value of the current scene."""
        valid = np.zeros(self._rows, bool)
        valid[self.first_row:] = True
        if self.prior is None:
            return self.cache, valid
        valid[:self.first_row] = self.prior_ok[:self.first_row]
        merged = dict(self.prior)
        merged.update(self.cache)
        return merged, valid

    def positions(self, rows: int) -> np.ndarray:
        """The points `(rows, 2)` evaluated by the first `rows` rows (with the on-line check also
        `step` to either side)."""
        return self.targets[:rows].view(np.float64).reshape(-1, 2)

    def inherit(self, old: _Evaluator, keep: Any) -> None:
        """Take over the rows of `old` (the evaluator of an earlier scene) for which `keep(points
        (n, 2))` says that the change of scene cannot affect the value at them or within `step`
        of them."""
        index, valid = old.rows()
        n = old._rows
        pts = old.positions(n)
        ok = valid.copy()
        ok[valid] = keep(pts[valid])
        self.kept, self.affected = int(ok.sum()), int(valid.sum() - ok.sum())
        # Copies (the old mesh keeps its evaluator), with room for the update's new rows.
        self.values, self.targets, self.lined = old.values[:0], old.targets[:0], old.lined[:0]
        self._rows = 0
        self._grow(n, spare=0.5)
        self.values[:n], self.targets[:n], self.lined[:n] = old.values[:n], old.targets[:n], old.lined[:n]
        self._rows = self.first_row = n
        self.prior, self.prior_ok = index, ok

    def luminance(self, xy: np.ndarray) -> np.ndarray:
        return self(xy).sum(axis=1)


def _away_normal(scene: Scene, frame: ev.Frame) -> np.ndarray | None:
    """A normal that puts every light of `scene` strictly below the horizon of any point of the
    receiver plane (`-normal` when all lights are above the plane, `normal` when all are below),
    or None when the lights are on both sides."""
    sides = set()
    for light in scene.lights:
        if isinstance(light, DirectionalLight):
            c = float(np.asarray(light.direction, np.float64) @ frame.normal)
            h = np.array([-c])  # light travelling along -normal comes from above
        elif isinstance(light, PolygonLight):
            h = frame.height(np.asarray(light.vertices, np.float64))
        elif isinstance(light, LinearLight):
            h = frame.height(np.stack([np.asarray(light.start, np.float64), np.asarray(light.end, np.float64)]))
        elif isinstance(light, PointLight):
            h = frame.height(np.asarray(light.position, np.float64)[None])
        else:
            return None
        if np.all(h > 0):
            sides.add(1.0)
        elif np.all(h < 0):
            sides.add(-1.0)
        else:
            return None
    if len(sides) != 1:
        return None
    return -sides.pop() * frame.normal


_RADIX = 1 << 21  # vertex indices per tile that `_Checked` can encode


class _Checked:
    """A tile's triangles `tt (T, 3)` over vertices `tv (V, 2)` with what the refinement found
    per triangle (`per`: arrays `(T, ...)`: checked errors, in a hole, at a corner), for the next
    round: `match` finds which of the next triangulation's triangles are the same (the next
    round's vertices start with these, in order) and `take` gives their rows."""

    def __init__(self, tv: np.ndarray, tt: np.ndarray, *per: np.ndarray):
        codes = _tri_codes(tt)
        order = np.argsort(codes)
        self.tv, self.codes, self.per = tv, codes[order], [a[order] for a in per]
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
    """The corners `(n, 2)` of the union of contact polygons `polys`: their vertices and the
    points where edges of two of them cross."""
    if not polys:
        return np.zeros((0, 2))
    a = np.concatenate(polys)
    b = np.concatenate([np.roll(q, -1, axis=0) for q in polys])
    owner = np.repeat(np.arange(len(polys)), [q.shape[0] for q in polys])
    r = b - a
    den = r[:, None, 0] * r[None, :, 1] - r[:, None, 1] * r[None, :, 0]  # (E, E)
    dx = a[None, :, :] - a[:, None, :]  # a_j - a_i
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (dx[..., 0] * r[None, :, 1] - dx[..., 1] * r[None, :, 0]) / den
        u = (dx[..., 0] * r[:, None, 1] - dx[..., 1] * r[:, None, 0]) / den
    hit = (den != 0) & (s >= 0) & (s <= 1) & (u >= 0) & (u <= 1) & (owner[:, None] < owner[None, :])
    i, _ = np.nonzero(hit)
    return np.concatenate([a, a[i] + s[hit][:, None] * r[i]])
