"""Meshes in and out (`jaxshadow._io.meshio` through trimesh), PLY value properties, the point
tables' API as the mesh writers use it, and per-receiver materials (`Material` fields of shape
(N, 3)); the CSV reader and writer themselves are in `test_tables.py`."""

import os

import numpy as np
import pytest

import jaxshadow as js

trimesh = pytest.importorskip("trimesh")
from jaxshadow._io.meshio import read_ply_values, tonemap  # noqa: E402
from jaxshadow._io.tables import read_csv  # noqa: E402


def _box():
    m = trimesh.creation.box(extents=(1.0, 2.0, 0.5))
    m.apply_translation([0.5, 1.0, 0.25])
    return m


@pytest.mark.parametrize("ext", [".ply", ".obj", ".glb", ".stl", ".off"])
def test_read_mesh_formats(tmp_path, ext):
    m = _box()
    path = tmp_path / f"box{ext}"
    js.write_mesh(path, m.vertices, m.faces)
    got = js.read_mesh(path)
    assert got.name == f"box{ext}" and len(got.faces) == 12
    # Same surface whatever the format does to the vertex order (STL stores triangle soups).
    np.testing.assert_allclose(np.sort(got.vertices[got.faces].reshape(-1, 3), axis=0),
                               np.sort(m.vertices[m.faces].reshape(-1, 3), axis=0), atol=1e-6)
    assert got.face_areas.sum() == pytest.approx(m.area, rel=1e-6)
    occ = got.occluder()
    if ext != ".stl":  # STL stores a triangle soup: no shared vertices, so no merging
        assert occ.closed and occ.convex and len(occ.polygons) == 6


def test_receiver_mesh_geometry_and_sampling():
    v = np.array([[0.0, 0, 0], [2, 0, 0], [0, 1, 0], [0, 0, 3]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    r = js.ReceiverMesh(v, f, name="two")
    np.testing.assert_allclose(r.face_areas, [1.0, 1.5])
    np.testing.assert_allclose(r.face_normals, [[0, 0, 1], [1, 0, 0]])
    np.testing.assert_allclose(r.face_centres, [[2 / 3, 1 / 3, 0], [0, 1 / 3, 1]])
    p, n = r.receivers("vertices")
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)
    np.testing.assert_allclose(n[1], [0, 0, 1]) and np.testing.assert_allclose(n[3], [1, 0, 0])
    p, n = r.sample(20_000, seed=3)
    on_xy = np.abs(p[:, 2]) < 1e-12
    assert np.all(on_xy | (np.abs(p[:, 0]) < 1e-12))
    frac = on_xy.mean()  # area fractions 1 : 1.5
    assert abs(frac - 0.4) < 4 * np.sqrt(0.4 * 0.6 / 20_000)
    assert np.all(p[on_xy, 0] / 2 + p[on_xy, 1] <= 1 + 1e-12) and np.all(p[on_xy] >= -1e-12)
    np.testing.assert_allclose(n[on_xy], np.tile([0, 0, 1.0], (on_xy.sum(), 1)))


@pytest.mark.parametrize(
    "vertices, faces, msg",
    [
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]], "out of range"),
        ([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], "zero area"),
        ([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]], [[0, 1, 2]], "finite"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0.0, 1.0, 2.0]], "integer"),
    ],
)
def test_receiver_mesh_rejects_bad_input(vertices, faces, msg):
    with pytest.raises(ValueError, match=msg):
        js.ReceiverMesh(vertices, np.asarray(faces))


def test_unused_vertices_have_no_normal():
    r = js.ReceiverMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]], np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match="1 vertices belong to no face"):
        r.receivers("vertices")
    assert r.receivers("faces")[0].shape == (1, 3)


def test_read_mesh_errors(tmp_path):
    with pytest.raises(ValueError, match="not a mesh file"):
        js.read_mesh(tmp_path / "a.txt")
    with pytest.raises(FileNotFoundError):
        js.read_mesh(tmp_path / "a.obj")
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(ValueError, match="bad.ply"):
        js.read_mesh(tmp_path / "bad.ply")


def test_write_ply_values_and_colours(tmp_path):
    m = _box()
    r = js.ReceiverMesh(m.vertices, m.faces)
    vals = np.random.default_rng(0).uniform(0, 3, (len(m.vertices), 3))
    js.write_ply(tmp_path / "v.ply", r, vals, name="irradiance")
    np.testing.assert_array_equal(read_ply_values(tmp_path / "v.ply", "irradiance"), vals)
    back = trimesh.load(tmp_path / "v.ply", process=False)
    np.testing.assert_array_equal(back.visual.vertex_colors[:, :3], tonemap(vals))
    fvals = np.arange(36.0).reshape(12, 3)
    js.write_ply(tmp_path / "f.ply", r, fvals, at="faces")
    np.testing.assert_array_equal(read_ply_values(tmp_path / "f.ply", at="faces"), fvals)
    with pytest.raises(ValueError, match=r"values must have shape \(12, 3\)"):
        js.write_ply(tmp_path / "g.ply", r, vals, at="faces")


