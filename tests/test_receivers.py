"""Receiver meshes, one route one answer: the vertex-normal convention (area-weighted, whatever
built the mesh), welding on load with a count, and affine transforms that carry normals.

Expected values are worked out by hand from the construction (areas, normals, vertex counts,
signed volumes), not by the code under test."""

import importlib.util
import math

import numpy as np
import pytest

import jaxshadow as js

trimesh = pytest.importorskip("trimesh")

S2 = math.sqrt(2.0)
# Two triangles meeting at the origin at right angles: A in z = 0 (normal +z, area 2), B in
# x = 0 (normal +x, area 1); both have a 90-degree corner at the origin, so an angle-weighted or
# an unweighted mean would give (1, 0, 1)/sqrt(2) there, the area-weighted one (1, 0, 2)/sqrt(5).
CORNER_V = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0, 0, S2], [0, -S2, 0]], dtype=np.float64)
CORNER_F = np.array([[0, 1, 2], [0, 3, 4]])
CORNER_N0 = np.array([1.0, 0.0, 2.0]) / math.sqrt(5.0)


def _write_obj(path, v, f, normals=None):
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(v, float).tolist()]
    if normals is not None:
        lines += [f"vn {x!r} {y!r} {z!r}" for x, y, z in np.asarray(normals, float).tolist()]
        lines += ["f " + " ".join(f"{i + 1}//{i + 1}" for i in tri) for tri in f]
    else:
        lines += ["f " + " ".join(str(i + 1) for i in tri) for tri in f]
    path.write_text("\n".join(lines) + "\n")


def test_vertex_normals_are_area_weighted_by_every_route(tmp_path):
    direct = js.ReceiverMesh(CORNER_V, CORNER_F)
    np.testing.assert_allclose(direct.vertex_normals[0], CORNER_N0, atol=1e-15)
    np.testing.assert_allclose(direct.vertex_normals[1:3], [[0, 0, 1]] * 2, atol=1e-15)
    np.testing.assert_allclose(direct.vertex_normals[3:], [[1, 0, 0]] * 2, atol=1e-15)
    # The file's own normals (deliberately wrong here) are not used: one geometry, one answer.
    _write_obj(tmp_path / "with_vn.obj", CORNER_V, CORNER_F, normals=np.tile([0.0, 1.0, 0.0], (5, 1)))
    _write_obj(tmp_path / "plain.obj", CORNER_V, CORNER_F)
    js.write_mesh(tmp_path / "corner.ply", CORNER_V, CORNER_F)
    for name in ("with_vn.obj", "plain.obj", "corner.ply"):
        got = js.read_mesh(tmp_path / name)
        np.testing.assert_allclose(got.vertices, CORNER_V, atol=1e-15)
        np.testing.assert_allclose(got.vertex_normals, direct.vertex_normals, atol=1e-15, err_msg=name)
        p, n, _ = js.read_points(tmp_path / name)
        np.testing.assert_allclose(n[0], CORNER_N0, atol=1e-15)


@pytest.mark.mitsuba
@pytest.mark.skipif(importlib.util.find_spec("mitsuba") is None, reason="needs mitsuba")
def test_from_mitsuba_receivers_follow_the_same_convention(tmp_path):
    from jaxshadow.mitsuba import from_mitsuba

    m = trimesh.creation.icosphere(subdivisions=1)
    v = np.asarray(m.vertices, np.float32).astype(np.float64)
    f = np.asarray(m.faces)
    # Split along a seam (as a UV-mapped export does): the vertices of faces 0-9 duplicated.
    seam = np.unique(f[:10])
    dup = np.arange(len(v), len(v) + len(seam))
    remap = np.arange(len(v))
    remap[seam] = dup
    f2 = f.copy()
    f2[:10] = remap[f[:10]]
    v2 = np.concatenate([v, v[seam]])
    _write_obj(tmp_path / "seamed.obj", v2, f2)
    _, receivers, _ = from_mitsuba({"type": "scene", "ball": {"type": "obj", "filename": str(tmp_path / "seamed.obj")}})
    (r,) = receivers
    # Mitsuba keeps the used vertices only: the duplicates are the seam vertices that faces
    # beyond the first ten use too.
    assert r.n_welded == len(np.intersect1d(seam, f[10:])) > 0 and len(r.vertices) == len(v)
    # Mitsuba may reorder the buffers: compare as sets of (position, normal).
    ref = js.ReceiverMesh(v, f)
    key = lambda x: np.lexsort(x.T[::-1])  # noqa: E731
    np.testing.assert_allclose(r.vertices[key(r.vertices)], v[key(v)], atol=0)
    np.testing.assert_allclose(r.vertex_normals[key(r.vertices)], ref.vertex_normals[key(v)], atol=1e-12)
    assert r.occluder().closed


