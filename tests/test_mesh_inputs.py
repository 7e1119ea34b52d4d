"""Hard mesh inputs (`benchmarks.mesh_sweep.generated`, generated with NumPy and trimesh): the
engine against independent references (polygon booleans in shapely for a quad light; the device
kernel, which shares no code with the host engine, and NumPy ray tests for a point light), and
the ray test of the sweep's references near a face.

Inputs: fins (three faces on an edge), T-junctions, half the faces flipped, two copies offset by 0
and 1e-9 m (a mesh and a soup), a mesh crossing the light's plane, receivers exactly on shadow
edges (planes through an occluder edge and a light vertex), a box sitting on a slab (coplanar
touching faces) with receivers on the slab around it. Slivers 1e-12 m wide are refused as
zero-area faces (`js.Mesh` and `Scene`), never silently dropped.
"""

from __future__ import annotations

from fractions import Fraction

import jax
import numpy as np
import pytest

import jaxshadow as js
from benchmarks import _robustness_checks as chk
from benchmarks import mesh_sweep as ms

jax.config.update("jax_enable_x64", True)
pytest.importorskip("trimesh")
import exact_reference as er  # noqa: E402
from test_clip import _may_meet, ray_blocked_np  # noqa: E402

CASES = ("fins", "T-junctions", "half flipped", "two copies, offset 0", "two copies, offset 1e-9",
         "two copies, offset 1e-9, soup", "crossing the light's plane", "receivers on shadow edges",
         "box on a slab, one mesh", "box on a slab, two meshes")


@pytest.fixture(scope="module")
def inputs() -> dict[str, dict]:
    return ms.generated(CASES + ("slivers 1e-12 m", "slivers 1e-12 m, soup"), subdivisions=2)


def _occluders(g: dict):
    if "tris" in g:
        return g["tris"]
    if "meshes" in g:
        return [js.Mesh(v, f) for v, f in g["meshes"]]
    return [js.Mesh(g["v"], g["f"])]


def _unit_normals(tris: np.ndarray) -> np.ndarray:
    nrm = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    return nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def _scene(g: dict, kind: str):
    tris = g["tris"] if "tris" in g else g["v"][g["f"]]
    groups = ms.receivers(tris, 60) | g.get("extra", {})
    p = np.concatenate([x[0] for x in groups.values()])
    n = np.concatenate([x[1] for x in groups.values()])
    extra = np.concatenate([np.full(len(x[0]), k in g.get("extra", {})) for k, x in groups.items()])
    centre = (tris.reshape(-1, 3).max(axis=0) + tris.reshape(-1, 3).min(axis=0)) / 2
    light = ms.light_of(kind, g["quad"], centre)
    scene = js.Scene([light], occluders=_occluders(g))
    e = np.asarray(js.irradiance(scene, p, n))[:, 0]
    unocc = np.asarray(js.irradiance(js.Scene([light]), p, n))[:, 0]
    assert np.all(np.isfinite(e))
    return tris, light, scene, p, n, extra, e, unocc, np.maximum(np.abs(unocc), 1e-3 * np.abs(unocc).max())


@pytest.mark.parametrize("name", CASES)
def test_quad_light_matches_polygon_booleans(inputs, name) -> None:
    """Up to eight penumbra receivers off the mesh's surface and six of the input's own (shadow edges,
    slab top) against exact polygon booleans in shapely; up to four penumbra receivers within
    1e-6 m of a face's plane (on the surface, 1e-9 m off it) against the exact rational reference
    (`exact_reference`): shapely's clipped points within that distance of the receiver round by
    the coordinates' size, which its projection magnifies (2e-8 U off at 1e-9 m off a fin's vertex,
    `test_exact_reference`)."""
    tris, light, _, p, n, extra, e, unocc, scale = _scene(inputs[name], "quad")
    rng = np.random.default_rng(1)
    off = np.min(np.abs(np.einsum("kd,md->km", p, _unit_normals(tris)) - np.einsum("md,md->m", tris[:, 0], _unit_normals(tris))),
                 axis=1) > 1e-6
    pen = np.flatnonzero((e > 0) & (e < 0.999 * unocc) & off)
    own = np.flatnonzero(extra)
    sel = np.concatenate([rng.choice(pen, min(8, len(pen)), replace=False),
                          rng.choice(own, min(6, len(own)), replace=False)])
    assert np.sum((e[sel] > 0) & (e[sel] < 0.999 * unocc[sel])) >= 4  # the check has teeth
    ref = chk.polygon_reference(np.asarray(light.vertices, float), tris, p[sel], n[sel])
    assert np.max(np.abs(e[sel] - ref) / scale[sel]) <= 1e-9
    near = np.flatnonzero((e > 0) & (e < 0.999 * unocc) & ~off & ~extra)
    near = rng.choice(near, min(4, len(near)), replace=False)
    exact = er.irradiance_many(np.asarray(light.vertices, float), tris, p[near], n[near])
    assert np.all(np.abs(e[near] - exact) / scale[near] <= 1e-9)


