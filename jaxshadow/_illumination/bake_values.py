"""Values shared by a bake chunk's planar and curved meshing: the scene per light, exact irradiance
in padded batches, points on an edge, and the points of a light a shadow volume is built from."""

from __future__ import annotations

from typing import Any

import numpy as np

from .._scene.model import Scene

MIN_BATCH = 256  # smallest padded batch of `_values`
_CODE = 1 << 31  # an edge (a, b) of local vertex ids is the code a * _CODE + b


def _light_scenes(scene: Scene) -> list[Scene]:
    import equinox as eqx

    return [eqx.tree_at(lambda s: s.lights, scene, (light,)) for light in scene.lights]


def _values(scenes: list[Scene], points: np.ndarray, normals: np.ndarray, chunk: int = 1 << 15) -> np.ndarray:
    """`(n, L, 3)` exact irradiance per light (W/m^2). Batches are padded to a power of two
    (at least `MIN_BATCH`): the engine compiles per batch shape, and a bake calls this with
    every count of points."""
    from .._shading.shade import irradiance

    n = points.shape[0]
    out = np.zeros((n, len(scenes), 3))
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        size = max(MIN_BATCH, 1 << (e - s - 1).bit_length())
        pad = size - (e - s)
        p = np.concatenate([points[s:e], np.repeat(points[s:s + 1], pad, axis=0)])
        q = np.concatenate([normals[s:e], np.repeat(normals[s:s + 1], pad, axis=0)])
        for li, sc in enumerate(scenes):
            out[s:e, li] = np.asarray(irradiance(sc, p, q), np.float64)[:e - s]
    return out


def _edge_param(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Parameter of points `p (n, 3)` along a -> b and their distance to the segment."""
    d = b - a
    t = (p - a) @ d / (d @ d)
    foot = a + np.clip(t, 0, 1)[:, None] * d
    return t, np.linalg.norm(p - foot, axis=1)


def _on_point(pos: np.ndarray, ka: int, kb: int, t: float) -> np.ndarray:
    """The point at parameter `t` of the welded edge `ka < kb` (endpoints exactly at 0 and 1)."""
    if t == 0.0:
        return pos[ka].copy()
    if t == 1.0:
        return pos[kb].copy()
    return pos[ka] + t * (pos[kb] - pos[ka])


ON_SURFACE = 2.0**-18  # `js.irradiance`'s on-surface distance, relative to the coordinates' magnitude


def _light_points(light: Any, pts: np.ndarray, reach: float) -> np.ndarray:
    """Points whose convex hull with the receiver points `pts` holds every segment from a
    receiver point to the light (for a directional light: up to `reach` towards it)."""
    from .._scene.model import DirectionalLight, LinearLight, PointLight, PolygonLight

    if isinstance(light, PolygonLight):
        return np.asarray(light.vertices, np.float64)
    if isinstance(light, LinearLight):
        return np.stack([np.asarray(light.start, np.float64), np.asarray(light.end, np.float64)])
    if isinstance(light, PointLight):
        return np.asarray(light.position, np.float64)[None, :]
    assert isinstance(light, DirectionalLight)
    d = np.asarray(light.direction, np.float64)
    return pts - reach * d / np.linalg.norm(d)

