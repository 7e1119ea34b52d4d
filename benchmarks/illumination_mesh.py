"""Illumination meshes against uniform grids, and incremental updates against re-meshing.

Scenes: (1) two overlapping quad occluders over a 4 m floor under a 0.6 m quad light at z = 2
(lit, penumbra, umbra); (2) `box_scene`: `benchmarks.scenes.box_field(180)`, 180 boxes standing
on the floor (2 160 triangles). Where a box stands the floor is covered: those points are holes of
the mesh (`interpolate` gives NaN there) and are left out of every error, the grid's too. For each tolerance the adaptive mesh (`js.illumination_mesh`) is checked on a dense
offset grid of exact values (`js.irradiance`); a uniform triangulated grid is grown until its
interpolation error on the same dense grid is at most the adaptive mesh's, and vertex counts and
times are compared (exact values at the grid's vertices: its time is their evaluation). Then one
occluder moves and `IlluminationMesh.update` is timed against a fresh mesh in the same run.

    python -m benchmarks.illumination_mesh [--quick]

writes `benchmarks/results/illumination_mesh.json` and `illumination_mesh_<scene>.png`.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

RESULTS = os.path.join(os.path.dirname(__file__), "results")
LIGHT = np.array([[-0.3, -0.3, 2.0], [-0.3, 0.3, 2.0], [0.3, 0.3, 2.0], [0.3, -0.3, 2.0]])


def two_occluder_scene(shift=(0.0, 0.0)):
    import jaxshadow as js

    high = np.array([[-0.5, -0.3, 1.0], [0.3, -0.3, 1.0], [0.3, 0.4, 1.0], [-0.5, 0.4, 1.0]])
    low = np.array([[-0.1, -0.6, 0.6], [0.7, -0.6, 0.6], [0.7, 0.1, 0.6], [-0.1, 0.1, 0.6]]) + [shift[0], shift[1], 0]
    floor = np.array([[-2.0, -2.0, 0.0], [2.0, -2.0, 0.0], [2.0, 2.0, 0.0], [-2.0, 2.0, 0.0]])
    return js.Scene([js.PolygonLight(LIGHT, 10.0)], [high, low]), floor


def box_scene(moved=None):
    """`benchmarks.scenes.box_field(180)` (the shadows-at-scale mesh scene: 180 boxes standing on
    the floor, 2 160 triangles) under the quad light; `moved`: `(index, dx, dy)` moves one box."""
    import jaxshadow as js
    from benchmarks.scenes import FLOOR, box_field

    bf = box_field(180)
    meshes = [js.Mesh(v + (np.array([moved[1], moved[2], 0.0]) if moved is not None and i == moved[0] else 0.0), f)
              for i, (v, f) in enumerate(bf.boxes)]
    floor = np.array([[-FLOOR, -FLOOR, 0.0], [FLOOR, -FLOOR, 0.0], [FLOOR, FLOOR, 0.0], [-FLOOR, FLOOR, 0.0]])
    return js.Scene([js.PolygonLight(bf.light, 10.0)], meshes), floor


def dense_grid(floor, n):
    lo, hi = floor[:, :2].min(axis=0), floor[:, :2].max(axis=0)
    xs = np.linspace(lo[0], hi[0], n + 2)[1:-1] + 1e-4 * np.pi
    ys = np.linspace(lo[1], hi[1], n + 2)[1:-1] + 1e-4 * np.e
    gx, gy = np.meshgrid(xs, ys)
    return np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]


def exact(scene, pts):
    import jaxshadow as js

    return np.asarray(js.irradiance(scene, pts, np.tile([0.0, 0.0, 1.0], (pts.shape[0], 1))))


def uniform_error(scene, floor, n, dense, ref, scale):
    """Max interpolation error (relative to `scale`) of an n x n vertex grid (each cell split
    along its diagonal), and the time of its exact values."""
    lo, hi = floor[:, :2].min(axis=0), floor[:, :2].max(axis=0)
    xs, ys = np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    v = np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]
    t0 = time.perf_counter()
    e = exact(scene, v).reshape(n, n, 3)
    el = time.perf_counter() - t0
    u = (dense[:, 0] - lo[0]) / (xs[1] - xs[0])
    w = (dense[:, 1] - lo[1]) / (ys[1] - ys[0])
    i = np.clip(np.floor(u).astype(int), 0, n - 2)
    j = np.clip(np.floor(w).astype(int), 0, n - 2)
    fx, fy = (u - i)[:, None], (w - j)[:, None]
    v00, v10, v01, v11 = e[i, j], e[i + 1, j], e[i, j + 1], e[i + 1, j + 1]
    lin = np.where(fx >= fy, v00 + fx * (v10 - v00) + fy * (v11 - v10), v00 + fx * (v11 - v01) + fy * (v01 - v00))
    return float(np.max(np.abs(lin - ref)) / scale), el


def grid_to_match(scene, floor, target, dense, ref, scale, n_max):
    """Smallest n (doubling, then bisection) whose grid error <= target; or the largest tried."""
    n, hist = 16, []
    while True:
        err, el = uniform_error(scene, floor, n, dense, ref, scale)
        hist.append((n, err, el))
        if err <= target or n >= n_max:
            break
        n = min(n_max, 2 * n)
    if hist[-1][1] <= target and len(hist) > 1:
        lo, hi = hist[-2][0], hist[-1][0]
        best = hist[-1]
        while hi - lo > max(2, hi // 20):
            mid = (lo + hi) // 2
            err, el = uniform_error(scene, floor, mid, dense, ref, scale)
            if err <= target:
                hi, best = mid, (mid, err, el)
            else:
                lo = mid
        return {"n": best[0], "vertices": best[0] ** 2, "error": best[1], "seconds": best[2], "reached": True}
    n, err, el = hist[-1]
    return {"n": n, "vertices": n * n, "error": err, "seconds": el, "reached": err <= target}


def picture(mesh, scene, floor, path, zoom):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxshadow._files import atomic_write_path

    lo, hi = floor[:, :2].min(axis=0), floor[:, :2].max(axis=0)
    n = 300
    pts = dense_grid(floor, n)
    img = exact(scene, pts)[:, 0].reshape(n, n)
    fig, ax = plt.subplots(1, 2, figsize=(10, 5))
    for a, (x0, x1, y0, y1) in zip(ax, [(lo[0], hi[0], lo[1], hi[1]), zoom], strict=True):
        a.imshow(img, extent=(lo[0], hi[0], lo[1], hi[1]), origin="lower", cmap="inferno")
        a.triplot(mesh.vertices[:, 0], mesh.vertices[:, 1], mesh.triangles, color="c", lw=0.15)
        a.set_xlim(x0, x1)
        a.set_ylim(y0, y1)
        a.set_aspect("equal")
    ax[0].set_title(f"{mesh.vertices.shape[0]} vertices, tol {mesh.tol:g}")
    ax[1].set_title("zoom")
    fig.tight_layout()
    atomic_write_path(path, lambda tmp: fig.savefig(tmp, dpi=90))
    plt.close(fig)


def run_scene(name, scene, floor, tols, n_dense, n_max, moved_scene, zoom):
    import jaxshadow as js

    dense = dense_grid(floor, n_dense)
    t0 = time.perf_counter()
    ref = exact(scene, dense)
    dense_s = time.perf_counter() - t0
    rows, meshes = [], {}
    for tol in tols:
        t0 = time.perf_counter()
        m = js.illumination_mesh(scene, floor, tol)
        el = time.perf_counter() - t0
        lin = m.interpolate(dense)
        ok = np.all(np.isfinite(lin), axis=1)  # outside the holes under standing objects
        err = float(np.max(np.abs(lin[ok] - ref[ok])) / m.scale)
        g = grid_to_match(scene, floor, err, dense[ok], ref[ok], m.scale, n_max)
        rows.append({"tol": tol, "vertices": int(m.vertices.shape[0]), "triangles": int(m.triangles.shape[0]),
                     "seconds": el, "dense_max_error": err, "within_tol": err <= tol,
                     "dense_points_in_holes": int(np.sum(~ok)),
                     "max_error_estimate": m.max_error_estimate, "scale": m.scale,
                     "stats": {k: v for k, v in m.stats.items() if isinstance(v, (int, float, str))},
                     "uniform_grid": g, "vertex_ratio": g["vertices"] / m.vertices.shape[0],
                     "time_ratio": g["seconds"] / el})
        meshes[tol] = m
        print(name, rows[-1], flush=True)
    out = {"scene": name, "dense_points": int(dense.shape[0]), "dense_seconds": dense_s, "tolerances": rows}
    tol_pic = 1e-3 if 1e-3 in meshes else tols[0]
    picture(meshes[tol_pic], scene, floor, os.path.join(RESULTS, f"illumination_mesh_{name}.png"), zoom)
    # Incremental update: one occluder moves.
    m = meshes[tol_pic]
    t0 = time.perf_counter()
    upd = m.update(moved_scene)
    t_upd = time.perf_counter() - t0
    t0 = time.perf_counter()
    fresh = js.illumination_mesh(moved_scene, floor, m.tol, scale=m.scale)
    t_fresh = time.perf_counter() - t0
    same = (upd.vertices.shape == fresh.vertices.shape
            and np.array_equal(np.sort(upd.vertices.view("f8,f8,f8"), axis=0), np.sort(fresh.vertices.view("f8,f8,f8"), axis=0)))
    out["update"] = {"tol": m.tol, "update_seconds": t_upd, "fresh_seconds": t_fresh, "speedup": t_fresh / t_upd,
                     "tiles_meshed": upd.stats["tiles_meshed"], "tiles": upd.stats["tiles"],
                     "same_vertices_as_fresh": bool(same)}
    print(name, out["update"], flush=True)
    return out


def run(quick: bool) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    two, floor2 = two_occluder_scene()
    moved2, _ = two_occluder_scene(shift=(0.25, -0.1))
    res = {"scenes": []}
    tols = [1e-2, 1e-3] if quick else [1e-2, 1e-3, 1e-4]
    res["scenes"].append(run_scene("two_occluders", two, floor2, tols, 300 if quick else 1000, 1024 if quick else 4096,
                                   moved2, (-1.6, -0.4, -1.2, 0.0)))
    if not quick:
        boxes, floor_b = box_scene()
        moved_b, _ = box_scene(moved=(0, 0.05, 0.025))
        res["scenes"].append(run_scene("boxes", boxes, floor_b, [1e-2, 1e-3, 1e-4], 1000, 4096, moved_b,
                                       (0.5, 1.5, 0.5, 1.5)))
    return res


def main(argv=None) -> int:
    from jaxshadow._files import atomic_write

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the two-occluder scene at tol 1e-2 and 1e-3 only")
    args = ap.parse_args(argv)
    os.makedirs(RESULTS, exist_ok=True)
    res = run(args.quick)
    with atomic_write(os.path.join(RESULTS, "illumination_mesh.json")) as fh:
        json.dump(res, fh, indent=1, default=float)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
