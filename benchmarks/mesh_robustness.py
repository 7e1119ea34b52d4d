"""Robustness sweep of the real-mesh engine: odd meshes, files, light kinds and entry points, against brute-force references.

A new user's tour of the shadow engine with meshes it was not tuned on. Occluders (generated with
trimesh and NumPy; `benchmarks.real_meshes.blob`, 1 280 triangles, 1 m, 0.3 m above the floor,
under the 0.8 m quad light at z = 2.5): the mesh as `js.Mesh`; as a triangle soup (an `(m, 3, 3)`
array and a list, vertices duplicated per triangle, faces shuffled); shuffled with a third of the
faces flipped; non-manifold (fins: three faces on an edge; two shapes sharing one vertex, a
bow-tie); zero-area and repeated-vertex faces (as a `Mesh`, a soup and in a file); sliver
triangles (faces split at a point 1e-6 or 1e-8 of their height off an edge); duplicate faces (some
reversed); intersecting and nested components; an open cup seen from inside (receivers on its
inner faces); a mesh crossing the floor (receivers on and under it); a mesh straddling the
light's plane; the scene scaled to 1e4 m and 1e-4 m and translated by 1e3 m; float32 inputs;
mesh files trimesh writes (OBJ with normals and texture coordinates, PLY, STL, OFF; OBJ quads
and n-gons; a PLY of triangle strips) read with `js.read_mesh`, and an empty file.

Per case: the scene's build time, `js.irradiance` (first and second call), the sanity counts
(non-finite, negative, above the unoccluded value, umbra not 0), the largest error against the
brute-force reference (`benchmarks._robustness_checks`) on receivers picked by class, the
float32 values against float64 on the same rounded inputs, and for soups the CPU-time ratio to
the same `js.Mesh` (alternating, best of five, `JAXSHADOW_THREADS=1`). Then point, directional and
segment lights on the mesh, the soup and the open cup; `js.shadow_plan`'s classes; `ShadowCache`
updated after moving the mesh against a rebuild; `js.illumination_mesh` of the floor; gradients
with respect to receivers and light vertices against central differences; a Mitsuba scene with
the soup rendered (`jaxshadow.cli.render.render`, when Mitsuba is installed).

    python -m benchmarks mesh_robustness [--quick]
    python -m benchmarks.mesh_robustness --mesh /path/bunny.obj [--mesh ...] [--quick]

The second form runs the per-case checks and light kinds on mesh files (`real_meshes.load_file`:
up axis y, 1 m, 0.3 m above the floor) and writes `results/mesh_robustness_files[_quick].{json,md}`.
"""

from __future__ import annotations

import os
import resource
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import _robustness_checks as chk
from benchmarks.real_meshes import LIGHT, blob

NAME = "mesh_robustness"
TOL = {"float64": 1e-9, "float32": 1e-5}


def floor(n: int, seed: int = 0, half: float = 1.2) -> tuple[np.ndarray, np.ndarray]:
    """Floor receivers on [-half, half]^2, a fifth of them with grazing normals (60-88 degrees)."""
    rng = np.random.default_rng(seed)
    p = np.c_[rng.uniform(-half, half, (n, 2)), np.zeros(n)]
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    k = n // 5
    t, a = np.radians(rng.uniform(60, 88, k)), rng.uniform(0, 2 * np.pi, k)
    nrm[:k] = np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=1)
    return p, nrm


# --------------------------------------------------------------------------------------
# Generated meshes
# --------------------------------------------------------------------------------------


def soup(v: np.ndarray, f: np.ndarray, seed: int = 0) -> np.ndarray:
    """`(m, 3, 3)`: the faces shuffled, each triangle's corners rotated (same orientation)."""
    rng = np.random.default_rng(seed)
    t = v[f][rng.permutation(len(f))]
    return np.stack([np.roll(x, int(rng.integers(3)), axis=0) for x in t])


