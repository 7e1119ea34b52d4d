"""Baking whole scenes (`js.bake`): vertices, time and peak memory per vertex, and vertices
against uniform grids of the same error on the planar surfaces.

Scenes: (1) `room`: a Cornell-box-like Mitsuba scene built here (`room_dict`, read by
`jaxshadow.mitsuba.from_mitsuba`): a 2 m room of six rectangles, a 0.5 m square light under the
ceiling, two floating cubes, a table top and a sphere (10 receiving surfaces, the sphere curved);
(2) `torus_floor`: the example scene's tilted torus (768 triangles, smooth vertex normals: a
curved patch) over a 4 m floor (`jaxshadow.mitsuba.write_example_scene`); (3) `box_floor` (full
run only, tol 1e-3): `benchmarks.illumination_mesh.box_scene` (180 boxes standing on an 8 m
floor), baked with that benchmark's tile size and vertex budget, no grid comparison (its patch
has a hole per box). Each bake runs in a
fresh process: its wall time (including compilation) and its peak resident memory
(`ru_maxrss`) are recorded, per output vertex too.

On every planar patch that is a parallelogram (every planar patch of these scenes), uniform
grids of n x n vertices (cells split along a diagonal, exact values at the vertices; n doubling
from 4 while its error is above the target, up to 1024) are compared with the bake: errors of
both are the largest difference between linear interpolation and exact irradiance over 8 random
points per triangle (fixed seed), relative to the bake's `scale`. Grids finer than 128 per side
are checked on 2 * 128^2 random triangles only: their error is then a lower bound, so the grid
vertex count, and with it the ratio, is one too. Sample points where the host engine's exact
value exceeds the unoccluded one (an engine error, counted in `samples_above_unoccluded`) are
left out. A grid matches when its error is at or below the bake's own error on that patch (its
`tol`, whichever is larger); the grid vertex count is the sum over the compared patches of the
smallest matching grid (a patch with no match up to 1024 counts 1024^2 and is counted apart: the
ratio is then a lower bound, shown with '>='). Planar patches that are not parallelograms are
left out of the comparison (`grid_skipped_patches`).

    python -m benchmarks bake [--quick]

writes `benchmarks/results/bake.json` (`--quick`: `results/quick/`, tol 1e-2 only); every case
also reports per surface its vertices and dense-grid error over tol (`surface_errors`).
`python -m benchmarks.bake --case room:1e-3 [--out F]` runs one case in this process;
`python -m benchmarks.bake --update box_floor:1e-3` runs one case of the full record again and
replaces it there (with its own commit and load, shown under the table).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import numpy as np

# `box_floor`: illumination_mesh's box scene and settings (tile 1/32 of the floor, its vertex budget)
BAKE_OPTIONS = {"box_floor": {"tile_size": 0.25, "max_vertices": 8_000_000}}
GRID_SCENES = ("room", "torus_floor")  # the box floor's patch is not a parallelogram with no holes
DESCRIPTION = "whole-scene bakes: vertices, time and memory per vertex, vertices vs uniform grids on planar surfaces"
SAMPLES = 8  # random points per triangle for the interpolation error
GRID_MAX = 1024
DEGENERATE = 1e-9  # a triangle of area <= this times its longest edge squared covers nothing (`surface_errors`)
GRID_ALL = 128  # grids up to this many vertices per side are checked on every triangle, finer ones on a sample


def room_dict() -> dict:
    """The room as a Mitsuba scene dictionary (z up, floor at z = 0, ceiling at z = 2)."""
    import mitsuba as mi

    from jaxshadow._io.mitsuba_io import import_mitsuba

    import_mitsuba()
    T = mi.ScalarTransform4f

    def rect(origin, target, up, scale=1.0, **extra):
        return {"type": "rectangle", "to_world": T().look_at(origin=origin, target=target, up=up) @ T().scale(scale),
                **extra}

    white = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.7, 0.7]}}
    d = {"type": "scene",
         "floor": rect([0, 0, 0], [0, 0, 1], [0, 1, 0], bsdf=white),
         "ceiling": rect([0, 0, 2], [0, 0, 1], [0, 1, 0], bsdf=white),
         "wall-x0": rect([-1, 0, 1], [0, 0, 1], [0, 0, 1], bsdf=white),
         "wall-x1": rect([1, 0, 1], [0, 0, 1], [0, 0, 1], bsdf=white),
         "wall-y0": rect([0, -1, 1], [0, 0, 1], [0, 0, 1], bsdf=white),
         "wall-y1": rect([0, 1, 1], [0, 0, 1], [0, 0, 1], bsdf=white),
         "table": rect([-0.3, 0.4, 0.5], [-0.3, 0.4, 1.5], [0, 1, 0], 0.3, bsdf=white),
         "cube-a": {"type": "cube", "to_world": T().translate([0.4, -0.3, 0.45]) @ T().rotate([0, 0, 1], 25)
                    @ T().scale(0.2), "bsdf": white},
         "cube-b": {"type": "cube", "to_world": T().translate([-0.45, -0.4, 0.3]) @ T().rotate([0, 0, 1], -15)
                    @ T().scale(0.15), "bsdf": white},
         "sphere": {"type": "sphere", "center": [0.3, 0.45, 0.9], "radius": 0.2, "bsdf": white},
         "light": rect([0, 0, 1.98], [0, 0, 0], [0, 1, 0], 0.25,
                       emitter={"type": "area", "radiance": {"type": "rgb", "value": [10.0, 10.0, 10.0]}})}
    return d


def scene_of(name: str):
    from jaxshadow.mitsuba import from_mitsuba, write_example_scene

    if name == "room":
        return from_mitsuba(room_dict())[:2]
    if name == "box_floor":
        from benchmarks.illumination_mesh import box_scene

        scene, floor = box_scene()
        return scene, [floor]
    import tempfile

    return from_mitsuba(write_example_scene(tempfile.mkdtemp()))[:2]


def _samples(vertices, values, tris, n, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.random((tris.shape[0], n, 2))
    flip = u.sum(axis=2) > 1
    u[flip] = 1 - u[flip]
    w = np.concatenate([1 - u.sum(axis=2, keepdims=True), u], axis=2)
    p = np.einsum("tnk,tkd->tnd", w, vertices[tris]).reshape(-1, 3)
    e = np.einsum("tnk,tkd->tnd", w, values[tris]).reshape(-1, 3)
    return p, e


def _error(scene, vertices, values, tris, normal, max_tris=None):
    """Largest |interpolated - exact| over the sample points, and how many points were left out
    because the host engine's value there exceeds the unoccluded one (an engine error, counted so
    that it shows). With `max_tris`, only that many triangles drawn at random are sampled: the
    result is then a lower bound of the error over all of them."""
    import jaxshadow as js

    if max_tris is not None and tris.shape[0] > max_tris:
        tris = tris[np.random.default_rng(1).choice(tris.shape[0], max_tris, replace=False)]
    p, e = _samples(vertices, values, tris, SAMPLES)
    nrm = np.ascontiguousarray(np.broadcast_to(normal, p.shape))
    exact = np.asarray(js.irradiance(scene, p, nrm))
    free = np.asarray(js.irradiance(js.Scene(scene.lights), p, nrm))
    bad = np.any(exact > free * (1 + 1e-9) + 1e-12 * free.max(), axis=1)
    return float(np.abs(e - exact)[~bad].max()), int(bad.sum())


def surface_errors(scene, b, samples=SAMPLES, max_tris=200_000, seed=2):
    """Per surface of the bake `b`: its vertices and the dense-grid error, the largest
    |interpolated - exact| over `samples` random points per triangle (all triangles, or
    `max_tris` drawn at random: then a lower bound), relative to `b.scale`, over `b.tol`.
    Exact values: `js.irradiance` at the points with the interpolated unit normal; in a curved
    patch's triangles (corners of different normals) with the faces' planes taken exactly
    (`exact_planes`, as the bake defines its values: `_refine_curved`). Points where the exact value exceeds the unoccluded one (an
    engine error) are left out and counted. Triangles of no area (area <= `DEGENERATE` times
    their longest edge squared: the slivers a constrained triangulation leaves along a contact
    edge, all three corners on it within 1e-10 m) are left out and counted
    (`samples_in_degenerate`): they cover nothing, and a point of one has many barycentric
    coordinates, so its interpolated value is not defined. `error_off_corners_over_tol` also
    leaves out the triangles with a corner within `CORNER_SIZE` of its patch's size of a
    corner where the irradiance takes a different limit along each direction of approach,
    which the mesher does not split below that size: a concave fold's corner or a vertex at the
    terminator on a curved patch (`stats["corners"]`) and, on a planar patch, a corner of an
    occluder face lying in its plane and facing away from it (the foot of an object standing on
    it: `illumination_mesh`'s contact corners; not the receiver's own corners, nor where two
    feet's edges cross: the irradiance has one limit there)."""
    from scipy.spatial import cKDTree

    import jaxshadow as js
    from jaxshadow._illumination.bake_curved import exact_planes
    from jaxshadow._illumination.refine import CORNER_SIZE

    exact_scene = js.Scene(scene.lights, occluders=None)
    if scene.occluders is not None:
        exact_scene = js.Scene(scene.lights, occluders=None)
        object.__setattr__(exact_scene, "occluders", jax_array(exact_planes(np.asarray(scene.occluders))))
        object.__setattr__(exact_scene, "occluder_topology", scene.occluder_topology)
    free_scene = js.Scene(scene.lights)
    rng = np.random.default_rng(seed)
    # each patch's size (CORNER_SIZE is relative to it)
    patch_size = {int(q): float(np.ptp(b.vertices[np.unique(b.triangles[b.patch == q])], axis=0).max())
                  for q in np.unique(b.patch)}
    out = []
    for si, name in enumerate(b.surface_names):
        rows_t = np.nonzero(b.surface == si)[0]
        if rows_t.size == 0:
            continue
        used = np.unique(b.triangles[rows_t])
        if max_tris is not None and rows_t.size > max_tris:
            rows_t = rows_t[rng.choice(rows_t.size, max_tris, replace=False)]
        tris = b.triangles[rows_t]
        u = rng.random((tris.shape[0], samples, 2))
        flip = u.sum(axis=2) > 1
        u[flip] = 1 - u[flip]
        w = np.concatenate([1 - u.sum(axis=2, keepdims=True), u], axis=2)
        p = np.einsum("tnk,tkd->tnd", w, b.vertices[tris]).reshape(-1, 3)
        e = np.einsum("tnk,tkd->tnd", w, b.irradiance[tris]).reshape(-1, 3)
        n = np.einsum("tnk,tkd->tnd", w, b.normals[tris]).reshape(-1, 3)
        n = np.ascontiguousarray(n / np.linalg.norm(n, axis=1, keepdims=True))
        # a triangle of a curved patch has corners of different normals; a planar patch's do not
        nt = b.normals[tris]
        curved_t = ~np.all(nt == nt[:, :1], axis=(1, 2))
        curved = np.repeat(curved_t, samples)
        exact = np.zeros_like(p)
        for sc, rows in ((exact_scene, curved), (scene, ~curved)):
            if rows.any():
                exact[rows] = np.asarray(js.irradiance(sc, p[rows], n[rows]))
        free = np.asarray(js.irradiance(free_scene, p, n))
        bad = np.any(exact > free * (1 + 1e-9) + 1e-12 * free.max(), axis=1)
        miss = np.abs(e - exact).max(axis=1)
        tv = b.vertices[tris]
        longest = np.max([np.linalg.norm(tv[:, k] - tv[:, (k + 1) % 3], axis=1) for k in range(3)], axis=0)
        area = 0.5 * np.linalg.norm(np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0]), axis=1)
        degenerate = np.repeat(area <= DEGENERATE * longest ** 2, samples)
        keep = ~bad & ~degenerate
        err = float(miss[keep].max(initial=0.0)) / b.scale
        # apart: the points next to a corner with a different limit along each direction (a
        # concave fold's corner, `stats["corners"]`; a contact corner of a planar patch): the
        # triangles with a corner within CORNER_SIZE of their patch's size of one
        folds = [np.array(c["points"], np.float64).reshape(-1, 3) for c in b.stats.get("corners", [])
                 if c["surface"] == name]
        if (~curved_t).any():
            folds.append(_contact_corners(scene, tv[~curved_t], nt[~curved_t, 0]))
        corners = np.concatenate(folds) if folds else np.zeros((0, 3))
        near = np.zeros(p.shape[0], bool)
        if corners.shape[0]:
            reach = CORNER_SIZE * (1 + 1e-9) * np.array([patch_size[int(q)] for q in b.patch[rows_t]])
            dist = cKDTree(corners).query(tv.reshape(-1, 3))[0].reshape(-1, 3)
            near = np.repeat(np.any(dist <= reach[:, None], axis=1), samples)
        off = float(miss[keep & ~near].max(initial=0.0)) / b.scale
        out.append({"surface": name, "curved": bool(curved.any()), "vertices": int(used.size),
                    "triangles_checked": int(tris.shape[0]), "error": err, "error_over_tol": err / b.tol,
                    "error_off_corners_over_tol": off / b.tol, "samples_near_corners": int(near.sum()),
                    "samples_in_degenerate": int(degenerate.sum()), "samples_above_unoccluded": int(bad.sum())})
    return out


