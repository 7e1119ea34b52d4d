"""Exact shadows from real meshes: a smooth non-convex shape tessellated from 320 to 327 680 triangles, an open mesh and a soup, against Radiance.

The occluder is one smooth, non-convex closed shape (an icosphere displaced by a smooth
function: the same shape at every tessellation, so the exact answer converges) scaled to 1 m,
0.3 m above a floor, under a 0.8 m quad light at z = 2.5; receivers uniform on [-2, 2]^2 (float64).
Per tessellation: the scene's build time (`js.Mesh` and `Scene`; beside it the engine's
precomputation for the occluder set, paid by the first shadow call), the engine's plan time per penumbra
receiver (`js.shadow_plan`, best of three), the receivers' classes, `js.irradiance`'s
throughput (second call), and Radiance (`rtrace -I -ab 0`, pyradiance) at its default and fine
settings on the same receivers in the same run, with its RMS error relative to our exact values.
The engine's two ways are measured on the same receivers: the silhouette path (contour edges
from a hierarchy of mesh edges, depth complexity) and the face path it falls back to
(`JAXSHADOW_SILHOUETTE=0`: every candidate face a region, interior edges left out); per penumbra
receiver with the engine's set-up per call (hierarchies, edge twins: a plan of one receiver)
subtracted and reported apart.
Beside them: the mesh given as a list of triangles (welded at `Scene` build) and an open version
(its lower part removed: no face can be culled). Exactness: the engine against the device kernel
(which clips every face) on penumbra and umbra receivers of the smallest tessellation.

Mesh files (scans, CAD parts downloaded by the user; never part of the suite's run):

    python -m benchmarks.real_meshes --mesh bunny.obj --mesh fandisk.obj [--quick] [--up y]

reads each with `js.read_mesh` (vertices at equal positions welded), turns its `--up` axis to +z,
scales it to 1 m (largest extent), centres it over the origin 0.3 m above the floor, and measures
it as the stand-ins above (same light, receivers, Radiance default, Embree sweep, exactness
against the polygon-boolean reference on 1000 receivers); rows are labelled by file name.
`--kinds` adds point, directional and segment lights over each file (`light_kinds`): jaxshadow,
Radiance default and fine (sources of equal radiometry from `benchmarks.peers`, with their
unoccluded agreement) and Embree on the same receivers. Radiance's start-up (process, octree)
dominates its figure at a few thousand receivers: compare throughputs with `--receivers 50000`
or more. Writes `benchmarks/results/real_meshes_files[_quick].json` and `.md`.
"""

from __future__ import annotations

import os
import resource
import time
from pathlib import Path
from typing import Any

import numpy as np

NAME = "real_meshes"
LIGHT = np.array([[-0.4, -0.4, 2.5], [-0.4, 0.4, 2.5], [0.4, 0.4, 2.5], [0.4, -0.4, 2.5]])


