r"""The gradient oracle (`jaxshadow.testing`) on Mitsuba 3: verdicts per catalogue scene and the
measured false-alarm rate of its comparisons.

1. **Verdicts.** For every catalogue scene, Mitsuba renders the scene's window (8 x 8 pixels,
   `ReferenceScene.mitsuba_dict(camera=True)`, `llvm_ad_rgb`) with `direct` (plain AD of
   Mitsuba's C++ integrator, emitter and BSDF samples combined by MIS), `direct` with emitter
   samples only (`bsdf_samples = 0`, called `direct_emitter` here) and `direct_projective`
   (projective sampling of the visibility boundary, `sppp = 0`, guiding `none`), and
   differentiates the image with respect
   to the light's translation in forward mode (`dr.forward_to`, one pass per axis). Means and
   standard errors over `batches` seeded renders are compared with the exact pixel means
   (`ReferenceScene.image`, 8 x 8 Gauss-Legendre nodes per pixel; the |q - q/2| difference is
   the allowance `atol`) by `assert_gradient_matches` (Holm, Student t with batches - 1 degrees
   of freedom, chi-square summary, family-wise alpha = 1e-3). Reported per scene: the verdict,
   the rejected entries, the largest |t|, and the relative bias per axis,
   $\sum(\hat g - g) / \sum|g|$ over pixels and channels, with its standard error. The primal
   values of `direct` are checked the same way, and on the penumbra scene the reverse mode
   (`dr.backward` of a weighted pixel sum) too.
2. **False alarms.** (a) Values: `jaxshadow.mitsuba.reference_irradiance` (Mitsuba's emitter
   sampling and shadow rays, per-sample standard errors) at each scene's 16 receivers, `seeds`
   independent seeds per scene, each compared at alpha = 0.05. (b) Derivatives:
   `direct_emitter` on the scenes without occluders (unoccluded, grazing), where plain AD of
   emitter sampling is unbiased (the samples move with the light, nothing crosses them),
   `repeats` independent comparisons of batch estimates at alpha = 0.05. (c) The same for
   `direct_projective` on the penumbra scene (fewer repeats: it is the expensive one).
   Counts with Clopper-Pearson 95 % intervals.

Run: `.venv/bin/python -m benchmarks.gradient_oracle` (~25 min on the shared 2-core machine;
`--quick`: a smoke test of a few minutes). Writes `benchmarks/results/gradient_oracle.{json,png,md}`
(`_quick` suffix for `--quick`). `run(quick)` returns the results without writing.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time
from typing import Any

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ALPHA = 1e-3
ALPHA_FA = 0.05


def _log(*msg: Any) -> None:
    print(f"[{time.strftime('%H:%M:%S')}]", *msg, flush=True)


def _settings(quick: bool) -> dict:
    if quick:
        return dict(scenes=["unoccluded", "penumbra"], resolution=8, quadrature=4, direct_spp=64, direct_batches=8,
                    proj_spp=256, proj_batches=4, fa_seeds=20, fa_value_spp=1024, fa_grad_repeats=10,
                    fa_grad_spp=32, fa_grad_batches=8, fa_proj_repeats=3, fa_proj_spp=256, fa_proj_batches=8)
    return dict(scenes=None, resolution=8, quadrature=8, direct_spp=256, direct_batches=16, proj_spp=2048,
                proj_batches=16, fa_seeds=200, fa_value_spp=1024, fa_grad_repeats=200, fa_grad_spp=32,
                fa_grad_batches=8, fa_proj_repeats=30, fa_proj_spp=1024, fa_proj_batches=8)


def _bias(est: Any, img: Any, params: tuple[str, ...]) -> dict:
    """Relative bias sum(est - ref) / sum|ref| per parameter; its standard error treats pixels as
    independent and the three channels of a pixel as fully correlated (they share samples)."""
    out = {}
    for p in params:
        ref = img.d_irradiance[p]
        den = float(np.sum(np.abs(ref)))
        pixel_err = np.sum(est.d_irradiance_err[p], axis=-1)
        out[p] = {
            "relative_bias": float(np.sum(est.d_irradiance[p] - ref)) / den if den > 0 else None,
            "stderr": float(np.sqrt(np.sum(pixel_err**2))) / den if den > 0 else None,
            "median_stderr_over_mean_abs_derivative": float(np.median(est.d_irradiance_err[p]) / (den / ref.size)) if den > 0 else None,
        }
    return out


def _verdict(name: str, kind: str, est: Any, img: Any, params: tuple[str, ...]) -> dict:
    from jaxshadow.testing import compare

    atol = np.stack([img.d_quadrature_error[p] for p in params])
    ref = np.stack([img.d_irradiance[p] for p in params])
    scale = np.broadcast_to(np.abs(ref).reshape(len(params), -1).max(axis=1)[:, None, None, None], ref.shape)
    res = compare(np.stack([est.d_irradiance[p] for p in params]), np.stack([est.d_irradiance_err[p] for p in params]),
                  ref, alpha=ALPHA, dof=est.dof, atol=atol, scale=scale, correlated_axes=(3,), chi2_axis=0,
                  prefix=[f"d/d {p}" for p in params], what=f"{name}: {kind} dE/d(light translation)")
    values = compare(est.irradiance, est.irradiance_err, img.irradiance, alpha=ALPHA, dof=est.dof,
                     atol=img.quadrature_error, what=f"{name}: {kind} E")
    bias = _bias(est, img, params)
    # Resolution: typical standard error over typical |derivative|, all axes pooled. Above 0.5 a
    # pass says little (a bias of the derivative's own size could hide in the noise).
    resolution = float(np.median(res.stderr) / max(np.mean(np.abs(res.reference)), 1e-300))
    verdict = "flagged" if not res.passed else ("passes" if resolution < 0.5 else "passes (uninformative)")
    return {
        "verdict": verdict, "passed": bool(res.passed), "rejected": int(res.rejected.sum()), "entries": int(res.z.size),
        "max_abs_t": res.max_abs_z, "chi2": res.chi2.tolist(), "chi2_dof": res.chi2_dof.tolist(),
        "chi2_p": res.chi2_p.tolist(), "chi2_p_combined": res.chi2_p_combined, "chi2_rejected": bool(res.chi2_rejected),
        "rejected_zero_stderr": int(np.sum(res.rejected & (res.stderr == 0))),
        "bias": bias, "resolution": resolution, "report": res.report(5),
        "values_passed": bool(values.passed), "values_max_abs_t": values.max_abs_z,
        "seconds_per_batch": est.seconds, "dof": est.dof,
    }


def _false_alarms_values(names: list[str], seeds: int, spp: int) -> dict:
    from jaxshadow.mitsuba import reference_irradiance
    from jaxshadow.testing import catalogue, clopper_pearson, compare

    out: dict[str, Any] = {"alpha": ALPHA_FA, "seeds_per_scene": seeds, "spp": spp, "scenes": {}}
    total = 0
    for name in names:
        ref = catalogue[name]
        k = 0
        t0 = time.perf_counter()
        for s in range(seeds):
            est, err = reference_irradiance(ref.scene, ref.points, ref.normals, spp=spp, seed=10_000 + s)
            k += not compare(est, err, ref.irradiance, alpha=ALPHA_FA).passed
        out["scenes"][name] = {"false_alarms": k, "seconds": time.perf_counter() - t0}
        total += k
        _log(f"false alarms (values) {name}: {k}/{seeds}")
    n = seeds * len(names)
    lo, hi = clopper_pearson(total, n)
    out.update(false_alarms=total, comparisons=n, rate=total / n, interval95=[lo, hi])
    return out


def _false_alarms_gradients(name: str, kind: str, repeats: int, spp: int, batches: int, quadrature: int) -> dict:
    from jaxshadow.testing import LIGHT_TRANSLATION, catalogue, clopper_pearson, compare
    from jaxshadow.testing._mitsuba import integrator, render_estimates

    ref = catalogue[name]
    img = ref.image(8, quadrature)
    params = LIGHT_TRANSLATION
    atol = np.stack([img.d_quadrature_error[p] for p in params])
    exact = np.stack([img.d_irradiance[p] for p in params])
    integ = integrator(kind)
    k, ts = 0, []
    for r in range(repeats):
        t0 = time.perf_counter()
        est = render_estimates(ref, integ, spp=spp, batches=batches, seed=100_000 + r * batches)
        res = compare(np.stack([est.d_irradiance[p] for p in params]), np.stack([est.d_irradiance_err[p] for p in params]),
                      exact, alpha=ALPHA_FA, dof=est.dof, atol=atol, correlated_axes=(3,), chi2_axis=0,
                      scale=np.abs(exact).max(axis=(1, 2, 3))[:, None, None, None] * np.ones_like(exact))
        k += not res.passed
        ts.append(time.perf_counter() - t0)
    lo, hi = clopper_pearson(k, repeats)
    _log(f"false alarms (derivatives, {kind}) {name}: {k}/{repeats}")
    return {"scene": name, "integrator": kind, "alpha": ALPHA_FA, "repeats": repeats, "spp": spp, "batches": batches,
            "false_alarms": k, "rate": k / repeats, "interval95": [lo, hi], "seconds_per_repeat": float(np.median(ts))}


def run(quick: bool = False) -> dict:
    """Run the study (see the module docstring) and return its results as a JSON-able dict."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    from jaxshadow.testing import LIGHT_TRANSLATION, catalogue, compare
    from jaxshadow.testing._mitsuba import backward_estimates, integrator, render_estimates

    cfg = _settings(quick)
    names = cfg["scenes"] or list(catalogue)
    t_start = time.perf_counter()
    out: dict[str, Any] = {
        "what": "Mitsuba 3 light-translation derivatives of irradiance vs jaxshadow.testing's exact oracle",
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "loadavg_start": os.getloadavg(),
                    "python": sys.version.split()[0], "jax": jax.__version__, "mitsuba": mi.__version__,
                    "drjit": dr.__version__, "variant": mi.variant()},
        "quick": quick, "settings": cfg, "alpha": ALPHA, "scenes": {},
    }
    params = LIGHT_TRANSLATION
    for name in names:
        ref = catalogue[name]
        t0 = time.perf_counter()
        img = ref.image(cfg["resolution"], cfg["quadrature"])
        t_img = time.perf_counter() - t0
        row: dict[str, Any] = {
            "classes": {c: int(np.sum(ref.classes == c)) for c in ("lit", "penumbra", "umbra")},
            "image_reference_s": t_img,
            "quadrature_error_max": float(img.quadrature_error.max()),
            "d_quadrature_error_max": float(max(v.max() for v in img.d_quadrature_error.values())),
            "mean_abs_derivative": {p: float(np.abs(img.d_irradiance[p]).mean()) for p in params},
        }
        for kind, spp, batches in (("direct", cfg["direct_spp"], cfg["direct_batches"]),
                                   ("direct_emitter", cfg["direct_spp"], cfg["direct_batches"]),
                                   ("direct_projective", cfg["proj_spp"], cfg["proj_batches"])):
            est = render_estimates(ref, integrator(kind), spp=spp, batches=batches, resolution=cfg["resolution"])
            row[kind] = _verdict(name, kind, est, img, params) | {"spp": spp, "batches": batches}
            r = row[kind]
            if kind == "direct_projective" and not r["passed"] and r["rejected"] == r["rejected_zero_stderr"]:
                # Every rejection is a pixel whose batches all gave the same value (no boundary
                # sample reached it): the t test's premise fails. Retry with 4x the samples.
                est = render_estimates(ref, integrator(kind), spp=4 * spp, batches=batches, resolution=cfg["resolution"])
                r["retry_4x_spp"] = _verdict(name, kind, est, img, params) | {"spp": 4 * spp, "batches": batches}
                _log(f"{name} {kind} retry at {4 * spp} spp: {r['retry_4x_spp']['verdict']}")
            b = row[kind]["bias"]
            _log(f"{name:10s} {kind:17s} {row[kind]['verdict']:22s} rejected {row[kind]['rejected']:3d}/{row[kind]['entries']} "
                 f"max|t| {row[kind]['max_abs_t']:9.1f}  bias tx {b['light.tx']['relative_bias']:+.3f}+-{b['light.tx']['stderr']:.3f}")
        if name == "penumbra":
            w = np.random.default_rng(0).uniform(0.0, 1.0, img.irradiance.shape) / img.irradiance.size
            exact = np.array([np.sum(w * img.d_irradiance[p]) for p in params])
            row["backward"] = {}
            for kind, spp, batches in (("direct", cfg["direct_spp"], cfg["direct_batches"]),
                                       ("direct_projective", cfg["proj_spp"] // 2, cfg["proj_batches"])):
                mean, err, sec = backward_estimates(ref, integrator(kind), w, spp=spp, batches=batches)
                res = compare(mean, err, exact, alpha=ALPHA, dof=batches - 1, prefix=[f"d/d {p}" for p in params],
                              what=f"{kind} dr.backward")
                row["backward"][kind] = {"estimate": mean.tolist(), "stderr": err.tolist(), "exact": exact.tolist(),
                                         "passed": bool(res.passed), "max_abs_t": res.max_abs_z, "spp": spp,
                                         "batches": batches, "seconds_per_batch": sec}
                _log(f"{name} {kind} dr.backward: passed={res.passed} max|t|={res.max_abs_z:.1f}")
        out["scenes"][name] = row
    fa_scenes = names
    out["false_alarms_values"] = _false_alarms_values(fa_scenes, cfg["fa_seeds"], cfg["fa_value_spp"])
    out["false_alarms_gradients"] = [
        _false_alarms_gradients(n, "direct_emitter", cfg["fa_grad_repeats"], cfg["fa_grad_spp"], cfg["fa_grad_batches"], cfg["quadrature"])
        for n in ("unoccluded", "grazing") if n in names or not quick
    ] + [_false_alarms_gradients("penumbra", "direct_projective", cfg["fa_proj_repeats"], cfg["fa_proj_spp"],
                                 cfg["fa_proj_batches"], cfg["quadrature"])]
    out["total_wall_s"] = time.perf_counter() - t_start
    out["machine"]["loadavg_end"] = os.getloadavg()
    return out


def _plot(out: dict, path: str) -> None:
    import matplotlib

    from jaxshadow._core.files import atomic_write_path

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(out["scenes"])
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4.2), gridspec_kw={"width_ratios": [3, 2]})
    x = np.arange(len(names))
    kinds = (("direct", "tab:red"), ("direct_emitter", "tab:orange"), ("direct_projective", "tab:blue"))
    top = 1e5
    for i, (kind, colour) in enumerate(kinds):
        t = [max(out["scenes"][n][kind]["max_abs_t"], 1e-2) for n in names]
        flagged = [out["scenes"][n][kind]["verdict"] == "flagged" for n in names]
        bars = ax.bar(x + (i - 1) * 0.27, [min(v, top) for v in t], 0.27, color=colour, label=kind)
        for b, f, v in zip(bars, flagged, t, strict=True):
            if f:
                b.set_hatch("///")
                b.set_edgecolor("k")
            if v > top:
                ax.text(b.get_x() + b.get_width() / 2, top * 1.3, "inf" if np.isinf(v) else f"{v:.0e}", ha="center", fontsize=7)
    ax.set_yscale("log")
    ax.set_ylim(1.0, top * 10)
    ax.set_xticks(x, names, rotation=30)
    ax.set_ylabel("largest |t| over pixels, channels, axes")
    ax.set_title(f"dE/d(light translation) vs the oracle; hatched: flagged (alpha = {out['alpha']:g})", fontsize=10)
    from matplotlib.patches import Patch

    handles = [Patch(facecolor=c, label=k) for k, c in kinds] + [Patch(facecolor="white", edgecolor="k", hatch="///", label="flagged")]
    ax.legend(handles=handles, fontsize=8, loc="upper right")
    rows = [("values\n(all scenes)", out["false_alarms_values"])] + [
        (f"{g['integrator']}\n{g['scene']}", g) for g in out["false_alarms_gradients"]]
    for j, (_, g) in enumerate(rows):
        lo, hi = g["interval95"]
        bx.errorbar([j], [g["rate"]], yerr=[[g["rate"] - lo], [hi - g["rate"]]], fmt="o", capsize=4, color="k")
    bx.axhline(ALPHA_FA, color="tab:green", ls="--", label=f"stated alpha = {ALPHA_FA}")
    bx.set_xticks(range(len(rows)), [r[0] for r in rows], fontsize=8)
    bx.set_ylabel("false-alarm rate (95 % interval)")
    bx.set_title("false alarms on unbiased Mitsuba estimates")
    bx.set_xlim(-0.5, len(rows) - 0.5)
    bx.legend(fontsize=8)
    fig.tight_layout()
    atomic_write_path(path, lambda p: fig.savefig(p, dpi=110))
    plt.close(fig)


