"""Light fits with a mesh occluder of thousands of triangles: `inverse.fit_light` through the
shadow engine's mesh path (the silhouette path, `csrc/engine/silhouette*.h`) inside the solver's
compiled program.

The mesh is generated (no download): an icosphere of 5120 triangles whose vertices are moved
radially by a smooth random field (non-convex: bumps and dents), 0.3 m across, hanging 0.3-0.9 m
above a floor under a quad light at 1.6 m. The targets are floor points painted by `js.shade`
(half in penumbra, some in umbra). Checked: the light is recovered exactly from a start 10 % of the
scene away; the solver's Jacobian at the answer (the engine inside the program, at its capacity)
equals central differences of the host engine's residual; the capacity the fit compiled for is
bounded by the mesh's contour as the targets see it, not by its triangle count.
"""

import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import inverse
import jaxshadow as js

PENUMBRA, UMBRA, LIT = 3, 2, 1


def bumpy_sphere(subdivisions: int = 4, radius: float = 0.3, centre=(0.0, 0.0, 0.6), amplitude: float = 0.3,
                 seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """`(vertices, faces)`: an icosphere (20 * 4**subdivisions triangles) with each vertex moved
    along its radius by `amplitude` times a sum of six random plane waves (non-convex)."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = np.asarray(m.vertices, np.float64)
    rng = np.random.default_rng(seed)
    k = rng.normal(size=(6, 3)) * 2.5
    phase = rng.uniform(0.0, 2 * np.pi, 6)
    bump = np.sin(v @ k.T + phase).mean(axis=1)
    return v * (1.0 + amplitude * bump)[:, None] * radius + np.asarray(centre), np.asarray(m.faces)


def quad_light(centre, half=(0.25, 0.15), tilt=0.15) -> np.ndarray:
    """A rectangle facing down (tilted by `tilt` rad about x), counter-clockwise seen from below."""
    hx, hy = half
    v = np.array([[-hx, hy, 0.0], [hx, hy, 0.0], [hx, -hy, 0.0], [-hx, -hy, 0.0]])
    c, s = np.cos(tilt), np.sin(tilt)
    return v @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]]).T + np.asarray(centre, np.float64)


def contour_edge_counts(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Per point, the mesh edges whose two faces lie on opposite sides of it (its silhouette
    edges; the mesh is closed): NumPy, independent of the engine."""
    tri = vertices[faces]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    m = trimesh.Trimesh(vertices, faces, process=False)
    a, b = m.face_adjacency.T
    side = np.einsum("fk,pfk->pf", nrm, points[:, None, :] - tri[None, :, 0]) > 0
    return np.count_nonzero(side[:, a] != side[:, b], axis=1)


@pytest.fixture(scope="module")
def mesh_scene():
    v, f = bumpy_sphere()
    mesh = js.Mesh(v, f)
    true = js.Scene([js.PolygonLight(quad_light([0.15, 0.1, 1.6]), radiance=[4.0, 3.5, 3.0])], occluders=[mesh],
                    ambient=0.05)
    rng = np.random.default_rng(1)
    cand = np.c_[rng.uniform(-1.0, 1.0, (1500, 2)), np.zeros(1500)]
    up = np.tile([0.0, 0.0, 1.0], (1500, 1))
    plan = js.shadow_plan(true, cand, up).lights[0]
    pick = [rng.choice(np.flatnonzero(plan.classes == c), k, replace=False) for c, k in ((PENUMBRA, 30), (UMBRA, 6),
                                                                                         (LIT, 24))]
    idx = np.concatenate(pick)
    pts, nrm = cand[idx], up[idx]
    material = js.Material(ka=0.2, kd=[0.6, 0.5, 0.4], ks=0.0, exponent=1.0)
    eye = np.array([0.0, -2.5, 2.0])
    targets = inverse.PaintedTargets(pts, nrm, js.shade(true, material, pts, nrm, eye), eye)
    return {"vertices": v, "faces": f, "mesh": mesh, "true": true, "targets": targets, "material": material,
            "kept": plan.kept[idx], "classes": plan.classes[idx]}


@pytest.fixture(scope="module")
def mesh_fit(mesh_scene):
    """`fit_light` from the true quad moved 10 % of the scene size and turned 3 degrees (one
    start, a local LM), with the solver's `Solution` kept."""
    s = mesh_scene
    true, targets = s["true"], s["targets"]
    size = inverse.scene_size(true, targets)
    v = np.asarray(true.lights[0].vertices)
    c = v.mean(axis=0)
    t = np.radians(3.0)
    rot = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1.0]])
    shift = 0.1 * size * np.array([0.6, -0.64, 0.48])
    start = js.Scene([js.PolygonLight((v - c) @ rot.T + c + shift, radiance=[4.0, 3.5, 3.0])],
                     occluders=true.occluders, ambient=true.ambient)
    kept: list = []
    fit = inverse.fit_light(start, targets, s["material"], fit=("position", "orientation"), starts=1,
                            solver=inverse.LM(refine=None), _solution=kept)
    return fit, kept[0], start


