"""The `jaxshadow` command.

- `jaxshadow --version`
- `jaxshadow irradiance SCENE POINTS -o OUT`: irradiance at many receivers, in chunks with
  progress. SCENE: scene JSON or Mitsuba XML. POINTS: `.csv` (header row naming the columns
  `px,py,pz,nx,ny,nz`), `.npy` `(N, 6)`, `.npz` (`points`, `normals`), or a mesh (`.ply`,
  `.obj`, `.glb`/`.gltf`, `.stl`, `.off`: receivers at its vertices or, with `--at faces`, its
  face centres). OUT: `.npy`, `.npz`, `.csv` (columns `px..nz,r,g,b`; from a `.csv` the
  receiver columns are the input's own text, not formatted again) or, for mesh receivers,
  `.ply` (vertex colours plus float properties `irradiance_r/g/b`).
- `jaxshadow render SCENE.xml -o IMAGE.exr -o IMAGE.png [--spp-compare N]`: an image from the
  scene's camera (Mitsuba finds what each pixel sees, jaxshadow shades it exactly).
- `jaxshadow report [--out DIR]`: irradiance of a built-in scene, checked point by point against
  Mitsuba 3, with a table and a plot.
- `jaxshadow fit SCENE TARGETS -o FITTED` and `jaxshadow demo`: the solvers' commands, provided
  by the `inverse` package (entry-point group `jaxshadow.commands`).
- `jaxshadow mesh SCENE -o OUT.ply --tol 1e-3 [--receiver R]`: adaptive illumination mesh of a
  receiver polygon (exact irradiance at the vertices), as PLY or glTF.
- `jaxshadow bake SCENE -o OUT.glb|.ply [--tol 1e-3] [--lights I,J] [--workers N | --scheduler
  ADDRESS]`: every receiving surface of a scene meshed (`jaxshadow.bake`), seam-free, exact
  irradiance per light at the vertices; per-chunk results in a work directory (resume).

Conventions: every output path is used exactly as given and its format follows its extension;
an output that is an input file (or an input scene's arrays file) is refused; inputs, outputs
and options are checked before any computation; outputs are written to a
temporary file renamed into place, so an interrupted run leaves no partial file. Exit codes:
0 success, 1 internal error (a bug: please report it), 2 usage error or bad input, 3 `report`
found a disagreement with Mitsuba beyond 4 standard errors.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback
from collections.abc import Callable
from importlib import metadata
from typing import Any

import numpy as np

from .common import (
    _USER_ERRORS,
    ENTRY_POINT_GROUP,
    EXIT_CHECK,
    EXIT_INTERNAL,
    EXIT_OK,
    EXIT_USAGE,
    INPUT_ARGUMENTS,
    OUTPUT_ARGUMENTS,
    PLUGIN_REQUIRES,
    SCENE_EXTS,
    Progress,
    _paths,
    _say,
    add_io_arguments,
    builtin_scene_path,
    check_directory,
    check_input,
    check_output,
    check_outputs_are_not_inputs,
    check_requirements,
    non_negative_float,
    positive_int,
    read_scene,
    scene_up,
)


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
    out_dir = check_directory(args.out, "--out", create=True)
    scene_path = args.scene or builtin_scene_path("room")
    if args.scene:
        check_input(args.scene, (".json",), "--scene")
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxshadow as js
    from jaxshadow import mitsuba as jm

    from .._core.files import atomic_write, atomic_write_path

    scene = js.load_scene(scene_path)
    if scene.occluders is not None and not args.with_occluders:
        scene = js.Scene(scene.lights, None, scene.ambient)
    points, normals = report_points()
    quiet = getattr(args, "quiet", False)
    show = (lambda *a: None) if quiet else print
    show(f"scene: {len(scene.lights)} lights; {points.shape[0]} receivers; Mitsuba spp={args.spp}")
    rep = jm.quick_report(scene, points, normals, spp=args.spp, seed=args.seed)
    ours, mits, se = (np.asarray(rep[k]) for k in ("ours", "mitsuba", "stderr"))
    sig = np.abs(ours - mits) / np.maximum(se, 1e-300)
    show(f"{'#':>3} {'point':>24} {'jaxshadow E (R)':>16} {'Mitsuba E (R)':>16} {'stderr':>10} {'|d|/sigma':>9}")
    for i in range(points.shape[0]):
        p = ", ".join(f"{x:+.2f}" for x in points[i])
        show(f"{i:3d} {p:>24} {ours[i, 0]:16.6f} {mits[i, 0]:16.6f} {se[i, 0]:10.2e} {sig[i].max():9.2f}")
    worst = float(sig.max())
    print(f"max |ours - Mitsuba| / stderr over all points and channels: {worst:.2f} (pass if <= 4)")
    show(f"time: jaxshadow {rep['ours_s']:.3f} s (incl. compile), Mitsuba {rep['mitsuba_s']:.3f} s")
    os.makedirs(out_dir, exist_ok=True)
    png, js_path = (os.path.join(out_dir, f"irradiance_report.{e}") for e in ("png", "json"))
    fig = _plot_report(scene, points, ours, mits, se)
    atomic_write_path(png, lambda tmp: fig.savefig(tmp, dpi=110))
    with atomic_write(js_path) as fh:
        json.dump({k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else v) for k, v in rep.items()}, fh)
    show(f"wrote {png} and {js_path}")
    return EXIT_OK if worst <= 4.0 else EXIT_CHECK


def _plot_report(scene: Any, points, ours, mits, se) -> Any:
    try:
        from matplotlib.figure import Figure
    except ImportError as err:
        raise ImportError("plots need the optional dependency 'matplotlib': `pip install 'jaxshadow[plot]'`.") from err

    import jaxshadow as js

    n = 200
    xs = np.linspace(-2, 2, n)
    gx, gy = np.meshgrid(xs, xs, indexing="xy")
    pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    e = np.asarray(js.irradiance(scene, pts, np.tile([0.0, 0.0, 1.0], (pts.shape[0], 1))))[:, 0].reshape(n, n)
    fig = Figure(figsize=(11, 4.6))
    ax = fig.subplots(1, 2)
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
    return fig


def _add_report(sub: Any) -> None:
    p = sub.add_parser("report", help="irradiance of a built-in scene vs Mitsuba 3, with a plot",
                       description="Irradiance of a scene at a grid of receivers, checked against Mitsuba 3 "
                                   "Monte Carlo (exit 3 if any point is off by more than 4 standard errors).")
    p.add_argument("--scene", default=None, help="scene JSON (default: the built-in room)")
    p.add_argument("--out", default="out", help="directory for irradiance_report.png/.json (created; default: out)")
    p.add_argument("--spp", type=positive_int, default=65536, help="Mitsuba samples per receiver (default: 65536)")
    p.add_argument("--seed", type=int, default=0, help="Mitsuba's random seed (default: 0)")
    p.add_argument("--with-occluders", action="store_true", help="keep the scene's occluders (shadows)")
    p.add_argument("-q", "--quiet", action="store_true", help="print only the verdict line (no table, no progress)")
    p.set_defaults(func=cmd_report, requires=(("mitsuba", "mitsuba", "the report's Mitsuba reference"),
                                              ("drjit", "mitsuba", "the report's Mitsuba reference"),
                                              ("matplotlib", "plot", "the report's plot")))


# --------------------------------------------------------------------------------------
# irradiance
# --------------------------------------------------------------------------------------

POINT_EXTS = (".csv", ".npy", ".npz", ".ply", ".obj", ".glb", ".gltf", ".stl", ".off")
VALUE_EXTS = (".npy", ".npz", ".csv", ".ply")


def cmd_irradiance(args: argparse.Namespace) -> int:
    check_input(args.scene, SCENE_EXTS, "scene")
    check_input(args.points, POINT_EXTS, "points")
    check_output(args.output, VALUE_EXTS)
    from .._io.meshio import IRRADIANCE_PROPERTY, MESH_EXTS, extension
    from .._io.tables import read_points_with_rows, write_values, write_values_beside_rows

    if extension(args.output) == ".ply" and extension(args.points) not in MESH_EXTS:
        raise ValueError(f"output {args.output!r}: a .ply output needs mesh receivers (points from a mesh file).")
    import jax

    if args.float64:
        jax.config.update("jax_enable_x64", True)
    import jaxshadow as js

    scene = read_scene(args.scene)[0]
    # CSV to CSV: the receiver columns are the input's rows as written (exact, and half the
    # formatting), taken from the same read of the file; any other input (or a CSV that needs the
    # csv module) gets them formatted.
    pts, nrm, mesh, rows = read_points_with_rows(args.points, at=args.at, weld=args.weld,
                                                 rows=extension(args.output) == ".csv")
    if mesh is not None and mesh.n_welded:
        _say(args)(f"{args.points}: {mesh.n_welded} duplicate vertices welded (--weld {args.weld:g})")
    dt = np.float64 if args.float64 else np.float32
    pts, nrm = pts.astype(dt), nrm.astype(dt)
    n = pts.shape[0]
    out = np.empty((n, 3), dtype=dt)
    chunk = args.chunk
    t0 = time.perf_counter()
    bar = Progress(n, "irradiance", quiet=args.quiet)
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        # pad the last chunk to the chunk size: one compilation for the whole run
        pp, nn = pts[s:e], nrm[s:e]
        if e - s < chunk and n > chunk:
            pad = chunk - (e - s)
            pp = np.concatenate([pp, np.repeat(pp[:1], pad, 0)])
            nn = np.concatenate([nn, np.repeat(nn[:1], pad, 0)])
        out[s:e] = np.asarray(js.irradiance(scene, pp, nn))[: e - s]
        bar.update(e - s)
    bar.close()
    if rows is not None and rows.count(b"\n") == n:
        write_values_beside_rows(args.output, rows, out)
    else:
        write_values(args.output, out, points=pts, normals=nrm, mesh=mesh, at=args.at, name=IRRADIANCE_PROPERTY)
    el = time.perf_counter() - t0
    _say(args)(f"{n} points in {el:.2f} s ({n / el:.3g} points/s, incl. compile) -> {args.output}")
    return EXIT_OK


def _add_irradiance(sub: Any) -> None:
    p = sub.add_parser("irradiance", help="irradiance (W/m^2, RGB) at many receivers",
                       description="Irradiance with exact soft shadows at receivers read from a file, "
                                   "evaluated in chunks, with progress after every chunk.")
    add_io_arguments(p, "points", "receivers: .csv with header px,py,pz,nx,ny,nz; .npy (N, 6); .npz with "
                     "'points' and 'normals'; or a mesh (.ply .obj .glb .gltf .stl .off)",
                     "irradiance: .npy (N, 3), .npz, .csv (px..nz,r,g,b; from a .csv, the receivers as "
                     "written there) or .ply (mesh receivers)")
    p.add_argument("--at", choices=("vertices", "faces"), default="vertices",
                   help="mesh receivers: at the vertices (default) or at the face centres")
    p.add_argument("--weld", type=non_negative_float, default=0.0, metavar="TOL",
                   help="mesh receivers: merge vertices within TOL (m) of each other (default 0: exactly "
                        "equal positions, e.g. UV-seam copies)")
    p.add_argument("--chunk", type=positive_int, default=1 << 16,
                   help="receivers per evaluation and per progress update (default: 65536); smaller uses "
                        "less memory, larger is a little faster")
    p.add_argument("--float64", action="store_true", help="evaluate in float64 (default: float32)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=cmd_irradiance)


# --------------------------------------------------------------------------------------
# render
# --------------------------------------------------------------------------------------


def _add_render(sub: Any) -> None:
    from .render import add_render_command

    add_render_command(sub)


# --------------------------------------------------------------------------------------
# main
# --------------------------------------------------------------------------------------

# The forward model's commands; each adds its sub-parser (the `mesh` command registers here).
def _add_mesh(sub: Any) -> None:
    from .mesh import add_mesh_parser

    add_mesh_parser(sub)


def _add_bake(sub: Any) -> None:
    p = sub.add_parser("bake", help="illumination mesh of every surface of a scene (exact irradiance per light), "
                                    "as glTF or PLY",
                       description="Mesh every receiving surface of a scene adaptively (planar faces by the "
                                   "illumination mesher, curved meshes by refining their triangles), seam-free "
                                   "across shared edges, with the exact irradiance of each light at the vertices; "
                                   "chunks run here or on a Dask cluster and are kept in a work directory, so an "
                                   "interrupted run resumes.")
    p.add_argument("scene", help="scene: jaxshadow JSON (.json: its occluders are the receivers, unless --receiver) "
                                 "or Mitsuba XML (.xml: every non-emitting shape)")
    p.add_argument("-o", "--output", required=True, help="output mesh: .glb or .ply, written exactly here")
    p.add_argument("--receiver", dest="receiver", action="append", default=None, metavar="MESH",
                   help="a mesh file (.obj .ply .glb .gltf .stl .off) to bake as a receiver (repeatable; replaces "
                        "the default receivers)")
    p.add_argument("--tol", type=float, default=1e-3,
                   help="interpolation tolerance relative to the scene's maximum irradiance (default 1e-3)")
    p.add_argument("--lights", default=None, metavar="I,J,...",
                   help="indices of the lights to bake, comma-separated (default: all)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the chunks on this Dask scheduler (tcp://host:8786); needs jaxshadow[bake]")
    p.add_argument("--workers", type=positive_int, default=None,
                   help="run the chunks on a local Dask cluster of this many worker processes")
    p.add_argument("--work-dir", default=None, metavar="DIR",
                   help="where the per-chunk results are kept (default: OUTPUT.chunks beside the output); "
                        "a second run with the same scene and settings reads them instead of computing")
    p.add_argument("--keep-work", action="store_true", help="keep the work directory after a successful run")
    p.add_argument("--max-vertices", type=positive_int, default=2_000_000,
                   help="refinement budget per planar face or curved surface (default 2000000)")
    p.add_argument("--min-edge", type=float, default=None,
                   help="elements shorter than this (m) are not split (default: see jaxshadow.bake)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    from .mesh import mesher_requires

    p.set_defaults(func=cmd_bake, requires=mesher_requires("bake"))


def parse_lights(text: str | None) -> list[int] | None:
    """`--lights "0,2"` -> `[0, 2]`; `None` -> `None`."""
    if text is None:
        return None
    try:
        out = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"--lights: expected comma-separated light indices, got {text!r}.") from None
    if not out:
        raise ValueError(f"--lights: expected comma-separated light indices, got {text!r}.")
    return out


def cmd_bake(args: argparse.Namespace) -> int:
    import shutil

    from .._illumination.bake import BAKE_FORMATS
    from .._io.meshio import MESH_EXTS

    check_input(args.scene, SCENE_EXTS, "scene")
    check_output(args.output, BAKE_FORMATS)
    for r in args.receiver or []:
        check_input(r, MESH_EXTS, "--receiver")
    if not (0 < args.tol < 1):
        raise ValueError(f"--tol must be in (0, 1), got {args.tol!r}.")
    if args.min_edge is not None and not (np.isfinite(args.min_edge) and args.min_edge > 0):
        raise ValueError(f"--min-edge must be a positive number, got {args.min_edge!r}.")
    lights = parse_lights(args.lights)
    if args.scheduler is not None and args.workers is not None:
        raise ValueError("give --scheduler or --workers, not both.")
    if args.scheduler is not None or args.workers is not None:
        check_requirements((("distributed", "bake", "--scheduler/--workers (Dask)"),))
    work = args.work_dir or args.output + ".chunks"
    check_directory(work, "--work-dir", create=True)
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxshadow as js

    scene, receivers, _ = read_scene(args.scene)
    if args.receiver:
        receivers = [js.read_mesh(r) for r in args.receiver]
    quiet = args.quiet or not sys.stderr.isatty()
    bar: Progress | None = None

    def progress(n: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            bar = Progress(total, "bake (chunks)", quiet=quiet)
        bar.update(n)

    baked = js.bake(scene, receivers or None, args.tol, lights=lights, work_dir=work, workers=args.workers,
                    scheduler=args.scheduler, max_vertices=args.max_vertices, min_edge=args.min_edge,
                    progress=progress)
    if bar is not None:
        bar.close()
    baked.save(args.output, up=scene_up(args.scene) if args.output.lower().endswith(".glb") else "z")
    if not args.keep_work:
        shutil.rmtree(work, ignore_errors=True)
    st = baked.stats
    _say(args)(f"{baked.vertices.shape[0]} vertices, {baked.triangles.shape[0]} triangles on "
               f"{len(baked.surface_names)} surfaces, {st['chunks']} chunks ({st['chunks_computed']} computed), "
               f"{st['seconds']:.1f} s -> {args.output}")
    return EXIT_OK


BUILTIN_COMMANDS: list[Callable[[Any], None]] = [_add_bake, _add_irradiance, _add_mesh, _add_render, _add_report]


def plugin_commands() -> dict[str, Any]:
    """Commands other packages register in the entry-point group `jaxshadow.commands` (the
    `inverse` package's `fit` and `demo`): name -> entry point, whose object is a function
    `add_command(subparsers)` adding an argparse sub-parser with `func=callable(args) -> int`."""
    found: dict[str, Any] = {}
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        found.setdefault(ep.name, ep)
    return found


def enable_compile_cache(directory: str | None = None, min_compile_s: float = 0.2) -> str:
    """Turn on JAX's persistent compilation cache (programs that took >= `min_compile_s` to
    compile are stored on disk and reused by later processes). `directory`: default
    `$JAX_COMPILATION_CACHE_DIR`, else `~/.cache/jaxshadow/xla`. Returns the directory. The
    cache is trusted code: keep it private to the user (see JAX's documentation). The library's
    solvers turn the same cache on by default (`ensure_default_compile_cache`)."""
    from .._core.compile_cache import enable_compile_cache as enable

    try:
        return enable(directory, min_compile_s, who="--compile-cache")
    except PermissionError as err:
        raise PermissionError(f"{err}; pass --compile-cache DIR or --no-compile-cache.") from None


def ensure_default_compile_cache() -> str | None:
    """The library's default persistent compilation cache, decided once per process: turned on
    in `~/.cache/jaxshadow/xla` unless JAX's cache is configured or disabled already or
    `$JAXSHADOW_COMPILE_CACHE` is `off` (or names another directory). Returns the directory in
    use, or None when there is none. The `inverse` solvers call it before their first compile."""
    from .._core.compile_cache import ensure_default_compile_cache as ensure

    return ensure()


def _version() -> str:
    try:
        return metadata.version("jaxshadow")
    except metadata.PackageNotFoundError:  # pragma: no cover
        return "0.0.0"


def _plain(text: str) -> str:
    """Help text from a Markdown docstring: without the backticks of code spans."""
    return text.replace("`", "")


def build_parser() -> argparse.ArgumentParser:
    """The `jaxshadow` argument parser, with the built-in and the registered commands."""
    parser = argparse.ArgumentParser(prog="jaxshadow", description=_plain(__doc__ or ""),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-V", "--version", action="version", version=f"jaxshadow {_version()}",
                        help="print the version and exit")
    parser.add_argument(
        "--compile-cache", default=None, metavar="DIR",
        help="JAX persistent compilation cache (default: $JAX_COMPILATION_CACHE_DIR, else "
             "~/.cache/jaxshadow/xla): a second run of the same job skips most XLA compilation",
    )
    parser.add_argument("--no-compile-cache", action="store_true", help="do not read or write the cache")
    sub = parser.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    for add in BUILTIN_COMMANDS:
        add(sub)
    plugins = plugin_commands()
    if not plugins:
        parser.epilog = ("No solver commands (fit, demo) are registered: they come from the inverse package "
                         f"through the entry-point group {ENTRY_POINT_GROUP!r}; reinstall jaxshadow (pip install -e .).")
    for name, ep in sorted(plugins.items()):
        try:
            ep.load()(sub)
        except ImportError as err:  # a registered package that cannot be imported here
            print(f"jaxshadow: command {name!r} unavailable ({err})", file=sys.stderr)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line `argv` (default: `sys.argv[1:]`); returns the exit code. Usage
    errors detected by argparse exit with status 2 through `SystemExit`."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        check_requirements(tuple(getattr(args, "requires", ())) + PLUGIN_REQUIRES.get(args.cmd, ()))
        check_outputs_are_not_inputs(_paths(args, OUTPUT_ARGUMENTS), _paths(args, INPUT_ARGUMENTS))
        if args.no_compile_cache:  # nor the library's default (`jaxshadow._core.compile_cache`)
            from .._core.compile_cache import decline_default_compile_cache

            decline_default_compile_cache()
        else:
            enable_compile_cache(args.compile_cache)
        return int(args.func(args) or 0)
    except _USER_ERRORS as err:
        print(f"jaxshadow {args.cmd}: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"jaxshadow {args.cmd}: interrupted (no output written)", file=sys.stderr)
        return 130
    except Exception as err:
        traceback.print_exc()
        print(f"jaxshadow {args.cmd}: internal error: {type(err).__name__}: {err} (a bug: please report it "
              "with the command line)", file=sys.stderr)
        return EXIT_INTERNAL
