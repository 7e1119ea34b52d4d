"""jaxshadow.testing: the statistics (on synthetic data with known truth), the catalogue's stored
references (against the library's values and float64 central differences), the parameter
moves, and the pytest plugin. The Mitsuba demonstrations are in test_testing_mitsuba.py."""

from __future__ import annotations

import json
import os

import jax.numpy as jnp
import numpy as np
import pytest

import jaxshadow as js
from _jaxshadow_pytest import SCENES
from jaxshadow.testing import (
    LIGHT_TRANSLATION,
    PARAMETERS,
    assert_gradient_matches,
    assert_values_match,
    catalogue,
    compare,
    false_alarm_bound,
)
from jaxshadow.testing._catalogue import DATA, build_spec, classify
from jaxshadow.testing._scenes import BUILDERS, apply_parameters, parameters_of
from jaxshadow.testing._stats import bonferroni_reject, clopper_pearson, holm_reject

pytest_plugins = ["pytester"]

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# ----------------------------------------------------------------------------- statistics


def test_holm_matches_its_definition():
    p = np.array([0.01, 0.04, 0.03, 0.005, 0.5])
    # Sorted: 0.005 <= .05/5, 0.01 <= .05/4, 0.03 > .05/3 -> stop: two rejections.
    assert holm_reject(p, 0.05).tolist() == [True, False, False, True, False]
    assert bonferroni_reject(p, 0.05).tolist() == [True, False, False, True, False]
    assert holm_reject(np.array([0.001, 0.002, 0.003]), 0.01).all()  # 0.003 <= 0.01 / 1
    assert not bonferroni_reject(np.array([0.001, 0.002, 0.004]), 0.01)[2]


def _false_alarms(rng, trials, alpha, shape, *, correlated=False, batches=None, **kw):
    """Number of comparisons (out of `trials`) that fail on unbiased synthetic estimates."""
    count = 0
    truth = rng.uniform(0.5, 2.0, size=shape)
    sigma = rng.uniform(0.01, 0.1, size=shape)
    for _ in range(trials):
        if batches is None:
            noise = rng.standard_normal(shape[:-1] + (1,)) if correlated else rng.standard_normal(shape)
            est, err, dof = truth + sigma * noise, sigma, None
        else:
            draws = truth + sigma * np.sqrt(batches) * rng.standard_normal((batches,) + shape)
            est, err = draws.mean(axis=0), draws.std(axis=0, ddof=1) / np.sqrt(batches)
            dof = batches - 1
        count += not compare(est, err, truth, alpha=alpha, dof=dof, rtol=0.0, **kw).passed
    return count


@pytest.mark.parametrize("method", ["holm", "bonferroni"])
def test_false_alarm_rate_within_alpha_on_gaussian_data(method):
    rng = np.random.default_rng(1)
    trials, alpha = 1000, 0.05
    bound = false_alarm_bound(trials, alpha)
    for correlated in (False, True):  # independent channels; channels sharing one sample
        k = _false_alarms(rng, trials, alpha, (16, 3), correlated=correlated, method=method)
        print(f"{method}, correlated={correlated}: {k} false alarms in {trials} at alpha {alpha}")
        assert k <= bound, (method, correlated, k, bound)


def test_batch_standard_errors_need_their_degrees_of_freedom():
    rng = np.random.default_rng(2)
    trials, alpha, batches = 600, 0.05, 5
    k_t = _false_alarms(rng, trials, alpha, (8, 3), batches=batches)
    assert k_t <= false_alarm_bound(trials, alpha)
    # The same data judged as if the standard errors were exact: far too many alarms.
    k_z = 0
    truth = np.ones((8, 3))
    for _ in range(trials):
        draws = truth + 0.1 * rng.standard_normal((batches, 8, 3))
        est, err = draws.mean(axis=0), draws.std(axis=0, ddof=1) / np.sqrt(batches)
        k_z += not compare(est, err, truth, alpha=alpha, rtol=0.0).passed
    assert k_z > 3 * false_alarm_bound(trials, alpha)


