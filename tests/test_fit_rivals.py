"""Issue #40: a fit that another distinct placement explains about as well says so
(`inverse._diagnostics.rival_placements`, flag `"competing_placements"`).

A point light over floor targets on a line (y = 0) whose normals tilt about the y axis only:
the mirror image of the light in the plane y = 0 paints every target exactly alike, so the
targets cannot tell the two placements apart; with 1 % noise the global placement refines both.
"""

import math
import warnings

import numpy as np
import pytest

import inverse
import jaxshadow as js
from inverse import _diagnostics as diag
from inverse import _multilight_result as _result

MATERIAL = js.Material(ka=0.2, kd=0.6, ks=0.0, exponent=1.0)
EYE = np.array([0.0, -2.0, 2.0])
TRUE = np.array([0.3, 0.15, 1.2])


def _pose(kind, centre, power=1.0, axis=None):
    return {"kind": kind, "centre": tuple(centre), "axis": axis, "power": power}


def _light_params():
    return {"light0": ("light0.x", "light0.y", "light0.z", "light0.power"),
            "light1": ("light1.x", "light1.y", "light1.z", "light1.rx", "light1.ry", "light1.rz", "light1.power")}


def test_rival_rule():
    """Within the chi-square allowance and far enough (1 % of the scene and 3 standard errors)
    from the answer: a rival; a swap of two lights of one kind is the same answer. A placement
    that only turns a light (by more than 5 degrees and 3 standard errors) is no rival: it
    widens that light's rotation standard errors instead (`rival_turns`)."""
    se = {"light0.x": 0.01, "light0.y": 0.01, "light0.z": 0.01, "light0.power": 0.01,
          "light1.x": 0.01, "light1.y": 0.01, "light1.z": 0.01, "light1.rx": 0.01, "light1.ry": 0.01,
          "light1.rz": 0.01, "light1.power": 0.01}
    down = (0.0, 0.0, -1.0)
    answer = {"light0": _pose("point", [0, 0, 1]), "light1": _pose("polygon", [1, 0, 1], axis=down)}
    n = 11
    allowed = diag.rival_allowance(n)
    assert allowed == pytest.approx(n + 3 * math.sqrt(2 * n))
    tilted = (math.sin(0.2), 0.0, -math.cos(0.2))  # 11.5 degrees
    others = [
        (10.0 + allowed - 1, {"light0": _pose("point", [0.2, 0, 1]), "light1": answer["light1"]}),  # moved: rival
        (10.0 + allowed + 1, {"light0": _pose("point", [0.2, 0, 1]), "light1": answer["light1"]}),  # too poor
        (10.0, {"light0": _pose("point", [0.02, 0, 1]), "light1": answer["light1"]}),  # within 3 se (0.052 m)
        (10.0, {"light0": _pose("point", [0, 0, 1]), "light1": _pose("polygon", [1, 0, 1], axis=tilted)}),  # turned
        (10.0, {"light0": _pose("point", [0, 0, 1]), "light1": _pose("polygon", [1, 0, 1], axis=(0, 0.03, -1))}),
    ]
    out = diag.rival_placements(answer, others, 10.0, n, 4.0, se, _light_params())
    assert [(x[0], x[2]) for x in out] == [(pytest.approx(allowed - 1), ("light0",))]
    turns = diag.rival_turns(answer, others, 10.0, n, se, _light_params())
    assert turns == {"light1": pytest.approx(0.2)}  # the 1.7 degree tilt is within 5 degrees
    wide = diag.turned_widened(se, turns, _light_params())
    assert [wide[f"light1.r{a}"] for a in "xyz"] == [pytest.approx(0.21)] * 3
    assert {k: v for k, v in wide.items() if not k.startswith("light1.r")} == \
        {k: v for k, v in se.items() if not k.startswith("light1.r")}
    # Two point lights swapped are the same placement; an undetermined centre is no rival's reason.
    two = {"light0": _pose("point", [0, 0, 1]), "light2": _pose("point", [1, 1, 1])}
    swapped = {"light0": _pose("point", [1, 1, 1]), "light2": _pose("point", [0, 0, 1])}
    params = {"light0": ("light0.x", "light0.y", "light0.z"), "light2": ("light2.x", "light2.y", "light2.z")}
    se2 = dict.fromkeys(params["light0"] + params["light2"], 0.01)
    assert diag.rival_placements(two, [(0.0, swapped)], 0.0, 6, 4.0, se2, params) == ()
    se2["light0.x"] = math.inf
    moved = {"light0": _pose("point", [0.5, 0, 1]), "light2": two["light2"]}
    assert diag.rival_placements(two, [(0.0, moved)], 0.0, 6, 4.0, se2, params) == ()


