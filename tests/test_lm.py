"""The batched Levenberg-Marquardt (`inverse/_lm.py`) and the culled light-placement residual.

The solver is checked against SciPy's MINPACK LM on classic test problems from many starts at
once (an independent implementation), for frozen starts, non-finite starts and the flag; the
culling with overflow-and-retry against the full model (solutions must agree to round-off).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import inverse
from benchmarks.inverse_scenes import occluded_light_problem
from inverse import _lights as L
from inverse import _multilight as ML
from inverse import _multistart as M
from inverse import _parametrisation as P
from inverse import _solvers as S
from inverse import pose_errors
from inverse._lm import batched_levenberg_marquardt

# Osborne / Meyer-style exponential fit: y = a exp(-b t) + c, with 3 parameters and 20 data.
T = np.linspace(0.0, 4.0, 20)
TRUE = np.array([2.0, 1.3, 0.5])
Y = TRUE[0] * np.exp(-TRUE[1] * T) + TRUE[2] + 0.01 * np.sin(7 * T)  # non-zero residual at the optimum


def _exp_resid(y, args):
    t, obs = args
    r = y[0] * jnp.exp(-y[1] * t) + y[2] - obs
    return r, y[0] < 0  # a flag, to check it is OR-ed over the evaluations


def _rosenbrock(y, args):
    return jnp.stack([10.0 * (y[1] - y[0] ** 2), 1.0 - y[0]]), jnp.zeros((), bool)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_lm_matches_minpack_on_exponential_fit(dtype):
    rng = np.random.default_rng(0)
    starts = np.concatenate([TRUE[None] * 1.5, TRUE[None] + rng.normal(0, 0.5, (7, 3))]).astype(dtype)
    args = (jnp.asarray(T, dtype), jnp.asarray(Y, dtype))
    res = jax.jit(lambda y0: batched_levenberg_marquardt(_exp_resid, y0, args, rtol=1e-10, atol=1e-12,
                                                         max_steps=200))(jnp.asarray(starts))
    ref = scipy.optimize.least_squares(lambda y: np.asarray(_exp_resid(y, (T, Y))[0]), TRUE * 1.5,
                                       method="lm", xtol=1e-15, ftol=1e-15)
    tol = 1e-8 if dtype == np.float64 else 2e-3
    for i in range(len(starts)):
        assert bool(res.converged[i]), i
        np.testing.assert_allclose(np.asarray(res.values[i]), ref.x, rtol=tol, atol=tol)
        np.testing.assert_allclose(float(res.losses[i]), 0.5 * np.sum(ref.fun**2), rtol=10 * tol)
    # The residual and Jacobian returned are those at the solution.
    J = jax.jacfwd(lambda y: _exp_resid(y, args)[0])(res.values[0])
    np.testing.assert_allclose(np.asarray(res.jacobians[0]), np.asarray(J), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(res.initial_losses[0]),
                               0.5 * np.sum(np.asarray(_exp_resid(jnp.asarray(starts[0]), args)[0]) ** 2),
                               rtol=1e-5)
    assert res.values.dtype == dtype


def test_lm_rosenbrock_and_flags():
    starts = jnp.array([[-1.2, 1.0], [2.0, -1.0], [0.0, 0.0], [jnp.nan, 0.0]])
    res = batched_levenberg_marquardt(_rosenbrock, starts, None, rtol=1e-12, atol=1e-14, max_steps=300)
    for i in range(3):
        assert bool(res.converged[i])
        np.testing.assert_allclose(np.asarray(res.values[i]), [1.0, 1.0], atol=1e-8)
    # A start where the residual is not finite stops at once, not converged, nothing NaN leaks.
    assert not bool(res.converged[3]) and int(res.num_steps[3]) == 0
    assert np.all(np.isfinite(np.asarray(res.losses[:3])))
    # Steps are counted per start (the easy start takes fewer).
    assert int(res.num_steps[2]) != int(res.num_steps[0]) or int(res.num_steps[1]) != int(res.num_steps[0])
    # The flag is raised iff some evaluated point raised it.
    args = (jnp.asarray(T), jnp.asarray(Y))
    ok = batched_levenberg_marquardt(_exp_resid, jnp.asarray([[2.5, 1.0, 0.4]]), args, rtol=1e-10, atol=1e-12,
                                     max_steps=100)
    bad = batched_levenberg_marquardt(_exp_resid, jnp.asarray([[-1.0, 1.0, 0.4]]), args, rtol=1e-10,
                                      atol=1e-12, max_steps=100)
    assert not bool(ok.flag) and bool(bad.flag)


def test_lm_max_steps_reports_not_converged():
    res = batched_levenberg_marquardt(_rosenbrock, jnp.array([[-1.2, 1.0]]), None, rtol=1e-12, atol=1e-14,
                                      max_steps=3)
    assert not bool(res.converged[0]) and int(res.num_steps[0]) == 3


def test_lm_chunked_evaluation_matches_batched():
    """Evaluating the starts one or three at a time (skipping finished ones) changes nothing."""
    rng = np.random.default_rng(1)
    starts = jnp.asarray(np.concatenate([TRUE[None] * 1.5, TRUE[None] + rng.normal(0, 0.5, (6, 3))]))
    args = (jnp.asarray(T), jnp.asarray(Y))
    run = jax.jit(lambda y0, chunk: batched_levenberg_marquardt(_exp_resid, y0, args, rtol=1e-10, atol=1e-12,
                                                                max_steps=200, chunk=chunk), static_argnums=1)
    full = run(starts, None)
    assert len(set(np.asarray(full.num_steps).tolist())) > 1  # starts finish at different iterations
    for chunk in (1, 3):
        got = run(starts, chunk)
        np.testing.assert_array_equal(np.asarray(got.num_steps), np.asarray(full.num_steps))
        np.testing.assert_allclose(np.asarray(got.values), np.asarray(full.values), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(np.asarray(got.jacobians), np.asarray(full.jacobians), rtol=1e-12, atol=1e-14)
        assert not np.any(np.asarray(got.abandoned))


@pytest.mark.parametrize("chunk", [None, 1, 3])
def test_lm_aux_is_kept_at_every_starts_answer(chunk):
    """A Jacobian callable returning a fourth value (`aux`): the iterates are those of the same
    callable without it, and `LMResult.aux` is that value at each start's final point (here the
    model's terms `exp(-b t)` and its derivative in b, checked in NumPy at `values`)."""
    rng = np.random.default_rng(2)
    starts = jnp.asarray(np.concatenate([TRUE[None] * 1.5, TRUE[None] + rng.normal(0, 0.5, (6, 3))]))
    args = (jnp.asarray(T), jnp.asarray(Y))

    def rj(y, a, with_aux):
        (r, e), lin = jax.linearize(lambda z: (z[0] * jnp.exp(-z[1] * a[0]) + z[2] - a[1], jnp.exp(-z[1] * a[0])), y)
        J, de = jax.vmap(lin, out_axes=(1, 0))(jnp.eye(3, dtype=y.dtype))
        flag = y[0] < 0
        return (r, J, flag, (e, de[1])) if with_aux else (r, J, flag)

    spec = (jax.ShapeDtypeStruct((T.size,), starts.dtype), jax.ShapeDtypeStruct((T.size,), starts.dtype))
    run = jax.jit(lambda y0, aux: batched_levenberg_marquardt(
        _exp_resid, y0, args, rtol=1e-10, atol=1e-12, max_steps=200, chunk=chunk,
        jacobian=lambda y, a: rj(y, a, aux), aux=spec if aux else None), static_argnums=1)
    plain, kept = run(starts, False), run(starts, True)
    assert plain.aux is None
    np.testing.assert_array_equal(np.asarray(kept.values), np.asarray(plain.values))
    np.testing.assert_array_equal(np.asarray(kept.num_steps), np.asarray(plain.num_steps))
    y = np.asarray(kept.values)
    np.testing.assert_allclose(np.asarray(kept.aux[0]), np.exp(-y[:, 1:2] * T[None]), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(kept.aux[1]), -T[None] * np.exp(-y[:, 1:2] * T[None]), rtol=1e-12,
                               atol=1e-15)


