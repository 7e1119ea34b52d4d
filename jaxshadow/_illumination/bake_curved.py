"""A curved bake chunk: conforming refinement of a curved triangle set (`_refine_curved`), faces' own
limits at their edges where the surface shadows itself, corners (concave folds, the terminator's
vertices) graded apart (`bake`, step 2)."""

from __future__ import annotations

from itertools import combinations

import numpy as np

from .._scene.model import Scene
from .bake_patches import _Patch
from .bake_values import _CODE, ON_SURFACE, _light_points, _on_point, _values
from .builder import ESTIMATE_MARGIN
from .refine import CORNER_GRADE, CORNER_SIZE

# A point on an edge of its receiver face takes the limit from inside the face: extrapolated
# linearly from the values CURVED_STEP and 2 CURVED_STEP (of the patch's size) inside, towards
# the face's centroid (error O(step^2)). Closer in, a neighbouring face is seen within the
# engine's horizon band (1e-7 rad: nearly edge-on faces block nothing) and still takes the
# point for one of its own.
CURVED_STEP = 1e-6


def exact_planes(occ: np.ndarray) -> np.ndarray:
    """`occ` with every float32 coordinate moved one double ulp up (`np.nextafter`): its faces
    then take the double on-surface rule (`jaxshadow._kernels.planes.ON_SURFACE_64`, 2^-44 of
    the coordinates' magnitude) instead of the float32 one (2^-18). A curved patch's points are
    computed in float64 on its own faces, so they lie in those planes to double rounding; under
    the float32 rule a point of a face within 2^-18 S / sin(dihedral angle) of an edge (1e-5 m
    on a 22-segment sphere of 1 m) counts as lying on the neighbouring face too, which then
    blocks nothing: a band along every edge near the terminator with another value, which no
    refinement resolves. The geometry moves by one ulp (2e-16 relative)."""
    occ = np.asarray(occ, np.float64)
    f32 = occ.astype(np.float32).astype(np.float64) == occ
    return np.where(f32, np.nextafter(occ, np.inf), occ)


def _front(scenes: list[Scene], corners: np.ndarray, size: float) -> np.ndarray:
    """`(L, t)` whether each light lies strictly in front of the plane of each face `corners
    (t, 3, 3)` (beyond 1e-9 of `size`): then the light sees no difference between the face
    and its neighbours' planes at the face's edges (see `_refine_curved`)."""
    from .._scene.model import DirectionalLight

    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    out = np.zeros((len(scenes), corners.shape[0]), bool)
    for li, sc in enumerate(scenes):
        light = sc.lights[0]
        if isinstance(light, DirectionalLight):
            d = np.asarray(light.direction, np.float64)
            out[li] = -(n @ (d / np.linalg.norm(d))) > 1e-9
            continue
        lp = _light_points(light, corners[:, 0], 0.0)  # (k, 3)
        h = np.einsum("tkd,td->tk", lp[None, :, :] - corners[:, None, 0, :], n)
        out[li] = np.all(h > 1e-9 * size, axis=1)
    return out


def _star_pairs(tri: np.ndarray) -> np.ndarray:
    """`(p, 2)` the ordered pairs of distinct faces of `tri (t, 3)` that share a corner."""
    star: dict[int, list[int]] = {}
    for f, t in enumerate(tri.tolist()):
        for v in t:
            star.setdefault(v, []).append(f)
    pairs = {(f, g) for fs in star.values() for f in fs for g in fs if f != g}
    return np.array(sorted(pairs), np.int64).reshape(-1, 2)


