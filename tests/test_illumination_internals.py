"""The vectorised pieces of the illumination mesher against plain per-item references.

Each reference below is the straightforward loop the vectorised code replaced (one segment, one
inserted point, one box at a time), written out here; the tests compare the two on random small
cases. The evaluator's bookkeeping is checked against its definition (a point is evaluated again
when it was moved, or marked on a line after it was evaluated without the on-line check) and its
values against `js.irradiance` called on the points alone."""

from __future__ import annotations

import numpy as np
import pytest

import jaxshadow as js
from jaxshadow._illumination import evaluator as evaluator
from jaxshadow._illumination import events as ev
from jaxshadow._illumination import pslg as pslg
from jaxshadow._shadows import cache as _cache

QUAD = np.array([[-0.3, -0.3, 2.0], [-0.3, 0.3, 2.0], [0.3, 0.3, 2.0], [0.3, -0.3, 2.0]])
FLOOR = np.array([[-1.5, -1.5, 0.0], [1.5, -1.5, 0.0], [1.5, 1.5, 0.0], [-1.5, 1.5, 0.0]])


# --------------------------------------------------------------------------------------
# Segment splits
# --------------------------------------------------------------------------------------


def split_at_loop(v, s, m, idx, tol):
    """`_split_at` one segment at a time."""
    out_s = [row for row in s[m == 1]]
    out_m = list(m[m == 1])
    for si in np.nonzero(m != 1)[0]:
        a, b = v[s[si, 0]], v[s[si, 1]]
        d = b - a
        hits = []
        for k in idx:
            if k in (s[si, 0], s[si, 1]):
                continue
            t = float(np.dot(v[k] - a, d) / max(np.dot(d, d), 1e-300))
            if 0 < t < 1 and np.linalg.norm(a + t * d - v[k]) <= tol:
                hits.append((t, int(k)))
        chain = [s[si, 0]] + [k for _, k in sorted(hits)] + [s[si, 1]]
        for i, j in zip(chain[:-1], chain[1:], strict=True):
            out_s.append(np.array([i, j]))
            out_m.append(m[si])
    return np.array(out_s).reshape(-1, 2), np.array(out_m)


@pytest.mark.parametrize("seed", range(6))
def test_split_at_matches_the_loop(seed):
    rng = np.random.default_rng(seed)
    n = 30
    v = rng.uniform(0, 1, (n, 2))
    s = np.stack([np.arange(4), (np.arange(4) + 1) % 4], axis=1)  # an outer square
    inner = rng.choice(np.arange(4, n), (8, 2), replace=False)
    s = np.concatenate([s, inner])
    m = np.concatenate([np.ones(4, int), rng.choice([0, 2], 8)])
    # New vertices: some exactly on inner segments (several on one), some a hair off, some away.
    new = []
    for r in range(8):
        a, b = v[inner[r, 0]], v[inner[r, 1]]
        for t in rng.uniform(0.05, 0.95, rng.integers(0, 4)):
            new.append(a + t * (b - a) + rng.choice([0.0, 1e-13, 1e-6]) * rng.normal(size=2))
    new.extend(rng.uniform(0, 1, (5, 2)))
    v = np.concatenate([v, np.array(new)])
    idx = np.arange(n, v.shape[0])
    got = pslg._split_at(v, s, m, idx, 1e-11)
    want = split_at_loop(v, s, m, idx, 1e-11)
    assert got[0].shape[0] > s.shape[0]  # something was split
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


def split_segments_loop(segs, marks, edges, mids):
    """`_split_segments` one segment at a time (the last split given for an edge wins)."""
    split = {}
    for (i, j), mid in zip(edges.tolist(), mids.tolist(), strict=True):
        split[(min(i, j), max(i, j))] = mid
    out_s, out_m = [], []
    for (i, j), mk in zip(segs.tolist(), marks.tolist(), strict=True):
        mid = split.get((min(i, j), max(i, j)))
        if mid is None:
            out_s.append([i, j])
            out_m.append(mk)
        else:
            out_s.extend([[i, mid], [mid, j]])
            out_m.extend([mk, mk])
    return np.array(out_s).reshape(-1, 2), np.array(out_m)


