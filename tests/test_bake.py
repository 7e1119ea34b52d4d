"""`js.bake` and `jaxshadow bake` (issue 39): every surface of a scene meshed, seam-free, exact
irradiance per light; chunks on Dask workers, resumable from per-chunk files.

References: the vertex values against `js.irradiance` of each light alone at the output
vertices; the interpolation error against `js.irradiance` at random points of every output
triangle; seams from the output geometry alone (no vertex of a patch strictly inside another
patch's boundary edge)."""

import os
import sys

import equinox as eqx
import numpy as np
import pytest

import jaxshadow as js
from jaxshadow.cli import main

pytest.importorskip("pythoncdt")
trimesh = pytest.importorskip("trimesh")

NC = "--no-compile-cache"
TOL = 5e-2


def _scene_and_receivers():
    """Two square lights above a floor made of two quads (one surface), a wall standing on the
    floor's edge (a crease), a blocker, and a UV sphere cut along a ring into two curved
    surfaces (a shared curved edge between surfaces) in the blocker's penumbra."""
    light = js.PolygonLight([[-0.3, -0.3, 2], [-0.3, 0.3, 2], [0.3, 0.3, 2], [0.3, -0.3, 2]], radiance=10.0)
    light2 = js.PolygonLight([[0.6, -0.8, 1.5], [0.6, -0.6, 1.5], [0.8, -0.6, 1.5], [0.8, -0.8, 1.5]], radiance=4.0)
    blocker = np.array([[-0.2, -0.25, 1], [0.5, -0.25, 1], [0.5, 0.15, 1], [-0.2, 0.15, 1]])
    floor = [np.array([[-1, -1, 0], [0, -1, 0], [0, 1, 0], [-1, 1, 0.0]]),
             np.array([[0, -1, 0], [1, -1, 0], [1, 1, 0], [0, 1, 0.0]])]
    wall = js.ReceiverMesh([[1, -1, 0], [1, 1, 0], [1, 1, 1], [1, -1, 1.0]], [[0, 2, 1], [0, 3, 2]], name="wall")
    s = trimesh.creation.uv_sphere(radius=0.18, count=[8, 8])
    s.apply_translation([0.55, 0.3, 0.45])
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    nrm = (v - [0.55, 0.3, 0.45]) / 0.18
    up = v[f].mean(axis=1)[:, 2] > 0.45
    halves = [js.ReceiverMesh(v, f[m], nrm, name=n) for m, n in ((up, "upper"), (~up, "lower"))]
    # The sphere receives the blocker's penumbra but casts no shadow: on a faceted sphere with
    # smooth normals a receiver's tangent plane cuts the neighbouring faces, whose (exact)
    # shadows near the terminator refine down to max_rounds.
    scene = js.Scene([light, light2], occluders=[blocker])
    return scene, [floor, wall, *halves]


@pytest.fixture(scope="module")
def baked():
    scene, receivers = _scene_and_receivers()
    return scene, js.bake(scene, receivers, TOL, tile_size=0.5)


def _boundary_segments(tris):
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    uniq, count = np.unique(edges, axis=0, return_counts=True)
    return uniq[count == 1]


def test_surfaces_and_patches(baked):
    _, b = baked
    assert b.surface_names[1:] == ["wall", "upper", "lower"]
    assert set(np.unique(b.surface)) == {0, 1, 2, 3}
    assert b.stats["patches_planar"] >= 3 and b.stats["patches_curved"] == 2
    assert b.irradiance_per_light.shape == (b.vertices.shape[0], 2, 3)
    np.testing.assert_array_equal(b.irradiance, b.irradiance_per_light.sum(axis=1))


def test_vertex_values_are_exact_per_light(baked):
    scene, b = baked
    for li, light in enumerate(scene.lights):
        alone = eqx.tree_at(lambda s: s.lights, scene, (light,))
        ref = np.asarray(js.irradiance(alone, b.vertices, b.normals))
        err = np.abs(b.irradiance_per_light[:, li] - ref)
        assert err.max() <= 1e-12 * max(np.abs(ref).max(), 1e-300)


