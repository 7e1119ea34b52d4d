# ruff: noqa: E501  (one table row per case reads better than wrapped lines)
"""Every public entry point rejects bad input with a `ValueError` that says what and where.

One parametrised case per kind of bad input and entry point. Cases marked `GAP` document
entry points that currently let the input through (or fail with a raw error from inside JAX /
NumPy); they are strict xfails, so fixing the gap makes them XPASS and fail: then drop the mark.
"""

import json
import os

import numpy as np
import pytest

import jaxshadow as js
from benchmarks.scenes import QUAD

NON_CONVEX = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.2, 0.2, 1.0], [0.0, 1.0, 1.0]])
NON_PLANAR = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.2], [0.0, 1.0, 1.0]])
COLLINEAR = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 0.0, 1.0]])
REPEATED = np.concatenate([QUAD, QUAD[:1]])
STAR = np.array(
    [[np.cos(a), np.sin(a), 1.0] for a in 4 * np.pi * np.arange(5) / 5]
)  # pentagram: turns one way, winds twice
P = np.zeros((2, 3))
N = np.tile([0.0, 0.0, 1.0], (2, 1))
A = np.array([-1.0, 0.0, 1.0])
B = np.array([1.0, 0.0, 1.0])


def _with(x, idx, value):
    y = np.array(x, dtype=np.float64)
    y[idx] = value
    return y


def gap(reason):
    return pytest.mark.xfail(strict=True, reason=f"GAP: {reason}")