@pytest.mark.parametrize("seed", range(6))
def test_split_segments_matches_the_loop(seed):
    rng = np.random.default_rng(seed)
    segs = rng.choice(40, (25, 2), replace=True)
    segs = segs[segs[:, 0] != segs[:, 1]]
    marks = rng.choice([0, 1, 2], segs.shape[0])
    pick = rng.choice(segs.shape[0], 10)  # repeats: the same edge split twice, the last wins
    edges = segs[pick].copy()
    flip = rng.random(10) < 0.5
    edges[flip] = edges[flip][:, ::-1]  # either way round
    edges = np.concatenate([edges, [[41, 42]]])  # an edge that is not a segment
    mids = 50 + np.arange(edges.shape[0])
    got = pslg._split_segments(segs, marks, edges, mids)
    want = split_segments_loop(segs, marks, edges, mids)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


# --------------------------------------------------------------------------------------
# The evaluator
# --------------------------------------------------------------------------------------


def _evaluator():
    occ = np.array([[-0.5, -0.3, 1.0], [0.3, -0.3, 1.0], [0.3, 0.4, 1.0], [-0.5, 0.4, 1.0]])
    scene = js.Scene([js.PolygonLight(QUAD, 10.0)], occluders=[occ])
    frame = ev.receiver_frame(FLOOR)
    return scene, frame, evaluator._Evaluator(scene, frame, 3.0)


def _by_definition(e, xy):
    keys = e._keys(xy)
    cached, online, checked = (set(t.items()[0].tolist()) for t in (e.cache, e.online, e.checked))
    return np.array([k not in cached or (k in online and k not in checked) for k in keys.tolist()])


def test_evaluator_values_and_padding():
    scene, frame, e = _evaluator()
    rng = np.random.default_rng(1)
    xy = rng.uniform(-1.4, 1.4, (37, 2))
    got = e(xy)  # 37 rows, padded to the smallest batch
    p3 = frame.to3d(xy)
    want = np.asarray(js.irradiance(scene, p3, np.tile(frame.normal, (37, 1))))
    np.testing.assert_array_equal(got, want)
    assert e.evaluations == 37
    assert got.max() > 0 and got.min() == 0  # lit and umbra points
    # The padding rows face away from the light: the engine gives them 0.
    assert e.away is not None
    np.testing.assert_array_equal(np.asarray(js.irradiance(scene, p3[:4], np.tile(e.away, (4, 1)))), 0.0)


def test_away_normal_needs_every_light_on_one_side():
    frame = ev.receiver_frame(FLOOR)
    below = QUAD[::-1] * np.array([1.0, 1.0, -1.0])
    up = js.Scene([js.PolygonLight(QUAD, 1.0), js.PointLight([0, 0, 1.0], 1.0)])
    down = js.Scene([js.PolygonLight(below, 1.0)])
    both = js.Scene([js.PolygonLight(QUAD, 1.0), js.PointLight([0, 0, -1.0], 1.0)])
    sun = js.Scene([js.DirectionalLight([0.1, 0.2, -1.0], 1.0)])
    np.testing.assert_array_equal(evaluator._away_normal(up, frame), -frame.normal)
    np.testing.assert_array_equal(evaluator._away_normal(down, frame), frame.normal)
    np.testing.assert_array_equal(evaluator._away_normal(sun, frame), -frame.normal)
    assert evaluator._away_normal(both, frame) is None


