"""`jaxshadow fit SCENE TARGETS -o FITTED`: fit a material (and optionally a light) to painted
targets and write the fitted scene and material as a scene JSON file."""

from __future__ import annotations

import os
import sys
import time

import jaxshadow as js

from ._lights import fit_light
from ._material import fit_material
from ._solvers import LM
from ._targets import load_targets


def fit_command(scene_path: str, targets_path: str, output: str | os.PathLike, light: int | None = None,
                combinatorics: str = "auto") -> int:
    """Run the fit; print the reports; write `output` (scene JSON with a `material` entry).

    With `light` (an index into the scene's lights), that light's placement is fitted first
    (Levenberg-Marquardt multistart, the material of the scene file as the starting material, or
    a first material fit at the given placement), then the material again at the fitted light.
    `combinatorics` is `fit_light`'s (`"auto"`, `"device"` or `"host"`: where the soft-shadow
    kernel's combinatorics run; on the CPU, with the compiled `_clipc`, `"auto"` is `"host"`).
    """
    if combinatorics not in ("auto", "device", "host"):
        raise ValueError(f"--combinatorics must be 'auto', 'device' or 'host', got {combinatorics!r}.")
    scene = js.load_scene(scene_path)
    targets = load_targets(targets_path)
    say = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731
    t0 = time.perf_counter()
    say(f"[1/{2 if light is None else 3}] material fit on {len(targets)} targets ...")
    mfit = fit_material(scene, targets)
    print(mfit.report)
    if light is not None:
        if not 0 <= light < len(scene.lights):
            raise ValueError(f"--light {light}: the scene has {len(scene.lights)} lights.")
        say("[2/3] light placement (multistart Levenberg-Marquardt) ...")
        lfit = fit_light(scene, targets, mfit.material, light_index=light, solver=LM(combinatorics=combinatorics))
        print(lfit.report)
        scene = lfit.scene
        say("[3/3] material fit at the fitted light ...")
        mfit = fit_material(scene, targets)
        print(mfit.report)
    js.save_scene(scene, output, material=mfit.material)
    say(f"wrote {output} ({time.perf_counter() - t0:.1f} s)")
    return 0
