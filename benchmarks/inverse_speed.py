"""Speed of the inverse solvers: compile time, time per solve, 64 vectorised starts, whole fits.

Targets (issue 5): compile <= 5 s, <= 200 ms per solve after compilation, 64 starts <= 2 s with
<= 8 occluders. Light placement (position, orientation, size: 8 parameters) on the demo
configuration (quad light, 48 painted points, diffuse material) with 1 and 8 random occluders,
timed end to end through `inverse.fit_light` (compile = first call - median later call):
`inverse.LM()` from 1 start, from 64 starts screened to the 8 best, from all 64 starts, with
every receiver against every occluder (`combinatorics="device"`) instead of the shadow engine, and `inverse.OptimistixLM()` from 1 start; a fresh process's first call
without and with the persistent compilation cache. Then the material fit on 20 points with the
roughness searched and fixed.

Whole fits (issue 40: one light + material <= 10 s, three lights <= 30 s, compilation
included): `fit_speed_study` times `inverse.fit_light_and_material` (the demo's quad light 30 %
away, one box, 40 targets) and `inverse.fit_lights` (quad + point + segment light 30 % away, a
box, 60 targets, global placement) in fresh processes: compile time, the first fit's wall and
CPU time, a second fit in the same process (another scene of the same shapes), and a fresh
process with JAX's persistent compilation cache warm; the load is recorded with every fit.

    python -m benchmarks inverse_speed [--quick]     # ~15 min on 2 shared cores; quick: whole fits only
    python -m benchmarks.inverse_speed ab NAME base=/tmp/base this=.   # whole fits, A/B of checkouts
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
    compile and lowering, `jax.monitoring`) and the seconds spent on the joint Jacobian (inside
    `joint_std_errors`, or in the rows made of the light fit's kept basis,
    `_joint._AtAnswer.joint_rows`); printed as JSON. The second call shows what the first one's compiled programs save. `cache_dir`:
    JAX's persistent compilation cache there (`jaxshadow.cli.enable_compile_cache`; "" none)."""
    from benchmarks.fit_lights import _timing
    from inverse import _joint

    if cache_dir:
        from jaxshadow.cli import enable_compile_cache

        enable_compile_cache(cache_dir, min_compile_s=0.0)
    else:  # not the library's default cache either
        os.environ["JAXSHADOW_COMPILE_CACHE"] = "off"

    timing = _timing()
    inside = {"s": 0.0}
    plain = _joint.joint_std_errors

    def timed(*args, **kwargs):
        t0 = time.perf_counter()
        out = plain(*args, **kwargs)
        inside["s"] += time.perf_counter() - t0
        return out

    _joint.joint_std_errors = timed
    rows = _joint._AtAnswer.joint_rows

    def timed_rows(self, *args, **kwargs):
        t0 = time.perf_counter()
        out = rows(self, *args, **kwargs)
        inside["s"] += time.perf_counter() - t0
        return out

    _joint._AtAnswer.joint_rows = timed_rows  # type: ignore[method-assign]
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


# The fit-speed study (issue 40): a case is fitted twice in one process (two scenes of the same
# shapes), in a fresh process whose persistent compilation cache it fills, then in another fresh
# process that finds the cache warm.
FIT_CASES = ("one light + material", "three lights")


def _counters() -> dict:
    """Seconds JAX spent compiling (XLA backend compile + lowering to MLIR) and tracing, the number
    of XLA backend compilations, and the persistent cache's hits, from `jax.monitoring`; under
    `"programs"`, the same seconds per program (the event's function name, `jit(...)` for the
    compile and lowering): `{name: {"backend_compile_s", "lowering_s", "trace_s"}}`."""
    acc: dict = {"compile_s": 0.0, "trace_s": 0.0, "compiles": 0, "cache_hits": 0, "programs": {}}
    kinds = {"/jax/core/compile/backend_compile_duration": "backend_compile_s",
             "/jax/core/compile/jaxpr_to_mlir_module_duration": "lowering_s",
             "/jax/core/compile/jaxpr_trace_duration": "trace_s"}

    def duration(event: str, secs: float, fun_name: str = "?", **_: object) -> None:
        if event not in kinds:
            return
        if event == "/jax/core/compile/backend_compile_duration":
            acc["compile_s"] += secs
            acc["compiles"] += 1
        elif event == "/jax/core/compile/jaxpr_to_mlir_module_duration":
            acc["compile_s"] += secs
        else:
            acc["trace_s"] += secs
        name = fun_name[4:-1] if fun_name.startswith("jit(") else fun_name
        prog = acc["programs"].setdefault(name, {"backend_compile_s": 0.0, "lowering_s": 0.0, "trace_s": 0.0})
        prog[kinds[event]] += secs

    def count(event: str, **_: object) -> None:
        if event == "/jax/compilation_cache/cache_hits":
            acc["cache_hits"] += 1

    jax.monitoring.register_event_duration_secs_listener(duration)
    jax.monitoring.register_event_listener(count)
    return acc