def check_seams(b):
    """Every vertex on a patch's boundary that lies on another patch's boundary edge is an end
    of it (never strictly inside: no T vertex); coincident vertices of two patches are at the
    same position exactly, and with equal normals carry values within 1e-12 relative. Returns
    the boundary vertices of each patch."""
    V, T = b.vertices, b.triangles
    size = np.ptp(V, axis=0).max()
    segs, bverts = [], []
    for p in np.unique(b.patch):
        s = _boundary_segments(T[b.patch == p])
        segs.append((p, s))
        bverts.append((p, np.unique(s)))
    shared = 0
    for p, s in segs:
        a, c = V[s[:, 0]], V[s[:, 1]]
        d = c - a
        for q, vs in bverts:
            if q == p:
                continue
            x = V[vs]
            t = np.einsum("snk,sk->sn", x[None] - a[:, None], d) / np.einsum("sk,sk->s", d, d)[:, None]
            foot = a[:, None] + t[..., None] * d[:, None]
            dist = np.linalg.norm(x[None] - foot, axis=2)
            on = dist <= 1e-9 * size
            inner = on & (t > 1e-9) & (t < 1 - 1e-9)
            assert not inner.any(), f"patch {q} vertex inside a boundary edge of patch {p}"
            shared += int((on & ((np.abs(t) <= 1e-9) | (np.abs(t - 1) <= 1e-9))).sum())
    assert shared > 0
    # coincident positions on patch boundaries (inside a patch the mesher may leave points 1e-13
    # apart: no seam)
    on_boundary = np.unique(np.concatenate([v for _, v in bverts]))
    key = V[on_boundary].round(12)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    groups = [on_boundary[inv.ravel() == g] for g in np.nonzero(cnt > 1)[0]]
    patches_of = {}
    for p, vs in bverts:
        for v in vs.tolist():
            patches_of.setdefault(v, set()).add(int(p))
    seams = [g for g in groups if len({frozenset(patches_of[v]) for v in g.tolist()}) > 1]
    assert seams
    same_normal = 0
    for g in seams:
        assert np.all(V[g] == V[g[0]]), "coincident vertices of two patches must be at the same position exactly"
        for i in g[1:]:
            if b.normals[i] @ b.normals[g[0]] > 1 - 1e-9:
                same_normal += 1
                e0, e1 = b.irradiance_per_light[g[0]], b.irradiance_per_light[i]
                assert np.abs(e0 - e1).max() <= 1e-12 * max(np.abs(e0).max(), 1e-12 * b.scale)
    return bverts


def test_no_t_junctions_and_one_value_per_point(baked):
    """`check_seams`; the floor-wall crease and the sphere's cut are shared."""
    _, b = baked
    V, T = b.vertices, b.triangles
    check_seams(b)
    # where the normals are equal (the floor halves' edge x = 0, the sphere's cut) the two
    # patches share the vertices themselves: one value per point
    users = {}
    for p in np.unique(b.patch):
        for v in np.unique(T[b.patch == p]).tolist():
            users.setdefault(v, set()).add(int(p))
    joint = np.array([v for v, u in users.items() if len(u) > 1])
    assert np.sum(np.abs(V[joint, 0]) < 1e-12) >= 3
    on_both = np.intersect1d(np.unique(T[b.surface == 2]), np.unique(T[b.surface == 3]))
    assert on_both.size >= 8  # the cut between the sphere's halves
    # the floor-wall crease: wall vertices on the floor line z = 0, x = 1 coincide with floor vertices
    wall_on = np.unique(T[b.surface == 1])
    wall_on = wall_on[np.abs(V[wall_on, 2]) < 1e-12]
    floor_on = np.unique(T[b.surface == 0])
    floor_on = floor_on[np.abs(V[floor_on, 0] - 1) < 1e-12]
    assert wall_on.size > 2
    np.testing.assert_array_equal(np.unique(V[wall_on], axis=0), np.unique(V[floor_on], axis=0))


