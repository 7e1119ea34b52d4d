"""The host shadow engine (`js.irradiance`) on receivers in and near the planes of occluder faces.

Receivers swept across the plane of a vertical occluder face, beside the corner where the face
meets the floor, at signed offsets 0 and +-1e-9 .. +-1e-3 m from that plane: on the floor (so
also in the plane of the occluder's bottom face, the "receivers on occluding surfaces" rule) and
above it. Occluders: single boxes of float64 coordinates (one of `benchmarks.scenes.box_field`,
where the bake found the defect, and a rotated one), an L-shaped prism and a many-sided annulus
(non-convex). The reference is the device kernel `js.visible_form_factor`, which clips every face
independently (no solids, no silhouettes); host and device must agree to 1e-9 of the largest value
among the case's receivers.

The host engine takes a convex solid through its silhouette, and a face whose plane holds the
receiver as a back face; counting a face as holding every receiver within an on-surface distance
(3.8e-6 S for faces of float32 values) leaves out the face's projection, a wedge of (offset) /
(distance to the face's nearest edge) radians (6.6e-4 of the irradiance 1e-6 m off the plane and
2.6 mm beside the corner), or, beside the middle of a face, everything (lit for umbra), since
the device kernel keeps the solid's back faces, which cover the dropped face. Offsets +-2e-13
and +-4e-13 lie within the host's rounding bound on a solid's face heights, where the host takes
the faces instead.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import jaxshadow as js
from benchmarks.scenes import LIGHT, box_field
from jaxshadow._shadows import binding as vis

pytestmark = pytest.mark.skipif(not vis.engine_available(), reason="the shadow engine is not built")

# m; 2e-13 and 4e-13: beyond the on-surface distance of faces of doubles (2^-44 S), within the
# host's rounding bound on a solid's face heights (1e3 eps of the coordinates)
OFFSETS = np.concatenate([[0.0, 2e-13, -2e-13, 4e-13, -4e-13], *[[10.0**-k, -(10.0**-k)] for k in range(9, 2, -1)]])
RADIANCE = 10.0
TOL = 1e-9


def _rot_z(v: np.ndarray, angle: float, centre: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (v - centre) @ r.T + centre


def _cross2(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def _prism(outline: np.ndarray, height: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed, outward prism over the simple counter-clockwise polygon `outline (n, 2)`
    standing on the floor: caps fanned from a triangulation by ear clipping, side quads as two
    triangles each."""
    n = len(outline)
    v = np.concatenate([np.c_[outline, np.zeros(n)], np.c_[outline, np.full(n, height)]])
    idx = list(range(n))
    tris = []
    while len(idx) > 3:
        for k in range(len(idx)):
            a, b, c = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            pa, pb, pc = outline[a], outline[b], outline[c]
            if _cross2(pb - pa, pc - pb) <= 0:
                continue
            others = [outline[j] for j in idx if j not in (a, b, c)]
            inside = any(
                _cross2(pb - pa, q - pa) > 0 and _cross2(pc - pb, q - pb) > 0 and _cross2(pa - pc, q - pc) > 0 for q in others
            )
            if not inside:
                tris.append((a, b, c))
                idx.pop(k)
                break
    tris.append(tuple(idx))
    faces = [(a, c, b) for a, b, c in tris]  # bottom: outward is -z
    faces += [(a + n, b + n, c + n) for a, b, c in tris]
    for i in range(n):
        j = (i + 1) % n
        faces += [(i, j, j + n), (i, j + n, i + n)]
    return v, np.asarray(faces, np.int64)


