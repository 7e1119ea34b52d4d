"""Multistart (Campbell & Fussell §4.4.2): the starting points stratify the search region (a
scrambled Sobol sequence, one point per cell of a coarse grid in the limit), all solved at once;
the lowest residual wins. Also what the LM's occluder culling must hold at the starts, the
choice of the best screened starts, and the successive-halving schedule.
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
from ._targets import PaintedTargets

# The smallest shadow capacity a light fit compiles for (`capacity_bucket`).
MIN_CAPACITY = 8


def capacity_bucket(need: int) -> int:
    """The shadow capacity a light fit's program is compiled for when receivers need `need`
    boundary edges: the next power of two, at least `MIN_CAPACITY`. The capacity is a static
    field of the program (`LightsProblem.capacity`); coarse buckets let
    scenes that need 13, 14 or 16 edges share one compiled program (a second fit in a process,
    or a fresh process with JAX's persistent compilation cache, compiles nothing) at most twice
    the engine's work per receiver."""
    return max(MIN_CAPACITY, 1 << max(int(need) - 1, 0).bit_length())


def capacity_with_room(most: int) -> int:
    """The capacity for a solve whose starts need at most `most` boundary edges: room for the
    lights to move (`ceil(1.25 * most) + 4`), rounded up by `capacity_bucket`."""
    return capacity_bucket(-(-5 * most // 4) + 4)


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
def _start_lights(param: LightParametrisation, thetas: Array) -> Any:
    """The light built at each row of `thetas (S, >=P)`, as one batched light pytree (compiled
    once per parametrisation shape, not per call)."""
    return jax.vmap(lambda th: param.build(th[: param.size]))(thetas)


def start_lights(param: LightParametrisation, starts: Array | np.ndarray) -> list[Any]:
    """The moving light at every start, as a list of lights with NumPy arrays."""
    th = np.asarray(starts)[:, : param.size]
    if th.shape[0] == 1 and param.constraint != "box" and not np.any(th):
        # The reference light itself (a one-start fit), without compiling `_start_lights`.
        # Equal to build(0) up to rounding; the lights only size the capacity, and an overflow
        # is caught and retried (`LM`).
        return [param.template]
    batched = jax.tree_util.tree_map(np.asarray, _start_lights(param, jax.device_put(np.asarray(starts))))
    return [jax.tree_util.tree_map(lambda x, i=i: x[i] if isinstance(x, np.ndarray) else x, batched)
            for i in range(th.shape[0])]


def culling_capacity_for_starts(param: LightParametrisation, scene: js.Scene, targets: PaintedTargets,
                                starts: Array) -> int | None:
    """The shadow engine's capacity for a solve from `starts`: the most boundary edges (candidate
    faces for a segment light) any receiver needs with the light at any start or from the other
    lights (`jaxshadow.traced.shadow_capacity`, on the host), with room for the light to move:
    `ceil(1.25 * most) + 4`, rounded up by `capacity_bucket`. None without occluders. A receiver
    that needs more during the solve raises the overflow flag and the `LM` solves again with twice
    the capacity."""
    if scene.occluders is None:
        return None
    others = [light for i, light in enumerate(scene.lights) if i != param.light_index]
    most = traced.shadow_capacity(scene, targets.points, targets.normals,
                                  lights=[*start_lights(param, starts), *others])
    return capacity_with_room(most)


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
