"""One light (and its material) from painted targets: success rate of `inverse.fit_light_and_material`
and of `inverse.fit_light` (material known) over random held-out-style scenes, per start distance.

Each scene is `benchmarks.inverse_random_scenes.random_case(seed, ("polygon",))`: one grey quad
light 1-2 m over a floor, a floating box occluder, 60 floor targets (tilted normals) painted by
`js.shade` (noise-free), a coloured diffuse material. The start is the truth moved 10 %, 30 % or
60 % of the scene size in a random direction at 0.5-2x its power (`shifted_start`), or "none": a
0.3 m white square 1.5 m above the targets' centroid, facing down.

- `joint`: `inverse.fit_light_and_material(start, targets, guess)` from a grey guess
  (`ka = 0.3`, `kd = 0.5`): the light's pose and the material, the power being part of
  the material ($k_d$ times the radiance). Recovered when the light is within 0.5 % of the scene
  size (`light_errors`: every vertex) and $k_a$ and $k_d \\cdot L$ within 1 % per channel.
- `fixed`: `inverse.fit_light(start, targets, material)` with the true material and the true
  radiance (pose only). Recovered when the light is within 0.5 % of the scene size.

Every fit's parameters (`report.theta`), loss and errors are kept, so two versions of the code
can be compared fit by fit (`compare(a, b)`: the largest relative difference of the recovered
parameters where both converged, and the success counts).

    python -m benchmarks fit_light [--quick]
    # quick: 3 scenes; full: 8
"""

from __future__ import annotations

import os
import time

NAME = "fit_light"
DESCRIPTION = "inverse.fit_light (+ material) from 10/30/60 % and no start: success over random one-light scenes"

STARTS = ("10%", "30%", "60%", "none")
FIXED_STARTS = ("10%", "30%")
SEEDS = 8
QUICK_SEEDS = 3
POSITION_TOL = 0.005  # of the scene size
MATERIAL_TOL = 0.01
N_TARGETS = 60


def _none_start(case, size: float):
    """A 0.3 m white square 1.5 m above the targets' centroid, facing down (no guess)."""
    import numpy as np

    import jaxshadow as js

    c = np.asarray(case.points, np.float64).mean(axis=0) + [0.0, 0.0, 1.5]
    h = 0.15
    v = c + np.array([[-h, -h, 0.0], [-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0]])  # normal -z
    return js.Scene([js.PolygonLight(v, [1.0, 1.0, 1.0])], occluders=case.true.occluders, ambient=case.true.ambient)


def _one(seed: int, start: str, mode: str) -> dict:
    import numpy as np

    import inverse
    import jaxshadow as js

    from .inverse_random_scenes import light_errors, random_case, shifted_start

    case = random_case(seed, ("polygon",), n_targets=N_TARGETS)
    col = np.asarray(js.shade(case.true, case.material, case.points, case.normals, case.eye), np.float64)
    tg = inverse.PaintedTargets(case.points, case.normals, col, case.eye)
    size = inverse.scene_size(case.true, tg)
    if start == "none":
        scene = _none_start(case, size)
    else:
        scene = shifted_start(case.true, float(start.rstrip("%")) / 100 * size, seed)
    t0 = time.perf_counter()
    if mode == "joint":
        guess = js.Material(ka=0.3, kd=0.5, ks=0.0, exponent=1.0)
        fit = inverse.fit_light_and_material(scene, tg, guess, light_kwargs={"warn": False})
        light, material, lf = fit.scene.lights[0], fit.material, fit.report[0]
    else:
        true_light = case.true.lights[0]
        scene = js.Scene([js.PolygonLight(scene.lights[0].vertices, true_light.radiance)],
                         occluders=scene.occluders, ambient=scene.ambient)
        lf = inverse.fit_light(scene, tg, case.material, warn=False)
        light, material = lf.light, case.material
        lf = lf.report
    fit_s = time.perf_counter() - t0
    pos = light_errors(light, case.true.lights[0])[0] / size
    kd_l = np.asarray(material.kd, np.float64) * np.asarray(light.radiance, np.float64)
    kd_l0 = np.asarray(case.material.kd, np.float64) * np.asarray(case.true.lights[0].radiance, np.float64)
    mat = float(max(np.max(np.abs(kd_l / kd_l0 - 1)),
                    np.max(np.abs(np.asarray(material.ka, np.float64) / np.asarray(case.material.ka) - 1))))
    ok = bool(pos < POSITION_TOL and (mode == "fixed" or mat < MATERIAL_TOL))
    return {"seed": seed, "start": start, "mode": mode, "position_err_of_scene": pos, "material_err_rel": mat,
            "success": ok, "loss": float(lf.loss), "theta": [float(x) for x in np.asarray(lf.theta)],
            "converged": bool(np.asarray(lf.converged)[lf.best_start]), "trusted": bool(lf.quality.trusted),
            "vertices": np.asarray(light.vertices, np.float64).tolist(),
            "kd": np.asarray(material.kd, np.float64).tolist(), "ka": np.asarray(material.ka, np.float64).tolist(),
            "fit_s": fit_s}


def run(quick: bool) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)

    seeds = list(range(QUICK_SEEDS if quick else SEEDS))
    runs = []
    for mode, starts in (("joint", STARTS), ("fixed", FIXED_STARTS)):
        for start in starts:
            for seed in seeds:
                runs.append(_one(seed, start, mode))
    summary = {}
    for r in runs:
        key = f"{r['mode']}/{r['start']}"
        s = summary.setdefault(key, {"recovered": 0, "fits": 0, "fit_s": []})
        s["recovered"] += int(r["success"])
        s["fits"] += 1
        s["fit_s"].append(r["fit_s"])
    return {"runs": runs, "summary": summary, "load": os.getloadavg()[0]}


def compare(a: dict, b: dict) -> dict:
    """Fit by fit: the largest relative difference of the fitted light's vertices and material
    (of the scene size, and relative) between two results of `run`, over the fits both
    recovered, and the success counts of each."""
    import numpy as np

    out: dict = {"pairs": 0, "max_vertex_diff_of_size": 0.0, "max_material_diff_rel": 0.0,
                 "recovered_a": 0, "recovered_b": 0, "differ": []}
    for ra, rb in zip(a["runs"], b["runs"], strict=True):
        assert (ra["seed"], ra["start"], ra["mode"]) == (rb["seed"], rb["start"], rb["mode"])
        out["recovered_a"] += int(ra["success"])
        out["recovered_b"] += int(rb["success"])
        if ra["success"] != rb["success"]:
            out["differ"].append((ra["mode"], ra["start"], ra["seed"]))
        if ra["success"] and rb["success"]:
            out["pairs"] += 1
            dv = float(np.max(np.abs(np.asarray(ra["vertices"]) - np.asarray(rb["vertices"]))))
            dm = float(np.max(np.abs(np.asarray(ra["kd"]) / np.asarray(rb["kd"]) - 1)))
            out["max_vertex_diff_of_size"] = max(out["max_vertex_diff_of_size"], dv)
            out["max_material_diff_rel"] = max(out["max_material_diff_rel"], dm)
    return out


def markdown(results: dict) -> str:
    lines = ["| fit | start | recovered | median fit time (s) |", "|---|---|---:|---:|"]
    for key, s in results["summary"].items():
        mode, start = key.split("/")
        t = sorted(s["fit_s"])[len(s["fit_s"]) // 2]
        lines.append(f"| {mode} | {start} | {s['recovered']}/{s['fits']} | {t:.1f} |")
    lines.append(f"\nMachine load at the end: {results['load']:.1f}.")
    return "\n".join(lines)
