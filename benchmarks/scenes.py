"""Scenes shared by the benchmarks: a floor under a quad light and random boxes (seeded).

`box_field(n_boxes)` is the mesh-scale scene of the shadows-at-scale study: a 0.6 m square
light at z = 2 facing down over a [-4, 4]^2 floor, and `n_boxes` closed boxes (12 triangles
each, footprints 0.1-0.35 m, standing on the floor, heights 0.3-1.2 m) clustered over the
middle of the floor.
"""

from __future__ import annotations

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
