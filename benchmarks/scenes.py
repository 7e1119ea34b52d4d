"""Shapes and scenes shared by the tests and the benchmarks (one definition each; tests import
them as `benchmarks.scenes`).

Geometry: `unit`, `rotation`, `random_rotation`, random convex polygons (`random_angles`,
`random_convex`), Sutherland-Hodgman half-space clipping (`clip_halfspace`, plain arithmetic: NumPy
or mpmath), a UV sphere (`uv_sphere`), an axis-aligned rectangle light (`square_light`), a box
(`box`).

Scenes: `box_field(n_boxes)` is the mesh-scale scene of the shadows-at-scale study: a 0.6 m square
light at z = 2 facing down over a [-4, 4]^2 floor, and `n_boxes` closed boxes (12 triangles
each, footprints 0.1-0.35 m, standing on the floor, heights 0.3-1.2 m) clustered over the
middle of the floor; `floor_receivers` draws points on that floor.

Forward-model benchmark inputs (`throughput`, `error_vs_time`): the unit quad `QUAD`, the segment
`SEG_A`-`SEG_B`, tilted floor `receivers`, `regular_polygon`, an `occluder_grid` of small quads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Counter-clockwise seen from below (the lit side faces -z).
LIGHT = np.array([[-0.3, -0.3, 2.0], [-0.3, 0.3, 2.0], [0.3, 0.3, 2.0], [0.3, -0.3, 2.0]])
FLOOR = 4.0
BOX_FACES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                      [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


@dataclass
class BoxField:
    light: np.ndarray  # (4, 3)
    boxes: list  # [(vertices (8, 3), faces (12, 3))]

    @property
    def triangles(self) -> np.ndarray:
        """All box triangles `(12 n, 3, 3)`, outward (counter-clockwise seen from outside)."""
        return np.concatenate([v[f] for v, f in self.boxes]) if self.boxes else np.zeros((0, 3, 3))


def box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], float)
    return v, BOX_FACES.copy()


def box_field(n_boxes: int, seed: int = 0, spread: float = 1.5) -> BoxField:
    """`n_boxes` boxes with centres normally distributed (sigma `spread` m) over the floor's
    middle, clipped to [-3.5, 3.5]^2."""
    rng = np.random.default_rng(seed)
    boxes = []
    for _ in range(n_boxes):
        c = np.clip(rng.normal(0.0, spread, 2), -3.5, 3.5)
        half = rng.uniform(0.05, 0.175, 2)
        h = rng.uniform(0.3, 1.2)
        boxes.append(box((c[0] - half[0], c[1] - half[1], 0.0), (c[0] + half[0], c[1] + half[1], h)))
    return BoxField(LIGHT.copy(), boxes)


def floor_receivers(n: int, seed: int = 1, grazing: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """`n` uniform points on the floor `[-4, 4]^2` with normal +z; a fraction `grazing` of them
    get normals tilted 60-89 degrees (their horizon cuts the light)."""
    rng = np.random.default_rng(seed)
    p = np.zeros((n, 3))
    p[:, :2] = rng.uniform(-FLOOR, FLOOR, (n, 2))
    nrm = np.zeros((n, 3))
    nrm[:, 2] = 1.0
    k = int(round(grazing * n))
    if k:
        tilt = np.radians(rng.uniform(60, 89, k))
        az = rng.uniform(0, 2 * np.pi, k)
        nrm[:k] = np.stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)], axis=1)
    return p, nrm


# --------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------


def unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def rotation(axis, angle):
    x, y, z = unit(axis)
    c, s = math.cos(angle), math.sin(angle)
    return np.array(
        [
            [c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
            [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
            [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)],
        ]
    )


def random_rotation(rng, max_angle):
    """A rotation by an angle uniform in `[-max_angle, max_angle]` about a random axis."""
    axis = rng.normal(size=3)
    return rotation(axis, rng.uniform(-max_angle, max_angle))


def random_angles(rng, k, max_gap=2 * math.pi):
    """`k` sorted angles uniform in `[0, 2 pi)`, drawn again while two neighbours are more than
    `max_gap` apart (with `max_gap < pi` the polygon on them contains its centre)."""
    while True:
        ang = np.sort(rng.uniform(0, 2 * np.pi, size=k))
        if np.max(np.diff(np.concatenate([ang, ang[:1] + 2 * np.pi]))) <= max_gap:
            return ang


def random_convex(rng, k, radii, centre=(0.0, 0.0, 0.0), max_tilt=math.pi, max_gap=2 * math.pi):
    """A random convex `k`-gon `(k, 3)`: points of an ellipse with semi-axes `radii = (rx, ry)`
    (or `radii(rng)`, drawn after the angles) at `random_angles`, counter-clockwise about +z
    before `random_rotation(rng, max_tilt)`, then moved to `centre`."""
    ang = random_angles(rng, k, max_gap)
    rx, ry = radii(rng) if callable(radii) else radii
    loc = np.stack([rx * np.cos(ang), ry * np.sin(ang), np.zeros(k)], axis=1)
    return loc @ random_rotation(rng, max_tilt).T + np.asarray(centre, np.float64)


def clip_halfspace(poly, p, n):
    """Sutherland-Hodgman: the part of a convex polygon (a sequence of 3-D points) with
    `n . (x - p) >= 0`, as a list of points. Plain arithmetic on the coordinates, so it works
    on NumPy arrays and on lists of mpmath numbers alike."""
    def side(x):
        return sum(ni * (xi - pi) for ni, xi, pi in zip(n, x, p, strict=True))

    out = []
    k = len(poly)
    for i in range(k):
        a, b = poly[i], poly[(i + 1) % k]
        da, db = side(a), side(b)
        if da >= 0:
            out.append(a)
        if (da >= 0) != (db >= 0):
            t = da / (da - db)
            out.append([x + t * (y - x) for x, y in zip(a, b, strict=True)])
    return out


def uv_sphere(centre, radius, n_lat, n_lon):
    """Closed triangle mesh of a UV sphere with outward (right-hand-rule) normals."""
    c = np.asarray(centre, np.float64)

    def v(i, j):
        th = math.pi * i / n_lat
        ph = 2 * math.pi * j / n_lon
        return c + radius * np.array(
            [math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)]
        )

    tris = []
    for i in range(n_lat):
        for j in range(n_lon):
            a, b, cc, d = v(i, j), v(i + 1, j), v(i + 1, j + 1), v(i, j + 1)
            if i > 0:
                tris.append([a, b, d])
            if i < n_lat - 1:
                tris.append([b, cc, d])
    tris = np.array(tris)
    out = np.einsum(
        "ti,ti->t", np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), tris.mean(1) - c
    )
    tris[out < 0] = tris[out < 0][:, ::-1]
    return tris


def square_light(x0, x1, y0, y1, z):
    """Axis-aligned rectangle in the plane z, counter-clockwise seen from below (it emits
    towards -z, the right-hand-rule normal of its vertex order)."""
    return np.array([[x0, y0, z], [x0, y1, z], [x1, y1, z], [x1, y0, z]], dtype=np.float64)


# --------------------------------------------------------------------------------------
# Forward-model benchmark inputs (throughput, error_vs_time)
# --------------------------------------------------------------------------------------

QUAD = np.array([[-0.5, -0.5, 1.0], [-0.5, 0.5, 1.0], [0.5, 0.5, 1.0], [0.5, -0.5, 1.0]])
SEG_A = np.array([-1.0, 0.3, 1.0])
SEG_B = np.array([1.0, 0.5, 1.2])


def receivers(n: int, dtype, seed: int = 0):
    """Points on the floor z = 0 around the light (some see it cut by their horizon)."""
    rng = np.random.default_rng(seed)
    p = np.zeros((n, 3))
    p[:, :2] = rng.uniform(-2.0, 2.0, (n, 2))
    nrm = np.zeros((n, 3))
    nrm[:, :2] = rng.normal(scale=0.5, size=(n, 2))
    nrm[:, 2] = 1.0
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return p.astype(dtype), nrm.astype(dtype)


def regular_polygon(k: int, radius: float = 0.6, z: float = 1.0) -> np.ndarray:
    t = -2 * np.pi * np.arange(k) / k
    return np.stack([radius * np.cos(t), radius * np.sin(t), np.full(k, z)], axis=1)


def occluder_grid(m: int) -> np.ndarray:
    """`m` small quads halfway between the floor and the light, (m, 4, 3)."""
    side = int(np.ceil(np.sqrt(m)))
    out = []
    for i in range(m):
        cx = -0.4 + 0.8 * ((i % side) + 0.5) / side
        cy = -0.4 + 0.8 * ((i // side) + 0.5) / side
        h = 0.3 / side
        out.append([[cx - h, cy - h, 0.5], [cx - h, cy + h, 0.5], [cx + h, cy + h, 0.5], [cx + h, cy - h, 0.5]])
    return np.asarray(out)
