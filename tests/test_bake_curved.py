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
    assert b.stats["unconverged"] == [] and b.stats["converged"], b.stats["unconverged"]
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


def _torus():
    """The example scene's torus (`write_example_scene`): 768 faces, float32 vertices, smooth normals."""
    t = trimesh.creation.torus(0.35, 0.12, major_sections=32, minor_sections=12)
    t.apply_transform(trimesh.transformations.rotation_matrix(np.radians(20), [1, 0, 0]))
    t.apply_translation([0.1, 0.0, 0.6])
    v = np.asarray(t.vertices).astype(np.float32).astype(np.float64)
    return v, np.asarray(t.faces), np.asarray(t.vertex_normals, np.float64)


def _torus_scene():
    v, f, n = _torus()
    light = js.PolygonLight([[-0.15, -0.2, 1.6], [-0.15, 0.4, 1.6], [0.45, 0.4, 1.6], [0.45, -0.2, 1.6]],
                            radiance=8.0)
    return js.Scene([light], occluders=[js.Mesh(v, f)]), js.ReceiverMesh(v, f, n, name="torus")


def test_vertices_with_a_limit_per_direction_are_corners():
    """Where the faces around a vertex shadow the light for points of one face near it (a
    concave fold, or the terminator: the faces below a face's plane block the part of the light
    under it), the irradiance takes a different limit along each direction of approach, the
    same at every distance: the mesher cannot meet tol next to it and must report it as a
    corner. Checked independently: `js.irradiance` at 1e-5 m and 1e-4 m from each vertex
    towards both edges of each face around it (the faces as exact planes); where the two
    directions differ by more than 1e-3 of the scale at both distances alike, the vertex must
    be in `stats["corners"]` (no refinement needed: `max_rounds=0`)."""
    v, f, n = _torus()
    scene, rec = _torus_scene()
    with pytest.warns(RuntimeWarning, match="over tol"):  # no refinement: reported, not silent
        b = js.bake(scene, [rec], 1e-3, max_rounds=0)
    assert not b.stats["converged"]
    pts, nrm, vid = [], [], []
    for vi in range(v.shape[0]):
        for fi in np.nonzero((f == vi).any(axis=1))[0]:
            a, c = (v[k] for k in f[fi] if k != vi)
            for r in (1e-5, 1e-4):
                for w in (0.05, 0.95):
                    q = w * a + (1 - w) * c - v[vi]
                    pts.append(v[vi] + r * q / np.linalg.norm(q))
                    nrm.append(n[vi])
            vid.append(vi)
    e = np.asarray(js.irradiance(_exact_scene(scene), np.array(pts), np.array(nrm))).max(axis=1).reshape(-1, 2, 2)
    spread = np.abs(e[:, :, 0] - e[:, :, 1]) / b.scale  # (vertex-face pairs, distance)
    turning = (spread.min(axis=1) > 1e-3) & (np.abs(spread[:, 0] - spread[:, 1]) < 0.2 * spread.max(axis=1))
    need = sorted(set(np.array(vid)[turning].tolist()))
    assert len(need) >= 10  # the torus has them: its concave inner side, the terminator
    listed = np.concatenate([np.array(c["points"]).reshape(-1, 3) for c in b.stats["corners"]])
    missing = [k for k in need if np.linalg.norm(listed - v[k], axis=1).min() > 1e-9]
    assert missing == [], (len(missing), len(need))


@pytest.mark.slow
def test_torus_meets_tol_off_its_corners():
    """The torus at tol 1e-3 (~3 min): converged, its corners' error (over tol) warned, and
    the interpolation error at random points strictly inside the output triangles within tol
    except in the triangles with a corner within `CORNER_SIZE` of the patch's size of a listed
    corner (the limit turns with the direction there). Against `js.irradiance` with the faces
    as exact planes."""
    from scipy.spatial import cKDTree

    from jaxshadow._illumination.refine import CORNER_SIZE

    scene, rec = _torus_scene()
    tol = 1e-3
    with pytest.warns(RuntimeWarning, match="corners of curved patches"):
        b = js.bake(scene, [rec], tol)
    assert b.stats["converged"] and b.stats["unconverged"] == []
    corners = np.concatenate([np.array(c["points"]).reshape(-1, 3) for c in b.stats["corners"]])
    reach = CORNER_SIZE * (1 + 1e-9) * np.ptp(b.vertices, axis=0).max()
    d = cKDTree(corners).query(b.vertices)[0]
    away = ~np.any(d[b.triangles] <= reach, axis=1)
    p, n, interp = _inside_samples(b, n_per=4)
    keep = np.repeat(away, 4)
    exact = np.asarray(js.irradiance(_exact_scene(scene), p[keep], n[keep]))
    assert np.abs(interp[keep] - exact).max() <= tol * b.scale
