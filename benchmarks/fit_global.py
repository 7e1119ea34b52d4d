r"""fit_lights from far: success rate of the default (global placement) over random held-out-style
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

Every fit is told its targets' noise (`fit_lights(noise=...)`): `NOISE_FREE_SIGMA` (1e-4) of
the RMS colour for the `js.shade`-painted ones (exact to rounding), the added noise (a fraction
of each colour) for the noisy ones, which the fit weights its targets by ($1/\sigma^2$) and
takes its standard errors from; the flags (`report.quality.trusted`) compare the residual
with it. A failure not flagged is a false negative, a recovered fit flagged a false positive.
The flags are also measured where wrong minima are common (`FLAG_SETTINGS`: the local search
alone from 30 % and 60 %).

The noisy settings (`NOISY_SETTINGS`: 1 % relative Gaussian noise per channel) paint their
targets with Mitsuba 3 (`benchmarks.fit_lights._painted`, Monte Carlo error kept under a fifth
of the noise) where the `mitsuba` extra is installed, else with `js.shade`; the setting's name
says which. There the reported standard errors are checked: each light's centre coordinates
(x, y, z, m) and power against the truth, `z = error / standard error`, and the fraction of
`|z| < 2` over all runs (`calibration_within_2se`; 95 % for Gaussian errors and honest
standard errors; the issue asks >= 90 %) and over the runs the library does not flag
(`calibration_unflagged_within_2se`, `calibration_unflagged_n`: every parameter's z of the runs
with `report.quality.trusted`). The second is the figure the standard errors answer for: a
flagged fit says its answer, and with it its standard errors, is not to be trusted (a wrong
basin, a competing placement, an undetermined light), and a user acts on that flag. A third,
`calibration_determined_within_2se` (`_n`), counts the parameters the report marks determined
(`report.determined`) in the runs flagged for nothing but `"undetermined"`: where one light is
weakly determined, the standard errors of the others are still reported as sound.

The statement the report makes is over its covered quantities (`report.quantities`,
`inverse._uncertainty`): each light's centre x, y, z and its emitted power (`flux`; a light's
radiance trades with its size and is not covered). `quantity_z` gives their errors over the
standard errors (`calibration_zq_within_2se`, over all runs; `calibration_zq_determined_...`,
over those marked determined) and over half their projected joint 95 % interval
(`calibration_zq_joint_within_2se`: the fraction inside the interval, the figure the report
vouches for: the issue's >= 90 %). A fit flagged with competing placements reports standard errors and
intervals widened over its rivals' spread (`inverse._uncertainty.widened`): those are what it
reports, and what these figures count.

A noisy fit succeeds (`noisy_success`) when its answer is as good as the noise allows: every
covered quantity (each light's centre coordinates and emitted power, what the report vouches
for) within `NOISY_Z` (3) reported standard errors of the truth (`quantity_z`; one with no
finite standard error is undetermined and not counted; a quad's radiance or a segment's power
per length trades with its size and is not held to its own standard error), or
the fit is flagged undetermined (`"undetermined"` in `report.quality.flags`: the targets do not
pin some parameter down, so no fit can be held to the truth there) or flagged with competing
placements (`"competing_placements"`: another placement explains the targets within the noise;
its standard errors are then widened over the rivals, `inverse._uncertainty.widened`, so
"within 3 of them" is not its test) and the truth does not
explain the targets better than the fit by more than the noise explains: with
$\chi^2 = \sum (r / \sigma)^2$ over the targets (residual over the told noise),
$\chi^2_{fit} - \chi^2_{truth} \le n + 3\sqrt{2n}$, $n$ the fitted parameters (the spread
of a $\chi^2_n$: a fit in a wrong basin, which the truth beats by far more, fails). Within
0.5 % is out of reach there by construction: 1 % noise moves an undetermined light much farther.

    python -m benchmarks fit_global [--quick]
    # quick: the three mixed lights (quad + point + segment), 3 scenes, from 30 %, 60 % and
    # none, and with 1 % noise from 30 %; no flag settings, no compile study
    python -m benchmarks.fit_global [--quick] [--seeds 0 2] [--starts 30% none] [--noisy | --no-noisy]
        [--out FILE.json]
    # a subset (the same settings, chosen seeds and starts), the table printed, the results
    # written to FILE.json; not recorded in benchmarks/results
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
FLAG_SETTINGS = (("quad+point", "30%", "local", 0.0), ("quad+point", "60%", "local", 0.0))
# 1 % relative noise, targets from Mitsuba where installed: (kinds, start).
NOISY_SETTINGS = (("quad+point", "30%"), ("quad+point+segment", "30%"), ("quad+point+segment", "none"))
NOISE = 0.01
NOISE_FREE_SIGMA = 1e-4  # the noise the fit is told for js.shade's targets, of their RMS colour
QUICK_STARTS = ("30%", "60%", "none")
SEEDS = 10
QUICK_SEEDS = 3
POSITION_TOL = 0.005  # of the scene size
POWER_TOL = 0.01
NOISY_Z = 3.0  # a noisy fit's errors within this many reported standard errors (module docstring)


def _mitsuba_available() -> bool:
    try:
        import mitsuba  # noqa: F401
    except ImportError:
        return False
    return True


def _centre(light) -> "np.ndarray":  # noqa: F821
    """A light's centre (m): a polygon's vertex mean, a segment's midpoint, a point's position."""
    import numpy as np

    import jaxshadow as js

    if isinstance(light, js.PolygonLight):
        return np.asarray(light.vertices, np.float64).mean(axis=0)
    if isinstance(light, js.LinearLight):
        return 0.5 * (np.asarray(light.start, np.float64) + np.asarray(light.end, np.float64))
    return np.asarray(light.position, np.float64)


def _emission(light) -> float:
    """A light's first emission channel (radiance, power per length or intensity)."""
    import numpy as np

    import jaxshadow as js

    if isinstance(light, js.PolygonLight):
        return float(np.asarray(light.radiance)[0])
    if isinstance(light, js.LinearLight):
        return float(np.asarray(light.power)[0])
    return float(np.asarray(light.intensity)[0])


