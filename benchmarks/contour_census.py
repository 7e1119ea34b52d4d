"""Census of contour pieces on real meshes: which cannot bound the lit region, and how many a same-facing patch of the silhouette hierarchy certifies.

The `real_meshes` setting (mesh 0.3 m above the floor, 0.8 m quad light at z = 2.5, floor
receivers). For a sample of penumbra receivers p (the engine's classes), every contour edge
(mesh boundary edge, or an edge whose two faces lie on the same side of their planes through p)
is projected centrally from p onto the light's plane and clipped to the light. A piece is *deep*
when the depth complexity C is at least 1 on both sides of its midpoint (two Embree rays a
1e-7 m step either side): it cannot bound the region {C = 0} that the receiver sees.

The certificate measured: for a set P of faces that all face p the same way, the signed count of
P's projected faces covering a point q equals the winding number of P's projected boundary chain
around q (the degree of the projection, each face counted with its orientation's sign), and with
one sign for all faces, C(q) >= C_P(q) = |wind(proj dP, q)|; no disk or embedding is needed. The
sets tried are the maximal nodes of the engine's edge hierarchy (`csrc/engine/silhouette_tree.h`:
median splits of the edges' midpoints along the box's longest axis, leaves of at most 4 edges)
that its walk drops by their normal cone (`node_side`), whose box projects into the light; P is
the faces of the node's edges. A piece is certified when it lies strictly inside one such
outline (winding number nonzero at its midpoint, no outline edge meeting it), reported per
smallest node size (edges) with the outlines one would have to project per receiver.

The hierarchy is rebuilt here from the triangles (the engine merges coplanar triangles into
quads first, so CAD parts differ in detail). No timing: the counts do not depend on the load.

    python -m benchmarks.contour_census --mesh stanford-bunny.obj [--mesh F ...] [--scan-like]
        [--receivers 20000] [--sample 12]

writes `benchmarks/results/contour_census.json` and `.md`.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

NAME = "contour_census"
SIZES = (8, 32, 128, 512)  # smallest node sizes (edges) reported
LIGHT_HALF = 0.4  # the light's half side (benchmarks.real_meshes.LIGHT)
LIGHT_Z = 2.5


class EdgeTree:
    """The mesh's undirected edges with their faces, and the engine's hierarchy over them."""

    def __init__(self, v: np.ndarray, f: np.ndarray):
        self.v, self.f = v, f
        nf = len(f)
        de = np.stack([f, np.roll(f, -1, axis=1)], -1).reshape(-1, 2)  # directed a -> b of face k // 3
        dface = np.repeat(np.arange(nf), 3)
        uk, inv, cnt = np.unique(np.sort(de, 1), axis=0, return_inverse=True, return_counts=True)
        order = np.argsort(inv.ravel(), kind="stable")
        starts = np.r_[0, np.cumsum(cnt)[:-1]]
        self.ends = uk
        self.first = dface[order[starts]]
        self.has2 = cnt == 2
        self.second = np.full(len(uk), -1)
        self.second[cnt >= 2] = dface[order[starts[cnt >= 2] + 1]]
        # consistent orientation: the second face runs the edge the other way
        self.consistent = np.ones(len(uk), bool)
        two = cnt >= 2
        self.consistent[two] = de[order[starts[two] + 1], 0] == de[order[starts[two]], 1]
        self.special = (cnt != 2) | ~self.consistent
        self.fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        fnu = self.fn / np.linalg.norm(self.fn, axis=1)[:, None]
        mid = 0.5 * (v[uk[:, 0]] + v[uk[:, 1]])
        g = np.where(self.second >= 0, self.second, self.first)
        flo, fhi = v[f].min(1), v[f].max(1)
        elo, ehi = np.minimum(flo[self.first], flo[g]), np.maximum(fhi[self.first], fhi[g])
        lo, hi, ax, cosa, arad, hrad, sp, size, kids, faces = [], [], [], [], [], [], [], [], [], []
        stack: list[tuple[np.ndarray, int]] = [(np.arange(len(uk)), -1)]
        while stack:  # preorder; children filled in as they are made
            idx, parent = stack.pop()
            k = len(lo)
            if parent >= 0:
                kids[parent].append(k)
            nlo, nhi = elo[idx].min(0), ehi[idx].max(0)
            fs = np.unique(np.r_[self.first[idx], self.second[idx][self.second[idx] >= 0]])
            a = fnu[fs].sum(0)
            an = np.linalg.norm(a)
            c = -1.0
            if an > 0:
                a = a / an
                c = max(-1.0, min(1.0, float((fnu[fs] @ a).min()))) - 1e-12
            h = 0.5 * (nhi - nlo)
            for store, value in ((lo, nlo), (hi, nhi), (ax, a), (cosa, c), (arad, np.abs(a) @ h), (hrad, np.linalg.norm(h)),
                                 (sp, bool(self.special[idx].any())), (size, len(idx)), (kids, []), (faces, fs)):
                store.append(value)
            if len(idx) > 4:
                d = int(np.argmax(nhi - nlo))
                o = np.argsort(mid[idx, d], kind="stable")
                half = len(idx) // 2
                stack.append((idx[o[:half]], k))
                stack.append((idx[o[half:]], k))
        self.lo, self.hi, self.ax = np.array(lo), np.array(hi), np.array(ax)
        self.cosa = np.array(cosa)
        self.sina = np.sqrt(np.maximum(0, 1 - self.cosa**2)) + 1e-12
        self.arad, self.hrad = np.array(arad), np.array(hrad)
        self.node_special, self.size, self.kids, self.faces = np.array(sp), np.array(size), kids, faces
        self._outline: dict[int, np.ndarray] = {}

    def dropped_by_cone(self, p: np.ndarray, margin: float) -> np.ndarray:
        """`node_side(nd, p, margin) != 0` for every node (as silhouette_tree.h), special nodes never."""
        d = p - 0.5 * (self.lo + self.hi)
        a = np.einsum("ij,ij->i", d, self.ax)
        perp = np.linalg.norm(d - a[:, None] * self.ax, axis=1) + self.hrad
        ok = self.cosa > 0
        plus = (a - self.arad) * self.cosa - perp * self.sina > margin
        minus = (a + self.arad) * self.cosa + perp * self.sina < -margin
        return ok & (plus | minus) & ~self.node_special

    def maximal(self, dropped: np.ndarray) -> list[int]:
        """The nodes the walk drops by their cone (their ancestors are not dropped)."""
        out, stack = [], [0]
        while stack:
            k = stack.pop()
            if dropped[k]:
                out.append(k)
            else:
                stack.extend(self.kids[k])
        return out

    def outline(self, k: int) -> np.ndarray:
        """Node k's boundary chain: its faces' directed edges whose reverse is not among them."""
        if k not in self._outline:
            fk = self.f[self.faces[k]]
            d = np.stack([fk, np.roll(fk, -1, 1)], -1).reshape(-1, 2)
            nv = len(self.v) + 1
            self._outline[k] = d[~np.isin(d[:, 0] * nv + d[:, 1], d[:, 1] * nv + d[:, 0])]
        return self._outline[k]


def _project(p: np.ndarray, x: np.ndarray) -> np.ndarray:
    t = (LIGHT_Z - p[2]) / (x[..., 2] - p[2])
    return p[:2] + t[..., None] * (x[..., :2] - p[:2])


def _clip_to_light(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t0, t1, d = np.zeros(len(a)), np.ones(len(a)), b - a
    for k in range(2):
        for s, bound in ((1.0, -LIGHT_HALF), (-1.0, LIGHT_HALF)):
            g0, g1 = s * (a[:, k] - bound), s * d[:, k]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = -g0 / g1
            t0 = np.where(g1 > 0, np.maximum(t0, t), t0)
            t1 = np.where(g1 < 0, np.minimum(t1, t), t1)
            t1 = np.where((g1 == 0) & (g0 < 0), -1.0, t1)
    return t0, t1


def _orient(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
    return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])


def _meets(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Segments a b (k) against c d (m): (k,) whether any of them meets (touching counts)."""
    A, B, C, D = a[:, None], b[:, None], c[None], d[None]
    return ((_orient(A, B, C) * _orient(A, B, D) <= 0) & (_orient(C, D, A) * _orient(C, D, B) <= 0)).any(1)