def _contact_corners(scene, tv, normals):
    """`(k, 3)` the corners of the occluder faces lying in the plane of one of the planar
    triangles `tv (t, 3, 3)` (unit normals `(t, 3)`) within 1e-9 of the scene's size and facing
    away from it: where an object stands on the receiver (`illumination_mesh`'s contact corners:
    a box's bottom face). Faces lying there and facing the receiver's way are the receiver's own
    surface (the room's floor is an occluder too), whose corners are no contact corners."""
    if scene.occluders is None or tv.shape[0] == 0:
        return np.zeros((0, 3))
    occ = np.asarray(scene.occluders, np.float64)
    size = max(float(np.abs(occ).max()), float(np.abs(tv).max()))
    facing = np.sum(np.cross(occ, np.roll(occ, -1, axis=1)), axis=1)  # (m, 3) Newell normals (padding adds 0)
    planes = np.unique(np.round(np.c_[normals, np.einsum("td,td->t", normals, tv[:, 0])], 9), axis=0)
    out = []
    for pl in planes:
        flat = np.all(np.abs(occ @ pl[:3] - pl[3]) <= 1e-9 * size, axis=1) & (facing @ pl[:3] < 0)
        if flat.any():
            out.append(occ[flat].reshape(-1, 3))
    return np.unique(np.concatenate(out), axis=0) if out else np.zeros((0, 3))


