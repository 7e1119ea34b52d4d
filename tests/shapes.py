"""Geometry shared by several test modules (meshes, rotations)."""

import math

import numpy as np


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