def test_a_biased_point_is_named_with_its_sigmas():
    rng = np.random.default_rng(3)
    truth = rng.uniform(1.0, 2.0, (16, 3))
    err = np.full((16, 3), 0.01)
    est = truth + err * rng.standard_normal((16, 3)).clip(-2, 2)
    est[5, 1] += 0.08  # 8 sigma
    with pytest.raises(AssertionError) as info:
        assert_values_match(est, err, truth, alpha=1e-3)
    msg = str(info.value)
    assert "1 of 48 entries" in msg and "point 5, G" in msg and "sigma" in msg
    z = float(msg.split("point 5, G")[1].split("sigma")[0].split(":")[-1])
    assert 6.0 < z < 10.0


def test_a_small_bias_everywhere_is_caught_by_the_chi_square():
    rng = np.random.default_rng(4)
    truth = np.ones((200, 3))
    err = np.full((200, 3), 0.01)
    noise = rng.standard_normal((200, 1)) * err  # channels share samples
    res = compare(truth + noise + 0.006, err, truth, alpha=1e-3)  # 0.6 sigma everywhere
    assert not res.rejected.any() and res.chi2_rejected and not res.passed
    assert compare(truth + noise, err, truth, alpha=1e-3).passed


def test_allowances_and_deterministic_estimates():
    ref = np.array([[1.0, 2.0, 0.0]])
    # Zero standard error: exact up to the allowance passes, beyond it fails with infinite z.
    assert_values_match(ref * (1 + 5e-6), 0.0, ref, rtol=1e-5)
    res = compare(ref + 1e-3, 0.0, ref)
    assert not res.passed and np.isinf(res.z).all()
    assert compare(ref + 1e-3, 0.0, ref, atol=2e-3).passed
    # A NaN estimate fails.
    assert not compare(np.array([[np.nan, 2.0, 0.0]]), 0.1, ref).passed


@pytest.mark.parametrize(
    "bad",
    [
        dict(alpha=0.0),
        dict(alpha=1.5),
        dict(method="sidak"),
        dict(dof=0),
        dict(stderr=-1.0),
        dict(reference=np.full((2, 3), np.inf)),
        dict(stderr=np.ones((3, 3))),
    ],
)
def test_bad_arguments_raise(bad):
    args = dict(estimate=np.ones((2, 3)), stderr=0.1, reference=np.ones((2, 3)))
    args.update({k: v for k, v in bad.items() if k in args})
    opts = {k: v for k, v in bad.items() if k not in args}
    with pytest.raises(ValueError):
        compare(args["estimate"], args["stderr"], args["reference"], **opts)


def test_gradient_comparison_by_name_and_scale():
    ref = {"light.tx": np.array([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]]), "light.ty": np.full((2, 3), 1e-3)}
    err = {k: np.full((2, 3), 1e-4) for k in ref}
    assert_gradient_matches(ref, err, ref)
    # The relative allowance is of the parameter's largest |derivative|: 1e-5 of 1 covers the
    # zero entry's round-off, not a 1e-3 error.
    est = {k: v.copy() for k, v in ref.items()}
    est["light.tx"][1] += 5e-6
    assert_gradient_matches(est, {k: 0 * v for k, v in err.items()}, ref)
    est["light.ty"][0, 2] += 2e-3
    with pytest.raises(AssertionError, match=r"d/d light.ty, point 0, B"):
        assert_gradient_matches(est, err, ref)
    # Arrays with a parameter axis and names give the same verdict.
    names = list(ref)
    stack = lambda d: np.stack([d[k] for k in names])  # noqa: E731
    with pytest.raises(AssertionError, match=r"d/d light.ty"):
        assert_gradient_matches(stack(est), stack(err), stack(ref), parameters=names)
    with pytest.raises(ValueError):
        assert_gradient_matches(stack(est)[:1], stack(err), stack(ref), parameters=names)


