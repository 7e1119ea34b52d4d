"""The front door to the shadow engine (jaxshadow._shading.shade, jaxshadow._shadows.evaluators).

Receivers are built once per public call; one evaluator is chosen from what the inputs are
(host engine, planned, traced with a capacity, device kernels) and all four give the same
values; lights say their kind, emission and geometry themselves; integrands declare what the
plan must produce.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxshadow as js
from jaxshadow._scene.format import light_from_dict, light_to_dict
from jaxshadow._scene.model import AbstractLight
from jaxshadow._shading import shade as shade_module
from jaxshadow._shadows import evaluators as ev
from jaxshadow._shadows.integrands import PRODUCE, Lambert, Phong
from jaxshadow._shadows.options import DEFAULT_OPTIONS, ShadowOptions
from jaxshadow._shadows.plan import plan

needs_engine = pytest.mark.skipif(not DEFAULT_OPTIONS.use_engine(), reason="shadow engine not built")

QUAD = [[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]]  # emits down (right-hand normal -z)
BLOCKER = [[0.2, 0.2, 1.0], [0.6, 0.2, 1.0], [0.6, 0.6, 1.0]]


def _lights() -> list:
    return [
        js.PolygonLight(QUAD, radiance=[4.0, 3.5, 3.0]),
        js.LinearLight([-0.5, 0.5, 1.8], [1.5, 0.5, 1.8], power=[2.0, 1.0, 0.5]),
        js.LinearLight([0.0, -0.5, 1.9], [0.2, 1.5, 2.1], power=1.5, profile="cosine", exponent=3),
        js.PointLight([0.3, 0.7, 2.5], intensity=[5.0, 4.0, 3.0]),
        js.DirectionalLight([0.2, -0.1, -1.0], irradiance=[1.0, 0.9, 0.8]),
    ]


def _scene() -> js.Scene:
    return js.Scene(_lights(), occluders=[BLOCKER], ambient=0.05)


def _receivers(n: int = 12) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    p = np.c_[rng.uniform(-0.3, 1.3, (n, 2)), np.zeros(n)]
    nrm = np.tile([0.0, 0.1, 1.0], (n, 1))
    return p, nrm


def test_lights_say_their_kind_emission_and_geometry() -> None:
    expected = {
        js.PolygonLight: ("polygon", "radiance", ("vertices",)),
        js.LinearLight: ("segment", "power", ("start", "end")),
        js.PointLight: ("point", "intensity", ("position",)),
        js.DirectionalLight: ("directional", "irradiance", ("direction",)),
    }
    for light in _lights():
        kind, emission, geometry = expected[type(light)]
        assert isinstance(light, AbstractLight)
        assert light.kind == kind
        assert light.emission(jnp.float32).dtype == jnp.float32
        np.testing.assert_array_equal(light.emission(jnp.float64), getattr(light, emission))
        assert len(light.geometry) == len(geometry)
        for got, name in zip(light.geometry, geometry, strict=True):
            np.testing.assert_array_equal(got, getattr(light, name))
    groups = [light.group for light in _lights()]
    assert groups == ["polygon", "linear-0", "linear-3", "point", "directional"]
    with pytest.raises(TypeError):
        AbstractLight()  # abstract: emission and geometry are not defined


def test_light_json_round_trip_by_kind() -> None:
    for light in _lights():
        d = light_to_dict(light)
        back = light_from_dict(d)
        assert type(back) is type(light)
        for a, b in zip(jax.tree_util.tree_leaves(light), jax.tree_util.tree_leaves(back), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(TypeError, match="not a light"):
        light_to_dict(js.Material())


def test_integrands_declare_what_the_plan_produces() -> None:
    assert Lambert.host_plan == "lambert" and not Lambert.reads_eye
    assert Phong.host_plan == "points" and Phong.reads_eye
    assert set(PRODUCE) == {"classes", "codes", "points", "lambert"}


@needs_engine
def test_plan_carries_what_was_asked_for() -> None:
    scene = js.Scene([js.PolygonLight(QUAD)], occluders=[BLOCKER])
    p, n = _receivers(40)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    got = {produce: plan(scene, p, n, produce=produce).lights[0] for produce in PRODUCE}
    assert np.count_nonzero(got["classes"].classes == 3) > 0  # some penumbra receivers
    for produce, lp in got.items():
        assert lp.produce == produce
        np.testing.assert_array_equal(lp.classes, got["classes"].classes)
        assert (lp.lambert is not None) == (produce == "lambert")
        assert (lp.points is not None) == (produce == "points")
        assert (lp.runs is not None) == (produce == "codes")
        assert lp.on_host == (produce != "codes")


@needs_engine
def test_evaluator_is_chosen_from_what_the_inputs_are() -> None:
    # The choice depends on what the inputs are (concrete, carrying derivatives, traced; the
    # options), not on the lights: one light keeps the four calls cheap.
    scene = js.Scene([js.PolygonLight(QUAD)], occluders=[BLOCKER])
    p, n = _receivers(4)
    chosen = []
    real_choose = ev.choose

    def spy(*args):
        out = real_choose(*args)
        chosen.append(type(out).__name__)
        return out

    shade_module.choose = spy
    try:
        js.irradiance(scene, p, n)
        jax.grad(lambda q: js.irradiance(scene, q, n).sum())(jnp.asarray(p))
        jax.jit(js.irradiance)(scene, p, n)
        js.irradiance(scene, p, n, shadows=ShadowOptions(engine="device"))
    finally:
        shade_module.choose = real_choose
    assert chosen == ["HostEngine", "Planned", "TracedEngine", "DeviceKernels"]


SCENE = _scene()
_TRACED: dict = {}


def _traced(integ):
    """`run(points, normals, eyes) -> (values, overflow)`: `ev.TracedEngine(64)` on SCENE with
    `integ`, inside one compiled program. An integrand without array leaves (Lambert) gets one
    wrapper per module, so the tests that evaluate it on the same receivers share its
    compilation; one with leaves (Phong's exponent) is closed over by a wrapper of its own."""
    def run(a, b, c, i=integ):
        return ev.TracedEngine(64)(SCENE, i, ev.receivers(a, b, c, "test"))

    if jax.tree_util.tree_leaves(integ):
        return jax.jit(run)
    return _TRACED.setdefault(type(integ), jax.jit(run))


@needs_engine
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_four_evaluators_agree(dtype) -> None:
    scene = SCENE
    p, n = (a.astype(dtype) for a in _receivers())
    eye = np.array([0.5, -1.5, 2.0], dtype)
    rx = ev.receivers(jnp.asarray(p), jnp.asarray(n), jnp.broadcast_to(jnp.asarray(eye), p.shape), "test")
    assert rx.concrete and rx.ok is None and rx.values is not None
    tol = 2e-4 if dtype == np.float32 else 1e-9
    for integ in (Lambert(), Phong(jnp.asarray(20.0, dtype))):
        host, o = ev.HostEngine()(scene, integ, rx)
        assert o is False
        assert np.asarray(host).dtype == dtype
        scale = float(np.max(np.abs(host)))
        assert scale > 0
        for evaluator in (ev.Planned(), ev.TracedEngine(64), ev.DeviceKernels()):
            if isinstance(evaluator, ev.TracedEngine):  # abstract values: inside one compiled program
                out, overflow = _traced(integ)(rx.points, rx.normals, jnp.broadcast_to(jnp.asarray(eye), p.shape))
            else:
                out, overflow = evaluator(scene, integ, rx)
            assert not bool(overflow)
            # The device kernels integrate a segment light's Phong lobe by another route than the
            # host path (a cos^m profile at exponent 20 differs by ~1e-8 of the scale in float64,
            # as before the evaluators were objects: js.specular with engine="device" vs the
            # engine); the other evaluators share the host's route and agree to rounding.
            t = 1e-7 if isinstance(evaluator, ev.DeviceKernels) and isinstance(integ, Phong) else tol
            np.testing.assert_allclose(np.asarray(out), np.asarray(host), rtol=0, atol=max(t, tol) * scale,
                                       err_msg=type(evaluator).__name__)


class _NoEye(Lambert):
    """Lambert's integrand that fails when it is handed an eye (it reads none)."""

    def polygon(self, p, n, e, verts):
        assert e is None, "Lambert was handed an eye"
        return Lambert.polygon(self, p, n, e, verts)

    def contour(self, p, n, e, verts, starts, ends):
        assert e is None, "Lambert was handed an eye"
        return Lambert.contour(self, p, n, e, verts, starts, ends)

    def segment(self, p, n, e, a, b, light):
        assert e is None, "Lambert was handed an eye"
        return Lambert.segment(self, p, n, e, a, b, light)

    def point(self, p, n, e, x):
        assert e is None, "Lambert was handed an eye"
        return Lambert.point(self, p, n, e, x)

    def directional(self, p, n, e, d):
        assert e is None, "Lambert was handed an eye"
        return Lambert.directional(self, p, n, e, d)


@needs_engine
def test_an_integrand_that_reads_no_eye_is_given_none() -> None:
    """Receivers with eyes (as `js.shade` builds them for both terms): Lambert is handed none by
    every evaluator, Phong its eyes; values as Lambert's own."""
    scene = SCENE
    p, n = _receivers()
    eyes = jnp.broadcast_to(jnp.asarray([0.5, -1.5, 2.0]), p.shape)
    rx = ev.receivers(jnp.asarray(p), jnp.asarray(n), eyes, "test")
    assert rx.eyes_for(Lambert()) is None and rx.eye_values_for(Lambert()) is None
    assert rx.eyes_for(Phong(20.0)) is eyes
    np.testing.assert_array_equal(rx.eye_values_for(Phong(20.0)), np.asarray(eyes))
    for evaluator in (ev.HostEngine(), ev.Planned(), ev.TracedEngine(64), ev.DeviceKernels()):
        if isinstance(evaluator, ev.TracedEngine):  # abstract values: inside one compiled program
            def run(integ):
                return _traced(integ)(rx.points, rx.normals, eyes)
        else:
            def run(integ, e=evaluator):
                return e(scene, integ, rx)
        got, _ = run(_NoEye())
        want, _ = run(Lambert())
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want), err_msg=type(evaluator).__name__)
    without = ev.receivers(p, n, None, "test")
    with pytest.raises(ValueError, match="Phong reads an eye"):
        without.eyes_for(Phong(20.0))
    with pytest.raises(ValueError, match="Phong reads an eye"):
        ev.HostEngine()(scene, Phong(20.0), without)