def blob(subdivisions: int, open_below: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The test shape of `tests/test_real_meshes.py`."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = np.asarray(m.vertices, float)
    d = 1 + 0.25 * np.sin(3 * v[:, 0]) * np.cos(2 * v[:, 1]) + 0.15 * np.sin(4 * v[:, 2] + 1)
    v = v * d[:, None]
    v = v / np.ptp(v, axis=0).max()
    v[:, 2] += 0.3 - v[:, 2].min()
    f = np.asarray(m.faces)
    if open_below is not None:
        f = f[v[f][:, :, 2].mean(axis=1) > open_below]
    return v, f


def scan_like(subdivisions: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """A scan's stand-in: the blob with 1 mm of vertex noise, open at the base (its lowest 15 %
    removed): 69 888 triangles at the default subdivision."""
    v, f = blob(subdivisions)
    v = v + np.random.default_rng(3).normal(0, 1e-3, v.shape)
    keep = v[f][:, :, 2].mean(axis=1) > v[:, 2].min() + 0.15 * np.ptp(v[:, 2])
    return v, f[keep]


def cad_like() -> tuple[np.ndarray, np.ndarray]:
    """A CAD part's stand-in: a thick ring (outer radius 0.5 m, inner 0.3 m, 0.2 m high) of 12 800
    triangles, sides of long thin triangles (170:1), sharp edges, tilted 30 degrees, 0.3 m above
    the floor."""
    import trimesh

    m = trimesh.creation.annulus(r_min=0.3, r_max=0.5, height=0.2, sections=1600)
    m.apply_transform(trimesh.transformations.rotation_matrix(np.radians(30), [1, 0, 0]))
    v = np.asarray(m.vertices, float)
    v[:, 2] += 0.3 - v[:, 2].min()
    return v, np.asarray(m.faces)


def exactness(scene: Any, tris: np.ndarray, p: np.ndarray, nrm: np.ndarray, n: int, seed: int = 11) -> dict:
    """`js.irradiance` against an independent exact reference (`reference_ff` of
    `tests/test_clip.py`: polygon booleans in shapely on the triangles that can block, no code
    shared with the engine) on `n` receivers: half penumbra, a fifth umbra, a tenth lit, and a fifth
    grazing (floor points under the mesh, normals 60-88 degrees from the vertical)."""
    import sys

    import jaxshadow as js
    from jaxshadow._shadows import binding as vis

    root = str(Path(__file__).resolve().parent.parent / "tests")
    if root not in sys.path:
        sys.path.insert(0, root)
    from test_clip import reference_ff
    from test_plan import culled

    rng = np.random.default_rng(seed)
    cls = js.shadow_plan(scene, p, nrm).lights[0].classes
    pick = []
    for c, k in ((vis.PENUMBRA, n // 2), (vis.UMBRA, n // 5), (vis.LIT, n // 10)):
        idx = np.where(cls == c)[0]
        pick.append(rng.choice(idx, min(k, len(idx)), replace=False))
    sel = np.concatenate(pick)
    m = n - len(sel)
    c = tris.reshape(-1, 3).mean(axis=0)
    gp = np.c_[c[:2] + rng.uniform(-0.8, 0.8, (m, 2)), np.zeros(m)]
    t, a = np.radians(rng.uniform(60, 88, m)), rng.uniform(0, 2 * np.pi, m)
    gn = np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=1)
    q, qn = np.concatenate([p[sel], gp]), np.concatenate([nrm[sel], gn])
    got = np.asarray(js.irradiance(scene, q, qn))[:, 0]
    ref = np.pi * np.array([reference_ff(x, y, LIGHT, culled(x, y, LIGHT, tris)) for x, y in zip(q, qn, strict=True)])
    cq = js.shadow_plan(scene, q, qn).lights[0].classes
    return {"receivers": int(len(q)), "classes": {name: int((cq == k).sum()) for k, name in enumerate(vis.CLASS_NAMES)},
            "grazing": int(m), "max_rel_err": float(np.abs(got - ref).max() / np.abs(ref).max())}


EMBREE_SAMPLES = (16, 64, 256, 1024)


def embree_sweep(tris: np.ndarray, p: np.ndarray, nrm: np.ndarray, exact: np.ndarray) -> dict:
    """Embree Monte Carlo (stratified shadow rays on the light) at several sample counts: points/s
    and RMS error relative to the exact values; the throughput at 1 % RMS error interpolated
    log-log between the two sample counts around it."""
    from benchmarks.peers import Embree

    em = Embree(tris)
    runs = []
    for spp in EMBREE_SAMPLES:
        x, sec = em.polygon_irradiance(p, nrm, LIGHT, 1.0, spp)
        runs.append({"samples": spp, "points_per_s": len(p) / sec,
                     "rms_rel_err": float(np.sqrt(np.mean((x - exact) ** 2)) / np.sqrt(np.mean(exact**2)))})
    at = None
    for a, b in zip(runs, runs[1:], strict=False):
        if a["rms_rel_err"] >= 0.01 >= b["rms_rel_err"]:
            w = np.log(a["rms_rel_err"] / 0.01) / np.log(a["rms_rel_err"] / b["rms_rel_err"])
            at = float(np.exp((1 - w) * np.log(a["points_per_s"]) + w * np.log(b["points_per_s"])))
    return {"build_s": em.build_seconds, "runs": runs, "points_per_s_at_1pct": at}


def _rms_rel(x: np.ndarray, ref: np.ndarray) -> float:
    return float(np.sqrt(np.mean((x - ref) ** 2)) / np.sqrt(np.mean(ref**2)))


def radiance_kind(light: Any, tris: np.ndarray, p: np.ndarray, nrm: np.ndarray, exact: np.ndarray,
                  n_check: int) -> dict:
    """Radiance (`rtrace -I -ab 0`) for one jaxshadow light over `tris (m, 3, 3)` on the receivers
    `p, nrm (N, 3)`, as a source of equal radiometry (`benchmarks.peers.radiance_source`), at its
    default setting and the fine one (`RADIANCE_FINE`; `RADIANCE_FINE_THIN` for the segment's thin
    cylinder): points/s (rtrace's wall time, start-up included) and RMS error relative to
    `exact (N,)` (jaxshadow's values; for point and directional lights also the receivers lit
    without occluders on which the lit/shadowed decision differs), and `unoccluded_rms_rel_err`:
    the same source with no occluder against `js.irradiance` without occluders on the first
    `n_check` receivers (the radiometric equivalence, up to Radiance's sampling error)."""
    import jaxshadow as js
    from benchmarks.peers import (
        RADIANCE_DEFAULT,
        RADIANCE_FINE,
        RADIANCE_FINE_THIN,
        Radiance,
        radiance_source,
    )

    src = radiance_source(light)
    settings = {"default": RADIANCE_DEFAULT, "fine": RADIANCE_FINE_THIN if light.kind == "segment" else RADIANCE_FINE}
    hard = light.kind in ("point", "directional")
    lit = np.asarray(js.irradiance(js.Scene([light]), p, nrm))[:, 0] > 0 if hard else None
    out: dict[str, Any] = {}
    with Radiance([src], tris) as r:
        for label, params in settings.items():
            er, sec = r.irradiance(p, nrm, params)
            row: dict[str, Any] = {"params": " ".join(params) or "(defaults)", "points_per_s": len(p) / sec,
                                   "rms_rel_err": _rms_rel(er[:, 0], exact)}
            if lit is not None:
                row["disagree"] = int(np.sum((er[lit, 0] > 0) != (exact[lit] > 0)))
            out[label] = row
    q, qn = p[:n_check], nrm[:n_check]
    ref = np.asarray(js.irradiance(js.Scene([light]), q, qn))[:, 0]
    with Radiance([src], np.zeros((0, 3, 3))) as r:
        out["unoccluded_receivers"] = int(len(q))
        out["unoccluded_rms_rel_err"] = {label: _rms_rel(r.irradiance(q, qn, params)[0][:, 0], ref)
                                         for label, params in settings.items()}
    return out


def light_kinds(v: np.ndarray, f: np.ndarray, p: np.ndarray, nrm: np.ndarray, n_exact: int,
                radiance: bool = True) -> dict:
    """Point, directional and segment lights over the mesh: jaxshadow's throughput (second call),
    its values against the engine-free device kernels on `n_exact` receivers (point and
    directional lights; the segment light's device kernel clips every face and is too large
    here), Radiance at its default and fine settings on the same receivers (`radiance_kind`;
    unless `radiance` is false), and Embree: hard-shadow rays for the point and directional
    lights (agreement of the lit/shadowed decision), Monte Carlo along the segment at 16 and 256
    samples (RMS error, points/s)."""
    import jaxshadow as js
    from benchmarks.peers import Embree

    em = Embree(v[f])
    kinds = {"point": js.PointLight([0.1, 0.2, 2.5], 1.0), "directional": js.DirectionalLight([0.2, 0.1, -1.0], 1.0),
             "segment": js.LinearLight([-0.4, 0.0, 2.5], [0.4, 0.0, 2.5], 1.0)}
    out = {}
    for name, light in kinds.items():
        scene = js.Scene([light], occluders=[js.Mesh(v, f)])
        np.asarray(js.irradiance(scene, p, nrm))
        t = time.perf_counter()
        e = np.asarray(js.irradiance(scene, p, nrm))[:, 0]
        row: dict[str, Any] = {"points_per_s": len(p) / (time.perf_counter() - t), "shadowed": float(np.mean(e == 0))}
        if name in ("point", "directional"):
            dev = np.asarray(js.irradiance(scene, p[:n_exact], nrm[:n_exact], shadows=js.ShadowOptions(engine="device")))[:, 0]
            row["exact_receivers"] = n_exact
            row["max_rel_diff_vs_device"] = float(np.abs(e[:n_exact] - dev).max() / np.abs(dev).max())
            towards = (np.asarray(light.position)[None, :] - p) if name == "point" else np.broadcast_to(-1e3 * np.asarray(light.direction), p.shape)
            unocc = np.asarray(js.irradiance(js.Scene([light]), p, nrm))[:, 0]
            vis, sec = em.hard_visibility(p, nrm, towards)
            lit = unocc > 0
            row["embree"] = {"points_per_s": len(p) / sec,
                             "disagree": int(np.sum((vis[lit]) != (e[lit] > 0)))}
        else:
            runs = []
            for spp in (16, 256):
                x, sec = em.segment_irradiance(p, nrm, np.asarray(light.start, float), np.asarray(light.end, float),
                                               float(np.asarray(light.power).reshape(-1)[0]), spp)
                runs.append({"samples": spp, "points_per_s": len(p) / sec, "rms_rel_err": _rms_rel(x, e)})
            row["embree"] = {"runs": runs}
        if radiance:
            rad = radiance_kind(light, v[f], p, nrm, e, n_exact)
            row["radiance_unoccluded_rel_err"] = rad.pop("unoccluded_rms_rel_err")
            row["radiance_unoccluded_receivers"] = rad.pop("unoccluded_receivers")
            row["radiance"] = rad
        out[name] = row
    return out


def _receivers(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-2, 2, (n, 2)), np.zeros(n)], np.tile([0.0, 0.0, 1.0], (n, 1))


def _case(occluders: Any, tris: np.ndarray, p: np.ndarray, nrm: np.ndarray, radiance: bool, fine: bool,
          embree: bool = False, face_path: bool = True) -> dict:
    import jaxshadow as js
    from jaxshadow._shadows import binding as vis

    builds = []
    for _ in range(2):  # the second build is the one reported: the first also pays imports and caches
        t = time.perf_counter()
        scene = js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=occluders() if callable(occluders) else occluders)
        builds.append(time.perf_counter() - t)
    build = builds[-1]
    # The engine's precomputation for this occluder set (hierarchies, edge twins, the silhouette
    # tree, interior sections; cached per set, so paid by the first call only): the engine time
    # of a first one-receiver plan less a second's. About 0 for a set already prepared in this
    # process (the same geometry measured before as another entry).
    # A box's plan first: the process's one-off costs (the extension's first call) are not the set's.
    js.shadow_plan(js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=[js.Mesh.box([3, 3, 0.3], [3.1, 3.1, 0.4])]), p[:1], nrm[:1])
    cold, warm = (js.shadow_plan(scene, p[:1], nrm[:1]).lights[0].seconds for _ in range(2))
    plans = [js.shadow_plan(scene, p, nrm).lights[0] for _ in range(3)]
    lp = min(plans, key=lambda x: x.seconds)
    cls = lp.classes
    pen = int((cls == vis.PENUMBRA).sum())
    # The engine's set-up per call (hierarchies, edge twins): a plan of one receiver.
    setup = min(js.shadow_plan(scene, p[:1], nrm[:1]).lights[0].seconds for _ in range(3))
    # The face path on the same receivers (the silhouette path switched off).
    face = e_face = None
    if face_path:
        os.environ["JAXSHADOW_SILHOUETTE"] = "0"
        try:
            face = min((js.shadow_plan(scene, p, nrm).lights[0] for _ in range(2)), key=lambda x: x.seconds)
            e_face = np.asarray(js.irradiance(scene, p, nrm))
        finally:
            del os.environ["JAXSHADOW_SILHOUETTE"]
    e = np.asarray(js.irradiance(scene, p, nrm))
    t = time.perf_counter()
    e = np.asarray(js.irradiance(scene, p, nrm))
    sec = time.perf_counter() - t
    out = {"triangles": int(len(tris)), "build_s": build, "plan_s": lp.seconds, "setup_s": setup,
           "plan_ms_per_penumbra": 1e3 * max(lp.seconds - setup, 0.0) / max(pen, 1),
           "face_path_ms_per_penumbra": None if face is None else 1e3 * max(face.seconds - setup, 0.0) / max(pen, 1),
           "classes": {name: int((cls == k).sum()) for k, name in enumerate(vis.CLASS_NAMES)},
           "candidates_penumbra_mean": float(lp.candidates[cls == vis.PENUMBRA].mean()) if pen else 0.0,
           "candidates_max": int(lp.candidates.max()), "points_per_s": len(p) / sec,
           "max_rel_diff_face_path": None if e_face is None else float(np.abs(e - e_face).max() / np.abs(e_face).max()),
           "build_first_s": builds[0], "engine_prepare_s": max(cold - warm, 0.0)}
    if embree:
        out["embree"] = embree_sweep(tris, p, nrm, e[:, 0])
    if radiance:
        from benchmarks.peers import RADIANCE_DEFAULT, RADIANCE_FINE, Radiance

        out["radiance"] = {}
        with Radiance([(LIGHT, np.ones(3))], tris) as r:
            for label, params in (("default", RADIANCE_DEFAULT), ("fine", RADIANCE_FINE))[: 2 if fine else 1]:
                er, s = r.irradiance(p, nrm, params)
                rms = float(np.sqrt(np.mean((er[:, 0] - e[:, 0]) ** 2)) / np.sqrt(np.mean(e[:, 0] ** 2)))
                out["radiance"][label] = {"points_per_s": len(p) / s, "rms_rel_err": rms}
    return out


