"""Built-in test / demo configurations for the inverse solvers (no Mitsuba here).

`quad(centre, width, height, frame)` builds a rectangular `PolygonLight` vertex array;
`demo_configuration()` is the hidden "true" scene of the demo and the acceptance tests: a quad
light over a floor with a square occluder (soft shadow), and painted points chosen to cover the
ambient-only, diffuse, highlight and penumbra regions.
"""

from __future__ import annotations

import dataclasses

import numpy as np

import jaxshadow as js


def quad(centre, width: float, height: float, omega=(np.pi, 0.0, 0.0)) -> np.ndarray:
    """`(4, 3)` vertices of a `width x height` rectangle centred at `centre`, rotated by the
    rotation vector `omega` from the +z-facing xy-rectangle (default: facing down, -z)."""
    loc = np.array([[-width / 2, -height / 2, 0.0], [width / 2, -height / 2, 0.0],
                    [width / 2, height / 2, 0.0], [-width / 2, height / 2, 0.0]])
    w = np.asarray(omega, np.float64)
    t = np.linalg.norm(w)
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    R = np.eye(3) if t == 0 else np.eye(3) + np.sin(t) / t * K + (1 - np.cos(t)) / t**2 * (K @ K)
    return np.asarray(centre, np.float64) + loc @ R.T


