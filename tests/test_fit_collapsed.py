"""A fit whose own answer is a degenerate light (a polygon with a zero-length edge or coincident
vertices, a segment of zero length) comes back flagged `collapsed`, evaluated as no light, and
does not raise (issue #40: `js.shade` rejected the fitted quad of a demo fit with `ValueError`).

The degenerate answers are forced: `fit_light` runs a solver whose answer is the start with one
log size at -40 (a side of e^-40 of its length: its vertices coincide in float64), and
`fit_lights` has its last step before the final evaluation (`_moved_outside`) return such a
pose, so the final evaluation sees exactly what a collapsing solve would hand it.
"""

import contextlib

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import inverse
import jaxshadow as js
from inverse import _diagnostics as diag
from inverse import _fit_lights, _solvers

MATERIAL = js.Material(ka=0.2, kd=0.6, ks=0.0, exponent=1.0)
EYE = np.array([0.0, -2.0, 2.0])
COLLAPSED_LOG_SIZE = -40.0


def _quad(c, h):
    """A square of half side `h` centred at `c`, facing down (-z)."""
    return np.array([[c[0] - h, c[1] - h, c[2]], [c[0] - h, c[1] + h, c[2]],
                     [c[0] + h, c[1] + h, c[2]], [c[0] + h, c[1] - h, c[2]]])


def _targets(scene, n=30):
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    return inverse.PaintedTargets(pts, nrm, js.shade(scene, MATERIAL, pts, nrm, EYE), EYE)


QUAD_SCENE = js.Scene([js.PolygonLight(_quad([0.2, 0.1, 1.5], 0.2), 5.0)], ambient=0.05)


def _shade(scene, material, targets):
    return np.asarray(js.shade(scene, material, targets.points, targets.normals, targets.eye), np.float64)


# --------------------------------------------------------------------------------------
# The rule
# --------------------------------------------------------------------------------------


def test_invalid_reason_is_what_jaxshadow_rejects():
    quad = js.PolygonLight(_quad([0.0, 0.0, 1.0], 0.3), 2.0)
    assert diag.invalid_reason(quad) is None
    v = np.asarray(quad.vertices)
    cases = {
        "zero-length edge": np.array([v[0], v[1], v[1], v[2], v[3]]),   # a repeated vertex
        "at least 3 distinct": np.array([v[0], v[0], v[2], v[2]]),      # a quad shrunk to a segment
        "zero area": np.array([v[0], 0.5 * (v[0] + v[2]), v[2]]),       # collinear
    }
    for words, bad in cases.items():
        light = eqx.tree_at(lambda x: x.vertices, quad, jnp.asarray(bad))
        why = diag.invalid_reason(light)
        assert why is not None and words in why
        with pytest.raises(ValueError, match="vertices"):   # what the fit must not hand to js.shade
            js.shade(js.Scene([light]), MATERIAL, np.zeros((1, 3)), [[0.0, 0.0, 1.0]], EYE)
    seg = js.LinearLight([0.0, 0.0, 1.0], [0.5, 0.0, 1.0], 1.0, "cosine", 3)
    assert diag.invalid_reason(seg) is None
    assert "zero-length segment" in diag.invalid_reason(eqx.tree_at(lambda x: x.end, seg, seg.start))
    point = js.PointLight([0.0, 0.0, 1.0], 1.0)
    assert diag.invalid_reason(point) is None
    assert "non-finite" in diag.invalid_reason(eqx.tree_at(lambda x: x.position, point, jnp.array([np.nan, 0.0, 1.0])))
    assert diag.invalid_reason(js.DirectionalLight([0.0, 0.0, -1.0], 1.0)) is None


def test_without_invalid_lights_is_the_scene_with_them_at_zero_contribution():
    good = js.PointLight([0.3, 0.1, 1.2], 2.0)
    bad = eqx.tree_at(lambda x: x.vertices, js.PolygonLight(_quad([0.0, 0.0, 1.0], 0.3), 2.0),
                      jnp.asarray(np.repeat(_quad([0.0, 0.0, 1.0], 0.3)[:2], 2, axis=0)))
    scene = js.Scene([bad, good], ambient=0.05)
    t = _targets(js.Scene([good], ambient=0.05))
    out = diag.without_invalid_lights(scene)
    assert len(out.lights) == 1 and isinstance(out.lights[0], js.PointLight)
    np.testing.assert_array_equal(out.lights[0].position, good.position)
    np.testing.assert_allclose(_shade(out, MATERIAL, t), _shade(js.Scene([good], ambient=0.05), MATERIAL, t))
    valid = js.Scene([good], ambient=0.05)
    assert diag.without_invalid_lights(valid) is valid