def run(quick: bool = False) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxshadow as js
    from jaxshadow._shadows import binding as vis

    n = 2000 if quick else 20000
    p, nrm = _receivers(n)
    subs = (2, 3, 4) if quick else (2, 3, 4, 5, 6, 7)
    sizes = []
    for s in subs:
        v, f = blob(s)
        sizes.append(_case(lambda v=v, f=f: [js.Mesh(v, f)], v[f], p, nrm, radiance=True, fine=s <= 4) if s <= 6 else
                     _case(lambda v=v, f=f: [js.Mesh(v, f)], v[f], p, nrm, radiance=True, fine=False))
    others = {}
    light = js.PolygonLight(LIGHT, 1.0)
    for name, (vx, fx) in (("scan-like (noisy, open base)", scan_like()),
                           ("CAD-like (annulus, long thin triangles)", cad_like())):
        others[name] = _case(lambda vx=vx, fx=fx: [js.Mesh(vx, fx)], vx[fx], p, nrm, radiance=True, fine=not quick, embree=True)
        others[name]["exactness"] = exactness(js.Scene([light], occluders=[js.Mesh(vx, fx)]), vx[fx], p, nrm,
                                              100 if quick else 1000)
    vs, fs = scan_like()
    kinds = light_kinds(vs, fs, p, nrm, 50 if quick else 200)
    v, f = blob(4)
    soup = _case(lambda: [v[t] for t in f], v[f], p, nrm, radiance=False, fine=False)
    mesh4 = next(x for x in sizes if x["triangles"] == len(f))
    vo, fo = blob(4, open_below=0.6)
    opened = _case(lambda: [js.Mesh(vo, fo)], vo[fo], p, nrm, radiance=True, fine=False)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # before the device kernel's own memory
    # Exactness on the smallest tessellation: the engine against the device kernel.
    v2, f2 = blob(2)
    scene = js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=[js.Mesh(v2, f2)])
    cls = js.shadow_plan(scene, p, nrm).lights[0].classes
    sel = np.concatenate([np.where(cls == vis.PENUMBRA)[0][:60], np.where(cls == vis.UMBRA)[0][:20]])
    host = np.asarray(js.irradiance(scene, p[sel], nrm[sel]))[:, 0]
    dev = np.asarray(js.irradiance(scene, p[sel], nrm[sel], shadows=js.ShadowOptions(engine="device")))[:, 0]
    first, last = sizes[0], sizes[-1]
    return {"receivers": n, "sizes": sizes, "soup": soup, "soup_vs_mesh": mesh4["points_per_s"] / soup["points_per_s"],
            "open": opened, "others": others, "light_kinds": kinds,
            "growth": {"triangles": last["triangles"] / first["triangles"],
                       "plan_per_penumbra": last["plan_ms_per_penumbra"] / first["plan_ms_per_penumbra"],
                       "face_path": last["face_path_ms_per_penumbra"] / first["face_path_ms_per_penumbra"]},
            "exactness": {"receivers": int(len(sel)), "max_rel_diff_vs_device": float(np.abs(host - dev).max() / np.abs(dev).max())},
            "peak_rss_gb": peak}


