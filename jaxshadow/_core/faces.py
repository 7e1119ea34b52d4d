"""The face table of an occluder mesh (`mesh.Mesh`, module docstring there): faces as one padded
index table, their normals and checks, closedness and orientation, convexity, the coplanar
merge and the edges of a convex solid. NumPy only, before any compiled code runs."""

from __future__ import annotations

import bisect
import heapq
import math
import operator
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


def _plane_values(pts: np.ndarray, p0: Any, nrm: np.ndarray) -> np.ndarray:
    """(pts - p0) . nrm over the last axis, with one fixed order of operations (broadcasting), so
    that every test of a vertex against a face plane below rounds the same way."""
    d = pts - p0
    return d[..., 0] * nrm[..., 0] + d[..., 1] * nrm[..., 1] + d[..., 2] * nrm[..., 2]


def _newell_many(p: np.ndarray) -> np.ndarray:
    """`_newell` of each polygon of `p (G, k, 3)`: the same products summed along a contiguous
    axis of length k (the same summation as `np.sum` of one face's terms)."""
    w = np.concatenate([p[:, 1:], p[:, :1]], axis=1)
    return np.stack([(p[:, :, 1] * w[:, :, 2] - p[:, :, 2] * w[:, :, 1]).sum(axis=1),
                     (p[:, :, 2] * w[:, :, 0] - p[:, :, 0] * w[:, :, 2]).sum(axis=1),
                     (p[:, :, 0] * w[:, :, 1] - p[:, :, 1] * w[:, :, 0]).sum(axis=1)], axis=1)