def _fit_case(case: str, seed: int):
    """One fit of `case` on scene `seed`: the problem is built (and its targets painted) before the
    clock starts. One light + material: the demo's quad light 30 % of the scene away with one box
    occluder, 40 targets, `inverse.fit_light_and_material` from a wrong material. Three lights: a
    quad, a point and a segment light over a floor with a box (`inverse_random_scenes.random_case`,
    60 targets painted by `js.shade`), every light 30 % of the scene away at 0.5-2x its power,
    `inverse.fit_lights(..., fit=position, orientation, power)` with its defaults (global
    placement). Returns the fit, a function returning the largest light position error / scene size."""
    import jaxshadow as js

    from .inverse_random_scenes import light_errors, random_case, shifted_start

    if case == "one light + material":
        cfg = demo_configuration(occluders=True, n_points=40, seed=seed)
        col = js.shade(cfg.scene, cfg.material, cfg.points, cfg.normals, cfg.eye)
        tg = inverse.PaintedTargets(cfg.points, cfg.normals, np.asarray(col), cfg.eye)
        guess = _material_guess(cfg.material)
        size = inverse.scene_size(cfg.scene, tg)

        def fit():
            f = inverse.fit_light_and_material(cfg.start_scene, tg, guess)
            return pose_errors(np.asarray(f.scene.lights[0].vertices),
                               np.asarray(cfg.scene.lights[0].vertices))["position"] / size
    elif case == "three lights":
        c = random_case(seed, ("polygon", "point", "segment"))
        col = np.asarray(js.shade(c.true, c.material, c.points, c.normals, c.eye), np.float64)
        tg = inverse.PaintedTargets(c.points, c.normals, col, c.eye)
        size = inverse.scene_size(c.true, tg)
        start = shifted_start(c.true, 0.3 * size, seed)
        noise = 1e-4 * float(np.sqrt(np.mean(col ** 2)))  # noise-free targets: exact to rounding

        def fit():
            f = inverse.fit_lights(start, tg, c.material, warn=False, noise=noise)
            return max(light_errors(a, b)[0] for a, b in zip(f.lights, c.true.lights, strict=True)) / size
    else:
        raise ValueError(f"unknown case {case!r}")
    return fit


def _speed_child(case: str, cache_dir: str, calls: int) -> None:
    """In a fresh process: `calls` fits of `case` (scene seeds 0, 1, ...), each with its wall and
    CPU time (`time.process_time`, all threads of this process), compile and trace seconds, XLA
    compilations and persistent-cache hits; printed as JSON. `cache_dir`: JAX's persistent
    compilation cache there, every program cached ("" none)."""
    if cache_dir:
        from jaxshadow.cli import enable_compile_cache

        enable_compile_cache(cache_dir, min_compile_s=0.0)
    else:  # not the library's default cache either
        os.environ["JAXSHADOW_COMPILE_CACHE"] = "off"
    acc = _counters()
    out = []
    for seed in range(calls):
        fit = _fit_case(case, seed)
        before = {k: v for k, v in acc.items() if k != "programs"}
        acc["programs"] = {}
        w0, c0 = time.perf_counter(), time.process_time()
        err = fit()
        progs = sorted(acc["programs"].items(), key=lambda kv: -sum(kv[1].values()))
        out.append({"seed": seed, "wall_s": time.perf_counter() - w0, "cpu_s": time.process_time() - c0,
                    **{k: acc[k] - before[k] for k in before}, "programs": dict(progs),
                    "position_err_of_scene": float(err), "load": os.getloadavg()[0]})
    store = os.path.join(cache_dir, "jaxshadow-exported") if cache_dir else ""
    exported = len(os.listdir(store)) if store and os.path.isdir(store) else 0
    print(json.dumps({"calls": out, "exported_programs": exported}))