def test_evaluator_pending_points_follow_the_definition():
    scene, frame, e = _evaluator()
    rng = np.random.default_rng(2)
    xy = rng.uniform(-1.4, 1.4, (40, 2))
    first = e.row_of(xy)
    assert not e.stale(xy).any() and not _by_definition(e, xy).any()
    # Marked on a line after their evaluation: evaluated again, with the on-line check.
    e.mark(xy[:5])
    e.mark(xy[:2])  # twice: once in the log
    np.testing.assert_array_equal(e.stale(xy), _by_definition(e, xy))
    assert e.stale(xy)[:5].all() and not e.stale(xy)[5:].any()
    # Moved (a point on a hole's edge takes the value beside it): evaluated again, elsewhere.
    to = xy[10:12] + 1e-3
    e.move(xy[10:12], to)
    np.testing.assert_array_equal(e.stale(xy), _by_definition(e, xy))
    assert e.stale(xy)[10:12].all()
    n0 = e.evaluations
    got = e(xy)
    assert e.evaluations == n0 + 5 * 3 + 2  # the marked ones with a point to either side
    assert not e.stale(xy).any() and not _by_definition(e, xy).any()
    np.testing.assert_array_equal(got[10:12], e(to))
    # The rows of the first evaluation lead to the current ones (a tile's old vertices).
    now = e.row_of(xy)
    assert np.sum(now != first) == 7
    np.testing.assert_array_equal(e.follow(first), now)
    # A point marked before its first evaluation is not pending twice.
    q = rng.uniform(-1.4, 1.4, (3, 2))
    e.mark(q)
    n0 = e.evaluations
    e(q)
    assert e.evaluations == n0 + 9
    assert not e.pending and not e.dropped
    # Nothing left to do: no engine call.
    n0 = e.evaluations
    e(np.concatenate([xy, q]))
    assert e.evaluations == n0


def test_evaluator_release_keeps_what_is_held():
    # `release` (a mesh without `update`): the keys `keep` rejects leave the cache, the rows
    # nothing refers to go (inner points, superseded evaluations), the rest is renumbered with
    # the same values; a dropped key asked for again is evaluated as before, to the same value.
    scene, frame, e = _evaluator()
    rng = np.random.default_rng(3)
    xy = rng.uniform(-1.4, 1.4, (60, 2))
    e.mark(xy[50:])  # on a line: evaluated with the on-line check
    rows = e.row_of(xy)
    want = e.values[rows].copy()
    inner = rng.uniform(-1.4, 1.4, (30, 2))
    irows = e.inner_rows(inner)
    e.adopt(inner[:3], irows[:3])  # three inner points become vertices
    e.mark(xy[:4])  # pending: evaluated again on the next call, their old rows then lead to new ones
    e.move(xy[4:6], xy[4:6] + 1e-3)  # moved: dropped from the cache until evaluated again
    held = {7: rows[:10].copy()}  # a tile's vertex rows from before the marks and moves
    n_rows = e._rows
    out = e.release(lambda q: q[:, 0] < 0.0, held)
    keep = xy[:, 0] < 0.0
    # Rows left: the kept keys', the held ones (followed), the moved keys' old rows.
    k, r = e.cache.items()
    assert e._rows < n_rows
    assert len(e.cache) == int(keep.sum()) - int(keep[4:6].sum()) + int((inner[:3, 0] < 0).sum())
    np.testing.assert_array_equal(e.values[out[7]], want[:10])
    kept_xy = xy[keep & (np.arange(60) >= 6)]
    n0 = e.evaluations
    np.testing.assert_array_equal(e(kept_xy), want[keep & (np.arange(60) >= 6)])
    assert e.evaluations == n0  # no engine call for kept keys
    # Every point again, the dropped ones too: one evaluation each for the dropped, the
    # pending and the moved (with the on-line check: three), values as by definition.
    got = e(xy)
    dropped = ~keep & (np.arange(60) >= 6)
    online = dropped & (np.arange(60) >= 50)
    assert e.evaluations == n0 + 4 * 3 + 2 + int(dropped.sum()) + 2 * int(online.sum())
    np.testing.assert_array_equal(got[6:], want[6:])
    np.testing.assert_array_equal(got[4:6], e(xy[4:6] + 1e-3))
    np.testing.assert_array_equal(e.values[e.follow(out[7])], got[:10])