def test_mirror_placement_is_flagged():
    """The light and its mirror image in y = 0 explain the noisy targets alike: the answer, one
    of the two, is not trusted, the warning names the light and the other placement."""
    x = np.linspace(-1.0, 1.0, 16)
    pts = np.c_[x, np.zeros(16), np.zeros(16)]
    a = np.linspace(-0.6, 0.6, 16)[np.random.default_rng(0).permutation(16)]
    nrm = np.c_[np.sin(a), np.zeros(16), np.cos(a)]
    true = js.Scene([js.PointLight(TRUE, 3.0)], ambient=0.05)
    col = np.asarray(js.shade(true, MATERIAL, pts, nrm, EYE), np.float64)
    col = col * (1.0 + 0.01 * np.random.default_rng(3).normal(size=col.shape))
    targets = inverse.PaintedTargets(pts, nrm, col, EYE)
    start = js.Scene([js.PointLight([-0.4, 0.1, 1.5], 3.0)], ambient=0.05)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fit = inverse.fit_lights(start, targets, MATERIAL, fit=("position", "power"), noise=0.01 * col)
    q = fit.report.quality
    assert not fit.report.trusted and "competing_placements" in q.flags
    assert q.chi2 < diag.WRONG_MINIMUM_CHI2  # the answer explains the targets: only the rival says no
    got = np.asarray(fit.lights[0].position, np.float64)
    mirror = got * [1.0, -1.0, 1.0]
    assert min(np.linalg.norm(got - TRUE), np.linalg.norm(mirror - TRUE)) < 0.05  # one of the two is the truth
    excess, poses, differ = q.rivals[0]
    assert differ == ("light0",) and abs(excess) <= diag.rival_allowance(len(fit.report.names))
    np.testing.assert_allclose(poses["light0"]["centre"], mirror, atol=0.02)
    assert any(issubclass(w.category, inverse.FitQualityWarning) and "light0" in str(w.message)
               and "other distinct placement" in str(w.message) for w in caught)
    assert "rival placement" in str(fit.report)


def test_rival_rule_per_coordinate():
    """A light whose centre is well determined along x and poorly along y: a placement that moves
    it 5 cm along x (50 standard errors of x, 0.5 of the centre's combined one) is a rival, the
    same move along y is not, and a move of 3 cm along x (30 standard errors, under 1 % of the
    4 m scene) is not either."""
    se = {"light0.x": 0.001, "light0.y": 0.1, "light0.z": 0.001, "light0.power": 0.01}
    params = {"light0": ("light0.x", "light0.y", "light0.z", "light0.power")}
    answer = {"light0": _pose("point", [0, 0, 1])}
    n = 4
    assert 0.05 < diag.RIVAL_SIGMAS * math.sqrt(sum(se[f"light0.{ax}"] ** 2 for ax in "xyz"))  # not by the norm
    along_x = (1.0, {"light0": _pose("point", [0.05, 0, 1])})
    along_y = (1.0, {"light0": _pose("point", [0, 0.05, 1])})
    near_x = (1.0, {"light0": _pose("point", [0.03, 0, 1])})
    out = diag.rival_placements(answer, [along_x, along_y, near_x], 0.0, n, 4.0, se, params)
    assert [(x[0], x[1]["light0"]["centre"], x[2]) for x in out] == [(1.0, (0.05, 0, 1), ("light0",))]