# (callable, regex the message must match)
CASES = {
    # ---- js.form_factor ----------------------------------------------------------------
    "ff-points-nan": (lambda: js.form_factor(_with(P, (1, 2), np.nan), N, QUAD), r"form_factor: points\[1\] is not finite"),
    "ff-points-inf": (lambda: js.form_factor(_with(P, (0, 0), np.inf), N, QUAD), r"form_factor: points\[0\] is not finite"),
    "ff-normals-nan": (lambda: js.form_factor(P, _with(N, (1, 0), np.nan), QUAD), r"form_factor: normals\[1\] is not finite"),
    "ff-normals-zero": (lambda: js.form_factor(P, _with(N, (1, 2), 0.0), QUAD), r"form_factor: normals\[1\] is the zero vector"),
    "ff-points-shape": (lambda: js.form_factor(P[:, :2], N, QUAD), r"form_factor: points must have shape \(N, 3\), got \(2, 2\)"),
    "ff-points-1d": (lambda: js.form_factor(np.zeros(3), N[0], QUAD), r"form_factor: points must have shape \(N, 3\), got \(3,\)"),
    "ff-length-mismatch": (lambda: js.form_factor(P, N[:1], QUAD), r"form_factor: points and normals must have the same length, got 2 and 1"),
    "ff-points-int": (lambda: js.form_factor(P.astype(np.int32), N, QUAD), r"form_factor: points must be a floating-point array, got dtype int32"),
    "ff-normals-complex": (lambda: js.form_factor(P, N.astype(complex), QUAD), r"form_factor: normals must be a floating-point array"),
    "ff-vertices-k2": (lambda: js.form_factor(P, N, QUAD[:, :2]), r"form_factor: vertices must have shape \(k, 3\), got \(4, 2\)"),
    "ff-vertices-two": (lambda: js.form_factor(P, N, QUAD[:2]), r"form_factor: a polygon needs at least 3 vertices, got 2"),
    "ff-vertices-nan": (lambda: js.form_factor(P, N, _with(QUAD, (2, 1), np.nan)), r"form_factor: vertices: non-finite value .*nan.* at index \(.*2.*1.*\)"),
    "ff-non-convex": (lambda: js.form_factor(P, N, NON_CONVEX), r"form_factor: vertices: non-convex polygon: the turn at vertex 2"),
    "ff-star": (lambda: js.form_factor(P, N, STAR), r"form_factor: vertices: non-convex polygon: its boundary winds 2"),
    "ff-non-planar": (lambda: js.form_factor(P, N, NON_PLANAR), r"form_factor: vertices: non-planar polygon: vertex \d is"),
    "ff-collinear": (lambda: js.form_factor(P, N, COLLINEAR), r"form_factor: vertices: zero area"),
    "ff-repeated": (lambda: js.form_factor(P, N, REPEATED), r"form_factor: vertices: vertices 4 and 0 coincide"),
    # ---- js.irradiance -----------------------------------------------------------------
    "irr-not-scene": (lambda: js.irradiance([js.PolygonLight(QUAD)], P, N), r"irradiance: expected a jaxshadow.Scene, got list"),
    "irr-points-nan": (lambda: js.irradiance(js.Scene([js.PolygonLight(QUAD)]), _with(P, (1, 1), np.nan), N), r"irradiance: points\[1\] is not finite"),
    "irr-normals-inf": (lambda: js.irradiance(js.Scene([js.PolygonLight(QUAD)]), P, _with(N, (0, 2), -np.inf)), r"irradiance: normals\[0\] is not finite"),
    "irr-normals-zero": (lambda: js.irradiance(js.Scene([js.PolygonLight(QUAD)]), P, np.zeros((2, 3))), r"irradiance: normals\[0\] is the zero vector"),
    "irr-points-shape": (lambda: js.irradiance(js.Scene([js.PolygonLight(QUAD)]), np.zeros((2, 4)), N), r"irradiance: points must have shape \(N, 3\), got \(2, 4\)"),
    "irr-normals-shape": (lambda: js.irradiance(js.Scene([js.PolygonLight(QUAD)]), P, np.zeros((2, 3, 1))), r"irradiance: normals must have shape \(N, 3\)"),
    "irr-length-mismatch": (lambda: js.irradiance(js.Scene([js.PolygonLight(QUAD)]), P, np.tile(N, (2, 1))), r"irradiance: points and normals must have the same length, got 2 and 4"),
    "irr-points-int": (lambda: js.irradiance(js.Scene([js.PolygonLight(QUAD)]), P.astype(int), N), r"irradiance: points must be a floating-point array"),
    "irr-normals-bool": (lambda: js.irradiance(js.Scene([js.PolygonLight(QUAD)]), P, N.astype(bool)), r"irradiance: normals must be a floating-point array, got dtype bool"),
    # ---- js.linear_irradiance (no validation yet) ---------------------------------------
    "lin-points-nan": pytest.param(lambda: js.linear_irradiance(_with(P, (0, 1), np.nan), N, A, B), r"points\[0\] is not finite"),
    "lin-normals-shape": pytest.param(lambda: js.linear_irradiance(P, N[:, :2], A, B), r"normals must have shape \(N, 3\)"),
    "lin-normals-zero": pytest.param(lambda: js.linear_irradiance(P, np.zeros((2, 3)), A, B), r"normals\[0\] is the zero vector"),
    "lin-length-mismatch": pytest.param(lambda: js.linear_irradiance(P, N[:1], A, B), r"points and normals must have the same length"),
    "lin-points-int": pytest.param(lambda: js.linear_irradiance(P.astype(int), N, A, B), r"points must be a floating-point array"),
    "lin-start-shape": pytest.param(lambda: js.linear_irradiance(P, N, A[:2], B), r"start: expected shape \(3,\)"),
    "lin-start-nan": pytest.param(lambda: js.linear_irradiance(P, N, _with(A, 1, np.nan), B), r"start: non-finite"),
    "lin-zero-length": pytest.param(lambda: js.linear_irradiance(P, N, A, A), r"zero-length segment"),
    "lin-negative-m": pytest.param(lambda: js.linear_irradiance(P, N, A, B, -1), r"m must be an integer >= 0"),
    "lin-fractional-m": pytest.param(lambda: js.linear_irradiance(P, N, A, B, 1.5), r"m must be an integer >= 0"),
    # ---- light / material / scene constructors ------------------------------------------
    "poly-nan": (lambda: js.PolygonLight(_with(QUAD, (1, 2), np.nan)), r"PolygonLight: non-finite value .*nan.* at index \(.*1.*2.*\)"),
    "poly-shape": (lambda: js.PolygonLight(QUAD[:, :2]), r"PolygonLight: vertices must have shape \(k, 3\), got \(4, 2\)"),
    "poly-non-convex": (lambda: js.PolygonLight(NON_CONVEX), r"PolygonLight: non-convex polygon"),
    "poly-star": (lambda: js.PolygonLight(STAR), r"PolygonLight: non-convex polygon: its boundary winds"),
    "poly-non-planar": (lambda: js.PolygonLight(NON_PLANAR), r"PolygonLight: non-planar polygon: vertex \d"),
    "poly-collinear": (lambda: js.PolygonLight(COLLINEAR), r"PolygonLight: zero area"),
    "poly-repeated": (lambda: js.PolygonLight(REPEATED), r"PolygonLight: vertices 4 and 0 coincide"),
    "poly-two-vertices": (lambda: js.PolygonLight(QUAD[:2]), r"PolygonLight: a polygon needs at least 3 distinct vertices, got 2"),
    "poly-radiance-negative": (lambda: js.PolygonLight(QUAD, [1.0, -2.0, 1.0]), r"PolygonLight.radiance: must be >= 0, got .*-2.0.* in channel G"),
    "poly-radiance-inf": (lambda: js.PolygonLight(QUAD, [1.0, 1.0, np.inf]), r"PolygonLight.radiance: non-finite value"),
    "poly-radiance-shape": (lambda: js.PolygonLight(QUAD, [1.0, 2.0]), r"PolygonLight.radiance: expected a scalar or an RGB triple of shape \(3,\), got \(2,\)"),
    "lin-light-nan": (lambda: js.LinearLight(_with(A, 0, np.nan), B), r"LinearLight.start: non-finite value"),
    "lin-light-shape": (lambda: js.LinearLight(A, B[:2]), r"LinearLight.end: expected shape \(3,\), got \(2,\)"),
    "lin-light-zero-length": (lambda: js.LinearLight(A, A), r"LinearLight: zero-length segment"),
    "lin-light-power-negative": (lambda: js.LinearLight(A, B, -1.0), r"LinearLight.power: must be >= 0"),
    "lin-light-profile": (lambda: js.LinearLight(A, B, 1.0, "spot"), r"LinearLight.profile must be one of"),
    "lin-light-exponent-negative": (lambda: js.LinearLight(A, B, 1.0, "cosine", -1), r"LinearLight.exponent must be an integer >= 1"),
    "lin-light-exponent-fraction": (lambda: js.LinearLight(A, B, 1.0, "cosine", 1.5), r"LinearLight.exponent must be an integer >= 1"),
    "lin-light-exponent-nan": pytest.param(lambda: js.LinearLight(A, B, 1.0, "cosine", float("nan")), r"LinearLight.exponent"),
    "point-nan": (lambda: js.PointLight(_with(A, 2, np.inf)), r"PointLight.position: non-finite value"),
    "point-shape": (lambda: js.PointLight([0.0, 1.0]), r"PointLight.position: expected shape \(3,\), got \(2,\)"),
    "point-negative": (lambda: js.PointLight(A, -1.0), r"PointLight.intensity: must be >= 0"),
    "dir-zero": (lambda: js.DirectionalLight([0.0, 0.0, 0.0]), r"DirectionalLight.direction: a direction must be non-zero"),
    "dir-nan": (lambda: js.DirectionalLight([0.0, np.nan, -1.0]), r"DirectionalLight.direction: non-finite value"),
    "dir-negative": (lambda: js.DirectionalLight([0.0, 0.0, -1.0], [1.0, 1.0, -1.0]), r"DirectionalLight.irradiance: must be >= 0, got .* in channel B"),
    "mat-kd-negative": (lambda: js.Material(kd=-0.1), r"Material.kd: must be >= 0"),
    "mat-ks-inf": (lambda: js.Material(ks=[0.0, np.inf, 0.0]), r"Material.ks: non-finite value"),
    "mat-ka-shape": (lambda: js.Material(ka=[0.1, 0.2]), r"Material.ka: expected a scalar or an RGB triple"),
    "mat-exponent-negative": (lambda: js.Material(exponent=-1.0), r"Material.exponent must be >= 0, got -1.0"),
    "mat-exponent-nan": (lambda: js.Material(exponent=np.nan), r"Material.exponent: non-finite value"),
    "mat-exponent-shape": (lambda: js.Material(exponent=[1.0, 2.0]), r"Material.exponent must be a scalar, got shape \(2,\)"),
    "scene-not-a-light": (lambda: js.Scene([QUAD]), r"Scene.lights\[0\]: expected PolygonLight, LinearLight, PointLight or DirectionalLight"),
    "scene-occluder-non-planar": (lambda: js.Scene([], occluders=[QUAD, NON_PLANAR]), r"Scene.occluders\[1\]: non-planar polygon"),
    "scene-occluder-non-convex": (lambda: js.Scene([], occluders=[NON_CONVEX]), r"Scene.occluders\[0\]: non-convex polygon"),
    "scene-occluder-nan": (lambda: js.Scene([], occluders=[_with(QUAD, (0, 0), np.nan)]), r"Scene.occluders\[0\]: non-finite value"),
    "scene-occluder-shape": (lambda: js.Scene([], occluders=np.zeros((2, 3, 2))), r"Scene.occluders: expected an array \(m, k, 3\)"),
    "scene-ambient-negative": (lambda: js.Scene([], ambient=-1.0), r"Scene.ambient: must be >= 0"),
    "scene-ambient-nan": (lambda: js.Scene([], ambient=[np.nan, 0.0, 0.0]), r"Scene.ambient: non-finite value"),
}


