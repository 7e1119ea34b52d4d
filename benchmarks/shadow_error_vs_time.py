"""Exact soft shadows: error against run time, ours (clipping, spline equation) vs Mitsuba MC.

Scene: one quad emitter (z = 2, [0, 1]^2, facing down, radiance 1), one square occluder
(z = 1, [0.3, 0.7]^2), receivers on the plane z = 0 with normal +z, all in the penumbra
(0.02 < F / F_unoccluded < 0.98), `N` of them on a jittered grid.

Methods, each in float32 and float64 where it has a dtype:

- clipping, public: `js.irradiance(scene, points, normals) / pi` (exact clipping, `_clip.py`);
- clipping, kernel: `jaxshadow._kernels.clip.visible_form_factor` (jitted, no input checks);
- spline: `js.spline_shadow(emitter, occluder, points)` (Stark eq. 24);
- Mitsuba Monte Carlo: `jaxshadow.mitsuba.reference_irradiance` / pi at an spp sweep (time
  includes the scene conversion done in every call; Dr.Jit's kernel cache is warm).

Error: relative RMS over the receivers, `sqrt(mean((F - F_ref)^2) / mean(F_ref^2))`, against
clipping in float64; that reference is justified by its agreement with the independent spline
equation in float64 (reported as `reference_check`, ~1e-15). Time: median of `reps` calls
after a warm-up, `block_until_ready`; compile time (first call minus a warm call) apart.

"Time to reach" an error target: ours, the time of one evaluation if its error is below the
target (else not reached); Mitsuba, from fits err = C spp^(-1/2) (least squares in log space,
slope fixed) and time = a + b spp, extrapolated beyond the largest measured spp (flagged).

    python -m benchmarks shadow_error_vs_time [--quick]    # needs the mitsuba extra
"""

from __future__ import annotations

import math
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxshadow as js
from jaxshadow._kernels.clip import visible_form_factor

DESCRIPTION = "exact soft shadows (clipping, spline equation) against Mitsuba Monte Carlo: error vs run time"
EMITTER = np.array([[0.0, 0.0, 2.0], [0.0, 1.0, 2.0], [1.0, 1.0, 2.0], [1.0, 0.0, 2.0]])  # faces -z
OCCLUDER = np.array([[0.3, 0.3, 1.0], [0.7, 0.3, 1.0], [0.7, 0.7, 1.0], [0.3, 0.7, 1.0]])
TARGETS = (1e-3, 1e-6)


def penumbra_points(n: int, seed: int = 0) -> np.ndarray:
    """`n` receivers on z = 0 in the penumbra of the occluder (jittered grid, then filtered)."""
    rng = np.random.default_rng(seed)
    side = int(math.ceil(math.sqrt(6 * n)))
    g = np.linspace(-0.6, 1.6, side)
    pts = np.array([[x, y, 0.0] for x in g for y in g])
    pts[:, :2] += rng.uniform(-0.5, 0.5, (len(pts), 2)) * (g[1] - g[0])
    up = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    e = jnp.asarray(EMITTER)
    f = np.asarray(
        visible_form_factor(jnp.asarray(pts), jnp.asarray(up), e, jnp.asarray(OCCLUDER[None]))
    )
    free = np.asarray(
        visible_form_factor(jnp.asarray(pts), jnp.asarray(up), e, jnp.zeros((0, 4, 3)))
    )
    frac = f / free
    pen = np.flatnonzero((frac > 0.02) & (frac < 0.98))
    if len(pen) < n:
        raise RuntimeError(f"only {len(pen)} penumbra points, {n} wanted")
    return pts[rng.choice(pen, n, replace=False)]


def timed(fn, reps: int) -> dict:
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t0)
    med = float(np.median(ts))
    return {
        "first_s": first,
        "median_s": med,
        "min_s": float(np.min(ts)),
        "compile_s": max(first - med, 0.0),
    }


def rel_rms(x: np.ndarray, ref: np.ndarray) -> float:
    return float(np.sqrt(np.mean((np.asarray(x, np.float64) - ref) ** 2) / np.mean(ref**2)))


