"""Speed of the inverse solvers: compile time, time per solve, 64 vectorised starts.

Targets (issue 5): compile <= 5 s, <= 200 ms per solve after compilation, 64 starts <= 2 s with
<= 8 occluders. Light placement (position, orientation, size: 8 parameters) on the demo
configuration (quad light, 48 painted points, diffuse material) with 1 and 8 random occluders,
timed end to end through `inverse.fit_light` (compile = first call - median later call):
`inverse.LM()` from 1 start, from 64 starts screened to the 8 best, from all 64 starts, with
every receiver against every occluder (`combinatorics="device"`) instead of the shadow engine, and `inverse.OptimistixLM()` from 1 start; a fresh process's first call
without and with the persistent compilation cache. Then the material fit on 20 points with the
roughness searched and fixed.

    python -m benchmarks inverse_speed [--quick]     # ~15 min on 2 shared cores
"""

from __future__ import annotations

import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import inverse
from inverse import demo_configuration, pose_errors
from inverse._forward import shade

from .inverse_scenes import occluded_light_problem

DESCRIPTION = "inverse solvers: light-placement compile / solve times (1, 64 -> 8, 64 starts), material fit"


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


def _light_problem(n_occ, seed=0):
    """The demo's quad light (48 painted points, diffuse material, noise-free targets from our
    model: this measures solver speed, not accuracy) with `n_occ` random 0.2 x 0.2 occluders."""
    return occluded_light_problem(n_occ, n_points=48, seed=seed)[:4]


def _child(n_occ, cache_dir):
    """In a fresh process: the first `fit_light` call (1 start) with the persistent cache in
    `cache_dir`; prints its wall time as JSON."""
    from jaxshadow.cli import enable_compile_cache

    enable_compile_cache(cache_dir)
    scene, start, material, targets = _light_problem(n_occ)
    t0 = time.perf_counter()
    _block(inverse.fit_light(start, targets, material, starts=1).light.vertices)
    print(json.dumps({"first_call_s": time.perf_counter() - t0}))


def _process_first_calls(n_occ):
    """First-call time of a fresh process without, then with, a warm persistent cache."""
    import subprocess
    import tempfile

    out = []
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with tempfile.TemporaryDirectory() as d:
        for _ in range(2):
            r = subprocess.run([sys.executable, "-m", "benchmarks.inverse_speed", str(n_occ), d],
                               capture_output=True, text=True, check=True, cwd=root)
            out.append(json.loads(r.stdout.strip().splitlines()[-1])["first_call_s"])
    return {"cold_process_first_call_s": out[0], "warm_cache_process_first_call_s": out[1]}


def _joint_child(cache_dir: str = "") -> None:
    """In a fresh process: `inverse.fit_light_and_material` (the demo's quad light 30 % of the
    scene away, 40 painted targets, one box occluder) on two target sets of the same shapes
    (scene seeds 0 and 1): per call its wall time, the seconds JAX spent compiling (XLA backend
    compile and lowering, `jax.monitoring`) and the seconds inside `joint_std_errors`; printed
    as JSON. The second call shows what the first one's compiled programs save. `cache_dir`:
    JAX's persistent compilation cache there (`jaxshadow.cli.enable_compile_cache`; "" none)."""
    from benchmarks.fit_lights import _timing
    from inverse import _joint

    if cache_dir:
        from jaxshadow.cli import enable_compile_cache

        enable_compile_cache(cache_dir, min_compile_s=0.0)

    timing = _timing()
    inside = {"s": 0.0}
    plain = _joint.joint_std_errors

    def timed(*args, **kwargs):
        t0 = time.perf_counter()
        out = plain(*args, **kwargs)
        inside["s"] += time.perf_counter() - t0
        return out

    _joint.joint_std_errors = timed
    calls = []
    for seed in (0, 1):
        cfg = demo_configuration(occluders=True, n_points=40, seed=seed)
        col = shade(cfg.scene, cfg.material, jnp.asarray(cfg.points), jnp.asarray(cfg.normals),
                    jnp.asarray(np.broadcast_to(cfg.eye, cfg.points.shape)))
        tg = inverse.PaintedTargets(cfg.points, cfg.normals, np.asarray(col), cfg.eye)
        guess = _material_guess(cfg.material)
        c0, s0 = timing["compile_s"], inside["s"]
        t0 = time.perf_counter()
        fit = inverse.fit_light_and_material(cfg.start_scene, tg, guess)
        wall = time.perf_counter() - t0
        err = pose_errors(np.asarray(fit.scene.lights[0].vertices), np.asarray(cfg.scene.lights[0].vertices))
        calls.append({"fit_s": wall, "compile_s": timing["compile_s"] - c0, "std_errors_s": inside["s"] - s0,
                      "position_err_m": err["position"]})
    print(json.dumps({"calls": calls, "load": os.getloadavg()[0]}))