def _own_occluders(scenes: list[Scene], tri: np.ndarray, P: np.ndarray, size: float) -> np.ndarray:
    """`(t,)` the occluder face of the scene each face `tri (t, 3)` (vertex positions `P`) lies
    in (its three corners among that face's corners, within 1e-7 of `size`: a face `Mesh`
    merged from coplanar triangles holds several), -1 for none: only then does the
    surface shadow itself next to its own edges (the on-surface rule at points of them)."""
    from scipy.spatial import cKDTree

    occ = scenes[0].occluders if scenes else None
    out = np.full(tri.shape[0], -1, np.int64)
    if occ is None or tri.shape[0] == 0:
        return out
    occ = np.asarray(occ, np.float64)
    dist, idx = cKDTree(P).query(occ.reshape(-1, 3), distance_upper_bound=1e-7 * size)
    idx = np.where(np.isfinite(dist), idx, -1).reshape(occ.shape[:2])
    hit: dict[tuple[int, ...], int] = {}
    for o, row in enumerate(idx.tolist()):
        ids = sorted(set(row))
        if len(ids) >= 3 and ids[0] >= 0:  # a merged coplanar face holds several of the receiver's
            hit.update((c, o) for c in combinations(ids, 3))
    for f, t in enumerate(tri.tolist()):
        out[f] = hit.get(tuple(sorted(t)), -1)
    return out


def _under_plane_lit(scenes: list[Scene], v: np.ndarray, nf: np.ndarray, nv: np.ndarray, eps: float) -> bool:
    """Whether a light of `scenes` has a part strictly below the plane through `v` of normal
    `nf` (by more than `eps`, m) that lies strictly above the tangent plane of normal `nv`
    there: the part the faces below that plane can block for points near `v`."""
    from .._scene.model import DirectionalLight

    for sc in scenes:
        light = sc.lights[0]
        if isinstance(light, DirectionalLight):
            w = -np.asarray(light.direction, np.float64)
            w = w / np.linalg.norm(w)
            if w @ nf < -1e-9 and w @ nv > 1e-9:
                return True
            continue
        q = _light_points(light, v[None, :], 0.0)
        h = (q - v) @ nf
        kept = [q[i] for i in range(q.shape[0]) if h[i] < -eps]  # the light clipped to below the plane
        for i in range(q.shape[0]):
            j = (i + 1) % q.shape[0]
            if (h[i] < -eps) != (h[j] < -eps) and h[i] != h[j]:
                kept.append(q[i] + (-eps - h[i]) / (h[j] - h[i]) * (q[j] - q[i]))
        if kept and np.max((np.array(kept) - v) @ nv) > eps:
            return True
    return False


def _folded(scenes: list[Scene], tri: np.ndarray, corners: np.ndarray, P: np.ndarray, N: np.ndarray, size: float,
            own: np.ndarray) -> np.ndarray:
    """The vertex ids where faces lying in two or more occluder faces of the surface (`own`:
    `_own_occluders`) meet and the faces around shadow the light for points of one of them
    near the vertex: one rises above another's plane (by more than `ON_SURFACE` of the largest
    coordinate magnitude, float32 rounding of the vertices apart, and faces of one occluder
    face apart: a concave fold's corner), or a light has a
    part below one's plane and above the tangent plane of the vertex normal `N` (the
    terminator: the faces below that plane block some of it, `_under_plane_lit`). Seen from a
    point of a face at distance r from such a vertex, the faces around it hide a solid angle
    that does not shrink with r but turns with the direction of approach, so the irradiance
    takes a different limit along each direction (as at the corner of a box standing on a
    floor): no mesh of linear elements meets `tol` there."""
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    star: dict[int, list[int]] = {}
    for f, t in enumerate(tri.tolist()):
        if own[f] >= 0:
            for v in t:
                star.setdefault(v, []).append(f)
    rise = ON_SURFACE * float(np.abs(P).max(initial=0.0))
    out = []
    for v, fs in star.items():
        fs_a = np.array(fs)
        if np.unique(own[fs_a]).size < 2:
            continue
        h = np.einsum("gkd,fd->fgk", P[tri[fs_a]] - P[v], n[fs_a])  # every corner against every plane
        h[own[fs_a][:, None] == own[fs_a][None, :]] = 0.0  # faces of one (planar) occluder face
        if np.any(h > rise) or any(_under_plane_lit(scenes, P[v], n[f], N[v], 1e-9 * size) for f in fs):
            out.append(v)
    return np.array(sorted(out), np.int64)