@pytest.mark.parametrize("call, match", list(CASES.values()), ids=list(CASES))
def test_rejects_bad_input(call, match):
    with pytest.raises(ValueError, match=match):
        call()


# ---- js.load_scene on malformed JSON --------------------------------------------------

GOOD = {
    "format": "jaxshadow.scene",
    "version": 1,
    "lights": [{"type": "polygon", "vertices": QUAD.tolist(), "radiance": [1.0, 1.0, 1.0]}],
    "occluders": [],
    "ambient": [0.0, 0.0, 0.0],
}


def _light(**kw):
    return {**GOOD, "lights": [kw]}


JSON_CASES = {
    "truncated": ('{"format": "jaxshadow.scene", "vers', r"(?i)unterminated string|expecting"),
    "not-an-object": ("[1, 2]", r"scene: expected a JSON object"),
    "wrong-format": ({**GOOD, "format": "mitsuba"}, r"scene: 'format' must be 'jaxshadow.scene', got 'mitsuba'"),
    "wrong-version": ({**GOOD, "version": 3}, r"scene: unsupported schema version 3"),
    "unknown-field": ({**GOOD, "camera": {}}, r"scene: unknown field\(s\) \['camera'\]"),
    "light-without-type": ({**GOOD, "lights": [{"vertices": QUAD.tolist()}]}, r"scene.lights\[0\]: expected an object with a 'type' field"),
    "light-unknown-type": (_light(type="spot"), r"scene.lights\[0\]: unknown light type 'spot'"),
    "light-missing-field": (_light(type="polygon"), r"scene.lights\[0\]: missing field\(s\) \['vertices'\]"),
    "light-unknown-field": (_light(type="point", position=[0, 0, 1], colour=[1, 1, 1]), r"scene.lights\[0\]: unknown field\(s\) \['colour'\]"),
    "light-non-convex": (_light(type="polygon", vertices=NON_CONVEX.tolist()), r"scene.lights\[0\]: PolygonLight: non-convex polygon"),
    "light-negative-power": (_light(type="linear", start=[0, 0, 0], end=[1, 0, 0], power=-1), r"scene.lights\[0\]: LinearLight.power: must be >= 0"),
    "light-nan-position": ('{"format": "jaxshadow.scene", "version": 1, "lights": [{"type": "point", "position": [0, NaN, 1]}]}', r"scene.lights\[0\]: PointLight.position: non-finite value"),
    "occluder-degenerate": ({**GOOD, "occluders": [[[0, 0, 1], [1, 0, 1]]]}, r"Scene.occluders\[0\]: a polygon needs at least 3 distinct vertices"),
    "material-negative-exponent": ({**GOOD, "material": {"exponent": -2}}, r"material: Material.exponent must be >= 0"),
    "light-string-vertices": pytest.param(_light(type="polygon", vertices="abc"), r"scene.lights\[0\]"),
    "light-ragged-vertices": pytest.param(_light(type="polygon", vertices=[[0, 0, 1], [1, 0], [1, 1, 1]]), r"scene.lights\[0\]"),
    "lights-not-a-list": pytest.param({**GOOD, "lights": {"type": "point"}}, r"scene: 'lights' must be a list"),
    "ambient-string": pytest.param({**GOOD, "ambient": "red"}, r"ambient"),
    "exponent-string": pytest.param(_light(type="linear", start=[0, 0, 0], end=[1, 0, 0], profile="cosine", exponent="2"), r"exponent"),
}


