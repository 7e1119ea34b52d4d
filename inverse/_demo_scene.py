"""The demo's scene (`jaxshadow demo`, `inverse.demo_configuration`) and the pose metric of its report.

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


SQUARE_REL = 1e-9  # sides equal to this relative tolerance: a square (`pose_errors`)


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
    symmetric under a half turn; a square, sides equal to `SQUARE_REL`, under a quarter turn),
    relative side-length error; `orientation_deg` is the angle
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
    if s0[0] >= (1.0 - SQUARE_REL) * s0[1] and s1[0] >= (1.0 - SQUARE_REL) * s1[1]:
        # Squares are symmetric under a quarter turn: which side is "longer" is rounding. The
        # fitted side nearest the true one stands for the axis.
        v = np.asarray(fitted, np.float64)
        sides = [(v[1] - v[0]) / np.linalg.norm(v[1] - v[0]), (v[2] - v[1]) / np.linalg.norm(v[2] - v[1])]
        e1 = max(sides, key=lambda d: abs(float(d @ e0)))
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