@needs_engine
def test_traced_capacity_overflow_is_reported() -> None:
    scene = js.Scene([js.PolygonLight(QUAD)], occluders=[BLOCKER])
    p, n = _receivers()
    rx = ev.traced_receivers(jnp.asarray(p), jnp.asarray(n), None)
    _, overflow = ev.TracedEngine(1)(scene, Lambert(), rx)
    assert bool(overflow)
    with pytest.raises(Exception, match="more than 1 boundary edges"):
        jax.jit(lambda s, a, b: js.irradiance(s, a, b, shadows=ShadowOptions(capacity=1)))(scene, p, n)


@needs_engine
def test_receivers_are_built_once_per_call(monkeypatch) -> None:
    scene = _scene()
    p, n = _receivers()
    calls = []
    real = shade_module.receivers

    def counting(*args):
        calls.append(args[-1])
        return real(*args)

    monkeypatch.setattr(shade_module, "receivers", counting)
    js.shade(scene, js.Material(ka=0.1, kd=0.5, ks=0.3, exponent=10.0), p, n, [0.0, -1.0, 2.0])
    assert calls == ["shade"]  # one receivers object for the Lambert and the Phong term


def test_bad_receivers_are_named_at_the_entrance() -> None:
    p, n = _receivers()
    n[3] = 0.0
    with pytest.raises(ValueError, match=r"irradiance: normals\[3\] is the zero vector"):
        ev.receivers(p, n, None, "irradiance")
    p[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"specular: points\[1\] is not finite"):
        ev.receivers(p, n, None, "specular")