def _material_guess(material):
    """The starting material of the joint fit: the true exponent, other coefficients off."""
    import jaxshadow as js

    return js.Material(ka=0.2, kd=0.5, ks=0.2, exponent=float(material.exponent))


def _joint_process(cache_dir: str = "") -> dict:
    """`_joint_child` in a fresh process (`cache_dir`: the persistent compilation cache)."""
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    r = subprocess.run([sys.executable, "-m", "benchmarks.inverse_speed", "joint", cache_dir], capture_output=True,
                       text=True, check=True, cwd=root)
    return json.loads(r.stdout.strip().splitlines()[-1])


def joint_study() -> dict:
    """`_joint_child` in fresh processes: without the persistent compilation cache, then twice
    with one (filled by the first, reused by the second)."""
    import tempfile

    out = {"no cache": _joint_process()}
    with tempfile.TemporaryDirectory() as d:
        out["cache filled"] = _joint_process(d)
        out["cache reused"] = _joint_process(d)
    return out


def run(quick: bool) -> dict:
    jax.config.update("jax_enable_x64", True)
    from inverse._lm import FIT_COMPILER_OPTIONS

    occluders, repeats = ([1], 1) if quick else ([1, 8], 3)
    results = {"fit_compiler_options": dict(FIT_COMPILER_OPTIONS), "backend": jax.default_backend(), "targets": 48,
               "dtype": "float64", "light": {}}
    # (solver, starts, refine, repeats, every receiver against every occluder)
    cases = [("lm", 1, None, repeats, False), ("lm", 64, 8, repeats, False)]
    if not quick:
        cases += [("lm", 64, None, 1, False), ("lm", 1, None, repeats, True),
                  ("optimistix", 1, None, repeats, False)]
    for n_occ in occluders:
        scene, start, material, targets = _light_problem(n_occ)
        true = np.asarray(scene.lights[0].vertices)
        for solver, starts, refine, reps, groups in cases:
            fits = []
            obj = (inverse.LM(refine=refine, combinatorics="device" if groups else "auto") if solver == "lm"
                   else inverse.OptimistixLM(refine=refine))

            def call(problem=(start, targets, material), obj=obj, starts=starts, fits=fits):
                fits.append(inverse.fit_light(*problem, starts=starts, solver=obj))
                return fits[-1].light.vertices

            first, med, runs = _timed(call, reps)
            fit = fits[-1]
            err = pose_errors(np.asarray(fit.light.vertices), true)
            key = (f"{solver}/occluders={n_occ}/starts={starts}" + (f"/refine={refine}" if refine else "")
                   + ("/device" if groups else ""))
            results["light"][key] = {
                "solver": solver, "occluders": n_occ, "starts": starts, "refine": refine, "device": groups,
                "abandoned_starts": int(np.count_nonzero(fit.report.abandoned)) if fit.report.abandoned is not None
                else 0,
                "first_call_s": first, "compile_s": first - med, "solve_s": med, "runs_s": runs,
                "max_steps_taken": int(np.max(fit.report.num_steps)), "best_loss": fit.report.loss,
                "position_error_rel": err["position"] / fit.report.scale, "orientation_deg": err["orientation_deg"],
                "warnings": list(fit.report.warnings),
            }
            print(f"{key:45s} compile {first - med:7.2f} s  solve {1e3 * med:9.1f} ms", flush=True)
        results["light"][f"lm/occluders={n_occ}/process_first_call"] = _process_first_calls(n_occ)
    # Material fit (roughness searched): whole call, after a warm-up call.
    mcfg = demo_configuration(occluders=False, n_points=20, seed=0)
    mcol = np.asarray(shade(mcfg.scene, mcfg.material, jnp.asarray(mcfg.points), jnp.asarray(mcfg.normals),
                            jnp.asarray(np.broadcast_to(mcfg.eye, (20, 3)))))
    mt = inverse.PaintedTargets(mcfg.points, mcfg.normals, mcol, mcfg.eye)
    for key, kw in (("material_fit_n_searched", {}), ("material_fit_n_fixed", {"exponent": 30.0})):
        first, med, runs = _timed(lambda kw=kw: inverse.fit_material(mcfg.scene, mt, **kw).material.kd, repeats)
        results[key] = {"first_call_s": first, "compile_s": first - med, "solve_s": med, "runs_s": runs}
    results["targets_s"] = {"compile": 5.0, "solve": 0.2, "starts_64": 2.0}
    results["joint"] = joint_study()
    return results


