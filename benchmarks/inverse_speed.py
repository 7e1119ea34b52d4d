"""Speed of the inverse solvers: compile time, time per solve, 64 vectorised starts.

Targets (issue 5): compile <= 5 s, <= 200 ms per solve after compilation, 64 starts <= 2 s with
<= 8 occluders. Light placement (position, orientation, size: 8 parameters) on the demo
configuration (quad light, 48 painted points, diffuse material) with 1 and 8 random occluders,
timed end to end through `inverse.fit_light` (compile = first call - median later call):
the default batched LM from 1 start, from 64 starts screened to the 8 best, from all 64 starts,
and `solver="optimistix"` from 1 start. Then the material fit on 20 points with the roughness
searched. Writes benchmarks/results/inverse_speed.json.

    .venv/bin/python benchmarks/inverse_speed.py [--occluders 1 8] [--repeats 3] [--no-optimistix]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import inverse  # noqa: E402
from inverse._forward import shade  # noqa: E402
from inverse._scenes import demo_configuration, occluded_light_problem, pose_errors  # noqa: E402


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


def _process_first_calls(n_occ, xla_defaults=False):
    """First-call time of a fresh process without, then with, a warm persistent cache."""
    import subprocess
    import tempfile

    out = []
    with tempfile.TemporaryDirectory() as d:
        for _ in range(2):
            r = subprocess.run([sys.executable, __file__, "--child", str(n_occ), d] + (["xla-defaults"] if xla_defaults else []),
                               capture_output=True, text=True,
                               check=True)
            out.append(json.loads(r.stdout.strip().splitlines()[-1])["first_call_s"])
    return {"cold_process_first_call_s": out[0], "warm_cache_process_first_call_s": out[1]}


def _use_xla_defaults():
    """Compile the fit programs with XLA's defaults (`fit_jit` reads the options at its first call)."""
    from inverse import _lm

    _lm.FIT_COMPILER_OPTIONS = {}


def main():
    if len(sys.argv) in (4, 5) and sys.argv[1] == "--child":
        if sys.argv[4:] == ["xla-defaults"]:
            _use_xla_defaults()
        _child(int(sys.argv[2]), sys.argv[3])
        return
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--occluders", type=int, nargs="+", default=[1, 8])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--full-repeats", type=int, default=1, help="repeats of the (slow) full 64-start solve")
    ap.add_argument("--no-optimistix", action="store_true", help="skip the optimistix comparison")
    ap.add_argument("--no-full", action="store_true", help="skip the (slow) LM from all 64 starts")
    ap.add_argument("--no-material", action="store_true", help="skip the material-fit timings")
    ap.add_argument("--xla-defaults", action="store_true",
                    help="compile the fit programs with XLA's default options instead of "
                         "inverse._lm.FIT_COMPILER_OPTIONS (the A/B of that choice)")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "inverse_speed.json"))
    args = ap.parse_args()
    if args.xla_defaults:
        _use_xla_defaults()
    from inverse._lm import FIT_COMPILER_OPTIONS

    results = {"machine": platform.platform(), "cpu_count": os.cpu_count(), "jax": jax.__version__,
               "fit_compiler_options": dict(FIT_COMPILER_OPTIONS),
               "backend": jax.default_backend(), "targets": 48, "dtype": "float64",
               "load_average_at_start": os.getloadavg(), "light": {}}
    cases = [("lm", 1, None, args.repeats, False), ("lm", 64, 8, args.repeats, False)]
    if not args.no_full:
        cases.append(("lm", 64, None, args.full_repeats, False))
    cases += [("lm", 1, None, args.repeats, True), ("lm", 64, 8, args.repeats, True)]
    if not args.no_optimistix:
        cases.append(("optimistix", 1, None, args.repeats, False))
    for n_occ in args.occluders:
        scene, start, material, targets = _light_problem(n_occ)
        true = np.asarray(scene.lights[0].vertices)
        for solver, starts, refine, reps, groups in cases:
            if groups and n_occ < 4:
                continue  # no culling, nothing to group
            fits = []

            def call(problem=(start, targets, material), solver=solver, starts=starts, refine=refine, fits=fits,
                     groups=groups):
                fits.append(inverse.fit_light(*problem, starts=starts, refine=refine, solver=solver,
                                              receiver_groups=groups))
                return fits[-1].light.vertices

            first, med, runs = _timed(call, reps)
            fit = fits[-1]
            err = pose_errors(np.asarray(fit.light.vertices), true)
            key = (f"{solver}/occluders={n_occ}/starts={starts}" + (f"/refine={refine}" if refine else "")
                   + ("/receiver_groups" if groups else ""))
            results["light"][key] = {
                "solver": solver, "occluders": n_occ, "starts": starts, "refine": refine, "receiver_groups": groups,
                "abandoned_starts": int(np.count_nonzero(fit.report.abandoned)) if fit.report.abandoned is not None
                else 0,
                "first_call_s": first, "compile_s": first - med, "solve_s": med, "runs_s": runs,
                "max_steps_taken": int(np.max(fit.report.num_steps)), "best_loss": fit.report.loss,
                "position_error_rel": err["position"] / fit.report.scale, "orientation_deg": err["orientation_deg"],
                "warnings": list(fit.report.warnings),
            }
            print(f"{key:45s} compile {first - med:7.2f} s  solve {1e3 * med:9.1f} ms  "
                  f"steps {int(np.max(fit.report.num_steps)):3d}  pos err {err['position'] / fit.report.scale:.1e}",
                  flush=True)
        results["light"][f"lm/occluders={n_occ}/process_first_call"] = pc = _process_first_calls(n_occ, args.xla_defaults)
        print(f"fresh process, 1 start, {n_occ} occluder(s): first call {pc['cold_process_first_call_s']:.1f} s "
              f"without, {pc['warm_cache_process_first_call_s']:.1f} s with a warm compilation cache", flush=True)
    if args.no_material:
        _write(results, args.out)
        return
    # Material fit (roughness searched): whole call, after a warm-up call.
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