def load_file(path: str | os.PathLike, up: str = "y") -> tuple[np.ndarray, np.ndarray]:
    """A mesh file as `(vertices (V, 3), faces (F, 3))`: read with `js.read_mesh`, vertices at
    equal positions welded, the `up` axis turned to +z, scaled to 1 m (largest extent), centred
    over the origin with its lowest point 0.3 m above the floor."""
    import jaxshadow as js
    from jaxshadow._core.welding import weld_vertices

    rm = js.read_mesh(path, crease=None)  # PLY triangle strips (the Stanford scans) included
    v, f = np.asarray(rm.vertices, float), np.asarray(rm.faces, np.int64)
    index, first = weld_vertices(v)
    v, f = v[first], index[f]
    # A right-handed turn taking the `up` axis to +z.
    turn = {"x": [1, 2, 0], "y": [2, 0, 1], "z": [0, 1, 2]}[up]
    v = v[:, turn]
    lo, hi = v.min(axis=0), v.max(axis=0)
    v = (v - np.r_[(lo[:2] + hi[:2]) / 2, lo[2]]) / (hi - lo).max()
    v[:, 2] += 0.3
    return v, f


def run_files(paths: list[str], quick: bool = False, up: str = "y", n_exact: int = 1000, receivers: int | None = None,
              face_path: bool = True, kinds: bool = False) -> dict:
    """The stand-ins' measurements on mesh files (`load_file`): one `_case` each on `receivers`
    floor receivers (default 2000 quick, 20000 otherwise; with Radiance default, and fine unless
    `quick`; the Embree sweep; the face path unless `face_path` is false) and `exactness` on
    `n_exact` receivers; with `kinds`, `light_kinds` on the same receivers (the segment light
    checked against the engine's face path, `JAXSHADOW_SEGMENT_PIECES=0`, on `n_exact` receivers, with
    both paths' capacities and throughputs)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import trimesh  # noqa: F401  (imported before the first `read_s`, which is the file's alone)

    import jaxshadow as js

    n = receivers or (2000 if quick else 20000)
    p, nrm = _receivers(n)
    light = js.PolygonLight(LIGHT, 1.0)
    out: dict[str, Any] = {}
    for path in paths:
        name = Path(path).name
        t = time.perf_counter()
        v, f = load_file(path, up)
        read = time.perf_counter() - t
        row = _case(lambda v=v, f=f: [js.Mesh(v, f)], v[f], p, nrm, radiance=True, fine=not quick, embree=True,
                    face_path=face_path)
        row["exactness"] = exactness(js.Scene([light], occluders=[js.Mesh(v, f)]), v[f], p, nrm, n_exact)
        row["vertices"] = int(len(v))
        row["read_s"] = read  # seconds of `load_file` (the file read, welded, placed)
        if kinds:
            row["kinds"] = light_kinds(v, f, p, nrm, min(n_exact, 200))
            seg = js.Scene([js.LinearLight([-0.4, 0.0, 2.5], [0.4, 0.0, 2.5], 1.0)], occluders=[js.Mesh(v, f)])
            q, qn = p[:n_exact], nrm[:n_exact]
            e = np.asarray(js.irradiance(seg, q, qn))[:, 0]
            lp = js.shadow_plan(seg, p, nrm).lights[0]
            os.environ["JAXSHADOW_SEGMENT_PIECES"] = "0"  # the face path: candidate faces clipped on the device
            try:
                e_face = np.asarray(js.irradiance(seg, q, qn))[:, 0]
                lp_face = js.shadow_plan(seg, p, nrm).lights[0]
                np.asarray(js.irradiance(seg, p, nrm))
                t = time.perf_counter()
                np.asarray(js.irradiance(seg, p, nrm))
                face_pps = len(p) / (time.perf_counter() - t)
            finally:
                del os.environ["JAXSHADOW_SEGMENT_PIECES"]
            row["kinds"]["segment"]["exact_receivers"] = int(len(q))
            row["kinds"]["segment"]["max_rel_diff_vs_face_path"] = float(np.abs(e - e_face).max() / np.abs(e_face).max())
            # Capacities (per receiver: the pieces path's visible pieces, the face path's candidate
            # faces) and the face path's throughput, measured after the pieces path's.
            row["kinds"]["segment"]["capacity"] = {"pieces": int(lp.counts.max()), "faces": int(lp_face.counts.max())}
            row["kinds"]["segment"]["face_path_points_per_s"] = face_pps
        out[name] = row
        print(f"{name}: {row['points_per_s']:.3g} points/s, exact to {row['exactness']['max_rel_err']:.1e}", flush=True)
    return {"receivers": n, "up": up, "others": out,
            "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}


def _build_cell(x: dict) -> str:
    """A build cell: the file read (files), `Scene` build and the engine's precomputation, where recorded."""
    parts = ([f"read {x['read_s']:.2f}"] if "read_s" in x else []) + [f"scene {x['build_s']:.2f}" if "engine_prepare_s" in x
                                                                        else f"{x['build_s']:.2f}"]
    if "engine_prepare_s" in x:
        parts.append(f"engine {x['engine_prepare_s']:.2f}")
    return " + ".join(parts) + " s"