def _concave(tri: np.ndarray, corners: np.ndarray, P: np.ndarray, size: float, pairs: np.ndarray) -> np.ndarray:
    """`(t,)` whether a face sharing a corner with each face `tri (t, 3)` (corners `(t, 3, 3)`,
    vertex positions `P`) rises above its plane (by more than 1e-9 of `size`): at its edges
    and corners that face shadows the face's inside (a concave fold), but not the points on the
    edge itself (which lie on it: the on-surface rule)."""
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    out = np.zeros(tri.shape[0], bool)
    if pairs.size:
        h = np.einsum("pkd,pd->pk", P[tri[pairs[:, 1]]] - corners[pairs[:, 0], 0][:, None, :], n[pairs[:, 0]])
        out[pairs[np.any(h > 1e-9 * size, axis=1), 0]] = True
    return out


def _refine_curved(scenes: list[Scene], patch: _Patch, pos: np.ndarray, tol: float, scale: float,
                   min_edge: float, max_vertices: int, max_rounds: int) -> dict[str, np.ndarray]:
    """Conforming refinement of a curved triangle set: edges whose midpoint value misses the
    mean of its ends by more than `ESTIMATE_MARGIN * tol * scale` (max over RGB of the light
    sum; the margin as `illumination_mesh`'s: the checked points bound the error elsewhere only
    roughly), and the three edges of triangles whose centroid misses the mean of the corners,
    are split; a triangle with
    two split edges gets its third split too (red: 1-to-4), one with one is bisected (green).
    Stops when no edge fails, at `max_vertices`, or after `max_rounds` rounds. The result
    reports `rounds`, `unrefined` (edges whose midpoint still misses `tol`, the short ones
    included), `stopped` (1: stopped by `max_vertices` with edges failing), `error` (the
    largest midpoint miss over `scale`) and `corner_error` (the same for the edges within
    `CORNER_SIZE` of the patch's size of a corner, `_folded`: a concave fold's, or one at the
    terminator; there the irradiance has a different limit along each direction, as at a standing box's footprint
    corner in `illumination_mesh`; those edges are not split and are left out of the others).

    **Values per receiver face.** Each triangle lies in one of the patch's own faces (its
    *face*) and takes that face's values: at a point inside the face, the exact irradiance there
    (the occluders with `exact_planes`); at a point on the face's edges or corners, the limit
    from inside the face (extrapolated from two points `CURVED_STEP` and twice that of the
    patch's size towards the face's centroid). The limit differs from the point's own value
    only where the surface is an occluder next to the face (`_own_occluders`; at a point of an
    edge both faces then lie on the point and block nothing) and, for a light, where that light
    is not strictly in front of the face's plane (`_front`: the terminator, where the faces'
    planes cut the light differently and the irradiance of the faceted surface jumps across its
    edges, the shadow-terminator step of a polygonal mesh) or a face sharing a corner rises
    above the face's plane (`_concave`: it shadows the face's inside up to the edge); elsewhere
    the point's own value is taken. A point where a limit was taken is one vertex per face
    (`side`: the face index + 1), any other one vertex. Points on the patch's boundary edges
    (shared with other patches) take their own value, so that both patches carry the same.

    Vertices are *value vertices* (a point and a face); the splitting decisions are made on
    *geometric* edges (pairs of points), so the two faces' triangles along an edge split
    together and the mesh stays conforming. Edges are int64 codes `a * _CODE + b` (`a < b`):
    each round's unique edges, the cache of evaluated midpoints and the inserted midpoints are
    sorted code arrays (`np.searchsorted`); only the few edges with both ends on the patch's
    boundary go through Python (their points are recorded for stitching)."""
    tri0 = patch.data["tri"].astype(np.int64)
    vwid = patch.data["vwid"]
    P0 = patch.data["vpos"].astype(np.float64)
    t0 = tri0.shape[0]
    corners = P0[tri0]
    size = float(np.max(np.ptp(P0, axis=0))) or 1.0
    step = CURVED_STEP * size
    pairs = _star_pairs(tri0)
    # where the point's own value is not the face's limit (see the docstring): push those
    push = ~_front(scenes, corners, size) | _concave(tri0, corners, P0, size, pairs)[None, :]
    holder = _own_occluders(scenes, tri0, P0, size)
    folded = P0[_folded(scenes, tri0, corners, P0, patch.data["vnrm"].astype(np.float64), size, holder)]
    own = holder >= 0
    own[pairs[own[pairs[:, 1]], 0]] = True  # a face next to an occluder face of the surface
    near_fold = None
    if folded.shape[0]:
        from scipy.spatial import cKDTree

        fold_tree = cKDTree(folded)

        def near_fold(x: np.ndarray) -> np.ndarray:
            return np.isfinite(fold_tree.query(x, distance_upper_bound=CORNER_SIZE * size)[0])

        def fold_distance(x: np.ndarray) -> np.ndarray:
            return fold_tree.query(x)[0]
    front = ~(push & own[None, :])  # (L, t0): the point's own value is the face's
    cent = corners.mean(axis=1)
    # value vertices: the corners of every face, on their own (merged at the end where equal)
    tri = np.arange(3 * t0, dtype=np.int64).reshape(t0, 3)
    G = tri0.ravel().copy()  # geometric id (the patch's local vertex)
    O = np.repeat(np.arange(t0, dtype=np.int64), 3)  # face
    k3 = np.tile(np.arange(3), t0)
    R = ((1 << k3) | (1 << ((k3 + 2) % 3))).astype(np.int8)  # which of the face's edges it lies on
    P = P0[G]
    N = patch.data["vnrm"].astype(np.float64)[G]
    ng = int(G.max(initial=-1)) + 1
    # the patch's boundary edges (used by one face), in the order the faces list them
    ged = np.sort(np.stack([tri0[:, [0, 1]], tri0[:, [1, 2]], tri0[:, [2, 0]]], axis=1), axis=2).reshape(-1, 2)
    _, inv0, cnt0 = np.unique(ged[:, 0] * _CODE + ged[:, 1], return_inverse=True, return_counts=True)
    once = cnt0[inv0.ravel()] == 1
    ved = np.stack([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]], axis=1).reshape(-1, 2)
    sel = once & (vwid[ged[:, 0]] != vwid[ged[:, 1]])
    bnd = ved[sel]
    edge_keys = np.sort(vwid[G[bnd]], axis=1).astype(np.int64).reshape(-1, 2)
    # on[v] = {boundary edge index: parameter in the welded key's direction}, boundary vertices only
    on: dict[int, dict[int, float]] = {}
    for j, (a, b) in enumerate(bnd.tolist()):
        lo = int(vwid[G[a]]) < int(vwid[G[b]])
        on.setdefault(a, {})[j] = 0.0 if lo else 1.0
        on.setdefault(b, {})[j] = 1.0 if lo else 0.0

    def evaluate(pts: np.ndarray, nrm: np.ndarray, face: np.ndarray, rim: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Values of points of faces `face`; `rim`: on the face's edges, off the patch's boundary."""
        vals = _values(scenes, pts, nrm)
        split = np.zeros(pts.shape[0], bool)
        rows = np.nonzero(rim)[0]
        if rows.size:
            need = ~front[:, face[rows]]  # (L, k)
            rows, need = rows[need.any(axis=0)], need[:, need.any(axis=0)]
            if rows.size:
                d = cent[face[rows]] - pts[rows]
                d *= step / np.linalg.norm(d, axis=1, keepdims=True)
                pv = 2 * _values(scenes, pts[rows] + d, nrm[rows]) - _values(scenes, pts[rows] + 2 * d, nrm[rows])
                vals[rows] = np.where(need.T[:, :, None], pv, vals[rows])
                split[rows] = True
        return vals, split

    E, S = evaluate(P, N, O, np.array([v not in on for v in range(P.shape[0])], bool))
    c_code = np.zeros(0, np.int64)  # evaluated midpoints, sorted by value-edge code
    c_p, c_n, c_v, c_s = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, E.shape[1], 3)), np.zeros(0, bool)
    m_code, m_idx = np.zeros(0, np.int64), np.zeros(0, np.int64)  # inserted midpoints
    fresh = np.ones(tri.shape[0], bool)  # triangles whose centroid is not checked yet
    limit = ESTIMATE_MARGIN * tol * scale  # the checked points bound the error between them only roughly

    def unit(x: np.ndarray) -> np.ndarray:
        return x / np.linalg.norm(x, axis=-1, keepdims=True)

    def lookup(codes: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        at = np.minimum(np.searchsorted(table, codes), max(table.size - 1, 0))
        return at, (table[at] == codes) if table.size else np.zeros(codes.size, bool)

    rounds, bad, emiss = 0, np.zeros(0, bool), np.zeros(0)
    while True:
        tot = E.sum(axis=1)
        ed = np.sort(np.stack([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]], axis=1), axis=2)
        ucode, eid = np.unique((ed[..., 0] * _CODE + ed[..., 1]).ravel(), return_inverse=True)
        eid = eid.reshape(-1, 3)
        ua, ub = ucode // _CODE, ucode % _CODE
        ga, gb = np.minimum(G[ua], G[ub]), np.maximum(G[ua], G[ub])
        gcode, vtog = np.unique(ga * _CODE + gb, return_inverse=True)
        vtog = vtog.ravel()
        at, found = lookup(ucode, c_code)
        if not found.all():
            na, nb = ua[~found], ub[~found]
            mp = 0.5 * (P[na] + P[nb])
            onb = np.zeros(na.size, bool)
            for r in np.nonzero(np.isin(na, list(on)) & np.isin(nb, list(on)))[0]:
                a, b = int(na[r]), int(nb[r])
                common = on[a].keys() & on[b].keys()
                if common:
                    j = min(common)
                    ka, kb = edge_keys[j]
                    mp[r] = _on_point(pos, int(ka), int(kb), 0.5 * (on[a][j] + on[b][j]))
                    onb[r] = True
            same = np.all(N[na] == N[nb], axis=1)
            mn = np.where(same[:, None], N[na], unit(N[na] + N[nb]))
            mv, ms = evaluate(mp, mn, O[na], ((R[na] & R[nb]) != 0) & ~onb)
            c_code = np.concatenate([c_code, ucode[~found]])
            order = np.argsort(c_code, kind="stable")
            c_code = c_code[order]
            c_p, c_n, c_v, c_s = (np.concatenate([c_p, mp])[order], np.concatenate([c_n, mn])[order],
                                  np.concatenate([c_v, mv])[order], np.concatenate([c_s, ms])[order])
            at, found = lookup(ucode, c_code)
        mval = c_v[at].sum(axis=1)
        long = np.linalg.norm(P[ua] - P[ub], axis=1) > min_edge
        corner = np.zeros(ucode.size, bool) if near_fold is None else near_fold(P[ua]) | near_fold(P[ub])
        # a fold's corner: edges there not split below CORNER_SIZE, their error reported apart
        corner &= np.linalg.norm(P[ua] - P[ub], axis=1) <= CORNER_SIZE * size
        if near_fold is not None:  # graded towards a fold's corner: down to CORNER_GRADE of the distance
            r = np.minimum(fold_distance(P[ua]), fold_distance(P[ub]))
            long |= np.linalg.norm(P[ua] - P[ub], axis=1) > CORNER_GRADE * r
        long &= ~corner
        emiss = np.max(np.abs(mval - 0.5 * (tot[ua] + tot[ub])), axis=1)
        cmiss = emiss[corner]
        emiss = np.where(corner, 0.0, emiss)
        gbad = np.zeros(gcode.size, bool)
        gbad[vtog[(emiss > limit) & long]] = True
        if fresh.any():
            ft = tri[fresh]
            same = np.all((N[ft[:, 0]] == N[ft[:, 1]]) & (N[ft[:, 0]] == N[ft[:, 2]]), axis=1)
            cn = np.where(same[:, None], N[ft[:, 0]], unit(N[ft].sum(axis=1)))
            cv = _values(scenes, P[ft].mean(axis=1), cn).sum(axis=1)
            miss = np.max(np.abs(cv - tot[ft].mean(axis=1)), axis=1) > limit
            fe = eid[fresh][miss].ravel()
            gbad[vtog[fe[long[fe]]]] = True
        if not gbad.any() or P.shape[0] >= max_vertices or rounds >= max_rounds:
            bad = gbad[vtog]
            break
        rounds += 1
        geid = vtog[eid]
        while True:  # closure: two split edges -> split the third
            two = gbad[geid].sum(axis=1) == 2
            if not two.any():
                break
            gbad[geid[two].ravel()] = True
        bad = gbad[vtog]
        split = bad[eid]  # (t, 3): which sides of each triangle are split
        bi = np.nonzero(bad)[0]
        mat, mfound = lookup(ucode[bi], m_code)
        newe = bi[~mfound]  # midpoints numbered in sorted edge order
        base = P.shape[0]
        for k, e in enumerate(newe.tolist()):
            a, b = int(ua[e]), int(ub[e])
            if a in on and b in on:
                common = on[a].keys() & on[b].keys()
                if common:
                    on[base + k] = {j: 0.5 * (on[a][j] + on[b][j]) for j in common}
        if newe.size:
            ce = at[newe]
            _, gnew = np.unique(vtog[newe], return_inverse=True)  # the faces on both sides: one point
            P, N, E = np.concatenate([P, c_p[ce]]), np.concatenate([N, c_n[ce]]), np.concatenate([E, c_v[ce]])
            S = np.concatenate([S, c_s[ce]])
            G = np.concatenate([G, ng + gnew.ravel()])
            ng += int(gnew.max()) + 1
            O = np.concatenate([O, O[ua[newe]]])
            R = np.concatenate([R, R[ua[newe]] & R[ub[newe]]])
            m_code = np.concatenate([m_code, ucode[newe]])
            m_idx = np.concatenate([m_idx, base + np.arange(newe.size)])
            order = np.argsort(m_code, kind="stable")
            m_code, m_idx = m_code[order], m_idx[order]
        mid = np.full(ucode.size, -1, np.int64)
        mid[bi] = m_idx[lookup(ucode[bi], m_code)[0]]
        M = mid[eid]  # (t, 3): the midpoint of each split side
        ns = split.sum(axis=1)
        out = np.full((tri.shape[0], 4, 3), -1, np.int64)
        keep = ns == 0
        out[keep, 0] = tri[keep]
        r = ns == 3
        a, b, c, ab, bc, ca = tri[r, 0], tri[r, 1], tri[r, 2], M[r, 0], M[r, 1], M[r, 2]
        out[r] = np.stack([np.c_[a, ab, ca], np.c_[ab, b, bc], np.c_[ca, bc, c], np.c_[ab, bc, ca]], axis=1)
        g = np.nonzero(ns == 1)[0]
        k = np.argmax(split[g], axis=1)
        a, b, c = tri[g, k], tri[g, (k + 1) % 3], tri[g, (k + 2) % 3]
        mm = M[g, k]
        out[g, 0], out[g, 1] = np.c_[a, mm, c], np.c_[mm, b, c]
        valid = out[:, :, 0] >= 0
        fresh = (valid & ~keep[:, None])[valid]
        tri = out[valid]
    # one vertex per point, but one per face where a face's limit was taken (S)
    side = np.where(S, O + 1, 0)
    _, first, inv = np.unique(np.stack([G, side], axis=1), axis=0, return_index=True, return_inverse=True)
    inv = inv.ravel()
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    keep_v = first[order]
    remap = rank[inv]
    occ_e, occ_v, occ_t = [], [], []
    for vi in sorted(on):
        for j, t in sorted(on[vi].items()):
            occ_e.append(j)
            occ_v.append(int(remap[vi]))
            occ_t.append(t)
    return {"vertices": P[keep_v], "normals": N[keep_v], "triangles": remap[tri], "values": E[keep_v],
            "side": side[keep_v], "edge_keys": edge_keys, "occ_edge": np.array(occ_e, np.int64),
            "occ_vertex": np.array(occ_v, np.int64), "occ_t": np.array(occ_t, np.float64),
            "rounds": np.array(rounds), "unrefined": np.array(int(np.sum(emiss > tol * scale))),
            "stopped": np.array(int(bad.any() and P.shape[0] >= max_vertices)),
            "error": np.array(float(emiss.max(initial=0.0)) / scale),
            "corner_error": np.array(float(cmiss.max(initial=0.0)) / scale), "corners": folded}