def flipped(f: np.ndarray, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    g = f[rng.permutation(len(f))].copy()
    k = rng.random(len(g)) < 1 / 3
    g[k] = g[k][:, ::-1]
    return g


def fins(v: np.ndarray, f: np.ndarray, k: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """`k` fin triangles on edges of the mesh, standing out 0.1 m: three faces on those edges."""
    new_v, new_f = [v], [f]
    for i, face in enumerate(f[:: max(1, len(f) // k)][:k]):
        a, b, c = v[face]
        nrm = np.cross(b - a, c - a)
        apex = (a + b) / 2 + 0.1 * nrm / np.linalg.norm(nrm) + 0.02 * (b - a)
        new_v.append(apex[None])
        new_f.append(np.array([[face[0], face[1], len(v) + i]]))
    return np.concatenate(new_v), np.concatenate(new_f)


def bowtie(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two half-size copies sharing one vertex (the first's highest x, the second's lowest x)."""
    a = (v - v.mean(axis=0)) * 0.5 + [-0.25, 0.0, 0.8]
    b = (v - v.mean(axis=0)) * 0.5
    i, j = int(np.argmax(a[:, 0])), int(np.argmin(b[:, 0]))
    b = b + (a[i] - b[j])
    keep = np.arange(len(b)) != j
    idx = np.full(len(b), -1)
    idx[keep] = len(a) + np.arange(keep.sum())
    idx[j] = i
    return np.concatenate([a, b[keep]]), np.concatenate([f, idx[f]])


def slivers(v: np.ndarray, f: np.ndarray, every: int = 7, off: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Every `every`-th face `(a, b, c)` split at `m`, `off` of the way from the midpoint of `a b`
    towards `c`: `(a, m, c)`, `(m, b, c)` and the sliver `(a, b, m)` (the same point set)."""
    new_v, out = [v], []
    n = len(v)
    for i, (a, b, c) in enumerate(f):
        if i % every:
            out.append([a, b, c])
            continue
        m = (v[a] + v[b]) / 2 + off * (v[c] - (v[a] + v[b]) / 2)
        new_v.append(m[None])
        out += [[a, n, c], [n, b, c], [a, b, n]]
        n += 1
    return np.concatenate(new_v), np.asarray(out)


def components(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Three components in one mesh: two intersecting copies and a small one nested in the first."""
    c = v.mean(axis=0)
    parts = [(v - c) * 0.6 + [-0.15, 0.0, 1.0], (v - c) * 0.6 + [0.15, 0.1, 1.1], (v - c) * 0.15 + [-0.15, 0.0, 1.0]]
    return np.concatenate(parts), np.concatenate([f + k * len(v) for k in range(3)])


def cup(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The mesh with its top third removed (open towards the light), and receivers on its inner
    surface (faces whose outward normal points down, with the inward normal) at random
    barycentric points."""
    zc = v[f][:, :, 2].mean(axis=1)
    g = f[zc < v[:, 2].min() + 0.66 * np.ptp(v[:, 2])]
    t = v[g]
    nrm = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    inner = np.where(nrm[:, 2] < -0.3)[0]
    rng = np.random.default_rng(5)
    pick = rng.choice(inner, min(60, len(inner)), replace=False)
    b = rng.dirichlet(np.ones(3), len(pick))
    return v, g, np.einsum("nk,nkd->nd", b, t[pick]), -nrm[pick]


# --------------------------------------------------------------------------------------
# Cases
# --------------------------------------------------------------------------------------


def cases(quick: bool) -> dict[str, dict]:
    """name -> {"make": () -> occluders, "tris": the blocking triangles (float64), "expect": "ok" |
    "error", optional "p", "n", "light", "dtype", "mesh_of" (the same geometry as a js.Mesh)}."""
    import jaxshadow as js

    v, f = blob(2 if quick else 3)
    tri = v[f]
    out: dict[str, dict] = {}
    out["mesh"] = {"make": lambda: [js.Mesh(v, f)], "tris": tri}
    s = soup(v, f)
    out["soup (m,3,3) array"] = {"make": lambda: s, "tris": s, "mesh_of": lambda: [js.Mesh(v, f)]}
    out["soup list"] = {"make": lambda: list(s), "tris": s, "mesh_of": lambda: [js.Mesh(v, f)]}
    g = flipped(f)
    out["shuffled, a third flipped"] = {"make": lambda: [js.Mesh(v, g)], "tris": v[g]}
    sf = soup(v, g)
    out["soup, flipped"] = {"make": lambda: sf, "tris": sf, "mesh_of": lambda: [js.Mesh(v, f)]}
    vf, ff = fins(v, f)
    out["fins (3 faces on an edge)"] = {"make": lambda: [js.Mesh(vf, ff)], "tris": vf[ff]}
    vb, fb = bowtie(v, f)
    out["bow-tie vertex"] = {"make": lambda: [js.Mesh(vb, fb)], "tris": vb[fb]}
    vs, fs = slivers(v, f)
    out["slivers (1e-6)"] = {"make": lambda: [js.Mesh(vs, fs)], "tris": vs[fs]}
    v8, f8 = slivers(v, f, off=1e-8)
    out["slivers (1e-8)"] = {"make": lambda: [js.Mesh(v8, f8)], "tris": v8[f8]}
    out["slivers (1e-8), soup"] = {"make": lambda: v8[f8], "tris": v8[f8], "mesh_of": lambda: [js.Mesh(v8, f8)]}
    dup = np.concatenate([f, f[:40], f[40:80, ::-1]])
    out["duplicate faces"] = {"make": lambda: [js.Mesh(v, dup)], "tris": v[dup]}
    out["duplicate faces, soup"] = {"make": lambda: v[dup], "tris": v[dup]}
    vc, fc = components(v, f)
    out["intersecting + nested components"] = {"make": lambda: [js.Mesh(vc, fc)], "tris": vc[fc]}
    out["components as a soup"] = {"make": lambda: soup(vc, fc), "tris": vc[fc]}
    vu, fu, pu, nu = cup(v, f)
    pf, nf = floor(60, seed=4)
    out["open cup seen from inside"] = {"make": lambda: [js.Mesh(vu, fu)], "tris": vu[fu],
                                        "p": np.concatenate([pu, pf]), "n": np.concatenate([nu, nf])}
    vx = v - [0.0, 0.0, v[:, 2].min() + 0.15]
    px, nx = floor(200, seed=6, half=0.8)
    px = np.concatenate([px, px[:40] - [0.0, 0.0, 0.05]])
    nx = np.concatenate([nx, nx[:40]])
    out["crossing the floor"] = {"make": lambda: [js.Mesh(vx, f)], "tris": vx[f], "p": px, "n": nx}
    vl = v - v.mean(axis=0) + [0.95, 0.0, 2.5]
    out["straddling the light's plane"] = {"make": lambda: [js.Mesh(vl, f)], "tris": vl[f]}
    for label, scale, shift in (("scaled 1e4", 1e4, 0.0), ("scaled 1e-4", 1e-4, 0.0), ("translated 1e3", 1.0, 1e3)):
        t = np.array([shift, -shift, shift])
        vt = v * scale + t
        pt, nt = floor(300, seed=2)
        out[label] = {"make": lambda vt=vt: [js.Mesh(vt, f)], "tris": vt[f], "p": pt * scale + t, "n": nt,
                      "light": LIGHT * scale + t}
        out[label + ", soup"] = {"make": lambda vt=vt: soup(vt, f), "tris": vt[f], "p": pt * scale + t, "n": nt,
                                 "light": LIGHT * scale + t}
    v32 = v.astype(np.float32)
    out["float32 mesh"] = {"make": lambda: [js.Mesh(v32, f)], "tris": v32.astype(float)[f], "dtype": np.float32}
    out["float32 soup"] = {"make": lambda: soup(v32, f), "tris": v32.astype(float)[f], "dtype": np.float32}
    # Zero-area faces: a repeated vertex, and three collinear vertices.
    vd = np.concatenate([v, [(v[f[0, 0]] + v[f[0, 1]]) / 2]])
    fd = np.concatenate([f, [[f[0, 0], f[0, 0], f[0, 1]], [f[0, 0], f[0, 1], len(v)]]])
    out["zero-area faces (Mesh)"] = {"make": lambda: [js.Mesh(vd, fd)], "tris": tri, "expect": "error"}
    out["zero-area faces (soup)"] = {"make": lambda: vd[fd], "tris": tri, "expect": "error"}
    return out


def file_cases(quick: bool, folder: str) -> dict[str, dict]:
    """Mesh files trimesh writes, read with `js.read_mesh` (`.occluder()`)."""
    import trimesh

    import jaxshadow as js

    v, f = blob(2 if quick else 3)
    out: dict[str, dict] = {}
    m = trimesh.Trimesh(v, f, process=False)
    uv = np.c_[np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi) + 0.5, v[:, 2]]
    m.visual = trimesh.visual.TextureVisuals(uv=uv)
    for ext in ("obj", "ply", "stl", "off"):
        path = os.path.join(folder, f"blob.{ext}")
        with open(path, "wb") as fh:
            data = m.export(file_type=ext, **({"include_normals": True, "include_texture": True} if ext == "obj" else {}))
            fh.write(data.encode() if isinstance(data, str) else data)
        out[f"file .{ext}"] = {"path": path}
    # OBJ of quads and hexagons: a hexagonal prism (two n-gon caps, six quad sides), 0.6 m.
    ang = np.arange(6) * np.pi / 3
    ring = np.c_[0.3 * np.cos(ang), 0.3 * np.sin(ang)]
    pv = np.concatenate([np.c_[ring, np.full(6, 0.5)], np.c_[ring, np.full(6, 1.1)]])
    lines = [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in pv]
    lines.append("f " + " ".join(str(i + 1) for i in range(5, -1, -1)))
    lines.append("f " + " ".join(str(i + 7) for i in range(6)))
    lines += [f"f {i + 1} {(i + 1) % 6 + 1} {(i + 1) % 6 + 7} {i + 7}" for i in range(6)]
    path = os.path.join(folder, "prism.obj")
    Path(path).write_text("\n".join(lines) + "\n")
    out["file .obj quads + n-gons"] = {"path": path}
    # PLY of triangle strips (the Stanford scans' format): each face a strip of its own.
    head = ["ply", "format binary_little_endian 1.0", f"element vertex {len(v)}", "property float x",
            "property float y", "property float z", "element tristrips 1", "property list int int vertex_indices",
            "end_header", ""]
    idx = np.c_[f, np.full(len(f), -1)].ravel().astype("<i4")
    path = os.path.join(folder, "strips.ply")
    Path(path).write_bytes("\n".join(head).encode() + v.astype("<f4").tobytes()
                          + np.array([len(idx)], "<i4").tobytes() + idx.tobytes())
    out["file .ply triangle strips"] = {"path": path}
    vd = np.concatenate([v, [(v[f[0, 0]] + v[f[0, 1]]) / 2]])
    fd = np.concatenate([f, [[f[0, 0], f[0, 1], len(v)]], [[f[1, 0], f[1, 0], f[1, 1]]]])
    path = os.path.join(folder, "degenerate.obj")
    js.write_mesh(path, vd, fd)
    out["file with zero-area faces"] = {"path": path}
    path = os.path.join(folder, "empty.obj")
    Path(path).write_text("")
    out["empty file"] = {"path": path, "expect": "error"}
    return out


# --------------------------------------------------------------------------------------
# Running a case
# --------------------------------------------------------------------------------------


def _build(make: Any, light: np.ndarray, dtype: Any = np.float64) -> tuple[Any, float, str | None]:
    import jaxshadow as js

    t = time.perf_counter()
    try:
        scene = js.Scene([js.PolygonLight(np.asarray(light, dtype), 1.0)], occluders=make())
    except (ValueError, TypeError) as err:
        return None, time.perf_counter() - t, f"{type(err).__name__}: {err}"
    return scene, time.perf_counter() - t, None


def run_case(c: dict, n_ref: int, p0: np.ndarray, n0: np.ndarray) -> dict:
    """One case: build, values, exactness, float32 against float64, soup cost."""
    light = c.get("light", LIGHT)
    p, n = c.get("p", p0), c.get("n", n0)
    dtype = c.get("dtype", np.float64)
    scene, build_s, error = _build(c["make"], light, dtype)
    row: dict[str, Any] = {"expect": c.get("expect", "ok"), "build_s": build_s, "error": error}
    if scene is None:
        row["pass"] = row["expect"] == "error"
        return row
    r = chk.exact(scene, np.asarray(light, dtype).astype(float), c["tris"], p.astype(dtype), n.astype(dtype), n_ref)
    e, unocc = r.pop("_e"), r.pop("_unocc")
    row.update(r)
    row["receivers"] = int(len(p))
    if dtype == np.float32:
        # float64 on the same rounded inputs: the soup/mesh rebuilt from float64 copies.
        import jaxshadow as js

        occ = c["make"]()
        occ64 = [js.Mesh(np.asarray(o.vertices, np.float64), o.loops) for o in occ] if isinstance(occ, list) \
            else np.asarray(occ, np.float64)
        s64 = js.Scene([js.PolygonLight(np.asarray(light, dtype).astype(float), 1.0)], occluders=occ64)
        e64 = np.asarray(js.irradiance(s64, p.astype(dtype).astype(float), n.astype(dtype).astype(float)))[:, 0]
        # The mesh property suite's float32 bound: 1e-5 U plus Lambert's sum's absolute rounding
        # (8 float32 epsilons of an edge term ~0.1, times pi for E of a unit radiance).
        floor_ = 1e-3 * np.abs(unocc).max()
        d = np.abs(e - e64)
        row["f32_vs_f64"] = float(np.max(d / np.maximum(np.abs(unocc), floor_)))
        row["f32_abs_max"] = float(d.max())
        bound = 1e-5 * np.maximum(np.abs(unocc), floor_) + 8 * np.finfo(np.float32).eps * 0.1 * np.pi
        row["f32_bound_ratio"] = float(np.max(d / bound))
    if "mesh_of" in c:
        import jaxshadow as js

        lv = np.asarray(light, float)
        row["soup_cost"] = chk.cpu_ratio(lambda: js.Scene([js.PolygonLight(lv, 1.0)], occluders=c["mesh_of"]()),
                                         lambda: js.Scene([js.PolygonLight(lv, 1.0)], occluders=c["make"]()), p, n)
    row["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    tol = TOL["float32" if dtype == np.float32 else "float64"]
    row["pass"] = (row["expect"] == "ok" and row["nonfinite"] == 0 and row["negative"] == 0
                   and row["above_unoccluded"] == 0 and row["umbra_not_zero"] == 0 and row["max_rel_err"] <= tol
                   and row.get("f32_bound_ratio", 0.0) <= 1.0 and row.get("soup_cost", {}).get("ratio", 1.0) <= 1.5)
    return row


def run_file(c: dict, n_ref: int, p: np.ndarray, n: np.ndarray) -> dict:
    import jaxshadow as js

    t = time.perf_counter()
    try:
        rm = js.read_mesh(c["path"])
        occ = rm.occluder()
    except (ValueError, TypeError) as err:
        ok = c.get("expect", "ok") == "error"
        return {"expect": c.get("expect", "ok"), "error": f"{type(err).__name__}: {err}", "pass": ok}
    row: dict[str, Any] = {"expect": c.get("expect", "ok"), "error": None, "read_s": time.perf_counter() - t,
                           "faces": int(len(rm.faces)), "closed": bool(occ.closed)}
    scene = js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=[occ])
    r = chk.exact(scene, LIGHT, np.asarray(rm.vertices)[rm.faces], p, n, n_ref)
    r.pop("_e"), r.pop("_unocc")
    row.update(r)
    row["pass"] = (row["expect"] == "ok" and row["nonfinite"] == 0 and row["negative"] == 0
                   and row["umbra_not_zero"] == 0 and row["max_rel_err"] <= TOL["float64"])
    return row


# --------------------------------------------------------------------------------------
# Light kinds and entry points
# --------------------------------------------------------------------------------------


def light_kinds(occluders: Any, tris: np.ndarray, p: np.ndarray, n: np.ndarray, n_ref: int) -> dict:
    """Point, directional and segment lights (isotropic and cos^2) over `occluders`."""
    import jaxshadow as js

    lights = {"point": js.PointLight([0.1, 0.05, 2.5], 1.0),
              "directional": js.DirectionalLight([0.25, 0.1, -1.0], 1.0),
              "segment": js.LinearLight([-0.4, 0.1, 2.5], [0.4, -0.1, 2.5], 1.0),
              "segment cos^2": js.LinearLight([-0.4, 0.1, 2.5], [0.4, -0.1, 2.5], 1.0, profile="cosine", exponent=2)}
    out = {}
    for name, lt in lights.items():
        t = time.perf_counter()
        try:
            scene = js.Scene([lt], occluders=occluders())
            r = chk.exact(scene, np.zeros((0, 3)), tris, p, n, n_ref // 2 if "segment" in name else n_ref,
                          kind=lt.kind if lt.kind != "linear" else "segment")
        except Exception as err:  # the sweep records what a user would meet
            out[name] = {"error": f"{type(err).__name__}: {err}", "pass": False}
            continue
        r.pop("_e"), r.pop("_unocc")
        r["seconds"] = time.perf_counter() - t
        r["pass"] = (r["nonfinite"] == 0 and r["negative"] == 0 and r["max_rel_err"] <= TOL["float64"]
                     and r.get("hard_disagree", 0) <= 1)
        out[name] = r
    return out


def entry_points(quick: bool, p: np.ndarray, n: np.ndarray) -> dict:
    """ShadowCache after a move, the illumination mesher, gradients, a Mitsuba rendering."""
    import jaxshadow as js

    v, f = blob(2 if quick else 3)
    s = soup(v, f)
    light = js.PolygonLight(LIGHT, 1.0)
    d = np.array([0.05, 0.02, 0.0])
    out: dict[str, Any] = {}

    def guarded(name: str, fn: Any) -> None:
        try:
            out[name] = fn()
        except Exception as err:  # the sweep records what a user would meet
            out[name] = {"error": f"{type(err).__name__}: {err}"}

    guarded("cache, mesh moved", lambda: chk.cache_update(lambda: js.Scene([light], occluders=[js.Mesh(v, f)]),
                                                          lambda: js.Scene([light], occluders=[js.Mesh(v + d, f)]), p, n))
    guarded("cache, soup moved", lambda: chk.cache_update(lambda: js.Scene([light], occluders=s),
                                                          lambda: js.Scene([light], occluders=s + d), p, n))
    g = flipped(f)
    guarded("cache, flipped mesh moved", lambda: chk.cache_update(
        lambda: js.Scene([light], occluders=[js.Mesh(v, g)]), lambda: js.Scene([light], occluders=[js.Mesh(v + d, g)]), p, n))
    guarded("illumination mesh", lambda: chk.mesher(js.Scene([light], occluders=[js.Mesh(v, f)])))
    vx = v - [0.0, 0.0, v[:, 2].min() + 0.15]
    if not quick:
        guarded("illumination mesh, crossing the floor", lambda: chk.mesher(js.Scene([light], occluders=[js.Mesh(vx, f)])))
    scene = js.Scene([light], occluders=[js.Mesh(v, f)])
    from jaxshadow._shadows import binding as vis

    cls = js.shadow_plan(scene, p, n).lights[0].classes
    pen = np.where(cls == vis.PENUMBRA)[0][:3]
    guarded("gradients, mesh", lambda: chk.gradients(
        lambda lv: js.Scene([js.PolygonLight(lv, 1.0)], occluders=[js.Mesh(v, f)]), LIGHT, p[pen], n[pen]))
    guarded("gradients, soup", lambda: chk.gradients(
        lambda lv: js.Scene([js.PolygonLight(lv, 1.0)], occluders=s), LIGHT, p[pen], n[pen]))
    guarded("render", lambda: render(s, 12 if quick else 24))
    return out


def render(tris: np.ndarray, resolution: int) -> dict:
    """The example Mitsuba scene (`jaxshadow.mitsuba.write_example_scene`) with its torus replaced
    by the triangle soup `tris` (written as an OBJ of unshared vertices), rendered."""
    try:
        import mitsuba  # noqa: F401
    except ImportError:
        return {"skipped": "mitsuba is not installed"}
    import jaxshadow as js
    from jaxshadow import mitsuba as jm
    from jaxshadow.cli.render import render as render_scene

    with tempfile.TemporaryDirectory() as d:
        xml = jm.write_example_scene(d, resolution=resolution, spp=4)
        t = tris * 0.5 + [0.1, 0.0, 0.3]
        js.write_mesh(os.path.join(d, "torus.obj"), t.reshape(-1, 3), np.arange(3 * len(t)).reshape(-1, 3))
        r = render_scene(xml)
    img = np.asarray(r.image)
    return {"pixels": int(img.shape[0] * img.shape[1]), "seconds": r.seconds, "finite": bool(np.all(np.isfinite(img))),
            "negative": int((img < 0).sum()), "mesh_pixels": int((r.surface == 1).sum())}


# --------------------------------------------------------------------------------------
# The suite's interface
# --------------------------------------------------------------------------------------


def run(quick: bool = False) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    os.environ.setdefault("JAXSHADOW_THREADS", "1")
    n_rec, n_ref = (150, 12) if quick else (400, 40)
    p, n = floor(n_rec)
    out: dict[str, Any] = {"receivers": n_rec, "reference_receivers": n_ref, "load": os.getloadavg()[0], "cases": {}}
    for name, c in cases(quick).items():
        out["cases"][name] = run_case(c, n_ref, p, n)
        print(f"{name}: {'pass' if out['cases'][name]['pass'] else 'FAIL'}", flush=True)
    with tempfile.TemporaryDirectory() as folder:
        for name, c in file_cases(quick, folder).items():
            out["cases"][name] = run_file(c, n_ref, p, n)
            print(f"{name}: {'pass' if out['cases'][name]['pass'] else 'FAIL'}", flush=True)
    import jaxshadow as js

    v, f = blob(2 if quick else 3)
    vu, fu, _, _ = cup(v, f)
    out["kinds"] = {"mesh": light_kinds(lambda: [js.Mesh(v, f)], v[f], p, n, n_ref),
                    "soup": light_kinds(lambda: soup(v, f), v[f], p, n, n_ref),
                    "open cup": light_kinds(lambda: [js.Mesh(vu, fu)], vu[fu], p, n, n_ref)}
    out["entry_points"] = entry_points(quick, p, n)
    out["load_end"] = os.getloadavg()[0]
    out["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    return out


def _fmt(x: Any, spec: str = ".1e") -> str:
    return "-" if x is None else format(x, spec)


def _case_rows(cases_: dict) -> list[str]:
    rows = ["| case | expected | result | build (s) | 2nd call (s) | receivers (penumbra / umbra) | max rel. err | "
            "float32 vs float64 (of its bound) | soup / mesh CPU (build CPU s) | peak RSS (GB) |",
            "|---|---|---|---:|---:|---|---:|---:|---:|---:|"]
    for name, r in cases_.items():
        if r.get("error"):
            res = ("refused: " if r["expect"] == "error" else "**FAILED**: ") + r["error"].replace("|", "/")[:90]
            rows.append(f"| {name} | {r['expect']} | {res} | - | - | - | - | - | - | - |")
            continue
        c = r.get("classes", {})
        sc = r.get("soup_cost")
        soup = "-" if sc is None else f"{sc['ratio']:.2f} ({sc['soup_build_cpu_s']:.2f} vs {sc['mesh_build_cpu_s']:.3f})"
        f32 = "-" if "f32_vs_f64" not in r else f"{r['f32_vs_f64']:.1e} ({r['f32_bound_ratio']:.2f})"
        rows.append(f"| {name} | {r['expect']} | {'pass' if r['pass'] else '**FAIL**'} | {_fmt(r.get('build_s', r.get('read_s')), '.3f')} | "
                    f"{_fmt(r.get('second_s'), '.3f')} | {r.get('receivers', '-')} ({c.get('penumbra', 0)} / {c.get('umbra', 0)}) | "
                    f"{_fmt(r.get('max_rel_err'))} | {f32} | {soup} | "
                    f"{_fmt(r.get('peak_rss_gb'), '.2f')} |")
    return rows


def markdown(r: dict) -> str:
    rows = _case_rows(r["cases"])
    rows.append(f"\n{r['receivers']} floor receivers per case (a fifth grazing), {r['reference_receivers']} of them "
                "(half penumbra, a fifth umbra) against the brute-force reference; max rel. err = max |E - ref| / "
                "max(U, 1e-3 max U), U unoccluded; float32 against float64 on the same rounded inputs (relative; in "
                "brackets the largest share of the property suite's bound, 1e-5 U plus Lambert's sum's absolute "
                f"rounding 8 eps 0.1 pi); soup build CPU against the Mesh's in brackets; load {r['load']:.1f} at start, "
                f"{r['load_end']:.1f} at end; peak RSS {r['peak_rss_gb']:.2f} GB.\n")
    rows += ["| occluder | light | result | 2nd call (s) | receivers checked | max rel. err | hard-shadow disagreements |",
             "|---|---|---|---:|---:|---:|---:|"]
    for occ, kinds in r["kinds"].items():
        for name, k in kinds.items():
            if "error" in k:
                rows.append(f"| {occ} | {name} | **FAILED**: {k['error'][:90]} | - | - | - | - |")
                continue
            rows.append(f"| {occ} | {name} | {'pass' if k['pass'] else '**FAIL**'} | {k['second_s']:.3f} | "
                        f"{k['ref_receivers']} | {k['max_rel_err']:.1e} | {k.get('hard_disagree', '-')} |")
    rows += ["", "| entry point | result |", "|---|---|"]
    for name, e in r["entry_points"].items():
        text = ", ".join(f"{k}: {_fmt(v, '.3g') if isinstance(v, float) else v}" for k, v in e.items())
        rows.append(f"| {name} | {text.replace('|', '/')[:300]} |")
    return "\n".join(rows)


def key_numbers(r: dict) -> list[tuple[str, str]]:
    ok = sum(1 for c in r["cases"].values() if c["pass"])
    f64 = max((c.get("max_rel_err") or 0.0) for c in r["cases"].values() if "f32_vs_f64" not in c)
    f32 = max((c.get("max_rel_err") or 0.0) for c in r["cases"].values() if "f32_vs_f64" in c)
    soup = max(c["soup_cost"]["ratio"] for c in r["cases"].values() if "soup_cost" in c)
    return [("Mesh robustness sweep (odd meshes, files, scales; every light kind)",
             f"{ok}/{len(r['cases'])} cases pass; max rel. err float64 {f64:.1e}, float32 {f32:.1e}; "
             f"soup / mesh CPU <= {soup:.2f}x")]


def run_files(paths: list[str], quick: bool = False, n_rec: int | None = None) -> dict:
    """The per-case checks and the light kinds on mesh files (`real_meshes.load_file`)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    os.environ.setdefault("JAXSHADOW_THREADS", "1")
    import jaxshadow as js
    from benchmarks.real_meshes import load_file

    n_rec = n_rec or (300 if quick else 1000)
    n_ref = 20 if quick else 60
    p, n = floor(n_rec)
    out: dict[str, Any] = {"receivers": n_rec, "reference_receivers": n_ref, "load": os.getloadavg()[0], "cases": {},
                           "kinds": {}}
    for path in paths:
        name = Path(path).name
        t = time.perf_counter()
        try:
            v, f = load_file(path)
        except ValueError as err:
            out["cases"][name] = {"expect": "ok", "error": f"ValueError: {err}", "pass": False}
            continue
        read = time.perf_counter() - t
        tris = v[f]
        c = {"make": lambda v=v, f=f: [js.Mesh(v, f)], "tris": tris}
        row = run_case(c, n_ref, p, n)
        row["read_s"], row["faces"] = read, int(len(f))
        out["cases"][name] = row
        s = soup(v, f)
        row2 = run_case({"make": lambda s=s: s, "tris": tris, "mesh_of": c["make"]}, n_ref // 2, p, n)
        out["cases"][name + ", soup"] = row2
        out["kinds"][name] = light_kinds(c["make"], tris, p, n, n_ref // 2)
        print(f"{name}: {row['pass']} {row2['pass']}", flush=True)
    out["load_end"] = os.getloadavg()[0]
    out["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    out["entry_points"] = {}
    return out


def main(argv: list[str] | None = None) -> int:
    """`python -m benchmarks.mesh_robustness --mesh FILE [--mesh FILE ...] [--quick]`."""
    import argparse
    import sys

    from benchmarks._suite import RESULTS, caption, meta, write_json, write_text

    ap = argparse.ArgumentParser(prog="python -m benchmarks.mesh_robustness", description=__doc__.split("\n")[0])
    ap.add_argument("--mesh", action="append", default=[], help="a mesh file (OBJ, PLY, ...); repeatable")
    ap.add_argument("--quick", action="store_true", help="fewer receivers")
    ap.add_argument("--receivers", type=int, default=None, help="floor receivers per file (default 1000, quick 300)")
    args = ap.parse_args(argv)
    if not args.mesh:
        ap.error("give --mesh FILE (the generated cases run with `python -m benchmarks mesh_robustness`)")
    info = meta(NAME, args.quick)
    info["command"] = "python -m benchmarks.mesh_robustness " + " ".join(sys.argv[1:] if argv is None else argv)
    r = run_files(args.mesh, args.quick, args.receivers)
    stem = "mesh_robustness_files" + ("_quick" if args.quick else "")
    record = {"benchmark": NAME + "_files", "meta": info, "results": r}
    write_json(RESULTS / f"{stem}.json", record)
    write_text(RESULTS / f"{stem}.md", caption(record) + "\n\n" + markdown(r) + "\n")
    print(markdown(r))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
