"""Illumination meshes out: PLY and glTF files (through trimesh) and the `jaxshadow mesh` command.

Vertex colours are the irradiance over the mesh's `scale` (the receiver's maximum), clipped to
[0, 1] and gamma-encoded (sRGB-like 1/2.2) for viewers; PLY files also carry the exact float
irradiance as the vertex properties `irradiance_r`, `irradiance_g`, `irradiance_b` (W/m^2).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from .._core.files import atomic_write_path
from .._io.meshio import IRRADIANCE_PROPERTY

FORMATS = {".ply": "ply", ".glb": "glb", ".gltf": "gltf"}


def vertex_colours(irradiance: np.ndarray, scale: float) -> np.ndarray:
    """`(V, 4)` uint8 RGBA display colours of irradiance `(V, 3)` relative to `scale`."""
    c = np.clip(np.asarray(irradiance, np.float64) / max(float(scale), 1e-300), 0.0, 1.0) ** (1 / 2.2)
    rgba = np.empty((c.shape[0], 4), np.uint8)
    rgba[:, :3] = np.round(255 * c).astype(np.uint8)
    rgba[:, 3] = 255
    return rgba


def save_mesh(mesh: Any, path: str | os.PathLike, up: Any = "z") -> dict[str, int] | None:
    """Write an `IlluminationMesh` to `path`: `.ply` (binary, vertex colours and the float
    irradiance as vertex properties, in the scene's frame), `.glb` or `.gltf` (buffers embedded;
    vertex colours as `COLOR_0`, the float irradiance as `_IRRADIANCE`, y-up: the scene's `up`
    axis turned to +y, and a clean float32 triangulation: `jaxshadow._io.meshio.write_gltf`, whose
    counts it returns). The file is replaced atomically."""
    import trimesh

    from .._io.meshio import write_gltf

    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in FORMATS:
        raise ValueError(f"illumination mesh: unknown output format {ext!r} (expected one of {sorted(FORMATS)}).")
    colours = vertex_colours(mesh.irradiance, mesh.scale)
    if ext != ".ply":
        return write_gltf(path, mesh.vertices, mesh.triangles, colours=colours,
                          attributes={IRRADIANCE_PROPERTY: np.asarray(mesh.irradiance, np.float64)}, up=up)
    tm = trimesh.Trimesh(mesh.vertices, mesh.triangles, vertex_colors=colours, process=False)
    for c, name in enumerate("rgb"):
        tm.vertex_attributes[f"{IRRADIANCE_PROPERTY}_{name}"] = np.ascontiguousarray(mesh.irradiance[:, c], np.float64)
    atomic_write_path(path, lambda tmp: tm.export(tmp, file_type="ply"))
    return None
