"""The engine against the exact reference (`tests/exact_reference.py`: rational clipping,
projection and polygon differences, Lambert's sum at 50 digits) under a quad light.

First the reference itself: closed forms (a parallel square light seen from its axis, unoccluded
and behind a parallel square occluder split into two triangles) and the engine on a few loose
triangles. Then the generated hard inputs of `benchmarks.mesh_sweep.generated` (fins, T-junctions,
half the faces flipped, two copies offset by 0 and 1e-9 m, a mesh crossing the light's plane,
receivers exactly on shadow edges, a box on a slab): receivers at vertices of the feature (the
fins' faces, the T-junctions' split faces, ...) with their area-weighted vertex normals, pushed
along them by 1e-9 m, 1e-12 m and 0 (on the vertex: its faces block nothing, the documented
on-surface rule), and the inputs' own receivers (shadow edges, slab top) at 0, 1e-9 and 1e-12 m
above their plane. Bound: the library's `1e-9 U`, `U = max(unoccluded, 1e-3 max unoccluded)`.
At a T-junction's vertex 1e-12 m off the surface two edge planes through the receiver cross at
2.4e-11 rad (`test_two_edge_planes_through_one_vertex`). The floating-point shapely reference (`test_clip.reference_ff`) is off by up to 2e-8 U at 1e-9 m
and 5e-6 U at 1e-12 m there (its clipped points within the push of the receiver carry an
absolute rounding of the coordinates' size, which the projection magnifies by the light's
distance over the push), so `test_mesh_inputs` checks those placements here.

`python tests/test_exact_reference.py` prints the study behind it: every case, more receivers,
the engine's silhouette path, face path and the faces as a soup, and shapely, against the
exact reference.
"""

from __future__ import annotations

import os
import sys

import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest

import jaxshadow as js

jax.config.update("jax_enable_x64", True)
pytest.importorskip("trimesh")
pytest.importorskip("shapely")
sys.path.insert(0, os.path.dirname(__file__))
import exact_reference as er  # noqa: E402

from benchmarks import mesh_sweep as ms  # noqa: E402

CASES = ("fins", "T-junctions", "half flipped", "two copies, offset 0", "two copies, offset 1e-9",
         "two copies, offset 1e-9, soup", "crossing the light's plane", "receivers on shadow edges",
         "box on a slab, one mesh")
PUSHES = (1e-9, 1e-12, 0.0)
RTOL = 1e-9


def _corner_ff(a: float, b: float, c: float) -> mpmath.mpf:
    """Form factor from a point to a parallel `a x b` rectangle at height `c` whose corner lies
    on the point's normal (Howell's catalogue, B-3)."""
    A, B = mpmath.mpf(a) / c, mpmath.mpf(b) / c
    sa, sb = mpmath.sqrt(1 + A * A), mpmath.sqrt(1 + B * B)
    return (A / sa * mpmath.atan(B / sa) + B / sb * mpmath.atan(A / sb)) / (2 * mpmath.pi)


def _square(h: float, z: float) -> np.ndarray:
    """A square of half-size `h` at height `z`, its normal pointing down."""
    return np.array([[-h, -h, z], [-h, h, z], [h, h, z], [h, -h, z]])


def test_reference_closed_forms() -> None:
    """A square light (half-size 0.5, 2 m above the receiver) seen from its axis: pi times four
    corner form factors; behind a parallel square occluder of half-size 0.25 at 1 m (two triangles
    sharing a diagonal), whose shadow is the light's central square of half-size 0.5."""
    p, n = np.zeros(3), np.array([0.0, 0.0, 1.0])
    light = _square(0.5, 2.0)
    with mpmath.workdps(40):
        whole = 4 * _corner_ff(0.5, 0.5, 2.0)
        hole = 4 * _corner_ff(0.5, 0.5, 2.0)  # the projection of the occluder: the same square
        big = _square(1.0, 2.0)
        ring = 4 * _corner_ff(1.0, 1.0, 2.0) - hole
    occ = _square(0.25, 1.0)
    tris = np.array([occ[[0, 1, 2]], occ[[0, 2, 3]]])
    assert er.irradiance(light, np.zeros((0, 3, 3)), p, n) == pytest.approx(float(mpmath.pi * whole), rel=4e-16)
    assert er.irradiance(light, tris, p, n) == 0.0
    assert er.irradiance(big, tris, p, n) == pytest.approx(float(mpmath.pi * ring), rel=4e-16)
    assert er.irradiance(big, tris, p, -n) == 0.0  # the receiver faces away
    # A tilted normal: the horizon cuts the light. The light turned over emits upwards.
    m = np.array([0.3, 0.0, 0.2])
    e = er.irradiance(big, tris, p, m)
    assert 0 < e < er.irradiance(big, np.zeros((0, 3, 3)), p, m)
    assert er.irradiance(big[::-1], tris, p, m) == 0.0


