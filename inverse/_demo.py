"""`jaxshadow demo`: recover a hidden light and material from Mitsuba-rendered painted colours.

A quad light over a floor with a square occluder (when this jaxshadow has soft shadows); the
colours at 40 painted points come from Mitsuba 3 (`jaxshadow.mitsuba.reference_shade`) with
1 % noise, or from jaxshadow's own forward model when Mitsuba is not installed (said so in the
output). The light starts 30 % of the scene size away, turned, the material
at a neutral guess; `fit_light_and_material` recovers both (the lamp size is taken as known:
with k_d free, the light area and k_d trade off far from the light).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from typing import Any

import jax.numpy as jnp
import numpy as np

import jaxshadow as js

from ._demo_scene import LIGHT_H, LIGHT_W, demo_configuration, polygon_pose, pose_errors, quad
from ._diagnostics import without_invalid_lights
from ._forward import shade
from ._joint import fit_light_and_material
from ._solvers import LM
from ._targets import PaintedTargets


def _floor_image(scene: Any, material: Any, eye: np.ndarray, res: int, extent: float) -> np.ndarray:
    xs = np.linspace(-extent, extent, res)
    X, Y = np.meshgrid(xs, xs)
    pts = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    nrm = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    # A fitted light that collapsed to a degenerate one shines as no light (`_diagnostics`).
    img = np.asarray(shade(without_invalid_lights(scene), material, jnp.asarray(pts), jnp.asarray(nrm),
                           jnp.asarray(np.broadcast_to(eye, pts.shape))))
    return img.reshape(res, res, 3)


def run_demo(out_dir: str | os.PathLike, progress: bool = True, *, n_points: int = 40, starts: int = 64,
             refine: int | None = 8, spp: int = 1 << 14, seed: int = 0, image_resolution: int = 96) -> dict:
    """Run the demo; write `demo_before_after.png` and `demo_targets.json` to `out_dir`.

    **Arguments:** `out_dir`; `progress` prints the steps; `n_points` painted targets,
    `starts` multistart points screened down to the `refine` best (None: solve from all),
    `spp` Mitsuba samples per point, `seed`, `image_resolution`.

    **Returns:** a dict with `true`, `recovered`, `errors` (light position in m and in % of the
    scene size, orientation in degrees, size, material coefficients, $n$), `targets_source`
    (`"mitsuba"` or `"jaxshadow"`), `timings` (s), `png` and `targets` paths, `table` (text).
    """
    out_dir = os.fspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    say = (lambda msg: print(msg, file=sys.stdout, flush=True)) if progress else (lambda msg: None)
    timings: dict[str, float] = {}
    occl = True
    cfg = demo_configuration(occluders=occl, n_points=n_points, seed=seed, penumbra_fraction=0.3,
                             near_fraction=0.15)
    say(f"[1/4] scene: quad light, {'one occluder (soft shadow)' if occl else 'no occluder (this jaxshadow has no shadows yet)'}, "
        f"{len(cfg.points)} painted points; scene size {cfg.size:.3f} m")

    t0 = time.perf_counter()
    try:
        from jaxshadow import mitsuba as jm

        say(f"[2/4] rendering the painted colours with Mitsuba ({spp} spp per point) ...")
        est, _ = jm.reference_shade(cfg.scene, cfg.material, cfg.points, cfg.normals, cfg.eye, spp=spp, seed=seed)
        source = "mitsuba"
    except ImportError:
        say("[2/4] Mitsuba is not installed: rendering the painted colours with jaxshadow itself")
        est = np.asarray(shade(cfg.scene, cfg.material, jnp.asarray(cfg.points), jnp.asarray(cfg.normals),
                               jnp.asarray(np.broadcast_to(cfg.eye, cfg.points.shape))))
        source = "jaxshadow"
    rng = np.random.default_rng(seed + 1)
    colours = np.maximum(est * (1 + 0.01 * rng.normal(size=est.shape)), 0.0)
    # 1 % relative noise: weight each colour by 1 / colour^2 (relative least squares).
    targets = PaintedTargets(cfg.points, cfg.normals, colours, cfg.eye,
                             weights=1.0 / np.maximum(colours, 1e-6) ** 2)
    targets_path = os.path.join(out_dir, "demo_targets.json")
    with js.files.atomic_write(targets_path) as fh:
        json.dump(targets.to_dict(), fh, indent=1)
    timings["targets"] = time.perf_counter() - t0

    with_spec = bool(np.any(np.asarray(cfg.material.ks) != 0))
    guess = js.Material(ka=0.2, kd=0.5, ks=0.2 if with_spec else 0.0, exponent=10.0)
    say(f"[3/4] fitting light position, orientation and roughness ({starts} stratified starts, Levenberg-Marquardt) with "
        "k_a, k_d, k_s projected out, then the exact bounded material ...")
    t0 = time.perf_counter()
    # The lamp's size is known (Poulin §5.2.1: "illuminants have fixed definition"); with k_d
    # free, the light's area and k_d would trade off (E ~ L * area / d^2 far from the light).
    c_start = np.asarray(cfg.start_scene.lights[0].vertices).mean(axis=0)
    start_scene = js.Scene([js.PolygonLight(quad(c_start, LIGHT_W, LIGHT_H), cfg.scene.lights[0].radiance)],
                           occluders=cfg.scene.occluders, ambient=cfg.scene.ambient)
    cfg = dataclasses.replace(cfg, start_scene=start_scene)
    fit = fit_light_and_material(cfg.start_scene, targets, guess, method="projected",
                                 light_kwargs={"starts": starts, "solver": LM(refine=refine), "fit": ("position", "orientation")},
                                 material_kwargs={} if with_spec else {"bounds": ((0, 0, 0), (1, 1, 0))},
                                 progress=say)
    timings["fit"] = time.perf_counter() - t0

    true_l, start_l, fit_l = (s.lights[0].vertices for s in (cfg.scene, cfg.start_scene, fit.scene))
    e_fit = pose_errors(fit_l, true_l)
    e_start = pose_errors(start_l, true_l)
    m_true, m_fit = cfg.material, fit.material
    c_t, n_t, _, s_t = polygon_pose(true_l)
    c_f, n_f, _, s_f = polygon_pose(fit_l)
    se = fit.std_errors
    rss = lambda *names: float(np.sqrt(sum(se.get(nm, 0.0) ** 2 for nm in names)))  # noqa: E731
    se_rot = np.degrees(rss("rx", "ry", "rz"))
    rows = [
        ("light centre (m)", np.round(c_t, 4).tolist(), np.round(c_f, 4).tolist(),
         f"{e_fit['position']:.2e} m = {100 * e_fit['position'] / cfg.size:.3f} % of scene (start {100 * e_start['position'] / cfg.size:.0f} %)",
         f"{rss('x', 'y', 'z'):.2e} m"),
        ("light normal", np.round(n_t, 4).tolist(), np.round(n_f, 4).tolist(),
         f"{e_fit['normal_deg']:.3f} deg (start {e_start['normal_deg']:.1f} deg)", f"{se_rot:.3f} deg (rotation)"),
        ("light in-plane axis", "", "", f"{e_fit['axis_deg']:.3f} deg (start {e_start['axis_deg']:.1f} deg)", ""),
        ("light size (m)", np.round(s_t, 4).tolist(), np.round(s_f, 4).tolist(), f"{100 * e_fit['size_rel']:.2f} %",
         "known (not fitted)"),
    ]
    errors = {"light_position_m": e_fit["position"], "light_position_rel": e_fit["position"] / cfg.size,
              "light_orientation_deg": e_fit["orientation_deg"], "light_size_rel": e_fit["size_rel"]}
    for f in ("ka", "kd", "ks"):
        a, b = np.asarray(getattr(m_true, f)), np.asarray(getattr(m_fit, f))
        err = float(np.max(np.abs(a - b)))
        errors[f] = err
        sig = [se.get(f"{f}[{c}]", 0.0) for c in "rgb"]
        rows.append((f, np.round(a, 4).tolist(), np.round(b, 4).tolist(), f"{err:.4f} (max abs)",
                     str(np.round(sig, 4).tolist())))
    if with_spec:
        n_err = abs(float(m_fit.exponent) / float(m_true.exponent) - 1)
        errors["n_rel"] = n_err
        rows.append(("n (roughness)", float(m_true.exponent), round(float(m_fit.exponent), 3), f"{100 * n_err:.2f} %",
                     f"{100 * se.get('n', 0.0) / float(m_fit.exponent):.2f} %"))
    else:
        errors["n_rel"] = None
        rows.append(("n (roughness)", "-", "-", "diffuse material: not fitted", ""))
    errors["std_errors"] = dict(se)
    w = [max(len(str(r[i])) for r in rows) for i in range(5)]
    head = ("quantity", "true", "recovered", "error", "1 sigma (joint fit)")
    w = [max(wi, len(h)) for wi, h in zip(w, head, strict=True)]
    line = lambda r: "  ".join(str(x).ljust(wi) for x, wi in zip(r, w, strict=True))  # noqa: E731
    table = "\n".join([line(head), line(["-" * wi for wi in w])] + [line(r) for r in rows])
    say("[4/4] results (targets from " + source + "); 1 sigma: standard errors of the joint fit from its "
        "Jacobian (1 % noise), an error of 2-3 sigma is expected in a few rows:\n" + table)

    t0 = time.perf_counter()
    try:
        from matplotlib.figure import Figure
    except ImportError as err:
        raise ImportError("plots need the optional dependency 'matplotlib': `pip install 'jaxshadow[plot]'`.") from err

    ext = 1.3
    imgs = [_floor_image(s, m, cfg.eye, image_resolution, ext)
            for s, m in ((cfg.start_scene, guess), (fit.scene, m_fit), (cfg.scene, m_true))]
    vmax = max(float(np.percentile(i, 99.5)) for i in imgs)
    fig = Figure(figsize=(12, 4.3))
    axes = fig.subplots(1, 3)
    for ax, img, title in zip(axes, imgs, ("before (start)", "after (fitted)", "hidden truth"), strict=True):
        ax.imshow(np.clip(img / vmax, 0, 1), origin="lower", extent=(-ext, ext, -ext, ext))
        on_floor = np.abs(cfg.points[:, 2]) < 1e-9
        ax.scatter(cfg.points[on_floor, 0], cfg.points[on_floor, 1], s=8, c="cyan", marker="x", linewidths=0.8)
        ax.set_title(title)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"floor z=0 seen from above; x: painted points on the floor (targets: {source})")
    fig.tight_layout()
    png = os.path.join(out_dir, "demo_before_after.png")
    js.files.atomic_write_path(png, lambda tmp: fig.savefig(tmp, dpi=90))
    timings["plot"] = time.perf_counter() - t0
    say(f"wrote {png}")
    return {
        "true": {"light_vertices": np.asarray(true_l).tolist(), "material": _mat(m_true)},
        "recovered": {"light_vertices": np.asarray(fit_l).tolist(), "material": _mat(m_fit)},
        "errors": errors,
        "targets_source": source,
        "occluders": occl,
        "timings": timings,
        "png": png,
        "targets": targets_path,
        "table": table,
        "history": list(fit.history),
    }


def _mat(m: Any) -> dict:
    return {f: np.asarray(getattr(m, f), np.float64).tolist() for f in ("ka", "kd", "ks", "exponent")}
