"""glTF out: y-up, float irradiance attributes, a clean float32 triangulation (`write_gltf`), and
`jaxshadow mesh` on jaxshadow JSON and Mitsuba XML scenes."""

import importlib.util
import json

import numpy as np
import pytest

import jaxshadow as js
from jaxshadow.cli import main

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("pythoncdt")
pytest.importorskip("shapely")
from jaxshadow._io.meshio import write_gltf  # noqa: E402

NC = "--no-compile-cache"


def _grid(n=4):
    """An n x n grid of vertices on z = 0 in [0, 1]^2, triangles counter-clockwise from +z."""
    xs = np.linspace(0.0, 1.0, n)
    v = np.array([[x, y, 0.0] for y in xs for x in xs])
    f = []
    for j in range(n - 1):
        for i in range(n - 1):
            a, b, c, d = j * n + i, j * n + i + 1, (j + 1) * n + i + 1, (j + 1) * n + i
            f += [[a, b, c], [a, c, d]]
    return v, np.array(f)


def _load(path):
    scene = trimesh.load(path, process=False)
    (geom,) = scene.geometry.values()
    return geom


def _check_clean(m, up_normal=(0.0, 1.0, 0.0)):
    """No duplicate vertex, no zero-area or inverted triangle, a valid 2-D triangulation."""
    v, f = np.asarray(m.vertices, np.float64), np.asarray(m.faces)
    assert len(np.unique(v, axis=0)) == len(v)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert np.all(cross @ np.asarray(up_normal) > 0)  # every triangle faces up (+y): none inverted
    assert m.nondegenerate_faces().all()
    import matplotlib.tri as mtri

    tri = mtri.Triangulation(v[:, 0], v[:, 2], f)
    tri.get_trifinder()  # raises "Triangulation is invalid" for overlapping or degenerate triangles


def test_write_gltf_y_up_attributes_and_clean_triangulation(tmp_path):
    v, f = _grid()
    e = np.c_[v[:, 0], v[:, 1], v[:, 0] + v[:, 1]] * 3.0
    # Defects of the kind float32 and meshers leave: vertex 16 a hair (1e-9 m) from vertex 5,
    # vertex 17 an exact copy of vertex 10, a sliver of height 1e-9 on the edge 0-1, and a
    # copy of face 0 turned over.
    v = np.concatenate([v, v[5:6] + [1e-9, 0, 0], v[10:11], [[0.5 / 3, 1e-9, 0.0]]])
    e = np.concatenate([e, e[5:6], e[10:11], [[9.0, 9.0, 9.0]]])
    f = f.copy()
    i5, i10 = np.flatnonzero((f == 5).any(axis=1))[0], np.flatnonzero((f == 10).any(axis=1))[-1]
    f[i5][f[i5] == 5] = 16
    f[i10][f[i10] == 10] = 17
    f = np.concatenate([f, [[0, 1, 18]], f[:1, ::-1]])
    normals = np.tile([0.0, 0.0, 1.0], (len(v), 1))
    got = write_gltf(tmp_path / "g.glb", v, f, normals=normals, attributes={"irradiance": e}, up="z")
    assert got == {"vertices": 16, "faces": 18, "welded": 2, "dropped": 2}
    m = _load(tmp_path / "g.glb")
    _check_clean(m)
    # z-up -> y-up: (x, y, z) -> (x, z, -y); normals +z -> +y.
    w = np.asarray(m.vertices, np.float64)
    order = np.lexsort((w[:, 0], -w[:, 2]))
    np.testing.assert_allclose(w[order], np.c_[v[:16, 0], v[:16, 2], -v[:16, 1]], atol=1e-7)
    np.testing.assert_allclose(m.vertex_normals, np.tile([0.0, 1.0, 0.0], (16, 1)), atol=1e-7)
    irr = m.vertex_attributes["_IRRADIANCE"]
    assert irr.dtype == np.float32 and irr.shape == (16, 3)
    np.testing.assert_allclose(irr[order], e[:16], rtol=1e-7)
    # .gltf (embedded buffers) holds the same; a y-up scene is written as it is.
    write_gltf(tmp_path / "g.gltf", v[:16], _grid()[1], up="y")
    doc = json.loads((tmp_path / "g.gltf").read_text())
    assert doc["asset"]["version"] == "2.0"
    np.testing.assert_allclose(np.sort(np.asarray(_load(tmp_path / "g.gltf").vertices), axis=0), np.sort(v[:16], axis=0), atol=1e-7)


def test_write_gltf_refuses_bad_input(tmp_path):
    v, f = _grid()
    with pytest.raises(ValueError, match="writes .glb or .gltf"):
        write_gltf(tmp_path / "g.ply", v, f)
    with pytest.raises(ValueError, match="coordinate axis"):
        write_gltf(tmp_path / "g.glb", v, f, up="w")