def markdown_files(r: dict) -> str:
    """The tables of `run_files`."""
    rows = ["| mesh | triangles | build | plan per penumbra receiver | penumbra / umbra receivers | contour edges (penumbra mean / max) | jaxshadow points/s | Radiance default points/s (RMS err) | Radiance fine points/s (RMS err) | vs face path |",
            "|---|---:|---:|---:|---|---|---:|---:|---:|---:|"]
    for name, x in r["others"].items():
        rad = x.get("radiance", {})
        cell = {k: f"{rad[k]['points_per_s']:.3g} ({100 * rad[k]['rms_rel_err']:.2g} %)" if k in rad else "-" for k in ("default", "fine")}
        rows.append(f"| {name} | {x['triangles']} | {_build_cell(x)} | {x['plan_ms_per_penumbra']:.3g} ms | "
                    f"{x['classes']['penumbra']} / {x['classes']['umbra']} | {x['candidates_penumbra_mean']:.0f} / {x['candidates_max']} | "
                    f"{x['points_per_s']:.3g} | {cell['default']} | {cell['fine']} | "
                    + (f"{x['max_rel_diff_face_path']:.1e} |" if x.get("max_rel_diff_face_path") is not None else "- |"))
    rows.append("")
    for name, x in r["others"].items():
        ex = x["exactness"]
        rows.append(f"{name}: against exact polygon booleans (shapely) on {ex['receivers']} receivers "
                    f"({ex['classes']['penumbra']} penumbra, {ex['classes']['umbra']} umbra, {ex['classes']['lit']} lit, "
                    f"{ex['grazing']} of them grazing): max error {ex['max_rel_err']:.1e} of the largest value.")
    for name, x in r["others"].items():
        runs = ", ".join(f"{y['samples']} rays {y['points_per_s']:.3g}/s ({100 * y['rms_rel_err']:.2g} %)" for y in x["embree"]["runs"])
        at = x["embree"]["points_per_s_at_1pct"]
        rows.append(f"{name}: Embree Monte Carlo: {runs}; "
                    + (f"at 1 % RMS error {at:.3g} points/s (jaxshadow, exact: {x['points_per_s']:.3g})." if at else "1 % not bracketed."))
    kinds = [(name, x["kinds"]) for name, x in r["others"].items() if "kinds" in x]
    if kinds:
        rows += ["", "| mesh | light | jaxshadow points/s | shadowed receivers | exactness | Radiance default points/s (RMS err) "
                 "| Radiance fine points/s (RMS err) | Radiance unoccluded RMS err (default / fine) | Embree |",
                 "|---|---|---:|---:|---|---:|---:|---|---|"]
        for name, k in kinds:
            for kind, y in k.items():
                if "max_rel_diff_vs_device" in y:
                    ex = f"{y['max_rel_diff_vs_device']:.1e} vs device kernel ({y['exact_receivers']} receivers)"
                elif "max_rel_diff_vs_face_path" in y:
                    ex = f"{y['max_rel_diff_vs_face_path']:.1e} vs face path ({y['exact_receivers']} receivers)"
                else:
                    ex = "-"
                em = y["embree"]
                emc = (f"{em['points_per_s']:.3g} points/s, {em['disagree']} lit/shadowed disagreements" if "disagree" in em else
                       ", ".join(f"{z['samples']} samples {z['points_per_s']:.3g}/s ({100 * z['rms_rel_err']:.2g} %)" for z in em["runs"]))
                rad = " | ".join(_radiance_kind_cells(y))
                rows.append(f"| {name} | {kind} | {y['points_per_s']:.3g} | {100 * y['shadowed']:.1f} % | {ex} | {rad} | {emc} |")
    rows.append("")
    rows.append(f"{r['receivers']} floor receivers; each mesh's `{r['up']}` axis turned up, scaled to 1 m, 0.3 m above the "
                f"floor. Peak RSS {r['peak_rss_gb']:.2f} GB.")
    rows.append(RADIANCE_NOTE)
    if kinds:
        rows.append(RADIANCE_KINDS_NOTE)
    return "\n".join(rows)