@pytest.mark.parametrize("content, match", list(JSON_CASES.values()), ids=list(JSON_CASES))
def test_load_scene_rejects_malformed_json(tmp_path, content, match):
    path = tmp_path / "scene.json"
    path.write_text(content if isinstance(content, str) else json.dumps(content))
    with pytest.raises(ValueError, match=match):
        if "material" in (content if isinstance(content, dict) else {}):
            js.load_material(path)
        else:
            js.load_scene(path)


def test_good_json_loads(tmp_path):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(GOOD))
    scene = js.load_scene(path)
    assert len(scene.lights) == 1


def test_valid_integer_vertices_are_accepted_and_cast():
    # Integer vertices are a valid polygon (cast to the points' dtype); integer *points* are not.
    verts = np.array([[-1, -1, 1], [-1, 1, 1], [1, 1, 1], [1, -1, 1]])
    f = js.form_factor(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32), verts)
    assert f.dtype == np.float32 and 0.0 < float(f[0]) < 1.0


# ---- the command line: bad files are usage errors (exit 2 with the reason), not exit 1 --------


def _cli(argv, capsys):
    from jaxshadow.cli import main

    try:
        rc = main(["--no-compile-cache", *argv])
    except SystemExit as err:
        rc = err.code
    return rc, capsys.readouterr().err


