"""fit_lights from far: success rate of the default (global placement) over random held-out-style
scenes, per start distance (10 %, 30 %, 60 % of the scene, or no start: lights given by kind
only), with the median fit time and the compile time reported apart.

Each scene is `inverse._random_scenes.random_case(seed, kinds)`: grey lights of the given kinds
(quad, point, segment) 1-2 m over a floor, a floating box occluder, 60 floor targets painted by
`js.shade` (noise-free); the start is the truth moved the given fraction of the scene size in a
random direction at 0.5-2x its power (`shifted_start`), or no light at all
(`fit_lights(..., kinds=[...])`). A fit succeeds when every light is within 0.5 % of the scene
size (vertices, ends, position) and every power within 1 %. One process per setting: its first
fit compiles (`compile_s`, from `jax.monitoring`), the later ones reuse the programs.
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
SEEDS = 10
QUICK_SEEDS = 3
POSITION_TOL = 0.005  # of the scene size
POWER_TOL = 0.01


def _setting(kinds: str, start: str, seeds: list[int]) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)

    import inverse
    import jaxshadow as js
    from benchmarks.fit_lights import _timing
    from inverse._random_scenes import light_errors, random_case, shifted_start

    timing = _timing()
    runs = []
    for seed in seeds:
        case = random_case(seed, KIND_SETS[kinds])
        col = js.shade(case.true, case.material, case.points, case.normals, case.eye)
        tg = inverse.PaintedTargets(case.points, case.normals, col, case.eye)
        size = inverse.scene_size(case.true, tg)
        c0 = timing["compile_s"]
        t0 = time.perf_counter()
        if start == "none":
            empty = js.Scene([], occluders=case.true.occluders, ambient=case.true.ambient)
            fit = inverse.fit_lights(empty, tg, case.material, kinds=list(case.kinds), warn=False)
        else:
            scene = shifted_start(case.true, float(start.rstrip("%")) / 100 * size, seed)
            fit = inverse.fit_lights(scene, tg, case.material, warn=False)
        fit_s = time.perf_counter() - t0
        errs = [light_errors(a, b) for a, b in zip(fit.lights, case.true.lights, strict=True)]
        pos = max(e[0] for e in errs) / size
        pw = max(e[1] for e in errs)
        runs.append({"seed": seed, "position_err_of_scene": pos, "power_err_rel": pw,
                     "success": bool(pos < POSITION_TOL and pw < POWER_TOL), "flagged": not fit.report.quality.trusted,
                     "loss": fit.report.loss, "fit_s": fit_s, "compile_s": timing["compile_s"] - c0})
    return {"runs": runs, "load": os.getloadavg()[0]}


def _child(kinds: str, start: str, seeds: list[int]) -> dict:
    code = (f"import json; import benchmarks.fit_global as b; "
            f"print(json.dumps(b._setting({kinds!r}, {start!r}, {seeds!r})))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=dict(os.environ), check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def _summary(runs: list[dict]) -> dict:
    import numpy as np

    later = runs[1:] or runs
    return {"success": sum(r["success"] for r in runs), "n": len(runs),
            "failed_flagged": sum(r["flagged"] for r in runs if not r["success"]),
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
    return {"settings": out}


def markdown(results: dict) -> str:
    rows = ["Success: every light within 0.5 % of the scene size and every power within 1 % (noise-free targets "
            "painted by `js.shade`). Times: the median over a setting's fits after its first (programs compiled); "
            "the first fit's time and compile time apart. Machine load in the JSON.", "",
            "| setting | recovered | failures flagged | worst position error (% of scene) | median fit (s) | "
            "first fit (s) | of which compiling (s) |", "|---|---|---|---|---|---|---|"]
    for name, r in results["settings"].items():
        rows.append(f"| {name} | {r['success']}/{r['n']} | {r['failed_flagged']}/{r['n'] - r['success']} | "
                    f"{r['worst_position_err_pct']:.2g} | {r['median_fit_s']:.1f} | {r['first_fit_s']:.1f} | "
                    f"{r['first_compile_s']:.1f} |")
    return "\n".join(rows) + "\n"