def test_tonemap():
    t = tonemap(np.array([[0.0, 0.5, 1.0], [2.0, 0.0031308, 1e9]]), exposure=1.0)
    assert t.dtype == np.uint8
    np.testing.assert_array_equal(t, [[0, 188, 255], [255, 10, 255]])


def test_point_tables(tmp_path):
    p = np.random.default_rng(1).normal(size=(5, 3))
    n = np.tile([0.0, 0.0, 1.0], (5, 1))
    vals = np.arange(15.0).reshape(5, 3)
    for ext in (".npy", ".npz", ".csv"):
        js.write_values(tmp_path / f"v{ext}", vals, points=p, normals=n)
    np.testing.assert_array_equal(np.load(tmp_path / "v.npy"), vals)
    with np.load(tmp_path / "v.npz") as z:
        np.testing.assert_array_equal(z["values"], vals)
        np.savez(tmp_path / "pn.npz", points=z["points"], normals=z["normals"])
    np.testing.assert_array_equal(read_csv(tmp_path / "v.csv", ("r", "g", "b")), vals)
    got_p, got_n, mesh = js.read_points(tmp_path / "v.csv")  # the output CSV is a points CSV
    assert mesh is None
    np.testing.assert_array_equal(got_p, p) and np.testing.assert_array_equal(got_n, n)
    np.testing.assert_array_equal(js.read_points(tmp_path / "pn.npz")[0], p)
    np.save(tmp_path / "pn.npy", np.c_[p, n])
    np.testing.assert_array_equal(js.read_points(tmp_path / "pn.npy")[1], n)
    np.savez(tmp_path / "bad.npz", points=p)
    with pytest.raises(ValueError, match=r"missing array\(s\) \['normals'\]"):
        js.read_points(tmp_path / "bad.npz")
    (tmp_path / "nan.csv").write_text("px,py,pz,nx,ny,nz\n0,0,nan,0,0,1\n")
    with pytest.raises(ValueError, match="finite"):
        js.read_points(tmp_path / "nan.csv")
    (tmp_path / "short.csv").write_text("px,py,pz,nx,ny,nz\n0,0,0,0,0\n")
    with pytest.raises(ValueError, match="row 1 has 5 fields"):
        js.read_points(tmp_path / "short.csv")
    with pytest.raises(ValueError, match="unknown output format '.txt'"):
        js.write_values(tmp_path / "v.txt", vals)
    with pytest.raises(ValueError, match="needs receivers read from a mesh"):
        js.write_values(tmp_path / "v.ply", vals)


def test_failing_writer_keeps_the_old_file(tmp_path, monkeypatch):
    out = tmp_path / "v.npy"
    out.write_bytes(b"old")

    def broken(fh, arr):
        fh.write(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(np, "save", broken)
    with pytest.raises(OSError, match="disk full"):
        js.write_values(out, np.zeros((2, 3)))
    assert out.read_bytes() == b"old" and os.listdir(tmp_path) == ["v.npy"]


# --------------------------------------------------------------------------------------
# Per-receiver materials (issue 20 item 5)
# --------------------------------------------------------------------------------------


def test_per_receiver_material():
    kd = np.array([[0.1, 0.2, 0.3], [0.5, 0.5, 0.5], [0.9, 0.0, 0.2]])
    m = js.Material(ka=0.1, kd=kd, ks=0.2, exponent=10.0)
    assert m.receivers == 3 and js.Material().receivers is None
    scene = js.Scene([js.PointLight([0.5, 0.5, 2.0], 3.0)], ambient=0.2)
    p = np.array([[0.5, 0.5, 0.0], [0.2, 0.7, 0.3], [1.5, 0.5, 0.0]])
    n = np.tile([0.0, 0.0, 1.0], (3, 1))
    eye = np.array([0.3, -2.0, 1.0])
    e = np.asarray(js.irradiance(scene, p, n))
    s = np.asarray(js.specular(scene, p, n, eye, 10.0))
    got = np.asarray(m.radiance(scene.ambient, e, s))
    for i in range(3):  # row i is the constant material kd[i] at receiver i
        mi = js.Material(ka=0.1, kd=kd[i], ks=0.2, exponent=10.0)
        ref = np.asarray(js.shade(scene, mi, p, n, eye))
        np.testing.assert_allclose(got[i], ref[i], rtol=1e-12)


@pytest.mark.parametrize(
    "kw, msg",
    [
        ({"kd": np.full((3, 3), -0.1)}, r"Material.kd\[0\]: must be >= 0"),
        ({"kd": np.zeros((3, 3)), "ks": np.zeros((4, 3))}, "different numbers of rows"),
        ({"kd": np.zeros((3, 2))}, r"expected a scalar, \(3,\) or \(N, 3\)"),
        ({"ka": np.full((2, 3), np.inf)}, "Material.ka"),
    ],
)
def test_per_receiver_material_rejects_bad_input(kw, msg):
    with pytest.raises(ValueError, match=msg):
        js.Material(**kw)


def test_shade_with_per_receiver_material():
    scene = js.Scene([js.PointLight([0, 0, 2], 1.0)])
    p = np.zeros((2, 3))
    n = np.tile([0.0, 0.0, 1.0], (2, 1))
    m = js.Material(kd=np.array([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]]))
    got = np.asarray(js.shade(scene, m, p, n, [0, 0, 1.0]))
    np.testing.assert_allclose(got, np.asarray(m.radiance(scene.ambient, js.irradiance(scene, p, n))), rtol=1e-12)