def _samples(b, tris, n_per, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.random((tris.shape[0], n_per, 2))
    flip = u.sum(axis=2) > 1
    u[flip] = 1 - u[flip]
    w = np.concatenate([1 - u.sum(axis=2, keepdims=True), u], axis=2)  # (t, n, 3)
    p = np.einsum("tnk,tkd->tnd", w, b.vertices[tris]).reshape(-1, 3)
    e = np.einsum("tnk,tkd->tnd", w, b.irradiance[tris]).reshape(-1, 3)
    nn = np.einsum("tnk,tkd->tnd", w, b.normals[tris]).reshape(-1, 3)
    return p, nn / np.linalg.norm(nn, axis=1)[:, None], e


def test_interpolation_error_on_planar_surfaces_within_tol(baked):
    scene, b = baked
    planar = b.triangles[b.surface <= 1]
    p, n, interp = _samples(b, planar, 12)
    exact = np.asarray(js.irradiance(scene, p, n))
    assert np.abs(interp - exact).max() <= TOL * b.scale


def test_curved_surfaces_refined_to_tol_at_edge_midpoints(baked):
    """Curved patches split every edge whose midpoint value misses linear interpolation by more
    than tol (or that is shorter than min_edge): checked at the output's edges."""
    scene, b = baked
    tris = b.triangles[b.surface >= 2]
    assert np.unique(tris).size > 2 * 42  # refined: the two halves of the UV sphere have 42 vertices
    e = np.unique(np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1), axis=0)
    mid = 0.5 * (b.vertices[e[:, 0]] + b.vertices[e[:, 1]])
    nn = b.normals[e[:, 0]] + b.normals[e[:, 1]]
    exact = np.asarray(js.irradiance(scene, mid, nn / np.linalg.norm(nn, axis=1)[:, None]))
    miss = np.abs(exact - 0.5 * (b.irradiance[e[:, 0]] + b.irradiance[e[:, 1]])).max(axis=1)
    short = np.linalg.norm(b.vertices[e[:, 0]] - b.vertices[e[:, 1]], axis=1) <= 1e-4 * np.ptp(b.vertices, axis=0).max()
    assert np.all((miss <= TOL * b.scale) | short)


def test_glb_and_ply_carry_values_per_light(baked, tmp_path):
    _, b = baked
    b.save(tmp_path / "s.glb")
    b.save(tmp_path / "s.ply")
    g = trimesh.load(tmp_path / "s.glb", force="mesh", process=False)
    # glTF is y-up: the scene's (x, y, z) is written as (x, z, -y), every vertex in its order
    # (copies on a crease keep their own values)
    yup = b.vertices[:, [0, 2, 1]] * np.array([1.0, 1.0, -1.0])
    np.testing.assert_allclose(g.vertices, yup, rtol=0, atol=1e-6 * np.abs(yup).max())
    np.testing.assert_allclose(g.vertex_attributes["_IRRADIANCE_1"], b.irradiance_per_light[:, 1], rtol=1e-6)
    np.testing.assert_allclose(g.vertex_attributes["_IRRADIANCE"], b.irradiance, rtol=1e-6)
    from jaxshadow._io.meshio import read_ply_values

    np.testing.assert_array_equal(read_ply_values(tmp_path / "s.ply"), b.irradiance)
    np.testing.assert_array_equal(read_ply_values(tmp_path / "s.ply", "irradiance_0"), b.irradiance_per_light[:, 0])


def test_lights_subset_and_bad_input():
    scene, rec = _scene_and_receivers()
    one = js.bake(scene, rec[:1], 0.2, lights=[1], tile_size=1.0)
    assert one.irradiance_per_light.shape[1] == 1 and list(one.lights) == [1]
    alone = eqx.tree_at(lambda s: s.lights, scene, (scene.lights[1],))
    ref = np.asarray(js.irradiance(alone, one.vertices, one.normals))
    np.testing.assert_allclose(one.irradiance, ref, rtol=1e-12, atol=1e-15)
    for bad in ({"tol": 0.0}, {"tol": 1.5}, {"lights": [2]}, {"lights": [0, 0]}, {"workers": 0}):
        kw = {"tol": 0.1, **bad}
        with pytest.raises(ValueError):
            js.bake(scene, rec[:1], **kw)
    with pytest.raises(ValueError):
        js.bake("scene", rec[:1], 0.1)


