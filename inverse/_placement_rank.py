r"""The global placement's (`_global_placement`) unit columns and its refine-then-rank: each
light's weighted unit contribution at candidate rows (step 3, one compiled program per light
kind), the placements in distinct basins, their joint refinement by `fit_lights`' batched LM
and the losses they are ranked by (step 7)."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._escape import escaped_rows
from ._forward import MAX_CAPACITY
from ._lm import fit_jit
from ._multilight import LightsProblem, _parts, build_lights, solve
from ._parametrisation import LightParametrisation
from ._powers import constrained_powers, emitted_power

CHUNK = 64  # candidate rows per call of the columns' program
# Shadow capacity the columns are first evaluated at (`unit_columns`), by light kind: a quad's
# candidates in a noisy three-light fit need 4-8 boundary edges at ~85 % of the rows and 16 at
# ~15 %; a segment's (its visible pieces) and a point light's 4 at every row.
COLUMN_CAPACITY = {"polygon": 8, "linear": 4, "point": 4, "directional": 4}
# Refine, then rank (`_global_placement`, step 7): BASIN_STEPS LM iterations each; distinct when
# some light's centre is BASIN_DISTANCE of the extent away or its orientation parameters
# BASIN_TURN (rad) apart.
BASIN_STEPS = 30
BASIN_DISTANCE, BASIN_TURN = 0.05, 0.25

def centre_of_row(param: LightParametrisation, row: np.ndarray) -> np.ndarray:
    """The light's centre (m) at parameters `row` (NumPy `LightParametrisation.centre_of`)."""
    sl = param._slices()
    c0, s = np.asarray(param.c0, np.float64), float(param.scale)
    if "position" not in sl:
        return c0
    z = np.asarray(row, np.float64)[sl["position"]]
    if param.constraint == "plane":
        return c0 + s * (z @ np.asarray(param.plane_e, np.float64))
    if param.constraint == "box" and param.box_map == "sigmoid":
        lo, hi = np.asarray(param.box_lo, np.float64), np.asarray(param.box_hi, np.float64)
        return lo + (hi - lo) / (1.0 + np.exp(-z))
    return c0 + s * z



def weighted_rest(problem: LightsProblem) -> np.ndarray:
    """`(3N,)` what the fitted lights are to paint, $\\sqrt{w}\\,(C - L_{fixed})$ (row-major `(N, 3)`):
    the targets' colours less the ambient term and the lights that are not fitted, weighted."""
    t, m = problem.targets, problem.material
    sw = np.sqrt(np.asarray(t.weights, np.float64))
    La = np.broadcast_to(np.asarray(problem.scene.ambient, np.float64), t.colours.shape)
    base_model = (np.asarray(m.ka, np.float64) * La + np.asarray(m.kd, np.float64) / np.pi
                  * np.asarray(problem.e_fixed, np.float64))
    if problem.with_specular:
        base_model = base_model + np.asarray(m.ks, np.float64) * np.asarray(problem.s_fixed, np.float64)
    return (sw * (np.asarray(t.colours, np.float64) - base_model)).reshape(-1)


def _single(problem: LightsProblem, j: int) -> LightsProblem:
    """The problem restricted to its fitted light `j` (its unit contribution alone)."""
    return dataclasses.replace(problem, params=(problem.params[j],), refs=(problem.refs[j],), offsets=(0,),
                               active=None, outside=(), paint=None, budget=None, powers_in_theta=False,
                               colour_free=False)


def _columns_impl(problem: LightsProblem, rows: Any) -> tuple[Any, Any]:
    """`(per_light (S, N, 3), overflow (S,))` of the one-light `problem` at every row `(S, P)`."""
    def one(th: Any) -> tuple[Any, Any]:
        _, per, over = _parts(th, problem, problem.capacity)
        return per[0], over

    return jax.vmap(one)(rows)


_columns = fit_jit(_columns_impl)


