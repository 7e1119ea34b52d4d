"""Issue 25: one regression test per row of the adversarial probe's table.

Every expected value comes from code that shares nothing with the kernel under test: float64
evaluations of the *same rounded inputs* through the float64 kernels (themselves checked
against mpmath in `test_stability.py`), the mpmath references of `test_stability.py`, the
shapely reference of `test_clip.py`, or closed forms. Row 4 (`--chunk`) belongs to the CLI
tests (`test_cli.py`).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from test_clip import reference_ff
from test_stability import mp_form_factor, mp_linear

import inverse
import jaxshadow as js
from benchmarks.scenes import square_light
from jaxshadow._kernels.linear import MAX_COSINE_EXPONENT, linear_irradiance_kernel
from jaxshadow._kernels.polygon import form_factor_kernel
from jaxshadow._kernels.specular import MAX_DEGREE

F32 = np.float32
UP = np.array([[0.0, 0.0, 1.0]])
# The light: a unit square at z = 2 emitting downwards, receiver under one corner.
Q = square_light(0.0, 1.0, 0.0, 1.0, 2.0)
P = np.array([[0.5, 0.5, 0.0]])


def _rel(got, ref):
    return abs(float(got) - float(ref)) / abs(float(ref))


# ---- row 1 -------------------------------------------------------------------------------


def test_row1_float32_light_far_from_the_origin():
    # 96 offsets in 6e4 .. 3e5, all exact in float32 (integers), so the float64 value of the
    # same inputs is the reference: float32 must be within 1e-5 of it (56 of 96 gave F = 0).
    offsets = np.unique(np.round(np.linspace(6e4, 3e5, 96)))
    assert all(np.all((Q + o).astype(F32) == Q + o) for o in offsets)
    ref = float(js.form_factor(P, UP, Q)[0])
    assert ref == pytest.approx(0.0734776, abs=1e-6)
    kern = jax.jit(jax.vmap(form_factor_kernel))
    pts, verts = (np.stack([x + o for o in offsets]).astype(F32) for x in (P[0], Q))
    f = np.asarray(kern(pts, np.repeat(UP.astype(F32), len(offsets), axis=0), verts))
    assert np.max(np.abs(f - ref)) <= 1e-5 * ref
    # ... and through the public entry point (its own lit-side test and normalisation).
    o = offsets[len(offsets) // 2]
    assert _rel(js.form_factor((P + o).astype(F32), UP.astype(F32), (Q + o).astype(F32))[0], ref) <= 1e-5


@pytest.mark.slow  # two compilations of the specular kernel (~15 s)
def test_row1_float32_specular_far_from_the_origin():
    # The Phong-lobe kernel had the same absolute-coordinate Newell normal.
    o = 1e5
    sc = [js.Scene([js.PolygonLight((Q + o).astype(dt), 1.0)]) for dt in (F32, np.float64)]
    s32, s64 = (
        js.specular(s, (P + o).astype(dt), UP.astype(dt), (np.array([0.25, 0.5, 1.0]) + o).astype(dt), 10.0)
        for s, dt in zip(sc, (F32, np.float64), strict=True)
    )
    assert float(s64[0, 0]) > 0.01
    assert _rel(s32[0, 0], s64[0, 0]) <= 1e-4


# ---- row 2 -------------------------------------------------------------------------------


@pytest.mark.parametrize("dt, scales", [(np.float64, (1e-160, 1e160, 1e-300, 1e300)), (F32, (1e-19, 1e19, 1e-37, 1e38))])
def test_row2_non_unit_normals_of_any_length(dt, scales):
    ref = float(js.form_factor(P, UP, Q)[0])
    for s in scales:
        n = np.array([[0.0, 0.0, s]], dt)
        assert n[0, 2] > 0
        f = js.form_factor(P.astype(dt), n, Q.astype(dt))
        assert _rel(f[0], ref) <= (1e-14 if dt == np.float64 else 1e-6), s
        e = js.irradiance(js.Scene([js.DirectionalLight(np.array([0.0, 0.0, -s], dt), 2.0)]), P.astype(dt), n)
        assert np.allclose(np.asarray(e), 2.0, rtol=1e-6)
        t = inverse.PaintedTargets(P.astype(dt), n, np.ones((1, 3), dt), np.array([0.0, 0.0, 1.0], dt))
        assert np.allclose(np.asarray(t.normals), [[0.0, 0.0, 1.0]])


# ---- row 3 (the shadow engine's: a failing test for its owner) ---------------------------

ROW3_LIGHT = Q - [0.0, 0.0, 2.0]
ROW3_OCC = square_light(0.4375, 0.5625, 0.4375, 0.5625, -5e-7)
ROW3_P = np.array([[0.5, 0.5, -1e-6]])


def test_row3_float64_soft_shadow_near_the_light_plane():
    ref = reference_ff(ROW3_P[0], UP[0], ROW3_LIGHT, [ROW3_OCC])
    assert 1e-11 < ref < 1e-10
    sc = js.Scene([js.PolygonLight(ROW3_LIGHT, 1.0 / np.pi)], occluders=[ROW3_OCC])
    assert float(js.irradiance(sc, ROW3_P, UP)[0, 0]) == pytest.approx(ref, rel=1e-5)


def test_row3_float32_soft_shadow_near_the_light_plane():
    # In float32 the occluder's coordinates are float32 values and it lies 5e-7 from the receiver,
    # within the on-surface distance 2^-18 S (S = 0.5625 here: 2.1e-6): the receiver lies on it
    # (`js.irradiance`'s documented rule) and it blocks nothing. Ten times farther (5e-6) it is
    # resolved in float32 as the exact reference says.
    unocc = float(js.form_factor(ROW3_P, UP, ROW3_LIGHT)[0])
    sc = js.Scene([js.PolygonLight(ROW3_LIGHT.astype(F32), 1.0 / np.pi)], occluders=[ROW3_OCC.astype(F32)])
    e = float(js.irradiance(sc, ROW3_P.astype(F32), UP.astype(F32))[0, 0])
    assert abs(e - unocc) <= 1e-5 * unocc
    p = ROW3_P - [0.0, 0.0, 5e-6]
    ref = reference_ff(p[0].astype(F32), UP[0], ROW3_LIGHT.astype(F32), [ROW3_OCC.astype(F32)])
    e = float(js.irradiance(sc, p.astype(F32), UP.astype(F32))[0, 0])
    assert abs(e - ref) <= 1e-5 * unocc


def test_float32_occluder_1e9_above_the_receiver_through_the_public_api():
    # The second float32 case of the stability suite, through js.irradiance (host engine):
    # an occluder 1e-9 above the receiver, covering its whole view of the light.
    em = square_light(-0.5, 0.5, -0.5, 0.5, 1.0)
    cover = square_light(0.2, 0.4, -0.3, -0.1, 1e-9)
    p = np.array([[0.3, -0.2, 0.0]])
    # float64: 0.2, 0.4 ... are no float32 values, the cover is resolved exactly.
    sc = js.Scene([js.PolygonLight(em, 1.0)], occluders=[cover])
    assert float(js.irradiance(sc, p, UP)[0, 0]) == 0.0
    # float32: a cover of float32 values 1e-9 from the receiver is within the on-surface distance
    # (2^-18 S): the receiver lies on it and it blocks nothing; 1e-5 away it covers the light.
    sc = js.Scene([js.PolygonLight(em.astype(F32), 1.0)], occluders=[cover.astype(F32)])
    free = float(js.irradiance(js.Scene([js.PolygonLight(em.astype(F32), 1.0)]), p.astype(F32), UP.astype(F32))[0, 0])
    assert float(js.irradiance(sc, p.astype(F32), UP.astype(F32))[0, 0]) == pytest.approx(free, rel=1e-6)
    high = square_light(0.2, 0.4, -0.3, -0.1, 1e-5)
    sc = js.Scene([js.PolygonLight(em.astype(F32), 1.0)], occluders=[high.astype(F32)])
    assert float(js.irradiance(sc, p.astype(F32), UP.astype(F32))[0, 0]) == 0.0


# ---- row 5 -------------------------------------------------------------------------------


def _scene(n_lights=1):
    return js.Scene([js.PolygonLight(Q + [2.0 * i, 0.0, 0.0], 1.0) for i in range(n_lights)])


def test_row5_failing_save_scene_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "s.json"
    js.save_scene(_scene(), path)
    before = path.read_bytes()
    with pytest.raises(ValueError, match="material must be a jaxshadow.Material"):
        js.save_scene(_scene(), path, material={"kd": 0.5})
    assert path.read_bytes() == before

    def broken(*args, **kwargs):
        raise RuntimeError("serialiser failed")

    import jaxshadow._scene.format as scene_module

    monkeypatch.setattr(scene_module, "scene_to_dict", broken)
    with pytest.raises(RuntimeError, match="serialiser failed"):
        js.save_scene(_scene(), path)
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["s.json"]  # no temporary file left behind


_FSIZE_SCRIPT = textwrap.dedent(
    """
    import resource, signal, sys
    import numpy as np
    import jaxshadow as js
    import inverse
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG
    limit = int(sys.argv[1])
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    sq = np.array([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2.0]])
    n = 200
    targets = inverse.PaintedTargets(np.zeros((n, 3)), np.tile([0, 0, 1.0], (n, 1)), np.ones((n, 3)), [0, 0, 5.0])
    for path in sys.argv[2:]:
        try:
            if path.endswith("s.json"):
                js.save_scene(js.Scene([js.PolygonLight(sq + [2.0 * i, 0, 0]) for i in range(50)]), path)
            else:
                targets.save(path)
            print("written", path)
        except OSError as err:
            print("failed", err.errno)
    """
)


def test_row5_file_size_limit_keeps_the_old_files(tmp_path):
    paths = [tmp_path / name for name in ("s.json", "t.csv", "t.json")]
    js.save_scene(_scene(), paths[0])
    small = inverse.PaintedTargets(np.zeros((2, 3)), np.tile([0, 0, 1.0], (2, 1)), np.ones((2, 3)), [0, 0, 5.0])
    for path in paths[1:]:
        small.save(path)
    before = [p.read_bytes() for p in paths]
    limit = max(len(b) for b in before) + 100  # the old files fit, the new ones do not
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]))
    run = subprocess.run([sys.executable, "-c", _FSIZE_SCRIPT, str(limit), *map(str, paths)],
                         capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    assert run.stdout.split("\n")[:3] == ["failed 27"] * 3, run.stdout  # EFBIG, each time
    assert [p.read_bytes() for p in paths] == before
    assert sorted(os.listdir(tmp_path)) == ["s.json", "t.csv", "t.json"]  # no temporary file left


# ---- row 6 -------------------------------------------------------------------------------


@pytest.mark.parametrize("m", [MAX_COSINE_EXPONENT + 1, 10**7, 1e300])
def test_row6_cosine_exponent_above_the_limit_is_a_build_time_error(m):
    a, b = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="above the supported maximum"):
        js.LinearLight(a, b, 1.0, "cosine", m)
    d = {"format": "jaxshadow.scene", "version": 1, "lights": [
        {"type": "linear", "start": a.tolist(), "end": b.tolist(), "profile": "cosine", "exponent": m}]}
    with pytest.raises(ValueError, match=r"scene.lights\[0\]: .*above the supported maximum"):
        js.scene_from_dict(json.loads(json.dumps(d)))
    if isinstance(m, int):
        with pytest.raises(ValueError, match="above the supported maximum"):
            js.linear_irradiance(P, UP, a, b, m)


def test_row6_large_cosine_exponent_has_a_bounded_program_and_the_right_value():
    # Above the unrolled range the recurrences are loops: the traced program has the same size
    # for m = 40 and m = MAX (it grew as m^2: m = 2000 took ~1 min and 2.7 GB to compile).
    p, n = jnp.zeros(3), jnp.array([0.1, 0.0, 1.0]) / np.sqrt(1.01)
    a, b = jnp.array([-1.0, 0.3, 1.0]), jnp.array([1.0, 0.5, 1.2])

    def size(m):
        return len(jax.make_jaxpr(lambda *x: linear_irradiance_kernel(*x, m))(p, n, a, b).eqns)

    assert size(40) == size(MAX_COSINE_EXPONENT)
    # The loop form is differentiable like the unrolled one (forward and reverse).
    check_grads(jax.jit(lambda q, nn: linear_irradiance_kernel(q, nn, a, b, 40)), (p + 0.1, n), order=1, modes=("fwd", "rev"))
    for m in (40, MAX_COSINE_EXPONENT):
        ref = float(mp_linear(np.asarray(p), np.asarray(n), np.asarray(a), np.asarray(b), m))
        got = float(js.linear_irradiance(np.asarray(p)[None], np.asarray(n)[None], a, b, m)[0])
        assert _rel(got, ref) <= 1e-12


def test_resource_limit_chebyshev_degree():
    # The fit's matrices and the traced program grow with the degree: a clear error above it.
    sc = js.Scene([js.PolygonLight(Q, 1.0)])
    for degree in (MAX_DEGREE + 1, 10**6, True):
        with pytest.raises(ValueError, match=r"degree must be a Python int in \[2, 64\]"):
            js.specular(sc, P, UP, [0.0, 0.0, 5.0], 10.0, degree=degree)


# ---- row 7 -------------------------------------------------------------------------------


def test_row7_spline_shadow_occluder_on_the_emitter():
    pts = np.array([[0.5, 0.5, 0.0], [0.3, 0.6, 0.0], [3.0, 3.0, 0.0]])
    emitter = Q - [0.0, 0.0, 1.0]  # lit side down, z = 1
    # Lying on the emitter with shared vertices (the whole emitter, or half of it sharing an
    # edge): the shadow nodes of the shared vertices are 0/0 -- it returned -F.
    half = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 1.0], [0.5, 1.0, 1.0], [0.5, 0.0, 1.0]])
    for occ in (emitter, half):
        with pytest.raises(ValueError, match="coincides with vertex .* of the emitter"):
            js.spline_shadow(emitter, occ, pts)
    # In the emitter's plane without shared vertices: the exact answer F(E) - F(O).
    inner = square_light(0.2, 0.8, 0.3, 0.9, 1.0)
    nz = np.repeat(UP, len(pts), axis=0)
    ref = np.asarray(js.form_factor(pts, nz, emitter)) - np.asarray(js.form_factor(pts, nz, inner))
    np.testing.assert_allclose(np.asarray(js.spline_shadow(emitter, inner, pts)), ref, rtol=1e-12, atol=1e-15)


# ---- row 8 -------------------------------------------------------------------------------


@pytest.mark.parametrize("m", [0, 1, 4])
def test_row8_float32_linear_light_receiver_just_past_the_end(m):
    rng = np.random.default_rng(8)
    worst = 0.0
    for _ in range(3):
        a = rng.normal(size=3)
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        b = a + u * rng.uniform(0.5, 2.0)
        perp = np.cross(u, rng.normal(size=3))
        perp /= np.linalg.norm(perp)
        p = b + 1e-7 * u + rng.uniform(0.0, 3e-7) * perp
        n = -u + 0.3 * rng.normal(size=3)
        a, b, p, n = (x.astype(F32) for x in (a, b, p, n))
        got = float(js.linear_irradiance(p[None], n[None], a, b, m)[0])
        ref = float(mp_linear(p.astype(float), n / np.linalg.norm(n.astype(float)), a, b, m))
        worst = max(worst, _rel(got, ref))
    assert worst <= 1e-5  # was 1.0 (m = 0) to 9.6 (m = 4)


# ---- row 9 -------------------------------------------------------------------------------

_NAN_P = np.array([[0.5, np.nan, 0.0]])


def _raises_at_run_time(fn, *args, match="not finite"):
    with pytest.raises((RuntimeError, ValueError), match=match):
        jax.block_until_ready(fn(*args))


def test_row9_traced_values_are_checked_at_the_public_entry_points():
    b = np.array([1.0, 0.0, 1.0])
    _raises_at_run_time(jax.jit(js.form_factor), _NAN_P, UP, Q)
    _raises_at_run_time(jax.jit(js.form_factor), P, UP, np.where(Q == 1.0, np.nan, Q))
    _raises_at_run_time(jax.jit(lambda s: js.linear_irradiance(P, UP, s, b)), np.array([0.0, np.nan, 1.0]))
    sc = js.Scene([js.PolygonLight(Q, 1.0)])
    bad = eqx.tree_at(lambda s: s.lights[0].vertices, sc, jnp.asarray(np.where(Q == 1.0, np.nan, Q)))
    _raises_at_run_time(jax.jit(lambda s: js.irradiance(s, P, UP)), bad)
    # Good traced values still evaluate, and agree with the eager call.
    np.testing.assert_allclose(np.asarray(jax.jit(js.form_factor)(P, UP, Q)), np.asarray(js.form_factor(P, UP, Q)), rtol=1e-14)


@pytest.mark.slow  # one compilation per entry point (~50 s)
def test_row9_traced_values_are_checked_at_every_public_entry_point():
    a, b = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 1.0])
    _raises_at_run_time(jax.jit(lambda p: js.linear_irradiance(p, UP, a, b)), _NAN_P)
    em, occ = Q + [0.0, 0.0, 1.0], square_light(0.3, 0.6, 0.3, 0.6, 1.0)
    _raises_at_run_time(jax.jit(js.spline_shadow), em, occ, _NAN_P)
    _raises_at_run_time(jax.jit(js.spline_shadow_faces), em[None], occ[None], _NAN_P)
    _raises_at_run_time(jax.jit(js.visible_form_factor), _NAN_P, UP, Q, occ[None])
    sc = js.Scene([js.PolygonLight(Q, 1.0)])
    _raises_at_run_time(jax.jit(js.irradiance), sc, _NAN_P, UP)
    eye = np.array([0.0, 0.0, 5.0])
    _raises_at_run_time(jax.jit(lambda p: js.specular(sc, p, UP, eye, 10.0)), _NAN_P)
    mat = js.Material(kd=0.5)
    bad = eqx.tree_at(lambda m: m.kd, mat, jnp.array([0.5, np.nan, 0.5]))
    _raises_at_run_time(jax.jit(lambda m: js.shade(sc, m, P, UP, eye)), bad)
    np.testing.assert_allclose(np.asarray(jax.jit(js.irradiance)(sc, P, UP)), np.asarray(js.irradiance(sc, P, UP)), rtol=1e-14)


def test_row9_values_changed_after_build_are_checked_again():
    sc = js.Scene([js.PolygonLight(Q, 1.0)], occluders=[square_light(0.3, 0.6, 0.3, 0.6, 1.0)])
    bad = eqx.tree_at(lambda s: s.lights[0].vertices, sc, np.where(Q == 1.0, np.nan, Q))
    with pytest.raises(ValueError, match=r"irradiance: scene.*lights.*non-finite"):
        js.irradiance(bad, P, UP)
    dented = Q.copy()
    dented[2, :2] = [0.3, 0.3]  # pulled inside: non-convex
    with pytest.raises(ValueError, match=r"specular: scene.lights\[0\].vertices: non-convex"):
        js.specular(eqx.tree_at(lambda s: s.lights[0].vertices, sc, dented), P, UP, [0, 0, 5.0], 10.0)
    occ_nan = eqx.tree_at(lambda s: s.occluders, sc, np.full(np.shape(sc.occluders), np.nan))
    with pytest.raises(ValueError, match=r"irradiance: scene.*occluders.*non-finite"):
        js.irradiance(occ_nan, P, UP)
    mat = eqx.tree_at(lambda m: m.kd, js.Material(), np.array([0.5, -1.0, 0.5]))
    with pytest.raises(ValueError, match=r"shade: material.kd: must be >= 0"):
        js.shade(sc, mat, P, UP, [0, 0, 5.0])


# ---- row 10 ------------------------------------------------------------------------------


def _targets():
    return inverse.PaintedTargets(np.array([[0.2, 0.3, 0.0], [0.6, 0.4, 0.0]]), np.tile([0, 0, 1.0], (2, 1)),
                                  np.full((2, 3), 0.1), [0.0, 0.0, 3.0])


@pytest.mark.parametrize("call, match", [
    (lambda: inverse.fit_material(_scene(), _targets(), exponent=-3), r"fit_material: exponent must be None \(fit it\) or a finite number >= 0, got -3"),
    (lambda: inverse.fit_material(_scene(), _targets(), exponent=float("nan")), r"fit_material: exponent must be"),
    (lambda: inverse.fit_material(None, _targets()), r"fit_material: expected a jaxshadow.Scene, got NoneType"),
    (lambda: inverse.fit_light(_scene(), _targets(), js.Material(), light_index=0.5), r"fit_light: light_index must be an integer, got 0.5"),
    (lambda: inverse.fit_light(_scene(), _targets(), js.Material(), light_index=True), r"fit_light: light_index must be an integer"),
], ids=["fit-material-negative-exponent", "fit-material-nan-exponent", "fit-material-no-scene", "fit-light-float-index", "fit-light-bool-index"])
def test_row10_solver_arguments(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_row10_json_and_paths(tmp_path):
    good = js.scene_to_dict(_scene())
    for version in (1.0, True):
        with pytest.raises(ValueError, match="unsupported schema version"):
            js.scene_from_dict({**good, "version": version})
    with pytest.raises(ValueError, match="missing field 'lights'"):
        js.scene_from_dict({k: v for k, v in good.items() if k != "lights"})
    d = json.loads(json.dumps(good))
    d["lights"][0]["vertices"][1][2] = True
    with pytest.raises(ValueError, match=r"scene.lights\[0\].vertices: expected numbers, got a boolean"):
        js.scene_from_dict(d)
    d = {**good, "material": {"kd": [0.5, False, 0.5]}}
    (tmp_path / "m.json").write_text(json.dumps(d))
    with pytest.raises(ValueError, match=r"material.kd: expected numbers, got a boolean"):
        js.load_material(tmp_path / "m.json")
    with pytest.raises(ValueError, match="is a directory, not a scene file"):
        js.load_scene(tmp_path)
    with pytest.raises(ValueError, match="no such file"):
        js.load_scene(tmp_path / "missing.json")
    with pytest.raises(IsADirectoryError):
        js.save_scene(_scene(), tmp_path)


# ---- failures found by the property suite (test_properties.py) ---------------------------


_VG = jax.jit(jax.value_and_grad(form_factor_kernel, argnums=(0, 1, 2)))


def _value_and_finite_gradient_f32(p, n, verts):
    """float32 value and gradients of a 5-slot padded polygon (one compilation for both cases)."""
    verts = np.concatenate([verts, np.repeat(verts[:1], 5 - len(verts), axis=0)])
    val, grads = _VG(*(jnp.asarray(x, F32) for x in (p, n, verts)))
    assert all(np.all(np.isfinite(np.asarray(g))) for g in grads)
    return float(val)


def test_found_float32_gradient_of_a_receiver_at_a_light_vertex():
    # The vertex (1, -2.4e-16, 0) of a rotated triangle and the receiver (1, 0, 0): v - p is
    # 2.4e-16 long, and 1/|v - p|^3 overflowed in float32's derivative of v/|v|: NaN gradients
    # of a zero value (the receiver is in the light's plane).
    v = np.array([[-0.5, 0.866025404, 0.0], [-0.5, -0.866025404, 0.0], [1.0, -2.44929360e-16, 0.0]])
    assert _value_and_finite_gradient_f32([1.0, 0.0, 0.0], [1.0, 0.0, 0.0], v) == 0.0


def test_found_float32_gradient_of_a_padded_polygon_below_the_horizon():
    # A padded polygon (its first vertex repeated, as the scene pads lights of different vertex
    # counts) whose first vertex is below the receiver's horizon: the unused horizon crossing
    # of the zero-length padding edge was rounding noise (~1e-9 long under XLA's fused
    # multiply-adds), whose derivative overflowed float32: NaN gradients, in jit only.
    v = np.array([[-0.70680073, 0.15123682, -0.13113843], [-0.05929406, 0.95284256, 0.15234019],
                  [0.47432375, -0.6667053, -0.01019427], [-0.21994245, -0.95167697, -0.21432746]])
    p, n = np.array([1.0, 0.0, 0.0]), np.array([-0.07710583, -0.99702291, 0.0])
    ref = float(js.form_factor(p[None], n[None], v)[0])
    assert _rel(_value_and_finite_gradient_f32(p, n, v), ref) <= 2e-6


def test_found_float32_receiver_near_the_light_plane_with_a_cut_horizon():
    # The receiver 1e-6 from the plane of a tilted triangle (near its centre), its horizon
    # cutting the light in two: the closing horizon edge spans nearly pi, and its term took
    # n . Gamma from the direction of a x b, rounding noise there. With the horizon crossings
    # as chord points (the padded-polygon fix above) float32 F was off by 7.6e-6 (before
    # either change: 1.1e-7; now 4e-8) on a problem whose 1-ulp input perturbations move F
    # by 2e-8. Found by the long property profile.
    v = np.array([[-0.5, 0.467915523, 0.728735249], [-0.5, -0.467915523, -0.728735249], [1.0, -1.32335898e-16, -2.06100950e-16]])
    p, n = np.array([2.13662521e-23, -8.41470985e-07, 5.40302306e-07]), np.array([0.0, 0.0, 1.0])
    v, p, n = (x.astype(F32) for x in (v, p, n))
    ref = float(mp_form_factor(p.astype(float), n.astype(float), v.astype(float)))
    assert ref == pytest.approx(0.22984796, abs=1e-8)
    assert abs(float(js.form_factor(p[None], n[None], v)[0]) - ref) <= 2e-7