def test_reference_matches_engine_on_loose_triangles() -> None:
    """Three triangles (one crossing the light's plane) over floor receivers with upright and
    tilted normals: the engine and the reference agree to 1e-13 U."""
    light = ms.LIGHT
    tris, p, n = _loose_triangles()
    lt = js.PolygonLight(light, 1.0)
    e = np.asarray(js.irradiance(js.Scene([lt], occluders=tris), p, n))[:, 0]
    u = np.asarray(js.irradiance(js.Scene([lt]), p, n))[:, 0]
    ref = er.irradiance_many(light, tris, p, n)
    assert np.sum((ref > 0) & (ref < 0.999 * u)) >= 5
    assert np.max(np.abs(e - ref) / u) <= 1e-13


def _loose_triangles() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three triangles (one crossing the light's plane) and ten floor receivers, upright and tilted."""
    tris = np.array([[[-0.3, -0.2, 1.0], [0.3, -0.1, 1.1], [0.0, 0.35, 0.9]],
                     [[-0.1, -0.3, 1.5], [0.25, 0.0, 1.4], [-0.2, 0.3, 1.6]],
                     [[0.0, -0.5, 2.0], [0.5, 0.2, 2.0], [0.2, 0.4, 2.7]]])
    rng = np.random.default_rng(0)
    p = np.c_[rng.uniform(-0.6, 0.6, (10, 2)), np.zeros(10)]
    n = np.tile([0.0, 0.0, 1.0], (10, 1))
    n[::3] = rng.normal(size=(4, 3))
    n[::3, 2] = np.abs(n[::3, 2]) + 0.2
    return tris, p, n


def test_float32_matches_exact_reference() -> None:
    """float32 inputs (`_loose_triangles` and the light rounded to float32) against the exact
    value of the rounded inputs, so that only the evaluation's error is measured: the host
    engine decides and sums the penumbra receivers' Lambert terms in double (rounded to float32
    once), the lit ones go through the float32 kernel; the device kernel is float32 throughout.
    Both within test_stability's float32 bound, 2e-6 U (measured: host 3.7e-8, device 6.4e-7)."""
    light = ms.LIGHT.astype(np.float32).astype(np.float64)
    tris, p, n = (x.astype(np.float32).astype(np.float64) for x in _loose_triangles())
    lt = js.PolygonLight(light, 1.0)
    u = np.asarray(js.irradiance(js.Scene([lt]), p, n))[:, 0]
    ref = er.irradiance_many(light, tris, p, n)
    assert np.sum((ref > 0) & (ref < 0.999 * u)) >= 5
    scene = js.Scene([lt], occluders=tris)
    for opts in (js.ShadowOptions(), js.ShadowOptions(engine="device")):
        e = np.asarray(js.irradiance(scene, p.astype(np.float32), n.astype(np.float32), shadows=opts))
        assert e.dtype == np.float32
        assert np.max(np.abs(e[:, 0] - ref) / u) <= 2e-6, opts


def vertex_normals(tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct vertices of `tris (m, 3, 3)` (exactly equal positions welded) and their
    area-weighted normals."""
    pts, inv = np.unique(tris.reshape(-1, 3), axis=0, return_inverse=True)
    fn = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    acc = np.zeros_like(pts)
    np.add.at(acc, inv.ravel(), np.repeat(fn, 3, axis=0))
    ok = np.linalg.norm(acc, axis=1) > 0
    return pts[ok], acc[ok] / np.linalg.norm(acc[ok], axis=1, keepdims=True)


def feature_faces(name: str, g: dict, n_blob: int) -> np.ndarray:
    """Indices of the faces that make an input hard: the fins, the T-junctions' split faces, the
    flipped faces, the second copy, the faces near the light's plane, every face otherwise."""
    tris = g["tris"] if "tris" in g else g["v"][g["f"]]
    m = len(tris)
    if name == "fins":
        return np.arange(n_blob, m)
    if name == "T-junctions":
        return np.flatnonzero(np.any(g["f"] >= len(g["v"]) - (m - n_blob), axis=1))
    if name == "crossing the light's plane":
        return np.flatnonzero(tris[:, :, 2].max(axis=1) > 2.3)
    if name.startswith("box on a slab"):
        return np.arange(12, m)
    return np.arange(m)


def placements(name: str, g: dict, k: int, seed: int = 0, subdivisions: int = 2) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Receivers of input `name`, per placement `(points, normals)`: `k` vertices of its feature
    faces pushed along their normals by each of `PUSHES` (with those normals, and with them
    tilted 60 degrees towards the light), and `k` of its own receivers (shadow
    edges, slab top) at the same heights above their plane; penumbra receivers (as the engine
    has them at 1e-9 m) first, drawn at random, then others."""
    rng = np.random.default_rng(seed)
    tris = g["tris"] if "tris" in g else g["v"][g["f"]]
    n_blob = 20 * 4**subdivisions  # the blob's faces come first
    pts, nrm = vertex_normals(tris)
    feat = np.unique(tris[feature_faces(name, g, n_blob)].reshape(-1, 3), axis=0)
    idx = np.flatnonzero((pts[:, None, :] == feat[None]).all(axis=2).any(axis=1))
    # The vertex normal, and the normal tilted by 60 degrees towards the light's centre: its
    # horizon then takes in light below the vertex's faces, which they hide seen nearly edge-on.
    to = ms.LIGHT.mean(axis=0) - pts[idx]
    side = to - np.einsum("kd,kd->k", to, nrm[idx])[:, None] * nrm[idx]
    side /= np.maximum(np.linalg.norm(side, axis=1, keepdims=True), 1e-300)
    tilt = np.cos(np.pi / 3) * nrm[idx] + np.sin(np.pi / 3) * side
    groups = {"vertex": (pts[idx], nrm[idx], nrm[idx]), "vertex tilted": (pts[idx], tilt, nrm[idx])}
    groups |= {label: (p, n, np.tile([0.0, 0.0, 1.0], (len(p), 1))) for label, (p, n, _) in g.get("extra", {}).items()}
    out = {}
    for label, (p, n, up) in groups.items():
        q = p + 1e-9 * up
        e = _engine(occluders(g), q, n)
        u = _engine([], q, n)
        pen = rng.permutation(np.flatnonzero((e > 0) & (e < 0.999 * u)))
        rest = rng.permutation(np.flatnonzero(~((e > 0) & (e < 0.999 * u))))
        sel = np.concatenate([pen, rest])[:k]
        for push in PUSHES:
            out[f"{label} {push:g}"] = (p[sel] + push * up[sel], n[sel])
    return out


def occluders(g: dict) -> list:
    if "tris" in g:
        return g["tris"]
    if "meshes" in g:
        return [js.Mesh(v, f) for v, f in g["meshes"]]
    return [js.Mesh(g["v"], g["f"])]


def _engine(occ: list, p: np.ndarray, n: np.ndarray, env: dict[str, str] | None = None) -> np.ndarray:
    old = {k: os.environ.get(k) for k in (env or {})}
    os.environ.update(env or {})
    try:
        scene = js.Scene([js.PolygonLight(ms.LIGHT, 1.0)], occluders=occ) if len(occ) else js.Scene([js.PolygonLight(ms.LIGHT, 1.0)])
        return np.asarray(js.irradiance(scene, p, n))[:, 0]
    finally:
        for key, x in old.items():
            if x is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = x


@pytest.fixture(scope="module")
def inputs() -> dict[str, dict]:
    return ms.generated(CASES, subdivisions=2)


def errors(g: dict, p: np.ndarray, n: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`|e - exact| / U`, the exact values and the unoccluded ones at `p`, `n`."""
    tris = g["tris"] if "tris" in g else g["v"][g["f"]]
    u = np.asarray(js.irradiance(js.Scene([js.PolygonLight(ms.LIGHT, 1.0)]), p, n))[:, 0]
    ref = er.irradiance_many(ms.LIGHT, tris, p, n)
    scale = np.maximum(np.abs(u), 1e-3 * np.abs(u).max())
    return np.abs(e - ref) / scale, ref, u


@pytest.mark.parametrize("name", CASES)
def test_engine_matches_exact_reference_near_vertices(inputs, name) -> None:
    """Three receivers per placement (vertex pushes of 1e-9, 1e-12 and 0 m; the input's own
    receivers at the same heights): the engine within `1e-9 U` of the exact reference, with
    penumbra receivers among them."""
    g = inputs[name]
    groups = placements(name, g, 3, seed=1)
    p = np.concatenate([x[0] for x in groups.values()])
    n = np.concatenate([x[1] for x in groups.values()])
    e = _engine(occluders(g), p, n)
    assert np.all(np.isfinite(e))
    err, ref, u = errors(g, p, n, e)
    assert np.sum((ref > 0) & (ref < 0.999 * u)) >= 6  # the check has teeth
    worst = int(np.argmax(err))
    assert err[worst] <= RTOL, (worst, p[worst], n[worst], e[worst], ref[worst])


def test_two_edge_planes_through_one_vertex() -> None:
    """Two faces of the T-junctions input sharing a vertex B, their other vertices C and D the
    ends of the split edge, and a receiver 1e-12 m off its midpoint (tilted normal): from it C and
    D lie in opposite directions to 2.4e-11 rad, so the planes through the receiver and the edges
    B C and B D are 2.4e-11 rad apart. The boundary vertex where they cross lies on the line from
    the receiver through B; the cross product of the planes' normals finds it only to 2.9e-7 rad
    (2.4e-6 U off). The host engine and the differentiated path (`binding.decode_endpoints`) both
    within 1e-13 U of the exact reference, the gradient finite."""
    tris = np.array([[[0.03886758408197239, 0.4736185949220285, 0.8277226655855978],
                      [0.07773516816394478, 0.4550696007952991, 0.8906117376908235],
                      [0.12694633548513853, 0.44686976472806433, 0.764833593480372]],
                     [[-0.08314283083995345, 0.4867266094997365, 0.8993615197002998],
                      [0.07773516816394478, 0.4550696007952991, 0.8906117376908235],
                      [0.0, 0.4921675890487579, 0.764833593480372]]])
    p = np.array([[0.06347316774285572, 0.46951867688921384, 0.764833593479849]])
    n = np.array([[0.3594102539572851, 0.8036269565236909, 0.4743500649297201]])
    e = _engine(tris, p, n)
    u = _engine([], p, n)
    ref = er.irradiance(ms.LIGHT, tris, p[0], n[0])
    assert 0 < ref < 0.999 * u[0]
    assert abs(e[0] - ref) <= 1e-13 * u[0]
    scene = js.Scene([js.PolygonLight(ms.LIGHT, 1.0)], occluders=tris)
    val, grad = jax.value_and_grad(lambda x: js.irradiance(scene, x, jnp.asarray(n))[0, 0])(jnp.asarray(p))
    assert abs(float(val) - ref) <= 1e-13 * u[0]
    assert np.all(np.isfinite(np.asarray(grad)))


def _grazing(light: np.ndarray, p: np.ndarray, i: int, d: float) -> np.ndarray:
    """A triangle 40 % of the way from `p` to the light: its edge a -> b runs from 0.8 to 0.2 of
    light edge `i` (as seen from `p`), a `d` m outside the plane through `p` and that edge and b
    `d` m inside: its shadow line crosses the light edge's at the edge's midpoint, and the two
    planes through `p` are about `d` / 0.1 m rad apart; the third vertex lies towards the light's
    centre."""
    l0, l1 = light[i], light[(i + 1) % len(light)]
    m = np.cross(l0 - p, l1 - p)
    m /= np.linalg.norm(m)
    if np.dot(m, light.mean(axis=0) - p) < 0:
        m = -m
    a = p + 0.4 * (0.8 * l0 + 0.2 * l1 - p) - d * m
    b = p + 0.4 * (0.2 * l0 + 0.8 * l1 - p) + d * m
    c = p + 0.4 * (0.25 * (l0 + l1) + 0.5 * light.mean(axis=0) - p)
    return np.array([[a, b, c]])


def _turned_light() -> np.ndarray:
    """`ms.LIGHT` turned by 0.5 rad about the vertical (its edges off the axes: an edge along an
    axis gives its plane through p a zero component, which hides the cross product's rounding)."""
    c, s = np.cos(0.5), np.sin(0.5)
    light = ms.LIGHT @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T
    light[:, 2] = 2.5
    return light


@pytest.mark.parametrize("d", [1e-9, 1e-12, 1e-13, 0.0])
def test_occluder_edge_grazing_a_light_edges_shadow_line(d) -> None:
    """An occluder edge `d` m off the plane through the receiver and a light edge (`_grazing`,
    two light edges, two receivers): the boundary vertex where the two planes cross lies on the
    light edge; the cross product of their normals was off by eps over their angle (1e-9: 2.6e-10
    U; 1e-12: 4.4e-7 U; 1e-13: 4.1e-6 U; and gradients off by up to 1e7 of their size). The host
    engine (soup and mesh) and the differentiated path within 1e-13 U of the exact reference,
    gradients finite; at 1e-9 m (one receiver, one edge) the gradients in the occluder's vertices
    and the receiver within 1e-6 of central differences of the exact reference (50 digits, steps
    of d / 1000; measured 9e-8, and 8e-5 at 1e-12 m, 1.3e-3 at 1e-13 m: eps over the angle)."""
    light = _turned_light()
    lt = js.PolygonLight(light, 1.0)
    n = np.array([0.0, 0.0, 1.0])
    for j, p in enumerate((np.array([0.3, -0.7, 0.1]), np.array([-0.55, 0.2, 0.0]))):
        u = float(np.asarray(js.irradiance(js.Scene([lt]), p[None], n[None]))[0, 0])
        for i in (1, 2):
            tris = _grazing(light, p, i, d)
            ref = er.irradiance(light, tris, p, n)
            assert 0 < ref < 0.99 * u
            for occ in (tris, [js.Mesh(tris.reshape(-1, 3), np.arange(3)[None])]):
                e = float(np.asarray(js.irradiance(js.Scene([lt], occluders=occ), p[None], n[None]))[0, 0])
                assert abs(e - ref) <= 1e-13 * u, (p, i, e, ref)

            def f(t, q):
                return js.irradiance(js.Scene([lt], occluders=t), q[None], jnp.asarray(n)[None])[0, 0]

            val, (gt, gp) = jax.value_and_grad(f, argnums=(0, 1))(jnp.asarray(tris), jnp.asarray(p))
            assert abs(float(val) - ref) <= 1e-13 * u
            assert np.all(np.isfinite(np.asarray(gt))) and np.all(np.isfinite(np.asarray(gp)))
            if d == 1e-9 and i == 1 and j == 0:
                fd_t, fd_p = _exact_gradients(light, tris, p, n, d / 1000)
                scale = max(np.abs(fd_t).max(), np.abs(fd_p).max())
                assert np.abs(np.asarray(gt) - fd_t).max() <= 1e-6 * scale
                assert np.abs(np.asarray(gp) - fd_p).max() <= 1e-6 * scale


def _nearly_in_line(light: np.ndarray, p: np.ndarray, d: float) -> np.ndarray:
    """Two triangles 35 % and 50 % of the way from `p` to the light's centre c, each with an edge
    a -> b in the plane through `p`, c and the horizontal direction w at 0.3 rad (the edges
    turned by +-0.2 rad within it, 0.105 m and 0.15 m long, centred on the line p c), a `d` m to
    one side of that plane and b `d` m to the other, oppositely for the two: seen from `p` the
    edges have no common end and cross near c at an angle of about d / 0.1 m rad; the third
    vertices lie on the same side of the plane, apart in projection (the triangles overlap in
    projection and the boundary switches from one edge to the other at the crossing)."""
    c = light.mean(axis=0)
    w = np.array([np.cos(0.3), np.sin(0.3), 0.0])
    dc = (c - p) / np.linalg.norm(c - p)
    m = np.cross(dc, w)
    m /= np.linalg.norm(m)

    def tri(s: float, tilt: float, dd: float, side: float) -> np.ndarray:
        ctr = p + s * (c - p)
        e = np.cos(tilt) * w + np.sin(tilt) * 0.3 * dc
        return np.array([ctr - 0.15 * s * e + dd * m, ctr + 0.15 * s * e - dd * m, ctr + side * s * m + 0.02 * s * dc])

    return np.array([tri(0.35, 0.2, d, 0.2), tri(0.5, -0.2, -d, 0.27)])


@pytest.mark.parametrize("d", [1e-9, 1e-12, 1e-13, 0.0])
def test_two_occluder_edges_nearly_in_line(d) -> None:
    """Two occluder edges of different triangles whose planes through the receiver are about
    `d` / 0.1 m rad apart (`_nearly_in_line`, two receivers): the boundary vertex where their
    projections cross lies on one edge's line (`occluder_edges_crossing`); the cross product of
    the planes' normals is off by eps over their angle (1e-9: 4.9e-11 U, 1e-12: 1.1e-7 U,
    1e-13: 2.4e-6 U). The host engine (soup and mesh), the differentiated path and the device
    kernel within 1e-13 U of the exact reference, gradients finite; at 1e-9 m (one receiver) the
    gradient in the triangles' vertices and the receiver, along two random directions, within
    1e-6 of central differences of the exact reference (measured 2e-8; the cross product's
    vertex: 8e-4)."""
    light = _turned_light()
    lt = js.PolygonLight(light, 1.0)
    n = np.array([0.0, 0.0, 1.0])
    for j, p in enumerate((np.array([-0.55, 0.2, 0.0]), np.array([0.3, -0.7, 0.1]))):
        u = float(np.asarray(js.irradiance(js.Scene([lt]), p[None], n[None]))[0, 0])
        tris = _nearly_in_line(light, p, d)
        ref = er.irradiance(light, tris, p, n)
        assert 0.9 * u < ref < 0.99 * u
        for occ in (tris, [js.Mesh(tris.reshape(-1, 3), np.arange(6).reshape(2, 3))]):
            e = float(np.asarray(js.irradiance(js.Scene([lt], occluders=occ), p[None], n[None]))[0, 0])
            assert abs(e - ref) <= 1e-13 * u, (p, e, ref)
        dev = js.irradiance(js.Scene([lt], occluders=tris), p[None], n[None], shadows=js.ShadowOptions(engine="device"))
        assert abs(float(np.asarray(dev)[0, 0]) - ref) <= 1e-13 * u

        def f(t, q):
            return js.irradiance(js.Scene([lt], occluders=t), q[None], jnp.asarray(n)[None])[0, 0]

        val, (gt, gp) = jax.value_and_grad(f, argnums=(0, 1))(jnp.asarray(tris), jnp.asarray(p))
        assert abs(float(val) - ref) <= 1e-13 * u
        assert np.all(np.isfinite(np.asarray(gt))) and np.all(np.isfinite(np.asarray(gp)))
        if d == 1e-9 and j == 1:
            g = np.concatenate([np.asarray(gt).ravel(), np.asarray(gp)])
            for v in np.random.default_rng(1).normal(size=(2, g.size)):
                fd, vt, vp = _exact_directional(light, tris, p, n, v[:-3].reshape(tris.shape), v[-3:], d / 1000)
                va = np.concatenate([vt.ravel(), vp])
                assert abs(g @ va - fd) <= 1e-6 * np.linalg.norm(g) * np.linalg.norm(va)


def _exact_directional(light: np.ndarray, tris: np.ndarray, p: np.ndarray, n: np.ndarray, vt: np.ndarray,
                       vp: np.ndarray, h: float) -> tuple[float, np.ndarray, np.ndarray]:
    """The central difference of the exact reference (`DIGITS` digits, not rounded to float64)
    along the direction `(vt, vp)` in `(tris, p)`, step `h`, and the direction actually taken
    (the float64 points `x +- h v` are rounded, by up to eps |x|, which is not small against
    `h`; their difference is exact): `(difference, vt', vp')`."""

    def value(t: np.ndarray, q: np.ndarray) -> mpmath.mpf:
        pieces, P = er.visible_region(light, t, q, n)
        N = er._q(n)
        return sum((er.lambert(P, N, pc) for pc in pieces), mpmath.mpf(0)) / (2 * mpmath.sqrt(er._mp(er._dot(N, N))))

    tp, tm, pp, pm = tris + h * vt, tris - h * vt, p + h * vp, p - h * vp
    with mpmath.workdps(er.DIGITS):
        fd = float((value(tp, pp) - value(tm, pm)) / (2 * h))
    return fd, (tp - tm) / (2 * h), (pp - pm) / (2 * h)


def _exact_gradients(light: np.ndarray, tris: np.ndarray, p: np.ndarray, n: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Central differences of the exact reference (`DIGITS` digits, not rounded to float64) in
    each coordinate of `tris` and `p`, over the float64 steps actually taken."""

    def value(t: np.ndarray, q: np.ndarray) -> mpmath.mpf:
        pieces, P = er.visible_region(light, t, q, n)
        N = er._q(n)
        return sum((er.lambert(P, N, pc) for pc in pieces), mpmath.mpf(0)) / (2 * mpmath.sqrt(er._mp(er._dot(N, N))))

    def diff(x: np.ndarray, idx: tuple, fn) -> float:
        xp, xm = x.copy(), x.copy()
        xp[idx] += h
        xm[idx] -= h
        return float((fn(xp) - fn(xm)) / (mpmath.mpf(float(xp[idx])) - mpmath.mpf(float(xm[idx]))))

    with mpmath.workdps(er.DIGITS):
        gt = np.array([diff(tris, idx, lambda t: value(t, p)) for idx in np.ndindex(*tris.shape)]).reshape(tris.shape)
        gp = np.array([diff(p, (k,), lambda q: value(tris, q)) for k in range(3)])
    return gt, gp


def study(k: int = 24) -> None:
    """Print, per input and placement, the largest `|E - exact| / U` of the engine's silhouette
    path, its face path, the faces as a soup and the shapely reference, and how many receivers
    are in penumbra (exactly)."""
    from benchmarks import _robustness_checks as chk

    gen = ms.generated(CASES, subdivisions=2)
    print("| input | placement | receivers | penumbra | silhouette | face path | soup | shapely |")
    print("|---|---|---|---|---|---|---|---|")
    for name in CASES:
        g = gen[name]
        tris = g["tris"] if "tris" in g else g["v"][g["f"]]
        for label, (p, n) in placements(name, g, k).items():
            cols = []
            for occ, env in ((occluders(g), None), (occluders(g), {"JAXSHADOW_SILHOUETTE": "0"}), (tris, None)):
                cols.append(_engine(occ, p, n, env))
            cols.append(chk.polygon_reference(ms.LIGHT, tris, p, n))
            errs = [errors(g, p, n, c) for c in cols[:1]]
            _, ref, u = errs[0]
            scale = np.maximum(np.abs(u), 1e-3 * np.abs(u).max())
            pen = int(np.sum((ref > 0) & (ref < 0.999 * u)))
            row = " | ".join(f"{np.max(np.abs(c - ref) / scale):.1e}" for c in cols)
            print(f"| {name} | {label} | {len(p)} | {pen} | {row} |", flush=True)


if __name__ == "__main__":
    study(int(sys.argv[1]) if len(sys.argv) > 1 else 24)