def markdown(results):
    return _markdown(results)


def key_numbers(results: dict) -> list[tuple[str, str]]:
    light = results["light"]
    occ = sorted({r["occluders"] for r in light.values() if "solver" in r})

    def cell(key: str) -> str:
        parts = [light.get(f"lm/occluders={n}/{key}") for n in occ]
        return " / ".join(f"{r['compile_s']:.1f} s + {r['solve_s'] * 1e3:.0f} ms" if r else "-" for r in parts)

    first = " / ".join(f"{light[f'lm/occluders={n}/process_first_call']['cold_process_first_call_s']:.1f} s"
                       for n in occ if f"lm/occluders={n}/process_first_call" in light)
    which = " / ".join(str(n) for n in occ)
    return [(f"light placement (8 parameters, 48 targets), `inverse.LM()`, {which} occluders: compile + solve",
             f"1 start {cell('starts=1')}; 64 starts screened to 8 (default) {cell('starts=64/refine=8')}; "
             f"a fresh process's first call {first}")]


def _markdown(results):
    lines = [
        "float64, 48 targets, 8 light parameters; fit programs compiled with "
        f"{results.get('fit_compiler_options') or 'XLA defaults'}.",
        "",
        "| solver | occluders | starts | compile (s) | solve (ms) | max LM steps | abandoned | position error / scene |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results["light"].values():
        if "cold_process_first_call_s" in r:
            continue
        starts = f"{r['starts']}" + (f" -> best {r['refine']}" if r["refine"] else "")
        solver = r["solver"] + (", device" if r.get("device") else "") + (", receiver_groups" if r.get("receiver_groups") else "")
        lines.append(f"| {solver} | {r['occluders']} | {starts} | {r['compile_s']:.1f} | {1e3 * r['solve_s']:.0f} | "
                     f"{r['max_steps_taken']} | {r.get('abandoned_starts', 0)} | {r['position_error_rel']:.1e} |")
    for key, label in (("material_fit_n_searched", "material fit, n searched (20 points)"),
                       ("material_fit_n_fixed", "material fit, n fixed (20 points)")):
        if key in results:
            r = results[key]
            lines.append(f"| {label} | | | {r['compile_s']:.1f} | {1e3 * r['solve_s']:.0f} | | | |")
    if "joint" in results:
        lines += ["", "`inverse.fit_light_and_material` (demo quad light 30 % away, 40 targets, one occluder) in a fresh "
                  "process, two target sets of the same shapes; seconds:", "",
                  "| process | call | fit | of which compiling | of which `joint_std_errors` |", "|---|---:|---:|---:|---:|"]
        for label, r in results["joint"].items():
            for n, c in enumerate(r["calls"], 1):
                lines.append(f"| {label} (load {r['load']:.1f}) | {n} | {c['fit_s']:.1f} | {c['compile_s']:.1f} | "
                             f"{c['std_errors_s']:.2f} |")
    lines.append("")
    for key, r in results["light"].items():
        if "cold_process_first_call_s" in r:
            lines.append(f"- {key.split('/')[1]}: a fresh process's first `fit_light` call (1 start) takes "
                         f"{r['cold_process_first_call_s']:.1f} s, {r['warm_cache_process_first_call_s']:.1f} s with "
                         "a warm persistent compilation cache (`jaxshadow.cli.enable_compile_cache`, on by default "
                         "in the `jaxshadow` command).")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    # A fresh process's first call, for `_process_first_calls`: N_OCCLUDERS CACHE_DIR; or
    # `joint` for `_joint_process`.
    jax.config.update("jax_enable_x64", True)
    if sys.argv[1] == "joint":
        _joint_child(sys.argv[2] if len(sys.argv) > 2 else "")
    else:
        _child(int(sys.argv[1]), sys.argv[2])
