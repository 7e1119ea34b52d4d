"""`fit_light` is `fit_lights` with one light: every solver (the `LM`, `OptimistixLM`, `LBFGSB`
and a solver of one's own) runs `fit_lights`' problem (`_multilight.LightsProblem`, one fitted
light, its power held), the `LM` through `fit_lights`' screening and compiled program
(`_multilight.screen`, `_multilight.solve`; with a projected material the same residual in
`_projected_lm.solve`, which keeps the basis). The problem holds what a one-light fit can ask
for: a fitted Phong exponent, a per-receiver material, a projected material beside other
lights. Its residual is checked against `js.shade` and a NumPy least squares on `js.irradiance`
and `js.specular` (independent of the solvers' programs); the fits against targets painted by
`js.shade` with known answers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import inverse
import jaxshadow as js
from inverse import _lights, _multilight, _projected_lm, _solvers
from inverse._multistart import make_starts
from inverse._parametrisation import LightParametrisation, scene_size, with_light

MATERIAL = js.Material(ka=0.2, kd=0.6, ks=0.0, exponent=1.0)
GUESS = js.Material(ka=0.4, kd=0.3, ks=0.0, exponent=1.0)
SHINY = js.Material(ka=[0.1, 0.2, 0.15], kd=[0.5, 0.3, 0.4], ks=[0.3, 0.35, 0.25], exponent=12.0)
BOX_TOP = [np.array([[-0.2, -0.2, 0.5], [0.2, -0.2, 0.5], [0.2, 0.2, 0.5], [-0.2, 0.2, 0.5]])]
OTHER = js.PointLight([-0.5, 0.1, 1.5], 1.0)


def _problem(n_lights: int, occluders: list | None = BOX_TOP, material: js.Material = MATERIAL, n: int = 24,
             tilted: bool = False):
    """A point light over `n` floor targets beside a square occluder (and, with `n_lights=2`, a
    second point light held fixed), painted by `js.shade` with `material`; the start 0.3 m off.
    `tilted`: normals tilted up to ~35 degrees (varied specular directions)."""
    dt = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)].astype(dt)
    normals = np.tile(np.array([0.0, 0.0, 1.0]), (n, 1))
    if tilted:
        normals[:, :2] = rng.uniform(-0.7, 0.7, (n, 2))
    normals = (normals / np.linalg.norm(normals, axis=1, keepdims=True)).astype(dt)
    eye = np.array([0.0, -2.0, 2.0], dt)
    other = [OTHER][: n_lights - 1]
    true = js.Scene([js.PointLight([0.2, 0.3, 2.0], 3.0), *other], occluders=occluders, ambient=0.05)
    targets = inverse.PaintedTargets(points, normals, js.shade(true, material, points, normals, eye), eye)
    start = js.Scene([js.PointLight([0.0, 0.0, 1.8], 3.0), *other], occluders=occluders, ambient=0.05)
    return start, targets, true


def _param(start, targets, solver=inverse.LM()):
    return LightParametrisation(start.lights[0], 0, ("position",), None, scene_size(start, targets), solver.box_map)


def _eps(targets):
    return float(jnp.finfo(targets.points.dtype).eps)


@pytest.mark.parametrize(("n_lights", "mode"), [(1, "fixed"), (2, "fixed"), (1, "projected")])
def test_fit_light_runs_the_program_of_fit_lights(monkeypatch, n_lights, mode):
    start, targets, true = _problem(n_lights, occluders=BOX_TOP if mode == "fixed" else None)
    calls = []
    # A projected fit runs the same residual in the program that also keeps its basis (`_projected_lm`).
    solve = _projected_lm.solve if mode == "projected" else _multilight.solve
    where = "inverse._projected_lm.solve" if mode == "projected" else "inverse._solvers.solve"
    monkeypatch.setattr(where, lambda pr, *a, **k: calls.append(pr) or solve(pr, *a, **k))
    fit = inverse.fit_light(start, targets, MATERIAL if mode == "fixed" else GUESS, fit=("position",), starts=4,
                            solver=inverse.LM(refine=2), material_mode=mode, warn=False)
    assert calls and all(isinstance(pr, _multilight.LightsProblem) for pr in calls)
    assert bool(calls[0].has_fixed) == (n_lights == 2)
    assert bool(calls[0].colour_free) == (mode == "projected")
    np.testing.assert_allclose(np.asarray(fit.light.position), np.asarray(true.lights[0].position), atol=1e-6)
    assert fit.report.loss < 1e-12 * float(np.sum(np.asarray(targets.colours) ** 2))
    assert isinstance(fit, inverse.LightsFit)
    _check_one_report_type(fit.report)


def _check_one_report_type(report):
    """`fit_light`'s report is `fit_lights`' report type (a `LightsReport`), its fields filled
    from the one light's solve: one stage, the starts it solved, the retries."""
    assert isinstance(report, inverse.LightsReport) and isinstance(report, inverse.LightReport)
    assert report.stage_losses == (report.loss,) and report.starts_solved == len(report.start_losses) >= 1
    assert report.retries >= 0 and report.suggestions == {} and report.suggestion_normals == {}
    assert all(a in report.names and b in report.names and abs(r) > 0.95 for a, b, r in report.correlated)
    assert str(report).startswith("light fit (lm)")


