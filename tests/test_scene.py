"""Scene model: validation messages, JSON round trip, pytree behaviour."""

import json
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxshadow as js

SQ = [[0.0, 0, 1], [0, 1, 1], [1, 1, 1], [1, 0, 1]]


@pytest.mark.parametrize(
    "verts,match",
    [
        ([[0, 0, 1], [0, 1, 1], [1, 1, 1.5], [1, 0, 1]], r"non-planar polygon: vertex \d is"),
        ([[0, 0, 0], [2, 0, 0], [1, 0.2, 0], [2, 2, 0], [0, 2, 0]], r"non-convex polygon: the turn at vertex"),
        ([[0, 0, 0], [1, 0, 0], [0, 0, 0]], r"at least 3 distinct vertices, got 2"),
        ([[0, 0, 0], [1, 0, 0], [1, 0, 0], [0, 1, 0]], r"vertices 1 and 2 coincide"),
        ([[0, 0, 0], [1, 0, 0], [2, 0, 0]], r"zero area"),
        ([[0, 0, 0], [1, np.nan, 0], [0, 1, 0]], r"non-finite value nan at index \(1, 1\)"),
        ([[0, 0, 0], [1, np.inf, 0], [0, 1, 0]], r"non-finite value inf"),
        ([[0, 0], [1, 0], [0, 1]], r"vertices must have shape \(k, 3\), got \(3, 2\)"),
        (
            [[np.cos(4 * np.pi * i / 5), np.sin(4 * np.pi * i / 5), 0] for i in range(5)],
            r"winds 2 times",
        ),
    ],
)
def test_polygon_light_validation(verts, match):
    with pytest.raises(ValueError, match="PolygonLight: .*" + match):
        js.PolygonLight(verts, 1.0)


def test_negative_radiance_names_the_channel():
    with pytest.raises(ValueError, match=r"PolygonLight.radiance: must be >= 0, got -1.0 in channel G"):
        js.PolygonLight(SQ, [1.0, -1.0, 0.0])


def test_light_field_validation():
    with pytest.raises(ValueError, match="LinearLight: zero-length segment"):
        js.LinearLight([0, 0, 1], [0, 0, 1], 1.0)
    with pytest.raises(ValueError, match=r"LinearLight.power: must be >= 0"):
        js.LinearLight([0, 0, 1], [0, 1, 1], -2.0)
    with pytest.raises(ValueError, match=r"LinearLight.exponent must be an integer >= 1"):
        js.LinearLight([0, 0, 1], [0, 1, 1], 1.0, profile="cosine", exponent=1.5)
    with pytest.raises(ValueError, match=r"LinearLight.profile must be one of"):
        js.LinearLight([0, 0, 1], [0, 1, 1], 1.0, profile="spot")
    with pytest.raises(ValueError, match=r"LinearLight.start: expected shape \(3,\), got \(2,\)"):
        js.LinearLight([0, 1], [0, 1, 1], 1.0)
    with pytest.raises(ValueError, match=r"PointLight.position: non-finite value nan"):
        js.PointLight([0, np.nan, 1], 1.0)
    with pytest.raises(ValueError, match=r"PointLight.intensity: must be >= 0"):
        js.PointLight([0, 0, 1], -1.0)
    with pytest.raises(ValueError, match=r"DirectionalLight.direction: a direction must be non-zero"):
        js.DirectionalLight([0, 0, 0], 1.0)
    with pytest.raises(ValueError, match=r"Material.exponent must be >= 0"):
        js.Material(exponent=-1.0)
    with pytest.raises(ValueError, match=r"Material.kd: must be >= 0"):
        js.Material(kd=[0.5, -0.1, 0.2])
    with pytest.raises(ValueError, match=r"Scene.occluders\[1\]: non-planar polygon"):
        js.Scene([], occluders=[SQ, [[0, 0, 0], [1, 0, 0], [1, 1, 1], [0, 1, 0]]])
    with pytest.raises(ValueError, match=r"Scene.lights\[0\]: expected PolygonLight"):
        js.Scene([SQ])
    with pytest.raises(ValueError, match=r"Scene.ambient: must be >= 0"):
        js.Scene([], ambient=-1.0)


