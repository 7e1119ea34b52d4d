"""`inverse.design_targets` (where to paint targets so the report's standard errors are small),
`fit_lights(search_targets=...)` and the fitted material's colour-free projection.

The Jacobian the design uses is checked against central differences of `js.shade` (the public
forward model, not the design's code); the targets are painted by `js.shade` from a hidden truth.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import inverse
import jaxshadow as js
from benchmarks.inverse_scenes import THREE_LIGHTS_EYE as EYE
from benchmarks.inverse_scenes import floor_receivers, near_light_candidates, quad
from inverse._design import candidate_jacobian, predicted_std_errors

MATERIAL = js.Material(ka=[0.3, 0.25, 0.2], kd=[0.6, 0.5, 0.4], ks=0.0, exponent=1.0)
QUAD = js.PolygonLight(quad([-0.4, 0.3, 1.6], 0.5, 0.3, (np.pi + 0.1, 0.05, 0.4)), [5.0, 4.5, 4.0])
POINT = js.PointLight([0.6, -0.2, 1.3], [1.5, 1.4, 1.3])
OCCLUDER = [quad([0.0, 0.0, 0.6], 0.4, 0.4, (0.0, 0.0, 0.3))]
SCENE = js.Scene([QUAD, POINT], occluders=OCCLUDER, ambient=0.1)


def _moved(scene, j, d):
    """`scene` with light `j` translated by `d (3,)`."""
    lights = list(scene.lights)
    x = lights[j]
    lights[j] = (js.PolygonLight(np.asarray(x.vertices) + d, x.radiance) if isinstance(x, js.PolygonLight)
                 else js.PointLight(np.asarray(x.position) + d, x.intensity))
    return js.Scene(lights, occluders=scene.occluders, ambient=scene.ambient)


def _scaled(scene, j, f):
    lights = list(scene.lights)
    x = lights[j]
    lights[j] = (js.PolygonLight(x.vertices, np.asarray(x.radiance) * f) if isinstance(x, js.PolygonLight)
                 else js.PointLight(x.position, np.asarray(x.intensity) * f))
    return js.Scene(lights, occluders=scene.occluders, ambient=scene.ambient)


def test_design_jacobian_matches_central_differences_of_shade():
    """The design's rows (positions in scene sizes, powers as factors) against `js.shade` of moved
    and brightened lights, at floor receivers in and around the occluder's soft shadow."""
    pts, nrm = floor_receivers(12, seed=3)
    pts[:6, :2] = np.random.default_rng(0).uniform(-0.5, 0.5, (6, 2))  # in and around the penumbrae
    size = 4.0
    jac, colours, names, scales = candidate_jacobian(SCENE, MATERIAL, pts, nrm, EYE, size=size)
    shade = lambda s: np.asarray(js.shade(s, MATERIAL, pts, nrm, EYE))  # noqa: E731
    np.testing.assert_allclose(colours, shade(SCENE), rtol=1e-12)
    h = 1e-5
    for j in (0, 1):
        for a, c in enumerate("xyz"):
            d = np.zeros(3)
            d[a] = h * size
            fd = (shade(_moved(SCENE, j, d)) - shade(_moved(SCENE, j, -d))) / (2 * h)
            col = jac[:, :, names.index(f"light{j}.{c}")]
            np.testing.assert_allclose(col, fd, atol=1e-6 * np.max(np.abs(fd)) + 1e-9, rtol=1e-4)
        fd = (shade(_scaled(SCENE, j, 1 + h)) - shade(_scaled(SCENE, j, 1 - h))) / (2 * h)
        np.testing.assert_allclose(jac[:, :, names.index(f"light{j}.power")], fd, rtol=1e-7, atol=1e-12)
    assert scales[names.index("light0.x")] == size and scales[names.index("light0.rx")] == 1.0


def test_designed_targets_lower_the_standard_errors():
    """Far floor targets leave the quad's orientation, size and power poorly determined; the design
    (keeping 6 of them, adding 10 from receivers near the lights) lowers every group's worst
    standard error, judged by the rows at the truth."""
    fp, fn = floor_receivers(40, seed=1)
    cp, cn = near_light_candidates([np.asarray(QUAD.vertices).mean(axis=0), np.asarray(POINT.position)],
                                   radii=(0.3, 0.6), drops=(0.2, 0.5), n_around=6)
    pts, nrm = np.concatenate([fp, cp]), np.concatenate([fn, cn])
    d = inverse.design_targets(SCENE, MATERIAL, (pts, nrm), 16, EYE, keep=np.arange(6), size=4.0)
    assert d.points.shape == (16, 3) and list(d.indices[:6]) == list(range(6)) and len(set(d.indices)) == 16
    jac, colours, names, scales = candidate_jacobian(SCENE, MATERIAL, pts, nrm, EYE, size=4.0)
    se_design = predicted_std_errors(jac[d.indices], colours[d.indices], 0.01) * scales
    se_floor = predicted_std_errors(jac[:16], colours[:16], 0.01) * scales
    np.testing.assert_allclose(se_design, [d.std_errors[n] for n in names], rtol=1e-9)
    # The criterion (every standard error over its default tolerance, squared, summed) and the worst
    # orientation, size and power errors drop (positions, already well determined, may rise a little).
    tol = {"x": 0.012, "y": 0.012, "z": 0.012, "rx": np.radians(0.3), "ry": np.radians(0.3), "rz": np.radians(0.3),
           "log_sx": 0.01, "log_sy": 0.01, "power": 0.006}
    w = np.array([1 / tol[n.split(".")[1]] ** 2 for n in names])
    assert np.sum(w * se_design**2) < 0.1 * np.sum(w * se_floor**2)
    for group in (("rx", "ry", "rz"), ("log_sx", "log_sy"), ("power",)):
        pick = [i for i, n in enumerate(names) if n.split(".")[1] in group]
        assert np.max(se_design[pick]) < 0.5 * np.max(se_floor[pick]), group
    with pytest.raises(ValueError, match="n must be"):
        inverse.design_targets(SCENE, MATERIAL, (pts, nrm), 0, EYE)
    with pytest.raises(ValueError, match="candidates"):
        inverse.design_targets(SCENE, MATERIAL, (pts[:, :2], nrm), 4, EYE)