RADIANCE_NOTE = ("Radiance's points/s are rtrace's wall time including its start-up (process, octree load), which "
                 "dominates at a few thousand receivers: compare throughputs on large receiver sets (>= 5e4).")
RADIANCE_KINDS_NOTE = ("Other light kinds in Radiance (benchmarks/peers.py): the point light a sphere of radius 1e-4 m, the "
                       "directional light a `source` of 0.01 degrees, the isotropic segment a cylinder of radius 1e-4 m whose "
                       "radiance a `brightfunc` scales by 1/sin(angle from the axis); fine = `-dj 1 -ds 0.01 -dt 0 -dc 1` "
                       "(the segment `-dj 0.8`: full jitter misses the thin tube). 'unoccluded': the same source without "
                       "occluders against jaxshadow's unoccluded values (the radiometric equivalence). For point and "
                       "directional lights 'n disagree': receivers whose lit/shadowed decision differs from jaxshadow's.")


def _radiance_kind_cells(y: dict) -> list[str]:
    """The Radiance cells of a light-kind row: default, fine (points/s, RMS error, lit/shadowed
    disagreements) and the unoccluded check; '-' where the record has no Radiance."""
    rad = y.get("radiance")
    if rad is None:
        return ["-", "-", "-"]
    cells = []
    for k in ("default", "fine"):
        z = rad[k]
        dis = f", {z['disagree']} disagree" if "disagree" in z else ""
        cells.append(f"{z['points_per_s']:.3g} ({100 * z['rms_rel_err']:.2g} %{dis})")
    u = y["radiance_unoccluded_rel_err"]
    cells.append(f"{u['default']:.1e} / {u['fine']:.1e} ({y['radiance_unoccluded_receivers']} receivers)")
    return cells


