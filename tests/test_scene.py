"""Scene model: validation messages, JSON round trip, pytree behaviour."""

import json

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