@pytest.mark.slow
def test_mitsuba_room_bakes_without_seams():
    """The benchmark's Cornell-box-like Mitsuba room (10 surfaces: six rectangles, a table top,
    two cubes, a sphere): no T vertex between any two patches, and the walls' shared edges carry
    the same points from both sides."""
    pytest.importorskip("mitsuba")
    from benchmarks.bake import scene_of

    scene, receivers = scene_of("room")
    b = js.bake(scene, receivers, 2e-2)
    assert len(b.surface_names) == 10 and b.stats["patches_curved"] == 1
    check_seams(b)
    V, T = b.vertices, b.triangles
    names = b.surface_names
    floor = np.unique(T[b.surface == names.index("floor")])
    wall = np.unique(T[b.surface == names.index("wall-x0")])
    line = lambda ids: np.unique(V[ids[(np.abs(V[ids, 2]) < 1e-6) & (np.abs(V[ids, 0] + 1) < 1e-6)]], axis=0)  # noqa: E731
    assert line(wall).shape[0] > 2
    np.testing.assert_array_equal(line(floor), line(wall))


def test_benchmark_contact_corners_are_feet_only():
    """`benchmarks.bake.surface_errors` leaves out the triangles at contact corners: the corners
    of an object's foot (a face lying on the receiver and facing away from it, the box's bottom),
    not the receiver's own corners (the floor is an occluder face too, facing its own way)."""
    from benchmarks.bake import _contact_corners

    floor = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    light = js.PolygonLight([[-0.3, -0.3, 2], [-0.3, 0.3, 2], [0.3, 0.3, 2], [0.3, -0.3, 2]], 10.0)
    scene = js.Scene([light], [floor, js.Mesh.box([0.1, 0.2, 0.0], [0.4, 0.6, 0.5])])
    got = _contact_corners(scene, floor[None, :3], np.array([[0.0, 0.0, 1.0]]))
    want = np.array([[x, y, 0.0] for x in (0.1, 0.4) for y in (0.2, 0.6)])
    np.testing.assert_array_equal(got[np.lexsort(got.T)], want[np.lexsort(want.T)])


# -- chunks: resume and Dask ---------------------------------------------------------------


def _small():
    scene, rec = _scene_and_receivers()
    return scene, [rec[0], rec[2], rec[3]]