def _ply_properties(path):
    """The vertex / face property names in a PLY header, read as text."""
    head = path.read_bytes().split(b"end_header")[0].decode("ascii")
    return [line.split()[-1] for line in head.splitlines() if line.startswith("property")]


def test_one_ply_property_naming_for_irradiance(tmp_path):
    # write_ply's default, the `irradiance` command and the illumination meshes: irradiance_r/g/b.
    from types import SimpleNamespace

    from jaxshadow._illumination.io import save_mesh

    m = _box()
    r = js.ReceiverMesh(m.vertices, m.faces)
    vals = np.random.default_rng(0).uniform(0, 3, (len(m.vertices), 3))
    js.write_ply(tmp_path / "api.ply", r, vals)
    save_mesh(SimpleNamespace(vertices=np.asarray(m.vertices), triangles=np.asarray(m.faces), irradiance=vals, scale=3.0),
              tmp_path / "mesh.ply")
    js.write_values(tmp_path / "values.ply", vals, mesh=r)
    for name in ("api.ply", "mesh.ply", "values.ply"):
        props = _ply_properties(tmp_path / name)
        assert {"irradiance_r", "irradiance_g", "irradiance_b"} <= set(props), (name, props)
        assert not any(p.startswith("value_") for p in props), (name, props)
    back = trimesh.load(tmp_path / "api.ply", process=False).metadata["_ply_raw"]["vertex"]["data"]
    np.testing.assert_array_equal(np.stack([back[f"irradiance_{c}"] for c in "rgb"], axis=1), vals)
    js.write_ply(tmp_path / "rad.ply", r, vals, name="radiance")
    assert "radiance_r" in _ply_properties(tmp_path / "rad.ply")
    with pytest.raises(ValueError, match="name must be a PLY property name"):
        js.write_ply(tmp_path / "bad.ply", r, vals, name="my value")


def test_csv_values_round_trip_exactly_in_their_own_precision(tmp_path):
    # float64 columns come back bit for bit as float64, float32 columns bit for bit as float32
    # (parsed by NumPy's own reader, not by the code under test), across several write blocks.
    from jaxshadow._io import tables as _tables

    rng = np.random.default_rng(3)
    n = 2 * _tables.CSV_BLOCK_ROWS + 17
    p64 = rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-12, 12, (n, 1))
    n64 = rng.normal(size=(n, 3))
    v32 = (rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-30, 30, (n, 1))).astype(np.float32)
    v32[:3] = [[0.1, 1 / 3, np.float32(np.pi)], [np.finfo(np.float32).max, np.finfo(np.float32).tiny, 0.0],
               [-0.0, 16777217.0, 1e-45]]
    js.write_values(tmp_path / "v.csv", v32, points=p64, normals=n64)
    raw = np.loadtxt(tmp_path / "v.csv", delimiter=",", skiprows=1)
    assert raw.shape == (n, 9)
    np.testing.assert_array_equal(raw[:, :3], p64)
    np.testing.assert_array_equal(raw[:, 3:6], n64)
    np.testing.assert_array_equal(raw[:, 6:].astype(np.float32), v32)
    assert (tmp_path / "v.csv").read_text().splitlines()[0] == "px,py,pz,nx,ny,nz,r,g,b"
    # float64 values are written as Python's shortest repr (what csv.writer of repr(x) wrote).
    js.write_values(tmp_path / "w.csv", p64[:4])
    assert (tmp_path / "w.csv").read_text().splitlines()[1:] == [",".join(repr(float(x)) for x in r) for r in p64[:4]]


def test_ply_irradiance_under_the_old_property_names_is_still_read(tmp_path):
    m = _box()
    r = js.ReceiverMesh(m.vertices, m.faces)
    vals = np.random.default_rng(4).uniform(0, 3, (len(m.vertices), 3))
    js.write_ply(tmp_path / "old.ply", r, vals, name="value")  # the API's former naming
    assert "value_r" in _ply_properties(tmp_path / "old.ply")
    np.testing.assert_array_equal(read_ply_values(tmp_path / "old.ply"), vals)
    with pytest.raises(ValueError, match="no vertices properties radiance_r/g/b"):
        read_ply_values(tmp_path / "old.ply", name="radiance")


# --------------------------------------------------------------------------------------
# Receiver tables (CSV) at array speed
# --------------------------------------------------------------------------------------
