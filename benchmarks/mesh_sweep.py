"""Exactness sweep of the shadow engine on mesh files: every light kind, placements and receivers chosen to break it.

Per mesh file (`real_meshes.load_file`: up axis y, 1 m, centred, 0.3 m above the floor) and
placement:

- `above`: as `benchmarks.real_meshes` (the 0.8 m quad light at z = 2.5);
- `on floor`: the mesh lowered onto the floor (its lowest vertices touch it);
- `close`: the light's plane 0.05 m above the mesh's top;
- `large`: a 3 m quad at z = 2.5;
- `tilted`: the quad turned 45 degrees about the x axis;
- `rotated`: the mesh turned by a random rotation about its centre, 0.3 m above the floor;
- `soup`: the mesh as an `(m, 3, 3)` triangle array, faces shuffled, 1 % of them repeated;
- `soup degenerate`: the shuffled soup with five zero-area (collinear) triangles added, which
  `Scene` refuses (an error at build time is the expected result);
- `float32`: the `above` scene with float32 vertices, light and receivers;

and light kind (`quad`: the placement's quad; `segment`: its middle line; `point`: its centre;
`directional`: from its centre towards the mesh, 10 degrees off the vertical). The default run takes
per light kind the placements that stress it most (`DEFAULT`); `--full` every kind on every
placement. Receivers: a floor grid (a fifth of it with grazing normals), floor points next to the
mesh's lowest vertices (contact, grazing normals), points on the mesh's own surface (face centres
and vertices with their normals, pushed along them by 0 and by 1e-9 m) and points inside the
mesh's bounding box (random normals). Then the generated inputs (`generated`: fins, T-junctions,
flipped faces, overlapping copies, slivers, a mesh through the light's plane, receivers on shadow
edges, coplanar touching faces) under every light kind.

The engine runs on every receiver; the brute-force path on `reference_subset`: every contact
receiver, every on-surface one on a face with a fold, boundary or non-manifold edge or at one of
its vertices (`fold_faces`), every penumbra one, and an eighth of the rest. References: quad
lights: the engine's face path (`JAXSHADOW_SILHOUETTE=0`: every candidate face clipped) on the
subset, and exact polygon booleans in shapely (`_robustness_checks.reference_ff_batched`:
`test_clip.reference_ff` with the occluders clipped as arrays, on the faces `test_plan.culled` keeps
and the on-surface rule leaves) on the receivers where the two disagree most, one of each group
with checked receivers (contact, on-surface near a fold, the input's own) and a few penumbra ones,
at most `FACE_CAP` faces per case in all (`--full`: no cap; the record says how many receivers of
each kind were checked and how many the cap left out); segment lights: the face path (`JAXSHADOW_SEGMENT_PIECES=0`)
on the subset and the Gauss-Legendre reference (`test_clip.reference_linear`) on the worst and one
more; point and directional lights: the device kernel (no engine) on up to `DEVICE_MAX` receivers
of the subset (checked ones first) and the ray test of the tests (`test_clip.ray_blocked_np`, on
the triangles that can meet each ray) on the whole subset. Errors are `|E - ref| / max(U, 1e-3
max U)` (U the unoccluded value); hard shadows count lit/shadowed disagreements apart (a receiver
on a shadow boundary is decided by rounding). float32 values are compared with the float64 engine
on the same rounded inputs, against the property suite's bound 1e-5 U + 8 eps32 0.1 pi (reported
as its share times 1e-5: passes at <= 1e-5).

    python -m benchmarks.mesh_sweep --mesh /work/meshes/stanford-bunny.obj [--mesh ...] [--record]
    python -m benchmarks.mesh_sweep --dir /work/meshes [--receivers 400] [--ref 8] [--full] [--record]
    python -m benchmarks.mesh_sweep --generated 240   # the generated inputs only

Prints one row per case (seconds of CPU, all threads, per step, and the case's wall time) and the
whole run's CPU seconds, wall time and load; with `--record` writes
`benchmarks/results/mesh_sweep.{json,md}`. On a shared machine the CPU seconds are the measure:
the references run on one thread, the engine on up to its thread count (2 here).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import _robustness_checks as chk
from benchmarks.real_meshes import LIGHT, load_file

NAME = "mesh_sweep"
PLACEMENTS = ("above", "on floor", "close", "large", "tilted", "rotated", "soup", "soup degenerate", "float32")
# The default run: per light kind, the placements that stress it most (`--full`: every kind on
# every placement). `above` is `rotated` without the rotation, and `large` a milder `close`.
DEFAULT = {"quad": ("on floor", "close", "tilted", "rotated", "soup", "soup degenerate", "float32"),
           "segment": ("on floor", "rotated"),
           "point": ("on floor", "rotated"),
           "directional": ("on floor", "rotated")}
KINDS = ("quad", "segment", "point", "directional")
TOL = {"float64": 1e-9, "float32": 1e-5}


def _quad(centre: np.ndarray, size: float, tilt_deg: float = 0.0) -> np.ndarray:
    """A square light of side `size` centred at `centre`, emitting downwards (the vertex order of
    `LIGHT`), turned by `tilt_deg` about the x axis."""
    q = LIGHT / 0.8 * size
    q = q - q.mean(axis=0)
    t = np.radians(tilt_deg)
    rot = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    return q @ rot.T + centre


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def placements(v: np.ndarray, f: np.ndarray, which: tuple[str, ...], seed: int = 0) -> dict[str, dict]:
    """The scenes of one mesh: per placement its vertices (float64), faces (or None for a soup,
    then `tris`), quad light and dtype."""
    rng = np.random.default_rng(seed)
    top = float(v[:, 2].max())
    out: dict[str, dict] = {}
    above = {"v": v, "f": f, "quad": LIGHT.copy(), "dtype": np.float64}
    for name in which:
        if name == "above":
            out[name] = above
        elif name == "on floor":
            w = v.copy()
            w[:, 2] -= w[:, 2].min()
            out[name] = dict(above, v=w)
        elif name == "close":
            out[name] = dict(above, quad=_quad(np.array([0.0, 0.0, top + 0.05]), 0.8))
        elif name == "large":
            out[name] = dict(above, quad=_quad(np.array([0.0, 0.0, 2.5]), 3.0))
        elif name == "tilted":
            out[name] = dict(above, quad=_quad(np.array([0.0, 0.0, 2.5]), 0.8, 45.0))
        elif name == "rotated":
            c = (v.max(axis=0) + v.min(axis=0)) / 2
            w = (v - c) @ _random_rotation(rng).T
            w[:, :2] -= (w[:, :2].max(axis=0) + w[:, :2].min(axis=0)) / 2
            w[:, 2] += 0.3 - w[:, 2].min()
            out[name] = dict(above, v=w)
        elif name == "soup":
            t = v[f][rng.permutation(len(f))]
            t = np.concatenate([t, t[rng.choice(len(t), max(1, len(t) // 100), replace=False)]])
            out[name] = dict(above, f=None, tris=t[rng.permutation(len(t))])
        elif name == "soup degenerate":
            # Zero-area triangles (three distinct collinear points on the mesh's own edges) in a
            # shuffled soup: `Scene` refuses them (docs/design.md: degenerate input is an error at
            # build time), so the expected result is that refusal.
            t = v[f][rng.permutation(len(f))]
            a, b = t[:5, 0], t[:5, 1]
            t = np.concatenate([t, np.stack([a, b, (a + b) / 2], axis=1)])
            out[name] = dict(above, f=None, tris=t[rng.permutation(len(t))], expect="error")
        elif name == "float32":
            out[name] = dict(above, v=v.astype(np.float32).astype(np.float64), dtype=np.float32)
        else:
            raise ValueError(f"unknown placement {name!r}")
    return out


BOX_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
BOX_F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                  [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


def box(lo: Any, hi: Any) -> tuple[np.ndarray, np.ndarray]:
    """A closed box (12 triangles, normals outwards) from corner `lo` to corner `hi`."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return lo + BOX_V * (hi - lo), BOX_F.copy()


