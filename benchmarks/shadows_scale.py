"""Exact shadows at mesh scale: throughput, memory, exactness and Radiance in the same run.

    .venv/bin/python -m benchmarks shadows_scale            # full (~15 min on 2 cores)
    .venv/bin/python -m benchmarks shadows_scale --quick    # smoke run (~2 min)

Scenes (`benchmarks/scenes.py`): a floor `[-4, 4]^2` under a 0.6 m quad light at z = 2, with
(a) `mesh`: 180 random closed boxes (2 160 triangles) as `js.Mesh` occluders, (b) `quad`: one
square occluder, (c) `lit90`: one box, so that about 90 % of the floor is lit, against the same
floor without occluders. Receivers: uniform floor points, 5 % with grazing normals.

Every jaxshadow case runs in a fresh worker process (its peak resident memory is the case's
own), float64: the first call (with compilation) is reported apart; the steady state is the
best of its calls. Radiance (`rtrace -I -ab 0 -n 2`, pyradiance) runs in the same worker on the
same receivers, at its defaults in `reps` rounds alternating with ours (each side the best of its
calls: a drift of the shared machine's load then moves both) and with fine source subdivision
(one run); its error is the RMS of its difference to jaxshadow's exact values relative to their RMS. jaxshadow's own error is measured
against the exact reference of the tests (the visible region clipped and subtracted in rational
arithmetic, its Lambert contour sum at 60 digits, correctly rounded; `tests/exact_reference.py`),
on receivers drawn from every class (lit, umbra, penumbra, grazing). (The float64 shapely
reference of `tests/test_clip.py` snap-rounds its overlay; its own error, up to ~1e-11 relative
on these scenes, would hide the engine's.)

Also `inverse.fit_light` with the mesh scene (48 targets): a solve's time and the gradient of
the loss against central differences. Writes `benchmarks/results/shadows_scale.json`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results"
NAME = "shadows_scale"
DESCRIPTION = "exact shadows at mesh scale (2 160 triangles, 2e5-1e6 receivers) against Radiance"


def _scene(kind: str, seed: int = 0):
    import jaxshadow as js
    from benchmarks.scenes import box, box_field

    if kind == "mesh":
        bf = box_field(180, seed=seed)
        occ = [js.Mesh(v, f) for v, f in bf.boxes]
        tris = bf.triangles
    elif kind == "quad":
        bf = box_field(0)
        sq = np.array([[-0.4, -0.4, 1.0], [0.4, -0.4, 1.0], [0.4, 0.4, 1.0], [-0.4, 0.4, 1.0]])
        occ, tris = [sq], sq[None]
    elif kind == "lit90":
        bf = box_field(0)
        v, f = box((-0.15, -0.15, 0.6), (0.15, 0.15, 0.9))
        occ, tris = [js.Mesh(v, f)], v[f]
    elif kind == "empty":
        bf = box_field(0)
        occ, tris = None, np.zeros((0, 3, 3))
    else:
        raise ValueError(kind)
    light = js.PolygonLight(bf.light, radiance=1.0)
    return js.Scene([light], occluders=occ), bf.light, tris


def _worker(kind: str, n: int, reps: int) -> dict:
    """One jaxshadow case in this (fresh) process: times, classes, peak memory, and Radiance on
    the same receivers, timed in alternating rounds with ours (`_rounds`)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxshadow as js
    from benchmarks.scenes import floor_receivers

    t = time.perf_counter()
    scene, light, tris = _scene(kind)
    build = time.perf_counter() - t
    p, nrm = floor_receivers(n, grazing=0.05)
    t = time.perf_counter()
    e = np.asarray(js.irradiance(scene, p, nrm))
    first = time.perf_counter() - t
    t = time.perf_counter()
    e = np.asarray(js.irradiance(scene, p, nrm))
    second = time.perf_counter() - t
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # before Radiance's rays and octree
    out = {"kind": kind, "n": n, "scene_build_s": build, "first_call_s": first, "peak_rss_gb": peak}
    out.update(_rounds(lambda: np.asarray(js.irradiance(scene, p, nrm)), second, light, tris, p, nrm, e, reps))
    if scene.occluders is not None:
        plan = js.shadow_plan(scene, p, nrm)
        out["plan"] = plan.summary()
    np.save(os.environ["JAXSHADOW_BENCH_OUT"], e)
    return out