def polygon_pose(vertices) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Centre, unit normal, unit direction of the longer side, and sorted side lengths
    `(short, long)` of a rectangle (independent of which vertex comes first)."""
    v = np.asarray(vertices, np.float64)
    c = v.mean(axis=0)
    n = np.sum(np.cross(v, np.roll(v, -1, axis=0)), axis=0)
    n /= np.linalg.norm(n)
    e1, e2 = v[1] - v[0], v[2] - v[1]
    long_ = e1 if np.linalg.norm(e1) >= np.linalg.norm(e2) else e2
    return c, n, long_ / np.linalg.norm(long_), np.sort([np.linalg.norm(e1), np.linalg.norm(e2)])


def pose_errors(fitted, true) -> dict:
    """Position error (m), normal angle (deg), long-axis angle modulo 180 deg (a rectangle is
    symmetric under a half turn), relative side-length error; `orientation_deg` is the angle
    of the rotation taking the true frame to the fitted one (normal and long axis).

    Example:
        ```python
        import numpy as np
        import inverse

        true = np.array([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]], float)
        err = inverse.pose_errors(true + [0.01, 0.0, 0.0], true)
        print(err["position"], err["orientation_deg"])   # 0.01 m, 0 deg
        ```
    """
    c1, n1, e1, s1 = polygon_pose(fitted)
    c0, n0, e0, s0 = polygon_pose(true)
    ang = lambda a, b: float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)))  # noqa: E731
    if e1 @ e0 < 0:
        e1 = -e1
    F1 = np.stack([e1, np.cross(n1, e1), n1], axis=1)
    F0 = np.stack([e0, np.cross(n0, e0), n0], axis=1)
    R = F1 @ F0.T
    rot = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
    return {
        "position": float(np.linalg.norm(c1 - c0)),
        "normal_deg": ang(n1, n0),
        "axis_deg": ang(e1, e0),
        "orientation_deg": rot,
        "size_rel": float(np.max(np.abs(s1 / s0 - 1))),
    }


@dataclasses.dataclass(frozen=True)
class Configuration:
    """A hidden true configuration: `scene` (true light), `material`, `points`, `normals`,
    `eye`, `start_scene` (the light moved 30 % of the scene size away, turned and resized)."""

    scene: js.Scene
    material: js.Material
    points: np.ndarray
    normals: np.ndarray
    eye: np.ndarray
    start_scene: js.Scene
    size: float


LIGHT_W, LIGHT_H = 1.0, 0.15  # a strip light: its in-plane rotation shows in the penumbra


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def demo_configuration(occluders: bool = True, n_points: int = 40, seed: int = 0,
                       penumbra_fraction: float = 0.25, near_fraction: float = 0.0) -> Configuration:
    """The demo / acceptance scene (see the module docstring). Deterministic for a seed.

    Example:
        ```python
        import inverse

        cfg = inverse.demo_configuration(occluders=True, n_points=40, seed=0)
        print(cfg.points.shape, len(cfg.scene.lights))   # (40, 3) receivers, the true light
        ```
    """
    rng = np.random.default_rng(seed)
    light_c = np.array([0.25, 0.15, 1.6])
    true_light = js.PolygonLight(quad(light_c, LIGHT_W, LIGHT_H, (np.pi + 0.15, 0.1, 0.3)), [20.0, 18.0, 16.0])
    occ = [quad([0.0, 0.0, 0.6], 0.5, 0.5, (0.0, 0.0, 0.0))] if occluders else None
    scene = js.Scene([true_light], occluders=occ, ambient=[0.3, 0.3, 0.3])
    material = js.Material(ka=[0.30, 0.25, 0.20], kd=[0.55, 0.45, 0.35], ks=[0.35, 0.30, 0.25],
                           exponent=30.0)
    eye = np.array([-1.5, -1.2, 1.4])
    pts, nrm = [], []
    k_amb = max(2, n_points // 10)
    k_hl = max(6, n_points // 4)
    k_pen = max(6, int(round(n_points * penumbra_fraction))) if occluders else 0
    k_near = int(round(n_points * near_fraction))
    k_dif = n_points - k_amb - k_hl - k_pen - k_near
    # Ambient only: facing away from the light.
    for _ in range(k_amb):
        pts.append(np.r_[rng.uniform(-1, 1, 2), 0.0])
        nrm.append(_unit([rng.normal() * 0.3, rng.normal() * 0.3, -1.0]))
    # Diffuse: floor and tilted patches.
    for _ in range(k_dif):
        pts.append(np.r_[rng.uniform(-1.2, 1.2, 2), rng.uniform(0, 0.3)])
        nrm.append(_unit([rng.normal() * 0.4, rng.normal() * 0.4, 1.0]))
    # Near the light (tops of tall objects, a wall): its shape and rotation matter most there.
    for _ in range(k_near):
        p = light_c + np.r_[rng.uniform(-0.5, 0.5, 2), -rng.uniform(0.35, 0.7)]
        pts.append(p)
        nrm.append(_unit(_unit(light_c - p) + 0.4 * rng.normal(size=3)))
    # Highlight region: normals near the half vector of eye and light centre, at offsets that
    # sample the lobe from its peak into its tail.
    for i in range(k_hl):
        p = np.r_[rng.uniform(-0.9, -0.3, 2), 0.0]
        h = _unit(_unit(eye - p) + _unit(light_c - p))
        off = 0.02 + 0.25 * i / max(k_hl - 1, 1)
        t = _unit(np.cross(h, rng.normal(size=3)))
        pts.append(p)
        nrm.append(_unit(np.cos(off) * h + np.sin(off) * t))
    # Penumbra: floor points around the corners of the occluder's shadow (cast from the light
    # centre), where the penumbra depends most on the light's in-plane rotation and size.
    if k_pen:
        o = quad([0.0, 0.0, 0.6], 0.5, 0.5, (0.0, 0.0, 0.0))
        corners = light_c + (o - light_c) * (light_c[2] / (light_c[2] - o[:, 2:3]))
        centre = corners.mean(axis=0)
        for i in range(k_pen):
            c = corners[i % 4]
            out = _unit(c - centre)
            perp = _unit(np.cross([0.0, 0.0, 1.0], out))
            p = c + rng.uniform(-0.12, 0.12) * out + rng.uniform(-0.15, 0.15) * perp
            pts.append(np.r_[p[:2], 0.0])
            nrm.append(np.array([0.0, 0.0, 1.0]))
    pts, nrm = np.asarray(pts), np.asarray(nrm)
    allp = np.concatenate([pts, np.asarray(true_light.vertices)] + ([occ[0]] if occ else []))
    size = float(np.linalg.norm(allp.max(0) - allp.min(0)))
    direction = _unit(np.array([0.6, -0.64, 0.48]))
    start_light = js.PolygonLight(quad(light_c + 0.3 * size * direction, 0.4, 0.4, (np.pi, 0.0, 0.0)),
                                  true_light.radiance)
    start_scene = js.Scene([start_light], occluders=occ, ambient=scene.ambient)
    return Configuration(scene, material, pts, nrm, eye, start_scene, size)


def occluded_light_problem(n_occluders: int, n_points: int = 48, seed: int = 0) -> tuple:
    """The demo's quad light and diffuse material with `n_occluders` random 0.2 x 0.2 occluders
    (heights 0.4-0.9, `seed`) over `n_points` painted points whose colours come from jaxshadow's
    own model (noise-free: for solver tests and speed benchmarks, never accuracy acceptance).

    **Returns:** `(true scene, start scene, material, PaintedTargets, scene size)`.
    """
    import jax.numpy as jnp

    from ._forward import shade
    from ._targets import PaintedTargets

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
