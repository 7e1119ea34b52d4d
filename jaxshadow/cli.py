"""The `jaxshadow` command.

- `jaxshadow report [--out DIR]`: irradiance of a built-in scene, checked point by point against
  Mitsuba 3 (needs the `mitsuba` extra), with a table and a plot.
- `jaxshadow demo [--out DIR]`: the inverse-shading demo (fit material and light to targets
  rendered by Mitsuba), when the `inverse` package provides it.
- `jaxshadow irradiance SCENE POINTS -o OUT`: batched irradiance for large point sets
  (POINTS: `.npy` of shape (N, 6) = points and normals, or `.csv` with 6 columns), in chunks
  with progress.
- `jaxshadow fit SCENE TARGETS -o FITTED`: fit material (and optionally a light) to painted
  targets.
- `jaxshadow mesh SCENE -o OUT.ply --tol 1e-3 [--receiver R]`: adaptive illumination mesh of a
  receiver polygon (exact irradiance at the vertices), as PLY or glTF.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from importlib import resources
from typing import Any

import numpy as np


def builtin_scene_path(name: str = "room") -> str:
    """Path of a built-in example scene shipped with the package (`jaxshadow/data/NAME.json`)."""
    return str(resources.files("jaxshadow") / "data" / f"{name}.json")


def _progress(i: int, n: int, t0: float, what: str) -> None:
    frac = i / max(n, 1)
    el = time.perf_counter() - t0
    eta = el / frac - el if frac > 0 else float("nan")
    bar = "#" * int(30 * frac)
    print(f"\r{what} [{bar:<30}] {100 * frac:5.1f}%  {el:6.1f}s elapsed, ~{eta:5.1f}s left", end="", file=sys.stderr)
    if i >= n:
        print(file=sys.stderr)


def report_points(n_side: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Receivers of the report: a grid on the floor (normal +z) and a row of tilted receivers."""
    xs = np.linspace(-1.5, 1.5, n_side)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    floor = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    fn = np.tile([0.0, 0.0, 1.0], (floor.shape[0], 1))
    tilt_p = np.stack([np.linspace(-1.0, 1.0, 6), np.full(6, 0.3), np.full(6, 1.2)], axis=1)
    ang = np.linspace(0.2, 1.4, 6)
    tilt_n = np.stack([np.sin(ang), np.zeros(6), np.cos(ang)], axis=1)
    return np.concatenate([floor, tilt_p]), np.concatenate([fn, tilt_n])


def cmd_report(args: argparse.Namespace) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxshadow as js
    from jaxshadow import mitsuba as jm

    scene = js.load_scene(args.scene or builtin_scene_path("room"))
    if scene.occluders is not None and not args.with_occluders:
        scene = js.Scene(scene.lights, None, scene.ambient)
    points, normals = report_points()
    print(f"scene: {len(scene.lights)} lights; {points.shape[0]} receivers; Mitsuba spp={args.spp}")
    rep = jm.quick_report(scene, points, normals, spp=args.spp, seed=args.seed)
    ours, mits, se = (np.asarray(rep[k]) for k in ("ours", "mitsuba", "stderr"))
    sig = np.abs(ours - mits) / np.maximum(se, 1e-300)
    print(f"{'#':>3} {'point':>24} {'jaxshadow E (R)':>16} {'Mitsuba E (R)':>16} {'stderr':>10} {'|d|/sigma':>9}")
    for i in range(points.shape[0]):
        p = ", ".join(f"{x:+.2f}" for x in points[i])
        print(f"{i:3d} {p:>24} {ours[i, 0]:16.6f} {mits[i, 0]:16.6f} {se[i, 0]:10.2e} {sig[i].max():9.2f}")
    worst = float(sig.max())
    print(f"max |ours - Mitsuba| / stderr over all points and channels: {worst:.2f} (pass if <= 4)")
    print(f"time: jaxshadow {rep['ours_s']:.3f} s (incl. compile), Mitsuba {rep['mitsuba_s']:.3f} s")
    os.makedirs(args.out, exist_ok=True)
    _plot_report(scene, points, ours, mits, se, os.path.join(args.out, "irradiance_report.png"))
    with open(os.path.join(args.out, "irradiance_report.json"), "w") as f:
        json.dump({k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else v) for k, v in rep.items()}, f)
    print(f"wrote {os.path.join(args.out, 'irradiance_report.png')} and irradiance_report.json")
    return 0 if worst <= 4.0 else 1


def _plot_report(scene: Any, points, ours, mits, se, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import jaxshadow as js

    n = 200
    xs = np.linspace(-2, 2, n)
    gx, gy = np.meshgrid(xs, xs, indexing="xy")
    pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    e = np.asarray(js.irradiance(scene, pts, np.tile([0.0, 0.0, 1.0], (pts.shape[0], 1))))[:, 0].reshape(n, n)
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.6))
    im = ax[0].imshow(e, extent=(-2, 2, -2, 2), origin="lower", cmap="inferno")
    fig.colorbar(im, ax=ax[0], label="irradiance E, red channel (W/m²)")
    ax[0].set_title("jaxshadow: floor irradiance (exact)")
    ax[0].plot(points[:, 0], points[:, 1], "c.", ms=4)
    ax[1].errorbar(mits[:, 0], ours[:, 0], xerr=4 * se[:, 0], fmt="o", ms=3, label="receivers (±4σ)")
    lo, hi = float(min(ours.min(), mits.min())), float(max(ours.max(), mits.max()))
    ax[1].plot([lo, hi], [lo, hi], "k--", lw=1, label="y = x")
    ax[1].set_xlabel("Mitsuba 3 Monte Carlo")
    ax[1].set_ylabel("jaxshadow")
    ax[1].set_title("agreement per receiver")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _load_points(path: str) -> tuple[np.ndarray, np.ndarray]:
    if path.endswith(".npy"):
        a = np.load(path)
    else:
        a = np.loadtxt(path, delimiter=",", ndmin=2, comments="#")
    if a.ndim != 2 or a.shape[1] != 6:
        raise SystemExit(f"{path}: expected N rows of 6 columns (px, py, pz, nx, ny, nz), got shape {a.shape}")
    return a[:, :3], a[:, 3:]


