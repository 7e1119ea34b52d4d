"""`fit_lights`' batched LM: repeated starts (the padding of its stages to `refine` rows) are
solved once (`mirror`) and give what solving each of them gives, with fewer evaluations."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from inverse._lm import batched_levenberg_marquardt, duplicate_sources

T = np.linspace(0.0, 4.0, 20)
Y = 2.0 * np.exp(-1.3 * T) + 0.5 + 0.01 * np.sin(7 * T)  # a non-zero residual at the optimum


def _solve(starts: np.ndarray, mirror: np.ndarray | None) -> tuple:
    calls = []

    def fn(y, args):
        jax.debug.callback(lambda: calls.append(1))
        return y[0] * jnp.exp(-y[1] * args) + y[2] - Y, jnp.zeros((), bool)

    res = jax.jit(lambda s: batched_levenberg_marquardt(
        fn, s, jnp.asarray(T), rtol=1e-10, atol=1e-14, max_steps=60, prune=(4, 8, 16, 32), chunk=1,
        num_residuals=T.size, mirror=None if mirror is None else jnp.asarray(mirror)))(jnp.asarray(starts))
    jax.block_until_ready(res)
    return res, len(calls)


def test_duplicate_sources():
    rows = np.array([[1.0, 2.0], [0.0, 1.0], [1.0, 2.0], [0.0, 1.0], [3.0, 3.0], [1.0, 2.0]])
    np.testing.assert_array_equal(duplicate_sources(rows), [0, 1, 0, 1, 4, 0])


def test_mirrored_starts_are_solved_once_with_the_same_result():
    distinct = np.array([[1.0, 1.0, 0.0], [3.0, 0.3, 1.0], [0.5, 2.5, -0.5]])
    # the stages' padding: copies of the first row; and one copy of another row in between
    starts = np.concatenate([distinct, distinct[1:2], np.repeat(distinct[:1], 4, axis=0)])
    mirror = duplicate_sources(starts)
    assert mirror.tolist() == [0, 1, 2, 1, 0, 0, 0, 0]
    plain, n_plain = _solve(starts, None)
    mirrored, n_mirrored = _solve(starts, mirror)
    for name in ("values", "losses", "converged", "num_steps", "residuals", "jacobians", "initial_losses",
                 "abandoned"):
        np.testing.assert_array_equal(getattr(mirrored, name), getattr(plain, name), err_msg=name)
    assert float(np.min(np.asarray(plain.losses))) < 1e-3  # they did solve
    assert 0 < n_mirrored < n_plain / 2  # only the 3 distinct rows were evaluated (the 5 copies were not)