def test_lm_successive_halving():
    """`prune`: at each listed iteration the worse half of the running starts stops (abandoned,
    not converged); the best survives and converges; fewer iterations than without."""
    starts = jnp.array([[-1.2, 1.0], [2.0, -1.0], [0.9, 0.8], [-3.0, 5.0], [1.5, 2.0], [-0.5, 3.0]])
    kw = dict(rtol=1e-12, atol=1e-14, max_steps=300)
    plain = batched_levenberg_marquardt(_rosenbrock, starts, None, **kw)
    pruned = batched_levenberg_marquardt(_rosenbrock, starts, None, prune=(2, 4), chunk=2, **kw)
    gone = np.asarray(pruned.abandoned)
    # 6 running after iteration 2 -> 3 kept; then 3 -> 2 kept (unless some finished before).
    assert 1 <= gone.sum() <= 4
    assert not np.any(np.asarray(pruned.converged)[gone])
    best = int(np.argmin(np.asarray(pruned.losses)))
    assert bool(pruned.converged[best]) and not gone[best]
    np.testing.assert_allclose(np.asarray(pruned.values[best]), [1.0, 1.0], atol=1e-8)
    # Abandoned starts stop early: fewer steps than when every start runs on.
    assert np.all(np.asarray(pruned.num_steps)[gone] <= 4)
    assert np.sum(np.asarray(pruned.num_steps)) < np.sum(np.asarray(plain.num_steps))