def ours(points: np.ndarray, reps: int) -> tuple[list[dict], np.ndarray, float]:
    n = len(points)
    up = np.tile([0.0, 0.0, 1.0], (n, 1))
    scene = js.Scene([js.PolygonLight(EMITTER, 1.0)], occluders=[OCCLUDER])
    rows = []
    ref = None
    values = {}
    for dt in (np.float64, np.float32):  # float64 first: clipping float64 is the reference
        p, nn = jnp.asarray(points, dt), jnp.asarray(up, dt)
        e, o = jnp.asarray(EMITTER, dt), jnp.asarray(OCCLUDER, dt)
        methods = {
            "clipping (js.irradiance)": lambda p=p, nn=nn: js.irradiance(scene, p, nn),
            "clipping kernel (visible_form_factor)": lambda p=p, nn=nn, e=e, o=o: (
                visible_form_factor(p, nn, e, o[None])
            ),
            "spline (js.spline_shadow)": lambda p=p, e=e, o=o: js.spline_shadow(e, o, p),
        }
        for name, fn in methods.items():
            t = timed(fn, reps)  # its first call compiles this (method, dtype)
            val = np.asarray(fn(), np.float64)
            f = val[:, 0] / np.pi if val.ndim == 2 else val
            if ref is None:
                ref = f
            values[(name, np.dtype(dt).name)] = f
            err = rel_rms(f, ref)
            note = ""
            if name == "clipping (js.irradiance)" and dt == np.float64:
                note = "the reference itself; its error is bounded by reference_check"
            rows.append(
                dict(
                    method=name, dtype=np.dtype(dt).name, knob="-", rel_rms_err=err, note=note, **t
                )
            )
            print(
                f"  {name:40s} {np.dtype(dt).name}: err {err:.3g}  "
                f"time {t['median_s'] * 1e3:.3g} ms  compile {t['compile_s']:.3g} s",
                flush=True,
            )
    check = rel_rms(values[("spline (js.spline_shadow)", "float64")], ref)
    return rows, ref, check


def mitsuba(points: np.ndarray, ref: np.ndarray, spps, reps: int) -> list[dict]:
    from jaxshadow import mitsuba as jm

    up = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    scene = js.Scene([js.PolygonLight(EMITTER, 1.0)], occluders=[OCCLUDER])
    jm.reference_irradiance(scene, points, up, spp=16, seed=99)  # warm Dr.Jit's kernel cache
    rows = []
    for spp in spps:
        if spp >= 262144:
            reps = min(reps, 2)
        ts = []
        errs = []
        stderr = []
        for r in range(reps):
            t0 = time.perf_counter()
            est, se = jm.reference_irradiance(scene, points, up, spp=spp, seed=1000 + r)
            ts.append(time.perf_counter() - t0)
            errs.append(rel_rms(est[:, 0] / np.pi, ref))
            stderr.append(float(np.sqrt(np.mean((se[:, 0] / np.pi) ** 2) / np.mean(ref**2))))
        row = dict(
            method="Mitsuba MC (reference_irradiance)",
            dtype="float32 (Dr.Jit) / float64 accumulation",
            knob=f"spp={spp}",
            spp=spp,
            rel_rms_err=float(np.sqrt(np.mean(np.square(errs)))),
            rel_rms_stderr=float(np.mean(stderr)),
            median_s=float(np.median(ts)),
            min_s=float(np.min(ts)),
            compile_s=None,
            note=f"{reps} seeds; error = RMS over seeds",
        )
        rows.append(row)
        print(
            f"  Mitsuba spp={spp:6d}: err {row['rel_rms_err']:.3g} (stderr {row['rel_rms_stderr']:.3g})  time {row['median_s']:.3g} s",
            flush=True,
        )
    return rows


def time_to_target(our_rows, mi_rows) -> dict:
    spp = np.array([r["spp"] for r in mi_rows], float)
    err = np.array([r["rel_rms_err"] for r in mi_rows])
    tm = np.array([r["median_s"] for r in mi_rows])
    log_c = float(np.mean(np.log(err) + 0.5 * np.log(spp)))  # err = C spp^-1/2
    slope_free = float(np.polyfit(np.log(spp), np.log(err), 1)[0])
    b, a = np.polyfit(spp, tm, 1)  # time = a + b spp
    a = max(float(a), float(tm.min()) if b <= 0 else float(a))
    out = {
        "mitsuba_fit": {
            "C": math.exp(log_c),
            "free_slope": slope_free,
            "a_s": float(a),
            "b_s_per_spp": float(b),
        }
    }
    for target in TARGETS:
        need = (math.exp(log_c) / target) ** 2
        t_mi = float(a + b * need)
        key = f"{target:.0e}"
        out[key] = {
            "mitsuba": {
                "spp": need,
                "seconds": t_mi,
                "extrapolated": bool(need > spp.max()),
            }
        }
        for r in our_rows:
            name = f"{r['method']} [{r['dtype']}]"
            ok = r["rel_rms_err"] <= target
            out[key][name] = {
                "seconds": r["median_s"] if ok else None,
                "ratio_ours_over_mitsuba": r["median_s"] / t_mi if ok else None,
                "reached": ok,
            }
    return out