def _scene_json(tmp_path):
    light = js.PolygonLight([[-0.3, -0.3, 1.5], [-0.3, 0.3, 1.5], [0.3, 0.3, 1.5], [0.3, -0.3, 1.5]], radiance=5.0)
    blocker = [[-0.1, -0.1, 0.7], [0.2, -0.1, 0.7], [0.2, 0.2, 0.7]]
    scene = js.Scene([light], occluders=[blocker])
    path = tmp_path / "scene.json"
    js.save_scene(scene, path)
    return path, scene


def test_mesh_command_writes_y_up_gltf_with_exact_float_irradiance(tmp_path):
    path, scene = _scene_json(tmp_path)
    recv = "-1,-1,0; 1,-1,0; 1,1,0; -1,1,0"
    out = tmp_path / "floor.glb"
    assert main([NC, "mesh", str(path), "-o", str(out), "--tol", "0.05", "--receiver", recv, "-q"]) == 0
    m = _load(out)
    _check_clean(m)
    w = np.asarray(m.vertices, np.float64)
    np.testing.assert_array_equal(w[:, 1], 0.0)  # the floor z = 0 is y = 0 in the file
    assert np.ptp(w[:, 0]) == pytest.approx(2.0) and np.ptp(w[:, 2]) == pytest.approx(2.0)
    irr = m.vertex_attributes["_IRRADIANCE"]
    assert irr.dtype == np.float32 and irr.shape == (len(w), 3)
    # Back to the scene's frame, (x, y, z) = (x', -z', y'): the exact irradiance there.
    p = np.c_[w[:, 0], -w[:, 2], w[:, 1]]
    want = np.asarray(js.irradiance(scene, p, np.tile([0.0, 0.0, 1.0], (len(p), 1))), np.float64)
    np.testing.assert_allclose(irr, want, rtol=0, atol=1e-5 * want.max())
    assert want.min() < 0.5 * want.max()  # the blocker's shadow is on it


@pytest.mark.mitsuba
@pytest.mark.skipif(importlib.util.find_spec("mitsuba") is None, reason="needs mitsuba")
def test_mesh_command_reads_a_mitsuba_scene(tmp_path):
    # A y-up scene (the camera's up is +y): a floor, a box floating over it, a ceiling light.
    (tmp_path / "box.xml").write_text("""<scene version="3.0.0">
  <sensor type="perspective">
    <transform name="to_world"><lookat origin="0, 1, 4" target="0, 0.5, 0" up="0, 1, 0"/></transform>
  </sensor>
  <shape type="rectangle" id="floor">
    <transform name="to_world"><rotate x="1" angle="-90"/></transform>
    <bsdf type="diffuse"/>
  </shape>
  <shape type="cube" id="box">
    <transform name="to_world"><scale value="0.25"/><translate x="0.1" y="0.8" z="0"/></transform>
    <bsdf type="diffuse"/>
  </shape>
  <shape type="rectangle" id="light">
    <transform name="to_world"><scale value="0.3"/><rotate x="1" angle="90"/><translate y="1.9"/></transform>
    <emitter type="area"><rgb name="radiance" value="10, 10, 10"/></emitter>
  </shape>
</scene>
""")
    out = tmp_path / "floor.glb"
    assert main([NC, "mesh", str(tmp_path / "box.xml"), "-o", str(out), "--tol", "0.05", "-q"]) == 0
    m = _load(out)
    _check_clean(m)
    w = np.asarray(m.vertices, np.float64)
    # The default receiver is the floor (largest face facing the light): y = 0, 2 x 2 m.
    np.testing.assert_allclose(w[:, 1], 0.0, atol=1e-6)
    assert np.ptp(w[:, 0]) == pytest.approx(2.0) and np.ptp(w[:, 2]) == pytest.approx(2.0)
    scene, _, _ = js.mitsuba.from_mitsuba(str(tmp_path / "box.xml"))
    want = np.asarray(js.irradiance(scene, w, np.tile([0.0, 1.0, 0.0], (len(w), 1))), np.float64)
    irr = m.vertex_attributes["_IRRADIANCE"]
    np.testing.assert_allclose(irr, want, rtol=0, atol=1e-4 * want.max())
    assert want.max() > 0 and want.min() < 0.5 * want.max()  # lit, with the box's shadow


def test_irradiance_command_welds_mesh_receivers(tmp_path, capsys):
    path, scene = _scene_json(tmp_path)
    box = trimesh.creation.box(extents=(0.4, 0.4, 0.2))
    js.write_mesh(tmp_path / "soup.stl", box.vertices, box.faces)  # 36 corners, 8 distinct
    out = tmp_path / "e.ply"
    assert main([NC, "irradiance", str(path), str(tmp_path / "soup.stl"), "-o", str(out), "--float64"]) == 0
    # each corner keeps one vertex per face (the crease), the face's own copies are merged
    assert "12 duplicate vertices welded" in capsys.readouterr().err
    back = trimesh.load(out, process=False)
    assert len(back.vertices) == 24
    with pytest.raises(SystemExit) as exit_:
        main([NC, "irradiance", str(path), str(tmp_path / "soup.stl"), "-o", str(out), "--weld=-1"])
    assert exit_.value.code == 2 and "--weld: must be a finite number >= 0" in capsys.readouterr().err