def _same(a, b):
    for name in ("vertices", "normals", "triangles", "irradiance_per_light", "surface", "patch"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


@pytest.fixture(scope="module")
def reference():
    scene, rec = _small()
    return js.bake(scene, rec, 0.1, tile_size=1.0)


def test_resume_reads_chunk_files_and_gives_the_same_result(reference, tmp_path):
    scene, rec = _small()
    first = js.bake(scene, rec, 0.1, tile_size=1.0, work_dir=tmp_path)
    files = sorted(os.listdir(tmp_path))
    assert first.stats["chunks_computed"] == first.stats["chunks"] == len(files) == 4
    _same(first, reference)
    os.remove(tmp_path / files[0])  # as if the run had been killed before that chunk
    calls = []
    again = js.bake(scene, rec, 0.1, tile_size=1.0, work_dir=tmp_path, _before_chunk=calls.append)
    assert again.stats["chunks_computed"] == 1 and len(calls) == 1
    _same(again, reference)
    other = js.bake(scene, rec, 0.09, tile_size=1.0, work_dir=tmp_path)  # other settings: other files
    assert other.stats["chunks_computed"] == 4


_CLIENT = """
import os, signal, sys
import jax
jax.config.update("jax_enable_x64", True)
sys.path.insert(0, {tests!r})
import jaxshadow as js
from test_bake import _small

def die(index):
    if index == 2:  # chunks 0 and 1 are on disk: the client process is killed (SIGKILL, no clean-up)
        os.kill(os.getpid(), signal.SIGKILL)

scene, rec = _small()
js.bake(scene, rec, 0.1, tile_size=1.0, work_dir={work!r}, _before_chunk=die)
"""


def test_a_killed_client_resumes_without_computing_its_chunks_again(reference, tmp_path):
    """A client process killed mid-run (SIGKILL while its third chunk starts): the re-run reads
    the two chunks it finished and computes only the other two, and the result is the one of a
    bake that was never interrupted."""
    import signal
    import subprocess

    work = tmp_path / "w"
    code = _CLIENT.format(tests=os.path.dirname(os.path.abspath(__file__)), work=str(work))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([os.path.dirname(os.path.dirname(js.__file__)),
                                                         os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == -signal.SIGKILL, run.stderr[-2000:]
    assert len([f for f in os.listdir(work) if f.endswith(".npz")]) == 2
    calls = []
    again = js.bake(*_small(), 0.1, tile_size=1.0, work_dir=work, _before_chunk=calls.append)
    assert calls == [2, 3] and again.stats["chunks_computed"] == 2
    _same(again, reference)
    assert len([f for f in os.listdir(work) if f.endswith(".npz")]) == 4


def _kill_once(index, marker):
    """Kill this worker process the first time chunk 0 runs (a marker file remembers)."""
    if index == 0 and not os.path.exists(marker):
        with open(marker, "w") as fh:
            fh.write(str(os.getpid()))
        os._exit(1)


@pytest.mark.slow
def test_dask_workers_a_scheduler_address_and_a_killed_worker_give_the_same_result(reference, tmp_path):
    pytest.importorskip("distributed")
    import functools

    import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    scene, rec = _small()
    two = js.bake(scene, rec, 0.1, tile_size=1.0, workers=2)
    _same(two, reference)
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        _same(js.bake(scene, rec, 0.1, tile_size=1.0, scheduler=cluster.scheduler_address), reference)
    marker = str(tmp_path / "killed")
    hook = functools.partial(_kill_once, marker=marker)
    survived = js.bake(scene, rec, 0.1, tile_size=1.0, workers=2, work_dir=tmp_path / "w", _before_chunk=hook)
    assert os.path.exists(marker)  # a worker did die
    assert survived.stats["chunks_computed"] == 4
    _same(survived, reference)


# -- incremental re-bakes --------------------------------------------------------------------


def _two_rooms(blocker_b=(3.0, 0.0), radiance_b=4.0, radiance_a=10.0):
    """Two lit floors 1 m apart, each under its own light and blocker (the shadow volumes of one
    floor reach neither the other's blocker), a hemisphere under light A (a curved patch), and a
    roof above both lights facing up (no light reaches it: both emit downwards)."""
    def quad(cx, cy, z, h, down=False):
        q = np.array([[cx - h, cy - h, z], [cx + h, cy - h, z], [cx + h, cy + h, z], [cx - h, cy + h, z]])
        return q[::-1] if down else q

    lights = [js.PolygonLight(quad(0.0, 0.0, 2.0, 0.3, down=True), radiance=radiance_a),
              js.PolygonLight(quad(3.0, 0.0, 2.0, 0.2, down=True), radiance=radiance_b)]
    blockers = [quad(0.1, 0.0, 1.0, 0.25), quad(*blocker_b, 1.0, 0.15)]
    s = trimesh.creation.uv_sphere(radius=0.15, count=[6, 6])
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    up = v[f].mean(axis=1)[:, 2] > 0
    centre = np.array([0.55, 0.5, 0.3])
    dome = js.ReceiverMesh(v + centre, f[up], v / 0.15, name="dome")
    receivers = [[quad(0.0, 0.0, 0.0, 1.0)], [quad(3.0, 0.0, 0.0, 1.0)], [quad(1.5, 0.0, 2.5, 2.5)], dome]
    return js.Scene(lights, occluders=blockers), receivers


def test_incremental_rebake_computes_only_the_chunks_a_change_reaches(tmp_path):
    """Moving blocker B re-bakes floor B alone; changing light B everything it reaches (not the
    roof); each result identical to a fresh bake of the changed scene (same scale)."""
    scene, rec = _two_rooms()
    kw = {"tile_size": 1.0, "scale": 1.0}
    first = js.bake(scene, rec, 0.1, work_dir=tmp_path, **kw)
    assert first.stats["chunks_computed"] == first.stats["chunks"] == 4
    roof = np.unique(first.triangles[first.surface == 2])
    np.testing.assert_array_equal(first.irradiance_per_light[roof], 0.0)  # dark: no light reaches it
    for light in scene.lights:  # its zeros are the exact values
        alone = eqx.tree_at(lambda s: s.lights, scene, (light,))
        np.testing.assert_array_equal(np.asarray(js.irradiance(alone, first.vertices[roof], first.normals[roof])), 0.0)
    changes = [(_two_rooms(blocker_b=(3.1, 0.05))[0], 1),  # floor B only
               (_two_rooms(radiance_b=6.0)[0], 3),  # floors A and B, the dome (not the roof)
               (_two_rooms(radiance_a=12.0)[0], 3)]
    for changed, n_computed in changes:
        calls = []
        again = js.bake(changed, rec, 0.1, work_dir=tmp_path, _before_chunk=calls.append, **kw)
        assert again.stats["chunks_computed"] == len(calls) == n_computed
        _same(again, js.bake(changed, rec, 0.1, **kw))
        assert not np.array_equal(again.irradiance, first.irradiance)  # the change did change the bake


# -- objects passing through receivers -------------------------------------------------------


def _through_floor(occluder):
    light = js.PolygonLight([[-0.3, 0.3, 2], [0.3, 0.3, 2], [0.3, -0.3, 2], [-0.3, -0.3, 2]], radiance=10.0)
    floor = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0.0]])
    return js.Scene([light], occluders=[occluder]), [floor]