def _winding(q: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Winding numbers of the chain c -> d (m edges) around the points q (k)."""
    cy, dy = c[None, :, 1] - q[:, None, 1], d[None, :, 1] - q[:, None, 1]
    cr = (c[None, :, 0] - q[:, None, 0]) * dy - cy * (d[None, :, 0] - q[:, None, 0])
    return ((cy <= 0) & (dy > 0) & (cr > 0)).sum(1) - ((cy > 0) & (dy <= 0) & (cr < 0)).sum(1)


def census_receiver(tree: EdgeTree, rays: Any, p: np.ndarray) -> dict[str, Any]:
    """One receiver: its pieces, the deep ones, and the largest certifying node per piece."""
    v, f = tree.v, tree.f
    side = np.sign(np.einsum("ij,ij->i", tree.fn, p - v[f[:, 0]]))  # +1: p in front
    sf = side[tree.first]
    sg = np.where(tree.second >= 0, side[np.maximum(tree.second, 0)], 0)
    w = np.where(tree.has2 & tree.consistent, sf - sg, np.where(tree.has2, sf + sg, sf))
    con = np.nonzero(w != 0)[0]
    a, b = _project(p, v[tree.ends[con, 0]]), _project(p, v[tree.ends[con, 1]])
    t0, t1 = _clip_to_light(a, b)
    keep = t1 > t0 + 1e-12
    a, b, t0, t1 = a[keep], b[keep], t0[keep], t1[keep]
    a2, b2 = a + t0[:, None] * (b - a), a + t1[:, None] * (b - a)
    n = len(a2)
    m = 0.5 * (a2 + b2)
    d = b2 - a2
    nrm = np.c_[-d[:, 1], d[:, 0]] / np.maximum(np.linalg.norm(d, axis=1), 1e-300)[:, None]
    deep = np.ones(n, bool)
    for s in (1.0, -1.0):
        target = np.c_[m + s * 1e-7 * nrm, np.full(n, LIGHT_Z)]
        deep &= rays.intersects_any(np.tile(p, (n, 1)), target - p)
    margin = 4 * 2.0**-18 * max(1.3, float(np.abs(p).max()))  # the walk's margin (kOnSurface)
    best = np.zeros(n, int)  # the largest certifying node's size per piece (0: none)
    cand_nodes = {s: 0 for s in SIZES}
    cand_edges = {s: 0 for s in SIZES}
    lo2, hi2 = np.minimum(a2, b2), np.maximum(a2, b2)
    for k in tree.maximal(tree.dropped_by_cone(p, margin)):
        size = int(tree.size[k])
        if size < SIZES[0]:
            continue
        corners = np.array([[(tree.lo if i & j else tree.hi)[k][x] for x, j in enumerate((1, 2, 4))] for i in range(8)])
        pc = _project(p, corners)
        if pc[:, 0].max() < -LIGHT_HALF or pc[:, 0].min() > LIGHT_HALF or pc[:, 1].max() < -LIGHT_HALF or pc[:, 1].min() > LIGHT_HALF:
            continue  # outside the light's pyramid
        ol = tree.outline(k)
        for s in SIZES:
            if size >= s:
                cand_nodes[s] += 1
                cand_edges[s] += len(ol)
        c, e = _project(p, v[ol[:, 0]]), _project(p, v[ol[:, 1]])
        olo, ohi = np.minimum(c, e).min(0), np.maximum(c, e).max(0)
        inside = np.nonzero((lo2[:, 0] > olo[0]) & (hi2[:, 0] < ohi[0]) & (lo2[:, 1] > olo[1]) & (hi2[:, 1] < ohi[1]) & (best < size))[0]
        if len(inside) == 0:
            continue
        ok = (_winding(m[inside], c, e) != 0) & ~_meets(a2[inside], b2[inside], c, e)
        best[inside[ok]] = size
    out: dict[str, Any] = {"pieces": n, "deep": int(deep.sum()), "certified_shallow": int(((best > 0) & ~deep).sum())}
    for s in SIZES:
        out[f"certified_{s}"] = int(((best >= s) & deep).sum())
        out[f"nodes_{s}"] = cand_nodes[s]
        out[f"outline_edges_{s}"] = cand_edges[s]
    return out


def census(v: np.ndarray, f: np.ndarray, receivers: int, sample: int) -> dict[str, Any]:
    """The census over `sample` penumbra receivers of `receivers` floor receivers."""
    import trimesh
    import trimesh.ray.ray_pyembree as embree

    import jaxshadow as js
    from benchmarks.real_meshes import LIGHT, _receivers
    from jaxshadow._shadows import binding

    scene = js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=[js.Mesh(v, f)])
    p, nrm = _receivers(receivers)
    cls = np.asarray(js.shadow_plan(scene, p, nrm).lights[0].classes)
    pen = p[cls == binding.PENUMBRA]
    pen = pen[np.random.default_rng(0).choice(len(pen), min(sample, len(pen)), replace=False)]
    t = time.perf_counter()
    tree = EdgeTree(np.asarray(v, float), np.asarray(f, np.int64))
    rays = embree.RayMeshIntersector(trimesh.Trimesh(v, f, process=False))
    rows = [census_receiver(tree, rays, q) for q in pen]
    total = {k: int(sum(r[k] for r in rows)) for k in rows[0]} if rows else {}
    pieces, deep = max(1, total.get("pieces", 0)), max(1, total.get("deep", 0))
    return {
        "faces": int(len(f)), "penumbra_share": float(np.mean(cls == binding.PENUMBRA)), "receivers": len(rows),
        "pieces_per_receiver": total.get("pieces", 0) / max(1, len(rows)), "deep_share": total.get("deep", 0) / pieces,
        "certified_share_of_deep": {s: total.get(f"certified_{s}", 0) / deep for s in SIZES},
        "certified_share_of_pieces": {s: total.get(f"certified_{s}", 0) / pieces for s in SIZES},
        "nodes_per_receiver": {s: total.get(f"nodes_{s}", 0) / max(1, len(rows)) for s in SIZES},
        "outline_edges_per_receiver": {s: total.get(f"outline_edges_{s}", 0) / max(1, len(rows)) for s in SIZES},
        "certified_shallow": total.get("certified_shallow", 0), "seconds": round(time.perf_counter() - t, 1),
    }


def markdown(results: dict[str, Any]) -> str:
    rows = ["| mesh | faces | pieces / receiver | deep | certified of deep (nodes >= 8 / 32 / 128 / 512 edges) | "
            "outline edges / receiver (>= 8 / 32 / 128) | certified but not deep |",
            "|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        cs = " / ".join(f"{r['certified_share_of_deep'][s]:.2f}" for s in SIZES)
        oe = " / ".join(f"{r['outline_edges_per_receiver'][s]:.0f}" for s in SIZES[:3])
        rows.append(f"| {name} | {r['faces']} | {r['pieces_per_receiver']:.0f} | {r['deep_share']:.2f} | {cs} | {oe} | "
                    f"{r['certified_shallow']} |")
    n = {r["receivers"] for r in results.values()}
    rows.append(f"\n{'/'.join(str(x) for x in sorted(n))} penumbra receivers per mesh; deep: C >= 1 on both sides of a "
                "piece's midpoint (Embree); certified: strictly inside the projected outline of a maximal cone-dropped "
                "node of the silhouette hierarchy (C >= |winding| there).")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    """`python -m benchmarks.contour_census --mesh FILE [--mesh FILE ...] [--scan-like]`."""
    import argparse
    import sys

    from benchmarks._suite import RESULTS, caption, meta, write_json, write_text
    from benchmarks.real_meshes import load_file, scan_like

    ap = argparse.ArgumentParser(prog="python -m benchmarks.contour_census", description=__doc__.split("\n")[0])
    ap.add_argument("--mesh", action="append", default=[], help="a mesh file (OBJ, PLY, ...); repeatable")
    ap.add_argument("--scan-like", action="store_true", help="also benchmarks.real_meshes.scan_like()")
    ap.add_argument("--up", choices=("x", "y", "z"), default="y", help="the files' up axis (default y)")
    ap.add_argument("--receivers", type=int, default=20000, help="floor receivers classified (default 20000)")
    ap.add_argument("--sample", type=int, default=12, help="penumbra receivers per mesh (default 12)")
    args = ap.parse_args(argv)
    info = meta(NAME, False)
    info["command"] = "python -m benchmarks.contour_census " + " ".join(sys.argv[1:] if argv is None else argv)
    meshes = [(str(m).rsplit("/", 1)[-1], lambda m=m: load_file(m, args.up)) for m in args.mesh]
    if args.scan_like:
        meshes.append(("scan_like", scan_like))
    results = {}
    for name, make in meshes:
        v, f = make()
        results[name] = census(v, f, args.receivers, args.sample)
        print(name, results[name], flush=True)
    record = {"benchmark": NAME, "meta": info, "results": results}
    write_json(RESULTS / f"{NAME}.json", record)
    write_text(RESULTS / f"{NAME}.md", caption(record) + "\n\n" + markdown(results) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
