"""The solvers' commands of `jaxshadow`: `fit` and `demo`.

`jaxshadow.cli` knows nothing of this package: it finds these commands through the entry-point
group `jaxshadow.commands` that `pyproject.toml` registers (`fit = "inverse.cli:add_fit_command"`,
`demo = "inverse.cli:add_demo_command"`), so every import runs from the solvers to the forward
model, never back.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

import jaxshadow as js
from jaxshadow.cli.common import (
    SCENE_EXTS,
    add_io_arguments,
    check_directory,
    check_input,
    check_output,
    positive_int,
    read_scene,
)

from ._demo import run_demo
from ._joint import fit_light_and_material
from ._material import fit_material
from ._solvers import LM
from ._targets import load_targets

TARGET_EXTS = (".csv", ".json")


LIGHT_PARAMETERS = ("position", "orientation", "size")


def fit_command(scene_path: str, targets_path: str, output: str | os.PathLike, light: int | None = None,
                combinatorics: str = "auto", fit: tuple[str, ...] = ("position", "orientation"),
                starts: int = 64, say: Callable[[str], None] | None = None) -> int:
    """Fit a material (and optionally a light) to painted targets; print the reports; write
    `output`.

    **Arguments:**

    - `scene_path`: scene JSON or Mitsuba XML (`jaxshadow.mitsuba.from_mitsuba`).
    - `targets_path`: painted targets, `.csv` (header `px,py,pz,nx,ny,nz,r,g,b,ex,ey,ez`, optional
      `wr,wg,wb`) or `.json` (`inverse.PaintedTargets.save`).
    - `output`: `.json` (the scene with a `material` entry) or `.xml` (a Mitsuba scene: the
      fitted lights, the input's occluders and surfaces with the fitted material as their BSDF,
      the input's camera; meshes as PLY files in `<output stem>_meshes/`), written atomically.
    - `light`: index of a light whose placement is fitted jointly with the material
      (`fit_light_and_material`: Levenberg-Marquardt multistart over the light's pose and the
      Phong exponent with $k_a, k_d, k_s$ projected out, then the exact bounded material fit).
    - `combinatorics`: `fit_light`'s (`"auto"`, `"device"` or `"host"`).
    - `fit`: the light's parameters to fit (`fit_light`'s `fit`); by default its size is known
      (with $k_d$ free, a light's area and $k_d$ trade off far from the light).
    - `starts`: multistart points of the light fit (`fit_light`'s `starts`; the best
      `min(8, starts)` are solved).
    - `say`: progress messages (default: to stderr).

    **Returns:** 0.
    """
    output = os.fspath(output)
    if combinatorics not in ("auto", "device", "host"):
        raise ValueError(f"--combinatorics must be 'auto', 'device' or 'host', got {combinatorics!r}.")
    bad = [f for f in fit if f not in LIGHT_PARAMETERS]
    if bad or not fit:
        raise ValueError(f"--fit: expected a comma-separated subset of {','.join(LIGHT_PARAMETERS)}, got {','.join(fit)!r}.")
    check_input(scene_path, SCENE_EXTS, "scene")
    check_input(targets_path, TARGET_EXTS, "targets")
    check_output(output, (".json", ".xml"))
    scene, receivers, materials = read_scene(scene_path)
    if light is not None and not 0 <= light < len(scene.lights):
        raise ValueError(f"--light {light}: the scene has {len(scene.lights)} lights.")
    targets = load_targets(targets_path)
    full_scene = scene
    if receivers:
        scene = _without_idle_occluders(scene, receivers, targets)
    if say is None:
        say = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731
    # A scene whose materials are all diffuse gets a diffuse fit (k_s held at 0).
    diffuse = bool(materials) and all(not np.any(np.asarray(m.ks) > 0) for m in materials)
    mkw: dict[str, Any] = {"bounds": ((0, 0, 0), (1, 1, 0)), "warn": False} if diffuse else {}
    t0 = time.perf_counter()
    say(f"[1/{1 if light is None else 2}] {'diffuse ' if diffuse else ''}material fit on {len(targets)} targets ...")
    mfit = fit_material(scene, targets, **mkw)
    print(mfit.report)
    material = mfit.material
    if light is not None:
        say(f"[2/2] light {light} ({', '.join(fit)}) and material, jointly (multistart Levenberg-Marquardt) ...")
        guess = js.Material(ka=0.0, kd=0.5, ks=0.0, exponent=1.0) if diffuse else material
        joint = fit_light_and_material(scene, targets, guess, light, progress=say, material_kwargs=mkw,
                                       light_kwargs={"solver": LM(combinatorics=combinatorics, refine=min(8, int(starts))),
                                                     "fit": tuple(fit), "starts": int(starts)})
        for rep in joint.report:
            print(rep)
        material = joint.material
        scene = js.Scene(joint.scene.lights, full_scene.occluders if receivers else joint.scene.occluders,
                         joint.scene.ambient)
    if output.lower().endswith(".xml"):
        from jaxshadow.mitsuba import read_sensor, write_mitsuba_xml

        sensor = read_sensor(scene_path) if scene_path.lower().endswith(".xml") else None
        write_mitsuba_xml(output, scene, receivers, [material] * len(receivers), sensor=sensor)
    else:
        with js.files.atomic_write(output) as fh:
            json.dump(js.scene_to_dict(scene, material), fh, indent=2)
    say(f"wrote {output} ({time.perf_counter() - t0:.1f} s)")
    return 0


def _without_idle_occluders(scene: Any, receivers: list, targets: Any) -> Any:
    """The scene without the receiver surfaces that cannot shadow any target: those lying
    entirely on or below every target's tangent plane (light reaches a target only from above
    it), such as the floor the targets are painted on. Exact: the values are unchanged."""
    p = np.asarray(targets.points, np.float64)
    n = np.asarray(targets.normals, np.float64)
    keep = []
    for r in receivers:
        size = float(np.max(np.ptp(r.vertices, axis=0)))
        heights = np.einsum("tvk,tk->tv", r.vertices[None] - p[:, None], n)
        if np.any(heights > 1e-9 * size):
            keep.append(r.occluder())
    return js.Scene(scene.lights, occluders=keep or None, ambient=scene.ambient)


def _cmd_fit(args: argparse.Namespace) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)  # the fits run in float64
    say = (lambda msg: None) if args.quiet else None
    return fit_command(args.scene, args.targets, args.output, light=args.light, combinatorics=args.combinatorics,
                       fit=tuple(x.strip() for x in args.fit.split(",") if x.strip()), starts=args.starts, say=say)


def add_fit_command(subparsers: Any) -> argparse.ArgumentParser:
    """Add `jaxshadow fit` to the `jaxshadow` sub-parsers (entry point `jaxshadow.commands`)."""
    # Declared like jaxshadow.cli's own sub-parsers (argparse calls of the same shape, not shared code).
    p = subparsers.add_parser("fit", help="fit material (and a light) to painted targets",
                              description="Fit k_a, k_d, k_s and the Phong roughness (and, with --light, a "
                                          "light's placement) to painted target colours.")
    add_io_arguments(p, "targets", "painted targets: .csv with header px,py,pz,nx,ny,nz,r,g,b,ex,ey,ez "
                     "(optional wr,wg,wb) or .json",
                     "fitted scene: .json (with a 'material' entry) or .xml (Mitsuba)")
    p.add_argument("--light", type=int, default=None,
                   help="also fit the placement of this light (index into the scene's lights), jointly with the material")
    p.add_argument("--fit", default="position,orientation",
                   help="with --light: the light's parameters to fit, comma-separated from position,orientation,size "
                        "(default: position,orientation: the lamp's size is known)")
    p.add_argument("--starts", type=positive_int, default=64,
                   help="with --light: multistart points of the light fit (default: 64; the best 8 are solved)")
    p.add_argument("--combinatorics", choices=("auto", "device", "host"), default="auto",
                   help="with --light and occluders: where the soft-shadow kernel's combinatorics run "
                        "(auto: host on the CPU when the compiled kernel is built; see fit_light)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages (the fit reports are still printed)")
    p.set_defaults(func=_cmd_fit)
    return p


def _cmd_demo(args: argparse.Namespace) -> int:
    check_directory(args.out, "--out", create=True)
    import jax

    jax.config.update("jax_enable_x64", True)  # the fits run in float64
    run_demo(args.out, progress=not args.quiet, spp=args.spp, seed=args.seed)
    return 0


def add_demo_command(subparsers: Any) -> argparse.ArgumentParser:
    """Add `jaxshadow demo` to the `jaxshadow` sub-parsers (entry point `jaxshadow.commands`)."""
    p = subparsers.add_parser("demo", help="inverse shading demo: recover material and light from Mitsuba targets",
                              description="Render painted colours with Mitsuba 3 from a hidden light and "
                                          "material, recover both, print a table and write a before/after picture.")
    p.add_argument("--out", default="out", help="directory for demo_before_after.png and demo_targets.json (default: out)")
    p.add_argument("--spp", type=positive_int, default=1 << 14, help="Mitsuba samples per painted point (default: 16384)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the targets and their noise (default: 0)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_cmd_demo)
    return p