def test_cli_deeply_nested_json_is_a_usage_error(tmp_path, capsys):
    deep = "[" * 200_000 + "]" * 200_000
    (tmp_path / "deep.json").write_text(deep)
    np.save(tmp_path / "pts.npy", np.array([[0.0, 0, 0, 0, 0, 1]]))
    with pytest.raises(ValueError, match="nested too deeply"):
        js.load_scene(tmp_path / "deep.json")
    rc, err = _cli(["irradiance", str(tmp_path / "deep.json"), str(tmp_path / "pts.npy"), "-o", str(tmp_path / "e.npy")], capsys)
    assert rc == 2 and "nested too deeply" in err and "internal error" not in err
    # nested within the JSON parser's reach but too deep for a scene entry
    d = js.scene_to_dict(js.Scene([js.PolygonLight(QUAD, 1.0)]))
    (tmp_path / "s.json").write_text(json.dumps(d))
    text = json.dumps({**d, "ambient": 0}).replace('"ambient": 0', '"ambient": ' + "[" * 5000 + "]" * 5000)
    (tmp_path / "a.json").write_text(text)
    rc, err = _cli(["irradiance", str(tmp_path / "a.json"), str(tmp_path / "pts.npy"), "-o", str(tmp_path / "e.npy")], capsys)
    assert rc == 2 and "internal error" not in err
    rc, err = _cli(["mesh", str(tmp_path / "s.json"), "-o", str(tmp_path / "m.ply"), "--receiver", str(tmp_path / "deep.json")], capsys)
    assert rc == 2 and "nested too deeply" in err
    (tmp_path / "r.json").write_text('[[0, 0, 0], [1, 0, "x"], [1, 1, 0]]')
    rc, err = _cli(["mesh", str(tmp_path / "s.json"), "-o", str(tmp_path / "m.ply"), "--receiver", str(tmp_path / "r.json")], capsys)
    assert rc == 2 and "--receiver" in err and "internal error" not in err
    assert sorted(os.listdir(tmp_path)) == ["a.json", "deep.json", "pts.npy", "r.json", "s.json"]


def test_render_refuses_a_film_too_large_before_allocating(tmp_path, capsys, monkeypatch):
    pytest.importorskip("mitsuba")
    from jaxshadow import mitsuba as jm
    from jaxshadow.cli import render as _render

    def forbidden(*a, **k):
        raise AssertionError("allocated the camera rays")

    monkeypatch.setattr(_render, "_camera_rays", forbidden)
    scene = jm.write_example_scene(tmp_path, resolution=100_000)
    rc, err = _cli(["render", scene, "-o", str(tmp_path / "a.png")], capsys)
    assert rc == 2 and "100000x100000 film" in err and "10,000,000,000 camera samples" in err
    with pytest.raises(ValueError, match="camera samples"):
        _render.render(scene)
    with pytest.raises(ValueError, match="supersample 3"):
        _render.check_film_size(2000, 2000, 3)
    assert _render.check_film_size(64, 48, 2) == 64 * 48 * 4
    assert not (tmp_path / "a.png").exists()