def jax_array(x):
    import jax.numpy as jnp

    return jnp.asarray(x)


def _grid(scene, corners, normal, n):
    import jaxshadow as js

    c0, c1, c3 = corners[0], corners[1], corners[3]
    s = np.linspace(0, 1, n)
    uu, vv = np.meshgrid(s, s, indexing="ij")
    pts = c0 + uu.reshape(-1, 1) * (c1 - c0) + vv.reshape(-1, 1) * (c3 - c0)
    vals = np.asarray(js.irradiance(scene, pts, np.ascontiguousarray(np.broadcast_to(normal, pts.shape))))
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.c_[a, b, c], np.c_[a, c, d]])
    return pts, vals, tris


def bake_case(name: str, tol: float) -> dict:
    """One bake in this process: counts, time, peak memory, and the grid comparison."""
    import resource
    import time

    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxshadow as js
    from jaxshadow._illumination.bake_patches import _newell

    scene, receivers = scene_of(name)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    t0 = time.perf_counter()
    b = js.bake(scene, receivers, tol, **BAKE_OPTIONS.get(name, {}))
    seconds = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    nv = int(b.vertices.shape[0])
    out = {"scene": name, "tol": tol, "vertices": nv, "triangles": int(b.triangles.shape[0]),
           "surfaces": len(b.surface_names), "lights": int(b.irradiance_per_light.shape[1]), "seconds": seconds,
           "seconds_per_vertex": seconds / nv, "peak_rss_bytes": rss, "rss_before_bytes": rss0,
           "peak_rss_per_vertex_bytes": rss / nv, "scale": b.scale, **{k: v for k, v in b.stats.items()
                                                                         if k != "seconds"}}
    # planar patches: the bake's error and the uniform grid of the same error
    planar_v, compared_v, grid_v, unmatched, skipped, errs, above_free = 0, 0, 0, 0, 0, [], 0
    for p in (np.unique(b.patch) if name in GRID_SCENES else []):
        tris = b.triangles[b.patch == p]
        used = np.unique(tris)
        nrm = b.normals[used[0]]
        if not np.allclose(b.normals[used], nrm, atol=1e-12):
            continue  # a curved patch
        planar_v += used.size
        err, nbad = _error(scene, b.vertices, b.irradiance, tris, nrm)
        above_free += nbad
        errs.append(err / b.scale)
        target = max(err, tol * b.scale)
        # the patch's corners: its convex hull in its plane, a parallelogram here
        from scipy.spatial import ConvexHull

        pts = b.vertices[used]
        e1 = pts[np.argmax(np.linalg.norm(pts - pts[0], axis=1))] - pts[0]
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(nrm, e1)
        uv = np.c_[(pts - pts[0]) @ e1, (pts - pts[0]) @ e2]
        hull = ConvexHull(uv).vertices
        poly = pts[hull]
        poly = poly[np.r_[True, np.linalg.norm(np.diff(poly, axis=0), axis=1) > 1e-9]]
        turn = [np.linalg.norm(np.cross(poly[i] - poly[i - 1], poly[(i + 1) % len(poly)] - poly[i]))
                for i in range(len(poly))]
        corners = poly[np.array(turn) > 1e-9 * np.ptp(pts, axis=0).max() ** 2]
        if corners.shape[0] != 4:
            skipped += 1  # not a parallelogram: no uniform grid to compare with
            continue
        compared_v += used.size
        if _newell(corners) @ nrm < 0:
            corners = corners[::-1]
        n, found = 4, False
        while n <= GRID_MAX:
            gp, gv, gt = _grid(scene, corners, nrm, n)
            sample = None if n <= GRID_ALL else 2 * GRID_ALL * GRID_ALL
            if _error(scene, gp, gv, gt, nrm, sample)[0] <= target:
                found = True
                break
            n *= 2
        grid_v += min(n, GRID_MAX) ** 2
        unmatched += not found
    out["surface_errors"] = surface_errors(scene, b)
    out.update({"planar_vertices": planar_v, "grid_vertices": grid_v, "grid_unmatched_patches": unmatched,
                "planar_error_max": max(errs) if errs else None, "samples_above_unoccluded": above_free,
                "grid_ratio": grid_v / compared_v if compared_v else None, "grid_max": GRID_MAX,
                "grid_compared_vertices": compared_v, "grid_skipped_patches": skipped})
    return out


