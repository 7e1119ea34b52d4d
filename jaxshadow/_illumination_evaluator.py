"""Exact irradiance at 2-D points of an illumination mesh's receiver (`_illumination`): the
evaluator that caches, batches and pads the host engine's calls, checks points on discontinuity
lines, and takes over an earlier scene's values on update."""

from __future__ import annotations

import itertools
import time
from typing import Any

import numpy as np

from . import _illumination_events as ev
from ._scene import DirectionalLight, LinearLight, PointLight, PolygonLight, Scene
from ._shade import irradiance

ON_LINE_STEP = 1e-9
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
