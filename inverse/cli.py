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

import jaxshadow as js
from jaxshadow.cli import (
    SCENE_EXTS,
    check_directory,
    check_input,
    check_output,
    positive_int,
    read_scene,
)

from ._demo import run_demo
from ._lights import fit_light
from ._material import fit_material
from ._targets import load_targets

TARGET_EXTS = (".csv", ".json")


def fit_command(scene_path: str, targets_path: str, output: str | os.PathLike, light: int | None = None,
                combinatorics: str = "auto", say: Callable[[str], None] | None = None) -> int:
    """Fit a material (and optionally a light) to painted targets; print the reports; write
    `output`.

    **Arguments:**

    - `scene_path`: scene JSON or Mitsuba XML (`jaxshadow.mitsuba.from_mitsuba`).
    - `targets_path`: painted targets, `.csv` (header `px,py,pz,nx,ny,nz,r,g,b,ex,ey,ez`, optional
      `wr,wg,wb`) or `.json` (`inverse.PaintedTargets.save`).
    - `output`: `.json` (the scene with a `material` entry) or `.xml` (a Mitsuba scene: the
      fitted lights, the input's occluders and surfaces with the fitted material as their BSDF,
      the input's camera; meshes as PLY files in `<output stem>_meshes/`), written atomically.
    - `light`: index of a light whose placement is fitted first (Levenberg-Marquardt multistart
      with the first material fit as the material), then the material again at the fitted light.
    - `combinatorics`: `fit_light`'s (`"auto"`, `"device"` or `"host"`).
    - `say`: progress messages (default: to stderr).

    **Returns:** 0.
    """
    output = os.fspath(output)
    if combinatorics not in ("auto", "device", "host"):
        raise ValueError(f"--combinatorics must be 'auto', 'device' or 'host', got {combinatorics!r}.")
    check_input(scene_path, SCENE_EXTS, "scene")
    check_input(targets_path, TARGET_EXTS, "targets")
    check_output(output, (".json", ".xml"))
    scene, receivers, _ = read_scene(scene_path)
    if light is not None and not 0 <= light < len(scene.lights):
        raise ValueError(f"--light {light}: the scene has {len(scene.lights)} lights.")
    targets = load_targets(targets_path)
    if say is None:
        say = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731
    t0 = time.perf_counter()
    say(f"[1/{2 if light is None else 3}] material fit on {len(targets)} targets ...")
    mfit = fit_material(scene, targets)
    print(mfit.report)
    if light is not None:
        say("[2/3] light placement (multistart Levenberg-Marquardt) ...")
        lfit = fit_light(scene, targets, mfit.material, light_index=light, combinatorics=combinatorics)
        print(lfit.report)
        scene = lfit.scene
        say("[3/3] material fit at the fitted light ...")
        mfit = fit_material(scene, targets)
        print(mfit.report)
    if output.lower().endswith(".xml"):
        from jaxshadow.mitsuba import read_sensor, write_mitsuba_xml

        sensor = read_sensor(scene_path) if scene_path.lower().endswith(".xml") else None
        write_mitsuba_xml(output, scene, receivers, [mfit.material] * len(receivers), sensor=sensor)
    else:
        with js.atomic_write(output) as fh:
            json.dump(js.scene_to_dict(scene, mfit.material), fh, indent=2)
    say(f"wrote {output} ({time.perf_counter() - t0:.1f} s)")
    return 0


def _cmd_fit(args: argparse.Namespace) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)  # the fits run in float64
    return fit_command(args.scene, args.targets, args.output, light=args.light, combinatorics=args.combinatorics)


def add_fit_command(subparsers: Any) -> argparse.ArgumentParser:
    """Add `jaxshadow fit` to the `jaxshadow` sub-parsers (entry point `jaxshadow.commands`)."""
    p = subparsers.add_parser("fit", help="fit material (and a light) to painted targets",
                              description="Fit k_a, k_d, k_s and the Phong roughness (and, with --light, a "
                                          "light's placement) to painted target colours.")
    p.add_argument("scene", help="scene: jaxshadow JSON (.json) or Mitsuba XML (.xml)")
    p.add_argument("targets", help="painted targets: .csv with header px,py,pz,nx,ny,nz,r,g,b,ex,ey,ez "
                                   "(optional wr,wg,wb) or .json")
    p.add_argument("-o", "--output", required=True,
                   help="fitted scene, written exactly here: .json (with a 'material' entry) or .xml (Mitsuba)")
    p.add_argument("--light", type=int, default=None, help="also fit the placement of this light (index)")
    p.add_argument("--combinatorics", choices=("auto", "device", "host"), default="auto",
                   help="with --light and occluders: where the soft-shadow kernel's combinatorics run "
                        "(auto: host on the CPU when the compiled kernel is built; see fit_light)")
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

