"""Issue #40: a fit that another distinct placement explains about as well says so
(`inverse._diagnostics.rival_placements`, flag `"competing_placements"`).

A point light over floor targets on a line (y = 0) whose normals tilt about the y axis only:
the mirror image of the light in the plane y = 0 paints every target exactly alike, so the
targets cannot tell the two placements apart; with 1 % noise the global placement refines both.
"""

import math
import warnings

import jax.numpy as jnp
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


def _line_targets(noise: float) -> inverse.PaintedTargets:
    """16 targets on the x axis (y = z = 0) with normals in the xz plane, painted by a point
    light at TRUE, with relative Gaussian noise `noise`: a light and its mirror image in y = 0
    explain them alike."""
    x = np.linspace(-1.0, 1.0, 16)
    pts = np.c_[x, np.zeros(16), np.zeros(16)]
    a = np.linspace(-0.6, 0.6, 16)[np.random.default_rng(0).permutation(16)]
    nrm = np.c_[np.sin(a), np.zeros(16), np.cos(a)]
    true = js.Scene([js.PointLight(TRUE, 3.0)], ambient=0.05)
    col = np.asarray(js.shade(true, MATERIAL, pts, nrm, EYE), np.float64)
    if noise:
        col = col * (1.0 + noise * np.random.default_rng(3).normal(size=col.shape))
    return inverse.PaintedTargets(pts, nrm, col, EYE)


def test_mirror_placement_is_flagged():
    """The light and its mirror image in y = 0 explain the noisy targets alike: the answer, one
    of the two, is not trusted, the warning names the light and the other placement."""
    targets = _line_targets(noise=0.01)
    start = js.Scene([js.PointLight([-0.4, 0.1, 1.5], 3.0)], ambient=0.05)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fit = inverse.fit_lights(start, targets, MATERIAL, fit=("position", "power"),
                                 noise=0.01 * np.asarray(targets.colours))
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


def test_estimated_noise_rivals_at_the_residual_scale():
    """With the noise estimated the rival chi-square takes the residual's scale, the one the
    standard errors take (`_multilight_result._chi2_at_residual`): the answer's chi-square is its
    degrees of freedom; a placement whose weighted residual sum of squares exceeds the answer's
    by less than the allowance times the residual's variance competes, one just beyond does not.
    After an exact fit (a residual of rounding size) a placement 0.14 % RMS off the targets is
    no rival (at the assumed 2.5 % noise it would be one), while another exact placement is."""
    rng = np.random.default_rng(0)
    colours, w = rng.uniform(0.2, 1.0, (60, 3)), np.ones((60, 3))
    m, n = colours.size, 20
    allowed = diag.rival_allowance(n)
    params = {"light0": ("light0.x", "light0.y", "light0.z", "light0.power")}
    answer = {"light0": _pose("point", [0, 0, 1])}
    far = {"light0": _pose("point", [0.5, 0, 1.5])}

    def rivals(r_answer, r_rival, sigma2):
        chi2_of = _result._chi2_at_residual(w, sigma2, colours, n)
        se = {"light0.x": 0.01, "light0.y": 0.01, "light0.z": 0.01, "light0.power": 0.01}
        return diag.rival_placements(answer, [(chi2_of(r_rival), far)], chi2_of(r_answer), n, 4.0, se, params)

    noisy = 0.01 * rng.normal(size=colours.shape)
    s2 = float(np.sum(noisy ** 2)) / (m - n)
    assert _result._chi2_at_residual(w, s2, colours, n)(noisy) == pytest.approx(m - n)
    for excess, competes in ((allowed - 1.0, True), (allowed + 1.0, False)):
        rival = noisy * math.sqrt(1.0 + excess * s2 / float(np.sum(noisy ** 2)))
        assert bool(rivals(noisy, rival, s2)) is competes
    exact = 1e-15 * rng.normal(size=colours.shape)
    s2 = float(np.sum(exact ** 2)) / (m - n)
    near = 0.0014 * math.sqrt(float(np.mean(colours ** 2))) * rng.choice([-1.0, 1.0], colours.shape)
    assert not rivals(exact, near, s2)
    assert rivals(exact, 30.0 * exact, s2)  # both exact (at the fit's exact level), each at its own rounding
    assumed = (0.025 * math.sqrt(float(np.mean(colours ** 2)))) ** 2
    assert float(np.sum(near ** 2)) / assumed < allowed  # within the allowance at the assumed noise


def test_mirror_placement_noise_free_is_flagged():
    """Noise-free targets on the line: the given pose's local search fits them exactly, so the
    search never places the light again, yet its mirror image in y = 0 fits them exactly too:
    the report adds that placement (`inverse._mirror`) and flags the answer."""
    targets = _line_targets(noise=0.0)
    start = js.Scene([js.PointLight([-0.4, 0.1, 1.5], 3.0)], ambient=0.05)
    fit = inverse.fit_lights(start, targets, MATERIAL, fit=("position", "power"), warn=False)
    q = fit.report.quality
    got = np.asarray(fit.lights[0].position, np.float64)
    np.testing.assert_allclose(got, TRUE, atol=1e-6)  # exact, in the truth's basin
    assert not fit.report.trusted and "competing_placements" in q.flags
    excess, poses, differ = q.rivals[0]
    assert differ == ("light0",) and abs(excess) <= diag.rival_allowance(len(fit.report.names))
    np.testing.assert_allclose(poses["light0"]["centre"], TRUE * [1.0, -1.0, 1.0], atol=1e-6)
    assert fit.report.std_errors["light0.y"] >= 0.3 - 1e-6  # widened over the mirror (2 x 0.15 m)