def test_fit_light_report_trades_off_as_fit_lights_does():
    """Targets on a short segment of the x axis under a point light: its x and z trade off (the
    peak's width and height move together). `fit_light` reports the pair in `correlated` as
    `fit_lights` does for the same light (power held), with the same correlation."""
    dt = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    x = np.linspace(0.25, 0.6, 12)
    points = np.c_[x, np.zeros_like(x), np.zeros_like(x)].astype(dt)
    normals = np.tile(np.array([0.0, 0.0, 1.0], dt), (len(x), 1))
    eye = np.array([0.0, -2.0, 2.0], dt)
    true = js.Scene([js.PointLight([0.0, 0.0, 2.0], 3.0)], ambient=0.05)
    targets = inverse.PaintedTargets(points, normals, js.shade(true, MATERIAL, points, normals, eye), eye)
    one = inverse.fit_light(true, targets, MATERIAL, fit=("position",), starts=1, warn=False)
    many = inverse.fit_lights(true, targets, MATERIAL, fit=("position",), starts=1, warn=False)
    _check_one_report_type(one.report)
    assert isinstance(many.report, inverse.LightsReport)
    pairs = {(a, b): r for a, b, r in one.report.correlated}
    assert ("x", "z") in pairs, one.report.correlated
    want = {(a.removeprefix("light0."), b.removeprefix("light0.")): r for a, b, r in many.report.correlated}
    assert set(pairs) == set(want)
    for k, r in pairs.items():
        assert r == pytest.approx(want[k], abs=1e-6)


def test_residual_is_js_shade_with_a_per_receiver_material():
    """The one-light problem's residual (fixed material given per receiver, a specular term,
    a second light held fixed) at a moved light equals $\\sqrt{w}$ (`js.shade` - colours) of the
    scene with that light, and is not that of the material's mean."""
    n = 24
    rng = np.random.default_rng(3)
    per = js.Material(ka=rng.uniform(0.05, 0.3, (n, 3)), kd=rng.uniform(0.2, 0.8, (n, 3)),
                      ks=rng.uniform(0.1, 0.4, (n, 3)), exponent=8.0)
    start, targets, _ = _problem(2, material=per, n=n, tilted=True)
    param = _param(start, targets)
    problem = _lights._problem(param, start, per, targets, None, True, False, False)
    theta = jnp.asarray([0.05, -0.1, 0.08], targets.points.dtype)
    got = np.asarray(problem.residual(theta), np.float64)
    moved = with_light(start, 0, problem.lights(theta)[0])
    t = targets
    want = np.sqrt(np.asarray(t.weights)) * (np.asarray(js.shade(moved, per, t.points, t.normals, t.eye))
                                             - np.asarray(t.colours))
    assert np.abs(want).max() > 1e-3
    np.testing.assert_allclose(got, want.reshape(-1), rtol=0, atol=1e3 * _eps(t) * np.abs(want).max())
    mean = js.Material(ka=np.asarray(per.ka).mean(0), kd=np.asarray(per.kd).mean(0), ks=np.asarray(per.ks).mean(0),
                       exponent=8.0)
    other = np.asarray(_lights._problem(param, start, mean, targets, None, True, False, False).residual(theta))
    assert np.abs(other - got).max() > 1e-3 * np.abs(want).max()