# Compiled once per problem shape and shared by the tests below (the full model's Jacobian with
# 8 occluders is the costliest program of this module to compile); op-by-op evaluation of the
# culled residual would compile each of its primitives on its own.
_full_jacobian = eqx.filter_jit(lambda setup, y: jax.jacfwd(lambda th: ML.projected_residual(th, setup, None)[0])(y))
_culled_jacobian = eqx.filter_jit(lambda setup, y: jax.jacfwd(
    lambda th: ML.projected_residual(th, setup, setup.capacity), has_aux=True)(y))
_overflow = eqx.filter_jit(lambda setup, y: ML.projected_residual(y, setup, setup.capacity)[1])


def _setup(param, start, material, t):
    """`fit_light`'s problem (`fit_lights`' one-light `LightsProblem`), material fixed, no specular."""
    return L._problem(param, start, material, t, None, False, False, False)


@pytest.fixture(scope="module")
def occluded_config():
    """The demo's quad light over 8 occluders, 24 targets, noise-free (solver test, not acceptance)."""
    return occluded_light_problem(8, n_points=24)


def test_culled_residual_equals_full_model(occluded_config):
    """Where no receiver overflows the capacity, the residual and Jacobian with the shadow
    engine in the program are those of every receiver against every occluder; with a capacity
    of 1 (too small here) the flag is raised."""
    scene, start, material, t, size = occluded_config
    param = P.LightParametrisation(start.lights[0], 0, ("position", "orientation", "size"), None, size, "sigmoid")
    setup = _setup(param, start, material, t)
    y = jnp.asarray(np.random.default_rng(1).normal(0, 0.05, param.size))
    cap = M.culling_capacity_for_starts(param, start, t, y[None])
    assert cap is not None and cap >= 8
    full = _full_jacobian(setup, y)
    culled, over = _culled_jacobian(dataclasses.replace(setup, capacity=cap), y)
    assert not bool(over)
    assert np.abs(np.asarray(full)).max() > 0
    np.testing.assert_allclose(np.asarray(culled), np.asarray(full), rtol=1e-9, atol=1e-12)
    assert bool(_overflow(dataclasses.replace(setup, capacity=1), y))