def test_mirrored_parameters():
    """`inverse._mirror`: the symmetry plane of targets on a line (normals in the plane through
    it), none for targets spread over a floor; the parameters of a segment, a quad and a point
    light mirrored across it build the reflected lights (a quad's winding kept facing its
    reflected normal)."""
    from inverse import _mirror
    from inverse._parametrisation import LightParametrisation

    x = np.linspace(-1.0, 1.0, 7)
    line = np.c_[x, 0.5 * x, np.zeros(7)]
    tilt = np.c_[0.2 * np.sin(x), 0.1 * np.sin(x), np.ones(7)]
    plane = _mirror.symmetry_plane(line, tilt)
    assert plane is not None
    np.testing.assert_allclose(abs(plane[1] @ np.array([1.0, -2.0, 0.0]) / math.sqrt(5.0)), 1.0, atol=1e-12)
    rng = np.random.default_rng(1)
    assert _mirror.symmetry_plane(np.c_[rng.uniform(-1, 1, (7, 2)), np.zeros(7)], tilt) is None
    assert _mirror.symmetry_plane(line, tilt, eye=np.array([0.0, -2.0, 2.0])) is None  # the eye off the plane
    seg = js.LinearLight(np.array([0.1, 0.4, 1.2]), np.array([0.5, 0.6, 1.3]), 2.0)
    u, v = np.array([0.4, 0.1, 0.05]), np.array([-0.1, 0.4, 0.0])
    quad = js.PolygonLight(np.array([0.0 * u, v, 1.5 * u + v, 1.5 * u]) + [0.0, 0.0, 1.5], 1.0)  # a rectangle, facing down
    kite = js.PolygonLight(np.array([[0.0, 0.0, 1.5], [0.4, 0.1, 1.55], [0.35, 0.5, 1.5], [-0.05, 0.4, 1.45]]), 1.0)
    p = LightParametrisation(kite, 0, ("position", "orientation"), None, 4.0, "sigmoid")
    assert _mirror.mirrored_theta(p, np.zeros(p.size), kite, plane) is None  # its mirror image is no rotation of it
    point = js.PointLight(np.array([0.2, 0.7, 1.1]), 1.0)
    groups = ("position", "orientation", "size")
    for light, fit in ((seg, groups), (quad, groups), (point, ("position",))):
        p = LightParametrisation(light, 0, fit, None, 4.0, "sigmoid")
        th = 0.05 * rng.normal(size=p.size)  # a fitted pose off the template
        fitted = p.build(jnp.asarray(th))
        new = _mirror.mirrored_theta(p, th, fitted, plane)
        assert new is not None
        back = p.build(jnp.asarray(new))
        if isinstance(light, js.LinearLight):
            ends = [np.asarray(fitted.start), np.asarray(fitted.end)]
            np.testing.assert_allclose(np.asarray(back.start), _mirror.reflect(ends[0], plane), atol=1e-9)
            np.testing.assert_allclose(np.asarray(back.end), _mirror.reflect(ends[1], plane), atol=1e-9)
        elif isinstance(light, js.PolygonLight):
            v, b = np.asarray(fitted.vertices), np.asarray(back.vertices)
            ref = _mirror.reflect(v, plane)[::-1]
            assert min(np.max(np.abs(np.roll(ref, s, axis=0) - b)) for s in range(4)) < 1e-9
        else:
            np.testing.assert_allclose(np.asarray(back.position), _mirror.reflect(np.asarray(fitted.position), plane),
                                       atol=1e-12)


def test_mirror_placement_shadowed_is_no_rival(monkeypatch):
    """The same line of targets with a box that shadows four of them from the light: its mirror
    image is evaluated (the targets still have their symmetry plane) but the box does not shadow
    it alike, so it misses the shadowed targets and does not compete: the exact answer stays
    trusted."""
    from benchmarks.inverse_random_scenes import box_faces

    x = np.linspace(-1.0, 1.0, 16)
    pts = np.c_[x, np.zeros(16), np.zeros(16)]
    a = np.linspace(-0.6, 0.6, 16)[np.random.default_rng(0).permutation(16)]
    nrm = np.c_[np.sin(a), np.zeros(16), np.cos(a)]
    box = box_faces(np.array([0.0, 0.02, 0.5]), np.array([0.3, 0.12, 0.6]))
    true = js.Scene([js.PointLight(TRUE, 3.0)], occluders=box, ambient=0.05)
    col = np.asarray(js.shade(true, MATERIAL, pts, nrm, EYE), np.float64)
    unshadowed = np.asarray(js.shade(js.Scene([js.PointLight(TRUE, 3.0)], ambient=0.05), MATERIAL, pts, nrm, EYE))
    assert np.sum(np.abs(col - unshadowed).max(axis=1) > 1e-6) == 4
    rows = []
    mirrored = _result.mirrored_rows
    monkeypatch.setattr(_result, "mirrored_rows", lambda *a: rows.append(mirrored(*a)) or rows[-1])
    start = js.Scene([js.PointLight([-0.4, 0.1, 1.5], 3.0)], occluders=box, ambient=0.05)
    fit = inverse.fit_lights(start, inverse.PaintedTargets(pts, nrm, col, EYE), MATERIAL, fit=("position", "power"),
                             warn=False)
    np.testing.assert_allclose(np.asarray(fit.lights[0].position, np.float64), TRUE, atol=1e-6)
    assert len(rows) == 1 and rows[0].shape[0] == 1  # the mirror image was checked
    assert fit.report.trusted and not fit.report.quality.rivals