def test_a_closed_object_through_a_receiver_is_cut_out_and_converges():
    """A box from z = -0.3 to 0.5 through the floor: its cross-section is a hole (no triangle
    inside it), every patch converges, and the interpolation error at random points of the
    output triangles is within tol (against `js.irradiance`)."""
    lo, hi = np.array([-0.2, -0.15, -0.3]), np.array([0.25, 0.2, 0.5])
    v = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])
    faces = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [1, 3, 7, 5], [3, 2, 6, 7], [2, 0, 4, 6]]
    scene, rec = _through_floor(js.Mesh(v, faces))
    tol = 0.05
    b = js.bake(scene, rec, tol, max_vertices=50_000)
    assert b.stats["pierced"] == [{"surface": "surface0", "patch": 0, "sections": 1, "open": 0}]
    assert b.stats["unconverged"] == []
    c = b.vertices[b.triangles].mean(axis=1)
    inside = np.all((c[:, :2] > lo[:2] + 1e-9) & (c[:, :2] < hi[:2] - 1e-9), axis=1)
    assert not inside.any()
    p, n, interp = _samples(b, b.triangles, 8)
    # (at a corner of the hole the irradiance has no limit: `illumination_mesh` refines only
    # down to CORNER_SIZE there, graded outside; those samples are left out)
    corners = np.array([[x, y] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])])
    away = np.linalg.norm(p[:, None, :2] - corners[None], axis=2).min(axis=1) > 2e-3
    exact = np.asarray(js.irradiance(scene, p[away], n[away]))
    assert np.abs(interp[away] - exact).max() <= tol * b.scale
    assert b.vertices.shape[0] < 20_000  # (without the cut, refinement along the jump ran to max_vertices)


