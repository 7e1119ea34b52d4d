"""`js.bake` on curved surfaces that shadow themselves (issue 39): a faceted sphere with smooth
normals, its faces both receiver and occluders, float32 vertices (as read from a file).

The exact irradiance of a faceted surface jumps across its edges near the terminator (the
faces' planes cut the light differently); the bake takes each face's own limits there (one
vertex per face) and evaluates the faces as exact planes. References: `js.irradiance` at random
points strictly inside the output triangles (inside one face each) with the interpolated
normal, the occluders moved to the double on-surface rule as the bake defines them
(`exact_planes`); and, where the surface is no occluder, `js.irradiance` at the vertices."""

import numpy as np
import pytest

import jaxshadow as js
from jaxshadow._illumination.bake_curved import exact_planes

trimesh = pytest.importorskip("trimesh")
TOL = 1e-2
CENTRE = np.array([0.1, -0.1, 0.6])


def _sphere():
    s = trimesh.creation.uv_sphere(radius=0.3, count=[14, 14])
    v = (np.asarray(s.vertices) + CENTRE).astype(np.float32).astype(np.float64)
    f = np.asarray(s.faces)
    n = v - CENTRE
    return v, f, n / np.linalg.norm(n, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def baked():
    v, f, n = _sphere()
    light = js.PolygonLight([[-0.3, -0.3, 2], [-0.3, 0.3, 2], [0.3, 0.3, 2], [0.3, -0.3, 2]], radiance=10.0)
    scene = js.Scene([light], occluders=[js.Mesh(v, f)])
    return scene, js.bake(scene, [js.ReceiverMesh(v, f, n, name="sphere")], TOL)


def _inside_samples(b, n_per=6, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.uniform(0.02, 0.96, (b.triangles.shape[0], n_per, 2))
    flip = u.sum(axis=2) > 0.98
    u[flip] = 0.98 - u[flip]
    w = np.concatenate([1 - u.sum(axis=2, keepdims=True), u], axis=2)
    t = b.triangles
    p = np.einsum("tnk,tkd->tnd", w, b.vertices[t]).reshape(-1, 3)
    e = np.einsum("tnk,tkd->tnd", w, b.irradiance[t]).reshape(-1, 3)
    nn = np.einsum("tnk,tkd->tnd", w, b.normals[t]).reshape(-1, 3)
    return p, np.ascontiguousarray(nn / np.linalg.norm(nn, axis=1, keepdims=True)), e


def _exact_scene(scene):
    import jax.numpy as jnp

    ex = js.Scene(scene.lights)
    object.__setattr__(ex, "occluders", jnp.asarray(exact_planes(np.asarray(scene.occluders))))
    object.__setattr__(ex, "occluder_topology", scene.occluder_topology)
    return ex


def test_self_shadowing_sphere_converges_to_tol(baked):
    scene, b = baked
    assert b.stats["unconverged"] == [], b.stats["unconverged"]
    p, n, interp = _inside_samples(b)
    exact = np.asarray(js.irradiance(_exact_scene(scene), p, n))
    err = np.abs(interp - exact).max() / b.scale
    assert err <= TOL, err
    # adaptive: refined near the terminator only, far from the minimum edge length everywhere
    assert b.triangles.shape[0] < 40 * 14 * 14


def test_terminator_edges_carry_each_faces_limit(baked):
    """Near the terminator the faces on either side of an edge give different limits: the
    point is then one vertex per face (same position and normal, different values), each the
    limit of its own triangles' values from inside."""
    scene, b = baked
    key = np.round(np.concatenate([b.vertices, b.normals], axis=1), 12)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    twins = np.nonzero(cnt[inv] > 1)[0]
    assert twins.size > 0
    groups = {}
    for v in twins.tolist():
        groups.setdefault(int(inv[v]), []).append(v)
    spread = max(np.abs(b.irradiance[g].sum(axis=1) - b.irradiance[g[0]].sum()).max() for g in groups.values())
    assert spread > TOL * b.scale  # a real jump, not round-off
    # each twin is the limit of its own triangles from inside: a point 1e-5 of the way in
    ex = _exact_scene(scene)
    rows = [(v, t) for v in twins[:200].tolist() for t in np.nonzero((b.triangles == v).any(axis=1))[0][:1].tolist()]
    pts, nrm, val = [], [], []
    for v, t in rows:
        c = b.vertices[b.triangles[t]].mean(axis=0)
        pts.append(b.vertices[v] + 1e-5 * (c - b.vertices[v]))
        nrm.append(b.normals[v])
        val.append(b.irradiance[v])
    got = np.asarray(js.irradiance(ex, np.array(pts), np.array(nrm)))
    assert np.abs(got - np.array(val)).max() <= 1e-3 * b.scale


def test_a_surface_that_shadows_nothing_keeps_one_value_per_point():
    """No occluder face passes through the surface's points: every value is the point's own,
    one vertex per point, equal to `js.irradiance` there."""
    v, f, n = _sphere()
    light = js.PolygonLight([[-0.3, -0.3, 2], [-0.3, 0.3, 2], [0.3, 0.3, 2], [0.3, -0.3, 2]], radiance=10.0)
    blocker = np.array([[-0.2, -0.4, 1.4], [0.3, -0.4, 1.4], [0.3, 0.0, 1.4], [-0.2, 0.0, 1.4]])
    scene = js.Scene([light], occluders=[blocker])
    b = js.bake(scene, [js.ReceiverMesh(v, f, n, name="sphere")], 5e-2)
    key = np.round(np.concatenate([b.vertices, b.normals], axis=1), 12)
    assert np.unique(key, axis=0).shape[0] == b.vertices.shape[0]
    ref = np.asarray(js.irradiance(scene, b.vertices, b.normals))
    assert np.abs(ref - b.irradiance).max() <= 1e-12 * np.abs(ref).max()
