"""The renderers a user would otherwise pick, driven on the same scenes as jaxshadow.

Radiance through pyradiance (the `bench` extra): `rtrace -I -ab 0` gives the irradiance at ray
origins (the ray direction is the surface normal) from light sources only, sampling area sources
by subdividing them (`-ds`, `-dj`, `-dt`, `-dc` set the accuracy). Occluders are black plastic
polygons: with `-ab 0` nothing but the light sources contributes.
"""

from __future__ import annotations

import os
import tempfile
import time
from typing import Any

import numpy as np

# Radiance's defaults, and a fine source subdivision (jittered, no shadow-test threshold).
RADIANCE_DEFAULT: tuple[str, ...] = ()
RADIANCE_FINE: tuple[str, ...] = ("-dj", "1", "-ds", "0.01", "-dt", "0", "-dc", "1")


def _polygon(mat: str, name: str, pts: np.ndarray) -> str:
    flat = " ".join(f"{x:.17g}" for x in np.asarray(pts, float).reshape(-1))
    return f"{mat} polygon {name}\n0\n0\n{3 * len(pts)} {flat}\n"


def radiance_scene(lights: list[tuple[np.ndarray, np.ndarray]], occluders: np.ndarray) -> str:
    """Radiance scene text: `lights` as `(vertices (k, 3) counter-clockwise seen from the lit
    side, radiance (3,))` polygons of `light` material, `occluders (m, k, 3)` black polygons."""
    out = ["void plastic black\n0\n0\n5 0 0 0 0 0\n"]
    for i, (verts, rad) in enumerate(lights):
        r = np.broadcast_to(np.asarray(rad, float), (3,))
        out.append(f"void light lmat{i}\n0\n0\n3 {r[0]:.17g} {r[1]:.17g} {r[2]:.17g}\n")
        out.append(_polygon(f"lmat{i}", f"light{i}", verts))
    for j, poly in enumerate(occluders):
        out.append(_polygon("black", f"occ{j}", poly))
    return "".join(out)


class Radiance:
    """A compiled octree of one scene; `irradiance(points, normals, params)` runs rtrace."""

    def __init__(self, lights: list[tuple[np.ndarray, np.ndarray]], occluders: np.ndarray):
        import pyradiance as pr

        self._pr = pr
        self._dir = tempfile.TemporaryDirectory(prefix="jaxshadow-radiance-")
        rad = os.path.join(self._dir.name, "scene.rad")
        with open(rad, "w") as fh:
            fh.write(radiance_scene(lights, occluders))
        t = time.perf_counter()
        octree = pr.oconv(rad, warning=False)
        self.oconv_seconds = time.perf_counter() - t
        self.octree = os.path.join(self._dir.name, "scene.oct")
        with open(self.octree, "wb") as fh:
            fh.write(octree)

    def irradiance(self, points: np.ndarray, normals: np.ndarray, params: tuple[str, ...] = RADIANCE_DEFAULT,
                   nproc: int = 2) -> tuple[np.ndarray, float]:
        """`(E (N, 3) W/m^2, seconds)`: rtrace's wall time, binary float64 in and out."""
        rays = np.ascontiguousarray(np.concatenate([points, normals], axis=1), np.float64)
        t = time.perf_counter()
        out = self._pr.rtrace(rays.tobytes(), self.octree, header=False, inform="d", outform="d", irradiance=True,
                              nproc=nproc, params=["-ab", "0", *params])
        seconds = time.perf_counter() - t
        e = np.frombuffer(out, np.float64).reshape(-1, 3)
        if e.shape[0] != points.shape[0]:
            raise RuntimeError(f"rtrace returned {e.shape[0]} values for {points.shape[0]} rays")
        return e.copy(), seconds

    def close(self) -> None:
        self._dir.cleanup()

    def __enter__(self) -> Radiance:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
