"""Scenes of `inverse`'s tests and benchmarks (`fit_light`, `fit_lights`): the hidden truths,
starts, receivers and candidates they share. Test support, not library: the library's own demo
scene is `inverse.demo_configuration` (`inverse/_demo_scene.py`), which these build on.
"""

from __future__ import annotations

import numpy as np

import jaxshadow as js
from inverse import demo_configuration
from inverse._demo_scene import polygon_pose, quad

__all__ = ["THREE_LIGHTS_EYE", "THREE_LIGHTS_OCCLUDERS", "SHADOW_OCCLUDER", "floor_receivers", "near_light_candidates",
           "occluded_light_problem", "one_light_shadow_case", "polygon_pose", "quad", "shadow_outline",
           "three_lights_scene", "three_lights_start", "turned"]


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def occluded_light_problem(n_occluders: int, n_points: int = 48, seed: int = 0) -> tuple:
    """The demo's quad light and diffuse material with `n_occluders` random 0.2 x 0.2 occluders
    (heights 0.4-0.9, `seed`) over `n_points` painted points whose colours come from jaxshadow's
    own model (noise-free: for solver tests and speed benchmarks, never accuracy acceptance).

    **Returns:** `(true scene, start scene, material, PaintedTargets, scene size)`.
    """
    import jax.numpy as jnp

    from inverse import PaintedTargets
    from inverse._forward import shade

    cfg = demo_configuration(occluders=False, n_points=n_points, seed=3)
    occ = None
    if n_occluders:
        rng = np.random.default_rng(seed)
        occ = [quad([*rng.uniform(-0.6, 0.6, 2), rng.uniform(0.4, 0.9)], 0.2, 0.2, (0.0, 0.0, rng.uniform(0, 1)))
               for _ in range(n_occluders)]
    scene = js.Scene(cfg.scene.lights, occluders=occ, ambient=cfg.scene.ambient)
    start = js.Scene(cfg.start_scene.lights, occluders=occ, ambient=cfg.scene.ambient)
    material = js.Material(ka=cfg.material.ka, kd=cfg.material.kd, ks=0.0, exponent=1.0)
    n = len(cfg.points)
    col = np.asarray(shade(scene, material, jnp.asarray(cfg.points), jnp.asarray(cfg.normals),
                           jnp.asarray(np.broadcast_to(cfg.eye, (n, 3))), with_specular=False))
    return scene, start, material, PaintedTargets(cfg.points, cfg.normals, col, cfg.eye), cfg.size


THREE_LIGHTS_OCCLUDERS = [quad([-0.5, 0.3, 0.6], 0.4, 0.4, (0, 0, 0.3)), quad([0.6, -0.2, 0.5], 0.35, 0.3, (0, 0, -0.2)),
                          quad([0.1, -0.7, 0.7], 0.3, 0.3, (0, 0, 0.0))]
THREE_LIGHTS_EYE = np.array([0.0, -3.0, 2.5])


def three_lights_scene() -> js.Scene:
    """The hidden truth of the several-lights tests and benchmark (`fit_lights`): two tilted quad
    lights and a point light over a floor, three square occluders (soft shadows)."""
    a = js.PolygonLight(quad([-0.6, 0.4, 1.8], 0.6, 0.3, (np.pi + 0.1, 0.05, 0.4)), [6.0, 5.5, 5.0])
    b = js.PolygonLight(quad([0.8, -0.3, 1.6], 0.4, 0.4, (np.pi - 0.15, 0.1, -0.3)), [4.0, 4.0, 4.5])
    c = js.PointLight([0.1, 0.9, 1.4], [1.5, 1.5, 1.5])
    return js.Scene([a, b, c], occluders=THREE_LIGHTS_OCCLUDERS, ambient=0.1)


def floor_receivers(n: int = 80, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """`n` floor points in [-1.5, 1.5]^2 (many in the penumbrae of `three_lights_scene`) with
    normals tilted up to ~20 degrees: `(points (n, 3), unit normals (n, 3))`."""
    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(-1.5, 1.5, (n, 2)), np.zeros(n)]
    nrm = rng.normal(size=(n, 3)) * 0.35 + [0.0, 0.0, 1.0]
    return pts, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def three_lights_start(true: js.Scene, shift: float, brightness=(0.7, 1.4, 0.6)) -> js.Scene:
    """The lights of `true` moved `shift` (m) in three different directions, at `brightness`
    times their power (the starting scene of `fit_lights` tests)."""
    d = np.array([[0.6, -0.64, 0.48], [-0.5, 0.7, 0.5], [0.7, 0.6, -0.4]])
    d = shift * d / np.linalg.norm(d, axis=1, keepdims=True)
    a, b, c = true.lights
    return js.Scene([js.PolygonLight(np.asarray(a.vertices) + d[0], brightness[0] * np.asarray(a.radiance)),
                     js.PolygonLight(np.asarray(b.vertices) + d[1], brightness[1] * np.asarray(b.radiance)),
                     js.PointLight(np.asarray(c.position) + d[2], brightness[2] * np.asarray(c.intensity))],
                    occluders=true.occluders, ambient=true.ambient)