def test_overflow_retry_gives_the_full_model_solution(occluded_config, monkeypatch):
    """A capacity that overflows during the solve is doubled until exact; the fit says so."""
    scene, start, material, t, size = occluded_config
    monkeypatch.setattr(S, "culling_capacity_for_starts", lambda *a: 1)
    f = inverse.fit_light(start, t, material, starts=1)
    assert any("culling capacity" in w for w in f.report.warnings), f.report.warnings
    err = pose_errors(f.light.vertices, scene.lights[0].vertices)
    assert err["position"] < 1e-7 * size and f.report.loss < 1e-20


def test_screening_by_the_lm_program(occluded_config, caplog, monkeypatch):
    """`fit_light` screens its starts with `fit_lights`' screening (`_multilight.screen`, k starts
    a call, the last call padded): the losses are those of the full model at every start (a
    vectorised loss, every receiver against every occluder), also when the capacity overflows
    at some start (screened again at twice the capacity, and said); `fit_light` compiles one LM
    program for its k best starts."""
    import logging

    scene, start, material, t, size = occluded_config
    param = P.LightParametrisation(start.lights[0], 0, ("position", "orientation", "size"), None, size, "sigmoid")
    setup = _setup(param, start, material, t)
    y0 = M.make_starts(param, 11, search_radius=0.5, orientation_spread=0.5, size_spread=0.5, seed=3,
                       dtype=jnp.float64)
    ys = np.asarray(y0)
    s = dataclasses.replace(setup, capacity=M.culling_capacity_for_starts(param, start, t, y0))
    mask = np.ones(ys.shape[1], bool)
    got, _, retries = ML.screen(s, ys, ys[0], mask, 4)
    ref = np.asarray([float(ML.loss_at(setup, y)) for y in y0])
    assert got.shape == (11,) and np.all(np.isfinite(got)) and retries == 0
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-30)
    # A capacity that overflows at some start: screened again with a larger one, the same losses.
    small, used, retries = ML.screen(dataclasses.replace(s, capacity=1), ys, ys[0], mask, 4)
    assert retries > 0 and used.capacity > 1
    np.testing.assert_allclose(small, ref, rtol=1e-12, atol=1e-30)
    # `fit_light` runs `fit_lights`' one-light problem: its screen, then one LM program for the k
    # best (compiled once; the caches are cleared so that programs of earlier tests do not count).
    jax.clear_caches()
    with jax.log_compiles(True), caplog.at_level(logging.WARNING):
        f = inverse.fit_light(start, t, material, starts=11, solver=inverse.LM(refine=3, combinatorics="host"))
    lm_compiles = [r for r in caplog.records
                   if any(f"compilation of jit({name})" in r.getMessage() for name in ("_lm_impl",))]
    assert len(lm_compiles) == 1, [r.getMessage() for r in lm_compiles]
    assert len(f.report.start_losses) == 3 and f.report.loss <= float(np.min(ref)) + 1e-12


