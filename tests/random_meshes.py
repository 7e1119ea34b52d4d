"""Random occluder meshes and receivers for the mesh property suite and the engine fuzzing:
one definition each. Everything is drawn from a NumPy generator, so a hypothesis draw of one seed
(plus a few choices) reproduces a scene; trimesh builds the base shapes.

Scenes stand between a floor (z = 0, the receivers' plane) and a light facing down at height
`LIGHT_Z`; `place` fits a shape into that slab (or makes it touch the floor or the light's plane).
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, Phase, settings

LIGHT_Z = 2.0
SHAPES = ("icosphere", "uv_sphere", "capsule", "torus", "box", "cylinder", "annulus")


def light(rng: np.random.Generator, half: float = 0.4) -> np.ndarray:
    """A horizontal convex quad or pentagon of half-size `half` at `LIGHT_Z`, lit side down
    (clockwise seen from above)."""
    k = int(rng.integers(4, 6))
    ang = np.sort(rng.uniform(0, 2 * np.pi, k))
    while np.max(np.diff(np.r_[ang, ang[0] + 2 * np.pi])) > 0.9 * np.pi:
        ang = np.sort(rng.uniform(0, 2 * np.pi, k))
    r = half * rng.uniform(0.7, 1.3)
    v = np.stack([r * np.cos(ang), r * np.sin(ang), np.full(k, LIGHT_Z)], axis=1)
    return v[::-1].copy()


def base_shape(rng: np.random.Generator, shape: str, fine: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A closed, outward-oriented trimesh shape `(V, F)` of unit size about the origin, then
    displaced smoothly along the normals (non-convex for the curved shapes)."""
    import trimesh

    c = trimesh.creation
    if shape == "icosphere":
        m = c.icosphere(subdivisions=3 if fine else int(rng.integers(1, 3)))
    elif shape == "uv_sphere":
        m = c.uv_sphere(count=[24, 24] if fine else [int(rng.integers(6, 14))] * 2)
    elif shape == "capsule":
        m = c.capsule(height=1.0, radius=0.4, count=[16, 16] if fine else [8, 8])
    elif shape == "torus":
        m = c.torus(major_radius=0.5, minor_radius=0.2, major_sections=24 if fine else 12,
                    minor_sections=12 if fine else 6)
    elif shape == "box":
        m = c.box(extents=rng.uniform(0.4, 1.0, 3))
        m = m.subdivide() if not fine else m.subdivide().subdivide().subdivide()
    elif shape == "cylinder":
        m = c.cylinder(radius=0.4, height=0.6, sections=32 if fine else int(rng.integers(5, 16)))
    else:
        m = c.annulus(r_min=0.2, r_max=0.5, height=0.3, sections=32 if fine else 12)
    v = np.asarray(m.vertices, np.float64)
    f = np.asarray(m.faces, np.int64)
    if shape in ("icosphere", "uv_sphere", "capsule", "torus") and rng.random() < 0.8:
        w = rng.uniform(1.0, 4.0, 3)
        phase = rng.uniform(0, 2 * np.pi, 3)
        d = 0.15 * np.sin(w[0] * v[:, 0] + phase[0]) * np.cos(w[1] * v[:, 1] + phase[1]) + 0.1 * np.sin(w[2] * v[:, 2] + phase[2])
        nrm = np.asarray(m.vertex_normals, np.float64)
        v = v + 0.5 * d[:, None] * nrm * np.min(np.ptp(v, axis=0))
    v = v - v.mean(axis=0)
    return v / np.ptp(v, axis=0).max(), f


def rotate(rng: np.random.Generator, v: np.ndarray) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return v @ q.T


def place(v: np.ndarray, size: float, centre_xy, touch: str | None, z: float) -> np.ndarray:
    """`v` scaled to `size`, centred at `centre_xy`, with its lowest point on the floor (`touch
    == "floor"`), its highest in the light's plane (`"light"`), or its centre at height `z`."""
    v = v * size
    v = v + np.r_[np.asarray(centre_xy, np.float64) - v[:, :2].mean(axis=0), 0.0]
    if touch == "floor":
        v[:, 2] -= v[:, 2].min()
    elif touch == "light":
        v[:, 2] += LIGHT_Z - v[:, 2].max()
    else:
        v[:, 2] += z - (v[:, 2].max() + v[:, 2].min()) / 2
    return v