def _rounds(ours, second: float, light, tris, p, nrm, e_ours, reps: int) -> dict:
    """jaxshadow (`ours()`) and Radiance at its defaults timed in `reps` alternating rounds in one
    process, each the best of its calls; a round runs ours for at least ~0.5 s (calls of 30 ms
    otherwise sampled the shared machine's load at one instant while Radiance's 0.4 s averaged it)
    and Radiance once. Radiance with fine source subdivision (10-15x slower) runs once."""
    from benchmarks.peers import RADIANCE_DEFAULT, RADIANCE_FINE, Radiance

    calls = max(1, min(20, int(np.ceil(0.5 / max(second, 1e-3)))))
    best, rad = second, {}
    loads = [os.getloadavg()[0]]
    with Radiance([(light, np.ones(3))], tris) as r:
        for _ in range(reps):
            for _ in range(calls):
                t = time.perf_counter()
                ours()
                best = min(best, time.perf_counter() - t)
            er, sec = r.irradiance(p, nrm, RADIANCE_DEFAULT)
            rad.setdefault("default", (er, np.inf))
            rad["default"] = (er, min(sec, rad["default"][1]))
            loads.append(os.getloadavg()[0])
        rad["fine"] = r.irradiance(p, nrm, RADIANCE_FINE)
    n = p.shape[0]
    radiance = {}
    for label, params in (("default", RADIANCE_DEFAULT), ("fine", RADIANCE_FINE)):
        er, sec = rad[label]
        rms = float(np.sqrt(np.mean((er[:, 0] - e_ours[:, 0]) ** 2)) / np.sqrt(np.mean(e_ours[:, 0] ** 2)))
        radiance[label] = {"seconds": sec, "points_per_s": n / sec, "rms_rel_err": rms, "params": list(params)}
    return {"best_s": best, "points_per_s": n / best, "rounds": reps, "calls_per_round": calls,
            "load_average": [min(loads), max(loads)], "radiance": radiance}


def _lit90_pair(n: int, reps: int) -> dict:
    """The 90 %-lit scene and the same floor without occluders in one process, in alternating
    blocks of 5 calls of one scene (a drift of the shared machine between two processes moved the
    ratio by more than the effects measured; alternating single calls slowed the unoccluded one,
    which then ran after the other's): best of `reps` calls each."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxshadow as js
    from benchmarks.scenes import floor_receivers

    p, nrm = floor_receivers(n, grazing=0.05)
    scenes = {"occluded": _scene("lit90")[0], "unoccluded": _scene("empty")[0]}
    out: dict = {}
    for key, scene in scenes.items():
        t = time.perf_counter()
        np.asarray(js.irradiance(scene, p, nrm))
        out[key] = {"n": n, "first_call_s": time.perf_counter() - t, "best_s": np.inf}
    for _ in range(max(1, reps // 5)):
        for key, scene in scenes.items():
            for _ in range(5):
                t = time.perf_counter()
                np.asarray(js.irradiance(scene, p, nrm))
                out[key]["best_s"] = min(out[key]["best_s"], time.perf_counter() - t)
    out["occluded"]["plan"] = js.shadow_plan(scenes["occluded"], p, nrm).summary()
    return out


def _incremental(n: int, reps: int) -> dict:
    """Move one box of the mesh scene: `ShadowCache.update` against a fresh cache (a rebuild)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxshadow as js
    from benchmarks.scenes import box_field, floor_receivers

    bf = box_field(180)
    light = js.PolygonLight(bf.light, radiance=1.0)
    p, nrm = floor_receivers(n, grazing=0.05)
    scenes = []
    for shift in (0.0, 0.05):
        meshes = [js.Mesh(v + (np.array([shift, 0.5 * shift, 0.0]) if i == 7 else 0.0), f)
                  for i, (v, f) in enumerate(bf.boxes)]
        scenes.append(js.Scene([light], occluders=meshes))
    js.ShadowCache(scenes[0], p, nrm)  # compile
    rebuild, update, identical, moved = np.inf, np.inf, True, 0
    for r in range(reps):
        t = time.perf_counter()
        cache = js.ShadowCache(scenes[0], p, nrm)
        rebuild = min(rebuild, time.perf_counter() - t)
        t = time.perf_counter()
        cache.update(scenes[1])
        update = min(update, time.perf_counter() - t)
        moved = cache.last_update["receivers"][0]
        if r == 0:
            fresh = js.ShadowCache(scenes[1], p, nrm)
            identical = bool(np.array_equal(cache.irradiance, fresh.irradiance))
            max_diff = float(np.max(np.abs(cache.irradiance - fresh.irradiance)))
    return {"n": n, "rebuild_s": rebuild, "update_s": update, "speedup": rebuild / update,
            "receivers_reevaluated": moved, "identical_to_rebuild": identical, "max_abs_diff": max_diff}


