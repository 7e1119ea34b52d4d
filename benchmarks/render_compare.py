"""`jaxshadow render` against Mitsuba's `direct` integrator on the example scene at 256 x 256
(`jaxshadow.mitsuba.write_example_scene`: a rectangle light, a 768-triangle OBJ torus, a floor).

1. jaxshadow's image (exact shading, 2 x 2 sub-pixels per pixel, box filter), timed as a second
   render in the process (the first compiles; both times are recorded).
2. Mitsuba `direct` at equal wall time: the spp at which Mitsuba takes as long as our (warm)
   render (`jaxshadow.cli.render.equal_time_spp`), and its image.
3. A high-spp Mitsuba reference (32 independent renders of 64 spp, for per-pixel standard
   errors): on the floor pixels, z = (ours - reference) / stderr and the same for the equal-time
   render; the RMS relative error of both against the reference.

    .venv/bin/python benchmarks/render_compare.py [--resolution 256]

Writes results/render_compare.{json,png} (the png: ours | Mitsuba at equal time | difference).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--batches", type=int, default=32)
    ap.add_argument("--batch-spp", type=int, default=64)
    args = ap.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxshadow as js
    from jaxshadow import mitsuba as jm
    from jaxshadow.cli.render import equal_time_spp, render, render_mitsuba, write_comparison

    with tempfile.TemporaryDirectory() as d:
        scene = jm.write_example_scene(d, resolution=args.resolution)
        first = render(scene, supersample=2)
        ours = render(scene, supersample=2)
        surface = render(scene).surface
        spp = equal_time_spp(scene, ours.seconds)
        equal, t_equal = render_mitsuba(scene, spp, seed=1000)
        imgs = np.stack([render_mitsuba(scene, args.batch_spp, seed=s)[0] for s in range(args.batches)])
        ref, se = imgs.mean(axis=0), imgs.std(axis=0, ddof=1) / np.sqrt(args.batches)
    floor = surface == 0
    inner = floor.copy()
    inner[1:-1, 1:-1] &= floor[:-2, 1:-1] & floor[2:, 1:-1] & floor[1:-1, :-2] & floor[1:-1, 2:]
    inner[[0, -1], :] = inner[:, [0, -1]] = False
    lit = inner[..., None] & (se > 0) & (ref > 1e-3 * ref.max())

    def stats(img: np.ndarray) -> dict:
        z = ((img - ref) / np.where(se > 0, se, 1.0))[lit]
        rel = (np.abs(img - ref) / np.maximum(ref, 1e-30))[lit]
        return {"mean_z2": float(np.mean(z**2)), "max_abs_z": float(np.abs(z).max()),
                "frac_abs_z_gt_4": float(np.mean(np.abs(z) > 4)), "rms_rel_error": float(np.sqrt(np.mean(rel**2))),
                "max_rel_error": float(rel.max())}

    out = {
        "resolution": args.resolution, "supersample": 2, "floor_pixels": int(inner.sum()),
        "jaxshadow_s": ours.seconds, "jaxshadow_first_s": first.seconds,
        "mitsuba_equal_time_spp": spp, "mitsuba_equal_time_s": t_equal,
        "reference_spp": args.batches * args.batch_spp,
        "jaxshadow_vs_reference": stats(ours.image), "mitsuba_equal_time_vs_reference": stats(equal),
        "version": js.__version__, "command": " ".join(["benchmarks/render_compare.py", *sys.argv[1:]]),
    }
    os.makedirs(os.path.join(HERE, "results"), exist_ok=True)
    write_comparison(os.path.join(HERE, "results", "render_compare.png"), ours, equal, t_equal, spp, dpi=64)
    with js.files.atomic_write(os.path.join(HERE, "results", "render_compare.json")) as fh:
        json.dump(out, fh, indent=1)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