def test_gradient_chi_square_per_parameter():
    """Parameters share their samples (fully correlated noise): the per-parameter chi-square
    tests (Bonferroni) keep the false-alarm rate, and a small bias of one parameter is caught."""
    rng = np.random.default_rng(5)
    names = ["light.tx", "light.ty", "light.tz"]
    ref = rng.uniform(-1.0, 1.0, (3, 64, 3))
    err = np.full(ref.shape, 0.02)
    trials, alpha, alarms = 500, 0.05, 0
    for _ in range(trials):
        noise = rng.standard_normal((1, 64, 1))
        res = compare(ref + err * noise, err, ref, alpha=alpha, rtol=0.0, correlated_axes=(2,), chi2_axis=0, prefix=names)
        alarms += not res.passed
    assert alarms <= false_alarm_bound(trials, alpha)
    est = ref + err * rng.standard_normal((1, 64, 1))
    est[1] += 1.5 * err[1]  # d/d light.ty biased by 1.5 sigma at every point: no single test sees it
    with pytest.raises(AssertionError, match=r"light.ty: .* \(p = ") as info:
        assert_gradient_matches(est, err, ref, parameters=names)
    assert "0 of 576 entries" in str(info.value) and "chi-square" in str(info.value)


def test_false_alarm_bound_and_interval():
    assert false_alarm_bound(200, 0.05) in range(18, 24)  # mean 10, sd 3.1
    lo, hi = clopper_pearson(10, 200)
    assert lo < 0.05 < hi and 0.02 < lo and hi < 0.1


# ----------------------------------------------------------------------------- the catalogue


def test_catalogue_lists_the_scenes_of_the_issue():
    assert list(catalogue) == list(BUILDERS) == list(SCENES)
    assert len(catalogue) == 8 and set(catalogue()) == set(SCENES)
    assert catalogue("umbra") is catalogue["umbra"]
    with pytest.raises(KeyError, match="no catalogue scene"):
        catalogue["nowhere"]
    with open(DATA) as fh:
        data = json.load(fh)
    assert data["parameters"] == PARAMETERS


def test_scenes_show_what_their_names_say():
    counts = {name: {c: int(np.sum(catalogue[name].classes == c)) for c in ("lit", "penumbra", "umbra")} for name in catalogue}
    assert counts["unoccluded"]["lit"] == 16 and counts["grazing"]["lit"] == 16
    assert counts["penumbra"]["penumbra"] == 16 and counts["highlight"]["penumbra"] == 16
    assert counts["umbra"]["umbra"] >= 6 and counts["umbra"]["penumbra"] >= 4
    assert counts["touching"]["penumbra"] >= 4 and counts["touching"]["lit"] >= 4
    assert counts["linear"]["penumbra"] >= 8 and counts["mesh"]["penumbra"] >= 8
    umbra = catalogue["umbra"]
    dark = umbra.classes == "umbra"
    assert np.all(umbra.irradiance[dark] == 0) and all(np.all(d[dark] == 0) for d in umbra.d_irradiance.values())
    # The grazing light reaches below every receiver's horizon.
    assert np.asarray(catalogue["grazing"].scene.lights[0].vertices)[:, 2].min() < 0
    # The touching wall stands on the receiver plane.
    assert np.asarray(catalogue["touching"].scene.occluders)[0, :, 2].min() == 0.0
    hl = catalogue["highlight"]
    assert np.max(hl.radiance[:, 0] - hl.irradiance[:, 0] * np.asarray(hl.material.kd)[0] / np.pi) > 0.3
    assert catalogue["mesh"].scene.occluder_topology is not None


@pytest.mark.parametrize("name", list(BUILDERS))
def test_stored_scene_is_the_defined_scene(name):
    """The stored geometry is what `_scenes.py` defines (no silent drift of either)."""
    ref, spec = catalogue[name], build_spec(name)
    assert js.scene_to_dict(ref.scene, ref.material) == js.scene_to_dict(spec.scene, spec.material)
    np.testing.assert_array_equal(ref.points, spec.window.grid(4))
    np.testing.assert_array_equal(ref.eye, spec.eye)
    assert ref.parameters == parameters_of(spec.scene)
    assert ref.classes.tolist() == classify(ref.scene, ref.points, ref.normals).tolist()