def _annulus(r_in: float, r_out: float, height: float, sections: int, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A closed, outward annulus (a thick ring) on the floor: `sections` flat outer and inner walls."""
    t = 2 * np.pi * np.arange(sections) / sections + 0.3
    ring = np.c_[np.cos(t), np.sin(t)]
    pts = []
    for z in (0.0, height):
        pts.append(np.c_[centre[:2] + r_out * ring, np.full(sections, z)])
        pts.append(np.c_[centre[:2] + r_in * ring, np.full(sections, z)])
    v = np.concatenate(pts)  # outer bottom, inner bottom, outer top, inner top
    ob, ib, ot, it = 0, sections, 2 * sections, 3 * sections
    faces = []
    for i in range(sections):
        j = (i + 1) % sections
        faces += [(ob + i, ob + j, ot + j), (ob + i, ot + j, ot + i)]  # outer wall
        faces += [(ib + j, ib + i, it + i), (ib + j, it + i, it + j)]  # inner wall
        faces += [(ot + i, ot + j, it + j), (ot + i, it + j, it + i)]  # top
        faces += [(ob + j, ob + i, ib + i), (ob + j, ib + i, ib + j)]  # bottom
    return v, np.asarray(faces, np.int64)


def _scenes() -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """name -> (light (4, 3), vertices, faces); float64 coordinates, not float32 values."""
    bf = box_field(180)
    out = {"box_field_30": (bf.light, *bf.boxes[30])}
    rng = np.random.default_rng(7)
    v, f = bf.boxes[30]
    c = np.array([0.0712345678, -0.1234567891, 0.0])
    vb = _rot_z(v - v.mean(axis=0) * np.array([1, 1, 0]) + c, 0.4123456789, c)
    out["rotated_box"] = (LIGHT, vb, f)
    ell = np.array([[0, 0], [0.31, 0], [0.31, 0.12], [0.13, 0.12], [0.13, 0.35], [0, 0.35]]) + rng.uniform(-0.01, 0.01, (6, 2))
    vl, fl = _prism(ell - [0.2, 0.1] + np.array([1e-10 * np.pi, 0]), 0.5123456789)
    out["l_prism"] = (LIGHT, _rot_z(vl, 0.2345678901, np.zeros(3)), fl)
    out["annulus"] = (LIGHT, *_annulus(0.21, 0.3317, 0.4123456789, 9, np.array([0.05123456789, 0.0312345678, 0.0])))
    return out


def _sweeps(v: np.ndarray, f: np.ndarray, n_faces: int, rng: np.random.Generator):
    """Per chosen vertical face with an edge on the floor: `(points (len(OFFSETS), 3), unit
    normal of the face)` for receivers 2.57 mm beyond each floor corner along the face's bottom
    edge (and 0.1 mm beyond one), plus one beside the edge's middle, swept across the face's plane by OFFSETS."""
    tri = v[f]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    cand = []
    for k in range(len(f)):
        on_floor = np.flatnonzero(tri[k, :, 2] == 0.0)
        if abs(nrm[k, 2]) < 1e-12 and len(on_floor) == 2:
            cand.append(k)
    picks = rng.choice(cand, size=min(n_faces, len(cand)), replace=False)
    for k in picks:
        a, b = tri[k, np.flatnonzero(tri[k, :, 2] == 0.0)]
        u = (b - a) / np.linalg.norm(b - a)
        for base in (b + 2.57e-3 * u, a - 2.57e-3 * u, a - 1e-4 * u, 0.5 * (a + b)):
            yield base[None, :] + OFFSETS[:, None] * nrm[k][None, :]


def _compare(light: np.ndarray, v: np.ndarray, f: np.ndarray, points: np.ndarray, normals: np.ndarray):
    scene = js.Scene([js.PolygonLight(light, RADIANCE)], [js.Mesh(v, f)])
    host = np.asarray(js.irradiance(scene, points, normals))[:, 0]
    occ = jnp.asarray(np.asarray(scene.occluders))
    dev = np.pi * RADIANCE * np.asarray(js.visible_form_factor(jnp.asarray(points), jnp.asarray(normals), jnp.asarray(light), occ))
    return host, dev


SCENES = _scenes()


@pytest.mark.parametrize("name", sorted(SCENES))
@pytest.mark.parametrize("height", [0.0, 0.0731, 0.2])
def test_host_matches_device_across_face_planes(name: str, height: float) -> None:
    light, v, f = SCENES[name]
    assert not np.all(v.astype(np.float32).astype(np.float64) == v)  # the rule for faces of doubles
    rng = np.random.default_rng(sum(map(ord, name)))
    sweeps = list(_sweeps(v, f, 6, rng))
    assert sweeps
    points = np.concatenate(sweeps) + np.array([0.0, 0.0, height])
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    host, dev = _compare(light, v, f, points, normals)
    assert np.all(np.isfinite(host)) and np.all(np.isfinite(dev))
    m = len(OFFSETS)
    scale = np.max(np.abs(dev))  # a sweep in umbra reads rounding (1e-16) on both sides
    bad = []
    for i in range(len(sweeps)):
        h, d = host[i * m:(i + 1) * m], dev[i * m:(i + 1) * m]
        err = np.abs(h - d)
        if np.any(err > TOL * scale):
            j = int(np.argmax(err))
            bad.append((i, float(OFFSETS[j]), float(h[j]), float(d[j]), float(err[j] / scale)))
    assert not bad, bad


def test_reproducer_box_field_corner() -> None:
    """The bake's receiver: box 30 of box_field(180), 2.57 mm beside its footprint's corner,
    1e-6 m outside the plane of its -x face (host 0.05569491 against the device's 0.05532907)."""
    light, v, f = SCENES["box_field_30"]
    corner = v[0]
    xs = np.array([-1e-4, -1e-5, -1e-6, -3.5e-9, 0.0, 1e-6, 1e-5])
    points = np.c_[corner[0] + xs, np.full(len(xs), corner[1] - 2.57e-3), np.zeros(len(xs))]
    normals = np.tile([0.0, 0.0, 1.0], (len(xs), 1))
    host, dev = _compare(light, v, f, points, normals)
    np.testing.assert_allclose(host, dev, rtol=0, atol=TOL * np.max(dev))


@pytest.mark.parametrize("name", ["box_field_30", "rotated_box"])
def test_float32_valued_boxes_across_face_planes(name: str) -> None:
    """Boxes of float32 values (meshes read from files): within their on-surface distance (2^-18 S,
    about 5e-6 m here) of a side face's plane, a floor receiver in front of it is not on the face;
    the solid still blocks its whole projection (the device kernel drops the face but keeps the
    back faces). Beside the middle of a side face's bottom edge the host read fully lit (0.43)
    where the receiver lies in umbra (0). Offsets 0 and +-1e-9..1e-3 m."""
    light, v, f = SCENES[name]
    v = v.astype(np.float32).astype(np.float64)
    rng = np.random.default_rng(sum(map(ord, name)))
    keep = (OFFSETS == 0) | (np.abs(OFFSETS) >= 1e-9)
    sweeps = [s[keep] for s in _sweeps(v, f, 6, rng)]
    points = np.concatenate(sweeps)
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    host, dev = _compare(light, v, f, points, normals)
    np.testing.assert_allclose(host, dev, rtol=0, atol=TOL * np.max(np.abs(dev)))
