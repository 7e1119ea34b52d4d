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
            dealt = ([np.concatenate([t[None], deal(t)]) for t in split] + [deal(moved({w: c})) for c in singles[w][:1]]
                     + [deal(values[i]) for i in top])
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