@dataclass(frozen=True)
class _Faces:
    """Face loops as arrays: `pad (F, K)` vertex indices, each face's loop padded with its first
    vertex (which changes no maximum over a face's vertices), and `lens (F,)` its vertex count."""

    pad: np.ndarray
    lens: np.ndarray

    @staticmethod
    def of(loops: list[list[int]]) -> _Faces:
        lens = np.fromiter((len(x) for x in loops), dtype=np.intp, count=len(loops))
        k = int(lens.max(initial=3))
        if len(loops) and int(lens.min()) == k:
            return _Faces(np.asarray(loops, dtype=np.int64).reshape(-1, k), lens)
        pad = np.empty((len(loops), k), dtype=np.int64)
        for j in np.unique(lens).tolist():
            idx = np.flatnonzero(lens == j)
            arr = np.asarray([loops[i] for i in idx.tolist()], dtype=np.int64).reshape(-1, j)
            pad[idx, :j] = arr
            pad[idx, j:] = arr[:, :1]
        return _Faces(pad, lens)

    def __len__(self) -> int:
        return len(self.lens)

    def groups(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The faces grouped by vertex count: (face indices (G,), vertex indices (G, k)) per count."""
        if len(self.lens) and int(self.lens.min()) == self.pad.shape[1]:
            return [(np.arange(len(self.lens)), self.pad)]
        return [(idx, self.pad[idx, :k]) for k in np.unique(self.lens).tolist()
                for idx in [np.flatnonzero(self.lens == k)]]

    def reversed(self) -> _Faces:
        """Every loop run backwards."""
        pad = np.empty_like(self.pad)
        for idx, arr in self.groups():
            pad[idx, :arr.shape[1]] = arr[:, ::-1]
            pad[idx, arr.shape[1]:] = arr[:, -1:]
        return _Faces(pad, self.lens)

    def edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Directed edges in face order: (face, position k in the face, a = loop[k], b = loop[k+1])."""
        f, kmax = self.pad.shape
        col = np.arange(kmax)
        if len(self.lens) and int(self.lens.min()) == kmax:
            face = np.repeat(np.arange(f), kmax)
            k = np.tile(col, f)
            return face, k, self.pad.reshape(-1), np.roll(self.pad, -1, axis=1).reshape(-1)
        mask = col[None, :] < self.lens[:, None]
        face = np.repeat(np.arange(f), self.lens)
        k = np.broadcast_to(col, self.pad.shape)[mask]
        return face, k, self.pad[mask], self.pad[face, (k + 1) % self.lens[face]]

    def loops(self) -> list[list[int]]:
        rows = self.pad.tolist()
        if len(self.lens) and int(self.lens.min()) == self.pad.shape[1]:
            return rows
        return [r[:n] for r, n in zip(rows, self.lens.tolist(), strict=True)]

    def distinct(self) -> tuple[_Faces, int]:
        """The faces without repeats: a face whose loop is an earlier face's, up to the starting
        vertex and the direction, is dropped (it covers the same point set, so it blocks nothing
        more; a repeated face would make each of its edges shared by four faces, which the shadow
        engine treats as a non-manifold edge, ~100x slower on a scan with 1 % of its faces
        repeated). **Returns:** (the faces left, in their order; the number dropped)."""
        keep = np.ones(len(self.lens), dtype=bool)
        for idx, arr in self.groups():
            if len(idx) < 2:
                continue
            k = arr.shape[1]
            start = np.argmin(arr, axis=1)  # each loop from its smallest index ...
            rot = arr[np.arange(len(arr))[:, None], (start[:, None] + np.arange(k)) % k]
            back = rot[:, 1] > rot[:, -1]  # ... in the direction of its smaller neighbour
            rot[back, 1:] = rot[back, :0:-1]
            _, first = np.unique(rot, axis=0, return_index=True)
            kept = np.zeros(len(idx), dtype=bool)
            kept[first] = True
            keep[idx[~kept]] = False
        dropped = int(len(keep) - keep.sum())
        if not dropped:
            return self, 0
        return _Faces(self.pad[keep], self.lens[keep]), dropped

    def padded_to(self, k: int) -> np.ndarray:
        """`(F, k)` vertex indices, padded with each face's first vertex (k >= K)."""
        if k == self.pad.shape[1]:
            return self.pad
        return np.concatenate([self.pad, np.repeat(self.pad[:, :1], k - self.pad.shape[1], axis=1)], axis=1)


def _normals(faces: _Faces, v: np.ndarray) -> np.ndarray:
    """Newell normals `(F, 3)` (not normalised) of all faces."""
    out = np.zeros((len(faces), 3))
    for idx, arr in faces.groups():
        out[idx] = _newell_many(v[arr])
    return out


def _unit(n: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return n / np.sqrt((n * n).sum(axis=1))[:, None]


def _check_faces(faces: _Faces, v: np.ndarray, size: float) -> None:
    """Zero-area and non-planar faces (the first offending face is reported). A face has zero
    area when twice its area is at most `COPLANAR_RTOL` times its own squared size (the largest
    distance of a vertex from its centroid): the rule of a polygon given to `Scene` (`DEGENERACY_RTOL`
    of `geometry.check_convex_polygon`), so a sliver that a soup may hold is a face of a `Mesh` too."""
    bad = np.zeros(len(faces), dtype=np.int8)  # 1: zero area, 2: not planar
    for idx, arr in faces.groups():
        pts = v[arr]
        # Newell's normal of the vertices about their centroid: the sum of products of absolute
        # coordinates cancels for a small face far from the origin (a sliver read as non-planar).
        rel = pts - pts.mean(axis=1, keepdims=True)
        n = _newell_many(rel)
        area = np.sqrt((n * n).sum(axis=1))
        own = np.sqrt((rel * rel).sum(axis=2)).max(axis=1)
        zero = ~(area > COPLANAR_RTOL * own * own)
        with np.errstate(invalid="ignore", divide="ignore"):
            off = np.abs(_plane_values(pts, pts[:, :1], (n / area[:, None])[:, None, :])).max(axis=1)
        bad[idx] = np.where(zero, 1, np.where(off > 1e-6 * size, 2, 0))
    hit = np.flatnonzero(bad)
    if len(hit):
        i = int(hit[0])
        raise ValueError(f"Mesh: face {i} has zero area." if bad[i] == 1 else f"Mesh: face {i} is not planar.")


def _index(x: Any, i: int) -> int:
    """One vertex index: an integer, or a number with an integral value (2.0); 2.5 is refused
    rather than truncated."""
    try:
        return operator.index(x)
    except TypeError:
        pass
    try:
        xf = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"Mesh: face {i} has a vertex index that is not an integer: {x!r}.") from None
    if not (math.isfinite(xf) and xf == int(xf)):
        raise ValueError(f"Mesh: face {i} has a vertex index that is not an integer: {x!r}.")
    return int(xf)


def _face_loops(faces: Any, n_vertices: int) -> list[list[int]]:
    arr = None
    if isinstance(faces, np.ndarray) or (isinstance(faces, list | tuple) and faces
                                         and all(isinstance(f, np.ndarray | list | tuple) for f in faces[:1])):
        try:
            arr = np.asarray(faces)
        except (ValueError, TypeError):
            arr = None
    if arr is not None and arr.ndim == 2 and arr.dtype.kind in "biuf":
        if arr.dtype.kind == "f":
            nonint = ~np.all(np.isfinite(arr) & (arr == np.round(arr)), axis=1)
            if nonint.any():
                i = int(np.flatnonzero(nonint)[0])
                bad = arr[i][~(np.isfinite(arr[i]) & (arr[i] == np.round(arr[i])))][0]
                raise ValueError(f"Mesh: face {i} has a vertex index that is not an integer: {bad!r}.")
        if arr.shape[1] != 3:
            return _face_loops_generic(arr.astype(np.int64).tolist(), n_vertices)
        a = arr.astype(np.int64) if arr.dtype.kind != "i" or arr.dtype.itemsize != 8 else arr
        if arr.dtype.kind == "u" and arr.size and arr.max() > np.iinfo(np.int64).max:
            return _face_loops_generic(arr.tolist(), n_vertices)
        out_of_range = np.any((a < 0) | (a >= n_vertices), axis=1)
        repeated = (a[:, 0] == a[:, 1]) | (a[:, 1] == a[:, 2]) | (a[:, 2] == a[:, 0])
        hit = np.flatnonzero(out_of_range | repeated)
        if len(hit):
            i = int(hit[0])
            if out_of_range[i]:
                raise ValueError(f"Mesh: face {i} has a vertex index out of range [0, {n_vertices}).")
            raise ValueError(f"Mesh: face {i} needs at least three distinct vertices, got {a[i].tolist()}.")
        return a.tolist()  # a triangle with three distinct vertices is its own deduplicated loop
    return _face_loops_generic(faces, n_vertices)


def _face_loops_generic(faces: Any, n_vertices: int) -> list[list[int]]:
    out = []
    for i, f in enumerate(faces):
        loop = [_index(x, i) for x in f]
        if any(j < 0 or j >= n_vertices for j in loop):
            raise ValueError(f"Mesh: face {i} has a vertex index out of range [0, {n_vertices}).")
        dedup = [a for k, a in enumerate(loop) if a != loop[k - 1]]
        if len(set(dedup)) < 3 or len(set(dedup)) != len(dedup):
            raise ValueError(f"Mesh: face {i} needs at least three distinct vertices, got {loop}.")
        out.append(dedup)
    return out



def _face_table(faces: Any, n_vertices: int) -> _Faces:
    """`_face_loops` as a `_Faces` table (an `(F, 3)` array of triangles without a Python list)."""
    if isinstance(faces, np.ndarray) and faces.ndim == 2 and faces.shape[1] == 3 and faces.dtype.kind in "iu" \
            and not (faces.dtype.kind == "u" and faces.size and faces.max() > np.iinfo(np.int64).max):
        a = faces.astype(np.int64)
        out_of_range = np.any((a < 0) | (a >= n_vertices), axis=1)
        repeated = (a[:, 0] == a[:, 1]) | (a[:, 1] == a[:, 2]) | (a[:, 2] == a[:, 0])
        if not np.any(out_of_range | repeated):
            return _Faces(a, np.full(len(a), 3, dtype=np.intp))
    return _Faces.of(_face_loops(faces, n_vertices))


@dataclass(frozen=True)
class _EdgeIndex:
    """The directed edges of one face table (`_Faces.edges`, keys `a n + b` for `n` vertices)
    sorted once: `order` the stable argsort of `keys`, `ks = keys[order]`, `pos` where each edge's
    reverse would sit in `ks` (clipped to the last entry). `_closed` decides with it and `_merge`
    reuses it for the same table."""

    face: np.ndarray
    ea: np.ndarray
    eb: np.ndarray
    keys: np.ndarray
    order: np.ndarray
    ks: np.ndarray
    rev: np.ndarray
    pos: np.ndarray

    @staticmethod
    def of(faces: _Faces, n_vertices: int) -> _EdgeIndex:
        face, _, a, b = faces.edges()
        n = np.int64(n_vertices)
        keys = a.astype(np.int64) * n + b
        order = np.argsort(keys, kind="stable")
        ks = keys[order]
        rev = b.astype(np.int64) * n + a
        pos = np.minimum(np.searchsorted(ks, rev), len(ks) - 1)
        return _EdgeIndex(face, a, b, keys, order, ks, rev, pos)


def _closed(faces: _Faces, v: np.ndarray) -> tuple[bool, bool, _EdgeIndex | None]:
    """(closed, flip, index): every edge used once in each direction; flip when the volume is
    negative; `index` the table's `_EdgeIndex` (None for no faces)."""
    if not len(faces):
        return True, False, None
    ix = _EdgeIndex.of(faces, v.shape[0])
    keys = ix.ks
    if np.any(keys[1:] == keys[:-1]):
        return False, False, ix
    if not np.all(keys[ix.pos] == ix.rev):
        return False, False, ix
    c = v.mean(axis=0)
    vol = np.zeros(len(faces))
    for idx, arr in faces.groups():
        pts = v[arr] - c
        nrm = _newell_many(pts)
        vol[idx] = _plane_values(pts[:, 0], 0.0, nrm)
    return True, bool(np.cumsum(vol)[-1] < 0), ix  # summed in face order, as a Python sum would



def _convex(faces: _Faces, v: np.ndarray, size: float) -> bool:
    """Every vertex on or behind every face plane: max over vertices of (v - p0) . n <= 1e-9 size
    for every face (p0 its first vertex, n its unit Newell normal).

    Four steps, each deciding exactly that test. (0) A few faces against every vertex. (1) Local: the vertices of each face's
    neighbours (across an edge) against its plane; any one in front is a witness, not convex
    (cheap, and what a non-convex mesh almost always fails). (2) Small meshes: every vertex
    against every plane, in chunks. (3) Large meshes: the maximum of a linear function over the
    vertices is attained at a vertex of their convex hull, and on a convex polytope a vertex none
    of whose hull neighbours has a larger value attains that maximum (the simplex method's
    argument). So each face's maximum is found by climbing the hull's edge graph from a vertex
    of the face; a climbed value above the tolerance is a witness (not convex); faces whose
    climbed value lies within half the tolerance of it (far above Qhull's round-off, far below
    the tolerance for a convex mesh, whose faces' maxima are their own vertices, ~0) are checked
    against every vertex directly, so round-off in the hull cannot change the answer."""
    tol = 1e-9 * size
    f_all = len(faces)
    nrm = _unit(_normals(faces, v))
    pad = faces.pad
    p0 = v[pad[:, 0]]
    # (0) Sixteen faces spread over the mesh against every vertex: a non-convex mesh almost
    # always has a witness among them, found before step (1)'s sort of the edges.
    if not _convex_brute(np.unique(np.linspace(0, f_all - 1, min(f_all, 16)).astype(np.intp)), v, p0, nrm, tol):
        return False
    # (1) neighbours' vertices against each face's plane.
    face, _, a, b = faces.edges()
    n = np.int64(v.shape[0])
    keys = a.astype(np.int64) * n + b
    order = np.argsort(keys, kind="stable")
    rev = b.astype(np.int64) * n + a
    pos = np.minimum(np.searchsorted(keys[order], rev), len(keys) - 1)
    found = keys[order][pos] == rev
    f, g = face[found], face[order[pos[found]]]
    for s in range(0, len(f), 200_000):
        fs, gs = f[s:s + 200_000], g[s:s + 200_000]
        if np.max(_plane_values(v[pad[gs]], p0[fs][:, None], nrm[fs][:, None])) > tol:
            return False
    # (2) every vertex against every plane.
    if f_all * v.shape[0] <= 4_000_000:
        return _convex_brute(np.arange(f_all), v, p0, nrm, tol)
    # (3) climb the convex hull's edge graph.
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(v)
    except (QhullError, ValueError):
        return _convex_brute(np.arange(f_all), v, p0, nrm, tol)
    s = hull.simplices
    src = np.concatenate([s[:, 0], s[:, 1], s[:, 2], s[:, 1], s[:, 2], s[:, 0]])
    dst = np.concatenate([s[:, 1], s[:, 2], s[:, 0], s[:, 0], s[:, 1], s[:, 2]])
    pairs = np.unique(src.astype(np.int64) * n + dst)
    src, dst = (pairs // n).astype(np.intp), (pairs % n).astype(np.intp)
    indptr = np.concatenate([[0], np.cumsum(np.bincount(src, minlength=v.shape[0]))]).astype(np.intp)
    on_hull = np.zeros(v.shape[0], dtype=bool)
    on_hull[hull.vertices] = True
    cur = np.where(on_hull[pad[:, 0]], pad[:, 0], hull.vertices[0])
    val = _plane_values(v[cur], p0, nrm)
    active = np.arange(f_all)
    while len(active):
        c = cur[active]
        deg = indptr[c + 1] - indptr[c]
        seg = np.repeat(np.arange(len(active)), deg)
        first = np.concatenate([[0], np.cumsum(deg)[:-1]]).astype(np.intp)
        nb = dst[indptr[c][seg] + np.arange(len(seg)) - first[seg]]
        nv = _plane_values(v[nb], p0[active][seg], nrm[active][seg])
        best = np.full(len(active), -np.inf)
        np.maximum.at(best, seg, nv)
        up = best > val[active]
        if not up.any():
            break
        # The first neighbour attaining each face's best value.
        hit = np.flatnonzero(nv == best[seg])
        pick = np.full(len(active), -1)
        pick[seg[hit][::-1]] = nb[hit][::-1]
        moved = active[up]
        cur[moved] = pick[up]
        val[moved] = best[up]
        active = moved
    if np.any(val > tol):
        return False
    unsure = np.flatnonzero(val > 0.5 * tol)
    return _convex_brute(unsure, v, p0, nrm, tol) if len(unsure) else True


def _convex_brute(faces: np.ndarray, v: np.ndarray, p0: np.ndarray, nrm: np.ndarray, tol: float) -> bool:
    step = max(1, 2_000_000 // max(1, v.shape[0]))
    for s in range(0, len(faces), step):
        fs = faces[s:s + step]
        if np.max(_plane_values(v[None], p0[fs][:, None], nrm[fs][:, None])) > tol:
            return False
    return True




def _coplanar(ni: np.ndarray, nj: np.ndarray, pts_j: np.ndarray, p0_i: np.ndarray, size: float) -> Any:
    """The merge test of two faces: unit normals `ni`, `nj`, `pts_j` the vertices of face j (last
    two axes), `p0_i` the first vertex of face i. Broadcasts (one or many pairs, same rounding)."""
    dot = ni[..., 0] * nj[..., 0] + ni[..., 1] * nj[..., 1] + ni[..., 2] * nj[..., 2]
    off = np.abs(_plane_values(pts_j, p0_i[..., None, :], ni[..., None, :])).max(axis=-1)
    return ~(dot < 1 - 1e-12) & ~(off > COPLANAR_RTOL * size)


def _coplanar1(ni: list[float], nj: list[float], pts_j: list[list[float]], p0: list[float], size: float) -> bool:
    """`_coplanar` of one pair in Python floats: the same operations in the same order (each
    NumPy operation above is one IEEE operation per element), so the same answer."""
    if ni[0] * nj[0] + ni[1] * nj[1] + ni[2] * nj[2] < 1 - 1e-12:
        return False
    tol = COPLANAR_RTOL * size
    for q in pts_j:
        if abs((q[0] - p0[0]) * ni[0] + (q[1] - p0[1]) * ni[1] + (q[2] - p0[2]) * ni[2]) > tol:
            return False
    return True


class _Rows:
    """Rows of an array as Python lists, converted when first read (`lens`: each row's length),
    and assignable: the merge reads the few faces it touches, not the whole mesh."""

    def __init__(self, a: np.ndarray, lens: np.ndarray | None = None):
        self.a, self.lens, self.rows = a, lens, {}

    def __getitem__(self, i: int) -> Any:
        r = self.rows.get(i)
        if r is None:
            r = self.rows[i] = (self.a[i] if self.lens is None else self.a[i, :self.lens[i]]).tolist()
        return r

    def __setitem__(self, i: int, row: Any) -> None:
        self.rows[i] = row


def _merge(faces: _Faces, v: np.ndarray, size: float, index: _EdgeIndex | None = None) -> _Faces:
    """Merge coplanar faces sharing an edge while the union stays a convex polygon (greedy, one
    pass over a queue of shared edges; a merged face's edges are queued again).

    Whether two faces are coplanar is first decided for every shared edge at once (vectorised);
    an edge between two faces that no merge has touched yet uses that answer, so a mesh without
    coplanar neighbours (a smooth surface) costs no Python loop over its edges. The loop over
    the rest works on Python floats (`_coplanar1`, `_union`).

    The queue is the one a dict of directed edges (`(a, b) -> the last face running a -> b`,
    filled in face order) gives: its shared edges with a < b in first-occurrence order, then the
    merged faces' edges pushed on top, popped from the top. Only its entries that can merge are
    visited: an entry whose two directed edges no merge has written or removed yet ("clean")
    still has its first owners, which no merge has touched, so it merges only where the
    vectorised test said coplanar; the others (written by a merge, tracked as they are
    written) run the full test. The owners live in the sorted edge keys plus a dict of what
    merges changed, so a mesh with a few coplanar pairs pays for those, not for its edges.
    `index`: this table's `_EdgeIndex` when the caller has it (`_closed`'s)."""
    if not len(faces):
        return faces
    normals = _unit(_normals(faces, v))
    pad = faces.pad
    ix = index if index is not None else _EdgeIndex.of(faces, v.shape[0])
    face, ea, eb, keys, order, ks, rev = ix.face, ix.ea, ix.eb, ix.keys, ix.order, ix.ks, ix.rev
    n = np.int64(v.shape[0])
    # owner[(a, b)]: the last face running a -> b (as a dict filled in face order would hold).
    last = np.concatenate([ks[1:] != ks[:-1], [True]])
    if last.all():  # no directed edge twice: each key's owner is its own face
        ukeys, uface = ks, face[order]
        pos = ix.pos
        shared = (ukeys[pos] == rev) & (ea < eb)
        fi = face[shared]
    else:
        ukeys, uface = ks[last], face[order[last]]
        pos = np.minimum(np.searchsorted(ukeys, rev), len(ukeys) - 1)
        shared = (ukeys[pos] == rev) & (ea < eb)
        fi = uface[np.searchsorted(ukeys, keys[shared])]
    fj = uface[pos[shared]]
    # The merge test (`_coplanar`) on the pairs whose normals pass its first half only: the
    # others fail it whatever their vertices (the same operations on fewer rows).
    ni_, nj_ = normals[fi], normals[fj]
    near = ~((ni_[:, 0] * nj_[:, 0] + ni_[:, 1] * nj_[:, 1] + ni_[:, 2] * nj_[:, 2]) < 1 - 1e-12) & (fi != fj)
    sel = np.flatnonzero(near)
    ok = np.zeros(len(fi), dtype=bool)
    ok[sel] = _coplanar(ni_[sel], nj_[sel], v[pad[fj[sel]]], v[pad[fi[sel], 0]], size)
    if not ok.any():
        return faces
    ni = int(n)
    candidates = set((ea[shared][ok] * n + eb[shared][ok]).tolist())
    # The initial queue: each distinct shared edge a -> b (a < b) at its first occurrence, in
    # edge order (whether an edge is shared, and the merge test, depend on its key alone).
    is_first = np.zeros(len(keys), dtype=bool)
    is_first[order[np.concatenate([[True], ks[1:] != ks[:-1]])]] = True
    in_queue = is_first & shared
    qat = np.flatnonzero(in_queue)
    qkeys = keys[qat]  # the queue, bottom first
    ok_edge = np.zeros(len(keys), dtype=bool)
    ok_edge[np.flatnonzero(shared)[ok]] = True
    cand_pos = np.flatnonzero(ok_edge[qat]).tolist()  # ascending; visited from the top
    # Queue entries by key (for `touch`): the sorted keys with their queue positions.
    qsorted = np.argsort(qkeys, kind="stable")
    qs_keys_a, qs_pos_a = qkeys[qsorted], qsorted
    # Python lists where the loop looks up many keys; NumPy searches where it looks up few.
    many = 16 * len(candidates) > len(faces)
    changed: dict[int, int] = {}  # owners a merge wrote (-1: removed)
    if many:
        ukeys_l, uface_l = ukeys.tolist(), uface.tolist()
        qs_keys, qs_pos = qs_keys_a.tolist(), qs_pos_a.tolist()

        def find_owner(k: int) -> int:
            x = bisect.bisect_left(ukeys_l, k)
            return uface_l[x] if x < len(ukeys_l) and ukeys_l[x] == k else -1

        def find_queue(u: int) -> int:
            x = bisect.bisect_left(qs_keys, u)
            return qs_pos[x] if x < len(qs_keys) and qs_keys[x] == u else -1
    else:
        nk, nq = len(ukeys), len(qs_keys_a)

        def find_owner(k: int) -> int:
            x = int(np.searchsorted(ukeys, k))
            return int(uface[x]) if x < nk and int(ukeys[x]) == k else -1

        def find_queue(u: int) -> int:
            x = int(np.searchsorted(qs_keys_a, u))
            return int(qs_pos_a[x]) if x < nq and int(qs_keys_a[x]) == u else -1

    def own(k: int) -> int:
        c = changed.get(k)
        if c is not None:
            return c
        return find_owner(k)

    top = len(qkeys) - 1  # the highest queue entry not yet visited
    dirty: list[int] = []  # max-heap (negated) of queue entries written by a merge

    def touch(k: int) -> None:  # owner of edge key k written: its queue entry (if any) is visited
        a, b = divmod(k, ni)
        x = find_queue(k if a < b else b * ni + a)
        if 0 <= x <= top:
            heapq.heappush(dirty, -x)

    loops = _Rows(pad, faces.lens)
    # Rows read on demand where few faces can merge; all at once where many do (cheaper per row).
    vl: Any = v.tolist() if many else _Rows(v)
    nl: Any = normals.tolist() if many else _Rows(normals)
    touched = [False] * len(faces)
    alive = [True] * len(faces)
    stack: list[int] = []
    while True:
        if stack:
            key = stack.pop()
        else:
            while cand_pos and cand_pos[-1] > top:
                cand_pos.pop()
            while dirty and -dirty[0] > top:
                heapq.heappop(dirty)
            s = max(cand_pos[-1] if cand_pos else -1, -dirty[0] if dirty else -1)
            if s < 0:
                break
            top = s - 1
            key = int(qkeys[s])
        a, b = divmod(key, ni)
        i, j = own(key), own(b * ni + a)
        if i < 0 or j < 0 or i == j or not (alive[i] and alive[j]):
            continue
        if not (touched[i] or touched[j]):
            if key not in candidates:
                continue
        elif not _coplanar1(nl[i], nl[j], [vl[x] for x in loops[j]], vl[loops[i][0]], size):
            continue
        m = _union(loops[i], loops[j], a, b, vl, v, nl[i], normals[i])
        if m is None:
            continue
        lj, li = loops[j], loops[i]
        for lp in (lj, li):
            for k in range(len(lp)):
                e = lp[k] * ni + lp[(k + 1) % len(lp)]
                if own(e) >= 0:
                    changed[e] = -1
                    touch(e)
        loops[i] = m
        alive[j] = False
        touched[i] = touched[j] = True
        for k in range(len(m)):
            e = m[k] * ni + m[(k + 1) % len(m)]
            changed[e] = i
            touch(e)
            if own(m[(k + 1) % len(m)] * ni + m[k]) >= 0:
                stack.append(e)
    keep = np.flatnonzero(np.asarray(alive))
    merged = [x for x in keep.tolist() if touched[x]]
    k_out = max([int(faces.lens[keep].max(initial=3))] + [len(loops[x]) for x in merged])
    out = faces.padded_to(k_out).copy() if k_out >= pad.shape[1] else pad[:, :k_out].copy()
    lens = faces.lens.copy()
    for x in merged:
        lp = loops[x]
        out[x, :len(lp)] = lp
        out[x, len(lp):] = lp[0]
        lens[x] = len(lp)
    return _Faces(out[keep], lens[keep])


def _straight(p0: list[float], p1: list[float], p2: list[float], nrm: list[float], v: np.ndarray, idx: tuple[int, int, int],
              nrm_np: np.ndarray) -> bool:
    """Whether the boundary goes straight at p1: |((p1 - p0) x (p2 - p1)) . n| <= 1e-12 |p1 - p0| |p2 - p1|.
    Decided in Python floats when the two sides differ by more than a factor of two; otherwise
    (a near tie) by the NumPy expression (whose dot products may round differently)."""
    d1 = (p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2])
    d2 = (p2[0] - p1[0], p2[1] - p1[1], p2[2] - p1[2])
    turn = abs((d1[1] * d2[2] - d1[2] * d2[1]) * nrm[0] + (d1[2] * d2[0] - d1[0] * d2[2]) * nrm[1]
               + (d1[0] * d2[1] - d1[1] * d2[0]) * nrm[2])
    bound = 1e-12 * math.sqrt(d1[0] * d1[0] + d1[1] * d1[1] + d1[2] * d1[2]) * math.sqrt(
        d2[0] * d2[0] + d2[1] * d2[1] + d2[2] * d2[2])
    if turn > 2 * bound:
        return False
    if turn < 0.5 * bound:
        return True
    q0, q1, q2 = v[idx[0]], v[idx[1]], v[idx[2]]
    t = np.dot(_cross3(q1 - q0, q2 - q1), nrm_np)
    return bool(abs(t) <= 1e-12 * np.linalg.norm(q1 - q0) * np.linalg.norm(q2 - q1))


def _union(la: list[int], lb: list[int], a: int, b: int, vl: Any, v: np.ndarray, nrm: list[float],
           nrm_np: np.ndarray) -> list[int] | None:
    """`la` (containing a -> b) and `lb` (containing b -> a) glued along that edge, if convex
    (`vl`: the vertices as Python lists, indexed by vertex (a list of rows or `_Rows`), `v` as an
    array; `nrm` the unit normal of `la`)."""
    ia = la.index(a)
    ra = la[ia + 1:] + la[:ia + 1]  # starts after a, ends at a; la's a -> b edge is last-to-first
    # ra runs b ... a (b first). Glue lb from a to b (excluding the shared ends).
    ib = lb.index(b)
    rb = lb[ib + 1:] + lb[:ib + 1]  # starts after b, so runs a ... b
    out = ra + rb[1:-1]
    # Drop vertices where the boundary goes straight (the merge removes the shared edge only).
    done = False
    while not done and len(out) > 3:
        done = True
        for k in range(len(out)):
            i0, i1, i2 = out[k - 1], out[k], out[(k + 1) % len(out)]
            if _straight(vl[i0], vl[i1], vl[i2], nrm, v, (i0, i1, i2), nrm_np):
                out = out[:k] + out[k + 1:]
                done = False
                break
    if len(out) > MAX_MERGED_VERTICES or len(set(out)) != len(out):
        return None
    # Strictly convex: every turn ((p[k+1] - p[k]) x (p[k+2] - p[k+1])) . n > 0, in the order
    # of operations of the vectorised form (e = roll(p, -1) - p, e2 = roll(e, -1)).
    pts = [vl[x] for x in out]
    m = len(pts)
    e = [(pts[(k + 1) % m][0] - pts[k][0], pts[(k + 1) % m][1] - pts[k][1], pts[(k + 1) % m][2] - pts[k][2]) for k in range(m)]
    for k in range(m):
        x, y = e[k], e[(k + 1) % m]
        turn = (x[1] * y[2] - x[2] * y[1]) * nrm[0] + (x[2] * y[0] - x[0] * y[2]) * nrm[1] + (x[0] * y[1] - x[1] * y[0]) * nrm[2]
        if turn <= 0:
            return None
    return out



def _solid_edges(faces: _Faces) -> list[tuple[int, int, int, int, int, int]] | None:
    """Per undirected edge of a closed polygon mesh: (f_left, k_a, k_b, f_right) with the edge
    running loop[f_left][k_a] -> loop[f_left][k_b] in f_left; None when some edge does not have
    exactly one opposite (a merge left a vertex on an edge of a neighbour)."""
    face, ka, a, b = faces.edges()
    n = np.int64(max(int(a.max(initial=0)), int(b.max(initial=0))) + 1)
    keys = a.astype(np.int64) * n + b
    order = np.argsort(keys, kind="stable")
    ks = keys[order]
    if np.any(ks[1:] == ks[:-1]):
        return _solid_edges_dict(faces.loops())
    rev = b.astype(np.int64) * n + a
    pos = np.minimum(np.searchsorted(ks, rev), len(ks) - 1)
    if len(ks) == 0 or not np.all(ks[pos] == rev):
        return None if len(ks) else []
    lens = faces.lens
    kb = (ka + 1) % lens[face]
    sel = a < b
    cols = (face[sel], ka[sel], kb[sel], face[order[pos[sel]]], a[sel], b[sel])
    return list(zip(*(c.tolist() for c in cols), strict=True))


def _solid_edges_dict(loops: list[list[int]]) -> list[tuple[int, int, int, int, int, int]] | None:
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
