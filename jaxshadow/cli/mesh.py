"""The `jaxshadow mesh` command: an adaptive illumination mesh of one receiver polygon of a scene
(`jaxshadow.illumination_mesh`), written as PLY or glTF (`jaxshadow._illumination.io`)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

import numpy as np

from .._illumination.io import FORMATS, save_mesh

# --------------------------------------------------------------------------------------
# `jaxshadow mesh`
# --------------------------------------------------------------------------------------


def default_receiver(scene: Any) -> np.ndarray:
    """The square on z = 0 (normal +z) under the scene: the x-y bounding box of its lights and
    occluders, grown on every side by the highest light's height."""
    pts = []
    for light in scene.lights:
        for name in ("vertices", "start", "end", "position"):
            if hasattr(light, name):
                pts.append(np.asarray(getattr(light, name), np.float64).reshape(-1, 3))
    if scene.occluders is not None:
        pts.append(np.asarray(scene.occluders, np.float64).reshape(-1, 3))
    if not pts:
        raise ValueError("the scene has no light with a position; give --receiver.")
    p = np.concatenate(pts)
    grow = max(float(np.max(p[:, 2])), 1e-3)
    lo, hi = p[:, :2].min(axis=0) - grow, p[:, :2].max(axis=0) + grow
    return np.array([[lo[0], lo[1], 0.0], [hi[0], lo[1], 0.0], [hi[0], hi[1], 0.0], [lo[0], hi[1], 0.0]])


def parse_receiver(text: str) -> np.ndarray:
    """`--receiver`: a JSON file holding a list of [x, y, z] vertices, or the vertices inline as
    `"x,y,z; x,y,z; ..."`."""
    if os.path.exists(text):
        with open(text) as fh:
            try:
                data = json.load(fh)
            except json.JSONDecodeError as err:
                raise ValueError(f"--receiver {text}: not valid JSON ({err}).") from None
            except RecursionError:
                raise ValueError(f"--receiver {text}: JSON nested too deeply to read.") from None
    else:
        try:
            data = [[float(x) for x in row.split(",")] for row in text.split(";") if row.strip()]
        except ValueError:
            raise ValueError(f"--receiver: expected a JSON file or 'x,y,z; x,y,z; ...', got {text!r}.") from None
    try:
        arr = np.asarray(data, np.float64)
    except (TypeError, ValueError, RecursionError):
        raise ValueError(f"--receiver: expected k rows of 3 numbers, got {str(data)[:80]!r}.") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"--receiver: expected k rows of 3 coordinates, got shape {arr.shape}.")
    return arr


def mesh_command(args: argparse.Namespace) -> int:
    """`jaxshadow mesh SCENE -o OUT --tol TOL [--receiver R]`."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxshadow as js

    out = os.fspath(args.output)
    if os.path.splitext(out)[1].lower() not in FORMATS:
        raise ValueError(f"-o {out}: the output must end in one of {sorted(FORMATS)}.")
    directory = os.path.dirname(os.path.abspath(out))
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"-o {out}: directory {directory} does not exist.")
    from .common import default_receiver_polygon, read_scene, scene_up

    scene, receivers, _ = read_scene(args.scene)
    if args.receiver:
        receiver = parse_receiver(args.receiver)
    elif receivers:
        receiver = default_receiver_polygon(scene, receivers)
    else:
        receiver = default_receiver(scene)
    up = args.up or scene_up(args.scene)
    # The receiver's own surface (faces on its plane facing its way) blocks nothing on it (the
    # on-surface rule); the mesher is given the scene without it, as `bake` does.
    from .._illumination.bake_chunks import without_own_faces

    normal = np.cross(receiver, np.roll(receiver, -1, axis=0)).sum(axis=0)
    scene = without_own_faces(scene, receiver, normal / np.linalg.norm(normal))
    def report(r: dict) -> None:
        print(f"round {r['round']}: {r['tiles_active']} tiles refining, {r['tile_vertices']:,} vertices, "
              f"{r['failing_elements']:,} elements split, {r['seconds']:.1f} s", file=sys.stderr, flush=True)

    mesh = js.illumination_mesh(scene, receiver, args.tol, max_vertices=args.max_vertices, tile_size=args.tile_size,
                                progress=None if args.quiet else report)
    written = save_mesh(mesh, out, up=up)
    cleaned = ""
    if written and (written["welded"] or written["dropped"]):
        cleaned = (f" (glTF, y-up from {up}: {written['welded']} vertices welded and {written['dropped']} "
                   "triangles removed at float32 resolution)")
    print(f"{mesh.vertices.shape[0]} vertices, {mesh.triangles.shape[0]} triangles, checked error "
          f"{mesh.max_error_estimate:.3g} of the maximum {mesh.scale:.4g} W/m^2 (tol {args.tol:g}), "
          f"{mesh.stats['seconds']:.1f} s -> {out}{cleaned}")
    return 0


def add_mesh_parser(sub: Any) -> None:
    """Register `jaxshadow mesh` on an argparse subparsers object."""
    p = sub.add_parser("mesh", help="adaptive illumination mesh of a receiver (exact irradiance at the vertices), "
                                    "written as PLY or glTF",
                       description="Mesh a receiver polygon adaptively until linear interpolation of the exact "
                                   "irradiance at its vertices is within --tol of the receiver's maximum, and write "
                                   "it as PLY (vertex colours and float properties irradiance_r/g/b) or glTF.")
    p.add_argument("scene", help="scene: jaxshadow JSON (.json) or Mitsuba XML (.xml)")
    p.add_argument("-o", "--output", required=True,
                   help="output mesh: .ply (scene frame) or .glb/.gltf (y-up, float32 irradiance _IRRADIANCE)")
    p.add_argument("--tol", type=float, default=1e-3,
                   help="interpolation tolerance relative to the receiver's maximum irradiance (default 1e-3)")
    p.add_argument("--receiver", default=None,
                   help="receiver polygon: a JSON file with a list of [x, y, z] vertices or 'x,y,z; x,y,z; ...' "
                        "(counter-clockwise seen from its lit side; default: for a JSON scene the floor z = 0 "
                        "under the scene, for a Mitsuba scene the largest face of its shapes facing the lights)")
    p.add_argument("--up", choices=("x", "y", "z", "-x", "-y", "-z"), default=None,
                   help="the scene's up axis, turned to +y in glTF output (default: z for a JSON scene, the "
                        "camera's up axis for a Mitsuba scene, y without a camera)")
    p.add_argument("--max-vertices", type=int, default=2_000_000, help="stop refining at this many vertices")
    p.add_argument("--tile-size", type=float, default=None,
                   help="side of the tiles the receiver is meshed in (m; default 1/16 of its extent)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output (one line per refinement round)")
    p.set_defaults(func=mesh_command, requires=mesher_requires("mesh"))


def mesher_requires(command: str) -> tuple[tuple[str, str, str], ...]:
    """What a command that runs the illumination mesher needs: `(module, extra, what for)`."""
    return (("trimesh", "mesh", f"{command} (writing the mesh)"),
            ("pythoncdt", "mesh", f"{command} (triangulation)"),
            ("shapely", "mesh", f"{command} (polygon clipping)"))


if __name__ == "__main__":  # pragma: no cover
    parser = argparse.ArgumentParser(prog="jaxshadow")
    add_mesh_parser(parser.add_subparsers(dest="cmd", required=True))
    a = parser.parse_args()
    sys.exit(a.func(a))