def test_mesh_scene_takes_the_silhouette_path(mesh_scene):
    """The scene is what the tests claim: thousands of triangles, a non-convex closed mesh, and
    every target served by the engine's silhouette path (at most one occluder region kept)."""
    m = trimesh.Trimesh(mesh_scene["vertices"], mesh_scene["faces"], process=False)
    assert len(m.faces) == 5120 and m.is_watertight
    assert len(m.convex_hull.vertices) < 0.8 * len(m.vertices)  # dents: a fifth of the vertices inside the hull
    assert np.all(mesh_scene["kept"] <= 1)
    assert np.count_nonzero(mesh_scene["classes"] == PENUMBRA) == 30


def test_fit_light_with_mesh_occluder_recovers_the_light_exactly(mesh_scene, mesh_fit):
    fit, sol, _ = mesh_fit
    true = np.asarray(mesh_scene["true"].lights[0].vertices)
    np.testing.assert_allclose(np.asarray(fit.light.vertices), true, rtol=0, atol=1e-9)
    assert fit.report.loss < 1e-20
    assert fit.report.trusted


def test_fit_jacobian_through_the_mesh_path_equals_central_differences(mesh_scene, mesh_fit):
    """d(residual)/d(theta) at the answer from the solver's program (the engine inside it, at
    the fit's capacity) against float64 central differences of the same residual evaluated by
    `js.shade` (the host engine, concrete values)."""
    fit, sol, start = mesh_fit
    s = mesh_scene
    t, material = s["targets"], s["material"]
    problem = sol.problem
    theta = np.asarray(sol.values[sol.best], np.float64)
    sw = np.sqrt(np.broadcast_to(np.asarray(t.weights, np.float64).reshape(len(t.points), -1), t.points.shape))

    def residual(th):
        light = problem.lights(jnp.asarray(th))[0]
        sc = js.Scene([light], occluders=start.occluders, ambient=start.ambient)
        model = np.asarray(js.shade(sc, material, t.points, t.normals, t.eye), np.float64)
        return (sw * (model - np.asarray(t.colours, np.float64))).reshape(-1)

    h = 1e-5
    fd = np.stack([(residual(theta + h * e) - residual(theta - h * e)) / (2 * h) for e in np.eye(theta.size)], axis=1)
    J = np.asarray(sol.jacobian, np.float64)
    assert J.shape == fd.shape
    penumbra_rows = np.repeat(s["classes"] == PENUMBRA, 3)
    assert np.all(np.abs(J[penumbra_rows]).max(axis=0) > 0)  # every parameter moves some penumbra
    np.testing.assert_allclose(J, fd, rtol=0, atol=1e-6 * np.abs(fd).max())


def test_fit_capacity_is_bounded_by_the_contour_not_the_triangle_count(mesh_scene, mesh_fit):
    """The capacity the fit's program was compiled for (`report.capacity`: boundary edges per
    receiver) is at most the number of the mesh's contour edges any target sees (counted in
    NumPy), a small fraction of the triangle count."""
    fit, _, _ = mesh_fit
    s = mesh_scene
    contour = contour_edge_counts(s["vertices"], s["faces"], np.asarray(s["targets"].points, np.float64))
    assert fit.report.capacity is not None
    assert fit.report.capacity <= contour.max() < len(s["faces"]) / 20