def markdown(out: dict) -> str:
    """The verdict table and the false-alarm table (generated from the JSON)."""
    lines = [
        f"Mitsuba {out['machine']['mitsuba']} (`{out['machine']['variant']}`), {out['date_utc']}"
        + (" (quick run)" if out["quick"] else "") + f"; family-wise alpha = {out['alpha']:g}.",
        "",
        "| scene | receivers lit / penumbra / umbra | `direct` | bias of dE/dx (rel.) | `direct_emitter` | bias of dE/dx (rel.) | `direct_projective` | bias of dE/dx (rel.) | largest rel. bias of `direct_projective` over x, y, z |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, row in out["scenes"].items():
        c = row["classes"]
        cells = [name, f"{c['lit']} / {c['penumbra']} / {c['umbra']}"]
        for kind in ("direct", "direct_emitter", "direct_projective"):
            r = row[kind]
            b = r["bias"]["light.tx"]
            zero = f", {r['rejected_zero_stderr']} of them with stderr 0" if r.get("rejected_zero_stderr") else ""
            chi = ", chi-square fails" if r.get("chi2_rejected") else ""
            cell = f"{r['verdict']} ({r['rejected']}/{r['entries']} rejected{zero}{chi}, max abs t {r['max_abs_t']:.3g})"
            if "retry_4x_spp" in r:
                rr = r["retry_4x_spp"]
                cell += f"; at {rr['spp']} spp: {rr['verdict']} ({rr['rejected']}/{rr['entries']} rejected, max abs t {rr['max_abs_t']:.3g})"
            cells.append(cell)
            cells.append("n/a" if b["relative_bias"] is None else f"{b['relative_bias']:+.3f} +- {b['stderr']:.3f}")
        worst = max((v for v in row["direct_projective"]["bias"].values() if v["relative_bias"] is not None),
                    key=lambda v: abs(v["relative_bias"]))
        cells.append(f"{worst['relative_bias']:+.3f} +- {worst['stderr']:.3f}")
        lines.append("| " + " | ".join(cells) + " |")
    fv = out["false_alarms_values"]
    lines += ["", "| false alarms at alpha = 0.05 | comparisons | false alarms | rate (95 % interval) |", "|---|---|---|---|",
              f"| values, `reference_irradiance`, {len(fv['scenes'])} scenes x {fv['seeds_per_scene']} seeds | {fv['comparisons']} | "
              f"{fv['false_alarms']} | {fv['rate']:.3f} ({fv['interval95'][0]:.3f} .. {fv['interval95'][1]:.3f}) |"]
    for g in out["false_alarms_gradients"]:
        lines.append(f"| derivatives, `{g['integrator']}` on {g['scene']}, {g['batches']} batches x {g['spp']} spp | "
                     f"{g['repeats']} | {g['false_alarms']} | {g['rate']:.3f} ({g['interval95'][0]:.3f} .. {g['interval95'][1]:.3f}) |")
    if "backward" in out["scenes"].get("penumbra", {}):
        bw = out["scenes"]["penumbra"]["backward"]
        lines += ["", "Reverse mode on the penumbra scene (`dr.backward` of a weighted pixel sum): "
                  + "; ".join(f"`{k}` {'passes' if v['passed'] else 'flagged'} (max abs t {v['max_abs_t']:.3g})" for k, v in bw.items()) + "."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    from jaxshadow._core.files import atomic_write

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="smoke test: two scenes, few samples")
    p.add_argument("--out", default=None, help="output stem (default benchmarks/results/gradient_oracle[_quick])")
    p.add_argument("--from-json", default=None, help="only re-render the PNG and markdown of a previous run's JSON")
    a = p.parse_args(argv)
    if a.from_json:
        with open(a.from_json) as fh:
            out = json.load(fh)
        stem = os.path.splitext(a.from_json)[0]
    else:
        out = run(a.quick)
        stem = a.out or os.path.join(HERE, "results", "gradient_oracle" + ("_quick" if a.quick else ""))
        with atomic_write(stem + ".json") as fh:
            json.dump(out, fh, indent=1)
    _plot(out, stem + ".png")
    with atomic_write(stem + ".md") as fh:
        fh.write(markdown(out))
    _log(f"wrote {stem}.json/.png/.md in {out['total_wall_s']:.0f} s")
    return out


if __name__ == "__main__":
    main()
