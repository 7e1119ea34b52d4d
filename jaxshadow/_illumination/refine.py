"""2-D refinement of an illumination mesh's tiles (`_illumination`'s module docstring, step 4):
rounds of constrained Delaunay triangulation, checks of each new element at seven points against
exact values, insertion of each failing element's worst point."""

from __future__ import annotations

import time
from typing import Any, Protocol, runtime_checkable

import numpy as np

from .pslg import (
    _RADIX,
    _Checked,
    _edge_kinds,
    _split_at,
    _split_segments,
    _triangulate,
)


@runtime_checkable
class Refinable(Protocol):
    """What refinement needs of a mesh under construction (`builder._Builder` is one): its tiles,
    its exact evaluator, sizes and limits, and the contact-polygon queries."""

    tiles: list[Any]
    eval: Any
    diam: float
    min_edge: float
    max_vertices: int
    stats: dict[str, Any]
    progress: Any

    def threshold(self) -> float: ...
    def tile_pslg(self, t: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...
    def in_contact(self, q: np.ndarray, ids: np.ndarray) -> np.ndarray: ...
    def at_contact_corner(self, c: np.ndarray) -> np.ndarray: ...
    def corner_distance(self, c: np.ndarray, reach: float) -> np.ndarray: ...
    def move_off_contact(self, xy: np.ndarray, ids: np.ndarray) -> None: ...
    def release(self, finished: list[int], held: dict[int, np.ndarray],
                current: Any = None) -> dict[int, np.ndarray] | None: ...

CORNER_SIZE = 1e-4  # elements at a contact polygon's corner are not split below this (of the receiver's size)
CORNER_GRADE = 1e-3  # elements at distance r from such a corner may be split down to CORNER_GRADE * r
MAX_ROUNDS = 200  # refinement rounds per tile (each halves the worst elements; a guard)
GROUP_ELEMENTS = 1 << 17  # new elements checked per evaluation call within a round (`_groups`)
_INNER = np.array([[0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.5]]) + 0.5 / 3  # between centroid and corners


def _groups(tiles: list[int], sizes: list[int]) -> list[tuple[list[int], int]]:
    """`tiles` in order, in consecutive groups of at most `GROUP_ELEMENTS` new elements (at least
    one tile each), each with the position of its first tile in `tiles`."""
    out: list[tuple[list[int], int]] = [([], 0)]
    n = 0
    for k_tile, (ti, k) in enumerate(zip(tiles, sizes, strict=True)):
        if out[-1][0] and n + k > GROUP_ELEMENTS:
            out.append(([], k_tile))
            n = 0
        out[-1][0].append(ti)
        n += k
    return out


def _pack_errors(err: np.ndarray, thr: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A round's checked errors `err (T, 7)` as kept for the next round: per element its largest
    error `(T,)` and, for the few over `thr`, the index `(T,)` (-1 for the others) of their
    whole row in `(K, 7)`. An element at or under `thr` is read only through its largest error
    (it is never a candidate for a split), so a row of seven copies of it (`_unpack_errors`)
    decides as its own row does; 8 + 4 bytes instead of 56 per element of every active tile."""
    emax = err.max(axis=1) if err.shape[0] else np.zeros(0)
    over = np.nonzero(emax > thr)[0]
    slot = np.full(err.shape[0], -1, np.int32)
    slot[over] = np.arange(over.size, dtype=np.int32)
    return emax, slot, err[over]


def _unpack_errors(emax: np.ndarray, slot: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """`(T, 7)` errors from `_pack_errors`' parts (the elements at or under the threshold: their
    largest error seven times)."""
    out = np.repeat(emax[:, None], 7, axis=1)
    full = slot >= 0
    out[full] = rows[slot[full]]
    return out


def refine_tiles(b: Refinable, tile_ids: list[int]) -> None:
    """Refine the tiles `tile_ids` of `b` until no element fails its check (`_illumination`,
    step 4); the result goes to each tile's `verts`, `tris`, `values`, `error`."""
    thr = b.threshold()
    state = {}
    on_tol = 1e-11 * b.diam
    for ti in tile_ids:
        v, s, m = b.tile_pslg(b.tiles[ti])
        s, m = _split_at(v, s, m, np.arange(v.shape[0]), on_tol)
        state[ti] = (v, s, m)
    active = list(tile_ids)
    rounds = 0
    t_start = time.perf_counter()
    tried: dict[int, np.ndarray] = {}  # per tile: the points inserted so far (as x + iy)
    # Each round re-triangulates a tile with its new vertices appended; the triangles of the
    # previous round that are still there (same vertices) keep their checked errors, so only
    # the new triangles' check points are looked up and evaluated.
    last: dict[int, _Checked] = {}
    vrows: dict[int, np.ndarray] = {}  # per tile: the evaluator's rows of the last round's vertices
    marked: dict[int, np.ndarray] = {}  # per tile: the last round's inner segments (vertex-pair codes)
    lean = bool(getattr(b, "lean", False))  # no `update` will follow: finished tiles' values may go
    finished: list[int] = []  # tiles done since the evaluator last dropped their rows (`lean`)
    while active:
        rounds += 1
        meshes, known, last_n = {}, {}, {}
        probes = []
        # Every active tile's triangulation, marks and moves first (they decide which of the
        # cached values are evaluated again).
        for ti in active:
            v, s, m = state.pop(ti)
            out, dropped = _triangulate(v, s, m, on_tol)
            del v, s, m
            b.stats["cdt_fallbacks"] = b.stats.get("cdt_fallbacks", 0) + int(dropped)
            tv, tt = out["vertices"], out["triangles"]
            meshes[ti] = out
            kn, n_old = last[ti].match(tv, tt) if ti in last else (np.zeros(tt.shape[0], bool), 0)
            if b.tiles[ti].contact.size:
                # Vertices and edge midpoints on a contact polygon's edge, found by position: a
                # discontinuity line along the edge (an occluder's edge on the receiver makes
                # one) can take the place of the contact segment in the triangulation.
                c = tv[tt[~kn]]  # (T_new, 3, 2)
                mids = 0.5 * (c + np.roll(c, -1, axis=1))  # edges (0,1), (1,2), (2,0)
                b.move_off_contact(np.concatenate([tv[n_old:], mids.reshape(-1, 2)]), b.tiles[ti].contact)
                del c, mids
            inner_seg = out["segments"][out["segment_markers"].ravel() == 0]
            ends = np.sort(inner_seg, axis=1).astype(np.int64)
            codes = ends[:, 0] * _RADIX + ends[:, 1]
            fresh = inner_seg[~np.isin(codes, marked[ti])] if n_old and ti in marked else inner_seg
            marked[ti] = codes
            if fresh.size:  # (marking again the segments marked before changes nothing)
                b.eval.mark(tv[fresh.ravel()])
                b.eval.mark(0.5 * (tv[fresh[:, 0]] + tv[fresh[:, 1]]))
            stale = b.eval.stale(tv[:n_old])  # an old vertex evaluated again: its triangles are new
            if np.any(stale):
                kn &= ~np.any(np.concatenate([stale, np.zeros(tv.shape[0] - n_old, bool)])[tt], axis=1)
            known[ti] = kn
            last_n[ti] = n_old
            c = tv[tt[~kn]]
            mids = 0.5 * (c + np.roll(c, -1, axis=1))
            # The vertices to look up: the new ones and the old ones to evaluate again (the
            # others keep their rows, followed to any later evaluation of the point).
            probes.append(np.concatenate([tv[:n_old][stale], tv[n_old:]]))
            probes.append(mids.reshape(-1, 2))
            del c, mids
        # All active tiles' vertices and edge midpoints in one call (they are cached, and shared
        # by neighbouring tiles); each tile reads its rows.
        allrows = b.eval.row_of(np.concatenate(probes))
        rows = np.cumsum([0] + [p.shape[0] for p in probes])
        del probes
        total = sum(meshes[ti]["vertices"].shape[0] for ti in meshes) + sum(
            b.tiles[ti].verts.shape[0] for ti in range(len(b.tiles))  # type: ignore[union-attr]
            if b.tiles[ti].verts is not None and ti not in meshes)
        budget = total < b.max_vertices
        nxt = []
        failing = 0
        for group, first in _groups(active, [int((~known[ti]).sum()) for ti in active]):
            # The points inside the group's new elements (most of the evaluations; not cached:
            # `_Evaluator.inner_rows`) in one call per group, so that they and their values are
            # held for one group at a time (the values do not depend on the grouping).
            inside = []
            for ti in group:
                tv, tt = meshes[ti]["vertices"], meshes[ti]["triangles"]
                c = tv[tt[~known[ti]]]  # (T_new, 3, 2)
                inner = np.einsum("ij,tjk->tik", _INNER, c)
                inside.append(np.concatenate([c.mean(axis=1, keepdims=True), inner], axis=1).reshape(-1, 2))
                del c, inner
            at = np.cumsum([0] + [p.shape[0] for p in inside])
            if lean:  # no rows: `in_rows` are positions in `in_val`
                in_val = b.eval.inner_values(np.concatenate(inside))
                in_rows = np.arange(in_val.shape[0])
            else:
                in_rows = b.eval.inner_rows(np.concatenate(inside))
                in_val = b.eval.values[in_rows]
            del inside
            for k_group, ti in enumerate(group):
                k_tile = first + k_group
                out = meshes.pop(ti)
                tv, tt = out["vertices"], out["triangles"]
                segs = out["segments"]
                smark = out["segment_markers"].ravel()
                c = tv[tt]
                n_old = last_n[ti]
                vr = np.empty(tv.shape[0], np.int64)
                vr[n_old:] = allrows[rows[2 * k_tile + 1] - (tv.shape[0] - n_old):rows[2 * k_tile + 1]]
                vr[:n_old] = b.eval.follow(vrows[ti]) if n_old else vr[:0]
                vrows[ti] = vr
                ve = b.eval.values[vr]
                kn = known[ti]
                vn = ve[tt[~kn]]  # (T_new, 3, 3)
                interp = np.concatenate([0.5 * (vn + np.roll(vn, -1, axis=1)), vn.mean(axis=1, keepdims=True),
                                         np.einsum("ij,tjk->tik", _INNER, vn)], axis=1)
                err = np.empty((tt.shape[0], 7))
                hole, corner = np.empty(tt.shape[0], bool), np.empty(tt.shape[0], bool)
                if np.any(kn):
                    emax, slot, hole[kn], corner[kn] = last[ti].take(kn)
                    err[kn] = _unpack_errors(emax, slot, last[ti].side)  # type: ignore[arg-type]
                    del emax, slot
                got = np.concatenate([b.eval.values[allrows[rows[2 * k_tile + 1]:rows[2 * k_tile + 2]]].reshape(-1, 3, 3),
                                      in_val[at[k_group]:at[k_group + 1]].reshape(-1, 4, 3)], axis=1)
                err[~kn] = np.abs(got - interp).max(axis=2)
                del got, interp, vn
                irow = np.full((tt.shape[0], 4), -1, np.int64)  # rows of the new elements' inner points
                irow[~kn] = in_rows[at[k_group]:at[k_group + 1]].reshape(-1, 4)
                hole[~kn] = b.in_contact(c[~kn].mean(axis=1), b.tiles[ti].contact)
                # At a contact polygon's corner the irradiance has no limit (it depends on the
                # direction of approach): the elements within CORNER_SIZE of it are refined down
                # to CORNER_SIZE only, and their error is reported apart (`stats["corner_error"]`).
                corner[~kn] = b.at_contact_corner(c[~kn])
                emax, slot, over_rows = _pack_errors(err, thr)
                last[ti] = _Checked(tv, tt, emax, slot, hole, corner, side=over_rows)
                del emax, slot, over_rows
                err[hole] = 0.0  # covered by an occluder face lying on the receiver: not meshed
                longest = np.linalg.norm(c - np.roll(c, -1, axis=1), axis=2).max(axis=1)
                # Zero-area slivers (three vertices on a line up to round-off, where CDT's computed
                # crossings land an ulp off a tile edge) hold no point of the receiver: their long
                # edge is checked by the element on its other side (or, on a tile edge, in 1-D).
                e1, e2 = c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]
                flat = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) <= 1e-9 * longest * longest
                err[flat] = 0.0
                over = err.max(axis=1) > thr
                floor = np.where(corner, CORNER_SIZE * b.diam, b.min_edge)
                # Just outside the corner discs the irradiance still varies with the direction from
                # the corner (across the standing edge's penumbra wedge), over an angle, so the
                # elements must shrink in proportion to their distance r from it: down to
                # CORNER_GRADE * r there, below min_edge (looked at for the failing elements only).
                near = np.nonzero(over & ~corner)[0]
                floor[near] = np.minimum(b.min_edge, CORNER_GRADE * b.corner_distance(c[near], b.min_edge / CORNER_GRADE))
                # The elements to split (the few that fail; the next lines look at those only).
                cand = np.nonzero(over & (longest > floor))[0]
                edge_ij = np.stack([tt[cand], np.roll(tt[cand], -1, axis=1)], axis=-1)  # (C, 3, 2)
                kind = _edge_kinds(edge_ij, segs, smark, tv.shape[0])
                sel_err = err[cand]
                sel_err[:, :3][kind == 1] = -1.0  # never insert on the tile boundary
                split = sel_err.max(axis=1) > thr
                bad = np.zeros(tt.shape[0], bool)
                bad[cand[split]] = True
                failing += int(split.sum())
                t = b.tiles[ti]
                t.corner_error = float(err[corner].max()) if np.any(corner) else 0.0
                err[corner] = 0.0
                # Elements that fail but stop at the minimum edge length (`stats["unrefined_min_edge"]`).
                short = over & ~corner & (longest <= floor)
                t.unrefined = int(short.sum())
                t.unrefined_error = float(err[short].max()) if t.unrefined else 0.0
                done = not np.any(bad) or not budget
                if done:
                    if np.any(bad):
                        b.stats["tiles_stopped_by_budget"] = b.stats.get("tiles_stopped_by_budget", 0) + 1
                else:
                    worst = np.argmax(sel_err[split], axis=1)
                    cb = c[bad]
                    pts = np.concatenate([0.5 * (cb + np.roll(cb, -1, axis=1)), cb.mean(axis=1, keepdims=True),
                                          np.einsum("ij,tjk->tik", _INNER, cb)], axis=1)  # (B, 7, 2)
                    newp = pts[np.arange(worst.size), worst]
                    edge_of = edge_ij[split][np.arange(worst.size), np.minimum(worst, 2)]
                    kd = kind[split][np.arange(worst.size), np.minimum(worst, 2)]
                    # A point is inserted once: not twice in a round, never again once tried (then
                    # the triangulation did not keep it).
                    key = np.ascontiguousarray(newp).view(np.complex128).ravel()
                    _, once = np.unique(key, return_index=True)
                    once = np.sort(once)
                    seen = tried.get(ti, np.zeros(0, np.complex128))
                    once = once[~np.isin(key[once], seen)]
                    tried[ti] = np.concatenate([seen, key[once]])
                    done = once.size == 0 or rounds >= MAX_ROUNDS
                if done:
                    t.verts, t.tris, t.values = tv, tt[~hole], ve
                    t.error = float(err.max()) if err.size else 0.0
                    # The tile is final: its refinement state goes.
                    for d in (last, vrows, marked, tried):
                        d.pop(ti, None)
                    finished.append(ti)
                    continue
                r = irow[bad][np.arange(worst.size), np.maximum(worst - 3, 0)][once]
                r[worst[once] < 3] = -1
                if lean:  # inner points that become vertices keep their values
                    b.eval.adopt_values(newp[once][r >= 0], in_val[r[r >= 0]])
                else:  # (and their rows)
                    b.eval.adopt(newp[once][r >= 0], r[r >= 0])
                nv = tv.shape[0]
                new_v = np.concatenate([tv, newp[once]])
                # Edge midpoints on a line or a hole's edge split that segment.
                on_seg = (worst[once] < 3) & ((kd[once] == 0) | (kd[once] == 2))
                new_s, new_m = _split_segments(segs, smark, edge_of[once][on_seg], nv + np.nonzero(on_seg)[0])
                new_s2, new_m2 = _split_at(new_v, new_s, new_m, np.arange(nv, new_v.shape[0]), on_tol)
                state[ti] = (new_v, new_s2, new_m2)
                nxt.append(ti)
            del in_rows, in_val
        del allrows
        active = nxt
        if lean:
            # Without `update`, the values only the finished tiles' interiors and the elements'
            # inner points needed go (the evaluator keeps the active tiles' rows, renumbered).
            def current(active: list[int] = active) -> np.ndarray:
                """The points the active tiles can still ask for: the vertices of their next
                triangulation and the midpoints of their last one's edges."""
                out = []
                for ti in active:
                    out.append(state[ti][0])
                    tv, codes = last[ti].tv, last[ti].codes
                    s0, s1, s2 = codes // (_RADIX * _RADIX), (codes // _RADIX) % _RADIX, codes % _RADIX
                    a, c = np.concatenate([s0, s1, s0]), np.concatenate([s1, s2, s2])
                    out.append(0.5 * (tv[a] + tv[c]))
                return np.concatenate(out).view(np.complex128).ravel() + 0.0 if out else np.zeros(0, np.complex128)

            kept = b.release(finished, {ti: vrows[ti] for ti in active}, current)
            finished = []
            if kept is not None:
                vrows.update(kept)
        if b.progress is not None:
            b.progress({"round": rounds, "tiles_active": len(active), "tile_vertices": total,
                        "failing_elements": failing, "seconds": time.perf_counter() - t_start})
    b.stats["rounds"] = max(b.stats.get("rounds", 0), rounds)