def _speed_process(case: str, cache_dir: str, calls: int, tree: str = "") -> dict:
    """`_speed_child` in a fresh process, on the checkout `tree` (default this one)."""
    import resource
    import subprocess

    root = tree or os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=root)
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    r = subprocess.run([sys.executable, "-m", "benchmarks.inverse_speed", "speed", case, cache_dir, str(calls)],
                       capture_output=True, text=True, check=True, cwd=root, env=env)
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    out = json.loads(r.stdout.strip().splitlines()[-1])
    # The whole child's CPU time (imports and every fit included): the stable figure on a loaded machine.
    out["process_cpu_s"] = r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime
    return out


def fit_speed_study(cases: tuple[str, ...] = FIT_CASES, trees: dict[str, str] | None = None) -> dict:
    """Per case (`FIT_CASES`): a fresh process fitting two scenes (the first fit compiles; the
    second shows what the first one's programs save) while it fills an empty persistent
    compilation cache, then a fresh process fitting the first scene with that cache warm. Loads
    recorded per fit. `trees`: label -> checkout to run the children on (default: this one,
    labelled "this"), alternated within each case (an A/B on a shared machine)."""
    import tempfile

    trees = trees or {"this": ""}
    out: dict = {}
    for case in cases:
        for label, tree in trees.items():
            with tempfile.TemporaryDirectory() as d:
                cold = _speed_process(case, d, 2, tree)
                warm = _speed_process(case, d, 1, tree)
            key = case if len(trees) == 1 else f"{case} [{label}]"
            out[key] = {"first": cold["calls"][0], "second": cold["calls"][1], "warm_cache_process": warm["calls"][0],
                        "process_cpu_s": {"cold (2 fits)": cold["process_cpu_s"],
                                          "warm cache (1 fit)": warm["process_cpu_s"]},
                        # programs the warm process loaded traced (`inverse._exported`; 0: no flatbuffers)
                        "exported_programs": warm.get("exported_programs", 0)}
            for k in ("first", "second", "warm_cache_process"):
                r = out[key][k]
                print(f"{key:30s} {k:20s} wall {r['wall_s']:6.1f} s  cpu {r['cpu_s']:6.1f} s  compile "
                      f"{r['compile_s']:6.1f} s ({r['compiles']} programs, {r['cache_hits']} cache hits)  "
                      f"error {r['position_err_of_scene']:.1e}  load {r['load']:.1f}", flush=True)
    return out


def fit_speed_markdown(study: dict) -> str:
    """The table of `fit_speed_study`."""
    lines = ["| case | fit | wall (s) | CPU (s) | compiling (s) | tracing (s) | XLA compilations | persistent "
             "cache hits | position error / scene | load |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    labels = {"first": "first in a process (cache empty)", "second": "second in that process (another scene)",
              "warm_cache_process": "first in a fresh process, cache warm"}
    for case, r in study.items():
        for k, label in labels.items():
            c = r[k]
            lines.append(f"| {case} | {label} | {c['wall_s']:.1f} | {c['cpu_s']:.1f} | {c['compile_s']:.1f} | "
                         f"{c['trace_s']:.1f} | {c['compiles']} | {c['cache_hits']} | "
                         f"{c['position_err_of_scene']:.1e} | {c['load']:.1f} |")
    for case, r in study.items():
        if "process_cpu_s" in r:
            lines.append("")
            lines.append(f"{case}: {r.get('exported_programs', 0)} programs stored traced (`inverse._exported`, "
                         "skips their tracing in the warm process); CPU of the whole processes (imports included) "
                         + ", ".join(f"{k} {v:.1f} s" for k, v in r["process_cpu_s"].items())
                         + "; the first fit's programs (trace + lowering + XLA compile, wall s): "
                         + ", ".join(f"`{n}` {sum(t.values()):.1f}" for n, t in
                                     list(r["first"].get("programs", {}).items())[:6]) + ".")
    return "\n".join(lines) + "\n"


