"""fit_lights: two quad lights and a point light with three occluders, placed jointly with their
powers from 80 painted floor targets; pose and power errors and the whole fit's time (a fresh
process per case: compile included).

The truth is `inverse._scenes.three_lights_scene` (targets painted by `js.shade`, or rendered by
Mitsuba 3 (`jaxshadow.mitsuba.reference_shade`, the "mitsuba/" case), optionally with
1 % multiplicative noise); the starts are the true lights moved a fraction of the scene size in
three directions at wrong powers (`three_lights_start`); material as given (`"fixed"`) or fitted
(`"projected"`, the first light's power held as the scale).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

NAME = "fit_lights"
DESCRIPTION = "inverse.fit_lights: 2 quad lights + 1 point light, 3 occluders: pose / power errors and time"

CASES = {
    "shift=10%/noise=0": dict(shift=0.10, noise=0.0, mode="fixed", fit="position,orientation,size,power"),
    # Started at the truth (one start, no search): the error 1 % noise alone leaves with these targets.
    "truth/noise=1%": dict(shift=0.0, noise=0.01, mode="fixed", fit="position,orientation,size,power", starts=1,
                           sweeps=1, grid=0),
    "greedy/shift=30%/noise=0": dict(shift=0.30, noise=0.0, mode="fixed", fit="position,orientation,size,power", grid=32),
    "greedy/shift=30%/noise=1%": dict(shift=0.30, noise=0.01, mode="fixed", fit="position,orientation,size,power",
                               grid=32),
    "greedy/shift=30%/noise=1%/fixed size": dict(shift=0.30, noise=0.01, mode="fixed", fit="position,orientation,power",
                                          grid=32),
    "greedy/mitsuba/shift=30%/noise=1%": dict(shift=0.30, noise=0.01, mode="fixed", fit="position,orientation,size,power",
                                       painter="mitsuba", grid=32),
    "shift=8%/projected/position+power": dict(shift=0.08, noise=0.0, mode="projected", fit="position,power"),
}
# One light from the shadow of an occluder (`inverse._scenes.one_light_shadow_case`): a
# directional light's direction, a segment light's ends, and a power budget below the truth's.
KIND_CASES = {
    "directional/shadow targets/noise=0": dict(kind="directional", noise=0.0),
    "directional/shadow targets/noise=1%": dict(kind="directional", noise=0.01),
    "segment/shadow targets/noise=0": dict(kind="segment", noise=0.0),
    "segment/shadow targets/noise=1%": dict(kind="segment", noise=0.01),
}
QUICK = ("greedy/shift=30%/noise=0", "directional/shadow targets/noise=1%", "segment/shadow targets/noise=1%")


def _painted(true, material, pts, nrm, eye, painter: str) -> tuple:
    """The hidden truth's colours at the targets: `js.shade` (`"jaxshadow"`) or Mitsuba 3's Monte
    Carlo render of the same scene (`"mitsuba"`, `jaxshadow.mitsuba.reference_shade`, 2^18
    samples per point: an independent ground truth). Returns `(colours, Monte Carlo stderr or 0)`."""
    import numpy as np

    import jaxshadow as js

    if painter == "mitsuba":
        from jaxshadow.mitsuba import reference_shade

        return reference_shade(true, material, pts, nrm, eye, spp=MITSUBA_SPP, seed=7)
    return np.asarray(js.shade(true, material, pts, nrm, eye)), np.zeros(np.shape(pts))


MITSUBA_SPP = 1 << 18


def _turn_deg(fitted, true) -> float:
    """The angle (deg) of the rotation taking the true quad's frame (first edge, normal) to the
    fitted one's, vertex i to vertex i (the fit moves the given vertices), least over the quad's
    symmetries: a half turn for a rectangle, quarter turns for a square (`pose_errors` takes
    the longer side as the axis, undefined for a square)."""
    import numpy as np

    def frame(v):
        e = v[1] - v[0]
        n = np.cross(v[1] - v[0], v[2] - v[1])
        e, n = e / np.linalg.norm(e), n / np.linalg.norm(n)
        return np.stack([e, np.cross(n, e), n], axis=1)

    sides = np.linalg.norm(np.roll(true, -1, axis=0) - true, axis=1)
    shifts = (0, 1, 2, 3) if np.allclose(sides, sides[0], rtol=1e-9) else (0, 2)
    best = 180.0
    for k in shifts:
        R = frame(np.roll(fitted, -k, axis=0)) @ frame(true).T
        best = min(best, float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))))
    return best


def _case(shift: float, noise: float, mode: str, fit: str, starts: int = 8, sweeps: int = 2,
          painter: str = "jaxshadow", **options) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import inverse
    import jaxshadow as js
    from inverse._scenes import (
        THREE_LIGHTS_EYE,
        floor_receivers,
        three_lights_scene,
        three_lights_start,
    )

    t0 = time.perf_counter()
    true = three_lights_scene()
    material = js.Material(ka=[0.3, 0.25, 0.2], kd=[0.6, 0.5, 0.4], ks=0.0, exponent=1.0)
    pts, nrm = floor_receivers()
    t_paint = time.perf_counter()
    col, mc_err = _painted(true, material, pts, nrm, THREE_LIGHTS_EYE, painter)
    t_paint = time.perf_counter() - t_paint
    col = col * (1.0 + noise * np.random.default_rng(0).normal(size=col.shape))
    targets = inverse.PaintedTargets(pts, nrm, np.maximum(col, 0.0), THREE_LIGHTS_EYE)
    size = inverse.scene_size(true, targets)
    brightness = (1.0, 1.4, 0.6) if mode == "projected" else (0.7, 1.4, 0.6)
    start = three_lights_start(true, shift * size, brightness)
    guess = material if mode == "fixed" else js.Material(ka=0.2, kd=0.5, ks=0.0, exponent=1.0)
    t1 = time.perf_counter()
    out = inverse.fit_lights(start, targets, guess, fit=tuple(fit.split(",")), starts=starts, sweeps=sweeps,
                             material_mode=mode, **options)
    fit_s = time.perf_counter() - t1
    pos, deg, size_rel, power = [], [], [], []
    for k in (0, 1):
        e = inverse.pose_errors(np.asarray(out.lights[k].vertices), np.asarray(true.lights[k].vertices))
        pos.append(e["position"])
        deg.append(_turn_deg(np.asarray(out.lights[k].vertices), np.asarray(true.lights[k].vertices)))
        size_rel.append(e["size_rel"])
        power.append(float(np.max(np.abs(np.asarray(out.lights[k].radiance) / np.asarray(true.lights[k].radiance) - 1))))
    pos.append(float(np.linalg.norm(np.asarray(out.lights[2].position) - np.asarray(true.lights[2].position))))
    power.append(float(np.max(np.abs(np.asarray(out.lights[2].intensity) / np.asarray(true.lights[2].intensity) - 1))))
    se = out.report.std_errors
    pos_se = max(se.get(f"light{k}.{c}", 0.0) for k in range(3) for c in "xyz")
    rot_se = max(se.get(f"light{k}.{c}", 0.0) for k in range(2) for c in ("rx", "ry", "rz"))
    pw = [float(out.powers[k]) for k in range(3)]
    power_se = max((se[f"light{k}.power"] / pw[k] if f"light{k}.power" in se else 0.0) for k in range(3))
    mat_err = max(float(np.max(np.abs(np.asarray(getattr(out.material, f)) - np.asarray(getattr(material, f)))))
                  for f in ("ka", "kd"))
    return {"scene_size_m": size, "position_err_pct_of_scene": 100 * max(pos) / size,
            "orientation_err_deg": max(deg), "size_err_rel": max(size_rel), "power_err_rel": max(power),
            "material_err": mat_err, "position_se_pct_of_scene": 100 * pos_se / size,
            "orientation_se_deg": float(np.degrees(rot_se)), "power_se_rel": power_se, "loss": out.report.loss, "initial_loss": out.report.initial_loss,
            "starts_per_light": starts, "starts_solved": out.report.starts_solved,
            "starts_if_multiplied": starts ** 3, "fit_s": fit_s, "painter": painter, "paint_s": t_paint,
            "mc_stderr_rel_max": float(np.max(mc_err / np.maximum(np.abs(col), 1e-12))),
            "process_s": time.perf_counter() - t0 + _IMPORT_S - t_paint}


def _kind_case(kind: str, noise: float) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import inverse
    import jaxshadow as js
    from inverse._scenes import THREE_LIGHTS_EYE, one_light_shadow_case

    t0 = time.perf_counter()
    material = js.Material(ka=0.2, kd=[0.6, 0.5, 0.4], ks=0.0, exponent=1.0)
    true, start, pts, nrm = one_light_shadow_case(kind)
    col = np.asarray(js.shade(true, material, pts, nrm, THREE_LIGHTS_EYE))
    col = col * (1.0 + noise * np.random.default_rng(0).normal(size=col.shape))
    targets = inverse.PaintedTargets(pts, nrm, np.maximum(col, 0.0), THREE_LIGHTS_EYE)
    size = inverse.scene_size(true, targets)
    fit = ("orientation", "power") if kind == "directional" else ("position", "orientation", "size", "power")
    t1 = time.perf_counter()
    out = inverse.fit_lights(start, targets, material, fit=fit, starts=4, sweeps=1)
    fit_s = time.perf_counter() - t1
    got, want = out.lights[0], true.lights[0]
    r = {"scene_size_m": size, "loss": out.report.loss, "starts_solved": out.report.starts_solved, "fit_s": fit_s,
         "process_s": time.perf_counter() - t0 + _IMPORT_S}
    if kind == "directional":
        d, d0 = np.asarray(got.direction), np.asarray(want.direction) / np.linalg.norm(want.direction)
        r["direction_err_deg"] = float(np.degrees(np.arctan2(np.linalg.norm(np.cross(d, d0)), d @ d0)))
        r["power_err_rel"] = float(np.max(np.abs(np.asarray(got.irradiance) / np.asarray(want.irradiance) - 1)))
        se = out.report.std_errors
        r["direction_se_deg"] = float(np.degrees(np.hypot(se["light0.ru"], se["light0.rv"])))
    else:
        ends = [np.linalg.norm(np.asarray(got.start) - np.asarray(want.start)),
                np.linalg.norm(np.asarray(got.end) - np.asarray(want.end))]
        r["end_err_pct_of_scene"] = float(100 * max(ends) / size)
        r["power_err_rel"] = float(np.max(np.abs(np.asarray(got.power) / np.asarray(want.power) - 1)))
    return r


_IMPORT_S = 0.0


def _child(name: str) -> dict:
    """Run one case in a fresh process (its first call: tracing and compiling included)."""
    call = f"b._case(**b.CASES[{name!r}])" if name in CASES else f"b._kind_case(**b.KIND_CASES[{name!r}])"
    code = (f"import json, time; t=time.perf_counter(); import benchmarks.fit_lights as b; "
            f"b._IMPORT_S = time.perf_counter() - t; print(json.dumps({call}))")
    env = dict(os.environ)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def run(quick: bool) -> dict:
    names = QUICK if quick else (*CASES, *KIND_CASES)
    return {"cases": {name: _child(name) for name in names if name in CASES},
            "kinds": {name: _child(name) for name in names if name in KIND_CASES}}


def markdown(results: dict) -> str:
    rows = ["| case | position error (% of scene) [std. error] | orientation (deg) [std. error] | size (rel) | "
            "power (rel) [std. error] | material | loss | starts solved (8 per light; 512 if multiplied) | "
            "fit (s, compile included) |",
            "|---|---|---|---|---|---|---|---|---|"]
    se = lambda r, k: f" [{r[k]:.2g}]" if k in r else ""  # noqa: E731
    for name, r in results["cases"].items():
        rows.append(f"| {name} | {r['position_err_pct_of_scene']:.2g}{se(r, 'position_se_pct_of_scene')} | "
                    f"{r['orientation_err_deg']:.2g}{se(r, 'orientation_se_deg')} | "
                    f"{r['size_err_rel']:.2g} | {r['power_err_rel']:.2g}{se(r, 'power_se_rel')} | "
                    f"{r['material_err']:.2g} | "
                    f"{r['loss']:.2g} | {r['starts_solved']} | {r['fit_s']:.1f} |")
    rows += ["", "| one light from an occluder's shadow (64 floor targets) | direction error (deg) | "
             "end error (% of scene) | power (rel) | loss | starts solved | fit (s, compile included) |",
             "|---|---|---|---|---|---|---|"]
    for name, r in results.get("kinds", {}).items():
        rows.append(f"| {name} | {r['direction_err_deg']:.2g} | | " if "direction_err_deg" in r else
                    f"| {name} | | {r['end_err_pct_of_scene']:.2g} | ")
        rows[-1] += f"{r['power_err_rel']:.2g} | {r['loss']:.2g} | {r['starts_solved']} | {r['fit_s']:.1f} |"
    return "\n".join(rows) + "\n"


def key_numbers(results: dict) -> list[tuple[str, str]]:
    r = results["cases"].get("greedy/mitsuba/shift=30%/noise=1%")
    if r is None:
        return []
    return [("`inverse.fit_lights`: 2 quad lights + 1 point light, 3 occluders, 80 targets, starts 30 % of the "
             "scene away (greedy placement), Mitsuba-rendered targets with 1 % noise: worst position error / power "
             "error / whole fit (compile included)",
             f"{r['position_err_pct_of_scene']:.2g} % / {r['power_err_rel']:.2g} / {r['fit_s']:.0f} s")]