def main(argv: list[str] | None = None) -> int:
    """`python -m benchmarks.real_meshes --mesh FILE [--mesh FILE ...] [--quick] [--up y]`."""
    import argparse
    import sys

    from benchmarks._suite import RESULTS, caption, meta, write_json, write_text

    ap = argparse.ArgumentParser(prog="python -m benchmarks.real_meshes", description=__doc__.split("\n")[0])
    ap.add_argument("--mesh", action="append", required=True, help="a mesh file (OBJ, PLY, ...); repeatable")
    ap.add_argument("--quick", action="store_true", help="2000 receivers, no Radiance fine")
    ap.add_argument("--up", choices=("x", "y", "z"), default="y", help="the files' up axis (default y)")
    ap.add_argument("--exact", type=int, default=1000, help="receivers checked against the reference (default 1000)")
    ap.add_argument("--receivers", type=int, default=None, help="floor receivers (default 2000 with --quick, else 20000)")
    ap.add_argument("--no-face-path", action="store_true", help="skip the comparison with the face path (slow on scans)")
    ap.add_argument("--kinds", action="store_true", help="also point, directional and segment lights on each mesh")
    args = ap.parse_args(argv)
    info = meta(NAME, args.quick)
    info["command"] = "python -m benchmarks.real_meshes " + " ".join(sys.argv[1:] if argv is None else argv)
    t0 = time.perf_counter()
    results = run_files(args.mesh, args.quick, args.up, args.exact, args.receivers, not args.no_face_path, args.kinds)
    info["wall_s"] = round(time.perf_counter() - t0, 1)
    record = {"benchmark": NAME + "_files", "meta": info, "results": results}
    stem = RESULTS / ("real_meshes_files" + ("_quick" if args.quick else "") + ("_acceptance" if (args.receivers or 0) >= 100000 else ""))
    write_json(stem.with_suffix(".json"), record)
    write_text(stem.with_suffix(".md"), caption(record) + "\n\n" + markdown_files(results) + "\n")
    return 0


def markdown(r: dict) -> str:
    rows = ["| triangles | build | engine set-up per call | plan per penumbra receiver: silhouette / face path | penumbra / umbra receivers | contour edges (penumbra mean / max) | jaxshadow points/s | Radiance default points/s (RMS err) | Radiance fine points/s (RMS err) | vs face path |",
            "|---:|---:|---:|---|---|---|---:|---:|---:|---:|"]
    named = [dict(x, triangles=f"{x['triangles']} ({k})") for k, x in r.get("others", {}).items()]
    for x in r["sizes"] + [dict(r["open"], triangles=f"{r['open']['triangles']} (open)")] + named:
        rad = x.get("radiance", {})
        cell = {k: f"{rad[k]['points_per_s']:.3g} ({100 * rad[k]['rms_rel_err']:.2g} %)" if k in rad else "-" for k in ("default", "fine")}
        face = f"{x['face_path_ms_per_penumbra']:.3g}" if "face_path_ms_per_penumbra" in x else "-"
        rows.append(f"| {x['triangles']} | {_build_cell(x)} | {x['setup_s']:.3f} s | {x['plan_ms_per_penumbra']:.3g} / {face} ms | "
                    f"{x['classes']['penumbra']} / {x['classes']['umbra']} | {x['candidates_penumbra_mean']:.0f} / {x['candidates_max']} | "
                    f"{x['points_per_s']:.3g} | {cell['default']} | {cell['fine']} | "
                    + (f"{x['max_rel_diff_face_path']:.1e} |" if "max_rel_diff_face_path" in x else "- |"))
    g = r["growth"]
    face_growth = f" (the face path: {g['face_path']:.1f}x)" if "face_path" in g else ""
    rows.append("")
    for name, x in r.get("others", {}).items():
        if "exactness" not in x:
            continue
        ex = x["exactness"]
        rows.append(f"{name}: against exact polygon booleans (shapely) on {ex['receivers']} receivers "
                    f"({ex['classes']['penumbra']} penumbra, {ex['classes']['umbra']} umbra, {ex['classes']['lit']} lit, "
                    f"{ex['grazing']} of them grazing): max error {ex['max_rel_err']:.1e} of the largest value.")
    for name, x in r.get("others", {}).items():
        if "embree" not in x:
            continue
        runs = ", ".join(f"{y['samples']} rays {y['points_per_s']:.3g}/s ({100 * y['rms_rel_err']:.2g} %)" for y in x["embree"]["runs"])
        at = x["embree"]["points_per_s_at_1pct"]
        rows.append(f"{name}: Embree Monte Carlo (stratified shadow rays per receiver, points/s and RMS error): {runs}; "
                    + (f"at 1 % RMS error {at:.3g} points/s (jaxshadow, exact: {x['points_per_s']:.3g})." if at else "1 % not bracketed."))
    if "light_kinds" in r:
        rows.append("")
        # Radiance's columns only where the record has them (records made before they existed render as before).
        with_rad = any("radiance" in x for x in r["light_kinds"].values())
        rad_head, rad_rule = (" Radiance default points/s (RMS err) | Radiance fine points/s (RMS err) | Radiance unoccluded RMS err (default / fine) |",
                              "---:|---:|---|") if with_rad else ("", "")
        rows.append(f"| light on the scan-like mesh | jaxshadow points/s | shadowed receivers | vs device kernel |{rad_head} Embree |")
        rows.append(f"|---|---:|---:|---:|{rad_rule}---|")
        for name, x in r["light_kinds"].items():
            dev = f"{x['max_rel_diff_vs_device']:.1e} ({x['exact_receivers']} receivers)" if "max_rel_diff_vs_device" in x else "-"
            em = x["embree"]
            emc = (f"{em['points_per_s']:.3g} points/s, {em['disagree']} lit/shadowed disagreements" if "disagree" in em else
                   ", ".join(f"{y['samples']} samples {y['points_per_s']:.3g}/s ({100 * y['rms_rel_err']:.2g} %)" for y in em["runs"]))
            rad = "".join(f" {c} |" for c in _radiance_kind_cells(x)) if with_rad else ""
            rows.append(f"| {name} | {x['points_per_s']:.3g} | {100 * x['shadowed']:.1f} % | {dev} |{rad} {emc} |")
    rows.append("")
    if "face_path_note" in r:
        rows.append(r["face_path_note"])
    rows.append("'vs face path': the largest difference from the engine's face path (the silhouette path switched off) on "
                "all receivers, relative to the largest value; where it exceeds 1e-9 the independent reference sides "
                "with the silhouette path (the face path's error on fine meshes, issue 'Reliability, round 3').")
    rows.append(f"{r['receivers']} floor receivers. Over {g['triangles']:.0f}x the triangles the plan time per penumbra "
                f"receiver (silhouette path, set-up excluded) grows {g['plan_per_penumbra']:.1f}x{face_growth}. The {r['soup']['triangles']}-triangle mesh as a list of "
                f"triangles: {r['soup']['points_per_s']:.3g} points/s, {r['soup_vs_mesh']:.2f}x the `js.Mesh`'s time. "
                f"Engine vs device kernel on {r['exactness']['receivers']} penumbra and umbra receivers: "
                f"{r['exactness']['max_rel_diff_vs_device']:.1e} relative. Peak RSS of the runs above {r['peak_rss_gb']:.2f} GB.")
    return "\n".join(rows)