def mesh_scene(rng: np.random.Generator, kind: str, fine: bool = False,
               shapes: tuple[str, ...] = SHAPES) -> list[tuple[np.ndarray, np.ndarray]]:
    """Occluder meshes `[(V, F), ...]` for one scene.

    - `closed`: one displaced closed shape floating between floor and light;
    - `open`: the same with faces cut away (below a height, or at random) and some flipped;
    - `components`: two or three closed or open shapes side by side;
    - `floor`, `light`: a shape touching the floor, or the light's plane;
    """
    n = int(rng.integers(2, 4)) if kind == "components" else 1
    out = []
    for i in range(n):
        shape = shapes[int(rng.integers(len(shapes)))]
        v, f = base_shape(rng, shape, fine)
        v = rotate(rng, v)
        if kind in ("open", "components") and (kind == "open" or rng.random() < 0.5):
            cut = rng.random()
            if cut < 0.4:
                zc = v[f][:, :, 2].mean(axis=1)
                f = f[zc > np.quantile(zc, rng.uniform(0.1, 0.5))]
            elif cut < 0.8:
                f = f[rng.random(len(f)) > 0.3]
            flip = rng.random(len(f)) < 0.2
            f[flip] = f[flip][:, ::-1]
        touch = {"floor": "floor", "light": "light"}.get(kind)
        size = rng.uniform(0.3, 0.9) if n == 1 else rng.uniform(0.25, 0.5)
        xy = rng.uniform(-0.3, 0.3, 2) if n == 1 else np.array([np.cos(2 * np.pi * i / n), np.sin(2 * np.pi * i / n)]) * 0.45
        z = rng.uniform(0.5 + size / 2, LIGHT_Z - 0.2 - size / 2) if size < LIGHT_Z - 0.7 else 1.0
        out.append((place(v, size, xy, touch, z), f))
    return out


def soup(rng: np.random.Generator, meshes: list[tuple[np.ndarray, np.ndarray]], duplicates: float = 0.1) -> np.ndarray:
    """The meshes' triangles as one `(T, 3, 3)` soup with a fraction of them duplicated (exact
    copies, some reversed) and shuffled."""
    tris = np.concatenate([v[f] for v, f in meshes])
    k = int(duplicates * len(tris))
    dup = tris[rng.integers(0, len(tris), k)]
    rev = rng.random(k) < 0.5
    dup[rev] = dup[rev][:, ::-1]
    tris = np.concatenate([tris, dup])
    return tris[rng.permutation(len(tris))]


def floor_receivers(rng: np.random.Generator, n: int, half: float = 1.2, tilt: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    p = np.c_[rng.uniform(-half, half, (n, 2)), np.zeros(n)]
    nrm = np.c_[rng.uniform(-tilt, tilt, (n, 2)), np.ones(n)]
    return p, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def face_normals(tris: np.ndarray) -> np.ndarray:
    c = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    return c / np.linalg.norm(c, axis=1, keepdims=True)


def surface_receivers(rng: np.random.Generator, tris: np.ndarray, n: int, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Receivers on the triangles `tris (T, 3, 3)` with the face normal: inside a face
    (`"face"`, random barycentric point) or on an edge (`"edge"`, normal of that face)."""
    idx = rng.integers(0, len(tris), n)
    t = tris[idx]
    if where == "face":
        b = rng.dirichlet(np.ones(3), n)
    else:
        s = rng.uniform(0.1, 0.9, n)
        b = np.stack([1 - s, s, np.zeros(n)], axis=1)
    return np.einsum("nk,nkd->nd", b, t), face_normals(t)


def event_receivers(rng: np.random.Generator, light_v: np.ndarray, tris: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Receivers on the floor on the line through a light vertex and an occluder vertex (where
    the projections of the two coincide: a vertex of the visible region's arrangement), or on
    the plane through a light vertex and an occluder edge."""
    lv = light_v[rng.integers(0, len(light_v), n)]
    t = tris[rng.integers(0, len(tris), n)]
    s = np.where(rng.random(n) < 0.5, 0.0, rng.uniform(0, 1, n))
    o = t[:, 0] + s[:, None] * (t[:, 1] - t[:, 0])
    d = o - lv
    ok = d[:, 2] < 0
    d = np.where(ok[:, None], d, [0.0, 0.0, -1.0])
    lam = -lv[:, 2] / d[:, 2]
    p = lv + lam[:, None] * d
    p[:, 2] = 0.0
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    return p, nrm


def profile(n: int, derandomize: bool) -> settings:
    """Hypothesis settings of the mesh suites: `n` examples; derandomized (the fixed-seed CI
    profile: explicit, reused and generated examples only) or random (the long profile)."""
    return settings(max_examples=n, derandomize=derandomize, deadline=None, database=None, print_blob=True,
                    phases=(Phase.explicit, Phase.reuse, Phase.generate) if derandomize else tuple(Phase),
                    suppress_health_check=list(HealthCheck))