def test_packed_errors():
    # Rows over the threshold come back whole; the others as seven copies of their largest error.
    from jaxshadow._illumination.refine import _pack_errors, _unpack_errors

    err = np.random.default_rng(5).random((50, 7))
    thr = 0.9
    emax, slot, rows = _pack_errors(err, thr)
    over = err.max(axis=1) > thr
    assert rows.shape == (int(over.sum()), 7) and 0 < over.sum() < 50
    back = _unpack_errors(emax, slot, rows)
    np.testing.assert_array_equal(back[over], err[over])
    np.testing.assert_array_equal(back[~over], np.repeat(err[~over].max(axis=1)[:, None], 7, axis=1))
    e0, s0, r0 = _pack_errors(np.zeros((0, 7)), thr)
    assert _unpack_errors(e0, s0, r0).shape == (0, 7)


def test_put_grows_the_table_in_chunks(monkeypatch):
    # The evaluator's puts grow its cache themselves, moving the live entries over a chunk at a
    # time: the same capacity as the table's own growth, the same mapping, deleted keys gone.
    from jaxshadow._core.keytable import KeyTable

    monkeypatch.setattr(evaluator, "ROW_CHUNK", 7)
    rng = np.random.default_rng(6)
    keys = rng.uniform(-1, 1, (3000, 2)).view(np.complex128).ravel()
    ours, theirs = KeyTable(), KeyTable()
    for t in (ours, theirs):
        t.put(keys[:500], np.arange(500))
        t.delete(keys[:100])
    evaluator._put(ours, keys[500:], np.arange(500, 3000))
    theirs.put(keys[500:], np.arange(500, 3000))
    assert ours.keys.size == theirs.keys.size > 1024 and len(ours) == len(theirs) == 2900
    np.testing.assert_array_equal(ours.get(keys), theirs.get(keys))
    assert np.all(ours.get(keys[:100]) == -1) and np.array_equal(ours.get(keys[100:]), np.arange(100, 3000))


def test_lean_evaluator_keeps_values_only():
    # `make_lean`: rows hold values alone (where, how and whether inner: `update`'s), and release
    # and growth give the same values as the full evaluator's.
    scene, frame, full = _evaluator()
    lean = evaluator._Evaluator(scene, frame, 3.0)
    lean.make_lean()
    rng = np.random.default_rng(4)
    xy = rng.uniform(-1.4, 1.4, (3000, 2))  # (past the first 1024 rows: the arrays grow)
    for e in (full, lean):
        e.mark(xy[2900:])
        e.adopt_values(xy[:5] + 0.25, e.inner_values(xy[:5] + 0.25))
    np.testing.assert_array_equal(lean(xy), full(xy))
    assert lean.targets.size == lean.lined.size == lean.inner.size == 0
    keep = {3: lean.row_of(xy[:10])}
    out = lean.release(lambda q: q[:, 0] < 0.0, keep)
    np.testing.assert_array_equal(lean.values[out[3]], full(xy[:10]))
    np.testing.assert_array_equal(lean(xy), full(xy))
    assert lean.targets.size == 0


# --------------------------------------------------------------------------------------
# Several boxes at once
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["polygon", "point", "segment", "directional"])
def test_affected_several_boxes_is_the_union_of_single_boxes(kind):
    light = {"polygon": js.PolygonLight(QUAD, 1.0), "point": js.PointLight([0.1, -0.2, 1.9], 1.0),
             "segment": js.LinearLight([-0.4, 0.0, 2.0], [0.4, 0.1, 2.0], 1.0),
             "directional": js.DirectionalLight([0.2, 0.1, -1.0], 1.0)}[kind]
    rng = np.random.default_rng(4)
    p = np.c_[rng.uniform(-3, 3, (3000, 2)), np.zeros(3000)]
    n = np.c_[rng.normal(0, 0.3, (3000, 2)), np.ones(3000)]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    lo = np.array([[0.2, -0.5, 0.0], [-0.2, -0.1, 1.2], [-1.5, 1.0, 0.0]])
    hi = np.array([[0.6, -0.1, 0.9], [0.1, 0.2, 1.5], [-1.2, 1.3, 0.4]])
    want = np.zeros(p.shape[0], bool)
    for g in range(lo.shape[0]):
        single = _cache.affected(light, p, n, lo[g], hi[g])
        assert single.any() and not single.all()
        want |= single
    got = _cache.affected(light, p, n, lo, hi)
    np.testing.assert_array_equal(got, want)
    assert want.sum() > max(_cache.affected(light, p, n, lo[g], hi[g]).sum() for g in range(3))


