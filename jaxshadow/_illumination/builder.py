"""The illumination mesher proper (`_illumination`'s module docstring describes the method):
discontinuity lines per tile, extrema, 1-D refinement of tile edges; the 2-D refinement of the
tiles is `_illumination_refine`."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from .._scene.model import Scene
from .._shading.shade import irradiance
from . import events as ev
from . import extrema as ex
from .evaluator import _Evaluator
from .pslg import (
    _contact_corners,
    _Edge,
    _grid,
    _noded,
    _segment_crossings,
    _Tile,
    _tiles,
)
from .refine import CORNER_SIZE, refine_tiles

ESTIMATE_MARGIN = 0.5  # elements pass when their checked error is below this fraction of tol
DEFAULT_TILES = 16  # tiles along the receiver's longer side
SAMPLES_PER_TILE = 6  # extremum-search grid per tile side
SEGMENT_SAMPLES_PER_TILE = 16  # visibility samples per tile length along a discontinuity line
CONTACT_STEP = 1e-9  # points on a hole's edge take the value this far outside (of the receiver's size)
RELEASE_MIN_ROWS = 1 << 16  # a lean mesher's evaluator drops rows once it holds this many (`release`)
RELEASE_GROWTH = 1.2  # and this many times the rows it kept the last time


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
        self.progress: Any = None  # called after each refinement round (`illumination_mesh`)
        self.scale = scale
        xs, ys = _grid(self.poly, self.tile_size)
        self.gp, self.tiles = _tiles(self.poly, xs, ys)
        self.grid = (xs, ys)
        self.lean = False  # True: no `update` will follow (`release`)
        self._done = np.zeros(len(self.tiles), bool)  # tiles whose refinement ended (`release`)
        self._live_rows = 0  # the evaluator's rows after the last `release` that dropped any
        self.edges: dict[tuple[int, int], _Edge] = {}
        for t in self.tiles:
            for ga, gb, _ in t.edge_keys():
                if (ga, gb) not in self.edges:
                    self.edges[(ga, gb)] = _Edge(self.gp[ga], self.gp[gb])
        self.stats: dict[str, Any] = {}
        self._corner_memo: dict[bytes, Any] = {}  # `corner_segments` per rising edge, kept across updates
        self._load_scene(scene)

    def _load_scene(self, scene: Scene, reuse: ev.Occluders | None = None) -> None:
        """Scene-dependent data; `reuse`: an earlier scene's occluder features (`update`)."""
        self.scene = scene
        self.eval = _Evaluator(scene, self.frame, self.diam)
        bbox = np.concatenate([self.poly.min(axis=0), self.poly.max(axis=0)])
        self.contact, self.contact_box = ev.contact_polygons(scene, self.frame, 1e-9 * self.diam)
        self.contact_corners = _contact_corners(self.contact)
        if scene.occluders is None:
            self.occ, self.seg, self.foot = None, None, np.zeros((0, 4))
            return
        self.occ = ev.occluder_features(scene, reuse)
        self.foot = ev.face_footprints(self.occ, scene, self.frame, bbox)
        self.seg = ev.Segments.concat([
            ev.discontinuity_segments(scene, self.occ, self.frame, self.poly),
            ev.corner_segments(scene, self.occ, self.frame, self.poly, self.foot, self.diam, self._corner_memo,
                               (self.contact, self.contact_box))])
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

    def _contact_ids(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        if not self.contact:
            return np.zeros(0, int)
        return np.nonzero(ev.boxes_overlap(self.contact_box, lo, hi, margin=1e-9 * self.diam))[0]

    def in_contact(self, q: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """Whether points `q (n, 2)` lie strictly inside one of the contact polygons `ids` (the
        receiver there is covered by an occluder face lying on it: a hole of the mesh)."""
        out = np.zeros(q.shape[0], bool)
        eps = 1e-14 * self.diam  # round-off; a sliver between a hole's edge and a point just inside is in the hole
        for i in ids:
            c = self.contact[i]
            e = np.roll(c, -1, axis=0) - c
            d = (e[None, :, 0] * (q[:, None, 1] - c[None, :, 1]) - e[None, :, 0 + 1] * (q[:, None, 0] - c[None, :, 0]))
            out |= np.all(d > eps * np.linalg.norm(e, axis=1)[None, :], axis=1)
        return out

    def at_contact_corner(self, c: np.ndarray) -> np.ndarray:
        """Whether triangles `c (T, 3, 2)` have a vertex within `CORNER_SIZE` (of the receiver's
        size) of a corner of the contact polygons (a vertex; where the edges of two overlapping
        objects' polygons cross the irradiance has one limit: `_contact_corners`), whether or
        not the polygon reaches the triangle's tile (a corner just outside a tile's edge reaches
        into it). Around such a corner the irradiance is continuous on every ray from it but takes a different limit
        along each (the walls standing there hide a direction-dependent part of the light), so
        every ring of elements around it sees the same variation, at any size: no refinement
        meets `tol` there."""
        r = CORNER_SIZE * self.diam
        return self.corner_distance(c, r) <= r

    def corner_distance(self, c: np.ndarray, reach: float) -> np.ndarray:
        """`(T,)`: the distance from triangles `c (T, 3, 2)` (their nearest vertex) to the
        nearest corner of the contact polygons (`at_contact_corner`), `inf` beyond `reach`."""
        out = np.full(c.shape[0], np.inf)
        k = self.contact_corners
        if k.shape[0] == 0 or c.shape[0] == 0:
            return out
        lo, hi = c.reshape(-1, 2).min(axis=0) - reach, c.reshape(-1, 2).max(axis=0) + reach
        k = k[np.all((k >= lo) & (k <= hi), axis=1)]
        if k.shape[0] == 0:
            return out
        d = np.min(np.linalg.norm(c[:, :, None, :] - k[None, None], axis=-1), axis=(1, 2))
        return np.where(d <= reach, d, np.inf)

    def _contact_edges(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The edges `(a, b)`, each `(n, 2)`, of the contact polygons `ids`."""
        if ids.size == 0:
            return np.zeros((0, 2)), np.zeros((0, 2))
        a = np.concatenate([self.contact[i] for i in ids])
        b = np.concatenate([np.roll(self.contact[i], -1, axis=0) for i in ids])
        return a, b

    def _contact_crossings(self, lo: np.ndarray, hi: np.ndarray, a: np.ndarray, b: np.ndarray) -> list[float]:
        """Parameters along the edge `a -> b` where contact polygons' edges cross it."""
        ca, cb = self._contact_edges(self._contact_ids(lo, hi))
        if ca.shape[0] == 0:
            return []
        r, e = cb - ca, b - a
        den = r[:, 0] * e[1] - r[:, 1] * e[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = ((ca[:, 0] - a[0]) * r[:, 1] - (ca[:, 1] - a[1]) * r[:, 0]) / -den
            t = ((ca[:, 0] - a[0]) * e[1] - (ca[:, 1] - a[1]) * e[0]) / -den
        ok = (den != 0) & (s > 1e-12) & (s < 1 - 1e-12) & (t >= 0) & (t <= 1)
        return sorted({float(x) for x in s[ok]})

    def move_off_contact(self, xy: np.ndarray, ids: np.ndarray) -> None:
        """Points `xy (n, 2)` on (within round-off of) the edges of contact polygons `ids` are
        evaluated `CONTACT_STEP` (of the receiver's size) outside them: along such an edge the
        irradiance jumps, and the mesh takes the value on the open receiver's side."""
        if ids.size == 0 or xy.shape[0] == 0:
            return
        eps = 1e-10 * self.diam
        box = self.contact_box[ids]  # only points in a polygon's bounding box can be on its edges
        cand = np.any(np.all((xy[:, None, :] >= box[None, :, :2] - eps) & (xy[:, None, :] <= box[None, :, 2:] + eps),
                             axis=2), axis=1)
        if not np.any(cand):
            return
        xy = xy[cand]
        ca, cb = self._contact_edges(ids)
        d = cb - ca
        ll = np.linalg.norm(d, axis=1)
        out = np.stack([d[:, 1], -d[:, 0]], axis=1) / ll[:, None]  # outward: the polygons are CCW
        t = np.einsum("nej,ej->ne", xy[:, None, :] - ca[None], d) / (ll * ll)[None]
        foot = ca[None] + np.clip(t, 0.0, 1.0)[..., None] * d[None]
        near = np.linalg.norm(xy[:, None, :] - foot, axis=2) <= eps  # (n, E)
        hit = np.any(near, axis=1)
        if not np.any(hit):
            return
        push = near[hit].astype(np.float64) @ out
        push /= np.maximum(np.linalg.norm(push, axis=1, keepdims=True), 1e-300)
        self.eval.move(xy[hit], xy[hit] + CONTACT_STEP * self.diam * push)

    def _visible(self, xy: np.ndarray, ids: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """Whether the event of segment `ids` is real at `xy`: its ray, nudged off the occluder,
        reaches the light."""
        nudge = ev.NUDGE_RTOL * self.diam
        assert self.seg is not None and self.occ is not None
        out = np.ones(ids.shape[0], bool)  # the corner lines are kept without the test
        test = ~self.seg.kept[ids]
        if np.any(test):
            p3 = self.frame.to3d(xy[test] + nudge * self.seg.free[ids[test]])
            out[test] = ev.ray_visible(p3, ev.ray_targets(self.seg, ids[test], p3), self.occ, faces)
        return out

    def _prepare_edges(self, keys: list[tuple[int, int]]) -> None:
        """Crossings of the discontinuity lines with edges `keys` and whether each is real."""
        for key in keys:
            e = self.edges[key]
            e.cross = {}
            lo, hi = np.minimum(e.a, e.b), np.maximum(e.a, e.b)
            # Contact polygons' edges (value discontinuities) crossing the edge: keys < 0.
            for j, sj in enumerate(self._contact_crossings(lo, hi, e.a, e.b)):
                e.cross[-1 - j] = (sj, e.point(sj), True)
            if len(e.cross):
                self.move_off_contact(np.array([x for _, x, _ in e.cross.values()]), self._contact_ids(lo, hi))
            if self.seg is None or len(self.seg) == 0:
                continue
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
        t.contact = self._contact_ids(t.lo, t.hi)
        ca, cb = self._contact_edges(t.contact)
        if ca.shape[0]:
            a, b, ok = ev._clip_to_polygon(ca, cb, t.poly)
            t.contact_pieces = [(p, q) for p, q, k in zip(a, b, ok, strict=True) if k]
        else:
            t.contact_pieces = []
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
        seen = np.array([bool(kv) for kv in known])
        if np.any(need):
            seen[need] = self._visible(xy[need], ids[need], t.faces)
        for _, start, n in runs_of:
            v = seen[start:start + n]
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
        mode = self.gradient
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
        grids = []
        for ti in tile_ids:
            t = self.tiles[ti]
            t.extrema = np.zeros((0, 2))
            fr = (np.arange(g) + 0.5) / g
            gx, gy = np.meshgrid(t.lo[0] + fr * (t.hi[0] - t.lo[0]), t.lo[1] + fr * (t.hi[1] - t.lo[1]), indexing="ij")
            q = np.stack([gx, gy], axis=-1)
            e = np.roll(t.poly, -1, axis=0) - t.poly
            c = e[None, None, :, 0] * (q[..., None, 1] - t.poly[:, 1]) - e[None, None, :, 1] * (q[..., None, 0] - t.poly[:, 0])
            grids.append((q, np.all(c > 0, axis=-1)))
        # Every tile's start grid in one call.
        allq = self.eval(np.concatenate([q[ok] for q, ok in grids]).reshape(-1, 2))
        at = np.cumsum([0] + [int(ok.sum()) for _, ok in grids])
        for k_tile, (ti, (q, ok)) in enumerate(zip(tile_ids, grids, strict=True)):
            t = self.tiles[ti]
            vals = np.full((g, g), np.nan)
            e3 = allq[at[k_tile]:at[k_tile + 1]]
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
            if found:
                top = max(top, float(self.eval(np.concatenate([np.array(lst) for lst in found.values()])).max()))
        # Along tile edges and along the discontinuity lines (a maximum often sits on a kink).
        found_e, vmax = self._line_extrema(np.array([self.edges[k].a for k in edge_keys]).reshape(-1, 2),
                                           np.array([self.edges[k].b for k in edge_keys]).reshape(-1, 2), False)
        top = max(top, vmax)
        self._edge_extrema = {}
        for r, s, v in found_e:
            self._edge_extrema.setdefault(edge_keys[r], []).append(s)
            top = max(top, v)
        where = [(ti, k) for ti in tile_ids for k in range(len(self.tiles[ti].pieces))]
        if where:
            P0 = np.array([self.tiles[i].pieces[j][0] for i, j in where])
            P1 = np.array([self.tiles[i].pieces[j][1] for i, j in where])
            found_p, vmax = self._line_extrema(P0, P1, True)
            top = max(top, vmax)
            for r, s, v in found_p:
                ti, k = where[r]
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
    def threshold(self) -> float:
        return ESTIMATE_MARGIN * self.tol * float(self.scale)

    def _refine_edges(self, keys: list[tuple[int, int]]) -> None:
        thr = self.threshold()
        params: dict[tuple[int, int], np.ndarray] = {}
        for key in keys:
            e = self.edges[key]
            on = [s for s, _, vis in e.cross.values() if vis]
            self.eval.mark(e.point(np.array(on)))
            params[key] = np.unique(np.array([0.0, 1.0] + on + self._edge_extrema.get(key, [])))
        active = list(keys)
        while active:
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
                hole = self.in_contact(e.point(s[:-1] + 0.5 * np.diff(s)),
                                        self._contact_ids(np.minimum(e.a, e.b), np.maximum(e.a, e.b)))
                bad = (err.max(axis=1) > thr) & (length > self.min_edge) & ~hole
                if np.any(bad):
                    worst = np.argmax(err[bad], axis=1)
                    new = probe.reshape(-1, 3)[bad][np.arange(worst.size), worst]
                    params[key] = np.unique(np.concatenate([s, new]))
                    nxt.append(key)
            active = nxt
        for key in keys:
            self.edges[key].s = params[key]

    def tile_pslg(self, t: _Tile) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
        for group, mk in ((_noded(lines), 0), (_noded(list(t.contact_pieces)), 2)):
            for q0, q1 in group:
                ends = []
                for q in (q0, q1):
                    d = np.abs(bverts - q).max(axis=1)
                    j = int(np.argmin(d))
                    ends.append(j if d[j] <= snap else vid(q))
                if ends[0] != ends[1]:
                    segs.append(ends)
                    marks.append(mk)
        for p in t.extrema:
            vid(p)
        return np.array(verts), np.array(segs), np.array(marks)

    def _tile_cells(self) -> np.ndarray:
        """`(len(xs) + 1, len(ys) + 1)`: the tile in each cell of the grid, -1 for none."""
        xs, ys = self.grid
        cells = np.full((xs.size + 1, ys.size + 1), -1, np.int64)
        for ti, t in enumerate(self.tiles):
            c = t.poly.mean(axis=0)
            cells[np.searchsorted(xs, c[0]), np.searchsorted(ys, c[1])] = ti
        return cells

    def release(self, finished: list[int], held: dict[int, np.ndarray],
                current: Any = None) -> dict[int, np.ndarray] | None:
        """For a mesh without `update` (`lean`), after a refinement round: tiles `finished` are
        final; once the evaluator holds `RELEASE_GROWTH` times the rows it kept last time (each
        round's inner check points alone pass that: in effect after every round; its cost is a
        few passes over the rows, small beside a round's evaluations), the values at points
        strictly inside finished tiles (no other tile asks for them: the points a tile shares
        with its neighbours lie on grid lines) and the rows nothing refers to any more (the
        elements' inner points) go (`_Evaluator.release`). `held`: per active tile the rows of
        its vertices; `current`: None, or a callable giving the keys (`x + iy`) that the active
        tiles can still ask for (their vertices, the midpoints of their triangulations' edges):
        then the other points strictly inside active tiles go too (the midpoints of edges the
        triangulation no longer has; one that comes back is evaluated again, to the same value).
        Returns `held` renumbered, or None when nothing was dropped."""
        self._done[finished] = True
        if not self.lean or self.eval._rows < max(RELEASE_GROWTH * self._live_rows, RELEASE_MIN_ROWS):
            return None
        xs, ys = self.grid
        cells = self._tile_cells()
        done = np.append(self._done, False)  # (index -1: no tile)

        def keep(xy: np.ndarray) -> np.ndarray:
            i, j = np.searchsorted(xs, xy[:, 0]), np.searchsorted(ys, xy[:, 1])
            on_line = (xs[np.minimum(i, xs.size - 1)] == xy[:, 0]) if xs.size else np.zeros(xy.shape[0], bool)
            if ys.size:
                on_line |= ys[np.minimum(j, ys.size - 1)] == xy[:, 1]
            ok = on_line | ~done[cells[i, j]]
            if keys is not None and keys.size:  # (membership in the sorted keys: no table, no merge sort)
                k = xy.view(np.complex128).ravel() + 0.0
                ok &= on_line | (keys[np.minimum(np.searchsorted(keys, k), keys.size - 1)] == k)
            elif keys is not None:
                ok &= on_line
            return ok  # type: ignore[no-any-return]

        keys = None if current is None else np.sort(current())

        before = self.eval._rows
        out = self.eval.release(keep, held)
        self._live_rows = self.eval._rows
        self.stats["rows_released"] = self.stats.get("rows_released", 0) + before - self._live_rows
        _return_free_memory()
        return out

    def _refine_tiles(self, tile_ids: list[int]) -> None:
        refine_tiles(self, tile_ids)

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
            evaluations=self.eval.evaluations, evaluation_seconds=self.eval.seconds, reused=self.eval.reused,
            values_kept=self.eval.kept, values_affected=self.eval.affected,
            tiles_meshed=len(tile_ids), edges_refined=len(edge_keys),
            segments=0 if self.seg is None else len(self.seg),
            pieces=sum(len(self.tiles[ti].pieces) for ti in tile_ids),
            extrema=sum(self.tiles[ti].extrema.shape[0] + sum(map(len, self.tiles[ti].piece_extrema.values())) for ti in tile_ids)
            + sum(len(v) for v in self._edge_extrema.values()),
            repairs=self.eval.repairs,
        )

    def assemble(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        vs = [t.verts for t in self.tiles]
        off = np.cumsum([0] + [v.shape[0] for v in vs])  # type: ignore[union-attr]
        # The tiles' vertices merged by position (rows as `x + iy`: a 1-D unique, in the order
        # of a row-wise one: by x, then y; the first occurrence of each kept).
        allv = np.concatenate([np.ascontiguousarray(v, np.float64).view(np.complex128).ravel() for v in vs])
        uniq, first, inv = np.unique(allv, return_index=True, return_inverse=True)
        del allv
        tris = np.concatenate([t.tris + o for t, o in zip(self.tiles, off[:-1], strict=True)])
        tris = inv.ravel()[tris]
        del inv
        used = np.zeros(uniq.shape[0], bool)
        used[tris.ravel()] = True  # vertices only inside holes are dropped
        renum = np.cumsum(used) - 1
        tris = renum[tris]
        del renum
        values = np.concatenate([t.values for t in self.tiles])[first[used]]  # type: ignore[misc]
        del first
        err = max(t.error for t in self.tiles) / float(self.scale)
        return self.frame.to3d(uniq[used].view(np.float64).reshape(-1, 2)), tris, values, err

    def release_evaluator(self) -> None:
        """Drop the exact values and the refinement's inputs once the tiles are meshed (a mesh
        without `update`)."""
        self.eval = None  # type: ignore[assignment]
        self.edges = {}
        self._corner_memo = {}
        self.seg = None
        self.occ = None

    def segments(self) -> np.ndarray:
        """`(k, 2, 3)` the discontinuity segments the tiles insert as mesh edges (m): the shadow
        lines (`pieces`, each tile's share of the event segments that survived the visibility
        test) and the contact lines (`contact_pieces`)."""
        ends = [(p0, p1) for t in self.tiles for p0, p1 in (*t.pieces, *t.contact_pieces)]
        if not ends:
            return np.zeros((0, 2, 3))
        xy = np.asarray(ends, np.float64).reshape(-1, 2)
        return self.frame.to3d(xy).reshape(-1, 2, 3)

    def release_all(self) -> None:
        """Drop everything but what the assembled mesh's statistics and `interpolate` read (a
        mesh without `update`)."""
        self.release_evaluator()
        for t in self.tiles:
            t.verts = t.tris = t.values = None
            t.pieces, t.contact_pieces, t.piece_extrema = [], [], {}


_TRIM: list[Any] = []  # glibc's `malloc_trim`, once looked up ([None] where there is none)


def _return_free_memory() -> None:
    """Hand the C heap's free pages back to the operating system (glibc's `malloc_trim(0)`; a
    no-op elsewhere). Arrays below glibc's mmap threshold, which rises to 32 MB once a larger one
    is freed, come from the heap, and what a round frees there stays resident until the heap's
    top is free; `release` calls this after dropping rows (a lean mesh's resident memory is then
    what it holds)."""
    if not _TRIM:
        import ctypes
        import ctypes.util

        try:
            _TRIM.append(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim)
        except (OSError, AttributeError):
            _TRIM.append(None)
    if _TRIM[0] is not None:
        _TRIM[0](0)


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
