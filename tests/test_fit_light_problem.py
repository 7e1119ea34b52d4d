"""`fit_light` with the `LM` runs `fit_lights`' problem (`_multilight.LightsProblem`, one fitted
light, its power held, the other lights' contribution computed once) through `fit_lights`'
screening and compiled solver program (`_multilight.screen`, `_multilight.solve`); the
answer equals, to rounding, that of the problem with every light inside the program
(`_residuals.LightProblem`, which the other solvers run)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import inverse
import jaxshadow as js
from inverse import _lights, _multilight
from inverse._multistart import make_starts
from inverse._parametrisation import LightParametrisation, scene_size
from inverse._residuals import LightProblem, projected_jit

MATERIAL = js.Material(ka=0.2, kd=0.6, ks=0.0, exponent=1.0)
GUESS = js.Material(ka=0.4, kd=0.3, ks=0.0, exponent=1.0)
BOX_TOP = [np.array([[-0.2, -0.2, 0.5], [0.2, -0.2, 0.5], [0.2, 0.2, 0.5], [-0.2, 0.2, 0.5]])]


def _problem(n_lights: int, occluders: list | None = BOX_TOP):
    """A point light over 24 floor targets beside a square occluder (and, with `n_lights=2`, a
    second point light held fixed), painted by `js.shade`; the start 0.3 m off."""
    dt = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-1, 1, (24, 2)), np.zeros(24)].astype(dt)
    normals, eye = np.tile(np.array([0.0, 0.0, 1.0], dt), (24, 1)), np.array([0.0, -2.0, 2.0], dt)
    other = [js.PointLight([-0.5, 0.1, 1.5], 1.0)][: n_lights - 1]
    true = js.Scene([js.PointLight([0.2, 0.3, 2.0], 3.0), *other], occluders=occluders, ambient=0.05)
    targets = inverse.PaintedTargets(points, normals, js.shade(true, MATERIAL, points, normals, eye), eye)
    start = js.Scene([js.PointLight([0.0, 0.0, 1.8], 3.0), *other], occluders=occluders, ambient=0.05)
    return start, targets, true


@pytest.mark.parametrize(("n_lights", "mode"), [(1, "fixed"), (2, "fixed"), (1, "projected")])
def test_fit_light_runs_the_program_of_fit_lights(monkeypatch, n_lights, mode):
    start, targets, true = _problem(n_lights, occluders=BOX_TOP if mode == "fixed" else None)
    calls = []
    solve = _multilight.solve
    monkeypatch.setattr("inverse._solvers.solve", lambda pr, *a, **k: calls.append(pr) or solve(pr, *a, **k))
    fit = inverse.fit_light(start, targets, MATERIAL if mode == "fixed" else GUESS, fit=("position",), starts=4,
                            solver=inverse.LM(refine=2), material_mode=mode, warn=False)
    assert calls and all(isinstance(pr, _multilight.LightsProblem) for pr in calls)
    assert bool(calls[0].has_fixed) == (n_lights == 2)
    assert bool(calls[0].colour_free) == (mode == "projected")
    np.testing.assert_allclose(np.asarray(fit.light.position), np.asarray(true.lights[0].position), atol=1e-6)
    assert fit.report.loss < 1e-12 * float(np.sum(np.asarray(targets.colours) ** 2))


@pytest.mark.parametrize(("n_lights", "mode", "solver"), [
    (1, "fixed", inverse.LM(refine=None)), (2, "fixed", inverse.LM(refine=None)),
    (1, "projected", inverse.LM(refine=None)), (2, "fixed", inverse.OptimistixLM(refine=2)),
    (2, "fixed", inverse.LBFGSB(refine=2))], ids=["lm-1", "lm-2", "lm-projected", "optimistix-2", "lbfgsb-2"])
def test_one_problem_same_answer(n_lights, mode, solver):
    """Each solver from the same starts on both problem objects: the same solved parameters and
    losses to rounding (the model's sums are ordered differently, and the fixed light is
    computed once by the host engine instead of inside the program)."""
    start, targets, _ = _problem(n_lights)
    material = MATERIAL if mode == "fixed" else GUESS
    project = mode == "projected"
    param = LightParametrisation(start.lights[0], 0, ("position",), None, scene_size(start, targets), solver.box_map)
    y0 = make_starts(param, 3, search_radius=0.5, orientation_spread=0.5, size_spread=0.5, seed=0,
                     dtype=targets.points.dtype)
    lights = _lights._problem(solver, param, start, material, targets, None, False, project, False)
    assert isinstance(lights, _multilight.LightsProblem)
    a = solver.minimise(lights, y0)
    b = solver.minimise(LightProblem(param, start, material, targets, None, False, project, False), y0)
    eps = float(jnp.finfo(targets.points.dtype).eps)
    scale = float(np.max(np.abs(b.values)))
    np.testing.assert_allclose(a.values, b.values, rtol=0, atol=1e5 * eps * scale)
    energy = 0.5 * float(np.sum(np.asarray(targets.colours, np.float64) ** 2))
    np.testing.assert_allclose(a.losses, b.losses, rtol=0, atol=1e3 * eps * energy)
    assert a.best == b.best


def test_projected_material_matches():
    """The material `fit_light(material_mode="projected")` reports (`_lights.colour_coefficients`
    on the `LightsProblem`) is the truth here, and the `LightProblem`'s projection at the same light."""
    start, targets, _ = _problem(1, occluders=None)
    fit = inverse.fit_light(start, targets, GUESS, fit=("position",), starts=4, solver=inverse.LM(refine=2),
                            material_mode="projected", warn=False)
    eps = float(jnp.finfo(targets.points.dtype).eps)
    np.testing.assert_allclose(np.asarray(fit.material.kd), np.asarray(MATERIAL.kd), rtol=1e7 * eps)
    np.testing.assert_allclose(np.asarray(fit.material.ka), np.asarray(MATERIAL.ka), rtol=1e7 * eps)
    param = fit.parametrisation
    theta = jnp.asarray(fit.report.theta, targets.points.dtype)
    lights = _lights._problem(inverse.LM(), param, start, GUESS, targets, None, False, True, False)
    k_new = np.asarray(_lights.colour_coefficients(lights, theta), np.float64)
    _, k_old, _ = projected_jit(LightProblem(param, start, GUESS, targets, None, False, True, False), theta)
    np.testing.assert_allclose(k_new, np.asarray(k_old, np.float64), rtol=0, atol=1e4 * eps)


def test_projected_negative_coefficient_is_reported_not_raised():
    """At a wrong minimum the unconstrained projection can give $k_d < 0$ (here: 4 starts, the
    best 2 solved, a point light behind a square occluder): the fit returns, with the
    coefficient held at 0 and said in the report, instead of raising from `js.Material`."""
    start, targets, _ = _problem(1)
    fit = inverse.fit_light(start, targets, GUESS, fit=("position",), starts=4, solver=inverse.LM(refine=2),
                            material_mode="projected", warn=False)
    assert np.all(np.asarray(fit.material.kd) >= 0) and np.all(np.asarray(fit.material.ka) >= 0)
    assert any("negative coefficients" in w for w in fit.report.warnings)
    assert not fit.report.trusted