@pytest.mark.parametrize("fit_n", [False, True])
def test_projected_residual_beside_another_light_is_least_squares_on_every_light(fit_n):
    """A projected material beside a fixed light (and with a fitted exponent, the other light
    inside the program): the residual is, per channel, the weighted least squares of the colours
    on the ambient, the irradiance of *every* light over pi and their specular integral (one
    $k_d$, one $k_s$ shared by the lights, as `js.shade` has them), from `js.irradiance` and
    `js.specular` and NumPy's `lstsq`."""
    start, targets, _ = _problem(2, occluders=None, material=SHINY, tilted=True)
    t = targets
    param = _param(start, t)
    problem = _lights._problem(param, start, SHINY, t, None, True, True, fit_n)
    assert problem.colour_free and problem.fit_exponent == fit_n and len(problem.params) == (2 if fit_n else 1)
    n = 6.0 if fit_n else float(SHINY.exponent)
    theta = jnp.asarray([0.05, -0.1, 0.08, *([np.log(n)] if fit_n else [])], t.points.dtype)
    got = np.asarray(problem.residual(theta), np.float64).reshape(-1, 3)
    moved = with_light(start, 0, problem.lights(theta)[0])
    e = np.asarray(js.irradiance(moved, t.points, t.normals), np.float64)
    s = np.asarray(js.specular(moved, t.points, t.normals, np.broadcast_to(t.eye, t.points.shape), n), np.float64)
    sw = np.sqrt(np.asarray(t.weights, np.float64))
    want = np.empty_like(got)
    for c in range(3):
        X = np.c_[np.full(len(e), 0.05), e[:, c] / np.pi, s[:, c]] * sw[:, c:c + 1]
        y = np.asarray(t.colours, np.float64)[:, c] * sw[:, c]
        k = np.linalg.lstsq(X, y, rcond=None)[0]
        want[:, c] = X @ k - y
    assert np.abs(want).max() > 1e-4
    np.testing.assert_allclose(got, want, rtol=0, atol=1e5 * _eps(t) * np.abs(np.asarray(t.colours)).max())


def test_fitted_exponent_is_recovered_beside_another_light():
    """`fit_light(material_mode="projected", fit_exponent=True)` on targets painted by `js.shade`
    with $n = 12$ and a second light, from $n = 5$: the light, the exponent and the material
    are recovered; the report names `log_n`."""
    start, targets, true = _problem(2, occluders=None, material=SHINY, tilted=True)
    guess = js.Material(ka=0.3, kd=0.3, ks=0.3, exponent=5.0)
    fit = inverse.fit_light(start, targets, guess, fit=("position",), starts=4, solver=inverse.LM(refine=2),
                            material_mode="projected", fit_exponent=True, warn=False)
    assert fit.report.names[-1] == "log_n"
    np.testing.assert_allclose(np.exp(fit.report.values["log_n"]), 12.0, rtol=1e-6)
    np.testing.assert_allclose(float(fit.material.exponent), 12.0, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(fit.light.position), np.asarray(true.lights[0].position), atol=1e-6)
    for f in ("ka", "kd", "ks"):
        np.testing.assert_allclose(np.asarray(getattr(fit.material, f)), np.asarray(getattr(SHINY, f)), rtol=1e-5)
    assert fit.theta.shape == (3,)


def test_fitted_exponent_with_optimistix():
    """The same problem (one light) through `OptimistixLM`: the exponent in the residual it
    minimises."""
    start, targets, true = _problem(1, occluders=None, material=SHINY, tilted=True)
    guess = js.Material(ka=0.3, kd=0.3, ks=0.3, exponent=5.0)
    fit = inverse.fit_light(start, targets, guess, fit=("position",), starts=1, material_mode="projected",
                            fit_exponent=True, solver=inverse.OptimistixLM(refine=None), warn=False)
    np.testing.assert_allclose(float(fit.material.exponent), 12.0, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(fit.light.position), np.asarray(true.lights[0].position), atol=1e-5)


