"""The host shadow engine on receivers in and near the planes of faces of closed meshes, above all
non-convex ones with float32 values (meshes read from files).

A receiver closer to a face's plane than the on-surface distance (2^-18 S for a face of float32
values: about 2e-6 m for these 0.5 m meshes) lies on that face: the face is dropped, by the host
engine and the device kernel alike. Where the receiver is in fact in front of the face, by less
than that distance, the face's projection, a wedge, is then blocked only by the mesh's faces
behind it. The device kernel keeps every face. The host engine drops the back faces of a closed
mesh seen from outside its box, and must keep them for a mesh one of whose faces holds the
receiver in its plane, or the wedge reads lit: 5.1e-3 of the irradiance 1e-6 m in front of an L
prism's side, 2.1e-3 beside a 9-sided annulus, 9.3e-4 1e-3 m in front of the L prism's side
beside a convex corner (where the receiver lies 1.7e-6 m in front of the neighbouring side's
plane), and, for a segment light (whose candidate faces drop back faces the same way), 0.83 1e-7
m in front of a float32 box's side. The reference is the device kernel (`js.visible_form_factor`
for polygon lights, `ShadowOptions(engine="device")` for the other kinds): every face clipped
independently, no solids, no culling. Host and device must agree to 1e-9 of the largest value
among a case's receivers.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_engine_planes import LIGHT, SCENES, _annulus, _compare, _prism, _rot_z

import jaxshadow as js
from jaxshadow._shadows import binding as vis

pytestmark = pytest.mark.skipif(not vis.engine_available(), reason="the shadow engine is not built")

TOL = 1e-9
# m, along a face's normal: 0, +-1e-9 .. +-1e-3 and +-3e-6 (the on-surface distance is about 2e-6)
OFFSETS = np.concatenate([[0.0, 3e-6, -3e-6], *[[10.0**-k, -(10.0**-k)] for k in range(9, 2, -1)]])
UP = np.array([0.0, 0.0, 1.0])


def _f32(v: np.ndarray) -> np.ndarray:
    return v.astype(np.float32).astype(np.float64)


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x)


def _side_sweeps(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Receivers beside every vertical face with an edge on the floor (as test_engine_planes'
    sweeps, every such face): 2.57 mm and 0.1 mm beyond each floor corner along the bottom edge and
    beside its middle, swept across the face's plane by OFFSETS. (m, 3)."""
    out = []
    for k in range(len(f)):
        tri = v[f[k]]
        nrm = _unit(np.cross(tri[1] - tri[0], tri[2] - tri[0]))
        floor = np.flatnonzero(tri[:, 2] == 0.0)
        if abs(nrm[2]) > 1e-12 or len(floor) != 2:
            continue
        a, b = tri[floor]
        u = _unit(b - a)
        for base in (b + 2.57e-3 * u, b + 1e-4 * u, a - 2.57e-3 * u, a - 1e-4 * u, 0.5 * (a + b)):
            out.append(base[None, :] + OFFSETS[:, None] * nrm[None, :])
    return np.concatenate(out)


def _plane_sweeps(v: np.ndarray, f: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Receivers in the planes of the given faces, off the mesh's surface: beyond each vertex (away
    from the centroid) and beyond the middle of each edge whose other face is not (nearly)
    coplanar (along the in-plane outward normal) by 1e-4, 2.57e-3 and 0.05 m, swept across the
    plane by OFFSETS. (m, 3)."""
    tri_n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    tri_n /= np.linalg.norm(tri_n, axis=1, keepdims=True)
    by_edge: dict = {}
    for k, (a, b, c) in enumerate(f):
        for e in ((a, b), (b, c), (c, a)):
            by_edge.setdefault(frozenset(e), []).append(k)
    out = []
    for k in faces:
        tri = v[f[k]]
        nrm = tri_n[k]
        c = tri.mean(axis=0)
        bases = []
        for i in range(3):
            a, b = tri[i], tri[(i + 1) % 3]
            bases.append((a, _unit(a - c)))
            if any(np.dot(tri_n[g], nrm) > 1 - 1e-6 for g in by_edge[frozenset((f[k][i], f[k][(i + 1) % 3]))] if g != k):
                continue  # beyond it lies the other face: a receiver on the surface
            w = _unit(np.cross(b - a, nrm))
            bases.append((0.5 * (a + b), w if np.dot(w, 0.5 * (a + b) - c) > 0 else -w))
        for x, d in bases:
            for s in (1e-4, 2.57e-3, 0.05):
                if not _on_surface(v, f, tri_n, x + s * d):
                    out.append((x + s * d)[None, :] + OFFSETS[:, None] * nrm[None, :])
    return np.concatenate(out)


def _on_surface(v: np.ndarray, f: np.ndarray, tri_n: np.ndarray, x: np.ndarray) -> bool:
    """Whether x lies on a face (within 1e-5 m of its plane, inside its triangle): beyond a
    vertex of one triangle of a non-planar float32 quad lies the other."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    near = np.abs(np.einsum("ij,ij->i", x - a, tri_n)) < 1e-5
    inside = np.ones(len(f), bool)
    for p0, p1 in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(p1 - p0, x - p0), tri_n) > -1e-9
    return bool(np.any(near & inside))


