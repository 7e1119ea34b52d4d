"""Bake's patches: a scene's receivers welded into surfaces, the surfaces cut into planar
patches (convex polygons of coplanar flat faces) and curved patches (`bake`, step 1)."""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

from .._scene.model import Scene

# --------------------------------------------------------------------------------------
# Receivers -> surfaces -> patches
# --------------------------------------------------------------------------------------


def _weld(points: np.ndarray, tol: float) -> np.ndarray:
    """`(n,)` welded id of each point: points within `tol > 0` are one (transitively,
    `jaxshadow._core.welding.weld_vertices`); the id is the lowest index of its group. `tol <= 0`:
    every point its own."""
    from .._core.welding import weld_vertices

    if points.shape[0] == 0 or tol <= 0:
        return np.arange(points.shape[0])
    index, first = weld_vertices(points, tol)
    return first[index]


def _surfaces(scene: Scene, receivers: Any) -> list[tuple[str, np.ndarray, Any, np.ndarray | None]]:
    """`(name, vertices, triangles or polygon rows, vertex normals or None)` per surface."""
    from .._io.meshio import ReceiverMesh

    if receivers is None:
        if scene.occluders is None:
            raise ValueError("bake: the scene has no occluders and no receivers were given.")
        occ = np.asarray(scene.occluders, np.float64)
        receivers = [_unpad(o) for o in occ]
    if isinstance(receivers, (ReceiverMesh, np.ndarray)) or not isinstance(receivers, (list, tuple)):
        receivers = [receivers]
    out: list[tuple[str, np.ndarray, Any, np.ndarray | None]] = []
    for i, r in enumerate(receivers):
        if isinstance(r, ReceiverMesh):
            out.append((r.name or f"surface{i}", r.vertices, r.faces, r.vertex_normals))
            continue
        from .._core.mesh import Mesh

        if isinstance(r, Mesh):
            polys = [_unpad(np.asarray(p, np.float64)) for p in r.polygons]
        else:
            p = np.asarray(r, np.float64)
            polys = [p] if p.ndim == 2 else [_unpad(q) for q in p]
        if not polys or any(p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 3 for p in polys):
            raise ValueError(f"bake: receivers[{i}] must be a ReceiverMesh, a Mesh or polygons (k, 3).")
        verts = np.concatenate(polys)
        off = np.cumsum([0] + [p.shape[0] for p in polys])
        rows = [np.arange(off[j], off[j + 1]) for j in range(len(polys))]
        out.append((f"surface{i}", verts, rows, None))
    return out


def _unpad(p: np.ndarray) -> np.ndarray:
    keep = np.r_[True, np.any(np.diff(p, axis=0) != 0, axis=1)]
    p = p[keep]
    if p.shape[0] > 1 and np.array_equal(p[0], p[-1]):
        p = p[:-1]
    return p


def _newell(p: np.ndarray) -> np.ndarray:
    n = np.sum(np.cross(p, np.roll(p, -1, axis=0)), axis=0)
    return n / np.linalg.norm(n)


def _convex_loop(loop: np.ndarray, normal: np.ndarray) -> bool:
    """Strictly convex, counter-clockwise about `normal`, no collinear corners."""
    d = np.roll(loop, -1, axis=0) - loop
    turn = np.cross(d, np.roll(d, -1, axis=0)) @ normal
    size = np.linalg.norm(d, axis=1)
    return bool(np.all(turn > 1e-9 * size * np.roll(size, -1)))


def _planar_groups(tris: np.ndarray, pos: np.ndarray) -> list[tuple[list[int], list[np.ndarray]]]:
    """Flat triangles (rows of welded ids) grouped into coplanar connected sets; each set is
    one convex polygon `(ids loop)` when its union is one, else one polygon per triangle.
    Returns `(triangle indices, polygon id loops)` per set."""
    n = tris.shape[0]
    nrm = np.array([_newell(pos[t]) for t in tris]) if n else np.zeros((0, 3))
    by_edge: dict[tuple[int, int], list[int]] = {}
    for i, t in enumerate(tris):
        for k in range(3):
            a, b = int(t[k]), int(t[(k + 1) % 3])
            by_edge.setdefault((min(a, b), max(a, b)), []).append(i)
    seen = np.zeros(n, bool)
    groups: list[tuple[list[int], list[np.ndarray]]] = []
    for s in range(n):
        if seen[s]:
            continue
        comp, stack = [s], [s]
        seen[s] = True
        while stack:
            i = stack.pop()
            t = tris[i]
            for k in range(3):
                a, b = int(t[k]), int(t[(k + 1) % 3])
                for j in by_edge[(min(a, b), max(a, b))]:
                    if not seen[j] and nrm[j] @ nrm[s] > 1 - 1e-9 and abs((pos[tris[j]] - pos[tris[s][0]]) @ nrm[s]).max() \
                            <= 1e-7 * (1 + np.abs(pos[tris[s]]).max()):
                        seen[j] = True
                        comp.append(j)
                        stack.append(j)
        comp.sort()
        loop = _boundary_loop(tris[comp])
        if loop is not None and len(comp) > 1 and set(loop.tolist()) == set(tris[comp].ravel().tolist()) \
                and _convex_loop(pos[loop], nrm[s]):
            groups.append((comp, [loop]))
        else:
            groups.append((comp, [tris[i] for i in comp]))
    return groups


