"""Speed of the inverse solvers: compile time, time per solve, 64 vectorised starts.

Targets (issue 5): compile <= 5 s, <= 200 ms per solve after compilation, 64 starts <= 2 s with
<= 8 occluders. Light placement on the demo configuration (quad light, up to 8 occluders when
this jaxshadow has soft shadows, 48 painted points, diffuse material), the material fit on 20
points with the roughness searched. Writes benchmarks/results/inverse_speed.json.

    .venv/bin/python benchmarks/inverse_speed.py [--occluders 8] [--repeats 5] [--starts 1 64]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import inverse  # noqa: E402
import jaxshadow as js  # noqa: E402
from inverse import _lights as L  # noqa: E402
from inverse._forward import shade  # noqa: E402
from inverse._scenes import demo_configuration, quad  # noqa: E402


def _block(x):
    return jax.block_until_ready(x)


def _timed(fn, repeats):
    t0 = time.perf_counter()
    _block(fn())
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        _block(fn())
        runs.append(time.perf_counter() - t0)
    return first, float(np.median(runs)), runs


def _shadows_supported():
    s = js.Scene([js.PointLight([0.0, 0.0, 2.0])], occluders=[quad([0, 0, 1.0], 0.2, 0.2, (0, 0, 0))])
    try:
        js.irradiance(s, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))
    except NotImplementedError:
        return False
    return True


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--occluders", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--starts", type=int, nargs="+", default=[1, 64], help="multistart sizes to time")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "inverse_speed.json"))
    args = ap.parse_args()
    shadows = _shadows_supported()
    n_occ = args.occluders if shadows else 0
    cfg = demo_configuration(occluders=False, n_points=48, seed=3)
    occ = None
    if n_occ:
        rng = np.random.default_rng(0)
        occ = [quad([*rng.uniform(-0.6, 0.6, 2), rng.uniform(0.4, 0.9)], 0.2, 0.2, (0.0, 0.0, rng.uniform(0, 1)))
               for _ in range(n_occ)]
    scene = js.Scene(cfg.scene.lights, occluders=occ, ambient=cfg.scene.ambient)
    start = js.Scene(cfg.start_scene.lights, occluders=occ, ambient=cfg.scene.ambient)
    material = js.Material(ka=cfg.material.ka, kd=cfg.material.kd, ks=0.0, exponent=1.0)
    n = len(cfg.points)
    col = np.asarray(shade(scene, material, jnp.asarray(cfg.points), jnp.asarray(cfg.normals),
                           jnp.asarray(np.broadcast_to(cfg.eye, (n, 3))), with_specular=False))
    targets = inverse.PaintedTargets(cfg.points, cfg.normals, col, cfg.eye)
    size = inverse.scene_size(start, targets)
    param = L.LightParametrisation(start.lights[0], 0, ("position", "orientation", "size"), None, size, "sigmoid")
    setup = L._Setup(param, start, material, targets, None, False)
    results = {"machine": platform.platform(), "cpu_count": os.cpu_count(), "jax": jax.__version__,
               "backend": jax.default_backend(), "occluders": n_occ, "shadows_supported": shadows,
               "targets": n, "dtype": "float64"}
    for S in args.starts:
        y0 = L.make_starts(param, S, search_radius=0.5, orientation_spread=0.5, size_spread=0.5, seed=0,
                           dtype=jnp.float64)
        first, med, runs = _timed(lambda y0=y0: L._multistart_lm(setup, y0, 1e-10, 1e-12, 200), args.repeats)
        out = L._multistart_lm(setup, y0, 1e-10, 1e-12, 200)
        results[f"light_lm_{S}_starts"] = {
            "first_call_s": first, "compile_s": first - med, "solve_s": med, "runs_s": runs,
            "max_steps_taken": int(np.max(np.asarray(out[3]))), "best_loss": float(np.min(np.asarray(out[1]))),
        }
        print(f"light LM, {S:2d} start(s): compile {first - med:6.2f} s, solve {1e3 * med:8.1f} ms")
    y0 = L.make_starts(param, 64, search_radius=0.5, orientation_spread=0.5, size_spread=0.5, seed=0,
                       dtype=jnp.float64)
    first, med, runs = _timed(lambda: L._screen_losses(setup, y0), args.repeats)
    results["light_screen_64_starts"] = {"first_call_s": first, "compile_s": first - med, "solve_s": med}
    print(f"screening 64 starts (loss only): compile {first - med:6.2f} s, run {1e3 * med:8.1f} ms")
    # Material fit (roughness searched): whole call, after a warm-up call.
    if not hasattr(js, "specular"):
        print("no js.specular in this jaxshadow: material timings skipped")
        results["material_fit"] = "skipped: no js.specular"
        _write(results, args.out)
        return
    mcfg = demo_configuration(occluders=False, n_points=20, seed=0)
    mcol = np.asarray(shade(mcfg.scene, mcfg.material, jnp.asarray(mcfg.points), jnp.asarray(mcfg.normals),
                            jnp.asarray(np.broadcast_to(mcfg.eye, (20, 3)))))
    mt = inverse.PaintedTargets(mcfg.points, mcfg.normals, mcol, mcfg.eye)
    first, med, runs = _timed(lambda: inverse.fit_material(mcfg.scene, mt).material.kd, args.repeats)
    results["material_fit_n_searched"] = {"first_call_s": first, "compile_s": first - med, "solve_s": med,
                                          "runs_s": runs}
    print(f"material fit (n searched): first call {first:6.2f} s, solve {1e3 * med:8.1f} ms")
    first, med, runs = _timed(lambda: inverse.fit_material(mcfg.scene, mt, exponent=30.0).material.kd,
                              args.repeats)
    results["material_fit_n_fixed"] = {"first_call_s": first, "compile_s": first - med, "solve_s": med,
                                       "runs_s": runs}
    print(f"material fit (n fixed):    first call {first:6.2f} s, solve {1e3 * med:8.1f} ms")
    _write(results, args.out)


def _write(results, out):
    results["targets_s"] = {"compile": 5.0, "solve": 0.2, "starts_64": 2.0}
    os.makedirs(os.path.dirname(out), exist_ok=True)
    with open(out, "w") as fh:
        json.dump(results, fh, indent=1)
    print("wrote", out)


if __name__ == "__main__":
    main()