def unit_columns(problem: LightsProblem, j: int, rows: np.ndarray) -> tuple[np.ndarray, LightsProblem]:
    """`(A (S, 3N), problem)`: light `j`'s weighted unit contribution $\\sqrt{w}\\,a_j$ at every
    row of `rows (S, P_j)`, `CHUNK` rows a call (one compiled program per light kind and
    capacity). The program's cost grows with the shadow capacity (every receiver integrates
    `capacity` boundary edges, most of them padding) while most candidates need a few edges:
    every row runs first at `COLUMN_CAPACITY[kind]` edges (at most the problem's), the rows some
    receiver overflowed again at twice that, up to `MAX_CAPACITY` (a `RuntimeError` beyond, as
    `at_capacity`). The problem's own capacity (the LM's, a static field of its program) is not
    raised for the few candidates that need more: the LM doubles it only where a solve
    overflows (`_multilight.solve`), so a candidate far from any answer does not recompile the
    LM at twice the capacity mid-fit. The problem is returned as given. A row that does not
    overflow has the same value at any capacity (the padding edges add zeros), to rounding
    where it runs in another chunk: the columns are those of one run at the final capacity to
    ~1e-16 (absolute; 3 of 1606 rows of a fit differ, by one ulp)."""
    dt = problem.targets.points.dtype
    sw = np.sqrt(np.asarray(problem.targets.weights, np.float64))
    per = np.zeros((rows.shape[0], *problem.targets.colours.shape))
    todo = np.arange(rows.shape[0])
    first = COLUMN_CAPACITY.get(problem.params[j].kind, 8)
    cap = None if problem.capacity is None else min(first, problem.capacity)

    while True:
        one = _single(dataclasses.replace(problem, capacity=cap), j)
        over = np.zeros(todo.size, bool)
        for a in range(0, todo.size, CHUNK):
            part = rows[todo[a:a + CHUNK]]
            part = np.concatenate([part, np.repeat(part[:1], CHUNK - part.shape[0], axis=0)])
            p, o = _columns(one, jax.device_put(np.asarray(part, dt)))
            n = min(CHUNK, todo.size - a)
            per[todo[a:a + n]] = np.asarray(p, np.float64)[:n]
            over[a:a + n] = np.asarray(o)[:n]
        todo = todo[over]
        if not todo.size or cap is None:
            return (sw[None] * per).reshape(rows.shape[0], sw.size), problem
        if cap >= MAX_CAPACITY:
            raise RuntimeError(f"fit_lights: some receiver's visible region needs more than {MAX_CAPACITY} boundary "
                               "edges during the global placement.")
        cap = min(2 * cap, MAX_CAPACITY)