def test_same_placement_is_no_rival():
    """The same placement written otherwise is no rival and turns nothing: two segments and two
    quads of one kind dealt to each other, a segment's ends swapped (its direction reversed), a
    quad's vertices listed from another corner (its normal unchanged); a quad facing up instead
    of down is turned (180 degrees: one-sided, it lights the other side)."""
    kinds = {"light0": "linear", "light1": "linear", "light2": "polygon", "light3": "polygon"}
    params = {nm: tuple(f"{nm}.{p}" for p in ("x", "y", "z", "ru", "rv", "power")) for nm in kinds}
    se = {p: 0.01 for ps in params.values() for p in ps}
    centres = {"light0": (0, 0, 1), "light1": (1, 0, 1), "light2": (0, 1, 1.5), "light3": (1, 1, 1.5)}
    axes = {"light0": (1, 0, 0), "light1": (0, 1, 0), "light2": (0, 0, -1), "light3": (0, 0, -1)}
    answer = {nm: _pose(kinds[nm], centres[nm], axis=axes[nm]) for nm in kinds}
    dealt = {"light0": answer["light1"], "light1": answer["light0"], "light2": answer["light3"],
             "light3": answer["light2"]}
    reversed_ends = {**answer, "light0": _pose("linear", centres["light0"], axis=(-1, 0, 0))}
    # a quad's pose (`_multilight_result._pose`) from its vertices listed from another corner
    v = np.array([[-0.1, -0.1, 1.5], [-0.1, 0.1, 1.5], [0.1, 0.1, 1.5], [0.1, -0.1, 1.5]])
    kind = type("Param", (), {"kind": "polygon"})()
    quad = _result._pose(js.PolygonLight(v, [1.0, 1.0, 1.0]), kind, 1.0)
    rolled = _result._pose(js.PolygonLight(np.roll(v, 1, axis=0), [1.0, 1.0, 1.0]), kind, 1.0)
    np.testing.assert_allclose(rolled["centre"], quad["centre"], atol=1e-12)
    np.testing.assert_allclose(rolled["axis"], quad["axis"], atol=1e-12)
    np.testing.assert_allclose(quad["axis"], (0, 0, -1), atol=1e-12)
    others = [(0.0, dealt), (0.5, reversed_ends), (1.0, dict(answer))]
    assert diag.rival_placements(answer, others, 0.0, 24, 4.0, se, params) == ()
    assert diag.rival_turns(answer, others, 0.0, 24, se, params) == {}
    flipped = {**answer, "light3": _pose("polygon", centres["light3"], axis=(0, 0, 1))}
    assert diag.rival_turns(answer, [(0.0, flipped)], 0.0, 24, se, params) == {"light3": pytest.approx(math.pi)}
    # a genuinely distinct placement still competes: a segment moved 10 cm (10 standard errors)
    moved = {**answer, "light1": _pose("linear", (1.1, 0, 1), axis=axes["light1"])}
    out = diag.rival_placements(answer, [(0.0, dealt), (2.0, moved)], 0.0, 24, 4.0, se, params)
    assert [(x[0], x[2]) for x in out] == [(2.0, ("light1",))]


def test_estimated_noise_distances_at_the_assumed_noise():
    """With the noise estimated the standard errors take the residual's scale, the chi-square the
    assumed noise's: the rival rule measures distances at the larger (`at_assumed_noise`). A
    light 16 cm off an exact fit (residual variance 1e-30, standard errors 1e-14 m) at the
    assumed noise's row variance 1e-4 is 1.6 of its 0.1 m standard errors away: no rival; at a residual
    above the assumed noise the errors stand."""
    se = {"light0.x": 1e-14, "light0.y": 1e-14, "light0.z": 1e-14, "light0.power": 0.0}
    wide = diag.at_assumed_noise(se, 1e-30, 1e-4)
    assert wide["light0.z"] == pytest.approx(0.1) and wide["light0.power"] == 0.0
    assert diag.at_assumed_noise(se, 1e-3, 1e-4) is se
    assert diag.at_assumed_noise(se, 0.0, 1e-4)["light0.power"] == math.inf
    params = {"light0": ("light0.x", "light0.y", "light0.z", "light0.power")}
    answer = {"light0": _pose("point", [0, 0, 1])}
    higher = [(0.05, {"light0": _pose("point", [0, 0, 1.16])})]
    assert diag.rival_placements(answer, higher, 0.0, 4, 4.0, se, params)  # at the residual's scale
    assert diag.rival_placements(answer, higher, 0.0, 4, 4.0, wide, params) == ()