def test_weld_on_read_counts_and_closes_the_surface(tmp_path):
    box = trimesh.creation.box(extents=(1.0, 2.0, 0.5))
    js.write_mesh(tmp_path / "soup.stl", box.vertices, box.faces)  # STL: 36 corners, 8 distinct
    # The crease (45 degrees) keeps a cube's hard edges: each corner one vertex per face (24),
    # the copies within a face (its two triangles) merged; the occluder is welded by position.
    hard = js.read_mesh(tmp_path / "soup.stl")
    assert len(hard.vertices) == 24 and hard.n_welded == 12
    np.testing.assert_allclose(np.abs(hard.vertex_normals).max(axis=1), 1.0)  # each along an axis
    occ = hard.occluder()
    assert occ.closed and occ.convex and len(occ.polygons) == 6
    got = js.read_mesh(tmp_path / "soup.stl", crease=None)  # every copy merged
    assert len(got.vertices) == 8 and got.n_welded == 28
    raw = js.read_mesh(tmp_path / "soup.stl", weld=None)
    assert len(raw.vertices) == 36 and raw.n_welded == 0
    # The (+, +, +) corner's normal: the normalised sum of the cross products of its triangles.
    p, n = got.receivers("vertices")
    corner = np.flatnonzero(np.all(p > 0, axis=1))
    assert len(corner) == 1
    # Independent: sum over the corner's triangles of their cross products.
    c = int(corner[0])
    cross = np.zeros(3)
    for t in got.faces:
        if c in t:
            a, b, d = got.vertices[t]
            cross += np.cross(b - a, d - a)
    np.testing.assert_allclose(n[c], cross / np.linalg.norm(cross), atol=1e-15)


def test_weld_within_a_tolerance(tmp_path):
    v = CORNER_V.copy()
    f = CORNER_F.copy()
    # Triangle B on its own copy of the origin, 1e-9 away.
    v = np.concatenate([v, [[1e-9, 0.0, 0.0]]])
    f[1, 0] = 5
    r = js.ReceiverMesh(v, f)
    assert r.welded().n_welded == 0  # not exactly equal
    assert r.welded(1e-6).n_welded == 0  # A and B meet at 90 degrees: the crease keeps them apart
    w = r.welded(1e-6, crease=None)
    assert w.n_welded == 1 and len(w.vertices) == 5
    np.testing.assert_array_equal(w.vertices[0], [0, 0, 0])  # the first (lowest index) position kept
    np.testing.assert_allclose(w.vertex_normals[0], CORNER_N0, atol=1e-9)
    with pytest.raises(ValueError, match="collapses every face"):
        js.ReceiverMesh(CORNER_V, CORNER_F).welded(10.0, crease=None)
    with pytest.raises(ValueError, match="tolerance must be a finite number"):
        r.welded(-1.0)


def test_weld_keeps_given_normals_apart():
    # A hard edge: two faces sharing an edge with their own (given) normals stay split there.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    f = np.array([[0, 1, 2], [3, 5, 4]])
    n = np.array([[0, 0, 1], [0, 0, 1], [0, 0, 1], [1, 0, 0], [1, 0, 0], [1, 0, 0.0]])
    assert js.ReceiverMesh(v, f, n).welded().n_welded == 0
    # Without given normals the crease decides: the two faces meet at 90 degrees.
    assert js.ReceiverMesh(v, f).welded().n_welded == 0
    assert js.ReceiverMesh(v, f).welded(crease=None).n_welded == 2
    assert js.ReceiverMesh(v, f).welded(crease=91.0).n_welded == 2
    n2 = n.copy()
    n2[3:5] = n2[0]  # equal normals on the shared vertices: merged
    w = js.ReceiverMesh(v, f, n2).welded()
    assert w.n_welded == 2 and len(w.vertices) == 4