def _markdown(results):
    lines = [
        f"Run: `benchmarks/inverse_speed.py` on {results['machine']} ({results['cpu_count']} cores), jax "
        f"{results['jax']}, float64, 48 targets, 8 light parameters; load average at start "
        f"{results['load_average_at_start'][0]:.1f}; fit programs compiled with "
        f"{results.get('fit_compiler_options') or 'XLA defaults'}.",
        "",
        "| solver | occluders | starts | compile (s) | solve (ms) | max LM steps | abandoned | position error / scene |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results["light"].values():
        if "cold_process_first_call_s" in r:
            continue
        starts = f"{r['starts']}" + (f" -> best {r['refine']}" if r["refine"] else "")
        solver = r["solver"] + (", receiver_groups" if r.get("receiver_groups") else "")
        lines.append(f"| {solver} | {r['occluders']} | {starts} | {r['compile_s']:.1f} | {1e3 * r['solve_s']:.0f} | "
                     f"{r['max_steps_taken']} | {r.get('abandoned_starts', 0)} | {r['position_error_rel']:.1e} |")
    for key, label in (("material_fit_n_searched", "material fit, n searched (20 points)"),
                       ("material_fit_n_fixed", "material fit, n fixed (20 points)")):
        if key in results:
            r = results[key]
            lines.append(f"| {label} | | | {r['compile_s']:.1f} | {1e3 * r['solve_s']:.0f} | | | |")
    lines.append("")
    for key, r in results["light"].items():
        if "cold_process_first_call_s" in r:
            lines.append(f"- {key.split('/')[1]}: a fresh process's first `fit_light` call (1 start) takes "
                         f"{r['cold_process_first_call_s']:.1f} s, {r['warm_cache_process_first_call_s']:.1f} s with "
                         "a warm persistent compilation cache (`jaxshadow.cli.enable_compile_cache`, on by default "
                         "in the `jaxshadow` command).")
    return "\n".join(lines) + "\n"


def _write(results, out):
    results["targets_s"] = {"compile": 5.0, "solve": 0.2, "starts_64": 2.0}
    os.makedirs(os.path.dirname(out), exist_ok=True)
    with open(out, "w") as fh:
        json.dump(results, fh, indent=1)
    md = os.path.splitext(out)[0] + ".md"
    with open(md, "w") as fh:
        fh.write(_markdown(results))
    print("wrote", out, "and", md)


if __name__ == "__main__":
    main()