def plot(results: dict, path) -> None:
    import matplotlib.pyplot as plt

    from ._suite import save_figure

    our_rows, mi_rows = results["ours"], results["mitsuba"]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.loglog([r["median_s"] for r in mi_rows], [r["rel_rms_err"] for r in mi_rows], "o-",
              label="Mitsuba MC (spp sweep)")
    for r in mi_rows:
        ax.annotate(str(r["spp"]), (r["median_s"], r["rel_rms_err"]), fontsize=7)
    markers = {"float32": "s", "float64": "^"}
    for r in our_rows:
        e = max(r["rel_rms_err"], 1e-17)
        ax.loglog([r["median_s"]], [e], markers[r["dtype"]], label=f"{r['method']} {r['dtype']}")
    for t in TARGETS:
        ax.axhline(t, color="grey", lw=0.5, ls="--")
    ax.set_xlabel("run time per batch (s), after compilation")
    ax.set_ylabel("relative RMS error of F")
    ax.set_title("Penumbra receivers, 1 quad light, 1 occluder")
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def run(quick: bool) -> dict:
    jax.config.update("jax_enable_x64", True)
    n = 64 if quick else 512
    reps = 3 if quick else 7
    spps = (16, 256) if quick else (16, 64, 256, 1024, 4096, 16384, 65536, 262144, 524288)
    points = penumbra_points(n)
    our_rows, ref, check = ours(points, reps)
    mi_rows = mitsuba(points, ref, spps, 2 if quick else 3)
    config = dict(points=n, reps=reps, reference="clipping float64 (js.irradiance / pi)",
                  reference_check_rel_rms_vs_spline_f64=check)
    return {"config": config, "ours": our_rows, "mitsuba": mi_rows, "time_to_target": time_to_target(our_rows, mi_rows)}


def markdown(results: dict) -> str:
    c = results["config"]
    lines = [f"{c['points']} penumbra receivers; error: relative RMS against {c['reference']} (which agrees with the "
             f"spline equation in float64 to {c['reference_check_rel_rms_vs_spline_f64']:.1e}); time: median of "
             f"{c['reps']} calls after compilation.", "",
             "| method | dtype / spp | time (s) | relative RMS error |", "|---|---|---:|---:|"]
    for r in results["ours"]:
        lines.append(f"| {r['method']} | {r['dtype']} | {r['median_s']:.3g} | {r['rel_rms_err']:.1e} |")
    for r in results["mitsuba"]:
        lines.append(f"| Mitsuba MC | {r['spp']} spp | {r['median_s']:.3g} | {r['rel_rms_err']:.1e} |")
    tt = results["time_to_target"]
    lines += ["", "Time to reach an error target (Mitsuba: from err = C spp^-1/2 and time = a + b spp fitted above; "
              "`extrapolated` beyond the largest spp measured):", "", "| target | method | time (s) | ours / Mitsuba |",
              "|---|---|---:|---:|"]
    for key in (f"{t:.0e}" for t in TARGETS):
        mi = tt[key]["mitsuba"]
        lines.append(f"| {key} | Mitsuba MC ({mi['spp']:.3g} spp{', extrapolated' if mi['extrapolated'] else ''}) | "
                     f"{mi['seconds']:.3g} | |")
        for name, r in tt[key].items():
            if name != "mitsuba" and r["reached"]:
                lines.append(f"| {key} | {name} | {r['seconds']:.3g} | {r['ratio_ours_over_mitsuba']:.1e} |")
    return "\n".join(lines)


def key_numbers(results: dict) -> list[tuple[str, str]]:
    tt = results["time_to_target"]["1e-03"]
    ours = {k: v for k, v in tt.items() if k != "mitsuba" and v["reached"] and k.startswith("clipping (js.irradiance)")}
    best = min(ours.values(), key=lambda v: v["seconds"])
    return [(f"soft shadows to 1e-3 relative RMS ({results['config']['points']} penumbra receivers), "
             "`js.irradiance` vs Mitsuba Monte Carlo",
             f"{best['seconds']:.3g} s vs {tt['mitsuba']['seconds']:.3g} s ({tt['mitsuba']['spp']:.2g} spp): "
             f"{1 / best['ratio_ours_over_mitsuba']:.0f}x faster")]
