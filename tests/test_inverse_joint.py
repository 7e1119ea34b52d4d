"""`inverse.joint_std_errors`: the joint light + material Jacobian, one compiled program reused
across calls (scene, targets and material are arguments, not constants of a closure), with the
shadow engine at a capacity where the scene has occluders."""

import jax.numpy as jnp
import numpy as np
import pytest

import inverse
import jaxshadow as js
from inverse import _joint
from inverse._identifiability import identifiability
from inverse._parametrisation import LightParametrisation, with_light


def _problem(seed, n_points=24):
    """The demo's quad light over one square occluder, specular material, `n_points` targets
    (1 % noise: a residual to scale the errors), the light at the truth."""
    cfg = inverse.demo_configuration(occluders=True, n_points=n_points, seed=seed)
    col = np.asarray(js.shade(cfg.scene, cfg.material, cfg.points, cfg.normals, cfg.eye))
    col = col * (1 + 0.01 * np.random.default_rng(seed).normal(size=col.shape))
    targets = inverse.PaintedTargets(cfg.points, cfg.normals, col, cfg.eye)
    param = LightParametrisation(cfg.scene.lights[0], 0, ("position", "orientation", "size"), None,
                                 inverse.scene_size(cfg.scene, targets), "sigmoid")
    return cfg, targets, param


def _finite_difference_errors(param, scene, material, targets, h=1e-6):
    """The same standard errors from a central-difference Jacobian of `js.shade` (the public,
    checked entry point with concrete occluders) in the light's parameters, the nine
    coefficients and log n."""
    P = param.size
    k0 = np.stack([np.asarray(getattr(material, f), np.float64) for f in ("ka", "kd", "ks")]).reshape(-1)
    phi0 = np.r_[np.zeros(P), k0, np.log(float(material.exponent))]

    def resid(phi):
        k = phi[P:P + 9].reshape(3, 3)
        sc = with_light(scene, 0, param.build(jnp.asarray(phi[:P])))
        m = js.Material(ka=k[0], kd=k[1], ks=k[2], exponent=float(np.exp(phi[-1])))
        model = np.asarray(js.shade(sc, m, targets.points, targets.normals, targets.eye))
        return (np.sqrt(np.asarray(targets.weights)) * (model - np.asarray(targets.colours))).reshape(-1)

    cols = []
    for i in range(phi0.size):
        e = np.zeros_like(phi0)
        e[i] = h
        cols.append((resid(phi0 + e) - resid(phi0 - e)) / (2 * h))
    J = np.stack(cols, axis=1)
    r = resid(phi0)
    se = identifiability(J, float(r @ r), r.size, cut=1e-10).std_errors  # every weight positive
    names = [*param.names, *[f"{f}[{c}]" for f in ("ka", "kd", "ks") for c in "rgb"], "n"]
    scale = {nm: float(param.scale) for nm in ("x", "y", "z")} | {"n": float(material.exponent)}
    return {nm: float(s) * scale.get(nm, 1.0) for nm, s in zip(names, se, strict=True)}


def test_joint_std_errors_with_an_occluder_match_finite_differences():
    cfg, targets, param = _problem(0)
    got = inverse.joint_std_errors(param, np.zeros(param.size), cfg.scene, cfg.material, targets, fit_exponent=True)
    want = _finite_difference_errors(param, cfg.scene, cfg.material, targets)
    assert set(got) == set(want)
    for nm in want:
        np.testing.assert_allclose(got[nm], want[nm], rtol=1e-4, err_msg=nm)


def test_joint_std_errors_compile_once_for_new_values(monkeypatch):
    """A second call with another scene's targets, light pose and material (same shapes) runs
    the compiled program: the residual is not traced again."""
    traced = []
    plain = _joint._joint_residuals

    def counting(phi, problem):
        traced.append(1)
        return plain(phi, problem)

    monkeypatch.setattr(_joint, "_joint_residuals", counting)
    out = []
    for seed in (3, 4):
        cfg, targets, param = _problem(seed, n_points=27)  # a target count no other test compiles
        theta = 0.01 * np.random.default_rng(seed).normal(size=param.size)
        out.append(inverse.joint_std_errors(param, theta, cfg.scene, cfg.material, targets, fit_exponent=True,
                                            free_k=np.array([[1, 1, 1], [1, 1, 1], [1, 0, 1]], bool)))
        if seed == 3:
            first = len(traced)
    assert first > 0 and len(traced) == first
    assert "ks[g]" not in out[1] and all(np.isfinite(v) and v > 0 for v in out[1].values())
    assert out[0] != out[1]


