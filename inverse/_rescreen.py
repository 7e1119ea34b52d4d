r"""Step 8 of `fit_lights`' global placement (`_global_placement`): the lights screened again at
the best *refined* placement, in rounds, until a round no longer improves it.

The screens of steps 4-6 hold the other lights at grid resolution, where their columns are a
few % of the scene off and a light's residual is theirs too; a wrong light can then stand in for
another (a segment where the quad is, the quad moved to explain what is left). At the best
refined placement the held columns are those of the refined poses instead. One round:

1. **Singles.** Each light's candidates are ranked with the others' refined columns held, and
   its `LOCAL_SEEDS` best distinct ones screened locally (step 6's screen); the placement with
   that light moved to each of them is a contender.
2. **Pairs.** Two lights that compensate for each other move only together: every pair of
   lights is re-chosen over all pairs of their candidates with the remaining lights' refined
   columns held (`_nnls_screen.pair_rss`, step 5's pair move at refined resolution); the
   placement with both moved is a contender.
3. The contenders in basins distinct from every placement refined so far (up to the LM's batch,
   each light's best single move and the pair moves first) are refined jointly and ranked as in
   step 7.
4. **Split and dealt.** Two lights close together pass for one light of either kind (a segment
   where a point and a quad are), and a light of one kind stands in for another where it sits
   (the quad shrunk to a bright spot where the segment is); the light so freed falls where it
   lights a few targets. No single or pair move fixes all three. The least useful light (the
   smallest rise of the NNLS residual when its refined column is left out) is re-placed at its
   best candidate (the others' refined columns held) near each other light's centre (`near`:
   the split) and at its best single move; those placements, and the `REDEAL` best refined
   placements (distinct basins), have their centres dealt to the lights in every other order
   (`deal`: orientations and sizes as given for the lights moved). Up to two more batches of
   those (the splits first), distinct from every placement refined so far, are refined and
   ranked as in step 7.

Rounds repeat while the best refined loss falls below `RESCREEN_GAIN` times the previous best,
at most `RESCREEN_ROUNDS`: coordinate descent over single lights and pairs at refined
resolution, where each round starts from a placement in which more lights are right.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

import numpy as np

from ._nnls_screen import nnls_rss, pair_rss

RESCREEN_ROUNDS = 3
RESCREEN_GAIN = 0.5
REDEAL = 3  # the refined placements (best first, distinct basins) whose centres are dealt (step 4)


def rescreen(values: np.ndarray, losses: np.ndarray, todo: list[int], offsets: tuple, sizes: list[int],
             rows: list, cols: list, y: np.ndarray, fit_power: bool,
             columns: Callable[[int, np.ndarray], np.ndarray],
             local_screen: Callable[[int, np.ndarray], list[int]],
             refine: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
             distinct: Callable[[np.ndarray, int], list[int]], batch: int,
             rounds: int = RESCREEN_ROUNDS, deal: Callable[[np.ndarray], np.ndarray] | None = None,
             near: Callable[[int, np.ndarray, np.ndarray], list[int]] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """`(values (S', Pt), losses (S',))`: the refined placements `values (S, Pt)` with losses
    `losses (S,)` (step 7's), extended by the rounds of the module docstring.

    `todo`: the fitted lights' indices; `offsets[j]`, `sizes[j]`: light j's slice of a
    placement; `rows[j] (M_j, P_j)`, `cols[j] (M_j, 3N)`: its candidates and their weighted unit
    columns (lists the callbacks extend in place); `y (3N,)`: the weighted colours to explain;
    `fit_power`: powers by NNLS (else 1). Callbacks: `columns(j, rows)` light j's columns at
    `rows (S, P_j)`; `local_screen(j, B)` light j's best distinct candidates with the columns
    `B (3N, m)` held, screened locally (indices into `rows[j]`); `refine(thetas)` the refined
    placements and their ranking losses; `distinct(thetas, k)` up to `k` indices of `thetas` in
    distinct basins, in order; `batch`: contenders refined per round; `deal(theta)` the placement
    `theta (Pt,)` with its lights' centres dealt in every other order `(D, Pt)` (step 4; None:
    no deals); `near(j, theta, B)` light j's candidates (indices into `rows[j]`) near each other
    light's centre in `theta`, the best with the columns `B` held (step 4's split)."""
    empty = np.zeros((y.shape[0], 0))
    for _ in range(rounds):
        i0 = int(np.argmin(losses))
        best, before = values[i0], float(losses[i0])
        if not np.isfinite(before):
            break
        at = {j: columns(j, best[offsets[j]:offsets[j] + sizes[j]][None])[0] for j in todo}

        def held(skip: tuple, at: dict = at) -> np.ndarray:
            others = [at[i] for i in todo if i not in skip]
            return np.stack(others, axis=1) if others else empty

        def moved(change: dict, best: np.ndarray = best) -> np.ndarray:
            th = best.copy()
            for j, c in change.items():
                th[offsets[j]:offsets[j] + sizes[j]] = rows[j][c]
            return th

        singles = {j: local_screen(j, held((j,))) for j in todo}
        pairs = []
        for a, b in itertools.combinations(todo, 2):
            _, s, t = pair_rss(held((a, b)), cols[a], cols[b], y, fit_power)
            if s >= 0:
                pairs.append(moved({a: s, b: t}))
        firsts = [moved({j: c[0]}) for j, c in singles.items() if c]
        rest = [moved({j: c}) for j, cs in singles.items() for c in cs[1:]]
        contenders = firsts + pairs + rest
        if not contenders:
            break
        cand = np.stack(contenders)
        both = np.concatenate([values[np.argsort(losses, kind="stable")], cand])
        new = [i - len(values) for i in distinct(both, len(both)) if i >= len(values)][:batch]
        if deal is not None and len(todo) > 1:  # step 4: the least useful light re-placed, the centres dealt
            w = least_useful(held, at, todo, y, fit_power)
            top = np.argsort(losses, kind="stable")
            top = top[distinct(values[top], REDEAL)]
            split = [moved({w: c}) for c in (near(w, best, held((w,))) if near is not None else [])]
            # the best refined placement's deals first: they alone undo two lights swapped there, and the
            # extras are cut at 2 * batch (the splits and the single move's deals fill that otherwise)
            dealt = ([deal(values[top[0]])] if len(top) else []) + (
                [np.concatenate([t[None], deal(t)]) for t in split] + [deal(moved({w: c})) for c in singles[w][:1]]
                + [deal(values[i]) for i in top[1:]])
            dealt = [d for d in dealt if d.shape[0]]
            if dealt:
                extra = np.concatenate(dealt)
                both = np.concatenate([values[np.argsort(losses, kind="stable")], cand[new], extra])
                skip = len(values) + len(new)
                more = [i - skip for i in distinct(both, len(both)) if i >= skip][:2 * batch]
                cand, new = np.concatenate([cand, extra[more]]), new + list(range(len(cand), len(cand) + len(more)))
        if not new:
            break
        v2, f2 = refine(cand[new])
        values, losses = np.concatenate([values, v2]), np.concatenate([losses, f2])
        if not float(np.min(losses)) < RESCREEN_GAIN * before:
            break
    return values, losses


def least_useful(held: Callable[[tuple], np.ndarray], at: dict, todo: list[int], y: np.ndarray,
                 fit_power: bool) -> int:
    """The light (of `todo`) whose column `at[j] (M,)` explains least: the smallest rise of the
    non-negative least squares' residual sum of squares when it is left out (`held(skip)`: the
    columns of the lights not in `skip`, `(M, m)`)."""
    zero = np.zeros((1, y.shape[0]))
    rise = [float(nnls_rss(held((j,)), zero, y, fit_power)[0] - nnls_rss(held((j,)), at[j][None], y, fit_power)[0])
            for j in todo]
    return todo[int(np.argmin(rise))]


# The check for competing placements at the noise level (`noise_rivals`).
NOISE_SEEDS = 2  # each light's candidates moved to and refined, at most
SCREEN_MARGIN = 4.0  # a candidate's screened chi-square excess, in allowances (`rival_allowance`)


def noise_contenders(theta: np.ndarray, todo: list[int], offsets: tuple, sizes: list[int], rows: list, cols: list,
                     y: np.ndarray, fit_power: bool, columns: Callable[[int, np.ndarray], np.ndarray],
                     centre: Callable[[int, np.ndarray], np.ndarray], variance: float, allowance: float,
                     away: float) -> np.ndarray:
    r"""`(R, Pt)`: the answer `theta (Pt,)` with one light, or two, moved to screened
    candidates that may explain the targets about as well (`noise_rivals`).

    Each light $j$'s candidates `rows[j] (M_j, P_j)` (weighted unit columns `cols[j] (M_j, 3N)`)
    are screened with the other lights' columns at the answer held, powers by non-negative least
    squares (`nnls_rss`); a candidate is kept when its centre (`centre(j, row)`, m) is more than
    `away` (m) from the light's at the answer and its residual sum of squares exceeds the
    answer's (all lights at the answer, the same NNLS) by at most `SCREEN_MARGIN * allowance`
    chi-square units (`variance`: a weighted row's noise variance, so that
    $\Delta\chi^2 = \Delta\mathrm{rss} / \mathrm{variance}$): up to `NOISE_SEEDS` per light,
    lowest first, each more than `away` from those kept before it. Then every pair of lights
    over all pairs of their candidates both more than `away` from the answer's, the rest held
    (`pair_rss`, two lights that stand in for each other move together): its best pair, kept
    by the same margin. `columns(j, rows)`: light j's columns at `rows (S, P_j)`; `offsets`,
    `sizes`, `y`, `fit_power` as in `rescreen`."""
    sl = {j: slice(offsets[j], offsets[j] + sizes[j]) for j in todo}
    at = {j: columns(j, theta[sl[j]][None])[0] for j in todo}
    empty = np.zeros((y.shape[0], 0))

    def held(skip: int) -> np.ndarray:
        others = [at[i] for i in todo if i != skip]
        return np.stack(others, axis=1) if others else empty

    r0 = float(nnls_rss(held(todo[0]), at[todo[0]][None], y, fit_power)[0])
    out = []
    for j in todo:
        f = nnls_rss(held(j), cols[j], y, fit_power)
        c0 = centre(j, theta[sl[j]])
        pos = np.stack([centre(j, r) for r in rows[j]])
        ok = (np.linalg.norm(pos - c0, axis=1) > away) & ((f - r0) / variance <= SCREEN_MARGIN * allowance)
        kept: list[int] = []
        for c in np.argsort(np.where(ok, f, np.inf), kind="stable"):
            if len(kept) == NOISE_SEEDS or not ok[c]:
                break
            if all(np.linalg.norm(pos[c] - pos[q]) > away for q in kept):
                kept.append(int(c))
                th = theta.copy()
                th[sl[j]] = rows[j][c]
                out.append(th)
    far = {j: np.linalg.norm(np.stack([centre(j, r) for r in rows[j]]) - centre(j, theta[sl[j]]), axis=1) > away
           for j in todo}
    for a, b in itertools.combinations(todo, 2):  # two lights that stand in for each other move together
        rest = [at[i] for i in todo if i not in (a, b)]
        B = np.stack(rest, axis=1) if rest else empty
        _, s, t = pair_rss(B, np.where(far[a][:, None], cols[a], np.nan), np.where(far[b][:, None], cols[b], np.nan),
                           y, fit_power)
        if s < 0:
            continue
        f = float(nnls_rss(np.concatenate([B, cols[a][s][:, None]], axis=1), cols[b][t][None], y, fit_power)[0])
        if (f - r0) / variance <= SCREEN_MARGIN * allowance:
            th = theta.copy()
            th[sl[a]], th[sl[b]] = rows[a][s], rows[b][t]
            out.append(th)
    return np.stack(out) if out else np.zeros((0, theta.shape[0]))


def noise_rivals(problem: Any, theta: np.ndarray, rows: list, cols: list, refined: tuple | None, batch: int,
                 lm: dict, noise: Any, keep: int) -> tuple[np.ndarray, tuple, Any]:
    r"""`(theta, (values (R, Pt), losses (R,)), problem)`: placements that may compete with the
    answer `theta (Pt,)` of `fit_lights` at the told noise, for the rival check of
    `_multilight_result.result` (which judges them at their exact $\chi^2$).

    The rival check over the final joint solve's rows alone misses placements whose basin the
    search refined only in its placement stage or never: under 1 % noise a three-light fit 16 %
    and 22 % of the scene off (two lights) explained the targets better than the truth
    ($\chi^2$ 148 against 185) while the placement stage had refined others 20 % from it to
    $\chi^2$ 149-158 and never finished them. So:

    1. the global placement's refined placements (`refined`, steps 7-8 of `_global_placement`;
       a partly refined placement's loss only falls with more steps, so one within the
       allowance competes already);
    2. each light screened again over its candidates `rows[j]`, `cols[j]` with the others held at
       the answer (`noise_contenders`; the allowance `rival_allowance(n)`, $n$ the poses'
       parameters and the powers), the kept placements (one batch of `fit_lights`' LM program
       at most: the program of its joint refinement, no new compilation) refined jointly with
       every parameter free (`lm`'s tolerances and steps);

    those in basins distinct from the answer's and each other's (`distinct_basins`), lowest loss
    first, `keep` at most. One with a lower loss than the answer's becomes the answer (the
    answer goes among them). `noise`: the told noise (`_diagnostics.noise_sigma`); `batch`: the
    LM program's rows."""
    from ._diagnostics import noise_sigma, rival_allowance
    from ._global_placement import region_of
    from ._multilight import solve
    from ._multilight_placement import pad
    from ._placement_rank import (
        BASIN_DISTANCE,
        centre_of_row,
        distinct_basins,
        ranking_losses,
        unit_columns,
        weighted_rest,
    )
    from ._solvers import screen_by_solver

    theta = np.asarray(theta, np.float64)
    params = problem.params
    none = (np.zeros((0, theta.shape[0])), np.zeros(0))
    todo = [j for j, p in enumerate(params) if p is not None and rows[j] is not None and rows[j].shape[0]]
    w = np.asarray(problem.targets.weights, np.float64)
    sigma, _ = noise_sigma(problem.targets, noise)
    pos = (w > 0) & np.isfinite(sigma)
    if not todo or not pos.any():
        return theta, none, problem
    variance = float((w * np.where(pos, sigma, 0.0) ** 2)[pos].flat[0])  # fit weights are 1/sigma^2 up to a factor
    sizes = [0 if p is None else p.size for p in params]
    n = sum(sizes) + (len(todo) if problem.fit_power else 0)
    region = region_of(problem.scene, np.asarray(problem.targets.points), np.asarray(problem.targets.normals))

    def columns(j: int, r: np.ndarray) -> np.ndarray:
        nonlocal problem
        a, problem = unit_columns(problem, j, r)
        return a

    cand = noise_contenders(theta, todo, problem.offsets, sizes, rows, cols, weighted_rest(problem),
                            problem.fit_power, columns, lambda j, r: centre_of_row(params[j], r), variance,
                            rival_allowance(n), BASIN_DISTANCE * region.extent)[:batch]
    values = [np.zeros((0, theta.shape[0]))] if refined is None else [np.asarray(refined[0], np.float64)]
    losses = [np.zeros(0)] if refined is None else [np.asarray(refined[1], np.float64)]
    if cand.shape[0]:
        res, problem, _ = solve(problem, pad(cand, batch), theta, np.ones(cand.shape[1], bool), **lm)
        v = np.asarray(res.values, np.float64)[:cand.shape[0]]
        f, problem = ranking_losses(problem, np.asarray(res.losses)[:cand.shape[0]], v)
        values.append(v)
        losses.append(np.asarray(f, np.float64))
    vals, fs = np.concatenate(values), np.concatenate(losses)
    if not vals.shape[0]:
        return theta, none, problem
    order = np.argsort(fs, kind="stable")
    vals, fs = vals[order], fs[order]
    # the answer's own loss: its row in the pool is absent; a lower refined loss replaces it (ranked first)
    f0, problem, _ = screen_by_solver(problem, theta[None], theta, np.ones(theta.shape[0], bool), batch,
                                      rtol=lm["rtol"], atol=lm["atol"])
    f_ans, problem = ranking_losses(problem, f0, theta[None])
    if fs[0] < float(f_ans[0]):
        vals, fs = np.concatenate([vals, theta[None]]), np.concatenate([fs, f_ans])
        theta = vals[0].copy()
        order = np.argsort(fs, kind="stable")
        vals, fs = vals[order], fs[order]
    picked = distinct_basins(params, problem.offsets, np.concatenate([theta[None], vals]), region.extent, keep + 1)
    picked = [i - 1 for i in picked if i > 0]
    return theta, (vals[picked], fs[picked]), problem