def run(quick: bool) -> dict:
    jax.config.update("jax_enable_x64", True)
    from inverse._lm import FIT_COMPILER_OPTIONS

    results: dict = {"fit_compiler_options": dict(FIT_COMPILER_OPTIONS), "backend": jax.default_backend(), "targets": 48,
               "dtype": "float64", "light": {}}
    results["fit_speed"] = fit_speed_study()
    results["fit_speed_targets_s"] = {"one light + material": 10.0, "three lights": 30.0}
    if quick:  # the fit-speed study alone
        return results
    occluders, repeats = [1, 8], 3
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
    rows = []
    for case, r in results.get("fit_speed", {}).items():
        rows.append((f"{case} fit (`inverse_speed`): first in a process / second / fresh process, warm cache",
                     " / ".join(f"{r[k]['wall_s']:.1f} s ({r[k]['cpu_s']:.1f} s CPU)"
                                for k in ("first", "second", "warm_cache_process")) + f", load {r['first']['load']:.0f}"))
    light = results["light"]
    if not light:
        return rows
    occ = sorted({r["occluders"] for r in light.values() if "solver" in r})

    def cell(key: str) -> str:
        parts = [light.get(f"lm/occluders={n}/{key}") for n in occ]
        return " / ".join(f"{r['compile_s']:.1f} s + {r['solve_s'] * 1e3:.0f} ms" if r else "-" for r in parts)

    first = " / ".join(f"{light[f'lm/occluders={n}/process_first_call']['cold_process_first_call_s']:.1f} s"
                       for n in occ if f"lm/occluders={n}/process_first_call" in light)
    which = " / ".join(str(n) for n in occ)
    return [(f"light placement (8 parameters, 48 targets), `inverse.LM()`, {which} occluders: compile + solve",
             f"1 start {cell('starts=1')}; 64 starts screened to 8 (default) {cell('starts=64/refine=8')}; "
             f"a fresh process's first call {first}"), *rows]


def _markdown(results):
    if not results["light"]:
        return _fit_speed_section(results)
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
    return "\n".join(lines) + "\n" + ("\n" + _fit_speed_section(results) if "fit_speed" in results else "")


def _fit_speed_section(results: dict) -> str:
    if "fit_speed" not in results:
        return ""
    t = results.get("fit_speed_targets_s", {})
    return ("Whole fits (`fit_speed_study`; targets: one light + material <= "
            f"{t.get('one light + material', 10):.0f} s, three lights <= {t.get('three lights', 30):.0f} s "
            "including compilation, on 2 quiet cores). CPU: `time.process_time` of the process (all its "
            "threads); the machine is shared, so the load is recorded.\n\n" + fit_speed_markdown(results["fit_speed"]))


if __name__ == "__main__":
    # A fresh process's first call, for `_process_first_calls`: N_OCCLUDERS CACHE_DIR; or
    # `joint` for `_joint_process`.
    jax.config.update("jax_enable_x64", True)
    if sys.argv[1] == "joint":
        _joint_child(sys.argv[2] if len(sys.argv) > 2 else "")
    elif sys.argv[1] == "speed":
        _speed_child(sys.argv[2], sys.argv[3], int(sys.argv[4]))
    elif sys.argv[1] == "ab":
        # ab NAME LABEL=TREE ...: `fit_speed_study` alternating between checkouts ("" or "." this
        # one), written to results/ab/NAME.json and NAME.md.
        from ._suite import RESULTS, meta, write_json, write_text

        trees = dict(a.split("=", 1) for a in sys.argv[3:])
        trees = {k: "" if v in ("", ".") else os.path.abspath(v) for k, v in trees.items()}
        study = fit_speed_study(FIT_CASES, trees)
        info = meta("inverse_speed", False)
        info["command"] = "python -m benchmarks.inverse_speed " + " ".join(sys.argv[1:])
        write_json(RESULTS / "ab" / f"{sys.argv[2]}.json", {"benchmark": sys.argv[2], "meta": info,
                                                             "results": study})
        write_text(RESULTS / "ab" / f"{sys.argv[2]}.md", f"`{info['command']}` (commit {info.get('commit')}, "
                   f"{info.get('date')}, {info.get('machine')}).\n\n" + fit_speed_markdown(study))
    else:
        _child(int(sys.argv[1]), sys.argv[2])
