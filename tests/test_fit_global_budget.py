"""Refine-then-rank under a power budget (`inverse._global_placement.refine_and_rank`,
`final_losses`): placements are ranked by the loss the final fit can reach there, with the
powers it solves ($p \\ge 0$ and the budget), not by the LM's own projection of the powers.

Two point lights over 40 floor targets (noise-free, painted by `js.shade`), a budget of 2/3 of
the truth's emitted power. The LM projects the powers by signed least squares, put on the
budget's plane when it exceeds it: placement A (both lights high up, far from the truth) meets
the budget there with one light's power negative and reaches a loss 0.031, below what any
placement can reach with powers >= 0 (0.052 near the truth); its final loss is 1.28. Placement B
is each light 8 % of the scene off the truth."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import lsq_linear, nnls

import inverse
import jaxshadow as js
from benchmarks.inverse_scenes import THREE_LIGHTS_EYE as EYE
from benchmarks.inverse_scenes import floor_receivers
from inverse import _global_placement
from inverse._global_placement import BASIN_STEPS, refine_and_rank
from inverse._multilight import LightsProblem, screen, solve
from inverse._multilight_placement import pad
from inverse._parametrisation import LightParametrisation

MATERIAL = js.Material(ka=0.2, kd=[0.6, 0.5, 0.4], ks=0.0, exponent=1.0)
TRUE = js.Scene([js.PointLight([-0.6, 0.2, 1.5], 4.0), js.PointLight([0.7, -0.3, 1.2], 2.0)], ambient=0.1)
BUDGET = 2 / 3 * 4 * np.pi * 6.0  # W: a point light emits 4 pi I
LM = {"rtol": 1e-8, "atol": 1e-12}
FAR = np.array([[0.1346, 0.3092, 2.2024], [0.4508, 0.9635, 2.7469]])  # m: placement A's lights


def _targets():
    pts, nrm = floor_receivers(40, seed=2)
    return inverse.PaintedTargets(pts, nrm, js.shade(TRUE, MATERIAL, pts, nrm, EYE), EYE)


def _constrained_loss(positions, t):
    """$\\tfrac12|r|^2$ with the best powers $p \\ge 0$, $c \\cdot p \\le B$ for point lights of the
    truth's intensities at `positions (2, 3)`, independently of the fit: NNLS when it keeps the
    budget, else the bounded one-variable problem on the budget's segment (scipy)."""
    kd = np.asarray(MATERIAL.kd)
    cols = [(kd / np.pi * np.asarray(js.irradiance(js.Scene([js.PointLight(x, light.intensity)]), t.points,
                                                   t.normals))).reshape(-1)
            for x, light in zip(positions, TRUE.lights, strict=True)]
    A = np.stack(cols, axis=1)
    y = (np.asarray(t.colours) - 0.2 * 0.1).reshape(-1)
    c = 4 * np.pi * np.array([float(np.asarray(light.intensity)[0]) for light in TRUE.lights])
    p = nnls(A, y)[0]
    if c @ p > BUDGET:  # on the segment c . p = B: p2 = (B - c1 p1) / c2, 0 <= p1 <= B / c1
        s = lsq_linear((A[:, 0] - c[0] / c[1] * A[:, 1])[:, None], y - BUDGET / c[1] * A[:, 1],
                       bounds=(0.0, BUDGET / c[0]), tol=1e-15, method="bvls").x[0]
        p = np.array([s, (BUDGET - c[0] * s) / c[1]])
    r = A @ p - y
    return 0.5 * float(r @ r)


@pytest.fixture(scope="module")
def budget_basins():
    t = _targets()
    size = inverse.scene_size(TRUE, t)
    # the parameters are the centre's offset from the true light over the scene size: 0 is the truth
    params = tuple(LightParametrisation(light, i, ("position",), None, size, "sigmoid")
                   for i, light in enumerate(TRUE.lights))
    z = jnp.zeros((len(t), 3))
    problem = LightsProblem(params, tuple(TRUE.lights), TRUE, MATERIAL, t, z, z, (0, 3), True, False, False, None,
                            budget=jnp.asarray(BUDGET))
    truth = np.stack([np.asarray(light.position, np.float64) for light in TRUE.lights])
    u = np.random.default_rng(0).normal(size=(2, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    rows = np.stack([((FAR - truth) / size).reshape(-1), 0.08 * u.reshape(-1)])
    return problem, t, size, truth, rows


def test_the_lm_projection_ranks_the_budget_breaking_placement_first(budget_basins):
    """The premise: by the LM's own loss A wins, screened and after the short refinement, but
    with powers >= 0 under the budget it explains the targets far worse than B."""
    problem, t, size, truth, rows = budget_basins
    f, problem, _ = screen(problem, rows, rows[0], np.ones(6, bool), 2)
    assert f[0] < f[1]
    res, _, _ = solve(problem, pad(rows, 2), rows[0], np.ones(6, bool), max_steps=BASIN_STEPS, prune=(), **LM)
    lm_losses = np.asarray(res.losses)
    assert lm_losses[0] < lm_losses[1]
    reachable = [_constrained_loss(truth + np.asarray(v).reshape(2, 3) * size, t) for v in np.asarray(res.values)[:2]]
    assert reachable[0] > 10 * reachable[1]
    assert lm_losses[0] < 0.9 * min(reachable)  # below anything the final powers reach: a negative power


def test_refine_then_rank_under_a_budget_ranks_by_the_final_loss(budget_basins):
    problem, t, size, truth, rows = budget_basins
    values, losses, _ = refine_and_rank(problem, rows, LM, 2)
    assert int(np.argmin(losses)) == 1
    for v, f in zip(values, losses, strict=True):  # each loss is the one the final fit reaches there
        np.testing.assert_allclose(f, _constrained_loss(truth + v.reshape(2, 3) * size, t), rtol=1e-6)


def test_a_budget_fit_runs_refine_then_rank(monkeypatch):
    """`fit_lights` under a budget ranks its placements by refinement (the global placement's
    step 7) and ends no worse than the true poses can do under the budget (the budget-breaking
    ranking ended at 25 times that)."""
    calls = []

    def spy(problem, thetas, lm, batch, *stop):
        out = refine_and_rank(problem, thetas, lm, batch, *stop)
        calls.append(out[1])
        return out

    monkeypatch.setattr(_global_placement, "refine_and_rank", spy)
    t = _targets()
    start = js.Scene([js.PointLight([-0.45, 0.05, 1.6], 3.0), js.PointLight([0.55, -0.15, 1.35], 3.0)], ambient=0.1)
    with pytest.warns(inverse.FitQualityWarning):  # the budget cannot paint these targets
        fit = inverse.fit_lights(start, t, MATERIAL, fit=("position", "power"), starts=4, sweeps=1,
                                 constraints={"budget": 2 / 3 * 4 * np.pi * 3.0 * 2.0})
    assert calls and len(calls[0]) > 1
    at_truth = _constrained_loss(np.stack([np.asarray(light.position) for light in TRUE.lights]), t)
    assert fit.report.loss <= at_truth * (1 + 1e-6)