def _boundary_loop(tris: np.ndarray) -> np.ndarray | None:
    directed = {(int(t[k]), int(t[(k + 1) % 3])) for t in tris for k in range(3)}
    nxt: dict[int, int] = {}
    for a, b in directed:
        if (b, a) not in directed:
            if a in nxt:
                return None
            nxt[a] = b
    if not nxt:
        return None
    start = min(nxt)
    loop = [start]
    while True:
        b = nxt[loop[-1]]
        if b == start:
            break
        if b in loop or b not in nxt:
            return None
        loop.append(b)
    return np.array(loop) if len(loop) == len(nxt) else None


class _Patch:
    """One chunk: a planar polygon (`ids (k,)` welded ids of its corners, counter-clockwise) or
    a curved triangle set (`tri (t, 3)` local vertex ids, `vpos`, `vnrm`, `vwid` per local
    vertex)."""

    def __init__(self, kind: str, surface: int, **data: Any):
        self.kind, self.surface = kind, surface
        self.data = {k: np.ascontiguousarray(v) for k, v in data.items()}

    def digest(self) -> bytes:
        h = hashlib.sha256(self.kind.encode())
        for k in sorted(self.data):
            v = self.data[k]
            h.update(k.encode() + str(v.dtype).encode() + str(v.shape).encode() + v.tobytes())
        return h.digest()


def _patches(surfaces: list, weld: float) -> tuple[list[_Patch], np.ndarray, list[str]]:
    """The patches of all surfaces, the welded positions `(W, 3)` and the surface names."""
    allv = np.concatenate([s[1] for s in surfaces])
    size = float(np.max(np.ptp(allv, axis=0))) if allv.shape[0] else 1.0
    wid_all = _weld(allv, weld * size)
    pos = allv[wid_all]  # every point at its group's representative
    off = np.cumsum([0] + [s[1].shape[0] for s in surfaces])
    patches: list[_Patch] = []
    names = []
    for si, (name, v, faces, vn) in enumerate(surfaces):
        names.append(name)
        wid = wid_all[off[si]:off[si + 1]]
        if vn is None:  # polygons given as rows
            for rows in faces:
                ids = _dedup_loop(wid[rows])
                if ids.shape[0] >= 3:
                    patches.append(_Patch("planar", si, ids=ids, normal=_newell(pos[ids])))
            continue
        f = np.asarray(faces)
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        fn /= np.linalg.norm(fn, axis=1)[:, None]
        flat = np.all(np.einsum("fkj,fj->fk", vn[f], fn) > 1 - 1e-6, axis=1)
        wt = wid[f]
        degenerate = (wt[:, 0] == wt[:, 1]) | (wt[:, 1] == wt[:, 2]) | (wt[:, 0] == wt[:, 2])
        flat_idx = np.nonzero(flat & ~degenerate)[0]
        for comp, polys in _planar_groups(wt[flat_idx], pos):
            # one normal per coplanar set: its vertices on inner edges are then one output vertex
            ct = pos[wt[flat_idx[comp]]]
            acc = np.cross(ct[:, 1] - ct[:, 0], ct[:, 2] - ct[:, 0]).sum(axis=0)
            normal = acc / np.linalg.norm(acc)
            for ids in polys:
                patches.append(_Patch("planar", si, ids=np.asarray(ids, np.int64), normal=normal))
        curved = np.nonzero(~flat & ~degenerate)[0]
        if curved.size:
            fc = f[curved]
            # local vertices: one per (welded position, normal)
            key = np.concatenate([wid[:, None].astype(np.float64), np.round(vn, 9)], axis=1)
            uk, inv = np.unique(key[fc.ravel()], axis=0, return_inverse=True)
            tri = inv.reshape(-1, 3).astype(np.int64)
            first = np.zeros(uk.shape[0], np.int64)
            first[inv.ravel()] = fc.ravel()
            lw = wid[first]
            patches.append(_Patch("curved", si, tri=tri, vpos=pos[lw], vnrm=vn[first], vwid=lw.astype(np.int64)))
    # planar patches carry their corners' positions; all patches the welded ids they touch
    for p in patches:
        if p.kind == "planar":
            p.data["poly"] = pos[p.data["ids"]]
    return patches, pos, names


def _dedup_loop(ids: np.ndarray) -> np.ndarray:
    keep = [int(i) for k, i in enumerate(ids) if i != ids[k - 1]] if ids.shape[0] > 1 else list(ids)
    return np.array(keep, np.int64)