def _assess(lights, targets):
    names = tuple(f"{nm}.x" for nm in lights)
    return diag.assess(targets=targets, residual=np.zeros(targets.colours.shape), noise=None, n_params=len(names),
                       names=names, std_errors=dict.fromkeys(names, 0.1), values=dict.fromkeys(names, 0.0),
                       determined=dict.fromkeys(names, True), scale=2.0, lights=lights,
                       light_params={nm: (f"{nm}.x",) for nm in lights}, messages=[])


def test_assess_degenerate_lights_are_collapsed_and_escaped_only_by_where_they_are():
    """A quad that ran off to 1e15 m (its vertices rounded onto two points) is escaped and
    collapsed; one rounded flat near the targets is collapsed only (a zero-area polygon faces
    nowhere, so "faces away from every target" is no reason); a NaN one is collapsed only."""
    t = _targets(QUAD_SCENE)
    quad = js.PolygonLight(_quad([0.0, 0.0, 1.0], 0.3), 2.0)
    far = eqx.tree_at(lambda x: x.vertices, quad, jnp.asarray(_quad([1e15, 0.0, 1e15], 0.03)))
    near = eqx.tree_at(lambda x: x.vertices, quad, jnp.asarray(np.repeat(_quad([0.0, 0.0, 1.0], 0.3)[:2], 2, axis=0)))
    nan = eqx.tree_at(lambda x: x.vertices, quad, jnp.full((4, 3), np.nan))
    assert diag.invalid_reason(far) is not None
    assert diag.escape_reason(near, t) == "it faces away from every target"  # what the facing test says
    quality, determined = _assess({"far": far, "near": near, "nan": nan, "ok": quad}, t)
    assert set(quality.collapsed) == {"far", "near", "nan"} and set(quality.escaped) == {"far"}
    assert "more than 10 times" in quality.escaped["far"]
    assert determined == {"far.x": False, "near.x": False, "nan.x": False, "ok.x": True}
    assert not quality.trusted and {"collapsed", "escaped"} <= set(quality.flags)


# --------------------------------------------------------------------------------------
# fit_light (and the joint light + material fit) on a collapsed answer
# --------------------------------------------------------------------------------------


class _Collapsing(_solvers.AbstractLightSolver):
    """A solver whose answer is its first start with the light's first log size at -40."""

    refine: int | None = None

    def minimise(self, problem, starts):
        names = problem.params[0].names
        th = np.asarray(starts[0], np.float64).copy()
        th[names.index("log_sx" if "log_sx" in names else "log_length")] = COLLAPSED_LOG_SIZE
        th = jnp.asarray(th, starts.dtype)
        r, J = problem.residual_and_jacobian(th)
        light = problem.lights(th)[0]
        r = np.asarray(r, np.float64)
        return _solvers.Solution(np.asarray(th, np.float64)[None], np.array([0.5 * float(r @ r)]), np.array([True]),
                                 np.array([1]), np.array([False]), 0, r, np.asarray(J, np.float64), light,
                                 0.5 * float(r @ r), 0, True, problem)


def _assert_collapsed(quality, name, rec=None):
    assert "collapsed" in quality.flags and "escaped" not in quality.flags and name not in quality.escaped
    assert "no valid light" in quality.collapsed[name] and "zero contribution" in quality.collapsed[name]
    assert not quality.trusted and f"{name} collapsed" in " ".join(quality.emitted)
    if rec is not None:  # warned about
        assert any(str(r.message).startswith(f"{name} collapsed") for r in rec)