def _signed_volume(v, loops):
    return sum(np.dot(v[lp[0]], np.cross(v[lp[k]], v[lp[k + 1]])) for lp in loops for k in range(1, len(lp) - 1)) / 6


@pytest.mark.parametrize("kind", ["rigid", "scaled", "mirror"])
def test_transformed_moves_vertices_and_normals(kind):
    rng = np.random.default_rng(7)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.linalg.det(q))  # a rotation
    t = np.array([0.3, -2.0, 5.0])
    a = {"rigid": 2.5 * q, "scaled": q @ np.diag([1.0, 3.0, 0.2]), "mirror": q @ np.diag([1.0, 1.0, -1.0])}[kind]
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = a, t
    sphere = trimesh.creation.icosphere(subdivisions=1)
    r = js.ReceiverMesh(sphere.vertices, sphere.faces)
    moved = r.transformed(m)
    np.testing.assert_allclose(moved.vertices, sphere.vertices @ a.T + t, atol=1e-12)
    # Normals as normals: the inverse transpose, so each face normal stays perpendicular to its
    # moved edges and on the outside (the moved sphere's outward side).
    want = r.face_normals @ np.linalg.inv(a)
    want /= np.linalg.norm(want, axis=1)[:, None]
    np.testing.assert_allclose(moved.face_normals, want, atol=1e-12)
    centre = t
    assert np.all(np.einsum("ij,ij->i", moved.face_centres - centre, moved.face_normals) > 0)
    if kind == "rigid":  # similarity: the area-weighted vertex normals rotate with the mesh
        np.testing.assert_allclose(moved.vertex_normals, r.vertex_normals @ q.T, atol=1e-12)
    # Given normals are carried by A^-T (not recomputed).
    g = js.ReceiverMesh(sphere.vertices, sphere.faces, vertex_normals=np.tile([0.0, 0.0, 1.0], (len(sphere.vertices), 1)))
    gn = np.linalg.inv(a).T @ [0.0, 0.0, 1.0]
    np.testing.assert_allclose(g.transformed(m).vertex_normals, np.tile(gn / np.linalg.norm(gn), (len(sphere.vertices), 1)),
                               atol=1e-12)
    # The same map given as rotation / translation / scale, and the occluder: still a closed,
    # outward (positive volume) convex solid.
    if kind == "rigid":
        np.testing.assert_allclose(r.transformed(rotation=q, translation=t, scale=2.5).vertices, moved.vertices, atol=1e-12)
    occ = js.Mesh(sphere.vertices, sphere.faces).transformed(m)
    assert occ.closed and occ.convex
    assert _signed_volume(occ.vertices, occ.loops) == pytest.approx(abs(np.linalg.det(a)) * sphere.volume, rel=1e-9)


def test_transformed_refuses_bad_maps():
    r = js.ReceiverMesh(CORNER_V, CORNER_F)
    with pytest.raises(ValueError, match="singular"):
        r.transformed(np.diag([1.0, 1.0, 0.0]))
    with pytest.raises(ValueError, match="last row"):
        r.transformed(np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0.5, 1]]))
    with pytest.raises(ValueError, match="shape"):
        r.transformed(np.eye(2))
    with pytest.raises(ValueError, match="not both"):
        r.transformed(np.eye(3), translation=[1, 0, 0])