def test_entry_point_input_validation():
    scene = js.Scene([js.PolygonLight(SQ, 1.0)])
    with pytest.raises(ValueError, match=r"irradiance: normals\[1\] is the zero vector"):
        js.irradiance(scene, np.zeros((2, 3)), np.array([[0, 0, 1.0], [0, 0, 0]]))
    with pytest.raises(ValueError, match=r"irradiance: points\[0\] is not finite"):
        js.irradiance(scene, np.array([[np.nan, 0, 0.0]]), np.array([[0, 0, 1.0]]))
    with pytest.raises(ValueError, match=r"irradiance: points must have shape \(N, 3\)"):
        js.irradiance(scene, np.zeros(3), np.array([[0, 0, 1.0]]))
    with pytest.raises(ValueError, match=r"irradiance: points and normals must have the same length"):
        js.irradiance(scene, np.zeros((2, 3)), np.array([[0, 0, 1.0]]))
    with pytest.raises(ValueError, match=r"irradiance: points must be a floating-point array"):
        js.irradiance(scene, np.zeros((1, 3), dtype=np.int32), np.array([[0, 0, 1.0]]))
    with pytest.raises(ValueError, match=r"irradiance: expected a jaxshadow.Scene"):
        js.irradiance([js.PolygonLight(SQ, 1.0)], np.zeros((1, 3)), np.array([[0, 0, 1.0]]))


def test_json_round_trip(tmp_path):
    scene = js.Scene(
        [
            js.PolygonLight(SQ, [1.0, 2.0, 3.0]),
            js.LinearLight([0, 0, 2], [1, 0, 2], 0.5, profile="cosine", exponent=2),
            js.PointLight([0, 0, 3], 4.0),
            js.DirectionalLight([0, 0, -1], 0.25),
        ],
        occluders=[
            [[0, 0, 0.5], [0.5, 0, 0.5], [0.5, 0.5, 0.5]],
            [[0, 0, 0.6], [0.5, 0, 0.6], [0.5, 0.5, 0.6], [0, 0.5, 0.6]],
        ],
        ambient=[0.1, 0.1, 0.2],
    )
    mat = js.Material(ka=0.1, kd=[0.5, 0.4, 0.3], ks=0.2, exponent=20.0)
    path = tmp_path / "scene.json"
    js.save_scene(scene, path, material=mat)
    d = json.loads(path.read_text())
    assert d["format"] == "jaxshadow.scene" and d["version"] == 1
    assert len(d["occluders"][0]) == 3  # padding dropped
    back = js.load_scene(path)
    for x, y in zip(jax.tree_util.tree_leaves(scene), jax.tree_util.tree_leaves(back), strict=False):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert back.lights[1].profile == "cosine" and back.lights[1].exponent == 2
    m2 = js.load_material(path)
    np.testing.assert_array_equal(np.asarray(m2.kd), [0.5, 0.4, 0.3])


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda d: d.update(version=7), r"unsupported schema version 7"),
        (lambda d: d.update(format="other"), r"'format' must be 'jaxshadow.scene'"),
        (lambda d: d["lights"][0].update(type="spot"), r"scene.lights\[0\]: unknown light type 'spot'"),
        (lambda d: d["lights"][0].pop("vertices"), r"scene.lights\[0\]: missing field\(s\) \['vertices'\]"),
        (
            lambda d: d["lights"][0]["vertices"][2].__setitem__(2, 5.0),
            r"scene.lights\[0\]: PolygonLight: non-planar polygon: vertex",
        ),
        (lambda d: d["lights"][0].update(colour=1), r"unknown field\(s\) \['colour'\]"),
    ],
)
def test_json_errors_name_the_entry(mutate, match):
    d = js.scene_to_dict(js.Scene([js.PolygonLight(SQ, 1.0)]))
    mutate(d)
    with pytest.raises(ValueError, match=match):
        js.scene_from_dict(d)


def test_scene_is_a_pytree_with_differentiable_leaves():
    scene = js.Scene([js.PolygonLight(SQ, 1.0)])
    p, n = jnp.array([[0.5, 0.5, 0.0]]), jnp.array([[0.0, 0.0, 1.0]])

    @eqx.filter_grad
    def g(s):
        return js.irradiance(s, p, n).sum()

    grads = g(scene)
    assert np.all(np.isfinite(np.asarray(grads.lights[0].vertices)))
    assert float(jnp.abs(grads.lights[0].radiance).sum()) > 0


# ---- meshes in a binary arrays file beside the scene JSON ---------------------------------


