"""Illumination meshes against uniform grids, and incremental updates against re-meshing.

Scenes: (1) two overlapping quad occluders over a 4 m floor under a 0.6 m quad light at z = 2
(lit, penumbra, umbra); (2) `box_scene`: `benchmarks.scenes.box_field(180)`, 180 boxes standing
on the floor (2 160 triangles), meshed with `max_vertices=BOX_MAX_VERTICES` (tol 1e-4 needs more
than the default) and `tile_size=BOX_TILE` (1/32 of the floor, not the default 1/16). Where a box stands the floor is covered: those points are holes
of the mesh (`interpolate` gives NaN there) and are left out of every error, the grid's too. For each tolerance the adaptive mesh
(`js.illumination_mesh`) is checked on a dense offset grid of exact values (`js.irradiance`);
uniform triangulated grids of n = 16 * 2^(k/2) vertices per side (exact values at their
vertices; their time is those values) are checked on the same dense grid, and the smallest that
reaches the mesh's own dense error is its match (or none does, up to the largest tried). Then
one occluder moves and `IlluminationMesh.update` is timed against a fresh mesh of the moved
scene in the same run (both after the engine's first calls; three alternating pairs, update first,
medians compared).

    python -m benchmarks illumination_mesh [--quick]
    python -m benchmarks.illumination_mesh --memory TOL [--updatable] [--part M] [--out FILE]

(the second: one mesh of the box scene in its own process, its time and peak resident memory;
the suite's meshes are built with `updatable=False` but the one the update starts from)

writes `benchmarks/results/illumination_mesh.json` (with the run's metadata, `benchmarks._suite`),
`illumination_mesh.md` and `illumination_mesh_<scene>.png` (the mesh over the illumination).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

RESULTS = os.path.join(os.path.dirname(__file__), "results")
LIGHT = np.array([[-0.3, -0.3, 2.0], [-0.3, 0.3, 2.0], [0.3, 0.3, 2.0], [0.3, -0.3, 2.0]])
MAX_VERTICES = 2_000_000  # js.illumination_mesh's default
BOX_MAX_VERTICES = 8_000_000  # the box scene's budget (tol 1e-4 on the whole floor needs ~5M vertices)
BOX_TILE = 0.25  # the box scene's tile size (m): 1/32 of the floor (the default 1/16 re-triangulates
# larger tiles every refinement round, and an update re-meshes more of the floor)
UPDATE_ROUNDS = 3  # update / fresh mesh pairs timed (alternating); the medians are compared


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


def grid_ladder(scene, floor, dense, ref, scale, n_max):
    """Errors of uniform n x n grids for n = 16 * 2^(k/2) up to `n_max` (half-octave steps),
    measured once per scene and shared by its tolerances."""
    out = []
    k = 0
    while True:
        n = int(round(16 * 2 ** (k / 2)))
        if n > n_max:
            break
        err, el = uniform_error(scene, floor, n, dense, ref, scale)
        out.append({"n": n, "vertices": n * n, "error": err, "seconds": el})
        k += 1
    return out


def grid_to_match(ladder, target):
    """The smallest grid of the ladder whose error is <= target. The true smallest grid lies
    between the previous rung (exclusive) and this one, so the vertex count credited to the
    grid is the previous rung's + 1 (a lower bound: the mesh's advantage is not overstated).
    Where no rung reaches `target`: `reached` False and the grid needs more than the largest."""
    for k, r in enumerate(ladder):
        if r["error"] <= target:
            low = ladder[k - 1]["vertices"] + 1 if k else 1
            return {**r, "reached": True, "vertices_lower_bound": low}
    r = ladder[-1]
    return {**r, "reached": False, "vertices_lower_bound": r["vertices"] + 1}


def picture(mesh, scene, floor, path, zoom):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from benchmarks._suite import save_figure

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
    save_figure(fig, path, dpi=90)
    plt.close(fig)


def _same(a, b) -> bool:
    """Whether two meshes have the same vertices (as sets) and triangles (by vertex position)."""
    def canon(m):
        order = np.lexsort(m.vertices.T[::-1])
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        tris = np.sort(rank[m.triangles], axis=1)
        return m.vertices[order], tris[np.lexsort(tris.T[::-1])]

    if a.vertices.shape != b.vertices.shape or a.triangles.shape != b.triangles.shape:
        return False
    (va, ta), (vb, tb) = canon(a), canon(b)
    return bool(np.array_equal(va, vb) and np.array_equal(ta, tb))


def run_scene(name, scene, floor, tols, n_dense, n_max, moved_scene, zoom, update_tol, outdir, skipped=None,
              picture_tol=1e-3, scale=None, max_vertices=MAX_VERTICES, tile_size=None):
    """Meshes of `floor` at each of `tols` against the dense grid and the uniform grids; the
    picture; the update after the move to `moved_scene` (None: no picture, no update). `scale`:
    the irradiance tol is relative to (default: the receiver's maximum)."""
    import jaxshadow as js

    dense = dense_grid(floor, n_dense)
    t0 = time.perf_counter()
    ref = exact(scene, dense)
    dense_s = time.perf_counter() - t0
    rows, meshes = [], {}
    ladder = None
    for tol in tols:
        t0 = time.perf_counter()
        # (only the update's mesh keeps what `update` needs)
        m = js.illumination_mesh(scene, floor, tol, scale=scale, max_vertices=max_vertices, tile_size=tile_size,
                                 updatable=moved_scene is not None and tol == update_tol)
        el = time.perf_counter() - t0
        lin = m.interpolate(dense)
        ok = np.all(np.isfinite(lin), axis=1)  # outside the holes under standing objects
        err = float(np.max(np.abs(lin[ok] - ref[ok])) / m.scale)
        if ladder is None:  # the grids' errors relative to the first mesh's scale (all equal)
            ladder = grid_ladder(scene, floor, dense[ok], ref[ok], m.scale, n_max)
        g = grid_to_match(ladder, err)
        rows.append({"tol": tol, "vertices": int(m.vertices.shape[0]), "triangles": int(m.triangles.shape[0]),
                     "seconds": el, "dense_max_error": err, "within_tol": err <= tol, "max_vertices": max_vertices,
                     "dense_points_in_holes": int(np.sum(~ok)),
                     "max_error_estimate": m.max_error_estimate, "scale": m.scale,
                     "stats": {k: v for k, v in m.stats.items() if isinstance(v, (int, float, str))},
                     "uniform_grid": g, "vertex_ratio_lower_bound": g["vertices_lower_bound"] / m.vertices.shape[0]})
        meshes[tol] = m
        print(name, {k: v for k, v in rows[-1].items() if k != "stats"}, flush=True)
    out = {"scene": name, "dense_points": int(dense.shape[0]), "dense_seconds": dense_s, "tolerances": rows,
           "uniform_grids": ladder, "not_run": skipped or [], "floor": floor.tolist()}
    if moved_scene is None:
        return out
    tol_pic = picture_tol if picture_tol in meshes else tols[0]
    picture(meshes[tol_pic], scene, floor, os.path.join(outdir, f"illumination_mesh_{name}.png"), zoom)
    # Incremental update: one occluder moves; a fresh mesh of the moved scene in the same run,
    # UPDATE_ROUNDS times alternating (each update from the same old mesh), medians compared.
    m = meshes[update_tol]
    t_upd, t_fresh, same = [], [], []
    for _ in range(UPDATE_ROUNDS):
        t0 = time.perf_counter()
        upd = m.update(moved_scene)
        t_upd.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        fresh = js.illumination_mesh(moved_scene, floor, m.tol, scale=m.scale, max_vertices=max_vertices,
                                     tile_size=tile_size)
        t_fresh.append(time.perf_counter() - t0)
        same.append(_same(upd, fresh))
    t_u, t_f = float(np.median(t_upd)), float(np.median(t_fresh))
    out["update"] = {"tol": m.tol, "update_seconds": t_u, "fresh_seconds": t_f, "speedup": t_f / t_u,
                     "rounds": UPDATE_ROUNDS, "update_seconds_all": t_upd, "fresh_seconds_all": t_fresh,
                     "tiles_meshed": upd.stats["tiles_meshed"], "tiles": upd.stats["tiles"],
                     "evaluations_update": upd.stats["evaluations"], "evaluations_fresh": fresh.stats["evaluations"],
                     "identical_to_fresh": all(same),
                     "values_identical_to_fresh": bool(_same(upd, fresh) and np.array_equal(
                         upd.irradiance[np.lexsort(upd.vertices.T[::-1])],
                         fresh.irradiance[np.lexsort(fresh.vertices.T[::-1])])),
                     "old_values_kept": upd.stats["values_kept"], "old_values_affected": upd.stats["values_affected"],
                     "affected_share": upd.stats["values_affected"]
                     / max(1, upd.stats["values_kept"] + upd.stats["values_affected"]),
                     "reused": upd.stats["reused"],
                     "max_value_difference": float(np.max(np.abs(np.sort(upd.irradiance, axis=0)
                                                                 - np.sort(fresh.irradiance, axis=0))))
                     if upd.irradiance.shape == fresh.irradiance.shape else None}
    print(name, out["update"], flush=True)
    return out


def run(quick: bool) -> dict:
    import jax

    from benchmarks._suite import QUICK_RESULTS, RESULTS

    jax.config.update("jax_enable_x64", True)
    outdir = str(QUICK_RESULTS if quick else RESULTS)
    os.makedirs(outdir, exist_ok=True)
    two, floor2 = two_occluder_scene()
    moved2, _ = two_occluder_scene(shift=(0.25, -0.1))
    res = {"scenes": []}
    tols = [1e-2, 1e-3] if quick else [1e-2, 1e-3, 1e-4]
    res["scenes"].append(run_scene("two_occluders", two, floor2, tols, 300 if quick else 1000, 362 if quick else 2048,
                                   moved2, (-1.6, -0.4, -1.2, 0.0), 1e-3, outdir))
    if not quick:
        boxes, floor_b = box_scene()
        moved_b, _ = box_scene(moved=(0, 0.05, 0.025))
        res["scenes"].append(run_scene(
            "boxes", boxes, floor_b, [1e-2, 1e-3, 1e-4], 700, 2048, moved_b, (0.5, 1.5, 0.5, 1.5), 1e-2, outdir,
            picture_tol=1e-2, max_vertices=BOX_MAX_VERTICES, tile_size=BOX_TILE))
    return res


def markdown(results: dict) -> str:
    """The tables of `benchmarks/README.md`."""
    lines = ["Adaptive illumination meshes (`js.illumination_mesh`) against uniform triangulated grids. "
             "`two_occluders`: two overlapping quads over a 4 m floor under a 0.6 m quad light; `boxes`: "
             "`box_field(180)` (180 boxes standing on an 8 m floor, 2 160 triangles; the floor under a box is a "
             "hole, left out of every error). Errors: max over a dense offset grid of exact values "
             "(`js.irradiance`), relative to the receiver's maximum. The box scene is meshed with "
             f"max_vertices={BOX_MAX_VERTICES:,} (tol 1e-4 needs more than the default {MAX_VERTICES:,}) and "
             f"tile_size={BOX_TILE} m (1/32 of the floor; the default is 1/16: smaller tiles make each refinement "
             "round's re-triangulation, and the region an update meshes again, smaller). "
             "A uniform grid is tried at n = 16 * 2^(k/2) "
             "per side; the grid column gives the smallest rung reaching the mesh's own dense error, credited "
             "with the previous rung's vertex count + 1 (a lower bound), or '>' the largest rung tried. "
             "A scene's first mesh time includes the engine's first calls (compilation). On `boxes` no uniform grid "
             "comes near: the irradiance jumps along every box's footprint (the floor there is a hole), and a grid "
             "triangle across that edge interpolates the jump.",
             "",
             "| scene | tol | vertices | time (s) | dense max error | estimate | uniform grid vertices "
             "(its error) | grid / mesh vertices |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for s in results["scenes"]:
        for r in s["tolerances"]:
            g = r["uniform_grid"]
            gtxt = (f"{g['vertices_lower_bound']:,}-{g['vertices']:,} ({g['error']:.1e})" if g["reached"]
                    else f"> {g['vertices']:,} ({g['error']:.1e})")
            # A grid that never reaches the mesh's error, with fewer vertices than the mesh, bounds nothing.
            ratio = (f">= {r['vertex_ratio_lower_bound']:.1f}x" if g["reached"] or r["vertex_ratio_lower_bound"] >= 1
                     else "no grid tried reaches it")
            lines.append(f"| {s['scene']} | {r['tol']:g} | {r['vertices']:,} | {r['seconds']:.1f} | "
                         f"{r['dense_max_error']:.2e} | {r['max_error_estimate']:.2e} | {gtxt} | {ratio} |")
        for nr in s.get("not_run", []):
            lines.append(f"| {s['scene']} | {nr['tol']:g} | not run{_why_not(results, s)} | | | | | |")
    lines += ["", "Moving one occluder: `IlluminationMesh.update` against a fresh mesh of the moved scene in the same "
              "run (median of three alternating pairs). The update re-meshes the tiles the occluder's shadow volume reaches (before or after) and takes "
              "over the old mesh's exact values that the move cannot change (`_cache.affected`); 'old values the "
              "move can change' is the share of the old mesh's exact values inside the moved occluder's shadow "
              "volumes, which any update equal to a fresh mesh must compute again.",
              "",
              "| scene | moving one occluder, tol | tiles re-meshed | old values the move can change | values taken over "
              "| update (s) | fresh mesh (s) | speedup | identical to the fresh mesh (values too) |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for s in results["scenes"]:
        if "update" not in s:
            continue
        u = s["update"]
        lines.append(f"| {s['scene']} | {u['tol']:g} | {u['tiles_meshed']} / {u['tiles']} | "
                     f"{100 * u['affected_share']:.0f} % | {u['reused']:,} | {u['update_seconds']:.1f} | "
                     f"{u['fresh_seconds']:.1f} | {u['speedup']:.1f}x | {u['identical_to_fresh']} "
                     f"({u['values_identical_to_fresh']}) |")
    return "\n".join(lines)


def _why_not(results: dict, scene: dict) -> str:
    """Why a tolerance was not run, from this run's numbers: the scene's own growth from 1e-2 to
    1e-3 (vertices, time) applied once more."""
    mine = {r["tol"]: r for r in scene["tolerances"]}
    if 1e-2 not in mine or 1e-3 not in mine:
        return ""
    gv = mine[1e-3]["vertices"] / mine[1e-2]["vertices"]
    gt = mine[1e-3]["seconds"] / mine[1e-2]["seconds"]
    need = mine[1e-3]["vertices"] * gv
    why = (f"more than the default max_vertices ({MAX_VERTICES:,}), where refinement stops short of tol"
           if need > MAX_VERTICES else "see the JSON")
    return (f": needs {why}: from 1e-2 to 1e-3 this mesh grew {gv:.1f}x in vertices and {gt:.1f}x in time; once "
            f"more gives ~{need:,.0f} vertices and ~{mine[1e-3]['seconds'] * gt / 60:.0f} min")


def key_numbers(results: dict) -> list[tuple[str, str]]:
    out = []
    for s in results["scenes"]:
        r = next((r for r in s["tolerances"] if r["tol"] == 1e-3), s["tolerances"][0])
        g = r["uniform_grid"]
        grid = f">= {g['vertices_lower_bound']:,}" if g["reached"] else f"> {g['vertices']:,} (the largest tried)"
        out.append((f"illumination mesh, {s['scene']}, tol {r['tol']:g}: vertices vs a uniform grid of the same max error",
                    f"{r['vertices']:,} vs {grid} ({r['vertex_ratio_lower_bound']:.1f}x fewer)"))
        if "update" not in s:
            continue
        u = s["update"]
        out.append((f"illumination mesh, {s['scene']}: moving one occluder, fresh mesh / update",
                    f"{u['speedup']:.1f}x (identical: {u['identical_to_fresh']})"))
    return out


def _rss() -> int:
    """This process's resident memory now (bytes; Linux `/proc`)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def memory(tol: float, updatable: bool, part: float | None, out: str | None) -> dict:
    """One mesh of the box scene's floor (or of its middle `part` x `part` m) at `tol` with the
    benchmark's settings, in this process: time, vertices, and the resident memory before the
    call (after the engine's first call), its peak during the call (sampled every 20 ms) and
    the process's peak (`ru_maxrss`), per output vertex too."""
    import resource
    import threading

    import jax

    import jaxshadow as js
    from benchmarks._suite import meta

    jax.config.update("jax_enable_x64", True)
    # how the record was made (the commit as the run starts; the load at its start and end)
    info = {**meta("illumination_mesh", False), "command": " ".join(["python -m benchmarks.illumination_mesh"]
                                                                     + sys.argv[1:])}
    scene, floor = box_scene()
    if part is not None:
        floor = np.array([[-part / 2, -part / 2, 0.0], [part / 2, -part / 2, 0.0], [part / 2, part / 2, 0.0],
                          [-part / 2, part / 2, 0.0]])
    exact(scene, floor)  # the engine's first call (compilation) before the baseline
    base = _rss()
    peak = [base]
    done = threading.Event()

    def sample():
        while not done.wait(0.02):
            peak[0] = max(peak[0], _rss())

    th = threading.Thread(target=sample, daemon=True)
    th.start()

    def progress(d: dict) -> None:
        print(f"round {d['round']}: {d['tiles_active']} tiles active, {d['tile_vertices']:,} tile vertices, "
              f"{d['seconds']:.0f} s, resident {_rss() / 1e9:.2f} GB (peak {peak[0] / 1e9:.2f})", file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    m = js.illumination_mesh(scene, floor, tol, max_vertices=BOX_MAX_VERTICES, tile_size=BOX_TILE, updatable=updatable,
                             progress=progress)
    el = time.perf_counter() - t0
    peak[0] = max(peak[0], _rss())
    done.set()
    th.join()
    v = int(m.vertices.shape[0])
    res = {"scene": "boxes" if part is None else f"boxes, middle {part:g} m", "tol": tol, "updatable": updatable,
           "vertices": v, "triangles": int(m.triangles.shape[0]), "seconds": el, "seconds_per_1k_vertices": 1e3 * el / v,
           "rss_before_bytes": base, "rss_peak_bytes": peak[0],
           "ru_maxrss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
           "peak_bytes_per_vertex": (peak[0] - base) / v, "max_error_estimate": m.max_error_estimate, "scale": m.scale,
           "stats": {k: val for k, val in m.stats.items() if isinstance(val, (int, float, str))},
           "meta": {**info, "load_average_end": list(os.getloadavg())}}
    print({k: val for k, val in res.items() if k not in ("stats", "meta")}, flush=True)
    if out:
        import json

        with open(out, "w") as f:
            json.dump(res, f, indent=1)
    return res


def main(argv=None) -> int:
    from benchmarks._suite import main as suite_main

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the two-occluder scene at tol 1e-2 and 1e-3 only")
    ap.add_argument("--memory", type=float, metavar="TOL",
                    help="instead: one mesh of the box scene at TOL, its time and peak resident memory (`memory`)")
    ap.add_argument("--updatable", action="store_true", help="with --memory: keep what update needs (the default "
                    "of js.illumination_mesh; without it updatable=False)")
    ap.add_argument("--part", type=float, help="with --memory: mesh the middle PART x PART m of the floor only")
    ap.add_argument("--out", help="with --memory: write the result as JSON here")
    args = ap.parse_args(argv)
    if args.memory is not None:
        memory(args.memory, args.updatable, args.part, args.out)
        return 0
    return suite_main(["illumination_mesh"] + (["--quick"] if args.quick else []))


if __name__ == "__main__":
    raise SystemExit(main())