def cmd_irradiance(args: argparse.Namespace) -> int:
    import jax

    if args.float64:
        jax.config.update("jax_enable_x64", True)
    import jaxshadow as js

    scene = js.load_scene(args.scene)
    pts, nrm = _load_points(args.points)
    dt = np.float64 if args.float64 else np.float32
    pts, nrm = pts.astype(dt), nrm.astype(dt)
    n = pts.shape[0]
    out = np.empty((n, 3), dtype=dt)
    chunk = args.chunk
    t0 = time.perf_counter()
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        # pad the last chunk to the chunk size: one compilation for the whole run
        pp, nn = pts[s:e], nrm[s:e]
        if e - s < chunk and n > chunk:
            pad = chunk - (e - s)
            pp = np.concatenate([pp, np.repeat(pp[:1], pad, 0)])
            nn = np.concatenate([nn, np.repeat(nn[:1], pad, 0)])
        out[s:e] = np.asarray(js.irradiance(scene, pp, nn))[: e - s]
        _progress(e, n, t0, "irradiance")
    if args.output.endswith(".csv"):
        np.savetxt(args.output, out, delimiter=",", header="E_r,E_g,E_b")
    else:
        np.save(args.output, out)
    el = time.perf_counter() - t0
    print(f"{n} points in {el:.2f} s ({n / el:.3g} points/s, incl. compile) -> {args.output}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)  # the fits run in float64
    try:
        from inverse._demo import run_demo
    except ImportError:
        print("the inverse demo is not available in this version; running `jaxshadow report`", file=sys.stderr)
        return cmd_report(args)
    run_demo(args.out, progress=True)
    return 0


def cmd_fit(args: argparse.Namespace) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    try:
        from inverse._cli import fit_command
    except ImportError:
        raise SystemExit("`jaxshadow fit` needs the inverse package's CLI support (inverse._cli).") from None
    return int(fit_command(args.scene, args.targets, args.output, light=args.light,
                           combinatorics=args.combinatorics) or 0)


def enable_compile_cache(directory: str | None = None, min_compile_s: float = 0.2) -> str:
    """Turn on JAX's persistent compilation cache (programs that took >= `min_compile_s` to
    compile are stored on disk and reused by later processes). `directory`: default
    `$JAX_COMPILATION_CACHE_DIR`, else `~/.cache/jaxshadow/xla`. Returns the directory. The
    cache is trusted code: keep it private to the user (see JAX's documentation)."""
    import jax

    d = directory or os.environ.get("JAX_COMPILATION_CACHE_DIR") or os.path.join(
        os.path.expanduser("~"), ".cache", "jaxshadow", "xla")
    os.makedirs(d, mode=0o700, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", d)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", min_compile_s)
    return d


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="jaxshadow", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--compile-cache", default=None, metavar="DIR",
        help="JAX persistent compilation cache (default: $JAX_COMPILATION_CACHE_DIR, else "
             "~/.cache/jaxshadow/xla): a second run of the same job skips most XLA compilation",
    )
    parser.add_argument("--no-compile-cache", action="store_true", help="do not read or write the cache")
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("report", help="irradiance of a built-in scene vs Mitsuba 3, with a plot")
    p.add_argument("--scene", default=None, help="scene JSON (default: the built-in room)")
    p.add_argument("--out", default="out")
    p.add_argument("--spp", type=int, default=65536)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--with-occluders", action="store_true", help="keep the scene's occluders (shadows)")
    p.set_defaults(func=cmd_report)
    p = sub.add_parser("demo", help="inverse shading demo: recover material and light from Mitsuba targets")
    p.add_argument("--out", default="out")
    p.add_argument("--scene", default=None)
    p.add_argument("--spp", type=int, default=65536)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--with-occluders", action="store_true")
    p.set_defaults(func=cmd_demo)
    p = sub.add_parser("irradiance", help="batched irradiance for many points")
    p.add_argument("scene")
    p.add_argument("points", help=".npy (N, 6) or .csv with columns px,py,pz,nx,ny,nz")
    p.add_argument("-o", "--output", required=True, help=".npy or .csv")
    p.add_argument("--chunk", type=int, default=1 << 18)
    p.add_argument("--float64", action="store_true")
    p.set_defaults(func=cmd_irradiance)
    p = sub.add_parser("fit", help="fit material (and a light) to painted targets")
    p.add_argument("scene")
    p.add_argument("targets")
    p.add_argument("-o", "--output", required=True)
    p.add_argument("--light", type=int, default=None, help="also fit the placement of this light")
    p.add_argument("--combinatorics", choices=("auto", "device", "host"), default="auto",
                   help="with --light and occluders: where the soft-shadow kernel's combinatorics run "
                        "(auto: host on the CPU when the compiled kernel is built; see fit_light)")
    p.set_defaults(func=cmd_fit)
    from ._illumination_io import add_mesh_parser

    add_mesh_parser(sub)
    args = parser.parse_args(argv)
    if not args.no_compile_cache:
        enable_compile_cache(args.compile_cache)
    try:
        return int(args.func(args) or 0)
    except (ValueError, NotImplementedError, FileNotFoundError) as err:
        print(f"jaxshadow {args.cmd}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