def _check(host: np.ndarray, dev: np.ndarray, points: np.ndarray, scale: float | None = None) -> None:
    """Host within TOL of `scale` (default: the largest device value) of the device."""
    assert np.all(np.isfinite(host)) and np.all(np.isfinite(dev))
    scale = float(np.max(np.abs(dev))) if scale is None else scale
    assert scale > 0
    err = np.abs(host - dev) / scale
    bad = [(points[i].tolist(), float(host[i]), float(dev[i]), float(err[i])) for i in np.argsort(-err)[:5] if err[i] > TOL]
    assert not bad, (f"{int(np.sum(err > TOL))} of {len(err)} receivers off, worst {float(err.max()):.3g}", bad)


@pytest.mark.parametrize("name", ["l_prism", "annulus"])
@pytest.mark.parametrize("height", [0.0, 0.0731])
def test_float32_nonconvex_meshes_across_side_planes(name: str, height: float) -> None:
    """The float32 L prism (5.1e-3 1e-6 m in front of a side, 9.3e-4 1e-3 m in front of one) and
    annulus (2.1e-3): every side face, on the floor and above it."""
    light, v, f = SCENES[name]
    v = _f32(v)
    points = _side_sweeps(v, f) + np.array([0.0, 0.0, height])
    host, dev = _compare(light, v, f, points, np.tile(UP, (len(points), 1)))
    _check(host, dev, points)


def test_float32_l_prism_beside_a_convex_corner() -> None:
    """1e-3 m in front of a side of the float32 L prism and 1e-4 m beyond its convex corner along
    its bottom edge (host 0.58038 against the device's 0.57983 there): the receiver lies 1.7e-6 m
    in front of the neighbouring side's plane, which drops that side. Each side's sweep point
    1e-3 m out, and the same point moved into the neighbour's plane (0, +-1e-6 m off it)."""
    light, v, f = SCENES["l_prism"]
    v = _f32(v)
    tri = v[f]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    pts = []
    for k in np.flatnonzero(np.abs(nrm[:, 2]) < 1e-12):
        floor = np.flatnonzero(tri[k, :, 2] == 0.0)
        if len(floor) != 2:
            continue
        a, b = tri[k, floor]
        for corner, other in ((a, b), (b, a)):
            u = _unit(corner - other)
            p = corner + 1e-4 * u + 1e-3 * nrm[k]
            pts.append(p)
            # the neighbours sharing this floor corner: p moved into their planes
            for g in np.flatnonzero(np.abs(nrm[:, 2]) < 1e-12):
                if g != k and np.any(np.all(tri[g] == corner, axis=1)):
                    h = np.dot(p - corner, nrm[g])
                    pts += [p - (h - d) * nrm[g] for d in (0.0, 1e-6, -1e-6)]
    points = np.array(pts)
    host, dev = _compare(light, v, f, points, np.tile(UP, (len(points), 1)))
    _check(host, dev, points)