def _run_case(name: str, tol: float) -> dict:
    """One case in a fresh process (its peak memory is its own): its result, or its error."""
    code = ("import json, sys; from benchmarks.bake import bake_case; "
            f"print('RESULT ' + json.dumps(bake_case({name!r}, {tol!r})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    line = [x for x in out.stdout.splitlines() if x.startswith("RESULT ")]
    if out.returncode != 0 or not line:
        return {"scene": name, "tol": tol, "error": out.stderr[-2000:]}
    r = json.loads(line[0][7:])
    print(f"{name} tol {tol:g}: {r['vertices']} vertices, {r['seconds']:.1f} s, "
          f"{r['peak_rss_per_vertex_bytes'] / 1024:.1f} KiB/vertex peak", file=sys.stderr, flush=True)
    return r


def run(quick: bool) -> dict:
    cases = [("room", 1e-2), ("torus_floor", 1e-2)] if quick else [
        ("room", 1e-2), ("torus_floor", 1e-2), ("room", 1e-3), ("torus_floor", 1e-3), ("box_floor", 1e-3)]
    return {"cases": [_run_case(name, tol) for name, tol in cases]}


def update_case(name: str, tol: float) -> dict:
    """Run one case of the full record again (a fresh process) and put it in place of that case
    in `results/bake.json`, with its own `measured` metadata (command, commit, date, load: the
    record's header describes the other cases); then regenerate the tables."""
    from benchmarks._suite import RESULTS, meta, read, regenerate, write_json

    record = read("bake")
    if record is None:
        raise SystemExit("python -m benchmarks.bake --update: no full record yet (run `python -m benchmarks bake`).")
    info = meta("bake", False)
    info["command"] = f"python -m benchmarks.bake --update {name}:{tol:g}"
    r = _run_case(name, tol)
    info["load_average_end"] = list(os.getloadavg())
    r["measured"] = info
    cases = record["results"]["cases"]
    at = [i for i, c in enumerate(cases) if c["scene"] == name and float(c["tol"]) == tol]
    if at:
        cases[at[0]] = r
    else:
        cases.append(r)
    write_json(RESULTS / "bake.json", record)
    regenerate()
    return r


def markdown(results: dict) -> str:
    rows = ["| scene | tol | surfaces | vertices | s | ms / vertex | peak RSS (MB) | KiB / vertex | planar vertices "
            "| uniform grid of the same error | ratio |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results["cases"]:
        if "error" in r:
            rows.append(f"| {r['scene']} | {r['tol']:g} | failed | | | | | | | | |")
            continue
        grid = f"{r['grid_vertices']:,}" + (f" ({r['grid_unmatched_patches']} patches > {r.get('grid_max', 128)}^2)"
                                             if r["grid_unmatched_patches"] else "")
        ratio = f"{r['grid_ratio']:.1f}x" if r["grid_ratio"] is not None else "–"
        if r["grid_unmatched_patches"] and r["grid_ratio"] is not None:
            ratio = ">= " + ratio
        if r["grid_ratio"] is None:
            grid = "–"
        rows.append(f"| {r['scene']} | {r['tol']:g} | {r['surfaces']} | {r['vertices']:,} | {r['seconds']:.1f} | "
                    f"{1e3 * r['seconds_per_vertex']:.2f} | {r['peak_rss_bytes'] / 1e6:.0f} | "
                    f"{r['peak_rss_per_vertex_bytes'] / 1024:.1f} | {r['planar_vertices']:,} | {grid} | {ratio} |")
    for r in results["cases"]:
        if "measured" in r:
            m = r["measured"]
            rows.append(f"\n{r['scene']} at tol {r['tol']:g} measured apart: `{m['command']}` (commit {m['commit']}, "
                        f"{m['date']}, load average {', '.join(f'{x:.1f}' for x in m['load_average'])} at its start, "
                        f"{', '.join(f'{x:.1f}' for x in m.get('load_average_end', []))} at its end).")
    if not any(r.get("surface_errors") for r in results["cases"]):
        return "\n".join(rows) + "\n"
    rows += ["", "Per surface: vertices and the dense-grid error (`surface_errors`: 8 random points per triangle "
             "against exact irradiance, triangles of no area left out) over tol; also without the triangles at "
             "a corner where the irradiance has a different limit along each direction of approach, which the "
             "mesher leaves at `CORNER_SIZE` (1e-4) of the patch's size: on a curved surface a concave fold's "
             "corner or a vertex at the terminator (`stats['corners']`), the corner of an object's foot on a planar "
             "one.", "",
             "| scene | tol | surface | vertices | error / tol | off those corners / tol |", "|---|---|---|---|---|---|"]
    for r in results["cases"]:
        for srf in r.get("surface_errors", []):
            rows.append(f"| {r['scene']} | {r['tol']:g} | {srf['surface']} | {srf['vertices']:,} | "
                        f"{srf['error_over_tol']:.2f} | {srf['error_off_corners_over_tol']:.2f} |")
    return "\n".join(rows) + "\n"


def main(argv=None) -> int:
    from benchmarks._suite import main as suite_main

    ap = argparse.ArgumentParser(prog="python -m benchmarks.bake")
    ap.add_argument("--quick", action="store_true", help="tol 1e-2 only")
    ap.add_argument("--case", metavar="SCENE:TOL", help="one bake in this process (e.g. room:1e-3), printed as JSON")
    ap.add_argument("--out", help="with --case: also write the JSON here")
    ap.add_argument("--update", metavar="SCENE:TOL", help="run that case of the full record again (a fresh "
                    "process) and replace it in results/bake.json, with its own commit and load, then the tables")
    args = ap.parse_args(argv)
    if args.update:
        name, tol = args.update.split(":")
        update_case(name, float(tol))
        return 0
    if args.case:
        name, tol = args.case.split(":")
        r = bake_case(name, float(tol))
        text = json.dumps(r, indent=1)
        print(text)
        if args.out:
            with open(args.out, "w") as fh:
                fh.write(text + "\n")
        return 0
    return suite_main(["bake"] + (["--quick"] if args.quick else []))


if __name__ == "__main__":
    sys.exit(main())