def _mesh_scene():
    trimesh = pytest.importorskip("trimesh")
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    # A pyramid: after merging, a square base and four triangles (faces of 3 and 4 vertices).
    pyramid = js.Mesh([[0, 0, 0.2], [1, 0, 0.2], [1, 1, 0.2], [0, 1, 0.2], [0.5, 0.5, 0.7]],
                      [[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    return js.Scene([js.PolygonLight(SQ, 2.0)], ambient=0.1, occluders=[
        js.Mesh(np.asarray(ball.vertices) + [0.5, 0.5, 0.5], np.asarray(ball.faces)),
        [[0, 0, 0.9], [0.2, 0, 0.9], [0.2, 0.2, 0.9]],
        pyramid,
    ])


def _topology(scene):
    t = scene.occluder_topology
    return [np.asarray(a) for a in (t.face_object, t.from_mesh, t.face_solid, t.face_closed, t.solid_faces)]


def test_meshes_are_saved_as_arrays_beside_the_json(tmp_path):
    scene = _mesh_scene()
    path = tmp_path / "room.json"
    js.save_scene(scene, path, material=js.Material(kd=0.4))
    assert sorted(os.listdir(tmp_path)) == ["room.json", "room.meshes.npz"]
    d = json.loads(path.read_text())
    assert d["version"] == 2 and d["arrays"]["file"] == "room.meshes.npz"
    assert d["occluders"][0] == {"mesh": {"arrays": "mesh0"}} and d["occluders"][2] == {"mesh": {"arrays": "mesh1"}}
    assert np.asarray(d["occluders"][1]).shape == (3, 3)  # a plain polygon stays inline
    with np.load(tmp_path / "room.meshes.npz") as z:
        assert z["mesh0_faces"].shape == (320, 3) and z["mesh0_vertices"].shape == (162, 3)
        assert z["mesh1_faces"].shape == (5, 4) and (z["mesh1_faces"] == -1).sum() == 4
    back = js.load_scene(path)
    np.testing.assert_array_equal(np.asarray(back.occluders), np.asarray(scene.occluders))
    # the same scene as the inline (version 1) form gives
    inline = js.scene_from_dict(js.scene_to_dict(scene))
    for a, b in zip(_topology(back), _topology(inline), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(np.asarray(js.load_material(path).kd), [0.4, 0.4, 0.4])


def test_inline_version_1_mesh_files_still_load(tmp_path):
    scene = _mesh_scene()
    d = js.scene_to_dict(scene)
    assert d["version"] == 1 and "vertices" in d["occluders"][0]["mesh"]
    (tmp_path / "old.json").write_text(json.dumps(d))
    np.testing.assert_array_equal(np.asarray(js.load_scene(tmp_path / "old.json").occluders),
                                  np.asarray(scene.occluders))


def test_scene_without_meshes_is_one_version_1_file(tmp_path):
    js.save_scene(js.Scene([js.PolygonLight(SQ, 1.0)], occluders=[[[0, 0, 0.5], [1, 0, 0.5], [0, 1, 0.5]]]),
                  tmp_path / "s.json")
    assert os.listdir(tmp_path) == ["s.json"] and json.loads((tmp_path / "s.json").read_text())["version"] == 1


def _rewrite_arrays(tmp_path, **arrays):
    """Replace the arrays file of tmp_path/s.json, with a matching hash in the JSON."""
    import hashlib
    import io

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    (tmp_path / "s.meshes.npz").write_bytes(buf.getvalue())
    d = json.loads((tmp_path / "s.json").read_text())
    d["arrays"]["sha256"] = hashlib.sha256(buf.getvalue()).hexdigest()
    (tmp_path / "s.json").write_text(json.dumps(d))


def test_missing_or_corrupt_arrays_file_is_a_clear_error(tmp_path):
    js.save_scene(_mesh_scene(), tmp_path / "s.json")
    npz = tmp_path / "s.meshes.npz"
    data = npz.read_bytes()
    npz.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"'s.meshes.npz' does not match the scene"):
        js.load_scene(tmp_path / "s.json")
    npz.unlink()
    with pytest.raises(ValueError, match=r"s.json: its mesh arrays file 's.meshes.npz' is missing"):
        js.load_scene(tmp_path / "s.json")
    npz.write_bytes(data)
    js.load_scene(tmp_path / "s.json")
    d = json.loads((tmp_path / "s.json").read_text())
    with pytest.raises(ValueError, match=r"stored in the scene's arrays file; read the scene with jaxshadow.load_scene"):
        js.scene_from_dict(d)
    (tmp_path / "t.json").write_text(json.dumps({**d, "arrays": {**d["arrays"], "file": "../s.meshes.npz"}}))
    with pytest.raises(ValueError, match=r"must be a file name in the scene's directory"):
        js.load_scene(tmp_path / "t.json")
    (tmp_path / "s.meshes.npz").write_bytes(b"not a zip file")
    d["arrays"]["sha256"] = __import__("hashlib").sha256(b"not a zip file").hexdigest()
    (tmp_path / "s.json").write_text(json.dumps(d))
    with pytest.raises(ValueError, match=r"is not a NumPy .npz file"):
        js.load_scene(tmp_path / "s.json")


def test_arrays_file_faces_must_be_integers(tmp_path):
    scene = _mesh_scene()
    js.save_scene(scene, tmp_path / "s.json")
    with np.load(tmp_path / "s.meshes.npz") as z:
        arrays = {k: z[k] for k in z.files}
    faces = arrays["mesh0_faces"].astype(np.float64)
    faces[0, 2] = 2.5
    _rewrite_arrays(tmp_path, **{**arrays, "mesh0_faces": faces})
    with pytest.raises(ValueError, match=r"scene.occluders\[0\]: mesh faces must be an \(F, K >= 3\) array of integer"):
        js.load_scene(tmp_path / "s.json")
    faces = arrays["mesh1_faces"].copy()
    faces[1, 1] = -1  # padding in the middle of a row
    _rewrite_arrays(tmp_path, **{**arrays, "mesh1_faces": faces})
    with pytest.raises(ValueError, match=r"scene.occluders\[2\]: mesh faces: a negative index other than"):
        js.load_scene(tmp_path / "s.json")
    _rewrite_arrays(tmp_path, **{k: v for k, v in arrays.items() if not k.startswith("mesh1")})
    with pytest.raises(ValueError, match=r"scene.occluders\[2\]: the arrays file has no mesh 'mesh1'"):
        js.load_scene(tmp_path / "s.json")


def test_inline_json_face_index_must_be_an_integer(tmp_path):
    d = js.scene_to_dict(_mesh_scene())
    d["occluders"][0]["mesh"]["faces"][0][1] = 2.5
    (tmp_path / "f.json").write_text(json.dumps(d))
    with pytest.raises(ValueError, match=r"scene.occluders\[0\]: mesh faces must be lists of integer vertex indices"):
        js.load_scene(tmp_path / "f.json")


def test_vectorised_mesh_entries_match_the_per_vertex_recovery():
    # scene_to_dict / save_scene recover each mesh's vertices and faces from the padded faces in
    # one vectorised pass; mesh_dicts does it vertex by vertex with a dict: the same entries.
    from jaxshadow._core.mesh import OccluderTopology, mesh_dicts

    trimesh = pytest.importorskip("trimesh")
    ball = trimesh.creation.icosphere(subdivisions=1)
    box = js.Mesh.box([-0.0, -1.0, 0.0], [1.0, 0.0, 2.0])  # quads, a -0.0 coordinate
    hexagon = np.array([[np.cos(a), np.sin(a), 3.0] for a in np.linspace(0, 2 * np.pi, 7)[:-1]])
    fan = js.Mesh(np.vstack([hexagon, [[0.0, 0.0, 3.0]]]), [[6, i, (i + 1) % 6] for i in range(6)])  # merges
    scene = js.Scene([js.PointLight([0, 0, 5.0], 1.0)],
                     occluders=[js.Mesh(ball.vertices, ball.faces), [[0, 0, 4.0], [1, 0, 4.0], [0, 1, 4.0]], box, fan])
    faces = np.asarray(scene.occluders, np.float64)
    want = mesh_dicts(faces, scene.occluder_topology or OccluderTopology.independent(len(faces)))
    got = js.scene_to_dict(scene)["occluders"]
    assert got == want
    assert [len(f) for f in got[2]["mesh"]["faces"]] == [4] * 6 and len(got[2]["mesh"]["vertices"]) == 8
    assert len(got[3]["mesh"]["vertices"]) == 6  # the fan merged into one hexagon: its centre unused