def z_scores(fit, true_lights, idx: list[int], determined_only: bool = False) -> list[float]:
    """Errors over reported standard errors: each fitted light's centre coordinates (x, y, z) and
    power against the truth (`fit.report.std_errors`: the centre's in m, the power's in units
    of the start's emission). Parameters with no finite, positive standard error are left out;
    with `determined_only`, also those the report marks not determined (nearly undetermined)."""
    import math

    import numpy as np

    out = []
    se = fit.report.std_errors
    for j, (a, b) in enumerate(zip(fit.lights, true_lights, strict=True)):
        name = f"light{idx[j]}"
        err = _centre(a) - _centre(b)
        for c, ax in enumerate("xyz"):
            s = se.get(f"{name}.{ax}", math.inf)
            if determined_only and not fit.report.determined.get(f"{name}.{ax}", False):
                continue
            if 0 < s < math.inf:
                out.append(float(err[c] / s))
        s = se.get(f"{name}.power", math.inf)
        if determined_only and not fit.report.determined.get(f"{name}.power", False):
            continue
        if 0 < s < math.inf:
            p = float(np.asarray(fit.powers)[j])
            unit = _emission(a) / p if p > 0 else math.nan  # the emission at power 1
            if np.isfinite(unit) and unit > 0:
                out.append(float((p - _emission(b) / unit) / s))
    return out


