"""The projected one-light fit's program (`inverse/_projected_lm.py`): the basis it keeps at the
answer against the public, checked entry points (`js.irradiance`, `js.specular`, the painting
material), and `fit_light_and_material` running no other program that holds the shadow engine,
with the standard errors of the separate joint program (`inverse.joint_std_errors`)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import inverse
import jaxshadow as js
from inverse import _joint, _lights, _material, _projected_lm
from inverse._multistart import culling_capacity_for_starts
from inverse._parametrisation import LightParametrisation, with_light


def _problem(noise=0.0, seed=0, n_points=24):
    """The demo's quad light over one occluder, a specular material, the projected problem of
    `fit_light_and_material` (pose and log n searched) and its parametrisation."""
    cfg = inverse.demo_configuration(occluders=True, n_points=n_points, seed=seed)
    col = np.asarray(js.shade(cfg.scene, cfg.material, cfg.points, cfg.normals, cfg.eye))
    if noise:
        col = col * (1 + noise * np.random.default_rng(seed).normal(size=col.shape))
    targets = inverse.PaintedTargets(cfg.points, cfg.normals, col, cfg.eye)
    param = LightParametrisation(cfg.scene.lights[0], 0, ("position", "orientation", "size"), None,
                                 inverse.scene_size(cfg.scene, targets), "sigmoid")
    problem = _lights._problem(param, cfg.scene, cfg.material, targets, None, True, True, True)
    return cfg, targets, param, problem


def test_kept_basis_is_the_public_model():
    """At the true pose with 4 exponents: the kept E, S are `js.irradiance` and `js.specular` of
    the light (1e-9), dS/dlog n is their central difference in log n, the projected material is
    the one the targets were painted with."""
    cfg, targets, param, problem = _problem()
    assert _projected_lm.keeps_basis(problem)
    ns = np.array([float(cfg.material.exponent), 3.0, 40.0, 900.0])
    rows = np.c_[np.zeros((ns.size, param.size)), np.log(ns)]
    cap = culling_capacity_for_starts(param, cfg.scene, targets, jnp.asarray(rows[:1]))
    problem = dataclasses.replace(problem, capacity=8 * -(-cap // 8))
    res, problem, _ = _projected_lm.solve(problem, rows, rows[0], np.ones(rows.shape[1], bool), rtol=1e-9,
                                          atol=1e-12, max_steps=0, prune=())
    scene = with_light(cfg.scene, 0, param.build(jnp.zeros(param.size)))
    E = np.asarray(js.irradiance(scene, targets.points, targets.normals))
    for i, n in enumerate(ns):
        aux = _projected_lm.aux_row(res.aux, i)
        e, s = _projected_lm.totals(problem, aux)
        np.testing.assert_allclose(e, E, rtol=1e-9, atol=1e-14)
        spec = [np.asarray(js.specular(scene, targets.points, targets.normals, targets.eye, float(m)))
                for m in (n, n * np.exp(1e-5), n * np.exp(-1e-5))]
        np.testing.assert_allclose(s, spec[0], rtol=1e-9, atol=1e-14)
        fd = (spec[1] - spec[2]) / 2e-5
        np.testing.assert_allclose(aux[3][-1].sum(axis=0), fd, rtol=1e-5, atol=1e-9 * np.abs(fd).max())
    k = _projected_lm.coefficients(problem, _projected_lm.aux_row(res.aux, 0))
    want = np.stack([np.broadcast_to(np.asarray(getattr(cfg.material, f), np.float64), (3,))
                     for f in ("ka", "kd", "ks")])
    np.testing.assert_allclose(k, want, rtol=1e-9)


def test_joint_fit_runs_one_engine_program(monkeypatch):
    """`fit_light_and_material` (1 % noise) compiles no joint Jacobian, material-fit specular or
    projection program: the LM's program serves them. Its standard errors are those of
    `inverse.joint_std_errors` (the separate joint program) at its answer (1e-7: the two
    evaluate the engine in different programs)."""
    cfg, targets, param, _ = _problem(noise=0.01, seed=1)
    guess = js.Material(ka=0.2, kd=0.5, ks=0.2, exponent=float(cfg.material.exponent))

    def refuse(*args, **kwargs):
        raise AssertionError("a second program holding the shadow engine")

    with monkeypatch.context() as m:
        for mod, name in ((_joint, "_joint_jacobian"), (_material, "_spec_eval"), (_lights, "colour_coefficients")):
            m.setattr(mod, name, refuse)
        fit = inverse.fit_light_and_material(cfg.start_scene, targets, guess, light_kwargs={"starts": 8})
    lf, mf = fit.report
    assert lf.loss < 1e-3 * lf.initial_loss
    free = np.ones((3, 3), bool)
    for a in mf.active_bounds:
        free["ka kd ks".split().index(a[:2]), "rgb".index(a[3])] = False
    want = inverse.joint_std_errors(_light_param(cfg, targets), lf.theta, cfg.start_scene, fit.material, targets,
                                    fit_exponent=True, free_k=free)
    assert set(fit.std_errors) == set(want)
    for nm, v in want.items():
        assert fit.std_errors[nm] == pytest.approx(v, rel=1e-7), nm


def _light_param(cfg, targets):
    """The parametrisation `fit_light_and_material` fits (the default groups, LM's box map)."""
    from inverse._parametrisation import FIT_GROUPS

    return LightParametrisation(cfg.start_scene.lights[0], 0, FIT_GROUPS, None,
                                inverse.scene_size(cfg.start_scene, targets), "sigmoid")