SHADOW_OCCLUDER = [quad([0.1, 0.0, 0.6], 0.5, 0.4, (0.0, 0.0, 0.3))]


def turned(d, degrees: float, axis) -> np.ndarray:
    """`d (3,)` turned by `degrees` about the unit vector perpendicular to `d` and `axis`."""
    d = np.asarray(d, np.float64)
    k = _unit(np.cross(d, axis))
    t = np.deg2rad(degrees)
    return d * np.cos(t) + np.cross(k, d) * np.sin(t) + k * (k @ d) * (1 - np.cos(t))


def shadow_outline(occluder, light) -> np.ndarray:
    """`(k, 3)` the occluder polygon projected onto the floor z = 0 along a `DirectionalLight`'s
    direction, or from a `LinearLight`'s midpoint (its shadow's core)."""
    occ = np.asarray(occluder, np.float64)
    if isinstance(light, js.DirectionalLight):
        d = np.asarray(light.direction, np.float64)
        return occ - (occ[:, 2:3] / d[2]) * d
    s = 0.5 * (np.asarray(light.start, np.float64) + np.asarray(light.end, np.float64))
    return s + (occ - s) * (s[2] / (s[2] - occ[:, 2:3]))


def one_light_shadow_case(kind: str) -> tuple:
    """A directional (`kind="directional"`) or segment (`"segment"`) light over a floor with one
    occluder (`SHADOW_OCCLUDER`): the hidden truth, a start (the direction turned 4 degrees at 70 %
    power; the segment moved 3 % of the scene size, turned 3 degrees, 4 % longer, at 2/3 power),
    and 64 floor receivers: 40 with tilted normals (`floor_receivers(40, seed=4)`) and 24 flat
    ones around the occluder's shadow (`shadow_outline`).

    **Returns:** `(true Scene, start Scene, points (64, 3), normals (64, 3))`.
    """
    occ = SHADOW_OCCLUDER
    if kind == "directional":
        d = _unit([0.35, 0.25, -1.0])
        true_light = js.DirectionalLight(d, [2.0, 1.9, 1.7])
        start_light = js.DirectionalLight(turned(d, 4.0, [0.0, 1.0, 0.3]), 0.7 * np.array([2.0, 1.9, 1.7]))
    elif kind == "segment":
        a, b = np.array([-0.5, 0.2, 1.6]), np.array([0.4, 0.5, 1.7])
        true_light = js.LinearLight(a, b, [3.0, 3.0, 2.8])
        size = 4.369  # m: the scene's bounding-box diagonal, about
        c, d, length = 0.5 * (a + b), _unit(b - a), np.linalg.norm(b - a)
        d2, c2, l2 = turned(d, 3.0, [0.0, 0.0, 1.0]), c + 0.03 * size * _unit([0.6, -0.6, 0.5]), 1.04 * length
        start_light = js.LinearLight(c2 - 0.5 * l2 * d2, c2 + 0.5 * l2 * d2, np.array([3.0, 3.0, 2.8]) * 2 / 3)
    else:
        raise ValueError(f"one_light_shadow_case: kind must be 'directional' or 'segment', got {kind!r}.")
    foot = shadow_outline(occ[0], true_light).mean(axis=0)
    pts, nrm = floor_receivers(40, seed=4)
    near = np.c_[foot[:2] + np.random.default_rng(5).uniform(-0.4, 0.4, (24, 2)), np.zeros(24)]
    pts, nrm = np.concatenate([pts, near]), np.concatenate([nrm, np.tile([0.0, 0.0, 1.0], (24, 1))])
    true = js.Scene([true_light], occluders=occ, ambient=0.1)
    start = js.Scene([start_light], occluders=occ, ambient=0.1)
    return true, start, pts, nrm


def near_light_candidates(centres, radii=(0.3, 0.5, 0.8), drops=(0.15, 0.35, 0.6),
                          n_around: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Candidate receivers around (estimated) light centres, where a light's orientation, size
    and power change the shading most (its near field, seen at grazing angles): for each centre
    `(3,)`, points `n_around` around it at horizontal `radii` (m) and `drops` (m) below it, each
    with two normals, towards the centre and up.

    **Returns:** `(points (K, 3), unit normals (K, 3))`, K = 2 len(centres) len(radii) len(drops) n_around.
    """
    pts, nrm = [], []
    for c in np.asarray(centres, np.float64).reshape(-1, 3):
        for r in radii:
            for a in np.linspace(0.0, 2 * np.pi, n_around, endpoint=False):
                for dz in drops:
                    p = c + [r * np.cos(a), r * np.sin(a), -dz]
                    pts += [p, p]
                    nrm += [_unit(c - p), np.array([0.0, 0.0, 1.0])]
    return np.asarray(pts), np.asarray(nrm)