@pytest.mark.parametrize("which", ["FIT_COMPILER_OPTIONS", "ONCE_COMPILER_OPTIONS"])
def test_lm_num_residuals_and_fit_compiler_options(which):
    """Passing the residual length (no extra trace) and compiling with `FIT_COMPILER_OPTIONS`
    (`fit_jit`) or `ONCE_COMPILER_OPTIONS` (LLVM at -O0) change nothing in the solution; a wrong
    length is an error, not a silent result."""
    from test_xla_flags import XLA_DEFAULTS

    import inverse._lm as lm
    from inverse._lm import fit_jit

    options = getattr(lm, which)

    starts = jnp.asarray(np.concatenate([TRUE[None] * 1.5, TRUE[None] * 0.7]))
    args = (jnp.asarray(T), jnp.asarray(Y))

    def solve(y0, m):
        return batched_levenberg_marquardt(_exp_resid, y0, args, rtol=1e-10, atol=1e-12, max_steps=200,
                                           num_residuals=m)

    # The reference with XLA's default options (the test run compiles with others, tests/conftest.py).
    ref = jax.jit(solve, static_argnums=1, compiler_options=XLA_DEFAULTS)(starts, None)
    fast = fit_jit(solve, options=options)
    got = fast(starts, T.size)
    # At -O0 some operations round differently (the values agree to ~1e-15): the last step's
    # convergence test may fall one iteration apart, the answer is the same to rounding.
    steps = np.asarray(got.num_steps) - np.asarray(ref.num_steps)
    assert np.all(steps == 0) if which == "FIT_COMPILER_OPTIONS" else np.all(np.abs(steps) <= 1), steps
    assert np.all(np.asarray(got.converged))
    np.testing.assert_allclose(np.asarray(got.values), np.asarray(ref.values), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.asarray(got.jacobians), np.asarray(ref.jacobians), rtol=1e-10, atol=1e-14)
    # The options are what the compiled program was built with (CPU backend).
    if jax.default_backend() == "cpu":
        lowered = jax.jit(solve, static_argnums=1, compiler_options=options).lower(starts, T.size)
        assert lowered.compile() is not None
    with pytest.raises((TypeError, ValueError)):
        jax.jit(solve, static_argnums=1)(starts, T.size + 1)


def test_fit_jit_falls_back_when_jaxlib_lacks_an_option(monkeypatch):
    import inverse._lm as lm

    monkeypatch.setattr(lm, "FIT_COMPILER_OPTIONS", {"xla_no_such_option_anywhere": True})
    f = lm.fit_jit(lambda x: 2.0 * x)
    np.testing.assert_array_equal(np.asarray(f(jnp.arange(3.0))), [0.0, 2.0, 4.0])
    np.testing.assert_array_equal(np.asarray(f(jnp.arange(2.0))), [0.0, 2.0])
    # Other errors are not swallowed.
    g = lm.fit_jit(lambda x: x.reshape(7))
    with pytest.raises(TypeError):
        g(jnp.arange(3.0))


def test_fit_programs_trace_with_the_garbage_collector_paused():
    """`fit_jit` traces and compiles with the cyclic GC off and restores it; a caller who had
    switched it off keeps it off."""
    import gc

    import inverse._lm as lm

    seen = []
    f = lm.fit_jit(lambda x: (seen.append(gc.isenabled()), 2.0 * x)[1])
    assert gc.isenabled()
    np.testing.assert_array_equal(np.asarray(f(jnp.arange(3.0))), [0.0, 2.0, 4.0])
    assert seen == [False] and gc.isenabled()
    gc.disable()
    try:
        with lm.gc_paused():
            pass
        assert not gc.isenabled()
    finally:
        gc.enable()


@pytest.mark.parametrize("n_starts", [1, 3])
def test_lm_linearize_and_jacfwd_jacobians_agree(n_starts):
    """The default Jacobian (`jax.linearize`, one start without a batching layer) and `jacfwd`
    give the same iterates: same solution, Jacobian and step count from every start."""
    rng = np.random.default_rng(1)
    starts = jnp.asarray(TRUE[None] + rng.normal(0, 0.3, (n_starts, 3)))
    args = (jnp.asarray(T), jnp.asarray(Y))
    out = {}
    for mode in ("linearize", "jacfwd"):
        out[mode] = jax.jit(lambda y0, m=mode: batched_levenberg_marquardt(
            _exp_resid, y0, args, rtol=1e-10, atol=1e-12, max_steps=200, jacobian=m))(starts)
    a, b = out["linearize"], out["jacfwd"]
    np.testing.assert_allclose(np.asarray(a.values), np.asarray(b.values), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(np.asarray(a.jacobians), np.asarray(b.jacobians), rtol=1e-12, atol=1e-13)
    np.testing.assert_array_equal(np.asarray(a.num_steps), np.asarray(b.num_steps))
    with pytest.raises(ValueError, match="jacobian must be"):
        batched_levenberg_marquardt(_exp_resid, starts, args, rtol=1e-10, atol=1e-12, max_steps=5, jacobian="fd")
