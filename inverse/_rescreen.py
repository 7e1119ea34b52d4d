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

Rounds repeat while the best refined loss falls below `RESCREEN_GAIN` times the previous best,
at most `RESCREEN_ROUNDS`: coordinate descent over single lights and pairs at refined
resolution, where each round starts from a placement in which more lights are right.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import numpy as np

from ._nnls_screen import pair_rss

RESCREEN_ROUNDS = 3
RESCREEN_GAIN = 0.5


def rescreen(values: np.ndarray, losses: np.ndarray, todo: list[int], offsets: tuple, sizes: list[int],
             rows: list, cols: list, y: np.ndarray, fit_power: bool,
             columns: Callable[[int, np.ndarray], np.ndarray],
             local_screen: Callable[[int, np.ndarray], list[int]],
             refine: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
             distinct: Callable[[np.ndarray, int], list[int]], batch: int,
             rounds: int = RESCREEN_ROUNDS) -> tuple[np.ndarray, np.ndarray]:
    """`(values (S', Pt), losses (S',))`: the refined placements `values (S, Pt)` with losses
    `losses (S,)` (step 7's), extended by the rounds of the module docstring.

    `todo`: the fitted lights' indices; `offsets[j]`, `sizes[j]`: light j's slice of a
    placement; `rows[j] (M_j, P_j)`, `cols[j] (M_j, 3N)`: its candidates and their weighted unit
    columns (lists the callbacks extend in place); `y (3N,)`: the weighted colours to explain;
    `fit_power`: powers by NNLS (else 1). Callbacks: `columns(j, rows)` light j's columns at
    `rows (S, P_j)`; `local_screen(j, B)` light j's best distinct candidates with the columns
    `B (3N, m)` held, screened locally (indices into `rows[j]`); `refine(thetas)` the refined
    placements and their ranking losses; `distinct(thetas, k)` up to `k` indices of `thetas` in
    distinct basins, in order; `batch`: contenders refined per round."""
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
        if not new:
            break
        v2, f2 = refine(cand[new])
        values, losses = np.concatenate([values, v2]), np.concatenate([losses, f2])
        if not float(np.min(losses)) < RESCREEN_GAIN * before:
            break
    return values, losses