@pytest.mark.parametrize("mode", ["fixed", "projected"])
def test_fit_light_collapsed_answer_is_flagged_not_raised(mode):
    """The projected mode evaluated the fitted quad with `js.shade` (ValueError before); the
    fixed mode called its zero-area quad escaped ("faces away from every target")."""
    t = _targets(QUAD_SCENE)
    with pytest.warns(inverse.FitQualityWarning) as rec:
        fit = inverse.fit_light(QUAD_SCENE, t, MATERIAL, fit=("position", "size"), starts=1, solver=_Collapsing(),
                                material_mode=mode)
    assert diag.invalid_reason(fit.light) is not None
    _assert_collapsed(fit.report.quality, "light0", rec)
    assert not any(fit.report.determined[nm] for nm in fit.parametrisation.names)
    # Evaluated as no light: the ambient term of the fitted material alone.
    expected = _shade(js.Scene([], ambient=0.05), fit.material, t) - np.asarray(t.colours, np.float64)
    assert np.all(np.isfinite(fit.residual))
    np.testing.assert_allclose(fit.residual, expected, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("method", ["projected", "alternate"])
def test_fit_light_and_material_collapsed_light_is_flagged_not_raised(method):
    """The material half fitted at the collapsed light (js.irradiance raised before): at no light."""
    t = _targets(QUAD_SCENE)
    deprecated = pytest.warns(DeprecationWarning, match="alternate") if method == "alternate" else contextlib.nullcontext()
    with pytest.warns(inverse.FitQualityWarning) as rec, deprecated:
        joint = inverse.fit_light_and_material(QUAD_SCENE, t, MATERIAL, method=method, rounds=3,
                                               light_kwargs={"fit": ("position", "size"), "starts": 1,
                                                             "solver": _Collapsing()})
    lrep, mrep = joint.report
    _assert_collapsed(lrep.quality, "light0", rec)
    assert len(joint.history) == 2  # the alternation stops: no light to place again from
    assert np.all(np.isfinite(joint.residual)) and np.all(np.isfinite(np.asarray(joint.material.ka)))


# --------------------------------------------------------------------------------------
# fit_lights with several lights
# --------------------------------------------------------------------------------------


def test_fit_lights_collapsed_polygon_and_segment_are_flagged_not_raised(monkeypatch):
    """A quad, a segment and a point light; the fit's final pose has the quad's first side and
    the segment's length at e^-40 of theirs: both flagged collapsed (not escaped), the point
    light not; the residual is the point light's alone (at its fitted power)."""
    true = js.Scene([js.PolygonLight(_quad([0.2, 0.1, 1.5], 0.2), 5.0),
                     js.LinearLight([-0.6, -0.4, 1.3], [-0.2, -0.4, 1.3], 2.0),
                     js.PointLight([-0.5, 0.4, 1.2], 2.0)], ambient=0.05)
    t = _targets(true, 40)
    moved = _fit_lights._moved_outside

    def collapse(problem, theta):
        theta = np.array(moved(problem, theta), np.float64)
        for j in (0, 1):
            p = problem.params[j]
            theta[problem.offsets[j] + p._slices()["size"].start] = COLLAPSED_LOG_SIZE
        return theta

    monkeypatch.setattr(_fit_lights, "_moved_outside", collapse)
    with pytest.warns(inverse.FitQualityWarning) as rec:
        fit = inverse.fit_lights(true, t, MATERIAL, fit=("position", "size", "power"), starts=1, sweeps=1,
                                 placement="local")
    q = fit.report.quality
    assert set(q.collapsed) == {"light0", "light1"} and "escaped" not in q.flags
    for nm in ("light0", "light1"):
        _assert_collapsed(q, nm, rec)
        assert not any(v for k, v in fit.report.determined.items() if k.startswith(nm + ".") and "power" not in k)
    assert diag.invalid_reason(fit.lights[0]) is not None and diag.invalid_reason(fit.lights[1]) is not None
    assert diag.invalid_reason(fit.lights[2]) is None
    # The collapsed lights shine as no light: the point light (at its fitted power) and the ambient term.
    rest = js.Scene([fit.lights[2]], ambient=0.05)
    expected = _shade(rest, MATERIAL, t) - np.asarray(t.colours, np.float64)
    assert np.all(np.isfinite(fit.residual))
    np.testing.assert_allclose(fit.residual, expected, rtol=1e-8, atol=1e-10)
    # The fitted scene, with its collapsed lights taken out, is one js.shade accepts.
    np.testing.assert_allclose(_shade(diag.without_invalid_lights(fit.scene), MATERIAL, t) - t.colours, fit.residual,
                               rtol=1e-8, atol=1e-10)


# --------------------------------------------------------------------------------------
# A collapse within the noise (`_multilight_result.collapse_within_noise`)
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("relative_noise", [1e-2, 1e-7])
def test_collapse_within_the_noise_is_a_loose_size_not_a_flag(relative_noise):
    """A quad 0.6 mm by 0.4 m (under 1 % of the scene wide) 1.5 m over 40 floor targets, fitted
    from itself: at 1 % noise the same quad widened to 10 % of the scene
    (`COLLAPSE_WIDTH_FRACTION`) paints the targets within the noise, so its size is reported
    not determined and the fit is trusted; told a noise of 1e-7 the widening is many standard
    deviations away and the collapse stays flagged."""
    quad = _quad([0.2, 0.1, 1.5], 0.2) * np.array([1.0, 0.0015, 1.0]) + np.array([0.0, 0.1, 0.0])
    true = js.Scene([js.PolygonLight(quad, 5.0)], ambient=0.05)
    t = _targets(true, 40)
    size = inverse.scene_size(true, t)
    assert "narrowest width" in diag.collapse_reason(true.lights[0], size)
    noise = relative_noise * np.abs(np.asarray(t.colours, np.float64))
    fit = inverse.fit_lights(true, t, MATERIAL, fit=("position", "size", "power"), starts=1, sweeps=1,
                             placement="local", noise=noise, warn=False)
    q = fit.report.quality
    if relative_noise > 1e-3:
        assert "collapsed" not in q.flags and set(q.loose_size) == {"light0"} and q.trusted
        assert 0.0 <= q.loose_size["light0"] < 1.0
        assert not fit.report.determined["light0.log_sy"] or not fit.report.determined["light0.log_sx"]
        assert any("size is not determined" in w for w in fit.report.warnings)
    else:
        assert "collapsed" in q.flags and not q.loose_size and not q.trusted
