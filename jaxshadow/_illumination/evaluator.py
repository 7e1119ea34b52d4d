"""Exact irradiance at 2-D points of an illumination mesh's receiver (`_illumination`): the
evaluator that caches, batches and pads the host engine's calls, checks points on discontinuity
lines, and takes over an earlier scene's values on update."""

from __future__ import annotations

import itertools
import time
from typing import Any

import numpy as np

from .._core.keytable import EMPTY, GONE, MAX_LOAD, KeyTable, as_keys, first_occurrence
from .._scene.model import DirectionalLight, LinearLight, PointLight, PolygonLight, Scene
from .._shading.shade import irradiance
from . import events as ev

ON_LINE_STEP = 1e-9
MIN_BATCH = 256  # smallest batch handed to the engine
MAX_BATCH = 1 << 18  # largest batch handed to the engine (its working memory grows with the batch)
ROW_CHUNK = 1 << 20  # points looked up per step of `row_of`
ROW_ARRAYS = ("values", "targets", "lined", "inner")  # per row: its value, and what `inherit` reads
SPARE = 0.25  # room added when the value arrays grow, as a fraction of the rows they must hold


class _Evaluator:
    """Exact irradiance at 2-D receiver points, cached by coordinates, batched per call.

    Points on a discontinuity line (`mark`) are also evaluated `ON_LINE_STEP` (of the receiver's
    size) to either side along a fixed oblique direction: the host engine can return the
    unoccluded value at a point exactly on an umbra boundary (an EV plane; see
    `tests/test_illumination_mesh.py::test_engine_on_event_plane`), and where the value at the
    point is not between its neighbours' (with a slack far above a kink's) their mean is used
    (`repairs` counts these; the irradiance is continuous there, so the mean is within
    `ON_LINE_STEP` times the gradient of the exact value).

    The cache (`KeyTable`) maps a point's coordinates, as the `complex128` key `x + iy` (exact),
    to a row of one growing value array; each row also records where it was evaluated and whether
    with the on-line check, so that an update (`inherit`) can take over the rows of the previous
    scene whose value the change cannot affect: a point asked for again with the same evaluation
    takes the old row instead of calling the engine (`reused`). Every look-up is done for a whole
    array of points at once.

    A point needs evaluating when it is not cached, or when it was marked on a line after its
    value was computed without the on-line check (or moved: then it leaves the cache); the
    latter are kept in `pending`, so that finding them (`stale`) looks at those few keys rather
    than at every point. Batches are padded to a power of two with rows whose normal faces away
    from every light (the engine gives them 0 without clipping), not with copies of real points."""

    def __init__(self, scene: Scene, frame: ev.Frame, size: float):
        self.scene, self.frame = scene, frame
        self.cache = KeyTable()
        self.values = np.zeros((1024, 3))
        self.targets = np.zeros(1024, np.complex128)  # per row: the point evaluated (`move`)
        self.lined = np.zeros(1024, bool)  # per row: evaluated with the on-line check
        self.inner = np.zeros(1024, bool)  # per row: an element's inner point, not in the cache (`inner_rows`)
        self._arrays = ROW_ARRAYS  # the per-row arrays kept (`make_lean`: `values` only)
        self.succ: dict[int, int] = {}  # row -> the row of the point's next evaluation (`follow`)
        self._succ_sorted: tuple[np.ndarray, np.ndarray] | None = None
        self._rows = 0
        self.prior: KeyTable | None = None  # an earlier scene's rows (`inherit`)
        self.prior_ok = np.zeros(0, bool)  # which of its rows hold a value of this scene
        self.prior_index: KeyTable | None = None  # all of the earlier scene's keys (`rows`)
        self.first_row = 0
        self.reused = 0
        self.kept = self.affected = 0  # earlier values taken over / that the change can affect (`inherit`)
        self.online = KeyTable()  # a set: the points marked on a line
        self.checked = KeyTable()  # a set: the points evaluated with the on-line check
        self.moved = KeyTable()  # points evaluated elsewhere (`move`) -> index into `moved_to`
        self.moved_to = np.zeros(0, np.complex128)
        self.pending: set[complex] = set()  # cached keys to evaluate again: `online` and not `checked`
        self.dropped: dict[complex, int] = {}  # keys evaluated (their row), then moved, not evaluated since
        self._log_version = 0  # counts changes of `pending` and `dropped` (`_log`)
        self._log_memo: dict[bool, tuple[int, KeyTable]] = {}
        self.away = _away_normal(scene, frame)
        self.step = ON_LINE_STEP * size * np.array([np.cos(0.6180339887), np.sin(0.6180339887)])
        self.evaluations = 0
        self.repairs = 0
        self.seconds = 0.0

    @staticmethod
    def _keys(xy: np.ndarray) -> np.ndarray:
        return as_keys(xy)

    def make_lean(self) -> None:
        """Keep only the values per row (a mesh without `update`): where each row was evaluated,
        whether with the on-line check and whether at an inner point are read by `inherit` and
        `_take_prior` alone (an update's evaluator taking over this one's rows), so those arrays
        go (18 of the 42 bytes a row holds with them; `release` and growth copy less too)."""
        assert self.prior is None, "make_lean: not on an update's evaluator"
        self._arrays = ("values",)
        self.targets, self.lined, self.inner = self.targets[:0], self.lined[:0], self.inner[:0]

    def mark(self, xy: np.ndarray) -> None:
        """Declare points `(n, 2)` to lie on discontinuity lines."""
        keys = self._keys(xy)
        if keys.size == 0:
            return
        self.online.put(keys)
        keys = keys[~self.checked.contains(keys)]
        keys = keys[self.cache.contains(keys)]
        if keys.size:  # cached without the check: pending (the others get it when first evaluated)
            self.pending.update(keys.tolist())
            self._log_version += 1

    def move(self, xy: np.ndarray, to: np.ndarray) -> None:
        """Evaluate points `xy (n, 2)` at `to (n, 2)` instead (a point on the edge of a hole takes
        the value just outside it)."""
        a, b = self._keys(xy), self._keys(to)
        a, first = np.unique(a, return_index=True)
        keep = ~self.moved.contains(a)
        a, b = a[keep], b[first[keep]]
        if a.size == 0:
            return
        self.moved.put(a, np.arange(self.moved_to.size, self.moved_to.size + a.size))
        self.moved_to = np.concatenate([self.moved_to, b])
        r = self.cache.delete(a)
        self.dropped.update(zip(a[r >= 0].tolist(), r[r >= 0].tolist(), strict=True))
        self._log_version += 1

    def _targets(self, keys: np.ndarray) -> np.ndarray:
        """Where each key is evaluated: itself, or where it was moved."""
        if len(self.moved) == 0:
            return keys.copy()
        m = self.moved.get(keys)
        return np.where(m >= 0, self.moved_to[np.maximum(m, 0)], keys)

    def _lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per key its cached row (-1 when none) and whether it needs evaluating."""
        rows = self.cache.get(keys)
        need = rows < 0
        if self.pending:
            need |= self._log(False).contains(keys)
        return rows, need

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        """Exact irradiance `(n, 3)` at points `xy (n, 2)`."""
        rows = self.row_of(xy)  # (first: it may grow the arrays)
        return self.values[rows]

    def _settle(self, keys: np.ndarray, rows: np.ndarray) -> None:
        """Keys `keys` now have rows `rows`: the rows they had before (pending or moved keys:
        the log, not every key, is searched) lead to the new ones (`follow`), and they leave
        the log."""
        if not self.pending and not self.dropped:
            return
        at = np.nonzero(self._log(True).contains(keys))[0]  # (keys are distinct)
        if at.size == 0:
            return
        new, hit = rows[at], keys[at]
        old = self.cache.get(hit)
        for k, o, n in zip(hit.tolist(), old.tolist(), new.tolist(), strict=True):
            if o < 0:
                o = self.dropped.get(k, -1)
            if o >= 0 and o != n:
                self.succ[o] = n
                self._succ_sorted = None
            self.dropped.pop(k, None)
            self._log_version += 1

    def _log(self, with_dropped: bool) -> KeyTable:
        """The keys of `pending` (and of `dropped`) as a table, rebuilt when they changed."""
        memo = self._log_memo.get(with_dropped)
        if memo is not None and memo[0] == self._log_version:
            return memo[1]
        keys = itertools.chain(self.pending, self.dropped) if with_dropped else iter(self.pending)
        n = len(self.pending) + (len(self.dropped) if with_dropped else 0)
        t = KeyTable(2 * n)
        t.put(np.fromiter(keys, np.complex128, n))
        self._log_memo[with_dropped] = (self._log_version, t)
        return t

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
        """The value rows `(n,)` of points `xy (n, 2)`, evaluated first where needed; in chunks
        of `ROW_CHUNK` points (the look-up tables of one call grow with it; a point of a later
        chunk finds the rows of an earlier one, as it would within one call)."""
        keys = self._keys(xy)
        if keys.size <= ROW_CHUNK:
            return self._row_of(keys)
        return np.concatenate([self._row_of(keys[s:s + ROW_CHUNK]) for s in range(0, keys.size, ROW_CHUNK)])

    def _row_of(self, keys: np.ndarray) -> np.ndarray:
        rows, need = self._lookup(keys)
        if not need.any():
            return rows
        asked = keys[need]
        todo = asked[first_occurrence(asked)]  # each key once, in the order asked
        if todo.size and self.prior is not None:
            todo = todo[~self._take_prior(todo, True)[0]]
        if todo.size:
            line = self.online.contains(todo) if len(self.online) else np.zeros(todo.size, bool)
            new_rows = self._evaluate(self._targets(todo), line)
            self._settle(todo, new_rows)
            _put(self.cache, todo, new_rows)
            self._checked(todo[line])
        rows[need] = self.cache.get(asked)
        return rows

    def inner_rows(self, xy: np.ndarray) -> np.ndarray:
        """The value rows `(n,)` of points `xy (n, 2)` inside elements (never on a line, never
        moved), evaluated without entering the cache: an element's inner check points are most of
        the evaluations and are asked for once, so they get rows but no keys (`adopt` keys the
        few that become vertices). An update's earlier scene may hold them (`inherit`)."""
        keys = self._keys(xy)
        rows = np.full(keys.size, -1, np.int64)
        todo = np.ones(keys.size, bool)
        if keys.size and self.prior is not None:
            took, rr = self._take_prior(keys, False)
            rows[took] = rr
            todo = ~took
        if np.any(todo):
            rows[todo] = self._evaluate(keys[todo], np.zeros(int(todo.sum()), bool))
            self.inner[rows[todo]] = True
        return rows

    def adopt(self, xy: np.ndarray, rows: np.ndarray) -> None:
        """Key the points `xy (n, 2)` to their rows `rows` (`inner_rows`): they become vertices."""
        _put(self.cache, self._keys(xy), rows)

    def inner_values(self, xy: np.ndarray) -> np.ndarray:
        """The values `(n, 3)` at points `xy (n, 2)` inside elements, evaluated without rows (a
        mesh without `update`: no later call asks for them; `adopt_values` keeps the few that
        become vertices)."""
        assert self.prior is None, "inner_values: not on an update's evaluator"
        keys = self._keys(xy)
        return self._compute(keys, np.zeros(keys.size, bool))

    def adopt_values(self, xy: np.ndarray, values: np.ndarray) -> None:
        """Key the points `xy (n, 2)` to new rows holding `values (n, 3)` (`inner_values`): they
        become vertices."""
        keys = self._keys(xy)
        rows = self._store(keys, values, np.zeros(keys.size, bool))
        if "inner" in self._arrays:
            self.inner[rows] = True
        _put(self.cache, keys, rows)

    def _evaluate(self, tgt: np.ndarray, line: np.ndarray) -> np.ndarray:
        """Evaluate at the points `tgt` (keys, `(n,)`), with the on-line check where `line`, into
        new rows; returns the rows."""
        return self._store(tgt, self._compute(tgt, line), line)

    def _store(self, tgt: np.ndarray, val: np.ndarray, line: np.ndarray) -> np.ndarray:
        """New rows for the values `val (n, 3)` at the points `tgt` (keys); returns the rows."""
        n = tgt.size
        start = self._rows  # rows are never reused (a key dropped by `move` leaves its row behind)
        self._grow(start + n)
        self.values[start:start + n] = val
        if "targets" in self._arrays:
            self.targets[start:start + n] = tgt
            self.lined[start:start + n] = line
        self._rows = start + n
        return np.arange(start, start + n)

    def _compute(self, tgt: np.ndarray, line: np.ndarray) -> np.ndarray:
        """The values `(n, 3)` at the points `tgt` (keys, `(n,)`), with the on-line check where
        `line`."""
        pts = tgt.view(np.float64).reshape(-1, 2)
        side = pts[line]
        allp = np.concatenate([pts, side + self.step, side - self.step])
        t0 = time.perf_counter()
        n_all = allp.shape[0]
        e = np.empty((n_all, 3))
        for s in range(0, n_all, MAX_BATCH):
            part = allp[s:s + MAX_BATCH]
            # Padded to a power of two: the engine compiles per batch shape.
            k = part.shape[0]
            size = max(MIN_BATCH, 1 << (k - 1).bit_length())
            p3 = self.frame.to3d(np.concatenate([part, np.repeat(part[:1], size - k, axis=0)]))
            nrm = np.empty_like(p3)
            nrm[:k] = self.frame.normal
            nrm[k:] = self.frame.normal if self.away is None else self.away
            e[s:s + k] = np.asarray(irradiance(self.scene, p3, nrm), np.float64)[:k]
            del p3, nrm
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
        return val

    def _checked(self, keys: np.ndarray) -> None:
        """Keys `keys` were evaluated with the on-line check: they leave `pending`."""
        if keys.size == 0:
            return
        self.checked.put(keys)
        if self.pending:
            self.pending.difference_update(keys.tolist())
            self._log_version += 1

    def stale(self, xy: np.ndarray) -> np.ndarray:
        """`(n,)` bool: whether points `xy (n, 2)`, all evaluated before, would be evaluated again
        by the next call: those marked on a line since, or moved since (the log of both, not a
        look-up of every point)."""
        log = self.pending | self.dropped.keys()
        if not log:
            return np.zeros(xy.shape[0], bool)
        keys = np.ascontiguousarray(np.asarray(xy, np.float64).reshape(-1, 2)).view(np.complex128).ravel()
        return np.isin(keys, np.fromiter(log, np.complex128, len(log)))

    def release(self, keep: Any, held: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Drop every row no longer needed and renumber the others, for a mesh that will not be
        updated: the keys for which `keep(points (n, 2))` is False leave the cache, and the rows
        that no key, no pending re-evaluation and none of the row arrays `held` (followed to
        their points' latest evaluations first) refer to go, the elements' inner points among
        them. Returns `held` renumbered. The marks (`online`, `checked`) and moves stay: a key
        asked for again is evaluated as before, to the same value."""
        assert self.prior is None, "release: not on an update's evaluator"
        table = self.cache
        slots = np.nonzero(table.vals >= 0)[0]  # the live keys, in place (no re-hashing)
        ok = np.ones(slots.size, bool)
        for s in range(0, slots.size, ROW_CHUNK):  # (in chunks: `keep` makes several arrays per point)
            ok[s:s + ROW_CHUNK] = keep(table.keys[slots[s:s + ROW_CHUNK]].view(np.float64).reshape(-1, 2))
        table.vals[slots[~ok]] = GONE  # (probing passes deleted slots; the table drops them when it grows)
        table.live -= int((~ok).sum())
        slots = slots[ok]
        held = {i: self.follow(v) for i, v in held.items()}
        live = np.zeros(self._rows, bool)
        live[table.vals[slots]] = True
        for v in held.values():
            live[v] = True
        if self.dropped:
            live[np.fromiter(self.dropped.values(), np.int64, len(self.dropped))] = True
        new = np.cumsum(live) - 1
        n = int(new[-1]) + 1 if new.size else 0
        for name in self._arrays:
            a = getattr(self, name)
            b = np.zeros((max(int(n * (1 + SPARE)), 1024),) + a.shape[1:], a.dtype)
            b[:n] = a[:self._rows][live]
            setattr(self, name, b)
            del a
        self._rows = n
        table.vals[slots] = new[table.vals[slots]]
        self.dropped = {key: int(new[row]) for key, row in self.dropped.items()}
        self.succ, self._succ_sorted = {}, None
        self._log_version += 1
        return {i: new[v] for i, v in held.items()}

    def _grow(self, rows: int, spare: float | None = None) -> None:
        """Room for `rows` rows, and `spare` times as many again when the arrays must grow."""
        if rows <= self.values.shape[0]:
            return
        size = max(int(rows * (1 + (SPARE if spare is None else spare))), 1024)
        for name in self._arrays:
            a = getattr(self, name)
            b = np.zeros((size,) + a.shape[1:], a.dtype)
            b[:self._rows] = a[:self._rows]
            setattr(self, name, b)

    def _take_prior(self, todo: np.ndarray, keyed: bool) -> tuple[np.ndarray, np.ndarray]:
        """Which of the keys `todo` have an evaluation (the same point, with the on-line check or
        without) in a kept row of the earlier scene, and those rows; with `keyed` the keys enter
        the cache at those rows."""
        prior = self.prior
        assert prior is not None
        none = np.zeros(todo.size, bool), np.zeros(0, np.int64)
        if self.prior_ok.size == 0:
            return none
        r = prior.get(todo)
        hit = r >= 0
        if not np.any(hit):
            return none
        cand, rr = todo[hit], r[hit]  # keys with an earlier row: the same evaluation?
        line = self.online.contains(cand) if len(self.online) else np.zeros(cand.size, bool)
        same = self.prior_ok[rr] & (self.targets[rr] == self._targets(cand)) & (self.lined[rr] == line)
        if not np.any(same):
            return none
        take = hit.copy()
        take[hit] = same
        keys = cand[same]
        if keyed:
            self._settle(keys, rr[same])
            _put(self.cache, keys, rr[same])
            self._checked(keys[line[same]])
        self.reused += keys.size
        return take, rr[same]

    def rows(self) -> tuple[KeyTable, np.ndarray]:
        """Every key evaluated so far or taken over (`inherit`), with its row, and which rows hold
        a value of the current scene."""
        valid = np.zeros(self._rows, bool)
        valid[self.first_row:] = True
        if self.prior is None:
            return self.cache, valid
        valid[:self.first_row] = self.prior_ok[:self.first_row]
        assert self.prior_index is not None
        merged = self.prior_index.copy()
        merged.put(*self.cache.items())
        return merged, valid

    def positions(self, rows: int) -> np.ndarray:
        """The points `(rows, 2)` evaluated by the first `rows` rows (with the on-line check also
        `step` to either side)."""
        return self.targets[:rows].view(np.float64).reshape(-1, 2)

    def inherit(self, old: _Evaluator, keep: Any, region: np.ndarray | None = None) -> None:
        """Take over the rows of `old` (the evaluator of an earlier scene) for which `keep(points
        (n, 2))` says that the change of scene cannot affect the value at them or within `step`
        of them. With `region (G, 4)` (boxes `lo_x, lo_y, hi_x, hi_y`: the tiles the update
        meshes again, which hold every point the change can affect), only rows there are
        looked at and taken over (the other tiles keep their meshes: nothing looks them up),
        the elements' inner points (not in `old`'s cache) among them."""
        index, valid = old.rows()
        n = old._rows
        pts = old.positions(n)
        look = valid if region is None else valid & _in_boxes(pts, region)
        ok = np.zeros(n, bool)
        ok[look] = keep(pts[look])
        now = valid.copy()  # rows holding a value of the new scene: all but the affected
        now[look] = ok[look]
        self.affected = int(look.sum() - ok.sum())
        self.kept = int(now.sum())
        self.prior_index = index  # (shared, not copied: `rows` copies it for the next update)
        if region is not None:  # a table of the region's rows alone: small, quick to probe
            k, r = index.items()
            sel = ok[r]
            inner = np.nonzero(old.inner[:n] & ok)[0]  # (inner points are never moved: their key is their target)
            index = KeyTable(int((sel.sum() + inner.size) / MAX_LOAD) + 1)
            index.put(k[sel], r[sel])
            index.put(old.targets[inner], inner)
        # Copies (the old mesh keeps its evaluator), with room for the update's new rows.
        self.values, self.targets, self.lined, self.inner = old.values[:0], old.targets[:0], old.lined[:0], old.inner[:0]
        self._rows = 0
        self._grow(n, spare=0.5)
        self.values[:n], self.targets[:n], self.lined[:n] = old.values[:n], old.targets[:n], old.lined[:n]
        self.inner[:n] = old.inner[:n]
        self._rows = self.first_row = n
        self.prior, self.prior_ok = index, now

    def luminance(self, xy: np.ndarray) -> np.ndarray:
        return self(xy).sum(axis=1)


def _put(table: KeyTable, keys: np.ndarray, values: np.ndarray) -> None:
    """`table.put(keys, values)` for distinct `keys`, first growing the table where that put
    would (to the same capacity: the same table) by moving its live entries over in chunks of
    `ROW_CHUNK` slots. The table's own growth inserts every live key in one pass, whose working
    arrays (its keys and values copied out, hashes, probe positions) come on top of the old and
    the new table: with tens of millions of keys (tol 1e-4 on the box floor) that pass was the
    mesher's peak."""
    keys = np.asarray(keys, np.complex128).ravel()
    if table.used + keys.size > MAX_LOAD * table.keys.size:
        live = table.live + keys.size
        cap = 1 << max(4, int(np.ceil(1.5 * live / MAX_LOAD)).bit_length())  # (`KeyTable._resize`'s)
        old_k, old_v = table.keys, table.vals
        table.keys = np.zeros(cap, np.complex128)
        table.vals = np.full(cap, EMPTY, np.int64)
        table.live = table.used = 0
        for s in range(0, old_v.size, ROW_CHUNK):
            v = old_v[s:s + ROW_CHUNK]
            ok = v >= 0
            if np.any(ok):
                table.put(old_k[s:s + ROW_CHUNK][ok], v[ok])
        del old_k, old_v
    table.put(keys, values)


def _in_boxes(xy: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """`(n,)` bool: whether points `xy (n, 2)` lie in one of `boxes (G, 4)` (`lo_x, lo_y, hi_x,
    hi_y`, closed)."""
    out = np.zeros(xy.shape[0], bool)
    if boxes.shape[0] == 0:
        return out
    x, y = xy[:, 0], xy[:, 1]
    idx = np.nonzero((x >= boxes[:, 0].min()) & (x <= boxes[:, 2].max())
                     & (y >= boxes[:, 1].min()) & (y <= boxes[:, 3].max()))[0]
    x, y = x[idx], y[idx]
    near = np.zeros(idx.size, bool)
    for lo_x, lo_y, hi_x, hi_y in boxes:
        near |= (x >= lo_x) & (x <= hi_x) & (y >= lo_y) & (y <= hi_y)
    out[idx[near]] = True
    return out


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
