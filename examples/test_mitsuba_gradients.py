"""Checking a renderer's shadow gradients against the exact oracle of `jaxshadow.testing`.

The renderer under test is a few lines of Mitsuba 3: next-event estimation of the irradiance at
the catalogue's receivers (one emitter sample and one shadow ray per sample, as Mitsuba's
`direct` integrator does at a surface point), differentiated in forward mode by Dr.Jit with
respect to a translation of the light. Automatic differentiation of this estimator misses the
boundary term of the derivative: the shadow ray's visibility is a step function of the light's
position, so the moving shadow edge contributes nothing. The oracle passes the estimator where
no shadow edge crosses the light and catches the missing term in the penumbra.

This file imports only `jaxshadow.testing`, Mitsuba (with its Dr.Jit) and NumPy; the fixtures
`jaxshadow_reference` and `jaxshadow_alpha` come from the pytest plugin that jaxshadow installs.
"""

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
import drjit as dr  # noqa: E402

from jaxshadow.testing import LIGHT_TRANSLATION, assert_gradient_matches, assert_values_match  # noqa: E402

SPP = 1 << 13
AXES = {"light.tx": (1.0, 0.0, 0.0), "light.ty": (0.0, 1.0, 0.0), "light.tz": (0.0, 0.0, 1.0)}


def irradiance_and_derivative(reference, axis, spp=SPP, seed=0):
    """Mean and standard error over `spp` samples of E and of dE/d(light translation along
    `axis`) at the reference's receivers: `(E, E_err, dE, dE_err)`, each `(N, 3)`."""
    if mi.variant() not in ("llvm_ad_rgb", "cuda_ad_rgb"):
        mi.set_variant("llvm_ad_rgb")
    scene = mi.load_dict(reference.mitsuba_dict())
    params = mi.traverse(scene)
    key = reference.mitsuba_light_key  # "light_000.vertex_positions" for a polygon light
    v0 = dr.unravel(mi.Point3f, params[key])
    t = mi.Vector3f(0.0)
    dr.enable_grad(t)
    params[key] = dr.ravel(v0 + t)
    dr.set_grad(t, mi.Vector3f(*AXES[axis]))
    dr.forward_to(params[key], flags=dr.ADFlag.ClearEdges)
    params.update()

    n_points = reference.points.shape[0]
    lanes = n_points * spp
    idx = dr.arange(mi.UInt32, lanes) // spp
    it = dr.zeros(mi.Interaction3f, lanes)
    it.p = dr.gather(mi.Point3f, mi.Point3f(reference.points.T.astype(np.float32)), idx)
    it.n = dr.gather(mi.Normal3f, mi.Normal3f(reference.normals.T.astype(np.float32)), idx)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, lanes)
    ds, weight = scene.sample_emitter_direction(it, sampler.next_2d(), test_visibility=True)
    value = weight * dr.maximum(dr.dot(ds.d, it.n), 0.0)
    dr.forward_to(value)
    stats = []
    for lanes_rgb in (value, dr.grad(value)):  # Color3f: (3, lanes) as a NumPy array
        s = np.asarray(lanes_rgb, np.float64).reshape(3, n_points, spp)
        stats += [s.mean(axis=2).T, s.std(axis=2, ddof=1).T / np.sqrt(spp)]
    return tuple(stats)


def estimates(reference, seed=0):
    out = {axis: irradiance_and_derivative(reference, axis, seed=seed) for axis in LIGHT_TRANSLATION}
    e, e_err = out["light.tx"][:2]
    d = {axis: out[axis][2] for axis in LIGHT_TRANSLATION}
    d_err = {axis: out[axis][3] for axis in LIGHT_TRANSLATION}
    return e, e_err, d, d_err


@pytest.mark.jaxshadow_scenes("unoccluded", "penumbra")
def test_irradiance_matches(jaxshadow_reference, jaxshadow_alpha):
    e, e_err, _, _ = estimates(jaxshadow_reference)
    assert_values_match(e, e_err, jaxshadow_reference.irradiance, alpha=jaxshadow_alpha)


@pytest.mark.jaxshadow_scenes("unoccluded", "grazing")
def test_gradient_matches_without_shadow_edges(jaxshadow_reference, jaxshadow_alpha):
    _, _, d, d_err = estimates(jaxshadow_reference, seed=1)
    exact = {axis: jaxshadow_reference.d_irradiance[axis] for axis in LIGHT_TRANSLATION}
    assert_gradient_matches(d, d_err, exact, alpha=jaxshadow_alpha)


@pytest.mark.jaxshadow_scenes("penumbra")
def test_missing_boundary_term_is_caught(jaxshadow_reference, jaxshadow_alpha):
    _, _, d, d_err = estimates(jaxshadow_reference, seed=2)
    exact = {axis: jaxshadow_reference.d_irradiance[axis] for axis in LIGHT_TRANSLATION}
    with pytest.raises(AssertionError) as failure:
        assert_gradient_matches(d, d_err, exact, alpha=jaxshadow_alpha)
    print(failure.value)
    # Every receiver sees a moving shadow edge: the estimate misses part of every derivative.
    assert "d/d light.tx" in str(failure.value)
