"""The renderers a user would otherwise pick, driven on the same scenes as jaxshadow.

Radiance through pyradiance (the `bench` extra): `rtrace -I -ab 0` gives the irradiance at ray
origins (the ray direction is the surface normal) from light sources only, sampling area sources
by subdividing them (`-ds`, `-dj`, `-dt`, `-dc` set the accuracy). Occluders are black plastic
polygons: with `-ab 0` nothing but the light sources contributes.

Embree through embreex (the `bench` extra): shadow rays from each receiver to stratified jittered
samples of a polygon light (Monte Carlo estimate of the irradiance; error falls as 1/samples), or
stratified points along a segment light, or one ray to a point / along a directional light (hard
shadows, exact up to float32 ray tests).
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


class Embree:
    """Embree's occlusion rays against `triangles (m, 3, 3)` (float32, as Embree stores them)."""

    def __init__(self, triangles: np.ndarray):
        from embreex import mesh_construction, rtcore_scene

        t = time.perf_counter()
        self._scene = rtcore_scene.EmbreeScene()
        self._mesh = mesh_construction.TriangleMesh(self._scene, np.ascontiguousarray(triangles, np.float32))
        self._occluded(np.zeros((1, 3)), np.ones((1, 3)))  # Embree builds its hierarchy on the first query
        self.build_seconds = time.perf_counter() - t

    def _occluded(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Whether each ray origin + t direction, 0 < t < 1, hits a triangle (bool (n,))."""
        hit = self._scene.run(np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(directions, np.float32),
                              dists=np.ones(len(origins), np.float32), query="OCCLUDED")
        return np.asarray(hit) >= 0

    def polygon_irradiance(self, points: np.ndarray, normals: np.ndarray, quad: np.ndarray, radiance: float,
                           samples: int, seed: int = 0) -> tuple[np.ndarray, float]:
        """`(E (N,) W/m^2, seconds)` from a parallelogram light `quad (4, 3)` (counter-clockwise
        seen from the lit side) of uniform radiance, `samples` (a square number) stratified
        jittered shadow rays per receiver; origins lifted 1e-6 m along the receiver normal."""
        k = int(round(np.sqrt(samples)))
        rng = np.random.default_rng(seed)
        e0, e1, e3 = quad[0], quad[1] - quad[0], quad[3] - quad[0]
        nl = np.cross(e1, e3)  # the emitting side (right-hand rule of the vertex order)
        area = np.linalg.norm(nl)
        nl = nl / area
        gi, gj = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
        out = np.empty(len(points))
        block = max(1, 2**16 // (k * k))  # receivers per batch of rays (batches of ~65k rays)
        t = time.perf_counter()
        for s in range(0, len(points), block):
            p, n = points[s:s + block], normals[s:s + block]
            u = (gi.reshape(-1)[None, :] + rng.random((len(p), k * k))) / k
            v = (gj.reshape(-1)[None, :] + rng.random((len(p), k * k))) / k
            q = e0 + u[..., None] * e1 + v[..., None] * e3  # (b, k*k, 3)
            d = q - p[:, None, :]
            r2 = np.einsum("bsi,bsi->bs", d, d)
            cos_p = np.einsum("bsi,bi->bs", d, n) / np.sqrt(r2)
            cos_l = -np.einsum("bsi,i->bs", d, nl) / np.sqrt(r2)
            w = np.where((cos_p > 0) & (cos_l > 0), cos_p * cos_l / r2, 0.0)
            o = np.repeat(p + 1e-6 * n, k * k, axis=0)
            blocked = self._occluded(o, d.reshape(-1, 3)).reshape(len(p), k * k)
            out[s:s + block] = radiance * area * np.where(blocked, 0.0, w).mean(axis=1)
        return out, time.perf_counter() - t

    def segment_irradiance(self, points: np.ndarray, normals: np.ndarray, start: np.ndarray, end: np.ndarray,
                           power: float, samples: int, seed: int = 0) -> tuple[np.ndarray, float]:
        """`(E (N,) W/m^2, seconds)` from an isotropic segment light of power `power` per unit
        length (per-length intensity Phi / (4 pi)): `samples` stratified jittered points along
        it per receiver; origins lifted 1e-6 m along the receiver normal."""
        rng = np.random.default_rng(seed)
        length = float(np.linalg.norm(end - start))
        block = max(1, 2**16 // samples)  # receivers per batch of rays (batches of ~65k rays)
        out = np.empty(len(points))
        t = time.perf_counter()
        for s in range(0, len(points), block):
            q, n = points[s:s + block], normals[s:s + block]
            u = (np.arange(samples)[None, :] + rng.random((len(q), samples))) / samples
            d = start + u[..., None] * (end - start) - q[:, None, :]
            r2 = np.einsum("bsi,bsi->bs", d, d)
            cos_p = np.maximum(np.einsum("bsi,bi->bs", d, n) / np.sqrt(r2), 0.0)
            blocked = self._occluded(np.repeat(q + 1e-6 * n, samples, axis=0), d.reshape(-1, 3)).reshape(len(q), samples)
            out[s:s + block] = power / (4 * np.pi) * length * np.where(blocked, 0.0, cos_p / r2).mean(axis=1)
        return out, time.perf_counter() - t

    def hard_visibility(self, points: np.ndarray, normals: np.ndarray, towards: np.ndarray) -> tuple[np.ndarray, float]:
        """`(visible (N,) bool, seconds)`: one ray per receiver along `towards (N, 3)` (to a
        point light: its position minus the receiver; a directional light: a long vector against
        its direction), origins lifted 1e-6 m along the normal."""
        t = time.perf_counter()
        vis = ~self._occluded(points + 1e-6 * normals, towards)
        return vis, time.perf_counter() - t
