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
