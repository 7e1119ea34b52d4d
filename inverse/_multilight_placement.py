"""`fit_lights`' placement of several lights: one light at a time (greedy, the lights not placed
yet left out of the model), the placed positions dealt to the lights in every order, and the
helpers the per-light sweeps share (`stage_mask`, `pad`).
"""

from __future__ import annotations

import dataclasses
import itertools

import jax.numpy as jnp
import numpy as np

from ._multilight import LightsProblem, solve
from ._multistart import best_starts
from ._parametrisation import LightParametrisation
from ._solvers import screen_by_solver


def greedy(problem: LightsProblem, base: np.ndarray, grid_rows: list, offsets: list, P: int, in_theta: bool,
            k: int, lm: dict, stage_losses: list) -> tuple[LightsProblem, np.ndarray, float, int, int]:
    """Greedy placement, one light at a time: the lights not placed yet are left out of the model
    (`LightsProblem.active`); at each stage every unplaced light's grid of positions
    (`grid_rows[j]`, a Sobol stratification of its search region) is screened with the placed
    lights, the light and positions that explain the targets best are refined (its position, the
    powers projected) and that light is placed. A misplaced light is thereby never compensated
    for, and the screened positions add up over the lights, they do not multiply.
    Returns `(problem, base, the given poses' loss, starts solved, retries)`."""
    dt = problem.targets.points.dtype
    J = len(problem.params)
    Pt = base.shape[0]
    f0, problem, retries = screen_by_solver(problem, base[None], base, np.ones(Pt, bool), k, lm["rtol"], lm["atol"])
    initial = float(f0[0])
    active = np.array([p is None for p in problem.params], np.float64)
    todo = [j for j in range(J) if problem.params[j] is not None]
    n_solved = 0
    while todo:
        best_f, chosen, rows, mask, trial = np.inf, -1, base[None], np.zeros(Pt, bool), problem
        for j in todo:
            p, sl = problem.params[j], slice(offsets[j], offsets[j] + problem.params[j].size)
            act = active.copy()
            act[j] = 1.0
            this = dataclasses.replace(problem, active=jnp.asarray(act, dt))
            m = np.zeros(Pt, bool)
            m[sl] = stage_mask(p)
            if in_theta:
                m[P + j] = True
            full = np.tile(base, (grid_rows[j].shape[0], 1))
            full[:, sl] = grid_rows[j]
            f, this, n = screen_by_solver(this, full, base, m, k, lm["rtol"], lm["atol"])
            retries += n
            f = np.where(np.isfinite(f), f, np.inf)
            if chosen < 0 or np.min(f) < best_f:
                best_f, chosen, rows, mask, trial = float(np.min(f)), j, full[best_starts(f, k)], m, this
        j = chosen
        res, trial, n = solve(trial, pad(rows, k), base, mask, **lm)
        retries += n
        n_solved += rows.shape[0]
        f = np.where(np.isfinite(np.asarray(res.losses)), np.asarray(res.losses), np.inf)
        base = np.where(mask, np.asarray(res.values)[int(np.argmin(f))], base)
        stage_losses.append(float(np.min(f)))
        active[j] = 1.0
        todo.remove(j)
        problem = dataclasses.replace(problem, capacity=trial.capacity)
    return dataclasses.replace(problem, active=jnp.ones(J, dt)), base, initial, n_solved, retries


def swaps(problem: LightsProblem, base: np.ndarray, offsets: list, k: int, lm: dict,
           stage_losses: list, given: np.ndarray | None = None) -> tuple[LightsProblem, np.ndarray, int, int]:
    """The greedy placement finds where lights are, not which light is where (a small polygon
    light high up passes for a point light lower down): the placed positions are dealt to the
    lights in every order (up to 4 movable lights; beyond, each exchange of two), every deal's
    positions refined jointly, the best kept (with `given`, each deal also with the given
    orientations and sizes). Lights on a plane or in a box keep their own.
    Returns `(problem, base, starts solved, retries)`."""
    movable = [j for j, p in enumerate(problem.params)
               if p is not None and "position" in p._slices() and p.constraint == "none"]
    if len(movable) < 2:
        return problem, base, 0, 0
    sl = {j: slice(offsets[j] + problem.params[j]._slices()["position"].start,
                   offsets[j] + problem.params[j]._slices()["position"].stop) for j in movable}
    c0 = {j: np.asarray(problem.params[j].c0, np.float64) for j in movable}
    s = float(problem.params[movable[0]].scale)
    where = {j: c0[j] + s * base[sl[j]] for j in movable}
    if len(movable) <= 4:
        deals = list(itertools.permutations(movable))
    else:
        deals = [tuple(movable)]
        for a, b in itertools.combinations(range(len(movable)), 2):
            d = list(movable)
            d[a], d[b] = d[b], d[a]
            deals.append(tuple(d))
    rows = np.tile(base, (len(deals), 1))
    for r, deal in enumerate(deals):
        for j, src in zip(movable, deal, strict=True):
            rows[r, sl[j]] = (where[src] - c0[j]) / s
    if given is not None:  # each deal also with the given orientations and sizes (the refined ones fit elsewhere)
        reset = rows.copy()
        for j in movable:
            o = slice(offsets[j], offsets[j] + problem.params[j].size)
            keep = reset[:, sl[j]].copy()
            reset[:, o] = given[o]
            reset[:, sl[j]] = keep
        rows = np.concatenate([rows, reset[1:]])
    mask = np.zeros(base.shape[0], bool)
    for j in movable:
        mask[sl[j]] = True
    best, best_f, n_solved, retries = base, np.inf, 0, 0
    for a in range(0, rows.shape[0], k):
        res, problem, r = solve(problem, pad(rows[a:a + k], k), base, mask, **lm)
        retries += r
        n_solved += min(k, rows.shape[0] - a)
        f = np.where(np.isfinite(np.asarray(res.losses)), np.asarray(res.losses), np.inf)
        if np.min(f) < best_f:
            best_f, best = float(np.min(f)), np.where(mask, np.asarray(res.values)[int(np.argmin(f))], base)
    stage_losses.append(best_f)
    return problem, best, n_solved, retries


def stage_mask(param: LightParametrisation) -> np.ndarray:
    """Which of a light's parameters its own multistart searches: its position when fitted (the
    orientation and size follow in the joint refinement: searched while the other lights are
    still misplaced they compensate for them - a polygon shrinks to a bright point), else all."""
    sl = param._slices()
    if "position" not in sl:
        return np.ones(param.size, bool)
    out = np.zeros(param.size, bool)
    out[sl["position"]] = True
    return out


def pad(rows: np.ndarray, k: int) -> np.ndarray:
    """`rows` padded to `k` rows with copies of the first (the same program for every call)."""
    return np.concatenate([rows, np.repeat(rows[:1], k - rows.shape[0], axis=0)]) if rows.shape[0] < k else rows
