"""Random held-out-style scenes for `fit_lights`' tests and benchmark: lights of given kinds over
a floor, a floating box occluder (its six faces), floor targets around it, and starts moved a
fraction of the scene size away. The solver never sees the truth; the targets are painted by
`js.shade` (noise-free) from it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

import jaxshadow as js

from .inverse_scenes import quad

EYE = np.array([0.0, -3.0, 2.5])


@dataclasses.dataclass(frozen=True)
class RandomCase:
    """`true` (the hidden scene), `points (N, 3)`, `normals (N, 3)`, `eye (3,)`, `material`,
    `kinds` (one of `"polygon"`, `"point"`, `"segment"` per light)."""

    true: js.Scene
    points: np.ndarray
    normals: np.ndarray
    eye: np.ndarray
    material: js.Material
    kinds: tuple


def box_faces(lo, hi) -> list[np.ndarray]:
    """The six faces `(4, 3)` of the axis-aligned box `lo (3,)`-`hi (3,)`."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    c = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], np.float64)
    faces = ((0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7))
    return [c[list(f)] for f in faces]


def random_case(seed: int, kinds=("polygon", "point"), n_targets: int = 60) -> RandomCase:
    """A quad / point / segment light per entry of `kinds` (grey, random powers), 1.0-2.0 m above
    a floor `[-1.5, 1.5]^2`, a floating box (0.3-0.5 m wide, 0.35-0.65 m high) and `n_targets`
    floor targets (normals tilted ~14 degrees RMS per axis) outside the box's footprint; a coloured
    diffuse material. Deterministic for a seed."""
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-0.5, 0.5, 2)
    half = rng.uniform(0.15, 0.25, 2)
    lo, hi = np.r_[centre - half, 0.35], np.r_[centre + half, 0.65]
    lights = []
    for kind in kinds:
        c = np.r_[rng.uniform(-1.0, 1.0, 2), rng.uniform(1.0, 2.0)]
        grey = float(rng.uniform(2.0, 6.0))
        if kind == "polygon":
            w, h = rng.uniform(0.3, 0.6, 2)
            omega = (np.pi + rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(-np.pi, np.pi))
            lights.append(js.PolygonLight(quad(c, w, h, omega), [grey] * 3))
        elif kind == "point":
            lights.append(js.PointLight(c, [grey / 2] * 3))
        elif kind == "segment":
            a = rng.uniform(0.0, np.pi)
            d = np.array([np.cos(a), np.sin(a), rng.uniform(-0.15, 0.15)])
            d *= 0.5 * rng.uniform(0.4, 0.8) / np.linalg.norm(d)
            lights.append(js.LinearLight(c - d, c + d, [grey / 2] * 3))
        else:
            raise ValueError(f"random_case: unknown light kind {kind!r}.")
    pts = []
    while len(pts) < n_targets:
        p = rng.uniform(-1.5, 1.5, 2)
        if np.any(np.abs(p - centre) > half + 0.02):
            pts.append(np.r_[p, 0.0])
    nrm = rng.normal(size=(n_targets, 3)) * 0.25 + [0.0, 0.0, 1.0]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    material = js.Material(ka=[0.2, 0.2, 0.2], kd=[0.6, 0.5, 0.4], ks=0.0, exponent=1.0)
    true = js.Scene(lights, occluders=box_faces(lo, hi), ambient=0.1)
    return RandomCase(true, np.asarray(pts), nrm, EYE, material, tuple(kinds))


def shifted_start(true: js.Scene, distance: float, seed: int) -> js.Scene:
    """`true` with every light moved `distance` (m) in a random direction (kept above the floor:
    the upward component made non-negative), at 0.5-2x its power."""
    rng = np.random.default_rng(seed + 1000)
    out = []
    for light in true.lights:
        d = rng.normal(size=3)
        d[2] = abs(d[2])
        d *= distance / np.linalg.norm(d)
        f = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
        if isinstance(light, js.PolygonLight):
            out.append(js.PolygonLight(np.asarray(light.vertices) + d, f * np.asarray(light.radiance)))
        elif isinstance(light, js.PointLight):
            out.append(js.PointLight(np.asarray(light.position) + d, f * np.asarray(light.intensity)))
        else:
            out.append(js.LinearLight(np.asarray(light.start) + d, np.asarray(light.end) + d,
                                      f * np.asarray(light.power)))
    return js.Scene(out, occluders=true.occluders, ambient=true.ambient)


def light_errors(fitted, true) -> tuple[float, float]:
    """`(position error (m), relative power error)` of one fitted light against the true one:
    the polygon's vertex set (each vertex to the nearest true vertex: the fit may turn the quad
    by a symmetry), the segment's ends (either order), the point's position."""
    if isinstance(true, js.PolygonLight):
        a, b = np.asarray(fitted.vertices), np.asarray(true.vertices)
        pos = float(max(np.min(np.linalg.norm(a[:, None] - b[None], axis=-1), axis=1).max(),
                        np.min(np.linalg.norm(b[:, None] - a[None], axis=-1), axis=1).max()))
        pw = np.asarray(fitted.radiance) / np.asarray(true.radiance)
    elif isinstance(true, js.PointLight):
        pos = float(np.linalg.norm(np.asarray(fitted.position) - np.asarray(true.position)))
        pw = np.asarray(fitted.intensity) / np.asarray(true.intensity)
    else:
        a = np.stack([np.asarray(fitted.start), np.asarray(fitted.end)])
        b = np.stack([np.asarray(true.start), np.asarray(true.end)])
        pos = float(min(np.linalg.norm(a - b, axis=1).max(), np.linalg.norm(a[::-1] - b, axis=1).max()))
        pw = np.asarray(fitted.power) / np.asarray(true.power)
    return pos, float(np.max(np.abs(pw - 1.0)))