@pytest.mark.parametrize("name", CASES)
def test_point_light_matches_device_kernel(inputs, name) -> None:
    """Every receiver against the device kernel (receivers on a shadow boundary, lit or shadowed by
    rounding, counted apart: at most two) and ray tests on twelve."""
    tris, light, scene, p, n, _, e, unocc, scale = _scene(inputs[name], "point")
    dev = np.asarray(js.irradiance(scene, p, n, shadows=js.ShadowOptions(engine="device")))[:, 0]
    flip = (e > 0) != (dev > 0)
    assert flip.sum() <= 2
    assert np.max(np.abs(e - dev)[~flip] / scale[~flip]) <= 1e-9
    assert 0 < (e == 0).sum() < len(e)  # shadowed and lit receivers both
    sel = np.random.default_rng(2).choice(np.flatnonzero(~flip), 12, replace=False)
    ref = chk.kind_reference("point", light, tris, p[sel], n[sel])
    assert np.max(np.abs(e[sel] - ref) / scale[sel]) <= 1e-9


@pytest.mark.parametrize("name", ["slivers 1e-12 m", "slivers 1e-12 m, soup"])
def test_slivers_1e12_are_refused(inputs, name) -> None:
    with pytest.raises(ValueError, match="zero area"):
        js.Scene([js.PolygonLight(ms.LIGHT, 1.0)], occluders=_occluders(inputs[name]))


def _exact_blocked(p: np.ndarray, x: np.ndarray, tris: np.ndarray) -> bool:
    """`ray_blocked_np`'s question in exact rational arithmetic on the same float inputs."""
    def q(a):
        return [Fraction(float(c)) for c in a]

    def sub(a, b):
        return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]

    def cross(a, b):
        return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]

    def dot(a, b):
        return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]

    P, X = q(p), q(x)
    for t in tris:
        v = [q(c) for c in t]
        no = cross(sub(v[1], v[0]), sub(v[2], v[0]))
        dp, dx = dot(no, sub(P, v[0])), dot(no, sub(X, v[0]))
        if dp == 0 or dp * dx >= 0:
            continue
        s = [dot(cross(sub(v[i], P), sub(v[(i + 1) % 3], P)), sub(X, P)) for i in range(3)]
        if all(c > 0 for c in s) or all(c < 0 for c in s):
            return True
    return False


def test_ray_test_near_a_face_is_exact() -> None:
    """A receiver 1e-9 m off a vertex of the fins input (blob of 1 280 triangles) under its segment
    light: across the segment's parameter where the fins' shadow ends, the NumPy ray test agrees
    with exact arithmetic. A test that computes the crossing point first moves that end by 2.3e-9
    of the segment, and the Gauss-Legendre reference off the engine by 1.9e-9 relative."""
    g = ms.generated(("fins",))["fins"]
    tris = g["v"][g["f"]]
    x = np.array([-0.35785452506158366, -0.22116625945339735, 0.9074972832647468])
    centre = (tris.reshape(-1, 3).max(axis=0) + tris.reshape(-1, 3).min(axis=0)) / 2
    light = ms.light_of("segment", g["quad"], centre)
    a, b = np.asarray(light.start, float), np.asarray(light.end, float)
    faces = chk._array(chk.refs()[2]._off_surface(x, chk._near_segment(x, a, b, tris), chk.ON_SURFACE_64))
    cut = 0.6945398039946367  # the exact end of the shadow (bisection in rational arithmetic)
    for t in cut + np.linspace(-4e-9, 4e-9, 17):
        if abs(t - cut) < 1e-12:
            continue
        y = a + t * (b - a)
        near = faces[_may_meet(x, y, faces)]
        assert ray_blocked_np(x, y, faces) == _exact_blocked(x, y, near), t
