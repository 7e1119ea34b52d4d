# ruff: noqa: E501, B023  (tables of one-line cases; lambdas are consumed inside their loop)
"""Throughput of the unoccluded and shadowed kernels against vectorised NumPy, and how the cost
scales with points, polygon vertices and occluders.

    python -m benchmarks throughput            # ~8 min on 2 shared cores
    python -m benchmarks throughput --quick    # smoke run

Ratios are NumPy time / JAX time, measured side by side in one run (`_common.time_side_by_side`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxshadow as js
from jaxshadow._kernels.linear import linear_irradiance_kernel
from jaxshadow._kernels.polygon import form_factor_kernel

from ._common import (
    QUAD,
    SEG_A,
    SEG_B,
    chunked,
    fmt,
    jax_bytes_per_point,
    numpy_bytes_per_point,
    numpy_chunked,
    occluder_grid,
    receivers,
    regular_polygon,
    shadowed_evaluator,
    time_side_by_side,
)
from .numpy_reference import form_factor_numpy, linear_irradiance_numpy

DESCRIPTION = "throughput vs vectorised NumPy (quad, segment, shadowed), scaling with points / vertices / occluders"


def run(quick: bool) -> dict:
    jax.config.update("jax_enable_x64", True)
    if quick:
        cfg = dict(sizes=[10_000, 100_000], reps=2, numpy_max=100_000, ks=[3, 8, 32], n_k=20_000, occ=[1, 2], n_occ=100, n_shadow=0)
    else:
        cfg = dict(sizes=[10_000, 100_000, 1_000_000, 10_000_000], reps=5, numpy_max=10_000_000, ks=[3, 4, 8, 16, 32, 64], n_k=100_000, occ=[1, 2, 4, 8, 16], n_occ=2_000, n_shadow=4_000)
    thr = bench_throughput(cfg["sizes"], cfg["reps"], cfg["numpy_max"], cfg["n_shadow"], quick)
    sca = bench_scaling(thr, cfg["ks"], cfg["n_k"], cfg["occ"], cfg["n_occ"], cfg["reps"])
    return {"config": cfg, "throughput": thr, "scaling": sca}


def bench_throughput(sizes, reps, numpy_max, n_shadow, quick=False) -> list[dict]:
    rows = []
    shadow_fn, shadow_note = shadowed_evaluator()
    occ8 = occluder_grid(8)
    core_ff = jax.jit(jax.vmap(form_factor_kernel, in_axes=(0, 0, None)))
    core_lin = jax.jit(jax.vmap(linear_irradiance_kernel, in_axes=(0, 0, None, None)))
    for dtype in (np.float32, np.float64):
        dn = np.dtype(dtype).name
        quad = jnp.asarray(QUAD, dtype)
        a, b = jnp.asarray(SEG_A, dtype), jnp.asarray(SEG_B, dtype)
        scene_quad = js.Scene([js.PolygonLight(quad, 1.0)])
        scene_seg = js.Scene([js.LinearLight(a, b, 1.0)])
        for n in sizes:
            p_np, n_np = receivers(n, dtype)
            p, nr = jnp.asarray(p_np), jnp.asarray(n_np)
            fns = {
                ("quad", "js.form_factor"): lambda: chunked(lambda x, y: js.form_factor(x, y, quad))(p, nr),
                ("quad", "js.irradiance"): lambda: chunked(lambda x, y: js.irradiance(scene_quad, x, y))(p, nr),
                ("quad", "jit(vmap(form_factor_kernel))"): lambda: chunked(lambda x, y: core_ff(x, y, quad))(p, nr),
                ("segment", "js.linear_irradiance"): lambda: chunked(lambda x, y: js.linear_irradiance(x, y, a, b))(p, nr),
                ("segment", "js.irradiance"): lambda: chunked(lambda x, y: js.irradiance(scene_seg, x, y))(p, nr),
                ("segment", "jit(vmap(linear_irradiance_kernel))"): lambda: chunked(lambda x, y: core_lin(x, y, a, b))(p, nr),
            }
            if n <= numpy_max:
                fns[("quad", "NumPy")] = lambda: numpy_chunked(form_factor_numpy, p_np, n_np, QUAD.astype(dtype))
                fns[("segment", "NumPy")] = lambda: numpy_chunked(linear_irradiance_numpy, p_np, n_np, SEG_A, SEG_B)
            # Best of more calls where one call is short (below 10^5 points: 4x `reps`), for
            # JAX and NumPy alike: a best-of-5 of a ~0.3 ms call is mostly scheduler noise.
            # From 5 10^6 points one timed call after the first (NumPy takes ~15 s per call).
            t = time_side_by_side(fns, 1 if n >= 5_000_000 else (reps if n >= 100_000 else 4 * reps))
            m_small = min(n, 100_000)
            ps, ns = p[:m_small], nr[:m_small]
            mem = {} if n != min(sizes[-1], 100_000) else {
                ("quad", "jit(vmap(form_factor_kernel))"): jax_bytes_per_point(lambda x, y: core_ff(x, y, quad), ps, ns),
                ("segment", "jit(vmap(linear_irradiance_kernel))"): jax_bytes_per_point(lambda x, y: core_lin(x, y, a, b), ps, ns),
                ("quad", "NumPy"): numpy_bytes_per_point(form_factor_numpy, p_np[:m_small], n_np[:m_small], QUAD.astype(dtype)),
                ("segment", "NumPy"): numpy_bytes_per_point(linear_irradiance_numpy, p_np[:m_small], n_np[:m_small], SEG_A, SEG_B),
            }
            if shadow_fn is not None and n == sizes[0] and not quick:
                # The exact-visibility kernel is ~100x costlier per point: a smaller batch.
                ps, ns = p[:n_shadow], nr[:n_shadow]
                ts = time_side_by_side({("shadowed-8", "shadowed"): lambda: shadow_fn(ps, ns, occ8)}, min(reps, 2))
                t.update({k: {**v, "n": n_shadow} for k, v in ts.items()})
            for (light, method), r in t.items():
                rows.append(
                    dict(
                        light=light,
                        method=method,
                        dtype=dn,
                        n=r.get("n", n),
                        best_s=r["best_s"],
                        median_s=r["median_s"],
                        first_call_s=r["first_s"],
                        compile_s=max(r["first_s"] - r["median_s"], 0.0) if method != "NumPy" else 0.0,
                        points_per_s=r.get("n", n) / r["best_s"],
                        bytes_per_point=mem.get((light, method), float("nan")),
                        note=shadow_note if light.startswith("shadowed") else "",
                    )
                )
            print(f"  throughput {dn} N={n:>9}: " + ", ".join(f"{k[0]}/{k[1]} {v['best_s']:.3g}s" for k, v in t.items()), flush=True)
    # Ratios against NumPy, same light, dtype, n.
    by = {(r["light"], r["method"], r["dtype"], r["n"]): r for r in rows}
    for r in rows:
        ref = by.get((r["light"], "NumPy", r["dtype"], r["n"]))
        r["speedup_vs_numpy"] = ref["best_s"] / r["best_s"] if ref else None
    return rows


# --------------------------------------------------------------------------------------
# 2. Scaling: points, polygon vertices, occluders
# --------------------------------------------------------------------------------------


def _slope(x, y) -> float:
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


def bench_scaling(throughput, ks, n_k, occ_counts, n_occ, reps) -> dict:
    out = {}
    # Points: from the throughput run (float32 quad).
    for method in ("jit(vmap(form_factor_kernel))", "NumPy"):
        pts = sorted((r["n"], r["best_s"]) for r in throughput if r["light"] == "quad" and r["method"] == method and r["dtype"] == "float32")
        if len(pts) >= 2:
            x, y = zip(*pts, strict=True)
            out.setdefault("points", {})[method] = {"x": list(x), "seconds": list(y), "slope": _slope(x, y)}
    # Vertices.
    p_np, n_np = receivers(n_k, np.float32)
    p, nr = jnp.asarray(p_np), jnp.asarray(n_np)
    core = jax.jit(jax.vmap(form_factor_kernel, in_axes=(0, 0, None)))
    res = {"jit(vmap(form_factor_kernel))": [], "NumPy": []}
    for k in ks:
        v = regular_polygon(k).astype(np.float32)
        vj = jnp.asarray(v)
        t = time_side_by_side(
            {
                "jit(vmap(form_factor_kernel))": lambda: core(p, nr, vj),
                "NumPy": lambda: form_factor_numpy(p_np, n_np, v),
            },
            reps,
        )
        for m, r in t.items():
            res[m].append(r["best_s"])
        print(f"  scaling K={k}: " + ", ".join(f"{m} {r['best_s']:.3g}s" for m, r in t.items()), flush=True)
    out["vertices"] = {m: {"x": list(ks), "seconds": s, "slope": _slope(ks, s), "n_points": n_k} for m, s in res.items()}
    # Occluders.
    shadow_fn, note = shadowed_evaluator()
    if shadow_fn is None:
        out["occluders"] = {"skipped": note}
    else:
        p_np, n_np = receivers(n_occ, np.float32)
        p, nr = jnp.asarray(p_np), jnp.asarray(n_np)
        secs, compile_s = [], []
        for m in occ_counts:
            occ = jnp.asarray(occluder_grid(m), jnp.float32)
            t = time_side_by_side({"s": lambda: shadow_fn(p, nr, occ)}, min(reps, 2))["s"]
            secs.append(t["best_s"])
            compile_s.append(t["first_s"] - t["median_s"])
            print(f"  scaling occluders={m}: {t['best_s']:.3g}s (compile {compile_s[-1]:.3g}s)", flush=True)
        unocc = time_side_by_side({"u": lambda: core(p, nr, jnp.asarray(QUAD, jnp.float32))}, reps)["u"]["best_s"]
        out["occluders"] = {
            "shadowed": {"x": list(occ_counts), "seconds": secs, "compile_s": compile_s, "slope": _slope(occ_counts, secs), "n_points": n_occ},
            "unoccluded_seconds": unocc,
            "note": note,
        }
    return out


# --------------------------------------------------------------------------------------
# 3. Error against run time
# --------------------------------------------------------------------------------------

def plot(results: dict, path) -> None:
    import matplotlib.pyplot as plt

    from ._suite import save_figure

    throughput, scaling = results["throughput"], results["scaling"]
    panels = [k for k in ("points", "vertices", "occluders") if k in scaling and "skipped" not in scaling[k]]
    fig, axes = plt.subplots(1, 2 + len(panels), figsize=(5 * (2 + len(panels)), 4.5), squeeze=False)
    for ax, light in zip(axes[0], ("quad", "segment"), strict=False):
        for (method, dn) in sorted({(r["method"], r["dtype"]) for r in throughput if r["light"] == light}):
            pts = sorted((r["n"], r["points_per_s"]) for r in throughput if r["light"] == light and r["method"] == method and r["dtype"] == dn)
            x, y = zip(*pts, strict=True)
            ax.loglog(x, y, "o-" if dn == "float32" else "s--", label=f"{method} {dn}")
        ax.set_title(f"{light} light: throughput")
        ax.set_xlabel("points")
        ax.set_ylabel("points / s")
        ax.legend(fontsize=6)
        ax.grid(True, which="both", alpha=0.3)
    for ax, key in zip(axes[0][2:], panels, strict=True):
        for name, s in scaling[key].items():
            if isinstance(s, dict) and "x" in s:
                ax.loglog(s["x"], s["seconds"], "o-", label=f"{name}: slope {s['slope']:.2f}")
        ax.set_title(f"cost vs {key} (float32)")
        ax.set_xlabel(key)
        ax.set_ylabel("seconds")
        ax.legend(fontsize=6)
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def markdown(results: dict) -> str:
    throughput, scaling = results["throughput"], results["scaling"]
    lines = ["**Throughput** (best of the repeats; compile = first call minus median steady call; ratio = NumPy time / this time, same run):", ""]
    lines += ["| light | method | dtype | N | points/s | vs NumPy | compile (s) | bytes/point |", "|---|---|---|---:|---:|---:|---:|---:|"]
    for r in sorted(throughput, key=lambda r: (r["light"], r["dtype"], r["n"], r["method"])):
        lines.append(f"| {r['light']} | {r['method']} | {r['dtype']} | {r['n']:.0e} | {r['points_per_s']:.3g} | {fmt(r['speedup_vs_numpy'], '.1f')} | {fmt(r['compile_s'], '.2f')} | {fmt(r['bytes_per_point'], '.0f')} |")
    for note in sorted({r["note"] for r in throughput if r["note"]}):
        lines.append(f"\nShadowed rows: {note}.")
    lines += ["", "**Scaling** (log-log slope of time against the parameter, float32):", "", "| parameter | method | values | slope |", "|---|---|---|---:|"]
    for key, series in scaling.items():
        if "skipped" in series:
            lines.append(f"| {key} | - | {series['skipped']} | - |")
            continue
        for name, s in series.items():
            if isinstance(s, dict) and "x" in s:
                lines.append(f"| {key} | {name} | {s['x'][0]}..{s['x'][-1]} | {s['slope']:.2f} |")
    if "occluders" in scaling and "unoccluded_seconds" in scaling["occluders"]:
        o = scaling["occluders"]
        lines.append(f"\nOccluders: {o['note']}; N = {o['shadowed']['n_points']}; unoccluded kernel {o['unoccluded_seconds']:.3g} s, with {o['shadowed']['x'][-1]} occluders {o['shadowed']['seconds'][-1]:.3g} s; compile times {', '.join(f'{c:.1f}' for c in o['shadowed']['compile_s'])} s.")
    return "\n".join(lines)


def key_numbers(results: dict) -> list[tuple[str, str]]:
    thr = results["throughput"]

    def ratios(method: str, light: str = "quad") -> str:
        rows = sorted((r for r in thr if r["light"] == light and r["method"] == method and r["dtype"] == "float32"), key=lambda r: r["n"])
        return " / ".join(f"{r['speedup_vs_numpy']:.0f}x" for r in rows if r["speedup_vs_numpy"])

    sizes = sorted({r["n"] for r in thr if r["method"] == "NumPy" and r["light"] == "quad" and r["dtype"] == "float32"})
    size_txt = " / ".join(f"10^{int(round(np.log10(n)))}" for n in sizes)
    out = [(f"quad light, float32, vs vectorised NumPy at {size_txt} points: `js.irradiance` (checks included) / `js.form_factor` / jitted kernel",
            f"{ratios('js.irradiance')}; {ratios('js.form_factor')}; {ratios('jit(vmap(form_factor_kernel))')}")]
    shadow = {r["dtype"]: r for r in thr if r["light"].startswith("shadowed")}
    if shadow:
        n_occ = shadow[next(iter(shadow))]["light"].split("-")[1]
        out.append((f"shadows, {n_occ} occluders, `js.irradiance` (exact, culled), float32 / float64",
                    " / ".join(f"{shadow[d]['points_per_s']:.2g} points/s" for d in ("float32", "float64") if d in shadow)))
    return out