def t_junctions(v: np.ndarray, f: np.ndarray, every: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Every `every`-th face `(a, b, c)` split at the midpoint m of `a b` into `(a, m, c)` and
    `(m, b, c)`; the face across `a b` keeps the whole edge: m lies on its edge (a T-junction)."""
    new_v, out, n = [v], [], len(v)
    for i, (a, b, c) in enumerate(f):
        if i % every:
            out.append([a, b, c])
            continue
        new_v.append(((v[a] + v[b]) / 2)[None])
        out += [[a, n, c], [n, b, c]]
        n += 1
    return np.concatenate(new_v), np.asarray(out)


def slivers_abs(v: np.ndarray, f: np.ndarray, width: float, every: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Every `every`-th face `(a, b, c)` split at m, `width` metres from the midpoint of `a b`
    towards `c`: `(a, m, c)`, `(m, b, c)` and the sliver `(a, b, m)`, `width` wide."""
    new_v, out, n = [v], [], len(v)
    for i, (a, b, c) in enumerate(f):
        if i % every:
            out.append([a, b, c])
            continue
        mid = (v[a] + v[b]) / 2
        d = v[c] - mid
        new_v.append((mid + width * d / np.linalg.norm(d))[None])
        out += [[a, n, c], [n, b, c], [a, b, n]]
        n += 1
    return np.concatenate(new_v), np.asarray(out)


def on_shadow_edges(tris: np.ndarray, quad: np.ndarray, k: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """`k` floor points on planes through an occluder edge and a light vertex: the point where the
    ray from the light vertex through a point of the edge meets the floor (z = 0), normals up."""
    rng = np.random.default_rng(seed)
    t = tris[rng.integers(len(tris), size=k)]
    j = rng.integers(3, size=k)
    a, b = t[np.arange(k), j], t[np.arange(k), (j + 1) % 3]
    q = a + rng.uniform(0.05, 0.95, (k, 1)) * (b - a)
    light = quad[rng.integers(len(quad), size=k)]
    x = light + (q - light) * (light[:, 2] / (light[:, 2] - q[:, 2]))[:, None]
    x[:, 2] = 0.0
    return x, np.tile([0.0, 0.0, 1.0], (k, 1))


def generated(which: tuple[str, ...] | None = None, subdivisions: int = 3) -> dict[str, dict]:
    """Generated hard inputs (NumPy, trimesh), per name `{"v", "f"}` or `{"tris"}` (a soup), the
    quad light, optional extra receiver groups and `expect`: the smooth blob of
    `benchmarks.real_meshes` (`subdivisions` 3: 1 280 triangles; 1 m, 0.3 m above the floor) with fins (three faces
    on an edge), T-junctions, half its faces flipped, two copies offset by 0 and by 1e-9 m (one
    mesh, and a soup), slivers 1e-12 m wide (a mesh and a soup: refused), crossing the light's plane (its
    top 0.15 m above it, through the light polygon: clipped at the plane like the references), and
    with receivers exactly on shadow edges; a box sitting on a slab (coplanar touching faces, one
    mesh and two) with receivers on the slab around it."""
    from benchmarks.mesh_robustness import fins
    from benchmarks.real_meshes import blob

    v, f = blob(subdivisions)
    rng = np.random.default_rng(7)
    out: dict[str, dict] = {}
    base = {"quad": LIGHT.copy()}
    vf, ff = fins(v, f, k=40)
    out["fins"] = dict(base, v=vf, f=ff)
    vt, ft = t_junctions(v, f)
    out["T-junctions"] = dict(base, v=vt, f=ft)
    g = f.copy()
    flip = rng.random(len(g)) < 0.5
    g[flip] = g[flip][:, ::-1]
    out["half flipped"] = dict(base, v=v, f=g)
    for label, off in (("two copies, offset 0", 0.0), ("two copies, offset 1e-9", 1e-9)):
        v2 = np.concatenate([v, v + off / np.sqrt(3)])
        f2 = np.concatenate([f, f + len(v)])
        out[label] = dict(base, v=v2, f=f2)
        out[label + ", soup"] = dict(base, tris=v2[f2][rng.permutation(len(f2))])
    # Twice their area is below COPLANAR_RTOL times their squared size: `Mesh` and `Scene` refuse
    # them as zero-area faces (the documented rule), the expected result.
    vs, fs = slivers_abs(v, f, 1e-12)
    out["slivers 1e-12 m"] = dict(base, v=vs, f=fs, expect="error")
    out["slivers 1e-12 m, soup"] = dict(base, tris=vs[fs], expect="error")
    vx = v * 0.6 + [0.0, 0.0, 2.5 + 0.15 - (v[:, 2].max() * 0.6)]
    out["crossing the light's plane"] = dict(base, v=vx, f=f)
    pe, ne = on_shadow_edges(v[f], LIGHT, 96)
    out["receivers on shadow edges"] = dict(base, v=v, f=f, extra={"shadow edge": (pe, ne, np.ones(len(pe), bool))})
    bv, bf = box([-0.6, -0.6, 0.2], [0.6, 0.6, 0.3])
    cv, cf = box([-0.2, -0.25, 0.3], [0.2, 0.15, 0.7])
    tv, tf = np.concatenate([bv, cv]), np.concatenate([bf, cf + len(bv)])
    k = 96
    ang = rng.uniform(0, 2 * np.pi, k)
    rad = rng.uniform(0.0, 0.05, k) * (rng.random(k) < 0.8)
    side = rng.integers(4, size=k)
    edge_pt = np.array([[-0.2, 0], [0.2, 0], [0, -0.25], [0, 0.15]])[side] + np.c_[
        np.where(side < 2, 0, rng.uniform(-0.2, 0.2, k)), np.where(side < 2, rng.uniform(-0.25, 0.15, k), 0)]
    out_dir = np.array([[-1, 0], [1, 0], [0, -1], [0, 1]])[side]
    xy = edge_pt + out_dir * rad[:, None] + 0 * ang[:, None]
    pt = np.c_[xy, np.full(k, 0.3)]
    nt = np.tile([0.0, 0.0, 1.0], (k, 1))
    tilt = rng.random(k) < 0.4
    th = np.radians(rng.uniform(60, 89, k))
    nt[tilt] = np.c_[np.sin(th) * np.cos(ang), np.sin(th) * np.sin(ang), np.cos(th)][tilt]
    touch = {"slab top": (pt, nt, np.ones(k, bool))}
    out["box on a slab, one mesh"] = dict(base, v=tv, f=tf, extra=touch)
    out["box on a slab, two meshes"] = dict(base, meshes=[(bv, bf), (cv, cf)], v=tv, f=tf, extra=touch)
    if which is not None:
        out = {k: c for k, c in out.items() if k in which}
    return out


def light_of(kind: str, quad: np.ndarray, centre: np.ndarray) -> Any:
    """The light of `kind` made from the placement's quad."""
    import jaxshadow as js

    c = quad.mean(axis=0)
    if kind == "quad":
        return js.PolygonLight(quad, 1.0)
    if kind == "segment":
        return js.LinearLight((quad[0] + quad[1]) / 2, (quad[2] + quad[3]) / 2, 1.0)
    if kind == "point":
        return js.PointLight(c, 1.0)
    d = centre - c
    d = d / np.linalg.norm(d)
    side = np.cross(d, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    t = np.radians(10.0)
    return js.DirectionalLight(np.cos(t) * d + np.sin(t) * side, 1.0)


def fold_faces(tris: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per triangle of `tris (m, 3, 3)`: whether one of its edges is a fold (the face across it
    rises above this face's plane or lies in it, so it can hide light from a point of this face),
    a boundary or a non-manifold edge (not exactly two faces). Also the welded vertices (exactly
    equal positions) and the faces' indices into them."""
    x = tris.reshape(-1, 3)
    # Welded by exact equality: the rows sorted (lexicographically, as `np.unique(axis=0)`, faster).
    srt = np.lexsort((x[:, 2], x[:, 1], x[:, 0]))
    new = np.r_[True, np.any(x[srt][1:] != x[srt][:-1], axis=1)]
    pts = x[srt][new]
    inv = np.empty(len(x), np.int64)
    inv[srt] = np.cumsum(new) - 1
    f = inv.reshape(-1, 3)
    m = len(f)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    opp = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])
    face = np.tile(np.arange(m), 3)
    nrm = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    order = np.lexsort((e[:, 1], e[:, 0]))
    e, opp, face = e[order], opp[order], face[order]
    new = np.r_[True, np.any(e[1:] != e[:-1], axis=1)]
    start = np.flatnonzero(new)
    count = np.diff(np.r_[start, len(e)])
    flag = np.zeros(m, bool)
    odd = np.repeat(count != 2, count)
    flag[face[odd]] = True
    a = start[count == 2]
    for i, j in ((a, a + 1), (a + 1, a)):
        rise = np.einsum("kd,kd->k", nrm[face[i]], pts[opp[j]] - pts[e[i, 0]])
        flag[face[i][rise >= 0]] = True
    return flag, pts, f


def receivers(tris: np.ndarray, n: int, seed: int = 0) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Receiver groups for a mesh given as `tris (m, 3, 3)` (float64), about `n` in all, each
    `(points, normals, checked)`: `floor` (a grid on [-1.5, 1.5]^2, a fifth of it with grazing
    normals 60-88 degrees from the vertical), `contact` (floor points within 2 cm of the mesh's
    lowest vertices, grazing normals), `surface 0` and `surface 1e-9` (face centres and vertices
    with their face / area-weighted vertex normals, pushed along them by 0 and 1e-9 m), `inside
    box` (uniform in the mesh's bounding box, random normals). `checked` marks the receivers the
    brute-force reference always sees: contact ones, and those on a face with a fold, boundary or
    non-manifold edge (`fold_faces`) or at one of its vertices."""
    rng = np.random.default_rng(seed)
    out = {}
    fold, wpts, wf = fold_faces(tris)
    vfold = np.zeros(len(wpts), bool)
    vfold[wf[fold].ravel()] = True

    def grazing(k: int) -> np.ndarray:
        t, a = np.radians(rng.uniform(60, 88, k)), rng.uniform(0, 2 * np.pi, k)
        return np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=1)

    k_floor = max(16, int(0.35 * n))
    side = int(np.ceil(np.sqrt(k_floor)))
    g = np.linspace(-1.5, 1.5, side)
    xy = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)[:k_floor] + rng.uniform(-1e-3, 1e-3, (k_floor, 2))
    nf = np.tile([0.0, 0.0, 1.0], (k_floor, 1))
    nf[::5] = grazing(len(nf[::5]))
    out["floor"] = (np.c_[xy, np.zeros(k_floor)], nf, np.zeros(k_floor, bool))

    k_contact = max(8, n // 10)
    pts = tris.reshape(-1, 3)
    low = pts[pts[:, 2] <= pts[:, 2].min() + 0.01]
    base = low[rng.integers(len(low), size=k_contact)]
    off = rng.normal(size=(k_contact, 2))
    off *= rng.uniform(1e-4, 0.02, (k_contact, 1)) / np.linalg.norm(off, axis=1, keepdims=True)
    out["contact"] = (np.c_[base[:, :2] + off, np.zeros(k_contact)], grazing(k_contact), np.ones(k_contact, bool))

    fn = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    area = np.linalg.norm(fn, axis=1)
    vertex_normals = np.zeros((len(wpts), 3))
    for j in range(3):
        np.add.at(vertex_normals, wf[:, j], fn)
    good = np.where(area > 0)[0]
    k_face = max(8, n // 10)
    for push, label in ((0.0, "surface 0"), (1e-9, "surface 1e-9")):
        fi = rng.choice(good, min(k_face, len(good)), replace=False)
        nrm = fn[fi] / area[fi, None]
        # Face centres in barycentric coordinates, and the faces' first vertices (mesh vertices).
        c = tris[fi].mean(axis=1)
        vf = rng.choice(good, min(k_face, len(good)), replace=False)
        vi = tris[vf]
        vn = np.cross(vi[:, 1] - vi[:, 0], vi[:, 2] - vi[:, 0])
        # The area-weighted normal of the faces around each picked vertex (welded: equal positions).
        acc = vertex_normals[wf[vf, 0]]
        acc = np.where(np.linalg.norm(acc, axis=1, keepdims=True) > 0, acc, vn)
        vnrm = acc / np.linalg.norm(acc, axis=1, keepdims=True)
        p = np.concatenate([c + push * nrm, vi[:, 0] + push * vnrm])
        out[label] = (p, np.concatenate([nrm, vnrm]), np.concatenate([fold[fi], vfold[wf[vf, 0]]]))

    k_in = max(8, n - sum(len(x[0]) for x in out.values()))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    nr = rng.normal(size=(k_in, 3))
    out["inside box"] = (rng.uniform(lo, hi, (k_in, 3)), nr / np.linalg.norm(nr, axis=1, keepdims=True),
                         np.zeros(k_in, bool))
    return out


def _engine(scene: Any, p: np.ndarray, n: np.ndarray, env: dict[str, str] | None = None,
            device: bool = False, second: bool = True) -> tuple[np.ndarray, float]:
    """`js.irradiance` (values, seconds of a second call, or of the only call if not `second`)
    with `env` set for the call."""
    import jaxshadow as js

    old = {k: os.environ.get(k) for k in (env or {})}
    os.environ.update(env or {})
    try:
        kw = {"shadows": js.ShadowOptions(engine="device")} if device else {}
        if second:
            np.asarray(js.irradiance(scene, p, n, **kw))
        t = time.perf_counter()
        e = np.asarray(js.irradiance(scene, p, n, **kw))[:, 0]
        return e, time.perf_counter() - t
    finally:
        for k, x in old.items():
            if x is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = x


FACE_PATH = {"quad": {"JAXSHADOW_SILHOUETTE": "0"}, "segment": {"JAXSHADOW_SEGMENT_PIECES": "0"}}


def _independent(kind: str, light: Any, tris: np.ndarray, p: np.ndarray, n: np.ndarray) -> np.ndarray:
    if kind == "quad":
        return chk.polygon_reference(np.asarray(light.vertices, float), tris, p, n)
    return chk.kind_reference({"segment": "segment", "point": "point", "directional": "directional"}[kind],
                              light, tris, p, n)


# The polygon booleans' cost grows with the faces a receiver's light pyramid holds (the overlay of
# their projections: about 8 CPU-s for 50 000): per case at most this many faces in all
# (`--full`: no cap), the first receiver (the worst disagreement) always checked.
FACE_CAP = 60_000


def _polygon_checked(light: Any, tris: np.ndarray, p: np.ndarray, n: np.ndarray, order: list[tuple[str, int]],
                     cap: int | None) -> tuple[np.ndarray, np.ndarray, dict[str, list[int]]]:
    """Polygon booleans (`chk.reference_ff_batched` on the faces `culled` keeps and the on-surface
    rule leaves) on the receivers `order` names, in its order: `(category, index)` pairs; a
    receiver whose faces would take the case's total over `cap` is left out (not the first).
    Returns the indices checked, their values (E / L) and per category `[checked, left out]`."""
    tc, tp, tm = chk.refs()
    lv = np.asarray(light.vertices, float)
    done: list[int] = []
    vals: list[float] = []
    count: dict[str, list[int]] = {}
    total = 0
    for what, i in order:
        if i in done:
            continue
        c = count.setdefault(what, [0, 0])
        y = n[i] / np.linalg.norm(n[i])
        faces = np.asarray(tm._off_surface(p[i], tp.culled(p[i], y, lv, tris), chk.ON_SURFACE_64), np.float64).reshape(-1, 3, 3)
        if cap is not None and done and total + len(faces) > cap:
            c[1] += 1
            continue
        total += len(faces)
        done.append(i)
        vals.append(np.pi * chk.reference_ff_batched(p[i], y, lv, faces))
        c[0] += 1
    return np.asarray(done, int), np.asarray(vals), count


# Receivers the brute-force reference sees besides the checked and penumbra ones: this share of
# the rest (at least REST_MIN); the device kernel (point, directional) on at most DEVICE_MAX of them.
REST_SHARE, REST_MIN, DEVICE_MAX = 0.125, 16, 32


def reference_subset(checked: np.ndarray, e: np.ndarray, unocc: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices of the receivers the brute-force reference sees: every `checked` one (contact, near
    folds and boundaries), every penumbra one (0 < E < U), and a random share of the rest."""
    pen = (e > 0) & (e < (1 - 1e-12) * np.abs(unocc))
    must = checked | pen
    rest = np.flatnonzero(~must)
    k = min(len(rest), max(REST_MIN, int(REST_SHARE * len(rest))))
    return np.union1d(np.flatnonzero(must), rng.choice(rest, k, replace=False)).astype(int)


def case(tris: np.ndarray, occluders: Any, kind: str, light: Any, groups: dict, dtype: Any,
         n_ref: int, seed: int = 0, scene64: Any = None, face_cap: int | None = FACE_CAP,
         second_call: bool = False) -> dict:
    """One mesh, placement and light kind: the engine on every receiver, against the brute-force
    path (face path / device kernel) on `reference_subset` and the independent reference (quad
    lights: the `n_ref // 2` worst disagreements, one receiver of each group with checked ones
    (contact, on-surface near a fold, the input's own), `n_ref - n_ref // 2` random penumbra ones,
    at most `face_cap` faces in all (`_polygon_checked`); segment lights: the worst disagreement
    and `n_ref - 1` penumbra ones; point and directional: ray tests on the whole subset). Seconds
    of wall (`*_s`) and of CPU, all threads (`*_cpu_s`), per step; the engine's wall seconds of its
    only call, or with `second_call` of a second one (compilation and caches warm)."""
    import jaxshadow as js

    names = list(groups)
    p = np.concatenate([groups[k][0] for k in names])
    nrm = np.concatenate([groups[k][1] for k in names])
    checked = np.concatenate([groups[k][2] for k in names])
    label = np.concatenate([[i] * len(groups[k][0]) for i, k in enumerate(names)])
    row: dict[str, Any] = {"receivers": int(len(p))}
    t = time.perf_counter()
    scene = js.Scene([light], occluders=occluders)
    row["build_s"] = time.perf_counter() - t
    if dtype == np.float32:
        p32, n32 = p.astype(np.float32), nrm.astype(np.float32)
        t, c = time.perf_counter(), time.process_time()
        e32 = np.asarray(js.irradiance(scene, p32, n32))[:, 0]
        row["engine_s"] = time.perf_counter() - t
        row["engine_cpu_s"] = time.process_time() - c
        row["nonfinite"] = int((~np.isfinite(e32)).sum())
        # The same rounded inputs in float64: the light's and occluders' values are float32 values
        # (the scene was built from them), so a float64 scene of the same numbers.
        p, nrm = p32.astype(np.float64), n32.astype(np.float64)
        e64, _ = _engine(scene64, p, nrm, second=False)
        unocc = np.asarray(js.irradiance(js.Scene(scene64.lights), p, nrm))[:, 0]
        # The property suite's float32 bound: 1e-5 U plus Lambert's sum's absolute rounding
        # (8 float32 epsilons of 0.1 pi); the share of it used.
        bound = 1e-5 * np.abs(unocc) + 8 * float(np.finfo(np.float32).eps) * 0.1 * np.pi
        err = np.abs(e32 - e64) / bound * TOL["float32"]
        row["max_rel_err"] = float(np.nanmax(err)) if len(err) else 0.0
        row["reference"] = "float64 engine, share of the float32 bound x 1e-5"
        row["reference_receivers"] = int(len(p))
        row["by_group"] = {k: float(np.nanmax(err[label == i])) for i, k in enumerate(names)}
        return row
    c = time.process_time()
    e, row["engine_s"] = _engine(scene, p, nrm, second=second_call)
    row["nonfinite"] = int((~np.isfinite(e)).sum())
    unocc = np.asarray(js.irradiance(js.Scene([light]), p, nrm))[:, 0]
    row["engine_cpu_s"] = time.process_time() - c
    floor = 1e-3 * max(float(np.abs(unocc).max()), 1e-300)
    scale = np.maximum(np.abs(unocc), floor)
    rng = np.random.default_rng(seed)
    sel = reference_subset(checked, e, unocc, rng)
    hard = kind in ("point", "directional")
    if hard and len(sel) > DEVICE_MAX:
        # The device kernel's cost grows with faces x receivers: the checked receivers first.
        order = np.argsort(~checked[sel], kind="stable")
        dsel = np.sort(sel[order[:DEVICE_MAX]])
    else:
        dsel = sel
    row["reference_receivers"] = int(len(dsel))
    # Padded to a fixed count (the engine's, or DEVICE_MAX) by receivers far below the floor facing
    # down (nothing to compute): one compiled shape per scene, not one per subset size.
    size = len(p) if kind in FACE_PATH else max(DEVICE_MAX, len(dsel))
    low = np.array([0.0, 0.0, float(p[:, 2].min()) - 1e3])
    pp = np.concatenate([p[dsel], np.tile(low, (size - len(dsel), 1))])
    pn = np.concatenate([nrm[dsel], np.tile([0.0, 0.0, -1.0], (size - len(dsel), 1))])
    c = time.process_time()
    if kind in FACE_PATH:
        ref, row["reference_s"] = _engine(scene, pp, pn, env=FACE_PATH[kind], second=False)
        row["reference"] = "face path"
    else:
        ref, row["reference_s"] = _engine(scene, pp, pn, device=True, second=False)
        row["reference"] = "device kernel"
    row["reference_cpu_s"] = time.process_time() - c
    ref = ref[: len(dsel)]
    err = np.abs(e[dsel] - ref) / scale[dsel]
    err[~np.isfinite(err)] = np.inf
    if hard:
        flip = (e[dsel] > 0) != (ref > 0)
        row["hard_disagree"] = int(flip.sum())
        err = np.where(flip, 0.0, err)
    row["max_rel_err"] = float(err.max()) if len(err) else 0.0
    row["by_group"] = {k: float(err[label[dsel] == i].max(initial=0.0)) for i, k in enumerate(names)}
    # The independent reference: hard shadows on the whole subset (ray tests are cheap); area
    # lights where the engine and the brute-force path disagree most, and on a few receivers of
    # the shadow's edge (neither 0 nor unoccluded).
    t, c = time.perf_counter(), time.process_time()
    if hard:
        isel = sel
        ind = _independent(kind, light, tris, p[isel], nrm[isel])
    else:
        worst = dsel[np.argsort(-err)[: max(1, n_ref // 2)]]
        edge = np.where((e > 0) & (e < 0.999 * unocc))[0]
        more = rng.choice(edge, min(len(edge), n_ref - len(worst)), replace=False) if len(edge) else np.zeros(0, int)
        if kind == "quad":
            picks = [("worst", int(i)) for i in worst]
            for gi, k in enumerate(names):
                own = np.flatnonzero(checked & (label == gi))
                if len(own):
                    picks.append((k, int(rng.choice(own))))
            picks += [("penumbra", int(i)) for i in more]
            isel, ind, row["independent_by_kind"] = _polygon_checked(light, tris, p, nrm, picks, face_cap)
            srt = np.argsort(isel)
            isel, ind = isel[srt], ind[srt]
        else:
            isel = np.unique(np.concatenate([worst, more]).astype(int))
            ind = _independent(kind, light, tris, p[isel], nrm[isel])
    row["independent_s"] = time.perf_counter() - t
    row["independent_cpu_s"] = time.process_time() - c
    row["independent_receivers"] = int(len(isel))
    ie = np.abs(e[isel] - ind) / scale[isel]
    pos = np.searchsorted(dsel, isel)
    pos = np.minimum(pos, len(dsel) - 1)
    both = dsel[pos] == isel
    ir = np.abs(ref[pos[both]] - ind[both]) / scale[isel[both]]
    if hard:
        row["hard_disagree_independent"] = int(np.sum((e[isel] > 0) != (ind > 0)))
        ie = np.where((e[isel] > 0) != (ind > 0), 0.0, ie)
        ir = np.where((ref[pos[both]] > 0) != (ind[both] > 0), 0.0, ir)
    row["max_rel_err_independent"] = float(ie.max()) if len(ie) else 0.0
    row["reference_vs_independent"] = float(ir.max()) if len(ir) else 0.0
    if row["max_rel_err_independent"] > TOL["float64"] or row["max_rel_err"] > TOL["float64"]:
        bad = np.unique(np.concatenate([isel[np.argsort(-ie)[:3]], dsel[np.argsort(-err)[:3]]]))
        row["worst"] = [{"group": names[label[i]], "p": p[i].tolist(), "n": nrm[i].tolist(), "engine": float(e[i]),
                         "unoccluded": float(unocc[i])} for i in bad]
    return row


def run(paths: list[str], n: int, n_ref: int, kinds: tuple[str, ...], which: tuple[str, ...],
        up: str = "y", verbose: bool = True, full: bool = False, n_generated: int = 0) -> list[dict]:
    """The sweep's rows: per file, placement (`which`) and light kind (`kinds`; each only on its
    `DEFAULT` placements unless `full`), `case` on about `n` receivers (`receivers`) with `n_ref`
    of them checked by the independent reference for area lights (2 for segment lights, whose
    reference integrates numerically). Then, if `n_generated`, every `generated` input under
    every light kind on about `n_generated` receivers (`receivers` and the input's own)."""
    import jax

    import jaxshadow as js

    jax.config.update("jax_enable_x64", True)
    cap = None if full else FACE_CAP
    rows = []
    for path in paths:
        try:
            v, f = load_file(path, up)
        except Exception as ex:  # an unreadable file is a row of the sweep, not its end
            row = {"mesh": Path(path).name, "triangles": 0, "placement": "-", "light": "-", "expect": "ok",
                   "error": f"{type(ex).__name__}: {str(ex)[:200]}", "wall_s": 0.0}
            rows.append(row)
            if verbose:
                print(_line(row), flush=True)
            continue
        for pname, pl in placements(v, f, which).items():
            if not full and not any(pname in DEFAULT[k] for k in kinds):
                continue
            tris = pl["tris"] if pl["f"] is None else pl["v"][pl["f"]]
            centre = (tris.reshape(-1, 3).max(axis=0) + tris.reshape(-1, 3).min(axis=0)) / 2
            groups = _receivers_cached(tris, n)
            meshes: dict[Any, Any] = {}  # one `js.Mesh` per placement and dtype, for every light kind

            def mesh(dt: Any, pl: dict = pl, meshes: dict = meshes) -> Any:
                if dt not in meshes:
                    meshes[dt] = js.Mesh(pl["v"].astype(dt), pl["f"])
                return meshes[dt]

            for kind in kinds:
                dt = pl["dtype"]
                quad = pl["quad"].astype(dt).astype(np.float64) if dt == np.float32 else pl["quad"]
                light = light_of(kind, quad.astype(dt), centre)
                if not full and pname not in DEFAULT[kind]:
                    continue
                if pl["f"] is None:
                    occ: Any = pl["tris"]
                else:
                    occ = lambda dt=dt, mesh=mesh: [mesh(dt)]  # noqa: E731
                # float32: the float64 engine on the same rounded numbers is the reference.
                s64 = js.Scene([light_of(kind, quad, centre)], occluders=[mesh(np.float64)]) if dt == np.float32 else None
                head = {"mesh": Path(path).name, "triangles": int(len(tris)), "placement": pname, "light": kind}
                rows.append(_row(head, tris, occ, kind, light, groups, dt, n_ref, s64, pl.get("expect", "ok"), verbose, cap, full))
    if n_generated:
        for name, g in generated().items():
            tris = g["tris"] if "tris" in g else g["v"][g["f"]]
            groups = receivers(tris, n_generated) | g.get("extra", {})
            centre = (tris.reshape(-1, 3).max(axis=0) + tris.reshape(-1, 3).min(axis=0)) / 2
            for kind in kinds:
                if "tris" in g:
                    occ = g["tris"]
                elif "meshes" in g:
                    occ = lambda g=g: [js.Mesh(x, y) for x, y in g["meshes"]]  # noqa: E731
                else:
                    occ = lambda g=g: [js.Mesh(g["v"], g["f"])]  # noqa: E731
                head = {"mesh": "generated", "triangles": int(len(tris)), "placement": name, "light": kind}
                rows.append(_row(head, tris, occ, kind, light_of(kind, g["quad"], centre), groups, np.float64, n_ref,
                                 None, g.get("expect", "ok"), verbose, cap, full))
    return rows


_RECEIVERS: dict[tuple, dict] = {}


def _receivers_cached(tris: np.ndarray, n: int) -> dict:
    """`receivers(tris, n)`, computed once per distinct triangle array (placements that only move
    the light share their mesh's)."""
    import hashlib

    key = (tris.shape, n, hashlib.blake2b(np.ascontiguousarray(tris).tobytes(), digest_size=16).hexdigest())
    if key not in _RECEIVERS:
        if len(_RECEIVERS) >= 4:
            _RECEIVERS.pop(next(iter(_RECEIVERS)))
        _RECEIVERS[key] = receivers(tris, n)
    return _RECEIVERS[key]


def _row(head: dict, tris: np.ndarray, occ: Any, kind: str, light: Any, groups: dict, dt: Any, n_ref: int,
         s64: Any, expect: str, verbose: bool, cap: int | None = FACE_CAP, second_call: bool = False) -> dict:
    t, c = time.perf_counter(), time.process_time()
    try:
        if callable(occ):  # a Mesh refusing its input is a result too
            occ = occ()
        row = head | case(tris, occ, kind, light, groups, dt, n_ref if kind != "segment" else min(n_ref, 2), scene64=s64,
                          face_cap=cap, second_call=second_call)
    except Exception as ex:  # a crash is a result of the sweep
        row = head | {"error": f"{type(ex).__name__}: {str(ex)[:200]}"}
    row["expect"] = expect
    row["wall_s"] = time.perf_counter() - t
    row["cpu_s"] = time.process_time() - c
    row["load_1min"] = os.getloadavg()[0]
    if verbose:
        print(_line(row), flush=True)
    return row


def _ok(r: dict) -> bool:
    if r.get("expect") == "error":
        return "error" in r
    if "error" in r or r.get("nonfinite", 0):
        return False
    tol = TOL["float32" if r["placement"] == "float32" else "float64"]
    return r["max_rel_err"] <= tol and r.get("max_rel_err_independent", 0.0) <= tol


def _line(r: dict) -> str:
    cells = [r["mesh"], str(r["triangles"]), r["placement"], r["light"], "pass" if _ok(r) else "FAIL"]
    if "error" in r:
        cells += [r["error"]]
    else:
        ind = r.get("max_rel_err_independent")
        cells += [f"{r['receivers']}", f"{r['max_rel_err']:.1e} ({r['reference']})",
                  f"{ind:.1e} ({_checked(r)})" if ind is not None else "-",
                  str(r["nonfinite"]), str(r.get("hard_disagree", "-")), f"{r['engine_s']:.3f}",
                  f"{r.get('reference_cpu_s', 0.0):.1f} ({r['reference_receivers']})", f"{r.get('independent_cpu_s', 0.0):.1f}",
                  f"{r['cpu_s']:.1f}", f"{r['wall_s']:.1f}"]
    return "| " + " | ".join(cells) + " |"


def _checked(r: dict) -> str:
    """The independent reference's receivers: how many, and for polygon booleans per category
    (and how many the face cap left out)."""
    by = r.get("independent_by_kind")
    if not by:
        return str(r["independent_receivers"])
    parts = [f"{k} {c[0]}" for k, c in by.items() if c[0]]
    out = sum(c[1] for c in by.values())
    return f"{r['independent_receivers']}: " + ", ".join(parts) + (f"; {out} over the face cap" if out else "")


HEADER = ("| mesh | triangles | placement | light | result | receivers | max rel. err vs brute force | "
          "max rel. err vs independent (receivers) | non-finite | hard-shadow flips | engine s (wall) | "
          "brute force CPU s (receivers) | independent CPU s | case CPU s | case wall s |\n"
          "|---|---:|---|---|---|---:|---|---|---:|---:|---:|---:|---:|---:|---:|")


def main(argv: list[str] | None = None) -> int:
    """`python -m benchmarks.mesh_sweep --mesh FILE [--mesh FILE ...] | --dir DIR [--record]`."""
    import argparse
    import sys

    ap = argparse.ArgumentParser(prog="python -m benchmarks.mesh_sweep", description=__doc__.split("\n")[0])
    ap.add_argument("--mesh", action="append", default=[], help="a mesh file; repeatable")
    ap.add_argument("--dir", default=None, help="every mesh file (.obj, .ply, .stl, .off) in this folder")
    ap.add_argument("--receivers", type=int, default=320, help="receivers per case (default 320)")
    ap.add_argument("--ref", type=int, default=4,
                    help="area-light receivers per case checked by the independent reference (default 4)")
    ap.add_argument("--kinds", default=",".join(KINDS), help="light kinds, comma-separated")
    ap.add_argument("--placements", default=",".join(PLACEMENTS), help="placements, comma-separated")
    ap.add_argument("--full", action="store_true",
                    help="every light kind on every placement, no face cap, the engine timed on a second call")
    ap.add_argument("--generated", type=int, default=240,
                    help="receivers per generated input (`generated`; default 240, 0: none)")
    ap.add_argument("--up", choices=("x", "y", "z"), default="y")
    ap.add_argument("--record", action="store_true", help="write benchmarks/results/mesh_sweep.{json,md}")
    args = ap.parse_args(argv)
    paths = list(args.mesh)
    if args.dir:
        paths += sorted(str(x) for x in Path(args.dir).iterdir() if x.suffix.lower() in (".obj", ".ply", ".stl", ".off"))
    if not paths and not args.generated:
        ap.error("nothing to sweep: give --mesh or --dir, or --generated N")
    print(HEADER, flush=True)
    load0 = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    rows = run(paths, args.receivers, args.ref, tuple(args.kinds.split(",")), tuple(args.placements.split(",")), args.up,
               full=args.full, n_generated=args.generated)
    failed = [r for r in rows if not _ok(r)]
    # CPU seconds of the whole process (all threads; the references are single-threaded, the
    # engine uses up to its thread count): a shared machine's load stretches the wall time, not these.
    cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    loads = [load0] + [r["load_1min"] for r in rows if "load_1min" in r] + [os.getloadavg()[0]]
    timing = (f"{cpu:.0f} CPU-s, {wall:.0f} s wall, 1-minute load {min(loads):.1f}-{max(loads):.1f} "
              f"(mean {np.mean(loads):.1f})")
    print(f"{len(rows)} cases, {len(failed)} failed, {timing}", flush=True)
    if args.record:
        from benchmarks._suite import RESULTS, caption, meta, write_json, write_text

        info = meta(NAME, False)
        info["command"] = "python -m benchmarks.mesh_sweep " + " ".join(sys.argv[1:] if argv is None else argv)
        info["wall_s"] = round(wall, 1)
        info["cpu_s"] = round(cpu, 1)
        info["load_1min_during"] = [round(min(loads), 2), round(float(np.mean(loads)), 2), round(max(loads), 2)]
        record = {"benchmark": NAME, "meta": info, "results": rows}
        write_json(RESULTS / "mesh_sweep.json", record)
        write_text(RESULTS / "mesh_sweep.md", caption(record) + f"\n\nWhole run: {timing}.\n\n" + HEADER + "\n"
                   + "\n".join(_line(r) for r in rows) + f"\n\n{len(rows)} cases, {len(failed)} failed. " + NOTE + "\n")
    return 1 if failed else 0


NOTE = ("Errors: |E - ref| / max(U, 1e-3 max U), U the unoccluded value; bound 1e-9 (float32: against the float64 engine on "
        "the same rounded inputs, the share of the bound 1e-5 U + 8 eps32 0.1 pi, times 1e-5). Brute force: the face path (quad, segment) or the device kernel (point, "
        "directional; at most 32 receivers) on the reference subset (contact receivers, on-surface ones near folds, "
        "boundaries and non-manifold edges, penumbra ones, an eighth of the rest); independent: polygon booleans in "
        "shapely (quad: the worst receivers, one of each group with checked ones, a few penumbra ones, at most "
        f"{FACE_CAP} faces per case in all, the first always; --full: no cap) and Gauss-Legendre (segment: the worst and one in the "
        "shadow's edge), ray tests "
        "(point, directional) on the whole subset. Hard-shadow flips: receivers whose lit/shadowed decision differs from the device "
        "kernel's (on a shadow boundary: rounding), left out of the errors. Times: CPU seconds of the process (all "
        "threads) per step and case, the case's wall seconds, and the engine's wall seconds (its only call; --full: a "
        "second call).")


if __name__ == "__main__":
    raise SystemExit(main())