def test_welded_mesh_blocks_what_the_soup_blocks():
    # A triangle soup of a box and the welded box are the same point set: the same irradiance.
    box = trimesh.creation.box(extents=(0.6, 0.6, 0.6))
    box.apply_translation([0.0, 0.0, 1.0])
    soup_v = box.vertices[box.faces].reshape(-1, 3)
    soup = js.Mesh(soup_v, np.arange(len(soup_v)).reshape(-1, 3))
    welded = soup.welded()
    assert not soup.closed and welded.closed and welded.convex and welded.n_welded == 28
    light = js.PolygonLight([[-0.5, -0.5, 2], [-0.5, 0.5, 2], [0.5, 0.5, 2], [0.5, -0.5, 2]], radiance=3.0)
    xs = np.linspace(-0.8, 0.8, 7)
    p = np.array([[x, y, 0.0] for x in xs for y in xs])
    n = np.tile([0.0, 0.0, 1.0], (len(p), 1))
    e_soup = np.asarray(js.irradiance(js.Scene([light], occluders=[soup]), p, n))
    e_weld = np.asarray(js.irradiance(js.Scene([light], occluders=[welded]), p, n))
    np.testing.assert_allclose(e_weld, e_soup, rtol=1e-9, atol=1e-12)
    assert e_weld[len(p) // 2, 0] < 0.5 * e_weld.max()  # the box does shadow the centre


def test_mesh_weld_option_counts_and_closes():
    """`js.Mesh(v, f, weld=...)`: a box split at seams (each face its own four corners: 24
    vertices, 8 distinct) is open as given, closed and convex welded, 16 vertices merged away;
    the same mesh with `weld=0.0` as with `.welded()`; without duplicates nothing changes."""
    box = js.Mesh.box([0, 0, 0.5], [1, 1, 1.5])
    quads = np.asarray(box.loops)                        # 6 faces x 4 corners
    v = box.vertices[quads].reshape(-1, 3)               # 24 copies
    f = np.arange(24).reshape(6, 4)
    raw = js.Mesh(v, f)
    assert not raw.closed and raw.n_welded == 0 and len(raw.vertices) == 24
    got = js.Mesh(v, f, weld=0.0)
    assert got.closed and got.convex and got.n_welded == 16 and len(got.vertices) == 8
    assert "16 welded" in repr(got)
    # The first copy of each position kept, in order of first occurrence.
    _, first = np.unique(v, axis=0, return_index=True)
    np.testing.assert_array_equal(got.vertices, v[np.sort(first)])
    assert got.loops == raw.welded().loops and raw.welded().n_welded == 16
    # No duplicates: vertices and faces as given.
    same = js.Mesh(box.vertices, box.loops, weld=0.0)
    assert same.n_welded == 0 and np.array_equal(same.vertices, box.vertices) and same.loops == box.loops
    # Within a tolerance: one corner moved by 1e-9 m is merged only with tol > 1e-9.
    v2 = v.copy()
    v2[5] += 1e-9
    assert js.Mesh(v2, f, weld=0.0).n_welded == 15 and not js.Mesh(v2, f, weld=0.0).closed
    assert js.Mesh(v2, f, weld=1e-6).n_welded == 16 and js.Mesh(v2, f, weld=1e-6).closed
    # A tolerance that collapses a face drops it; one that collapses every face is an error.
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [2 + 1e-7, 0, 0], [2, 1e-7, 0]], float)  # B: tiny
    assert len(js.Mesh(tri, [[0, 1, 2], [3, 4, 5]], weld=1e-6).polygons) == 1
    with pytest.raises(ValueError, match="collapses every face"):
        js.Mesh(tri, [[0, 1, 2], [3, 4, 5]], weld=10.0)
    with pytest.raises(ValueError, match="tolerance must be a finite number"):
        js.Mesh(v, f, weld=-1.0)


def test_mesh_weld_option_blocks_the_same_light():
    """Welding changes the structure, never the point set: the same irradiance (1e-9)."""
    box = js.Mesh.box([-0.3, -0.3, 0.7], [0.3, 0.3, 1.3])
    v = box.vertices[np.asarray(box.loops)].reshape(-1, 3)
    f = np.arange(24).reshape(6, 4)
    light = js.PolygonLight([[-0.5, -0.5, 2], [-0.5, 0.5, 2], [0.5, 0.5, 2], [0.5, -0.5, 2]], radiance=3.0)
    xs = np.linspace(-0.8, 0.8, 7)
    p = np.array([[x, y, 0.0] for x in xs for y in xs])
    n = np.tile([0.0, 0.0, 1.0], (len(p), 1))
    e = [np.asarray(js.irradiance(js.Scene([light], occluders=[js.Mesh(v, f, weld=w)]), p, n)) for w in (None, 0.0)]
    np.testing.assert_allclose(e[1], e[0], rtol=1e-9, atol=1e-12)
    assert e[1][len(p) // 2, 0] < 0.5 * e[1].max()  # the box does shadow the centre