def _problem(scene, targets, material, colour_free):
    from inverse._fit_lights import _groups_for
    from inverse._multilight import LightsProblem

    size = inverse.scene_size(scene, targets)
    params, offsets, off = [], [], 0
    for i, light in enumerate(scene.lights):
        params.append(inverse.LightParametrisation(light, i, _groups_for(light, ("position", "power")), None, size,
                                                   "sigmoid"))
        offsets.append(off)
        off += params[-1].size
    z = jnp.zeros(targets.points.shape, jnp.float64)
    return LightsProblem(tuple(params), tuple(scene.lights), scene, material, targets, z, z, tuple(offsets), True,
                         False, False, None, 64, colour_free=colour_free), off


def _colour_free_case(scene):
    pts, nrm = floor_receivers(30, seed=2)
    t = inverse.PaintedTargets(pts, nrm, js.shade(scene, MATERIAL, pts, nrm, EYE), EYE)
    wrong = js.Material(ka=[0.2, 0.2, 0.2], kd=[0.5, 0.5, 0.5], ks=[0.0, 0.0, 0.0], exponent=1.0)
    return t, wrong


def test_colour_free_residual_is_zero_at_the_truth_for_any_material():
    """With the material projected per channel, the true poses explain noise-free targets whatever
    material the problem holds; the structured residual at that wrong material does not."""
    from inverse._multilight import projected_residual

    scene = js.Scene([POINT, js.PointLight([-0.5, 0.4, 1.5], [3.0, 2.5, 2.0])], occluders=OCCLUDER, ambient=0.1)
    t, wrong = _colour_free_case(scene)
    free, n = _problem(scene, t, wrong, True)
    structured, _ = _problem(scene, t, wrong, False)
    zero = jnp.zeros(n)
    assert np.max(np.abs(np.asarray(projected_residual(zero, free, 64)[0]))) < 1e-12
    assert np.max(np.abs(np.asarray(projected_residual(zero, structured, 64)[0]))) > 1e-3


@pytest.mark.slow
def test_colour_free_residual_gradient_matches_central_differences():
    """Its forward-mode Jacobian in the lights' positions against central differences, through
    the occluder's soft shadow (30 s: the compile)."""
    from inverse._multilight import projected_residual

    t, wrong = _colour_free_case(SCENE)
    free, n = _problem(SCENE, t, wrong, True)
    fn = jax.jit(lambda th: projected_residual(th, free, 64)[0])
    theta = jnp.asarray(np.random.default_rng(1).normal(0.0, 0.02, n))
    J = np.asarray(jax.jit(jax.jacfwd(fn))(theta))
    h = 1e-6
    fd = np.stack([(np.asarray(fn(theta.at[i].add(h))) - np.asarray(fn(theta.at[i].add(-h)))) / (2 * h)
                   for i in range(n)], axis=1)
    np.testing.assert_allclose(J, fd, atol=2e-6 * np.max(np.abs(fd)), rtol=1e-4)


def test_material_recovered_with_two_lights_placed_from_a_subset_of_targets():
    """Two point lights placed from 0.25 m away at wrong powers with the material fitted (light 0's
    power known: it sets the scale of k_d p); the search uses half the targets
    (`search_targets`), the refinement all: positions, the other power and k_a, k_d exact."""
    true = js.Scene([js.PointLight([-0.6, 0.2, 1.5], [4.0, 3.0, 2.0]), js.PointLight([0.7, -0.3, 1.2], [1.0, 1.5, 2.5])],
                    ambient=0.1)
    start = js.Scene([js.PointLight([-0.45, 0.0, 1.6], [4.0, 3.0, 2.0]),
                      js.PointLight([0.55, -0.1, 1.35], [1.5, 2.25, 3.75])], ambient=0.1)
    pts, nrm = floor_receivers(40, seed=2)
    t = inverse.PaintedTargets(pts, nrm, js.shade(true, MATERIAL, pts, nrm, EYE), EYE)
    guess = js.Material(ka=0.2, kd=0.5, ks=0.0, exponent=1.0)
    fit = inverse.fit_lights(start, t, guess, fit=("position", "power"), starts=2, sweeps=1,
                             material_mode="projected", search_targets=np.arange(0, 40, 2))
    for got, want in zip(fit.lights, true.lights, strict=True):
        np.testing.assert_allclose(got.position, want.position, atol=1e-6)
        np.testing.assert_allclose(got.intensity, want.intensity, rtol=1e-6)
    np.testing.assert_allclose(fit.material.ka, MATERIAL.ka, atol=1e-7)
    np.testing.assert_allclose(fit.material.kd, MATERIAL.kd, atol=1e-7)
    assert fit.report.determined["kd[g]"] and fit.report.loss < 1e-20
    with pytest.raises(ValueError, match="search_targets"):
        inverse.fit_lights(start, t, guess, search_targets=np.array([40]))
    with pytest.raises(ValueError, match="mask must have shape"):
        inverse.fit_lights(start, t, guess, search_targets=np.ones(3, bool))
    with pytest.raises(ValueError, match="selects no target"):
        inverse.fit_lights(start, t, guess, search_targets=np.zeros(40, bool))