def test_open_geometry_through_a_receiver_stops_at_a_bounded_size_and_is_reported():
    """A single wall through the floor: the value jumps along the line where it crosses; the
    patch's elements stop at PIERCED_MIN_EDGE of its size (bounded, no budget stop) and the
    elements left over tol are reported with their error."""
    wall = np.array([[-0.4, 0.1, -0.3], [0.4, 0.1, -0.3], [0.4, 0.1, 0.5], [-0.4, 0.1, 0.5]])
    scene, rec = _through_floor(wall)
    tol = 0.05
    with pytest.warns(RuntimeWarning, match="over tol") as caught:  # reported, not silent
        b = js.bake(scene, rec, tol, max_vertices=50_000)
    assert not any("max_vertices" in str(w.message) for w in caught)  # no budget stop
    assert not b.stats["converged"]
    assert b.stats["pierced"] == [{"surface": "surface0", "patch": 0, "sections": 0, "open": 1}]
    (u,) = b.stats["unconverged"]
    assert u["elements"] > 0 and u["error"] > tol and not u["stopped_by_budget"]
    assert b.vertices.shape[0] < 20_000


# -- the command ---------------------------------------------------------------------------


def _write_json_scene(tmp_path):
    scene, rec = _small()
    occ = js.Scene(scene.lights, occluders=[np.asarray(p) for p in rec[0]] + [np.asarray(scene.occluders)[0]])
    js.save_scene(occ, tmp_path / "scene.json")
    return tmp_path / "scene.json"


def test_bake_command(tmp_path, capsys):
    path = _write_json_scene(tmp_path)
    out = tmp_path / "b.glb"
    assert main([NC, "bake", str(path), "-o", str(out), "--tol", "0.2", "--lights", "0"]) == 0
    assert out.exists() and not (tmp_path / "b.glb.chunks").exists()
    err = capsys.readouterr().err
    assert "vertices" in err and "%" not in err  # piped: no progress, a summary
    g = trimesh.load(out, force="mesh", process=False)
    assert "_IRRADIANCE_0" in g.vertex_attributes and "_IRRADIANCE_1" not in g.vertex_attributes
    assert main([NC, "bake", str(path), "-o", str(tmp_path / "b.ply"), "--tol", "0.2", "-q"]) == 0
    assert capsys.readouterr().err == ""
    with pytest.raises(SystemExit) as exc:
        main([NC, "bake", str(path), "-o", str(tmp_path / "c.glb"), "--workers", "0"])
    assert exc.value.code == 2
    for bad in (["--tol", "2"], ["--lights", "x"], ["--lights", "7"]):
        assert main([NC, "bake", str(path), "-o", str(tmp_path / "c.glb"), *bad, "-q"]) == 2, bad
        capsys.readouterr()
    assert main([NC, "bake", str(path), "-o", str(tmp_path / "c.obj"), "-q"]) == 2
    assert main([NC, "bake", str(path), "-o", str(path), "-q"]) == 2
    assert not (tmp_path / "c.glb").exists()
    assert "destroy the input" in capsys.readouterr().err


def test_discontinuity_segments_per_surface(baked):
    """`BakedScene.discontinuity_segments`: the planar patches' mesher lines, per surface; each
    runs along output edges of its surface; curved surfaces have none."""
    _, b = baked
    floor = b.discontinuity_segments(0)
    assert floor.shape[1:] == (2, 3) and floor.shape[0] > 4
    assert np.all(np.abs(floor[..., 2]) <= 1e-12) and np.all(np.abs(floor[..., :2]) <= 1 + 1e-12)
    np.testing.assert_array_equal(b.discontinuity_segments("upper"), np.zeros((0, 2, 3)))
    every = b.discontinuity_segments()
    assert every.shape[0] == sum(b.discontinuity_segments(i).shape[0] for i in range(len(b.surface_names)))
    tris = b.triangles[b.surface == 0]
    a = b.vertices[np.concatenate([tris[:, 0], tris[:, 1], tris[:, 2]])]
    c = b.vertices[np.concatenate([tris[:, 1], tris[:, 2], tris[:, 0]])]
    d = c - a
    for q in 0.5 * (floor[:, 0] + floor[:, 1]):
        s = np.clip(np.einsum("ek,ek->e", q - a, d) / np.einsum("ek,ek->e", d, d), 0.0, 1.0)
        assert np.min(np.linalg.norm(a + s[:, None] * d - q, axis=1)) <= 1e-9
    with pytest.raises(ValueError, match="no surface"):
        b.discontinuity_segments("nope")
