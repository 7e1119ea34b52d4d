"""One inverse stack: `fit_light` and `fit_lights` share their search options (`inverse.Search`),
their constraint dictionary, their solver objects, their fit type (`LightFit` is a `LightsFit`
of one light) and their capacity retry (`_forward.at_capacity`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import inverse
import jaxshadow as js
from inverse._forward import MAX_CAPACITY, at_capacity
from inverse._options import STARTS_ONE_LIGHT, STARTS_PER_LIGHT, Search, search_options

MATERIAL = js.Material(ka=0.2, kd=0.6, ks=0.0, exponent=1.0)


@pytest.fixture(scope="module")
def point_problem():
    """One point light over 24 floor targets (painted by `js.shade`), a start 0.3 m off."""
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-1, 1, (24, 2)), np.zeros(24)]
    normals, eye = np.tile([0.0, 0.0, 1.0], (24, 1)), np.array([0.0, -2.0, 2.0])
    true = js.Scene([js.PointLight([0.2, 0.3, 2.0], 3.0)], ambient=0.05)
    targets = inverse.PaintedTargets(points, normals, js.shade(true, MATERIAL, points, normals, eye), eye)
    start = js.Scene([js.PointLight([0.0, 0.0, 1.8], 3.0)], ambient=0.05)
    return start, targets


def test_search_defaults_and_keywords():
    one = search_options(None, {}, "fit_light", several=False)
    several = search_options(None, {}, "fit_lights", several=True)
    assert (one.starts, several.starts) == (STARTS_ONE_LIGHT, STARTS_PER_LIGHT) == (64, 16)
    # keywords replace the fields of the object given
    s = search_options(Search(starts=5, seed=3, search_radius=0.2), {"seed": 7}, "fit_lights", several=True)
    assert (s.starts, s.seed, s.search_radius) == (5, 7, 0.2)
    with pytest.raises(TypeError, match="unexpected keyword"):
        search_options(None, {"strats": 4}, "fit_lights", several=True)
    with pytest.raises(ValueError, match="starts must be >= 1"):
        search_options(Search(starts=0), {}, "fit_light", several=False)
    with pytest.raises(ValueError, match="placement must be"):
        search_options(None, {"placement": "near"}, "fit_lights", several=True)
    with pytest.raises(ValueError, match="search must be an inverse.Search"):
        search_options({"starts": 4}, {}, "fit_lights", several=True)


@pytest.mark.parametrize("option", [{"sweeps": 3}, {"grid": 4}, {"placement": "local"},
                                    {"search_targets": np.arange(3)}])
def test_fit_light_refuses_the_options_of_several_lights(point_problem, option):
    start, targets = point_problem
    with pytest.raises(ValueError, match="apply to several lights"):
        inverse.fit_light(start, targets, MATERIAL, fit=("position",), starts=2, **option)


def test_fit_light_constraints(point_problem):
    start, targets = point_problem
    with pytest.raises(ValueError, match="not fitted"):
        inverse.fit_light(start, targets, MATERIAL, fit=("position",), constraints={1: inverse.Plane([0, 0, 2.0], [0, 0, 1.0])})
    with pytest.raises(ValueError, match="budget"):
        inverse.fit_light(start, targets, MATERIAL, fit=("position",), constraints={"budget": 10.0})
    outside = inverse.Outside([0, 1, 2, 3, 4, 5])
    with pytest.raises(ValueError, match="Plane or inverse.Box"):
        inverse.fit_light(start, targets, MATERIAL, fit=("position",), constraints={0: outside})


def test_search_object_keywords_and_deprecated_constraint_give_the_same_fit(point_problem):
    """`search=Search(...)` and its fields as keywords are the same search; `constraint=c` (deprecated)
    is `constraints={light_index: c}`: bit for bit the same light."""
    start, targets = point_problem
    plane = inverse.Plane([0.0, 0.0, 2.0], [0.0, 0.0, 1.0])
    solver = inverse.LM(refine=2, max_steps=30)
    a = inverse.fit_light(start, targets, MATERIAL, fit=("position",), search=Search(starts=3, seed=4),
                          constraints={0: plane}, solver=solver)
    b = inverse.fit_light(start, targets, MATERIAL, fit=("position",), starts=3, seed=4, constraints={0: plane},
                          solver=solver)
    with pytest.warns(DeprecationWarning, match="constraints="):
        c = inverse.fit_light(start, targets, MATERIAL, fit=("position",), starts=3, seed=4, constraint=plane,
                              solver=solver)
    for f in (b, c):
        np.testing.assert_array_equal(np.asarray(f.light.position), np.asarray(a.light.position))
        np.testing.assert_array_equal(f.report.start_losses, a.report.start_losses)
    # a different seed stratifies other starts: the check above can fail
    d = inverse.fit_light(start, targets, MATERIAL, fit=("position",), starts=3, seed=5, constraints={0: plane},
                          solver=solver)
    assert not np.array_equal(d.report.start_losses, a.report.start_losses)


def test_light_fit_is_a_lights_fit_of_one_light(point_problem):
    start, targets = point_problem
    f = inverse.fit_light(start, targets, MATERIAL, fit=("position",), starts=2, solver=inverse.LM(refine=None))
    assert isinstance(f, inverse.LightsFit) and isinstance(f.report, inverse.FitReport)
    assert f.lights == (f.light,) and f.parametrisations == (f.parametrisation,)
    np.testing.assert_array_equal(f.powers, [1.0])
    np.testing.assert_array_equal(f.theta, f.report.theta[:f.parametrisation.size])
    np.testing.assert_array_equal(np.asarray(f.scene.lights[0].position), np.asarray(f.light.position))


def test_fit_lights_takes_lm_only(point_problem):
    start, targets = point_problem
    with pytest.raises(ValueError, match="solver must be an inverse.LM"):
        inverse.fit_lights(start, targets, MATERIAL, fit=("position",), starts=2, solver=inverse.LBFGSB())


@dataclasses.dataclass(frozen=True)
class _Problem:
    capacity: int | None


def test_at_capacity_doubles_until_no_receiver_overflows():
    seen = []

    def run(pr):
        seen.append(pr.capacity)
        return pr.capacity * 10, pr.capacity < 40   # overflows below 40 edges

    out, pr, retries = at_capacity(run, _Problem(8), "fit_x", "solve")
    assert seen == [8, 16, 32, 64] and (out, pr.capacity, retries) == (640, 64, 3)
    # no capacity (every receiver against every occluder): one run, whatever the flag says
    out, pr, retries = at_capacity(lambda pr: ("all", True), _Problem(None), "fit_x", "solve")
    assert (out, pr.capacity, retries) == ("all", None, 0)


def test_at_capacity_gives_up_at_the_most_edges():
    with pytest.raises(RuntimeError, match=f"fit_x: .* more than {MAX_CAPACITY} boundary edges during the screening; hint"):
        at_capacity(lambda pr: (None, True), _Problem(MAX_CAPACITY // 4), "fit_x", "screening", "; hint")