def quantity_z(fit, true_lights, idx: list[int], determined_only: bool = False, joint: bool = False) -> list[float]:
    """Errors of the covered quantities (`fit.report.quantities`: each fitted light's centre x, y,
    z and its emitted power `flux`, `inverse._uncertainty`) over their standard errors, or with
    `joint`, over half their projected joint 95 % interval (so that |z| < 2 is inside it).
    Quantities with no finite, positive error are left out; with `determined_only`, also those
    the report marks not determined."""
    import math

    from inverse._powers import emitted_power

    out = []
    q = fit.report.quantities
    for j, (a, b) in enumerate(zip(fit.lights, true_lights, strict=True)):
        name = f"light{idx[j]}"
        truth = dict(zip("xyz", _centre(b), strict=True))
        if f"{name}.flux" in q:  # in units of the start's emitted power: the fit's emitted power over its value
            truth["flux"] = float(emitted_power(b)) * q[f"{name}.flux"].value / float(emitted_power(a))
        for key, t in truth.items():
            qv = q.get(f"{name}.{key}")
            if qv is None or (determined_only and not qv.determined):
                continue
            s = 0.5 * qv.interval if joint else qv.std_error
            if 0 < s < math.inf:
                out.append(float((qv.value - t) / s))
    return out


def noisy_verdict(z: list[float], flags: list[str], residual_fit, residual_truth, sigma, n_params: int) -> dict:
    """The noisy success criterion (module docstring): `z` the fit's z-scores (`quantity_z`),
    `flags` its quality flags, `residual_fit`, `residual_truth` `(N, 3)` (model - colours) at
    the fit and at the true lights, `sigma` the told noise (a number or `(N, 3)`), `n_params`
    the fitted parameters."""
    import numpy as np

    chi_fit = float(np.sum((residual_fit / sigma) ** 2))
    chi_truth = float(np.sum((residual_truth / sigma) ** 2))
    allowed = n_params + 3.0 * np.sqrt(2.0 * n_params)
    within = bool(len(z) and np.all(np.abs(z) <= NOISY_Z))
    undetermined = "undetermined" in flags
    competing = "competing_placements" in flags  # its standard errors widened over the rivals: not "within"
    ok = (within and not competing) or ((undetermined or competing) and chi_fit - chi_truth <= allowed)
    return {"within_3se": within, "undetermined": undetermined, "competing": competing, "chi2_sum_fit": chi_fit,
            "chi2_sum_truth": chi_truth, "chi2_allowed_excess": float(allowed), "noisy_success": bool(ok)}


def _setting(kinds: str, start: str, seeds: list[int], placement: str = "global", noise: float = 0.0,
             painter: str = "jaxshadow") -> dict:
    """`fit_lights` on `seeds`' random scenes from `start` ("10%", ... or "none") with
    `placement`; `noise`: relative Gaussian noise on the painted colours (0: noise-free);
    `painter`: `"jaxshadow"` (`js.shade`) or `"mitsuba"` (`benchmarks.fit_lights._painted`).
    Per fit: errors, success, whether the answer was flagged (`report.quality`) and why, the
    z-scores of the reported standard errors (noisy settings), times."""
    import jax

    jax.config.update("jax_enable_x64", True)

    import numpy as np

    import inverse
    import jaxshadow as js
    from benchmarks.fit_lights import _painted, _timing

    from .inverse_random_scenes import light_errors, random_case, shifted_start

    timing = _timing()
    runs = []
    for seed in seeds:
        case = random_case(seed, KIND_SETS[kinds])
        col, _ = _painted(case.true, case.material, case.points, case.normals, case.eye, painter, noise)
        col = np.asarray(col, np.float64)
        if noise:
            col = col * (1.0 + noise * np.random.default_rng(1000 + seed).normal(size=col.shape))
            sigma = noise * np.maximum(np.abs(col), 1e-6 * np.abs(col).max())
        else:
            sigma = NOISE_FREE_SIGMA * float(np.sqrt(np.mean(col ** 2)))
        tg = inverse.PaintedTargets(case.points, case.normals, col, case.eye)
        size = inverse.scene_size(case.true, tg)
        c0 = timing["compile_s"]
        t0 = time.perf_counter()
        if start == "none":
            empty = js.Scene([], occluders=case.true.occluders, ambient=case.true.ambient)
            fit = inverse.fit_lights(empty, tg, case.material, kinds=list(case.kinds), warn=False, noise=sigma)
            idx = list(range(len(case.kinds)))
        else:
            scene = shifted_start(case.true, float(start.rstrip("%")) / 100 * size, seed)
            fit = inverse.fit_lights(scene, tg, case.material, warn=False, placement=placement, noise=sigma)
            idx = list(range(len(scene.lights)))
        fit_s = time.perf_counter() - t0
        errs = [light_errors(a, b) for a, b in zip(fit.lights, case.true.lights, strict=True)]
        pos = max(e[0] for e in errs) / size
        pw = max(e[1] for e in errs)
        exact = bool(pos < POSITION_TOL and pw < POWER_TOL)
        run = {"seed": seed, "position_err_of_scene": pos, "power_err_rel": pw, "success": exact,
               "flagged": not fit.report.quality.trusted, "flags": list(fit.report.quality.flags),
               "chi2": fit.report.quality.chi2, "loss": fit.report.loss, "fit_s": fit_s,
               "compile_s": timing["compile_s"] - c0, "z": z_scores(fit, case.true.lights, idx) if noise else [],
               "z_determined": z_scores(fit, case.true.lights, idx, determined_only=True) if noise else [],
               "zq": quantity_z(fit, case.true.lights, idx) if noise else [],
               "zq_determined": quantity_z(fit, case.true.lights, idx, determined_only=True) if noise else [],
               "zq_joint": quantity_z(fit, case.true.lights, idx, joint=True) if noise else []}
        if noise:
            truth = np.asarray(js.shade(case.true, case.material, case.points, case.normals, case.eye), np.float64)
            n_par = len(fit.report.names)
            run.update(noisy_verdict(run["zq"], run["flags"], np.asarray(fit.residual, np.float64), truth - col,
                                     sigma, n_par))
            run["success"] = run["noisy_success"]
            run["within_0.5%"] = exact
        runs.append(run)
    return {"runs": runs, "load": os.getloadavg()[0], "painter": painter, "noise": noise}


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