# --------------------------------------------------------------------------------------
# Occluder features reused on update
# --------------------------------------------------------------------------------------


def _boxes(shift):
    out = []
    for i, (x, y) in enumerate([(-0.8, -0.6), (0.3, 0.4), (0.9, -0.7)]):
        lo = np.array([x, y, 0.0]) + (shift if i == 1 else 0.0)
        c = lo + np.array([[0, 0, 0], [0.3, 0, 0], [0.3, 0.3, 0], [0, 0.3, 0],
                           [0, 0, 0.4], [0.3, 0, 0.4], [0.3, 0.3, 0.4], [0, 0.3, 0.4]])
        f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                      [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
        out.append(js.Mesh(c, f))
    return js.Scene([js.PolygonLight(QUAD, 1.0)], out)


def test_occluder_features_reused_equal_fresh():
    old = ev.occluder_features(_boxes(np.zeros(3)))
    new_scene = _boxes(np.array([0.05, 0.02, 0.0]))
    fresh = ev.occluder_features(new_scene)
    reused = ev.occluder_features(new_scene, reuse=old)
    for name in ("faces", "face_normal", "face_object", "edge", "edge_adj", "edge_object", "vert", "vert_adj",
                 "vert_object"):
        np.testing.assert_array_equal(getattr(reused, name), getattr(fresh, name), err_msg=name)
    # The boxes that did not move are taken over, the moved one is computed again.
    taken = [k for k, part in reused.objects.items() if any(part is q for q in old.objects.values())]
    assert len(old.objects) == len(reused.objects) == 3 and len(taken) == 2


# --------------------------------------------------------------------------------------
# The evaluator's hash table
# --------------------------------------------------------------------------------------


def test_key_table_matches_a_dict():
    """Random puts (with repeated keys in a batch), deletes and look-ups against a `dict`, with
    keys from a coarse lattice so that batches collide often, through several resizes."""
    from jaxshadow._core.keytable import KeyTable, as_keys, first_occurrence

    rng = np.random.default_rng(5)
    t, d = KeyTable(16), {}
    for _ in range(200):
        k = as_keys(np.round(rng.uniform(-1, 1, (int(rng.integers(0, 300)), 2)), 2))
        if rng.random() < 0.7:
            v = rng.integers(0, 1000, k.size)
            t.put(k, v)
            d.update(zip(k.tolist(), v.tolist(), strict=True))  # the last value of a repeated key
        else:
            got = t.delete(k)
            want = [d.get(x, -1) for x in k.tolist()]
            for x in k.tolist():
                d.pop(x, None)
            np.testing.assert_array_equal(got, want)
        q = np.concatenate([k, as_keys(np.round(rng.uniform(-1, 1, (200, 2)), 2))])
        np.testing.assert_array_equal(t.get(q), [d.get(x, -1) for x in q.tolist()])
        assert len(t) == len(d)
        _, first = np.unique(q, return_index=True)
        np.testing.assert_array_equal(np.nonzero(first_occurrence(q))[0], np.sort(first))
    keys, vals = t.items()
    assert dict(zip(keys.tolist(), vals.tolist(), strict=True)) == d
    # -0.0 and 0.0 are one key, as in a dict of complex numbers.
    t.put(np.array([complex(-0.0, -0.0)]), 3)
    assert t.get(np.array([0j]))[0] == 3 and t.contains(np.array([complex(0.0, -0.0)]))[0]


def test_cut_by_polygons_hand_computed():
    # A segment along the x axis through a square (cut out, grown by g), from inside a square
    # at its start (its own object's foot: kept) and short of a square past its end.
    from jaxshadow._illumination.events import _cut_by_polygons

    sq = lambda x0, x1: np.array([[x0, -1.0], [x1, -1.0], [x1, 1.0], [x0, 1.0]])  # noqa: E731
    polys = [sq(2.0, 3.0), sq(-1.0, 0.0), sq(11.0, 12.0)]
    boxes = np.array([[p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max()] for p in polys])
    a, b = np.array([[0.0, 0.0], [0.0, 5.0]]), np.array([[10.0, 0.0], [10.0, 5.0]])
    pa, pb, idx = _cut_by_polygons(a, b, polys, boxes, 0.01)
    np.testing.assert_allclose(pa, [[0.0, 0.0], [3.01, 0.0], [0.0, 5.0]])
    np.testing.assert_allclose(pb, [[1.99, 0.0], [10.0, 0.0], [10.0, 5.0]])
    assert idx.tolist() == [0, 0, 1]


def test_corner_lines_run_their_whole_length_outside_other_feet():
    # Boxes A and B of `box_field(180)` (rounded): the plane through A's vertical edge at
    # (-0.048, -1.951) and B's at (0.093, -1.211) meets the floor in a line leaving A's corner
    # away from B. Its kink matters far from the corner where the light is faint: with the line
    # 8 cm long (the earlier min_edge / tol rule at tol 1e-3), an element 27 cm from the corner
    # kept an interpolation error of 1.07e-3 that its seven check points did not see. The line
    # now runs as far as both boxes can shadow, but not through box C's foot (a hole), which it
    # resumes beyond.
    from jaxshadow._illumination.builder import _Builder

    A = ((-0.270, -1.951, 0.0), (-0.048, -1.606, 0.998))
    B = ((-0.108, -1.211, 0.0), (0.093, -0.906, 1.106))
    c, far = np.array([-0.048, -1.951]), np.array([0.093, -1.211])
    d = (c - far) / np.linalg.norm(c - far)  # the line's direction, away from B
    mid = c + 0.5 * d  # C straddles the line half a metre from the corner
    C = ((mid[0] - 0.03, mid[1] - 0.03, 0.0), (mid[0] + 0.03, mid[1] + 0.03, 0.3))
    floor = np.array([[-2.0, -4.0, 0.0], [2.0, -4.0, 0.0], [2.0, 0.0, 0.0], [-2.0, 0.0, 0.0]])
    scene = js.Scene([js.PolygonLight(np.array([[-0.3, -0.3, 2.0], [-0.3, 0.3, 2.0], [0.3, 0.3, 2.0],
                                                [0.3, -0.3, 2.0]]), 10.0)],
                     [js.Mesh.box(lo, hi) for lo, hi in (A, B, C)])
    b = _Builder(scene, floor, 1e-3, None, None, 1_000_000, "differences", None)
    s = b.seg
    o = b.frame.to2d(np.array([[0.0, 0.0, 0.0]]))[0]  # frame coordinates of the world origin
    k = s.kept
    a2, b2 = s.a[k] - o, s.b[k] - o
    u = (b2 - a2) / np.linalg.norm(b2 - a2, axis=1)[:, None]
    on = np.abs((a2[:, 0] - c[0]) * d[1] - (a2[:, 1] - c[1]) * d[0]) < 1e-6  # pieces on the line
    on &= np.abs(u @ d - 1.0) < 1e-9
    t0, t1 = (a2[on] - c) @ d, (b2[on] - c) @ d
    assert np.isclose(t0.min(), 0.0, atol=1e-9)  # from the corner
    assert t1.max() > 0.6  # past C, far beyond 8 cm
    assert not np.any((t0 < 0.52) & (t1 > 0.48))  # nothing inside C's foot (half-width >= 0.03)
    assert np.sum(on) >= 2  # the line resumes beyond C