def test_joint_std_errors_overflow_retries_at_twice_the_capacity(monkeypatch):
    """When some receiver overflows the capacity (simulated: the flag raised on the first
    call), the Jacobian is computed again at twice the capacity (`at_capacity`, the retry of
    every fit), not with every receiver against every occluder: equal to the first capacity's
    values (both exact)."""
    cfg, targets, param = _problem(0)
    args = (param, np.zeros(param.size), cfg.scene, cfg.material, targets)
    want = inverse.joint_std_errors(*args, fit_exponent=True)
    calls = []
    jac = _joint._joint_jacobian

    def overflowing(problem, phi):
        calls.append(problem.capacity)
        r, J, _ = jac(problem, phi)
        return r, J, jnp.asarray(len(calls) == 1)

    monkeypatch.setattr(_joint, "_joint_jacobian", overflowing)
    got = inverse.joint_std_errors(*args, fit_exponent=True)
    assert len(calls) == 2 and calls[0] is not None and calls[0] % 8 == 0 and calls[1] == 2 * calls[0]
    for nm in want:
        assert got[nm] == pytest.approx(want[nm], rel=1e-9)


def test_joint_std_errors_overflow_past_the_largest_capacity_raises(monkeypatch):
    """A receiver that overflows every capacity up to the largest raises the retry's
    `RuntimeError`, naming the entry point (no silent inexact value)."""
    cfg, targets, param = _problem(0)
    jac = _joint._joint_jacobian
    calls, first = [], []

    def always(problem, phi):  # the first capacity's program only: nothing else compiles
        calls.append(problem.capacity)
        if not first:
            first.append(jac(problem, phi)[:2])
        return (*first[0], jnp.asarray(True))

    monkeypatch.setattr(_joint, "_joint_jacobian", always)
    with pytest.raises(RuntimeError, match="joint_std_errors"):
        inverse.joint_std_errors(param, np.zeros(param.size), cfg.scene, cfg.material, targets, fit_exponent=True)
    assert calls[-1] == 4096 and all(b == min(2 * a, 4096) for a, b in zip(calls, calls[1:], strict=False))


def test_projected_coefficients_by_the_joint_program_are_the_painting_material():
    """`fit_light_and_material`'s projected material at the answer, from the joint Jacobian's
    coefficient columns (`_joint.projected_coefficients`): at the true light and exponent on
    noise-free targets it is the material the targets were painted with, and it agrees with the
    projection's own program (`colour_coefficients`)."""
    from inverse._lights import _problem as light_problem
    from inverse._lights import colour_coefficients

    cfg = inverse.demo_configuration(occluders=True, n_points=24, seed=0)
    col = np.asarray(js.shade(cfg.scene, cfg.material, cfg.points, cfg.normals, cfg.eye))
    targets = inverse.PaintedTargets(cfg.points, cfg.normals, col, cfg.eye)
    param = LightParametrisation(cfg.scene.lights[0], 0, ("position", "orientation", "size"), None,
                                 inverse.scene_size(cfg.scene, targets), "sigmoid")
    problem = light_problem(param, cfg.scene, cfg.material, targets, None, True, True, True)
    n_true = float(cfg.material.exponent)
    theta = jnp.asarray(np.r_[np.zeros(param.size), np.log(n_true)])
    k, n = _joint.projected_coefficients(problem, theta)
    want = np.stack([np.broadcast_to(np.asarray(getattr(cfg.material, f), np.float64), (3,))
                     for f in ("ka", "kd", "ks")])
    assert np.all(want[2] > 0)  # a specular material: every row of the projection is tested
    np.testing.assert_allclose(k, want, rtol=1e-9)
    assert n == pytest.approx(n_true, rel=1e-14)
    k2, _ = colour_coefficients(problem, theta)
    np.testing.assert_allclose(k, np.asarray(k2), rtol=1e-12)
