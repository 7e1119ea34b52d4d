"""Multistart (Campbell & Fussell §4.4.2): the starting points stratify the search region (a
scrambled Sobol sequence, one point per cell of a coarse grid in the limit), all solved at once;
the lowest residual wins. Also what the LM's occluder culling must hold at the starts, the
screening of many starts down to a few, and the successive-halving schedule.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

import jaxshadow as js
from jaxshadow import traced

from ._lm import fit_jit
from ._parametrisation import LightParametrisation
from ._residuals import LightProblem, residuals_culled
from ._targets import PaintedTargets


def make_starts(param: LightParametrisation, starts: int, *, search_radius: float, orientation_spread: float,
                size_spread: float, seed: int, dtype: Any) -> Array:
    """`(starts, P)` starting parameters: the reference first, then a scrambled Sobol
    stratification of the search region (Campbell & Fussell §4.4.2's coarse-grid multistart).

    Positions within `search_radius` (in scene-size units) of the reference (the whole box for
    a box constraint), rotation vectors within `orientation_spread` rad, log-sizes within
    `log(1 + size_spread)`.
    """
    th0 = np.asarray(param.theta0(np.float64))
    if starts <= 1:
        return jnp.asarray(th0[None], dtype)
    # Imported here, after the one-start return: scipy.stats takes ~1.3 s to import, which was
    # a seventh of a one-start fit's first call.
    from scipy.stats import qmc

    P = param.size
    m = max(int(math.ceil(math.log2(starts - 1))), 0)
    u = qmc.Sobol(P, scramble=True, seed=seed).random_base2(m)[: starts - 1] * 2.0 - 1.0  # [-1, 1)
    th = np.tile(th0, (starts - 1, 1))
    sl = param._slices()
    if "position" in sl:
        if param.constraint == "box" and param.box_map == "sigmoid":
            f = np.clip(0.5 * (u[:, sl["position"]] + 1.0), 0.02, 0.98)
            th[:, sl["position"]] = np.log(f / (1 - f))
        elif param.constraint == "box":
            lo, hi = param.lbfgsb_bounds(np.float64)
            lo_, hi_ = np.asarray(lo)[sl["position"]], np.asarray(hi)[sl["position"]]
            th[:, sl["position"]] = lo_ + (hi_ - lo_) * 0.5 * (u[:, sl["position"]] + 1.0)
        else:
            th[:, sl["position"]] += search_radius * u[:, sl["position"]]
    if "orientation" in sl:
        th[:, sl["orientation"]] += orientation_spread * u[:, sl["orientation"]]
    if "size" in sl:
        th[:, sl["size"]] += math.log1p(size_spread) * u[:, sl["size"]]
    return jnp.asarray(np.concatenate([th0[None], th]), dtype)


def prune_schedule(n_starts: int, max_steps: int) -> tuple[int, ...]:
    """Iterations 4, 8, 16, ... (below `max_steps`) at which the worse half of the running starts
    is abandoned (`_lm`'s successive halving); empty for one start."""
    if n_starts <= 1:
        return ()
    out, it = [], 4
    while it < max_steps:
        out.append(it)
        it *= 2
    return tuple(out)


@fit_jit
def _light_vertices(param: LightParametrisation, thetas: Array) -> Array:
    """`(S, K, 3)` vertices of the polygon light for each row of `thetas (S, >=P)` (compiled
    once per parametrisation shape, not per call)."""
    return jax.vmap(lambda th: param.build(th[: param.size]).vertices)(thetas)


def start_counts(param: LightParametrisation, scene: js.Scene, targets: PaintedTargets, starts: Array) -> np.ndarray:
    """`(L, N)` relevant-occluder counts (`jaxshadow.traced.relevant_occluder_counts`) of every
    receiver for the light at each start and for the other polygon lights where they are."""
    assert scene.occluders is not None
    others = [np.asarray(light.vertices, np.float64) for i, light in enumerate(scene.lights)
              if i != param.light_index and isinstance(light, js.PolygonLight)]
    th = np.asarray(starts)[:, : param.size]
    if th.shape[0] == 1 and param.constraint != "box" and not np.any(th):
        # The reference light itself (a one-start fit): its vertices, without compiling
        # `_light_vertices` (~0.15 s of the first call). Equal to build(0) up to rounding; the
        # counts only size the capacity, and an overflow is caught and retried (`LM`).
        moving = np.asarray(param.template.vertices, np.float64)[None]
    else:
        moving = np.asarray(_light_vertices(param, starts), np.float64)
    emitters = [*moving, *others]
    k = max(e.shape[0] for e in emitters)
    padded = np.stack([np.concatenate([e, np.repeat(e[:1], k - e.shape[0], axis=0)]) for e in emitters])
    nrm = np.asarray(targets.normals, np.float64)
    nrm = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    # In NumPy: nothing to compile for a count.
    return traced.relevant_occluder_counts(targets.points, nrm, padded, scene.occluders)


def culling_capacity_for_starts(param: LightParametrisation, scene: js.Scene, targets: PaintedTargets,
                                starts: Array) -> int | None:
    """The occluder-culling capacity for an LM from `starts`: enough for every receiver with the
    light at any start and the other polygon lights where they are, plus one (None when culling
    cannot pay: fewer than 4 occluders, or not a polygon light). The light moves during the
    solve; a receiver that then sees more occluders (or a visible region with more edges than
    the kernel's edge capacity) raises the overflow flag and the `LM` solves again."""
    occ = scene.occluders
    if occ is None or occ.shape[0] < 4 or param.kind != "polygon":
        return None
    counts = start_counts(param, scene, targets, starts)
    # One spare (the light moves); not rounded to a power of two: the kernel's cost grows with it.
    return min(int(counts.max(initial=0)) + 1, int(occ.shape[0]))


def wide_group_for_starts(param: LightParametrisation, scene: js.Scene, targets: PaintedTargets,
                          starts: Array, max_active: int | None) -> int | None:
    """How many receivers get the full culling capacity in the irradiance (the others get 1,
    `jaxshadow.traced.irradiance(n_wide=...)`): twice the number that see two or more
    occluders from some light at some start, at least a quarter of them, a multiple of 8; None
    (no split) when that is all of them. Too few raises the overflow flag (the `LM` solves again
    without the split)."""
    n = int(targets.points.shape[0])
    if scene.occluders is None or max_active is None or max_active <= 1 or param.kind != "polygon":
        return None
    counts = start_counts(param, scene, targets, starts)
    many = int(np.count_nonzero(counts.max(axis=0) >= 2))
    wide = -(-max(2 * many, n // 4, 1) // 8) * 8
    return None if wide >= n else wide


@fit_jit
def screen_losses(problem: LightProblem, starts: Array) -> Array:
    """$\\tfrac12|r|^2$ at every start, one vectorised loss (culled at `problem.max_active`: the
    caller sizes it for these starts, so nothing overflows): the screening of the Optimistix
    and L-BFGS-B solvers (the LM screens with its own program, `_solvers.screen_with_lm`)."""

    def loss(theta: Array) -> Array:
        r = residuals_culled(theta, problem)[0]
        return 0.5 * jnp.sum(r * r)

    return jax.vmap(loss)(starts)



def best_starts(losses: np.ndarray, k: int) -> np.ndarray:
    """Indices (ascending) of the `k` lowest `losses` (non-finite ones last)."""
    return np.sort(np.argsort(np.where(np.isfinite(losses), losses, np.inf), kind="stable")[:k])


def distinct_minima(values: np.ndarray, losses: np.ndarray, converged: np.ndarray, best: int) -> int:
    """Final points more than 1e-3 (parameter units) apart among the converged starts within
    1 % of the best loss: a measure of ambiguity (at least 1)."""
    near = np.flatnonzero(converged & (losses <= losses[best] * 1.01 + 1e-30))
    reps: list[np.ndarray] = []
    for i in near:
        if all(np.max(np.abs(values[i] - q)) > 1e-3 for q in reps):
            reps.append(values[i])
    return max(len(reps), 1)
