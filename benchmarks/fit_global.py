"""fit_lights from far: success rate of the default (global placement) over random held-out-style
scenes, per start distance (10 %, 30 %, 60 % of the scene, or no start: lights given by kind
only), with the median fit time and the compile time reported apart.

Each scene is `benchmarks.inverse_random_scenes.random_case(seed, kinds)`: grey lights of the given kinds
(quad, point, segment) 1-2 m over a floor, a floating box occluder, 60 floor targets painted by
`js.shade` (noise-free); the start is the truth moved the given fraction of the scene size in a
random direction at 0.5-2x its power (`shifted_start`), or no light at all
(`fit_lights(..., kinds=[...])`). A fit succeeds when every light is within 0.5 % of the scene
size (vertices, ends, position) and every power within 1 %. One process per setting: its first
fit compiles (`compile_s`, from `jax.monitoring`), the later ones reuse the programs (a scene
whose shadow capacity differs compiles again).

`compile_study`: the first fit of fresh processes without and with JAX's persistent compilation
cache (`jaxshadow.cli.enable_compile_cache`), for a one-light + material fit
(`inverse.fit_light_and_material` on the demo scene) and for `fit_lights` from no start.

The flags (`report.quality.trusted`) are measured where wrong minima are common
(`FLAG_SETTINGS`: the local search alone from 30 % and 60 %, the default with 1 % noise): a
failure not flagged is a false negative, a recovered fit flagged a false positive.

    python -m benchmarks fit_global [--quick]    # quick: quad + point, 3 scenes per setting
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

NAME = "fit_global"
DESCRIPTION = ("inverse.fit_lights from far (global placement): success rate over random scenes, starts 10/30/60 % "
               "and none, median time, compile time")

KIND_SETS = {"quad+point": ("polygon", "point"), "quad+point+segment": ("polygon", "point", "segment")}
STARTS = ("10%", "30%", "60%", "none")
# Where wrong minima are common: the local search alone from far starts (`placement="local"`),
# and the default with 1 % noise. What the flags are measured on (false negatives: a failure
# not flagged; false positives: a recovered fit flagged).
FLAG_SETTINGS = (("quad+point", "30%", "local", 0.0), ("quad+point", "60%", "local", 0.0),
                 ("quad+point", "30%", "global", 0.01))
SEEDS = 10
QUICK_SEEDS = 3
POSITION_TOL = 0.005  # of the scene size
POWER_TOL = 0.01


def _setting(kinds: str, start: str, seeds: list[int], placement: str = "global", noise: float = 0.0) -> dict:
    """`fit_lights` on `seeds`' random scenes from `start` ("10%", ... or "none") with
    `placement`; `noise`: relative Gaussian noise on the painted colours (0: noise-free). Per
    fit: errors, success, whether the answer was flagged (`report.quality`) and why, times."""
    import jax

    jax.config.update("jax_enable_x64", True)

    import numpy as np

    import inverse
    import jaxshadow as js
    from benchmarks.fit_lights import _timing

    from .inverse_random_scenes import light_errors, random_case, shifted_start

    timing = _timing()
    runs = []
    for seed in seeds:
        case = random_case(seed, KIND_SETS[kinds])
        col = np.asarray(js.shade(case.true, case.material, case.points, case.normals, case.eye))
        if noise:
            col = col * (1.0 + noise * np.random.default_rng(1000 + seed).normal(size=col.shape))
        tg = inverse.PaintedTargets(case.points, case.normals, col, case.eye)
        size = inverse.scene_size(case.true, tg)
        c0 = timing["compile_s"]
        t0 = time.perf_counter()
        if start == "none":
            empty = js.Scene([], occluders=case.true.occluders, ambient=case.true.ambient)
            fit = inverse.fit_lights(empty, tg, case.material, kinds=list(case.kinds), warn=False)
        else:
            scene = shifted_start(case.true, float(start.rstrip("%")) / 100 * size, seed)
            fit = inverse.fit_lights(scene, tg, case.material, warn=False, placement=placement)
        fit_s = time.perf_counter() - t0
        errs = [light_errors(a, b) for a, b in zip(fit.lights, case.true.lights, strict=True)]
        pos = max(e[0] for e in errs) / size
        pw = max(e[1] for e in errs)
        runs.append({"seed": seed, "position_err_of_scene": pos, "power_err_rel": pw,
                     "success": bool(pos < POSITION_TOL and pw < POWER_TOL), "flagged": not fit.report.quality.trusted,
                     "flags": list(fit.report.quality.flags), "chi2": fit.report.quality.chi2,
                     "loss": fit.report.loss, "fit_s": fit_s, "compile_s": timing["compile_s"] - c0})
    return {"runs": runs, "load": os.getloadavg()[0]}


def _one_light_and_material(cache_dir: str) -> dict:
    """The demo's quad light (30 % of the scene away) and its material from 40 painted targets
    (`inverse.fit_light_and_material`), in this fresh process: the fit's wall time and the time
    JAX spent compiling and tracing (`jax.monitoring`), with the persistent compilation cache
    in `cache_dir` (`jaxshadow.cli.enable_compile_cache`; "" for none)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import inverse
    import jaxshadow as js
    from benchmarks.fit_lights import _timing
    from jaxshadow.cli import enable_compile_cache

    if cache_dir:
        enable_compile_cache(cache_dir, min_compile_s=0.0)
    timing = _timing()
    cfg = inverse.demo_configuration(occluders=True, n_points=40, seed=0)
    col = js.shade(cfg.scene, cfg.material, cfg.points, cfg.normals, cfg.eye)
    tg = inverse.PaintedTargets(cfg.points, cfg.normals, col, cfg.eye)
    guess = js.Material(ka=0.2, kd=0.5, ks=0.2, exponent=float(cfg.material.exponent))
    t0 = time.perf_counter()
    fit = inverse.fit_light_and_material(cfg.start_scene, tg, guess)
    fit_s = time.perf_counter() - t0
    err = inverse.pose_errors(np.asarray(fit.scene.lights[0].vertices), np.asarray(cfg.scene.lights[0].vertices))
    return {"fit_s": fit_s, **timing, "position_err_m": err["position"], "load": os.getloadavg()[0]}