def _basin_key(param: LightParametrisation, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(centre (3,) m, orientation parameters)` of light `param` at its parameters `row`."""
    sl = param._slices()
    o = np.asarray(row, np.float64)[sl["orientation"]] if "orientation" in sl else np.zeros(0)
    return centre_of_row(param, row), o


def distinct_basins(params: tuple, offsets: tuple, thetas: np.ndarray, extent: float, k: int) -> list[int]:
    """Up to `k` indices into `thetas (S, Pt)` (placements, most promising first), in that order,
    each in a basin distinct from every one picked before it: some light's centre more than
    `BASIN_DISTANCE * extent` (m) away, or its orientation parameters more than `BASIN_TURN`
    (rad) apart."""
    keys = [[_basin_key(p, th[o:o + p.size]) for p, o in zip(params, offsets, strict=True) if p is not None]
            for th in thetas]
    picked: list[int] = []
    for i, ki in enumerate(keys):
        if len(picked) == k:
            break
        if not np.all(np.isfinite(thetas[i])):
            continue
        if all(any(np.linalg.norm(a[0] - b[0]) > BASIN_DISTANCE * extent
                   or (a[1].size and np.max(np.abs(a[1] - b[1])) > BASIN_TURN)
                   for a, b in zip(ki, keys[q], strict=True)) for q in picked):
            picked.append(i)
    return picked


def refine_and_rank(problem: LightsProblem, thetas: np.ndarray, lm: dict, batch: int, stop: float = -np.inf
                    ) -> tuple[np.ndarray, np.ndarray, LightsProblem]:
    """`(values (S, Pt), losses (S,), problem)`: every placement of `thetas (S, Pt)` refined
    jointly (all its parameters) for `BASIN_STEPS` iterations of `fit_lights`' batched LM
    (`_multilight.solve`, `lm`'s tolerances, no pruning: a basin's loss at grid resolution says
    little), `batch` rows a call (padded: the program of `fit_lights`' joint refinement, no
    new compilation), up to the first batch with a loss at most `stop` (no power budget; the
    rows after it are not returned); non-finite losses are infinite."""
    from ._multilight_placement import pad

    mask = np.ones(thetas.shape[1], bool)
    values, losses = [], []
    for a in range(0, thetas.shape[0], batch):
        part = thetas[a:a + batch]
        res, problem, _ = solve(problem, pad(part, batch), part[0], mask, rtol=lm["rtol"], atol=lm["atol"],
                                max_steps=BASIN_STEPS, prune=())
        values.append(np.asarray(res.values, np.float64)[:part.shape[0]])
        losses.append(np.asarray(res.losses, np.float64)[:part.shape[0]])
        if problem.budget is None and np.any(losses[-1] <= stop):
            break
    v = np.concatenate(values)
    f, problem = ranking_losses(problem, np.concatenate(losses), v)
    return v, f, problem


def ranking_losses(problem: LightsProblem, losses: Any, thetas: np.ndarray) -> tuple[np.ndarray, LightsProblem]:
    """`(losses (S,), problem)` ranking the rows `thetas (S, Pt)` of an LM solve: its `losses`
    (infinite where not finite) or, under a power budget, `final_losses`; infinite for the rows in
    which a light escaped (`_escape.escaped_rows`) while some row keeps every light in bounds."""
    if problem.budget is None:
        f = np.asarray(losses, np.float64)
        f = np.where(np.isfinite(f), f, np.inf)
    else:
        f, problem = final_losses(problem, np.asarray(thetas, np.float64))
    out = escaped_rows(problem, thetas)  # the escape bound (`_escape`): such rows not ranked, unless all are
    return (np.where(out, np.inf, f) if out.any() and not out.all() else f), problem


def final_losses(problem: LightsProblem, thetas: np.ndarray) -> tuple[np.ndarray, LightsProblem]:
    """`(losses (S,), problem)`: $\\tfrac12|r|^2$ at every placement of `thetas (S, Pt)` with the
    powers the final fit solves there (`_powers.constrained_powers`: $p \\ge 0$ and, under a
    budget $B$, $c \\cdot p \\le B$, $c$ the emitted powers there), the loss `fit_lights` reports;
    infinite where not finite. The LM's projection (`_multilight._data_residual`: signed least
    squares moved onto the budget's plane) lets a negative power meet the budget where no answer
    with $p \\ge 0$ does (0.031 in the LM where the final loss is 1.28). Columns: `unit_columns`."""
    y = weighted_rest(problem)
    cols = []
    for j, p in enumerate(problem.params):
        o, size = problem.offsets[j], 0 if p is None else p.size
        a, problem = unit_columns(problem, j, np.asarray(thetas[:, o:o + size], np.float64))
        cols.append(a)
    A = np.stack(cols, axis=1)  # (S, J, 3N)
    zero, one = np.zeros((y.shape[0] // 3, 3)), np.ones((y.shape[0] // 3, 3))
    out = np.full(thetas.shape[0], np.inf)
    for s in range(out.shape[0]):
        if not (np.all(np.isfinite(thetas[s])) and np.all(np.isfinite(A[s]))):
            continue
        bud = None
        if problem.budget is not None:
            lights = build_lights(problem, jnp.asarray(thetas[s, :problem.n_pose], problem.targets.points.dtype))
            bud = (np.array([float(emitted_power(x)) for x in lights]), float(problem.budget))
        # the weighted problem as it stands: colours y, columns A, unit weights
        cj = A[s].reshape(A.shape[1], -1, 3)
        p = constrained_powers(zero, cj, y.reshape(-1, 3), one, None, bud, np.zeros(A.shape[1]))
        r = np.tensordot(p, A[s], axes=1) - y
        out[s] = 0.5 * float(r @ r)
    return out, problem