def test_plain_arrays():
    for name in catalogue:
        ref = catalogue[name]
        a = ref.arrays()
        assert all(isinstance(v, np.ndarray) and v.dtype == np.float64 for v in a.values())
        assert a["points"].shape == a["normals"].shape == a["irradiance"].shape == (16, 3)
        assert ("light_vertices" in a) != ("light_start" in a)
        assert ("occluders" in a) == (ref.scene.occluders is not None)
        for p in ref.parameters:
            assert a[f"d_radiance/{p}"].shape == (16, 3)
            assert (f"d_irradiance/{p}" in a) == (not p.startswith("material."))
        assert ref.gradient("radiance").shape == (len(ref.parameters), 16, 3)
    with pytest.raises(ValueError):
        catalogue["unoccluded"].perturbed("occluder.tx", 1e-3)


def test_parameter_moves():
    ref = catalogue["penumbra"]
    v = np.asarray(ref.scene.lights[0].vertices)
    c = v.mean(axis=0)
    move = lambda p, t: np.asarray(ref.perturbed(p, t)[0].lights[0].vertices)  # noqa: E731
    np.testing.assert_array_equal(move("light.tx", 0.0), v)
    np.testing.assert_allclose(move("light.ty", 0.25), v + [0.0, 0.25, 0.0], rtol=0, atol=1e-15)
    r = move("light.rz", np.pi / 2)  # a quarter turn about z through the centre
    np.testing.assert_allclose(r - c, (v - c)[:, [1, 0, 2]] * [-1.0, 1.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(move("light.scale", 1.0) - c, 2.0 * (v - c), atol=1e-15)
    occ = np.asarray(ref.perturbed("occluder.tz", 0.1)[0].occluders) - np.asarray(ref.scene.occluders)
    np.testing.assert_allclose(occ, np.broadcast_to([0.0, 0.0, 0.1], occ.shape), atol=1e-15)
    mat = ref.perturbed("material.kd", 0.1)[1]
    np.testing.assert_allclose(np.asarray(mat.kd), np.asarray(ref.material.kd) + 0.1)
    seg = catalogue["linear"]
    light = seg.perturbed("light.rx", 0.3)[0].lights[0]
    mid = lambda lt: (np.asarray(lt.start) + np.asarray(lt.end)) / 2  # noqa: E731
    np.testing.assert_allclose(mid(light), mid(seg.scene.lights[0]), atol=1e-15)
    with pytest.raises(ValueError, match="unknown parameter"):
        apply_parameters(ref.scene, ref.material, ("light.warp",), jnp.zeros(1))


def _live(ref, scene, material, quantity):
    if quantity == "irradiance":
        return np.asarray(js.irradiance(scene, ref.points, ref.normals), np.float64)
    return np.asarray(js.shade(scene, material, ref.points, ref.normals, ref.eye, method="exact"), np.float64)


# The exact specular compiles for a few seconds per scene structure (and runs ~0.1 s per call):
# CI checks the radiance of one scene (its material derivatives included), the rest is slow.
CI_RADIANCE = ("penumbra",)


def _cases(known_bugs=frozenset()):
    out = []
    for name in BUILDERS:
        for quantity in ("irradiance", "radiance"):
            marks = []
            if quantity == "radiance" and name not in CI_RADIANCE:
                marks.append(pytest.mark.slow)
            if (name, quantity) in known_bugs:
                marks.append(pytest.mark.xfail(strict=True, reason="wrong derivative of the exact specular at a grazing receiver"))
            out.append(pytest.param(name, quantity, marks=marks, id=f"{name}-{quantity}"))
    return out


@pytest.mark.parametrize("name,quantity", _cases())
def test_stored_values_are_the_library_values(name, quantity):
    ref = catalogue[name]
    stored = getattr(ref, quantity)
    live = _live(ref, ref.scene, ref.material, quantity)
    np.testing.assert_allclose(stored, live, rtol=1e-12, atol=1e-14 * np.abs(stored).max())


# Central differences in float64, Richardson-extrapolated from steps H and H/2 (truncation
# O(H^4)); their rounding error is about 1e-16 |f| / H ~ 1e-11 |f|. Agreement is required to
# RTOL relative to max(|fd|, floor), the floor being 1 % of the parameter's largest |derivative|
# or 0.1 % of the largest value (per unit of the parameter), whichever is larger: 1e-10 |f|
# absolute, ten times the rounding. The references are forward-mode derivatives of the traced
# JAX code; the differences evaluate concrete inputs through the host shadow engine.
H = 2e-5
RTOL = 1e-7

@pytest.mark.parametrize("name,quantity", _cases())
def test_derivatives_agree_with_central_differences(name, quantity):
    ref = catalogue[name]
    table = ref.d_irradiance if quantity == "irradiance" else ref.d_radiance
    bad = []
    for p in table:
        f = {t: _live(ref, *ref.perturbed(p, t), quantity) for t in (-H, -H / 2, H / 2, H)}
        d_h = (f[H] - f[-H]) / (2 * H)
        d_h2 = (f[H / 2] - f[-H / 2]) / H
        fd = (4.0 * d_h2 - d_h) / 3.0
        floor = max(1e-2 * np.abs(fd).max(), 1e-3 * np.abs(getattr(ref, quantity)).max())
        err = np.abs(table[p] - fd) / np.maximum(np.abs(fd), floor)
        if err.max() > RTOL:
            i = np.unravel_index(np.argmax(err), err.shape)
            bad.append(f"{p}: point {i[0]} channel {i[1]}: oracle {table[p][i]:.10g}, central differences {fd[i]:.10g} (rel {err[i]:.1e})")
    assert not bad, f"{name} d{quantity}:\n" + "\n".join(bad)


def test_exact_specular_derivative_at_the_grazing_receiver():
    """Once a wrong derivative of the catalogue's grazing scene, reduced to the kernel: light
    crossing the receiver's horizon, exponent 5, exact method (its quadrature's limits move with
    the light: differentiated by Leibniz's rule); forward mode equals central differences."""
    import jax

    from jaxshadow._kernels.specular import polygon_specular_kernel

    ref = catalogue["grazing"]
    v = jnp.asarray(ref.scene.lights[0].vertices)
    p, n, eye = (jnp.asarray(x) for x in (ref.points[14], ref.normals[14], ref.eye))
    tangent = jnp.asarray(np.random.default_rng(0).normal(size=v.shape))
    f = jax.jit(lambda w: polygon_specular_kernel(p, n, eye, w, jnp.asarray(5.0), method="exact"))
    _, d = jax.jit(lambda w, t: jax.jvp(f, (w,), (t,)))(v, tangent)
    h = 1e-6
    fd = (float(f(v + h * tangent)) - float(f(v - h * tangent))) / (2 * h)
    assert abs(float(d) - fd) <= 1e-6 * abs(fd), (float(d), fd)


# ----------------------------------------------------------------------------- the plugin


PLUGIN_TEST = '''
import pytest

def test_catalogue(jaxshadow_catalogue):
    assert "penumbra" in jaxshadow_catalogue

def test_every_scene(jaxshadow_reference):
    assert jaxshadow_reference.irradiance.shape == (16, 3)

@pytest.mark.jaxshadow_scenes("umbra", "mesh")
def test_selected(jaxshadow_reference, jaxshadow_alpha):
    assert jaxshadow_reference.name in ("umbra", "mesh") and jaxshadow_alpha == 0.01
'''


def test_pytest_plugin(pytester):
    pytester.makepyfile(test_uses_plugin=PLUGIN_TEST)
    result = pytester.runpytest_inprocess("--jaxshadow-alpha", "0.01", "-v", "-p", "no:xdist")
    result.assert_outcomes(passed=1 + len(SCENES) + 2)
    result.stdout.fnmatch_lines(["*test_every_scene?penumbra? PASSED*", "*test_selected?mesh? PASSED*"])
    pytester.makepyfile(test_bad='import pytest\n@pytest.mark.jaxshadow_scenes("nowhere")\ndef test_x(jaxshadow_reference):\n    pass\n')
    bad = pytester.runpytest_inprocess("test_bad.py", "-p", "no:xdist")
    assert bad.ret != 0
    bad.stdout.fnmatch_lines(["*unknown scene*nowhere*"])


def test_entry_point_is_declared():
    tomllib = pytest.importorskip("tomllib")

    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as fh:
        meta = tomllib.load(fh)
    eps = meta["project"]["entry-points"]["pytest11"]
    assert eps == {"jaxshadow": "_jaxshadow_pytest"}
    assert "jaxshadow.testing" in meta["tool"]["setuptools"]["packages"]
    assert "_jaxshadow_pytest" in meta["tool"]["setuptools"]["py-modules"]


def test_plugin_module_does_not_import_jaxshadow():
    """pytest imports entry-point plugins before anything else: the plugin must not import
    jaxshadow (jaxtyping's import hook, which the test run itself uses, must see it first)."""
    import subprocess
    import sys

    code = "import sys, _jaxshadow_pytest; print(any(m.split('.')[0] == 'jaxshadow' for m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "False"
    assert LIGHT_TRANSLATION == ("light.tx", "light.ty", "light.tz")


# ----------------------------------------------------------------------------- regeneration


@pytest.mark.slow
@pytest.mark.parametrize("name", list(BUILDERS))
def test_stored_references_are_reproduced_by_forward_mode(name):
    """`python -m jaxshadow.testing._catalogue` would write the same numbers (float64 jvp)."""
    ref = catalogue[name]
    live = ref.compute()
    for q in ("irradiance", "radiance"):
        np.testing.assert_allclose(live[q], getattr(ref, q), rtol=1e-12, atol=1e-15)
        table = getattr(ref, f"d_{q}")
        assert set(live[f"d_{q}"]) == set(table)
        for p, d in table.items():
            np.testing.assert_allclose(live[f"d_{q}"][p], d, rtol=1e-10, atol=1e-13, err_msg=f"{q} {p}")


@pytest.mark.slow
def test_image_references_agree_with_central_differences():
    """Pixel means of the penumbra scene's window (8 x 8 pixels, 4 x 4 nodes) and their
    derivatives: the values against the mean of the same nodes through the host engine, the
    derivatives against Richardson central differences of those means."""
    from jaxshadow.testing._catalogue import _gauss_nodes

    ref = catalogue["penumbra"]
    r, q = 8, 4
    img = ref.image(r, q)
    nodes, weights = _gauss_nodes(ref.window, r, q)
    normals = np.tile([0.0, 0.0, 1.0], (nodes.shape[0], 1))

    def means(scene):
        e = np.asarray(js.irradiance(scene, nodes, normals), np.float64).reshape(q * q, r * r, 3)
        return np.einsum("k,kpc->pc", weights, e).reshape(r, r, 3)

    np.testing.assert_allclose(img.irradiance, means(ref.scene), rtol=1e-12, atol=1e-15)
    for p in LIGHT_TRANSLATION:
        f = {t: means(ref.perturbed(p, t)[0]) for t in (-H, -H / 2, H / 2, H)}
        fd = (4.0 * (f[H / 2] - f[-H / 2]) / H - (f[H] - f[-H]) / (2 * H)) / 3.0
        floor = max(1e-2 * np.abs(fd).max(), 1e-3 * np.abs(img.irradiance).max())
        err = np.abs(img.d_irradiance[p] - fd) / np.maximum(np.abs(fd), floor)
        assert err.max() < RTOL, (p, err.max())
