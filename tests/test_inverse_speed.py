"""What keeps a fit's compiled programs reusable (issue 40): the shadow capacity buckets, the
successive-halving schedule as a traced input of the batched LM, and the material fit's one
specular program (values and d/dlog n, a fixed batch of exponents).

Each test counts XLA compilations with `jax.monitoring` and checks the values against an
independent evaluation (the tuple schedule, plain `jax.jvp` of `js.specular`, finite differences).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import inverse
import jaxshadow as js
from inverse import _material as MAT
from inverse._lm import PRUNE_SLOTS, batched_levenberg_marquardt, prune_array
from inverse._multistart import MIN_CAPACITY, capacity_bucket

_COUNT = {"n": 0}


def _listen(event: str, duration: float, **_: object) -> None:
    if event == "/jax/core/compile/backend_compile_duration":
        _COUNT["n"] += 1


jax.monitoring.register_event_duration_secs_listener(_listen)


def _compiles(fn):
    before = _COUNT["n"]
    out = fn()
    jax.block_until_ready(out)
    return out, _COUNT["n"] - before


def test_capacity_bucket_holds_the_need_within_a_factor_two():
    """Every need fits its bucket; buckets are powers of two from MIN_CAPACITY, at most twice
    the need above it, and nearby needs share one (13 and 14 edges: one compiled program)."""
    for need in range(0, 600):
        b = capacity_bucket(need)
        assert b >= max(need, MIN_CAPACITY)
        assert b & (b - 1) == 0
        if need > MIN_CAPACITY:
            assert b < 2 * need
        assert capacity_bucket(b) == b
    assert capacity_bucket(13) == capacity_bucket(14) == capacity_bucket(16)
    assert capacity_bucket(17) != capacity_bucket(16)


T = np.linspace(0.0, 4.0, 20)
Y = 2.0 * np.exp(-1.3 * T) + 0.5 + 0.01 * np.sin(7 * T)


def _resid(y, args):
    t, obs = args
    return y[0] * jnp.exp(-y[1] * t) + y[2] - obs, y[0] < 0


@jax.jit
def _lm_traced(y0, prune):
    return batched_levenberg_marquardt(_resid, y0, (jnp.asarray(T), jnp.asarray(Y)), rtol=1e-10, atol=1e-14,
                                       max_steps=60, prune=prune)


def test_prune_schedule_as_an_input_one_program_same_result():
    """The schedule as a traced array (`prune_array`): two schedules run one compiled program,
    and each gives what the static tuple gives (the same pruned starts, losses, steps)."""
    rng = np.random.default_rng(0)
    y0 = jnp.asarray(np.c_[rng.uniform(0.5, 4, 8), rng.uniform(0.2, 3, 8), rng.uniform(-1, 1, 8)])
    outs, counts = [], []
    for sched in ((4, 8, 16), (2, 4, 8, 16, 32)):
        out, n = _compiles(lambda s=sched: _lm_traced(y0, jnp.asarray(prune_array(s))))
        outs.append(out)
        counts.append(n)
        ref = batched_levenberg_marquardt(_resid, y0, (jnp.asarray(T), jnp.asarray(Y)), rtol=1e-10, atol=1e-14,
                                          max_steps=60, prune=sched)
        np.testing.assert_array_equal(np.asarray(out.abandoned), np.asarray(ref.abandoned))
        np.testing.assert_array_equal(np.asarray(out.num_steps), np.asarray(ref.num_steps))
        np.testing.assert_allclose(np.asarray(out.losses), np.asarray(ref.losses), rtol=1e-12, atol=1e-300)
        assert np.any(np.asarray(ref.abandoned))  # the schedule did prune: the comparison has teeth
    assert counts[1] == 0, counts
    # The schedules differ, and so do the starts they abandon.
    assert not np.array_equal(np.asarray(outs[0].abandoned), np.asarray(outs[1].abandoned))


def test_prune_array_pads_and_rejects_long_schedules():
    a = prune_array((16, 4, 8, 4))
    assert a.dtype == np.int32 and a.shape == (PRUNE_SLOTS,)
    assert list(a[:3]) == [4, 8, 16] and np.all(a[3:] == -1)
    with pytest.raises(ValueError, match="at most"):
        prune_array(tuple(range(1, PRUNE_SLOTS + 2)))


@pytest.fixture(scope="module")
def spec_basis():
    rng = np.random.default_rng(3)
    pts = np.c_[rng.uniform(-1, 1, (12, 2)), np.zeros(12)]
    nrm = np.tile([0.0, 0.0, 1.0], (12, 1))
    eye = np.array([0.3, -1.5, 1.5])
    scene = js.Scene([js.PolygonLight(np.array([[-0.3, -0.2, 1.6], [-0.3, 0.2, 1.7], [0.3, 0.2, 1.7],
                                                [0.3, -0.2, 1.6]]), 4.0)], ambient=0.05)  # facing down
    t = inverse.PaintedTargets(pts, nrm, np.zeros((12, 3)), eye)
    return scene, t


def test_material_specular_one_program_values_and_derivative(spec_basis):
    """`_Basis`: the grid (41 exponents), single exponents and d/dlog n run one compiled program
    (`SPEC_CHUNK` exponents a call), and give `js.specular`'s values and n dS/dn (central
    differences in log n)."""
    scene, t = spec_basis
    basis = MAT._Basis(scene, t, js.specular)
    grid = np.exp(np.linspace(np.log(1.0), np.log(200.0), 41))
    many, n0 = _compiles(lambda: basis.spec_many(grid))
    assert many.shape == (41, 12, 3)
    one, n1 = _compiles(lambda: basis.spec(17.3))
    d, n2 = _compiles(lambda: basis.dspec_dlogn(17.3))
    assert n1 == 0 and n2 == 0, (n0, n1, n2)
    eyes = np.broadcast_to(t.eye, t.points.shape)
    for e in (grid[0], grid[20], grid[40], 17.3):
        ref = np.asarray(js.specular(scene, t.points, t.normals, eyes, jnp.asarray(e)))
        got = basis.spec(float(e))
        assert np.abs(ref).max() > 0
        np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-14)
    h = 1e-4
    fd = (np.asarray(js.specular(scene, t.points, t.normals, eyes, jnp.asarray(17.3 * np.exp(h))))
          - np.asarray(js.specular(scene, t.points, t.normals, eyes, jnp.asarray(17.3 * np.exp(-h))))) / (2 * h)
    np.testing.assert_allclose(d, fd, rtol=1e-5, atol=1e-9 * np.abs(fd).max())
    np.testing.assert_allclose(one, basis.spec_many(np.array([17.3]))[0], rtol=0, atol=0)


@pytest.fixture
def pristine_cache(monkeypatch):
    """JAX's persistent cache unconfigured and the library's default undecided; restored after."""
    from jax.experimental.compilation_cache import compilation_cache

    from jaxshadow._core import compile_cache as CC

    saved = (jax.config.jax_compilation_cache_dir, jax.config.jax_persistent_cache_min_compile_time_secs)
    jax.config.update("jax_compilation_cache_dir", None)
    compilation_cache.reset_cache()
    CC.reset_default_compile_cache()
    yield CC
    jax.config.update("jax_compilation_cache_dir", saved[0])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", saved[1])
    compilation_cache.reset_cache()
    CC.reset_default_compile_cache()


def _fresh_program():
    """A fit program that has not run in this process (`fit_jit` decides the cache at its first call)."""
    from inverse._lm import fit_jit

    return fit_jit(lambda x: jnp.sin(x) * 2.0)


def test_default_compile_cache_is_turned_on_by_the_first_fit_program(pristine_cache, monkeypatch, tmp_path):
    """The library's default: a fit program's first call turns JAX's persistent cache on in
    `$JAXSHADOW_COMPILE_CACHE` (here a temporary directory), created private to the user."""
    d = tmp_path / "xla"
    monkeypatch.setenv("JAXSHADOW_COMPILE_CACHE", str(d))
    assert jax.config.jax_compilation_cache_dir is None
    _fresh_program()(jnp.ones(3))
    assert jax.config.jax_compilation_cache_dir == str(d)
    assert d.is_dir() and (d.stat().st_mode & 0o777) == 0o700
    assert pristine_cache.ensure_default_compile_cache() == str(d)


@pytest.mark.parametrize("how", ["env off", "user dir", "jax disabled", "declined"])
def test_default_compile_cache_leaves_a_users_choice_alone(pristine_cache, monkeypatch, tmp_path, how):
    """Off by `JAXSHADOW_COMPILE_CACHE=off`, by `jax_enable_compilation_cache=False` and by the
    command's `--no-compile-cache` (`decline_default_compile_cache`); a directory the user gave
    JAX is kept (the library's default directory is not created)."""
    mine = tmp_path / "mine"
    monkeypatch.setenv("JAXSHADOW_COMPILE_CACHE", str(tmp_path / "default"))
    if how == "env off":
        monkeypatch.setenv("JAXSHADOW_COMPILE_CACHE", "off")
    elif how == "user dir":
        jax.config.update("jax_compilation_cache_dir", str(mine))
    elif how == "jax disabled":
        jax.config.update("jax_enable_compilation_cache", False)
    else:
        pristine_cache.decline_default_compile_cache()
    try:
        _fresh_program()(jnp.ones(3))
        expect = str(mine) if how == "user dir" else None
        assert jax.config.jax_compilation_cache_dir == expect
        assert pristine_cache.ensure_default_compile_cache() == expect
        assert not (tmp_path / "default").exists()
    finally:
        jax.config.update("jax_enable_compilation_cache", True)


_CHILD = """
import jax, jax.numpy as jnp
hits = []
jax.monitoring.register_event_listener(lambda e, **k: hits.append(e) if e == "/jax/compilation_cache/cache_hits" else None)
from inverse._lm import fit_jit
f = fit_jit(lambda x: jnp.cumsum(jnp.sin(x) ** 2))
jax.block_until_ready(f(jnp.ones(5)))
print("HITS", len(hits), jax.config.jax_compilation_cache_dir)
"""


def test_default_compile_cache_serves_a_later_process(tmp_path):
    """Across processes: the second process finds the first one's fit program in the default
    cache (a persistent-cache hit), without any configuration by the caller."""
    import os
    import subprocess
    import sys

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, JAXSHADOW_COMPILE_CACHE=str(tmp_path / "xla"), PYTHONPATH=root,
               JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")  # a tiny program: cache it anyway
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    outs = [subprocess.run([sys.executable, "-c", _CHILD], env=env, capture_output=True, text=True, check=True,
                           cwd=root).stdout.split() for _ in range(2)]
    assert outs[0][-2:] == ["0", str(tmp_path / "xla")] and outs[1][-2] == "1", outs
    assert any((tmp_path / "xla").iterdir())


@pytest.mark.parametrize("variant", ["powers projected, exponent searched"])
def test_structured_jacobian_is_the_residuals_jacobian(variant):
    """`_multilight.structured_jacobian` (each light's engine differentiated along its own
    parameters only) against `jax.jacfwd` of the whole projected residual: three lights of
    distinct kinds behind a box, a specular term, one light whose power alone is fitted, the
    Phong exponent searched (every light's column of log n). And the LM program's columns
    outside its mask are zero. (The per-channel colour-free model is not served by it: there the
    two differ at ~1e-5 relative in some columns, the projection's conditioning.)"""
    from benchmarks.inverse_random_scenes import random_case
    from inverse import _multilight as ML
    from inverse._fit_lights import FIT_LIGHTS_GROUPS, _groups_for

    c = random_case(3, ("polygon", "point", "segment"), n_targets=12)
    material = js.Material(ka=0.2, kd=[0.6, 0.5, 0.4], ks=0.3, exponent=12.0)
    t = inverse.PaintedTargets(c.points, c.normals, np.asarray(js.shade(c.true, material, c.points, c.normals,
                                                                         c.eye)), c.eye)
    size = inverse.scene_size(c.true, t)
    params, offsets, off = [], [], 0
    for i, light in enumerate(c.true.lights):
        p = None if i == 1 else inverse.LightParametrisation(light, i, _groups_for(light, FIT_LIGHTS_GROUPS), None,
                                                              size, "sigmoid")
        params.append(p)
        offsets.append(off)
        off += 0 if p is None else p.size
    z = jnp.zeros(t.points.shape, jnp.float64)
    colour_free = variant.startswith("colour")
    problem = ML.LightsProblem(tuple(params), tuple(c.true.lights), c.true, material, t, z, z, tuple(offsets),
                               True, True, False, None, 64, fit_exponent=not colour_free, colour_free=colour_free)
    theta = jnp.asarray(np.random.default_rng(2).normal(0.0, 0.05, problem.n_theta))
    r, J, over = jax.jit(lambda th: ML.structured_jacobian(th, problem, problem.capacity))(theta)
    # The reference Jacobian and residual from one compiled program (the residual is jacfwd's
    # primal, returned as its auxiliary output).
    ref, r0 = jax.jit(jax.jacfwd(lambda th: (lambda r: (r, r))(ML.projected_residual(th, problem, problem.capacity)[0]),
                                 has_aux=True))(theta)
    assert not bool(over) and J.shape == ref.shape == (r0.shape[0], problem.n_theta)
    assert np.abs(np.asarray(ref)).max() > 0 and np.all(np.abs(np.asarray(ref)).max(axis=0) > 0)  # every column moves
    np.testing.assert_allclose(np.asarray(r), np.asarray(r0), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.asarray(J), np.asarray(ref), rtol=1e-9, atol=1e-12 * np.abs(np.asarray(ref)).max())
    # The LM program's Jacobian: held columns zero, the others the same.
    mask = np.zeros(problem.n_theta, bool)
    mask[offsets[2]:] = True
    res = ML._lm(problem, theta[None], theta, jnp.asarray(mask), 1e-8, 1e-12, np.asarray(0, np.int32),
                 jnp.asarray(ML.prune_array(())), 1, jnp.zeros(1, jnp.int32))
    Jl = np.asarray(res.jacobians[0])
    assert np.all(Jl[:, ~mask] == 0)
    np.testing.assert_allclose(Jl[:, mask], np.asarray(ref)[:, mask], rtol=1e-9,
                               atol=1e-12 * np.abs(np.asarray(ref)).max())


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_emitted_power_of_concrete_lights_compiles_nothing(dtype):
    """`_powers.emitted_power` of lights with concrete arrays (the report and the budget's
    ranking, on the host) compiles no XLA program, and equals the traced formula under `jit`
    (to one rounding of the dtype) and the closed forms ($\\pi \\bar L A$, $\\bar\\Phi \\ell$,
    $4 \\pi \\bar I$) computed here."""
    from inverse._powers import emitted_power

    eps = float(np.finfo(dtype).eps)
    quad = js.PolygonLight(np.array([[0, 0, 2], [0.3, 0, 2], [0.3, 0.2, 2.1], [0, 0.2, 2.1]], dtype),
                           np.array([1.0, 2.0, 3.0], dtype))
    seg = js.LinearLight(np.array([0, 0, 1], dtype), np.array([0.3, 0.4, 1], dtype), np.array([2.0, 2.0, 5.0], dtype))
    point = js.PointLight(np.array([0, 0, 1], dtype), np.array([1.0, 1.0, 4.0], dtype))
    area = 0.3 * float(np.hypot(0.2, 0.1))  # the quad: a 0.3 x |(0.2, 0.1)| rectangle
    expected = [np.pi * 2.0 * area, 3.0 * 0.5, 4.0 * np.pi * 2.0]
    for light, want in zip((quad, seg, point), expected, strict=True):
        got, n = _compiles(lambda light=light: emitted_power(light))
        assert n == 0
        assert isinstance(got, np.ndarray) and got.dtype == dtype
        traced = float(jax.jit(emitted_power)(light))
        assert abs(float(got) - traced) <= 4 * eps * abs(traced)
        assert abs(float(got) - want) <= 8 * eps * want


def test_parametrisations_are_built_without_compiling():
    """`LightParametrisation` puts its host arrays on the device as they are (`jax.device_put`):
    building one for each light kind compiles no XLA program (eager `jnp.asarray` of a NumPy
    array compiles a copy program per new shape), and its fields hold the host values exactly."""
    from inverse._parametrisation import LightParametrisation

    quad = js.PolygonLight(np.array([[0, 0, 2], [0.3, 0, 2], [0.3, 0.2, 2.1], [0, 0.2, 2.1]]), np.ones(3))
    seg = js.LinearLight(np.array([0.0, 0.0, 1.0]), np.array([0.3, 0.4, 1.0]), np.ones(3))
    point = js.PointLight(np.array([0.1, 0.2, 1.0]), np.ones(3))
    fits = (("position", "orientation", "size"), ("position", "orientation", "size"), ("position",))
    for k, (light, fit) in enumerate(zip((quad, seg, point), fits, strict=True)):
        p, n = _compiles(lambda light=light, fit=fit, k=k: LightParametrisation(light, k, fit, None, 1.7, "sigmoid"))
        assert n == 0
        assert np.asarray(p.c0).dtype == np.float64
    assert np.array_equal(np.asarray(p.c0), [0.1, 0.2, 1.0])
    assert np.array_equal(np.asarray(p.frame0), np.eye(3))