def _star_prism(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A closed non-convex prism over a star outline (8 points, alternating radii), tilted about
    a horizontal axis, resting on the floor or floating above it."""
    n = 8
    t = np.sort(rng.uniform(0, 2 * np.pi, n)) if rng.random() < 0.3 else 2 * np.pi * np.arange(n) / n + rng.uniform(-0.15, 0.15, n)
    r = np.where(np.arange(n) % 2 == 0, rng.uniform(0.22, 0.32), rng.uniform(0.08, 0.14)) * rng.uniform(0.9, 1.1, n)
    outline = np.c_[r * np.cos(t), r * np.sin(t)]
    v, f = _prism(outline, rng.uniform(0.25, 0.45))
    axis = _unit(np.r_[rng.normal(size=2), 0.0])
    ang = rng.uniform(0.0, 0.5)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(ang) * k + (1 - np.cos(ang)) * (k @ k)
    v = v @ rot.T
    v = _rot_z(v, rng.uniform(0, 2 * np.pi), np.zeros(3))
    v[:, :2] += rng.uniform(-0.15, 0.15, 2) + np.pi * 1e-9
    v[:, 2] += (0.0 if rng.random() < 0.5 else rng.uniform(0.02, 0.3)) - v[:, 2].min()
    return v, f


def _tilted_annulus(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    v, f = _annulus(0.12, rng.uniform(0.2, 0.3), rng.uniform(0.15, 0.35), int(rng.integers(7, 11)), np.zeros(3))
    v = _rot_z(v[:, [0, 2, 1]] * [1, 1, -1], rng.uniform(0, 2 * np.pi), np.zeros(3))  # stood on its edge (a rotation)
    v[:, 2] += rng.uniform(0.0, 0.2) - v[:, 2].min()
    return v, f


@pytest.mark.parametrize(("dtype", "seed"), [
    ("float32", 0), ("float64", 0), ("float64", 1), ("float32", 1),
])
def test_random_nonconvex_meshes_across_face_planes(dtype: str, seed: int) -> None:
    """Generated non-convex closed meshes (tilted star prisms, an annulus stood on its edge), of
    float32 or float64 values: receivers in the planes of their faces, beside vertices and
    edges, swept across them, outside the mesh's box (where the host drops back faces); receivers
    face up or tilted."""
    rng = np.random.default_rng(1000 + seed)
    v, f = _tilted_annulus(rng) if seed == 3 else _star_prism(rng)
    if dtype == "float32":
        v = _f32(v)
    tri = v[f]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.sum(np.einsum("ij,ij->i", tri[:, 0], nrm)) > 0  # closed and outward: positive volume
    points = _plane_sweeps(v, f, np.arange(len(f)))
    # outside the mesh's box by more than the sweep's offsets: where the host drops back faces
    m = len(OFFSETS)
    base = points[::m]
    out = np.any((base < v.min(axis=0) - 2e-3) | (base > v.max(axis=0) + 2e-3), axis=1)
    points = points.reshape(-1, m, 3)[out].reshape(-1, 3)
    assert len(points) >= 10 * m
    normals = np.tile(UP, (len(points), 1))
    normals[1::2] = _unit(np.cross(UP, [1.0, 2.0, 0.5]) + UP)  # every other receiver tilted
    host, dev = _compare(LIGHT, v, f, points, normals)
    _check(host, dev, points)


@pytest.mark.parametrize("name", ["box_field_30", "rotated_box", "l_prism", "annulus"])
def test_float32_meshes_segment_light_across_side_planes(name: str) -> None:
    """A segment light: its candidate faces (hard.h) drop a closed mesh's back faces the same way
    (0.83 of the largest value 1e-7 m in front of a float32 box's side); point and directional
    lights test every face along the ray and are checked beside it."""
    _, v, f = SCENES[name]
    v = _f32(v)
    points = _side_sweeps(v, f) + np.array([0.0, 0.0, 0.0731])
    normals = np.tile(UP, (len(points), 1))
    c = LIGHT.mean(axis=0)
    for light in (js.LinearLight(c + [-0.4, 0.1, -0.05], c + [0.5, -0.2, 0.0], 1.0),
                  js.PointLight(c + [0.05, -0.03, -0.1], 1.0)):
        scene = js.Scene([light], [js.Mesh(v, f)])
        host = np.asarray(js.irradiance(scene, points, normals))[:, 0]
        dev = np.asarray(js.irradiance(scene, points, normals, shadows=js.ShadowOptions(engine="device")))[:, 0]
        free = np.asarray(js.irradiance(js.Scene([light]), points, normals))[:, 0]  # the scale where all is shadowed
        _check(host, dev, points, float(np.max(free)))


def test_float32_star_prism_beside_an_edge_inside_its_box() -> None:
    """The random sweep's seed-0 float32 star prism: a receiver 1.6e-4 m beyond a side quad's
    outer edge, in the plane of one of its triangles (0) and 8e-9 m in front of the other's
    (the float32 quad is not planar), inside the mesh's box (no culling). Its boundary has a
    vertex where two edge planes through p share an occluder vertex: decoded on the line from p
    through that vertex (`decode.h`), not from the planes' nearly parallel normals."""
    rng = np.random.default_rng(1000)
    v, f = _star_prism(rng)
    v = _f32(v)
    points = np.array([[-0.2324055925134336, -0.28997341191611886, 0.4186312438101932]] * 2)
    normals = np.array([UP, _unit(np.cross(UP, [1.0, 2.0, 0.5]) + UP)])
    host, dev = _compare(LIGHT, v, f, points, normals)
    _check(host, dev, points)
