"""The global placement's candidate columns (`inverse._placement_rank.unit_columns`): evaluated
at a small shadow capacity first and again at twice it only where a receiver overflowed, they
equal the columns of one run at a capacity every receiver fits in (to rounding), and the
problem's capacity (the LM program's) is left as it is.

A quad light over a box occluder on 24 floor targets; its candidate centres spread over and
beside the box, so that some candidates' receivers need more boundary edges than others."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import inverse
import inverse._placement_rank as placement_rank
import jaxshadow as js
from benchmarks.inverse_random_scenes import box_faces
from benchmarks.inverse_scenes import THREE_LIGHTS_EYE as EYE
from benchmarks.inverse_scenes import floor_receivers
from inverse._multilight import LightsProblem
from inverse._parametrisation import LightParametrisation

MATERIAL = js.Material(ka=0.1, kd=0.7, ks=0.0, exponent=1.0)


def _problem(capacity: int, dtype) -> tuple[LightsProblem, np.ndarray]:
    quad = js.PolygonLight([[-0.3, -0.3, 1.6], [-0.3, 0.3, 1.6], [0.3, 0.3, 1.6], [0.3, -0.3, 1.6]], [2.0, 2.0, 2.0])
    scene = js.Scene([quad], occluders=box_faces([-0.4, -0.2, 0.3], [0.2, 0.4, 0.6]), ambient=0.1)
    pts, nrm = floor_receivers(24, seed=3)
    t = inverse.PaintedTargets(jnp.asarray(pts, dtype), jnp.asarray(nrm, dtype),
                               jnp.ones((len(pts), 3), dtype), jnp.asarray(EYE, dtype))  # colours unused
    size = inverse.scene_size(scene, t)
    p = LightParametrisation(quad, 0, ("position", "orientation"), None, size, "none")
    z = jnp.zeros((len(t), 3), dtype)
    problem = LightsProblem((p,), (quad,), scene, MATERIAL, t, z, z, (0,), True, False, False, None,
                            capacity=capacity)
    rng = np.random.default_rng(0)
    rows = np.zeros((70, p.size))  # more than a chunk: the rerun rows come from several chunks
    rows[:, :3] = rng.uniform([-1.2, -1.2, -0.8], [1.2, 1.2, 0.4], (70, 3)) / size
    rows[:, 3:] = rng.uniform(-0.4, 0.4, (70, p.size - 3))
    return problem, rows


def _need(problem: LightsProblem, rows: np.ndarray, cap: int) -> np.ndarray:
    """`(S,)` whether some receiver of each row overflows `cap` edges."""
    one = placement_rank._single(dataclasses.replace(problem, capacity=cap), 0)
    return np.asarray(placement_rank._columns(one, jnp.asarray(rows, problem.targets.points.dtype))[1])


@pytest.mark.parametrize("dtype", [pytest.param(jnp.float32, marks=pytest.mark.slow), jnp.float64])
def test_columns_at_rising_capacity_equal_one_run(dtype, monkeypatch):
    problem, rows = _problem(8, dtype)
    assert 0 < _need(problem, rows, 4).sum() < rows.shape[0]  # some rows are rerun, not all (the premise)
    monkeypatch.setattr(placement_rank, "COLUMN_CAPACITY", {"polygon": 1 << 20})  # one run at the problem's capacity
    ref, p_ref = placement_rank.unit_columns(problem, 0, rows)
    assert p_ref.capacity == 8  # no row overflows it
    monkeypatch.setattr(placement_rank, "COLUMN_CAPACITY", {"polygon": 4})
    out, p_out = placement_rank.unit_columns(problem, 0, rows)
    assert p_out.capacity == 8
    assert out.shape == (rows.shape[0], 3 * len(problem.targets))
    assert np.all(np.isfinite(out)) and np.any(out != 0)
    # to rounding: a row rerun in another chunk may round differently
    eps = float(jnp.finfo(dtype).eps)
    np.testing.assert_allclose(out, ref, rtol=100 * eps, atol=4 * eps * float(np.abs(ref).max()))


def test_rows_rerun_until_they_fit(monkeypatch):
    """The loop alone, with a stand-in program whose row `s` needs `need[s]` edges (its value is
    `s` where it fits, NaN where it overflows): every row ends with its value, each row runs at
    every level from `COLUMN_CAPACITY[kind]` up to its need and no further, past the problem's
    capacity (8), which is returned unchanged (the LM's program is not recompiled for a few
    candidates); a row beyond `MAX_CAPACITY` is a `RuntimeError`."""
    problem, _ = _problem(8, jnp.float64)
    need = np.array([1, 3, 8, 9, 16, 2, 30, 5] * 9 + [4])  # 73 rows: two chunks at the first level
    rows = np.arange(need.size, dtype=np.float64)[:, None] * np.ones(problem.params[0].size)
    runs: list = []

    def program(one, part):
        s = np.asarray(part[:, 0]).astype(int)
        runs.append((one.capacity, s))
        over = need[s] > one.capacity
        val = np.where(over, np.nan, s.astype(np.float64))
        return np.broadcast_to(val[:, None, None], (s.size, *problem.targets.colours.shape)), over

    monkeypatch.setattr(placement_rank, "_columns", program)
    monkeypatch.setattr(placement_rank, "COLUMN_CAPACITY", {"polygon": 2})
    out, p_out = placement_rank.unit_columns(problem, 0, rows)
    assert p_out.capacity == 8  # the columns ran up to 32 (row need 30), the problem's is not raised
    sw = np.sqrt(np.asarray(problem.targets.weights, np.float64)).reshape(-1)
    np.testing.assert_array_equal(out, np.arange(need.size)[:, None] * sw[None])
    for s in range(need.size):
        caps = sorted({c for c, part in runs if s in part})
        assert caps == [c for c in (2, 4, 8, 16, 32) if c == 2 or c < 2 * need[s]], (s, caps)
    monkeypatch.setattr(placement_rank, "MAX_CAPACITY", 16)
    with pytest.raises(RuntimeError, match="more than 16 boundary edges"):
        placement_rank.unit_columns(problem, 0, rows)