def plot(r: dict, path: Any) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from benchmarks._suite import save_figure

    t = [x["triangles"] for x in r["sizes"]]
    fig, ax = plt.subplots(figsize=(5.5, 4))
    ax.loglog(t, [x["plan_ms_per_penumbra"] for x in r["sizes"]], "o-", label="silhouette path, per penumbra receiver (ms)")
    if all("face_path_ms_per_penumbra" in x for x in r["sizes"]):
        ax.loglog(t, [x["face_path_ms_per_penumbra"] for x in r["sizes"]], "^-", label="face path, per penumbra receiver (ms)")
    ax.loglog(t, [1e3 / x["points_per_s"] * 1e3 for x in r["sizes"]], "s--", label="js.irradiance per 1000 receivers (ms)")
    ax.loglog(t, [x["plan_ms_per_penumbra"] for x in r["sizes"]][0] * np.asarray(t) / t[0], ":", color="grey", label="linear in triangles")
    ax.set_xlabel("triangles")
    ax.set_ylabel("ms")
    ax.legend(fontsize=8)
    ax.set_title("one non-convex mesh over a floor")
    save_figure(fig, path)


def key_numbers_files(r: dict) -> list[tuple[str, str]]:
    """Key numbers of a mesh-file record (`run_files`, e.g. the issue's acceptance run): per mesh the
    quad light against Radiance's default and Embree at 1 % RMS error, the exactness, and the other
    light kinds' throughput against Radiance's default."""
    rows = []
    for name, x in r["others"].items():
        rad = x["radiance"]["default"]
        at = x.get("embree", {}).get("points_per_s_at_1pct")
        rows.append((f"exact shadows of `{name}` ({x['triangles']} triangles), {r['receivers']} floor receivers, quad light: "
                     "points/s vs Radiance default (its RMS error), Embree at 1 % RMS error; max error vs polygon booleans",
                     f"{x['points_per_s']:.3g} vs {rad['points_per_s']:.3g} ({100 * rad['rms_rel_err']:.2g} %)"
                     + (f", Embree {at:.3g}" if at else "") + f"; {x['exactness']['max_rel_err']:.1e}"))
        if "kinds" in x:
            cells = [f"{kind} {y['points_per_s']:.3g} vs {y['radiance']['default']['points_per_s']:.3g}"
                     for kind, y in x["kinds"].items() if "radiance" in y]
            rows.append((f"`{name}`, other lights, {r['receivers']} floor receivers: points/s vs Radiance default", "; ".join(cells)))
    return rows


def key_numbers(r: dict) -> list[tuple[str, str]]:
    last = r["sizes"][-1]
    rad = last.get("radiance", {}).get("default")
    fig = f"{last['points_per_s']:.2g} points/s" + (f" vs Radiance default {rad['points_per_s']:.2g} ({100 * rad['rms_rel_err']:.2g} % RMS)" if rad else "")
    return [(f"exact shadows of a {last['triangles']}-triangle non-convex mesh, {r['receivers']} floor receivers",
             fig + f"; plan per penumbra receiver grows {r['growth']['plan_per_penumbra']:.1f}x over {r['growth']['triangles']:.0f}x triangles"),
            ("a triangle soup vs the same `js.Mesh`", f"{r['soup_vs_mesh']:.2f}x the mesh's time")] + [
        (f"exact shadows, {name} {x['triangles']}-triangle mesh, {r['receivers']} floor receivers: points/s vs Radiance default / fine (their RMS error)",
         f"{x['points_per_s']:.2g} vs {x['radiance']['default']['points_per_s']:.2g} ({100 * x['radiance']['default']['rms_rel_err']:.2g} %)"
         + (f" / {x['radiance']['fine']['points_per_s']:.2g} ({100 * x['radiance']['fine']['rms_rel_err']:.2g} %)" if "fine" in x["radiance"] else ""))
        for name, x in r.get("others", {}).items()]


if __name__ == "__main__":
    raise SystemExit(main())