def test_per_receiver_material_light_is_recovered():
    """Targets painted by `js.shade` with a material given per receiver (each target its own
    $k_d$): `fit_light` with that material finds the light."""
    n = 24
    rng = np.random.default_rng(1)
    per = js.Material(ka=0.1, kd=rng.uniform(0.1, 0.9, (n, 3)), ks=0.0, exponent=1.0)
    start, targets, true = _problem(2, material=per, n=n)
    fit = inverse.fit_light(start, targets, per, fit=("position",), starts=4, solver=inverse.LM(refine=2), warn=False)
    np.testing.assert_allclose(np.asarray(fit.light.position), np.asarray(true.lights[0].position), atol=1e-6)
    assert fit.report.loss < 1e-12 * float(np.sum(np.asarray(targets.colours) ** 2))


def test_projected_material_beside_another_light_is_the_truth():
    """A projected material beside a fixed light: the light and the material that painted the
    targets (one $k_d$ for both lights); with the lights' coefficients apart, $k_d$ would be
    the fitted light's alone and not the truth's."""
    start, targets, true = _problem(2, occluders=None)
    fit = inverse.fit_light(start, targets, GUESS, fit=("position",), starts=4, solver=inverse.LM(refine=2),
                            material_mode="projected", warn=False)
    np.testing.assert_allclose(np.asarray(fit.light.position), np.asarray(true.lights[0].position), atol=1e-6)
    eps = _eps(targets)
    np.testing.assert_allclose(np.asarray(fit.material.kd), np.asarray(MATERIAL.kd), rtol=1e7 * eps)
    np.testing.assert_allclose(np.asarray(fit.material.ka), np.asarray(MATERIAL.ka), rtol=1e7 * eps)


class _GaussNewton(inverse.AbstractLightSolver):
    """A solver of one's own: plain Gauss-Newton from the first start, written on the problem's
    documented methods."""

    refine: int | None = None
    seen: list = None  # type: ignore[assignment]

    def minimise(self, problem, starts):
        self.seen.append(problem)
        th = jnp.asarray(starts[0])
        for _ in range(20):
            r, J = problem.residual_and_jacobian(th)
            th = th - jnp.linalg.lstsq(J, r)[0]
        r, J = (np.asarray(x, np.float64) for x in problem.residual_and_jacobian(th))
        loss = np.array([0.5 * float(r @ r)])
        return _solvers.Solution(np.asarray(th, np.float64)[None], loss, np.array([True]), np.array([20]),
                                 np.array([False]), 0, r, J, problem.lights(th)[0], loss[0], 0, True, problem)


def test_a_solver_of_ones_own_gets_the_lights_problem():
    start, targets, true = _problem(2)
    seen: list = []
    fit = inverse.fit_light(start, targets, MATERIAL, fit=("position",), starts=1, solver=_GaussNewton(seen=seen),
                            warn=False)
    assert len(seen) == 1 and isinstance(seen[0], _multilight.LightsProblem) and seen[0].n_theta == 3
    np.testing.assert_allclose(np.asarray(fit.light.position), np.asarray(true.lights[0].position), atol=1e-8)
    assert fit.report.solver == "" and fit.report.loss < 1e-20


@pytest.mark.parametrize("solver", [inverse.OptimistixLM(refine=2), inverse.LBFGSB(refine=2)],
                         ids=["optimistix", "lbfgsb"])
def test_vectorised_solvers_agree_with_the_lm(solver):
    """Each solver from the same starts on the same problem reaches the LM's answer (the truth)."""
    start, targets, _ = _problem(2)
    param = _param(start, targets, solver)
    y0 = make_starts(param, 3, search_radius=0.5, orientation_spread=0.5, size_spread=0.5, seed=0,
                     dtype=targets.points.dtype)
    problem = _lights._problem(param, start, MATERIAL, targets, None, False, False, False)
    a = inverse.LM(refine=None).minimise(problem, y0)
    b = solver.minimise(problem, y0)
    np.testing.assert_allclose(b.values[b.best], a.values[a.best], rtol=0, atol=1e-6)
    assert b.losses[b.best] < 1e-14 and a.losses[a.best] < 1e-20


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