def _run_child(call: str, cache: bool = True) -> dict:
    """`call` in a fresh process; with `cache` False the library's default persistent
    compilation cache (`~/.cache/jaxshadow`, warm from earlier runs) is turned off there."""
    code = f"import json; import benchmarks.fit_global as b; print(json.dumps(b.{call}))"
    env = dict(os.environ)
    if not cache:
        env["JAXSHADOW_COMPILE_CACHE"] = "off"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def compile_study() -> dict:
    """First fits of fresh processes: without the persistent compilation cache, then twice with
    one (cold: it is filled; warm: a later process reuses it), for a one-light + material fit
    and for `fit_lights` from no start (quad + point, scene seed 1)."""
    import tempfile

    out: dict = {}
    with tempfile.TemporaryDirectory() as d:
        for label, cache in (("no cache", ""), ("cache filled", d), ("cache reused", d)):
            out[f"one light + material/{label}"] = _run_child(f"_one_light_and_material({cache!r})", bool(cache))
    with tempfile.TemporaryDirectory() as d:
        for label, cache in (("no cache", ""), ("cache filled", d), ("cache reused", d)):
            call = (f"_cached_setting({cache!r}, 'quad+point', 'none', [1])" if cache
                    else "_setting('quad+point', 'none', [1])")
            r = _run_child(call, bool(cache))["runs"][0]
            out[f"fit_lights quad+point no start/{label}"] = {"fit_s": r["fit_s"], "compile_s": r["compile_s"],
                                                             "success": r["success"]}
    return out


