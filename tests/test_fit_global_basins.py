"""The global placement's refine-then-rank (`inverse._global_placement`, step 7): competing
placements are ranked by their loss after a short joint refinement, not by their screened loss.

Two point lights of nearly the same colour over 40 floor targets (noise-free). Placement A has
them swapped (each at the other's true position): the grey powers almost make up for the colour,
so its screened loss is the lower one; placement B has each light 8 % of the scene off the
truth. Ranked by the screened loss (the placement before refine-then-rank) A wins, and from A
the refinement stays in A's basin; refined first, B reaches the truth and wins."""

import numpy as np
import pytest
from position_problems import position_problem

import jaxshadow as js
from inverse._global_placement import BASIN_DISTANCE, distinct_basins, refine_and_rank
from inverse._multilight import screen
from inverse._parametrisation import LightParametrisation

MATERIAL = js.Material(ka=0.2, kd=0.6, ks=0.0, exponent=1.0)
TRUE = js.Scene([js.PointLight([-0.6, 0.2, 1.5], [3.0, 3.0, 3.0]), js.PointLight([0.7, -0.3, 1.2], [2.5, 3.0, 3.5])],
                ambient=0.1)
LM = {"rtol": 1e-8, "atol": 1e-12}


@pytest.fixture(scope="module")
def two_basins():
    # the parameters are the centre's offset from the true light over the scene size: 0 is the truth
    problem, params, _, size = position_problem(TRUE, MATERIAL, "sigmoid")
    p0, p1 = (np.asarray(light.position, np.float64) for light in TRUE.lights)
    u = np.random.default_rng(0).normal(size=(2, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    swapped = np.r_[p1 - p0, p0 - p1] / size
    near = 0.08 * u.reshape(-1)
    return problem, params, size, np.stack([swapped, near])


def test_screened_ranking_picks_the_wrong_basin(two_basins):
    """The premise: by the screened loss the swapped placement wins, and refined alone it stays
    far from the truth (what the placement returned when it ranked at grid resolution)."""
    problem, _, size, rows = two_basins
    f, problem, _ = screen(problem, rows, rows[0], np.ones(6, bool), 2)
    assert f[0] < f[1]
    values, losses, _ = refine_and_rank(problem, rows[:1], LM, 2)
    assert losses[0] > 1e-6
    assert np.max(np.abs(values[0])) * size > 0.5  # m: still about swapped


def test_refine_then_rank_finds_the_truth(two_basins):
    problem, params, size, rows = two_basins
    assert distinct_basins(params, (0, 3), rows, size, 16) == [0, 1]
    values, losses, _ = refine_and_rank(problem, rows, LM, 2)
    best = int(np.argmin(losses))
    assert best == 1
    assert losses[best] < 1e-20 and losses[0] > 1e6 * losses[best]
    np.testing.assert_allclose(values[best] * size, 0.0, atol=1e-9)  # m


def test_distinct_basins_keeps_one_row_per_basin():
    """Rows closer than `BASIN_DISTANCE` of the extent in every light (and within `BASIN_TURN` in
    orientation) are one basin: the first of them is kept, in the given order, at most k."""
    size = 4.0
    params = tuple(LightParametrisation(light, i, ("position",), None, size, "sigmoid")
                   for i, light in enumerate(TRUE.lights))
    step = BASIN_DISTANCE * size / size  # the parameters are in scene-size units
    rows = np.array([[0, 0, 0, 0, 0, 0], [0.5 * step, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 1.5 * step],
                     [2 * step, 0, 0, 0, 0, 0], [np.nan, 0, 0, 0, 0, 0]], np.float64)
    assert distinct_basins(params, (0, 3), rows, size, 16) == [0, 2, 3]
    assert distinct_basins(params, (0, 3), rows, size, 2) == [0, 2]


def test_noisy_success_criterion():
    """`benchmarks.fit_global.noisy_verdict`: within 3 reported standard errors succeeds; beyond,
    only a fit flagged undetermined that the truth does not beat by more than n + 3 sqrt(2n) in
    chi-square."""
    from benchmarks.fit_global import noisy_verdict

    sigma, n = 0.1, 8  # allowed excess: 8 + 3 * 4 = 20
    fit = np.full((10, 3), 0.1)  # chi2 30
    truth_close, truth_far = np.full((10, 3), 0.05), np.zeros((10, 3))  # chi2 7.5 (excess 22.5), 0
    ok = lambda *a: noisy_verdict(*a)["noisy_success"]  # noqa: E731
    assert ok([0.5, -2.9], [], fit, truth_far, sigma, n)
    assert not ok([0.5, 3.1], [], fit, truth_far, sigma, n)
    assert not ok([], [], fit, fit, sigma, n)  # no finite standard error: not "within"
    assert ok([0.5, 3.1], ["undetermined"], fit, np.full((10, 3), 0.08), sigma, n)  # excess 10.8
    assert not ok([0.5, 3.1], ["undetermined"], fit, truth_close, sigma, n)
    assert not ok([0.5, 3.1], ["collapsed"], fit, fit, sigma, n)