def _cached_setting(cache_dir: str, kinds: str, start: str, seeds: list[int]) -> dict:
    """`_setting` with the persistent compilation cache in `cache_dir`."""
    from jaxshadow.cli import enable_compile_cache

    enable_compile_cache(cache_dir, min_compile_s=0.0)
    return _setting(kinds, start, seeds)


def _run_child(call: str) -> dict:
    code = f"import json; import benchmarks.fit_global as b; print(json.dumps(b.{call}))"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=dict(os.environ), check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def compile_study() -> dict:
    """First fits of fresh processes: without the persistent compilation cache, then twice with
    one (cold: it is filled; warm: a later process reuses it), for a one-light + material fit
    and for `fit_lights` from no start (quad + point, scene seed 1)."""
    import tempfile

    out: dict = {}
    with tempfile.TemporaryDirectory() as d:
        for label, cache in (("no cache", ""), ("cache filled", d), ("cache reused", d)):
            out[f"one light + material/{label}"] = _run_child(f"_one_light_and_material({cache!r})")
    with tempfile.TemporaryDirectory() as d:
        for label, cache in (("no cache", ""), ("cache filled", d), ("cache reused", d)):
            call = (f"_cached_setting({cache!r}, 'quad+point', 'none', [1])" if cache
                    else "_setting('quad+point', 'none', [1])")
            r = _run_child(call)["runs"][0]
            out[f"fit_lights quad+point no start/{label}"] = {"fit_s": r["fit_s"], "compile_s": r["compile_s"],
                                                             "success": r["success"]}
    return out


def _child(kinds: str, start: str, seeds: list[int], placement: str = "global", noise: float = 0.0) -> dict:
    code = (f"import json; import benchmarks.fit_global as b; "
            f"print(json.dumps(b._setting({kinds!r}, {start!r}, {seeds!r}, {placement!r}, {noise!r})))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=dict(os.environ), check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def _summary(runs: list[dict]) -> dict:
    import numpy as np

    later = runs[1:] or runs
    return {"success": sum(r["success"] for r in runs), "n": len(runs),
            "failed_flagged": sum(r["flagged"] for r in runs if not r["success"]),
            "recovered_flagged": sum(r["flagged"] for r in runs if r["success"]),
            "median_fit_s": float(np.median([r["fit_s"] for r in later])),
            "first_fit_s": runs[0]["fit_s"], "first_compile_s": runs[0]["compile_s"],
            "worst_position_err_pct": 100 * max(r["position_err_of_scene"] for r in runs)}


def run(quick: bool) -> dict:
    seeds = list(range(QUICK_SEEDS if quick else SEEDS))
    kind_sets = ("quad+point",) if quick else tuple(KIND_SETS)
    out: dict = {}
    for kinds in kind_sets:
        for start in STARTS:
            r = _child(kinds, start, seeds)
            out[f"{kinds}/start={start}"] = {**_summary(r["runs"]), **r}
    for kinds, start, placement, noise in FLAG_SETTINGS:
        r = _child(kinds, start, seeds, placement, noise)
        out[f"{kinds}/start={start}/{placement}" + (f"/noise={noise:g}" if noise else "")] = {**_summary(r["runs"]), **r}
    return {"settings": out, "compile": compile_study()}


def markdown(results: dict) -> str:
    rows = ["Success: every light within 0.5 % of the scene size and every power within 1 % (noise-free targets "
            "painted by `js.shade`). Times: the median over a setting's fits after its first (programs compiled); "
            "the first fit's time and compile time apart. Machine load in the JSON.", "",
            "| setting | recovered | failures flagged | recovered but flagged | worst position error (% of scene) | "
            "median fit (s) | first fit (s) | of which compiling (s) |", "|---|---|---|---|---|---|---|---|"]
    for name, r in results["settings"].items():
        rows.append(f"| {name} | {r['success']}/{r['n']} | {r['failed_flagged']}/{r['n'] - r['success']} | "
                    f"{r.get('recovered_flagged', 0)}/{r['success']} | "
                    f"{r['worst_position_err_pct']:.2g} | {r['median_fit_s']:.1f} | {r['first_fit_s']:.1f} | "
                    f"{r['first_compile_s']:.1f} |")
    rows += ["", "| first fit of a fresh process | fit (s) | of which compiling (s) |", "|---|---|---|"]
    for name, r in results.get("compile", {}).items():
        rows.append(f"| {name} | {r['fit_s']:.1f} | {r['compile_s']:.1f} |")
    return "\n".join(rows) + "\n"