def _fit(n_targets: int, reps: int) -> dict:
    """`inverse.fit_light` with the 2 160-triangle mesh scene (180 `js.Mesh` boxes) and
    `n_targets` painted floor points (half in penumbra), from one start 3 cm / 2 degrees off:
    first call, best later solve, pose error; d(loss)/d(light) (each vertex's x and y, and the
    light's height) at the start through the solver's
    compiled residual (shadow engine through the FFI) against float64 central differences of
    the loss evaluated point by point by `js.shade` (host engine)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import inverse
    import jaxshadow as js
    from benchmarks.scenes import floor_receivers
    from inverse import _forward as R
    from inverse._parametrisation import LightParametrisation

    scene, light, _ = _scene("mesh")
    rng = np.random.default_rng(5)
    p, nrm = floor_receivers(20_000, seed=3)
    near = np.abs(p[:, :2]).max(axis=1) < 2.5
    cls = js.shadow_plan(scene, p, nrm).classes[0]
    pen = np.nonzero((cls == 3) & near)[0]
    lit = np.nonzero((cls == 1) & near)[0]
    idx = np.concatenate([rng.choice(pen, n_targets // 2, replace=False),
                          rng.choice(lit, n_targets - n_targets // 2, replace=False)])
    pts, nn = p[idx], nrm[idx]
    material = js.Material(ka=0.0, kd=0.6, ks=0.0, exponent=1.0)
    eye = np.array([0.0, -5.0, 4.0])
    targets = inverse.PaintedTargets(pts, nn, js.shade(scene, material, pts, nn, eye), eye)
    c = light.mean(axis=0)
    t = np.radians(2.0)
    rot = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1.0]])
    moved = (light - c) @ rot.T + c + np.array([0.03, -0.02, 0.01])
    start = js.Scene([js.PolygonLight(moved, radiance=1.0)], occluders=scene.occluders)
    solver = inverse.LM(refine=None)
    times = []
    for _ in range(1 + reps):
        t0 = time.perf_counter()
        fit = inverse.fit_light(start, targets, material, starts=1, solver=solver)
        jax.block_until_ready(fit.light.vertices)
        times.append(time.perf_counter() - t0)
    err = float(np.abs(np.asarray(fit.light.vertices) - light).max())

    # Gradient of the loss in the light's vertices: the solver's residual (traced engine) ...
    from inverse._multistart import culling_capacity_for_starts

    param = LightParametrisation(start.lights[0], 0, ("position",), None, 1.0, "sigmoid")
    cap = culling_capacity_for_starts(param, start, targets, jnp.zeros((1, param.size)))
    occ = start.occluders

    def loss_at(v, capacity):
        sc = js.Scene([js.PolygonLight(v, radiance=1.0)], occluders=occ)
        model, over = R.shade_culled(sc, material, targets.points, targets.normals, targets.eye, None, False, capacity)
        r = model - targets.colours
        return 0.5 * jnp.sum(r * r), over

    # Parameters that keep the light planar: each vertex's x and y (8), and a lift of the
    # whole light along z (a single vertex moved in z would bend the quad out of its plane).
    def verts(theta):
        return jnp.asarray(moved) + jnp.concatenate([theta[:8].reshape(4, 2), jnp.zeros((4, 1))], axis=1) \
            + theta[8] * jnp.array([[0.0, 0.0, 1.0]])

    theta0 = jnp.zeros(9)
    g, over = jax.jit(jax.grad(lambda th, c: loss_at(verts(th), c), has_aux=True), static_argnums=1)(theta0, cap)
    g = np.asarray(g)

    # ... against central differences of the loss from js.shade (the host engine, concrete).
    def host_loss(theta):
        sc = js.Scene([js.PolygonLight(np.asarray(verts(jnp.asarray(theta))), radiance=1.0)], occluders=occ)
        r = np.asarray(js.shade(sc, material, pts, nn, eye)) - np.asarray(targets.colours)
        return 0.5 * float(np.sum(r * r))

    h = 1e-6
    fd = np.zeros(9)
    for i in range(9):
        e = np.zeros(9)
        e[i] = h
        fd[i] = (host_loss(e) - host_loss(-e)) / (2 * h)
    rel = float(np.abs(g - fd).max() / np.abs(fd).max())
    return {"targets": n_targets, "triangles": 2160, "capacity": cap, "first_call_s": times[0],
            "solve_s": min(times[1:]), "vertex_error_m": err, "loss": float(fit.report.loss),
            "grad_rel_err_vs_central_fd": rel, "overflow": bool(over), "fd_step": h}


def _run_worker(kind: str, n: int, reps: int, tmp: Path) -> tuple[dict, np.ndarray]:
    out = tmp / f"{kind}-{n}.npy"
    env = dict(os.environ, JAXSHADOW_BENCH_OUT=str(out), PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-m", "benchmarks.shadows_scale", "--worker", kind, str(n), str(reps)],
                         cwd=ROOT, env=env, capture_output=True, text=True, check=False)
    if res.returncode:
        raise RuntimeError(f"worker {kind} {n} failed:\n{res.stderr[-4000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1]), np.load(out)


def _oracle():
    """`tests/exact_reference.irradiance(light, tris (m, 3, 3), p, n)`: pi F, exact to rounding."""
    sys.path.insert(0, str(ROOT / "tests"))
    from exact_reference import irradiance  # type: ignore[import-not-found]

    return irradiance


def _triangles(polys: np.ndarray) -> np.ndarray:
    """Convex polygons `(m, k, 3)` as `(m (k - 2), 3, 3)` triangles (fans)."""
    polys = np.asarray(polys, np.float64).reshape(-1, np.shape(polys)[-2] if np.size(polys) else 3, 3)
    k = polys.shape[1]
    return np.concatenate([polys[:, [0, j, j + 1]] for j in range(1, k - 1)]) if len(polys) else np.zeros((0, 3, 3))


def _culled(p: np.ndarray, n: np.ndarray, em: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """The triangles that can block part of `em` seen from `p` (an exact cull: a triangle with
    all vertices strictly outside one bounding plane of the pyramid conv(p, em), or behind the
    light's plane, or below p's tangent plane, or not above p's plane parallel to the light,
    blocks nothing); the oracle then clips these."""
    if len(tris) == 0:
        return tris
    ne = np.cross(em[1] - em[0], em[2] - em[0])
    keep = ~np.all((tris - em[0]) @ ne <= 0, axis=1)  # beyond the light's plane (lit side is +ne)
    keep &= ~np.all((tris - p) @ n <= 0, axis=1)
    # Not beyond p's plane parallel to the light (rays to the light leave it at once: a face
    # there meets them at p only; e.g. a box's bottom face around a floor point under it).
    toward = np.sign(np.dot(em[0] - p, ne))
    keep &= ~np.all(((tris - p) @ ne) * toward <= 0, axis=1)
    for i in range(len(em)):
        a, b = em[i], em[(i + 1) % len(em)]
        c = np.cross(a - p, b - p)
        side = np.dot(em[(i + 2) % len(em)] - p, c)
        keep &= ~np.all(((tris - p) @ c) * np.sign(side) < 0, axis=1)
    return tris[keep]


def _exactness(kind: str, e: np.ndarray, plan_classes: np.ndarray, n_check: int, seed: int = 7) -> dict:
    from benchmarks.scenes import floor_receivers

    exact = _oracle()
    _, light, tris = _scene(kind)
    p, nrm = floor_receivers(e.shape[0], grazing=0.05)
    rng = np.random.default_rng(seed)
    picks = []
    n_grazing = int(round(0.05 * e.shape[0]))
    groups = {"lit": np.nonzero(plan_classes == 1)[0], "umbra": np.nonzero(plan_classes == 2)[0],
              "penumbra": np.nonzero(plan_classes == 3)[0], "grazing": np.arange(n_grazing)}
    per = n_check // 4
    for name, idx in groups.items():
        if idx.size:
            picks.append((name, rng.choice(idx, min(per, idx.size), replace=False)))
    errs = {}
    worst = 0.0
    scale = float(np.max(e[:, 0]))
    for name, idx in picks:
        ref = np.array([exact(light, _triangles(_culled(p[i], nrm[i], light, tris)), p[i], nrm[i]) for i in idx])
        err = np.abs(e[idx, 0] - ref) / np.maximum(np.abs(ref), 1e-3 * scale)
        errs[name] = {"count": int(idx.size), "max_rel_err": float(err.max())}
        worst = max(worst, float(err.max()))
    return {"classes": errs, "max_rel_err": worst, "checked": int(sum(v["count"] for v in errs.values()))}


def run(quick: bool = False) -> dict:
    import tempfile

    tmp = Path(tempfile.mkdtemp(prefix="jaxshadow-bench-"))
    reps = 2 if quick else 3
    sizes = [20_000] if quick else [200_000, 1_000_000]
    n_check = 100 if quick else 1000
    results: dict = {"name": NAME, "quick": quick, "machine": platform.processor() or platform.machine(),
                     "cpus": os.cpu_count(), "cases": []}
    for kind in ("mesh", "quad"):
        for n in sizes if kind == "mesh" else sizes[:1]:
            ours, e = _run_worker(kind, n, reps, tmp)
            case = {"scene": kind, "n": n, "jaxshadow": ours, "radiance": ours.pop("radiance")}
            if n == sizes[0]:
                classes = np.load(tmp / f"{kind}-{n}.classes.npy") if (tmp / f"{kind}-{n}.classes.npy").exists() else None
                if classes is None:
                    classes = _classes(kind, n)
                case["exactness"] = _exactness(kind, e, classes, n_check)
            for label in ("default", "fine"):
                case[f"speedup_vs_radiance_{label}"] = ours["points_per_s"] / case["radiance"][label]["points_per_s"]
            results["cases"].append(case)
            print(json.dumps({k: v for k, v in case.items() if k != "jaxshadow"} | {"ours_pts_s": ours["points_per_s"]}),
                  flush=True)
    n = sizes[0]
    # Calls of 10-50 ms: best of more of them (a best of 3 moved the ratio by +-0.4 between runs).
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-m", "benchmarks.shadows_scale", "--worker", "lit90_pair", str(n),
                          str(10 * reps)], cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    pair = json.loads(res.stdout.strip().splitlines()[-1])
    results["lit90"] = {"n": n, **pair, "cost_ratio": pair["occluded"]["best_s"] / pair["unoccluded"]["best_s"]}
    print(json.dumps({"lit90_cost_ratio": results["lit90"]["cost_ratio"]}), flush=True)
    res = subprocess.run([sys.executable, "-m", "benchmarks.shadows_scale", "--worker", "incremental", str(n), str(reps)],
                         cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    results["incremental"] = json.loads(res.stdout.strip().splitlines()[-1])
    print(json.dumps({"incremental": results["incremental"]}), flush=True)
    res = subprocess.run([sys.executable, "-m", "benchmarks.shadows_scale", "--worker", "fit", "48", str(reps)],
                         cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    results["fit_light"] = json.loads(res.stdout.strip().splitlines()[-1])
    print(json.dumps({"fit_light": results["fit_light"]}), flush=True)
    return results


def markdown(results: dict) -> str:
    """The tables of `benchmarks/README.md`."""
    lines = ["Scene: a floor [-4, 4]^2 under a 0.6 m quad light at z = 2; `mesh`: 180 closed boxes "
             "(2 160 triangles, `js.Mesh`), `quad`: one square occluder. float64, best of the steady-state "
             "calls; Radiance `rtrace -I -ab 0` on the same receivers in the same process, its default setting "
             "timed in rounds alternating with ours (default / fine source subdivision), its error the RMS difference to jaxshadow's exact values relative to their RMS.",
             "",
             "| scene | receivers | jaxshadow points/s | first call (s) | peak memory (GB) | max rel. error vs "
             "the exact reference (checked) | Radiance default points/s (RMS err) | Radiance fine points/s (RMS err) | "
             "speedup vs default / fine |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for c in results["cases"]:
        j, r = c["jaxshadow"], c["radiance"]
        ex = c.get("exactness")
        ex_txt = f"{ex['max_rel_err']:.1e} ({ex['checked']})" if ex else "-"
        lines.append(f"| {c['scene']} | {c['n']:,} | {j['points_per_s']:.3g} | {j['first_call_s']:.1f} | "
                     f"{j['peak_rss_gb']:.2f} | {ex_txt} | {r['default']['points_per_s']:.3g} "
                     f"({100 * r['default']['rms_rel_err']:.1f} %) | {r['fine']['points_per_s']:.3g} "
                     f"({100 * r['fine']['rms_rel_err']:.1f} %) | {c['speedup_vs_radiance_default']:.2f}x / "
                     f"{c['speedup_vs_radiance_fine']:.2f}x |")
    mesh = next(c for c in results["cases"] if c["scene"] == "mesh")
    plan = mesh["jaxshadow"].get("plan", {})
    if plan:
        lp = plan["lights"][0]
        fr = lp["fractions"]
        lines += ["", f"Classes of the mesh scene ({mesh['n']:,} receivers): lit {100 * fr['lit']:.1f} %, umbra "
                  f"{100 * fr['umbra']:.1f} %, penumbra {100 * fr['penumbra']:.1f} %, behind / below the horizon "
                  f"{100 * fr['zero']:.1f} %; candidates per penumbra receiver: mean {lp['candidates']['mean']:.1f}, "
                  f"max {lp['candidates']['max']}; engine time {plan['seconds']:.2f} s; scene build "
                  f"{mesh['jaxshadow']['scene_build_s']:.2f} s."]
    lit = results["lit90"]
    inc = results["incremental"]
    fit = results["fit_light"]
    lines += ["",
              "| measure | value |", "|---|---:|",
              f"| 90 % lit scene: cost / the same scene without occluders ({lit['n']:,} receivers; one process, "
              f"alternating blocks of 5 calls, best of each: {1e3 * lit['occluded']['best_s']:.1f} / "
              f"{1e3 * lit['unoccluded']['best_s']:.1f} ms) | {lit['cost_ratio']:.2f}x |",
              f"| moving one box: rebuild / update ({inc['n']:,} receivers, {inc['receivers_reevaluated']} re-evaluated) "
              f"| {inc['speedup']:.1f}x (identical: {inc['identical_to_rebuild']}) |",
              f"| `fit_light`, 2 160-triangle mesh, {fit['targets']} targets: first call / one solve | "
              f"{fit['first_call_s']:.1f} s / {fit['solve_s']:.2f} s |",
              f"| `fit_light`: d(loss)/d(light) vs float64 central differences (max rel.) | "
              f"{fit['grad_rel_err_vs_central_fd']:.1e} |"]
    return "\n".join(lines)


def key_numbers(results: dict) -> list[tuple[str, str]]:
    """Rows of the top-level README's key numbers."""
    out = []
    for c in results["cases"]:
        what = ("exact shadows, 2 160-triangle mesh" if c["scene"] == "mesh" else "exact shadows, one quad occluder")
        out.append((f"{what}, {c['n']:,} receivers: points/s vs Radiance default (its RMS error), peak memory",
                    f"{c['jaxshadow']['points_per_s']:.2g} vs {c['radiance']['default']['points_per_s']:.2g} "
                    f"({100 * c['radiance']['default']['rms_rel_err']:.1f} %), {c['jaxshadow']['peak_rss_gb']:.1f} GB"))
    fit = results["fit_light"]
    out.append(("`fit_light` with a 2 160-triangle mesh occluder, 48 targets: one solve after compilation",
                f"{fit['solve_s']:.2f} s"))
    return out


def _classes(kind: str, n: int) -> np.ndarray:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxshadow as js
    from benchmarks.scenes import floor_receivers

    scene, _, _ = _scene(kind)
    p, nrm = floor_receivers(n, grazing=0.05)
    return js.shadow_plan(scene, p, nrm).classes[0]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke run)")
    ap.add_argument("--worker", nargs=3, metavar=("KIND", "N", "REPS"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        kind, n, reps = args.worker
        special = {"incremental": _incremental, "fit": _fit, "lit90_pair": _lit90_pair}
        fn = special.get(kind, lambda n_, r_: _worker(kind, n_, r_))
        print(json.dumps(fn(int(n), int(reps))))
        return
    from benchmarks._suite import main as suite

    raise SystemExit(suite([NAME, *(["--quick"] if args.quick else [])]))


if __name__ == "__main__":
    main()