def _child(kinds: str, start: str, seeds: list[int], placement: str = "global", noise: float = 0.0,
           painter: str = "jaxshadow") -> dict:
    code = (f"import json; import benchmarks.fit_global as b; "
            f"print(json.dumps(b._setting({kinds!r}, {start!r}, {seeds!r}, {placement!r}, {noise!r}, {painter!r})))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=dict(os.environ), check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def _summary(runs: list[dict]) -> dict:
    import numpy as np

    later = runs[1:] or runs
    z = np.abs(np.concatenate([np.asarray(r.get("z", []), np.float64) for r in runs]))
    calib = {"calibration_within_2se": float(np.mean(z < 2.0)), "calibration_n": int(z.size)} if z.size else {}
    zu = np.abs(np.concatenate([np.asarray(r.get("z", []), np.float64) for r in runs if not r["flagged"]]
                               + [np.zeros(0)]))
    if z.size:  # the runs the library does not flag (module docstring)
        calib.update({"calibration_unflagged_within_2se": float(np.mean(zu < 2.0)) if zu.size else float("nan"),
                      "calibration_unflagged_n": int(zu.size),
                      "unflagged_runs": sum(not r["flagged"] for r in runs)})
        # the parameters the report marks determined, in the runs flagged for nothing else
        zd = np.abs(np.concatenate([np.asarray(r.get("z_determined", []), np.float64) for r in runs
                                    if set(r["flags"]) <= {"undetermined"}] + [np.zeros(0)]))
        calib.update({"calibration_determined_within_2se": float(np.mean(zd < 2.0)) if zd.size else float("nan"),
                      "calibration_determined_n": int(zd.size)})
    for key in ("zq", "zq_determined", "zq_joint"):  # the covered quantities (module docstring)
        zq = np.abs(np.concatenate([np.asarray(r.get(key, []), np.float64) for r in runs] + [np.zeros(0)]))
        if zq.size:
            calib.update({f"calibration_{key}_within_2se": float(np.mean(zq < 2.0)), f"calibration_{key}_n": int(zq.size)})
    return {**calib, "success": sum(r["success"] for r in runs), "n": len(runs),
            "failed_flagged": sum(r["flagged"] for r in runs if not r["success"]),
            "recovered_flagged": sum(r["flagged"] for r in runs if r["success"]),
            "median_fit_s": float(np.median([r["fit_s"] for r in later])),
            "first_fit_s": runs[0]["fit_s"], "first_compile_s": runs[0]["compile_s"],
            "worst_position_err_pct": 100 * max(r["position_err_of_scene"] for r in runs)}


def run(quick: bool, seeds: list[int] | None = None, starts: tuple | None = None, noisy: bool = True) -> dict:
    """The benchmark; `seeds`, `starts` (noise-free settings) and `noisy` (the noisy settings)
    select a subset (`main`), by default everything of the quick or the full run."""
    seeds = list(range(QUICK_SEEDS if quick else SEEDS)) if seeds is None else list(seeds)
    kind_sets = ("quad+point+segment",) if quick else tuple(KIND_SETS)
    starts = (QUICK_STARTS if quick else STARTS) if starts is None else tuple(starts)
    painter = "mitsuba" if _mitsuba_available() else "jaxshadow"
    out: dict = {"loadavg_before": list(os.getloadavg())}
    settings: dict = {}
    for kinds in kind_sets:
        for start in starts:
            t0 = time.perf_counter()
            r = _child(kinds, start, seeds)
            settings[f"{kinds}/start={start}"] = {**_summary(r["runs"]), **r, "wall_s": time.perf_counter() - t0}
    for kinds, start in (NOISY_SETTINGS[-2:-1] if quick else NOISY_SETTINGS) if noisy else ():
        t0 = time.perf_counter()
        r = _child(kinds, start, seeds, "global", NOISE, painter)
        settings[f"{kinds}/start={start}/noise={NOISE:g}/{painter}"] = {**_summary(r["runs"]), **r,
                                                                          "wall_s": time.perf_counter() - t0}
    for kinds, start, placement, noise in () if quick or not noisy else FLAG_SETTINGS:
        r = _child(kinds, start, seeds, placement, noise)
        settings[f"{kinds}/start={start}/{placement}" + (f"/noise={noise:g}" if noise else "")] = {
            **_summary(r["runs"]), **r}
    out["settings"] = settings
    if not quick:
        out["compile"] = compile_study()
    out["loadavg_after"] = list(os.getloadavg())
    return out


def markdown(results: dict) -> str:
    rows = ["Success: every light within 0.5 % of the scene size and every power within 1 % (noise-free targets "
            "painted by `js.shade`). Times: the median over a setting's fits after its first (programs compiled); "
            "the first fit's time and compile time apart. Noisy settings: 1 % relative noise, targets from the named "
            "painter; success there: every light's centre coordinates and emitted power within 3 reported standard errors of "
            "the truth, or the fit flagged undetermined with the truth's chi-square not below the fit's by more than "
            "n + 3 sqrt(2n) (n fitted parameters); 'within 2 se': errors within 2 reported standard errors (centres' "
            "x, y, z and powers, over all runs); 'unflagged: within 2 se': the same over the runs the library does not "
            "flag (report.quality.trusted), the runs whose standard errors it vouches for; 'determined: within 2 se': the "
            "parameters marked determined in the runs flagged for nothing but 'undetermined'; 'covered': the quantities "
            "the standard errors cover (report.quantities: centres' x, y, z and emitted powers, all runs), within 2 "
            "standard errors, the same over those marked determined, and within their projected joint 95 % interval. "
            f"Machine load (1-minute average) before/after: {results.get('loadavg_before', ['?'])[0]} / "
            f"{results.get('loadavg_after', ['?'])[0]}.", "",
            "| setting | recovered | failures flagged | recovered but flagged | worst position error (% of scene) | "
            "within 2 se | unflagged: within 2 se | determined: within 2 se | covered: within 2 se / determined / "
            "within joint 95 % | median fit (s) | first fit (s) | of which compiling (s) |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in results["settings"].items():
        rows.append(f"| {name} | {r['success']}/{r['n']} | {r['failed_flagged']}/{r['n'] - r['success']} | "
                    f"{r.get('recovered_flagged', 0)}/{r['success']} | "
                    f"{r['worst_position_err_pct']:.2g} | "
                    + (f"{100 * r['calibration_within_2se']:.0f} % of {r['calibration_n']} | "
                       if "calibration_n" in r else "- | ")
                    + (f"{100 * r['calibration_unflagged_within_2se']:.0f} % of {r['calibration_unflagged_n']} "
                       f"({r['unflagged_runs']} runs) | " if r.get("calibration_unflagged_n") else
                       ("none unflagged | " if "calibration_unflagged_n" in r else "- | "))
                    + (f"{100 * r['calibration_determined_within_2se']:.0f} % of {r['calibration_determined_n']} | "
                       if r.get("calibration_determined_n") else "- | ")
                    + (f"{100 * r['calibration_zq_within_2se']:.0f} % of {r['calibration_zq_n']} / "
                       + (f"{100 * r['calibration_zq_determined_within_2se']:.0f} % of "
                          f"{r['calibration_zq_determined_n']} / " if r.get("calibration_zq_determined_n") else "- / ")
                       + f"{100 * r['calibration_zq_joint_within_2se']:.0f} % | "
                       if r.get("calibration_zq_n") else "- | ")
                    + f"{r['median_fit_s']:.1f} | {r['first_fit_s']:.1f} | "
                    f"{r['first_compile_s']:.1f} |")
    rows += ["", "| first fit of a fresh process | fit (s) | of which compiling (s) |", "|---|---|---|"]
    for name, r in results.get("compile", {}).items():
        rows.append(f"| {name} | {r['fit_s']:.1f} | {r['compile_s']:.1f} |")
    return "\n".join(rows) + "\n"


def main(argv: list[str] | None = None) -> int:
    """A subset of the benchmark (module docstring): the table printed, the results written to
    `--out`."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m benchmarks.fit_global", description=DESCRIPTION)
    ap.add_argument("--quick", action="store_true", help="the quick settings (three mixed lights)")
    ap.add_argument("--seeds", type=int, nargs="+", help="scene seeds (default: the run's)")
    ap.add_argument("--starts", nargs="+", choices=STARTS, help="noise-free starts (default: the run's)")
    ap.add_argument("--noisy", action=argparse.BooleanOptionalAction, default=True,
                    help="also the noisy settings (and, not quick, the flag settings)")
    ap.add_argument("--out", help="write the results (JSON) here")
    args = ap.parse_args(argv)
    res = run(args.quick, args.seeds, args.starts, args.noisy)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(res, f, indent=1)
    print(markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
